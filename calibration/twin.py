"""Synthetic twin: can the calibration recover known micro-parameters?

Targets are generated with known ("true") parameters on one set of Voronoi seeds; the fit
starts from a perturbed guess on another set of seeds, by Gauss-Newton (forward-mode
Jacobian), by Adam (forward-mode gradient, ``--gradient reverse`` for reverse mode) and by
Nelder-Mead (gradient-free baseline) on the same loss. The target uncertainties are the
standard errors of the truth ensemble means (at least ``--min-uncertainty`` of the value).

Two small ensembles of different seeds differ by their sampling error, so the fit cannot
land closer to the truth than that error allows. Before fitting, :func:`predicted_recovery`
linearises the problem at the truth and reports the predicted scatter of every recovered
group and the error these two seed sets imply; ``within_3_predicted_std`` says whether a
fit is consistent with it, ``recovered_within_5_percent`` whether it meets 5 %.

    python -m calibration.twin --realisations 4 --cells 30 --out twin_out

Writes ``twin.json`` (truth, start, fits, relative errors of the free groups, numbers of
simulations and wall times) and ``convergence.png`` in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
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


FIGURES = ("sigma_t", "slope_S", "E_c", "nu")
"""The twin's figures. Poisson's ratio is the one figure that moves strongly with B_n/B_t
(d log nu / d log(B_n/B_t) ~ 1.2, against 0.1-0.2 for the others): without it B_n/B_t is
resolved to ~90 % only. The unconfined strength is not used: the short unconfined test
(``max_strain`` 0.012) stops before the peak, so its maximum would be the final stress."""


def truth_values(truth: dict, seeds: list[int], options: dict, figures=FIGURES):
    """Figure names and values ``[n_figures, len(seeds)]`` of the truth ensemble."""
    dummy = {f: {"value": 1.0, "uncertainty": 1.0} for f in figures}
    spec = {"targets": dummy, "initial": truth, "free": FREE} | options
    scenes = sorted({fit.FIGURE_SCENE[f] for f in figures})
    problem = fit.make_problem(spec, scenes, len(seeds), seeds=seeds, peak_from_targets=False)
    _, fwd = fit.make_functions(problem)
    _, (vals, errs) = fwd(np.asarray(problem.z0[problem.free]))
    fit._check(errs)
    return [t.name for t in problem.targets], np.asarray(vals)


def targets_from_values(names, vals, min_uncertainty: float) -> dict:
    """Targets: value = ensemble mean, uncertainty = its standard error, at least
    ``min_uncertainty`` x value."""
    k = vals.shape[1]
    out = {}
    for name, v in zip(names, vals, strict=True):
        m = float(v.mean())
        se = float(v.std(ddof=1) / np.sqrt(k)) if k > 1 else 0.0
        out[name] = {"value": m, "uncertainty": max(se, min_uncertainty * abs(m))}
    return out


def make_targets(
    truth: dict, seeds: list[int], options: dict, min_uncertainty: float, figures=FIGURES
) -> dict:
    """Targets (value = ensemble mean over ``seeds`` with the true parameters, uncertainty =
    its standard error, at least ``min_uncertainty`` x value)."""
    names, vals = truth_values(truth, seeds, options, figures)
    return targets_from_values(names, vals, min_uncertainty)


def predicted_recovery(problem: fit.Problem, truth: dict, truth_vals) -> dict:
    """How well can the fit recover the truth, given that targets and fit use different
    Voronoi seeds? Linearised at the truth on the fit's seeds (one forward-mode Jacobian):
    the fit's step is ``dz = A (t - m)`` with ``A = (J^T W J)^-1 J^T W``, ``W = 1 / u^2``
    (the target uncertainties), ``t`` the targets and ``m`` the fit ensemble's means at the
    truth. Both ensembles are random samples of the same material, so ``t - m`` has the
    variance ``s_t^2 / K_t + s_m^2 / K`` (spreads over the seeds) and the recovered log
    groups scatter with ``cov = A diag(s_t^2 / K_t + s_m^2 / K) A^T``.

    Returns the predicted relative std of each free group (``predicted_relative_std``),
    the linearised error for these two seed sets (``linearised_error``, relative), the
    relative spread of each figure over the fit seeds and ``d log figure / d log group``.
    The 5 % criterion can only be met reliably when the predicted std is below ~2.5 %."""
    if len(problem.seeds) < 2 or np.asarray(truth_vals).shape[1] < 2:
        raise ValueError("predicted_recovery needs at least 2 realisations in each ensemble")
    z = fit.groups_from_values(truth)
    fixed = [i for i in range(z.size) if i not in problem.free]
    if not np.allclose(np.asarray(problem.z0)[fixed], z[fixed], rtol=0.0, atol=1e-12):
        raise ValueError("the problem's fixed groups must have the truth's values")
    jac, vals = fit.mean_jacobian(problem, z[problem.free])
    truth_vals = np.asarray(truth_vals)
    m, mt = vals.mean(axis=1), truth_vals.mean(axis=1)
    t = np.array([tt.value for tt in problem.targets])
    u = np.array([tt.uncertainty for tt in problem.targets])
    var = (
        vals.var(axis=1, ddof=1) / vals.shape[1]
        + truth_vals.var(axis=1, ddof=1) / (truth_vals.shape[1])
    )
    w = 1.0 / u**2
    try:
        a = np.linalg.solve(jac.T @ (w[:, None] * jac), jac.T * w)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"the {len(problem.targets)} figures do not determine the {problem.n_free} free "
            "groups (singular J^T W J): add figures or free fewer groups"
        ) from None
    cov = a @ np.diag(var) @ a.T
    names = [fit.GROUPS[i] for i in problem.free]
    return {
        "free": names,
        "figures": [tt.label for tt in problem.targets],
        "predicted_relative_std": dict(zip(names, np.sqrt(np.diag(cov)).tolist(), strict=True)),
        "linearised_error": dict(zip(names, np.expm1(a @ (t - m)).tolist(), strict=True)),
        "fit_seed_means_at_truth": m.tolist(),
        "truth_seed_means": mt.tolist(),
        "figure_relative_spread": (vals.std(axis=1, ddof=1) / np.abs(m)).tolist(),
        "jacobian_dlog": (jac / m[:, None]).tolist(),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m calibration.twin", description=__doc__)
    ap.add_argument("--realisations", type=int, default=4)
    ap.add_argument("--cells", type=int, default=30)
    ap.add_argument("--truth-seeds-from", type=int, default=1000, help="first truth seed")
    ap.add_argument("--fit-seeds-from", type=int, default=0, help="first seed of the fit")
    ap.add_argument("--strain-rate", type=float, default=80.0)
    ap.add_argument("--width", type=float, default=1.0)
    ap.add_argument("--damping", type=float, default=2.0e4)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--learning-rate", type=float, default=0.05)
    ap.add_argument("--max-evaluations", type=int, default=120)
    ap.add_argument("--min-uncertainty", type=float, default=0.01)
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument(
        "--methods",
        default="gauss_newton,adam",
        help="gradient fits to run, comma-separated (gauss_newton, adam); Nelder-Mead "
        "follows unless --no-baseline. Adam needs tens of gradient evaluations: leave it "
        "out of large ensembles",
    )
    ap.add_argument(
        "--gradient",
        choices=fit.GRADIENTS,
        default="forward",
        help="Adam's gradient: forward mode (one run with one tangent per free group) or "
        "reverse mode",
    )
    ap.add_argument("--out", type=Path, default=Path("twin_out"))
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = set(methods) - {"gauss_newton", "adam"}
    if unknown or not methods:
        ap.error(f"--methods: choose from gauss_newton, adam (got {args.methods!r})")

    import os

    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", True)
    from .plots import plot_convergence

    args.out.mkdir(parents=True, exist_ok=True)
    k = args.realisations
    truth_seeds = list(range(args.truth_seeds_from, args.truth_seeds_from + k))
    fit_seeds = list(range(args.fit_seeds_from, args.fit_seeds_from + k))
    if set(truth_seeds) & set(fit_seeds):
        ap.error("the truth and fit seed sets overlap: the twin needs two independent sets")
    opts = scene_options(args.cells, args.strain_rate, args.width, args.damping)
    for scene in fit.SCENES:  # truth and fit share one time step (dt depends on K_n)
        opts[scene]["lab"]["dt"] = fit.common_time_step(
            scene, opts[scene], [TRUTH, START], seeds=truth_seeds + fit_seeds
        )
    t0 = time.perf_counter()
    names, tvals = truth_values(TRUTH, truth_seeds, opts)
    targets = targets_from_values(names, tvals, args.min_uncertainty)
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
    t0 = time.perf_counter()
    summary["predicted"] = predicted_recovery(problem, TRUTH, tvals)
    summary["predicted"]["wall_time_s"] = time.perf_counter() - t0
    print(
        "predicted recovery",
        json.dumps(
            {k: summary["predicted"][k] for k in ("predicted_relative_std", "linearised_error")}
        ),
    )
    runs = {}
    if "gauss_newton" in methods:
        runs["gauss_newton"] = fit.gauss_newton(problem)
    if "adam" in methods:
        runs["adam"] = fit.adam(
            problem, learning_rate=args.learning_rate, steps=args.steps, gradient=args.gradient
        )
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
        sd = summary["predicted"]["predicted_relative_std"]
        rep["within_3_predicted_std"] = all(
            abs(math.log1p(v)) <= 3.0 * sd[g] for g, v in rep["relative_error"].items()
        )
        summary[name] = rep
        print(name, rep["relative_error"], rep["simulations"], f"{rep['wall_time_s']:.0f} s")
        print(fit.format_table(rep["table"]))
    if "adam" in runs:
        summary["adam"]["uncertainty"] = fit.uncertainty(problem, runs["adam"]["x"])
    label = {
        "gauss_newton": "Gauss-Newton (forward-mode Jacobian)",
        "adam": f"Adam ({args.gradient}-mode gradient)",
        "nelder_mead": "Nelder-Mead (no gradient)",
    }
    hist = {label[n]: r["history"] for n, r in runs.items()}
    summary["convergence_plot"] = str(plot_convergence(hist, args.out / "convergence.png"))
    (args.out / "twin.json").write_text(json.dumps(summary, indent=2, default=fit._json))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
