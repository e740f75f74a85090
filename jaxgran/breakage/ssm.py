"""Subset separation method (SSM): cut a convex polygon by any number of straight lines.

Paper 000 (Jiang, Mora, Herrmann, Alonso-Marroquín, PRE 104, 045311, 2021), §II.C,
Algorithm 1 and Eq. 4-6. Host-side numpy: fragment counts and vertex counts are data
dependent, so this never runs under jit.

The method in four steps:

1. The *Set*: the polygon's vertices, the points where a line meets the boundary and the
   points where two lines cross inside the polygon; points closer than ``tol`` are merged.
2. Each Set point is assigned to the side(s) of each line; a point on a line (within ``tol``,
   or built on it) belongs to both sides.
3. A cell of the arrangement is a full sign pattern ``sigma in {-1, +1}^k``; its subset is every
   Set point compatible with ``sigma`` (Eq. 4-6). Instead of visiting all ``2^k`` patterns, the
   realised ones are read off the Set: every cell has a Set point as a corner, and around a
   point the lines through it split a small disc into sectors, one pattern per sector.
4. A subset with more than two points (paper: ``|S_i| > 2``), not all on one line and lying
   strictly on its own side of every line, becomes a fragment: its points ordered
   counter-clockwise around their mean (as in the paper), duplicate and collinear points
   removed. The polygon's corners are kept exactly, so the fragments tile its area.

Two tolerances: ``tol`` (default ``1e-12`` x diameter) decides coincidence and "on the line";
``min_cut`` (default ``1e-9`` x diameter) is the shallowest cut a line must make to count.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["split_convex"]

# Default tolerance relative to the polygon's diameter: ~5000x float64 round-off of the
# intersection arithmetic, yet small enough that tolerance-sized slivers, which can be
# absorbed by a neighbour and counted twice, cost less than 1e-10 of the parent's area.
_DEFAULT_RELATIVE_TOL = 1e-12
# Default smallest cut depth relative to the diameter (see split_convex's min_cut).
_DEFAULT_MIN_CUT_REL = 1e-9
# Angular gap (rad) below which two half-lines through the same Set point are one direction.
_ANGLE_GAP = 1e-12
# Relative height (times the diameter) below which a corner of the input polygon counts as
# exactly collinear (round-off only); such corners are the only ones the parent ever loses.
_COLLINEAR_REL = 1e-14


def split_convex(
    vertices: npt.ArrayLike,
    lines: npt.ArrayLike,
    *,
    tol: float | None = None,
    min_cut: float | None = None,
) -> list[np.ndarray]:
    """Cut a convex polygon by straight lines into convex fragments (paper 000, Algorithm 1).

    Args:
        vertices: ``[n_vertices, 2]`` polygon corners (m), in boundary order, clockwise or
            counter-clockwise. Duplicate and collinear corners are allowed.
        lines: ``[n_lines, 2, 2]`` fracture planes, each given by two distinct points (m) on the
            (infinite) line. Lines that miss the polygon, only touch it (through one corner,
            along an edge) or repeat another line change nothing.
        tol: absolute length tolerance (m) for merging points, for "on the line" and for
            dropping degenerate cells. Default: ``1e-12`` times the polygon diameter.
        min_cut: a line is used only if corners lie deeper than this (m) on both of its
            sides; shallower cuts are ignored, which never changes the total area. Default:
            ``1e-9`` times the diameter, far below any physical fragment yet above the
            round-off of a line drawn between two nearby points on one edge (e.g. the two
            contact points of an edge-edge contact) far from the origin.

    Returns:
        Fragments as a list of ``[n_i, 2]`` float64 arrays (m), each convex, counter-clockwise
        and free of duplicate or collinear corners. Their areas sum to the polygon's area.
        With no line crossing the interior the list holds the (cleaned) polygon itself.

    Raises:
        ValueError: on bad shapes, non-finite input, a degenerate or non-convex polygon, or a
            line given by two coincident points.
    """
    polygon = _convex_polygon(vertices)
    segs = np.asarray(lines, dtype=np.float64)
    if segs.size == 0:
        segs = segs.reshape(0, 2, 2)
    if segs.ndim != 3 or segs.shape[1:] != (2, 2):
        raise ValueError(
            f"lines must have shape [n_lines, 2, 2] (two points per line); got {segs.shape}"
        )
    if not np.all(np.isfinite(segs)):
        raise ValueError("lines contain NaN or inf; pass two finite points per line")

    # Local frame centred on the polygon: keeps the arithmetic relative to the particle size.
    origin = polygon.mean(axis=0)
    poly = polygon - origin
    diameter = _diameter(poly)
    tol = _DEFAULT_RELATIVE_TOL * diameter if tol is None else float(tol)
    if not tol > 0.0:
        raise ValueError(f"tol must be a positive length (m); got {tol}")

    if _area(poly) <= tol * diameter:
        raise ValueError("the polygon is degenerate (no area); drop it instead of splitting it")
    _check_convex(poly, max(tol, _DEFAULT_MIN_CUT_REL * diameter))
    floor = _COLLINEAR_REL * diameter
    kept = _convex_cycle(poly, floor)
    poly, polygon = poly[kept], polygon[kept]

    anchor = segs[:, 0, :] - origin
    direction = segs[:, 1, :] - segs[:, 0, :]
    length = np.linalg.norm(direction, axis=1)
    if np.any(length <= 0.0):
        bad = np.flatnonzero(length <= 0.0).tolist()
        raise ValueError(f"lines {bad} are given by two identical points; pass distinct points")
    direction = direction / length[:, None]
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    offset = np.einsum("kd,kd->k", normal, anchor)

    # Keep only lines that cross the interior: corners clearly on both sides.
    min_cut = max(_DEFAULT_MIN_CUT_REL * diameter if min_cut is None else min_cut, tol)
    dist_vertices = poly @ normal.T - offset
    crossing = (dist_vertices.max(axis=0) > min_cut) & (dist_vertices.min(axis=0) < -min_cut)
    if not np.any(crossing):
        return [polygon]
    direction, normal, offset = direction[crossing], normal[crossing], offset[crossing]
    dist_vertices = dist_vertices[:, crossing]

    points, incidence = _build_set(poly, dist_vertices, normal, offset, tol)
    corner = np.arange(points.shape[0]) < poly.shape[0]
    dist = points @ normal.T - offset
    signs = np.sign(dist).astype(np.int8)
    signs[(np.abs(dist) <= tol) | incidence] = 0

    patterns = _realised_patterns(signs, direction, normal)

    fragments: list[np.ndarray] = []
    seen: set[bytes] = set()
    compatible = np.all((signs[None, :, :] == 0) | (signs[None, :, :] == patterns[:, None, :]), 2)
    for pattern, mask in zip(patterns, compatible, strict=True):
        # Fewer than three points, or all on one line (then both sides already own them).
        if np.count_nonzero(mask) < 3 or np.any(np.all(signs[mask] == 0, axis=0)):
            continue
        members = np.flatnonzero(mask)
        ring = members[_convex_cycle(points[members], tol, protected=corner[members], floor=floor)]
        cell = points[ring]
        if ring.size < 3 or _area(cell) <= tol * tol:
            continue
        # A real cell lies strictly on its own side of every line; a pattern that is not
        # realised only collects points within tol of some line, and its mean shows it.
        if np.any(pattern * (cell.mean(axis=0) @ normal.T - offset) <= 0.0):
            continue
        key = np.sort(ring).tobytes()
        if key in seen:
            continue
        seen.add(key)
        # Parent corners are returned bit for bit as given.
        out = cell + origin
        is_corner = ring < polygon.shape[0]
        out[is_corner] = polygon[ring[is_corner]]
        fragments.append(out)
    return fragments


def _convex_polygon(vertices: npt.ArrayLike) -> np.ndarray:
    """Validate ``[n, 2]`` corners and return them counter-clockwise as float64."""
    poly = np.array(vertices, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3:
        raise ValueError(f"vertices must have shape [n_vertices >= 3, 2]; got {np.shape(vertices)}")
    if not np.all(np.isfinite(poly)):
        raise ValueError("vertices contain NaN or inf")
    if _signed_area(poly) < 0.0:
        poly = poly[::-1].copy()
    return poly


def _check_convex(poly: np.ndarray, tol: float) -> None:
    """Raise unless the CCW corners (in the given order) bound a convex polygon; corners
    reflex by up to ``tol`` (round-off upstream) pass and are dropped by the cleanup."""
    step = np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1)
    ring = poly[step > tol]
    if ring.shape[0] >= 3:
        e0 = ring - np.roll(ring, 1, axis=0)
        e1 = np.roll(ring, -1, axis=0) - ring
        cross = e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0]
        chord = np.linalg.norm(e0 + e1, axis=1)
        height = cross / np.maximum(chord, np.finfo(np.float64).tiny)
        turning = np.sum(np.arctan2(cross, np.einsum("vd,vd->v", e0, e1)))
        if height.min() >= -tol and abs(turning - 2.0 * np.pi) < 1e-6:
            return
    raise ValueError(
        "vertices do not form a convex polygon in boundary order; split a non-convex shape "
        "into convex parts first and cut each part (paper 000, §II.C)"
    )


def _build_set(
    poly: np.ndarray,
    dist_vertices: np.ndarray,
    normal: np.ndarray,
    offset: np.ndarray,
    tol: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The Set of paper 000 §II.C: corners, line-boundary and interior line-line points.

    Returns the merged points ``[M, 2]`` and ``incidence [M, k]``: True where a point was
    constructed on a line. Carrying incidence through the merge keeps "on the line" exact
    even when a merged representative sits up to ``tol`` away from one of its lines.
    """
    n_lines = normal.shape[0]
    n_vert = poly.shape[0]
    cand_xy = [poly]
    cand_inc = [np.zeros((n_vert, n_lines), dtype=bool)]

    # Line-boundary points: edges whose end points lie strictly on opposite sides.
    nxt = np.roll(np.arange(n_vert), -1)
    d_a, d_b = dist_vertices, dist_vertices[nxt]
    edge, line = np.nonzero(d_a * d_b < 0.0)
    if edge.size:
        t = d_a[edge, line] / (d_a[edge, line] - d_b[edge, line])
        xy = poly[edge] + t[:, None] * (poly[nxt[edge]] - poly[edge])
        inc = np.zeros((edge.size, n_lines), dtype=bool)
        inc[np.arange(edge.size), line] = True
        cand_xy.append(xy)
        cand_inc.append(inc)

    # Line-line crossings inside the polygon, walked along line i from its foot point: the
    # result lies on both lines to round-off even when they are nearly parallel (its error
    # is then along the lines, where they are closer than tol anyway).
    i, j = np.triu_indices(n_lines, k=1)
    direction = np.stack([normal[:, 1], -normal[:, 0]], axis=1)
    sin = np.einsum("md,md->m", normal[j], direction[i])
    ok = sin != 0.0
    i, j, sin = i[ok], j[ok], sin[ok]
    if i.size:
        foot = normal[i] * offset[i, None]
        with np.errstate(over="ignore"):
            t = (offset[j] - np.einsum("md,md->m", normal[j], foot)) / sin
            xy = foot + t[:, None] * direction[i]
        finite = np.all(np.isfinite(xy), axis=1)
        xy, i, j = xy[finite], i[finite], j[finite]
        depth = _inward_distance(poly, xy).min(axis=1)
        inside = depth >= -tol
        xy, i, j, depth = xy[inside], i[inside], j[inside], depth[inside]
        # Crossings a hair outside (round-off, lines meeting on the boundary) are snapped onto
        # the boundary so that no fragment pokes out of the parent.
        for m in np.flatnonzero(depth < 0.0):
            xy[m] = _nearest_on_boundary(poly, xy[m])
        inc = np.zeros((xy.shape[0], n_lines), dtype=bool)
        inc[np.arange(xy.shape[0]), i] = True
        inc[np.arange(xy.shape[0]), j] = True
        cand_xy.append(xy)
        cand_inc.append(inc)

    # Greedy merge into the nearest kept point; the corners come first and are all kept
    # exactly, so the fragments tile exactly the parent's area.
    keep_xy = list(poly)
    keep_inc = list(cand_inc[0])
    extra_xy = np.concatenate([np.zeros((0, 2)), *cand_xy[1:]])
    extra_inc = np.concatenate([np.zeros((0, n_lines), dtype=bool), *cand_inc[1:]])
    for xy, inc in zip(extra_xy, extra_inc, strict=True):
        d = np.linalg.norm(np.asarray(keep_xy) - xy, axis=1)
        nearest = int(np.argmin(d))
        if d[nearest] <= tol:
            keep_inc[nearest] = keep_inc[nearest] | inc
            continue
        keep_xy.append(xy)
        keep_inc.append(inc.copy())
    return np.asarray(keep_xy), np.asarray(keep_inc)


