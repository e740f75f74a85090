"""Stress field inside each particle by the boundary element method (BSEM), and psi.

The particle is a spheropolygon: a convex core polygon dilated by a disc of radius ``r`` (a
core of one vertex is a disc). It is treated as a linear elastic body loaded only by its
contact forces (a pure traction problem, paper 000 Sec. II.A), in plane stress or plane
strain, per unit thickness divided by ``thickness``.

Method (paper 000 Sec. II.A, Eq. 1; Brebbia & Dominguez, *Boundary Elements*, ch. 5):

* The outline is cut into ``N`` straight constant elements, spread over the edges and corner
  arcs in proportion to length, with their end points on the outline (arcs become chords).
* Kelvin fundamental solution, collocation at element midpoints (there c = I/2 and the own
  element's principal value vanishes, so H_ii = I/2), analytic G_ii. All other element
  integrals (U*, T*, and Somigliana's D and S) are taken in closed form over the straight
  elements, so they are exact however close a point is to the boundary and cost one
  evaluation per (point, element) pair.
* Rigid-body modes: the system is bordered with three Lagrange constraints (zero mean
  displacement and rotation over the boundary), which also absorb any load imbalance, so
  results do not depend on the length unit and no loaded element is ever pinned.
* Interior stress by Somigliana's identity (D and S kernels), on a regular grid of sample
  points kept at least 1.5 element lengths inside the boundary, where constant elements are
  accurate (closer, the piecewise constant displacement spoils the S integral).
* Everything that depends only on the shape is folded into one body-frame operator per particle,
  built once (``build_operators``): stress at the sample points per unit contact force on each
  element. A check (``psi_batched``) is then a gather of the loaded columns and a small
  contraction for all particles at once.

Contact forces (``load_model``):

* ``"flamant"`` (default): the singular part of a point force is taken in closed form, the
  Flamant radial field sigma = -(2 / pi t rho) (F . e_rho) e_rho (x) e_rho of a force at the edge
  of a half-plane (exact for any supporting line through the contact, so for any convex body);
  the BEM only solves for the smooth remainder, whose tractions are -sigma_F . n on the other
  elements. The field near contacts is then that of a point force (psi -> infinity at the
  contact, as the connection-point search expects), and the error is that of a smooth
  traction problem (Brazilian disc, N = 128: max 0.1 % of 2P/(pi D t) over the sample grid).
* ``"element"`` (paper 000, Fig. 1c): the force is spread as a uniform traction F / (L_e t) over
  the loaded element. Much less accurate near the load (Brazilian disc, N = 128: max 15 %,
  4.5 % at half a radius from the load).

In both models a contact is shared linearly between the two elements whose midpoints bracket
its projection on the element polygon (a "hat" split), so stress is continuous as a contact
slides along the boundary; a contact at a midpoint loads that element alone. The Flamant part
acts at the contact point itself, on the true outline. Before the solve the forces of each particle
are equilibrated by the minimum-norm correction (resultant removed equally, moment by a
tangential rotation field about the mean contact point), skipped with fewer than two contacts.

Screening (``psi_bound``, ``psi_bound_flat``, ``screen``): psi is a norm of the stress, so by
the triangle inequality over contacts the largest psi of a particle is at most a sum over its
contacts of |F| times per-element numbers tabulated at build time for a few angular groups of
sample points (the operator block's norm; for the Flamant part the distances from the
group to the element's chord). That bound reads a few numbers per contact instead of the
[2, M, 3] blocks; particles whose bound is below the threshold cannot reach it anywhere, and
only the others need the field. The bound exceeds the field by a factor of about 2 (median
1.8 on a settled pile, ``benchmarks/SCREENING_RESULTS.md``).

psi (paper 000, Eq. 2) is the strain-energy equivalent stress psi = sqrt(2 E W); uniaxially
psi = |sigma|. In-plane stresses of a traction-loaded simply connected body do not depend on E
or nu (Michell), so no Young's modulus is needed anywhere; nu enters the kernels only through
discretisation error, and psi through sigma_zz (plane strain) and Eq. 2.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from numpy.typing import ArrayLike

from .geometry import polygon_area_padded, polygon_centroid_padded, validate_polygon

Plane = Literal["stress", "strain"]
LoadModel = Literal["flamant", "element"]

PLANES = ("stress", "strain")
LOAD_MODELS = ("flamant", "element")
_TWO_PI = 2.0 * math.pi
# Sample points stay this many (largest) element lengths inside the boundary (PHYSICS A2:
# errors are 0.1-0.2 % beyond 1.3 h, several % at 0.6 h).
_MARGIN = 1.5
# Grid search for sample points: candidate offsets -G..G with G = ceil(_GRID_REACH sqrt(M)).
_GRID_REACH = 2.0
# Angular groups of sample points in the screening bound (psi_bound): more groups, a tighter
# bound and a larger table [P, N, G].
_SCREEN_GROUPS = 8
# Force directions (over a half turn) at which the screening tables sample each element's
# response; a force between two of them is bounded from those two (``_direction_weights``),
# within 1 / cos(pi / (2 K)) of its own direction's value (8 % at K = 4).
_SCREEN_DIRECTIONS = 4
# Positions along each element's chord at which the Flamant table places the load; a contact
# between them (or off the chord) is covered by the Lipschitz margin of ``_flamant_near``.
_CHORD_SAMPLES = 8


def _dot(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Sum of ``a * b`` over the last axis, written out term by term for short axes: XLA
    then fuses it with the element-wise work around it (a reduction over an axis of 2-9
    starts a kernel of its own on CPU, and the bounds' per-contact code was mostly such
    kernels). Not for operands that are gathers used again elsewhere: the fusion then
    repeats the gather for every term (``psi_batched`` took 2.6 times as long with it in
    ``_contact_elements``)."""
    n = jnp.shape(a)[-1]
    if n > 16:
        return jnp.sum(a * b, axis=-1)
    out = a[..., 0] * b[..., 0]
    for k in range(1, n):
        out = out + a[..., k] * b[..., k]
    return out


def _safe_norm(v: jnp.ndarray, fused: bool = False) -> jnp.ndarray:
    """|v| over the last axis with a finite gradient at v = 0 (double where); ``fused``:
    the sum of squares written out (``_dot``), for the bounds' per-contact code (where a
    gathered ``v`` is used once; elsewhere XLA would repeat the gather in each term)."""
    s = _dot(v, v) if fused else jnp.sum(v * v, axis=-1)
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)


