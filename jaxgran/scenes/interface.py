"""Shared builders of the interface-bond scenes (paper 003): gypsum-like material, specimens
of bonded discs or Voronoi cells, assembly, time step, loading and the Mohr-envelope fits.

**Material (2D, plane stress, slab thickness T = 1 cm stated in ``thickness``).** Paper 003's
Table 1 was lost in extraction; the defaults are chosen for a high-strength gypsum / soft rock:
density 2300 kg/m^3, element modulus ``E_c = 8 GPa`` (``k_n = E_c / L`` with L the centre
distance, ``k_s = k_n / 2.5``), element tensile strength ``sigma_b = 10 MPa``, cohesion
``c = 30 MPa``, residual friction ``mu_b = 0.5``, ultimate compressive strain off, 4 elements per
interface, radius multiplier ``lambda = 1.5`` (disc interfaces 1.5 times as wide as the smaller
disc's radius on each side, so wider than that disc: PFC's flat joints default to 1; here it is
the parameter that sets the ratio of compressive to tensile strength). With these the 25 x 50 mm
disc specimen (seed 0, 76 discs) has a direct tensile strength of 3.00 MPa and an unconfined
compressive strength of 30.8 MPa, 10.3 times it, as for a gypsum (``jaxgran run
interface-tension`` and ``interface-uniaxial``, 2026-12-05; 2.98 and 30.8 MPa at the step of
0.5 of the springs-only bound used before). The unconfined strength is set
by the interface width, not by the cohesion: with ``lambda = 1`` (sigma_b = 14 MPa) it was
16.4-16.5 MPa for c = 42-140 MPa, 5.9 times the tensile strength, and a residual friction of 1
instead of 0.5 only raised that to 6.2; ``lambda = 1.5`` gave 9.4. The parallel-bond baseline
keeps everything and swaps the envelope for the straight line ``c - sigma tan(phi)`` with
``phi = 41 deg``: the secant of the parabola between ``sigma = 0`` and ``sigma = -5 sigma_b``
(``tan(phi) = (sqrt(6) - 1) c / (5 sigma_b)``), so both envelopes agree at zero and at 5 sigma_b
(50 MPa) of compression and differ in curvature only. The calibration is for the disc
specimen: the same material on the same region meshed as 76 Voronoi cells gives 7.3 MPa and
88 MPa (12.1x; ``benchmarks/INTERFACE_ENVELOPE_RESULTS.md``), and the ``plate-contact`` disc,
meshed as cells by default, peaks at 3.9 kN on average against 2.2 kN as discs (32 seeds).

**Specimens.** *Discs* (paper 003's elementary balls, diameters ``d_min .. d_max`` =
2.5-5 mm, uniform): placed at random in the region at solid fraction ``solid_fraction`` and
pushed apart until no two overlap (host-side relaxation); every pair whose surfaces are
closer than ``bond_gap`` x the smallest radius is bonded, the largest bonded cluster is kept
(discs without a bond and small clusters bonded to nothing else are dropped), and then
every radius is reduced by ``clearance`` so that the contact law does not act between
bonded discs (the interface carries their compression, as in a flat joint) unless they are
pushed ``2 clearance r`` together. *Voronoi cells*: a tessellation of the same
region with the same number of particles, each cell eroded by ``sphero_fraction x`` the mean
cell size and swept by ``(1 - clearance)`` of that radius (the same clearance); the shared
edges are the interfaces.

**Stress measurement.** The Love-Weber stress ``(1 / V) sum_p sum_e (x_e - x_p) (x) F_e``
over a measurement circle (paper 003's measurement balls) weights each particle by the share
of its tile (the particle's area divided by the specimen's solid fraction, or its Voronoi
cell) inside the circle (lens area of the tile's equivalent disc).
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
import warnings
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .. import geometry as geo
from .. import interface as itf
from ..bonds import attach_to_walls
from ..contact import damping_from_restitution
from ..errors import SceneError
from ..integrate import contact_dashpot_rate, mode_time_step_limit
from ..state import SimState, make_params, make_state, make_walls, particles_from_polygons, replace
from . import bonded as bd
from .limits import COUNT_OR_AUTO, Checked

# ------------------------------------------------------------------------------ material


@dataclasses.dataclass(frozen=True)
class Material(Checked):
    """Gypsum-like interface-bond material (module docstring); SI units."""

    bond: str = "interface"  # "interface" (paper 003) or "parallel" (baseline)
    thickness: float = 0.01  # m, T (plane stress slab)
    density: float = 2300.0  # kg/m^3
    modulus: float = 8.0e9  # Pa, E_c: k_n = E_c / L
    stiffness_ratio: float = 2.5  # k_n / k_s
    tensile_strength: float = 10.0e6  # Pa, sigma_b
    cohesion: float = 30.0e6  # Pa, c
    friction_angle_deg: float = 41.0  # phi of the parallel bond's line (deg)
    residual_friction: float = 0.5  # mu_b after failure
    compressive_strain: float = math.inf  # eps_u; inf = off (paper 003's default)
    n_elements: int = 4  # interface elements per bond (paper 003: 16 sectors in 3D)
    radius_multiplier: float = 1.5  # lambda: disc interface width 2 lambda min(r)
    damping_ratio: float = 0.3  # element dashpots (zeta)
    contact_friction: float = 0.5  # particle-particle and particle-plate mu
    wall_friction: float = math.nan  # particle-wall (platen) mu; nan: contact_friction
    restitution: float = 0.3  # contact dashpots

    @property
    def contact_stiffness(self) -> float:
        """K_n of the contact law (N/m): ``E_c T``, about one interface's normal stiffness."""
        return self.modulus * self.thickness


