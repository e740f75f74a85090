"""Replace a broken particle by its fragments (paper 000 §II.D-E, steps vi-viii).

Host-side numpy between segments: fragment and vertex counts are data dependent. The
functions here write fragments into the padded :class:`~jaxgran.state.Particles` arrays and
return the new state; the caller then runs :func:`jaxgran.simulate.prepare` so that the pair
list and the forces match the new particles.

Geometry of a fragment (the erosion rule).
    The parent is the spheropolygon ``S = C + D(r)`` (core ``C``, disc of radius ``r``). The
    fracture planes cut its *dilated outline* into pieces ``S_f = S ∩ H_f`` (``H_f`` the
    intersection of half-planes on the fragment's side of every plane). Each piece is eroded
    by ``r + delta`` and swept again by ``r``: the fragment is
    ``C_f + D(r)`` with ``C_f = S_f ⊖ D(r + delta)``, where ``delta`` is the parent's largest
    current overlap with any neighbour or wall (plus a tiny ``clearance``). Since a convex
    set closed under erosion-dilation gives back itself, ``C_f = (C ⊖ D(delta)) ∩ (H_f ⊖
    D(r + delta))``: the parent's core shrunk by ``delta`` and cut by the planes shifted
    ``r + delta`` towards the fragment. Hence

    * the fragment lies inside ``S ⊖ D(delta)``: a neighbour that penetrated the parent by
      at most ``delta`` no longer touches it, so no fragment starts with an overlap (paper
      000 Fig. 6: the contact force between A and B vanishes);
    * siblings are ``2 delta`` apart across each plane (they touch when ``delta = 0``);
    * with ``delta = 0`` only the new corners made by the planes are rounded: a straight cut
      loses ``r^2 (tan(a/2) - a/2)`` per new corner of exterior angle ``a``.

    That is ``erosion="uniform"``, the parent's largest overlap taken off all round. The
    default ``erosion="local"`` takes material off only where a body overlaps a piece: for
    every unit ``u`` the line ``u . x = h_B(u) + r_B`` (``h_B`` the support function of
    neighbour B's core) has all of B on one side, so clipping the piece to the other side
    before the erosion by ``r + clearance`` leaves no overlap with B whatever ``u``; ``u`` is
    chosen per piece to keep the most of it (:func:`separating_halfplane`). Where B presses
    flat on a face the line runs parallel to it and a strip of the overlap's depth along the
    contact goes; where a fracture plane runs through the contact point (DSM planes join
    contacts), each piece has a corner there, and a line along B's flank cuts off a small
    triangle instead of a strip the length of the face. An overlapping wall clips its strip.
    ``erosion="local-axis"`` is the earlier rule (one line per neighbour, along its
    direction of least penetration into the whole parent, for every piece), kept for
    comparison (``docs/stability.md``).

    The rounding is not small where a plane runs nearly parallel to a face (DSM planes
    join contacts, and contacts sit at corners): the sliver between them has a tip of angle
    ``a`` that the erosion by ``r`` moves back by ``r / sin(a / 2)``, and the fragment loses
    about ``r^2 (1 / tan(a / 2) - (pi - a) / 2)`` there (4.3 mm^2, 6 % of the sliver cut
    from a 20 mm square at ``a = 20 deg`` with ``r = 1 mm``). With ``min_radius`` each
    fragment's sphero-radius adapts instead: the largest radius in ``[min_radius, r]``
    whose rounding keeps 99.9 % of its piece (:meth:`_PieceCut.radius_for`). The fragment
    still lies inside its piece, so nothing above changes but the radius; slivers keep
    their tips as sharper spheropolygons (which then break more readily:
    ``docs/stability.md``).

    To make the erosion of a *polygonal* outline exact, :func:`dilated_outline` returns the
    polygon *circumscribed* to ``S`` (tangent to it on every flat edge and at ``n_arc`` points
    per turn on the corner arcs): eroding it by ``r`` gives back the core ``C`` exactly, so
    fragments have at most ``n + k`` vertices (``n`` parent vertices, ``k`` planes).

Mass bookkeeping (per event, areal density ``rho`` of the parent, ``rho = m / A``):
    ``parent_mass = sum(fragment_masses) + fines_mass + eroded_mass``; ``fines_mass`` is the
    mass of the pieces dropped because their fragment vanished under erosion or fell below
    ``min_area`` (their area measured on the circumscribed outline, which overestimates the
    true piece by less than ``3e-3 r^2``); ``eroded_mass`` is the strip removed by the
    erosion; ``mass_lost = parent_mass - sum(fragment_masses)`` (fines included). Pieces
    below ``min_area`` are merged into a neighbouring piece by default
    (``small_pieces="merge"``, :func:`merge_small_pieces`), so fines occur only where a
    piece has no neighbour to join. With ``conserve_mass`` each fragment keeps the mass of
    its uneroded piece (density raised by the eroded fraction) and ``eroded_mass`` is 0 up
    to round-off; ``area_lost`` (m^2) records the geometric loss in every mode.
    ``eroded_mass = caps_mass + rounding_mass``: ``caps_mass`` is what the erosion clear of
    the neighbours and walls took (the loss paper 000 Fig. 6 marks; ``caps_area`` in m^2:
    the area the kept pieces would have kept with nothing in the way, eroded by ``r`` and
    the clearance only, minus the fragments' area; 0 kg with ``conserve_mass``) and
    ``rounding_mass`` the rest, the rounding of the new corners that any fragment of
    sphero-radius ``r`` pays (with the outline's ``3e-3 r^2`` excess).

Kinematics: a fragment takes the parent's rigid-body velocity field at its centroid,
``v_f = v + omega x (c_f - x)``, and ``omega_f = omega``. Linear and angular momentum are
then conserved exactly up to the mass removed (no rescaling is done):
``|sum m_f v_f - m v| <= mass_lost (|v| + |omega| R)``, ``R`` the parent's bounding radius.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax import Array

from .. import geometry as geo
from ..contact import closest_features, world_vertices
from ..state import Contacts, Particles, SimState, empty_contacts, replace
from .criteria import breakage_type

log = logging.getLogger(__name__)

__all__ = [
    "Replacement",
    "dilated_outline",
    "fragment_cores",
    "merge_small_pieces",
    "contact_halfplanes",
    "overlapping_bodies",
    "separating_halfplane",
    "max_overlap",
    "fit_vertex_capacity",
    "replace_particle",
    "replace_particles",
]

# Erosion of the fragments (replace_particles): local clipping, uniform, or none.
EROSION_MODES = ("local", "local-axis", "uniform", "none")
# Pieces below the smallest fragment: merged into a neighbour, or dropped as fines.
SMALL_PIECE_MODES = ("merge", "fines")

# Clearance added to the erosion, relative to the parent's bounding radius: keeps the first
# contact after creation at a (tiny) positive gap despite round-off.
_CLEARANCE_REL = 1e-9
# Vertices closer than this (relative to the fragment size) to a neighbour, or within this of
# the chord of their neighbours, are dropped (removing a vertex of a convex polygon only
# shrinks it, so this never creates an overlap).
_CLEAN_REL = 1e-9
# Pieces below this x min_area are dust (merge_small_pieces): merged only to fill a notch.
_DUST_REL = 1e-3
# Local erosion (separating_halfplane): evenly spaced directions searched per piece and
# neighbour, and golden-section steps refining the best of them.
_SEARCH_DIRECTIONS = 90
_SEARCH_REFINE = 24
# Default capacity growth factor when the free slots run out.
_GROWTH = 2.0
# Adaptive fragment radius (``min_radius``): area of a piece the rounding may take, relative
# to the piece, and bisection steps on the radius.
_ROUNDING_TOL = 1e-3
_RADIUS_STEPS = 24

# Values of a fresh inactive slot, per Particles field (others are zero).
_PAD = {"mass": 1.0, "inertia": 1.0, "uid": -1, "parent_uid": -1, "active": False}


class Replacement(NamedTuple):
    """One particle to replace: slot ``index``, its outline ``pieces`` (world frame, m) as
    cut by the fracture ``planes`` (``[k, 2, 2]`` m, for the event log; optional)."""

    index: int
    pieces: list
    planes: np.ndarray | None = None


# ---------------------------------------------------------------------------- geometry


def dilated_outline(core: npt.ArrayLike, radius: float, n_arc: int = 64) -> np.ndarray:
    """Polygon circumscribed to the spheropolygon ``core + disc(radius)``, CCW ``[m, 2]`` (m).

    Every flat edge of the spheropolygon is an edge of the polygon; each corner arc of
    exterior angle ``a`` is replaced by ``s = ceil(n_arc a / 2 pi)`` tangent segments (tangent
    at the middle of ``s`` equal sub-arcs), so the polygon contains the shape and eroding it
    by ``radius`` gives back ``core`` exactly. Its area exceeds the shape's by about
    ``pi^3 r^2 / (3 n_arc^2)`` (``3e-3 r^2`` for ``n_arc = 64``).

    Args:
        core: convex core ``[n, 2]`` (m), n >= 3 (either orientation), or 1-2 vertices.
        radius: sweeping radius r > 0 (m); 0 returns the validated core.
        n_arc: tangent segments per full turn (>= 4).
    """
    n_arc = int(n_arc)
    if n_arc < 4:
        raise ValueError(f"n_arc must be >= 4 tangent segments per turn, got {n_arc}")
    radius = float(radius)
    if not (math.isfinite(radius) and radius >= 0.0):
        raise ValueError(f"radius must be finite and >= 0 m, got {radius}")
    c = np.asarray(core, dtype=np.float64).reshape(-1, 2)
    if len(c) >= 3:
        c = geo.validate_polygon(c, name="core")
    if radius == 0.0:
        if len(c) < 3:
            raise ValueError("a core of 1-2 vertices needs radius > 0 to have an outline")
        return c
    if len(c) == 1:
        a = 2.0 * math.pi * (np.arange(n_arc) + 0.5) / n_arc
        rho = radius / math.cos(math.pi / n_arc)
        return c[0] + rho * np.stack([np.cos(a), np.sin(a)], axis=1)
    e = np.roll(c, -1, axis=0) - c
    normal = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.linalg.norm(e, axis=1)[:, None]
    n_prev = np.roll(normal, 1, axis=0)
    if len(c) == 2:
        theta = np.full(2, math.pi)
    else:
        cross = n_prev[:, 0] * normal[:, 1] - n_prev[:, 1] * normal[:, 0]
        theta = np.clip(np.arctan2(cross, np.einsum("ij,ij->i", n_prev, normal)), 0.0, math.pi)
    phi0 = np.arctan2(n_prev[:, 1], n_prev[:, 0])
    out = []
    for k in range(len(c)):
        s = math.ceil(n_arc * theta[k] / (2.0 * math.pi) - 1e-9)
        if s <= 0:  # collinear corner: the two edge lines meet at the offset point
            out.append((c[k] + radius * n_prev[k])[None, :])
            continue
        # tangent lines at phi0, phi0 + (j + 1/2) a / s (j < s), phi0 + a; consecutive lines
        # at angles p < q meet at c + r / cos((q - p) / 2) * u((p + q) / 2)
        lines = np.concatenate([[0.0], (np.arange(s) + 0.5) / s, [1.0]]) * theta[k] + phi0[k]
        mid = 0.5 * (lines[1:] + lines[:-1])
        half = 0.5 * (lines[1:] - lines[:-1])
        rho = radius / np.cos(half)
        out.append(c[k] + rho[:, None] * np.stack([np.cos(mid), np.sin(mid)], axis=1))
    return np.concatenate(out, axis=0)


def _clean_convex(p: np.ndarray) -> np.ndarray:
    """Drop near-duplicate and near-collinear vertices of a convex CCW polygon (only
    shrinks it)."""
    size = geo.circumradius(p) if len(p) else 0.0
    tol = _CLEAN_REL * max(size, np.finfo(float).tiny)
    changed = True
    while changed and len(p) > 3:
        changed = False
        prev, nxt = np.roll(p, 1, axis=0), np.roll(p, -1, axis=0)
        chord = nxt - prev
        rel = p - prev
        clen = np.linalg.norm(chord, axis=1)
        height = (rel[:, 0] * chord[:, 1] - rel[:, 1] * chord[:, 0]) / np.maximum(clen, 1e-300)
        short = np.linalg.norm(nxt - p, axis=1) <= tol
        bad = (np.abs(height) <= tol) | short
        if bad.any():
            p = np.delete(p, int(np.argmax(bad)), axis=0)
            changed = True
    return p


def fragment_cores(
    pieces: Sequence[npt.ArrayLike], radius: float, erosion: float
) -> list[np.ndarray | None]:
    """Erode outline pieces by ``radius + erosion`` into fragment cores (world frame, m).

    Args:
        pieces: convex pieces of the parent's dilated outline ``[m_i, 2]`` (m), best cut from
            :func:`dilated_outline` (see the module docstring).
        radius: sphero-radius r of the fragments (m).
        erosion: extra erosion ``delta`` >= 0 (m): the parent's largest overlap.

    Returns:
        One core ``[n_i, 2]`` per piece, or ``None`` where the piece vanishes.
    """
    out: list[np.ndarray | None] = []
    d = float(radius) + float(erosion)
    for piece in pieces:
        try:
            core = geo.offset_polygon(piece, d)
        except ValueError:  # erased by the erosion: fines
            out.append(None)
            continue
        core = _clean_convex(core)
        out.append(core if len(core) >= 3 else None)
    return out


def merge_small_pieces(
    pieces: Sequence[npt.ArrayLike], kept_area, min_area: float
) -> tuple[list[np.ndarray], int]:
    """Merge the pieces that would fall below ``min_area`` into a neighbour (m, m^2).

    The fracture planes cut the outline into the cells of a line arrangement. Two cells that
    share an edge differ in the side of one line only, so their union is the convex region
    with the same sides of all other lines: merging them is exact (their convex hull, whose
    area is checked against the sum). The smallest piece below ``min_area`` (its area as
    ``kept_area(piece)`` measures it after clipping and erosion, 0 where it vanishes) joins the
    neighbour with which it shares the longest edge (after earlier merges a union may not be
    convex: the next neighbour is tried); this repeats until every piece is large enough, or
    a small piece has no neighbour it merges with (it stays, to become fines), or one piece
    is left (the planes cut nothing above the resolution). Dust, pieces under ``1e-3 x
    min_area`` (slivers where three lines nearly meet), is not merged on its own: joined to
    one neighbour it would leave a hairline notch that keeps the next small piece from
    merging anywhere. It joins a merge whose convex hull covers it (the two pieces and the
    dust they cover add up to the hull's area; the part of a dust piece outside the hull is
    lost, under ``1e-3 x min_area``); dust left over becomes fines (a negligible mass).

    Args:
        pieces: convex CCW pieces ``[m_i, 2]`` (m) of one parent's outline.
        kept_area: callable, piece -> area (m^2) of the fragment it would become.
        min_area: smallest fragment area kept (m^2).

    Returns:
        ``(pieces, n_merged)``.
    """
    from scipy.spatial import ConvexHull

    out = [np.asarray(q, dtype=np.float64).reshape(-1, 2) for q in pieces]
    if min_area <= 0.0 or len(out) < 2:
        return out, 0
    areas = [kept_area(q) if len(q) >= 3 else 0.0 for q in out]
    # dust: slivers where lines nearly meet at one point; merged alone, they would leave a
    # hairline notch that makes later unions non-convex (see the docstring)
    dust = [abs(geo.polygon_area(q)) < _DUST_REL * min_area if len(q) >= 3 else True for q in out]
    stuck: set[int] = set()
    n_merged = 0
    while len(out) > 1:
        small = [i for i, a in enumerate(areas) if a < min_area and i not in stuck and not dust[i]]
        if not small:
            break
        i = min(small, key=lambda m: areas[m])
        nbrs = sorted(
            (
                (float(np.linalg.norm(q - p)), b if a == i else a)
                for a, b, p, q in geo.shared_edges(out)
                if i in (a, b) and not dust[b if a == i else a]
            ),
            reverse=True,
        )
        hull, absorbed = None, []
        for _, best in nbrs:
            pts = np.concatenate([out[i], out[best]])
            cand = pts[ConvexHull(pts).vertices]
            a_hull = abs(geo.polygon_area(cand))
            total = abs(geo.polygon_area(out[i])) + abs(geo.polygon_area(out[best]))
            # dust the hull covers fills the notch between the two: if the hull's excess
            # over the two pieces is exactly the dust it covers, the dust joins the merge
            covered = {d: _covered_area(out[d], cand) for d in range(len(out)) if dust[d]}
            covered = {d: a for d, a in covered.items() if a > 0.0}
            filled = total + sum(covered.values())
            if abs(a_hull - total) <= 1e-9 * total:
                hull, absorbed = cand, []  # the union is convex
                break
            if covered and abs(a_hull - filled) <= 1e-9 * filled:
                hull, absorbed = cand, sorted(covered)  # convex with the dust between them
                break
        if hull is None:  # no neighbour whose union with it is convex: it stays
            stuck.add(i)
            continue
        merged = _clean_convex(hull)
        keep = [m for m in range(len(out)) if m not in (i, best, *absorbed)]
        stuck = set()  # the neighbours changed: try the stuck pieces again
        out = [out[m] for m in keep] + [merged]
        areas = [areas[m] for m in keep] + [kept_area(merged)]
        dust = [dust[m] for m in keep] + [False]
        n_merged += 1 + len(absorbed)
    return out, n_merged


def _covered_area(piece: np.ndarray, hull: np.ndarray) -> float:
    """Area (m^2) of ``piece`` inside the convex ``hull``."""
    try:
        cut = geo.clip_convex(piece, hull)
    except ValueError:  # degenerate sliver
        return 0.0
    return abs(geo.polygon_area(cut)) if len(cut) >= 3 else 0.0


@eqx.filter_jit
def max_overlap(state: SimState) -> Array:
    """Largest overlap (m) of each particle with any neighbour in the pair list or any wall
    ``[P]``; 0 for particles without contact. Vertex-to-core distances in both directions,
    as the contact law measures them (``r_i + r_j - gap``)."""
    p = state.particles
    n_p = p.pos.shape[0]
    pairs = state.contacts.pairs
    ok = pairs[:, 0] < n_p
    i = jnp.where(ok, pairs[:, 0], 0)
    j = jnp.where(ok, pairs[:, 1], 0)
    wv = world_vertices(p)
    both = ok & p.active[i] & p.active[j]
    r_sum = p.radius[i] + p.radius[j]
    g0, *_, v0 = closest_features(wv[i], p.n_verts[i], wv[j], p.n_verts[j])
    g1, *_, v1 = closest_features(wv[j], p.n_verts[j], wv[i], p.n_verts[i])
    ov0 = jnp.max(jnp.where(v0, r_sum[:, None] - g0, 0.0), axis=-1)
    ov1 = jnp.max(jnp.where(v1, r_sum[:, None] - g1, 0.0), axis=-1)
    ov = jnp.where(both, jnp.maximum(jnp.maximum(ov0, ov1), 0.0), 0.0)
    out = jnp.zeros(n_p, wv.dtype)
    out = out.at[i].max(ov).at[j].max(ov)
    w = state.walls
    rel = wv[:, None, :, :] - w.point[None, :, None, :]
    gap = jnp.sum(rel * w.normal[None, :, None, :], axis=-1)
    tan = jnp.stack([-w.normal[:, 1], w.normal[:, 0]], axis=-1)
    s = jnp.sum(rel * tan[None, :, None, :], axis=-1)
    inside = (s >= w.extent[None, :, None, 0]) & (s <= w.extent[None, :, None, 1])
    real = jnp.arange(wv.shape[1])[None, None, :] < p.n_verts[:, None, None]
    use = inside & real & w.active[None, :, None] & p.active[:, None, None]
    ov_w = jnp.max(jnp.where(use, p.radius[:, None, None] - gap, 0.0), axis=(1, 2))
    return jnp.where(p.active, jnp.maximum(out, jnp.maximum(ov_w, 0.0)), 0.0)


def _penetration_axis(a: np.ndarray, ra: float, b: np.ndarray, rb: float):
    """Direction ``u`` (unit, from B towards A) of least penetration of two convex
    spheropolygons (cores ``a``, ``b`` ``[n, 2]`` m, radii m) and their signed gap along it
    (m, < 0 when they overlap). Candidates: edge normals of both cores and the unit vectors
    between their vertices, among which the separating axis of two convex spheropolygons
    always is."""
    ea = np.roll(a, -1, axis=0) - a
    eb = np.roll(b, -1, axis=0) - b
    cand = [np.stack([-ea[:, 1], ea[:, 0]], 1), np.stack([eb[:, 1], -eb[:, 0]], 1)]
    cand.append((a[:, None, :] - b[None, :, :]).reshape(-1, 2))
    u = np.concatenate(cand)
    length = np.linalg.norm(u, axis=1)
    u = u[length > 1e-300] / length[length > 1e-300, None]
    gap = (a @ u.T).min(axis=0) - (b @ u.T).max(axis=0) - ra - rb
    best = int(np.argmax(gap))
    return u[best], float(gap[best])


def _overlapping(state: SimState, k: int, clearance: float):
    """Bodies overlapping particle ``k``: ``[(core [n, 2] m, radius m, u)]`` for the active
    particles (``u`` the unit direction of least penetration, from the body towards ``k``)
    and the half-planes ``normals . x <= offsets`` of the overlapping walls."""
    p = state.particles
    act = np.asarray(p.active)
    pos = np.asarray(p.pos, dtype=np.float64)
    angle = np.asarray(p.angle, dtype=np.float64)
    verts = np.asarray(p.verts, dtype=np.float64)
    nv = np.asarray(p.n_verts)
    rad = np.asarray(p.radius, dtype=np.float64)
    bound = np.asarray(p.bound_radius, dtype=np.float64)

    def core(m: int) -> np.ndarray:
        c, s = math.cos(angle[m]), math.sin(angle[m])
        return verts[m, : nv[m]] @ np.array([[c, s], [-s, c]]) + pos[m]

    a = core(k)
    bodies = []
    near = act & (np.linalg.norm(pos - pos[k], axis=1) < bound + bound[k])
    near[k] = False
    for m in np.flatnonzero(near):
        b = core(int(m))
        u, gap = _penetration_axis(a, rad[k], b, rad[m])
        if gap < 0.0:
            bodies.append((b, float(rad[m]), u))
    normals, offsets = [], []
    w = state.walls
    for q in np.flatnonzero(np.asarray(w.active)):
        n = np.asarray(w.normal[q], dtype=np.float64)
        pt = np.asarray(w.point[q], dtype=np.float64)
        ext = np.asarray(w.extent[q], dtype=np.float64)
        rel = a - pt
        s_t = rel @ np.array([-n[1], n[0]])
        inside = (s_t >= ext[0]) & (s_t <= ext[1])
        if inside.any() and (rad[k] - (rel @ n)[inside].min()) > 0.0:
            normals.append(-n)
            offsets.append(-(n @ pt + clearance))
    return (
        bodies,
        np.reshape(np.array(normals, dtype=np.float64), (-1, 2)),
        np.array(offsets, dtype=np.float64),
    )


def contact_halfplanes(state: SimState, k: int, clearance: float = 0.0):
    """Half-planes that keep fragments of particle ``k`` clear of every body overlapping it
    (the ``local-axis`` rule).

    For each active particle B overlapping ``k`` now, with ``u`` its direction of least
    penetration (from B towards ``k``), the fragments' dilated outline must satisfy
    ``u . x >= h_B(u) + r_B + clearance``; for an overlapping wall (inward normal ``n``
    through point ``p``), ``n . (x - p) >= clearance``.

    Returns:
        ``(normals [m, 2], offsets [m])`` in the convention ``normals . x <= offsets`` of
        :func:`jaxgran.geometry.clip_halfplanes` (m).
    """
    return _axis_lines(*_overlapping(state, k, clearance), clearance)


def _axis_lines(bodies, w_normals, w_offsets, clearance: float):
    """The ``local-axis`` half-planes of :func:`_overlapping`'s bodies, walls appended."""
    normals = [-u for _, _, u in bodies]
    offsets = [-((b @ u).max() + r + clearance) for b, r, u in bodies]
    return (
        np.concatenate([np.reshape(np.array(normals, dtype=np.float64), (-1, 2)), w_normals]),
        np.concatenate([np.array(offsets, dtype=np.float64), w_offsets]),
    )