def _safe_div(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    ok = b != 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def _cross2(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _perp(a: jnp.ndarray) -> jnp.ndarray:
    """z x a (rotation by +90 degrees)."""
    return jnp.stack([-a[..., 1], a[..., 0]], axis=-1)


def _kernel_poisson(poisson_ratio, plane: str):
    """Poisson ratio used in the plane-strain kernels: nu, or nu / (1 + nu) in plane stress."""
    return poisson_ratio / (1.0 + poisson_ratio) if plane == "stress" else poisson_ratio


# ---------------------------------------------------------------------------------------------
# geometry of one particle: outline, boundary elements, depth
# ---------------------------------------------------------------------------------------------


def _core_edges(verts: jnp.ndarray, n_verts):
    """Edges of a padded core polygon: (vector, length, outward normal, real mask).

    Edge k runs from vertex k to vertex k + 1 (0 for the last real one); padded and zero-length
    edges get length 0 and the normal of the last edge before them that has a length.
    """
    V = verts.shape[0]
    k = jnp.arange(V)
    n = jnp.maximum(n_verts, 1)
    real = k < n
    nxt = jnp.where(k + 1 < n, k + 1, 0)
    vec = jnp.where(real[:, None], verts[nxt] - verts, 0.0)
    length = _safe_norm(vec)
    scale = jnp.max(jnp.abs(verts - verts[0]))
    has_len = length > 1e-12 * jnp.maximum(scale, jnp.finfo(verts.dtype).tiny)
    tangent = vec / jnp.where(has_len, length, 1.0)[:, None]
    normal = jnp.stack([tangent[:, 1], -tangent[:, 0]], axis=-1)
    last = lax.cummax(jnp.where(has_len, k, -1))
    last = jnp.where(last >= 0, last, jnp.max(jnp.where(has_len, k, -1)))
    normal = normal[jnp.maximum(last, 0)]
    return vec, jnp.where(has_len, length, 0.0), normal, real


def _outline_segments(verts: jnp.ndarray, n_verts, radius, n_elements: int):
    """Outline as 2V segments (corner arc k, then edge k) and a point function on them."""
    V = verts.shape[0]
    k = jnp.arange(V)
    n = jnp.maximum(n_verts, 1)
    vec, edge_len, normal, real = _core_edges(verts, n_verts)
    prev = jnp.where(k == 0, n - 1, k - 1)
    n_prev = normal[prev]
    sweep = jnp.arctan2(jnp.abs(_cross2(n_prev, normal)), jnp.sum(n_prev * normal, -1))
    is_disc = n == 1
    sweep = jnp.where(is_disc, jnp.where(k == 0, _TWO_PI, 0.0), jnp.where(real, sweep, 0.0))
    # a disc starts half an element below angle 0, so midpoints sit at 2 pi j / N (loads at
    # the poles then fall on element midpoints when N is a multiple of 4)
    phi0 = jnp.where(is_disc, -math.pi / n_elements, jnp.arctan2(n_prev[:, 1], n_prev[:, 0]))
    arc_len = radius * sweep
    seg_len = jnp.stack([arc_len, edge_len], axis=1).reshape(-1)

    def point(seg, s):
        vi = seg // 2
        ang = phi0[vi] + s * sweep[vi]
        on_arc = verts[vi] + radius * jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=-1)
        on_edge = verts[vi] + radius * normal[vi] + s[..., None] * vec[vi]
        return jnp.where((seg % 2 == 1)[..., None], on_edge, on_arc)

    return seg_len, point


def _allocate(seg_len: jnp.ndarray, n_elements: int) -> jnp.ndarray:
    """Elements per segment (sums to N), minimising the longest element.

    Greedy (D'Hondt-like): each element goes to the segment whose elements are currently the
    longest, so every segment longer than 1e-3 of a nominal element gets at least one element
    when N allows (polygon corners and arc ends become element ends) and the longest element
    is as short as the split into segments permits. Shorter pieces are cut by a chord.
    """
    eligible = seg_len > 1e-3 * jnp.sum(seg_len) / n_elements

    def give(_, count):
        size = jnp.where(eligible, seg_len / jnp.maximum(count, 1), -1.0)
        size = jnp.where(eligible & (count == 0), jnp.inf, size)
        return count.at[jnp.argmax(size)].add(1)

    return lax.fori_loop(0, n_elements, give, jnp.zeros(seg_len.shape, jnp.int32))


def _elements_padded(verts: jnp.ndarray, n_verts, radius, n_elements: int):
    """Nodes ``[N, 2]`` of the element polygon: element e runs from node e to node e + 1."""
    seg_len, point = _outline_segments(verts, n_verts, radius, n_elements)
    count = _allocate(seg_len, n_elements)
    cum = jnp.cumsum(count)
    e = jnp.arange(n_elements)
    seg = jnp.sum(cum[None, :] <= e[:, None], axis=1)  # segment of each element
    start = cum[seg] - count[seg]
    s = (e - start).astype(verts.dtype) / jnp.maximum(count[seg], 1).astype(verts.dtype)
    return point(seg, s)


def _element_geometry(nodes: jnp.ndarray):
    """(start, end, midpoint, length, outward normal) of the closed element polygon."""
    a = nodes
    b = jnp.roll(nodes, -1, axis=0)
    d = b - a
    length = _safe_norm(d)
    normal = jnp.stack([d[:, 1], -d[:, 0]], axis=-1) / jnp.where(length > 0, length, 1.0)[:, None]
    return a, b, 0.5 * (a + b), length, normal


def _boundary_elements(verts: ArrayLike, radius, n_elements: int, n_verts=None):
    """Constant boundary elements on the outline of a spheropolygon.

    Args:
        verts: core vertices ``[V, 2]`` (m), CCW, convex; slots ``k >= n_verts`` repeat the last
            real vertex.
        radius: sweeping radius (m); 0 gives the polygon itself.
        n_elements: number of elements ``N`` (static).
        n_verts: number of real vertices (default ``V``); 1 is a disc of ``radius``.

    Returns:
        ``(midpoints [N, 2], endpoints [N, 2, 2], lengths [N], normals [N, 2])`` (m, m, m, -),
        CCW, normals outward.
    """
    verts = np.asarray(verts, float)
    n_verts = len(verts) if n_verts is None else n_verts
    verts = jnp.asarray(_pad_rows(verts, _bucket(len(verts), 8)))  # fewer shapes to compile
    return _boundary_elements_jit(verts, n_verts, jnp.asarray(radius, verts.dtype), n_elements)


@jax.jit(static_argnames=("n_elements",))
def _boundary_elements_jit(verts, n_verts, radius, n_elements):
    a, b, mid, length, normal = _element_geometry(
        _elements_padded(verts, n_verts, radius, n_elements)
    )
    return mid, jnp.stack([a, b], axis=1), length, normal


def _outline_depth(x: jnp.ndarray, verts: jnp.ndarray, n_verts, radius) -> jnp.ndarray:
    """Distance (m) of points ``[Q, 2]`` inside the spheropolygon outline (negative outside)."""
    vec, edge_len, _, real = _core_edges(verts, n_verts)
    # edges first, points last (vectorises over the points)
    rx = x[:, 0] - verts[:, 0, None]  # [V, Q]
    ry = x[:, 1] - verts[:, 1, None]
    ex, ey = vec[:, 0, None], vec[:, 1, None]
    t = jnp.clip(_safe_div(rx * ex + ry * ey, (edge_len**2)[:, None]), 0.0, 1.0)
    dist2 = jnp.min(jnp.where(real[:, None], (rx - t * ex) ** 2 + (ry - t * ey) ** 2, jnp.inf), 0)
    dist = jnp.sqrt(dist2)
    left = jnp.all(jnp.where((real & (edge_len > 0))[:, None], ex * ry - ey * rx >= 0, True), 0)
    inside_core = left & (jnp.sum(edge_len > 0) >= 3)
    return radius + jnp.where(inside_core, dist, -dist)


def _outline_area(verts: jnp.ndarray, n_verts, radius) -> jnp.ndarray:
    """Area (m^2) of a spheropolygon: core + radius x perimeter + pi radius^2 (Steiner)."""
    _, edge_len, _, _ = _core_edges(verts, n_verts)
    core = jnp.where(n_verts >= 3, polygon_area_padded(verts, n_verts), 0.0)
    return core + radius * jnp.sum(edge_len) + math.pi * radius**2


def _grid(anchor, spacing, reach: int):
    """Offsets -reach..reach in both directions: points ``[Q, 2]`` (m) and indices ``[Q, 2]``."""
    offs = jnp.arange(-reach, reach + 1)
    ij = jnp.stack(jnp.meshgrid(offs, offs, indexing="ij"), axis=-1).reshape(-1, 2)
    return anchor + spacing * ij.astype(anchor.dtype), ij


def _sample_grid(verts, n_verts, radius, margin, n_points: int):
    """At most ``n_points`` grid points with depth >= margin, as many as the grid allows.

    The grid is anchored at the core centroid; its spacing is tuned so that the count is close
    to, never above, ``n_points``. Returns (points [M, 2], ij [M, 2], mask [M], spacing).
    """
    reach = int(math.ceil(_GRID_REACH * math.sqrt(n_points)))
    anchor = polygon_centroid_padded(verts, n_verts)
    real = jnp.arange(verts.shape[0]) < jnp.maximum(n_verts, 1)
    extent = jnp.max(jnp.where(real, _safe_norm(verts - anchor), 0.0)) + radius
    s_min = extent / reach  # the candidate grid must cover the particle

    def count(s):
        pts, _ = _grid(anchor, s, reach)
        return jnp.sum(_outline_depth(pts, verts, n_verts, radius) >= margin)

    area = _outline_area(verts, n_verts, radius)
    per = 2.0 * jnp.sqrt(math.pi * area)
    s = jnp.maximum(jnp.sqrt(jnp.maximum(area - per * margin, 0.05 * area) / n_points), s_min)

    def refine(_, s):
        c = count(s).astype(s.dtype)
        return jnp.maximum(s * jnp.sqrt(jnp.maximum(c, 1.0) / n_points), s_min)

    s = lax.fori_loop(0, 4, refine, s)
    s = lax.while_loop(lambda s: count(s) > n_points, lambda s: s * 1.02, s)
    pts, ij = _grid(anchor, s, reach)
    inside = _outline_depth(pts, verts, n_verts, radius) >= margin
    (sel,) = jnp.nonzero(inside, size=n_points, fill_value=0)
    mask = jnp.arange(n_points) < jnp.sum(inside)
    return (
        jnp.where(mask[:, None], pts[sel], anchor),
        jnp.where(mask[:, None], ij[sel], 0),
        mask,
        s,
    )


# ---------------------------------------------------------------------------------------------
# boundary integrals, in closed form over straight elements
#
# Plane-strain Kelvin kernels with shear modulus 1 (pass nu / (1 + nu) for plane stress);
# Brebbia & Dominguez, Boundary Elements, Sec. 5; r = x - xi from the source point xi to the
# boundary point x, n the outward normal at x:
#   U*_ij = [(3 - 4 nu) ln(1/r) d_ij + r,i r,j] / (8 pi (1 - nu))
#   T*_ij = -[dr/dn ((1 - 2 nu) d_ij + 2 r,i r,j) - (1 - 2 nu)(r,i n_j - r,j n_i)]
#           / (4 pi (1 - nu) r)
#   D_kij = [(1 - 2 nu)(d_ki r,j + d_kj r,i - d_ij r,k) + 2 r,i r,j r,k] / (4 pi (1 - nu) r)
#   S_kij = {2 dr/dn [(1 - 2 nu) d_ij r,k + nu (d_ik r,j + d_jk r,i) - 4 r,i r,j r,k]
#            + 2 nu (n_i r,j r,k + n_j r,i r,k) + (1 - 2 nu)(2 n_k r,i r,j + n_j d_ik + n_i d_jk)
#            - (1 - 4 nu) n_k d_ij} / (2 pi (1 - nu) r^2)
# On an element with tangent t and normal n, r = u t + d n with u in [u1, u2] and d >= 0 (the
# source is inside a convex body). With theta = atan(u / d), s = u / r = sin(theta) and
# c = d / r = cos(theta), every integral above reduces to ln(r2 / r1), the subtended angle phi and
# trigonometric polynomials at the two ends, so each (source, element) pair costs one evaluation
# and is exact however close the source is (no quadrature, no near-singular special case).
# Components come first and (source, element) axes last, which XLA vectorises well.
# ---------------------------------------------------------------------------------------------

# stress components (xx, yy, xy) as index pairs
_I3, _J3 = (0, 1, 0), (0, 1, 1)


class _Pair(NamedTuple):
    """Closed-form building blocks for sources ``[S]`` x elements ``[E]`` (arrays ``[S, E]``)."""

    t: tuple  # element unit tangent (tx, ty), each [E]
    n: tuple  # element outward normal (nx, ny), each [E]
    length: jax.Array  # [E]
    d: jax.Array  # distance of the source from the element's line (>= 0)
    log_r: tuple  # (ln r1, ln r2) at the element ends
    u: tuple  # (u1, u2) tangential coordinates of the ends
    phi: jax.Array  # angle subtended by the element: int d / r^2 du
    lr: jax.Array  # ln(r2 / r1) = int u / r^2 du
    c2: jax.Array  # [c^2] = c^2(u2) - c^2(u1)
    c4: jax.Array  # [c^4]
    sc: jax.Array  # [s c]
    scc: jax.Array  # [s c (2 c^2 - 1)]


def _pair(src, a, b) -> _Pair:
    """Geometry of every (source ``[S, 2]``, element ``a -> b`` ``[E, 2]``) pair."""
    ab = b - a
    length = _safe_norm(ab)
    tx, ty = (ab / jnp.where(length > 0, length, 1.0)[:, None]).T
    nx, ny = ty, -tx
    rx = a[:, 0] - src[:, 0, None]
    ry = a[:, 1] - src[:, 1, None]
    u1 = rx * tx + ry * ty
    d = rx * nx + ry * ny
    u2 = u1 + length
    r1s, r2s = u1 * u1 + d * d, u2 * u2 + d * d
    inv1, inv2 = 1.0 / r1s, 1.0 / r2s
    c1, c2 = d * d * inv1, d * d * inv2  # c^2 at the two ends
    sc1, sc2 = u1 * d * inv1, u2 * d * inv2
    log1, log2 = 0.5 * jnp.log(r1s), 0.5 * jnp.log(r2s)
    return _Pair(
        t=(tx, ty),
        n=(nx, ny),
        length=length,
        d=d,
        log_r=(log1, log2),
        u=(u1, u2),
        phi=jnp.arctan2(d * length, u1 * u2 + d * d),
        lr=log2 - log1,
        c2=c2 - c1,
        c4=c2 * c2 - c1 * c1,
        sc=sc2 - sc1,
        scc=sc2 * (2.0 * c2 - 1.0) - sc1 * (2.0 * c1 - 1.0),
    )


def _lin(p: _Pair, k, ps, pc):
    """int w r,k  from int w s and int w c."""
    return p.t[k] * ps + p.n[k] * pc


def _quad(p: _Pair, i, j, pss, psc, pcc):
    """int w r,i r,j  from the local moments (s s, s c, c c)."""
    t, n = p.t, p.n
    return t[i] * t[j] * pss + (t[i] * n[j] + n[i] * t[j]) * psc + n[i] * n[j] * pcc


def _cub(p: _Pair, i, j, k, p3, p2, p1, p0):
    """int w r,i r,j r,k  from the local moments (sss, ssc, scc, ccc)."""
    t, n = p.t, p.n
    return (
        t[i] * t[j] * t[k] * p3
        + (t[i] * t[j] * n[k] + t[i] * n[j] * t[k] + n[i] * t[j] * t[k]) * p2
        + (t[i] * n[j] * n[k] + n[i] * t[j] * n[k] + n[i] * n[j] * t[k]) * p1
        + n[i] * n[j] * n[k] * p0
    )


def _c_moments(p: _Pair):
    """int (c / r) (s^2, s c, c^2) du: the weights of T* and of the Flamant traction."""
    return 0.5 * (p.phi - p.sc), -0.5 * p.c2, 0.5 * (p.phi + p.sc)


def _kelvin_ut(p: _Pair, nu):
    """Element integrals of U*_ij and T*_ij: ``[2 (U, T), 2 (i), 2 (j), S, E]``."""
    a = 1.0 - 2.0 * nu
    u1, u2 = p.u
    int_log = u2 * p.log_r[1] - u1 * p.log_r[0] - p.length + p.d * p.phi  # int ln r du
    uu = (p.length - p.d * p.phi, p.d * p.lr, p.d * p.phi)  # int (s^2, s c, c^2) du
    cm = _c_moments(p)
    cu = 1.0 / (8.0 * math.pi * (1.0 - nu))
    ct = -1.0 / (4.0 * math.pi * (1.0 - nu))
    u, t = [], []
    for i in range(2):
        row_u, row_t = [], []
        for j in range(2):
            dij = float(i == j)
            row_u.append(cu * (-(3.0 - 4.0 * nu) * int_log * dij + _quad(p, i, j, *uu)))
            skew = p.t[i] * p.n[j] - p.t[j] * p.n[i]
            row_t.append(ct * (a * dij * p.phi + 2.0 * _quad(p, i, j, *cm) - a * p.lr * skew))
        u.append(jnp.stack(row_u))
        t.append(jnp.stack(row_t))
    return jnp.stack([jnp.stack(u), jnp.stack(t)])


def _kelvin_ds(p: _Pair, nu):
    """Element integrals of D_kij and S_kij: ``[2 (D, S), 2 (k), 3 (xx, yy, xy), S, E]``.

    Sources must lie off the element lines (d > 0): interior points.
    """
    a = 1.0 - 2.0 * nu
    # int (1/r) (s, c) du and int (1/r) (s^3, s^2 c, s c^2, c^3) du
    v = (p.lr, p.phi)
    w = (p.lr + 0.5 * p.c2, 0.5 * (p.phi - p.sc), -0.5 * p.c2, 0.5 * (p.phi + p.sc))
    # int (1/r^2) f du = (1/d) int f dtheta; moments of f = c (s, c), (s^2, s c, c^2) and
    # c (s^3, s^2 c, s c^2, c^3)
    x = (-0.5 * p.c2, 0.5 * (p.phi + p.sc))
    z = (0.5 * (p.phi - p.sc), -0.5 * p.c2, 0.5 * (p.phi + p.sc))
    s4 = -2.0 * p.c2 + p.c4
    y = (
        0.25 * s4,
        p.phi / 8.0 - p.scc / 8.0,
        -0.25 * p.c4,
        3.0 * p.phi / 8.0 + 0.5 * p.sc + p.scc / 8.0,
    )
    cd = 1.0 / (4.0 * math.pi * (1.0 - nu))
    cs = 1.0 / (2.0 * math.pi * (1.0 - nu) * jnp.where(p.d > 0, p.d, 1.0))
    n = p.n
    big_d, big_s = [], []
    for k in range(2):
        row_d, row_s = [], []
        for i, j in zip(_I3, _J3, strict=True):
            dij, dik, djk = float(i == j), float(i == k), float(j == k)
            vi, vj, vk = _lin(p, i, *v), _lin(p, j, *v), _lin(p, k, *v)
            row_d.append(cd * (a * (dik * vj + djk * vi - dij * vk) + 2.0 * _cub(p, i, j, k, *w)))
            xi, xj, xk = _lin(p, i, *x), _lin(p, j, *x), _lin(p, k, *x)
            row_s.append(
                cs
                * (
                    2.0 * (a * dij * xk + nu * (dik * xj + djk * xi) - 4.0 * _cub(p, i, j, k, *y))
                    + 2.0 * nu * (n[i] * _quad(p, j, k, *z) + n[j] * _quad(p, i, k, *z))
                    + a * (2.0 * n[k] * _quad(p, i, j, *z) + (n[j] * dik + n[i] * djk) * p.phi)
                    - (1.0 - 4.0 * nu) * n[k] * dij * p.phi
                )
            )
        big_d.append(jnp.stack(row_d))
        big_s.append(jnp.stack(row_s))
    return jnp.stack([jnp.stack(big_d), jnp.stack(big_s)])


def _flamant_traction(p: _Pair, nu):
    """Element integrals of the Flamant traction -sigma_F . n, per unit force (k) at the source,
    ``[2 (k), 2 (l), S, E]`` (N/m per N/m: integrate (2 / pi)(e . n) e_k e_l / rho)."""
    del nu
    cm = _c_moments(p)
    return (2.0 / math.pi) * jnp.stack(
        [jnp.stack([_quad(p, k, m, *cm) for m in range(2)]) for k in range(2)]
    )


def _flamant_field(points, contact_points, forces):
    """Flamant stress ``[M, 3]`` (per unit thickness) of point forces ``[C, 2]`` at
    ``contact_points [C, 2]``: sigma = -(2 / pi rho) (F . e) e (x) e, e = (x - x_c) / rho.

    It is the field of a force on the edge of a half-plane and is traction-free on every line
    through the load point, so it holds for any convex body (Timoshenko & Goodier, Sec. 36).
    """
    rx = points[None, :, 0] - contact_points[:, 0, None]  # [C, M]
    ry = points[None, :, 1] - contact_points[:, 1, None]
    r2 = rx * rx + ry * ry
    r2 = jnp.where(r2 > 0, r2, 1.0)
    s = -(2.0 / math.pi) * (forces[:, 0, None] * rx + forces[:, 1, None] * ry) / (r2 * r2)
    return jnp.stack([(s * rx * rx).sum(0), (s * ry * ry).sum(0), (s * rx * ry).sum(0)], -1)


def _traction_operator(a, b, mid, length, points, nu):
    """Stress at ``points [M, 2]`` per unit element traction, ``[3 M, 2 N]`` (-), rows
    (point, component), columns (element, direction).

    Solves the pure traction problem H u = G t with the three rigid modes removed by Lagrange
    multipliers, then applies Somigliana's identity sigma = D t - S u.
    """
    N = mid.shape[0]
    dtype = mid.dtype
    ut = _kelvin_ut(_pair(mid, a, b), nu)
    eye = jnp.eye(2, dtype=dtype)[:, :, None, None]
    own = jnp.eye(N, dtype=bool)
    tau = (b - a) / length[:, None]
    # own element: CPV of T* vanishes (collocation at the midpoint of a straight element) and
    # int ln(1/r) = L (1 - ln(L/2))
    g_self = (length / (8.0 * math.pi * (1.0 - nu))) * (
        (3.0 - 4.0 * nu) * (1.0 - jnp.log(0.5 * length)) * eye[..., 0] + tau.T[:, None] * tau.T
    )  # [2, 2, N]
    g = jnp.where(own, g_self[..., None], ut[0]).transpose(2, 0, 3, 1).reshape(2 * N, 2 * N)
    h = jnp.where(own, 0.5 * eye, ut[1]).transpose(2, 0, 3, 1).reshape(2 * N, 2 * N)
    # bordered system [H R; W^T 0]: W = diag(L) R, rigid modes scaled to be dimensionless
    x0 = jnp.sum(length[:, None] * mid, 0) / jnp.sum(length)
    ell = jnp.sqrt(jnp.sum(length * jnp.sum((mid - x0) ** 2, -1)) / jnp.sum(length))
    rot = _perp(mid - x0) / ell
    zeros, ones = jnp.zeros(N, dtype), jnp.ones(N, dtype)
    modes = jnp.stack(
        [jnp.stack([ones, zeros], -1), jnp.stack([zeros, ones], -1), rot], axis=-1
    ).reshape(2 * N, 3)
    weights = jnp.repeat(length / jnp.mean(length), 2)[:, None] * modes
    lhs = jnp.block([[h, modes], [weights.T, jnp.zeros((3, 3), dtype)]])
    rhs = jnp.concatenate([g, jnp.zeros((3, 2 * N), dtype)], axis=0)
    u_op = jnp.linalg.solve(lhs, rhs)[: 2 * N]  # boundary displacement per unit traction
    ds = _kelvin_ds(_pair(points, a, b), nu)
    M = points.shape[0]
    d_op = ds[0].transpose(2, 1, 3, 0).reshape(3 * M, 2 * N)
    s_op = ds[1].transpose(2, 1, 3, 0).reshape(3 * M, 2 * N)
    return d_op - s_op @ u_op


def _force_operator(nodes, points, nu, load_model: str) -> jnp.ndarray:
    """Stress at ``points`` per unit force (per unit thickness) at each element midpoint.

    ``"element"``: the whole stress, force spread over the element. ``"flamant"``: only the
    smooth BEM remainder; the Flamant part is added at the true contact point later.
    Returns ``[N, 2, M, 3]`` (1/m).
    """
    a, b, mid, length, _ = _element_geometry(nodes)
    k_t = _traction_operator(a, b, mid, length, points, nu)  # [3 M, 2 N]
    N, M = mid.shape[0], points.shape[0]
    if load_model == "element":
        k_f = k_t / jnp.repeat(length, 2)
    else:
        # element-averaged remainder traction (l) on element j from a unit force (k) at the
        # midpoint of element e; zero on e itself, whose line is a free edge of the half-plane
        t_r = _flamant_traction(_pair(mid, a, b), nu)  # [k, l, e, j]
        t_r = jnp.where(jnp.eye(N, dtype=bool), 0.0, t_r / length)
        k_f = k_t @ t_r.transpose(3, 1, 2, 0).reshape(2 * N, 2 * N)
    return k_f.reshape(M, 3, N, 2).transpose(2, 3, 0, 1)


# ---------------------------------------------------------------------------------------------
# loads -> stress
# ---------------------------------------------------------------------------------------------


def _node_angles(nodes):
    """Centre ``[2]`` (mean of the nodes, inside a convex outline) and the polar angles of the
    nodes about it ``[N]`` (rad), unwrapped so that they increase from node 0 (CCW)."""
    centre = jnp.mean(nodes, axis=0)
    d = nodes - centre
    th = jnp.arctan2(d[:, 1], d[:, 0])
    return centre, th[0] + jnp.mod(th - th[0], _TWO_PI)


def _assign_contacts(contact_points, nodes, centre, node_angles):
    """Split each contact between the two elements whose midpoints bracket it along the
    element polygon (a hat function along the boundary).

    Returns (first element ``lo`` [C] in 0..N-1, weight of element ``(lo + 1) mod N`` [C]);
    see ``_contact_elements``.
    """
    _, lo, w_hi = _contact_elements(contact_points, nodes, centre, node_angles)
    return lo, w_hi


# the binned element lookup of psi_bound_flat reads this many nodes past a bin's start
_BIN_SPAN = 3


def _angle_bins(node_angles):
    """``[4 N]`` element holding the start of each of 4 N equal angular bins from node 0,
    or -1 for all bins if one bin holds more than ``_BIN_SPAN`` node angles (``_binned_element``
    is then not exact for this particle)."""
    N = node_angles.shape[0]
    Q = 4 * N
    starts = node_angles[0] + jnp.arange(Q, dtype=node_angles.dtype) * (_TWO_PI / Q)
    first = jnp.sum(node_angles[None, :] <= starts[:, None], axis=1) - 1
    nxt = jnp.concatenate([first[1:], jnp.array([N - 1], first.dtype)])
    ok = jnp.max(nxt - first) <= _BIN_SPAN
    return jnp.where(ok, first, -1).astype(jnp.int32)


def _binned_element(contact_point, centre, angle, bins):
    """Element whose angular sector holds one contact, from the bins of ``_angle_bins``:
    the count of node angles <= the contact's angle over a window of ``_BIN_SPAN + 2`` nodes
    from one before the bin's start (rounding at a bin edge cannot move the answer).
    ``angle(k)`` returns node angles of given indices. Equals ``_contact_elements``'s ``e``
    when ``bins`` is not -1."""
    Q = bins.shape[0]
    N = Q // 4
    theta0 = angle(0)
    d = contact_point - centre
    rel = jnp.mod(jnp.arctan2(d[1], d[0]) - theta0, _TWO_PI)
    phi = theta0 + rel
    q = jnp.clip(jnp.floor(rel * (Q / _TWO_PI)).astype(jnp.int32), 0, Q - 1)
    base = jnp.maximum(bins[q] - 1, 0)
    k = base + jnp.arange(_BIN_SPAN + 2)
    count = base + jnp.sum((k < N) & (angle(jnp.minimum(k, N - 1)) <= phi))
    return jnp.clip(count - 1, 0, N - 1)


def _contact_elements(
    contact_points, nodes, centre, node_angles, e=None, n_elements=None, fused=False
):
    """The element holding each contact and its hat split over two elements.

    The element ``e`` is the one whose angular sector (seen from ``centre``) holds the contact:
    C x N comparisons, no distances. Returns (``e`` [C], first element of the split ``lo`` [C]
    in 0..N-1, weight ``w`` in [0, 1] of element ``(lo + 1) mod N`` [C]). ``nodes`` is the
    ``[N, 2]`` array or a function returning the nodes of given indices; ``e`` the element
    if already known (``_binned_element``; ``node_angles`` is then not read, and
    ``n_elements`` gives N); ``fused``: the dot products written out (``_dot``; the bounds'
    per-contact code).
    """
    N = node_angles.shape[0] if n_elements is None else n_elements
    if callable(nodes):
        node = nodes
    else:

        def node(k):
            return nodes[k]

    if e is None:
        d = contact_points - centre
        theta0 = node_angles[0]
        phi = theta0 + jnp.mod(jnp.arctan2(d[:, 1], d[:, 0]) - theta0, _TWO_PI)
        e = jnp.clip(jnp.sum(node_angles[None, :] <= phi[:, None], axis=1) - 1, 0, N - 1)
    a = node(e)
    b = node((e + 1) % N)
    ab = b - a
    if fused:
        le2 = _dot(ab, ab)
        along = _dot(contact_points - a, ab)
    else:
        le2 = jnp.sum(ab * ab, axis=-1)
        along = jnp.sum((contact_points - a) * ab, axis=-1)
    le = jnp.sqrt(le2)
    u = jnp.clip(_safe_div(along, le2), 0.0, 1.0) * le
    ahead = u >= 0.5 * le
    prev = (e - 1) % N
    l_next = _safe_norm(node((e + 2) % N) - b, fused)
    l_prev = _safe_norm(a - node(prev), fused)
    w_next = _safe_div(u - 0.5 * le, 0.5 * (le + l_next))  # weight of e + 1 when ahead
    w_prev = _safe_div(0.5 * le - u, 0.5 * (le + l_prev))  # weight of e - 1 when behind
    lo = jnp.where(ahead, e, prev)
    w_hi = jnp.where(ahead, w_next, 1.0 - w_prev)
    return e, lo, w_hi


def _equilibrate(x, f, mask):
    """Minimum-norm correction of forces ``[C, 2]`` at ``x [C, 2]``: zero resultant force and
    moment (PHYSICS A4); unchanged with fewer than two contacts."""
    m = mask.astype(f.dtype)[:, None]
    count = jnp.sum(mask)
    nn = jnp.maximum(count, 1).astype(f.dtype)
    f1 = f - m * (jnp.sum(m * f, 0) / nn)
    dx = m * (x - jnp.sum(m * x, 0) / nn)
    omega = -_safe_div(jnp.sum(_cross2(dx, f1)), jnp.sum(dx * dx))
    f2 = f1 + omega * _perp(dx)
    return jnp.where(count >= 2, f2, f)


def _contact_stress(
    k_f, nodes, centre, node_angles, points, contact_points, contact_forces, contact_mask,
    load_model,
):  # fmt: skip
    """Stress ``[M, 3]`` (Pa x thickness) of one particle from its contact forces (N).

    ``k_f`` is the particle's ``[N, 2, M, 3]`` operator. Each contact reads the two
    ``[2, M, 3]`` blocks of ``k_f`` around it, blended by the hat weights into one (XLA
    fuses the two gathers and the blend).
    The Flamant part acts at the contact points themselves (on the true outline), not at
    their projections on the chords: the near field is very sensitive to the load position
    (projecting moved the Brazilian error from 0.1 % to 0.7 % at N = 128).
    """
    lo, w = _assign_contacts(contact_points, nodes, centre, node_angles)
    forces = jnp.where(contact_mask[:, None], contact_forces, 0.0)
    forces = _equilibrate(contact_points, forces, contact_mask)
    w = w.astype(k_f.dtype)[:, None, None, None]
    col = (1.0 - w) * k_f[lo] + w * k_f[(lo + 1) % k_f.shape[0]]
    sigma = jnp.einsum("ckmj,ck->mj", col, forces.astype(k_f.dtype))
    if load_model == "flamant":
        sigma = sigma + _flamant_field(points, contact_points, forces)
    return sigma


def _chosen_stress(ops, idx, contact_points, contact_forces, contact_mask):
    """``_contact_stress`` of the particles ``idx [K]`` (lists ``[K, C]``), ``[K, M, 3]``
    (Pa x thickness), reading only their loaded operator blocks: one gather of the
    ``[2, 3 M]`` blocks of every contact's two elements from ``ops.stress_per_force`` seen
    as ``[P N, 2, 3 M]`` rows, then one contraction with the hat-weighted forces. (A
    gather indexed by particle and element inside a vmap, fused into the contraction, took
    twice as long on CPU.)"""
    k_f = ops.stress_per_force
    P, N, _, M, _ = k_f.shape

    def loads(i, x, f, m):
        lo, w = _assign_contacts(x, ops.nodes[i], ops.centres[i], ops.node_angles[i])
        return lo, w, _equilibrate(x, jnp.where(m[:, None], f, 0.0), m)

    lo, w, forces = jax.vmap(loads)(idx, contact_points, contact_forces, contact_mask)
    rows = idx[:, None] * N + jnp.concatenate([lo, (lo + 1) % N], axis=1)  # [K, 2 C]
    w = w.astype(k_f.dtype)[..., None]
    g = forces.astype(k_f.dtype)
    coef = jnp.concatenate([(1.0 - w) * g, w * g], axis=1)  # [K, 2 C, 2]
    blocks = k_f.reshape(P * N, 2, 3 * M)[rows]  # [K, 2 C, 2, 3 M]
    sigma = jnp.einsum("kcd,kcdm->km", coef, blocks).reshape(-1, M, 3)
    if ops.load_model == "flamant":
        sigma = sigma + jax.vmap(_flamant_field)(ops.points[idx], contact_points, forces)
    return sigma


# ---------------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------------


def equivalent_stress(sigma: ArrayLike, poisson_ratio: float | jax.Array, plane: Plane = "stress"):
    """Strain-energy equivalent stress psi = sqrt(2 E W) (Pa), paper 000 Eq. 2.

    psi^2 = (1 + nu) sigma:sigma - nu (tr sigma)^2 over the 3D stress, i.e.
    psi = sigma_v [2/3 (1 + nu) + 3 (1 - 2 nu)(sigma_m / sigma_v)^2]^(1/2); uniaxially
    psi = |sigma|. Plane strain includes sigma_zz = nu (sigma_xx + sigma_yy).

    Args:
        sigma: in-plane stress ``[..., 3]`` = (sigma_xx, sigma_yy, sigma_xy) (Pa).
        poisson_ratio: Poisson's ratio nu (-).
        plane: ``"stress"`` (sigma_zz = 0) or ``"strain"``.

    Returns:
        psi ``[...]`` (Pa); a numpy array for numpy input, else a jax array. Differentiable
        (finite gradient at zero stress).
    """
    _check_plane(plane)
    is_np = isinstance(sigma, np.ndarray)
    s = jnp.asarray(sigma)
    sxx, syy, sxy = s[..., 0], s[..., 1], s[..., 2]
    szz = poisson_ratio * (sxx + syy) if plane == "strain" else jnp.zeros_like(sxx)
    ss = sxx**2 + syy**2 + szz**2 + 2.0 * sxy**2
    i1 = sxx + syy + szz
    w2 = jnp.maximum((1.0 + poisson_ratio) * ss - poisson_ratio * i1**2, 0.0)
    pos = w2 > 0
    psi = jnp.where(pos, jnp.sqrt(jnp.where(pos, w2, 1.0)), 0.0)
    return np.asarray(psi) if is_np else psi


def _check_plane(plane) -> None:
    if plane not in PLANES:
        raise ValueError(f"plane must be 'stress' or 'strain', got {plane!r}")


def _check_load_model(load_model) -> None:
    if load_model not in LOAD_MODELS:
        raise ValueError(f"load_model must be 'flamant' or 'element', got {load_model!r}")


def _check_poisson(poisson_ratio) -> float:
    nu = float(poisson_ratio)
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"poisson_ratio must lie in (-1, 0.5), got {nu}")
    return nu


