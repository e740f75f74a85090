"""Simulation state as immutable pytrees (equinox Modules).

Shapes use named axes: ``P`` particle capacity, ``V`` vertex capacity, ``W`` number of walls,
``C`` pair capacity. Capacities are static (they fix array shapes and so the compiled code);
values never recompile. Units are SI; 2D quantities are per unit thickness unless stated
(``Params.thickness`` converts them to forces on a slab of that thickness where needed).

Particles are spheropolygons (paper 000 §II.A; paper 002 §2.1): a convex core polygon, stored
in its body frame with the centroid at the origin, swept by a disc of radius ``radius``. Padded
vertex slots repeat the last real vertex and are masked by ``n_verts``; padded particle slots
have ``active == False``, unit mass and inertia (no division by zero) and sit at their last
position.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array

# Error bitmask raised by run_segment (see simulate.py); never silently truncate.
ERR_CELL_OVERFLOW = 1
ERR_PAIR_OVERFLOW = 2
ERR_NAN = 4
ERR_LEFT_DOMAIN = 8
ERR_SKIN_EXCEEDED = 16
# more touching vertex slots than the compacted contact list (2 x pair capacity) holds; it is
# always raised together with ERR_PAIR_OVERFLOW, so every host loop grows the pair capacity
ERR_CONTACT_OVERFLOW = 32
ERROR_NAMES = {
    ERR_CELL_OVERFLOW: "cell capacity exceeded",
    ERR_PAIR_OVERFLOW: "pair capacity exceeded",
    ERR_NAN: "NaN or inf in the state",
    ERR_LEFT_DOMAIN: "a particle left the domain",
    ERR_SKIN_EXCEEDED: "a particle moved more than half the Verlet skin in one step",
    ERR_CONTACT_OVERFLOW: "vertex contacts exceed the compacted list (2 x pair capacity)",
}

WALL_FIXED = 0
WALL_VELOCITY = 1
WALL_SERVO = 2


def describe_errors(code: int) -> list[str]:
    """Names of the error bits set in ``code``."""
    return [name for bit, name in ERROR_NAMES.items() if int(code) & bit]


class Particles(eqx.Module):
    """Padded spheropolygons.

    Attributes:
        verts: core vertices in the body frame, centroid at the origin, CCW ``[P, V, 2]`` (m).
        n_verts: number of real vertices ``[P]``; 1 is a disc, 2 a stadium.
        radius: sphero-radius ``[P]`` (m).
        bound_radius: circumradius of the core plus ``radius`` ``[P]`` (m), for the broad phase.
        mass: ``[P]`` (kg, per ``Params.thickness`` slab: areal density x area).
        inertia: polar moment about the centroid ``[P]`` (kg m^2).
        pos: centroid position ``[P, 2]`` (m).  angle: orientation ``[P]`` (rad).
        vel: ``[P, 2]`` (m/s).  omega: angular velocity ``[P]`` (rad/s).
        force: total force of the last step ``[P, 2]`` (N).  torque: ``[P]`` (N m).
        active: ``[P]`` bool.  uid, parent_uid, material: ``[P]`` int32 (parent -1 if none).
        fixed: ``[P]`` bool, kinematically driven particles (their velocity is not integrated).
    """

    verts: Array
    n_verts: Array
    radius: Array
    bound_radius: Array
    mass: Array
    inertia: Array
    pos: Array
    angle: Array
    vel: Array
    omega: Array
    force: Array
    torque: Array
    active: Array
    fixed: Array
    uid: Array
    parent_uid: Array
    material: Array

    @property
    def capacity(self) -> int:
        return self.pos.shape[0]

    @property
    def vertex_capacity(self) -> int:
        return self.verts.shape[1]


class Walls(eqx.Module):
    """Planar walls (lines), each acting on particle vertices on its positive side.

    A wall is the line through ``point`` with unit ``normal`` pointing into the domain; it is
    limited along its tangent ``t = (-n_y, n_x)`` to ``extent = [s_min, s_max]`` (m, measured
    from ``point``; use +-inf for an infinite wall).

    Attributes:
        point ``[W, 2]`` (m), normal ``[W, 2]``, extent ``[W, 2]`` (m), vel ``[W, 2]`` (m/s).
        mode ``[W]`` int32: WALL_FIXED, WALL_VELOCITY (moves at ``vel``) or WALL_SERVO
            (moves along its normal to hold ``target_stress``).
        target_stress ``[W]`` (Pa, compression positive), servo_gain ``[W]`` (m/(s Pa)),
        max_speed ``[W]`` (m/s, servo speed cap), length ``[W]`` (m, loaded length used to turn
        force into stress: stress = force / (length * thickness)).
        servo_time ``[W]`` (s): integral time T_i of the servo; +inf (the default) is the
        proportional servo alone, which trails a specimen that keeps dilating or contracting
        by ``speed / servo_gain``; finite adds the integral term that removes that offset
        (:func:`jaxgran.integrate.wall_velocity`).
        servo_integral ``[W]`` (m/s): the integral term's speed, carried from step to step.
        force ``[W, 2]`` (N): force exerted BY the particles ON the wall in the last step.
        active ``[W]`` bool.
    """

    point: Array
    normal: Array
    extent: Array
    vel: Array
    mode: Array
    target_stress: Array
    servo_gain: Array
    max_speed: Array
    length: Array
    force: Array
    active: Array
    servo_time: Array
    servo_integral: Array

    @property
    def count(self) -> int:
        return self.point.shape[0]


class Contacts(eqx.Module):
    """Verlet pair list and tangential spring history (Cundall-Strack).

    Attributes:
        pairs: ``[C, 2]`` int32 particle indices (i < j), padded with the sentinel ``P``; sorted
            by key ``i * P + j`` so the history can be carried over a rebuild by search.
        n_pairs: number of valid pairs (int32 scalar); above the capacity after an overflow,
            the largest number a build needed since.
        xi: tangential spring ``[2, C, 2, V]`` (m): (x, y) component first, then per pair, per
            direction (0: vertices of i against j; 1: vertices of j against i) and per vertex.
        wall_xi: tangential spring against walls ``[2, P, W, V]`` (m).
        ref_pos: particle positions at the last rebuild ``[P, 2]`` (m).
        ref_angle: orientations at the last rebuild ``[P]`` (rad).
        n_builds: number of pair-list builds so far (int32 scalar).
    """

    pairs: Array
    n_pairs: Array
    xi: Array
    wall_xi: Array
    ref_pos: Array
    ref_angle: Array
    n_builds: Array

    @property
    def capacity(self) -> int:
        """Pair slots, also of a batch of pair lists (``pairs`` ``[..., C, 2]``)."""
        return self.pairs.shape[-2]


class Params(eqx.Module):
    """Contact-law and run parameters (all traced: changing a value never recompiles).

    Attributes:
        normal_stiffness: K_n (N/m), paper 000 Table I.
        tangential_stiffness: K_t (N/m).
        friction: particle-particle Coulomb coefficient mu.
        wall_friction: particle-wall Coulomb coefficient: a scalar, or one per wall ``[W]``
            (e.g. frictional platens and frictionless side walls of a biaxial cell).
        normal_damping: G_n (1/s), paper 002 Eq. 10: F_v = G_n m_e v_n.
        tangential_damping: G_t (1/s).
        gravity: ``[2]`` (m/s^2).
        dt: time step (s).
        skin: Verlet distance (m), paper 000 Table I: the pair list holds every pair whose
            bounding circles are closer than ``skin``; it is rebuilt when a particle has moved
            more than ``skin / 2``.
        thickness: out-of-plane thickness (m) used to turn 2D wall forces into stresses.
        shear_modulus (Pa), poisson_ratio: elastic constants of the grain material (BEM).
    """

    normal_stiffness: Array
    tangential_stiffness: Array
    friction: Array
    wall_friction: Array
    normal_damping: Array
    tangential_damping: Array
    gravity: Array
    dt: Array
    skin: Array
    thickness: Array
    shear_modulus: Array
    poisson_ratio: Array


def make_params(
    *,
    normal_stiffness: float = 6.0e5,
    tangential_stiffness: float = 2.2e4,
    friction: float = 0.74,
    wall_friction: float | tuple | None = None,
    normal_damping: float = 0.0,
    tangential_damping: float = 0.0,
    gravity: tuple[float, float] = (0.0, -9.81),
    dt: float = 1.0e-5,
    skin: float = 2.0e-3,
    thickness: float = 1.0,
    shear_modulus: float = 2.1e8,
    poisson_ratio: float = 0.3,
    dtype=None,
) -> Params:
    """Build :class:`Params`; defaults are paper 000 Table I (K_n, K_t, mu, Verlet distance,
    G, nu). ``dt`` should come from :func:`jaxgran.integrate.stable_time_step`;
    ``wall_friction`` is ``friction`` where None, or a scalar, or one value per wall."""
    dtype = dtype or jnp.result_type(float)
    checks = {
        "normal_stiffness": normal_stiffness,
        "dt": dt,
        "skin": skin,
        "thickness": thickness,
    }
    for name, value in checks.items():
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be positive and finite, got {value!r}")
    for name, value in {
        "tangential_stiffness": tangential_stiffness,
        "friction": friction,
        "normal_damping": normal_damping,
        "tangential_damping": tangential_damping,
    }.items():
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} must be >= 0 and finite, got {value!r}")
    mu_w = np.asarray(friction if wall_friction is None else wall_friction, dtype=float)
    if mu_w.ndim > 1 or not np.all(np.isfinite(mu_w)) or np.any(mu_w < 0):
        raise ValueError(
            f"wall_friction must be >= 0 and finite, one value or one per wall, "
            f"got {wall_friction!r}"
        )
    f = lambda x: jnp.asarray(x, dtype=dtype)
    return Params(
        normal_stiffness=f(normal_stiffness),
        tangential_stiffness=f(tangential_stiffness),
        friction=f(friction),
        wall_friction=f(mu_w),
        normal_damping=f(normal_damping),
        tangential_damping=f(tangential_damping),
        gravity=f(np.asarray(gravity, dtype=float)),
        dt=f(dt),
        skin=f(skin),
        thickness=f(thickness),
        shear_modulus=f(shear_modulus),
        poisson_ratio=f(poisson_ratio),
    )


def _as_origin(x) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.shape != (2,) or not np.all(np.isfinite(a)):
        raise ValueError(f"grid origin must be two finite numbers (x, y) in m, got {x!r}")
    return a


def _as_cell_size(x) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.size != 1 or not (np.isfinite(a) and a > 0):
        raise ValueError(f"grid cell size must be one positive, finite number (m), got {x!r}")
    return a.reshape(())


class Grid(eqx.Module):
    """Broad-phase configuration.

    The domain ``[origin, origin + cell_size * (nx, ny)]`` (m) is divided into square cells of
    side ``cell_size`` >= the largest bounding diameter plus the skin; ``cell_capacity``
    particles fit in a cell. A particle outside the domain raises ``ERR_LEFT_DOMAIN``.

    ``origin`` ``[2]`` and ``cell_size`` (0-d) are values (float64 numpy arrays, leaves of the
    pytree): moving or rescaling the grid reuses the compiled code. ``nx``, ``ny`` and
    ``cell_capacity`` fix array shapes, so they are static: changing them recompiles.
    """

    origin: np.ndarray = eqx.field(converter=_as_origin)
    cell_size: np.ndarray = eqx.field(converter=_as_cell_size)
    nx: int = eqx.field(static=True)
    ny: int = eqx.field(static=True)
    cell_capacity: int = eqx.field(static=True)

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    def __setstate__(self, state: dict) -> None:
        # checkpoints written before the grid became a pytree hold a plain tuple and float
        state = dict(state)
        state["origin"] = _as_origin(state["origin"])
        state["cell_size"] = _as_cell_size(state["cell_size"])
        for k, v in state.items():
            object.__setattr__(self, k, v)


class EnergyLedger(eqx.Module):
    """Energy supplied and dissipated since the ledger was attached (J, scalars, cumulative;
    on a slab of the scene's thickness wherever the forces are). Attach one with
    :func:`jaxgran.energy.attach`; with ``SimState.energy`` set, every step accumulates:

    - ``boundary_work``: work of the walls on the particles (contacts and wall bonds),
    - ``body_work``: work of gravity and of applied body forces,
    - ``dashpot``: dissipated by the normal and tangential contact dashpots,
    - ``friction``: dissipated by Coulomb slip,
    - ``damping``: removed by a scene's background (velocity-proportional) damping,
    - ``breakage``: released at breakage (elastic energy of bonds as they soften or break,
      plus the mechanical energy a host-side particle replacement removes),

    and ``stored0`` holds the kinetic + elastic energy at attachment. The balance is
    ``boundary_work + body_work = (stored - stored0) + dashpot + friction + damping +
    breakage`` (:func:`jaxgran.energy.balance`).
    """

    boundary_work: Array
    body_work: Array
    dashpot: Array
    friction: Array
    damping: Array
    breakage: Array
    stored0: Array


class SimState(eqx.Module):
    """Everything that evolves in time. ``time`` (s) and ``step`` are scalars. ``energy``
    (optional, static presence like ``bonds``) is an :class:`EnergyLedger` that the step
    updates; without it the step computes no energy terms."""

    particles: Particles
    walls: Walls
    contacts: Contacts
    time: Array
    step: Array
    bonds: eqx.Module | None = None
    energy: EnergyLedger | None = None


def replace(module: eqx.Module, **changes) -> eqx.Module:
    """Functional update of some fields of an equinox Module (returns a new Module)."""
    names = list(changes)
    return eqx.tree_at(
        lambda m: [getattr(m, n) for n in names],
        module,
        list(changes.values()),
        is_leaf=lambda x: x is None,
    )


# ----------------------------------------------------------------------------- constructors


def _float(dtype):
    return dtype or jnp.result_type(float)


def particles_from_polygons(
    polygons: list,
    radius,
    areal_density,
    *,
    capacity: int | None = None,
    vertex_capacity: int | None = None,
    velocities=None,
    material=None,
    dtype=None,
) -> Particles:
    """Spheropolygons from core polygons given in world coordinates.

    Args:
        polygons: list of ``[n, 2]`` arrays (m): convex core polygons (n >= 3), or a single
            point (n = 1, a disc) or a segment (n = 2) when ``radius > 0``.
        radius: sphero-radius r (m), scalar or one per polygon.
        areal_density: mass per unit area (kg/m^2), i.e. density x thickness; scalar or one per
            polygon. Mass and inertia are exact for the swept shape.
        capacity: particle slots P (>= len(polygons)); extra slots are inactive.
        vertex_capacity: V (>= the largest n).
        velocities: optional ``[N, 2]`` initial velocities (m/s).
        material: optional ``[N]`` int material ids.
    """
    from . import geometry as geo

    n = len(polygons)
    if n == 0:
        raise ValueError("no particle given")
    radius = np.broadcast_to(np.asarray(radius, dtype=float), (n,))
    dens = np.broadcast_to(np.asarray(areal_density, dtype=float), (n,))
    if np.any(~np.isfinite(radius)) or np.any(radius < 0):
        raise ValueError("sphero-radius must be finite and >= 0")
    if np.any(~np.isfinite(dens)) or np.any(dens <= 0):
        raise ValueError("areal density must be positive (kg/m^2 = density x thickness)")
    body, pos, mass, inertia = [], [], [], []
    for k, poly in enumerate(polygons):
        v = np.asarray(poly, dtype=float).reshape(-1, 2)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"particle {k}: vertices contain NaN or inf")
        if len(v) >= 3:
            v = geo.validate_polygon(v, name=f"particle {k}")
        elif radius[k] <= 0:
            raise ValueError(
                f"particle {k} has {len(v)} vertices and zero sphero-radius: a polygon needs "
                "at least 3 vertices, a disc (1 vertex) or stadium (2) needs radius > 0"
            )
        m, c, i = geo.spheropolygon_mass_properties(v, radius[k], dens[k])
        if not (m > 0 and i > 0):
            raise ValueError(f"particle {k}: zero mass or inertia; check its size and density")
        body.append(v - c)
        pos.append(c)
        mass.append(m)
        inertia.append(i)
    cap = n if capacity is None else int(capacity)
    if cap < n:
        raise ValueError(f"capacity {cap} is smaller than the {n} particles given")
    nmax = max(len(b) for b in body)
    vcap = nmax if vertex_capacity is None else int(vertex_capacity)
    if vcap < nmax:
        raise ValueError(f"vertex capacity {vcap} too small: a polygon has {nmax} vertices")
    verts = np.zeros((cap, vcap, 2))
    nv = np.ones(cap, dtype=np.int32)
    for k, b in enumerate(body):
        verts[k, : len(b)] = b
        verts[k, len(b) :] = b[-1]
        nv[k] = len(b)
    bound = np.zeros(cap)
    bound[:n] = [np.max(np.linalg.norm(b, axis=1)) + radius[k] for k, b in enumerate(body)]
    r = np.zeros(cap)
    r[:n] = radius
    m_arr = np.ones(cap)
    m_arr[:n] = mass
    i_arr = np.ones(cap)
    i_arr[:n] = inertia
    p_arr = np.zeros((cap, 2))
    p_arr[:n] = pos
    vel = np.zeros((cap, 2))
    if velocities is not None:
        vel[:n] = np.asarray(velocities, dtype=float).reshape(n, 2)
    mat = np.zeros(cap, dtype=np.int32)
    if material is not None:
        mat[:n] = np.asarray(material, dtype=np.int32)
    active = np.zeros(cap, dtype=bool)
    active[:n] = True
    fd = _float(dtype)
    f = lambda x: jnp.asarray(x, dtype=fd)
    return Particles(
        verts=f(verts),
        n_verts=jnp.asarray(nv),
        radius=f(r),
        bound_radius=f(bound),
        mass=f(m_arr),
        inertia=f(i_arr),
        pos=f(p_arr),
        angle=f(np.zeros(cap)),
        vel=f(vel),
        omega=f(np.zeros(cap)),
        force=f(np.zeros((cap, 2))),
        torque=f(np.zeros(cap)),
        active=jnp.asarray(active),
        fixed=jnp.zeros(cap, dtype=bool),
        uid=jnp.arange(cap, dtype=jnp.int32),
        parent_uid=jnp.full(cap, -1, dtype=jnp.int32),
        material=jnp.asarray(mat),
    )


def wall(
    point,
    normal,
    *,
    extent=(-np.inf, np.inf),
    velocity=(0.0, 0.0),
    mode: int = WALL_FIXED,
    target_stress: float = 0.0,
    servo_gain: float = 0.0,
    max_speed: float = np.inf,
    length: float = 1.0,
    servo_time: float = np.inf,
) -> dict:
    """One wall description for :func:`make_walls` (see :class:`Walls` for the fields)."""
    nrm = np.asarray(normal, dtype=float)
    norm = np.linalg.norm(nrm)
    if not norm > 0:
        raise ValueError("wall normal must be a non-zero vector")
    if length <= 0:
        raise ValueError("wall length (used to turn force into stress) must be positive")
    if not servo_time > 0:
        raise ValueError(f"servo_time (integral time, s) must be > 0 or inf, got {servo_time}")
    return {
        "point": np.asarray(point, dtype=float),
        "normal": nrm / norm,
        "extent": np.asarray(extent, dtype=float),
        "vel": np.asarray(velocity, dtype=float),
        "mode": int(mode),
        "target_stress": float(target_stress),
        "servo_gain": float(servo_gain),
        "max_speed": float(max_speed),
        "length": float(length),
        "servo_time": float(servo_time),
    }


def make_walls(walls: list[dict], dtype=None) -> Walls:
    """Stack wall descriptions (from :func:`wall`) into a :class:`Walls` pytree. An empty
    list gives one inactive wall (so shapes stay non-empty)."""
    active = np.ones(len(walls), dtype=bool)
    if not walls:
        walls = [wall((0.0, 0.0), (0.0, 1.0))]
        active = np.zeros(1, dtype=bool)
    fd = _float(dtype)
    col = lambda key: np.stack([np.asarray(w[key]) for w in walls])
    return Walls(
        point=jnp.asarray(col("point"), fd),
        normal=jnp.asarray(col("normal"), fd),
        extent=jnp.asarray(col("extent"), fd),
        vel=jnp.asarray(col("vel"), fd),
        mode=jnp.asarray(col("mode"), jnp.int32),
        target_stress=jnp.asarray(col("target_stress"), fd),
        servo_gain=jnp.asarray(col("servo_gain"), fd),
        max_speed=jnp.asarray(col("max_speed"), fd),
        length=jnp.asarray(col("length"), fd),
        force=jnp.zeros((len(walls), 2), fd),
        active=jnp.asarray(active),
        servo_time=jnp.asarray(col("servo_time"), fd),
        servo_integral=jnp.zeros(len(walls), fd),
    )


def box_walls(lower, upper, *, top: bool = True) -> list[dict]:
    """Four (or three, without the lid) walls enclosing ``[lower, upper]`` (m), normals
    inward, in the order bottom, left, right, (top)."""
    (x0, y0), (x1, y1) = lower, upper
    w, h = x1 - x0, y1 - y0
    out = [
        wall((x0, y0), (0.0, 1.0), length=w),
        wall((x0, y0), (1.0, 0.0), length=h),
        wall((x1, y0), (-1.0, 0.0), length=h),
    ]
    if top:
        out.append(wall((x0, y1), (0.0, -1.0), length=w))
    return out


def empty_contacts(
    n_particles: int, n_vertices: int, n_walls: int, pair_capacity: int, dtype=None
) -> Contacts:
    """A pair list with no pairs (all sentinel) and zero spring history."""
    fd = _float(dtype)
    return Contacts(
        pairs=jnp.full((pair_capacity, 2), n_particles, dtype=jnp.int32),
        n_pairs=jnp.zeros((), jnp.int32),
        xi=jnp.zeros((2, pair_capacity, 2, n_vertices), fd),
        wall_xi=jnp.zeros((2, n_particles, n_walls, n_vertices), fd),
        ref_pos=jnp.full((n_particles, 2), jnp.inf, fd),
        ref_angle=jnp.zeros((n_particles,), fd),
        n_builds=jnp.zeros((), jnp.int32),
    )


def make_state(particles: Particles, walls: Walls, *, pair_capacity: int | None = None) -> SimState:
    """Assemble a :class:`SimState` at t = 0. The default pair capacity is 4 per particle;
    the host loop grows it when needed."""
    n_p, n_v = particles.verts.shape[:2]
    # a multiple of the contact kernel's block (jaxgran.contact.PAIR_BLOCK) by default
    cap = -(-4 * n_p // 256) * 256 if pair_capacity is None else int(pair_capacity)
    if cap < 1:
        raise ValueError("pair capacity must be >= 1")
    fd = particles.pos.dtype
    if not bool(jnp.all(jnp.isfinite(particles.pos))) or not bool(
        jnp.all(jnp.isfinite(particles.vel))
    ):
        raise ValueError("particle positions/velocities contain NaN or inf")
    return SimState(
        particles=particles,
        walls=walls,
        contacts=empty_contacts(n_p, n_v, walls.point.shape[0], cap, dtype=fd),
        time=jnp.zeros((), fd),
        step=jnp.zeros((), jnp.int32),
    )
