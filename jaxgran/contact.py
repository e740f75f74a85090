"""Narrow phase and contact law for 2D spheropolygons, and particle-wall contacts.

The classic split is kept visible: **geometry** (closest features, overlap, normal, contact
point) -> **mixing** (pair effective mass) -> **law** (linear spring-dashpot + Cundall-Strack
friction) -> **history** update.

Geometry (Alonso-Marroquin 2008; paper 002 §2.1 in 3D): every vertex of one core polygon is
tested against the other core polygon. Its closest point on that polygon is either inside an
edge (vertex-edge contact, normal = the edge's outward normal, so a vertex that has crossed
the core edge still gets a restoring force) or a vertex (vertex-vertex contact, normal along
the two vertices). Taking the closest feature, not every edge in range, avoids the 4x
stiffness of coincident corners (PHYSICS §D pitfall). A vertex-vertex contact is kept only
when the two vertices are each other's closest feature and only in the direction i -> j, so it
is counted once. Both directions are tested, so a flat edge-edge contact gives two contacts
(one vertex of each at the ends of the overlap), as in the Minkowski-sum picture.

Law (paper 002 Eq. 6-10): ``F_n = K_n delta - G_n m_e v_n`` (clamped >= 0: contacts do not
pull), ``F_t = -K_t xi - G_t m_e v_t`` capped at ``mu F_n`` (Cundall-Strack); the spring ``xi``
is kept per (pair, direction, vertex), projected onto the current tangent (magnitude kept) and
advanced by ``v_t dt``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .state import Contacts, Params, Particles, Walls

_TINY = 1e-30


def world_vertices(p: Particles) -> Array:
    """Core vertices in the world frame ``[P, V, 2]`` (m)."""
    c, s = jnp.cos(p.angle), jnp.sin(p.angle)
    x, y = p.verts[..., 0], p.verts[..., 1]
    wx = c[:, None] * x - s[:, None] * y + p.pos[:, 0:1]
    wy = s[:, None] * x + c[:, None] * y + p.pos[:, 1:2]
    return jnp.stack([wx, wy], axis=-1)


def _dot(a: Array, b: Array) -> Array:
    """Dot product over the last axis (size 2), written out: XLA's CPU backend reduces tiny
    trailing axes far more slowly than it fuses the explicit sum."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _safe_norm(v: Array) -> tuple[Array, Array]:
    """|v| and v/|v| with finite values and gradients at v = 0 (double-where)."""
    n2 = _dot(v, v)
    ok = n2 > _TINY
    n = jnp.sqrt(jnp.where(ok, n2, 1.0))
    unit = jnp.where(ok[..., None], v / n[..., None], 0.0)
    return jnp.where(ok, n, 0.0), unit


def edge_frames(wv: Array, n_verts: Array) -> tuple[Array, Array, Array]:
    """Per-edge unit outward normal ``[..., V, 2]``, unit tangent ``[..., V, 2]`` and length
    ``[..., V]`` (m) of CCW core polygons. Edge k runs from vertex k to vertex k+1 (or 0);
    padded edges (k >= n) get length 0 and a zero normal. A disc (n = 1) has one zero-length
    edge at its centre."""
    k = jnp.arange(wv.shape[-2])
    n = jnp.asarray(n_verts)[..., None]
    nxt = jnp.where((k + 1 < n)[..., None], jnp.roll(wv, -1, axis=-2), wv[..., 0:1, :])
    length, tangent = _safe_norm(nxt - wv)
    real = k < n
    length = jnp.where(real, length, 0.0)
    tangent = jnp.where(real[..., None], tangent, 0.0)
    normal = jnp.stack([tangent[..., 1], -tangent[..., 0]], axis=-1)
    return normal, tangent, length


