"""Synthetic twin: can the calibration recover known micro-parameters?

Targets are generated with known ("true") parameters on one set of Voronoi seeds; the fit
starts from a perturbed guess on another set of seeds, by Adam (gradient) and by
Nelder-Mead (gradient-free baseline) on the same loss. The target uncertainties are the
standard errors of the truth ensemble means (at least ``--min-uncertainty`` of the value).

    python -m calibration.twin --realisations 4 --cells 30 --out twin_out

Writes ``twin.json`` (truth, start, fits, relative errors of the free groups, numbers of
simulations and wall times) and ``convergence.png`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from . import fit

TRUTH = {"K_n": 1.2e8, "K_n/K_t": 1.0, "B_n": 2.0e10, "B_n/B_t": 1.5, "eps_th": 0.025, "mu": 0.3}
START = {"K_n": 1.0e8, "K_n/K_t": 1.0, "B_n": 2.0e10, "B_n/B_t": 1.0, "eps_th": 0.02, "mu": 0.3}
FREE = ["K_n", "B_n/B_t", "eps_th"]


def scene_options(cells: int, strain_rate: float, width: float, damping: float) -> dict:
    """Small, fast labs (both scenes) with the smooth surrogate and global damping."""
    lab = {"surrogate_width": width, "damping": damping, "contact_damping": 0.0}
    return {
        "bonded-brazilian": {
            "n_cells": cells,
            "strain_rate": strain_rate,
            "record_every": 25,
            "lab": lab | {"max_strain": 0.05},
        },
        "bonded-biaxial": {
            "n_cells": cells,
            "strain_rate": strain_rate,
            "record_every": 25,
            "max_strain": 0.012,
            "lab": lab | {"fit_strains": [0.002, 0.008]},
        },
    }


FIGURES = ("sigma_t", "slope_S", "E_c", "ucs")


def make_targets(
    truth: dict, seeds: list[int], options: dict, min_uncertainty: float, figures=FIGURES
) -> dict:
    """Targets (value = ensemble mean over ``seeds`` with the true parameters, uncertainty =
    its standard error, at least ``min_uncertainty`` x value)."""
    dummy = {f: {"value": 1.0, "uncertainty": 1.0} for f in figures}
    spec = {"targets": dummy, "initial": truth, "free": FREE} | options
    scenes = sorted({fit.FIGURE_SCENE[f] for f in figures})
    problem = fit.make_problem(spec, scenes, len(seeds), seeds=seeds, peak_from_targets=False)
    _, fwd = fit.make_functions(problem)
    _, (vals, errs) = fwd(np.asarray(problem.z0[problem.free]))
    fit._check(errs)
    vals = np.asarray(vals)
    k = vals.shape[1]
    out = {}
    for t, v in zip(problem.targets, vals, strict=True):
        m = float(v.mean())
        se = float(v.std(ddof=1) / np.sqrt(k)) if k > 1 else 0.0
        out[t.name] = {"value": m, "uncertainty": max(se, min_uncertainty * abs(m))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m calibration.twin", description=__doc__)
    ap.add_argument("--realisations", type=int, default=4)
    ap.add_argument("--cells", type=int, default=30)
    ap.add_argument("--strain-rate", type=float, default=80.0)
    ap.add_argument("--width", type=float, default=1.0)
    ap.add_argument("--damping", type=float, default=2.0e4)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--learning-rate", type=float, default=0.05)
    ap.add_argument("--max-evaluations", type=int, default=120)
    ap.add_argument("--min-uncertainty", type=float, default=0.01)
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("twin_out"))
    args = ap.parse_args(argv)

    import os

    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", True)
    from .plots import plot_convergence

    args.out.mkdir(parents=True, exist_ok=True)
    k = args.realisations
    truth_seeds = list(range(1000, 1000 + k))
    fit_seeds = list(range(k))
    opts = scene_options(args.cells, args.strain_rate, args.width, args.damping)
    for scene in fit.SCENES:  # truth and fit share one time step (dt depends on K_n)
        opts[scene]["lab"]["dt"] = fit.common_time_step(scene, opts[scene], [TRUTH, START])
    t0 = time.perf_counter()
    targets = make_targets(TRUTH, truth_seeds, opts, args.min_uncertainty)
    t_targets = time.perf_counter() - t0
    print("targets", json.dumps(targets))
    spec = {"targets": targets, "initial": START, "free": FREE, "seeds": fit_seeds} | opts
    t0 = time.perf_counter()
    problem = fit.make_problem(spec, list(fit.SCENES), k)
    t_build = time.perf_counter() - t0
    truth_z = fit.groups_from_values(TRUTH)[problem.free]
    summary = {
        "truth": TRUTH,
        "start": START,
        "free": FREE,
        "realisations": k,
        "cells": args.cells,
        "truth_seeds": truth_seeds,
        "fit_seeds": fit_seeds,
        "targets": targets,
        "targets_wall_time_s": t_targets,
        "build_wall_time_s": t_build,
    }
    runs = {"adam": fit.adam(problem, learning_rate=args.learning_rate, steps=args.steps)}
    if not args.no_baseline:
        runs["nelder_mead"] = fit.nelder_mead(problem, max_evaluations=args.max_evaluations)
    for name, res in runs.items():
        rep = fit.report(problem, res, name)
        rep["relative_error"] = {
            g: float(np.exp(x - t) - 1.0)
            for g, x, t in zip(FREE, np.asarray(res["x"]), truth_z, strict=True)
        }
        rep["recovered_within_5_percent"] = all(
            abs(v) < 0.05 for v in rep["relative_error"].values()
        )
        summary[name] = rep
        print(name, rep["relative_error"], rep["simulations"], f"{rep['wall_time_s']:.0f} s")
        print(fit.format_table(rep["table"]))
    summary["adam"]["uncertainty"] = fit.uncertainty(problem, runs["adam"]["x"])
    hist = {n: r["history"] for n, r in runs.items()}
    summary["convergence_plot"] = str(plot_convergence(hist, args.out / "convergence.png"))
    (args.out / "twin.json").write_text(json.dumps(summary, indent=2, default=fit._json))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
