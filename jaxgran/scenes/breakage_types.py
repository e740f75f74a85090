"""Breakage types of one grain under N = 2, 3, 4 point loads, for the four breakage methods
(paper 000 §IV.A, Fig. 12).

The grain is the calibration disc (a 36-gon core swept by r, outer radius R = 1 cm, a vertex
every 10 degrees starting at 90 degrees). Each load is a short fixed wall pressing one vertex
along the inward radius, so each contact force is ``K_n x overlap`` at a known point and
direction and each wall is one neighbour for the DSM. The loads of a configuration are
balanced (force and moment) and scaled together: the load factor is raised in steps of
``ramp`` (quasi-static, no time stepping: the walls are moved, :func:`~jaxgran.simulate.
prepare` recomputes the forces and the method's ``check`` is called) until the method breaks
the grain; the first decision is applied with the shared replacement and classified by
paper 000 Table III (``m_r`` = smallest fragment / grain mass).

Configurations (angles of the loaded vertices in degrees, relative magnitudes):

* ``N2``: 90, 270 (1, 1): the Brazilian test;
* ``N3``: 90, 230, 310 (1, b, b), b = 1 / (2 sin 50): one load against two spread ones;
* ``N4``: 50 and 130 pinched towards each other (forces 30 degrees below the horizontal,
  magnitude 1) against 250 and 290 (radial, balancing): a force concentration near the
  boundary, which the DSM should chip off.

Expected (paper 000 Fig. 12): split-cell and Mohr-Coulomb always split in two (through the
centroid), cross-cut always gives four quarters, the DSM follows the loading.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .. import geometry as geo
from ..breakage.averaged import METHODS, make_breakage
from ..breakage.criteria import breakage_type
from ..breakage.dsm import calibrate_eps, critical_load
from ..errors import SceneError
from ..integrate import stable_time_step
from ..io import world_vertices_np
from ..partition import make_grid
from ..simulate import prepare
from ..state import make_params, make_state, make_walls, particles_from_polygons, replace, wall
from .base import environment
from .limits import Checked, OneOf, Range, require_less

__all__ = ["CONFIGURATIONS", "Config", "QUICK", "build", "load_test", "run"]

# relative magnitudes that balance the vertical resultants of N3 and N4
_B = 0.5 / math.sin(math.radians(50.0))
_C = 0.5 / math.sin(math.radians(70.0))
# name -> loads (vertex angle in degrees, relative magnitude, force direction in degrees or
# None for the inward radius); every configuration is balanced in force and moment
CONFIGURATIONS: dict[str, tuple[tuple[float, float, float | None], ...]] = {
    "N2": ((90.0, 1.0, None), (270.0, 1.0, None)),
    "N3": ((90.0, 1.0, None), (230.0, _B, None), (310.0, _B, None)),
    "N4": ((50.0, 1.0, 210.0), (130.0, 1.0, 330.0), (250.0, _C, None), (290.0, _C, None)),
}


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    LIMITS: ClassVar[dict] = {
        "n_elements": Range(8, integer=True, note="BEM elements"),
        "configurations": OneOf(tuple(CONFIGURATIONS), many=True),
    }

    disc_radius: float = 0.01  # m, outer radius R of the grain
    n_vertices: int = 36  # core vertices (a vertex every 10 degrees)
    sphero_radius: float = 1.0e-3  # m
    thickness: float = 0.01  # m
    areal_density: float = 12.0  # kg/m^2, Table I
    calibration_force: float = 150.79  # N, Brazilian breaking force (paper 000 §III)
    normal_stiffness: float = 2.0e7  # N/m (stiff: small overlaps, small erosion)
    poisson_ratio: float = 0.3  # of the grain, for the BEM (paper 000 Table I)
    start_fraction: float = 0.3  # first load: this x the Brazilian critical load (largest F)
    ramp: float = 1.03  # load factor ratio between two checks
    max_fraction: float = 20.0  # give up above this x the Brazilian critical load
    n_elements: int = 96  # DSM BEM elements (>= 2 x 36 vertices)
    n_points: int = 300  # DSM BEM sample points
    wall_half_width: float = 5.0e-4  # m, each loading wall touches one vertex only
    min_area_fraction: float = 1.0e-3  # fragments below this x the grain area are fines
    configurations: str = "N2,N3,N4"  # paper 000 Fig. 12 load cases (CONFIGURATIONS)
    methods: str = "dsm,split-cell,cross-cut,mohr-coulomb"  # breakage methods compared

    def relations(self) -> None:
        require_less(self, "sphero_radius", "disc_radius")
        require_less(self, "start_fraction", "max_fraction")


QUICK = {"n_points": 200, "ramp": 1.08, "start_fraction": 0.5}


def build(cfg: Config, configuration: str, load_factor: float):
    """State with the grain loaded by ``configuration`` scaled so the largest force is
    ``load_factor`` (N); returns ``(state, params, grid, forces)`` (forces: the applied
    ``[N, 2]`` world forces on the grain, N, and their points ``[N, 2]``, m)."""
    loads = CONFIGURATIONS[configuration]
    angles = [a for a, _, _ in loads]
    r = cfg.sphero_radius
    core = geo.regular_polygon(cfg.n_vertices, cfg.disc_radius - r, math.pi / 2)
    step = 360.0 / cfg.n_vertices
    for a in angles:
        k = (a - 90.0) / step
        if abs(k - round(k)) > 1e-9:
            raise SceneError(f"load angle {a} deg is not at a vertex (every {step} deg)")
    parts = particles_from_polygons(
        [core], r, cfg.areal_density, capacity=8, vertex_capacity=cfg.n_vertices
    )
    params = make_params(
        normal_stiffness=cfg.normal_stiffness,
        tangential_stiffness=0.3 * cfg.normal_stiffness,
        friction=0.74,
        gravity=(0.0, 0.0),
        thickness=cfg.thickness,
        poisson_ratio=cfg.poisson_ratio,
        skin=2.0e-4,
    )
    params = replace(params, dt=jnp.asarray(stable_time_step(parts, params, 0.15), params.dt.dtype))
    top = max(m for _, m, _ in loads)
    walls, pts, frc = [], [], []
    for a, m, direction in loads:
        u = np.array([math.cos(math.radians(a)), math.sin(math.radians(a))])
        d = (
            -u
            if direction is None
            else np.array([math.cos(math.radians(direction)), math.sin(math.radians(direction))])
        )
        f = load_factor * m / top
        vertex = u * (cfg.disc_radius - r)
        # a wall of normal d whose overlap with the vertex (swept by r) is f / K_n
        point = vertex - (r - f / cfg.normal_stiffness) * d
        walls.append(
            wall(
                point,
                d,
                extent=(-cfg.wall_half_width, cfg.wall_half_width),
                length=2 * cfg.wall_half_width,
            )
        )
        pts.append(vertex)
        frc.append(f * d)
    state = make_state(parts, make_walls(walls), pair_capacity=16)
    size = 3.0 * cfg.disc_radius
    grid = make_grid((-size, -size), (size, size), cfg.disc_radius, 2.0e-4, cell_capacity=16)
    state, err = prepare(state, params, grid)
    if int(err):
        raise RuntimeError(f"preparing the loaded grain failed (error bits {int(err)})")
    return state, params, grid, {"points": np.array(pts), "forces": np.array(frc)}


def load_test(cfg: Config, configuration: str, method: str) -> dict:
    """Raise the load of ``configuration`` until ``method`` breaks the grain.

    Returns a JSON-ready dict (``broke``, ``breaking_load_N``, ``breakage_type``,
    ``mass_ratio_m_r``, fragment mass fractions, planes, the applied loads) plus ``event``
    (the replacement event) and ``state`` (after the breakage) when it broke."""
    t = cfg.thickness
    eps = calibrate_eps(
        cfg.calibration_force, cfg.disc_radius, poisson_ratio=cfg.poisson_ratio, thickness=t
    )
    f_c = critical_load(eps, cfg.disc_radius, t, poisson_ratio=cfg.poisson_ratio)
    load = cfg.start_fraction * f_c
    brk = None
    while load <= cfg.max_fraction * f_c:
        state, params, grid, applied = build(cfg, configuration, load)
        if brk is None:
            m0 = float(state.particles.mass[0])
            area = m0 / cfg.areal_density
            brk = make_breakage(
                method,
                params,
                grid,
                calibration_force=cfg.calibration_force,
                calibration_radius=cfg.disc_radius,
                thickness=t,
                poisson_ratio=cfg.poisson_ratio,
                min_area=cfg.min_area_fraction * area,
                mean_initial_mass=m0,
                dsm_options={
                    "n_elements": cfg.n_elements,
                    "n_points": cfg.n_points,
                    "batch_size": 1,
                    "screen_fraction": 0.0,
                },
                averaged_options={"screen_fraction": 0.0},
            )
        else:
            brk.params, brk.grid = params, grid
        decisions = brk.check(state)
        if decisions:
            broken = brk.apply(state, decisions[:1])
            ev = brk.events[-1]
            masses = np.asarray(ev["fragment_masses"], float)
            return {
                "configuration": configuration,
                "method": method,
                "broke": True,
                "breaking_load_N": float(load),
                "breaking_load_over_brazilian": float(load / f_c),
                "n_fragments": int(masses.size),
                "fragment_mass_fractions": (masses / ev["parent_mass"]).tolist(),
                "mass_ratio_m_r": float(masses.min() / ev["parent_mass"]),
                "breakage_type": breakage_type(masses, ev["parent_mass"]),
                "planes_m": np.asarray(ev["planes"]).tolist(),
                "mass_lost_fraction": float(ev["mass_lost"] / ev["parent_mass"]),
                "applied": {k: v.tolist() for k, v in applied.items()},
                "event": ev,
                "state": broken,
            }
        load *= cfg.ramp
    return {"configuration": configuration, "method": method, "broke": False}


def run_table(cfg: Config) -> list[dict]:
    """:func:`load_test` of every configuration and method of ``cfg``."""
    out = []
    for conf in cfg.configurations.split(","):
        for method in cfg.methods.split(","):
            if method.strip() not in METHODS:
                raise SceneError(f"unknown method {method!r}; choose from {METHODS}")
            out.append(load_test(cfg, conf.strip(), method.strip()))
    return out


def markdown_table(rows: list[dict]) -> str:
    """Breakage type per configuration (rows) and method (columns)."""
    confs = list(dict.fromkeys(r["configuration"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["configuration"], r["method"]): r for r in rows}
    lines = [
        "| loading | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for c in confs:
        items = []
        for m in methods:
            r = cell.get((c, m))
            if r is None or not r["broke"]:
                items.append("no break")
            else:
                items.append(
                    f"{r['breakage_type']} ({r['n_fragments']} frag., m_r = "
                    f"{r['mass_ratio_m_r']:.2f}, F = {r['breaking_load_N']:.0f} N)"
                )
        lines.append(f"| {c} | " + " | ".join(items) + " |")
    return "\n".join(lines) + "\n"


def _figure(cfg: Config, rows: list[dict], path: Path) -> Path:
    from .. import plot

    plt = plot.plt
    confs = list(dict.fromkeys(r["configuration"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig, axes = plt.subplots(
        len(confs), len(methods), figsize=(3 * len(methods), 3 * len(confs)), squeeze=False
    )
    cell = {(r["configuration"], r["method"]): r for r in rows}
    for i, c in enumerate(confs):
        for j, m in enumerate(methods):
            ax = axes[i, j]
            r = cell.get((c, m))
            ax.set_title(f"{c} {m}", fontsize=8)
            if r is None or not r["broke"]:
                ax.text(0.5, 0.5, "no break", ha="center", transform=ax.transAxes)
                continue
            st = r["state"]
            p = st.particles
            wv = world_vertices_np(
                np.asarray(p.verts), np.asarray(p.n_verts), np.asarray(p.pos), np.asarray(p.angle)
            )
            plot.draw_particles(
                ax, wv, np.asarray(p.n_verts), np.asarray(p.radius), np.asarray(p.active)
            )
            pts = np.asarray(r["applied"]["points"])
            frc = np.asarray(r["applied"]["forces"])
            scale = 0.4 * cfg.disc_radius / np.abs(frc).max()
            for x, f in zip(pts, frc, strict=True):
                tail = (x - scale * f) * 100
                ax.annotate(
                    "", xy=x * 100, xytext=tail, arrowprops={"arrowstyle": "->", "color": "k"}
                )
            ax.set_xlabel("")
            ax.set_ylabel("")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    """Run every configuration with every method; write ``breakage_types.md`` / ``.json``,
    ``breakage_types.png`` and ``summary.json``."""
    from .. import io

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = run_table(cfg)
    md = markdown_table(rows)
    (out_dir / "breakage_types.md").write_text(md)
    plain = [{k: v for k, v in r.items() if k not in ("event", "state")} for r in rows]
    table = {
        f"{r['configuration']}/{r['method']}": r.get("breakage_type", "no break") for r in rows
    }
    (out_dir / "breakage_types.json").write_text(
        json.dumps({"table": table, "rows": plain}, indent=2, default=float)
    )
    figures = []
    try:
        figures.append(str(_figure(cfg, rows, out_dir / "breakage_types.png")))
    except Exception as exc:  # a figure must not lose the table
        figures.append(f"figure failed: {exc}")
    summary = {
        "scene": "breakage-types",
        "table": table,
        "markdown": md,
        "rows": plain,
        "figures": figures,
        "config": dataclasses.asdict(cfg),
        **environment(),
    }
    io.write_summary(out_dir / "summary.json", summary)
    return summary
