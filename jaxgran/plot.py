"""Figures of a run: packings, frames and time series (PNG, Agg backend).

This is the only module that imports matplotlib (DESIGN §2). It reads the plain dicts that
:func:`jaxgran.io.read_run` returns, so a run can be plotted long after it was simulated.
Lengths are drawn in ``length_unit`` (cm by default); forces in N, energies in J, times in s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402

from .io import particle_outlines  # noqa: E402
from .io import world_vertices_np as world_vertices_np  # noqa: E402

_SCALE = {"m": 1.0, "cm": 100.0, "mm": 1000.0}
_DPI = 150


def _scale(length_unit: str) -> float:
    if length_unit not in _SCALE:
        raise ValueError(f"length_unit must be one of {sorted(_SCALE)}, got {length_unit!r}")
    return _SCALE[length_unit]


def _clip_line(point, tangent, s_range, box) -> tuple[float, float] | None:
    """Part ``[s0, s1]`` of the line ``point + s * tangent`` inside ``box`` and ``s_range``
    (Liang-Barsky); None when the line misses the box."""
    s0, s1 = float(s_range[0]), float(s_range[1])
    (x0, y0), (x1, y1) = box
    for p, d, lo, hi in ((point[0], tangent[0], x0, x1), (point[1], tangent[1], y0, y1)):
        if abs(d) < 1e-15:
            if p < lo or p > hi:
                return None
            continue
        a, b = (lo - p) / d, (hi - p) / d
        s0, s1 = max(s0, min(a, b)), min(s1, max(a, b))
    return (s0, s1) if s0 <= s1 else None


def _wall_box(outlines, walls, margin: float):
    pts = [np.concatenate(outlines)] if outlines else []
    if walls is not None:
        act = np.asarray(walls.get("active", np.ones(len(walls["point"]), bool)), bool)
        point = np.asarray(walls["point"], float)[act]
        pts.append(point)
        normal = np.asarray(walls["normal"], float)[act]
        ext = np.asarray(walls.get("extent", np.full((len(point), 2), np.inf)), float)[act]
        tang = np.stack([-normal[:, 1], normal[:, 0]], axis=-1)
        for end in (0, 1):
            ok = np.isfinite(ext[:, end])
            pts.append(point[ok] + ext[ok, end : end + 1] * tang[ok])
    if not pts or sum(len(p) for p in pts) == 0:
        return np.array([[-1.0, -1.0], [1.0, 1.0]])
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    pad = margin * max(float(np.max(hi - lo)), 1e-12)
    return np.array([lo - pad, hi + pad])


def draw_particles(
    ax,
    verts_world,
    n_verts,
    radius,
    active,
    values=None,
    cmap: str = "viridis",
    label: str | None = None,
    walls: Mapping[str, Any] | None = None,
    *,
    norm=None,
    colorbar: bool = True,
    length_unit: str = "cm",
    n_arc: int = 24,
    margin: float = 0.05,
):
    """Draw spheropolygons as filled rounded outlines.

    Args:
        ax: matplotlib Axes.
        verts_world: core vertices in the world frame ``[P, V, 2]`` (m).
        n_verts, radius (m), active: ``[P]``.
        values: optional ``[P]`` colour values (e.g. |F| in N, material id); a colorbar
            labelled ``label`` is added when given.
        walls: optional dict with ``point [W, 2]`` (m), ``normal [W, 2]``, ``extent [W, 2]``
            (m, may be infinite) and ``active [W]``; walls are drawn as thick lines, infinite
            ones clipped to the box around particles and wall points plus ``margin``.
        norm: a shared :class:`matplotlib.colors.Normalize` (multi-panel figures).
        length_unit: ``"m"``, ``"cm"`` or ``"mm"`` for the axes.

    Returns:
        the PolyCollection of the particles.
    """
    sc = _scale(length_unit)
    outlines, idx = particle_outlines(verts_world, n_verts, radius, active, n_arc)
    box = _wall_box(outlines, walls, margin)
    pc = PolyCollection([o * sc for o in outlines], linewidths=0.4)
    if values is None:
        pc.set_facecolor("#d9c6a5")
        pc.set_edgecolor("#5a4a32")
    else:
        pc.set_array(np.asarray(values, dtype=float)[idx])
        pc.set_cmap(cmap)
        pc.set_edgecolor("k")
        if norm is not None:
            pc.set_norm(norm)
    ax.add_collection(pc)
    if walls is not None:
        act = np.asarray(walls.get("active", np.ones(len(walls["point"]), bool)), bool)
        ext_all = walls.get("extent", np.full((len(act), 2), np.inf))
        for w in np.flatnonzero(act):
            pt = np.asarray(walls["point"][w], float)
            n = np.asarray(walls["normal"][w], float)
            t = np.array([-n[1], n[0]])
            seg = _clip_line(pt, t, np.asarray(ext_all[w], float), box)
            if seg is None:
                continue
            xy = np.stack([pt + seg[0] * t, pt + seg[1] * t]) * sc
            ax.plot(xy[:, 0], xy[:, 1], color="0.15", linewidth=3, solid_capstyle="butt")
    ax.set_xlim(box[0, 0] * sc, box[1, 0] * sc)
    ax.set_ylim(box[0, 1] * sc, box[1, 1] * sc)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({length_unit})")
    ax.set_ylabel(f"y ({length_unit})")
    if values is not None and colorbar:
        ax.figure.colorbar(pc, ax=ax, label=label or "")
    return pc


def _frame_world(frames: Mapping[str, np.ndarray], k: int) -> np.ndarray:
    return world_vertices_np(
        frames["verts"][k], frames["n_verts"][k], frames["pos"][k], frames["angle"][k]
    )


def _frame_walls(run: Mapping[str, Any], k: int) -> dict[str, np.ndarray] | None:
    walls = run.get("final", {}).get("walls")
    if not walls:
        return None
    out = {key: np.asarray(walls[key]) for key in ("normal", "extent", "active") if key in walls}
    frames = run.get("frames", {})
    out["point"] = np.asarray(frames["wall_point"][k] if "wall_point" in frames else walls["point"])
    return out


def _force_values(frames: Mapping[str, np.ndarray], k: int) -> tuple[np.ndarray, str]:
    # A per-particle contact-force measure, when frames record one, says more than the net
    # force (which vanishes in a packing at rest).
    if "contact_force" in frames:
        f = np.asarray(frames["contact_force"][k])
        val = np.linalg.norm(f, axis=-1) if f.ndim == 2 else f
        return val, "contact force |F| (N)"
    return np.linalg.norm(frames["force"][k], axis=-1), "net force |F| (N)"


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=_DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def _out_dir(out_dir) -> Path:
    d = Path(out_dir)
    if d.exists() and not d.is_dir():
        raise NotADirectoryError(f"{d} is a file; give a folder for the figures")
    d.mkdir(parents=True, exist_ok=True)
    return d


def plot_series(
    x, ys: Mapping[str, Any], xlabel: str, ylabel: str, path, logy: bool = False
) -> Path:
    """Curves ``ys[name]`` against ``x`` in one axes (legend when more than one); with
    ``logy`` non-positive values are left out. Returns the PNG path."""
    p = Path(path)
    _out_dir(p.parent)
    fig, ax = plt.subplots(figsize=(6, 4))
    x = np.asarray(x, dtype=float)
    for name, y in ys.items():
        y = np.asarray(y, dtype=float)
        if logy:
            y = np.where(y > 0, y, np.nan)
        ax.plot(x, y, label=name)
    if logy and any(np.any(np.asarray(y, float) > 0) for y in ys.values()):
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if len(ys) > 1:
        ax.legend()
    ax.grid(True, alpha=0.3)
    return _save(fig, p)


def plot_frames(
    run: Mapping[str, Any],
    out_dir,
    indices: Sequence[int],
    name: str = "frames",
    *,
    length_unit: str = "cm",
) -> Path:
    """Frames ``indices`` (negative counts from the end) side by side, coloured by a shared
    force scale; writes ``<out_dir>/<name>.png`` and returns its path."""
    frames = run.get("frames") or {}
    if not frames:
        raise ValueError("the run has no frames to plot")
    n_frames = frames["pos"].shape[0]
    idx = [int(i) % n_frames for i in indices]
    if not idx:
        raise ValueError("give at least one frame index")
    vals = [_force_values(frames, k) for k in idx]
    vmax = max(
        float(np.max(v[np.asarray(frames["active"][k], bool)], initial=0.0))
        for (v, _), k in zip(vals, idx, strict=True)
    )
    norm = Normalize(vmin=0.0, vmax=vmax if vmax > 0 else 1.0)
    ncol = min(len(idx), 3)
    nrow = -(-len(idx) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.5 * ncol, 4.2 * nrow), squeeze=False)
    pc = None
    for ax, k, (v, _) in zip(axes.flat, idx, vals, strict=False):
        pc = draw_particles(
            ax,
            _frame_world(frames, k),
            frames["n_verts"][k],
            frames["radius"][k],
            frames["active"][k],
            values=v,
            walls=_frame_walls(run, k),
            norm=norm,
            colorbar=False,
            length_unit=length_unit,
        )
        t = float(frames["time"][k]) if "time" in frames else float(k)
        ax.set_title(f"frame {k}, t = {t:.4g} s")
    for ax in list(axes.flat)[len(idx) :]:
        ax.set_visible(False)
    fig.colorbar(pc, ax=axes.ravel().tolist(), label=vals[0][1])
    return _save(fig, _out_dir(out_dir) / f"{name}.png")


def plot_run(run: Mapping[str, Any], out_dir, *, length_unit: str = "cm") -> list[Path]:
    """The figures a researcher looks at first, from ``read_run(path)``.

    Writes ``packing.png`` (last frame coloured by force magnitude per particle),
    ``kinetic_energy.png`` (KE vs time, log scale) and, when walls were recorded,
    ``wall_forces.png`` (normal force of the particles on each active wall, compression
    positive). Returns the paths written.
    """
    out = _out_dir(out_dir)
    paths: list[Path] = []
    frames = run.get("frames") or {}
    if frames:
        k = frames["pos"].shape[0] - 1
        fig, ax = plt.subplots(figsize=(6, 5))
        values, label = _force_values(frames, k)
        draw_particles(
            ax,
            _frame_world(frames, k),
            frames["n_verts"][k],
            frames["radius"][k],
            frames["active"][k],
            values=values,
            label=label,
            walls=_frame_walls(run, k),
            length_unit=length_unit,
        )
        t = float(frames["time"][k]) if "time" in frames else float(k)
        scene = run.get("metadata", {}).get("scene", "")
        ax.set_title(f"{scene + ': ' if scene else ''}t = {t:.4g} s")
        paths.append(_save(fig, out / "packing.png"))
    series = run.get("series") or {}
    if "kinetic_energy" in series and "time" in series:
        paths.append(
            plot_series(
                series["time"],
                {"kinetic energy": series["kinetic_energy"]},
                "time (s)",
                "kinetic energy (J)",
                out / "kinetic_energy.png",
                logy=True,
            )
        )
    if "wall_force" in series and "time" in series:
        force = np.asarray(series["wall_force"], dtype=float)  # [R, W, 2]
        walls = run.get("final", {}).get("walls") or {}
        n_walls = force.shape[1]
        active = np.asarray(walls.get("active", np.ones(n_walls, bool)), bool)
        if "normal" in walls:
            normal = np.asarray(walls["normal"], dtype=float)
            # the wall normal points into the domain, so pushing grains give -F.n > 0
            fn = -np.einsum("rwk,wk->rw", force, normal)
            ylabel = "wall normal force (N, compression > 0)"
        else:
            fn = np.linalg.norm(force, axis=-1)
            ylabel = "wall force |F| (N)"
        ys = {f"wall {w}": fn[:, w] for w in np.flatnonzero(active)}
        if ys:
            paths.append(
                plot_series(series["time"], ys, "time (s)", ylabel, out / "wall_forces.png")
            )
    return paths