@dataclasses.dataclass(frozen=True)
class Common(Material):
    """Fields every interface scene's ``Config`` shares (SI units): the :class:`Material`
    ones (``bond`` picks the model, ``--set bond=parallel`` for the baseline), then the
    specimen (``particles`` its kind) and the loading."""

    LIMITS: ClassVar[dict] = {"n_cells": COUNT_OR_AUTO}

    particles: str = "discs"  # "discs" (elementary balls) or "voronoi"
    seed: int = 0
    d_min: float = 2.5e-3  # m, smallest elementary disc diameter
    d_max: float = 5.0e-3  # m, largest
    solid_fraction: float = 0.7  # of the disc packing before bonding
    bond_gap: float = 0.4  # bond discs closer than this x the smallest radius
    clearance: float = 0.05  # radius reduction after bonding (fraction)
    n_cells: int = 0  # Voronoi cells (0: as many as the disc packing has discs)
    sphero_fraction: float = 0.1  # Voronoi erosion / mean cell size
    strain_rate: float = 2.0  # 1/s, loading (both walls together / specimen size)
    max_strain: float = 0.01  # stop here at the latest
    drop_fraction: float = 0.5  # stop once the load falls below this x the peak
    dt_safety: float = 1.0  # of stable_dt's limit, itself about half the true one (docstring)
    record_every: int = 50
    records_per_segment: int = 10

    def relations(self) -> None:
        if not self.d_min <= self.d_max:
            raise ValueError(
                f"settings d_min={self.d_min!r} and d_max={self.d_max!r}: "
                "d_min must not exceed d_max"
            )


def material_from(cfg) -> Material:
    """The :class:`Material` fields found in a scene config (same names)."""
    names = {f.name for f in dataclasses.fields(Material)}
    return Material(**{n: getattr(cfg, n) for n in names if hasattr(cfg, n)})


# ------------------------------------------------------------------------------ specimens


@dataclasses.dataclass
class Specimen:
    """Particles before assembly: core polygons (m, world; one vertex for a disc), sphero-radii
    (m), interfaces (:func:`jaxgran.interface.disc_interfaces` / ``edge_interfaces``), tile
    areas (m^2) for stress averaging, and ``kind`` "discs" or "voronoi"."""

    cores: list[np.ndarray]
    radius: np.ndarray
    interfaces: dict
    tile_area: np.ndarray
    kind: str

    @property
    def n_particles(self) -> int:
        return len(self.cores)

    @property
    def n_bonds(self) -> int:
        return len(self.interfaces["pairs"])

    def centres(self) -> np.ndarray:
        return np.array([geo.polygon_centroid(c) if len(c) >= 3 else c[0] for c in self.cores])


def _inside(x, r, region):
    """Project disc centres so the discs lie inside ``region``."""
    if region[0] == "disc":
        _, radius, c = region
        d = x - c
        dist = np.linalg.norm(d, axis=1)
        lim = radius - r
        out = dist > lim
        x = x.copy()
        x[out] = c + d[out] * (lim[out] / dist[out])[:, None]
        return x
    _, (x0, y0), (x1, y1) = region
    return np.stack([np.clip(x[:, 0], x0 + r, x1 - r), np.clip(x[:, 1], y0 + r, y1 - r)], 1)


