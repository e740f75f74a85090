"""Planar geometry of convex polygons and spheropolygons.

Host-side numpy functions (scenes, breakage) and a few jax twins over padded arrays (used
inside jit). Conventions used throughout:

* A polygon is an array ``[n_vertices, 2]`` of vertex coordinates (m), listed counter-clockwise
  (CCW) without repeating the first vertex at the end. Signed areas are positive for CCW.
* A spheropolygon is the Minkowski sum of a convex core polygon and a disc of radius ``r`` (m).
  Its core may degenerate to one vertex (a disc) or two vertices (a stadium).
* Padded polygon arrays are ``verts[..., V, 2]`` with ``n_verts[...]`` real vertices; slots
  ``k >= n_verts`` repeat the last real vertex and are masked. Edge ``k`` runs from vertex ``k``
  to vertex ``k + 1`` (or ``0`` for the last real vertex).
* Tolerances named ``tol`` are relative to the size of the figure, so results do not depend on
  the choice of length unit.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

_TWO_PI = 2.0 * math.pi
# Relative tolerance under which two consecutive vertices count as duplicates.
_DUP_TOL = 1e-12
# Relative tolerance (area / size^2) under which a polygon counts as having no area.
_AREA_TOL = 1e-12


# ---------------------------------------------------------------------------------------------
# small private helpers
# ---------------------------------------------------------------------------------------------


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _size(p: np.ndarray) -> float:
    """Length scale of a point set for relative tolerances: its bounding-box diagonal, but at
    least 1e-4 x its largest |coordinate| (round-off in coordinates far from the origin)."""
    if len(p) == 0:
        return 0.0
    diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    return max(diag, 1e-4 * float(np.abs(p).max()))


def _as_points(verts: ArrayLike, name: str = "verts") -> np.ndarray:
    p = np.asarray(verts, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(
            f"{name} must be an array of shape [n_vertices, 2], got shape {p.shape}; "
            "pass one vertex per row as (x, y) in metres"
        )
    return p


def _dedupe(p: np.ndarray, rel_tol: float = _DUP_TOL, scale: float | None = None) -> np.ndarray:
    """Drop each vertex closer than ``rel_tol * scale`` to its cyclic predecessor.

    ``scale`` defaults to the size of ``p``. At least one vertex is always kept.
    """
    if len(p) < 2:
        return p
    tol = rel_tol * (_size(p) if scale is None else scale)
    keep = np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1) > tol
    keep[0] |= not keep.any()
    return p[keep]


def _halfplanes(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward normals [n, 2] and offsets [n] so that a CCW convex polygon is n.x <= h."""
    e = np.roll(p, -1, axis=0) - p
    length = np.linalg.norm(e, axis=1)
    normals = np.stack([e[:, 1], -e[:, 0]], axis=1) / length[:, None]
    return normals, np.einsum("ij,ij->i", normals, p)