def _nearest_on_boundary(poly: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Closest point to ``x`` on the boundary of a polygon ``[n, 2]``."""
    a = poly
    e = np.roll(poly, -1, axis=0) - poly
    t = np.clip(np.einsum("nd,nd->n", x - a, e) / np.einsum("nd,nd->n", e, e), 0.0, 1.0)
    foot = a + t[:, None] * e
    return foot[int(np.argmin(np.linalg.norm(foot - x, axis=1)))]


def _realised_patterns(signs: np.ndarray, direction: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Full sign patterns ``[C, k]`` of every cell that has a Set point as a corner.

    A point with no zero sign is inside exactly one cell. Around a point on lines Z, the
    half-lines ``+-direction_j`` (j in Z) cut a small disc into sectors; a sector's pattern
    takes ``sign(normal_j . u)`` for its bisector ``u`` on Z and the point's signs elsewhere.
    Sectors pointing out of the polygon give patterns whose subsets are degenerate; the
    caller drops them. The work is linear in the number of (point, line) incidences, not 2^k.
    """
    found = [signs[np.all(signs != 0, axis=1)]]
    for row in signs[np.any(signs == 0, axis=1)]:
        on = np.flatnonzero(row == 0)
        base = np.arctan2(direction[on, 1], direction[on, 0])
        angles = np.sort(np.mod(np.concatenate([base, base + np.pi]), 2.0 * np.pi))
        gaps = np.diff(np.append(angles, angles[0] + 2.0 * np.pi))
        starts = gaps > _ANGLE_GAP
        mid = angles[starts] + 0.5 * gaps[starts]
        u = np.stack([np.cos(mid), np.sin(mid)], axis=1)
        side = np.sign(u @ normal[on].T).astype(np.int8)
        side = side[np.all(side != 0, axis=1)]
        sector = np.repeat(row[None, :], side.shape[0], axis=0)
        sector[:, on] = side
        found.append(sector)
    return np.unique(np.concatenate(found), axis=0)


def _convex_cycle(
    points: np.ndarray,
    tol: float,
    protected: np.ndarray | None = None,
    floor: float = 0.0,
) -> np.ndarray:
    """Order points counter-clockwise around their mean (paper 000 §II.C), then drop
    duplicates (closer than ``tol``) and corners within ``tol`` of the chord joining their
    neighbours, flattest first. ``protected`` points (the parent's corners, which are exact)
    are dropped only when reflex or collinear to within ``floor``. Returns the indices of the
    kept points in counter-clockwise order."""
    centre = points.mean(axis=0)
    rel = points - centre
    order = np.argsort(np.arctan2(rel[:, 1], rel[:, 0]), kind="stable")
    ring = points[order]
    index = order
    keep = np.zeros(len(ring), bool) if protected is None else np.asarray(protected)[order]
    tiny = np.finfo(np.float64).tiny
    while ring.shape[0] > 1:
        step = np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)
        both = keep & np.roll(keep, -1)
        step = np.where(both & (step > floor), np.inf, step)
        first = int(np.argmin(step))
        if step[first] > tol:
            break
        drop = (first + 1) % ring.shape[0] if not keep[(first + 1) % ring.shape[0]] else first
        ring, keep, index = (np.delete(a, drop, axis=0) for a in (ring, keep, index))
    while ring.shape[0] >= 3:
        prev, nxt = np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0)
        chord = nxt - prev
        rel_prev = ring - prev
        # Height of the corner outside its chord (positive for a convex CCW corner).
        height = (rel_prev[:, 0] * chord[:, 1] - rel_prev[:, 1] * chord[:, 0]) / np.maximum(
            np.linalg.norm(chord, axis=1), tiny
        )
        height = np.where(keep & (height > floor), np.inf, height)
        flattest = int(np.argmin(height))
        if height[flattest] > tol:
            break
        ring, keep, index = (np.delete(a, flattest, axis=0) for a in (ring, keep, index))
    return index


def _inward_distance(poly: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Signed distance ``[m, n_edges]`` of points to each edge line, positive inside."""
    edge = np.roll(poly, -1, axis=0) - poly
    inward = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    return np.einsum("ed,med->me", inward, xy[:, None, :] - poly[None, :, :])


def _signed_area(poly: np.ndarray) -> float:
    rel = poly - poly[0]
    x, y = rel[:, 0], rel[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _area(poly: np.ndarray) -> float:
    return abs(_signed_area(poly))


def _diameter(points: np.ndarray) -> float:
    diff = points[:, None, :] - points[None, :, :]
    return float(np.sqrt(np.max(np.einsum("abd,abd->ab", diff, diff))))