def disc_packing(
    region, d_min: float, d_max: float, seed: int, solid_fraction: float, iterations: int = 4000
):
    """Non-overlapping discs of diameters uniform in ``[d_min, d_max]`` (m) filling ``region``
    (``("disc", R, centre)`` or ``("rect", lower, upper)``) at ``solid_fraction``: random
    positions relaxed by pushing overlapping pairs apart. A disc region gets a largest disc
    pinned at each pole on the vertical axis (the plates touch the specimen there). Returns
    centres ``[n, 2]`` (m) and radii ``[n]`` (m)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    if region[0] == "disc":
        area = math.pi * region[1] ** 2
        centre = np.asarray(region[2], float)
    else:
        (x0, y0), (x1, y1) = region[1], region[2]
        area = (x1 - x0) * (y1 - y0)
    r0, r1 = 0.5 * d_min, 0.5 * d_max
    mean_area = math.pi * (r0 * r0 + r0 * r1 + r1 * r1) / 3.0
    n = max(2, int(round(solid_fraction * area / mean_area)))
    r = np.sort(rng.uniform(r0, r1, n))[::-1]
    if region[0] == "disc":
        rho = region[1] * np.sqrt(rng.uniform(0, 1, n))
        phi = rng.uniform(0, 2 * math.pi, n)
        x = centre + np.stack([rho * np.cos(phi), rho * np.sin(phi)], 1)
    else:
        x = np.stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)], 1)
    pinned = np.zeros(n, bool)
    if region[0] == "disc" and n > 2:
        # a largest disc at each pole on the loading axis, so plates load along a diameter
        r[:2] = r1
        x[0] = centre + [0.0, region[1] - r1]
        x[1] = centre - [0.0, region[1] - r1]
        pinned[:2] = True
    tol = 0.02 * r0  # the clearance (5 % of r on each disc) opens what is left
    # grow the discs from 70 % of their size while relaxing: far more robust than relaxing
    # the full-size random placement
    for scale in np.r_[np.linspace(0.6, 1.0, 21), 1.0]:
        rs = scale * r
        x = _inside(x, rs, region)
        for _ in range(iterations // 40 if scale < 1 else iterations):
            pairs = cKDTree(x).query_pairs(2 * scale * r1, output_type="ndarray")
            if len(pairs) == 0:
                break
            i, j = pairs[:, 0], pairs[:, 1]
            d = x[j] - x[i]
            dist = np.maximum(np.linalg.norm(d, axis=1), 1e-12 * r0)
            ov = rs[i] + rs[j] - dist
            hit = ov > 0
            if not hit.any() or ov.max() < tol:
                break
            count = np.bincount(pairs[hit].ravel(), minlength=len(x))
            push = (0.5 * ov[hit] / dist[hit])[:, None] * d[hit]
            damp = 1.0 / np.sqrt(np.maximum(count, 1))[:, None]
            step = np.zeros_like(x)
            np.add.at(step, i[hit], -push)
            np.add.at(step, j[hit], push)
            step = step * damp + rng.normal(0.0, 1e-3 * r0, x.shape) * (count > 0)[:, None]
            step[pinned] = 0.0
            x = _inside(x + step, rs, region)
    # a few discs may stay jammed: drop the smaller disc of each pair still overlapping
    pairs = cKDTree(x).query_pairs(2 * r1, output_type="ndarray").reshape(-1, 2)
    ov = r[pairs[:, 0]] + r[pairs[:, 1]] - np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1)
    bad = pairs[ov >= tol]
    drop = np.where(pinned[bad[:, 0]] | (r[bad[:, 1]] <= r[bad[:, 0]]), bad[:, 1], bad[:, 0])
    keep = np.ones(len(x), bool)
    keep[drop] = False
    x, r = x[keep], r[keep]
    return x, r


def discs_specimen(
    region,
    d_min: float,
    d_max: float,
    seed: int,
    mat: Material,
    *,
    solid_fraction: float = 0.7,
    bond_gap: float = 0.4,
    clearance: float = 0.05,
) -> Specimen:
    """Bonded disc specimen (module docstring)."""
    from ..analysis import fragments

    x, r = disc_packing(region, d_min, d_max, seed, solid_fraction)
    pairs = itf.disc_interfaces(x, r, bond_gap * r.min())["pairs"]
    # the specimen is the largest bonded cluster: discs without a bond, and small clusters
    # bonded to nothing else (loose debris in a pore, which a plate would push in without
    # resistance), are dropped
    keep = np.zeros(len(x), bool)
    keep[fragments(pairs[:, 0], pairs[:, 1], len(x))[0]] = True
    pairs = pairs[keep[pairs[:, 0]] & keep[pairs[:, 1]]]
    index = np.cumsum(keep) - 1
    x, r, pairs = x[keep], r[keep] * (1.0 - clearance), index[pairs]
    d = x[pairs[:, 1]] - x[pairs[:, 0]]
    dist = np.linalg.norm(d, axis=1)
    n = d / dist[:, None]
    gap = dist - r[pairs[:, 0]] - r[pairs[:, 1]]
    faces = {
        "pairs": pairs,
        "centres": x[pairs[:, 0]] + (r[pairs[:, 0]] + 0.5 * gap)[:, None] * n,
        "normals": n,
        "widths": 2.0 * mat.radius_multiplier * np.minimum(r[pairs[:, 0]], r[pairs[:, 1]]),
    }
    if region[0] == "disc":
        area = math.pi * region[1] ** 2
    else:
        area = float(np.prod(np.subtract(region[2], region[1])))
    phi = float(np.sum(math.pi * r**2) / area)
    return Specimen(
        cores=[xi[None, :] for xi in x],
        radius=r,
        interfaces=faces,
        tile_area=math.pi * r**2 / phi,
        kind="discs",
    )


def voronoi_specimen(
    region,
    n_cells: int,
    seed: int,
    *,
    sphero_fraction: float = 0.1,
    clearance: float = 0.5,
    lloyd_iterations: int = 2,
) -> Specimen:
    """Bonded Voronoi specimen of ``n_cells`` cells (module docstring)."""
    if region[0] == "disc":
        radius, centre = region[1], region[2]
        nb = max(16, 4 * int(math.ceil(0.9 * math.sqrt(math.pi * n_cells))))
        cells = geo.voronoi_disc(
            radius, n_cells, seed, center=centre, n_boundary=nb, lloyd_iterations=lloyd_iterations
        )
        area = math.pi * radius**2
    else:
        (x0, y0), (x1, y1) = region[1], region[2]
        cells = geo.voronoi_rectangle(
            x1 - x0, y1 - y0, n_cells, seed, origin=(x0, y0), lloyd_iterations=lloyd_iterations
        )
        area = (x1 - x0) * (y1 - y0)
    r_e = sphero_fraction * math.sqrt(area / n_cells)
    cores = [geo.offset_polygon(c, r_e) for c in cells]
    return Specimen(
        cores=cores,
        radius=np.full(len(cells), r_e * (1.0 - clearance)),
        interfaces=itf.edge_interfaces(cells),
        tile_area=np.array([geo.polygon_area(c) for c in cells]),
        kind="voronoi",
    )


def make_specimen(cfg, region, mat: Material) -> Specimen:
    """Discs or Voronoi cells (``cfg.particles``) for the fields of a scene config; Voronoi
    specimens get the disc packing's particle count unless ``cfg.n_cells > 0``."""
    discs = discs_specimen(
        region,
        cfg.d_min,
        cfg.d_max,
        cfg.seed,
        mat,
        solid_fraction=cfg.solid_fraction,
        bond_gap=cfg.bond_gap,
        clearance=cfg.clearance,
    )
    if cfg.particles == "discs":
        return discs
    if cfg.particles != "voronoi":
        raise SceneError(f"particles must be 'discs' or 'voronoi', got {cfg.particles!r}")
    n = cfg.n_cells if cfg.n_cells > 0 else discs.n_particles
    return voronoi_specimen(region, n, cfg.seed, sphero_fraction=cfg.sphero_fraction)


# ------------------------------------------------------------------------------ assembly


