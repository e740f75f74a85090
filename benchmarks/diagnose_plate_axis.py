"""Is the plate-contact axis stress linear in the plate force before the first failure?

For each seed, every record before the first element failure gives the mean horizontal
stress of the middle-third measurement circles and the plate force P. A least-squares line
through them gives the slope (over the closed form's, also averaged over those circles) and
the intercept (over the closed form at the peak force). A slope equal to the last record's
ratio and an intercept near 0 mean no residual stress from the assembly and no dynamic lag:
the scatter between seeds is then the packings' own load paths (docs/speed_vs_accuracy.md
section 4).

    python benchmarks/diagnose_plate_axis.py --seeds 8                # discs, 2.5-5 mm
    python benchmarks/diagnose_plate_axis.py --seeds 8 --particles voronoi

Writes ``benchmarks/plate_acceptance/axis_linearity_<particles>.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def one_seed(seed: int, particles: str) -> dict:
    from jaxgran.scenes import interface_plate as pc

    cfg = dataclasses.replace(pc.Config(), **pc.QUICK, seed=seed, particles=particles)
    t0 = time.perf_counter()
    res, _ = pc.simulate_test(cfg)
    c = pc.circle_centres(cfg)
    mid = np.abs(c[:, 1]) < cfg.diameter / 6
    radius = 0.5 * cfg.circle_diameter
    ref_per_newton = np.mean([pc.closed_form_circle_mean(1.0, cfg, ck, radius) for ck in c[mid]])
    force = np.array([p["force"] for p in res.probes])
    intact = np.array([p["n_failed"] == 0 for p in res.probes])
    sigma = np.array([np.mean(np.asarray(p["sigma_xx"])[mid]) for p in res.probes])
    pre = intact & (force > 0)
    last = np.nonzero(pre)[0][-1]
    a = np.stack([force[intact], np.ones(intact.sum())], axis=1)
    (slope, intercept), *_ = np.linalg.lstsq(a, sigma[intact], rcond=None)
    return {
        "seed": seed,
        "records_before_first_failure": int(intact.sum()),
        "last_record_ratio": float(sigma[last] / (ref_per_newton * force[last])),
        "slope_ratio": float(slope / ref_per_newton),
        "intercept_over_closed_form_at_peak": float(intercept / (ref_per_newton * force.max())),
        "force_max_N": float(force.max()),
        "wall_time_s": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--particles", choices=("discs", "voronoi"), default="discs")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "plate_acceptance"))
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    runs = []
    for s in range(args.seeds):
        runs.append(one_seed(s, args.particles))
        print(json.dumps(runs[-1]), flush=True)
    gap = [
        abs(r["slope_ratio"] - r["last_record_ratio"]) / abs(r["last_record_ratio"]) for r in runs
    ]
    out = {
        "particles": args.particles,
        "runs": runs,
        "largest_relative_gap_slope_vs_last_record": max(gap),
        "largest_abs_intercept_over_closed_form_at_peak": max(
            abs(r["intercept_over_closed_form_at_peak"]) for r in runs
        ),
        "date": time.strftime("%Y-%m-%d"),
    }
    path = Path(args.out) / f"axis_linearity_{args.particles}.json"
    path.write_text(json.dumps(out, indent=1))
    print(
        f"wrote {path}: slope vs last record within {100 * max(gap):.2f} %, intercept at most "
        f"{100 * out['largest_abs_intercept_over_closed_form_at_peak']:.2f} % of the peak's"
    )


if __name__ == "__main__":
    main()
