"""Narrow phase and contact law for 2D spheropolygons, and particle-wall contacts.

The classic split is kept visible: **geometry** (closest features, overlap, normal, contact
point) -> **mixing** (pair effective mass) -> **law** (linear spring-dashpot + Cundall-Strack
friction) -> **history** update.

Geometry (Alonso-Marroquin 2008; paper 002 §2.1 in 3D): every vertex of one core polygon is
tested against the other core polygon. Its closest point on that polygon is either inside an
edge (vertex-edge contact, normal = the edge's outward normal, so a vertex that has crossed
the core edge still gets a restoring force) or a vertex (vertex-vertex contact, normal along
the two vertices). Taking the closest feature, not every edge in range, avoids the 4x
stiffness of coincident corners (PHYSICS §D pitfall). Both directions are tested and every
vertex keeps its contact, weighted by :func:`corner_weight` so that two corners that meet
count as one contact without a jump in the energy (counting a vertex-vertex pair once by a
rule switched between one and two contacts at a finite overlap); a flat edge-edge contact
gives two contacts (one vertex of each at the ends of the overlap), as in the Minkowski-sum
picture. The elastic part of the law is the gradient of ``w (K_n delta^2 + K_t xi^2) / 2``.

Law (paper 002 Eq. 6-10): ``F_n = K_n delta - G_n m_e v_n`` (clamped >= 0: contacts do not
pull), ``F_t = -K_t xi - G_t m_e v_t`` capped at ``mu F_n`` (Cundall-Strack); the spring ``xi``
is kept per (pair, direction, vertex), projected onto the current tangent (magnitude kept) and
advanced by ``v_t dt``. When the cap acts, spring and dashpot are scaled by the same factor, so
slip never adds energy to the spring (with ``G_t = 0``, paper 002's law, this is the usual
``xi = -F_t / K_t``).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .state import Contacts, Params, Particles, Walls

Vec = tuple  # (x, y) pair of arrays of one shape

_TINY = 1e-30


def world_vertices(p: Particles) -> Array:
    """Core vertices in the world frame ``[P, V, 2]`` (m)."""
    c, s = jnp.cos(p.angle), jnp.sin(p.angle)
    x, y = p.verts[..., 0], p.verts[..., 1]
    wx = c[:, None] * x - s[:, None] * y + p.pos[:, 0:1]
    wy = s[:, None] * x + c[:, None] * y + p.pos[:, 1:2]
    return jnp.stack([wx, wy], axis=-1)


def closest_features(va: Array, na: Array, vb: Array, nb: Array):
    """Closest point on core polygon B of every vertex of core polygon A.

    For a convex polygon the closest feature of an outside point is found from the edge of
    largest signed distance ``h_k = (x - a_k) . n_k``: if the point projects inside that edge
    the contact is vertex-edge with gap ``h_k``; otherwise the closest point is the edge's end
    on that side (vertex-vertex, gap = distance). A point inside B gets its least-penetrated
    edge (the way out). Leading batch axes ``...`` are allowed (one pair or ``C`` pairs).

    Args:
        va, vb: world vertices ``[..., V, 2]`` (m), CCW, padded by repeating the last vertex.
        na, nb: real vertex counts ``[...]``.

    Returns:
        gap ``[..., V]``: signed distance from the vertex to B's core (m), negative if inside.
        normal ``[..., V, 2]``: unit vector from B towards the vertex.
        point ``[..., V, 2]``: closest point on B's core (m).
        vertex ``[..., V]``: index of B's vertex if the closest point is a vertex, else -1.
        valid ``[..., V]``: the vertex slot is real.
    """
    na, nb = jnp.asarray(na), jnp.asarray(nb)
    frames = _frames_soa(vb[..., 0], vb[..., 1], nb)
    gap, normal, point, vertex, valid, *_ = _closest_soa(
        va[..., 0], va[..., 1], na, vb[..., 0], vb[..., 1], nb, frames
    )
    return gap, jnp.stack(normal, axis=-1), jnp.stack(point, axis=-1), vertex, valid


def contact_law(
    overlap: Array,
    normal: Vec,
    v_rel: Vec,
    xi: Vec,
    m_eff: Array,
    active: Array,
    stiffness_n: Array,
    stiffness_t: Array,
    damping_n: Array,
    damping_t: Array,
    friction: Array,
    dt: Array,
    v_damp: Vec | None = None,
    energy: bool = False,
) -> tuple:
    """Linear spring-dashpot normal force and Cundall-Strack friction (paper 002 Eq. 6-10).

    Vectors are ``(x, y)`` pairs of arrays of one shape (structure of arrays: XLA's CPU
    backend handles a trailing axis of size 2 poorly).

    Args:
        overlap: delta (m), normal: unit normal towards the body receiving the force,
        v_rel: velocity of that body's material point minus the other's at the contact (m/s),
        xi: tangential spring from the previous step (m), m_eff: effective mass (kg),
        active: contact exists.
        v_damp: relative velocity used by the dashpots (default ``v_rel``). The integrator
            passes the half-step velocity as ``v_rel`` (the spring increment over the step is
            then centred) and a predicted end-of-step velocity here, which keeps the
            dissipation second order in dt.

    Returns: (force on the body (N), new xi (m), normal force magnitude F_n (N)), and with
    ``energy`` a fourth item, a dict of per-contact energies (J, on the thickness the
    stiffnesses refer to): ``elastic`` ``K_n delta^2 / 2 + K_t |xi|^2 / 2`` after the step,
    and what this step dissipated, ``dashpot`` (``-f_d . v_damp dt`` of the normal and
    tangential dashpots, where ``f_d`` is the dashpot's share of the applied force: normal,
    the force minus its spring part, so a force clamped at zero counts too; tangential,
    while the contact sticks) and ``slip`` (while it slips, the dashpot's share of the capped
    force plus what the spring loses beyond the work of its force,
    ``K_t (|xi_old|^2 - |xi_new|^2) / 2 + K_t xi_new . (xi_trial - xi_old)``, which in
    steady sliding is the force at the cap times the slip displacement).
    """
    nx, ny = normal
    vdx, vdy = v_rel if v_damp is None else v_damp
    vn_d = vdx * nx + vdy * ny
    vtdx, vtdy = vdx - vn_d * nx, vdy - vn_d * ny
    fn = stiffness_n * overlap - damping_n * m_eff * vn_d
    fn = jnp.where(active, jnp.maximum(fn, 0.0), 0.0)
    vx, vy = v_rel
    vn = vx * nx + vy * ny
    vtx, vty = vx - vn * nx, vy - vn * ny
    # rotate the spring into the current tangent plane, keeping its length
    xx, xy = xi
    xi_len = _norm(xx, xy)
    xin = xx * nx + xy * ny
    tx, ty = xx - xin * nx, xy - xin * ny
    t_len = _norm(tx, ty)
    scale = jnp.where(t_len > 0, xi_len / jnp.where(t_len > 0, t_len, 1.0), 0.0)
    ox, oy = tx * scale, ty * scale  # old spring in the current tangent plane
    xx = ox + vtx * dt
    xy = oy + vty * dt
    trial = (xx, xy)
    ftx = -stiffness_t * xx - damping_t * m_eff * vtdx
    fty = -stiffness_t * xy - damping_t * m_eff * vtdy
    ft_len = _norm(ftx, fty)
    cap = friction * fn
    slip = ft_len > cap
    shrink = jnp.where(slip, cap / jnp.where(slip, ft_len, 1.0), 1.0)
    ftx, fty = ftx * shrink, fty * shrink
    # slipping: the spring keeps its share of the capped force. (Resetting it to -F_t / K_t
    # instead would turn the dashpot's share into stored spring energy: a sticking contact
    # whose dashpot alone exceeds the cap would gain energy from nothing; the energy ledger
    # measured 24 % of the input so created in a quick Cantor oedometer.)
    xx = jnp.where(slip, shrink * xx, xx)
    xy = jnp.where(slip, shrink * xy, xy)
    fx = jnp.where(active, fn * nx + ftx, 0.0)
    fy = jnp.where(active, fn * ny + fty, 0.0)
    xi_new = (jnp.where(active, xx, 0.0), jnp.where(active, xy, 0.0))
    if not energy:
        return (fx, fy), xi_new, fn
    # the energy terms of this step (module docstring of jaxgran.energy)
    elastic = 0.5 * stiffness_n * overlap**2 + 0.5 * stiffness_t * (xx * xx + xy * xy)
    f_dn = fn - stiffness_n * overlap  # applied normal force minus its spring part
    d_normal = -f_dn * vn_d * dt
    # the tangential dashpot's share of the applied (possibly capped) force
    f_tdx = -shrink * damping_t * m_eff * vtdx
    f_tdy = -shrink * damping_t * m_eff * vtdy
    d_tangent = -(f_tdx * vtdx + f_tdy * vtdy) * dt
    # slipping, the force is mu F_n whatever its parts, so all of the tangential loss is
    # friction: the dashpot's share, and what the spring loses beyond the work of its force,
    # K_t (|xi_old|^2 - |xi_new|^2) / 2 + K_t xi_new . (xi_trial - xi_old) (>= 0; xi_old the
    # spring turned into the current tangent plane). In steady sliding that is the force at
    # the cap times the slip displacement; where the cap falls (a contact unloading, as
    # every contact with friction does before it opens) the force at the cap times the slip
    # displacement booked only part of the spring energy released, and the rest went
    # missing from the balance
    d_slip = d_tangent + stiffness_t * (
        0.5 * (ox * ox + oy * oy - xx * xx - xy * xy) + xx * (trial[0] - ox) + xy * (trial[1] - oy)
    )
    terms = {
        "elastic": jnp.where(active, elastic, 0.0),
        "dashpot": jnp.where(active, d_normal + jnp.where(slip, 0.0, d_tangent), 0.0),
        "slip": jnp.where(active & slip, d_slip, 0.0),
    }
    return (fx, fy), xi_new, fn, terms


def _norm(x: Array, y: Array) -> Array:
    """sqrt(x^2 + y^2) with a finite gradient at 0 (double-where)."""
    n2 = x * x + y * y
    ok = n2 > _TINY
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def _closest_soa(ax, ay, na, bx, by, nb, frames):
    """Structure-of-arrays core of :func:`closest_features` (arrays ``[..., V]``)."""
    k = jnp.arange(ax.shape[-1])
    nb_ = nb[..., None]
    enx, eny, etx, ety, elen = frames
    h = (ax[..., :, None] - bx[..., None, :]) * enx[..., None, :] + (
        ay[..., :, None] - by[..., None, :]
    ) * eny[..., None, :]
    h = jnp.where((k < nb_)[..., None, :], h, -jnp.inf)
    best = jnp.argmax(h, axis=-1)
    take = lambda x: jnp.take_along_axis(x, best, axis=-1)
    abx, aby, nbx, nby, tbx, tby, lb = (take(x) for x in (bx, by, enx, eny, etx, ety, elen))
    dx, dy = ax - abx, ay - aby
    s = dx * tbx + dy * tby
    interior = (s > 0.0) & (s < lb) & (nb_ >= 2)
    at_start = s <= 0.0
    wx = jnp.where(at_start, abx, abx + lb * tbx)
    wy = jnp.where(at_start, aby, aby + lb * tby)
    ex, ey = ax - wx, ay - wy
    dist = _norm(ex, ey)
    ok = dist > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, dist, 1.0), 0.0)
    ux = jnp.where(ok, ex * inv, nbx)
    uy = jnp.where(ok, ey * inv, nby)
    normal = (jnp.where(interior, nbx, ux), jnp.where(interior, nby, uy))
    gap = jnp.where(interior, dx * nbx + dy * nby, dist)
    point = (jnp.where(interior, abx + s * tbx, wx), jnp.where(interior, aby + s * tby, wy))
    nxt = jnp.where(best + 1 < nb_, best + 1, 0)
    vertex = jnp.where(interior, -1, jnp.where(at_start, best, nxt))
    valid = k < na[..., None]
    # distance along the edge to its nearer end, and d(that distance) / d(vertex position)
    near_start = s < lb - s
    s_end = jnp.where(interior, jnp.where(near_start, s, lb - s), 0.0)
    sign = jnp.where(near_start, 1.0, -1.0)
    return gap, normal, point, vertex, valid, s_end, (sign * tbx, sign * tby)


def _frames_soa(wx, wy, n_verts):
    k = jnp.arange(wx.shape[-1])
    n = n_verts[..., None]
    last = k + 1 < n
    nx_ = jnp.where(last, jnp.roll(wx, -1, axis=-1), wx[..., 0:1])
    ny_ = jnp.where(last, jnp.roll(wy, -1, axis=-1), wy[..., 0:1])
    ex, ey = nx_ - wx, ny_ - wy
    length = _norm(ex, ey)
    real = (k < n) & (length > 0)
    inv = jnp.where(real, 1.0 / jnp.where(real, length, 1.0), 0.0)
    tx, ty = ex * inv, ey * inv
    return ty, -tx, tx, ty, jnp.where(real, length, 0.0)


def _materialise(arrays: tuple) -> tuple:
    """The same arrays (all of one shape), computed once into memory. Without this XLA's
    CPU backend fuses a producer into each of its consumers and recomputes it there per
    element: the per-particle world vertices and edge frames (rotation, sqrt, division) into
    every gather of their per-pair copies (about 40 % of a contact step), and the
    closest-feature selects and the lever arms into every value of the contact law on the
    compacted list (about 40 % of the step of a small scene). A product with the identity is
    a library call that fusion does not enter (an optimization barrier is removed before
    fusion on CPU). It is exact for finite values; an infinite or NaN entry spreads to the
    same position of the others (``inf x 0``), so callers pass finite arrays."""
    stacked = jnp.stack(arrays)
    eye = jnp.eye(len(arrays), dtype=stacked.dtype)
    out = jnp.einsum("k...,kl->l...", stacked, eye, precision=jax.lax.Precision.HIGHEST)
    return tuple(out)


def _compacted(ok: Array, **arrays: Array) -> dict[str, Array]:
    """The per-entry inputs of the contact law on a compacted list (by name, one shape),
    zero where ``ok`` is False (the padding entries read the last slot, whose values may be
    infinite) and materialised (:func:`_materialise`): the law, the corner weights and the
    scatters then read them from memory instead of each recomputing the gathers and what
    feeds them."""
    zero = jnp.zeros((), next(iter(arrays.values())).dtype)
    out = _materialise(tuple(jnp.where(ok, a, zero) for a in arrays.values()))
    return dict(zip(arrays, out, strict=True))


def _pair_geometry_soa(wx, wy, nv, frames, i, j):
    """Both directions for pairs (i, j): i's vertices on j, then j's on i, stacked on a
    direction axis ``[C, 2, V]``. Every vertex keeps its closest-feature contact in both
    directions; the corner weights of :func:`corner_weight` keep the sum at one contact
    where two corners meet. Returns gap, normal, closest point, real-slot mask, whether the
    closest point is inside an edge, the distance along that edge to its nearer end and the
    unit vector along which that distance grows with the vertex position."""
    wx, wy, *frames = _materialise((wx, wy) + tuple(frames))
    fi = tuple(f[i] for f in frames)
    fj = tuple(f[j] for f in frames)
    xi_, yi_, ni = wx[i], wy[i], nv[i]
    xj_, yj_, nj = wx[j], wy[j], nv[j]
    g0, n0, q0, vx0, ok0, s0, d0 = _closest_soa(xi_, yi_, ni, xj_, yj_, nj, fj)
    g1, n1, q1, vx1, ok1, s1, d1 = _closest_soa(xj_, yj_, nj, xi_, yi_, ni, fi)
    st = lambda a, b: jnp.stack([a, b], axis=1)
    return (
        st(g0, g1),
        (st(n0[0], n1[0]), st(n0[1], n1[1])),
        (st(q0[0], q1[0]), st(q0[1], q1[1])),
        st(ok0, ok1),
        st(vx0 < 0, vx1 < 0),
        st(s0, s1),
        (st(d0[0], d1[0]), st(d0[1], d1[1])),
    )


def corner_weight(interior: Array, s_end: Array, overlap: Array, r_sum: Array):
    """Weight of one vertex contact, and its derivatives (``w``, ``dw/ds``, ``dw/ddelta``).

    Every vertex of both bodies keeps its contact with the other core (closest feature).
    Where two corners meet, the vertex of each sees the other body: counted in full both
    would double the stiffness, and counting the pair once (the earlier rule) switches
    between one and two contacts at a finite overlap, an energy jump of ``K_n delta^2 / 2``
    each time two corners slide past each other. Here a vertex-vertex contact weighs 1/2
    (its partner, the other vertex, weighs 1/2 too) and a vertex-edge contact weighs
    ``1/2 + S(s / beta) / 2``, ``S`` the C1 smoothstep, ``s`` the distance of the contact
    along the edge to its nearer end, ``beta = sqrt(2 R delta - delta^2)`` (``R`` the sum
    of the radii): 1/2 at the edge's end (continuous with the vertex-vertex weight) and 1
    beyond ``beta``, the distance beyond which the edge's end vertex, at the same height,
    no longer overlaps. A contact's energy is ``w (K_n delta^2 + K_t |xi|^2) / 2``; the
    forces include its gradient through ``w`` (so the law stays conservative) and the total
    stiffness where two corners meet is 1-1.15 contacts.
    """
    beta2 = jnp.maximum(2.0 * r_sum * overlap - overlap * overlap, 0.0)
    ok = interior & (beta2 > 0)
    beta = jnp.sqrt(jnp.where(ok, beta2, 1.0))
    t = jnp.where(ok, s_end / beta, 1.0)
    tc = jnp.clip(t, 0.0, 1.0)
    smooth = tc * tc * (3.0 - 2.0 * tc)
    slope = jnp.where(t < 1.0, 6.0 * tc * (1.0 - tc), 0.0)
    w = jnp.where(interior, 0.5 + 0.5 * jnp.where(ok, smooth, 1.0), 0.5)
    dw_ds = jnp.where(ok, 0.5 * slope / beta, 0.0)
    dw_dd = jnp.where(ok, -0.5 * slope * t * (r_sum - overlap) / beta2, 0.0)
    return w, dw_ds, dw_dd


def _soa_world(p: Particles):
    c, s = jnp.cos(p.angle)[:, None], jnp.sin(p.angle)[:, None]
    bx, by = p.verts[..., 0], p.verts[..., 1]
    wx = c * bx - s * by + p.pos[:, 0:1]
    wy = s * bx + c * by + p.pos[:, 1:2]
    return wx, wy, _frames_soa(wx, wy, p.n_verts)


def _compact(flags: Array, size: int) -> tuple[Array, Array]:
    """Indices of the true entries of the flat bool array ``flags`` in ascending order, padded
    with ``flags.size`` to ``size`` entries (``jnp.nonzero(flags, size=size)``), and their
    count. The prefix sum comes from triangular matmuls over blocks of 128 (exact in floats
    for fewer than 2^24 entries): XLA's CPU cumsum over 10^5-10^6 entries costs a few ms, a
    sizeable part of a contact step."""
    n = flags.shape[0]
    count = jnp.sum(flags)
    if n >= 2**24:
        return jnp.nonzero(flags, size=size, fill_value=n)[0], count
    w = 128
    x = jnp.pad(flags.astype(jnp.float32), (0, (-n) % w)).reshape(-1, w)
    tri = jnp.triu(jnp.ones((w, w), jnp.float32))
    inner = x @ tri  # inclusive prefix sum inside each block
    tot = inner[:, -1]
    r = tot.shape[0]
    t2 = jnp.pad(tot, (0, (-r) % w)).reshape(-1, w) @ tri
    off2 = jnp.cumsum(t2[:, -1]) - t2[:, -1]
    start = (t2 + off2[:, None]).reshape(-1)[:r] - tot  # exclusive offset of each block
    rank = (inner + start[:, None]).reshape(-1)[:n].astype(jnp.int32) - 1
    target = jnp.where(flags, rank, size)
    out = (
        jnp.full((size,), n, jnp.int32).at[target].set(jnp.arange(n, dtype=jnp.int32), mode="drop")
    )
    return out, count


def _spread(a: Array, slot: Array, shape: tuple) -> Array:
    """Values ``a [K, ...]`` of the compacted list back in the slot layout ``shape + ...``
    (zeros where no slot touches)."""
    n = math.prod(shape)
    out = jnp.zeros((n,) + a.shape[1:], a.dtype).at[slot].set(a, mode="drop")
    return out.reshape(shape + a.shape[1:])


def _pair_kernel(p: Particles, world, pairs: Array, xi: Array, params: Params, damp_velocity):
    """Contact forces of the pairs ``[C, 2]`` with history ``[2, C, 2, V]``.

    The closest-feature geometry is evaluated for every (pair, direction, vertex) slot, but
    only a few slots touch (about two per touching pair out of ``2 V``), so the slots in
    contact are compacted into a list of ``2 C`` entries (:func:`jnp.nonzero` with a fixed
    size) and the contact law, lever arms and relative velocities run on that list only. The
    list is full when more than ``2 C`` slots touch: ``overflow`` is then set and the host
    grows the pair capacity (so the list) and repeats the segment, as for a full pair list.

    Returns the force ``[P, 2]`` and torque ``[P]`` on every particle, the new history, the
    overflow flag and per-contact data in the slot layout ``[C, 2, V]``."""
    n_p = p.pos.shape[0]
    n_c, n_v = pairs.shape[0], p.verts.shape[1]
    wx, wy, frames = world
    pair_ok = pairs[:, 0] < n_p
    i = jnp.where(pair_ok, pairs[:, 0], 0)
    j = jnp.where(pair_ok, pairs[:, 1], 0)
    geo_ = _pair_geometry_soa(wx, wy, p.n_verts, frames, i, j)
    gap, (nx, ny), (qx, qy), keep, interior, s_end, (ex, ey) = geo_
    owner = jnp.stack([i, j], axis=1)  # [c, 2] body whose vertex is tested
    other = jnp.stack([j, i], axis=1)
    overlap = (p.radius[owner] + p.radius[other])[..., None] - gap
    both_active = (pair_ok & p.active[i] & p.active[j])[:, None, None]
    act = keep & (overlap > 0) & both_active

    # compaction: the touching slots, in slot order (so results do not depend on capacity)
    n_slots = act.size
    cap = 2 * n_c
    slot, n_touch = _compact(act.reshape(-1), cap)
    ok = slot < n_slots
    at = jnp.minimum(slot, n_slots - 1)
    take = lambda a: a.reshape(-1)[at]
    c_of = at // (2 * n_v)
    first = (at // n_v) % 2 == 0
    own = jnp.where(first, i[c_of], j[c_of])
    oth = jnp.where(first, j[c_of], i[c_of])
    ov, cnx, cny = take(overlap), take(nx), take(ny)
    r_oth = p.radius[oth]
    # contact point: middle of the overlap, measured from the other body's core
    off = r_oth - 0.5 * ov
    xcx, xcy = take(qx) + off * cnx, take(qy) + off * cny
    inv_m = jnp.where(p.fixed, 0.0, 1.0 / p.mass)
    m_eff = 1.0 / jnp.maximum(inv_m[own] + inv_m[oth], _TINY)
    rox, roy = xcx - p.pos[own, 0], xcy - p.pos[own, 1]
    rtx, rty = xcx - p.pos[oth, 0], xcy - p.pos[oth, 1]

    def rel_vel(vel, omega):
        wo, wt = omega[own], omega[oth]
        vx = vel[own, 0] - wo * roy - vel[oth, 0] + wt * rty
        vy = vel[own, 1] + wo * rox - vel[oth, 1] - wt * rtx
        return vx, vy

    v_rel = rel_vel(p.vel, p.omega)
    v_damp = v_rel if damp_velocity is None else rel_vel(*damp_velocity)
    flat_xi = xi.reshape(2, -1)
    # the law's inputs per entry, computed once (_compacted); zero on the padding entries
    dtype = ov.dtype
    damped = {} if damp_velocity is None else {"vdx": v_damp[0], "vdy": v_damp[1]}
    c = _compacted(
        ok,
        ov=ov, cnx=cnx, cny=cny, xcx=xcx, xcy=xcy, m_eff=m_eff,
        rox=rox, roy=roy, rtx=rtx, rty=rty, r_own=p.radius[own], r_oth=r_oth,
        xi0x=flat_xi[0, at], xi0y=flat_xi[1, at], interior=take(interior).astype(dtype),
        s_end=take(s_end), ex=take(ex), ey=take(ey), vx=v_rel[0], vy=v_rel[1], **damped,
    )  # fmt: skip
    ov, cnx, cny, xcx, xcy, m_eff = (c[k] for k in ("ov", "cnx", "cny", "xcx", "xcy", "m_eff"))
    rox, roy, rtx, rty, r_own, r_oth = (
        c[k] for k in ("rox", "roy", "rtx", "rty", "r_own", "r_oth")
    )
    v_rel = (c["vx"], c["vy"])
    v_damp = v_rel if damp_velocity is None else (c["vdx"], c["vdy"])
    (fx, fy), (xx, xy), fn, terms = contact_law(
        ov,
        (cnx, cny),
        v_rel,
        (c["xi0x"], c["xi0y"]),
        m_eff,
        ok,
        params.normal_stiffness,
        params.tangential_stiffness,
        params.normal_damping,
        params.tangential_damping,
        params.friction,
        params.dt,
        v_damp=v_damp,
        energy=True,
    )
    # corner weights (corner_weight) and the forces of their gradient: the energy
    # w e, e = (K_n delta^2 + K_t |xi|^2) / 2, depends on the vertex's position in the other
    # body's frame through delta (along n) and through s (along e_dir), so the owner gets
    # (w_d e) n - (w_s e) e_dir, applied at its vertex, and the other body the opposite
    r_sum = r_own + r_oth
    w, w_s, w_d = corner_weight(c["interior"] > 0.5, c["s_end"], ov, r_sum)
    w = jnp.where(ok, w, 0.0)
    e = 0.5 * (
        params.normal_stiffness * ov * ov + params.tangential_stiffness * (xx * xx + xy * xy)
    )
    e = jnp.where(ok, e, 0.0)
    gx = w_d * e * cnx - w_s * e * c["ex"]
    gy = w_d * e * cny - w_s * e * c["ey"]
    fx, fy, fn = w * fx + gx, w * fy + gy, w * fn
    terms = {k: w * v for k, v in terms.items()}
    # the along-edge part acts at the vertex, (r_own - delta / 2) n from the contact point
    lever = r_own - 0.5 * ov
    tx_, ty_ = -w_s * e * c["ex"], -w_s * e * c["ey"]
    couple = lever * (cnx * ty_ - cny * tx_)
    force = jnp.stack([fx, fy], axis=-1)
    f = jnp.zeros((n_p, 2), dtype).at[own].add(force).at[oth].add(-force)
    t = (
        jnp.zeros((n_p,), dtype)
        .at[own]
        .add(rox * fy - roy * fx + couple)
        .at[oth]
        .add(-(rtx * fy - rty * fx) - couple)
    )
    xi_new = jnp.zeros_like(flat_xi).at[:, slot].set(jnp.stack([xx, xy]), mode="drop")

    spread = lambda a: _spread(a, slot, act.shape)
    info = {
        "point": spread(jnp.stack([xcx, xcy], axis=-1)),
        "force": spread(force),
        "active": act,
        "normal_force": spread(fn),
        "energy": {k: jnp.sum(v) for k, v in terms.items()},
    }
    return (f, t), xi_new.reshape(xi.shape), n_touch > cap, info


def pair_forces(
    p: Particles, contacts: Contacts, params: Params, damp_velocity=None
) -> tuple[Array, Array, Array, dict]:
    """Forces and torques from all particle pairs in the Verlet list.

    ``damp_velocity``: optional ``(vel [P, 2], omega [P])`` used by the dashpots (see
    :func:`contact_law`); ``p.vel``, ``p.omega`` drive the tangential spring.

    Returns:
        force ``[P, 2]`` (N), torque ``[P]`` (N m), new tangential history ``[2, C, 2, V]``,
        and per-contact data (``point [C,2,V,2]``, ``force`` on the vertex owner
        ``[C,2,V,2]``, ``active [C,2,V]``, ``normal_force``, ``overflow``: more vertex
        contacts than the compacted list of ``2 C`` holds, see :func:`_pair_kernel`, and
        ``energy``: the sums over contacts of :func:`contact_law`'s energy terms, J) for
        post-processing (force chains, BEM loading, the energy ledger); under jit, unused
        outputs cost nothing.
    """
    (f, t), xi, overflow, info = _pair_kernel(
        p, _soa_world(p), contacts.pairs, contacts.xi, params, damp_velocity
    )
    return f, t, xi, info | {"overflow": overflow}


def wall_forces(
    p: Particles,
    walls: Walls,
    wall_xi: Array,
    params: Params,
    damp_velocity=None,
    capacity: int | None = None,
):
    """Forces between particle vertices (discs of radius ``radius``) and planar walls.

    ``capacity``: length of the compacted list of touching (particle, wall, vertex) slots on
    which the contact law runs (static; default: all ``P W V`` slots, never full). The step
    passes twice the pair capacity, so a full list (``overflow`` in the returned data) is
    grown with the pair list by the host.

    Returns force ``[P, 2]`` (N), torque ``[P]`` (N m), new history ``[2, P, W, V]``, force on
    each wall ``[W, 2]`` (N), and per-contact data (``point``/``force`` ``[P, W, V, 2]``,
    ``active``, ``normal_force`` ``[P, W, V]``, ``overflow``, ``energy`` as in
    :func:`pair_forces`).
    """
    c, s = jnp.cos(p.angle)[:, None], jnp.sin(p.angle)[:, None]
    bx, by = p.verts[..., 0], p.verts[..., 1]
    wx = (c * bx - s * by + p.pos[:, 0:1])[:, None, :]  # [P, 1, V]
    wy = (s * bx + c * by + p.pos[:, 1:2])[:, None, :]
    n_p, n_w, n_v = wx.shape[0], walls.point.shape[0], wx.shape[-1]
    e = lambda a: a[None, :, None]  # wall array [W] -> [1, W, 1]
    nx, ny = e(walls.normal[:, 0]), e(walls.normal[:, 1])
    relx, rely = wx - e(walls.point[:, 0]), wy - e(walls.point[:, 1])
    gap = relx * nx + rely * ny
    s_t = -relx * ny + rely * nx
    inside = (s_t >= e(walls.extent[:, 0])) & (s_t <= e(walls.extent[:, 1]))
    vert_ok = (jnp.arange(n_v)[None, :] < p.n_verts[:, None])[:, None, :]
    overlap = p.radius[:, None, None] - gap
    act = inside & vert_ok & (overlap > 0) & p.active[:, None, None] & e(walls.active)

    # the contact law runs on the touching slots only (see _pair_kernel)
    n_slots = act.size
    cap = n_slots if capacity is None else min(int(capacity), n_slots)
    slot, n_touch = _compact(act.reshape(-1), cap)
    ok = slot < n_slots
    at = jnp.minimum(slot, n_slots - 1)
    pi, wi, vi = at // (n_w * n_v), (at // n_v) % n_w, at % n_v
    ov = overlap.reshape(-1)[at]
    cnx, cny = walls.normal[wi, 0], walls.normal[wi, 1]
    off = p.radius[pi] - 0.5 * ov
    xcx, xcy = wx[pi, 0, vi] - off * cnx, wy[pi, 0, vi] - off * cny
    rx, ry = xcx - p.pos[pi, 0], xcy - p.pos[pi, 1]

    def rel_vel(vel, omega):
        w = omega[pi]
        return vel[pi, 0] - w * ry - walls.vel[wi, 0], vel[pi, 1] + w * rx - walls.vel[wi, 1]

    v_rel = rel_vel(p.vel, p.omega)
    v_damp = v_rel if damp_velocity is None else rel_vel(*damp_velocity)
    flat_xi = wall_xi.reshape(2, -1)
    mu_w = jnp.asarray(params.wall_friction)  # scalar, or one per wall [W]
    if mu_w.ndim == 1 and mu_w.shape[0] != n_w:  # static shapes: checked at trace time
        raise ValueError(f"wall_friction has {mu_w.shape[0]} values for {n_w} walls")
    # the law's inputs per entry, computed once (see _pair_kernel)
    damped = {} if damp_velocity is None else {"vdx": v_damp[0], "vdy": v_damp[1]}
    c = _compacted(
        ok,
        ov=ov, cnx=cnx, cny=cny, xcx=xcx, xcy=xcy, rx=rx, ry=ry, mass=p.mass[pi],
        xi0x=flat_xi[0, at], xi0y=flat_xi[1, at], vx=v_rel[0], vy=v_rel[1], **damped,
    )  # fmt: skip
    ov, cnx, cny, xcx, xcy, rx, ry = (c[k] for k in ("ov", "cnx", "cny", "xcx", "xcy", "rx", "ry"))
    v_rel = (c["vx"], c["vy"])
    v_damp = v_rel if damp_velocity is None else (c["vdx"], c["vdy"])
    (fx, fy), (xx, xy), fn, terms = contact_law(
        ov,
        (cnx, cny),
        v_rel,
        (c["xi0x"], c["xi0y"]),
        c["mass"],
        ok,
        params.normal_stiffness,
        params.tangential_stiffness,
        params.normal_damping,
        params.tangential_damping,
        mu_w if mu_w.ndim == 0 else mu_w[wi],
        params.dt,
        v_damp=v_damp,
        energy=True,
    )
    force = jnp.stack([fx, fy], axis=-1)
    f = jnp.zeros((n_p, 2), fx.dtype).at[pi].add(force)
    t = jnp.zeros((n_p,), fx.dtype).at[pi].add(rx * fy - ry * fx)
    on_wall = -jnp.zeros((n_w, 2), fx.dtype).at[wi].add(force)
    xi = jnp.zeros_like(flat_xi).at[:, slot].set(jnp.stack([xx, xy]), mode="drop")

    spread = lambda a: _spread(a, slot, act.shape)
    info = {
        "point": spread(jnp.stack([xcx, xcy], axis=-1)),
        "force": spread(force),
        "active": act,
        "normal_force": spread(fn),
        "overflow": n_touch > cap,
        "energy": {k: jnp.sum(v) for k, v in terms.items()},
    }
    return f, t, xi.reshape(wall_xi.shape), on_wall, info


def restitution_of_damping(zeta: float) -> float:
    """Coefficient of restitution of the linear spring-dashpot whose normal force is clamped
    at zero (no pull, as in :func:`contact_law`), for damping ratio ``zeta`` >= 0.

    The overlap obeys ``x'' + 2 z x' + x = 0`` (time in units of 1/w0) from ``x = 0``; the
    contact ends when ``x + 2 z x' = 0`` (the force vanishes), not when ``x = 0``.
    Underdamped (z < 1): the end is at phase ``tau_e = pi - atan2(2 z sqrt(1 - z^2),
    1 - 2 z^2)`` of the damped oscillation and ``e = exp(-beta tau_e) (beta sin tau_e -
    cos tau_e)``, ``beta = z / sqrt(1 - z^2)``. Overdamped (z > 1): with ``s = sqrt(z^2 - 1)``
    and ``l+- = -z +- s`` the end time is ``ln(A- / A+) / (2 s)``, ``A+- = 1 + 2 z l+-``
    (cf. Schwager & Poschel, Phys. Rev. E 75, 051304, 2007)."""
    z = float(zeta)
    if not z >= 0:
        raise ValueError(f"damping ratio must be >= 0, got {zeta}")
    if abs(z - 1.0) < 1e-9:
        z = 1.0 - 1e-9
    if z < 1:
        root = np.sqrt(1.0 - z * z)
        tau = np.pi - np.arctan2(2.0 * z * root, 1.0 - 2.0 * z * z)
        beta = z / root
        return float(np.exp(-beta * tau) * (beta * np.sin(tau) - np.cos(tau)))
    s = np.sqrt(z * z - 1.0)
    lp, lm = -z + s, -z - s
    t = np.log((1 + 2 * z * lm) / (1 + 2 * z * lp)) / (2 * s)
    return float(-(lp * np.exp(lp * t) - lm * np.exp(lm * t)) / (2 * s))


def damping_from_restitution(restitution: float, stiffness: float, m_eff: float) -> float:
    """Normal viscous coefficient G_n (1/s) of paper 002 Eq. 10 that gives the coefficient of
    restitution ``e`` to a contact of effective mass ``m_eff`` (kg) and stiffness K_n (N/m).

    The damping ratio ``zeta`` is found by inverting :func:`restitution_of_damping` (the force
    is clamped at zero, so the textbook ``zeta = -ln e / sqrt(pi^2 + ln^2 e)`` of the unclamped
    dashpot would give a larger e); then ``G_n m_e = 2 zeta sqrt(K_n m_e)``."""
    from scipy.optimize import brentq

    if not 0 < restitution <= 1:
        raise ValueError(f"restitution must be in (0, 1], got {restitution}")
    if stiffness <= 0 or m_eff <= 0:
        raise ValueError("stiffness and effective mass must be positive")
    if restitution == 1:
        return 0.0
    lowest = restitution_of_damping(50.0)
    if restitution <= lowest:
        raise ValueError(f"restitution must exceed {lowest:.3g} (damping ratio 50)")
    zeta = brentq(lambda z: restitution_of_damping(z) - restitution, 0.0, 50.0, xtol=1e-14)
    return float(2.0 * zeta * np.sqrt(stiffness / m_eff))