def assemble(
    spec: Specimen,
    mat: Material,
    walls: list[dict],
    *,
    bond_walls: tuple[int, ...] = (),
    wall_bond_distance: float = 0.0,
    dtype=None,
) -> SimState:
    """State of a bonded specimen at rest between ``walls`` (descriptions from
    :func:`jaxgran.state.wall`); the walls in ``bond_walls`` are tied to the particles within
    ``wall_bond_distance`` (m) of them by normal wall bonds of modulus ``E_c``."""
    parts = particles_from_polygons(
        spec.cores, spec.radius, mat.density * mat.thickness, dtype=dtype
    )
    pairs = spec.interfaces["pairs"]
    pos = np.asarray(parts.pos)
    length = np.linalg.norm(pos[pairs[:, 1]] - pos[pairs[:, 0]], axis=1)
    k_n = mat.modulus / length
    bonds = itf.make_interface_bonds(
        parts,
        spec.interfaces,
        thickness=mat.thickness,
        normal_stiffness=k_n,
        shear_stiffness=k_n / mat.stiffness_ratio,
        tensile_strength=mat.tensile_strength,
        cohesion=mat.cohesion,
        residual_friction=mat.residual_friction,
        bond=mat.bond,
        friction_angle=math.radians(mat.friction_angle_deg),
        compressive_strain=mat.compressive_strain,
        n_elements=mat.n_elements,
        damping_ratio=mat.damping_ratio,
    )
    w = make_walls(walls, dtype=dtype)
    if bond_walls:
        only = replace(w, active=jnp.asarray([k in bond_walls for k in range(w.count)]))
        wb = attach_to_walls(
            bonds.wall_bonds,
            parts,
            only,
            distance=wall_bond_distance,
            b_n=mat.modulus,
            thickness=mat.thickness,
        )
        bonds = itf.with_wall_bonds(bonds, wb)
    return replace(make_state(parts, w, pair_capacity=8 * parts.capacity), bonds=bonds)


def contact_damping(state: SimState, mat: Material) -> tuple[float, float]:
    """Contact dashpots ``(G_n, G_t)`` (1/s) of an interface scene: the rates that give
    ``mat.restitution`` to a contact of ``K_n = E_c T`` (``K_t = K_n / stiffness_ratio``)
    between two particles of the median mass (``m_e`` = half of it)."""
    m = np.asarray(state.particles.mass)[np.asarray(state.particles.active)]
    m_eff = 0.5 * float(np.median(m))
    k_n = mat.contact_stiffness
    return (
        damping_from_restitution(mat.restitution, k_n, m_eff),
        damping_from_restitution(mat.restitution, k_n / mat.stiffness_ratio, m_eff),
    )


def stable_dt(state: SimState, mat: Material, safety: float = 1.0, dashpots: bool = True) -> float:
    """Time step (s): ``safety`` x the step limit of the interface network with its dashpots,
    ``2 / (Gamma + sqrt(Gamma^2 + Omega^2))`` (:func:`jaxgran.integrate.mode_time_step_limit`).

    * Springs: ``Omega^2 = max_i 2 k_i / m_i`` with ``k_i`` the sum over the interfaces of
      particle i of ``max(k_n, k_s) A`` plus two contacts ``2 K_n``, and ``m_i = min(m, I /
      l^2)`` (the Gershgorin estimate of :func:`jaxgran.scenes.bonded.stable_dt`).
    * Element dashpots, estimated the same way: ``Gamma_b = max_i 2 c_i / m_i`` with ``c_i``
      the sum over the interfaces of particle i of ``n_e max(eta_n, eta_s)`` (N s/m). They
      damp the half-step velocity, so they count half in the criterion ``(Omega dt / 2)^2 +
      (Gamma_c + Gamma_b / 2) dt <= 1``.
    * Contact dashpots (:func:`contact_damping`): one contact's rate, ``Gamma_c = max(G_n,
      G_t) (1 + max m l^2 / I)`` (:func:`jaxgran.integrate.contact_dashpot_rate`); they take
      over from the element dashpots as the interfaces fail.

    With the element dashpots of ``damping_ratio = 0.3`` the dashpots set most of the
    limit. The springs-only limit this function gave before (``sqrt(2 m_i / k_i)``,
    ``dashpots=False`` here, for comparisons) was unstable from 0.86 of it with the scene's
    dashpots (119 discs). Like the springs' estimate, the whole is about half the true limit:
    the step linearised about the scenes' specimens is at 0.15-0.45 of the stability
    criterion at ``safety = 1`` (``docs/stability.md``).
    """
    if not 0 < safety <= 1:
        raise ValueError(f"safety must be in (0, 1], got {safety}")
    p, b = state.particles, state.bonds
    n_p = p.capacity
    real = np.asarray(b.i < b.j)
    i, j = np.asarray(b.i)[real], np.asarray(b.j)[real]

    def per_particle(x: np.ndarray) -> np.ndarray:
        return np.bincount(i, x, minlength=n_p) + np.bincount(j, x, minlength=n_p)

    k_b = np.maximum(np.asarray(b.normal_stiffness), np.asarray(b.shear_stiffness))[real]
    k = per_particle(k_b * np.asarray(b.area)[real] + 2.0 * mat.contact_stiffness)
    k = np.maximum(k, 2.0 * mat.contact_stiffness)
    n_e = b.elem_point_i.shape[1]  # each element has the bond's dashpots eta_n, eta_s
    c = per_particle(n_e * np.maximum(np.asarray(b.damping_n), np.asarray(b.damping_s))[real])
    act = np.asarray(p.active)
    m, inertia = np.asarray(p.mass)[act], np.asarray(p.inertia)[act]
    ell = np.asarray(p.bound_radius)[act]
    m_rot = np.minimum(m, inertia / ell**2)
    omega2 = float(np.max(2.0 * k[act] / m_rot))
    gamma_b = float(np.max(2.0 * c[act] / m_rot)) if dashpots else 0.0
    gamma_c = contact_dashpot_rate(p, max(contact_damping(state, mat))) if dashpots else 0.0
    return safety * mode_time_step_limit(omega2, gamma_c + 0.5 * gamma_b)


