"""Interface bonds divided into elements (flat-joint type) with a parabolic Mohr shear strength
(paper 003 §2), and the parallel bond with a linear Mohr-Coulomb strength as the baseline.

Paper 003 lost its equations in extraction; the forms below are the standard published ones
of the flat-joint model (Potyondy's flat joint, which paper 003 §2 builds on) with paper 003's
quadratic-parabolic shear strength, written out here.

**Geometry.** A bonded pair (i, j) shares a straight interface of width ``W`` (m) through the
*interface centre* with unit normal ``n`` (from i to j) and tangent ``t = z x n``: for two
discs (1-vertex spheropolygons, paper 003's elementary balls) the segment of width
``W = 2 lambda min(r_i, r_j)`` across the gap on the line of centres (``lambda`` the radius
multiplier, PFC's ``fj_radmult``, default 1); for two Voronoi cells their shared edge. The
interface is cut into ``n_e`` equal elements (default 4 in 2D; paper 003 uses 16 sectors of a
disc in 3D). Element e has the area ``A_e = W T / n_e`` (T the slab thickness, plane stress)
and its centre at ``s_e = W ((e + 1/2) / n_e - 1/2)`` along ``t``; that point is stored once
in each body frame, so as the bodies move its two copies separate by ``d_e = x_j,e - x_i,e``
(total-displacement form: zero in the bonding configuration). With ``theta`` the relative
rotation, the current normal is i's reference normal turned by ``angle_i + theta / 2`` (the
bisector, as in :mod:`jaxgran.bonds`), and

    u_n = d_e . n   (m, opening positive),      u_s = d_e . t   (m).

**Bonded element (paper 003 Eq. 1, stresses tension positive).**

    sigma = k_n u_n,    tau = k_s u_s           (k_n, k_s: Pa/m, stress per displacement)

Failure is checked every evaluation in this order (tension first, so that the root below is
always defined):

1. tension:      ``sigma >= sigma_b``                      -> mode 1 (paper 003 §2),
2. compression:  ``-u_n / L >= eps_u`` (L centre distance) -> mode 3 (paper 003 Eq. 2, the
   ultimate compressive strain; ``eps_u = inf``, the default, switches it off),
3. shear:        ``|tau| >= tau_c(sigma)``                 -> mode 2, with

       tau_c = c sqrt(1 - sigma / sigma_b)                 interface (paper 003 Eq. 3),
       tau_c = max(c - sigma tan(phi), 0)                  parallel bond (linear Mohr-Coulomb),

   a parabola through (sigma_b, 0) and (0, c), and the classical straight line through
   (0, c); both with sigma positive in tension, so compression raises the strength.

**Failed element (paper 003 Eq. 4).** It carries compression and friction only:

    sigma = k_n min(u_n, 0),    tau = k_s (u_s - s),   |tau| <= mu_b max(-sigma, 0),

with the plastic slip ``s`` (m) updated whenever the cap is reached (Cundall-Strack in total
form); an open element carries nothing and its slip follows ``u_s``. The crack faces meet
again where they were bonded (the bonding configuration is the zero of ``u_n``).

**Forces.** Element e pushes j with ``F_e = -A_e (sigma n + tau t)`` plus a dashpot
``-eta (v_rel . n) n - eta_s (v_rel . t) t`` per element (``eta = 2 zeta sqrt(k_n A m_e) / n_e``,
``m_e`` the pair's reduced mass; weighted by the element's health and kept out of the
failure criterion), applied at the midpoint of its two copies; i receives ``-F_e`` at the same
point. So Newton's third law holds exactly for forces and moments, and the distributed
elements resist relative rotation without a separate moment term (the flat joint's bending
stiffness ``k_n A W^2 / 12`` for many elements). The forces and torques on each particle are
the sums over its elements.

**Damage.** Each element keeps its own health (1 bonded, 0 failed), failure mode (0 intact,
1 tension, 2 shear, 3 compression) and failure time. Hard failure is the default; as in
:mod:`jaxgran.bonds`, a surrogate width ``w > 0`` turns the step into a smoothstep of the
largest of the three ratios above (DESIGN §7) and an element then carries ``h x bonded +
(1 - h) x frictional``. A bond is *intact* while any element is bonded (so
:func:`jaxgran.bonds.broken_mask` and the bonded scenes' ``n_broken`` count fully broken
interfaces), and its ``break_time`` is when the last element failed.

**Walls.** Wall bonds (tension grips) are the normal wall bonds of :mod:`jaxgran.bonds`
(paper 002 §4.3), kept in the nested :class:`jaxgran.bonds.Bonds` ``wall_bonds`` (build them
with :func:`jaxgran.bonds.attach_to_walls` on it).

**Integration.** :class:`InterfaceBonds` sits in ``SimState.bonds``; the step's bond hook
(:func:`jaxgran.bonds.bond_forces`) hands any bond model other than
:class:`jaxgran.bonds.Bonds` to its ``forces`` method.

Shapes: ``B`` bond capacity, ``E`` elements per interface (static), ``P`` particle capacity.
Padded bonds have ``i = j = P`` and no intact element.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .bonds import Bonds, bond_forces, health_limit
from .state import Particles, Walls

MODE_INTACT = 0
MODE_TENSION = 1
MODE_SHEAR = 2
MODE_COMPRESSION = 3
MODE_NAMES = {MODE_INTACT: "intact", MODE_TENSION: "tension", MODE_SHEAR: "shear"}
MODE_NAMES[MODE_COMPRESSION] = "compression"

ENVELOPE_PARABOLIC = 0  # the interface model, paper 003 Eq. 3
ENVELOPE_LINEAR = 1  # the parallel bond baseline, linear Mohr-Coulomb
ENVELOPES = {"interface": ENVELOPE_PARABOLIC, "parallel": ENVELOPE_LINEAR}

_LARGE = 1.0e6  # stands for an infinite strength ratio (finite for gradients)


class InterfaceBonds(eqx.Module):
    """Padded interface bonds, each cut into ``E`` elements (module docstring).

    Attributes:
        i, j: bonded particles ``[B]`` int32 (i < j), sentinel ``P`` for padding.
        point_i, point_j: interface centre in the body frames of i and j ``[B, 2]`` (m).
        normal_i: reference unit normal (i towards j) in i's body frame ``[B, 2]``.
        theta0: reference relative rotation ``angle_j - angle_i`` ``[B]`` (rad).
        length: L, centre-to-centre distance at bonding ``[B]`` (m), of the compressive strain.
        width: interface width W ``[B]`` (m).  area: W x T ``[B]`` (m^2).
        elem_point_i, elem_point_j: element centres in each body frame ``[B, E, 2]`` (m).
        normal_stiffness, shear_stiffness: k_n, k_s ``[B]`` (Pa/m).
        tensile_strength: sigma_b ``[B]`` (Pa).  cohesion: c ``[B]`` (Pa).
        tan_friction_angle: tan(phi) of the linear envelope ``[B]`` (-).
        envelope: ``[B]`` int32, ENVELOPE_PARABOLIC (interface) or ENVELOPE_LINEAR (parallel).
        compressive_strain: eps_u ``[B]`` (-), inf = no compressive failure.
        residual_friction: mu_b of failed elements ``[B]`` (-).
        damping_n, damping_s: dashpot per element ``[B]`` (N s/m).
        health: ``[B, E]`` in [0, 1].  mode: failure mode ``[B, E]`` int32 (MODE_*).
        elem_break_time: ``[B, E]`` (s), +inf while bonded.
        slip: plastic shear slip of the frictional part ``[B, E]`` (m).
        sigma, tau: element stresses of the last evaluation ``[B, E]`` (Pa, tension positive).
        intact: ``[B]`` bool, some element still bonded (False for padding).
        break_time: ``[B]`` (s), when the last element failed.
        surrogate_width: w (scalar, -); 0 is hard failure.
        time: time of the configuration last evaluated (scalar, s).
        wall_bonds: normal wall bonds (:class:`jaxgran.bonds.Bonds` with one padded pair).
    """

    i: Array
    j: Array
    point_i: Array
    point_j: Array
    normal_i: Array
    theta0: Array
    length: Array
    width: Array
    area: Array
    elem_point_i: Array
    elem_point_j: Array
    normal_stiffness: Array
    shear_stiffness: Array
    tensile_strength: Array
    cohesion: Array
    tan_friction_angle: Array
    envelope: Array
    compressive_strain: Array
    residual_friction: Array
    damping_n: Array
    damping_s: Array
    health: Array
    mode: Array
    elem_break_time: Array
    slip: Array
    sigma: Array
    tau: Array
    intact: Array
    break_time: Array
    surrogate_width: Array
    time: Array
    wall_bonds: Bonds

    @property
    def capacity(self) -> int:
        return self.i.shape[0]

    @property
    def n_elements(self) -> int:
        return self.health.shape[1]

    # the wall-bond view that jaxgran.bonds.force_on_walls reads
    @property
    def wall_force(self) -> Array:
        return self.wall_bonds.wall_force

    @property
    def wall_w(self) -> Array:
        return self.wall_bonds.wall_w

    @property
    def wall_active(self) -> Array:
        return self.wall_bonds.wall_active

    def forces(self, p: Particles, walls: Walls, dt) -> tuple[Array, Array, InterfaceBonds]:
        """The bond hook of :func:`jaxgran.integrate.step`: :func:`interface_forces`."""
        return interface_forces(p, self, walls, dt)


# ------------------------------------------------------------------------------ kinematics


def _dot(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _cross(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _perp(v: Array) -> Array:
    """z x v (+90 deg)."""
    return jnp.stack([-v[..., 1], v[..., 0]], axis=-1)


def _rotate(v: Array, angle: Array) -> Array:
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _rows(p: Particles, b: InterfaceBonds):
    """Safe indices and the mask of real bonds between active particles."""
    n_p = p.pos.shape[0]
    real = (b.i < b.j) & (b.j < n_p)
    i = jnp.where(real, b.i, 0)
    j = jnp.where(real, b.j, 0)
    return i, j, real & p.active[i] & p.active[j]


def interface_kinematics(p: Particles, b: InterfaceBonds) -> dict[str, Array]:
    """Current geometry of every interface and element.

    Returns ``normal``, ``tangent`` ``[B, 2]`` (unit, world); ``x_i``, ``x_j`` the element
    centres carried by i and j ``[B, E, 2]`` (m); ``u_n``, ``u_s`` the element opening and
    sliding ``[B, E]`` (m); ``live`` ``[B]``; ``i``, ``j`` safe indices ``[B]``.
    """
    i, j, live = _rows(p, b)
    a_i, a_j = p.angle[i], p.angle[j]
    theta = (a_j - a_i) - b.theta0
    normal = _rotate(b.normal_i, a_i + 0.5 * theta)
    tangent = _perp(normal)
    x_i = p.pos[i][:, None, :] + _rotate(b.elem_point_i, a_i[:, None])
    x_j = p.pos[j][:, None, :] + _rotate(b.elem_point_j, a_j[:, None])
    d = x_j - x_i
    return {
        "normal": normal,
        "tangent": tangent,
        "x_i": x_i,
        "x_j": x_j,
        "u_n": _dot(d, normal[:, None, :]),
        "u_s": _dot(d, tangent[:, None, :]),
        "live": live,
        "i": i,
        "j": j,
    }


# ------------------------------------------------------------------------------ law


def shear_strength(
    sigma: Array, cohesion: Array, tensile_strength: Array, tan_friction_angle: Array, envelope
) -> Array:
    """Shear strength tau_c (Pa) of a bonded element at normal stress ``sigma`` (Pa, tension
    positive): ``c sqrt(1 - sigma / sigma_b)`` (paper 003 Eq. 3, ENVELOPE_PARABOLIC) or
    ``max(c - sigma tan(phi), 0)`` (ENVELOPE_LINEAR). The parabola is taken as 0 beyond
    sigma_b (tension failure comes first there); double-where keeps its gradient finite."""
    x = 1.0 - sigma / tensile_strength
    pos = x > 0
    parabola = cohesion * jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)
    line = jnp.maximum(cohesion - sigma * tan_friction_angle, 0.0)
    return jnp.where(envelope == ENVELOPE_PARABOLIC, parabola, line)


def strength_ratios(
    sigma: Array,
    tau: Array,
    u_n: Array,
    length: Array,
    tensile_strength: Array,
    cohesion: Array,
    tan_friction_angle: Array,
    envelope,
    compressive_strain: Array,
) -> tuple[Array, Array, Array]:
    """Tension, compression and shear ratios of one bonded element (each fails at 1):
    ``sigma / sigma_b``, ``(-u_n / L) / eps_u`` and ``|tau| / tau_c(sigma)`` (-)."""
    r_t = sigma / tensile_strength
    r_c = jnp.maximum(-u_n / length, 0.0) / compressive_strain
    t_c = shear_strength(sigma, cohesion, tensile_strength, tan_friction_angle, envelope)
    some = t_c > 0
    r_s = jnp.where(some, jnp.abs(tau) / jnp.where(some, t_c, 1.0), 0.0)
    r_s = jnp.where(some | (tau == 0), r_s, _LARGE)
    return r_t, r_c, r_s


def failure_mode(r_t: Array, r_c: Array, r_s: Array) -> Array:
    """Mode of an element that fails now (int32): tension is checked first, then the
    compressive strain, then shear (paper 003 §2)."""
    mode = jnp.where(r_s > 1.0, MODE_SHEAR, MODE_INTACT)
    mode = jnp.where(r_c > 1.0, MODE_COMPRESSION, mode)
    return jnp.where(r_t > 1.0, MODE_TENSION, mode).astype(jnp.int32)


def frictional_stresses(
    u_n: Array, u_s: Array, slip: Array, k_n: Array, k_s: Array, mu: Array
) -> tuple[Array, Array, Array]:
    """Stresses of a failed element (paper 003 Eq. 4): ``sigma = k_n min(u_n, 0)``,
    ``tau = k_s (u_s - s)`` capped at ``mu max(-sigma, 0)``; returns sigma, tau (Pa) and the
    new slip s (m)."""
    sigma = k_n * jnp.minimum(u_n, 0.0)
    trial = k_s * (u_s - slip)
    cap = mu * jnp.maximum(-sigma, 0.0)
    slipping = jnp.abs(trial) > cap
    tau = jnp.where(slipping, jnp.sign(trial) * cap, trial)
    has_k = k_s > 0
    slip_new = jnp.where(slipping & has_k, u_s - tau / jnp.where(has_k, k_s, 1.0), slip)
    return sigma, tau, slip_new


def element_update(b: InterfaceBonds, u_n: Array, u_s: Array, live: Array, time: Array):
    """Failure check and stresses of every element ``[B, E]``.

    Returns sigma, tau (Pa), new health, mode, element break time, slip and the per-element
    ratios' maximum (the failure measure, -).
    """
    col = lambda x: x[:, None]
    k_n, k_s = col(b.normal_stiffness), col(b.shear_stiffness)
    sig_b, tau_b = k_n * u_n, k_s * u_s
    length = col(jnp.where(live & (b.length > 0), b.length, 1.0))
    r_t, r_c, r_s = strength_ratios(
        sig_b,
        tau_b,
        u_n,
        length,
        col(b.tensile_strength),
        col(b.cohesion),
        col(b.tan_friction_angle),
        col(b.envelope),
        col(b.compressive_strain),
    )
    measure = jnp.maximum(jnp.maximum(r_t, r_c), r_s)
    live2 = col(live)
    health = jnp.where(
        live2, jnp.minimum(b.health, health_limit(measure, b.surrogate_width)), b.health
    )
    failed_now = (b.health > 0) & (health <= 0) & live2
    mode = jnp.where(failed_now, failure_mode(r_t, r_c, r_s), b.mode)
    brk = jnp.where(failed_now, time, b.elem_break_time)
    sig_f, tau_f, slip_f = frictional_stresses(u_n, u_s, b.slip, k_n, k_s, col(b.residual_friction))
    slip = jnp.where(live2 & (health < 1.0), slip_f, b.slip)
    sigma = health * sig_b + (1.0 - health) * sig_f
    tau = health * tau_b + (1.0 - health) * tau_f
    return sigma, tau, health, mode, brk, slip, measure


def interface_forces(
    p: Particles, b: InterfaceBonds, walls: Walls, dt
) -> tuple[Array, Array, InterfaceBonds]:
    """Forces ``[P, 2]`` (N) and torques ``[P]`` (N m) of every interface and wall bond, and
    the bonds after this evaluation (failures recorded, ``time`` advanced by ``dt`` first, as
    :func:`jaxgran.bonds.bond_forces`). Jit-able; finite for padded bonds."""
    n_p = p.pos.shape[0]
    time = b.time + dt
    k = interface_kinematics(p, b)
    live, i, j = k["live"], k["i"], k["j"]
    sigma, tau, health, mode, brk, slip, _ = element_update(b, k["u_n"], k["u_s"], live, time)
    n, t = k["normal"][:, None, :], k["tangent"][:, None, :]
    a_e = (b.area / b.n_elements)[:, None]
    c = 0.5 * (k["x_i"] + k["x_j"])
    r_i, r_j = c - p.pos[i][:, None, :], c - p.pos[j][:, None, :]
    v_i = p.vel[i][:, None, :] + p.omega[i][:, None, None] * _perp(r_i)
    v_j = p.vel[j][:, None, :] + p.omega[j][:, None, None] * _perp(r_j)
    v = v_j - v_i
    damp = -(b.damping_n[:, None] * _dot(v, n))[..., None] * n
    damp = damp - (b.damping_s[:, None] * _dot(v, t))[..., None] * t
    elastic = -a_e[..., None] * (sigma[..., None] * n + tau[..., None] * t)
    f_j = jnp.where(live[:, None, None], elastic + health[..., None] * damp, 0.0)
    torque_j = _cross(r_j, f_j).sum(axis=1)
    torque_i = -_cross(r_i, f_j).sum(axis=1)
    f_bond = f_j.sum(axis=1)
    seg = lambda data, idx: jax.ops.segment_sum(data, idx, num_segments=n_p)
    force = seg(f_bond, j) - seg(f_bond, i)
    torque = seg(torque_j, j) + seg(torque_i, i)

    f_w, t_w, wall_bonds = bond_forces(p, b.wall_bonds, walls, dt)
    intact = (b.i < b.j) & jnp.any(health > 0, axis=1)
    broke = b.intact & ~intact
    keep = live[:, None]
    new = eqx.tree_at(
        lambda m: (
            m.health,
            m.mode,
            m.elem_break_time,
            m.slip,
            m.sigma,
            m.tau,
            m.intact,
            m.break_time,
            m.time,
            m.wall_bonds,
        ),
        b,
        (
            health,
            mode,
            brk,
            slip,
            jnp.where(keep, sigma, 0.0),
            jnp.where(keep, tau, 0.0),
            intact,
            jnp.where(broke, time, b.break_time),
            time,
            wall_bonds,
        ),
    )
    return force + f_w, torque + t_w, new


# ------------------------------------------------------------------------------ measures


def interface_normal_stiffness(b: InterfaceBonds) -> Array:
    """Tensile stiffness of each interface ``[B]`` (N/m): ``k_n A_e`` summed over its bonded
    elements (health-weighted), i.e. ``k_n A (n_bonded / n_e)`` with hard failure."""
    return b.normal_stiffness * b.area / b.n_elements * jnp.sum(b.health, axis=1)


def elastic_energy(p: Particles, b: InterfaceBonds) -> Array:
    """Elastic energy of the bonded interface elements (J, scalar):
    ``sum_e health_e A_e (k_n u_n^2 + k_s u_s^2) / 2``, the potential of the bonded-element law
    (Eq. 1) for a fixed interface normal (exact for translations; a rotation also turns the
    normal). Failed elements (health 0) store nothing here."""
    k = interface_kinematics(p, b)
    a_e = (b.area / b.n_elements)[:, None]
    k_n, k_s = b.normal_stiffness[:, None], b.shear_stiffness[:, None]
    u = a_e * (k_n * k["u_n"] ** 2 + k_s * k["u_s"] ** 2)
    return jnp.sum(jnp.where(k["live"][:, None], 0.5 * b.health * u, 0.0))


def element_positions(p: Particles, b: InterfaceBonds) -> Array:
    """World position of every element (midpoint of its two copies) ``[B, E, 2]`` (m)."""
    k = interface_kinematics(p, b)
    return 0.5 * (k["x_i"] + k["x_j"])


def interface_normal_force(b: InterfaceBonds) -> Array:
    """Normal force of each interface of the last evaluation ``[B]`` (N, tension positive)."""
    return jnp.sum(b.sigma * (b.area / b.n_elements)[:, None], axis=1)


def particle_moment(p: Particles, b: InterfaceBonds) -> Array:
    """First moment of the interface forces on each particle ``[P, 2, 2]`` (N m),
    ``sum_e (x_e - x_p) (x) F_e`` over its elements (last evaluation), symmetrised. Divided by
    a volume (area x thickness, m^3) it is the Love-Weber stress (Pa, tension positive)."""
    n_p = p.pos.shape[0]
    k = interface_kinematics(p, b)
    live, i, j = k["live"], k["i"], k["j"]
    n, t = k["normal"][:, None, :], k["tangent"][:, None, :]
    a_e = (b.area / b.n_elements)[:, None, None]
    f_j = -a_e * (b.sigma[..., None] * n + b.tau[..., None] * t)
    f_j = jnp.where(live[:, None, None], f_j, 0.0)
    c = 0.5 * (k["x_i"] + k["x_j"])
    r_i, r_j = c - p.pos[i][:, None, :], c - p.pos[j][:, None, :]
    m_j = (r_j[..., :, None] * f_j[..., None, :]).sum(axis=1)
    m_i = -(r_i[..., :, None] * f_j[..., None, :]).sum(axis=1)
    seg = lambda data, idx: jax.ops.segment_sum(data, idx, num_segments=n_p)
    m = seg(m_j, j) + seg(m_i, i)
    return 0.5 * (m + jnp.swapaxes(m, -1, -2))


def friction_crossover(cohesion: float, tensile_strength: float, residual_friction: float) -> float:
    """Compression (Pa, positive) above which the parabola of paper 003 Eq. 3,
    ``c sqrt(1 + s / sigma_b)``, lies below the friction line ``mu_b s`` of a failed element:

        s* = (c^2 / sigma_b + sqrt(c^4 / sigma_b^2 + 4 mu_b^2 c^2)) / (2 mu_b^2).

    A bonded element sheared to failure above s* carries more after failing than before, so
    there the bond adds nothing to the strength of the frictional contact. (The parallel
    bond's line ``c + s tan(phi)`` stays above ``mu_b s`` for every s when ``tan(phi) >=
    mu_b``.) ``inf`` for ``mu_b = 0``."""
    if residual_friction <= 0:
        return math.inf
    a = cohesion**2 / tensile_strength
    mu2 = residual_friction**2
    return (a + math.sqrt(a * a + 4.0 * mu2 * cohesion**2)) / (2.0 * mu2)


def element_summary(b: InterfaceBonds) -> dict[str, int | float]:
    """Host-side counts: bonds, elements, failed elements per mode, fully broken bonds and
    the mean damage (failed fraction of the elements of real bonds)."""
    real = np.asarray(b.i < b.j)
    mode = np.asarray(b.mode)[real]
    health = np.asarray(b.health)[real]
    out = {
        "n_bonds": int(real.sum()),
        "n_elements": int(mode.size),
        "n_bonds_broken": int((real & ~np.asarray(b.intact)).sum()),
        "mean_damage": float(1.0 - health.mean()) if health.size else 0.0,
    }
    for code, name in MODE_NAMES.items():
        if code != MODE_INTACT:
            out[f"n_failed_{name}"] = int((mode == code).sum())
    return out


# ------------------------------------------------------------------------------ constructors


def disc_interfaces(pos, radius, gap: float, radius_multiplier: float = 1.0) -> dict:
    """Interfaces of discs whose surfaces are at most ``gap`` (m) apart: pairs (i < j),
    centres in the middle of the gap on the line of centres (m), unit normals (i to j) and
    widths ``2 lambda min(r_i, r_j)`` (m), as arrays for :func:`make_interface_bonds`."""
    from scipy.spatial import cKDTree

    pos = np.asarray(pos, float).reshape(-1, 2)
    rad = np.broadcast_to(np.asarray(radius, float), (len(pos),))
    pairs = cKDTree(pos).query_pairs(2.0 * rad.max() + gap, output_type="ndarray")
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].reshape(-1, 2)
    d = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    dist = np.linalg.norm(d, axis=1)
    g = dist - rad[pairs[:, 0]] - rad[pairs[:, 1]]
    keep = g <= gap
    pairs, d, dist, g = pairs[keep], d[keep], dist[keep], g[keep]
    n = d / dist[:, None]
    centre = pos[pairs[:, 0]] + (rad[pairs[:, 0]] + 0.5 * g)[:, None] * n
    width = 2.0 * radius_multiplier * np.minimum(rad[pairs[:, 0]], rad[pairs[:, 1]])
    return {"pairs": pairs, "centres": centre, "normals": n, "widths": width}


def edge_interfaces(cells: list, tol: float = 1e-9) -> dict:
    """Interfaces of the cells of a tessellation: every shared edge
    (:func:`jaxgran.geometry.shared_edges`), centred on its midpoint, normal out of cell i,
    width its length (m)."""
    from .geometry import shared_edges

    edges = shared_edges(cells, tol=tol)
    n = len(edges)
    pairs = np.array([(e[0], e[1]) for e in edges], np.int64).reshape(n, 2)
    a = np.array([e[2] for e in edges], float).reshape(n, 2)
    q = np.array([e[3] for e in edges], float).reshape(n, 2)
    w = np.linalg.norm(q - a, axis=1)
    tan = (q - a) / np.where(w > 0, w, 1.0)[:, None]
    normal = np.stack([tan[:, 1], -tan[:, 0]], axis=1)  # the edge runs CCW along cell i
    return {"pairs": pairs, "centres": 0.5 * (a + q), "normals": normal, "widths": w}


def _rot_np(v: np.ndarray, angle) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _per_bond(value, n: int, name: str, *, positive: bool) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim not in (0, 1) or (arr.ndim == 1 and arr.shape[0] != n):
        raise ValueError(f"{name} must be a scalar or one value per bond ({n}), got {arr.shape}")
    arr = np.broadcast_to(arr, (n,)).copy()
    bad = np.isnan(arr) | ~((arr > 0) if positive else (arr >= 0))
    if np.any(bad):
        sign = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be {sign} (inf allowed), got {arr[bad][:5]}")
    return arr


def _pad(values: np.ndarray, cap: int, fill) -> np.ndarray:
    out = np.full((cap,) + values.shape[1:], fill, dtype=values.dtype)
    out[: len(values)] = values
    return out


def empty_wall_bonds(n_particles: int, dtype=None, capacity: int = 1) -> Bonds:
    """A :class:`jaxgran.bonds.Bonds` with no particle bond and ``capacity`` empty wall-bond
    slots: the ``wall_bonds`` of an :class:`InterfaceBonds` before
    :func:`jaxgran.bonds.attach_to_walls`."""
    fd = dtype or jnp.result_type(float)
    z = lambda *s: jnp.zeros(s, fd)
    one = lambda *s: jnp.ones(s, fd)
    w = max(int(capacity), 1)
    return Bonds(
        i=jnp.full((1,), n_particles, jnp.int32),
        j=jnp.full((1,), n_particles, jnp.int32),
        point_i=z(1, 2),
        point_j=z(1, 2),
        normal_i=jnp.asarray([[1.0, 0.0]], fd),
        area=z(1),
        length=one(1),
        theta0=z(1),
        b_n=z(1),
        b_t=z(1),
        b_m=z(1),
        eps_th=one(1),
        theta_th=one(1),
        intact=jnp.zeros((1,), bool),
        health=z(1),
        surrogate_width=jnp.asarray(0.0, fd),
        time=jnp.asarray(0.0, fd),
        break_time=jnp.full((1,), jnp.inf, fd),
        strain_measure=z(1),
        wall_p=jnp.full((w,), n_particles, jnp.int32),
        wall_w=jnp.zeros((w,), jnp.int32),
        wall_point=z(w, 2),
        wall_gap0=z(w),
        wall_area=z(w),
        wall_length=one(w),
        wall_b_n=z(w),
        wall_active=jnp.zeros((w,), bool),
        wall_force=z(w, 2),
    )


def make_interface_bonds(
    particles: Particles,
    interfaces: dict,
    *,
    thickness: float,
    normal_stiffness,
    shear_stiffness,
    tensile_strength,
    cohesion,
    residual_friction,
    bond: str = "interface",
    friction_angle=0.0,
    compressive_strain=math.inf,
    n_elements: int = 4,
    damping_ratio: float = 0.0,
    capacity: int | None = None,
    wall_capacity: int = 1,
    surrogate_width: float = 0.0,
    time: float = 0.0,
) -> InterfaceBonds:
    """Interface bonds for the ``interfaces`` of :func:`disc_interfaces` or
    :func:`edge_interfaces` (world frame, the particles' current configuration is the bonding
    configuration, unstressed).

    Args:
        particles: :class:`Particles`; interface pair (i, j) joins particles i and j.
        interfaces: dict with ``pairs [n, 2]``, ``centres [n, 2]`` (m), ``normals [n, 2]``
            (unit, i to j) and ``widths [n]`` (m).
        thickness: slab thickness T (m); A = W T.
        normal_stiffness, shear_stiffness: k_n, k_s (Pa/m), scalars or per bond.
        tensile_strength: sigma_b (Pa).  cohesion: c (Pa).  residual_friction: mu_b (-).
        bond: "interface" (parabolic envelope, paper 003) or "parallel" (linear).
        friction_angle: phi of the linear envelope (rad).
        compressive_strain: eps_u (-); inf (default) switches compressive failure off.
        n_elements: elements per interface E (static).
        damping_ratio: zeta of the element dashpots (-), relative to ``sqrt(k A m_e)``.
        capacity: bond slots B (default: the number of interfaces, at least 1).
        wall_capacity: wall-bond slots of the nested wall bonds.
        surrogate_width: 0 hard failure; > 0 the smooth surrogate (DESIGN §7).
        time: current simulation time (s).
    """
    if bond not in ENVELOPES:
        raise ValueError(f"bond must be one of {sorted(ENVELOPES)}, got {bond!r}")
    if int(n_elements) < 1:
        raise ValueError(f"n_elements must be >= 1, got {n_elements}")
    if not thickness > 0:
        raise ValueError(f"thickness must be > 0 m, got {thickness}")
    if not surrogate_width >= 0:
        raise ValueError(f"surrogate_width must be >= 0, got {surrogate_width}")
    pairs = np.asarray(interfaces["pairs"], np.int64).reshape(-1, 2)
    n = len(pairs)
    n_p = particles.capacity
    cap = max(n, 1) if capacity is None else int(capacity)
    if cap < max(n, 1):
        raise ValueError(f"bond capacity {cap} too small for {n} interfaces; use capacity>={n}")
    ii, jj = pairs[:, 0], pairs[:, 1]
    if np.any(ii >= jj) or (n and jj.max() >= n_p):
        raise ValueError("interface pairs must be (i, j) with i < j < particle capacity")
    active = np.asarray(particles.active)
    if n and not (active[ii].all() and active[jj].all()):
        raise ValueError("an interface joins an inactive particle slot")
    centre = np.asarray(interfaces["centres"], float).reshape(n, 2)
    normal = np.asarray(interfaces["normals"], float).reshape(n, 2)
    width = _per_bond(interfaces["widths"], n, "widths", positive=True)
    pos = np.asarray(particles.pos, float)
    ang = np.asarray(particles.angle, float)
    gap = pos[jj] - pos[ii]
    if n and np.any(np.sum(gap * normal, axis=1) <= 0):
        raise ValueError("an interface normal does not point from particle i towards j")
    ne = int(n_elements)
    tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
    s = ((np.arange(ne) + 0.5) / ne - 0.5)[None, :] * width[:, None]  # [n, E]
    x_e = centre[:, None, :] + s[..., None] * tangent[:, None, :]
    pt_i = _rot_np(x_e - pos[ii][:, None, :], -ang[ii][:, None])
    pt_j = _rot_np(x_e - pos[jj][:, None, :], -ang[jj][:, None])
    length = np.linalg.norm(gap, axis=1)
    k_n = _per_bond(normal_stiffness, n, "normal_stiffness", positive=False)
    k_s = _per_bond(shear_stiffness, n, "shear_stiffness", positive=False)
    area = width * thickness
    m = np.asarray(particles.mass, float)
    m_e = m[ii] * m[jj] / (m[ii] + m[jj]) if n else np.zeros(0)
    eta = lambda k: 2.0 * damping_ratio * np.sqrt(k * area * m_e) / ne
    fd = particles.pos.dtype
    f = lambda x, fill=0.0: jnp.asarray(_pad(np.asarray(x, float), cap, fill), fd)
    env = np.full(n, ENVELOPES[bond], np.int32)
    return InterfaceBonds(
        i=jnp.asarray(_pad(ii.astype(np.int32), cap, n_p), jnp.int32),
        j=jnp.asarray(_pad(jj.astype(np.int32), cap, n_p), jnp.int32),
        point_i=f(_rot_np(centre - pos[ii], -ang[ii])),
        point_j=f(_rot_np(centre - pos[jj], -ang[jj])),
        normal_i=f(_rot_np(normal, -ang[ii]), 0.0),
        theta0=f(ang[jj] - ang[ii]),
        length=f(length, 1.0),
        width=f(width),
        area=f(area),
        elem_point_i=f(pt_i.reshape(n, ne, 2)),
        elem_point_j=f(pt_j.reshape(n, ne, 2)),
        normal_stiffness=f(k_n),
        shear_stiffness=f(k_s),
        tensile_strength=f(_per_bond(tensile_strength, n, "tensile_strength", positive=True), 1),
        cohesion=f(_per_bond(cohesion, n, "cohesion", positive=False)),
        tan_friction_angle=f(
            np.tan(_per_bond(friction_angle, n, "friction_angle", positive=False))
        ),
        envelope=jnp.asarray(_pad(env, cap, 0), jnp.int32),
        compressive_strain=f(
            _per_bond(compressive_strain, n, "compressive_strain", positive=True), 1.0
        ),
        residual_friction=f(_per_bond(residual_friction, n, "residual_friction", positive=False)),
        damping_n=f(eta(k_n)),
        damping_s=f(eta(k_s)),
        health=f(np.ones((n, ne))),
        mode=jnp.zeros((cap, ne), jnp.int32),
        elem_break_time=jnp.full((cap, ne), jnp.inf, fd),
        slip=jnp.zeros((cap, ne), fd),
        sigma=jnp.zeros((cap, ne), fd),
        tau=jnp.zeros((cap, ne), fd),
        intact=jnp.asarray(_pad(np.ones(n, bool), cap, False)),
        break_time=jnp.full((cap,), jnp.inf, fd),
        surrogate_width=jnp.asarray(surrogate_width, fd),
        time=jnp.asarray(time, fd),
        wall_bonds=empty_wall_bonds(n_p, fd, wall_capacity),
    )


def with_wall_bonds(b: InterfaceBonds, wall_bonds: Bonds) -> InterfaceBonds:
    """``b`` with new wall bonds (e.g. from :func:`jaxgran.bonds.attach_to_walls`)."""
    return eqx.tree_at(lambda m: m.wall_bonds, b, wall_bonds)
