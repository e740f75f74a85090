"""Oedometric test of breakable Voronoi spheropolygons (paper 000 §IV.B).

A Voronoi tessellation (Lloyd-smoothed) of a ``box_width`` x ``fill_height`` rectangle is
eroded by ``sphero_radius + gap``, each cell shrunk by ``shrink`` about its centroid and the
rows spread vertically so the grains fall freely; they pack under gravity in a container
137 cm wide (paper 000), then a top bar moves down at ``bar_speed`` (1 mm/s) for
``load_time`` (10 s) while the breakage method of ``method`` acts. Table I parameters except
mu = 0.4 (paper 000 §IV.B). The default ``n_cells = 600`` on 1.37 m x 1.10 m gives cells of
about 6 cm circumdiameter (area 1.5 m^2 / 600 = 25 cm^2), inside the 400-800 range.

Simulation, outputs and figures are those of :mod:`jaxgran.scenes.oedometer_cantor` (same
time step rule, event log, KE spikes, mass bookkeeping); the summary adds the PSD (d10,
d50), the fracture-plane polar histogram and the locking-effect detector (Figs. 13-16).
The full test is ~1e6 steps of ~600 grains: a GPU job; ``--quick`` is a 30 cm wide box.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .. import geometry as geo
from ..breakage import metrics
from ..integrate import check_time_step
from ..partition import make_grid
from ..state import (
    WALL_VELOCITY,
    box_walls,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
    wall,
)
from . import oedometer_cantor as oc
from .base import contact_params, finished_summary, write_outputs
from .limits import Checked, Range

__all__ = ["Config", "QUICK", "SCENE", "build", "run"]

SCENE = "oedometer-voronoi"


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    LIMITS: ClassVar[dict] = {"n_elements": Range(8, integer=True, note="BEM elements")}

    method: str = "dsm"  # dsm, split-cell, cross-cut, mohr-coulomb
    n_cells: int = 600  # Voronoi cells tessellating the fill region
    box_width: float = 1.37  # m (paper 000 §IV.B)
    fill_height: float = 1.10  # m, tessellated height (the packing is ~110 cm high)
    sphero_radius: float = 2.0e-3  # m
    gap: float = 5.0e-4  # m, extra erosion: no contact at t = 0
    shrink: float = 0.9  # cells scaled about their centroid
    spread: float = 1.08  # vertical spreading of the cells
    lloyd_iterations: int = 3
    normal_stiffness: float = 6.0e5  # N/m, Table I
    tangential_stiffness: float = 2.2e4  # N/m, Table I
    friction: float = 0.4  # paper 000 §IV.B
    areal_density: float = 12.0  # kg/m^2, Table I
    poisson_ratio: float = 0.3  # of the grains, for the BEM (Table I)
    thickness: float = 0.01  # m
    restitution: float = 0.3  # sets G_n, G_t (not in Table I)
    skin: float = 2.0e-3  # m, Table I
    calibration_force: float = 150.79  # N (paper 000 §III)
    calibration_radius: float = 0.01  # m
    min_fragment_fraction: float = 0.05  # lighter pieces (x mean mass): see small_pieces
    dt_safety: float = 0.4  # see oedometer_cantor.Config.dt_safety
    settle_time: float = 1.5  # s
    settle_ke_ratio: float = 1.0e-4  # settled when KE < this x its peak
    bar_gap: float = 1.0e-3  # m
    bar_speed: float = 1.0e-3  # m/s (paper: v_y = -1 mm/s)
    load_time: float = 10.0  # s
    snapshot_times: tuple = (0.0, 2.5, 5.0, 7.0, 10.0)  # s after loading starts
    record_every: int = 200
    records_per_segment: int = 10
    n_elements: int = 64  # DSM BEM elements
    n_points: int = 200  # DSM BEM sample points
    screen: str = "bound"  # DSM screening: bound (proven) or force (heuristic)
    erosion: str = "local"  # fragments' erosion: local, local-axis, uniform, none
    small_pieces: str = "merge"  # pieces below min_fragment_fraction: merge or fines
    conserve_mass: bool = False  # density compensation of the erosion
    fragment_radius_floor: float = 0.0  # adaptive fragment radius floor / sphero_radius
    capacity_factor: float = 2.0  # particle slots at the start / n_cells (growth recompiles)
    seed: int = 0


QUICK = {
    "n_cells": 30,
    "box_width": 0.30,
    "fill_height": 0.20,
    "min_fragment_fraction": 0.1,
    "settle_time": 0.25,
    "bar_speed": 0.1,
    "load_time": 0.03,
    "snapshot_times": (0.0, 0.015, 0.03),
    "record_every": 100,
    "records_per_segment": 5,
}


def cells(cfg: Config) -> list[np.ndarray]:
    """Eroded, shrunk and spread Voronoi cores (m) above the container floor."""
    out = []
    for c in geo.voronoi_rectangle(
        cfg.box_width,
        cfg.fill_height,
        cfg.n_cells,
        cfg.seed,
        lloyd_iterations=cfg.lloyd_iterations,
    ):
        cen = geo.polygon_centroid(c)
        c = cen + cfg.shrink * (c - cen)
        try:
            core = geo.offset_polygon(c, cfg.sphero_radius + cfg.gap)
        except ValueError:
            continue
        out.append(core + [0.0, (cfg.spread - 1.0) * cen[1] + cfg.sphero_radius + 1e-3])
    return out


def build(cfg: Config):
    """Initial state (cells in the air, bar parked above), parameters and grid."""
    cores = cells(cfg)
    parts = particles_from_polygons(
        cores,
        cfg.sphero_radius,
        cfg.areal_density,
        capacity=max(len(cores), math.ceil(cfg.capacity_factor * len(cores))),
    )
    m_mean = float(np.asarray(parts.mass)[np.asarray(parts.active)].mean())
    params = contact_params(cfg, m_mean, poisson_ratio=cfg.poisson_ratio)
    params = replace(
        params, dt=jnp.asarray(oc.adaptive_dt(parts, params, cfg.dt_safety), params.dt.dtype)
    )
    check_time_step(parts, params)
    pos = np.asarray(parts.pos)
    rmax = float(np.asarray(parts.bound_radius).max())
    height = float(pos[:, 1].max()) + rmax + 0.02
    walls = box_walls((0.0, 0.0), (cfg.box_width, height), top=False)
    walls.append(wall((0.0, height), (0.0, -1.0), mode=WALL_VELOCITY, length=cfg.box_width))
    state = make_state(parts, make_walls(walls))
    grid = make_grid((-0.05, -0.05), (cfg.box_width + 0.05, height + 0.05), rmax, cfg.skin)
    return state, params, grid


def run(
    cfg: Config, out_dir: Path, *, progress=True, vtk=False, checkpoint_minutes=10.0, resume=False
):
    """As :func:`jaxgran.scenes.oedometer_cantor.run` (checkpoints included), for the
    Voronoi packing; the summary adds the PSD."""
    done = finished_summary(Path(out_dir), SCENE, cfg) if resume else None
    if done is not None:
        return done
    ckpt, (settle, load, brk, info) = oc.checkpointed_test(
        cfg, Path(out_dir), progress, checkpoint_minutes, resume, build_fn=build
    )
    summary = oc.summarize(settle, load, brk, info, cfg)
    p = load.state.particles
    act = np.asarray(p.active)
    area = np.asarray(p.mass)[act] / cfg.areal_density
    psd = metrics.particle_size_distribution(
        metrics.equivalent_diameters(area), np.asarray(p.mass)[act]
    )
    summary["psd"] = {"d10_m": psd["d10"], "d50_m": psd["d50"], "n": psd["n"]}
    summary["cell_size_note"] = (
        f"{cfg.n_cells} Voronoi cells on {cfg.box_width} m x {cfg.fill_height} m "
        f"(mean cell area {cfg.box_width * cfg.fill_height / cfg.n_cells * 1e4:.1f} cm^2)"
    )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figs = oc.figures(load, brk, info, cfg, out_dir)
    summary = write_outputs(
        out_dir, SCENE, cfg, load, brk.params, summary, events=brk.events, vtk=vtk
    )
    summary["figures"] = list(summary.get("figures", [])) + figs
    summary["force_chains"] = info.get("force_chains")
    from .. import io

    io.write_summary(out_dir / "summary.json", summary)
    if ckpt is not None:
        ckpt.unlink(missing_ok=True)
    return summary
