"""Bonded Brazilian benchmark (paper 002 §3): a whole test to failure, and ensembles under
vmap against the same realisations run one after another.

1. A disc of ``--cells`` (default 1000) bonded Voronoi cells loaded to failure (the scene's
   stop rule) in float64 and float32: steps, wall time (compilation included and excluded),
   F_max and sigma_t, so the precision's effect on the result shows next to its speed.
2. K = 1, 8, 32 realisations (``--ks``) of a ``--ensemble-cells`` disc: ``--steps`` steps
   of K stacked realisations under one jax.vmap call, against the K realisations run one
   after another with the single-realisation segment (same compiled code for all K). The
   figure is realisation-steps per second, compilation excluded; the ratio is the vmap
   gain. Each case runs in its own process (precision is process-wide in JAX).

    python benchmarks/bench_bonded.py                  # everything, markdown table at the end
    python benchmarks/bench_bonded.py --cells 300 --ks 1,4 --ensemble-cells 100 --steps 200
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")


def _config(cells: int, **kw):
    import dataclasses

    from jaxgran.scenes import bonded_brazilian as bz

    return dataclasses.replace(bz.Config(), n_cells=cells, **kw)


def case_failure(cells: int, dtype: str) -> dict:
    """One disc to failure; returns steps, wall times and the strength."""
    import jax

    jax.config.update("jax_enable_x64", dtype == "float64")
    from jaxgran.scenes import bonded_brazilian as bz

    cfg = _config(cells)
    t0 = time.perf_counter()
    setup = bz.build(cfg)
    t_build = time.perf_counter() - t0
    res, _ = bz.simulate_test(cfg, setup=setup)
    run = res.realisation(0)
    m = bz.measure(run, setup.gap0[0], cfg.diameter, setup.material)
    seg = cfg.record_every * cfg.records_per_segment
    # time of one more segment with everything compiled, for the steady rate
    from jaxgran import ensemble as ens

    t1 = time.perf_counter()
    ens.drive(
        res.state,
        setup.params,
        setup.controls[0],
        setup.grid,
        n_steps=seg,
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        progress=False,
    )
    t_seg = time.perf_counter() - t1
    return {
        "case": "failure",
        "dtype": dtype,
        "cells": cells,
        "steps": int(res.steps),
        "dt_s": float(setup.params.dt),
        "build_s": t_build,
        "wall_s": float(res.wall_time_s),
        "steps_per_s": seg / t_seg,
        "force_max_N": m["force_max_N"],
        "tensile_strength_MPa": m["tensile_strength_Pa"] / 1e6,
        "strain_at_peak": m["strain_at_force_max"],
        "n_broken": m["n_broken"],
    }


def case_ensemble(cells: int, k: int, steps: int, dtype: str) -> dict:
    """K realisations: vmapped vs sequential, realisation-steps per second."""
    import jax

    jax.config.update("jax_enable_x64", dtype == "float64")
    from jaxgran import ensemble as ens
    from jaxgran.scenes import bonded_brazilian as bz

    cfg = _config(cells, realisations=k, record_every=50)
    n_rec = max(1, steps // cfg.record_every)
    setup = bz.build(cfg)
    p, g = setup.params, setup.grid

    def timed(fn, *args):
        out = fn(*args)  # compile and warm up
        jax.block_until_ready(out)
        t0 = time.perf_counter()
        out = fn(*args)
        jax.block_until_ready(out)
        return time.perf_counter() - t0

    single = lambda s, c: ens._run_single(s, p, c, g, n_rec, cfg.record_every)
    states = [ens._prepare_single(s, p, g)[0] for s in setup.states]
    t_seq = 0.0
    for idx, (s, c) in enumerate(zip(states, setup.controls, strict=True)):
        if idx == 0:
            t_seq += timed(single, s, c)
        else:
            t0 = time.perf_counter()
            jax.block_until_ready(single(s, c))
            t_seq += time.perf_counter() - t0
    out = {"case": "ensemble", "dtype": dtype, "cells": cells, "K": k, "steps": n_rec * 50}
    out["sequential_rs_per_s"] = k * n_rec * cfg.record_every / t_seq
    stacked, controls = ens.stack(states), ens.stack(setup.controls)
    batch = lambda s, c: ens.run_segments(s, p, c, g, n_rec, cfg.record_every)
    t_vm = timed(batch, stacked, controls)
    out["vmap_rs_per_s"] = k * n_rec * cfg.record_every / t_vm
    out["vmap_over_sequential"] = out["vmap_rs_per_s"] / out["sequential_rs_per_s"]
    return out


def _sub(args: list[str]) -> dict:
    cmd = [sys.executable, __file__, "--one", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        sys.stderr.write(res.stderr)
        raise RuntimeError(f"benchmark case {args} failed")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", type=int, default=1000)
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--ks", default="1,8,32")
    ap.add_argument("--ensemble-cells", type=int, default=200)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--skip-failure", action="store_true")
    ap.add_argument("--one", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one is not None:
        kind, *rest = args.one
        if kind == "failure":
            out = case_failure(int(rest[0]), rest[1])
        else:
            out = case_ensemble(int(rest[0]), int(rest[1]), int(rest[2]), rest[3])
        print(json.dumps(out))
        return

    import jax

    print(f"jax {jax.__version__}, backend {jax.default_backend()}, {os.cpu_count()} cores")
    dtypes = args.dtypes.split(",")
    if not args.skip_failure:
        rows = [_sub(["failure", str(args.cells), d]) for d in dtypes]
        print(
            "\n| cells | dtype | dt (s) | steps to failure | wall (s) | steps/s | F_max (kN) "
            "| sigma_t (MPa) | strain at peak | broken bonds |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(
                f"| {r['cells']} | {r['dtype']} | {r['dt_s']:.3g} | {r['steps']} | "
                f"{r['wall_s']:.1f} | {r['steps_per_s']:.0f} | {r['force_max_N'] / 1e3:.1f} | "
                f"{r['tensile_strength_MPa']:.1f} | {r['strain_at_peak']:.4f} | "
                f"{r['n_broken']} |"
            )
    ks = [int(k) for k in args.ks.split(",")]
    rows = [
        _sub(["ensemble", str(args.ensemble_cells), str(k), str(args.steps), dtypes[0]]) for k in ks
    ]
    print(
        "\n| K | cells | dtype | steps | sequential (realisation-steps/s) | "
        "vmap (realisation-steps/s) | vmap / sequential |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['K']} | {r['cells']} | {r['dtype']} | {r['steps']} | "
            f"{r['sequential_rs_per_s']:.0f} | {r['vmap_rs_per_s']:.0f} | "
            f"{r['vmap_over_sequential']:.2f} |"
        )


if __name__ == "__main__":
    main()