def make_run_params(state: SimState, mat: Material, dt: float, skin: float):
    """:class:`jaxgran.state.Params` of an interface scene: no gravity, contact law with
    ``K_n = E_c T``, ``K_t = K_n / stiffness_ratio``, dashpots for ``restitution``; walls
    have ``wall_friction`` (``contact_friction`` where it is nan)."""
    g_n, g_t = contact_damping(state, mat)
    return make_params(
        normal_stiffness=mat.contact_stiffness,
        tangential_stiffness=mat.contact_stiffness / mat.stiffness_ratio,
        friction=mat.contact_friction,
        wall_friction=None if math.isnan(mat.wall_friction) else mat.wall_friction,
        normal_damping=g_n,
        tangential_damping=g_t,
        gravity=(0.0, 0.0),
        dt=dt,
        skin=skin,
        thickness=mat.thickness,
    )


@dataclasses.dataclass
class Setup:
    """A ready-to-run scene: state, parameters, grid, control, specimen and material."""

    state: SimState
    params: object
    grid: object
    control: object
    spec: Specimen
    material: Material
    margin: float = 0.0  # m, the grid's margin around the specimen (ejection: see drive)


def prepare(spec: Specimen, mat: Material, walls: list[dict], cfg, margin: float, **kw) -> Setup:
    """Assemble, choose dt, skin, grid and pair capacity (the bonded scenes' helpers)."""
    state = assemble(spec, mat, walls, **kw)
    dt = stable_dt(state, mat, cfg.dt_safety)
    skin = (
        0.2 * float(np.min(spec.radius))
        if spec.kind == "discs"
        else 0.1 * float(np.sqrt(np.median(spec.tile_area)))
    )
    params = make_run_params(state, mat, dt, skin)
    grid = bd.grid_around([state], margin, skin)
    state = bd.with_pair_capacity(state, bd.fit_pair_capacity([state], skin, headroom=2.0))
    return Setup(state, params, grid, bd.make_control(state), spec, mat, float(margin))


def eject_escaping(state: SimState, grid, guard: float) -> tuple[SimState, np.ndarray]:
    """Deactivate the particles whose centre is within ``guard`` (m) of the grid's edge:
    fragments thrown off an unconfined specimen after its failure, which would otherwise
    leave the grid and stop the run. Returns the state and the slots removed."""
    p = state.particles
    pos, act = np.asarray(p.pos), np.asarray(p.active)
    lo = np.asarray(grid.origin, float)
    hi = lo + grid.cell_size * np.array([grid.nx, grid.ny], float)
    near = np.any((pos < lo + guard) | (pos > hi - guard), axis=1)
    out = np.flatnonzero(act & near)
    if out.size == 0:
        return state, out
    active = jnp.asarray(act).at[out].set(False)
    vel = p.vel.at[out].set(0.0)
    omega = p.omega.at[out].set(0.0)
    return replace(state, particles=replace(p, active=active, vel=vel, omega=omega)), out


def drive(setup: Setup, n_steps: int, cfg, callback=None, progress: bool = False, desc: str = ""):
    """Run with :func:`jaxgran.ensemble.drive` (one realisation); a callback
    ``callback(state, records) -> (state, stop)`` runs after each segment. The result's
    ``segment_wall_times`` (s, host clock after each segment) give the compiled speed.

    Particles that come within half the grid margin of its edge are taken out after each
    segment (:func:`eject_escaping`): a fragment thrown off a failing specimen flies on,
    and a run of an unconfined test would otherwise stop on it. The result's ``ejected``
    lists ``(time s, slot, mass kg)`` per particle taken out; a warning says how many."""
    from .. import ensemble as ens

    stamps = []
    ejected: list[tuple[float, int, float]] = []
    guard = 0.5 * setup.margin

    def cb(state, rec):
        stamps.append(_time.perf_counter())
        if guard > 0:
            state, out = eject_escaping(state, setup.grid, guard)
            if out.size:
                mass = np.asarray(state.particles.mass)
                ejected.extend((float(state.time), int(k), float(mass[k])) for k in out)
        if callback is None:
            return state, False
        return callback(state, rec)

    res = ens.drive(
        setup.state,
        setup.params,
        setup.control,
        setup.grid,
        n_steps=n_steps,
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        callback=cb,
        progress=progress,
        desc=desc,
    )
    res.segment_wall_times = stamps
    res.ejected = ejected
    if ejected:
        warnings.warn(
            f"{desc or 'run'}: {len(ejected)} particle(s) thrown towards the edge of the grid "
            f"were taken out (first at t = {ejected[0][0]:.4g} s; the summary counts them "
            "as n_ejected)",
            stacklevel=2,
        )
    return res


def steady_rate(res, n_particles: int, cfg) -> dict:
    """Wall time per step after the first (compiling) segment, and particle-steps/s."""
    t = np.asarray(getattr(res, "segment_wall_times", []))
    seg = cfg.record_every * cfg.records_per_segment
    if t.size < 3:
        return {}
    per_step = float((t[-1] - t[0]) / ((t.size - 1) * seg))
    return {"s_per_step": per_step, "particle_steps_per_s": n_particles / per_step}


# ------------------------------------------------------------------------------ analysis


_particle_moment = jax.jit(itf.particle_moment)
_element_positions = jax.jit(itf.element_positions)