def separating_halfplane(
    piece: npt.ArrayLike,
    body: npt.ArrayLike,
    body_radius: float,
    clearance: float = 0.0,
    n_directions: int = _SEARCH_DIRECTIONS,
) -> tuple[np.ndarray, float] | None:
    """The half-plane that keeps the largest part of ``piece`` clear of a spheropolygon B.

    For every unit ``u`` the half-plane ``u . x >= h_B(u) + r_B + clearance`` (``h_B`` the
    support function of B's core) excludes ``B = core + disc(r_B)``, so the part of the
    piece it keeps never overlaps B, whatever ``u``. The direction is chosen to keep the
    most area: candidates are the edge normals of both polygons and the directions between
    their vertices (among them the separating axis, when the piece does not overlap B, and
    the flanks of a vertex of B poking into the piece), ``n_directions`` directions evenly
    spaced, and a golden-section refinement around the best of them. Where a vertex of B
    presses on a corner of the piece (a fracture plane through a contact point), a line
    along B's flank cuts off a small triangle instead of a strip the length of the face.

    Args:
        piece: convex CCW polygon ``[m, 2]`` (m): a piece of the parent's dilated outline.
        body: B's convex core ``[n, 2]`` (m), world frame (1-2 vertices allowed).
        body_radius: B's sphero-radius r_B (m).
        clearance: extra gap (m) >= 0.
        n_directions: evenly spaced directions searched besides the geometric candidates.

    Returns:
        ``(normal [2], offset)`` in the convention ``normal . x <= offset`` of
        :func:`jaxgran.geometry.clip_halfplanes`, or ``None`` when the piece does not
        overlap B (nothing to clip).
    """
    q = np.asarray(piece, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(body, dtype=np.float64).reshape(-1, 2)
    lift = float(body_radius) + float(clearance)

    def offsets(u: np.ndarray) -> np.ndarray:  # keep u.x >= t: as -u.x <= -t
        return -((b @ u.T).max(axis=0) + lift)

    def kept(u: np.ndarray) -> np.ndarray:
        return geo.halfplane_clip_areas(q, -u, offsets(u))

    cand = [(q[:, None, :] - b[None, :, :]).reshape(-1, 2)]
    for poly, sign in ((q, -1.0), (b, 1.0)):
        if len(poly) >= 2:
            e = np.roll(poly, -1, axis=0) - poly
            cand.append(sign * np.stack([e[:, 1], -e[:, 0]], axis=1))  # outward of CCW
    phi = 2.0 * math.pi * np.arange(int(n_directions)) / max(int(n_directions), 1)
    cand.append(np.stack([np.cos(phi), np.sin(phi)], axis=1))
    u = np.concatenate(cand)
    length = np.linalg.norm(u, axis=1)
    u = u[length > 1e-300] / length[length > 1e-300, None]
    area = kept(u)
    full = abs(geo.polygon_area(q))
    best = int(np.argmax(area))
    if area[best] >= full * (1.0 - 1e-12):
        return None  # a separating axis keeps the whole piece: no overlap
    # golden-section search on the angle around the best candidate (keeps the best seen)
    theta = math.atan2(u[best, 1], u[best, 0])
    best_u, best_a = u[best], float(area[best])
    step = math.pi / max(int(n_directions), 4)
    lo, hi = theta - step, theta + step
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)

    def at(t: float) -> tuple[float, np.ndarray]:
        v = np.array([[math.cos(t), math.sin(t)]])
        return float(kept(v)[0]), v[0]

    f1, v1 = at(x1)
    f2, v2 = at(x2)
    for _ in range(_SEARCH_REFINE):
        if f1 > best_a:
            best_a, best_u = f1, v1
        if f2 > best_a:
            best_a, best_u = f2, v2
        if f1 >= f2:
            hi, x2, f2, v2 = x2, x1, f1, v1
            x1 = hi - g * (hi - lo)
            f1, v1 = at(x1)
        else:
            lo, x1, f1, v1 = x1, x2, f2, v2
            x2 = lo + g * (hi - lo)
            f2, v2 = at(x2)
    return -best_u, float(offsets(best_u[None, :])[0])


