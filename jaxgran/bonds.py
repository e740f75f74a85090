"""Cohesive bonds between Voronoi cells that share an edge, and particle-wall bonds.

The 2D form of the bonding model of paper 002 §2.2 (Galindo-Torres et al., MechSys). Two cells
of a tessellation that share an edge are joined at the edge midpoint, the *common point*,
stored once in each body frame. As the bodies move the two copies of the point separate by
``d = x_j - x_i`` and the bond resists

* opening along the normal ``n`` (tension only, Eq. 11-12): ``F_n = B_n A R(eps_n) n``,
  ``R(x) = max(x, 0)``; compression is left to the contact law (paper 002 Eq. 6),
* sliding along the tangent ``t`` (Eq. 13): ``F_t = B_t A eps_t t``,
* relative rotation (Eq. 14): ``tau = B_m A L theta``,

with ``eps_n = d . n / L``, ``eps_t = d . t / L``, ``theta = (angle_j - angle_i) - theta0`` and
``A`` the shared edge length times the slab thickness (m^2). It breaks for good when (Eq. 15)

    (|eps_n| + |eps_t|) / eps_th + |theta| / theta_th > 1.

Choices (paper 002 leaves them open in 2D; written down here and in DESIGN §6):

* **Length scale** ``L``: the distance between the two particle centroids when the bond is
  made (as MechSys does), so a strain is a displacement over the centre-to-centre distance and
  the bond is a spring of stiffness ``B_n A / L`` (N/m) in tension.
* **Rotation term** (Eq. 14): in 3D ``B_m A theta`` is a force; a torque needs one more length,
  and we use the same ``L``: ``tau = B_m A L theta`` (N m), so ``B_m`` is a modulus (Pa, Table 1
  gives 3.3 GPa) and the elastic energy keeps one form,
  ``U = A L (B_n R(eps_n)^2 + B_t eps_t^2 + B_m theta^2) / 2`` (J).
* **Normal**: the mean of the two bodies' rotated reference normals (paper 002 Fig. 5), i.e.
  i's reference normal rotated by ``angle_i + theta / 2``; it is exactly antisymmetric in
  (i, j) and needs no normalisation.
* **Point of application**: both forces act at the midpoint of the two current common points,
  so Newton's third law holds exactly for forces and for moments (the total moment of a bond
  about any point is zero), not only to first order.

Breakage is either hard (``surrogate_width == 0``: ``intact`` drops the first time Eq. 15
exceeds 1) or smooth (DESIGN §7): with width ``w > 0`` the health becomes
``min(health, 1 - smoothstep((measure - 1) / w))`` and never recovers; forces scale with the
health and the bond counts as broken once the health reaches 0 (``measure >= 1 + w``). As
``w -> 0`` this is the hard model. ``Bonds.time`` is advanced by ``dt`` at each call, so the
time of breakage is recorded without changing the integrator's call.

Wall bonds (paper 002 §4.3): a particle touching a wall is tied to it by the normal cohesive
force of Eq. 11 alone (no tangential force, no torque term, no breakage), with
``eps = (gap - gap0) / L_w`` along the wall normal and ``L_w`` the centroid-to-wall distance at
creation (the particle bonded to its mirror image across a rigid wall).

Shapes: ``B`` bond capacity, ``Bw`` wall-bond capacity, ``P`` particle capacity. Padded bonds
have ``i = j = P`` and ``intact = False``; padded wall bonds ``wall_p = P`` and
``wall_active = False``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .state import Particles, Walls


class Bonds(eqx.Module):
    """Padded particle-particle and particle-wall bonds (paper 002 §2.2, §4.3).

    Attributes:
        i, j: bonded particle indices ``[B]`` int32 (i < j), sentinel ``P`` for padding.
        point_i, point_j: the common point (shared-edge midpoint at creation) in the body
            frame of i and of j ``[B, 2]`` (m).
        normal_i: reference unit normal of the shared edge in i's body frame, from i towards j
            ``[B, 2]``.
        area: A = shared edge length x thickness ``[B]`` (m^2).
        length: L, centroid-to-centroid distance at creation ``[B]`` (m); strain = disp. / L.
        theta0: reference relative rotation ``angle_j - angle_i`` ``[B]`` (rad).
        b_n, b_t, b_m: bond moduli B_n, B_t, B_m ``[B]`` (Pa), paper 002 Eq. 11, 13, 14.
        eps_th, theta_th: strain and rotation thresholds of Eq. 15 ``[B]`` (-, rad).
        intact: ``[B]`` bool (False for broken and padded bonds).
        health: ``[B]`` in [0, 1]; 1 intact, 0 broken, between only with the smooth surrogate.
        surrogate_width: w (scalar, -); 0 is hard breakage.
        time: time of the configuration last evaluated (scalar, s).
        break_time: time of breakage ``[B]`` (s), +inf while intact.
        strain_measure: last value of the left side of Eq. 15 ``[B]`` (-).
        wall_p: bonded particle ``[Bw]`` int32 (sentinel P).  wall_w: wall index ``[Bw]`` int32.
        wall_point: attachment point in the particle's body frame ``[Bw, 2]`` (m).
        wall_gap0: reference signed distance of that point to the wall ``[Bw]`` (m).
        wall_area: ``[Bw]`` (m^2).  wall_length: L_w ``[Bw]`` (m).  wall_b_n: ``[Bw]`` (Pa).
        wall_active: ``[Bw]`` bool.
        wall_force: force of each wall bond ON its wall in the last call ``[Bw, 2]`` (N); see
            :func:`force_on_walls` (``Walls.force`` holds contact forces only).
    """

    i: Array
    j: Array
    point_i: Array
    point_j: Array
    normal_i: Array
    area: Array
    length: Array
    theta0: Array
    b_n: Array
    b_t: Array
    b_m: Array
    eps_th: Array
    theta_th: Array
    intact: Array
    health: Array
    surrogate_width: Array
    time: Array
    break_time: Array
    strain_measure: Array
    wall_p: Array
    wall_w: Array
    wall_point: Array
    wall_gap0: Array
    wall_area: Array
    wall_length: Array
    wall_b_n: Array
    wall_active: Array
    wall_force: Array

    @property
    def capacity(self) -> int:
        return self.i.shape[0]

    @property
    def wall_capacity(self) -> int:
        return self.wall_p.shape[0]


# ------------------------------------------------------------------------------ kinematics


def _dot(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _cross(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _rotate(v: Array, angle: Array) -> Array:
    """Rotate vectors ``[..., 2]`` by ``angle [...]`` (rad, CCW)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _bond_rows(p: Particles, bonds: Bonds):
    """Safe indices and the mask of bonds whose two particles exist and are active."""
    n_p = p.pos.shape[0]
    real = (bonds.i < bonds.j) & (bonds.j < n_p)
    i = jnp.where(real, bonds.i, 0)
    j = jnp.where(real, bonds.j, 0)
    return i, j, real & p.active[i] & p.active[j]