def element_table(state) -> dict[str, np.ndarray]:
    """Host arrays of every real element: world position ``[n, 2]`` (m), mode, failure time
    (s), sigma and tau (Pa), and the bond index."""
    b = state.bonds
    real = np.asarray(b.i < b.j)
    x = np.asarray(_element_positions(state.particles, b))[real]
    ne = b.n_elements
    return {
        "pos": x.reshape(-1, 2),
        "mode": np.asarray(b.mode)[real].ravel(),
        "time": np.asarray(b.elem_break_time)[real].ravel(),
        "sigma": np.asarray(b.sigma)[real].ravel(),
        "tau": np.asarray(b.tau)[real].ravel(),
        "bond": np.repeat(np.nonzero(real)[0], ne),
    }


def _host_bonds(bonds) -> dict[str, np.ndarray]:
    """The real bonds of an :class:`jaxgran.interface.InterfaceBonds` or of the ``bonds``
    group of :func:`jaxgran.io.read_run` as host arrays (wall bonds left out)."""
    if isinstance(bonds, itf.InterfaceBonds):
        raw = {f.name: getattr(bonds, f.name) for f in dataclasses.fields(bonds)}
    else:
        raw = dict(bonds)
    raw.pop("wall_bonds", None)
    b = {k: np.asarray(v) for k, v in raw.items()}
    real = b["i"] < b["j"]
    return {k: (v[real] if v.ndim and len(v) == len(real) else v) for k, v in b.items()}


def bond_material(bonds) -> dict[str, float | int]:
    """``cohesion``, ``tensile_strength`` (Pa), ``tan_friction_angle``, ``residual_friction``
    (-) and the ``envelope`` code of the first real bond (the scenes give every bond one
    material), from bonds as :func:`element_failures` takes them."""
    b = _host_bonds(bonds)
    keys = ("cohesion", "tensile_strength", "tan_friction_angle", "residual_friction")
    out: dict[str, float | int] = {k: float(b[k][0]) for k in keys}
    out["envelope"] = int(b["envelope"][0])
    return out


def _rot_rows(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def bonded_element_stresses(pos, angle, b: dict) -> tuple[np.ndarray, np.ndarray]:
    """``sigma = k_n u_n`` and ``tau = k_s u_s`` (Pa, tension positive) ``[B, E]`` of every
    element as if bonded, for particle positions ``pos [P, 2]`` (m) and angles ``[P]``
    (rad): the kinematics of :func:`jaxgran.interface.interface_kinematics` on the host."""
    i, j = b["i"], b["j"]
    a_i, a_j = angle[i], angle[j]
    theta = (a_j - a_i) - b["theta0"]
    normal = _rot_rows(b["normal_i"], a_i + 0.5 * theta)
    tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=-1)
    d = (pos[j][:, None, :] + _rot_rows(b["elem_point_j"], a_j[:, None])) - (
        pos[i][:, None, :] + _rot_rows(b["elem_point_i"], a_i[:, None])
    )
    u_n = np.einsum("bek,bk->be", d, normal)
    u_s = np.einsum("bek,bk->be", d, tangent)
    return b["normal_stiffness"][:, None] * u_n, b["shear_stiffness"][:, None] * u_s


def element_failures(frames, bonds) -> dict[str, np.ndarray]:
    """Where on its envelope each element failed: for every element of ``bonds`` (final
    :class:`jaxgran.interface.InterfaceBonds`, or the ``final/bonds`` group of a run file)
    that failed after the first of ``frames`` (stacked frames with ``time``, ``pos`` and
    ``angle``: :func:`jaxgran.io.stack_frames`, or ``frames`` of a run file), its failure
    ``time`` (s), ``mode`` (:data:`jaxgran.interface.MODE_NAMES`) and ``bond`` index, and at
    the last frame recorded before the failure its normal and shear stress ``sigma`` and
    ``tau`` (Pa, tension positive; :func:`bonded_element_stresses`), its shear strength
    there ``tau_c`` and the friction it carries once failed, ``friction = mu_b max(-sigma,
    0)`` (Pa). Frames are decimated, so the stresses are those of up to one frame interval
    before the failure: inside the envelope, and the nearer it the denser the frames."""
    b = _host_bonds(bonds)
    t_frames = np.asarray(frames["time"], float) if len(frames) else np.zeros(0)
    t_fail = b["elem_break_time"]
    failed = np.isfinite(t_fail)
    if t_frames.size:
        failed &= t_fail > t_frames[0]
    else:
        failed[:] = False
    bond, elem = np.nonzero(failed)
    k_frame = np.searchsorted(t_frames, t_fail[failed], side="left") - 1  # strictly before
    sigma = np.zeros(bond.size)
    tau = np.zeros(bond.size)
    for k in np.unique(k_frame):
        sel = k_frame == k
        s_k, t_k = bonded_element_stresses(
            np.asarray(frames["pos"][k], float), np.asarray(frames["angle"][k], float), b
        )
        sigma[sel], tau[sel] = s_k[bond[sel], elem[sel]], t_k[bond[sel], elem[sel]]
    tau_c = np.asarray(
        itf.shear_strength(
            sigma,
            b["cohesion"][bond],
            b["tensile_strength"][bond],
            b["tan_friction_angle"][bond],
            b["envelope"][bond],
        )
    )
    return {
        "time": t_fail[failed],
        "mode": b["mode"][failed],
        "bond": bond,
        "sigma": sigma,
        "tau": tau,
        "tau_c": tau_c,
        "friction": b["residual_friction"][bond] * np.maximum(-sigma, 0.0),
    }


