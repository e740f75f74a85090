"""Figures of the interface-bond scenes (paper 003): loading curves, cracks coloured by
failure mode, Mohr circles with the fitted envelopes, stress along the loading axis, the
velocity field at breakage and force chains (PNG, Agg backend; lengths in mm, stresses in
MPa). Like :mod:`jaxgran.plot`, the only other module that imports matplotlib."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from .io import world_vertices_np  # noqa: E402
from .plot import draw_particles  # noqa: E402

_DPI = 150
MODE_COLOURS = {1: ("tension", "#e6b800"), 2: ("shear", "#d62728"), 3: ("compression", "#1f77b4")}


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_curve(curves: dict, xlabel: str, ylabel: str, path: Path, marks=None) -> Path:
    """Curves ``{label: (x, y)}`` on one axes; ``marks`` optional ``{label: (x, y)}`` points."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, (x, y) in curves.items():
        ax.plot(x, y, lw=1.2, label=label)
    for label, (x, y) in (marks or {}).items():
        ax.plot(x, y, "o", ms=5, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _particles(ax, state, colour_values=None, walls=True):
    p = state.particles
    vw = world_vertices_np(p.verts, p.n_verts, p.pos, p.angle)
    w = state.walls
    wd = {
        "point": np.asarray(w.point),
        "normal": np.asarray(w.normal),
        "extent": np.asarray(w.extent),
        "active": np.asarray(w.active),
    }
    draw_particles(
        ax,
        vw,
        np.asarray(p.n_verts),
        np.asarray(p.radius),
        np.asarray(p.active),
        walls=wd if walls else None,
        length_unit="mm",
    )


def plot_cracks(state, elements: dict, path: Path, stages=None) -> Path:
    """Failed elements coloured by mode (tension yellow, shear red, compression blue) over
    the specimen; ``stages`` ``[(title, time)]`` draws one panel per time (elements failed by
    then), at the final positions."""
    stages = stages or [("final", np.inf)]
    fig, axes = plt.subplots(1, len(stages), figsize=(4.5 * len(stages), 4.8), squeeze=False)
    for ax, (title, t) in zip(axes[0], stages, strict=True):
        _particles(ax, state)
        done = elements["time"] <= t
        drawn = False
        for code, (name, colour) in MODE_COLOURS.items():
            sel = done & (elements["mode"] == code)
            if sel.any():
                x = elements["pos"][sel] * 1e3
                ax.plot(x[:, 0], x[:, 1], "s", ms=3, color=colour, label=f"{name} ({sel.sum()})")
                drawn = True
        ax.set_title(title, fontsize=9)
        if drawn:
            ax.legend(fontsize=7, loc="upper right")
        else:
            ax.text(0.5, 1.01, "no element failed", transform=ax.transAxes, ha="center",
                    va="bottom", fontsize=7)  # fmt: skip
    return _save(fig, path)


def plot_mohr(sigma_1, sigma_3, fits: dict, path: Path, title: str = "", peaked=None) -> Path:
    """Peak Mohr circles (compression positive, MPa) with the fitted linear and parabolic
    envelopes (:func:`jaxgran.scenes.interface.mohr_envelope_fits`); circles whose
    ``peaked`` is False (still hardening at the strain limit: no peak, a lower bound) are
    drawn grey and dashed."""
    s1, s3 = np.asarray(sigma_1, float) / 1e6, np.asarray(sigma_3, float) / 1e6
    peaked = np.ones(s1.size, bool) if peaked is None else np.asarray(peaked, bool)
    fig, ax = plt.subplots(figsize=(7, 4))
    a = np.linspace(0, np.pi, 100)
    for x1, x3, pk in zip(s1, s3, peaked, strict=True):
        c, r = 0.5 * (x1 + x3), 0.5 * abs(x1 - x3)
        style = {"color": "k", "ls": "-"} if pk else {"color": "0.5", "ls": "--"}
        ax.plot(c + r * np.cos(a), r * np.sin(a), lw=0.8, **style)
    lo = min(float(s3.min()), -0.1 * float(s1.max()))
    s = np.linspace(lo, float(s1.max()), 200)
    if "linear_cohesion_Pa" in fits:
        c = fits["linear_cohesion_Pa"] / 1e6
        t = np.tan(np.radians(fits["linear_friction_angle_deg"]))
        ax.plot(s, c + s * t, "b--", label=f"linear, R2 = {fits['linear_r2']:.4f}")
    if "parabola_cohesion_Pa" in fits:
        c = fits["parabola_cohesion_Pa"] / 1e6
        sb = fits["parabola_tensile_strength_Pa"] / 1e6
        ok = s > -sb
        ax.plot(
            s[ok],
            c * np.sqrt(1 + s[ok] / sb),
            "r-",
            label=f"parabola, R2 = {fits['parabola_r2']:.4f}",
        )
    ax.set_xlabel("normal stress (MPa, compression positive)")
    ax.set_ylabel("shear stress (MPa)")
    ax.set_aspect("equal")
    ax.set_ylim(bottom=0)
    ax.set_title(title, fontsize=9)
    if ax.get_legend_handles_labels()[0]:  # no fit (fewer than 3 circles): no legend
        ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_element_failures(failures: dict, material: dict, path: Path, title: str = "") -> Path:
    """Each failed element on the (compression, |tau|) plane at its last frame before failure
    (:func:`jaxgran.scenes.interface.element_failures`; ``failures`` maps a label, e.g. the
    confinement, to one such dict), shear failures as dots and tension failures as crosses,
    with the bonded element's shear strength (``material``: ``cohesion``,
    ``tensile_strength``, ``tan_friction_angle`` in Pa / -, ``envelope`` code) and the
    friction line ``mu_b |sigma|`` of a failed one (``residual_friction``); stresses in MPa,
    compression positive."""
    from .interface import ENVELOPE_PARABOLIC, MODE_SHEAR, friction_crossover, shear_strength

    fig, ax = plt.subplots(figsize=(7, 4.5))
    top = 0.0
    for k, (label, f) in enumerate(failures.items()):
        comp, tau = -np.asarray(f["sigma"]) / 1e6, np.abs(np.asarray(f["tau"])) / 1e6
        shear = np.asarray(f["mode"]) == MODE_SHEAR
        colour = f"C{k}"
        ax.plot(comp[shear], tau[shear], ".", ms=3, color=colour, alpha=0.6, label=label)
        ax.plot(comp[~shear], tau[~shear], "x", ms=3, color=colour, alpha=0.6)
        if comp.size:
            top = max(top, float(np.percentile(comp, 99)))
    c, sb = material["cohesion"], material["tensile_strength"]
    mu = material["residual_friction"]
    top = max(top, 2.0 * c / 1e6)
    s = np.linspace(-sb, top * 1e6, 400)  # compression positive
    strength = np.asarray(
        shear_strength(-s, c, sb, material["tan_friction_angle"], material["envelope"])
    )
    ax.plot(s / 1e6, strength / 1e6, "k-", lw=1.2, label="bonded strength tau_c")
    ax.plot(s / 1e6, mu * np.maximum(s, 0.0) / 1e6, "k--", lw=1.0, label=f"friction {mu:g} |sigma|")
    if material["envelope"] == ENVELOPE_PARABOLIC:
        s_star = friction_crossover(c, sb, mu) / 1e6
        if s_star <= top:
            ax.axvline(s_star, color="0.5", lw=0.8, ls=":")
            ax.annotate(
                f"crossover {s_star:.0f} MPa",
                (s_star, 0),
                fontsize=7,
                rotation=90,
                va="bottom",
                ha="right",
            )
    ax.set_xlim(-1.5 * sb / 1e6, top)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("element normal stress (MPa, compression positive)")
    ax.set_ylabel("element shear stress |tau| (MPa)")
    ax.set_title(
        title or "failed elements at the last frame before failure (x: tension)", fontsize=9
    )
    ax.legend(fontsize=7, markerscale=3)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_axis_stress(y, measured, closed_form_y, closed_form, path: Path, title: str = "") -> Path:
    """Horizontal stress along the loading axis (MPa, tension positive) from the measurement
    circles against the closed-form disc solution; ``y`` in m."""
    fig, ax = plt.subplots(figsize=(4.5, 5))
    ax.plot(
        np.asarray(closed_form) / 1e6, np.asarray(closed_form_y) * 1e3, "k-", label="closed form"
    )
    ax.plot(np.asarray(measured) / 1e6, np.asarray(y) * 1e3, "o", label="measurement circles")
    ax.axvline(0, color="0.6", lw=0.8)
    ax.set_xlabel("sigma_xx (MPa, tension positive)")
    ax.set_ylabel("y (mm)")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_velocity(state, pos, vel, path: Path, title: str = "") -> Path:
    """Particle velocities (arrows) at the moment of breakage."""
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    _particles(ax, state, walls=False)
    pos, vel = np.asarray(pos) * 1e3, np.asarray(vel)
    ax.quiver(pos[:, 0], pos[:, 1], vel[:, 0], vel[:, 1], color="#1f3b73", width=0.004)
    ax.set_title(title, fontsize=9)
    return _save(fig, path)


def plot_force_chains(state, x_i, x_j, force, path: Path, title: str = "") -> Path:
    """Interface normal forces as segments between particle centres: compression blue and
    tension red, line width proportional to |F| (scaled separately)."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    force = np.asarray(force, float)
    seg = np.stack([np.asarray(x_i), np.asarray(x_j)], axis=1) * 1e3
    for ax, sel, colour, name in (
        (axes[0], force < 0, "#1f4fbf", "compression"),
        (axes[1], force > 0, "#d62728", "tension"),
    ):
        _particles(ax, state, walls=False)
        f = np.abs(force[sel])
        if f.size:
            lw = 0.3 + 4.0 * f / f.max()
            ax.add_collection(LineCollection(seg[sel], colors=colour, linewidths=lw))
        ax.set_title(f"{name} chains {title}", fontsize=9)
    return _save(fig, path)