def bond_kinematics(p: Particles, bonds: Bonds) -> dict[str, Array]:
    """Current geometry and strains of every bond (paper 002 §2.2).

    Returns a dict of ``[B]`` / ``[B, 2]`` arrays: ``x_i``, ``x_j`` the common point carried by
    each body (m, world); ``normal``, ``tangent`` (unit, world; normal from i to j, tangent
    the normal turned +90 deg); ``eps_n``, ``eps_t`` (signed, -), ``theta`` (rad) and ``live``
    (real bond between active particles). Padded rows hold finite dummies.
    """
    i, j, live = _bond_rows(p, bonds)
    a_i, a_j = p.angle[i], p.angle[j]
    x_i = p.pos[i] + _rotate(bonds.point_i, a_i)
    x_j = p.pos[j] + _rotate(bonds.point_j, a_j)
    theta = (a_j - a_i) - bonds.theta0
    # mean of R(a_i) n_i and R(a_j - theta0) n_i: the bisector, already unit length
    normal = _rotate(bonds.normal_i, a_i + 0.5 * theta)
    tangent = jnp.stack([-normal[..., 1], normal[..., 0]], axis=-1)
    length = jnp.where(live & (bonds.length > 0), bonds.length, 1.0)
    d = x_j - x_i
    return {
        "x_i": x_i,
        "x_j": x_j,
        "normal": normal,
        "tangent": tangent,
        "eps_n": _dot(d, normal) / length,
        "eps_t": _dot(d, tangent) / length,
        "theta": theta,
        "live": live,
    }


