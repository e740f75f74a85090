"""Plate-contact acceptance numbers (issue 7, paper 003 §5), over seeds and resolutions.

A single 2D specimen of a few hundred bonded discs is one draw of a random packing, and
the plate-contact figures (split angle, where the shear failures are, the horizontal stress
on the axis) scatter from draw to draw. This runner repeats the scene for several seeds and
elementary-disc sizes and reports every run and the summary over seeds:

    python benchmarks/run_plate_acceptance.py seeds        # default disc size, --seeds seeds
    python benchmarks/run_plate_acceptance.py seeds --size "1-2 mm" --name seeds_1-2mm
    python benchmarks/run_plate_acceptance.py seeds --particles voronoi --name seeds_voronoi
    python benchmarks/run_plate_acceptance.py resolution   # three disc sizes (4 seeds finest)
    python benchmarks/run_plate_acceptance.py speed        # discs (V = 1) vs Voronoi, 3 runs

Results go to ``<out>/<part>.json`` (default ``benchmarks/plate_acceptance``) and the
resolution figure to ``docs/plate_contact_resolution.png``. Runs are sequential (on a
2-core CPU one specimen already keeps both cores busy), float64.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
# elementary disc diameters (d_min, d_max) in m: paper 003's 2.5-5 mm, and two finer ones
SIZES = {"2.5-5 mm": (2.5e-3, 5e-3), "1.25-2.5 mm": (1.25e-3, 2.5e-3), "1-2 mm": (1e-3, 2e-3)}


def _x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def one_run(**overrides) -> dict:
    """The plate-contact scene with ``overrides`` (Config fields): its measured figures,
    the signed axis-stress ratio in the middle third, and the speed."""
    from jaxgran.scenes import interface as si
    from jaxgran.scenes import interface_plate as pc

    cfg = dataclasses.replace(pc.Config(), **pc.QUICK, **overrides)
    t0 = time.perf_counter()
    res, setup = pc.simulate_test(cfg)
    wall = time.perf_counter() - t0
    m = pc.measure(res, setup, cfg)
    out = {
        "overrides": overrides,
        "n_particles": setup.spec.n_particles,
        "dt_s": float(setup.params.dt),
        "steps": int(res.steps),
        "wall_time_s": wall,
    }
    out.update(si.steady_rate(res, setup.spec.n_particles, cfg))
    for k in (
        "force_max_N",
        "displacement_at_peak_m",
        "first_failure_force_over_max",
        "final_force_over_max",
        "n_failed_tension",
        "n_failed_shear",
        "split_angle_from_loading_axis_deg",
        "fragment_sizes",
        "shear_share_near_plates",
        "element_share_near_plates",
        "cone_half_angle_deg",
    ):
        out[k] = m.get(k)
    prof = m.get("axis_before_first_failure")
    if prof:
        y = np.asarray(prof["y_m"])
        mid = np.abs(y) < cfg.diameter / 6
        meas = np.asarray(prof["sigma_xx_Pa"])[mid].mean()
        ref = np.asarray(prof["closed_form_circle_Pa"])[mid].mean()
        out["axis_force_N"] = prof["force_N"]
        out["axis_middle_third_ratio"] = float(meas / ref)
        out["axis_profile_over_closed_form_centre"] = (
            np.asarray(prof["sigma_xx_Pa"]) / prof["closed_form_Pa"]
        ).tolist()
    frags = out["fragment_sizes"] or [out["n_particles"]]
    out["split"] = bool(
        out["final_force_over_max"] < cfg.drop_fraction
        and len(frags) >= 2
        and frags[1] >= 0.2 * out["n_particles"]
        and (out["split_angle_from_loading_axis_deg"] or 90.0) < 25.0
    )
    near = out["shear_share_near_plates"]
    out["shear_concentrated_under_plates"] = bool(
        near is not None and near > 1.2 * out["element_share_near_plates"]
    )
    print(json.dumps({k: out[k] for k in ("overrides", "n_particles", "wall_time_s")}), flush=True)
    return out


def one_seed_run(**overrides) -> dict:
    """:func:`one_run`, then the compiled code dropped: each seed's specimen has its own
    capacities, and a long series of seeds in one process would otherwise pass the kernel's
    limit of memory mappings (``benchmarks/machine.py``). The speed part keeps its compiled
    code, so that its repeats of one specimen time the warm runs."""
    out = one_run(**overrides)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from machine import release_compiled

    release_compiled()
    return out


def summarise(runs: list[dict]) -> dict:
    ratios = [r["axis_middle_third_ratio"] for r in runs if "axis_middle_third_ratio" in r]
    angles = [r["split_angle_from_loading_axis_deg"] for r in runs if r["split"]]
    return {
        "n_runs": len(runs),
        "n_particles_mean": statistics.mean(r["n_particles"] for r in runs),
        "split_along_axis": sum(r["split"] for r in runs),
        "split_angle_deg_of_the_splits": angles,
        "shear_concentrated_under_plates": sum(r["shear_concentrated_under_plates"] for r in runs),
        "axis_middle_third_ratio_mean": statistics.mean(ratios) if ratios else None,
        "axis_middle_third_ratio_std": statistics.stdev(ratios) if len(ratios) > 1 else None,
        # standard error of the mean over the seeds: is the ensemble biased, not just noisy?
        "axis_middle_third_ratio_sem": (
            statistics.stdev(ratios) / len(ratios) ** 0.5 if len(ratios) > 1 else None
        ),
        "axis_middle_third_ratio_median": statistics.median(ratios) if ratios else None,
        "axis_within_10_percent": sum(abs(x - 1) < 0.10 for x in ratios),
        "force_max_N_mean": statistics.mean(r["force_max_N"] for r in runs),
        # NaN where no element failed before the run stopped
        "first_failure_force_over_max_mean": float(
            np.nanmean([r["first_failure_force_over_max"] for r in runs])
        ),
        "runs_without_element_failure": sum(
            not np.isfinite(r["first_failure_force_over_max"]) for r in runs
        ),
        "wall_time_s_median": statistics.median(r["wall_time_s"] for r in runs),
    }


def seeds(args) -> dict:
    over = {"particles": args.particles}
    if args.size is not None:
        over["d_min"], over["d_max"] = SIZES[args.size]
    first = args.first_seed
    runs = [one_seed_run(seed=s, **over) for s in range(first, first + args.seeds)]
    return {
        "size": args.size or "default",
        "particles": args.particles,
        "runs": runs,
        "summary": summarise(runs),
    }


def resolution(args) -> dict:
    out = {}
    for k, (name, (d0, d1)) in enumerate(SIZES.items()):
        n = args.seeds if k < len(SIZES) - 1 else min(args.seeds, args.finest_seeds)
        runs = [one_seed_run(seed=s, particles="discs", d_min=d0, d_max=d1) for s in range(n)]
        out[name] = {"runs": runs, "summary": summarise(runs)}
    _figure(out, DOCS / "plate_contact_resolution.png")
    return out


def speed(args) -> dict:
    """Wall time and particle-steps/s of the same specimen (seed 0) as discs and as Voronoi
    cells: ``--repeats`` runs of each, the median of each timing and every run's values
    (the runs are deterministic, so only the timings differ between them)."""
    out = {}
    timings = ("wall_time_s", "s_per_step", "particle_steps_per_s")
    for kind in ("discs", "voronoi"):
        runs = [one_run(particles=kind, seed=0) for _ in range(args.repeats)]
        r = runs[0]
        out[kind] = {k: r.get(k) for k in ("n_particles", "dt_s", "steps", "force_max_N")}
        out[kind] |= {k: statistics.median(x[k] for x in runs) for k in timings}
        out[kind]["runs"] = [{k: x[k] for k in timings} for x in runs]
    return out


def _figure(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from machine import save_figure

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for k, (name, part) in enumerate(res.items()):
        runs = part["runs"]
        n = part["summary"]["n_particles_mean"]
        ratios = [r.get("axis_middle_third_ratio", np.nan) for r in runs]
        ax[0].plot(np.full(len(ratios), n), ratios, "o", alpha=0.6, label=name)
        walls = [r["wall_time_s"] for r in runs]
        ax[1].plot(np.full(len(walls), n), walls, "s", alpha=0.6, color=f"C{k}")
    ax[0].axhline(1.0, color="k", lw=1)
    ax[0].axhspan(0.9, 1.1, color="0.85")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("elementary discs")
    ax[0].set_ylabel("axis sigma_xx / closed form\n(middle third, before first failure)")
    ax[0].legend(fontsize=8)
    ax[1].set_xscale("log")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("elementary discs")
    ax[1].set_ylabel("wall time to breakage (s)")
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("part", choices=("seeds", "resolution", "speed"))
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument(
        "--finest-seeds", type=int, default=4, help="seeds of the finest size (the dearest)"
    )
    ap.add_argument(
        "--size", choices=tuple(SIZES), default=None, help="seeds: elementary disc size"
    )
    ap.add_argument("--first-seed", type=int, default=0, help="seeds: the first seed")
    ap.add_argument("--repeats", type=int, default=3, help="speed: runs of each specimen")
    ap.add_argument(
        "--particles",
        choices=("discs", "voronoi"),
        default="discs",
        help="seeds: bonded discs, or the same region meshed as Voronoi cells (as many)",
    )
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "plate_acceptance"))
    ap.add_argument("--name", default=None, help="output file stem (default: the part)")
    args = ap.parse_args()
    _x64()
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from machine import cpu_name

    t = time.perf_counter()
    result = {"seeds": seeds, "resolution": resolution, "speed": speed}[args.part](args)
    result["machine"] = f"{cpu_name()}, {os.cpu_count()} cores"
    result["date"] = time.strftime("%Y-%m-%d")
    result["load_average_at_end"] = os.getloadavg()[0]
    result["wall_time_s_total"] = time.perf_counter() - t
    path = Path(args.out) / f"{args.name or args.part}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=float))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
