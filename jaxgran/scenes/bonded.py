"""Shared builders of the bonded Voronoi scenes (paper 002 §2.2-4): material, specimens,
platens, loading control and the jitted segment the bonded scenes run.

**Material in 2D (plane stress, thickness T stated explicitly).** The defaults keep the
numbers of paper 002 Table 1 and choose the slab thickness ``T = 1 cm``:
K_n = K_t = 1e8 N/m (per vertex-edge contact of the slab), G_n = 2529.8 1/s, G_t = 0,
mu = 0.3, B_n = B_t = 20 GPa, B_m = 3.3 GPa, eps_th = 0.02, theta_th = 0.05 rad, and a rock
density of 2700 kg/m^3 (27 kg/m^2 areal density), which Table 1 does not give. In 2D a bond
is a spring ``B A / L = B T (e / L)`` (e shared edge length, L centre distance), so with
T = 1 cm the bond and contact stiffnesses are of the same order (~1e8 N/m), as in the 3D
paper, and both are independent of the cell size: the macroscopic moduli do not depend on
the mesh, only on ``K_n / T``, ``B_n``, ``B_t`` and the cell shapes. Stresses are forces per
``length x T`` (Pa); the dimensionless groups of paper 002 Eq. 18-19 (K_n/K_t, B_n/B_t,
eps_th) are what carries over from 3D.

**Specimen.** A Voronoi tessellation of the specimen shape (a few Lloyd iterations make the
cells rounder), each cell eroded by the sphero-radius r so that the swept shapes tile the
specimen with zero overlap; every shared edge is a bond (:func:`jaxgran.bonds.make_bonds`).
Capacities (particles, vertices, bonds, wall bonds, pairs) may be given so that several
realisations share one compiled segment (:mod:`jaxgran.ensemble`).

**Control.** The bonded tests need what the plain step does not do, applied as a pure
function before every step (:func:`apply_control`): an external force per particle (the
cantilever's tip load; the state has no such field, so it is applied as the impulse
``F(t_n) dt / m`` before step n, which reproduces the Verlet positions of a force F that
starts from zero, e.g. a ramp; stored velocities then lead by ``F dt / (2 m)``), a global
viscous damping for dynamic relaxation to a static state, the constant-p servo of the
biaxial test (with walls in :func:`jaxgran.state.box_walls` order the loaded wall lengths
follow the specimen, and the lateral walls' target is ``2 p - sigma_axial`` so that
``p = (sigma_1 + sigma_3) / 2`` stays at its target), and strain gauges (mean positions of
groups of cells, recorded with every record).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import analysis as _an
from .. import geometry as geo
from ..bonds import Bonds, attach_to_walls, make_bonds
from ..errors import SceneError
from ..integrate import step
from ..partition import make_grid
from ..simulate import Record, record
from ..state import (
    Grid,
    Params,
    Particles,
    SimState,
    empty_contacts,
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
)
from .limits import Checked

# wall order of jaxgran.state.box_walls
BOTTOM, LEFT, RIGHT, TOP = 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class Material(Checked):
    """Micro-parameters of a bonded Voronoi solid (paper 002 Table 1 with T = 1 cm). Every
    bonded scene's ``Config`` starts with these settings (it derives from this class), and
    they are checked when made (:mod:`jaxgran.scenes.limits`)."""

    thickness: float = 0.01  # m, T (plane stress slab)
    areal_density: float = 27.0  # kg/m^2 (2700 kg/m^3 x T; not in Table 1)
    normal_stiffness: float = 1.0e8  # N/m, K_n
    tangential_stiffness: float = 1.0e8  # N/m, K_t
    normal_damping: float = 2529.8  # 1/s, G_n
    tangential_damping: float = 0.0  # 1/s, G_t
    friction: float = 0.3  # mu (cells and platens)
    b_n: float = 20.0e9  # Pa, B_n
    b_t: float = 20.0e9  # Pa, B_t
    b_m: float = 3.3e9  # Pa, B_m
    eps_th: float = 0.02  # Eq. 15 strain threshold
    theta_th: float = 0.05  # rad, Eq. 15 rotation threshold
    sphero_fraction: float = 0.05  # r = this x mean cell size sqrt(area / n_cells)


def material_from(cfg) -> Material:
    """The :class:`Material` fields found in a scene config (same names)."""
    names = {f.name for f in dataclasses.fields(Material)}
    return Material(**{n: getattr(cfg, n) for n in names if hasattr(cfg, n)})


# ------------------------------------------------------------------------------ specimens


@dataclasses.dataclass
class Specimen:
    """A tessellated specimen before assembly: ``cells`` tile the shape (m), ``cores`` are
    the cells eroded by ``sphero_radius`` (m); same order (cell k is particle k)."""

    cells: list[np.ndarray]
    cores: list[np.ndarray]
    sphero_radius: float

    @property
    def n_particles(self) -> int:
        return len(self.cells)

    @property
    def max_vertices(self) -> int:
        return max(len(c) for c in self.cores)

    @property
    def n_bonds(self) -> int:
        return len(geo.shared_edges(self.cells))

    def centroids(self) -> np.ndarray:
        return np.array([geo.polygon_centroid(c) for c in self.cells])


def specimen_from_cells(cells: list[np.ndarray], area: float, material: Material) -> Specimen:
    """Specimen of a tessellation ``cells`` (m) covering ``area`` (m^2): each cell eroded by
    ``sphero_fraction x sqrt(area / n)``."""
    r = material.sphero_fraction * math.sqrt(area / len(cells))
    cores = []
    for k, c in enumerate(cells):
        try:
            cores.append(geo.offset_polygon(c, r))
        except ValueError as exc:
            raise SceneError(
                f"cell {k} is too thin for the sphero-radius {r:.3g} m; lower "
                "sphero_fraction or use Lloyd iterations for rounder cells"
            ) from exc
    return Specimen(cells=cells, cores=cores, sphero_radius=r)


def disc_specimen(
    diameter: float,
    n_cells: int,
    seed: int,
    material: Material,
    *,
    center=(0.0, 0.0),
    lloyd_iterations: int = 2,
    n_boundary: int = 96,
) -> Specimen:
    """Voronoi disc of ``diameter`` (m) with ``n_cells`` cells (boundary an
    ``n_boundary``-gon with a vertex at each pole)."""
    if n_boundary % 4:
        raise SceneError("n_boundary must be a multiple of 4 (a vertex at each pole)")
    cells = geo.voronoi_disc(
        0.5 * diameter,
        n_cells,
        seed,
        center=center,
        n_boundary=n_boundary,
        lloyd_iterations=lloyd_iterations,
    )
    return specimen_from_cells(cells, math.pi * diameter**2 / 4, material)


def rectangle_specimen(
    width: float,
    height: float,
    n_cells: int,
    seed: int,
    material: Material,
    *,
    origin=(0.0, 0.0),
    lloyd_iterations: int = 2,
) -> Specimen:
    """Voronoi rectangle ``origin + [0, width] x [0, height]`` (m) of ``n_cells`` cells."""
    cells = geo.voronoi_rectangle(
        width, height, n_cells, seed, origin=origin, lloyd_iterations=lloyd_iterations
    )
    return specimen_from_cells(cells, width * height, material)


@dataclasses.dataclass(frozen=True)
class Capacities:
    """Static array sizes shared by the realisations of an ensemble."""

    particles: int
    vertices: int
    bonds: int
    wall_bonds: int = 1
    pairs: int = 0  # 0: 8 per particle slot

    @staticmethod
    def covering(specimens: list[Specimen], wall_bonds: int = 1) -> Capacities:
        """The smallest capacities that hold every specimen."""
        return Capacities(
            particles=max(s.n_particles for s in specimens),
            vertices=max(s.max_vertices for s in specimens),
            bonds=max(max(s.n_bonds for s in specimens), 1),
            wall_bonds=max(wall_bonds, 1),
        )


def assemble(
    specimen: Specimen,
    material: Material,
    walls: list[dict],
    *,
    capacities: Capacities | None = None,
    bond_walls: tuple[int, ...] = (),
    dtype=None,
) -> SimState:
    """State of a bonded specimen between ``walls`` (descriptions from
    :func:`jaxgran.state.wall`), at rest. Walls listed in ``bond_walls`` are tied to the
    cells that touch them (paper 002 §4.3, :func:`jaxgran.bonds.attach_to_walls`)."""
    cap = capacities or Capacities.covering([specimen])
    parts = particles_from_polygons(
        specimen.cores,
        specimen.sphero_radius,
        material.areal_density,
        capacity=cap.particles,
        vertex_capacity=cap.vertices,
        dtype=dtype,
    )
    bonds = make_bonds(
        specimen.cells,
        parts,
        thickness=material.thickness,
        b_n=material.b_n,
        b_t=material.b_t,
        b_m=material.b_m,
        eps_th=material.eps_th,
        theta_th=material.theta_th,
        capacity=cap.bonds,
    )
    w = make_walls(walls, dtype=dtype)
    if bond_walls:
        only = replace(w, active=jnp.asarray([k in bond_walls for k in range(w.count)]))
        bonds = attach_to_walls(
            bonds,
            parts,
            only,
            distance=1e-3 * specimen.sphero_radius,
            b_n=material.b_n,
            thickness=material.thickness,
            capacity=cap.wall_bonds,
        )
    elif cap.wall_bonds > 1:
        bonds = pad_wall_bonds(bonds, cap.wall_bonds, cap.particles)
    pairs = cap.pairs or 8 * cap.particles
    return replace(make_state(parts, w, pair_capacity=pairs), bonds=bonds)


def pad_wall_bonds(bonds: Bonds, capacity: int, n_particles: int) -> Bonds:
    """``bonds`` with ``capacity`` wall-bond slots (inactive padding, sentinel particle
    index ``n_particles``, the particle capacity)."""
    n = bonds.wall_capacity
    if capacity <= n:
        return bonds
    extra = capacity - n
    n_p = int(n_particles)

    def pad(x, fill):
        return jnp.concatenate([x, jnp.full((extra,) + x.shape[1:], fill, x.dtype)], axis=0)

    names = {
        "wall_p": n_p,
        "wall_w": 0,
        "wall_point": 0.0,
        "wall_gap0": 0.0,
        "wall_area": 0.0,
        "wall_length": 1.0,
        "wall_b_n": 0.0,
        "wall_active": False,
        "wall_force": 0.0,
    }
    return eqx.tree_at(
        lambda b: [getattr(b, k) for k in names],
        bonds,
        [pad(getattr(bonds, k), v) for k, v in names.items()],
    )


def stable_dt(particles: Particles, bonds: Bonds, material: Material, safety: float = 0.5):
    """Time step (s) of a bonded specimen: ``safety x min_i sqrt(2 m_i / k_i)``.

    ``k_i`` sums, over the bonds of cell i, the stiffest bond spring
    ``max(B_n, B_t) A / L`` plus two vertex contacts ``2 max(K_n, K_t)`` (an edge in
    compression); ``m_i = min(m, I / l^2)`` (l the bounding radius) stands in for rotation.
    By Gershgorin's theorem the squared frequencies of the spring network are at most
    ``max_i 2 k_i / m_i``, so Verlet (stable for ``omega dt < 2``, PHYSICS §D) is stable for
    ``safety <= 1``, without the large blanket margin that
    :func:`jaxgran.integrate.stable_time_step` needs because it knows only K_n and not the
    number of neighbours (0.5 here gives about twice its step).

    The contact dashpots are not counted. With Table 1's ``G_n = 2529.8`` 1/s a contact's
    damping rate ``G_n (1 + m l^2 / I)`` (:func:`jaxgran.integrate.critical_time_step`) moves
    the limit ``2 / (Gamma + sqrt(Gamma^2 + Omega^2))`` by 0.1-0.3 %, and the 100-cell disc
    with them is measured stable up to 2.44 times this bound (2.51 without;
    ``benchmarks/TIMESTEP_RESULTS.md``). A much larger ``normal_damping`` needs a smaller
    ``safety``; the interface scenes, whose element dashpots are strong, count theirs
    (:func:`jaxgran.scenes.interface.stable_dt`).
    """
    if not 0 < safety <= 1:
        raise ValueError(f"safety must be in (0, 1], got {safety}")
    n_p = particles.capacity
    real = np.asarray(bonds.i < bonds.j)
    i, j = np.asarray(bonds.i)[real], np.asarray(bonds.j)[real]
    b = np.maximum(np.asarray(bonds.b_n), np.asarray(bonds.b_t))[real]
    k_b = b * np.asarray(bonds.area)[real] / np.asarray(bonds.length)[real]
    k_b = k_b + 2.0 * max(material.normal_stiffness, material.tangential_stiffness)
    k = np.bincount(i, k_b, minlength=n_p) + np.bincount(j, k_b, minlength=n_p)
    k = np.maximum(k, 2.0 * material.normal_stiffness)  # a lone cell still meets a wall
    act = np.asarray(particles.active)
    m = np.asarray(particles.mass)
    m_rot = np.minimum(m, np.asarray(particles.inertia) / np.asarray(particles.bound_radius) ** 2)
    return safety * float(np.min(np.sqrt(2.0 * m_rot[act] / k[act])))


def make_bonded_params(material: Material, dt: float, skin: float, dtype=None) -> Params:
    """:class:`Params` of a bonded test: no gravity, Table-1 contact law."""
    return make_params(
        normal_stiffness=material.normal_stiffness,
        tangential_stiffness=material.tangential_stiffness,
        friction=material.friction,
        normal_damping=material.normal_damping,
        tangential_damping=material.tangential_damping,
        gravity=(0.0, 0.0),
        dt=dt,
        skin=skin,
        thickness=material.thickness,
        dtype=dtype,
    )


def grid_around(states: list[SimState], margin: float, skin: float) -> Grid:
    """One broad-phase grid for all ``states``: their active particles' bounding box grown by
    ``margin`` (m) on each side, with a cell capacity 1.5x the fullest initial cell."""
    pos, rmax = [], 0.0
    for s in states:
        act = np.asarray(s.particles.active)
        pos.append(np.asarray(s.particles.pos)[act])
        rmax = max(rmax, float(np.max(np.asarray(s.particles.bound_radius)[act])))
    allp = np.concatenate(pos)
    lo, hi = allp.min(axis=0) - margin, allp.max(axis=0) + margin
    grid = make_grid(tuple(lo), tuple(hi), rmax, skin)
    fullest = 1
    for p in pos:
        cx = np.floor((p[:, 0] - lo[0]) / grid.cell_size).astype(int)
        cy = np.floor((p[:, 1] - lo[1]) / grid.cell_size).astype(int)
        fullest = max(fullest, int(np.bincount(cx + grid.nx * cy).max()))
    return dataclasses.replace(grid, cell_capacity=int(math.ceil(1.5 * fullest)) + 2)


def count_pairs(state: SimState, skin: float) -> int:
    """Pairs the broad phase lists now: active particles whose bounding circles are closer
    than ``skin`` (m) (the criterion of :func:`jaxgran.partition.candidate_pairs`), counted
    on the host with a k-d tree."""
    from scipy.spatial import cKDTree

    act = np.asarray(state.particles.active)
    pos = np.asarray(state.particles.pos)[act]
    rad = np.asarray(state.particles.bound_radius)[act]
    if len(pos) < 2:
        return 0
    pairs = cKDTree(pos).query_pairs(2.0 * rad.max() + skin, output_type="ndarray")
    dist = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    return int(np.sum(dist < rad[pairs[:, 0]] + rad[pairs[:, 1]] + skin))


def fit_pair_capacity(states: list[SimState], skin: float, headroom: float = 1.25) -> int:
    """Pair capacity for ``states``: ``headroom`` x the most pairs any of them has now. The
    contact kernels cost in proportion to the capacity, and the host loop grows a full list,
    so a tight start pays."""
    need = max(count_pairs(s, skin) for s in states)
    return int(math.ceil(headroom * need)) + 8


def with_pair_capacity(state: SimState, capacity: int) -> SimState:
    """``state`` with an empty pair list of ``capacity`` slots (before the first step)."""
    p = state.particles
    contacts = empty_contacts(
        p.capacity, p.vertex_capacity, state.walls.count, capacity, dtype=p.pos.dtype
    )
    return replace(state, contacts=contacts)


# ------------------------------------------------------------------------------ control


class Control(eqx.Module):
    """Loading applied before every step (see the module docstring); all traced.

    Attributes:
        external_force: ``[P, 2]`` (N), external force on each particle, ramped linearly
            from zero over ``ramp_time`` (s; 0 applies it at once).
        ramp_time: (s).
        damping: global viscous damping rate (1/s) on free particles (0: off).
        p_target: mean stress p = (s1 + s3) / 2 held by the lateral walls (Pa).
        p_constant: scalar bool; True sets the lateral walls' target to ``2 p - s_axial``.
        box: scalar bool; True when the walls are a box (bottom, left, right, top) whose
            loaded lengths follow the specimen.
        gauges: ``[G, P]`` weights (rows sum to 1, or 0): the segment records the weighted
            mean particle position of each row (a strain gauge: e.g. the cells of a band at
            a specimen's edge), series ``gauge_position`` ``[G, 2]`` (m).
    """

    external_force: Array
    ramp_time: Array
    damping: Array
    p_target: Array
    p_constant: Array
    box: Array
    gauges: Array


def make_control(
    state: SimState,
    *,
    external_force=None,
    ramp_time: float = 0.0,
    damping: float = 0.0,
    p_target: float = 0.0,
    p_constant: bool = False,
    box: bool = False,
    gauges=None,
) -> Control:
    """A :class:`Control` for ``state``; ``gauges`` is a list of particle-index arrays (the
    cells of each gauge, equal weights) or ``None``."""
    fd = state.particles.pos.dtype
    n_p = state.particles.capacity
    ext = np.zeros((n_p, 2)) if external_force is None else np.asarray(external_force, float)
    groups = list(gauges or [])
    weights = np.zeros((max(len(groups), 1), n_p))
    for g, idx in enumerate(groups):
        idx = np.asarray(idx, int)
        if idx.size == 0:
            raise SceneError(f"gauge {g} holds no particle")
        weights[g, idx] = 1.0 / idx.size
    return Control(
        external_force=jnp.asarray(ext, fd),
        ramp_time=jnp.asarray(ramp_time, fd),
        damping=jnp.asarray(damping, fd),
        p_target=jnp.asarray(p_target, fd),
        p_constant=jnp.asarray(p_constant),
        box=jnp.asarray(box),
        gauges=jnp.asarray(weights, fd),
    )


def box_stresses(walls, thickness) -> tuple[Array, Array]:
    """Axial and lateral stress of a box (Pa, compression positive): mean of bottom/top and
    of left/right, ``-F . n / (length T)`` with the current specimen size as length."""
    width = walls.point[RIGHT, 0] - walls.point[LEFT, 0]
    height = walls.point[TOP, 1] - walls.point[BOTTOM, 1]
    fn = -jnp.sum(walls.force * walls.normal, axis=-1)
    s_ax = 0.5 * (fn[BOTTOM] + fn[TOP]) / (width * thickness)
    s_lat = 0.5 * (fn[LEFT] + fn[RIGHT]) / (height * thickness)
    return s_ax, s_lat


def apply_control(state: SimState, params: Params, control: Control) -> SimState:
    """The loading of :class:`Control` for the coming step (pure, jit-able)."""
    p = state.particles
    dt = params.dt
    free = (p.active & ~p.fixed)[:, None]
    decay = jnp.exp(-control.damping * dt)
    inv_m = jnp.where(free, 1.0 / p.mass[:, None], 0.0)
    ramped = control.ramp_time > 0
    scale = jnp.where(
        ramped, jnp.clip(state.time / jnp.where(ramped, control.ramp_time, 1.0), 0.0, 1.0), 1.0
    )
    force = scale * control.external_force
    damped_vel = jnp.where(free, p.vel * decay, p.vel)
    damped_omega = jnp.where(free[:, 0], p.omega * decay, p.omega)
    vel = damped_vel + dt * force * inv_m
    led = state.energy
    if led is not None:  # static: book the damping and the body forces' work
        from ..energy import control_terms, kinetic_energy

        ke0 = kinetic_energy(state)
        ke1 = kinetic_energy(
            replace(state, particles=replace(p, vel=damped_vel, omega=damped_omega))
        )
        ke2 = kinetic_energy(replace(state, particles=replace(p, vel=vel, omega=damped_omega)))
        led = control_terms(led, ke0, ke1, ke2)
    p = replace(p, vel=vel, omega=damped_omega)
    walls = state.walls
    if walls.count == 4:  # static: only a four-wall box can be a biaxial cell
        width = walls.point[RIGHT, 0] - walls.point[LEFT, 0]
        height = walls.point[TOP, 1] - walls.point[BOTTOM, 1]
        length = jnp.stack([width, height, height, width])
        length = jnp.where(control.box, length, walls.length)
        walls = replace(walls, length=length)
        s_ax, _ = box_stresses(walls, params.thickness)
        lateral = jnp.array([False, True, True, False])
        target = jnp.where(
            control.p_constant & lateral, 2.0 * control.p_target - s_ax, walls.target_stress
        )
        walls = replace(walls, target_stress=target)
    return replace(state, particles=p, walls=walls, energy=led)


def pooled_bursts(runs: list) -> dict:
    """Burst-size exponent (paper 002 Fig. 24) of the broken bonds per record interval,
    pooled over ``runs`` (every p and seed), by discrete maximum likelihood."""
    sizes = []
    for r in runs:
        t = np.asarray(r.series["time"], float)
        _, times = _an.broken_bond_points(r.state)
        window = float(t[1] - t[0]) if t.size > 1 else 1.0
        counts, _ = _an.burst_sizes(times, window)
        sizes.append(counts[counts > 0])
    s = np.concatenate(sizes) if sizes else np.zeros(0)
    if s.size < 10 or np.unique(s).size < 2:
        return {"n_bursts": int(s.size)}
    fit = _an.power_law_mle(s, 1)
    return {
        "n_bursts": int(s.size),
        "burst_exponent": fit["alpha"],
        "burst_exponent_err": fit["alpha_err"],
        "burst_ks": fit["ks"],
    }


# ------------------------------------------------------------------------------ segment


def n_broken(state: SimState) -> Array:
    """Number of real bonds broken so far (int32 scalar)."""
    b = state.bonds
    return jnp.sum((b.i < b.j) & ~b.intact).astype(jnp.int32)


def segment(
    state: SimState,
    params: Params,
    control: Control,
    grid: Grid,
    n_records: int,
    record_every: int,
) -> tuple[SimState, Record, dict[str, Array], Array]:
    """``n_records x record_every`` controlled steps in one scan (not jitted; see
    :func:`run_segment` and :func:`jaxgran.ensemble.run_segments`).

    Returns the final state, the records (wall forces averaged over each interval), extra
    series ``n_broken`` (broken bonds, ``[n_records]``) and ``gauge_position``
    (``[n_records, G, 2]``, m), and the error bitmask.
    """

    def inner(carry, _):
        s, err, wf = carry
        s = apply_control(s, params, control)
        s, e = step(s, params, grid)
        return (s, err | e, wf + s.walls.force), None

    def outer(carry, _):
        s, err = carry
        wf0 = jnp.zeros_like(s.walls.force)
        (s, err, wf), _ = jax.lax.scan(inner, (s, err, wf0), None, length=record_every)
        extra = {"n_broken": n_broken(s), "gauge_position": control.gauges @ s.particles.pos}
        return (s, err), (record(s, wf / record_every), extra)

    (state, err), (recs, broken) = jax.lax.scan(
        outer, (state, jnp.zeros((), jnp.int32)), None, length=n_records
    )
    return state, recs, broken, err


run_segment = eqx.filter_jit(segment)
