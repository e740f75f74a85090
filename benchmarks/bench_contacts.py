"""Contact + integration throughput (particle-steps per second) on dense Voronoi packings.

The packing is a Voronoi tessellation of a square eroded by slightly less than the
sphero-radius, so every shared edge is an edge-edge contact (about 6 contacts per particle,
more than a settled pile's ~4: a pessimistic load), under gravity in a box. Timings exclude
compilation; the figure is the median of ``--repeats`` runs of ``--steps`` steps.

    python benchmarks/bench_contacts.py                       # 1k, 4k, 16k, 64k; f32 and f64
    python benchmarks/bench_contacts.py --sizes 4000 --dtypes float32
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name  # noqa: E402


def packing(n: int, dtype, seed: int = 0):
    import jax.numpy as jnp
    import numpy as np

    from jaxgran import geometry as geo
    from jaxgran.integrate import stable_time_step
    from jaxgran.partition import make_grid
    from jaxgran.state import (
        box_walls,
        make_params,
        make_state,
        make_walls,
        particles_from_polygons,
        replace,
    )

    cell = 0.02
    side = cell * np.sqrt(n * 0.65)
    r = 1e-3
    cells = geo.voronoi_rectangle(side, side, n, seed, lloyd_iterations=2)
    cores = [geo.offset_polygon(c, r - 1e-6) for c in cells]
    parts = particles_from_polygons(cores, r, 12.0, dtype=dtype)
    params = make_params(dtype=dtype)
    params = replace(params, dt=jnp.asarray(stable_time_step(parts, params), dtype))
    walls = make_walls(box_walls((0.0, 0.0), (side, side)), dtype=dtype)
    state = make_state(parts, walls, pair_capacity=-(-5 * n // 256) * 256)
    grid = make_grid(
        (-0.05, -0.05),
        (side + 0.05, side + 0.05),
        float(jnp.max(parts.bound_radius)),
        2e-3,
        cell_capacity=12,
    )
    return state, params, grid


def prepared(n: int, dtype_name: str):
    """:func:`packing` with its pair list built and capacities grown: (state, params, grid)."""
    import jax.numpy as jnp

    from jaxgran.simulate import _grow_until_ok, prepare

    dtype = jnp.float32 if dtype_name == "float32" else jnp.float64
    state, params, grid = packing(n, dtype)
    state, err = prepare(state, params, grid)
    state, grid, err = _grow_until_ok(state, params, grid, int(err), [], 8)
    assert err == 0, err
    return state, params, grid


def bench(n: int, dtype_name: str, steps: int, repeats: int) -> dict:
    import jax

    from jaxgran.simulate import run_segment

    state, params, grid = prepared(n, dtype_name)
    out = run_segment(state, params, grid, 1, steps)  # compile
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = run_segment(state, params, grid, 1, steps)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    n_act = int(state.particles.active.sum())
    return {
        "n_particles": n_act,
        "dtype": dtype_name,
        "steps": steps,
        "median_s": med,
        "particle_steps_per_s": n_act * steps / med,
        "runs": times,
        "error_bits": int(out[2]),
        "pairs": int(out[0].contacts.n_pairs),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 4000, 16000, 64000])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    import jax

    results = []
    for dt in args.dtypes:
        jax.config.update("jax_enable_x64", dt == "float64")
        for n in args.sizes:
            r = bench(n, dt, args.steps, args.repeats)
            print(json.dumps({k: v for k, v in r.items() if k != "runs"}), flush=True)
            results.append(r)
    meta = {
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d"),
        "jax": jax.__version__,
        "python": sys.version.split()[0],
    }
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "results": results}, indent=2))
    print(json.dumps(meta))


if __name__ == "__main__":
    main()
