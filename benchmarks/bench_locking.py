"""Locking counts per breakage method (issue 9, stability study): the same Cantor pentagon
oedometer (`oedometer-cantor`, paper 000 §III; the mid-size pile of
`benchmarks/bench_erosion.py`) broken by each of the four replaceable-particle methods, all
calibrated to the same Brazilian breaking force, several seeds each.

The locking effect (paper 000 §IV.A, Fig. 10) is a fragment that keeps its parent's load and
breaks again along nearly the same direction, shaving strips off the grain.
:func:`jaxgran.breakage.metrics.locking_effect` counts, per run, the *repeats* (an event
whose parent is a fragment of an earlier event cut within 15 degrees of that event's plane)
and the *locking chains* (two or more repeats in one lineage).

    python benchmarks/bench_locking.py                     # 4 methods x seeds 0, 1
    python benchmarks/bench_locking.py --seeds 0 --methods dsm,split-cell
    python benchmarks/bench_locking.py --pile default --seeds 0 --jobs 4 \
        --md benchmarks/LOCKING_RESULTS_quasistatic.md   # the scene's own quasi-static test

``--pile mid`` (the default) is the 12-grain pile above, a dynamic test (the bar at 0.1 m/s,
grains broken at 50 N) that runs in a minute; ``--pile default`` is `oedometer-cantor` with
its own settings (24 grains, the bar at 1 mm/s, paper 000's strength), the quasi-static test,
about 20-45 min per run on 2 CPU cores. ``--jobs N`` runs N of the (method, seed) runs at once
in separate processes.

Writes ``benchmarks/LOCKING_RESULTS.md`` (and the per-run numbers as JSON next to it).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_erosion import MID  # noqa: E402
from machine import choices, cpu_name, release_compiled, write_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("dsm", "split-cell", "cross-cut", "mohr-coulomb")
# the piles: overrides of the scene's defaults
PILES = {"mid": MID, "default": {}}


def one(method: str, seed: int, sets: dict | None = None, pile: str = "mid") -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)  # also in a worker process of --jobs
    from jaxgran.breakage import metrics
    from jaxgran.scenes import oedometer_cantor as oc
    from jaxgran.scenes.base import apply_overrides

    cfg = dataclasses.replace(oc.Config(), **PILES[pile], method=method, seed=seed)
    cfg = apply_overrides(cfg, sets)
    t0 = time.perf_counter()
    settle, load, brk, info = oc.simulate_test(cfg)
    wall = time.perf_counter() - t0
    ev = brk.events
    lock = metrics.locking_effect(ev)
    lost = sum(float(e["mass_lost"]) for e in ev)
    return {
        "method": method,
        "seed": seed,
        "n_events": len(ev),
        "n_repeats": int(lock["n_repeats"]),
        "repeat_fraction": float(lock["repeat_fraction"]),
        "n_locking_chains": int(lock["n_locking_chains"]),
        "max_chain": int(lock["max_chain"]),
        "n_candidates": int(lock["n_candidates"]),
        "repeats_by_chance": float(lock["repeats_by_chance"]),
        "mass_lost_pct": 100.0 * lost / info["initial_mass"],
        # loading time (s) at the first breakage, None without one
        "first_event_s": (float(ev[0]["time"]) - float(info["load_start_time"])) if ev else None,
        "steps": int(load.steps),
        "wall_time_s": wall,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "LOCKING_RESULTS.md"))
    ap.add_argument("--pile", default="mid", help="mid (12 grains, dynamic) or default")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (separate processes)")
    ap.add_argument(
        "--add",
        action="store_true",
        help="keep the rows of the JSON next to --md of other (method, seed) pairs",
    )
    ap.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change a setting of the scene for every run (e.g. erosion=uniform)",
    )
    args = ap.parse_args()
    from jaxgran.scenes import oedometer_cantor as oc
    from jaxgran.scenes.base import apply_overrides, parse_sets

    sets = parse_sets(args.sets)
    typed = apply_overrides(oc.Config(), sets)  # checked now, and echoed with their types
    set_values = {k: getattr(typed, k) for k in sets}

    import jax

    jax.config.update("jax_enable_x64", True)
    methods = choices(args.methods, METHODS, "--methods")
    if args.pile not in PILES:
        raise SystemExit(f"--pile: {args.pile!r} is not one of {', '.join(PILES)}")
    pile = args.pile
    if args.jobs < 1:
        raise SystemExit(f"--jobs must be >= 1, got {args.jobs}")
    seeds = [int(s) for s in args.seeds.split(",")]
    runs = [(m, s) for m in methods for s in seeds]
    if args.jobs == 1:
        rows = []
        for m, s in runs:
            rows.append(one(m, s, sets, pile))
            release_compiled()  # the next run compiles its own shapes
            print(rows[-1], flush=True)
    else:
        import concurrent.futures
        import multiprocessing

        # a fresh process (and JAX) for every run, so that no worker piles up compiled code
        # (see machine.release_compiled)
        ctx = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
            args.jobs, mp_context=ctx, max_tasks_per_child=1
        ) as pool:
            futures = [pool.submit(one, m, s, sets, pile) for m, s in runs]
            for f in concurrent.futures.as_completed(futures):
                print(f.result(), flush=True)
            rows = [f.result() for f in futures]  # in the order of the runs
    store = Path(args.md).with_suffix(".json")
    if args.add and store.exists():
        kept = [r for r in json.loads(store.read_text()) if (r["method"], r["seed"]) not in runs]
        rows = sorted(kept + rows, key=lambda r: (METHODS.index(r["method"]), r["seed"]))
        seeds = sorted({r["seed"] for r in rows})
        methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    store.write_text(json.dumps(rows, indent=1))
    cmd = "python benchmarks/bench_locking.py"
    if seeds != [0, 1]:
        cmd += f" --seeds {','.join(str(s) for s in seeds)}"
    if methods != list(METHODS):
        cmd += f" --methods {','.join(methods)}"
    if pile != "mid":
        cmd += f" --pile {pile}"
    if args.jobs != 1:
        cmd += f" --jobs {args.jobs}"
    cmd += "".join(f" --set {k}={v}" for k, v in sets.items())
    default_md = ROOT / "benchmarks" / "LOCKING_RESULTS.md"
    if Path(args.md).resolve() != default_md:
        cmd += f" --md {os.path.relpath(Path(args.md).resolve(), ROOT)}"
    lines = [
        "# Locking counts per breakage method",
        "",
        f"`{cmd}` on {cpu_name()} ({os.cpu_count()} cores), jax {jax.__version__} on the "
        f"CPU, float64, {datetime.date.today().isoformat()}. Scene: `oedometer-cantor` with "
        + (
            f"{json.dumps(MID | set_values)} (12 grains, weaker grains and a faster bar so "
            "that several break in a minute); every method calibrated to the same Brazilian "
            "force (50 N). "
            if pile == "mid"
            else f"its own settings{' and ' + json.dumps(set_values) if set_values else ''} "
            "(24 grains, the bar at 1 mm/s: the quasi-static test); every method calibrated "
            "to the same Brazilian force (150.79 N, paper 000 §III). "
        )
        + "Repeat: an event whose parent is a fragment of an earlier event, cut within "
        "15 deg of that event's plane; locking chain: 2 or more repeats in one lineage "
        "(`jaxgran.breakage.metrics.locking_effect`). Candidates: events whose parent is a "
        "fragment of an earlier event; by chance: the repeats expected if each candidate's "
        "planes were turned (as one set) by a random angle, which counts that an event cut "
        "by several planes matches more often.",
        "",
        "| method | seed | events | candidates | repeats | by chance | repeat fraction | "
        "locking chains | longest chain (events) | mass lost % | first breakage (s of "
        "loading) | steps | wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        first = r.get("first_event_s")
        lines.append(
            f"| {r['method']} | {r['seed']} | {r['n_events']} | {r['n_candidates']} | "
            f"{r['n_repeats']} | {r['repeats_by_chance']:.1f} | {r['repeat_fraction']:.2f} | "
            f"{r['n_locking_chains']} | {r['max_chain']} | "
            f"{r['mass_lost_pct']:.2f} | {'-' if first is None else f'{first:.2f}'} | "
            f"{r['steps']} | {r['wall_time_s']:.0f} |"
        )
    lines += [
        "",
        "| method | runs | events (sum) | candidates (sum) | repeats (sum) | repeats by chance "
        "(sum) | locking chains (sum) |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in methods:
        sel = [r for r in rows if r["method"] == m]
        lines.append(
            f"| {m} | {len(sel)} | {sum(r['n_events'] for r in sel)} | "
            f"{sum(r['n_candidates'] for r in sel)} | {sum(r['n_repeats'] for r in sel)} | "
            f"{sum(r['repeats_by_chance'] for r in sel):.1f} | "
            f"{sum(r['n_locking_chains'] for r in sel)} |"
        )
    write_table(args.md, lines)


if __name__ == "__main__":
    main()
