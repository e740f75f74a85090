"""Damage separation model (DSM, paper 000 §II), run between simulation segments.

:class:`DsmBreakage` is a host callback for :func:`jaxgran.simulate.simulate`. Each call:

1. **Screening** (jit, all particles at once): a particle goes on if it has at least two
   contacts (neighbours or walls) and, with ``screen="bound"`` (the default), the proven
   upper bound of its largest psi (:func:`jaxgran.bem.psi_bound`, from per-shape tables kept
   for every particle) reaches ``eps``: no particle that the BEM would break is screened
   out. With ``screen="force"`` (a heuristic, the earlier rule) it goes on when its largest
   contact force (resultant per neighbour) exceeds ``screen_fraction`` times its critical
   load ``F_c = eps pi R_eq t / k(nu, plane)`` (``R_eq = sqrt(A / pi)``), the load that
   breaks a Brazilian disc of the same area (:func:`critical_load`); a load concentrated
   near an edge can break a particle well below that.
2. **Contacts** (same jit): every particle's vertex contacts, the largest ``max_contacts``
   first, with their points and forces ON the particle in its body frame and the neighbour
   they come from (particle slot, or ``P + wall``); forces are those of the current springs.
3. **BEM** (jit, batched): the strain-energy equivalent stress psi (paper 000 Eq. 2) at the
   interior sample points, from per-shape operators (:func:`jaxgran.bem.build_operators`)
   built once per particle shape and cached by uid; batches are padded to a fixed size, so
   nothing recompiles while particles break.
4. **Connection points** (host, :func:`~jaxgran.breakage.criteria.connection_points`): the
   contacts of one neighbour form one seed set (the sample points nearest each of its
   contact points, counted as psi = inf: the loads are singular); the particle breaks iff the
   highest saddle between two seed sets reaches ``eps`` (paper 000 Eq. 3). Where the seeds of
   two neighbours touch on the sample grid (two neighbours pressing on one corner), those
   samples keep their computed psi, or they would connect at infinity and break the particle
   under any load (:func:`_touching_seeds`). Each connection point selects the nearest line
   joining two neighbours' contact points (force-weighted centre of each neighbour's
   contacts) as a fracture plane (:func:`~jaxgran.breakage.criteria.fracture_planes`).
5. **Replacement**: the planes cut the dilated outline (:func:`~jaxgran.breakage.ssm.
   split_convex` of :func:`~jaxgran.breakage.replace.dilated_outline`); the pieces are
   eroded and written into free slots (:func:`~jaxgran.breakage.replace.replace_particles`),
   then :func:`jaxgran.simulate.prepare` rebuilds the pair list and forces.

Calibration (PHYSICS §C): in a Brazilian test of a disc of radius R and thickness t the
connection point is the centre, where ``psi_c = k F / (pi R t)`` with
``k = sqrt(10 + 6 nu)`` (plane stress) or ``sqrt(10 + 6 nu - 4 nu^2)`` (plane strain); so the
measured breaking force F gives ``eps = k F / (pi R t)`` (:func:`calibrate_eps`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import OrderedDict
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import bem
from ..contact import pair_forces, wall_forces
from ..geometry import polygon_area_padded
from ..simulate import SimulationError, grow_capacities, prepare
from ..state import (
    ERR_CELL_OVERFLOW,
    ERR_LEFT_DOMAIN,
    ERR_NAN,
    ERR_PAIR_OVERFLOW,
    Grid,
    Params,
    SimState,
    replace,
)
from .criteria import connection_points, fracture_planes
from .replace import (
    EROSION_MODES,
    SMALL_PIECE_MODES,
    Replacement,
    dilated_outline,
    replace_particles,
)
from .ssm import split_convex

log = logging.getLogger(__name__)

__all__ = [
    "SCREEN_MODES",
    "DsmBreakage",
    "brazilian_factor",
    "calibrate_eps",
    "calibration_report",
    "contact_table",
    "critical_load",
]

# The paper's calibration (paper 000 §III): eps = 2.80251 MPa from F = 150.79 N, r = 1 cm.
PAPER_EPS = 2.80251e6
PAPER_FORCE = 150.79
PAPER_RADIUS = 0.01

# screening rules of DsmBreakage: the proven psi bound, or the contact-force heuristic
SCREEN_MODES = ("bound", "force")
# the most memory the per-shape operator cache may take when it grows to hold every particle
# one check screens (about 0.64 MB per shape at 64 elements and 200 sample points, float64)
CACHE_BYTES = 2 << 30


# ---------------------------------------------------------------------------- calibration


def brazilian_factor(poisson_ratio: float = 0.3, plane: str = "stress") -> float:
    """``k = psi_c / p`` at the centre of a Brazilian disc, ``p = F / (pi R t)`` (-).

    The centre stresses are ``sigma_1 = p``, ``sigma_2 = -3 p`` (Timoshenko & Goodier), so
    ``psi^2 = (1 + nu) sigma:sigma - nu (tr sigma)^2`` (paper 000 Eq. 2) gives
    ``k = sqrt(10 + 6 nu)`` in plane stress and ``sqrt(10 + 6 nu - 4 nu^2)`` in plane
    strain (``sigma_3 = -2 nu p``); PHYSICS §C.
    """
    nu = float(poisson_ratio)
    if not -1.0 < nu < 0.5:
        raise ValueError(f"poisson_ratio must lie in (-1, 0.5), got {nu}")
    if plane == "stress":
        return math.sqrt(10.0 + 6.0 * nu)
    if plane == "strain":
        return math.sqrt(10.0 + 6.0 * nu - 4.0 * nu * nu)
    raise ValueError(f"plane must be 'stress' or 'strain', got {plane!r}")


def critical_load(
    eps: float, radius: float, thickness: float, *, poisson_ratio: float = 0.3, plane="stress"
) -> float:
    """Force (N) that breaks a Brazilian disc of ``radius`` R (m) and ``thickness`` t (m):
    ``F_c = eps pi R t / k`` (eps in Pa)."""
    return (
        float(eps)
        * math.pi
        * float(radius)
        * float(thickness)
        / brazilian_factor(poisson_ratio, plane)
    )


def _check_positive(**values: float) -> None:
    for name, v in values.items():
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be positive and finite, got {v}")


def calibrate_eps(
    force: float,
    radius: float,
    *,
    poisson_ratio: float = 0.3,
    plane: str = "stress",
    thickness: float = 0.01,
    method: str = "analytic",
    n_elements: int = 128,
    n_points: int = 400,
) -> float:
    """DSM threshold eps (Pa) from a Brazilian test: the disc of ``radius`` R (m) and
    ``thickness`` t (m) breaks under the diametral ``force`` F (N).

    ``method="analytic"``: ``eps = k F / (pi R t)`` (:func:`brazilian_factor`).
    ``method="bem"``: the same disc solved by our BEM (Flamant point loads at the poles) and
    the connection-point value found on the sample grid, exactly as the DSM sees it; it
    agrees with the closed form to the BEM's accuracy (about 0.1 % for N = 128).

    The paper's eps = 2.80251 MPa (F = 150.79 N, R = 1 cm) cannot be reproduced with any
    standard thickness: t = 1 cm gives 1.649 MPa (plane stress, nu = 0.3), and 2.80251 MPa
    needs t = 5.88 mm (PHYSICS §C). Use this function with *our* thickness convention.
    """
    _check_positive(force=force, radius=radius, thickness=thickness)
    k = brazilian_factor(poisson_ratio, plane)
    if method == "analytic":
        return k * force / (math.pi * radius * thickness)
    if method != "bem":
        raise ValueError(f"method must be 'analytic' or 'bem', got {method!r}")
    ops = bem.build_operators(
        np.zeros((1, 1, 2)),
        np.ones(1, np.int32),
        np.array([radius]),
        n_elements=n_elements,
        n_points=n_points,
        poisson_ratio=poisson_ratio,
        plane=plane,
    )
    cp = np.array([[[0.0, radius], [0.0, -radius]]])
    cf = np.array([[[0.0, -force], [0.0, force]]])
    _, psi = _psi_jit(
        ops, jnp.asarray(cp), jnp.asarray(cf), jnp.ones((1, 2), bool), thickness, poisson_ratio
    )
    mask = np.asarray(ops.point_mask[0])
    pts = np.asarray(ops.points[0])[mask]
    ij = np.asarray(ops.grid_index[0])[mask]
    seeds = [[int(np.argmin(np.linalg.norm(pts - x, axis=1)))] for x in cp[0]]
    res = connection_points(np.asarray(psi[0])[mask], ij, seeds, eps=0.0)
    return float(res.bottleneck[0, 1])


def calibration_report(
    force: float,
    radius: float,
    *,
    poisson_ratio: float = 0.3,
    plane: str = "stress",
    thickness: float = 0.01,
    bem_check: bool = True,
) -> dict[str, Any]:
    """eps for a Brazilian breaking force, analytic and by BEM, with the paper's number.

    Returns a JSON-ready dict: ``eps_analytic_Pa``, ``eps_bem_Pa`` (with ``bem_check``),
    ``k``, the implied thickness at which the paper's 2.80251 MPa would follow, and a note.
    """
    k = brazilian_factor(poisson_ratio, plane)
    eps = calibrate_eps(
        force, radius, poisson_ratio=poisson_ratio, plane=plane, thickness=thickness
    )
    out: dict[str, Any] = {
        "force_N": float(force),
        "radius_m": float(radius),
        "thickness_m": float(thickness),
        "poisson_ratio": float(poisson_ratio),
        "plane": plane,
        "k": k,
        "eps_analytic_Pa": eps,
    }
    if bem_check:
        eb = calibrate_eps(
            force,
            radius,
            poisson_ratio=poisson_ratio,
            plane=plane,
            thickness=thickness,
            method="bem",
        )
        out["eps_bem_Pa"] = eb
        out["bem_over_analytic"] = eb / eps
    out["paper_eps_Pa"] = PAPER_EPS
    out["thickness_for_paper_eps_m"] = k * force / (math.pi * radius * PAPER_EPS)
    out["note"] = (
        "eps = k F / (pi R t), k = psi at the disc centre per F/(pi R t) (PHYSICS §C). "
        "Paper 000's 2.80251 MPa for F = 150.79 N, R = 1 cm matches no standard thickness "
        "(t = 1 cm gives 1.649 MPa in plane stress); it implies t = "
        f"{1e3 * out['thickness_for_paper_eps_m']:.2f} mm with this nu and plane."
    )
    return out


# ---------------------------------------------------------------------------- jitted parts


@eqx.filter_jit
def contact_table(
    state: SimState,
    params: Params,
    eps: Array,
    screen_fraction: Array,
    brazil_k: Array,
    thickness: Array,
    max_contacts: int,
) -> dict[str, Array]:
    """Per-particle contact lists and the DSM screening, for all particles at once.

    Returns a dict of arrays (P particles, K = ``max_contacts``):
        ``points``, ``forces`` ``[P, K, 2]``: contact points (m) and forces ON the particle
        (N), body frame, largest |force| first; ``neighbour [P, K]``: slot of the other
        particle, or ``P + w`` for wall w; ``mask [P, K]``; ``count [P]``: vertex contacts
        (more than K means the list was cut); ``n_neighbours [P]``; ``max_force [P]``:
        largest resultant force of one neighbour (N); ``critical_load [P]`` (N);
        ``flag [P]``: goes on to the BEM.
    """
    p = state.particles
    n_p = p.pos.shape[0]
    # the forces of the current springs (dt = 0: no spring increment)
    prm = replace(params, dt=jnp.zeros_like(params.dt))
    _, _, _, info = pair_forces(p, state.contacts, prm)
    *_, winfo = wall_forces(p, state.walls, state.contacts.wall_xi, prm)
    pairs = state.contacts.pairs
    ok = pairs[:, 0] < n_p
    i = jnp.where(ok, pairs[:, 0], n_p)
    j = jnp.where(ok, pairs[:, 1], n_p)
    act = info["active"]  # [C, 2, V]
    n_c, _, n_v = act.shape
    f = info["force"].reshape(-1, 2)
    x = info["point"].reshape(-1, 2)
    owner = jnp.broadcast_to(jnp.stack([i, j], 1)[:, :, None], act.shape).ravel()
    other = jnp.broadcast_to(jnp.stack([j, i], 1)[:, :, None], act.shape).ravel()
    a = act.ravel()
    wact = winfo["active"]  # [P, W, V]
    n_w = wact.shape[1]
    wpid = jnp.broadcast_to(jnp.arange(n_p)[:, None, None], wact.shape).ravel()
    wnb = jnp.broadcast_to(n_p + jnp.arange(n_w)[None, :, None], wact.shape).ravel()
    pid = jnp.concatenate(
        [jnp.where(a, owner, n_p), jnp.where(a, other, n_p), jnp.where(wact.ravel(), wpid, n_p)]
    )
    nbr = jnp.concatenate([other, owner, wnb])
    fx = jnp.concatenate([f, -f, winfo["force"].reshape(-1, 2)])
    px = jnp.concatenate([x, x, winfo["point"].reshape(-1, 2)])
    mag = jnp.sqrt(jnp.sum(fx * fx, axis=-1))
    order = jnp.lexsort((-mag, pid))
    spid = pid[order]
    rng = jnp.arange(n_p)
    start = jnp.searchsorted(spid, rng, side="left")
    end = jnp.searchsorted(spid, rng, side="right")
    slot = start[:, None] + jnp.arange(max_contacts)[None, :]
    mask = slot < end[:, None]
    take = order[jnp.clip(slot, 0, pid.shape[0] - 1)]
    c, s = jnp.cos(p.angle)[:, None], jnp.sin(p.angle)[:, None]
    rx = px[take, 0] - p.pos[:, 0, None]
    ry = px[take, 1] - p.pos[:, 1, None]
    gx, gy = fx[take, 0], fx[take, 1]
    points = jnp.stack([c * rx + s * ry, -s * rx + c * ry], axis=-1)
    forces = jnp.stack([c * gx + s * gy, -s * gx + c * gy], axis=-1)
    points = jnp.where(mask[..., None], points, 0.0)
    forces = jnp.where(mask[..., None], forces, 0.0)
    neighbour = jnp.where(mask, nbr[take], -1)

    # screening: neighbours in contact and their resultant forces
    pair_on = jnp.any(act, axis=(1, 2))
    fo = info["force"]
    res = fo[:, 0].sum(axis=1) - fo[:, 1].sum(axis=1)  # on i, [C, 2]
    res_mag = jnp.where(pair_on, jnp.sqrt(jnp.sum(res * res, axis=-1)), 0.0)
    on = pair_on.astype(jnp.int32)
    n_nb = jnp.zeros(n_p + 1, jnp.int32).at[i].add(on).at[j].add(on)[:n_p]
    fmax = jnp.zeros(n_p + 1, mag.dtype).at[i].max(res_mag).at[j].max(res_mag)[:n_p]
    wall_on = jnp.any(wact, axis=2)  # [P, W]
    wres = winfo["force"].sum(axis=2)
    wmag = jnp.where(wall_on, jnp.sqrt(jnp.sum(wres * wres, axis=-1)), 0.0)
    n_nb = n_nb + jnp.sum(wall_on, axis=1).astype(jnp.int32)
    fmax = jnp.maximum(fmax, jnp.max(wmag, axis=1))
    area = _spheropolygon_area_padded(p.verts, p.n_verts, p.radius)
    f_crit = eps * jnp.pi * jnp.sqrt(area / jnp.pi) * thickness / brazil_k
    flag = p.active & (n_nb >= 2) & (fmax >= screen_fraction * f_crit)
    return {
        "points": points,
        "forces": forces,
        "neighbour": neighbour,
        "mask": mask,
        "count": end - start,
        "n_neighbours": n_nb,
        "max_force": fmax,
        "critical_load": f_crit,
        "flag": flag,
    }


def _spheropolygon_area_padded(verts: Array, n_verts: Array, radius: Array) -> Array:
    """Area (m^2) of padded spheropolygons: core + r x perimeter + pi r^2 (Steiner)."""
    k = jnp.arange(verts.shape[-2])
    n = n_verts[..., None]
    nxt = jnp.where(k + 1 < n, k + 1, 0)
    e = jnp.take_along_axis(verts, jnp.broadcast_to(nxt[..., None], verts.shape), -2) - verts
    length = jnp.sqrt(jnp.sum(e * e, axis=-1))
    perimeter = jnp.sum(jnp.where(k < n, length, 0.0), axis=-1)
    core = jnp.where(n_verts >= 3, polygon_area_padded(verts, n_verts), 0.0)
    return core + radius * perimeter + jnp.pi * radius**2


@eqx.filter_jit
def _bound_jit(ops, particle, contact_points, contact_forces, contact_mask, thickness):
    """The psi bound over a flat list of the real contacts (``bem._flat_contacts``): its cost
    grows with the contacts, not with particles x the padded list (half the padded cost on a
    settled pile, ``benchmarks/SCREENING_RESULTS.md``)."""
    return bem.psi_bound_flat(
        ops, particle, contact_points, contact_forces, contact_mask, thickness=thickness
    )


@eqx.filter_jit
def _psi_jit(ops, contact_points, contact_forces, contact_mask, thickness, poisson_ratio):
    return bem.psi_batched(
        ops,
        contact_points,
        contact_forces,
        contact_mask,
        thickness=thickness,
        poisson_ratio=poisson_ratio,
    )


# ---------------------------------------------------------------------------- the callback


@dataclasses.dataclass
class _Decision:
    slot: int
    planes: np.ndarray  # world, [k, 2, 2]
    pieces: list
    info: dict


class DsmBreakage:
    """Damage separation model as a :func:`~jaxgran.simulate.simulate` callback.

    Usage::

        dsm = DsmBreakage(params, grid, eps=1.65e6, mean_initial_mass=m0, min_area=a_min)
        result = simulate(state, params, grid, n_steps=..., callback=dsm)
        dsm.events  # one dict per breakage (see replace.replace_particle), plus the DSM's
                    # psi_saddle (Pa), connection_points / contact_points (world, m)

    Args:
        params, grid: those given to ``simulate`` (the grid only for the post-breakage
            :func:`~jaxgran.simulate.prepare`; its cell capacity is grown here if needed).
        eps: damage threshold epsilon (Pa), paper 000 Eq. 3 (see :func:`calibrate_eps`).
        poisson_ratio: nu of the grains (-); plane: ``"stress"`` or ``"strain"``.
        thickness: t (m); default ``params.thickness``.
        n_elements: BEM elements per particle (>= 2 x vertex capacity; raised if needed).
        n_points: BEM sample points per particle (capacity M).
        screen: ``"bound"`` (default): a particle is checked when the proven upper bound of
            its psi (:func:`jaxgran.bem.psi_bound`) reaches eps, so none that would break is
            missed; the bound's tables (about 40 kB per shape, float64) are kept for every particle.
            ``"force"``: when its largest contact force exceeds ``screen_fraction`` of its
            critical load (a heuristic: loads near an edge or a corner break below it; in
            the default Cantor oedometer 5 of 15 breakages came below half of it).
        screen_fraction: the fraction of ``screen="force"``; 0 checks every particle with
            two or more neighbours (in either mode).
        min_area: fragments smaller than this (m^2) become fines.
        mean_initial_mass: mean particle mass at t = 0 (kg), for the breakage type.
        max_contacts: vertex contacts kept per particle (grown if exceeded; recompiles).
        batch_size: particles per BEM batch (fixed, so batches never recompile).
        n_arc: tangent segments per turn of the dilated outline that is cut.
        load_model: BEM contact load model, ``"flamant"`` or ``"element"``.
        cache_size: per-shape BEM operators kept (least recently used dropped first), on the
            host. It grows to the number of particles one check screens, up to
            ``CACHE_BYTES`` of operators, with a note: a cache smaller than one check's
            candidates would rebuild every operator at every check.
        max_events: stop the run once this many breakage events happened (None: never).
        erosion: erosion of the fragments, ``"local"`` (default), ``"uniform"`` or
            ``"none"`` (:func:`~jaxgran.breakage.replace.replace_particles`).
        small_pieces: pieces below ``min_area``: ``"merge"`` (default) into a neighbour, or
            ``"fines"`` (dropped as lost mass); a decision whose pieces all merge back is not
            applied and goes to ``self.suppressed``.
        conserve_mass: fragments keep the mass of their uneroded pieces (density
            compensation, :func:`~jaxgran.breakage.replace.replace_particles`).
        min_radius: None: fragments keep the parent's sphero-radius; given (m), each
            fragment's radius adapts between it and the parent's so that its corner rounding
            keeps 99.9 % of its piece (:func:`~jaxgran.breakage.replace.replace_particles`).
    """

    def __init__(
        self,
        params: Params,
        grid: Grid,
        *,
        eps: float,
        poisson_ratio: float = 0.3,
        plane: str = "stress",
        thickness: float | None = None,
        n_elements: int = 64,
        n_points: int = 200,
        screen: str = "bound",
        screen_fraction: float = 0.5,
        min_area: float = 0.0,
        mean_initial_mass: float | None = None,
        max_contacts: int = 16,
        batch_size: int = 4,
        n_arc: int = 64,
        load_model: str = "flamant",
        cache_size: int = 256,
        max_events: int | None = None,
        erosion: str = "local",
        small_pieces: str = "merge",
        conserve_mass: bool = False,
        min_radius: float | None = None,
    ) -> None:
        _check_positive(eps=eps)
        if min_radius is not None:
            _check_positive(min_radius=min_radius)
        self.min_radius = None if min_radius is None else float(min_radius)
        if erosion not in EROSION_MODES:
            raise ValueError(f"erosion must be one of {EROSION_MODES}, got {erosion!r}")
        if small_pieces not in SMALL_PIECE_MODES:
            raise ValueError(
                f"small_pieces must be one of {SMALL_PIECE_MODES}, got {small_pieces!r}"
            )
        self.erosion = erosion
        self.small_pieces = small_pieces
        self.conserve_mass = bool(conserve_mass)
        self.params = params
        self.grid = grid
        self.eps = float(eps)
        self.poisson_ratio = float(poisson_ratio)
        self.plane = plane
        self.k = brazilian_factor(poisson_ratio, plane)
        self.thickness = float(params.thickness if thickness is None else thickness)
        _check_positive(thickness=self.thickness)
        self.n_elements = int(n_elements)
        self.n_points = int(n_points)
        if not 0.0 <= screen_fraction <= 1.0:
            raise ValueError(f"screen_fraction must lie in [0, 1], got {screen_fraction}")
        self.screen_fraction = float(screen_fraction)
        if screen not in SCREEN_MODES:
            raise ValueError(f"screen must be one of {SCREEN_MODES}, got {screen!r}")
        self.screen = screen
        self.min_area = float(min_area)
        self.mean_initial_mass = mean_initial_mass
        self.max_contacts = int(max_contacts)
        self.batch_size = int(batch_size)
        self.n_arc = int(n_arc)
        if load_model not in ("flamant", "element"):
            raise ValueError(f"load_model must be 'flamant' or 'element', got {load_model!r}")
        self.load_model = load_model
        self.cache_size = int(cache_size)
        self.max_events = max_events
        self.events: list[dict] = []
        # decisions whose pieces all merged back below the resolution (not replaced)
        self.suppressed: list[dict] = []
        self.log: list[str] = []
        self.n_calls = 0
        self.n_checked = 0
        self.last_saddle: dict[int, float] = {}  # uid -> highest saddle psi (Pa), last check
        self._reset_caches()
        self.n_screened = 0  # particles that passed the screening, summed over calls

    # per-shape operators and screening tables: rebuilt on demand, so a pickled handler
    # (a checkpoint of a long run, jaxgran.io.save_checkpoint) leaves them out
    _REBUILT = ("_cache", "_ops_static", "_bound_rows", "_bound_stack", "_bound_uid")

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        for name in self._REBUILT:
            state.pop(name, None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._reset_caches()

    def _reset_caches(self) -> None:
        """Empty the per-shape BEM operators (LRU) and the screening tables."""
        self._cache: OrderedDict[int, dict[str, Array]] = OrderedDict()
        self._ops_static: dict[str, Any] | None = None
        # screening tables of every shape built (uid -> BOUND_FIELDS rows), never evicted
        # while the particle lives, and their stack by slot (device) with the slot's uid
        self._bound_rows: dict[int, dict[str, Array]] = {}
        self._bound_stack: dict[str, Array] | None = None
        self._bound_uid = np.zeros(0, np.int64)

    # -------------------------------------------------------------- public entry points

    def critical_load(self, radius: float) -> float:
        """Breaking force (N) of a Brazilian disc of ``radius`` (m) for this eps."""
        return critical_load(
            self.eps,
            radius,
            self.thickness,
            poisson_ratio=self.poisson_ratio,
            plane=self.plane,
        )

    def __call__(self, state: SimState, records: Any = None) -> tuple[SimState, bool]:
        """Check all particles, replace those that break; returns ``(state, stop)``."""
        self.n_calls += 1
        decisions = self.check(state)
        if decisions:
            state = self.apply(state, decisions)
        stop = self.max_events is not None and len(self.events) >= self.max_events
        return state, stop

    def prebuild(self, state: SimState) -> None:
        """Build the BEM operators of every active particle now (otherwise each shape is
        built the first time it passes the screening). Up to ``cache_size`` are kept."""
        self._fit_elements(state)
        slots = np.flatnonzero(np.asarray(state.particles.active))[: self.cache_size]
        bs = self.batch_size
        for start in range(0, slots.size, bs):
            chunk = slots[start : start + bs]
            self._operators(state, np.concatenate([chunk, np.full(bs - chunk.size, chunk[0])]))

    def _candidates(self, state: SimState):
        """Screened particle slots and their contact table on the host, growing the
        per-particle contact list first if a candidate has more contacts than it holds.
        Returns ``(slots, table)`` or ``None`` when nothing passes the screening."""
        tab = self._table(state)
        cand = self._flagged(state, tab)
        if cand.size == 0:
            return None
        count = np.asarray(tab["count"])[cand]
        if count.max() > self.max_contacts:
            new = 1 << int(math.ceil(math.log2(int(count.max()))))
            self._note(
                f"contact list of {self.max_contacts} per particle exceeded "
                f"({int(count.max())} needed); grown to {new}"
            )
            self.max_contacts = new
            tab = self._table(state)
            cand = self._flagged(state, tab)
            if cand.size == 0:
                return None
        self.n_screened += int(cand.size)
        return cand, {k: np.asarray(v)[cand] for k, v in tab.items()}

    def _flagged(self, state: SimState, tab: dict[str, Array]) -> np.ndarray:
        """Slots that pass the screening (see the class docstring). Under the bound, a
        particle whose contact list was cut is flagged too (its bound would miss the
        dropped contacts), so that ``_candidates`` grows the list."""
        if self.screen == "force" or self.screen_fraction == 0.0:
            return np.flatnonzero(np.asarray(tab["flag"]))
        p = state.particles
        live = np.asarray(p.active) & (np.asarray(tab["n_neighbours"]) >= 2)
        if not live.any():
            return np.zeros(0, np.int64)
        dt = p.pos.dtype
        flat = bem._flat_contacts(tab["points"], tab["forces"], tab["mask"])
        bound = _bound_jit(
            self._bound_operators(state),
            *(jnp.asarray(x) for x in flat),
            jnp.asarray(self.thickness, dt),
        )
        cut = np.asarray(tab["count"]) > self.max_contacts
        return np.flatnonzero(live & ((np.asarray(bound) >= self.eps) | cut))

    def _bound_operators(self, state: SimState) -> bem.BemOperators:
        """Screening-only operators (:func:`jaxgran.bem.bound_operators`) of every slot:
        the tables of each active particle's shape (built once per shape), invalid rows
        for free slots. Only the rows whose particle changed are rewritten."""
        p = state.particles
        n_p = p.pos.shape[0]
        self._fit_elements(state)
        want = np.where(np.asarray(p.active), np.asarray(p.uid), -1).astype(np.int64)
        known = np.fromiter(self._bound_rows, np.int64, len(self._bound_rows))
        # particles that left (fines, merged or replaced) never come back: drop their rows
        for u in known[~np.isin(known, want)].tolist():
            del self._bound_rows[u]
        missing = np.flatnonzero((want >= 0) & ~np.isin(want, known))
        bs = self.batch_size
        for start in range(0, missing.size, bs):
            chunk = missing[start : start + bs]
            self._operators(state, np.concatenate([chunk, np.full(bs - chunk.size, chunk[0])]))
        if self._bound_stack is None or self._bound_uid.shape[0] != n_p:
            row = next(iter(self._bound_rows.values()))
            self._bound_stack = {k: jnp.zeros((n_p, *v.shape), v.dtype) for k, v in row.items()}
            self._bound_uid = np.full(n_p, -2, np.int64)
        stale = np.flatnonzero(want != self._bound_uid)
        if stale.size:
            blank = {k: jnp.zeros_like(v[0]) for k, v in self._bound_stack.items()}
            rows = [self._bound_rows.get(int(want[s]), blank) for s in stale.tolist()]
            idx = jnp.asarray(stale)
            self._bound_stack = {
                k: v.at[idx].set(jnp.stack([r[k] for r in rows]))
                for k, v in self._bound_stack.items()
            }
            self._bound_uid = want
        st = self._ops_static
        return bem.bound_operators(
            **self._bound_stack,
            poisson_ratio=st["shared"]["poisson_ratio"],
            plane=st["static"]["plane"],
            load_model=st["static"]["load_model"],
        )

    def check(self, state: SimState) -> list[_Decision]:
        """The breakage decisions for ``state`` (no state change)."""
        found = self._candidates(state)
        if found is None:
            return []
        cand, host = found
        self._fit_elements(state)
        self._grow_cache(cand.size)
        decisions = []
        for start in range(0, cand.size, self.batch_size):
            rows = np.arange(start, min(start + self.batch_size, cand.size))
            decisions += self._check_batch(state, cand, rows, host)
        return decisions

    def apply(self, state: SimState, decisions: list[_Decision]) -> SimState:
        """Replace the broken particles, log the events and rebuild contacts and forces."""
        reps = [Replacement(d.slot, d.pieces, d.planes) for d in decisions]
        state, events = replace_particles(
            state,
            reps,
            min_area=self.min_area,
            mean_initial_mass=self.mean_initial_mass,
            erosion=self.erosion,
            small_pieces=self.small_pieces,
            conserve_mass=self.conserve_mass,
            min_radius=self.min_radius,
        )
        replaced = False
        for d, ev in zip(decisions, events, strict=True):
            ev.update(d.info)
            ev["eps"] = self.eps
            if ev["kind"] == "suppressed":
                self.suppressed.append(ev)
                continue
            replaced = True
            self._cache.pop(int(ev["parent_uid"]), None)
            self._bound_rows.pop(int(ev["parent_uid"]), None)
            if "capacity_growth" in ev:
                self._note(ev["capacity_growth"])
            self.events.append(ev)
        return self._prepare(state) if replaced else state

    # -------------------------------------------------------------- internals

    def _grow_cache(self, n: int) -> None:
        """Let the operator cache hold ``n`` shapes (one check's candidates), as far as
        ``CACHE_BYTES`` allows: an LRU cache smaller than the set it cycles through misses
        on every access."""
        if n <= self.cache_size:
            return
        entry = next(iter(self._cache.values()), None)
        per_shape = (
            sum(v.nbytes for v in entry.values())
            if entry is not None
            else 8 * self.n_points * (6 * self.n_elements + 8)
        )
        cap = max(self.cache_size, CACHE_BYTES // max(per_shape, 1))
        new = min(1 << int(math.ceil(math.log2(n))), cap)
        if new > self.cache_size:
            self._note(
                f"operator cache grown from {self.cache_size} to {new} shapes "
                f"({n} screened in one check, {per_shape / 1e6:.2f} MB each)"
            )
            self.cache_size = new

    def _note(self, msg: str) -> None:
        log.info(msg)
        self.log.append(msg)

    def _table(self, state: SimState) -> dict[str, Array]:
        dt = state.particles.pos.dtype
        return contact_table(
            state,
            self.params,
            jnp.asarray(self.eps, dt),
            jnp.asarray(self.screen_fraction, dt),
            jnp.asarray(self.k, dt),
            jnp.asarray(self.thickness, dt),
            self.max_contacts,
        )

    def _fit_elements(self, state: SimState) -> None:
        need = bem.min_elements(state.particles.verts.shape[1])
        if self.n_elements < need:
            new = -(-need // 8) * 8
            self._note(
                f"BEM elements raised from {self.n_elements} to {new} for vertex capacity "
                f"{state.particles.verts.shape[1]}; cached operators rebuilt"
            )
            self.n_elements = new
            self._cache.clear()
            self._bound_rows.clear()
            self._bound_stack = None

    def _operators(self, state: SimState, slots: np.ndarray) -> bem.BemOperators:
        """Stacked operators of ``slots`` (length ``batch_size``), built when not cached."""
        p = state.particles
        uids = np.asarray(p.uid)[slots]
        todo = []
        for s, u in zip(slots.tolist(), uids.tolist(), strict=True):
            if u in self._cache:
                self._cache.move_to_end(u)
                if u not in self._bound_rows:
                    self._bound_rows[u] = {k: self._cache[u][k] for k in bem.BOUND_FIELDS}
            elif u not in [t[1] for t in todo]:
                todo.append((s, u))
        bs = self.batch_size
        for start in range(0, len(todo), bs):
            chunk = todo[start : start + bs]
            idx = np.array([s for s, _ in chunk] + [chunk[0][0]] * (bs - len(chunk)))
            ops = bem.build_operators(
                p.verts[idx],
                p.n_verts[idx],
                p.radius[idx],
                n_elements=self.n_elements,
                n_points=self.n_points,
                poisson_ratio=self.poisson_ratio,
                plane=self.plane,
                load_model=self.load_model,
                batch_size=bs,
            )
            per, shared = {}, {}
            for f in dataclasses.fields(ops):
                if f.metadata.get("static", False):
                    continue
                val = getattr(ops, f.name)
                if isinstance(val, jax.Array) and val.ndim >= 1 and val.shape[0] == bs:
                    # one transfer per field and batch; the rows are kept on the host, where
                    # slicing and stacking cost no dispatch of an eager device op each
                    per[f.name] = np.asarray(val)
                else:
                    shared[f.name] = val
            self._ops_static = {
                "shared": shared,
                "static": {
                    f.name: getattr(ops, f.name)
                    for f in dataclasses.fields(ops)
                    if f.metadata.get("static", False)
                },
            }
            for t, (_, u) in enumerate(chunk):
                self._cache[u] = {k: v[t].copy() for k, v in per.items()}
                self._bound_rows[u] = {k: self._cache[u][k] for k in bem.BOUND_FIELDS}
        while len(self._cache) > max(self.cache_size, bs):
            self._cache.popitem(last=False)
        stacked = {
            k: jnp.asarray(np.stack([self._cache[u][k] for u in uids.tolist()]))
            for k in self._cache[int(uids[0])]
        }
        return bem.BemOperators(
            **stacked, **self._ops_static["shared"], **self._ops_static["static"]
        )

    def _check_batch(self, state, cand, rows, host) -> list[_Decision]:
        p = state.particles
        bs = self.batch_size
        pad = np.concatenate([rows, np.full(bs - rows.size, rows[0])])
        slots = cand[pad]
        ops = self._operators(state, slots)
        # the real contacts come first in each list: solve over the batch's longest list,
        # rounded up to a power of two (at least 4), not over all max_contacts slots
        longest = int(host["mask"][rows].sum(axis=1).max())
        c = min(self.max_contacts, max(4, 1 << max(longest - 1, 0).bit_length()))
        mask = host["mask"][pad, :c].copy()
        mask[rows.size :] = False
        dt = p.pos.dtype
        _, psi = _psi_jit(
            ops,
            jnp.asarray(host["points"][pad, :c], dt),
            jnp.asarray(host["forces"][pad, :c], dt),
            jnp.asarray(mask),
            jnp.asarray(self.thickness, dt),
            jnp.asarray(self.poisson_ratio, dt),
        )
        psi = np.asarray(psi)
        pts_all = np.asarray(ops.points)
        ij_all = np.asarray(ops.grid_index)
        pm_all = np.asarray(ops.point_mask)
        out = []
        for b, row in enumerate(rows.tolist()):
            self.n_checked += 1
            slot = int(cand[row])
            m = host["mask"][row]
            nb = host["neighbour"][row][m]
            cpts = host["points"][row][m]
            cfs = host["forces"][row][m]
            groups = np.unique(nb)
            pm = pm_all[b]
            if groups.size < 2 or not pm.any():
                continue
            samples = pts_all[b][pm]
            ij = ij_all[b][pm]
            seeds, centres = [], []
            for g in groups.tolist():
                sel = nb == g
                d = np.linalg.norm(samples[None, :, :] - cpts[sel][:, None, :], axis=-1)
                seeds.append(np.unique(np.argmin(d, axis=1)))
                w = np.linalg.norm(cfs[sel], axis=1)
                w = w if w.sum() > 0 else np.ones_like(w)
                centres.append((w[:, None] * cpts[sel]).sum(0) / w.sum())
            res = connection_points(
                psi[b][pm], ij, seeds, self.eps, finite=_touching_seeds(seeds, ij)
            )
            off = ~np.eye(groups.size, dtype=bool)
            saddle = float(np.max(res.bottleneck[off]))
            uid = int(np.asarray(p.uid)[slot])
            self.last_saddle[uid] = saddle
            if not res.breaks:
                continue
            centres = np.asarray(centres)
            conn = samples[res.connection_index]
            size = float(np.asarray(p.bound_radius)[slot])
            i, j = np.triu_indices(len(centres), k=1)
            far = np.linalg.norm(centres[i] - centres[j], axis=1) > 1e-9 * size
            if not far.any():
                continue
            planes_b = fracture_planes(conn, centres, np.stack([i[far], j[far]], axis=1))
            to_world = _body_to_world(state, slot)
            planes_w = to_world(planes_b.reshape(-1, 2)).reshape(-1, 2, 2)
            n = int(np.asarray(p.n_verts)[slot])
            core_w = to_world(np.asarray(p.verts[slot, :n]))
            r = float(np.asarray(p.radius)[slot])
            pieces = split_convex(dilated_outline(core_w, r, self.n_arc), planes_w)
            if len(pieces) < 2:
                continue
            info = {
                "psi_saddle": saddle,
                "connection_points": to_world(conn),
                "contact_points": to_world(centres),
                "n_contacts": int(groups.size),
                "max_contact_force": float(host["max_force"][row]),
                "critical_load": float(host["critical_load"][row]),
            }
            out.append(_Decision(slot, planes_w, pieces, info))
        return out

    def _prepare(self, state: SimState) -> SimState:
        """Pair list and forces for the new particles (grows pair / cell capacity)."""
        for _ in range(8):
            state, err = prepare(state, self.params, self.grid)
            err = int(err)
            if not err & (ERR_PAIR_OVERFLOW | ERR_CELL_OVERFLOW):
                break
            grown: list[str] = []
            state, self.grid = grow_capacities(state, state, self.grid, err, grown)
            for msg in grown:
                self._note(f"{msg} after breakage")
        else:
            raise SimulationError("capacity still exceeded after 8 regrowths after breakage")
        if err & (ERR_NAN | ERR_LEFT_DOMAIN):
            raise SimulationError(
                "after breakage a fragment is NaN or outside the domain; check the fracture "
                "planes and the grid bounds"
            )
        return state


def _touching_seeds(seeds: list, ij: np.ndarray) -> np.ndarray:
    """Seed samples that share or neighbour (4-connectivity on the sample grid) a seed of
    another contact.

    Seed samples count as ``psi = +inf`` (the load points are singular). Two seed sets that
    touch would then be joined at an infinite level and the particle would break under any
    load, however small. That happens when two neighbours press on one corner (three
    Voronoi cells meet at a point) closer together than the sample spacing, where the
    sampled field cannot tell the two loads apart. Those samples keep their computed psi
    (:func:`~jaxgran.breakage.criteria.connection_points`, ``finite``), so the level at which
    the two contacts connect scales with the load."""
    out = []
    for a in range(len(seeds)):
        for b in range(a + 1, len(seeds)):
            gap = np.abs(ij[seeds[a]][:, None, :] - ij[seeds[b]][None, :, :]).sum(axis=-1)
            near = gap <= 1
            if near.any():
                out += [seeds[a][near.any(axis=1)], seeds[b][near.any(axis=0)]]
    return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)


def _body_to_world(state: SimState, slot: int):
    p = state.particles
    a = float(p.angle[slot])
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    pos = np.asarray(p.pos[slot])
    return lambda x: np.asarray(x) @ rot.T + pos