# ------------------------------------------------------------------------------ law


def strain_measure(eps_n: Array, eps_t: Array, theta: Array, eps_th: Array, theta_th: Array):
    """Left side of the de-bonding condition, paper 002 Eq. 15 (-): the bond breaks when it
    exceeds 1. Compression counts too (``|eps_n|``), as in the paper."""
    return (jnp.abs(eps_n) + jnp.abs(eps_t)) / eps_th + jnp.abs(theta) / theta_th


def health_limit(measure: Array, width: Array) -> Array:
    """Health allowed by the current Eq. 15 measure: a step at 1 for ``width == 0`` (hard
    breakage), else ``1 - smoothstep((measure - 1) / width)`` (C1, 1 up to ``measure = 1``
    and 0 from ``1 + width``), so gradients with respect to thresholds exist (DESIGN §7)."""
    smooth = width > 0
    x = jnp.clip((measure - 1.0) / jnp.where(smooth, width, 1.0), 0.0, 1.0)
    soft = 1.0 - x * x * (3.0 - 2.0 * x)
    hard = jnp.where(measure > 1.0, 0.0, 1.0)
    return jnp.where(smooth, soft, hard)


def bond_law(eps_n, eps_t, theta, normal, tangent, area, length, b_n, b_t, b_m, health):
    """Force on j (N, ``[..., 2]``) and torque on j from the rotation term (N m) of one bond,
    paper 002 Eq. 11-14, scaled by the health; i receives the opposite of both."""
    f_n = b_n * area * jnp.maximum(eps_n, 0.0)  # Eq. 11-12: tension only
    f_t = b_t * area * eps_t  # Eq. 13
    force = -health[..., None] * (f_n[..., None] * normal + f_t[..., None] * tangent)
    moment = -health * b_m * area * length * theta  # Eq. 14 with the lever L
    return force, moment


def bond_forces(p: Particles, bonds: Bonds, walls: Walls, dt: Array) -> tuple[Array, Array, Bonds]:
    """Bond forces and torques on every particle, and the bonds after this evaluation.

    Evaluates the strains of the current configuration, updates breakage (Eq. 15; hard or
    smooth, never healing), then applies the forces of the surviving bonds (Eq. 11-14) at the
    midpoint of the two common points, plus the normal wall-bond forces. ``Bonds.time`` is
    advanced by ``dt`` (s) first: the integrator calls this with the positions at the end of
    the drift, i.e. at time ``t + dt``; pass ``dt = 0`` to evaluate without advancing.

    Returns:
        force ``[P, 2]`` (N), torque ``[P]`` (N m), new :class:`Bonds`. Jit-able,
        differentiable, finite (values and gradients) for padded bonds.

    Another bond model in ``SimState.bonds`` (e.g. :class:`jaxgran.interface.InterfaceBonds`)
    brings its own law as a ``forces(p, walls, dt)`` method, called here instead.
    """
    if not isinstance(bonds, Bonds):
        return bonds.forces(p, walls, dt)
    n_p = p.pos.shape[0]
    time = bonds.time + dt
    k = bond_kinematics(p, bonds)
    live = k["live"]
    eps_th = jnp.where(live, bonds.eps_th, 1.0)
    theta_th = jnp.where(live, bonds.theta_th, 1.0)
    measure = strain_measure(k["eps_n"], k["eps_t"], k["theta"], eps_th, theta_th)
    limit = health_limit(measure, bonds.surrogate_width)
    health = jnp.minimum(bonds.health, limit)
    intact = jnp.where(live, bonds.intact & (health > 0.0), bonds.intact)
    health = jnp.where(live, jnp.where(intact, health, 0.0), bonds.health)
    broke = bonds.intact & ~intact
    force_j, moment_j = bond_law(
        k["eps_n"],
        k["eps_t"],
        k["theta"],
        k["normal"],
        k["tangent"],
        bonds.area,
        bonds.length,
        bonds.b_n,
        bonds.b_t,
        bonds.b_m,
        jnp.where(live & intact, health, 0.0),
    )
    i, j, _ = _bond_rows(p, bonds)
    c = 0.5 * (k["x_i"] + k["x_j"])
    torque_j = _cross(c - p.pos[j], force_j) + moment_j
    torque_i = -_cross(c - p.pos[i], force_j) - moment_j
    seg = lambda data, idx: jax.ops.segment_sum(data, idx, num_segments=n_p)
    force = seg(force_j, j) - seg(force_j, i)
    torque = seg(torque_j, j) + seg(torque_i, i)

    f_w, t_w, on_wall = _wall_bond_forces(p, bonds, walls)
    new = eqx.tree_at(
        lambda b: (b.intact, b.health, b.time, b.break_time, b.strain_measure, b.wall_force),
        bonds,
        (
            intact,
            health,
            time,
            jnp.where(broke, time, bonds.break_time),
            jnp.where(live, measure, bonds.strain_measure),
            on_wall,
        ),
    )
    return force + f_w, torque + t_w, new