def min_elements(n_vertices: int) -> int:
    """Fewest boundary elements the solver takes for a core of ``n_vertices`` vertices: two
    per vertex (an edge and a corner arc each need one), at least 8."""
    return max(8, 2 * int(n_vertices))


def _check_particle(vertices, radius, n_elements) -> tuple[np.ndarray, float]:
    """Validated CCW core ``[n, 2]`` (float64) and radius of one spheropolygon."""
    radius = float(radius)
    if not (math.isfinite(radius) and radius >= 0.0):
        raise ValueError(f"radius must be finite and >= 0 m, got {radius}")
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 2 or len(v) == 0:
        raise ValueError(
            f"vertices must have shape [n_vertices, 2] with n_vertices >= 1, got {v.shape}"
        )
    if not np.isfinite(v).all():
        raise ValueError("vertices contain NaN or inf; check how they were computed")
    distinct = np.unique(np.round(v / max(np.abs(v).max(), 1e-300), 12), axis=0)
    if len(distinct) >= 3:
        v = validate_polygon(v, name="vertices")
    elif radius == 0.0:
        raise ValueError(
            f"vertices has {len(distinct)} distinct point(s) and radius 0, so the particle has "
            "no area; give at least 3 vertices or a radius > 0 (1 vertex = disc)"
        )
    elif len(distinct) == 2:  # a stadium: the segment between the two distinct points
        v = v[[0, int(np.argmax(np.linalg.norm(v - v[0], axis=1)))]]
    else:
        v = v[:1]
    n_elements = int(n_elements)
    if n_elements < min_elements(len(v)):
        raise ValueError(
            f"n_elements={n_elements} is too small for a core of {len(v)} vertices; use at "
            f"least {min_elements(len(v))} (64-128 is typical)"
        )
    return v, radius


