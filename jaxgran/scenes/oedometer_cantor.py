"""Oedometric compression of breakable pentagons (paper 000 §III, after Cantor et al. 2015).

About ``n_particles`` pentagon-like grains (irregular pentagons of circumdiameter
``min_diameter``-``max_diameter``, swept by ``sphero_radius``) are dropped into a container
``box_width`` wide and settle under gravity, without friction by default (``settle_friction``:
a dense pile, as in paper 000's 9 cm high container; the contact friction is back before
the loading); then a top bar (a wall in velocity mode) is put just above the pile and
moves down at ``bar_speed`` (1 mm/s) for ``load_time``, while the breakage method of
``method`` (``dsm``, ``split-cell``, ``cross-cut``, ``mohr-coulomb``,
:func:`jaxgran.breakage.averaged.make_breakage`) checks the grains between segments.

Parameters: paper 000 Table I (K_n = 6e5 N/m, K_t = 2.2e4 N/m, mu = 0.74, areal density
1.2 g/cm^2 = 12 kg/m^2, Verlet distance 2 mm, nu = 0.3), a viscous damping from a restitution
coefficient (not in Table I), and the breakage thresholds calibrated on the Brazilian test
of the paper (F = 150.79 N, r = 1 cm) at our thickness t = 1 cm. Table I's dt = 5e-4 s is
far above the explicit stability limit of the springs and dashpots
(:func:`jaxgran.integrate.critical_time_step`: about 1.2e-5 s for 1 cm pentagons and less
for their fragments); dt here is ``dt_safety`` times the limit of the particles present,
shrunk as lighter fragments appear (none lighter than ``min_fragment_fraction`` of the
mean grain mass is kept). A smaller piece merges into the neighbouring piece across its
fracture segment (``small_pieces = "merge"``; a breakage whose pieces all merge back is
suppressed and the grain stays whole), or is dropped as fines that count as lost mass
(``"fines"``). The mass a replacement loses
is then the rounding of the new corners (sphero-radius ``sphero_radius``) and the caps the
erosion clips where neighbours overlap (``erosion``); ``conserve_mass`` gives the fragments
the mass of their uneroded pieces instead (paper 000 §III). See ``docs/stability.md``.

Outputs (summary.json, run.h5 with the event log, figures): snapshots at
``snapshot_times`` after the loading starts (paper 000 Fig. 7), the relative mass, mean
speed and mean angular speed against time (Fig. 8), number and types of breakage events
(Table III), the kinetic-energy spike of each event and the mass lost.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .. import energy
from .. import geometry as geo
from ..breakage import metrics
from ..breakage.averaged import make_breakage, method_name
from ..errors import SceneError
from ..integrate import check_time_step, critical_time_step, mode_time_step_limit
from ..partition import make_grid
from ..simulate import frame_of, simulate
from ..state import (
    WALL_VELOCITY,
    box_walls,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
    wall,
)
from .base import contact_params, finished_summary, write_outputs
from .limits import Checked, Range, require_less

__all__ = ["Config", "QUICK", "SCENE", "build", "run", "simulate_test", "summarize"]

SCENE = "oedometer-cantor"


@dataclasses.dataclass(frozen=True)
class Config(Checked):
    LIMITS: ClassVar[dict] = {"n_elements": Range(8, integer=True, note="BEM elements")}

    method: str = "dsm"  # dsm, split-cell, cross-cut, mohr-coulomb
    n_particles: int = 24  # pentagons in the pile
    box_width: float = 0.10  # m
    box_height: float = 0.09  # m, container height (the bar starts at the pile top)
    min_diameter: float = 0.01  # m, circumdiameter range of the pentagons
    max_diameter: float = 0.03  # m
    # m; paper 000 does not give it. The new corners a fracture plane makes are rounded
    # by r, a loss of about r^2 (tan(a/2) - a/2) each, so r sets the mass an event loses
    # (1 mm: ~2 % of a parent per event, 0.5 mm: ~0.5 %); 0.5 mm is still twice the
    # overlap at 150 N (0.25 mm with K_n = 6e5 N/m)
    sphero_radius: float = 0.5e-3
    irregularity: float = 0.12  # random perturbation of the pentagon's angles and radii
    normal_stiffness: float = 6.0e5  # N/m, Table I
    tangential_stiffness: float = 2.2e4  # N/m, Table I
    friction: float = 0.74  # Table I
    areal_density: float = 12.0  # kg/m^2, Table I (1.2 g/cm^2)
    poisson_ratio: float = 0.3  # Table I
    thickness: float = 0.01  # m
    restitution: float = 0.3  # sets G_n, G_t (not in Table I)
    skin: float = 2.0e-3  # m, Table I Verlet distance
    calibration_force: float = 150.79  # N, Brazilian breaking force (paper 000 §III)
    calibration_radius: float = 0.01  # m
    min_fragment_fraction: float = 0.05  # fragments lighter than this x mean mass: fines
    # x the stability limit (springs and dashpots) of the particles present: several
    # contacts stiffen and damp a grain more than the one-contact limit assumes; 0.4 keeps
    # the linearised step of the settled and the loaded quick piles at 0.43 and 0.70 of its
    # stability limit (benchmarks/LINEAR_STABILITY_RESULTS.md)
    dt_safety: float = 0.4
    settle_time: float = 0.6  # s, at most, under gravity before loading
    # Coulomb coefficient of grains and walls while the pile settles (nan: ``friction``),
    # ``friction`` is restored for the loading. Settled at 0 the pile is dense (solid
    # fraction 0.68-0.72 under the bar, 7.7-9.6 cm high: paper 000's 10 cm x 9 cm
    # container) and grains break after 1.5-2.5 s of loading; settled at 0.74 it stands
    # loose (0.55-0.58, up to 11.7 cm) and shifts under the bar for 4-8.5 s first
    # (docs/stability.md, "Frictionless settling")
    settle_friction: float = 0.0
    settle_ke_ratio: float = 1.0e-4  # settled when KE < this x its peak
    bar_gap: float = 5.0e-4  # m, bar above the highest grain when loading starts
    bar_speed: float = 1.0e-3  # m/s
    # s; paper 000's figures reach 2.4 s, and the densely settled pile's first grains break
    # at 1.5-2.5 s (seeds 0-2). The loosely settled pile (settle_friction = nan) needs
    # about 11 s: its first grains broke at 4.0-8.5 s
    load_time: float = 4.0
    snapshot_times: tuple = (0.0, 0.9, 1.1, 2.4, 4.0)  # s after loading starts
    record_every: int = 100
    records_per_segment: int = 10
    n_elements: int = 64  # DSM BEM elements
    n_points: int = 200  # DSM BEM sample points
    # DSM screening: bound (the proven psi bound, misses nothing) or force (largest
    # neighbour force >= half the Brazilian load of the grain's area, a heuristic that
    # missed 5 of the 15 breakages of the default run, docs/stability.md)
    screen: str = "bound"
    # fragments' erosion: local, local-axis, uniform, none (docs/stability.md)
    erosion: str = "local"
    # pieces below min_fragment_fraction: merge (into a neighbour piece) or fines (lost)
    small_pieces: str = "merge"
    # fragments keep their uneroded piece's mass (density compensation, paper 000 §III)
    conserve_mass: bool = False
    # floor of the fragments' adaptive sphero-radius, a fraction of sphero_radius: each
    # fragment takes the largest radius between it and its parent's whose corner rounding
    # keeps 99.9 % of its piece (slivers keep their tips); 0: fragments keep the parent's
    fragment_radius_floor: float = 0.0
    # particle slots at the start, as a multiple of n_particles: fragments fill free slots,
    # and each growth of the capacity recompiles the jitted segment and the DSM's kernels
    # (inactive slots cost next to nothing per step)
    capacity_factor: float = 2.0
    # vertex slots at the start (0: the largest pentagon's). Fragments with more vertices
    # grow it; a larger V makes every contact step dearer (V x V features per pair)
    vertex_capacity: int = 0
    seed: int = 0

    def relations(self) -> None:
        require_less(self, "min_diameter", "max_diameter")


QUICK = {
    "n_particles": 4,
    "box_width": 0.045,
    "min_diameter": 0.016,
    "max_diameter": 0.02,
    "min_fragment_fraction": 0.1,
    "settle_time": 0.15,
    "bar_speed": 0.1,
    "load_time": 0.04,
    "snapshot_times": (0.0, 0.01, 0.02, 0.04),
    "records_per_segment": 5,
    # the quick pile breaks into about 12 pieces with up to 9 vertices: start there, so the
    # test compiles once instead of at every growth
    "capacity_factor": 4.0,
    "vertex_capacity": 10,
}


def adaptive_dt(particles, params, safety: float) -> float:
    """Time step (s) for the particles present now: ``safety`` x their stability limit
    (:func:`jaxgran.integrate.critical_time_step`: the springs of the lightest, the
    dashpots at the largest lever arm). The scenes start with the
    intact grains' step and shrink it when a breakage creates a lighter fragment (dt is a
    traced parameter, so this never recompiles)."""
    return safety * critical_time_step(particles, params)


def smallest_dt(cfg, mean_mass: float, params) -> float:
    """Lower bound (s) on the adaptive step, used to size the step budget of the loading
    stage: ``dt_safety`` x the limit of :func:`jaxgran.integrate.critical_time_step` for the
    lightest fragment kept (``min_fragment_fraction`` x the mean grain mass ``m``) taken
    as a sliver, ``m l^2 / I`` = 8 (a thin triangle; a regular pentagon has 2.6): springs
    ``Omega^2 = 2 K_n / (m / 8)``, dashpots ``Gamma = 9 max(G_n, G_t)`` of ``params``."""
    lever = 8.0
    m_rot = cfg.min_fragment_fraction * mean_mass / lever
    omega2 = 2.0 * cfg.normal_stiffness / m_rot
    gamma = (1.0 + lever) * max(float(params.normal_damping), float(params.tangential_damping))
    return cfg.dt_safety * mode_time_step_limit(omega2, gamma)


def pentagons(cfg: Config) -> list[np.ndarray]:
    """Irregular pentagon cores (m) on a loose lattice above the container floor."""
    rng = np.random.default_rng(cfg.seed)
    r = cfg.sphero_radius
    per_row = max(1, int(cfg.box_width // (cfg.max_diameter + 2e-3)))
    pitch = cfg.box_width / per_row
    out, y = [], 0.0
    k = 0
    while k < cfg.n_particles:
        ds = rng.uniform(cfg.min_diameter, cfg.max_diameter, per_row)
        row_h = float(ds.max()) + 2e-3
        for c in range(per_row):
            if k >= cfg.n_particles:
                break
            big = 0.5 * ds[c] - r
            ang = 2 * np.pi * np.arange(5) / 5 + rng.uniform(-1, 1, 5) * cfg.irregularity
            ang += rng.uniform(0, 2 * np.pi)
            rad = big * (1 - cfg.irregularity * rng.uniform(0, 1, 5))
            poly = np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
            poly = poly * (big / geo.circumradius(poly - geo.polygon_centroid(poly)))
            centre = np.array([(c + 0.5) * pitch, y + 0.5 * row_h + r + 1e-3])
            out.append(geo.validate_polygon(poly - geo.polygon_centroid(poly) + centre))
            k += 1
        y += row_h
    return out


def build(cfg: Config):
    """Initial state (grains in the air, bar parked above them), parameters and grid."""
    cores = pentagons(cfg)
    parts = particles_from_polygons(
        cores,
        cfg.sphero_radius,
        cfg.areal_density,
        capacity=max(len(cores), math.ceil(cfg.capacity_factor * len(cores))),
        vertex_capacity=max([len(c) for c in cores] + [cfg.vertex_capacity]),
    )
    active = np.asarray(parts.active)
    m = np.asarray(parts.mass)[active]
    m_mean = float(m.mean())
    params = contact_params(cfg, m_mean, poisson_ratio=cfg.poisson_ratio)
    params = replace(
        params, dt=jnp.asarray(adaptive_dt(parts, params, cfg.dt_safety), params.dt.dtype)
    )
    check_time_step(parts, params)
    pos = np.asarray(parts.pos)
    top = float(pos[:, 1].max() + np.asarray(parts.bound_radius).max()) + 0.01
    height = max(top, cfg.box_height)
    walls = box_walls((0.0, 0.0), (cfg.box_width, height), top=False)
    walls.append(wall((0.0, height), (0.0, -1.0), mode=WALL_VELOCITY, length=cfg.box_width))
    state = make_state(parts, make_walls(walls))
    rmax = float(np.asarray(parts.bound_radius).max())
    grid = make_grid((-0.02, -0.02), (cfg.box_width + 0.02, height + 0.03), rmax, cfg.skin)
    return state, params, grid


def _pile_top(state) -> float:
    p = state.particles
    act = np.asarray(p.active)
    pos = np.asarray(p.pos)[act]
    wv = np.asarray(p.verts)[act]
    a = np.asarray(p.angle)[act]
    c, s = np.cos(a)[:, None], np.sin(a)[:, None]
    y = pos[:, 1:2] + s * wv[..., 0] + c * wv[..., 1]
    n = np.asarray(p.n_verts)[act]
    y = np.where(np.arange(wv.shape[1])[None] < n[:, None], y, -np.inf)
    return float((y.max(axis=1) + np.asarray(p.radius)[act]).max())


def simulate_test(
    cfg,
    *,
    progress: bool = False,
    build_fn=None,
    energy_ledger: bool = False,
    checkpoint: str | Path | None = None,
    checkpoint_every_s: float = 600.0,
    resume: bool = False,
):
    """Settle, then load with breakage. Returns ``(settle_result, load_result, breakage,
    info)``; ``info`` holds snapshots, the initial mass and timing. ``build_fn(cfg) ->
    (state, params, grid)`` (default :func:`build`) must put the top bar last among the walls;
    ``cfg`` needs the fields of :class:`Config` used here.

    ``energy_ledger``: attach a :mod:`jaxgran.energy` ledger when the loading starts, book
    what each replacement removes (:func:`jaxgran.energy.account_host_change`) and return
    the balance after every segment in ``info["energy"]`` (a list of dicts, J).

    ``checkpoint``: a file (pickle) that receives everything the loading needs to go on
    (state, breakage handler with its event log, snapshots, series so far) every
    ``checkpoint_every_s`` seconds of wall time during the loading; with ``resume`` an
    existing file of the same configuration is continued from
    (:func:`jaxgran.io.load_checkpoint`), and the result is that of the uninterrupted run.
    The file is left in place; ``run`` deletes it once the outputs are written."""
    _min_radius(cfg)  # a bad floor fails here, not after the settling
    key = checkpoint_key(cfg, build_fn)
    saved = None
    if resume and checkpoint is not None and Path(checkpoint).exists():
        from .. import io

        saved = io.load_checkpoint(checkpoint, key)
        _check_precision(saved.get("x64", True), checkpoint)
    if saved is None:
        settle, ctx, s0 = _settle_and_arm(cfg, build_fn, progress, energy_ledger)
    else:
        settle, ctx, s0 = saved["settle"], saved["context"], None
        # a checkpoint of a run whose vertex capacity grew by a factor (before exact growth)
        # steps at the capacity its particles need, but no lower than the configured start,
        # so that a resumed run has the uninterrupted run's shapes (and compilations): a
        # numerical no-op (fit_vertex_capacity)
        from ..breakage.replace import fit_vertex_capacity

        saved["simulate"]["state"] = fit_vertex_capacity(
            saved["simulate"]["state"], minimum=getattr(cfg, "vertex_capacity", 0)
        )
    brk, t0, m_mean = ctx["brk"], ctx["t0"], ctx["m_mean"]

    def step_callback(s, rec):
        before = s
        s, stop = brk(s, rec)
        if energy_ledger:
            if s is not before:
                s = energy.account_host_change(before, s, ctx["params"])
            ctx["balances"].append({"time": float(s.time), **energy.balance(s, ctx["params"])})
        t_load = float(s.time) - t0
        prm = ctx["params"]
        if len(brk.events) > ctx["n_events"]:
            ctx["n_events"] = len(brk.events)
            new_dt = adaptive_dt(s.particles, prm, cfg.dt_safety)
            if new_dt < float(prm.dt):
                prm = replace(prm, dt=jnp.asarray(new_dt, prm.dt.dtype))
                brk.params = replace(brk.params, dt=prm.dt)
                ctx["params"] = prm
                ctx["dt_log"].append((t_load, new_dt))
        step_dt = float(prm.dt)
        pending = ctx["pending"]
        while pending and t_load >= pending[0] - 0.5 * step_dt * cfg.record_every:
            ctx["snaps"].append({"t_load": t_load, "target": pending.pop(0), **frame_of(s)})
        done = t_load >= cfg.load_time - 0.5 * step_dt
        return s, stop or done, prm

    save = None
    if checkpoint is not None:
        from .. import io

        def save(payload):
            io.save_checkpoint(
                checkpoint,
                key,
                {"settle": settle, "context": ctx, "simulate": payload, "x64": _x64()},
            )

    params0 = ctx["params0"]
    load = simulate(
        s0 if s0 is not None else saved["simulate"]["state"],
        params0,
        brk.grid,
        n_steps=int(
            math.ceil(cfg.load_time / min(float(params0.dt), smallest_dt(cfg, m_mean, params0)))
        ),
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        frame_every=10,
        callback=step_callback,
        progress=progress,
        desc=f"oedometer {cfg.method}",
        checkpoint=save,
        checkpoint_every_s=checkpoint_every_s,
        resume=None if saved is None else saved["simulate"],
    )
    snaps = ctx["snaps"]
    snaps[0]["target"] = 0.0
    info = {
        "snapshots": snaps,
        "initial_mass": ctx["mass0"],
        "initial_area": ctx["area0"],
        "mean_initial_mass": ctx["m_mean"],
        "load_start_time": t0,
        "bar_start_y": ctx["y_bar"],
        "dt_log": ctx["dt_log"],
        "forked_from": ctx.get("forked_from"),
    }
    if energy_ledger:
        info["energy"] = ctx["balances"]
    return settle, load, brk, info


def _x64() -> bool:
    import jax

    return bool(jax.config.jax_enable_x64)


def _check_precision(saved_x64: bool, path) -> None:
    """A checkpoint continues only in its own precision (unpickled float64 arrays would be
    cast to float32 without a word)."""
    if bool(saved_x64) != _x64():
        want = "float64 (without --float32)" if saved_x64 else "float32 (--float32)"
        raise SceneError(f"{path}: the checkpoint was written in {want}; resume it so")


def checkpoint_key(cfg, build_fn=None) -> dict:
    """What a checkpoint of :func:`simulate_test` must match to be continued: the whole
    configuration and the scene that built the packing."""
    build_name = None if build_fn is None else f"{build_fn.__module__}.{build_fn.__qualname__}"
    return {"config": dataclasses.asdict(cfg), "build": build_name}


def checkpointed_test(cfg, out_dir: Path, progress, checkpoint_minutes, resume, build_fn=None):
    """:func:`simulate_test` with the checkpoints of ``run``: ``(path or None, result)``."""
    ckpt = checkpoint_path(out_dir, checkpoint_minutes)
    return ckpt, simulate_test(
        cfg,
        progress=progress,
        build_fn=build_fn,
        checkpoint=ckpt,
        checkpoint_every_s=60.0 * checkpoint_minutes,
        resume=resume,
    )


def checkpoint_path(out_dir: Path, minutes: float) -> Path | None:
    """``out_dir/checkpoint.pkl``, or None when ``minutes`` is 0 (no checkpoints)."""
    if not (math.isfinite(minutes) and minutes >= 0.0):
        raise SceneError(f"checkpoint_minutes must be finite and >= 0, got {minutes}")
    return Path(out_dir) / "checkpoint.pkl" if minutes > 0 else None


def _settle_and_arm(cfg, build_fn, progress: bool, energy_ledger: bool):
    """The settling, then the top bar put above the pile and the breakage handler made:
    ``(settle_result, context, loading_state)``; the context holds what the loading's
    callback keeps between segments (all of it goes into a checkpoint)."""
    state, params, grid = (build_fn or build)(cfg)
    dt = float(params.dt)
    peak = [0.0]
    settle_params = settling_params(cfg, params)

    def settled(s, rec):
        ke = rec["kinetic_energy"]
        peak[0] = max(peak[0], float(ke.max()))
        return s, bool(float(rec["time"][-1]) > 0.1 and ke[-1] <= cfg.settle_ke_ratio * peak[0])

    def stage(s, prm, g, desc):
        return simulate(
            s,
            prm,
            g,
            n_steps=int(math.ceil(cfg.settle_time / dt)),
            record_every=cfg.record_every,
            records_per_segment=cfg.records_per_segment,
            frame_every=10**9,
            callback=settled,
            progress=progress,
            desc=desc,
        )

    settle = stage(state, settle_params, grid, "oedometer settle")
    if settle_params is not params:
        # frictionless grains come to rest slowly (only the normal dashpots damp a
        # sliding grain); with the contact friction back the pile stops in a few ms
        rest = stage(settle.state, params, settle.grid, "oedometer settle (contact friction)")
        settle = dataclasses.replace(
            rest,
            steps=settle.steps + rest.steps,
            wall_time_s=settle.wall_time_s + rest.wall_time_s,
            regrows=list(settle.regrows) + list(rest.regrows),
        )
    s0 = settle.state
    w = s0.walls
    bar = int(w.point.shape[0]) - 1
    y_bar = _pile_top(s0) + cfg.bar_gap
    point = w.point.at[bar, 1].set(y_bar)
    vel = w.vel.at[bar].set(jnp.array([0.0, -cfg.bar_speed]))
    s0 = replace(s0, walls=replace(w, point=point, vel=vel))
    p0 = s0.particles
    act0 = np.asarray(p0.active)
    m_mean = float(np.asarray(p0.mass)[act0].mean())
    brk = _make_handler(cfg, params, settle.grid, m_mean)
    if energy_ledger:
        s0 = energy.attach(s0, params, settle.grid)
    ctx = {
        "brk": brk,
        "t0": float(s0.time),
        "params0": params,
        "params": params,
        "n_events": 0,
        "snaps": [{"t_load": 0.0, **frame_of(s0)}],
        "pending": [t for t in sorted(cfg.snapshot_times) if t > 0],
        "dt_log": [(0.0, dt)],
        "balances": [],
        "mass0": float(np.asarray(p0.mass)[act0].sum()),
        "area0": _total_area(p0),
        "m_mean": m_mean,
        "y_bar": y_bar,
    }
    return settle, ctx, s0


def settling_params(cfg, params):
    """``params`` with the grains' and walls' Coulomb coefficient set to
    ``cfg.settle_friction`` for the settling (unchanged where it is nan or absent). The
    settling then ends with the contact friction, until the pile is at rest by
    ``settle_ke_ratio`` (the ``series`` of the settling result are that last stage's)."""
    mu = float(getattr(cfg, "settle_friction", math.nan))
    if math.isnan(mu):
        return params
    return replace(
        params,
        friction=jnp.full_like(params.friction, mu),
        wall_friction=jnp.full_like(params.wall_friction, mu),
    )


def _make_handler(cfg, params, grid, m_mean: float):
    """The breakage handler of ``cfg.method`` for a packing of mean grain mass ``m_mean``
    (kg), with the strengths of the Brazilian calibration and the scene's options."""
    return make_breakage(
        cfg.method,
        params,
        grid,
        calibration_force=cfg.calibration_force,
        calibration_radius=cfg.calibration_radius,
        thickness=cfg.thickness,
        poisson_ratio=cfg.poisson_ratio,
        min_area=cfg.min_fragment_fraction * m_mean / cfg.areal_density,
        mean_initial_mass=m_mean,
        dsm_options={"n_elements": cfg.n_elements, "n_points": cfg.n_points, "screen": cfg.screen},
        erosion=cfg.erosion,
        small_pieces=cfg.small_pieces,
        conserve_mass=cfg.conserve_mass,
        min_radius=_min_radius(cfg),
    )


def fork_checkpoint(src, dst, cfg_src, cfg_dst, build_fn=None) -> dict:
    """Start the run of ``cfg_dst`` from the checkpoint ``src`` of the run of ``cfg_src``:
    writes ``dst``, which :func:`simulate_test` with ``resume=True`` continues. Returns
    ``{"method", "t_load", "wall_time_s"}`` of the source at the fork (kept in the summary as
    ``forked_from``; the run's wall time includes the source's).

    The configurations may differ in ``method`` alone, and the source must not have broken
    a grain yet: up to the first breakage the methods only evaluate their criteria, so every
    method's run is the source's run up to there (the test checks it bit for bit), and the
    comparison of methods starts from one packing and one loaded state even where the
    settling is not reproducible (GPU sums are not ordered). Raises ``ValueError``
    otherwise."""
    from .. import io

    if dataclasses.replace(cfg_dst, method=cfg_src.method) != cfg_src:
        raise SceneError("fork_checkpoint: the configurations differ in more than the method")
    saved = io.load_checkpoint(src, checkpoint_key(cfg_src, build_fn))
    ctx = dict(saved["context"])
    if ctx["brk"].events or ctx["n_events"]:
        raise SceneError(
            f"fork_checkpoint: {src} has {len(ctx['brk'].events)} breakage events; runs of "
            "other methods share only the stretch before the first breakage"
        )
    t_load = float(saved["simulate"]["state"].time) - float(ctx["t0"])
    origin = {
        "method": cfg_src.method,
        "t_load": t_load,
        "wall_time_s": float(saved["simulate"]["wall_time_s"]),
    }
    ctx["brk"] = _make_handler(cfg_dst, ctx["params0"], saved["settle"].grid, ctx["m_mean"])
    ctx["forked_from"] = origin
    payload = dict(saved, context=ctx)
    io.save_checkpoint(dst, checkpoint_key(cfg_dst, build_fn), payload)
    return origin


def checkpoint_progress(path) -> dict:
    """How far the loading of a :func:`simulate_test` checkpoint has got (for ``jaxgran
    progress``): method, loading time done and asked (s), breakage events, suppressed
    decisions, particles, the current dt (s), wall time so far (s) and where the run was
    forked from. Reads the file without checking its configuration against any run (only
    the format); unpickles, so read only your own files."""
    from .. import io

    key, pay = io.read_checkpoint(path)
    cfg = key["config"]
    ctx, sim = pay["context"], pay["simulate"]
    t_load = float(sim["state"].time) - float(ctx["t0"])
    brk = ctx["brk"]
    return {
        "scene": key.get("build") or SCENE,
        "method": cfg["method"],
        "t_load_s": t_load,
        "load_time_s": float(cfg["load_time"]),
        "done_fraction": t_load / float(cfg["load_time"]),
        "bar_speed_m_s": float(cfg["bar_speed"]),
        "events": len(brk.events),
        "suppressed": len(getattr(brk, "suppressed", [])),
        "particles": int(np.asarray(sim["state"].particles.active).sum()),
        "dt_s": float(ctx["params"].dt),
        "wall_time_s": float(sim["wall_time_s"]),
        "forked_from": ctx.get("forked_from"),
        "x64": bool(pay.get("x64", True)),
    }


def _min_radius(cfg) -> float | None:
    """Floor (m) of the fragments' adaptive sphero-radius, None when they keep the parent's."""
    f = float(getattr(cfg, "fragment_radius_floor", 0.0))  # [0, 1]: Config checks it
    return None if f == 0.0 else f * cfg.sphero_radius


def _total_area(p) -> float:
    """Area (m^2) of the active spheropolygons of ``p``."""
    verts, nv, rad = np.asarray(p.verts), np.asarray(p.n_verts), np.asarray(p.radius)
    return float(
        sum(
            geo.spheropolygon_mass_properties(verts[k, : nv[k]], float(rad[k]), 1.0)[0]
            for k in np.flatnonzero(np.asarray(p.active))
        )
    )


def relative_mass(times: np.ndarray, events: list[dict], mass0: float) -> np.ndarray:
    """Total mass / initial mass at ``times`` (s) from the events' ``mass_lost`` (kg)."""
    te = np.array([float(e["time"]) for e in events])
    lost = np.array([float(e["mass_lost"]) for e in events])
    cum = np.array([lost[te <= t].sum() for t in np.asarray(times, float)])
    return 1.0 - cum / mass0


def summarize(settle, load, brk, info, cfg) -> dict:
    ev = brk.events
    p = load.state.particles
    act = np.asarray(p.active)
    mass_final = float(np.asarray(p.mass)[act].sum())
    mass0 = info["initial_mass"]
    lost = float(sum(float(e["mass_lost"]) for e in ev))
    series = load.series
    t0 = info["load_start_time"]
    window = max(0.05 * cfg.load_time, 20 * cfg.record_every * float(info["dt_log"][-1][1]))
    t_ev = [float(e["time"]) for e in ev]
    spikes = metrics.kinetic_energy_spikes(
        series["time"], series["kinetic_energy"], t_ev, window=window
    )
    speed_spikes = metrics.kinetic_energy_spikes(
        series["time"], series["mean_speed"], t_ev, window=window
    )
    quiet = metrics.quiet_speeds(
        series["time"], series["mean_speed"], t_ev, window=window, limit=cfg.bar_speed
    )
    pos = np.asarray(p.pos)[act]
    w = load.state.walls
    escaped = bool(
        np.any(pos[:, 0] < 0)
        or np.any(pos[:, 0] > cfg.box_width)
        or np.any(pos[:, 1] < 0)
        or np.any(pos[:, 1] > float(w.point[-1, 1]))
    )
    types = metrics.breakage_type_percentages(ev, info["mean_initial_mass"])
    return {
        "method": method_name(brk),
        "n_particles_initial": int(np.asarray(settle.state.particles.active).sum()),
        "n_particles_final": int(act.sum()),
        "dt_s": float(info["dt_log"][0][1]),
        "dt_final_s": float(info["dt_log"][-1][1]),
        "dt_changes": [[float(t), float(d)] for t, d in info["dt_log"]],
        "dt_table_I_s": 5.0e-4,
        "dt_note": "Table I's 5e-4 s exceeds the stability limit of the springs and dashpots "
        "(jaxgran.integrate.critical_time_step); dt here is dt_safety x the limit of the "
        "particles present, shrunk after each "
        "breakage that creates a lighter fragment (dt_changes: [t_load s, dt s])",
        "settle_time_s": float(settle.state.time),
        "settled": bool(settle.stopped_early),
        "load_time_s": float(load.state.time) - t0,
        "bar_travel_m": float(info["bar_start_y"] - float(w.point[-1, 1])),
        "bar_force_final_N": float(abs(series["wall_force"][-1, -1, 1])),
        "bar_force_max_N": float(np.abs(series["wall_force"][:, -1, 1]).max()),
        "steps": int(settle.steps + load.steps),
        "wall_time_s": float(settle.wall_time_s + load.wall_time_s),
        "forked_from": info.get("forked_from"),
        "n_events": len(ev),
        "breakage_types": types,
        "mean_initial_mass_kg": info["mean_initial_mass"],  # Table III's reference mass
        "mass_lost_kg": lost,
        "mass_lost_fraction": lost / mass0,
        "mass_fines_fraction": sum(float(e["fines_mass"]) for e in ev) / mass0,
        "mass_eroded_fraction": sum(float(e["eroded_mass"]) for e in ev) / mass0,
        # the eroded mass split: the erosion clear of the neighbours (paper 000 Fig. 6's
        # loss) and the rounding of the new corners (jaxgran.breakage.replace); None for
        # events resumed from a checkpoint written before the split was logged
        "mass_caps_fraction": _event_sum(ev, "caps_mass", mass0),
        "mass_rounding_fraction": _event_sum(ev, "rounding_mass", mass0),
        "small_pieces": cfg.small_pieces,
        "conserve_mass": cfg.conserve_mass,
        "fragment_radius_floor": cfg.fragment_radius_floor,
        "area_lost_fraction": sum(float(e["area_lost"]) for e in ev) / info["initial_area"],
        "n_pieces_merged": int(sum(int(e.get("n_merged", 0)) for e in ev)),
        "n_suppressed": len(getattr(brk, "suppressed", [])),
        # particles that passed the screening / were solved by the BEM, over all checks
        "n_screened": int(getattr(brk, "n_screened", 0)),
        "n_solved": int(getattr(brk, "n_checked", 0)),
        "mass_bookkeeping_error": abs((mass0 - lost) - mass_final) / mass0,
        "ke_spikes": spikes,
        # the same measure on the mean speed (m/s): peak and 1/e decay time per event
        "speed_spikes": speed_spikes,
        # mean speed (m/s) of the loading records at least `spike_window_s` after any event
        "quiet_speed": quiet,
        "spike_window_s": window,
        "escaped": escaped,
        "finite": bool(np.all(np.isfinite(np.asarray(p.pos)[act]))),
        "fracture_planes": {
            k: v.tolist() if hasattr(v, "tolist") else v
            for k, v in metrics.fracture_plane_histogram(ev).items()
        },
        "locking": metrics.locking_effect(ev),
        "snapshot_times_s": [float(s["t_load"]) for s in info["snapshots"]],
        "regrows": list(settle.regrows) + list(load.regrows) + brk.log,
        "strengths": brk.strengths() if hasattr(brk, "strengths") else {"eps_Pa": brk.eps},
    }


def _event_sum(events, key: str, scale: float) -> float | None:
    """Sum of ``key`` over ``events`` divided by ``scale``; None if an event lacks it."""
    if any(key not in e for e in events):
        return None
    return sum(float(e[key]) for e in events) / scale


def figures(load, brk, info, cfg, out_dir: Path) -> list[str]:
    """Snapshots (paper 000 Fig. 7), the relative mass / speeds (Fig. 8) and the force-chain
    map of the final state (Fig. 17: ``I = sigma_1 - sigma_2`` from each grain's BEM field,
    :mod:`jaxgran.breakage.photoelastic`), whose statistics go to
    ``info["force_chains"]``."""
    from .. import plot
    from ..breakage import photoelastic
    from ..io import world_vertices_np

    plt = plot.plt
    out = []
    t_end = float(load.state.time) - info["load_start_time"]
    try:
        field = photoelastic.force_chain_field(
            load.state,
            load.params,
            poisson_ratio=cfg.poisson_ratio,
            thickness=cfg.thickness,
            n_elements=cfg.n_elements,
        )
    except (ValueError, RuntimeError) as err:  # a diagnostic must not lose a finished run
        info["force_chains"] = {"t_load_s": t_end, "error": str(err)}
        field = None
    if field is not None:
        path = photoelastic.plot_force_chain_field(
            load.state,
            field,
            Path(out_dir) / "force_chains.png",
            title=f"{cfg.method}: I = sigma_1 - sigma_2 at t = {t_end:.2f} s (BEM field)",
        )
        out.append(str(path))
        i_kpa = field["intensity"] / 1e3
        info["force_chains"] = {
            "t_load_s": t_end,
            "n_loaded_particles": int(field["n_loaded"]),
            "n_skipped": len(field["skipped"]),
            "skipped": [f"slot {k}: {why}" for k, why in field["skipped"][:10]],
            "n_points": int(i_kpa.size),
            "I_median_kPa": float(np.median(i_kpa)) if i_kpa.size else 0.0,
            "I_p99_kPa": float(np.percentile(i_kpa, 99)) if i_kpa.size else 0.0,
            "I_max_kPa": float(i_kpa.max()) if i_kpa.size else 0.0,
        }
    snaps = info["snapshots"]
    fig, axes = plt.subplots(1, len(snaps), figsize=(3.2 * len(snaps), 3.4), squeeze=False)
    uid0 = set(np.asarray(snaps[0]["uid"])[np.asarray(snaps[0]["active"])].tolist())
    for ax, s in zip(axes[0], snaps, strict=True):
        wv = world_vertices_np(s["verts"], s["n_verts"], s["pos"], s["angle"])
        new = np.array([u not in uid0 for u in np.asarray(s["uid"]).tolist()], float)
        walls = {
            "point": s["wall_point"],
            "normal": np.asarray(load.state.walls.normal),
            "extent": np.asarray(load.state.walls.extent),
        }
        plot.draw_particles(
            ax,
            wv,
            s["n_verts"],
            s["radius"],
            s["active"],
            values=new,
            cmap="coolwarm",
            walls=walls,
            colorbar=False,
        )
        ax.set_title(f"t = {s['t_load']:.2f} s", fontsize=9)
    fig.tight_layout()
    path = Path(out_dir) / "snapshots.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    out.append(str(path))
    series = load.series
    t = series["time"] - info["load_start_time"]
    rel = relative_mass(series["time"], brk.events, info["initial_mass"])
    out.append(
        str(
            plot.plot_series(
                t, {"relative mass": rel}, "t (s)", "M / M0", Path(out_dir) / "relative_mass.png"
            )
        )
    )
    out.append(
        str(
            plot.plot_series(
                t,
                {
                    "mean speed (m/s)": series["mean_speed"],
                    "mean angular speed (rad/s)": series["mean_angular_speed"],
                },
                "t (s)",
                "speed",
                Path(out_dir) / "speeds.png",
                logy=True,
            )
        )
    )
    return out


def run(
    cfg: Config,
    out_dir: Path,
    *,
    progress: bool = True,
    vtk: bool = False,
    checkpoint_minutes: float = 10.0,
    resume: bool = False,
) -> dict:
    """Run the test and write its outputs to ``out_dir``. During the loading the run is
    saved to ``out_dir/checkpoint.pkl`` every ``checkpoint_minutes`` (0: never); with
    ``resume`` a run interrupted after such a save goes on from it (same configuration
    only), and gives the outputs of the uninterrupted run; if that run already finished in
    ``out_dir`` (its summary.json has this configuration), its summary is returned as it is.
    The checkpoint is deleted at the end."""
    out_dir = Path(out_dir)
    done = finished_summary(out_dir, SCENE, cfg) if resume else None
    if done is not None:
        return done
    ckpt, (settle, load, brk, info) = checkpointed_test(
        cfg, out_dir, progress, checkpoint_minutes, resume
    )
    summary = summarize(settle, load, brk, info, cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    figs = figures(load, brk, info, cfg, out_dir)
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