def failure_stress_summary(fails: dict, bonds) -> dict[str, float | None]:
    """Key figures of :func:`element_failures`: counts of the shear and tension failures it
    found (those after the first frame); of the shear failures the
    median and 90th percentile of the compression ``-sigma`` (Pa) and the median of the
    strength an element lost on failing, ``(tau_c - friction) / tau_c`` (negative where it
    gained: above the crossover of :func:`jaxgran.interface.friction_crossover`); for the
    interface bond the crossover (Pa; of the first bond's material, which the scenes give
    every bond) and the fraction of shear failures above it."""
    shear = fails["mode"] == itf.MODE_SHEAR
    comp = np.maximum(-fails["sigma"][shear], 0.0)
    # (a frame before a shear failure may find the element past sigma_b, where tau_c = 0)
    some = shear & (fails["tau_c"] > 0)
    lost = (fails["tau_c"] - fails["friction"])[some] / fails["tau_c"][some]
    out: dict[str, float | None] = {
        "n_shear_failures_recorded": int(shear.sum()),
        "n_tension_failures_recorded": int((fails["mode"] == itf.MODE_TENSION).sum()),
        "shear_failure_compression_median_Pa": float(np.median(comp)) if comp.size else None,
        "shear_failure_compression_p90_Pa": float(np.percentile(comp, 90)) if comp.size else None,
        "strength_lost_on_failing_median": float(np.median(lost)) if lost.size else None,
    }
    m = bond_material(bonds)
    if m["envelope"] == itf.ENVELOPE_PARABOLIC:
        s_star = itf.friction_crossover(
            m["cohesion"], m["tensile_strength"], m["residual_friction"]
        )
        out["friction_crossover_Pa"] = s_star
        out["shear_failures_above_crossover"] = float((comp > s_star).mean()) if comp.size else None
    return out


def _lens_area(a: np.ndarray, b: float, d: np.ndarray) -> np.ndarray:
    """Area of the intersection of discs of radii ``a`` and ``b`` at distance ``d`` (m^2)."""
    a = np.asarray(a, float)
    d = np.asarray(d, float)
    out = np.zeros_like(d)
    full = d <= np.abs(a - b)
    out[full] = math.pi * np.minimum(a, b)[full] ** 2 if np.ndim(a) else math.pi * min(a, b) ** 2
    part = (d < a + b) & ~full
    if part.any():
        aa, dd = a[part], d[part]
        c1 = np.clip((dd**2 + aa**2 - b**2) / (2 * dd * aa), -1, 1)
        c2 = np.clip((dd**2 + b**2 - aa**2) / (2 * dd * b), -1, 1)
        k = (-dd + aa + b) * (dd + aa - b) * (dd - aa + b) * (dd + aa + b)
        out[part] = aa**2 * np.arccos(c1) + b**2 * np.arccos(c2) - 0.5 * np.sqrt(np.maximum(k, 0))
    return out


def circle_stresses(state, spec: Specimen, centres, radius: float, thickness: float):
    """Mean stress in measurement circles ``[n, 2, 2]`` (Pa, tension positive) from the
    interface forces: ``sum_p w_p M_p / (T sum_p w_p A_p)`` with ``M_p`` the first moment of
    particle p (:func:`jaxgran.interface.particle_moment`), ``A_p`` its tile area and ``w_p``
    the share of that tile inside the circle. A circle that covers no tile (one left in an
    opened crack after a split) has no stress: its entry is NaN, on purpose."""
    p = state.particles
    moment = np.asarray(_particle_moment(p, state.bonds))
    act = np.asarray(p.active)
    pos = np.asarray(p.pos)[act]
    moment = moment[act]
    tile = spec.tile_area[: len(pos)]
    r_t = np.sqrt(tile / math.pi)
    out = []
    for c in np.asarray(centres, float).reshape(-1, 2):
        w = _lens_area(r_t, radius, np.linalg.norm(pos - c, axis=1)) / tile
        covered = thickness * np.sum(w * tile)
        if covered > 0:
            out.append(np.tensordot(w, moment, axes=1) / covered)
        else:
            out.append(np.full((2, 2), np.nan))
    return np.array(out)


def mohr_envelope_fits(sigma_1, sigma_3) -> dict:
    """Linear Mohr-Coulomb and parabolic Mohr envelopes of peak Mohr circles (compression
    positive). With ``p = (s1 + s3) / 2`` and ``q = (s1 - s3) / 2`` the circles touch the line
    ``tau = c + sigma tan(phi)`` iff ``q = c cos(phi) + p sin(phi)``, and the parabola
    ``tau^2 = c^2 (1 + sigma / sigma_b)`` (paper 003 Eq. 3 with compression positive) iff
    ``q^2 = c^2 - c^4 / (4 sigma_b^2) + (c^2 / sigma_b) p`` (distance from (p, 0) to the
    parabola). Both are least-squares lines (q on p, q^2 on p); R^2 is reported on q for both.
    """
    s1 = np.asarray(sigma_1, float)
    s3 = np.asarray(sigma_3, float)
    p, q = 0.5 * (s1 + s3), 0.5 * (s1 - s3)
    out: dict = {"n_circles": int(p.size)}
    if p.size < 3:
        return out
    ss_tot = float(np.sum((q - q.mean()) ** 2))
    if ss_tot <= 0:
        return out
    a1, a0 = np.polyfit(p, q, 1)
    q_lin = a0 + a1 * p
    sin_phi = float(np.clip(a1, -0.999, 0.999))
    out["linear_r2"] = 1.0 - float(np.sum((q - q_lin) ** 2)) / ss_tot
    out["linear_friction_angle_deg"] = math.degrees(math.asin(sin_phi))
    out["linear_cohesion_Pa"] = float(a0 / math.sqrt(1 - sin_phi**2))
    b1, b0 = np.polyfit(p, q**2, 1)
    q_par = np.sqrt(np.maximum(b0 + b1 * p, 0.0))
    out["parabola_r2"] = 1.0 - float(np.sum((q - q_par) ** 2)) / ss_tot
    if b1 > 0:
        # b1 = c^2 / sigma_b, b0 = c^2 - b1^2 / 4
        c2 = b0 + 0.25 * b1 * b1
        if c2 > 0:
            out["parabola_cohesion_Pa"] = math.sqrt(c2)
            out["parabola_tensile_strength_Pa"] = c2 / b1
    return out


