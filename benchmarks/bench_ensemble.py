"""Ensemble throughput: K bonded Brazilian discs in one batch against K runs one after
another (DESIGN §7, issue 8).

For K = 1, 8, 32, 64 (``--ks``) a batch of K discs of ``--cells`` Voronoi cells runs
``--steps`` steps of the loading (:func:`jaxgran.ensemble.run_segments`: one jitted scan,
``vmap`` over K, one pair-list rebuild decision per step for the batch); the figure is
specimens per second, i.e. ``K / wall time`` for that stretch of the test (compilation
excluded), and realisation-steps per second. The baselines are

* *sequential*: the same realisations one after another with the single-realisation
  segment (one compiled function for all; timed on ``min(K, --seq-max)`` realisations and
  scaled to K, since every run costs the same);
* *naive vmap* (``--naive``): ``vmap`` of the single-realisation segment, where the pair-list
  rebuild's ``lax.cond`` turns into a ``select`` that rebuilds every step
  (:func:`jaxgran.ensemble.run_segments_naive`), the state before the fix.

Realisations beyond ``--distinct`` reuse the first ones' specimens (cost does not depend on
the seed). Float64 unless ``--float32``. Each time is the median of ``--repeats`` calls
after a compiling one.

    python benchmarks/bench_ensemble.py                          # K = 1, 8, 32, 64
    python benchmarks/bench_ensemble.py --cells 30 --steps 200 --ks 1,8 --naive
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def _timed(fn, *args, repeats: int = 1):
    """Median wall time (s) of ``repeats`` calls after one that compiles and warms up."""
    import jax

    jax.block_until_ready(fn(*args))  # compile and warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", type=int, default=100)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--ks", default="1,8,32,64")
    ap.add_argument("--distinct", type=int, default=8, help="distinct Voronoi seeds")
    ap.add_argument("--seq-max", type=int, default=4, help="sequential runs actually timed")
    ap.add_argument("--naive", action="store_true", help="also time the naive vmap")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls; the median is kept")
    ap.add_argument("--float32", action="store_true")
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)

    import dataclasses

    import jax

    jax.config.update("jax_enable_x64", not args.float32)
    from jaxgran import ensemble as ens
    from jaxgran.scenes import bonded_brazilian as bz

    ks = [int(k) for k in args.ks.split(",")]
    record_every = 50
    n_rec = max(1, args.steps // record_every)
    steps = n_rec * record_every
    cfg = dataclasses.replace(bz.Config(), n_cells=args.cells, record_every=record_every)
    setup = bz.build(cfg, seeds=list(range(min(args.distinct, max(ks)))))
    p, g = setup.params, setup.grid
    ready = [ens._prepare_single(s, p, g)[0] for s in setup.states]
    controls = setup.controls
    pick = lambda k: [ready[i % len(ready)] for i in range(k)]
    pick_c = lambda k: [controls[i % len(controls)] for i in range(k)]

    single = lambda s, c: ens._run_single(s, p, c, g, n_rec, record_every)
    t_one = []
    for i in range(min(args.seq_max, len(ready))):
        t_one.append(_timed(single, ready[i], controls[i], repeats=args.repeats))
    t_single = sum(t_one) / len(t_one)

    rows = []
    from machine import cpu_name  # benchmarks/machine.py

    facts = (
        f"{cpu_name()}, {os.cpu_count()} cores, jax {jax.__version__}, "
        f"{time.strftime('%Y-%m-%d')}, median of {args.repeats} timed calls"
    )
    for k in ks:
        states, cs = ens.stack(pick(k)), ens.stack(pick_c(k))
        batch = lambda s, c: ens.run_segments(s, p, c, g, n_rec, record_every)
        t_b = _timed(batch, states, cs, repeats=args.repeats)
        row = {
            "K": k,
            "cells": args.cells,
            "steps": steps,
            "dtype": "float32" if args.float32 else "float64",
            "batch_s": t_b,
            "batch_specimens_per_s": k / t_b,
            "batch_realisation_steps_per_s": k * steps / t_b,
            "sequential_s": k * t_single,
            "sequential_specimens_per_s": 1.0 / t_single,
            "speedup_vs_sequential": k * t_single / t_b,
        }
        if args.naive:
            naive = lambda s, c: ens.run_segments_naive(s, p, c, g, n_rec, record_every)
            t_n = _timed(naive, states, cs, repeats=args.repeats)
            row["naive_vmap_s"] = t_n
            row["naive_vmap_specimens_per_s"] = k / t_n
        rows.append(row)
        print(json.dumps(row), flush=True)
    print()
    print(f"bonded Brazilian, {args.cells} cells, {steps} steps, {rows[0]['dtype']}; {facts}")
    head = "| K | batch (s) | specimens/s | sequential specimens/s | speed-up |"
    if args.naive:
        head += " naive vmap specimens/s |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for r in rows:
        line = (
            f"| {r['K']} | {r['batch_s']:.2f} | {r['batch_specimens_per_s']:.2f} | "
            f"{r['sequential_specimens_per_s']:.2f} | {r['speedup_vs_sequential']:.2f}x |"
        )
        if args.naive:
            line += f" {r['naive_vmap_specimens_per_s']:.2f} |"
        print(line)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": facts, "rows": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