def closest_features(va: Array, na: Array, vb: Array, nb: Array, frames=None):
    """Closest point on core polygon B of every vertex of core polygon A.

    For a convex polygon the closest feature of an outside point is found from the edge of
    largest signed distance ``h_k = (x - a_k) . n_k``: if the point projects inside that edge
    the contact is vertex-edge with gap ``h_k``; otherwise the closest point is the edge's end
    on that side (vertex-vertex, gap = distance). A point inside B gets its least-penetrated
    edge (the way out). Written with leading batch axes ``...`` (one pair or ``C`` pairs).

    Args:
        va, vb: world vertices ``[..., V, 2]`` (m), CCW, padded by repeating the last vertex.
        na, nb: real vertex counts ``[...]``.
        frames: optional precomputed :func:`edge_frames` of B.

    Returns:
        gap ``[..., V]``: signed distance from the vertex to B's core (m), negative if inside.
        normal ``[..., V, 2]``: unit vector from B towards the vertex.
        point ``[..., V, 2]``: closest point on B's core (m).
        vertex ``[..., V]``: index of B's vertex if the closest point is a vertex, else -1.
        valid ``[..., V]``: the vertex slot is real.
    """
    v = va.shape[-2]
    k = jnp.arange(v)
    nb_ = jnp.asarray(nb)[..., None]
    normal_e, tangent_e, length_e = edge_frames(vb, nb) if frames is None else frames
    rel = va[..., :, None, :] - vb[..., None, :, :]  # [..., Va, Ve, 2]
    h = _dot(rel, normal_e[..., None, :, :])
    h = jnp.where((k < nb_)[..., None, :], h, -jnp.inf)
    best = jnp.argmax(h, axis=-1)  # [..., Va]
    take = lambda x: jnp.take_along_axis(x, best[..., None], axis=-2)  # x: [..., Ve, 2]
    a_b = take(vb)
    n_b = take(normal_e)
    t_b = take(tangent_e)
    l_b = jnp.take_along_axis(length_e, best, axis=-1)
    d = va - a_b
    s = _dot(d, t_b)
    interior = (s > 0.0) & (s < l_b) & (nb_ >= 2)
    nxt = jnp.where(best + 1 < nb_, best + 1, 0)
    w = jnp.where((s <= 0.0)[..., None], a_b, a_b + l_b[..., None] * t_b)
    dist, n_pt = _safe_norm(va - w)
    n_pt = jnp.where((dist > 0)[..., None], n_pt, n_b)
    normal = jnp.where(interior[..., None], n_b, n_pt)
    gap = jnp.where(interior, _dot(d, n_b), dist)
    point = jnp.where(interior[..., None], a_b + s[..., None] * t_b, w)
    vertex = jnp.where(interior, -1, jnp.where(s <= 0.0, best, nxt))
    valid = k < jnp.asarray(na)[..., None]
    return gap, normal, point, vertex, valid


def contact_law(
    overlap: Array,
    normal: Array,
    v_rel: Array,
    xi: Array,
    m_eff: Array,
    active: Array,
    stiffness_n: Array,
    stiffness_t: Array,
    damping_n: Array,
    damping_t: Array,
    friction: Array,
    dt: Array,
    v_damp: Array | None = None,
) -> tuple[Array, Array, Array]:
    """Linear spring-dashpot normal force and Cundall-Strack friction for one contact.

    Args:
        overlap: delta (m), normal: unit normal towards the body receiving the force,
        v_rel: velocity of that body's material point minus the other's at the contact (m/s),
        xi: tangential spring from the previous step (m), m_eff: effective mass (kg),
        active: contact exists.
        v_damp: relative velocity used by the dashpots (default ``v_rel``). The integrator
            passes the half-step velocity as ``v_rel`` (the spring increment over the step is
            then centred) and a predicted end-of-step velocity here, which keeps the
            dissipation second order in dt.

    Returns: (force on the body (N), new xi (m), normal force magnitude F_n (N)).
    """
    v_damp = v_rel if v_damp is None else v_damp
    vn_d = _dot(v_damp, normal)
    vt_d = v_damp - vn_d[..., None] * normal
    fn = stiffness_n * overlap - damping_n * m_eff * vn_d
    fn = jnp.where(active, jnp.maximum(fn, 0.0), 0.0)
    vn = _dot(v_rel, normal)
    vt = v_rel - vn[..., None] * normal
    # rotate the spring into the current tangent plane, keeping its length
    xi_len, _ = _safe_norm(xi)
    xi_t = xi - _dot(xi, normal)[..., None] * normal
    xi_t_len, xi_t_dir = _safe_norm(xi_t)
    xi = jnp.where((xi_t_len > 0)[..., None], xi_t_dir * xi_len[..., None], 0.0)
    xi = xi + vt * dt
    ft = -stiffness_t * xi - damping_t * m_eff[..., None] * vt_d
    ft_len, ft_dir = _safe_norm(ft)
    cap = friction * fn
    slip = ft_len > cap
    ft = jnp.where(slip[..., None], cap[..., None] * ft_dir, ft)
    safe_kt = jnp.where(stiffness_t > 0, stiffness_t, 1.0)
    xi = jnp.where(slip[..., None], jnp.where(stiffness_t > 0, -ft / safe_kt, 0.0), xi)
    act = active[..., None]
    force = jnp.where(act, fn[..., None] * normal + ft, 0.0)
    return force, jnp.where(act, xi, 0.0), fn