def jax_float(x) -> float:
    return float(jax.device_get(x))


# ------------------------------------------------------------------------------ loading


def extent(spec: Specimen) -> tuple[float, float, float, float]:
    """Bounding box of the swept particles (xmin, xmax, ymin, ymax) (m)."""
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for c, r in zip(spec.cores, spec.radius, strict=True):
        lo = np.minimum(lo, c.min(axis=0) - r)
        hi = np.maximum(hi, c.max(axis=0) + r)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def axial_walls(spec: Specimen, speed: float, length: float) -> list[dict]:
    """Bottom and top walls touching the specimen, moving towards each other at ``speed``
    (m/s, negative: apart)."""
    from ..state import WALL_VELOCITY, wall

    _, _, y0, y1 = extent(spec)
    return [
        wall((0.0, y0), (0.0, 1.0), velocity=(0.0, speed), mode=WALL_VELOCITY, length=length),
        wall((0.0, y1), (0.0, -1.0), velocity=(0.0, -speed), mode=WALL_VELOCITY, length=length),
    ]


def axial_load(series: dict) -> tuple[np.ndarray, np.ndarray]:
    """Mean compressive force of the bottom (first) and top (last) walls per record (N,
    tension negative) and their distance (m)."""
    f = np.asarray(series["wall_force"], float)
    pts = np.asarray(series["wall_point"], float)
    return 0.5 * (-f[:, 0, 1] + f[:, -1, 1]), pts[:, -1, 1] - pts[:, 0, 1]


def peak_stopper(load_fn, drop_fraction: float):
    """Callback that stops a run once ``load_fn(records)`` (one value per record) has fallen
    below ``drop_fraction`` of its running maximum after the peak."""
    best = {"max": -np.inf}

    def callback(state, rec):
        v = np.asarray(load_fn(rec), float)
        prev = best["max"]
        best["max"] = max(prev, float(v.max()))
        past = float(v.max()) < best["max"] or prev >= best["max"]
        drop = best["max"] > 0 and v[-1] < drop_fraction * best["max"] and past
        return state, bool(drop and any_failed(state))

    return callback


def n_damaged(state) -> int:
    """Damaged (health < 1) elements of the real bonds."""
    b = state.bonds
    return int(np.sum((np.asarray(b.health) < 1) & np.asarray(b.i < b.j)[:, None]))


def any_failed(state) -> bool:
    """Whether some element of a real bond has failed (a drop before that is vibration)."""
    return n_damaged(state) > 0


def concat_series(parts: list[dict]) -> dict:
    """Join the series of consecutive runs (record axis first)."""
    keys = set.intersection(*(set(p) for p in parts))
    return {k: np.concatenate([np.asarray(p[k]) for p in parts], axis=0) for k in keys}


def linearity(strain, stress, upto: float = 0.9) -> dict:
    """How linear the rising branch is up to ``upto`` x the peak: R^2 of a straight line
    through the origin-free fit, and the secant modulus at the peak over the initial
    tangent (1 for linear-elastic up to a brittle peak)."""
    from .. import analysis as an

    strain, stress = np.asarray(strain, float), np.asarray(stress, float)
    k = int(np.argmax(stress))
    rise = slice(0, k + 1)
    x, y = strain[rise], stress[rise]
    ok = y <= upto * stress[k]
    out: dict = {}
    if ok.sum() >= 3:
        fit = an.linear_fit(x[ok], y[ok])
        out["rising_branch_r2"] = fit["r2"]
        out["rising_modulus_Pa"] = fit["slope"]
        if fit["slope"] > 0 and strain[k] > 0:
            out["secant_over_tangent_at_peak"] = float(
                (stress[k] - fit["intercept"]) / strain[k] / fit["slope"]
            )
    return out


def run_facts(res, setup: Setup, cfg) -> dict:
    """What every single-test interface scene reports about the run itself: bond model,
    particle kind, particle count, time step (s), steps and wall time (s)."""
    return {
        "bond": cfg.bond,
        "particles": cfg.particles,
        "n_particles": setup.spec.n_particles,
        "dt_s": float(setup.params.dt),
        "steps": int(res.steps),
        "wall_time_s": float(res.wall_time_s),
        **ejection_facts(res, setup),
    }


def ejection_facts(res, setup: Setup) -> dict:
    """Particles taken out near the grid's edge (:func:`drive`): count, mass fraction of the
    specimen and the time of the first (s; nan if none)."""
    ej = getattr(res, "ejected", [])
    total = float(
        np.sum(np.asarray(setup.state.particles.mass)[np.asarray(setup.state.particles.active)])
    )
    return {
        "n_ejected": len(ej),
        "ejected_mass_fraction": sum(m for _, _, m in ej) / total if total > 0 else 0.0,
        "first_ejection_time_s": ej[0][0] if ej else math.nan,
    }


def finish(out_dir, summary: dict, figures: list) -> dict:
    """Add the scene's own figures to ``summary`` and rewrite summary.json."""
    from pathlib import Path

    from .. import io

    summary["figures"] = list(summary.get("figures", [])) + [str(f) for f in figures if f]
    io.write_summary(Path(out_dir) / "summary.json", summary)
    return summary