def overlapping_bodies(state: SimState, k: int, clearance: float = 0.0):
    """The bodies that overlap particle ``k`` now: ``(cores, radii, wall_normals,
    wall_offsets)``. ``cores`` are the world-frame cores ``[n_j, 2]`` (m) of the active
    particles overlapping it and ``radii`` their sphero-radii (m); every overlapping wall
    (inward normal ``n`` through ``p``) gives the half-plane ``-n . x <= -(n . p +
    clearance)`` (convention of :func:`jaxgran.geometry.clip_halfplanes`)."""
    bodies, w_normals, w_offsets = _overlapping(state, k, clearance)
    return [b for b, _, _ in bodies], [r for _, r, _ in bodies], w_normals, w_offsets


# ---------------------------------------------------------------------------- replacement


@dataclasses.dataclass
class _Fragment:
    core_body: np.ndarray  # [n, 2] m, centred on the mass centroid
    centroid: np.ndarray  # [2] m, world
    mass: float
    inertia: float
    area: float  # m^2, of the spheropolygon
    radius: float  # m, sphero-radius
    # m^2, what the erosion clear of neighbours and walls took from it: the area its piece
    # would keep with nothing in the way (:meth:`_PieceCut.unobstructed`) minus ``area``
    cap_area: float = 0.0


