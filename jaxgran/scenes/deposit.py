"""Deposit: Voronoi spheropolygons poured into a box under gravity until they settle.

The default pours ~500 cells of circumdiameter 1-3 cm into a 50 cm wide box with the
paper-000 Table I parameters (K_n = 6e5 N/m, K_t = 2.2e4 N/m, mu = 0.74, rho = 1.2 g/cm^2
areal density, i.e. 12 kg/m^2), plus a normal viscous damping G_n (paper 002 Eq. 10) set from a
coefficient of restitution, which Table I does not give. The run stops when the kinetic energy
has decayed below ``ke_stop_ratio`` of its peak (or at ``max_time``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .. import geometry as geo
from ..errors import SceneError
from ..integrate import check_time_step, stable_time_step
from ..partition import make_grid
from ..simulate import simulate
from ..state import (
    box_walls,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
)
from .base import contact_params, write_outputs
from .limits import Checked, require_less


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    n_cells: int = 500  # Voronoi cells generated (particles kept after the size filter)
    box_width: float = 0.50  # m
    cell_size: float = 0.022  # m, mean circumdiameter of the tessellation's cells
    min_diameter: float = 0.01  # m, circumdiameter range kept
    max_diameter: float = 0.03  # m
    sphero_radius: float = 1.0e-3  # m
    gap: float = 2.0e-4  # m, extra erosion so no two cells touch at t = 0
    spread: float = 1.05  # vertical spreading of the initial lattice
    shrink: float = 0.85  # cells are scaled by this about their centroid (room to fall freely)
    normal_stiffness: float = 6.0e5  # N/m, Table I
    tangential_stiffness: float = 2.2e4  # N/m, Table I
    friction: float = 0.74  # Table I
    areal_density: float = 12.0  # kg/m^2, Table I (1.2 g/cm^2)
    restitution: float = 0.2  # sets G_n and G_t (not in Table I)
    dt: float = 0.0  # s; 0 = safety x stability limit, capped at dt_max
    dt_max: float = 5.0e-4  # s, Table I
    # x the one-contact limit of springs and dashpots (integrate.critical_time_step); the
    # settled quick pile's linearised step is then at 0.52 of its stability criterion
    # (0.87 at 0.5: several contacts per grain damp it more than one contact does)
    dt_safety: float = 0.3
    skin: float = 2.0e-3  # m, Table I Verlet distance
    max_time: float = 1.5  # s
    ke_stop_ratio: float = 1.0e-6  # settled once the kinetic energy is below this x its peak
    min_time: float = 0.1  # s, never stop before this (the pour must start)
    record_every: int = 200
    records_per_segment: int = 10
    seed: int = 0
    lloyd_iterations: int = 3
    thickness: float = 0.01  # m, out of plane (used for stresses only)

    def relations(self) -> None:
        require_less(self, "min_diameter", "max_diameter")
        require_less(self, "min_time", "max_time")


QUICK = {"n_cells": 60, "box_width": 0.16, "normal_stiffness": 6.0e4, "max_time": 2.0}


def make_cells(cfg: Config) -> list[np.ndarray]:
    """Voronoi cells of the pour region, filtered by circumdiameter, eroded by r + gap."""
    area_per_cell = 0.65 * cfg.cell_size**2  # regular hexagon of that circumdiameter
    height = cfg.n_cells * area_per_cell / cfg.box_width
    cells = geo.voronoi_rectangle(
        cfg.box_width,
        height,
        cfg.n_cells,
        cfg.seed,
        lloyd_iterations=cfg.lloyd_iterations,
    )
    out = []
    for c in cells:
        cen = geo.polygon_centroid(c)
        c = cen + cfg.shrink * (c - cen)
        d = 2 * (geo.circumradius(c) + cfg.sphero_radius)
        if not cfg.min_diameter <= d <= cfg.max_diameter:
            continue
        core = geo.offset_polygon(c, cfg.sphero_radius + cfg.gap)
        core = core + [0.0, (cfg.spread - 1.0) * cen[1]]
        out.append(core + [0.0, cfg.sphero_radius + 0.002])
    if not out:
        raise SceneError("no Voronoi cell within the circumdiameter range; adjust cell_size")
    return out


def build(cfg: Config):
    """Initial state, parameters and grid of the deposit."""
    cells = make_cells(cfg)
    parts = particles_from_polygons(cells, cfg.sphero_radius, cfg.areal_density)
    m_typ = float(np.median(np.asarray(parts.mass)))
    params = contact_params(cfg, m_typ)
    dt = cfg.dt or min(cfg.dt_max, stable_time_step(parts, params, cfg.dt_safety))
    params = replace(params, dt=jnp.asarray(dt, params.dt.dtype))
    check_time_step(parts, params)
    top = float(np.max(np.asarray(parts.pos)[:, 1])) + 0.05
    walls = make_walls(box_walls((0.0, 0.0), (cfg.box_width, top), top=False))
    state = make_state(parts, walls)
    rmax = float(jnp.max(parts.bound_radius))
    grid = make_grid((-0.02, -0.02), (cfg.box_width + 0.02, top + 0.05), rmax, cfg.skin)
    return state, params, grid


def pour(cfg: Config, *, progress: bool = True, frame_every: int = 5):
    """Build the deposit and run it until it settles (kinetic energy below
    ``ke_stop_ratio`` x its peak, after ``min_time``) or ``max_time``.

    Returns ``(result, params, peak kinetic energy (J))``."""
    state, params, grid = build(cfg)
    dt = float(params.dt)
    n_steps = int(np.ceil(cfg.max_time / dt))
    peak = [0.0]

    def settled(s, rec):
        ke = rec["kinetic_energy"]
        peak[0] = max(peak[0], float(ke.max()))
        t = float(rec["time"][-1])
        return s, bool(t >= cfg.min_time and ke[-1] <= cfg.ke_stop_ratio * peak[0])

    result = simulate(
        state,
        params,
        grid,
        n_steps=n_steps,
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        frame_every=frame_every,
        callback=settled,
        progress=progress,
        desc="deposit (stops once settled)",
        progress_note=lambda rec: (
            f"KE/peak={float(rec['kinetic_energy'][-1]) / max(peak[0], 1e-300):.1e} "
            f"(settled below {cfg.ke_stop_ratio:.0e} after {cfg.min_time:g} s)"
        ),
    )
    return result, params, peak[0]


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    result, params, peak = pour(cfg, progress=progress)
    summary = summarize(result, params, cfg, peak)
    return write_outputs(out_dir, "deposit", cfg, result, params, summary, vtk=vtk)


def summarize(result, params, cfg: Config, peak_ke: float) -> dict:
    p = result.state.particles
    act = np.asarray(p.active)
    mass = np.asarray(p.mass)[act]
    g = float(np.linalg.norm(np.asarray(params.gravity)))
    weight = float(mass.sum() * g)
    # floor reaction averaged over the last records (the particles push the floor down)
    bottom = -float(np.mean(result.series["wall_force"][-5:, 0, 1]))
    ke = float(result.series["kinetic_energy"][-1])
    return {
        "n_particles": int(act.sum()),
        "steps": int(result.steps),
        "simulated_time_s": float(result.state.time),
        "dt_s": float(params.dt),
        "wall_time_s": float(result.wall_time_s),
        "particle_steps_per_s": float(act.sum() * result.steps / result.wall_time_s),
        "final_kinetic_energy_J": ke,
        "peak_kinetic_energy_J": float(peak_ke),
        "kinetic_energy_ratio": ke / peak_ke if peak_ke > 0 else 0.0,
        "settled": bool(result.stopped_early),
        "packing_fraction": packing_fraction(result.state, cfg),
        "bottom_reaction_over_weight": bottom / weight if weight > 0 else float("nan"),
        "normal_damping_per_s": float(params.normal_damping),
        "regrows": result.regrows,
    }


def packing_fraction(state, cfg: Config) -> float:
    """Solid area fraction of the band between 10% and 80% of the pile height, from the
    particles whose centroids lie in it (area = mass / areal density)."""
    p = state.particles
    act = np.asarray(p.active)
    y = np.asarray(p.pos)[act, 1]
    area = np.asarray(p.mass)[act] / cfg.areal_density
    h = float(np.percentile(y, 95))
    band = (y > 0.1 * h) & (y < 0.8 * h)
    return float(area[band].sum() / (cfg.box_width * 0.7 * h))