def _wall_bond_geometry(p: Particles, bonds: Bonds, walls: Walls):
    """Per wall bond: safe particle index, attachment point (m, world), wall normal, strain
    ``(gap - gap0) / L_w`` (-), length L_w (m) and the live mask."""
    n_p = p.pos.shape[0]
    ok = bonds.wall_active & (bonds.wall_p < n_p) & (bonds.wall_w < walls.point.shape[0])
    k = jnp.where(ok, bonds.wall_p, 0)
    w = jnp.where(ok, bonds.wall_w, 0)
    live = ok & p.active[k] & walls.active[w]
    x = p.pos[k] + _rotate(bonds.wall_point, p.angle[k])
    normal = walls.normal[w]
    gap = _dot(x - walls.point[w], normal)
    length = jnp.where(live & (bonds.wall_length > 0), bonds.wall_length, 1.0)
    return k, x, normal, (gap - bonds.wall_gap0) / length, length, live


def _wall_bond_forces(p: Particles, bonds: Bonds, walls: Walls):
    """Normal cohesive wall-bond forces (paper 002 §4.3, Eq. 11 only): force ``[P, 2]`` (N)
    and torque ``[P]`` (N m) on the particles, force on the wall per bond ``[Bw, 2]`` (N)."""
    n_p = p.pos.shape[0]
    k, x, normal, eps, _, live = _wall_bond_geometry(p, bonds, walls)
    mag = jnp.where(live, bonds.wall_b_n * bonds.wall_area * jnp.maximum(eps, 0.0), 0.0)
    f = -mag[:, None] * normal
    force = jax.ops.segment_sum(f, k, num_segments=n_p)
    torque = jax.ops.segment_sum(_cross(x - p.pos[k], f), k, num_segments=n_p)
    return force, torque, -f


def force_on_walls(bonds: Bonds, n_walls: int) -> Array:
    """Total force of the wall bonds on each wall in the last evaluation ``[W, 2]`` (N); add it
    to ``Walls.force`` (contacts only) to get the full wall load in a tension test."""
    w = jnp.where(bonds.wall_active, bonds.wall_w, n_walls)
    return jax.ops.segment_sum(bonds.wall_force, w, num_segments=n_walls)


def bond_energy(p: Particles, bonds: Bonds) -> Array:
    """Elastic energy stored in the particle-particle bonds (J, scalar), health-weighted:
    ``A L (B_n R(eps_n)^2 + B_t eps_t^2 + B_m theta^2) / 2`` per bond, the potential of
    Eq. 11-14 for a fixed normal (see :func:`wall_bond_energy` for the wall bonds)."""
    k = bond_kinematics(p, bonds)
    h = jnp.where(k["live"] & bonds.intact, bonds.health, 0.0)
    e = (
        bonds.b_n * jnp.maximum(k["eps_n"], 0.0) ** 2
        + bonds.b_t * k["eps_t"] ** 2
        + bonds.b_m * k["theta"] ** 2
    )
    return jnp.sum(h * 0.5 * bonds.area * bonds.length * e)


def wall_bond_energy(p: Particles, bonds: Bonds, walls: Walls) -> Array:
    """Elastic energy of the wall bonds (J, scalar): ``A L_w B_n R(eps)^2 / 2`` each."""
    _, _, _, eps, length, live = _wall_bond_geometry(p, bonds, walls)
    u = 0.5 * bonds.wall_b_n * bonds.wall_area * length * jnp.maximum(eps, 0.0) ** 2
    return jnp.sum(jnp.where(live, u, 0.0))