class _PieceCut(NamedTuple):
    """How an outline piece becomes a fragment core: clipped by fixed half-planes
    (``normals . x <= offsets``: overlapping walls, and in ``local-axis`` mode one line per
    overlapping neighbour; none when ``normals`` is None), then clear of each overlapping
    neighbour in ``bodies`` (``(core, radius)``) by the half-plane that keeps the most of
    that piece (:func:`separating_halfplane`, one neighbour after the other), eroded by
    ``r + delta``. ``axis_normals``/``axis_offsets`` are the ``local-axis`` lines of the same
    neighbours: where clipping by all of them keeps more of a piece than the search (the
    search samples directions, and takes one neighbour after the other), they are used, so
    the local rule never keeps less than the earlier one. With ``r_min`` the sphero-radius
    adapts per piece (:meth:`radius_for`)."""

    normals: np.ndarray | None
    offsets: np.ndarray | None
    r: float
    delta: float
    bodies: tuple = ()
    clearance: float = 0.0
    axis_normals: np.ndarray | None = None
    axis_offsets: np.ndarray | None = None
    r_min: float | None = None

    def clip(self, q: np.ndarray) -> np.ndarray:
        return self.clip_count(q)[0]

    def clip_count(self, q: np.ndarray) -> tuple[np.ndarray, int]:
        """The clipped piece and how many neighbours it had to be clipped against."""
        if self.normals is not None and len(self.normals):
            q = geo.clip_halfplanes(q, self.normals, self.offsets)
        base, n = q, 0
        for core, radius in self.bodies:
            if len(q) < 3:
                break
            h = separating_halfplane(q, core, radius, self.clearance)
            if h is not None:
                q = geo.clip_halfplanes(q, h[0][None, :], np.array([h[1]]))
                n += 1
        if n and self.axis_normals is not None and len(base) >= 3:
            alt = geo.clip_halfplanes(base, self.axis_normals, self.axis_offsets)
            if _area(alt) > _area(q):
                return alt, n
        return q, n

    def _core_r(self, clipped: np.ndarray, r: float) -> np.ndarray | None:
        return None if len(clipped) < 3 else fragment_cores([clipped], r, self.delta)[0]

    def radius_for(self, clipped: np.ndarray) -> float:
        """Sphero-radius (m) of the fragment made from the clipped piece: ``r``, or with
        ``r_min`` the largest radius in ``[r_min, r]`` whose rounding (the erosion by ``r_f +
        delta`` and the sweep by ``r_f``) keeps all but ``_ROUNDING_TOL`` of the piece's area
        (``r_min`` if none does). A sliver between a fracture plane and a nearly parallel face
        loses its tip, ``r / sin(a / 2)`` long at an angle ``a``, to the parent's radius; the
        kept area grows as the radius falls (openings by discs shrink with the disc), so a
        bisection finds it."""
        if self.r_min is None or self.r_min >= self.r or len(clipped) < 3:
            return self.r
        goal = (1.0 - _ROUNDING_TOL) * _area(clipped)

        def kept(r):
            core = self._core_r(clipped, r)
            return 0.0 if core is None else _spheropolygon_area(core, r)

        if kept(self.r) >= goal:
            return self.r
        lo, hi = self.r_min, self.r
        if kept(lo) < goal:
            return lo
        for _ in range(_RADIUS_STEPS):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if kept(mid) >= goal else (lo, mid)
        return lo

    def core(self, clipped: np.ndarray) -> tuple[np.ndarray | None, float]:
        """Core (m) and sphero-radius (m) of the fragment made from a clipped piece."""
        r = self.radius_for(clipped)
        return self._core_r(clipped, r), r

    def kept_area(self, q: np.ndarray) -> float:
        """Area (m^2) of the fragment the piece ``q`` becomes, 0 if it vanishes."""
        core, r = self.core(self.clip(q))
        return 0.0 if core is None else _spheropolygon_area(core, r)

    def unobstructed(self) -> _PieceCut:
        """The same cut with no neighbour or wall in the way: no clipping, eroded by ``r``
        and the clearance only. What a piece keeps under it is lost to the new corners'
        rounding alone; the rest of a fragment's loss is the erosion clear of the
        neighbours (the loss paper 000 Fig. 6 marks)."""
        return self._replace(
            normals=None,
            offsets=None,
            bodies=(),
            axis_normals=None,
            axis_offsets=None,
            delta=self.clearance,
        )