def _cross(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _omega_cross(w: Array, r: Array) -> Array:
    """(w z) x r for scalar w."""
    return jnp.stack([-w * r[..., 1], w * r[..., 0]], axis=-1)


def _pair_geometry(va: Array, na: Array, vb: Array, nb: Array, fa=None, fb=None):
    """Both directions of pairs ``[..., V, 2]``: i's vertices on j, then j's vertices on i.

    Returns gap, normal, closest point and a keep mask stacked on a direction axis
    ``[..., 2, V(, 2)]``."""
    g0, n0, q0, vx0, ok0 = closest_features(va, na, vb, nb, fb)
    g1, n1, q1, vx1, ok1 = closest_features(vb, nb, va, na, fa)
    idx = jnp.arange(va.shape[-2])
    # vertex-vertex: keep when mutual (b is a's closest and a is b's), in direction 0 only
    back = jnp.take_along_axis(vx1, jnp.clip(vx0, 0), axis=-1)
    mutual0 = (vx0 >= 0) & (back == idx)
    keep0 = ok0 & ((vx0 < 0) | mutual0)
    keep1 = ok1 & (vx1 < 0)
    stack = lambda x, y: jnp.stack([x, y], axis=-3 if x.ndim > keep0.ndim else -2)
    return stack(g0, g1), stack(n0, n1), stack(q0, q1), stack(keep0, keep1)


def pair_forces(
    p: Particles, contacts: Contacts, params: Params, damp_velocity=None
) -> tuple[Array, Array, Array, dict]:
    """Forces and torques from all particle pairs in the Verlet list.

    ``damp_velocity``: optional ``(vel [P, 2], omega [P])`` used by the dashpots (see
    :func:`contact_law`); ``p.vel``, ``p.omega`` drive the tangential spring.

    Returns:
        force ``[P, 2]`` (N), torque ``[P]`` (N m), new tangential history ``[C, 2, V, 2]``,
        and per-contact data (``point [C,2,V,2]``, ``force`` on the vertex owner, ``active``,
        ``normal_force``) for post-processing (force chains, BEM loading).
    """
    n_p = p.pos.shape[0]
    pairs = contacts.pairs
    pair_ok = pairs[:, 0] < n_p
    i = jnp.where(pair_ok, pairs[:, 0], 0)
    j = jnp.where(pair_ok, pairs[:, 1], 0)
    wv = world_vertices(p)
    frames = edge_frames(wv, p.n_verts)
    fi = tuple(f[i] for f in frames)
    fj = tuple(f[j] for f in frames)
    gap, normal, q, keep = _pair_geometry(wv[i], p.n_verts[i], wv[j], p.n_verts[j], fi, fj)
    # gap etc: [C, 2, V(, 2)]
    owner = jnp.stack([i, j], axis=1)  # [C, 2] body whose vertex is tested
    other = jnp.stack([j, i], axis=1)
    r_own = p.radius[owner][..., None]
    r_oth = p.radius[other][..., None]
    overlap = r_own + r_oth - gap
    both_active = (pair_ok & p.active[i] & p.active[j])[:, None, None]
    act = keep & (overlap > 0) & both_active
    # contact point: middle of the overlap, measured from the other body's core
    x_c = q + (r_oth - 0.5 * overlap)[..., None] * normal
    # mixing
    inv_m = jnp.where(p.fixed, 0.0, 1.0 / p.mass)
    m_eff = 1.0 / jnp.maximum(inv_m[owner] + inv_m[other], _TINY)
    m_eff = jnp.broadcast_to(m_eff[..., None], overlap.shape)
    # kinematics at the contact point
    x_own = p.pos[owner][:, :, None, :]
    x_oth = p.pos[other][:, :, None, :]
    v_own = p.vel[owner][:, :, None, :] + _omega_cross(p.omega[owner][..., None], x_c - x_own)
    v_oth = p.vel[other][:, :, None, :] + _omega_cross(p.omega[other][..., None], x_c - x_oth)
    vd, wd = (p.vel, p.omega) if damp_velocity is None else damp_velocity
    vd_own = vd[owner][:, :, None, :] + _omega_cross(wd[owner][..., None], x_c - x_own)
    vd_oth = vd[other][:, :, None, :] + _omega_cross(wd[other][..., None], x_c - x_oth)
    force, xi, fn = contact_law(
        overlap,
        normal,
        v_own - v_oth,
        contacts.xi,
        m_eff,
        act,
        params.normal_stiffness,
        params.tangential_stiffness,
        params.normal_damping,
        params.tangential_damping,
        params.friction,
        params.dt,
        v_damp=vd_own - vd_oth,
    )
    torque_own = _cross(x_c - x_own, force)
    torque_oth = -_cross(x_c - x_oth, force)
    f_own = force.sum(axis=2)  # [C, 2, 2]
    t_own = torque_own.sum(axis=2)
    t_oth = torque_oth.sum(axis=2)
    seg = lambda data, idx: jax.ops.segment_sum(data, idx, num_segments=n_p)
    f = seg(f_own[:, 0], i) + seg(f_own[:, 1], j) - seg(f_own[:, 0], j) - seg(f_own[:, 1], i)
    t = seg(t_own[:, 0], i) + seg(t_own[:, 1], j) + seg(t_oth[:, 0], j) + seg(t_oth[:, 1], i)
    info = {"point": x_c, "force": force, "active": act, "normal_force": fn}
    return f, t, xi, info


def wall_forces(p: Particles, walls: Walls, wall_xi: Array, params: Params, damp_velocity=None):
    """Forces between particle vertices (discs of radius ``radius``) and planar walls.

    Returns force ``[P, 2]`` (N), torque ``[P]`` (N m), new history ``[P, W, V, 2]``, force on
    each wall ``[W, 2]`` (N), and per-contact data.
    """
    wv = world_vertices(p)  # [P, V, 2]
    n_v = wv.shape[1]
    rel = wv[:, None, :, :] - walls.point[None, :, None, :]  # [P, W, V, 2]
    nrm = walls.normal[None, :, None, :]
    gap = _dot(rel, nrm)
    tan = jnp.stack([-walls.normal[:, 1], walls.normal[:, 0]], axis=-1)[None, :, None, :]
    s = _dot(rel, tan)
    inside = (s >= walls.extent[None, :, None, 0]) & (s <= walls.extent[None, :, None, 1])
    vert_ok = jnp.arange(n_v)[None, None, :] < p.n_verts[:, None, None]
    overlap = p.radius[:, None, None] - gap
    act = inside & vert_ok & (overlap > 0) & p.active[:, None, None] & walls.active[None, :, None]
    normal = jnp.broadcast_to(nrm, rel.shape)
    x_c = wv[:, None, :, :] - (p.radius[:, None, None] - 0.5 * overlap)[..., None] * normal
    r = x_c - p.pos[:, None, None, :]
    v_p = p.vel[:, None, None, :] + _omega_cross(p.omega[:, None, None], r)
    v_rel = v_p - walls.vel[None, :, None, :]
    vd, wd = (p.vel, p.omega) if damp_velocity is None else damp_velocity
    v_damp = vd[:, None, None, :] + _omega_cross(wd[:, None, None], r) - walls.vel[None, :, None, :]
    m_eff = jnp.broadcast_to(p.mass[:, None, None], overlap.shape)
    force, xi, fn = contact_law(
        overlap,
        normal,
        v_rel,
        wall_xi,
        m_eff,
        act,
        params.normal_stiffness,
        params.tangential_stiffness,
        params.normal_damping,
        params.tangential_damping,
        params.wall_friction,
        params.dt,
        v_damp=v_damp,
    )
    f = force.sum(axis=(1, 2))
    t = _cross(r, force).sum(axis=(1, 2))
    on_wall = -force.sum(axis=(0, 2))
    info = {"point": x_c, "force": force, "active": act, "normal_force": fn}
    return f, t, xi, on_wall, info


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