# ------------------------------------------------------------------------------ bookkeeping


def broken_mask(bonds: Bonds) -> Array:
    """Real bonds that have broken ``[B]`` bool (padding excluded)."""
    return (bonds.i < bonds.j) & ~bonds.intact


def bond_summary(bonds: Bonds) -> dict[str, int | float]:
    """Host-side counts: ``n_bonds`` (real), ``n_intact``, ``n_broken``, ``n_wall_bonds``,
    ``mean_health`` of the intact bonds and ``time`` (s)."""
    real = np.asarray(bonds.i < bonds.j)
    intact = np.asarray(bonds.intact) & real
    health = np.asarray(bonds.health)
    return {
        "n_bonds": int(real.sum()),
        "n_intact": int(intact.sum()),
        "n_broken": int((real & ~intact).sum()),
        "n_wall_bonds": int(np.asarray(bonds.wall_active).sum()),
        "mean_health": float(health[intact].mean()) if intact.any() else 0.0,
        "time": float(bonds.time),
    }


# ------------------------------------------------------------------------------ constructors


def _per_bond(value, n: int, name: str, *, positive: bool) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim not in (0, 1) or (arr.ndim == 1 and arr.shape[0] != n):
        raise ValueError(f"{name} must be a scalar or one value per bond ({n}), got {arr.shape}")
    arr = np.broadcast_to(arr, (n,)).copy()
    bad = ~(arr > 0) if positive else ~(arr >= 0)
    if np.any(bad | np.isnan(arr)):
        sign = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be {sign} (inf allowed), got {arr[bad | np.isnan(arr)]}")
    return arr


def _pad(values: np.ndarray, cap: int, fill) -> np.ndarray:
    out = np.full((cap,) + values.shape[1:], fill, dtype=values.dtype)
    out[: len(values)] = values
    return out


def _rot_np(v: np.ndarray, angle) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _empty_wall_fields(n_p: int, fd) -> dict:
    return {
        "wall_p": jnp.full((1,), n_p, jnp.int32),
        "wall_w": jnp.zeros((1,), jnp.int32),
        "wall_point": jnp.zeros((1, 2), fd),
        "wall_gap0": jnp.zeros((1,), fd),
        "wall_area": jnp.zeros((1,), fd),
        "wall_length": jnp.ones((1,), fd),
        "wall_b_n": jnp.zeros((1,), fd),
        "wall_active": jnp.zeros((1,), bool),
        "wall_force": jnp.zeros((1, 2), fd),
    }


