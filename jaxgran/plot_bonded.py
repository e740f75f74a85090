"""Figures of the bonded Voronoi acceptance runs (paper 002): the p-q strength envelope with
its Hoek-Brown fit, the cantilever deflection against beam theory, the pooled burst-size
distribution and the calibration sweeps. Matplotlib only here (Agg backend); every function
takes plain dicts / arrays and writes one PNG, returning its path."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from . import analysis as an  # noqa: E402


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path


def hoek_brown_figure(result: dict, path: Path) -> Path:
    """Left: p-q plane (MPa) with every test's peak (filled: true peak, open: no softening
    peak) and residual state, the Hoek-Brown fit of Eq. 31 (2D) and the residual line.
    Right: the same peaks as (s3, s1) with the fit of Eq. 30."""
    runs = result.get("runs", [])
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
    mpa = 1e-6
    true = [r for r in runs if r["true_peak"]]
    other = [r for r in runs if not r["true_peak"]]
    if true:
        a1.plot(
            [r["p_at_peak_Pa"] * mpa for r in true],
            [r["q_peak_Pa"] * mpa for r in true],
            "o",
            color="C0",
            label="peak",
        )
    if other:
        a1.plot(
            [r["p_at_peak_Pa"] * mpa for r in other],
            [r["q_peak_Pa"] * mpa for r in other],
            "o",
            mfc="none",
            color="C0",
            label="max q, no softening peak",
        )
    a1.plot(
        [r["p_residual_Pa"] * mpa for r in runs],
        [r["q_residual_Pa"] * mpa for r in runs],
        "s",
        color="C1",
        ms=4,
        label="residual",
    )
    ucs = result.get("unconfined", [])
    if ucs:
        u = np.array([v["strength_Pa"] for v in ucs]) * mpa
        a1.plot(u / 2, u / 2, "^", color="C2", label="unconfined")
        a2.plot(np.zeros_like(u), u, "^", color="C2", label="unconfined")
    pmax = max([r["p_residual_Pa"] for r in runs] + [r["p_at_peak_Pa"] for r in runs] + [1.0])
    pp = np.linspace(0.0, 1.1 * pmax, 100)
    fits = result.get("fits", {}).get("with_unconfined", {})
    fit = fits.get("hoek_brown", {})
    if "A" in fit:
        a1.plot(
            pp * mpa,
            an.hoek_brown_q(pp, fit["A"], fit["B"]) * mpa,
            "-",
            color="C0",
            label=(
                f"Hoek-Brown (Eq. 31, 2D): A = {fit['A'] * mpa:.0f} ± {fit['A_err'] * mpa:.0f}, "
                f"B = {fit['B'] * mpa:.0f} ± {fit['B_err'] * mpa:.0f} MPa, R² = {fit['r2']:.3f}"
            ),
        )
    line = fits.get("residual_line")
    if line:
        a1.plot(
            pp * mpa,
            (line["slope"] * pp + line["intercept"]) * mpa,
            "--",
            color="C1",
            label=f"residual line: q = {line['slope']:.2f} p + {line['intercept'] * mpa:.0f} MPa, "
            f"R² = {line['r2']:.3f}",
        )
    a1.set_xlabel("p = (s1 + s3) / 2 (MPa)")
    a1.set_ylabel("q = (s1 - s3) / 2 (MPa)")
    a1.legend(fontsize=7)
    a1.grid(True, alpha=0.3)
    if true:
        s3 = np.array([r["sigma_3_peak_Pa"] for r in true]) * mpa
        s1 = np.array([r["sigma_1_peak_Pa"] for r in true]) * mpa
        a2.plot(s3, s1, "o", color="C0", label="peak")
    fit2 = fits.get("hoek_brown_s1s3", {})
    if "A" in fit2 and true:
        xs = np.linspace(min(s3.min(), 0.0), max(s3.max(), 0.0), 100) / mpa
        a2.plot(
            xs * mpa,
            an.hoek_brown_sigma1(xs, fit2["A"], fit2["B"]) * mpa,
            "-",
            color="C0",
            label=(
                f"Eq. 30 (regression on s3): A = {fit2['A'] * mpa:.0f}, "
                f"B = {fit2['B'] * mpa:.0f} MPa, R²(s1) = {fit2['r2']:.3f}"
            ),
        )
    a2.set_xlabel("s3 at peak (MPa, compression > 0)")
    a2.set_ylabel("s1 at peak (MPa)")
    a2.legend(fontsize=7)
    a2.grid(True, alpha=0.3)
    return _save(fig, path)


def cantilever_figure(curves: list[dict], path: Path) -> Path:
    """Middle-line deflection (mm, down) against the distance from the clamp (cm) for each
    case of ``curves`` (dicts with ``x``, ``w``, ``theory`` {label: w} and ``label``)."""
    fig, axes = plt.subplots(1, len(curves), figsize=(5.5 * len(curves), 4), squeeze=False)
    for ax, c in zip(axes[0], curves, strict=True):
        ax.plot(100 * np.asarray(c["x"]), 1e3 * np.asarray(c["w"]), "o", ms=3, label="DEM")
        for k, (label, w) in enumerate(c["theory"].items()):
            ax.plot(
                100 * np.asarray(c["x"]), 1e3 * np.asarray(w), "-", color=f"C{k + 1}", label=label
            )
        ax.set_title(c["label"], fontsize=9)
        ax.set_xlabel("distance from the clamp (cm)")
        ax.set_ylabel("deflection w (mm, down)")
        ax.invert_yaxis()
        ax.legend(fontsize=7)
        ax.grid(True, alpha=0.3)
    return _save(fig, path)


def bursts_figure(sizes_by_label: dict[str, np.ndarray], path: Path) -> Path:
    """Pooled burst-size distributions (log bins) with their maximum-likelihood power laws
    (:func:`jaxgran.analysis.power_law_mle`, discrete, x_min = 1)."""
    from scipy.special import zeta

    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    for k, (label, sizes) in enumerate(sizes_by_label.items()):
        s = np.asarray(sizes)
        s = s[s > 0]
        if s.size < 10 or np.unique(s).size < 2:
            continue
        x, dens = an.log_histogram(s)
        fit = an.power_law_mle(s, 1)
        ok = dens > 0
        ax.loglog(x[ok], dens[ok], "o", color=f"C{k}")
        xs = np.geomspace(1, s.max(), 30)
        ax.loglog(
            xs,
            xs ** (-fit["alpha"]) / zeta(fit["alpha"], 1),
            "-",
            color=f"C{k}",
            label=f"{label}: alpha = {fit['alpha']:.2f} ± {fit['alpha_err']:.2f} (n = {fit['n']})",
        )
    ax.set_xlabel("broken bonds per record window")
    ax.set_ylabel("probability")
    ax.legend(fontsize=7)
    ax.grid(True, alpha=0.3, which="both")
    return _save(fig, path)


def sweeps_figure(brazil: dict, path: Path) -> Path:
    """Calibration curves of paper 002 Fig. 8-9 (Eq. 18-19): sigma_t / B_n against B_n / B_t
    for each eps_th, and S / K_n against K_n / K_t for each B_n / B_t."""
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    t = brazil["tensile"]
    for e, row in zip(t["eps_th"], t["tensile_strength_over_b_n"], strict=True):
        a1.plot(t["ratios_b_n_over_b_t"], row, "o-", label=f"eps_th = {e:g}")
    a1.set_xscale("log")
    a1.set_xlabel("B_n / B_t")
    a1.set_ylabel("sigma_t / B_n")
    a1.legend(fontsize=7)
    a1.grid(True, alpha=0.3)
    s = brazil["slope"]
    for r, row in zip(s["ratios_b_n_over_b_t"], s["slope_S_over_k_n_per_m"], strict=True):
        a2.plot(s["ratios_k_n_over_k_t"], row, "s-", label=f"B_n / B_t = {r:g}")
    a2.set_xscale("log")
    a2.set_xlabel("K_n / K_t")
    a2.set_ylabel("S / K_n (1/m)")
    a2.legend(fontsize=7)
    a2.grid(True, alpha=0.3)
    for ax, ticks in ((a1, t["ratios_b_n_over_b_t"]), (a2, s["ratios_k_n_over_k_t"])):
        ax.set_xticks(ticks, [f"{v:g}" for v in ticks])  # the swept values, not 10^k labels
        ax.xaxis.set_minor_formatter(plt.NullFormatter())
    if "n_cells" in brazil:
        fig.suptitle(f"bonded Brazilian disc, {brazil['n_cells']} cells", fontsize=9)
    return _save(fig, path)