def _clip_halfplane(p: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland-Hodgman step: keep the part of polygon ``p`` with normal.x <= offset."""
    if len(p) == 0:
        return p
    d = p @ normal - offset
    inside = d <= 0.0
    if inside.all():
        return p
    if not inside.any():
        return np.zeros((0, 2))
    q = np.roll(p, -1, axis=0)
    dq = np.roll(d, -1)
    crosses = inside != np.roll(inside, -1)
    denom = np.where(crosses, d - dq, 1.0)
    t = np.where(crosses, d / denom, 0.0)
    hit = p + t[:, None] * (q - p)
    # per edge: [start vertex if inside, crossing point if the edge crosses]
    cand = np.stack([p, hit], axis=1).reshape(-1, 2)
    keep = np.stack([inside, crosses], axis=1).reshape(-1)
    return cand[keep]


def _clip_to_halfplanes(p: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Clip polygon ``p`` by the half-planes normals.x <= offsets that any vertex violates.

    Clipping by a half-plane that no vertex violates is a no-op, and new vertices are convex
    combinations of old ones, so skipping those half-planes gives the same result.
    """
    violated = np.nonzero(((p @ normals.T) > offsets[None, :]).any(axis=0))[0]
    for k in violated:
        p = _clip_halfplane(p, normals[k], offsets[k])
        if len(p) == 0:
            break
    return p


def _finish_clip(p: np.ndarray, scale: float) -> np.ndarray:
    """Remove duplicates created by clipping; return [0, 2] if nothing of area is left."""
    if len(p) == 0:
        return np.zeros((0, 2))
    p = _dedupe(p, scale=scale)
    if len(p) < 3 or abs(polygon_area(p)) <= _AREA_TOL * scale * scale:
        return np.zeros((0, 2))
    return p


def _turning(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turning angle at each vertex (rad) and its length-based deviation (m).

    The deviation is cross(e_in, e_out) / (|e_in| + |e_out|): about the distance by which the
    vertex lies off the chord of its neighbours, positive for a left (CCW) turn. Unlike the
    sine of the turning angle, it stays meaningful next to very short edges.
    """
    e_out = np.roll(p, -1, axis=0) - p
    e_in = np.roll(e_out, 1, axis=0)
    c = _cross(e_in, e_out)
    d = np.einsum("ij,ij->i", e_in, e_out)
    length = np.linalg.norm(e_in, axis=1) + np.linalg.norm(e_out, axis=1)
    return np.arctan2(c, d), c / length


# ---------------------------------------------------------------------------------------------
# area, centroid, moments
# ---------------------------------------------------------------------------------------------


def polygon_area(verts: ArrayLike) -> float:
    """Signed area of a simple polygon (m^2), positive when the vertices run CCW.

    Args:
        verts: vertices ``[n_vertices, 2]`` (m). Fewer than three vertices give 0.
    """
    p = _as_points(verts)
    if len(p) < 3:
        return 0.0
    p = p - p.mean(axis=0)  # shoelace about a nearby point: less cancellation far from 0
    return 0.5 * float(_cross(p, np.roll(p, -1, axis=0)).sum())


def polygon_centroid(verts: ArrayLike) -> np.ndarray:
    """Area centroid ``[2]`` (m) of a simple polygon ``[n_vertices, 2]`` (either orientation).

    A polygon without area (fewer than three vertices, or all collinear) returns the mean of
    its vertices.
    """
    p = _as_points(verts)
    if len(p) == 0:
        raise ValueError("polygon_centroid needs at least one vertex")
    ref = p.mean(axis=0)
    q = p - ref
    r = np.roll(q, -1, axis=0)
    c = _cross(q, r)
    twice_area = c.sum()
    if len(p) < 3 or abs(twice_area) <= 64 * np.finfo(float).eps * np.abs(c).sum():
        return ref.copy()
    return ref + ((q + r) * c[:, None]).sum(axis=0) / (3.0 * twice_area)


def polygon_polar_moment(verts: ArrayLike) -> float:
    """Polar second moment of area about the centroid (m^4), i.e. the polar moment of inertia
    of the polygon at unit areal density (kg m^2 per kg/m^2).

    Args:
        verts: vertices ``[n_vertices, 2]`` (m) of a simple polygon. The value is positive for
            either orientation; fewer than three vertices give 0.
    """
    p = _as_points(verts)
    if len(p) < 3:
        return 0.0
    c = polygon_centroid(p)
    q = p - c
    r = np.roll(q, -1, axis=0)
    w = _cross(q, r)
    j = (w * ((q * q).sum(1) + (q * r).sum(1) + (r * r).sum(1))).sum() / 12.0
    # about the centroid the first moment vanishes, so no parallel-axis correction is needed
    return abs(float(j))


def _core(verts: ArrayLike, name: str) -> np.ndarray:
    """Core of a spheropolygon: one point, a segment of two distinct points, or a valid
    convex CCW polygon (validated, duplicates removed)."""
    p = _as_points(verts, name)
    if len(p) == 0:
        raise ValueError(f"{name} has no vertices; give at least one (a disc)")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} contains NaN or inf; check how its vertices were computed")
    p = _dedupe(p)
    if len(p) >= 3:
        return validate_polygon(p, name=name)
    return p


def spheropolygon_mass_properties(
    verts: ArrayLike, radius: float, areal_density: float
) -> tuple[float, np.ndarray, float]:
    """Exact mass, centroid and polar moment of inertia of a spheropolygon.

    The shape is the Minkowski sum of the convex core ``verts`` and a disc of ``radius``. It is
    decomposed into the core polygon, one rectangle (edge length x ``radius``) outside each
    edge, and one circular sector at each vertex whose angle is the exterior angle there (the
    sectors sum to a full disc); the pieces are combined with the parallel-axis theorem.

    Args:
        verts: core vertices ``[n_vertices, 2]`` (m): one vertex (disc), two (stadium) or a
            convex polygon of three or more (CW input is reversed, duplicates removed).
        radius: sweeping radius r >= 0 (m).
        areal_density: mass per unit area (kg/m^2), i.e. density x thickness.

    Returns:
        ``(mass, centroid, inertia)``: mass (kg), centroid ``[2]`` (m) and polar moment of
        inertia about the centroid (kg m^2).

    Raises:
        ValueError: for a negative radius or density, a core of 1-2 vertices with radius 0, or
            an invalid polygon core (see :func:`validate_polygon`).
    """
    radius = float(radius)
    rho = float(areal_density)
    if not (math.isfinite(radius) and radius >= 0.0):
        raise ValueError(f"radius must be finite and >= 0 m, got {radius}")
    if not (math.isfinite(rho) and rho >= 0.0):
        raise ValueError(f"areal_density must be finite and >= 0 kg/m^2, got {rho}")
    core = _core(verts, "verts")
    r = radius
    if len(core) < 3 and r == 0.0:
        raise ValueError(
            f"a core of {len(core)} vertex(es) with radius 0 has no area; give radius > 0"
        )
    if len(core) == 1:
        m = rho * math.pi * r * r
        return m, core[0].copy(), 0.5 * m * r * r

    ref = core.mean(axis=0)
    p = core - ref
    n = len(p)
    # core polygon: area, first moment, second moment about ref (0 for a segment)
    if n >= 3:
        a0 = polygon_area(p)
        c0 = polygon_centroid(p)
        area, first, second = a0, a0 * c0, polygon_polar_moment(p) + a0 * (c0 @ c0)
    else:
        area, first, second = 0.0, np.zeros(2), 0.0

    if r > 0.0:
        q = np.roll(p, -1, axis=0)
        e = q - p
        length = np.linalg.norm(e, axis=1)
        normal = np.stack([e[:, 1], -e[:, 0]], axis=1) / length[:, None]
        # edge rectangles, outside each edge
        a_rect = length * r
        c_rect = 0.5 * (p + q) + 0.5 * r * normal
        area += a_rect.sum()
        first = first + (a_rect[:, None] * c_rect).sum(axis=0)
        second += (a_rect * (length**2 + r * r) / 12.0 + a_rect * (c_rect * c_rect).sum(1)).sum()
        # corner sectors: apex at each vertex, from the previous edge's normal to the next's
        n_prev = np.roll(normal, 1, axis=0)
        if n == 2:
            theta = np.full(2, math.pi)
        else:
            theta = np.clip(
                np.arctan2(_cross(n_prev, normal), (n_prev * normal).sum(1)), 0.0, math.pi
            )
        phi = np.arctan2(n_prev[:, 1], n_prev[:, 0]) + 0.5 * theta
        u = np.stack([np.cos(phi), np.sin(phi)], axis=1)
        half = 0.5 * theta
        safe = np.where(half > 1e-8, half, 1.0)
        # centroid distance from the apex: 2 r sin(a) / (3 a) for half-angle a
        dist = np.where(half > 1e-8, 2.0 * r * np.sin(safe) / (3.0 * safe), 2.0 * r / 3.0)
        a_sec = 0.5 * theta * r * r
        c_sec = p + dist[:, None] * u
        area += a_sec.sum()
        first = first + (a_sec[:, None] * c_sec).sum(axis=0)
        # J about ref = J about apex + A (|v|^2 + 2 v.(c - v)), J about apex = A r^2 / 2
        second += (a_sec * (0.5 * r * r + (p * p).sum(1) + 2.0 * dist * (p * u).sum(1))).sum()

    centroid = first / area
    j = second - area * (centroid @ centroid)
    return rho * area, ref + centroid, rho * j


# ---------------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------------


def is_convex(verts: ArrayLike, tol: float = 1e-12) -> bool:
    """Whether a polygon is convex (either orientation), with non-zero area.

    Collinear vertices are allowed. A vertex may lie up to ``tol x size`` on the wrong side of
    the chord of its neighbours (round-off); the polygon must turn exactly once around.

    Args:
        verts: vertices ``[n_vertices, 2]`` (m); consecutive duplicates are ignored.
        tol: relative tolerance (dimensionless).
    """
    p = _as_points(verts)
    if not np.isfinite(p).all():
        return False
    p = _dedupe(p)
    if len(p) < 3:
        return False
    size = _size(p)
    area = polygon_area(p)
    if abs(area) <= _AREA_TOL * size * size:
        return False
    s = 1.0 if area > 0 else -1.0
    angle, deviation = _turning(p)
    if (s * deviation < -tol * size).any():
        return False
    # a spike (turn of ~pi) or a polygon that winds twice turns by more than 2 pi in total
    return abs(s * angle.sum() - _TWO_PI) < 0.5


def _segments_cross(p: np.ndarray) -> tuple[int, int] | None:
    """First pair of non-adjacent edges that properly cross, or None."""
    n = len(p)
    if n < 4:
        return None
    a = p
    b = np.roll(p, -1, axis=0)
    i, j = np.triu_indices(n, k=2)
    adjacent = (i == 0) & (j == n - 1)
    i, j = i[~adjacent], j[~adjacent]
    tol = 1e-14 * _size(p) ** 2

    def orient(o, x, y):
        return _cross(x - o, y - o)

    o1 = orient(a[i], b[i], a[j])
    o2 = orient(a[i], b[i], b[j])
    o3 = orient(a[j], b[j], a[i])
    o4 = orient(a[j], b[j], b[i])
    hit = (o1 * o2 < -tol * tol) & (o3 * o4 < -tol * tol)
    hit &= (np.abs(o1) > tol) & (np.abs(o2) > tol) & (np.abs(o3) > tol) & (np.abs(o4) > tol)
    k = np.nonzero(hit)[0]
    if len(k) == 0:
        return None
    return int(i[k[0]]), int(j[k[0]])


def validate_polygon(verts: ArrayLike, *, name: str = "polygon") -> np.ndarray:
    """Check that ``verts`` is a convex polygon and return a clean float64 CCW copy.

    Consecutive vertices closer than 1e-12 x size are merged; a CW polygon is reversed.

    Args:
        verts: vertices ``[n_vertices, 2]`` (m).
        name: what to call the polygon in error messages.

    Returns:
        Vertices ``[m, 2]`` (m), CCW, ``m <= n_vertices``.

    Raises:
        ValueError: saying what is wrong and what to do, if the array has the wrong shape,
            contains NaN/inf, has fewer than three distinct vertices, has (near-)zero area, is
            self-intersecting or is not convex.
    """
    p = _as_points(verts, name)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{name} contains NaN or inf at vertex {int(np.nonzero(bad)[0][0])}; "
            "check how its coordinates were computed (all must be finite, in metres)"
        )
    n_in = len(p)
    p = _dedupe(p)
    if len(p) < 3:
        raise ValueError(
            f"{name} has {len(p)} distinct vertices ({n_in} given); a polygon needs at least 3 "
            "non-coincident vertices (for a disc or a segment use a spheropolygon core of 1 or "
            "2 vertices with radius > 0)"
        )
    size = _size(p)
    crossing = _segments_cross(p)
    if crossing is not None:
        i, j = crossing
        raise ValueError(
            f"{name} is self-intersecting (edges {i} and {j} cross); list its vertices in order "
            "around the boundary, e.g. sorted by angle about the centroid, or use its convex hull"
        )
    area = polygon_area(p)
    if abs(area) <= _AREA_TOL * size * size:
        raise ValueError(
            f"{name} has (near-)zero area ({area:.3g} m^2 for size {size:.3g} m): its vertices "
            "are (almost) collinear; drop it or check its coordinates and units"
        )
    if area < 0:
        p = p[::-1].copy()
    angle, deviation = _turning(p)
    reflex = np.nonzero(deviation < -1e-12 * size)[0]
    if len(reflex):
        k = int(reflex[0])
        if area < 0:
            k = len(p) - 1 - k  # index in the caller's (CW) order
        raise ValueError(
            f"{name} is not convex (reflex vertex at index {k}); jaxgran particles must be "
            "convex: use its convex hull (scipy.spatial.ConvexHull) or split it into convex "
            "pieces"
        )
    if abs(angle.sum() - _TWO_PI) >= 0.5:
        raise ValueError(
            f"{name} turns {angle.sum() / _TWO_PI:.2f} times around instead of once (a spike "
            "that doubles back, or vertices listed more than once); list each vertex of the "
            "boundary once, in order"
        )
    return np.ascontiguousarray(p, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# construction, offsetting, clipping
# ---------------------------------------------------------------------------------------------


def regular_polygon(
    n: int,
    circumradius: float,
    rotation: float = 0.0,
    center: ArrayLike = (0.0, 0.0),
) -> np.ndarray:
    """Regular polygon ``[n, 2]`` (m), CCW, with vertex ``k`` at angle
    ``rotation + 2 pi k / n`` (rad) and distance ``circumradius`` (m) from ``center`` [2] (m).
    """
    n = int(n)
    if n < 3:
        raise ValueError(f"regular_polygon needs n >= 3 vertices, got {n}")
    if not circumradius > 0:
        raise ValueError(f"circumradius must be > 0 m, got {circumradius}")
    a = rotation + _TWO_PI * np.arange(n) / n
    c = np.asarray(center, dtype=np.float64)
    return c + circumradius * np.stack([np.cos(a), np.sin(a)], axis=1)


def inradius(verts: ArrayLike) -> float:
    """Radius (m) of the largest circle inside a convex polygon ``[n_vertices, 2]`` (m).

    Solved as the Chebyshev-centre linear programme (scipy HiGHS) in normalised coordinates,
    then polished to round-off by solving exactly for the optimal vertex of the programme.
    """
    from scipy.optimize import linprog

    p = validate_polygon(verts)
    c0 = p.mean(axis=0)
    s = float(np.abs(p - c0).max())
    q = (p - c0) / s
    normals, h = _halfplanes(q)
    a_ub = np.concatenate([normals, np.ones((len(q), 1))], axis=1)
    res = linprog(
        c=[0.0, 0.0, -1.0],
        A_ub=a_ub,
        b_ub=h,
        bounds=[(None, None), (None, None), (0.0, None)],
        method="highs",
    )
    if res.status != 0:  # pragma: no cover - a valid convex polygon always has a solution
        raise RuntimeError(f"inradius: linear programme failed ({res.message})")
    best = float(res.x[2])
    # the optimum sits at a vertex of the programme: three constraints active
    slack = h - a_ub @ res.x
    near = np.argsort(slack)[: min(len(q), 7)]
    for i, j, k in _triples(len(near)):
        m = a_ub[near[[i, j, k]]]
        if abs(np.linalg.det(m)) < 1e-12:
            continue
        x = np.linalg.solve(m, h[near[[i, j, k]]])
        if x[2] > best and (h - a_ub @ x >= -1e-13).all():
            best = float(x[2])
    return best * s


def _triples(n: int) -> list[tuple[int, int, int]]:
    return [(i, j, k) for i in range(n) for j in range(i + 1, n) for k in range(j + 1, n)]


def offset_polygon(verts: ArrayLike, distance: float) -> np.ndarray:
    """Inward offset (erosion) of a convex polygon.

    Each edge moves inward by ``distance`` along its normal; the result is the intersection of
    the shifted half-planes (edges that vanish are dropped), computed by clipping.

    Args:
        verts: convex polygon ``[n_vertices, 2]`` (m); CW input is reversed.
        distance: erosion distance d >= 0 (m), smaller than the inradius.

    Returns:
        Convex CCW polygon ``[m, 2]`` (m), ``m <= n_vertices``.

    Raises:
        ValueError: for a negative distance (outward offsets are not provided: sweep with a
            spheropolygon radius instead) or one that erases the polygon (d >= inradius).
    """
    distance = float(distance)
    if not math.isfinite(distance) or distance < 0.0:
        raise ValueError(
            f"offset_polygon erodes only: distance must be finite and >= 0 m, got {distance}; "
            "to dilate, give the particle a spheropolygon radius (see spheropolygon_outline)"
        )
    p = validate_polygon(verts)
    if distance == 0.0:
        return p
    size = _size(p)

    def vanish():
        r_in = inradius(p)  # only on failure: the linear programme is the slow part
        return ValueError(
            f"offset distance {distance:.6g} m erases the polygon; the largest admissible "
            f"distance is its inradius {r_in:.6g} m (use a smaller distance)"
        )

    normals, h = _halfplanes(p)
    out = p
    for k in range(len(p)):
        out = _clip_halfplane(out, normals[k], h[k] - distance)
    out = _finish_clip(out, size)
    if len(out) < 3 or abs(polygon_area(out)) <= 1e-18 * size * size:
        raise vanish()
    return out


def spheropolygon_outline(verts: ArrayLike, radius: float, n_arc: int = 8) -> np.ndarray:
    """Closed CCW outline of a spheropolygon, as a polygon ``[m, 2]`` (m).

    Edges are the core edges shifted outward by ``radius``; each corner is an arc of the
    corner's exterior angle theta sampled with ``max(1, ceil(n_arc * theta / 2 pi))`` straight
    segments, i.e. ``n_arc`` is the number of segments per full turn (a disc gives an
    ``n_arc``-gon, a convex core about ``n_arc + n_vertices`` segments in all). All outline
    points lie on the true boundary, so the outline polygon is inscribed in the shape.

    Args:
        verts: core vertices ``[n_vertices, 2]`` (m): one (disc), two (stadium) or a convex
            polygon.
        radius: sweeping radius r >= 0 (m); r = 0 returns the validated core (n >= 3).
        n_arc: segments per full turn, >= 3.
    """
    if int(n_arc) < 3:
        raise ValueError(f"n_arc must be >= 3 segments per full turn, got {n_arc}")
    n_arc = int(n_arc)
    radius = float(radius)
    if not (math.isfinite(radius) and radius >= 0.0):
        raise ValueError(f"radius must be finite and >= 0 m, got {radius}")
    core = _core(verts, "verts")
    if radius == 0.0:
        if len(core) < 3:
            raise ValueError("a core of 1 or 2 vertices needs radius > 0 to have an outline")
        return core
    if len(core) == 1:
        a = _TWO_PI * np.arange(n_arc) / n_arc
        return core[0] + radius * np.stack([np.cos(a), np.sin(a)], axis=1)
    e = np.roll(core, -1, axis=0) - core
    normal = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.linalg.norm(e, axis=1)[:, None]
    n_prev = np.roll(normal, 1, axis=0)
    if len(core) == 2:
        theta = np.full(2, math.pi)
    else:
        theta = np.clip(np.arctan2(_cross(n_prev, normal), (n_prev * normal).sum(1)), 0, math.pi)
    phi0 = np.arctan2(n_prev[:, 1], n_prev[:, 0])
    pts = []
    for k in range(len(core)):
        if theta[k] <= 1e-12:
            segs = 0
        else:
            segs = max(1, math.ceil(n_arc * theta[k] / _TWO_PI - 1e-9))
        a = phi0[k] + theta[k] * np.arange(segs + 1) / max(segs, 1)
        pts.append(core[k] + radius * np.stack([np.cos(a), np.sin(a)], axis=1))
    return _dedupe(np.concatenate(pts, axis=0))


def clip_convex(poly: ArrayLike, clip: ArrayLike) -> np.ndarray:
    """Intersection of two convex polygons (Sutherland-Hodgman).

    Args:
        poly: convex polygon ``[n, 2]`` (m) to be clipped.
        clip: convex clip polygon ``[k, 2]`` (m).

    Returns:
        Convex CCW polygon ``[m, 2]`` (m), or an empty ``[0, 2]`` array when the intersection
        has no area.
    """
    p = validate_polygon(poly, name="poly")
    c = validate_polygon(clip, name="clip")
    normals, h = _halfplanes(c)
    return _finish_clip(_clip_to_halfplanes(p, normals, h), max(_size(p), _size(c)))


def clip_halfplanes(poly: ArrayLike, normals: ArrayLike, offsets: ArrayLike) -> np.ndarray:
    """Part of a convex polygon inside the half-planes ``normals[k] . x <= offsets[k]``.

    Args:
        poly: convex CCW polygon ``[n, 2]`` (m).
        normals: outward normals ``[k, 2]`` of the half-planes (any length > 0).
        offsets: ``[k]`` (m times the normal's length).

    Returns:
        Convex CCW polygon ``[m, 2]`` (m), or ``[0, 2]`` when nothing of area is left.
    """
    p = _as_points(poly, "poly")
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    off = np.asarray(offsets, dtype=np.float64).reshape(-1)
    if len(nrm) != len(off):
        raise ValueError(f"{len(nrm)} normals but {len(off)} offsets")
    if not len(nrm):
        return p
    if not (np.isfinite(nrm).all() and np.isfinite(off).all()):
        raise ValueError("half-plane normals and offsets must be finite")
    return _finish_clip(_clip_to_halfplanes(p, nrm, off), _size(p))


def halfplane_clip_areas(poly: ArrayLike, normals: ArrayLike, offsets: ArrayLike) -> np.ndarray:
    """Area of a convex polygon inside each half-plane ``normals[k] . x <= offsets[k]`` (m^2).

    Vectorised over the half-planes (one shoelace sum per half-plane over the kept part of
    every edge, closed by the chord from the exit point to the entry point), for searching
    many candidate cuts at once; :func:`clip_halfplanes` returns the polygon of one.

    Args:
        poly: convex CCW polygon ``[n, 2]`` (m).
        normals: ``[k, 2]`` (any length > 0).
        offsets: ``[k]`` (m times the normal's length).

    Returns:
        ``[k]`` areas (m^2), between 0 and the polygon's area.
    """
    p = _as_points(poly, "poly")
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    off = np.asarray(offsets, dtype=np.float64).reshape(-1)
    if len(nrm) != len(off):
        raise ValueError(f"{len(nrm)} normals but {len(off)} offsets")
    c = p.mean(axis=0)  # shoelace about a point inside: no cancellation of large terms
    p = p - c
    off = off - nrm @ c
    q = np.roll(p, -1, axis=0)
    d0 = p @ nrm.T - off[None, :]  # [n, k], <= 0 inside
    d1 = np.roll(d0, -1, axis=0)
    in0, in1 = d0 <= 0.0, d1 <= 0.0
    crosses = in0 != in1
    t = np.where(crosses, d0 / np.where(crosses, d0 - d1, 1.0), 0.0)
    hit = p[:, None, :] + t[..., None] * (q - p)[:, None, :]  # [n, k, 2]
    a = np.where(in0[..., None], p[:, None, :], hit)
    b = np.where(in1[..., None], q[:, None, :], hit)
    edges = np.where(in0 | in1, a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], 0.0).sum(0)
    # the chord closes the kept part: from the exit point (in -> out) to the entry (out -> in)
    exit_ = np.where((in0 & ~in1)[..., None], hit, 0.0).sum(0)
    entry = np.where((~in0 & in1)[..., None], hit, 0.0).sum(0)
    chord = exit_[:, 0] * entry[:, 1] - exit_[:, 1] * entry[:, 0]
    return np.clip(0.5 * (edges + chord), 0.0, None)


def point_in_convex_polygon(
    points: ArrayLike, verts: ArrayLike, *, tol: float | None = None
) -> np.ndarray:
    """Which points lie in a closed convex polygon (boundary included).

    Args:
        points: query points ``[k, 2]`` (m) (a single point ``[2]`` is accepted).
        verts: convex polygon ``[n, 2]`` (m), either orientation.
        tol: points up to ``tol`` (m) outside still count as inside; default ``1e-12 x`` the
            polygon's size, so that the polygon's own vertices test inside despite round-off.

    Returns:
        ``bool[k]``.
    """
    x = np.atleast_2d(np.asarray(points, dtype=np.float64))
    p = validate_polygon(verts)
    if tol is None:
        tol = 1e-12 * _size(p)
    normals, h = _halfplanes(p)
    return ((x @ normals.T) <= h[None, :] + tol).all(axis=1)


def circumradius(verts: ArrayLike) -> float:
    """Largest distance (m) from the area centroid to a vertex of ``verts`` ``[n, 2]`` (m)."""
    p = _as_points(verts)
    return float(np.linalg.norm(p - polygon_centroid(p), axis=1).max())


# ---------------------------------------------------------------------------------------------
# Voronoi tessellations and their shared edges
# ---------------------------------------------------------------------------------------------


def _voronoi_cells(
    seeds: np.ndarray,
    extra: np.ndarray,
    normals: np.ndarray,
    offsets: np.ndarray,
    scale: float,
) -> list[np.ndarray]:
    """Voronoi cells of ``seeds`` (with helper points ``extra``), clipped to a convex region."""
    from scipy.spatial import Voronoi

    vor = Voronoi(np.concatenate([seeds, extra], axis=0))
    cells = []
    for i in range(len(seeds)):
        region = vor.regions[vor.point_region[i]]
        if len(region) < 3 or -1 in region:
            raise RuntimeError(
                f"Voronoi cell of seed {i} is unbounded; this should not happen with mirrored "
                "seeds, please report it with the seed and n_cells used"
            )
        v = vor.vertices[region]
        # order CCW about the seed (the cell is convex and contains its seed)
        d = v - seeds[i]
        v = v[np.argsort(np.arctan2(d[:, 1], d[:, 0]))]
        cell = _finish_clip(_clip_to_halfplanes(v, normals, offsets), scale)
        if len(cell) == 0:
            raise RuntimeError(f"Voronoi cell of seed {i} is empty after clipping")
        cells.append(cell)
    return cells


def _lloyd(seeds, make_cells, iterations):
    cells = make_cells(seeds)
    for _ in range(int(iterations)):
        seeds = np.array([polygon_centroid(c) for c in cells])
        cells = make_cells(seeds)
    return cells


def voronoi_rectangle(
    width: float,
    height: float,
    n_cells: int,
    seed: int | np.random.Generator,
    *,
    origin: ArrayLike = (0.0, 0.0),
    lloyd_iterations: int = 0,
) -> list[np.ndarray]:
    """Random Voronoi tessellation of the rectangle ``origin + [0, width] x [0, height]``.

    Seeds are uniform in the rectangle and mirrored across its four sides, so every cell of an
    original seed is bounded and its boundary on the rectangle is exact; cells are then clipped
    to the rectangle to remove round-off. Each Lloyd iteration moves the seeds to their cells'
    centroids, which makes the cells more uniform.

    Args:
        width, height: rectangle size (m).
        n_cells: number of cells (>= 1).
        seed: seed for ``numpy.random.default_rng`` (same seed, same tessellation).
        origin: lower-left corner ``[2]`` (m).
        lloyd_iterations: number of Lloyd relaxation steps (>= 0).

    Returns:
        ``n_cells`` convex CCW polygons ``[m_i, 2]`` (m) tiling the rectangle.
    """
    if not (width > 0 and height > 0):
        raise ValueError(f"width and height must be > 0 m, got {width} x {height}")
    if int(n_cells) < 1:
        raise ValueError(f"n_cells must be >= 1, got {n_cells}")
    n_cells = int(n_cells)
    o = np.asarray(origin, dtype=np.float64)
    box = o + np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]])
    if n_cells == 1:
        return [box]
    rng = np.random.default_rng(seed)
    seeds = o + rng.random((n_cells, 2)) * np.array([width, height])
    normals, h = _halfplanes(box)
    scale = _size(box)
    x0, y0 = o
    x1, y1 = o + np.array([width, height])

    def make_cells(s):
        mirrors = [
            np.stack([2 * x0 - s[:, 0], s[:, 1]], axis=1),
            np.stack([2 * x1 - s[:, 0], s[:, 1]], axis=1),
            np.stack([s[:, 0], 2 * y0 - s[:, 1]], axis=1),
            np.stack([s[:, 0], 2 * y1 - s[:, 1]], axis=1),
        ]
        return _voronoi_cells(s, np.concatenate(mirrors), normals, h, scale)

    return _lloyd(seeds, make_cells, lloyd_iterations)


def voronoi_disc(
    radius: float,
    n_cells: int,
    seed: int | np.random.Generator,
    *,
    center: ArrayLike = (0.0, 0.0),
    n_boundary: int = 64,
    lloyd_iterations: int = 0,
) -> list[np.ndarray]:
    """Random Voronoi tessellation of a disc, approximated by a regular ``n_boundary``-gon.

    The region is ``regular_polygon(n_boundary, radius, center=center)``. Seeds are uniform in
    it and mirrored radially across the circle (a seed at distance rho from the centre gets a
    mirror at 2 radius - rho), plus a ring of far guard points, so all cells of original seeds
    are bounded; neither changes the tessellation inside the disc. Cells are then clipped to
    the polygon.

    Args:
        radius: disc radius (m), the circumradius of the boundary polygon.
        n_cells: number of cells (>= 1).
        seed: seed for ``numpy.random.default_rng``.
        center: disc centre ``[2]`` (m).
        n_boundary: vertices of the boundary polygon (>= 3).
        lloyd_iterations: number of Lloyd relaxation steps (>= 0).

    Returns:
        ``n_cells`` convex CCW polygons ``[m_i, 2]`` (m) tiling the boundary polygon.
    """
    if not radius > 0:
        raise ValueError(f"radius must be > 0 m, got {radius}")
    if int(n_cells) < 1:
        raise ValueError(f"n_cells must be >= 1, got {n_cells}")
    n_cells = int(n_cells)
    c = np.asarray(center, dtype=np.float64)
    region = regular_polygon(n_boundary, radius, center=c)
    if n_cells == 1:
        return [region]
    rng = np.random.default_rng(seed)
    normals, h = _halfplanes(region)
    scale = _size(region)
    seeds = np.zeros((0, 2))
    while len(seeds) < n_cells:  # rejection sampling, uniform in the polygon
        r = radius * np.sqrt(rng.random(2 * n_cells))
        a = _TWO_PI * rng.random(2 * n_cells)
        cand = c + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        cand = cand[((cand @ normals.T) < h[None, :]).all(axis=1)]
        seeds = np.concatenate([seeds, cand])[:n_cells]
    guard_angle = _TWO_PI * np.arange(8) / 8
    guards = c + 4.0 * radius * np.stack([np.cos(guard_angle), np.sin(guard_angle)], axis=1)

    def make_cells(s):
        d = s - c
        rho = np.linalg.norm(d, axis=1)
        ok = rho > 1e-9 * radius
        mirrors = c + d[ok] * ((2.0 * radius - rho[ok]) / rho[ok])[:, None]
        return _voronoi_cells(s, np.concatenate([mirrors, guards]), normals, h, scale)

    return _lloyd(seeds, make_cells, lloyd_iterations)


def shared_edges(
    cells: list[ArrayLike], tol: float = 1e-9
) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Pairs of cells of a tessellation that share a boundary segment of positive length.

    Works edge against edge (an edge of one cell may span several edges of its neighbour, so
    T-junctions are fine): two edges are shared where both endpoints of one lie within
    ``tol x size`` of the other's line and their projections overlap by more than that. The
    pieces found for one pair are merged into one segment (convex cells share at most one).
    Candidate pairs come from a k-d tree on cell centres (5000 Voronoi cells take about
    half a second).

    Args:
        cells: convex polygons ``[m_i, 2]`` (m), CCW, e.g. from :func:`voronoi_rectangle`.
        tol: relative tolerance; ``size`` is the bounding-box diagonal of all cells.

    Returns:
        ``(i, j, p, q)`` with ``i < j`` and the shared segment's endpoints ``p``, ``q`` ``[2]``
        (m), running CCW along cell ``i`` (so CW along cell ``j``); sorted by ``(i, j)``.
    """
    from scipy.spatial import cKDTree

    if len(cells) < 2:
        return []
    verts, n_verts = pad_polygons(cells)
    V = verts.shape[1]
    k = np.arange(V)
    real = k[None, :] < n_verts[:, None]
    all_pts = verts[real]
    lo, hi = all_pts.min(axis=0), all_pts.max(axis=0)
    atol = tol * float(np.linalg.norm(hi - lo))
    centre = np.where(real[..., None], verts, 0.0).sum(1) / np.maximum(n_verts, 1)[:, None]
    reach = np.where(real, np.linalg.norm(verts - centre[:, None, :], axis=2), 0.0).max(axis=1)
    tree = cKDTree(centre)
    pairs = tree.query_pairs(2.0 * reach.max() + 2.0 * atol, output_type="ndarray")
    if len(pairs) == 0:
        return []
    gap = np.linalg.norm(centre[pairs[:, 0]] - centre[pairs[:, 1]], axis=1)
    pairs = pairs[gap <= reach[pairs[:, 0]] + reach[pairs[:, 1]] + 2.0 * atol]
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    # edges of every cell: start a [P, V, 2], unit direction u, length, validity
    nxt = np.where(k[None, :] + 1 < n_verts[:, None], k[None, :] + 1, 0)
    a = verts
    b = np.take_along_axis(verts, nxt[..., None], axis=1)
    length = np.linalg.norm(b - a, axis=2)
    valid = real & (length > atol)
    u = (b - a) / np.where(length > 0, length, 1.0)[..., None]

    found_pair, found_p, found_q = [], [], []
    chunk = max(1, 2_000_000 // (V * V))
    for s in range(0, len(pairs), chunk):
        pi, pj = pairs[s : s + chunk, 0], pairs[s : s + chunk, 1]
        ai, ui, li = a[pi][:, :, None, :], u[pi][:, :, None, :], length[pi][:, :, None]
        aj, bj = a[pj][:, None, :, :], b[pj][:, None, :, :]
        d0 = _cross(ui, aj - ai)
        d1 = _cross(ui, bj - ai)
        t0 = (ui * (aj - ai)).sum(-1)
        t1 = (ui * (bj - ai)).sum(-1)
        lo_t = np.maximum(0.0, np.minimum(t0, t1))
        hi_t = np.minimum(li, np.maximum(t0, t1))
        hit = (np.abs(d0) <= atol) & (np.abs(d1) <= atol) & (hi_t - lo_t > atol)
        hit &= valid[pi][:, :, None] & valid[pj][:, None, :]
        w, ei, _ = np.nonzero(hit)
        base = ai[w, ei, 0]
        dirn = ui[w, ei, 0]
        found_pair.append(s + w)
        found_p.append(base + lo_t[hit][:, None] * dirn)
        found_q.append(base + hi_t[hit][:, None] * dirn)
    which = np.concatenate(found_pair)
    p_all = np.concatenate(found_p)
    q_all = np.concatenate(found_q)
    out = []
    starts = np.nonzero(np.r_[True, which[1:] != which[:-1]])[0]
    ends = np.r_[starts[1:], len(which)]
    for s0, s1 in zip(starts, ends, strict=True):
        i, j = (int(x) for x in pairs[which[s0]])
        if s1 - s0 == 1:
            out.append((i, j, p_all[s0].copy(), q_all[s0].copy()))
            continue
        # several collinear pieces (a cell with collinear vertices): merge into one segment
        pts = np.concatenate([p_all[s0:s1], q_all[s0:s1]])
        dirn = q_all[s0] - p_all[s0]
        t = (pts - p_all[s0]) @ dirn
        out.append((i, j, pts[np.argmin(t)].copy(), pts[np.argmax(t)].copy()))
    return out


# ---------------------------------------------------------------------------------------------
# padded arrays and jax twins
# ---------------------------------------------------------------------------------------------


def pad_polygons(
    polys: list[ArrayLike], n_vertex_capacity: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Stack polygons into fixed-shape arrays, padding with copies of each last real vertex.

    Args:
        polys: ``P`` polygons ``[n_i, 2]`` (m).
        n_vertex_capacity: number of vertex slots ``V``; default ``max(n_i)``.

    Returns:
        ``(verts, n_verts)``: ``verts [P, V, 2]`` (m, float64) and ``n_verts [P]`` (int32).

    Raises:
        ValueError: if a polygon has more vertices than ``n_vertex_capacity``.
    """
    arrays = [_as_points(p, f"polys[{i}]") for i, p in enumerate(polys)]
    counts = np.array([len(p) for p in arrays], dtype=np.int32)
    needed = int(counts.max()) if len(counts) else 0
    if n_vertex_capacity is None:
        cap = needed
    else:
        cap = int(n_vertex_capacity)
        if needed > cap:
            worst = int(np.argmax(counts))
            raise ValueError(
                f"vertex capacity {cap} exceeded: polygon {worst} has {needed} vertices; rerun "
                f"with n_vertex_capacity>={needed}"
            )
    verts = np.zeros((len(arrays), cap, 2))
    for i, p in enumerate(arrays):
        if len(p):
            verts[i, : len(p)] = p
            verts[i, len(p) :] = p[-1]
    return verts, counts


def _padded_cross(verts: jnp.ndarray, n_verts: jnp.ndarray):
    """Edge terms of a padded polygon, relative to vertex 0: (v, w, cross, mask)."""
    V = verts.shape[-2]
    k = jnp.arange(V)
    n = jnp.asarray(n_verts)[..., None]
    mask = k < n
    nxt = jnp.broadcast_to(jnp.where(k + 1 < n, k + 1, 0), verts.shape[:-1])
    v = verts - verts[..., :1, :]  # translation invariant: less cancellation far from 0
    w = jnp.take_along_axis(v, nxt[..., None], axis=-2)
    cross = jnp.where(mask, v[..., 0] * w[..., 1] - v[..., 1] * w[..., 0], 0.0)
    return v, w, cross, mask


def polygon_area_padded(verts: jnp.ndarray, n_verts: jnp.ndarray) -> jnp.ndarray:
    """Signed area (m^2, CCW positive) of padded polygons; jit- and gradient-safe.

    Args:
        verts: ``[..., V, 2]`` (m); slots ``k >= n_verts`` are ignored.
        n_verts: ``[...]`` number of real vertices (polygons with < 3 give 0).

    Returns:
        ``[...]`` (m^2).
    """
    _, _, cross, _ = _padded_cross(verts, n_verts)
    return 0.5 * cross.sum(-1)


def polygon_centroid_padded(verts: jnp.ndarray, n_verts: jnp.ndarray) -> jnp.ndarray:
    """Area centroid (m) of padded polygons; jit- and gradient-safe.

    Polygons without area (fewer than three vertices, collinear, or all padding) give the mean
    of their real vertices (vertex 0 for ``n_verts == 0``), with finite gradients.

    Args:
        verts: ``[..., V, 2]`` (m); slots ``k >= n_verts`` are ignored.
        n_verts: ``[...]`` number of real vertices.

    Returns:
        ``[..., 2]`` (m).
    """
    v, w, cross, mask = _padded_cross(verts, n_verts)
    twice_area = cross.sum(-1)
    eps = jnp.finfo(verts.dtype).eps
    ok = jnp.abs(twice_area) > 64 * eps * jnp.abs(cross).sum(-1)
    safe = jnp.where(ok, twice_area, 1.0)  # double-where: no NaN gradient when area is 0
    moment = ((v + w) * cross[..., None]).sum(-2)
    c_area = moment / (3.0 * safe[..., None])
    count = jnp.maximum(mask.sum(-1), 1)
    c_mean = jnp.where(mask[..., None], v, 0.0).sum(-2) / count[..., None]
    return verts[..., 0, :] + jnp.where(ok[..., None], c_area, c_mean)