def make_bonds(
    cells_world: list,
    particles: Particles,
    *,
    thickness: float,
    b_n,
    b_t,
    b_m,
    eps_th,
    theta_th,
    capacity: int | None = None,
    tol: float = 1e-9,
    surrogate_width: float = 0.0,
    time: float = 0.0,
) -> Bonds:
    """Bond every pair of cells that share an edge (paper 002 §2.2).

    Args:
        cells_world: the tessellation BEFORE erosion, ``[n_k, 2]`` polygons (m); cell k is
            particle k (``particles`` built from the eroded cells in the same order).
        particles: :class:`Particles` in the configuration that defines the unstrained bonds.
        thickness: slab thickness (m); A = shared edge length x thickness.
        b_n, b_t, b_m: moduli (Pa), scalars or one per bond (in :func:`geometry.shared_edges`
            order, sorted by (i, j)).
        eps_th, theta_th: thresholds of Eq. 15 (-, rad), scalars or per bond (random
            thresholds); ``inf`` switches a term off.
        capacity: bond slots B (default: the number of shared edges, at least 1).
        tol: relative tolerance for shared edges (see :func:`geometry.shared_edges`).
        surrogate_width: 0 for hard breakage, > 0 for the smooth surrogate (DESIGN §7).
        time: current simulation time (s), the clock of ``break_time``.
    """
    from .geometry import shared_edges

    n_p = particles.capacity
    if len(cells_world) > n_p:
        raise ValueError(f"{len(cells_world)} cells but only {n_p} particle slots")
    active = np.asarray(particles.active)
    if not active[: len(cells_world)].all():
        raise ValueError("every cell must be an active particle (same order as cells_world)")
    if not thickness > 0:
        raise ValueError(f"thickness must be > 0 m, got {thickness}")
    edges = shared_edges(cells_world, tol=tol)
    n = len(edges)
    cap = max(n, 1) if capacity is None else int(capacity)
    if cap < max(n, 1):
        raise ValueError(
            f"bond capacity {cap} too small for the {n} shared edges; use capacity>={n}"
        )
    pos = np.asarray(particles.pos, dtype=float)
    ang = np.asarray(particles.angle, dtype=float)
    ii = np.array([e[0] for e in edges], dtype=np.int32).reshape(n)
    jj = np.array([e[1] for e in edges], dtype=np.int32).reshape(n)
    a = np.array([e[2] for e in edges], dtype=float).reshape(n, 2)
    b = np.array([e[3] for e in edges], dtype=float).reshape(n, 2)
    mid = 0.5 * (a + b)
    edge_len = np.linalg.norm(b - a, axis=1)
    tan = (b - a) / np.where(edge_len > 0, edge_len, 1.0)[:, None]
    normal = np.stack([tan[:, 1], -tan[:, 0]], axis=1)  # outward of i (edge is CCW along i)
    centre_gap = pos[jj] - pos[ii]
    if np.any(np.sum(centre_gap * normal, axis=1) <= 0):
        bad = int(np.argmin(np.sum(centre_gap * normal, axis=1)))
        raise ValueError(
            f"bond ({ii[bad]}, {jj[bad]}): particle j is not on the outer side of the shared "
            "edge; are the particles in the same order as cells_world?"
        )
    params = {
        "b_n": _per_bond(b_n, n, "b_n", positive=False),
        "b_t": _per_bond(b_t, n, "b_t", positive=False),
        "b_m": _per_bond(b_m, n, "b_m", positive=False),
        "eps_th": _per_bond(eps_th, n, "eps_th", positive=True),
        "theta_th": _per_bond(theta_th, n, "theta_th", positive=True),
    }
    if not surrogate_width >= 0:
        raise ValueError(f"surrogate_width must be >= 0, got {surrogate_width}")
    fd = particles.pos.dtype
    f = lambda x, fill=0.0: jnp.asarray(_pad(x, cap, fill), fd)
    return Bonds(
        i=jnp.asarray(_pad(ii, cap, n_p), jnp.int32),
        j=jnp.asarray(_pad(jj, cap, n_p), jnp.int32),
        point_i=f(_rot_np(mid - pos[ii], -ang[ii])),
        point_j=f(_rot_np(mid - pos[jj], -ang[jj])),
        normal_i=f(_rot_np(normal, -ang[ii])),
        area=f(edge_len * thickness),
        length=f(np.linalg.norm(centre_gap, axis=1), 1.0),
        theta0=f(ang[jj] - ang[ii]),
        b_n=f(params["b_n"]),
        b_t=f(params["b_t"]),
        b_m=f(params["b_m"]),
        eps_th=f(params["eps_th"], 1.0),
        theta_th=f(params["theta_th"], 1.0),
        intact=jnp.asarray(_pad(np.ones(n, bool), cap, False)),
        health=f(np.ones(n)),
        surrogate_width=jnp.asarray(surrogate_width, fd),
        time=jnp.asarray(time, fd),
        break_time=jnp.full((cap,), jnp.inf, fd),
        strain_measure=jnp.zeros((cap,), fd),
        **_empty_wall_fields(n_p, fd),
    )