def _area(q: np.ndarray) -> float:
    return abs(geo.polygon_area(q)) if len(q) >= 3 else 0.0


def _spheropolygon_area(core: np.ndarray, radius: float) -> float:
    m, _, _ = geo.spheropolygon_mass_properties(core, radius, 1.0)
    return m


def _parent_core_world(arr: dict, k: int) -> np.ndarray:
    n = int(arr["n_verts"][k])
    v = arr["verts"][k, :n]
    c, s = math.cos(arr["angle"][k]), math.sin(arr["angle"][k])
    rot = np.array([[c, -s], [s, c]])
    return v @ rot.T + arr["pos"][k]


def _resize(name: str, a: np.ndarray, n_p: int, n_v: int) -> np.ndarray:
    """Pad a per-particle array to ``n_p`` slots (and verts to ``n_v`` vertices)."""
    if name == "verts" and a.shape[1] < n_v:
        a = np.concatenate([a, np.repeat(a[:, -1:, :], n_v - a.shape[1], axis=1)], axis=1)
    if a.shape[0] < n_p:
        fill = np.full((n_p - a.shape[0],) + a.shape[1:], _PAD.get(name, 0), dtype=a.dtype)
        if name == "pos":  # park new slots on an existing position (inside the domain)
            fill[:] = a[0]
        a = np.concatenate([a, fill], axis=0)
    return a


