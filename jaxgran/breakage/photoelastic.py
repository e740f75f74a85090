"""Force-chain maps from the stress field inside every grain (paper 000 Fig. 17).

The photoelastic quantity ``I = sigma_1 - sigma_2`` (Pa) is what a circular polariscope
shows as fringes; here it is evaluated from the boundary-element stress field of each
particle under its current contact forces (:func:`jaxgran.bem.stress_field`), on the
interior sample grid of the DSM (:func:`jaxgran.bem.sample_points`), so that a map of a
packing shows the chains inside the grains at the resolution of a photoelastic image, not
one colour per grain.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import bem
from ..io import world_vertices_np
from ..state import Params, SimState
from .dsm import contact_table

__all__ = ["force_chain_field", "plot_force_chain_field"]


def force_chain_field(
    state: SimState,
    params: Params,
    *,
    poisson_ratio: float,
    thickness: float,
    n_elements: int = 64,
    n_points: int = 48,
    max_contacts: int = 32,
    plane: str = "stress",
) -> dict[str, np.ndarray]:
    """``I = sigma_1 - sigma_2`` at interior points of every loaded particle.

    Args:
        state, params: the packing and its contact law (the contact forces are those of
            the current springs).
        poisson_ratio: nu of the grains (-).
        thickness: out-of-plane thickness (m): stresses are force per unit thickness / t.
        n_elements, n_points: boundary elements and sample points per particle (the
            elements are raised to twice the vertices of a core that has more, as the DSM
            raises them: fragments of an adaptive radius keep arc vertices).
        max_contacts: contact list per particle to start with; grown to the next power
            of two when a particle has more vertex contacts (its field would miss forces).
        plane: ``"stress"`` or ``"strain"``.

    Returns:
        ``points [N, 2]`` (m, world frame), ``intensity [N]`` (Pa), ``slot [N]`` (particle
        of each point), ``mean [P]`` (Pa, the mean of each particle's points; 0 for a
        particle with fewer than two contacts, which carries no field), ``n_loaded`` and
        ``skipped``: ``(slot, reason)`` of the loaded particles whose field the BEM refused
        (a map is a diagnostic: it reports them rather than fail a finished run).
    """
    p = state.particles
    dt = p.pos.dtype
    one = np.ones((), dtype=np.dtype(str(dt)))
    active = np.asarray(p.active)
    k = int(max_contacts)
    while True:
        tab = contact_table(state, params, one, 0.0 * one, one, thickness * one, k)
        need = int(np.asarray(tab["count"])[active].max(initial=0))
        if need <= k:
            break
        k = 1 << (need - 1).bit_length()  # the longest list, as the DSM grows it
    mask = np.asarray(tab["mask"])
    cps, cfs = np.asarray(tab["points"], float), np.asarray(tab["forces"], float)
    verts, n_verts = np.asarray(p.verts, float), np.asarray(p.n_verts)
    radius, pos, angle = np.asarray(p.radius, float), np.asarray(p.pos, float), np.asarray(p.angle)
    mean = np.zeros(active.shape[0])
    pts_all, i_all, slot_all, skipped = [], [], [], []
    for s in np.flatnonzero(active & (mask.sum(axis=1) >= 2)).tolist():
        v = verts[s, : n_verts[s]]
        m = mask[s]
        n_el = max(int(n_elements), bem.min_elements(len(v)))
        pts, _ = bem.sample_points(v, radius[s], n_el, n_points=n_points)
        if len(pts) == 0:  # a chip thinner than the band kept clear of the outline
            skipped.append((s, "no sample point inside (grain too small for n_elements)"))
            continue
        try:
            sig = bem.stress_field(
                v,
                cps[s][m],
                cfs[s][m],
                pts,
                poisson_ratio=poisson_ratio,
                plane=plane,
                n_elements=n_el,
                thickness=thickness,
                radius=radius[s],
            )
        except ValueError as err:  # e.g. a contact point off the outline (deep overlap)
            skipped.append((s, str(err)))
            continue
        intensity = 2.0 * np.hypot(0.5 * (sig[:, 0] - sig[:, 1]), sig[:, 2])
        pts_all.append(world_vertices_np(pts[None], None, pos[s][None], angle[s][None])[0])
        i_all.append(intensity)
        slot_all.append(np.full(len(pts), s))
        mean[s] = float(intensity.mean())
    return {
        "points": np.concatenate(pts_all) if pts_all else np.zeros((0, 2)),
        "intensity": np.concatenate(i_all) if i_all else np.zeros(0),
        "slot": np.concatenate(slot_all) if slot_all else np.zeros(0, int),
        "mean": mean,
        "n_loaded": len(pts_all),
        "skipped": skipped,
    }


def plot_force_chain_field(state: SimState, field: dict, path: str | Path, title: str = ""):
    """The map of :func:`force_chain_field`: each particle's points coloured by ``I`` (kPa,
    colour scale clipped at the 99th percentile), over the particle outlines. Returns the
    path written."""
    from .. import plot

    plt = plot.plt
    p = state.particles
    wv = world_vertices_np(
        np.asarray(p.verts), np.asarray(p.n_verts), np.asarray(p.pos), np.asarray(p.angle)
    )
    fig, ax = plt.subplots(figsize=(8, 6.5))
    plot.draw_particles(ax, wv, np.asarray(p.n_verts), np.asarray(p.radius), np.asarray(p.active))
    for coll in ax.collections:
        coll.set_facecolor("0.93")
        coll.set_edgecolor("0.6")
    if field["intensity"].size:
        kpa = field["intensity"] / 1e3
        top = float(np.percentile(kpa, 99))
        sc = ax.scatter(
            field["points"][:, 0] * 100,
            field["points"][:, 1] * 100,
            c=kpa,
            s=2.0,
            cmap="inferno",
            vmin=0.0,
            vmax=top if top > 0 else None,
            linewidths=0,
        )
        fig.colorbar(sc, ax=ax, label="I = sigma_1 - sigma_2 (kPa)")
    ax.set_title(title or "force chains: I = sigma_1 - sigma_2 inside each grain (BEM)")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return path
