"""Cost of the grid's origin and cell size as traced values rather than constants.

The same segment (``--steps`` steps of the ``bench_contacts`` packing) compiled twice in one
process: once with the grid passed as an argument (its origin and cell size traced, as every
scene runs it) and once closed over (they become compile-time constants, as when the grid
was static). The two are timed alternately, so drift of a shared machine hits both alike.

    python benchmarks/bench_grid_values.py --sizes 1000 4000 --dtypes float32 float64
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
from bench_contacts import prepared  # noqa: E402
from machine import cpu_name  # noqa: E402


def bench(n: int, dtype_name: str, steps: int, repeats: int) -> dict:
    import equinox as eqx
    import jax

    from jaxgran.simulate import run_segment

    state, params, grid = prepared(n, dtype_name)
    variants = {
        "traced": lambda s: run_segment(s, params, grid, 1, steps),
        "constant": eqx.filter_jit(lambda s: run_segment.__wrapped__(s, params, grid, 1, steps)),
    }
    for f in variants.values():
        jax.block_until_ready(f(state))  # compile
    times = {k: [] for k in variants}
    for r in range(repeats):
        order = list(variants) if r % 2 == 0 else list(variants)[::-1]
        for k in order:
            t0 = time.perf_counter()
            jax.block_until_ready(variants[k](state))
            times[k].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "n_particles": int(state.particles.active.sum()),
        "dtype": dtype_name,
        "steps": steps,
        "traced_s": med["traced"],
        "constant_s": med["constant"],
        "ratio": med["traced"] / med["constant"],
        "runs": times,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 4000])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    print(f"| particles | dtype | grid traced, s / {args.steps} steps | grid constant | ratio |")
    print("|---|---|---|---|---|")
    for n in args.sizes:
        for d in args.dtypes:
            r = bench(n, d, args.steps, args.repeats)
            print(
                f"| {r['n_particles']:,} | {d} | {r['traced_s']:.3f} | {r['constant_s']:.3f} "
                f"| {r['ratio']:.3f} |",
                flush=True,
            )
    meta = {"machine": cpu_name(), "cores": os.cpu_count(), "jax": jax.__version__}
    print(json.dumps(meta | {"date": time.strftime("%Y-%m-%d")}))


if __name__ == "__main__":
    main()