def fit_vertex_capacity(state: SimState, minimum: int = 3) -> SimState:
    """The state with its vertex axis cut to the most vertices an active particle has, or to
    ``minimum`` if that is more (a run that starts with spare vertex slots, so that its
    fragments fit without a recompilation, keeps them).

    A numerical no-op: the cut entries are padding (copies of each particle's last vertex,
    and tangential histories of vertex slots that no particle has, always zero); the pair
    kernel's cost goes with the square of the vertex capacity, so a state whose capacity
    outgrew its particles (a checkpoint of a run whose capacity grew by a factor, or whose
    many-sided fragment broke again) steps faster fitted. Changes the compiled shapes
    (recompiles once). Returns ``state`` itself when nothing can be cut.
    """
    p, c = state.particles, state.contacts
    n_v = p.verts.shape[1]
    active = np.asarray(p.active)
    need = max(3, minimum, int(np.asarray(p.n_verts)[active].max()) if active.any() else 3)
    if need >= n_v:
        return state
    if np.any(np.asarray(c.xi)[..., need:]) or np.any(np.asarray(c.wall_xi)[..., need:]):
        raise ValueError("tangential history on vertex slots beyond every particle's count")
    particles = dataclasses.replace(p, verts=p.verts[:, :need])
    contacts = dataclasses.replace(c, xi=c.xi[..., :need], wall_xi=c.wall_xi[..., :need])
    return dataclasses.replace(state, particles=particles, contacts=contacts)


def _pad_vertex_axis(x: Array, axis: int, n_v: int) -> np.ndarray:
    x = np.asarray(x)
    if x.shape[axis] >= n_v:
        return x
    shape = list(x.shape)
    shape[axis] = n_v - x.shape[axis]
    return np.concatenate([x, np.zeros(shape, x.dtype)], axis=axis)