def attach_to_walls(
    bonds: Bonds,
    particles: Particles,
    walls: Walls,
    *,
    distance: float,
    b_n,
    thickness: float,
    width: float | None = None,
    capacity: int | None = None,
) -> Bonds:
    """Tie every particle that has a vertex within ``distance`` of a wall to it (paper 002
    §4.3): normal cohesive force of Eq. 11 only, never breaking. Existing wall bonds are kept.

    For each (active particle, active wall) the *near* core vertices are those whose surface
    gap (distance of the vertex to the wall line minus the sphero-radius) is at most
    ``distance`` and that lie within the wall's extent. The attachment point is their mean,
    the bonded width their span along the wall (a face lying on the wall gives its length; a
    lone corner gives ``2 * radius``), unless ``width`` (m) is given; A = width x thickness.
    The length scale is the centroid-to-wall distance.

    Args:
        distance: capture distance (m, >= 0).
        b_n: B_n (Pa), scalar or one per new wall bond.
        thickness: slab thickness (m).
        capacity: wall-bond slots Bw (default: exactly the number of wall bonds, at least 1).
    """
    if not distance >= 0:
        raise ValueError(f"distance must be >= 0 m, got {distance}")
    if not thickness > 0:
        raise ValueError(f"thickness must be > 0 m, got {thickness}")
    n_p = particles.capacity
    verts = np.asarray(particles.verts, dtype=float)
    nv = np.asarray(particles.n_verts)
    pos = np.asarray(particles.pos, dtype=float)
    ang = np.asarray(particles.angle, dtype=float)
    rad = np.asarray(particles.radius, dtype=float)
    act = np.asarray(particles.active)
    wp, wn = np.asarray(walls.point, dtype=float), np.asarray(walls.normal, dtype=float)
    wext, wact = np.asarray(walls.extent, dtype=float), np.asarray(walls.active)
    rows = []
    for k in np.nonzero(act)[0]:
        v = pos[k] + _rot_np(verts[k, : nv[k]], ang[k])
        for w in np.nonzero(wact)[0]:
            n = wn[w]
            t = np.array([-n[1], n[0]])
            gap = (v - wp[w]) @ n
            s = (v - wp[w]) @ t
            near = (gap - rad[k] <= distance) & (s >= wext[w, 0]) & (s <= wext[w, 1])
            if not near.any():
                continue
            x = v[near].mean(axis=0)
            span = float(s[near].max() - s[near].min())
            bw = width if width is not None else (span if span > 0 else 2.0 * rad[k])
            if not bw > 0:
                raise ValueError(
                    f"particle {k} touches wall {w} at a single corner and has no sphero-radius"
                    ": give attach_to_walls a bond width"
                )
            rows.append(
                (k, w, _rot_np(x - pos[k], -ang[k]), (x - wp[w]) @ n, bw, (pos[k] - wp[w]) @ n)
            )
    old = np.asarray(bonds.wall_active)
    n_old = int(old.sum())
    n_new = len(rows)
    cap = max(n_old + n_new, 1) if capacity is None else int(capacity)
    if cap < n_old + n_new:
        raise ValueError(
            f"wall-bond capacity {cap} too small for {n_old + n_new} wall bonds; use "
            f"capacity>={n_old + n_new}"
        )
    if any(r[5] <= 0 for r in rows):
        raise ValueError("a bonded particle's centroid is not on the inner side of its wall")
    new_b_n = _per_bond(b_n, n_new, "b_n", positive=False)
    keep = lambda x: np.asarray(x)[old]
    stack = lambda old_vals, new_vals: np.concatenate([old_vals, np.asarray(new_vals)], axis=0)
    fd = bonds.area.dtype
    col = lambda idx: [r[idx] for r in rows]
    fields = {
        "wall_p": (stack(keep(bonds.wall_p), np.array(col(0), np.int32)), n_p, jnp.int32),
        "wall_w": (stack(keep(bonds.wall_w), np.array(col(1), np.int32)), 0, jnp.int32),
        "wall_point": (
            stack(keep(bonds.wall_point), np.array(col(2), float).reshape(n_new, 2)),
            0.0,
            fd,
        ),
        "wall_gap0": (stack(keep(bonds.wall_gap0), np.array(col(3), float)), 0.0, fd),
        "wall_area": (stack(keep(bonds.wall_area), np.array(col(4)) * thickness), 0.0, fd),
        "wall_length": (stack(keep(bonds.wall_length), np.array(col(5), float)), 1.0, fd),
        "wall_b_n": (stack(keep(bonds.wall_b_n), new_b_n), 0.0, fd),
        "wall_active": (np.ones(n_old + n_new, bool), False, bool),
    }
    out = {
        name: jnp.asarray(_pad(np.asarray(v, dtype=np.dtype(dt)), cap, fill), dt)
        for name, (v, fill, dt) in fields.items()
    }
    out["wall_force"] = jnp.zeros((cap, 2), fd)
    names = list(out)
    return eqx.tree_at(lambda b: [getattr(b, m) for m in names], bonds, list(out.values()))
