"""Brazilian test with the damage separation model: one disc-like grain between two platens.

A regular polygon (``n_vertices`` >= 32, a vertex at each pole) swept by ``sphero_radius``
makes a disc of outer radius R = ``disc_radius``; two platens (walls in velocity mode) close
on it at ``platen_speed`` each, with no gravity. The DSM (paper 000 §II) checks the grain
every ``check_every`` steps; it breaks when the strain-energy equivalent stress at the saddle
between the two contacts (the disc centre) reaches eps. The run stops ``post_break_time``
after the first breakage.

Reported: the platen force at the check that detected the break, the bracket from the
previous check, the force interpolated to psi = eps (psi is linear in the load), the
prediction ``F_c = eps pi R t / k`` (PHYSICS §C), the fracture-plane angle from the loading
diameter, and the fragment masses.

Why the measurement is quasi-static: both platens move at the same speed, so the disc stays
centred and the two contact forces are equal at every step (no inertia enters the load seen
by the BEM); the only timing error is the load increase between two checks,
``K_n v dt check_every`` (0.8 N by default). A normal and tangential dashpot damps what
the first contact excites.

eps defaults to :func:`jaxgran.breakage.dsm.calibrate_eps` of the paper's Brazilian
breaking force F = 150.79 N for R = 1 cm with our thickness t = 1 cm (1.649 MPa in plane
stress, nu = 0.3), so the disc should break at 150.79 N. The paper's own 2.80251 MPa cannot
be matched literally (it implies t = 5.88 mm, PHYSICS §C); with it and t = 1 cm the disc
would break at 256 N.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .. import geometry as geo
from ..breakage.dsm import (
    PAPER_EPS,
    DsmBreakage,
    brazilian_factor,
    calibrate_eps,
    critical_load,
)
from ..contact import damping_from_restitution
from ..errors import SceneError
from ..integrate import check_time_step, stable_time_step
from ..partition import make_grid
from ..simulate import simulate
from ..state import (
    WALL_VELOCITY,
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
    wall,
)
from .base import write_outputs
from .limits import Checked, Range, require_less

__all__ = ["Config", "QUICK", "build", "calibrate_eps", "run", "simulate_test"]


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    LIMITS: ClassVar[dict] = {"n_elements": Range(8, integer=True, note="BEM elements")}

    disc_radius: float = 0.01  # m, R: outer radius of the grain (core circumradius + r)
    n_vertices: int = 32  # core polygon vertices (>= 32 for a disc-like grain)
    sphero_radius: float = 1.0e-3  # m, r
    thickness: float = 0.01  # m, t (out of plane)
    areal_density: float = 12.0  # kg/m^2 (1.2 g/cm^2, paper 000 Table I)
    target_force: float = 150.79  # N, Brazilian breaking force that calibrates eps
    eps: float = 0.0  # Pa, DSM threshold; 0 = calibrate_eps(target_force, disc_radius)
    poisson_ratio: float = 0.3  # paper 000 Table I
    plane: str = "stress"  # "stress" or "strain"
    normal_stiffness: float = 2.0e7  # N/m (stiff: the erosion removes the overlap)
    tangential_stiffness: float = 6.7e6  # N/m
    friction: float = 0.74  # paper 000 Table I
    restitution: float = 0.3  # sets the dashpots G_n, G_t
    platen_speed: float = 4.0e-4  # m/s, each platen
    # x the one-contact limit of springs and dashpots; the squeezed grain's linearised step
    # sits at 0.27 of its stability criterion (docs/stability.md)
    dt_safety: float = 0.5
    skin: float = 2.0e-4  # m, Verlet distance
    check_every: int = 50  # steps between two DSM checks (one segment)
    record_every: int = 10  # steps between two records
    post_break_time: float = 2.0e-3  # s simulated after the first breakage
    max_force_ratio: float = 1.5  # give up when the load exceeds this x the prediction
    n_elements: int = 128  # BEM elements
    n_points: int = 400  # BEM sample points
    screen_fraction: float = 0.5  # BEM only once a contact force reaches this x the critical load
    min_area_fraction: float = 1.0e-3  # fragments below this x the grain area become fines
    load_model: str = "flamant"  # BEM contact load model

    def relations(self) -> None:
        require_less(self, "sphero_radius", "disc_radius")


QUICK = {
    "n_elements": 64,
    "n_points": 200,
    "platen_speed": 1.0e-3,
    "check_every": 20,
    "record_every": 10,
    "post_break_time": 3.0e-4,
}


def _eps(cfg: Config) -> float:
    if cfg.eps > 0:
        return cfg.eps
    return calibrate_eps(
        cfg.target_force,
        cfg.disc_radius,
        poisson_ratio=cfg.poisson_ratio,
        plane=cfg.plane,
        thickness=cfg.thickness,
    )


def build(cfg: Config, rotation: float = 0.0):
    """Initial state (platens touching the grain), parameters and grid.

    ``rotation`` (rad) turns the grain about its centre (0: a vertex at each pole)."""
    if cfg.n_vertices < 3 or cfg.n_vertices % 2:
        raise SceneError("n_vertices must be even (a vertex at each pole) and >= 4")
    r = cfg.sphero_radius
    core = geo.regular_polygon(cfg.n_vertices, cfg.disc_radius - r, math.pi / 2 + rotation)
    parts = particles_from_polygons(
        [core], r, cfg.areal_density, capacity=4, vertex_capacity=cfg.n_vertices
    )
    m = float(parts.mass[0])
    params = make_params(
        normal_stiffness=cfg.normal_stiffness,
        tangential_stiffness=cfg.tangential_stiffness,
        friction=cfg.friction,
        normal_damping=damping_from_restitution(cfg.restitution, cfg.normal_stiffness, m),
        tangential_damping=damping_from_restitution(cfg.restitution, cfg.tangential_stiffness, m),
        gravity=(0.0, 0.0),
        skin=cfg.skin,
        thickness=cfg.thickness,
        poisson_ratio=cfg.poisson_ratio,
    )
    params = replace(
        params, dt=jnp.asarray(stable_time_step(parts, params, cfg.dt_safety), params.dt.dtype)
    )
    check_time_step(parts, params)
    # the platens touch the outline where it is highest and lowest
    top = float(np.max(core[:, 1])) + r
    bottom = float(np.min(core[:, 1])) - r
    width = 4.0 * cfg.disc_radius
    walls = make_walls(
        [
            wall(
                (0.0, bottom),
                (0.0, 1.0),
                velocity=(0.0, cfg.platen_speed),
                mode=WALL_VELOCITY,
                length=2.0 * cfg.disc_radius,
            ),
            wall(
                (0.0, top),
                (0.0, -1.0),
                velocity=(0.0, -cfg.platen_speed),
                mode=WALL_VELOCITY,
                length=2.0 * cfg.disc_radius,
            ),
        ]
    )
    state = make_state(parts, walls, pair_capacity=8)
    grid = make_grid(
        (-width, -width), (width, width), float(parts.bound_radius[0]), cfg.skin, cell_capacity=8
    )
    return state, params, grid


def _platen_force(state) -> float:
    """Mean compressive force of the two platens (N), last step."""
    f = np.asarray(state.walls.force)[:, 1]
    return 0.5 * (abs(float(f[0])) + abs(float(f[1])))


def simulate_test(cfg: Config, *, progress: bool = False, rotation: float = 0.0):
    """Run the test; returns ``(result, dsm, measurement dict)`` without writing files."""
    state, params, grid = build(cfg, rotation)
    eps = _eps(cfg)
    p0 = state.particles
    area0 = float(p0.mass[0]) / cfg.areal_density
    dsm = DsmBreakage(
        params,
        grid,
        eps=eps,
        poisson_ratio=cfg.poisson_ratio,
        plane=cfg.plane,
        thickness=cfg.thickness,
        n_elements=cfg.n_elements,
        n_points=cfg.n_points,
        screen_fraction=cfg.screen_fraction,
        min_area=cfg.min_area_fraction * area0,
        mean_initial_mass=float(p0.mass[0]),
        load_model=cfg.load_model,
        batch_size=1,
    )
    f_pred = critical_load(
        eps, cfg.disc_radius, cfg.thickness, poisson_ratio=cfg.poisson_ratio, plane=cfg.plane
    )
    dt = float(params.dt)
    t_load = cfg.max_force_ratio * f_pred / (cfg.normal_stiffness * cfg.platen_speed)
    n_steps = int(math.ceil((t_load + cfg.post_break_time) / dt))
    meas: dict = {"forces_checked": [], "break_time": None}

    def callback(s, rec):
        force = _platen_force(s)
        n_before = len(dsm.events)
        s, _ = dsm(s, rec)
        t = float(s.time)
        if meas["break_time"] is None:
            if len(dsm.events) > n_before:
                meas["break_time"] = t
                meas["force_at_break"] = force
                prev = meas["forces_checked"]
                meas["force_previous_check"] = prev[-1] if prev else 0.0
                meas["psi_saddle"] = float(dsm.events[n_before]["psi_saddle"])
            else:
                meas["forces_checked"].append(force)
                return s, force > cfg.max_force_ratio * f_pred
        return s, t >= meas["break_time"] + cfg.post_break_time

    shapes0 = {k: np.asarray(getattr(p0, k)) for k in ("verts", "n_verts", "radius", "uid")}
    records_per_segment = max(1, cfg.check_every // cfg.record_every)
    result = simulate(
        state,
        params,
        grid,
        n_steps=n_steps,
        record_every=cfg.record_every,
        records_per_segment=records_per_segment,
        frame_every=max(1, (n_steps // (cfg.record_every * records_per_segment)) // 20),
        callback=callback,
        progress=progress,
        desc="brazilian_dsm",
    )
    # frames before the break show the intact grain (simulate records no shapes)
    final = {k: np.asarray(getattr(result.state.particles, k)) for k in shapes0}
    t_break = meas["break_time"]
    for fr in result.frames:
        before = t_break is None or float(fr["time"]) < t_break
        src = shapes0 if before else final
        for k, v in src.items():
            fr[k] = v[: fr["pos"].shape[0]] if v.shape[0] >= fr["pos"].shape[0] else v
    meas.update(eps=eps, predicted_force=f_pred, area=area0)
    return result, dsm, meas


def summarize(result, dsm: DsmBreakage, meas: dict, cfg: Config) -> dict:
    f_pred = meas["predicted_force"]
    out = {
        "eps_Pa": meas["eps"],
        "eps_paper_Pa": PAPER_EPS,
        "brazilian_factor_k": brazilian_factor(cfg.poisson_ratio, cfg.plane),
        "predicted_critical_force_N": f_pred,
        "broke": meas["break_time"] is not None,
        "n_events": len(dsm.events),
        "steps": int(result.steps),
        "dt_s": float(dsm.params.dt),
        "simulated_time_s": float(result.state.time),
        "wall_time_s": float(result.wall_time_s),
        "dsm_checks": int(dsm.n_checked),
        "regrows": list(result.regrows) + dsm.log,
    }
    if meas["break_time"] is None:
        return out
    ev = dsm.events[0]
    f_break = meas["force_at_break"]
    f_interp = f_break * meas["eps"] / meas["psi_saddle"]
    planes = np.asarray(ev["planes"]).reshape(-1, 2, 2)
    d = planes[:, 1] - planes[:, 0]
    angles = np.degrees(np.arccos(np.clip(np.abs(d[:, 1]) / np.linalg.norm(d, axis=1), 0, 1)))
    masses = np.asarray(ev["fragment_masses"])
    out.update(
        {
            "critical_force_N": f_break,
            "critical_force_over_predicted": f_break / f_pred,
            "force_previous_check_N": meas["force_previous_check"],
            "critical_force_interpolated_N": f_interp,
            "interpolated_over_predicted": f_interp / f_pred,
            "break_time_s": meas["break_time"],
            "psi_saddle_Pa": meas["psi_saddle"],
            "fracture_plane_angles_deg": angles.tolist(),
            "n_fragments": int(masses.size),
            "fragment_masses_kg": masses.tolist(),
            "fragment_mass_ratio": float(masses.min() / masses.max()) if masses.size else 0.0,
            "parent_mass_kg": float(ev["parent_mass"]),
            "mass_lost_fraction": float(ev["mass_lost"]) / float(ev["parent_mass"]),
            "fines_mass_kg": float(ev["fines_mass"]),
            "erosion_m": float(ev["erosion"]),
            "breakage_type": ev.get("breakage_type", ""),
            "connection_points_m": np.asarray(ev["connection_points"]).tolist(),
        }
    )
    return out


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    result, dsm, meas = simulate_test(cfg, progress=progress)
    params = dsm.params
    summary = summarize(result, dsm, meas, cfg)
    return write_outputs(
        out_dir, "brazilian_dsm", cfg, result, params, summary, events=dsm.events, vtk=vtk
    )