def replace_particles(
    state: SimState,
    replacements: Sequence[Replacement],
    *,
    radius: float | None = None,
    areal_density: float | None = None,
    min_area: float = 0.0,
    overlap: npt.ArrayLike | None = None,
    clearance: float | None = None,
    mean_initial_mass: float | None = None,
    growth: float = _GROWTH,
    erosion: str = "local",
    small_pieces: str = "merge",
    conserve_mass: bool = False,
    min_radius: float | None = None,
) -> tuple[SimState, list[dict]]:
    """Replace several particles by their fragments at once (see :func:`replace_particle`).

    Args:
        state: current state.
        replacements: one :class:`Replacement` per broken particle (distinct slots).
        radius: sphero-radius of the fragments (m); default the parent's.
        areal_density: kg/m^2 of the fragments; default the parent's, ``mass / area``.
        min_area: smallest fragment area kept (m^2, after erosion); see ``small_pieces``.
        overlap: ``[P]`` erosion beyond ``r`` (m) per slot, taken off all round; given, it
            overrides ``erosion``.
        clearance: added to the erosion (m); default ``1e-9`` x the parent's bound radius.
        erosion: ``"local"`` (default: clip each piece clear of every neighbour that
            overlaps it by the line that keeps the most of that piece,
            :func:`separating_halfplane`, and of every overlapping wall), ``"local-axis"``
            (the earlier rule: one line per neighbour, along its direction of least
            penetration into the parent, :func:`contact_halfplanes`, for every piece),
            ``"uniform"`` (erode by the parent's largest overlap, :func:`max_overlap`, all
            round) or ``"none"`` (only the sphero-radius, so fragments inherit the parent's
            overlaps; for comparisons, see ``docs/stability.md``); module docstring.
        mean_initial_mass: mean particle mass at t = 0 (kg), for the breakage type (paper 000
            Table III); without it the type is not classified.
        growth: factor by which the particle capacity grows when free slots run out (the
            vertex capacity grows to the largest fragment's vertex count exactly).
        small_pieces: what becomes of a piece below ``min_area``: ``"merge"`` (default) joins
            it to the neighbouring piece across its longest fracture segment
            (:func:`merge_small_pieces`), so material below the resolution stays in the
            fragments; ``"fines"`` drops it as lost mass (counted as ``fines_mass``). A piece
            without a neighbour becomes fines in both modes. When merging leaves a single
            piece, the particle is not replaced: its event has ``kind = "suppressed"``.
        conserve_mass: give each fragment the mass of its uneroded outline piece (the
            parent's mass shared by piece area) through a slightly higher areal density, so
            the erosion removes area but no mass (paper 000 §III: "this loss of mass can also
            be compensated by slightly increasing the density"). The area removed is
            ``area_lost`` in the event either way; fines still lose their share.
        min_radius: None (default): every fragment takes the radius ``r`` (``radius`` or the
            parent's). Given (m, ``0 < min_radius``): each fragment's sphero-radius adapts,
            the largest value in ``[min_radius, r]`` whose corner rounding keeps all but
            0.1 % of its piece (:meth:`_PieceCut.radius_for`); slivers cut by a plane nearly
            parallel to a face keep their tips with a smaller radius instead of losing them.
            Radii only shrink, so give an absolute floor (e.g. a fraction of the scene's
            radius), not one relative to each parent. ``fragment_radii`` in the event.

    Returns:
        ``(state, events)``: the new state (call :func:`jaxgran.simulate.prepare` before
        stepping) and one event dict per replacement (``kind`` ``"breakage"`` or
        ``"suppressed"``).
    """
    if not replacements:
        return state, []
    p = state.particles
    n_p, n_v = p.verts.shape[:2]
    idx = [int(r.index) for r in replacements]
    if len(set(idx)) != len(idx):
        raise ValueError(f"each slot may be replaced once per call; got slots {idx}")
    arr = {f.name: np.array(getattr(p, f.name)) for f in dataclasses.fields(p)}
    for k in idx:
        if not 0 <= k < n_p or not arr["active"][k]:
            raise ValueError(f"slot {k} is not an active particle (capacity {n_p})")
    if erosion not in EROSION_MODES:
        raise ValueError(f"erosion must be one of {EROSION_MODES}, got {erosion!r}")
    if small_pieces not in SMALL_PIECE_MODES:
        raise ValueError(f"small_pieces must be one of {SMALL_PIECE_MODES}, got {small_pieces!r}")
    if min_radius is not None and not (math.isfinite(min_radius) and min_radius > 0.0):
        raise ValueError(f"min_radius must be finite and > 0 m (or None), got {min_radius}")
    local = overlap is None and erosion in ("local", "local-axis")
    mode = erosion if overlap is None else "uniform"  # a given overlap is taken off all round
    if overlap is None and erosion == "none":
        overlap = np.zeros(n_p)
    if overlap is None:
        overlap = np.zeros(n_p) if local else np.asarray(max_overlap(state))
    overlap = np.broadcast_to(np.asarray(overlap, dtype=float), (n_p,))
    time = float(state.time)

    # 1. fragments of every parent
    plans = []
    for rep in replacements:
        k = int(rep.index)
        r = float(arr["radius"][k]) if radius is None else float(radius)
        core_w = _parent_core_world(arr, k)
        m_parent = float(arr["mass"][k])
        a_parent = _spheropolygon_area(core_w, float(arr["radius"][k]))
        rho = m_parent / a_parent if areal_density is None else float(areal_density)
        clear = _CLEARANCE_REL * float(arr["bound_radius"][k]) if clearance is None else clearance
        delta = max(float(overlap[k]), 0.0) + float(clear)
        pieces = [np.asarray(q, dtype=np.float64).reshape(-1, 2) for q in rep.pieces]
        if mode == "local":
            near, normals, offsets = _overlapping(state, k, clear)
            bodies = tuple((b, rb) for b, rb, _ in near)
            n_clips = len(bodies) + len(offsets)
            axis = _axis_lines(near, normals, offsets, clear)
        elif mode == "local-axis":
            normals, offsets = contact_halfplanes(state, k)
            bodies, n_clips, axis = (), len(offsets), (None, None)
        else:
            normals, offsets, bodies, n_clips, axis = None, None, (), 0, (None, None)
        r_min = None if min_radius is None else float(min_radius)
        cut = _PieceCut(normals, offsets, r, delta, bodies, float(clear), *axis, r_min)
        n_merged = 0
        if small_pieces == "merge":
            pieces, n_merged = merge_small_pieces(pieces, cut.kept_area, min_area)
        if n_merged and len(pieces) == 1:  # nothing above the resolution breaks off
            plans.append((k, None, n_merged, len(rep.pieces)))
            continue
        clip_counts = [cut.clip_count(q) for q in pieces]
        clipped = [c for c, _ in clip_counts]
        n_piece_clips = sum(n for _, n in clip_counts)
        cores = [cut.core(q) for q in clipped]
        unobstructed = cut.unobstructed()
        frags: list[_Fragment] = []
        fines_area = 0.0
        # share of the parent's mass per outline piece (conserve_mass), before clipping
        piece_area = np.array([abs(geo.polygon_area(q)) if len(q) >= 3 else 0.0 for q in pieces])
        share = m_parent * piece_area / max(piece_area.sum(), np.finfo(float).tiny)
        fines_share = 0.0
        for whole, piece, (core, r_f), m_share in zip(pieces, clipped, cores, share, strict=True):
            area = None if core is None else _spheropolygon_area(core, r_f)
            if core is None or area < min_area:
                fines_area += abs(geo.polygon_area(piece)) if len(piece) >= 3 else 0.0
                fines_share += m_share
                continue
            rho_f = m_share / area if conserve_mass else rho
            m, c, inertia = geo.spheropolygon_mass_properties(core, r_f, rho_f)
            cap = unobstructed.kept_area(whole) - area if n_clips or mode == "uniform" else 0.0
            frags.append(_Fragment(core - c, c, m, inertia, area, r_f, cap))
        fines_mass = fines_share if conserve_mass else rho * fines_area
        plans.append(
            (
                k,
                r,
                rho,
                delta,
                frags,
                fines_mass,
                m_parent,
                a_parent,
                rep,
                n_clips,
                n_merged,
                n_piece_clips,
            )
        )

    # 2. capacity: free slots and vertex slots
    suppressed = {pl[0]: pl for pl in plans if pl[1] is None}
    plans = [pl for pl in plans if pl[1] is not None]
    needed = sum(max(len(pl[4]) - 1, 0) for pl in plans)
    free = np.flatnonzero(~arr["active"]).tolist()
    v_need = max([len(f.core_body) for pl in plans for f in pl[4]] + [n_v])
    new_p = n_p
    if needed > len(free):
        new_p = max(n_p + needed - len(free), math.ceil(growth * n_p))
    # the vertex axis grows to the need exactly: the pair kernel's cost goes with V^2, and
    # fragments with more vertices than the parent are rare (one of ~700 in the Voronoi
    # oedometer), so a factor would make every later step pay for headroom seldom used
    new_v = max(v_need, n_v)
    grew = []
    if new_p != n_p:
        grew.append(f"particle capacity {n_p} -> {new_p}")
    if new_v != n_v:
        grew.append(f"vertex capacity {n_v} -> {new_v}")
    if grew:
        arr = {name: _resize(name, a, new_p, new_v) for name, a in arr.items()}
        free = free + list(range(n_p, new_p))
        msg = "breakage grew " + " and ".join(grew) + " (recompiles once)"
        log.info(msg)

    # 3. write fragments
    next_uid = int(arr["uid"].max()) + 1
    touched: list[int] = []
    events = {}
    free_iter = iter(free)
    for plan in plans:
        k, r, rho_k, delta, frags, fines_mass, m_parent, a_parent, rep, n_clips, n_merged, n_pc = (
            plan
        )
        pos_k = arr["pos"][k].copy()
        vel_k = arr["vel"][k].copy()
        om_k = float(arr["omega"][k])
        parent_uid = int(arr["uid"][k])
        slots = [k] + [next(free_iter) for _ in frags[1:]]
        uids = []
        for slot, f in zip(slots, frags, strict=False):
            nb = len(f.core_body)
            arr["verts"][slot, :nb] = f.core_body
            arr["verts"][slot, nb:] = f.core_body[-1]
            arr["n_verts"][slot] = nb
            arr["radius"][slot] = f.radius
            arr["bound_radius"][slot] = np.max(np.linalg.norm(f.core_body, axis=1)) + f.radius
            arr["mass"][slot] = f.mass
            arr["inertia"][slot] = f.inertia
            arr["pos"][slot] = f.centroid
            arr["angle"][slot] = 0.0
            d = f.centroid - pos_k
            arr["vel"][slot] = vel_k + om_k * np.array([-d[1], d[0]])
            arr["omega"][slot] = om_k
            arr["force"][slot] = 0.0
            arr["torque"][slot] = 0.0
            arr["active"][slot] = True
            arr["fixed"][slot] = arr["fixed"][k]
            arr["material"][slot] = arr["material"][k]
            arr["parent_uid"][slot] = parent_uid
            arr["uid"][slot] = next_uid
            uids.append(next_uid)
            next_uid += 1
            touched.append(slot)
        if not frags:  # pulverised: the slot becomes free
            arr["active"][k] = False
            arr["mass"][k] = 1.0
            arr["inertia"][k] = 1.0
            arr["vel"][k] = 0.0
            arr["omega"][k] = 0.0
            arr["force"][k] = 0.0
            arr["torque"][k] = 0.0
            touched.append(k)
        masses = np.array([f.mass for f in frags])
        areas = np.array([f.area for f in frags])
        lost = m_parent - float(masses.sum())
        caps = float(sum(f.cap_area for f in frags))
        caps_mass = 0.0 if conserve_mass else rho_k * caps
        planes = np.zeros((0, 2, 2)) if rep.planes is None else np.asarray(rep.planes, float)
        event = {
            "kind": "breakage",
            "time": time,
            "parent_uid": parent_uid,
            "parent_slot": k,
            "fragment_uids": np.array(uids, dtype=np.int64),
            "fragment_slots": np.array(slots[: len(frags)], dtype=np.int64),
            "fragment_masses": masses,
            "fragment_areas": areas,
            "fragment_radii": np.array([f.radius for f in frags]),
            "parent_mass": m_parent,
            "parent_area": a_parent,
            "area_lost": a_parent - float(areas.sum()),
            "conserve_mass": conserve_mass,
            "mass_lost": lost,
            "fines_mass": fines_mass,
            "eroded_mass": lost - fines_mass,
            "caps_area": caps,
            "caps_mass": caps_mass,
            "rounding_mass": lost - fines_mass - caps_mass,
            "n_fines": len(rep.pieces) - n_merged - len(frags),
            "n_merged": n_merged,
            "erosion": delta,
            "erosion_mode": mode,
            "n_contact_clips": n_clips,
            "n_piece_clips": n_pc,
            "planes": planes.reshape(-1, 2, 2),
            "position": pos_k,
        }
        if mean_initial_mass is not None:
            event["breakage_type"] = (
                breakage_type(masses, mean_initial_mass) if len(masses) else "pulverised"
            )
        if grew:
            event["capacity_growth"] = msg
            grew = []  # report it once
        events[k] = event
    for k, _, n_merged, n_pieces in suppressed.values():
        events[k] = {
            "kind": "suppressed",
            "time": time,
            "parent_uid": int(arr["uid"][k]),
            "parent_slot": k,
            "n_pieces": n_pieces,
            "n_merged": n_merged,
            "position": arr["pos"][k].copy(),
        }
    events = [events[k] for k in idx]

    # 4. new state: particles, and contacts with the history of touched slots cleared
    dtypes = {f.name: getattr(p, f.name).dtype for f in dataclasses.fields(p)}
    particles = Particles(**{n: jnp.asarray(a, dtype=dtypes[n]) for n, a in arr.items()})
    contacts = _contacts_after(state.contacts, touched, new_p, new_v, state.walls.count)
    return (
        SimState(
            particles=particles,
            walls=state.walls,
            contacts=contacts,
            time=state.time,
            step=state.step,
            bonds=_bonds_after(state.bonds, touched, n_p, new_p),
            energy=state.energy,
        ),
        events,
    )