def _bucket(n: int, step: int) -> int:
    """Round a count up to a multiple of ``step`` (fewer distinct shapes, fewer compiles)."""
    return max(step, -(-n // step) * step)


def _pow2(n: int, floor: int = 64) -> int:
    """Next power of two >= max(n, floor) (``floor`` a power of two): padded counts (query
    points, contact lists, screening slots) that compile once per size."""
    return max(floor, 1 << (max(n, 1) - 1).bit_length())


def _pad_rows(x: np.ndarray, size: int) -> np.ndarray:
    """Pad ``[n, 2]`` to ``[size, 2]`` by repeating the last row (or zeros when empty)."""
    fill = x[-1:] if len(x) else np.zeros((1, 2))
    return np.concatenate([x, np.repeat(fill, size - len(x), axis=0)], axis=0)


def _padded_core(vertices, radius, n_elements):
    """Validated core padded to a multiple of 8 vertex slots: (verts [V, 2], n, radius)."""
    v, radius = _check_particle(vertices, radius, n_elements)
    return jnp.asarray(_pad_rows(v, _bucket(len(v), 8))), len(v), radius


def _margin(nodes):
    """How far inside sample points stay (m): 1.5 x the longest element."""
    return _MARGIN * jnp.max(_element_geometry(nodes)[3])


def stress_field(
    vertices: ArrayLike,
    contact_points: ArrayLike,
    contact_forces: ArrayLike,
    points: ArrayLike,
    *,
    poisson_ratio: float,
    plane: Plane = "stress",
    n_elements: int = 128,
    thickness: float = 1.0,
    radius: float = 0.0,
    load_model: LoadModel = "flamant",
) -> np.ndarray:
    """Stress at interior points of one particle loaded by contact forces (BEM).

    Args:
        vertices: convex core polygon ``[n, 2]`` (m), CCW (CW is reversed); with
            ``radius > 0`` also 1 vertex (disc) or 2 (stadium).
        contact_points: ``[k, 2]`` (m) on the outline (within one element length).
        contact_forces: ``[k, 2]`` (N) acting ON the particle; equilibrated by the minimum-norm
            correction when k >= 2.
        points: where to evaluate, ``[M, 2]`` (m), inside the particle. Accuracy is good from
            about 1.5 element lengths inside the boundary (see ``sample_points``).
        poisson_ratio: nu (-); in-plane stress depends on it only through discretisation.
        plane: ``"stress"`` or ``"strain"``.
        n_elements: boundary elements N.
        thickness: out-of-plane thickness t (m); stress = force per unit thickness / t.
        radius: sweeping radius r of the spheropolygon (m).
        load_model: ``"flamant"`` (point forces, default) or ``"element"`` (paper 000: uniform
            traction on the loaded element); see the module docstring.

    Returns:
        ``[M, 3]`` = (sigma_xx, sigma_yy, sigma_xy) (Pa), tension positive.

    Raises:
        ValueError: non-convex outline, fewer than 3 vertices with radius 0, NaN input,
            contact point off the boundary, point outside the particle, bad settings.
    """
    _check_plane(plane)
    _check_load_model(load_model)
    nu = _check_poisson(poisson_ratio)
    thickness = float(thickness)
    if not (math.isfinite(thickness) and thickness > 0):
        raise ValueError(f"thickness must be finite and > 0 m, got {thickness}")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    cp = np.asarray(contact_points, dtype=np.float64).reshape(-1, 2)
    cf = np.asarray(contact_forces, dtype=np.float64).reshape(-1, 2)
    if cp.shape != cf.shape:
        raise ValueError(
            f"contact_points {cp.shape} and contact_forces {cf.shape} must both be [k, 2]"
        )
    for name, x in (("points", pts), ("contact_points", cp), ("contact_forces", cf)):
        bad = ~np.isfinite(x).all(axis=1)
        if bad.any():
            raise ValueError(
                f"{name}[{int(np.nonzero(bad)[0][0])}] is NaN or inf; check how it was computed "
                "(a NaN contact force usually comes from the contact law)"
            )
    verts, n, radius = _padded_core(vertices, radius, n_elements)
    query = np.concatenate([cp, pts])
    depth = np.asarray(
        _depth_jit(jnp.asarray(_pad_rows(query, _pow2(len(query)))), verts, n, radius)
    )[: len(query)]
    # nominal element length: perimeter / N
    v = np.asarray(verts)[:n]
    perimeter = np.linalg.norm(np.roll(v, -1, axis=0) - v, axis=1).sum() + _TWO_PI * radius
    tol = perimeter / int(n_elements)
    off = np.abs(depth[: len(cp)]) > tol
    if off.any():
        i = int(np.nonzero(off)[0][0])
        raise ValueError(
            f"contact point {i} {cp[i].tolist()} is {abs(depth[i]):.3g} m off the particle "
            f"boundary (tolerance: one element length, {tol:.3g} m); contact points must lie "
            "on the outline, in the same frame as the vertices"
        )
    outside = depth[len(cp) :] <= 0
    if outside.any():
        i = int(np.nonzero(outside)[0][0])
        raise ValueError(
            f"points[{i}] {pts[i].tolist()} is not inside the particle; stress is only defined "
            "inside (sample_points gives a grid where the BEM is accurate)"
        )
    if len(cp) == 0 or len(pts) == 0:
        return np.zeros((len(pts), 3))
    c_pad = _bucket(len(cp), 8)
    sigma = _stress_field_jit(
        verts,
        n,
        jnp.asarray(radius),
        jnp.asarray(_pad_rows(pts, _pow2(len(pts)))),
        jnp.asarray(_pad_rows(cp, c_pad)),
        jnp.asarray(np.concatenate([cf, np.zeros((c_pad - len(cf), 2))])),
        jnp.arange(c_pad) < len(cp),
        jnp.asarray(_kernel_poisson(nu, plane)),
        n_elements=int(n_elements),
        load_model=load_model,
    )
    return np.asarray(sigma)[: len(pts)] / thickness


_depth_jit = jax.jit(_outline_depth)


@jax.jit(static_argnames=("n_elements", "load_model"))
def _stress_field_jit(
    verts, n_verts, radius, points, contact_points, contact_forces, contact_mask, nu, *,
    n_elements, load_model
):  # fmt: skip
    nodes = _elements_padded(verts, n_verts, radius, n_elements)
    k_f = _force_operator(nodes, points, nu, load_model)
    centre, angles = _node_angles(nodes)
    return _contact_stress(
        k_f,
        nodes,
        centre,
        angles,
        points,
        contact_points,
        contact_forces,
        contact_mask,
        load_model,
    )


@jax.jit(static_argnames=("n_elements", "reach"))
def _grid_inside(verts, n_verts, radius, spacing, *, n_elements, reach):
    """Grid points (spacing given) at least the sample margin inside: (points, ij, inside)."""
    margin = _margin(_elements_padded(verts, n_verts, radius, n_elements))
    pts, ij = _grid(polygon_centroid_padded(verts, n_verts), spacing, reach)
    return pts, ij, _outline_depth(pts, verts, n_verts, radius) >= margin


@jax.jit(static_argnames=("n_elements", "n_points"))
def _sample_points_jit(verts, n_verts, radius, *, n_elements, n_points):
    margin = _margin(_elements_padded(verts, n_verts, radius, n_elements))
    return _sample_grid(verts, n_verts, radius, margin, n_points)


def sample_points(
    vertices: ArrayLike,
    radius: float,
    n_elements: int,
    spacing: float | None = None,
    n_points: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid of interior sample points, at least 1.5 element lengths inside.

    The grid is aligned with the axes and contains the core centroid. Element lengths are those
    of ``n_elements`` boundary elements on this outline, so the points are where the BEM with
    that many elements is accurate. ``build_operators`` uses the same grid.

    Args:
        vertices: core polygon ``[n, 2]`` (m) (1 vertex + radius > 0 is a disc).
        radius: sweeping radius (m).
        n_elements: number of boundary elements N.
        spacing: grid spacing (m); or give
        n_points: the most points wanted (default 100 when neither is given); the spacing is
            chosen so that the count is as close to it as the grid allows.

    Returns:
        ``(points [M, 2] (m), ij [M, 2] (int))``: grid indices relative to the centroid,
        for 4-connectivity (neighbours differ by 1 in one index).
    """
    verts, n, radius = _padded_core(vertices, radius, n_elements)
    if spacing is not None:
        if n_points is not None:
            raise ValueError("give either spacing or n_points, not both")
        spacing = float(spacing)
        if not (math.isfinite(spacing) and spacing > 0):
            raise ValueError(f"spacing must be finite and > 0 m, got {spacing}")
        v = np.asarray(verts)[:n]
        extent = float(np.max(np.linalg.norm(v - v.mean(0), axis=1))) * 2.0 + radius
        reach = int(math.ceil(extent / spacing)) + 1
        if (2 * reach + 1) ** 2 > 10_000_000:
            raise ValueError(
                f"spacing {spacing:.3g} m gives more than 1e7 grid points for a particle of "
                f"size {extent:.3g} m; use a coarser spacing or n_points"
            )
        pts, ij, inside = _grid_inside(
            verts,
            n,
            jnp.asarray(radius),
            jnp.asarray(spacing),
            n_elements=int(n_elements),
            reach=_bucket(reach, 8),
        )
        inside = np.asarray(inside)
        return np.asarray(pts)[inside], np.asarray(ij)[inside]
    n_points = 100 if n_points is None else int(n_points)
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    pts, ij, mask, _ = _sample_points_jit(
        verts, n, jnp.asarray(radius), n_elements=int(n_elements), n_points=n_points
    )
    mask = np.asarray(mask)
    return np.asarray(pts)[mask], np.asarray(ij)[mask]


class BemOperators(eqx.Module):
    """Per-particle BEM operators in each particle's body frame (the frame of ``verts``).

    Shapes: P particles, N elements, M sample points. Build with ``build_operators`` once per
    shape; use with ``psi_batched``.

    Attributes:
        nodes: element start points ``[P, N, 2]`` (m); element e runs to node e + 1.
        midpoints: element midpoints ``[P, N, 2]`` (m).
        normals: outward unit normals ``[P, N, 2]``.
        lengths: element lengths ``[P, N]`` (m).
        points: sample points ``[P, M, 2]`` (m); padded slots hold the centroid.
        point_mask: real sample points ``[P, M]``.
        grid_index: grid indices of the points ``[P, M, 2]`` (int), for 4-connectivity.
        spacing: grid spacing ``[P]`` (m).
        stress_per_force: ``[P, N, 2, M, 3]`` (1/m): stress at the points per unit force per
            unit thickness (N/m) in direction k at the midpoint of element e; the whole
            stress for ``load_model="element"``, the BEM remainder for ``"flamant"``.
        valid: particles with a usable outline ``[P]`` (others give zero stress).
        centres: mean of the nodes ``[P, 2]`` (m), inside each outline.
        node_angles: polar angles of the nodes about ``centres`` ``[P, N]`` (rad), increasing
            from node 0; a contact's element is found from its angle (C x N comparisons).
        screen_table: ``[P, N, G, 1 + 2 K]``: per element and group of sample points (G
            angular sectors) the numbers of the screening bound ``psi_bound``
            (``_screen_tables``; K = ``_SCREEN_DIRECTIONS``).
        screen_coarse: ``[P, N, 1 + 2 K]``: one row per element for the first, cheaper level
            of ``screen`` (``_coarse_rows``).
        angle_bins: ``[P, 4 N]`` (int): element at the start of each of 4 N equal angle bins
            from node 0, -1 where a bin holds more than ``_BIN_SPAN`` nodes (then the
            element lookup of ``psi_bound_flat`` compares with every node instead).
        poisson_ratio: nu used in the kernels (-).
        plane: ``"stress"`` or ``"strain"`` (static).
        load_model: ``"flamant"`` or ``"element"`` (static).
    """

    nodes: jax.Array
    midpoints: jax.Array
    normals: jax.Array
    lengths: jax.Array
    points: jax.Array
    point_mask: jax.Array
    grid_index: jax.Array
    spacing: jax.Array
    stress_per_force: jax.Array
    valid: jax.Array
    centres: jax.Array
    node_angles: jax.Array
    screen_table: jax.Array
    screen_coarse: jax.Array
    angle_bins: jax.Array
    poisson_ratio: jax.Array
    plane: str = eqx.field(static=True)
    load_model: str = eqx.field(static=True)


def _psi_form(poisson_ratio, plane: str, dtype) -> jnp.ndarray:
    """``Q [3, 3]`` with psi^2 = s^T Q s for s = (sigma_xx, sigma_yy, sigma_xy), by polarising
    ``equivalent_stress`` (Q is positive definite for -1 < nu < 1/2, so psi is a norm)."""
    eye = jnp.eye(3, dtype=dtype)
    diag = equivalent_stress(eye, poisson_ratio, plane) ** 2
    pair = equivalent_stress(eye[:, None, :] + eye[None, :, :], poisson_ratio, plane) ** 2
    return 0.5 * (pair - diag[:, None] - diag[None, :])


def _half_turn_directions(dtype) -> jnp.ndarray:
    """``[K, 2]`` unit vectors at angles k pi / K, k = 0..K-1 (K = ``_SCREEN_DIRECTIONS``)."""
    phi = jnp.arange(_SCREEN_DIRECTIONS, dtype=dtype) * (math.pi / _SCREEN_DIRECTIONS)
    return jnp.stack([jnp.cos(phi), jnp.sin(phi)], axis=-1)


def _screen_tables(k_f, nodes, points, mask, centre, q, n_groups: int):
    """Per element e and group g of sample points, the numbers ``psi_bound`` needs.

    Groups are angular sectors of the sample points about ``centre``. With u_k the K unit
    vectors of ``_half_turn_directions`` and x_s the ``_CHORD_SAMPLES`` midpoints of equal
    parts of the element's chord, returns ``[N, G, 1 + 2 K]``: (min over the group of the
    distance d of p to the chord (m); for each k the max over the group of
    psi(``k_f[e, :, p, :]`` u_k) (1/m); for each k the max over the group and the x_s of
    |u_k . (p - x_s)| / |p - x_s|^2 (1/m), the direction factor of the Flamant field of a
    load at x_s). An empty group gives (+inf, 0..., 0...).

    Both directional columns are values at u_k of functions that are norms of the force
    direction (a maximum of norms of linear maps), so ``_direction_weights`` may interpolate
    them.
    """
    dtype = k_f.dtype
    u = _half_turn_directions(dtype)  # [K, 2]
    gram = jnp.einsum("ekmi,ij,elmj->emkl", k_f, q, k_f)  # [N, M, 2, 2]
    # psi of the remainder per unit force along u_k: sqrt(u^T gram u)
    quad = jnp.einsum("kx,emxy,ky->ekm", u, gram, u)
    rem = jnp.sqrt(jnp.maximum(quad, 0.0))  # [N, K, M]
    d = points - centre
    ang = jnp.arctan2(d[:, 1], d[:, 0])
    grp = jnp.clip(jnp.floor((ang + math.pi) / _TWO_PI * n_groups), 0, n_groups - 1)
    member = (grp[:, None] == jnp.arange(n_groups)[None, :]) & mask[:, None]  # [M, G]
    a0 = nodes
    ab = jnp.roll(nodes, -1, axis=0) - a0
    rel = points[None] - a0[:, None]  # [N, M, 2]
    t = _safe_div(jnp.sum(rel * ab[:, None], -1), jnp.sum(ab * ab, -1)[:, None])
    dist = _safe_norm(rel - jnp.clip(t, 0.0, 1.0)[..., None] * ab[:, None])  # [N, M]
    # Flamant direction factor: the inversion w / |w|^2 of w = p - x_s, projected on u_k
    frac = (jnp.arange(_CHORD_SAMPLES, dtype=dtype) + 0.5) / _CHORD_SAMPLES
    xs = a0[:, None, :] + frac[None, :, None] * ab[:, None, :]  # [N, S, 2]
    w = points[None, None] - xs[:, :, None]  # [N, S, M, 2]
    r2 = jnp.sum(w * w, -1)
    inv = w / jnp.where(r2 > 0, r2, 1.0)[..., None]
    flam = jnp.max(jnp.abs(jnp.einsum("nsmc,kc->nskm", inv, u)), axis=1)  # [N, K, M]

    def gmin(x):  # [N, M] -> [N, G]
        return jnp.min(jnp.where(member[None], x[:, :, None], jnp.inf), axis=1)

    def gmax_k(x):  # [N, K, M] -> [N, G, K]
        return jnp.max(jnp.where(member[None, None], x[..., None], 0.0), axis=2).transpose(0, 2, 1)

    table = jnp.concatenate([gmin(dist)[..., None], gmax_k(rem), gmax_k(flam)], axis=-1)
    return table, _coarse_rows(table)


def _coarse_rows(table):
    """``[N, 1 + 2 K]`` per element e, from its ``[N, G, 1 + 2 K]`` screening table, in the
    same column order: (min over the groups of the distance to e's chord; for each k the max
    over the groups and over the elements e - 1, e, e + 1 of the remainder's directional
    value (a contact on e blends two of those three); for each k the max over the groups of
    the Flamant support). The numbers of the one-row bound ``psi_bound_coarse``."""
    K = _SCREEN_DIRECTIONS
    rem = jnp.max(table[:, :, 1 : 1 + K], axis=1)  # [N, K]
    rem3 = jnp.maximum(rem, jnp.maximum(jnp.roll(rem, 1, axis=0), jnp.roll(rem, -1, axis=0)))
    return jnp.concatenate(
        [jnp.min(table[:, :, 0], axis=1)[:, None], rem3, jnp.max(table[:, :, 1 + K :], axis=1)],
        axis=-1,
    )


def _build_one(verts, n_verts, radius, nu_kernel, q, *, n_elements, n_points, load_model):
    dtype = verts.dtype
    _, edge_len, _, _ = _core_edges(verts, n_verts)
    scale = jnp.max(jnp.abs(verts - verts[0])) + radius
    valid = (n_verts >= 1) & ((radius > 1e-9 * scale) | (jnp.sum(edge_len > 0) >= 3)) & (scale > 0)
    # degenerate slots get a unit disc so the algebra stays finite; their output is zeroed
    verts = jnp.where(valid, verts, jnp.zeros_like(verts))
    n_verts = jnp.where(valid, n_verts, 1)
    radius = jnp.where(valid, radius, jnp.ones((), dtype))
    nodes = _elements_padded(verts, n_verts, radius, n_elements)
    _, _, mid, length, normal = _element_geometry(nodes)
    points, ij, mask, spacing = _sample_grid(verts, n_verts, radius, _margin(nodes), n_points)
    mask = mask & valid
    k_f = _force_operator(nodes, points, nu_kernel, load_model)
    k_f = jnp.where(valid & mask[None, None, :, None], k_f, 0.0)
    centre, angles = _node_angles(nodes)
    table, coarse = _screen_tables(k_f, nodes, points, mask, centre, q, _SCREEN_GROUPS)
    bins = _angle_bins(angles)
    out = nodes, mid, normal, length, points, mask, ij, spacing, k_f, valid, centre, angles
    return (*out, table, coarse, bins)


@jax.jit(static_argnames=("n_elements", "n_points", "load_model", "batch_size"))
def _build_jit(
    verts, n_verts, radius, nu_kernel, q, *, n_elements, n_points, load_model, batch_size
):  # fmt: skip
    def one(args):
        v, n, r = args
        return _build_one(
            v, n, r, nu_kernel, q, n_elements=n_elements, n_points=n_points, load_model=load_model
        )

    return lax.map(one, (verts, n_verts, radius), batch_size=batch_size)


def build_operators(
    verts: ArrayLike,
    n_verts: ArrayLike,
    radius: ArrayLike,
    *,
    n_elements: int = 64,
    n_points: int = 100,
    poisson_ratio: float,
    plane: Plane = "stress",
    load_model: LoadModel = "flamant",
    batch_size: int = 32,
) -> BemOperators:
    """Build the BEM operators of padded particles (once per shape).

    Per particle: N boundary elements, a grid of at most M = ``n_points`` sample points at least
    1.5 element lengths inside, and the stress at those points per unit contact force on each
    element (the traction problem solved once, with Lagrange rigid-mode constraints).

    Args:
        verts: core vertices ``[P, V, 2]`` (m) in each body frame, CCW and convex; slots
            ``k >= n_verts`` repeat the last real vertex.
        n_verts: real vertex counts ``[P]``; 1 is a disc of ``radius``. Slots whose outline has
            no area (e.g. ``n_verts = 0``, or fewer than 3 vertices and radius 0) are marked
            invalid and give zero stress.
        radius: sweeping radii ``[P]`` (m).
        n_elements: elements per particle N (static).
        n_points: sample point capacity M per particle (static).
        poisson_ratio: nu (-), used in the kernels.
        plane: ``"stress"`` (kernels with nu / (1 + nu)) or ``"strain"``.
        load_model: ``"flamant"`` or ``"element"``.
        batch_size: particles assembled together (working memory grows with it).

    Returns:
        ``BemOperators``; dtype follows ``verts`` (float32 works). The operator holds
        P x N x 2 x M x 3 numbers: 310 MB for 1,000 particles at N = 64, M = 100 in float64.
        Cost per particle grows like N^2 M (measured in benchmarks/BEM_RESULTS.md).
    """
    _check_plane(plane)
    _check_load_model(load_model)
    nu = _check_poisson(poisson_ratio)
    verts = jnp.asarray(verts)
    if not jnp.issubdtype(verts.dtype, jnp.floating):
        verts = verts.astype(float)
    if verts.ndim != 3 or verts.shape[-1] != 2:
        raise ValueError(f"verts must have shape [P, V, 2], got {verts.shape}")
    P, V = verts.shape[:2]
    n_verts = jnp.broadcast_to(jnp.asarray(n_verts, jnp.int32), (P,))
    radius = jnp.broadcast_to(jnp.asarray(radius, verts.dtype), (P,))
    if int(n_elements) < max(8, 2 * V):
        raise ValueError(
            f"n_elements={n_elements} is too small for {V} vertex slots; use at least "
            f"{max(8, 2 * V)}"
        )
    if int(n_points) < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    bs = max(1, min(int(batch_size), P))
    pad = _bucket(P, bs) - P  # lax.map would compile the remainder batch separately
    out = _build_jit(
        jnp.concatenate([verts, jnp.zeros((pad, V, 2), verts.dtype)]),
        jnp.concatenate([n_verts, jnp.zeros(pad, jnp.int32)]),
        jnp.concatenate([radius, jnp.zeros(pad, verts.dtype)]),
        jnp.asarray(_kernel_poisson(nu, plane), verts.dtype),
        _psi_form(nu, plane, verts.dtype),
        n_elements=int(n_elements),
        n_points=int(n_points),
        load_model=load_model,
        batch_size=bs,
    )
    if pad:
        out = [x[:P] for x in out]
    nodes, mid, normal, length, points, mask, ij, spacing, k_f, valid, centre, angles = out[:12]
    table, coarse, bins = out[12:]
    return BemOperators(
        nodes=nodes,
        midpoints=mid,
        normals=normal,
        lengths=length,
        points=points,
        point_mask=mask,
        grid_index=ij,
        spacing=spacing,
        stress_per_force=k_f,
        valid=valid,
        centres=centre,
        node_angles=angles,
        screen_table=table,
        screen_coarse=coarse,
        angle_bins=bins,
        poisson_ratio=jnp.asarray(nu, verts.dtype),
        plane=plane,
        load_model=load_model,
    )


def update_operators(
    ops: BemOperators,
    slots: ArrayLike,
    verts: ArrayLike,
    n_verts: ArrayLike,
    radius: ArrayLike,
    *,
    batch_size: int = 32,
) -> BemOperators:
    """Rebuild the operators of some particle slots (new fragments after breakage), keeping
    the others: the cache update of DSM step 2 (paper 000 Sec. II; DESIGN.md 5).

    N, M, nu, plane and load model are those of ``ops``.

    Args:
        ops: operators to update.
        slots: particle indices ``[K]`` to rebuild.
        verts, n_verts, radius: the new shapes ``[K, V, 2]``, ``[K]``, ``[K]``, as in
            ``build_operators``.
        batch_size: as in ``build_operators``.

    Returns:
        A new ``BemOperators`` (the input is unchanged).
    """
    slots = np.asarray(slots, dtype=np.int64).reshape(-1)
    P = ops.lengths.shape[0]
    if len(slots) and (slots.min() < 0 or slots.max() >= P):
        raise ValueError(f"slots must lie in [0, {P}), got {slots.min()}..{slots.max()}")
    if len(np.unique(slots)) != len(slots):
        raise ValueError("slots must not repeat")
    if len(slots) == 0:
        return ops
    plane = ops.plane
    nu = float(ops.poisson_ratio)
    new = build_operators(
        jnp.asarray(verts, ops.nodes.dtype),
        n_verts,
        radius,
        n_elements=ops.lengths.shape[1],
        n_points=ops.points.shape[1],
        poisson_ratio=nu,
        plane=plane,
        load_model=ops.load_model,
        batch_size=batch_size,
    )
    idx = jnp.asarray(slots)
    return jax.tree_util.tree_map(
        lambda old, fresh: old if old.ndim == 0 else old.at[idx].set(fresh), ops, new
    )


def psi_batched(
    ops: BemOperators,
    contact_points: jax.Array,
    contact_forces: jax.Array,
    contact_mask: jax.Array,
    *,
    thickness: float | jax.Array = 1.0,
    poisson_ratio: float | jax.Array | None = None,
    plane: Plane | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Stress and psi at the sample points of all particles (jit-able, differentiable).

    Contacts should lie on the outline (no check under jit: ``stress_field`` checks that for
    one particle). With ``load_model="flamant"`` psi grows
    like 1/distance towards each contact, as the connection-point search expects.

    Args:
        ops: operators from ``build_operators``.
        contact_points: ``[P, C, 2]`` (m), body frame, on each outline.
        contact_forces: ``[P, C, 2]`` (N), body frame, acting on the particle.
        contact_mask: ``[P, C]`` real contacts.
        thickness: t (m), scalar or ``[P]``.
        poisson_ratio: nu for psi (default: the operators' nu).
        plane: for psi (default: the operators' plane).

    Returns:
        ``(sigma [P, M, 3] (Pa), psi [P, M] (Pa))``; zero at masked points.
    """
    nu = ops.poisson_ratio if poisson_ratio is None else poisson_ratio
    plane = ops.plane if plane is None else plane
    _check_plane(plane)
    thickness = jnp.broadcast_to(jnp.asarray(thickness), ops.lengths.shape[:1])
    stress = jax.vmap(
        lambda k, nodes, c, ang, pts, cp, cf, cm: _contact_stress(
            k, nodes, c, ang, pts, cp, cf, cm, ops.load_model
        )
    )(
        ops.stress_per_force,
        ops.nodes,
        ops.centres,
        ops.node_angles,
        ops.points,
        contact_points,
        contact_forces,
        contact_mask,
    )
    keep = ops.point_mask & ops.valid[:, None]
    sigma = jnp.where(keep[..., None], stress / thickness[:, None, None], 0.0)
    psi = equivalent_stress(sigma, nu, plane)
    return sigma, jnp.where(keep, psi, 0.0)


# ---------------------------------------------------------------------------------------------
# screening: a rigorous upper bound of psi, then the exact field only where it can matter
# ---------------------------------------------------------------------------------------------


def _equilibrate_flat(x, f, mask, particle, n_particles):
    """``_equilibrate`` for a flat contact list: forces ``[S, 2]`` at ``x [S, 2]`` of
    particles ``particle [S]``, each particle corrected with its own contacts. Kept apart
    from ``_equilibrate``: routing the padded path through these segment sums made
    ``psi_batched`` 40 % slower (4.5 -> 6.5 ms, 1,000 particles, float32); the two are
    checked equal by ``tests/test_bem.py::test_flat_bound_equals_padded_bound``."""
    m = mask.astype(f.dtype)[:, None]
    f = m * f

    def seg(v):
        return jax.ops.segment_sum(v, particle, num_segments=n_particles)

    count = seg(mask.astype(jnp.int32))
    nn = jnp.maximum(count, 1).astype(f.dtype)[:, None]
    f1 = f - m * (seg(m * f) / nn)[particle]
    dx = m * (x - (seg(m * x) / nn)[particle])
    omega = -_safe_div(seg(_cross2(dx, f1)), seg(_dot(dx, dx)))
    f2 = f1 + omega[particle][:, None] * _perp(dx)
    return jnp.where((count >= 2)[particle][:, None], f2, f)


def _direction_weights(f):
    """``[K]`` weights w with sum_k w_k h_k a bound at the force ``f [2]`` of any function h
    known at the K directions u_k of ``_half_turn_directions`` that is even, subadditive and
    positively homogeneous in the force (a maximum of |u . v| over vectors v, or of norms of
    linear maps of u): with f (or -f, turned into the upper half-plane) = alpha u_k +
    beta u_(k+1), alpha, beta >= 0 (u_K = -u_0), w_k = alpha and w_(k+1) = beta. No
    trigonometry: the sector and the coefficients come from cross products."""
    K = _SCREEN_DIRECTIONS
    flip = (f[1] < 0) | ((f[1] == 0) & (f[0] < 0))
    g = jnp.where(flip, -f, f)
    u = _half_turn_directions(f.dtype)
    ue = jnp.concatenate([u, -u[:1]], axis=0)  # [K + 1, 2]
    c = ue[:, 0] * g[1] - ue[:, 1] * g[0]  # cross(u_k, g): >= 0 iff g is at or past u_k
    sector = (c[:-1] >= 0) & (c[1:] < 0)  # [K]: g lies in [u_k, u_(k+1))
    inv = 1.0 / math.sin(math.pi / K)
    alpha = jnp.where(sector, jnp.maximum(-c[1:], 0.0) * inv, 0.0)
    beta = jnp.where(sector, jnp.maximum(c[:-1], 0.0) * inv, 0.0)
    return alpha + jnp.roll(beta, 1)


def _flamant_near(a, b, cp, f, wts, d_min, support, c_uniaxial):
    """Bound of psi of a contact's Flamant field (Pa x thickness) over the points whose least
    distance to the chord ``a``-``b`` of its element is ``d_min`` (``[G]`` or scalar):
    (2 / pi) psi(unit uniaxial) (``support`` (``[G, K]`` or ``[K]``) interpolated at the force
    by ``wts`` + |F| delta / (d_min - delta)^2). The margin: the inversion w -> w / |w|^2
    changes by at most |dx| / (d - |dx|)^2 when the load moves by |dx| <= delta = (half the
    chord samples' spacing) + eta, with eta the contact's distance from the chord. +inf where
    delta is not below d_min (a contact deep inside, or far off the chord)."""
    ab = b - a
    le = jnp.maximum(_safe_norm(ab, fused=True), 1e-300)
    t = jnp.clip(_dot(cp - a, ab) / (le * le), 0.0, 1.0)
    delta = 0.5 * le / _CHORD_SAMPLES + _safe_norm(cp - a - t * ab, fused=True)
    ok = d_min > delta
    gap = jnp.where(ok, d_min - delta, 1.0)
    near = (
        (2.0 / math.pi)
        * c_uniaxial
        * (_dot(support, wts) + _safe_norm(f, fused=True) * delta / (gap * gap))
    )
    return jnp.where(ok, near, jnp.inf)


def _bound_terms(table, nodes, centre, e, n_el, cp, f, c_uniaxial, flamant):
    """Per contact and point group, the bound of its psi (Pa x thickness), ``[G]``.

    psi is a norm of the stress (``_psi_form``), and the stress is a sum over contacts of
    (hat-blended operator block) . force plus, for ``flamant``, the Flamant field of the
    force, whose psi at a point p is (2 / pi) |F . e| / rho x psi(unit uniaxial stress), with
    rho e = p - x_c. The triangle inequality over contacts and the per-group numbers of
    ``_screen_tables`` bound the whole field: the remainder by the directional values of
    the two blended elements, the Flamant part by the directional support of a load at the
    chord samples plus a Lipschitz margin (``_flamant_near``).
    ``f`` is the (equilibrated) force ``[2]``, ``e`` the contact's element (of N = ``n_el``);
    ``table(r)`` and ``nodes(k)`` return the particle's ``[G, 1 + 2 K]`` table row of element
    r and its node k (gathers from the arrays of all particles, so that only the rows used are
    read); ``centre`` is the particle's.
    """
    K = _SCREEN_DIRECTIONS
    _, lo, w = _contact_elements(
        cp[None], nodes, centre, None, e=e[None], n_elements=n_el, fused=True
    )
    lo, w = lo[0], w[0]
    fm = _safe_norm(f, fused=True)
    wts = _direction_weights(f)  # [K]

    row_lo, row_hi = table(lo), table((lo + 1) % n_el)  # e is one of the two

    def remainder(row):
        return _dot(row[:, 1 : 1 + K], wts)

    per = (1.0 - w) * remainder(row_lo) + w * remainder(row_hi)  # [G]
    if flamant:
        row = jnp.where(e == lo, row_lo, row_hi)
        a, b = nodes(e), nodes((e + 1) % n_el)
        per = per + _flamant_near(a, b, cp, f, wts, row[:, 0], row[:, 1 + K :], c_uniaxial)
    return jnp.where(fm > 0, per, 0.0)


def _flat_elements(ops, particle, cp, contact_mask):
    """The element ``[S]`` holding each contact of a flat list (``_binned_element`` when every
    particle's bins are exact, else the comparison with every node)."""

    def binned(_):
        return jax.vmap(
            lambda i, x: _binned_element(
                x, ops.centres[i], lambda k: ops.node_angles[i, k], ops.angle_bins[i]
            )
        )(particle, cp)

    def compared(_):
        return jax.vmap(
            lambda i, x: _contact_elements(
                x[None], lambda k: ops.nodes[i, k], ops.centres[i], ops.node_angles[i]
            )[0][0]
        )(particle, cp)

    exact_bins = jnp.all(~contact_mask | (ops.angle_bins[particle, 0] >= 0))
    return lax.cond(exact_bins, binned, compared, None)


class _FlatLoads(NamedTuple):
    """A flat contact list ready for the bounds: particle ``[S]`` (int32), points ``[S, 2]``
    and equilibrated forces ``[S, 2]`` in the tables' dtype, mask ``[S]``, element ``[S]``."""

    particle: jax.Array
    points: jax.Array
    forces: jax.Array
    mask: jax.Array
    element: jax.Array


def _flat_loads(ops, particle, contact_points, contact_forces, contact_mask) -> _FlatLoads:
    """The bounds' common start (computed once for both levels of ``screen``)."""
    dtype = ops.screen_table.dtype
    particle = jnp.asarray(particle, jnp.int32)
    cp = contact_points.astype(dtype)
    n = ops.lengths.shape[0]
    f = _equilibrate_flat(cp, contact_forces.astype(dtype), contact_mask, particle, n)
    e = _flat_elements(ops, particle, cp, contact_mask)
    return _FlatLoads(particle, cp, f, contact_mask, e)


def _c_uniaxial(ops):
    """psi of a unit uniaxial stress, in the tables' dtype."""
    unit = jnp.array([1.0, 0.0, 0.0], ops.screen_table.dtype)
    return equivalent_stress(unit, ops.poisson_ratio, ops.plane)


def _per_particle(ops, b, thickness):
    """Sums per particle (Pa x thickness) -> bounds (Pa), with a relative margin of 1000
    machine epsilons for rounding; 0 for invalid slots."""
    dtype = b.dtype
    thickness = jnp.broadcast_to(jnp.asarray(thickness, dtype), b.shape)
    b = jnp.where(ops.valid, b / thickness, 0.0)
    return b * (1.0 + 1000.0 * jnp.finfo(dtype).eps)


def _coarse_term(row, a, b, cp, f, c_uniaxial, flamant):
    """One contact's share of ``psi_bound_coarse`` (Pa x thickness): ``row`` its element's
    ``_coarse_rows`` row, ``a``, ``b`` the element's nodes, ``f`` the equilibrated force."""
    K = _SCREEN_DIRECTIONS
    wts = _direction_weights(f)
    per = _dot(row[1 : 1 + K], wts)
    if flamant:
        per = per + _flamant_near(a, b, cp, f, wts, row[0], row[1 + K :], c_uniaxial)
    return jnp.where(_safe_norm(f, fused=True) > 0, per, 0.0)


def psi_bound_coarse(
    ops: BemOperators,
    particle: jax.Array,
    contact_points: jax.Array,
    contact_forces: jax.Array,
    contact_mask: jax.Array,
    *,
    thickness: float | jax.Array = 1.0,
) -> jax.Array:
    """A cheaper, looser upper bound of the largest psi of every particle (Pa), ``[P]``.

    The sum over contacts of each contact's bound over all the sample points (one row of
    ``ops.screen_coarse`` per contact), where ``psi_bound_flat`` takes the largest over the
    point groups of the sums. It is never below ``psi_bound_flat`` (so never below the
    field); ``screen`` uses it to pick the particles that get the finer bound. Arguments as
    in ``psi_bound_flat``.
    """
    loads = _flat_loads(ops, particle, contact_points, contact_forces, contact_mask)
    return _per_particle(ops, _coarse_sums(ops, loads), thickness)


def _coarse_sums(ops, loads: _FlatLoads):
    """``psi_bound_coarse`` before the division by the thickness, ``[P]``."""
    P, dtype = ops.lengths.shape[0], loads.points.dtype
    n_el = ops.node_angles.shape[1]
    if ops.screen_coarse.shape[1] != n_el:  # operators without the rows (bound_operators)
        count = jax.ops.segment_sum(loads.mask.astype(jnp.int32), loads.particle, num_segments=P)
        return jnp.where(ops.valid & (count > 0), jnp.inf, 0.0).astype(dtype)
    c_uni = _c_uniaxial(ops)
    terms = jax.vmap(
        lambda i, r, x, g: _coarse_term(
            ops.screen_coarse[i, r],
            ops.nodes[i, r],
            ops.nodes[i, (r + 1) % n_el],
            x,
            g,
            c_uni,
            ops.load_model == "flamant",
        )  # fmt: skip
    )(loads.particle, loads.element, loads.points, loads.forces)
    terms = jnp.where(loads.mask, terms, 0.0)
    return jax.ops.segment_sum(terms, loads.particle, num_segments=P)


def psi_bound_flat(
    ops: BemOperators,
    particle: jax.Array,
    contact_points: jax.Array,
    contact_forces: jax.Array,
    contact_mask: jax.Array,
    *,
    thickness: float | jax.Array = 1.0,
) -> jax.Array:
    """``psi_bound`` for a flat contact list ``[S]`` (cost grows with S, not with P x the
    longest contact list): ``particle [S]`` (int) the slot each contact belongs to,
    ``contact_points``, ``contact_forces`` ``[S, 2]`` in that particle's body frame,
    ``contact_mask [S]``. Returns ``[P]`` (Pa)."""
    loads = _flat_loads(ops, particle, contact_points, contact_forces, contact_mask)
    return _per_particle(ops, _fine_sums(ops, loads), thickness)


def _fine_sums(ops, loads: _FlatLoads):
    """``psi_bound_flat`` before the division by the thickness, ``[P]``."""
    P = ops.lengths.shape[0]
    flamant = ops.load_model == "flamant"
    n_el = ops.node_angles.shape[1]
    c_uni = _c_uniaxial(ops)
    terms = jax.vmap(
        lambda i, x, g, e: _bound_terms(
            lambda r: ops.screen_table[i, r],
            lambda k: ops.nodes[i, k],
            ops.centres[i],
            e,
            n_el,
            x,
            g,
            c_uni,
            flamant,
        )  # fmt: skip
    )(loads.particle, loads.points, loads.forces, loads.element)
    terms = jnp.where(loads.mask[:, None], terms, 0.0)
    return jnp.max(jax.ops.segment_sum(terms, loads.particle, num_segments=P), axis=1)


def psi_bound(
    ops: BemOperators,
    contact_points: jax.Array,
    contact_forces: jax.Array,
    contact_mask: jax.Array,
    *,
    thickness: float | jax.Array = 1.0,
) -> jax.Array:
    """Upper bound of the largest psi over the sample points of every particle (Pa), jit-able.

    Guaranteed (up to rounding, covered by a relative margin of 1000 machine epsilons):
    ``psi_bound(...) >= psi_batched(...)[1].max(axis=1)`` for the operators' nu and plane. It
    reads a few numbers per contact (``ops.screen_table``) instead of the ``[2, M, 3]``
    operator blocks, so it costs a small fraction of ``psi_batched``. It is +inf for a
    contact that is not on the far side of its element's chord from the points (a contact
    point pushed deep into the particle), so such a particle is never screened out.
    Arguments as in ``psi_batched``; masked slots cost as much as real contacts (see
    ``psi_bound_flat`` for a flat list).

    Returns:
        ``[P]`` (Pa); 0 for particles without contacts or without a valid outline.
    """
    P, C = contact_mask.shape
    particle = jnp.repeat(jnp.arange(P, dtype=jnp.int32), C)
    return psi_bound_flat(
        ops,
        particle,
        contact_points.reshape(P * C, 2),
        contact_forces.reshape(P * C, 2),
        contact_mask.reshape(P * C),
        thickness=thickness,
    )


# the fields of BemOperators that psi_bound / psi_bound_flat read
BOUND_FIELDS = ("nodes", "centres", "node_angles", "angle_bins", "screen_table", "valid")


def bound_operators(
    *,
    nodes: ArrayLike,
    centres: ArrayLike,
    node_angles: ArrayLike,
    angle_bins: ArrayLike,
    screen_table: ArrayLike,
    valid: ArrayLike,
    poisson_ratio: float | ArrayLike,
    plane: Plane,
    load_model: LoadModel,
) -> BemOperators:
    """Operators that carry only what ``psi_bound`` reads (``BOUND_FIELDS``).

    The screening tables of P particles take ``P x N x ((1 + 2 K) G + 7)`` numbers, against
    ``P x N x 6 M`` for the whole operator, so every particle of a large packing can keep
    its tables while the full operators are built (and cached) only for the particles that
    pass the bound. The other fields hold size-1 placeholders: such operators must not be
    given to ``psi_batched`` or ``screen``.

    Args:
        nodes ``[P, N, 2]``, centres ``[P, 2]``, node_angles ``[P, N]``, angle_bins
        ``[P, 4 N]``, screen_table ``[P, N, G, 1 + 2 K]``, valid ``[P]``: the same fields of
        operators from ``build_operators`` (stacked rows of several builds are fine).
        poisson_ratio, plane, load_model: those of the builds.
    """
    _check_plane(plane)
    _check_load_model(load_model)
    nodes = jnp.asarray(nodes)
    P, N = nodes.shape[:2]
    dt = nodes.dtype
    return BemOperators(
        nodes=nodes,
        midpoints=nodes,
        normals=nodes,
        lengths=jnp.zeros((P, N), dt),
        points=jnp.zeros((P, 1, 2), dt),
        point_mask=jnp.zeros((P, 1), bool),
        grid_index=jnp.zeros((P, 1, 2), jnp.int32),
        spacing=jnp.zeros((P,), dt),
        stress_per_force=jnp.zeros((P, 1, 2, 1, 3), dt),
        valid=jnp.asarray(valid, bool),
        centres=jnp.asarray(centres, dt),
        node_angles=jnp.asarray(node_angles, dt),
        screen_table=jnp.asarray(screen_table, dt),
        # not carried: psi_bound_coarse is then +inf for every loaded particle (still exact)
        screen_coarse=jnp.zeros((P, 1, 1 + 2 * _SCREEN_DIRECTIONS), dt),
        angle_bins=jnp.asarray(angle_bins),
        poisson_ratio=jnp.asarray(poisson_ratio, dt),
        plane=plane,
        load_model=load_model,
    )


class Screening(NamedTuple):
    """Result of ``screen`` (P particles, K candidate slots, M sample points).

    Attributes:
        bound: ``[P]`` upper bound of each particle's largest psi (Pa), ``psi_bound``.
        candidates: ``[K]`` particle indices, largest ``bound / threshold`` first.
        is_candidate: ``[K]`` bound >= threshold (the others fill the slots).
        sigma: ``[K, M, 3]`` stress of the particles in ``candidates`` (Pa), as
            ``psi_batched``; zeros when no particle passes the bound (the field is then not
            computed).
        psi: ``[K, M]`` psi of the particles in ``candidates`` (Pa), as ``psi_batched``;
            zeros when no particle passes the bound.
        reaches: ``[K]`` candidate whose largest psi reaches the threshold.
        n_candidates: number of particles with bound >= threshold (scalar int).
        max_contacts: most real contacts of a particle in ``candidates`` (scalar int).
        complete: ``n_candidates <= K`` (every particle not in ``candidates`` has psi below
            the threshold at every sample point) and every candidate's contacts were used
            (and, with the coarse level, every particle it passed got the fine bound).
        n_coarse: number of particles whose coarse bound (``psi_bound_coarse``) reaches the
            threshold (P without the coarse level).
        n_fine_contacts: real contacts of the particles given the fine bound (0 without the
            coarse level).
    """

    bound: jax.Array
    candidates: jax.Array
    is_candidate: jax.Array
    sigma: jax.Array
    psi: jax.Array
    reaches: jax.Array
    n_candidates: jax.Array
    max_contacts: jax.Array
    complete: jax.Array
    n_coarse: jax.Array
    n_fine_contacts: jax.Array


def _flat_contacts(contact_points, contact_forces, contact_mask):
    """The real contacts of padded lists as a flat list (host), padded to a power of two
    (at least 8) so that the compiled bound is reused: (particle, points, forces, mask)."""
    mask = np.asarray(contact_mask, bool)
    rows, cols = np.nonzero(mask)
    size = _pow2(len(rows), 8)
    pad = size - len(rows)
    cp, cf = np.asarray(contact_points), np.asarray(contact_forces)
    return (
        np.concatenate([rows, np.zeros(pad, int)]).astype(np.int32),
        np.concatenate([cp[rows, cols], np.zeros((pad, 2), cp.dtype)]),
        np.concatenate([cf[rows, cols], np.zeros((pad, 2), cf.dtype)]),
        np.arange(size) < len(rows),
    )


def _compact(contact_points, contact_forces, contact_mask, c_keep):
    """Real contacts of padded lists ``[K, C]`` moved to the first ``c_keep`` slots: (points,
    forces, mask, every list fits, real contacts per list)."""
    n_real = jnp.sum(contact_mask, axis=1)
    if c_keep is None or c_keep >= contact_mask.shape[1]:
        return contact_points, contact_forces, contact_mask, jnp.asarray(True), n_real
    order = jnp.argsort(~contact_mask, axis=1, stable=True)[:, :c_keep]
    return (
        jnp.take_along_axis(contact_points, order[..., None], axis=1),
        jnp.take_along_axis(contact_forces, order[..., None], axis=1),
        jnp.take_along_axis(contact_mask, order, axis=1),
        jnp.all(n_real <= c_keep),
        n_real,
    )


def _select_contacts(loads: _FlatLoads, chosen, size):
    """The contacts of ``loads`` whose particle is ``chosen [P]``, moved in order to the front
    of lists of ``size`` slots: (``_FlatLoads`` of the lists, how many there are; the lists
    hold them all if that is <= ``size``)."""
    take = loads.mask & chosen[loads.particle]
    dest = jnp.where(take, jnp.cumsum(take) - 1, size)  # size: dropped

    def put(val):
        return jnp.zeros((size, *val.shape[1:]), val.dtype).at[dest].set(val, mode="drop")

    picked = _FlatLoads(*(put(v) for v in loads._replace(mask=take)))
    return picked, jnp.sum(take).astype(jnp.int32)


def _screen_core(
    ops, contact_points, contact_forces, contact_mask, threshold, thickness, k, flat=None,
    c_keep=None, s_fine=None,
):  # fmt: skip
    """The levels of ``screen`` for K = ``k`` candidate slots (jit-able); ``flat``: the
    same contacts as ``_flat_contacts`` (the bound then costs per real contact); ``c_keep``:
    the candidates' field is taken over their real contacts moved to the first ``c_keep``
    slots (fewer padded slots to process; ``complete`` is False if one has more);
    ``s_fine`` (with ``flat``): the coarse bound first, then the fine bound only for the
    particles whose coarse bound reaches the threshold, over their real contacts moved into
    ``s_fine`` slots (``complete`` is False if they overflow)."""
    P = ops.lengths.shape[0]
    dtype = ops.screen_table.dtype
    thickness = jnp.broadcast_to(jnp.asarray(thickness, dtype), (P,))
    threshold = jnp.broadcast_to(jnp.asarray(threshold, dtype), (P,))
    coarse_done = jnp.asarray(True)
    n_coarse = jnp.asarray(P, jnp.int32)
    n_fine = jnp.asarray(0, jnp.int32)
    if flat is None:
        bound = psi_bound(ops, contact_points, contact_forces, contact_mask, thickness=thickness)
    elif s_fine is None:
        bound = psi_bound_flat(ops, *flat, thickness=thickness)
    else:
        loads = _flat_loads(ops, *flat)
        coarse = _per_particle(ops, _coarse_sums(ops, loads), thickness)
        # a mask, not a top k: a top_k over P is a sort (0.13 ms for 1,000 particles on CPU)
        chosen = coarse / threshold >= 1.0
        sel, n_fine = _select_contacts(loads, chosen, s_fine)
        fine = _per_particle(ops, _fine_sums(ops, sel), thickness)
        bound = jnp.where(chosen, jnp.minimum(coarse, fine), coarse)
        n_coarse = jnp.sum(chosen).astype(jnp.int32)
        coarse_done = n_fine <= s_fine
    ratio = bound / threshold
    passing = ratio >= 1.0
    n_cand = jnp.sum(passing)
    # the first k passing particles in slot order (cumulative sum and scatter, no sort over
    # P), then sorted by ratio; the slots past n_cand repeat a particle and are not candidates
    (first,) = jnp.nonzero(passing, size=k, fill_value=0)
    key = jnp.where(jnp.arange(k) < n_cand, ratio[first], -jnp.inf)
    top, order = lax.top_k(key, k)
    idx = first[order]
    cp_k, cf_k, cm_k, fits, n_real = _compact(
        contact_points[idx], contact_forces[idx], contact_mask[idx], c_keep
    )
    keep = ops.point_mask[idx] & ops.valid[idx][:, None]
    n_cand = jnp.sum(ratio >= 1.0)

    def field(_):
        stress = _chosen_stress(ops, idx, cp_k.astype(dtype), cf_k.astype(dtype), cm_k)
        sigma = jnp.where(keep[..., None], stress / thickness[idx][:, None, None], 0.0)
        psi = jnp.where(keep, equivalent_stress(sigma, ops.poisson_ratio, ops.plane), 0.0)
        return sigma, psi

    def nothing(_):
        return jnp.zeros((*keep.shape, 3), dtype), jnp.zeros(keep.shape, dtype)

    # most screenings of a loaded packing find no candidate: the field is then skipped
    sigma, psi = lax.cond(n_cand > 0, field, nothing, None)
    is_cand = top >= 1.0
    return Screening(
        bound=bound,
        candidates=idx,
        is_candidate=is_cand,
        sigma=sigma,
        psi=psi,
        reaches=is_cand & (jnp.max(psi, axis=1) >= threshold[idx]),
        n_candidates=n_cand,
        max_contacts=jnp.max(n_real),
        complete=(n_cand <= k) & fits & coarse_done,
        n_coarse=n_coarse,
        n_fine_contacts=n_fine,
    )


_screen_jit = eqx.filter_jit(_screen_core)


def screen(
    ops: BemOperators,
    contact_points: ArrayLike,
    contact_forces: ArrayLike,
    contact_mask: ArrayLike,
    threshold: float | ArrayLike,
    *,
    thickness: float | ArrayLike = 1.0,
    max_candidates: int = 64,
    fine_slots: int | None = 1024,
) -> Screening:
    """Which particles can reach psi >= ``threshold``, with their exact field (host call).

    Three levels, each run only where the one before cannot rule a particle out: the coarse
    bound ``psi_bound_coarse`` for every particle (one table row read per real contact), the
    finer ``psi_bound_flat`` for the particles whose coarse bound reaches the threshold,
    then ``psi_batched``'s field only for the particles whose bound reaches it. The answer
    is the same as thresholding ``psi_batched`` of all particles: particles left out are
    proven below the threshold. If a level's slots cannot hold what the level before passes
    (contacts of the fine level, particles of the field), the call is repeated with the next
    power of two at or above their count (the K used is ``Screening.candidates.shape[0]``,
    the fine level's contacts ``Screening.n_fine_contacts``; each size compiles once), so
    nothing is cut. A loop that screens every step can pass the sizes the last call settled
    on: the cost of each level follows its slots, filled or not. The candidates' bound and
    field run over their real contacts only (padded to a power of two, at least 8 slots or
    the list's length).

    Args:
        ops, contact_points, contact_forces, contact_mask, thickness: as in ``psi_batched``.
        threshold: psi threshold (Pa), scalar or ``[P]``, > 0.
        max_candidates: K, candidate slots of the first attempt (static: one compilation
            per K).
        fine_slots: contact slots of the fine level in the first attempt (static); None,
            or at least as many as the flat list of real contacts holds, skips the coarse
            level and bounds every particle finely.

    Returns:
        ``Screening``.
    """
    thr = np.asarray(threshold, dtype=float)
    if not np.all(np.isfinite(thr)) or np.any(thr <= 0):
        raise ValueError("threshold must be finite and > 0")
    if fine_slots is not None and int(fine_slots) < 1:
        raise ValueError(f"fine_slots must be >= 1 or None, got {fine_slots}")
    P = ops.lengths.shape[0]
    k = max(1, min(int(max_candidates), P))
    dtype = ops.screen_table.dtype
    args = (
        ops,
        jnp.asarray(contact_points, dtype),
        jnp.asarray(contact_forces, dtype),
        jnp.asarray(contact_mask, bool),
        jnp.asarray(thr, dtype),
        jnp.asarray(thickness, dtype),
    )
    flat = tuple(jnp.asarray(x) for x in _flat_contacts(*args[1:4]))
    c_max = args[3].shape[1]
    c_keep = min(c_max, 8)

    def fine(slots):  # None: the fine bound of every contact costs no more than the slots
        return None if slots is None or slots >= flat[0].shape[0] else int(slots)

    s1 = fine(fine_slots)
    while True:
        res = _screen_jit(*args, k, flat, c_keep, s1)
        if bool(res.complete):
            return res
        if s1 is not None and int(res.n_fine_contacts) > s1:
            s1 = fine(_pow2(int(res.n_fine_contacts), 1))
        elif int(res.n_candidates) > k:
            k = min(P, _pow2(int(res.n_candidates), 1))
        c_keep = max(c_keep, min(c_max, _pow2(int(res.max_contacts), 1)))