def _contacts_after(c: Contacts, touched: list[int], n_p: int, n_v: int, n_w: int) -> Contacts:
    """Contacts for the new particle arrays: a fresh list if P changed (the sentinel ``P``
    changes), else the old one with the tangential history of touched slots zeroed and the
    vertex axis padded. Layouts (state.Contacts): ``xi [2, C, 2, V]``,
    ``wall_xi [2, P, W, V]``."""
    fd = c.xi.dtype
    if c.ref_pos.shape[0] != n_p:
        return empty_contacts(n_p, n_v, n_w, c.pairs.shape[0], dtype=fd)
    pairs = np.asarray(c.pairs)
    hit = np.isin(pairs[:, 0], touched) | np.isin(pairs[:, 1], touched)
    xi = _pad_vertex_axis(c.xi, -1, n_v).copy()
    xi[:, hit] = 0.0
    wall_xi = _pad_vertex_axis(c.wall_xi, -1, n_v).copy()
    wall_xi[:, touched] = 0.0
    return Contacts(
        pairs=c.pairs,
        n_pairs=c.n_pairs,
        xi=jnp.asarray(xi, fd),
        wall_xi=jnp.asarray(wall_xi, fd),
        ref_pos=c.ref_pos,
        ref_angle=c.ref_angle,
        n_builds=c.n_builds,
    )


def _bonds_after(bonds, touched: list[int], old_p: int, new_p: int):
    """Bonds (jaxgran.bonds.Bonds) after replacement: those of a replaced slot are broken
    (the fragments are new bodies) and the padding sentinel follows the capacity."""
    if bonds is None:
        return None
    changes = {}
    i, j = np.asarray(bonds.i), np.asarray(bonds.j)
    hit = np.isin(i, touched) | np.isin(j, touched)
    if hit.any():
        changes["intact"] = jnp.asarray(np.asarray(bonds.intact) & ~hit)
        if hasattr(bonds, "health"):
            h = np.asarray(bonds.health)
            changes["health"] = jnp.asarray(np.where(hit, 0.0, h), h.dtype)
    wp = np.asarray(bonds.wall_p)
    whit = np.isin(wp, touched)
    if whit.any():
        changes["wall_active"] = jnp.asarray(np.asarray(bonds.wall_active) & ~whit)
    if new_p != old_p:
        for name, a in (("i", i), ("j", j), ("wall_p", wp)):
            changes[name] = jnp.asarray(np.where(a >= old_p, new_p, a), a.dtype)
    return replace(bonds, **changes) if changes else bonds


def replace_particle(
    state: SimState,
    k: int,
    fragments_world: Sequence[npt.ArrayLike],
    *,
    radius: float | None = None,
    areal_density: float | None = None,
    min_area: float = 0.0,
    overlap: float | None = None,
    clearance: float | None = None,
    mean_initial_mass: float | None = None,
    planes: npt.ArrayLike | None = None,
    growth: float = _GROWTH,
    erosion: str = "local",
    small_pieces: str = "merge",
    conserve_mass: bool = False,
    min_radius: float | None = None,
) -> tuple[SimState, dict]:
    """Replace particle ``k`` by fragments (paper 000 §II.D; erosion rule in the module doc).

    The parent's slot is reused by the first fragment, the others go to free (inactive)
    slots; when there are not enough, the particle capacity grows by ``growth`` (all
    per-particle arrays, and the pair list restarts empty because its sentinel ``P``
    changes); a fragment with more vertices than ``V`` grows the vertex capacity. Fragments
    get new uids, ``parent_uid`` = the parent's uid, its material, the rigid-body velocity
    field and exact mass and inertia. The tangential history of every pair and wall contact
    of a touched slot is zeroed. Call :func:`jaxgran.simulate.prepare` afterwards.

    Args:
        state: current state.
        k: slot of the broken particle.
        fragments_world: pieces of the parent's dilated outline (world frame, m), e.g.
            ``split_convex(dilated_outline(core_world, r), planes)``. Each piece is eroded by
            ``r + overlap + clearance``; pieces that vanish or end up below ``min_area``
            become fines.
        radius: fragment sphero-radius (m); default the parent's.
        areal_density: kg/m^2; default the parent's (mass / area).
        min_area: smallest fragment area kept (m^2).
        overlap: erosion beyond r (m), all round; given, it overrides ``erosion``.
        erosion: ``"local"`` (default), ``"local-axis"``, ``"uniform"`` or ``"none"``, see
            :func:`replace_particles`.
        clearance: extra erosion (m); default ``1e-9`` x the parent's bound radius.
        mean_initial_mass: mean initial particle mass (kg) for the breakage type.
        planes: ``[k, 2, 2]`` fracture planes (m), stored in the event.
        growth: capacity growth factor.
        small_pieces: ``"merge"`` (default) or ``"fines"``, see :func:`replace_particles`.
        conserve_mass: density compensation of the erosion, see :func:`replace_particles`.
        min_radius: floor of the adaptive fragment radius (m), see :func:`replace_particles`.

    Returns:
        ``(state, event)``. The event holds ``time`` (s), ``parent_uid``,
        ``fragment_uids``, ``fragment_slots``, ``fragment_masses`` (kg), ``parent_mass``,
        ``mass_lost`` (= parent - fragments, kg), ``fines_mass``, ``eroded_mass``
        (= ``caps_mass + rounding_mass``, see the module's bookkeeping), ``n_fines``,
        ``erosion`` (m), ``planes`` and, with ``mean_initial_mass``, ``breakage_type``;
        ``capacity_growth`` when a capacity grew.
    """
    n_p = state.particles.pos.shape[0]
    ov = None
    if overlap is not None:
        ov = np.zeros(n_p)
        ov[int(k)] = float(overlap)
    state, events = replace_particles(
        state,
        [Replacement(int(k), list(fragments_world), None if planes is None else planes)],
        radius=radius,
        areal_density=areal_density,
        min_area=min_area,
        overlap=ov,
        clearance=clearance,
        mean_initial_mass=mean_initial_mass,
        growth=growth,
        erosion=erosion,
        small_pieces=small_pieces,
        conserve_mass=conserve_mass,
        min_radius=min_radius,
    )
    return state, events[0]
