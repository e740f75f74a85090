"""Bonded Brazilian test: a Voronoi disc of bonded cells split between two platens
(paper 002 §3).

A disc of diameter D = 10 cm is tessellated into ``n_cells`` Voronoi cells (default 800,
QUICK 150) bonded across their shared edges (paper 002 Eq. 11-15) with the Table-1-like 2D
material of :mod:`jaxgran.scenes.bonded` (plane stress, slab thickness T = 1 cm stated in
``thickness``). Two frictional platens (walls moving at a constant speed, strain control)
close on it at ``strain_rate x D`` in total; there is no gravity. The run stops once the
force has fallen below ``drop_fraction x F_max`` after the peak (or at ``max_strain``).

Reported: F_max (N), the axial strain at the peak, sigma_t = 2 F_max / (pi D T) (Eq. 16), the
slope S = 2 F(eps_max / 2) / (eps_max T) (Eq. 17) and S / K_n, the linearity (R^2) of the
rising branch, the broken bonds (count, time series, crack pattern figure), the crack angle
(principal axis of the broken-bond midpoints, from the loading diameter), the burst-size
exponent (maximum likelihood, :func:`jaxgran.analysis.power_law_mle`) and the onset of the
avalanche at the peak. With ``realisations = K > 1`` K discs of different Voronoi seeds run
under ``jax.vmap`` and every figure is reported as mean and standard deviation.

:func:`sweep` runs the calibration curves of paper 002 Fig. 8 / Eq. 18 (sigma_t / B_n
against B_n / B_t for several eps_th) as one vmapped batch over the parameters (the bond
moduli and thresholds are per-bond arrays of the stacked states), and
:func:`sweep_stiffness` those of Fig. 9 / Eq. 19 (S / K_n against K_n / K_t for several
B_n / B_t), where the contact law's :class:`jaxgran.state.Params` are stacked as well
(``params_batched``).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .. import analysis as an
from .. import ensemble as ens
from ..errors import SceneError
from ..state import WALL_VELOCITY, wall
from . import bonded as bd
from .base import write_outputs

SCENE = "bonded-brazilian"


@dataclasses.dataclass(frozen=True)
class Config(bd.Material):
    """Scene settings after the material ones of :class:`jaxgran.scenes.bonded.Material`
    (paper 002 Table 1, SI units)."""

    diameter: float = 0.10  # m, D
    n_cells: int = 800  # Voronoi cells
    seed: int = 0  # Voronoi seed of realisation 0 (realisation k uses seed + k)
    realisations: int = 1  # K > 1: K seeds under jax.vmap, mean +- std reported
    lloyd_iterations: int = 2
    strain_rate: float = 20.0  # 1/s, closing speed of the two platens / D (10/s: F_max -3 %)
    max_strain: float = 0.08  # stop here at the latest
    drop_fraction: float = 0.3  # stop once F < this x F_max after the peak
    dt_safety: float = 0.5  # fraction of the Gershgorin stability bound (bonded.stable_dt)
    skin_fraction: float = 0.1  # Verlet skin / mean cell size
    record_every: int = 100  # steps per record (also the burst window)
    records_per_segment: int = 10


QUICK = {"n_cells": 150, "record_every": 50}


def n_boundary_for(n_cells: int) -> int:
    """Vertices of the disc's boundary polygon: about one per boundary cell, a multiple of 4
    (a vertex at each pole, where the platens touch)."""
    return max(16, 4 * int(math.ceil(0.9 * math.sqrt(math.pi * n_cells))))


@dataclasses.dataclass
class Setup:
    """What :func:`build` returns: one state per realisation (common shapes), shared
    parameters and grid, and the initial platen gap of each realisation (m)."""

    states: list
    params: object
    grid: object
    controls: list
    gap0: list[float]
    material: bd.Material


def _platens(spec: bd.Specimen, diameter: float, speed: float):
    r = spec.sphero_radius
    ys = np.concatenate([c[:, 1] for c in spec.cores])
    bottom, top = float(ys.min()) - r, float(ys.max()) + r
    walls = [
        wall((0.0, bottom), (0.0, 1.0), velocity=(0.0, speed), mode=WALL_VELOCITY, length=diameter),
        wall((0.0, top), (0.0, -1.0), velocity=(0.0, -speed), mode=WALL_VELOCITY, length=diameter),
    ]
    return walls, top - bottom


def build(cfg: Config, seeds: list[int] | None = None, materials=None) -> Setup:
    """States of the discs of ``seeds`` (default ``seed .. seed + realisations - 1``) padded to
    common capacities, or of one disc with each of ``materials`` (a parameter sweep)."""
    mat = bd.material_from(cfg)
    if seeds is None:
        seeds = [cfg.seed + k for k in range(max(1, cfg.realisations))]
    mats = list(materials) if materials is not None else [mat] * len(seeds)
    if len(seeds) == 1 and len(mats) > 1:
        seeds = seeds * len(mats)
    if len(seeds) != len(mats):
        raise SceneError("give one material per seed (or one seed for a sweep)")
    nb = n_boundary_for(cfg.n_cells)
    cache: dict[int, bd.Specimen] = {}
    for s in seeds:
        if s not in cache:
            cache[s] = bd.disc_specimen(
                cfg.diameter,
                cfg.n_cells,
                s,
                mat,
                lloyd_iterations=cfg.lloyd_iterations,
                n_boundary=nb,
            )
    specs = [cache[s] for s in seeds]
    caps = bd.Capacities.covering(specs)
    speed = 0.5 * cfg.strain_rate * cfg.diameter
    states, gaps = [], []
    for spec, m in zip(specs, mats, strict=True):
        walls, gap = _platens(spec, cfg.diameter, speed)
        states.append(bd.assemble(spec, m, walls, capacities=caps))
        gaps.append(gap)
    dt = min(
        bd.stable_dt(s.particles, s.bonds, m, cfg.dt_safety)
        for s, m in zip(states, mats, strict=True)
    )
    h = math.sqrt(math.pi * cfg.diameter**2 / 4 / cfg.n_cells)
    skin = cfg.skin_fraction * h
    params = bd.make_bonded_params(mat, dt, skin)
    grid = bd.grid_around(states, 0.6 * cfg.diameter, skin)
    cap = bd.fit_pair_capacity(states, skin)
    states = [bd.with_pair_capacity(s, cap) for s in states]
    controls = [bd.make_control(s) for s in states]
    return Setup(states, params, grid, controls, gaps, mat)


def platen_force(series: dict, k: int | None = None) -> np.ndarray:
    """Mean compressive force of the two platens per record (N), from the interval-averaged
    wall forces; ``k`` picks a realisation of a batched series."""
    f = np.asarray(series["wall_force"], float)
    pts = np.asarray(series["wall_point"], float)
    if k is not None:
        f, pts = f[:, k], pts[:, k]
    return 0.5 * (-f[:, 0, 1] + f[:, 1, 1]), pts[:, 1, 1] - pts[:, 0, 1]


def _stopper(cfg: Config, n_real: int, batched: bool):
    f_max = np.zeros(n_real)
    done = np.zeros(n_real, bool)

    def callback(state, rec):
        for k in range(n_real):
            force, _ = platen_force(rec, k if batched else None)
            f_max[k] = max(f_max[k], float(force.max()))
            if f_max[k] > 0 and force[-1] < cfg.drop_fraction * f_max[k]:
                done[k] = done[k] or float(force.max()) < f_max[k]  # past the peak
        return state, bool(done.all())

    return callback


def _chain(first, stopper):
    if first is None:
        return stopper

    def both(state, rec):
        first(state, rec)
        return stopper(state, rec)

    return both


def simulate_test(
    cfg: Config,
    *,
    progress: bool = False,
    setup: Setup | None = None,
    params_batched: bool = False,
    callback=None,
):
    """Run the test (all realisations); returns ``(EnsembleResult, Setup)``. With
    ``params_batched`` ``setup.params`` is stacked like the states (a contact-law sweep).
    ``callback(state, records)`` runs on the host after each segment, before the post-peak
    stopping rule (e.g. to sample an energy ledger)."""
    setup = setup or build(cfg)
    k = len(setup.states)
    batched = k > 1
    dt = float(np.max(np.asarray(setup.params.dt)))  # stacked when params_batched
    n_steps = int(math.ceil(cfg.max_strain / cfg.strain_rate / dt))
    if batched:
        state = ens.stack(setup.states)
        control = ens.stack(setup.controls)
    else:
        state, control = setup.states[0], setup.controls[0]
    res = ens.drive(
        state,
        setup.params,
        control,
        setup.grid,
        n_steps=n_steps,
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        batched=batched,
        params_batched=params_batched,
        callback=_chain(callback, _stopper(cfg, k, batched)),
        frame_every=max(1, n_steps // (cfg.record_every * cfg.records_per_segment * 10)),
        progress=progress,
        desc=SCENE,
    )
    return res, setup


def measure(run, gap0: float, diameter: float, material: bd.Material) -> dict:
    """Key figures of one realisation (a :class:`jaxgran.simulate.RunResult`)."""
    force, gap = platen_force(run.series)
    strain = 1.0 - gap / gap0
    t = np.asarray(run.series["time"], float)
    n_b = np.asarray(run.series["n_broken"])
    T = material.thickness
    kmax = int(np.argmax(force))
    f_max = float(force[kmax])
    out = {
        "force_max_N": f_max,
        "strain_at_force_max": float(strain[kmax]),
        "tensile_strength_Pa": an.brazilian_tensile_strength(f_max, diameter, T),
        "final_force_over_max": float(force[-1] / f_max) if f_max > 0 else float("nan"),
        "final_strain": float(strain[-1]),
        "n_bonds": int(np.asarray(run.state.bonds.i < run.state.bonds.j).sum()),
        "n_broken": int(n_b[-1]),
        "broken_at_peak": int(n_b[kmax]),
    }
    out["tensile_strength_over_b_n"] = out["tensile_strength_Pa"] / material.b_n
    if kmax > 2:
        slope = an.brazilian_slope(strain, force, T)
        out["slope_S_Pa"] = slope["slope_S"]
        out["slope_S_over_k_n_per_m"] = slope["slope_S"] / material.normal_stiffness
        rise = an.fit_window(strain[: kmax + 1], force[: kmax + 1], 0.1, 0.7)
        out["rising_branch_r2"] = rise["r2"]
        out["rising_branch_stiffness_N"] = rise["slope"]
    pts, times = an.broken_bond_points(run.state)
    if len(pts) >= 3:
        ang = an.principal_axis_angle(pts)
        out["crack_angle_from_loading_axis_deg"] = ang["angle_deg"]
        out["crack_elongation"] = ang["elongation"]
        centre = np.asarray(run.state.particles.pos)[np.asarray(run.state.particles.active)]
        c = centre.mean(axis=0)
        out["broken_mean_distance_from_loading_axis_over_D"] = float(
            np.mean(np.abs(pts[:, 0] - c[0])) / diameter
        )
    sizes, _ = an.burst_sizes(times, window=float(t[1] - t[0]) if t.size > 1 else 1.0)
    sizes = sizes[sizes > 0]
    out["n_bursts"] = int(sizes.size)
    if sizes.size >= 10 and np.unique(sizes).size > 1:
        fit = an.power_law_mle(sizes, 1, discrete=True)
        out["burst_exponent"] = fit["alpha"]
        out["burst_exponent_err"] = fit["alpha_err"]
        out["burst_ks"] = fit["ks"]
    ava = an.second_avalanche(t, n_b)
    if ava["onset_time"] is not None:
        out["avalanche_onset_time_s"] = ava["onset_time"]
        out["avalanche_onset_strain"] = float(np.interp(ava["onset_time"], t, strain))
        out["peak_time_s"] = float(t[kmax])
    return out


def bond_events(state) -> list[dict]:
    """One event per broken bond: time (s), cells i, j and the common point (m)."""
    pts, times = an.broken_bond_points(state)
    b = state.bonds
    from ..bonds import broken_mask

    mask = np.asarray(broken_mask(b))
    ii, jj = np.asarray(b.i)[mask], np.asarray(b.j)[mask]
    order = np.argsort(times)
    return [
        {
            "kind": "bond_break",
            "time": float(times[k]),
            "i": int(ii[k]),
            "j": int(jj[k]),
            "point": pts[k],
        }
        for k in order
    ]


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    res, setup = simulate_test(cfg, progress=progress)
    per = []
    for k in range(res.size):
        rk = res.realisation(k)
        per.append(measure(rk, setup.gap0[k], cfg.diameter, setup.material))
    summary = ens.ensemble_summary(per)
    if res.size > 1:  # paper 002 Fig. 24 pools the bursts of all realisations
        pooled = bd.pooled_bursts([res.realisation(k) for k in range(res.size)])
        summary.update({f"pooled_{k}": v for k, v in pooled.items()})
    summary.update(
        {
            "n_cells": cfg.n_cells,
            "thickness_m": setup.material.thickness,
            "dt_s": float(setup.params.dt),
            "steps": int(res.steps),
            "wall_time_s": float(res.wall_time_s),
            "regrows": res.regrows,
        }
    )
    r0 = res.realisation(0)
    summary = write_outputs(
        out_dir, SCENE, cfg, r0, setup.params, summary, events=bond_events(r0.state), vtk=vtk
    )
    figs = _figures(res, setup, cfg, Path(out_dir))
    summary["figures"] = list(summary.get("figures", [])) + [str(p) for p in figs]
    from .. import io

    io.write_summary(Path(out_dir) / "summary.json", summary)
    return summary


# ------------------------------------------------------------------------------ sweep


def sweep(
    cfg: Config,
    ratios=(0.5, 1.0, 2.0, 4.0),
    eps_values=(0.01, 0.02, 0.03),
    *,
    out_dir: Path | None = None,
    progress: bool = False,
) -> dict:
    """Calibration curves of paper 002 Fig. 8 / Eq. 18: sigma_t / B_n against B_n / B_t for
    each eps_th, one disc (``cfg.seed``) with every parameter pair in one vmapped batch.

    B_n stays at ``cfg.b_n``; B_t = B_n / ratio. Returns the grid of ratios and eps_th,
    sigma_t / B_n and S / K_n ``[len(eps_values), len(ratios)]``, and the figure path when
    ``out_dir`` is given.
    """
    base = bd.material_from(cfg)
    mats = [
        dataclasses.replace(base, b_t=base.b_n / r, eps_th=e) for e in eps_values for r in ratios
    ]
    setup = build(cfg, seeds=[cfg.seed], materials=mats)
    max_eps = max(eps_values)
    cfg_run = dataclasses.replace(
        cfg, realisations=len(mats), max_strain=max(cfg.max_strain, 4.0 * max_eps)
    )
    res, _ = simulate_test(cfg_run, progress=progress, setup=setup)
    sig = np.zeros((len(eps_values), len(ratios)))
    slope = np.full_like(sig, np.nan)
    for k in range(res.size):
        m = measure(res.realisation(k), setup.gap0[k], cfg.diameter, mats[k])
        e, r = divmod(k, len(ratios))
        sig[e, r] = m["tensile_strength_over_b_n"]
        slope[e, r] = m.get("slope_S_over_k_n_per_m", np.nan)
    out = {
        "ratios_b_n_over_b_t": list(map(float, ratios)),
        "eps_th": list(map(float, eps_values)),
        "tensile_strength_over_b_n": sig.tolist(),
        "slope_S_over_k_n_per_m": slope.tolist(),
        "wall_time_s": float(res.wall_time_s),
    }
    if out_dir is not None:
        out["figure"] = str(_sweep_figure(out, Path(out_dir)))
    return out


def sweep_stiffness(
    cfg: Config,
    kn_over_kt=(0.5, 1.0, 2.0, 4.0),
    bn_over_bt=(1.0, 4.0),
    *,
    progress: bool = False,
) -> dict:
    """Calibration curves of paper 002 Fig. 9 / Eq. 19: the slope S / K_n against K_n / K_t
    for each B_n / B_t, one disc (``cfg.seed``), every pair in one vmapped batch with the
    contact law batched too (``params_batched``: K_t lives in :class:`Params`).

    K_n and B_n stay at ``cfg``'s values; K_t = K_n / (K_n / K_t), B_t = B_n / (B_n / B_t).
    All members share the smallest stable time step. Returns the grids, S / K_n (1/m) and
    sigma_t / B_n ``[len(bn_over_bt), len(kn_over_kt)]``.
    """
    base = bd.material_from(cfg)
    mats = [
        dataclasses.replace(
            base, b_t=base.b_n / rb, tangential_stiffness=base.normal_stiffness / rk
        )
        for rb in bn_over_bt
        for rk in kn_over_kt
    ]
    setup = build(cfg, seeds=[cfg.seed], materials=mats)
    dt = float(setup.params.dt)
    skin = float(setup.params.skin)
    # K_t enters the time-step bound through max(K_n, K_t)
    dt = min(
        [dt]
        + [
            bd.stable_dt(s.particles, s.bonds, m, cfg.dt_safety)
            for s, m in zip(setup.states, mats, strict=True)
        ]
    )
    setup.params = ens.stack([bd.make_bonded_params(m, dt, skin) for m in mats])
    res, _ = simulate_test(
        dataclasses.replace(cfg, realisations=len(mats)),
        progress=progress,
        setup=setup,
        params_batched=True,
    )
    slope = np.full((len(bn_over_bt), len(kn_over_kt)), np.nan)
    sig = np.full_like(slope, np.nan)
    for k in range(res.size):
        m = measure(res.realisation(k), setup.gap0[k], cfg.diameter, mats[k])
        b, r = divmod(k, len(kn_over_kt))
        slope[b, r] = m.get("slope_S_over_k_n_per_m", np.nan)
        sig[b, r] = m["tensile_strength_over_b_n"]
    return {
        "ratios_k_n_over_k_t": list(map(float, kn_over_kt)),
        "ratios_b_n_over_b_t": list(map(float, bn_over_bt)),
        "slope_S_over_k_n_per_m": slope.tolist(),
        "tensile_strength_over_b_n": sig.tolist(),
        "dt_s": dt,
        "steps": int(res.steps),
        "wall_time_s": float(res.wall_time_s),
    }


# ------------------------------------------------------------------------------ figures


def _figures(res, setup: Setup, cfg: Config, out_dir: Path) -> list[Path]:
    """Force-strain curves, broken bonds against time, the crack pattern and the burst-size
    distribution (Agg backend, imported here only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .. import plot

    paths = []
    curves = {}
    for k in range(res.size):
        rk = res.realisation(k)
        force, gap = platen_force(rk.series)
        curves[k] = (100.0 * (1.0 - gap / setup.gap0[k]), force / 1e3)
    fig, ax = plt.subplots(figsize=(6, 4))
    for k, (x, y) in curves.items():
        ax.plot(x, y, lw=1, label=f"seed {cfg.seed + k}" if res.size <= 8 else None)
    ax.set_xlabel("axial strain (%)")
    ax.set_ylabel("platen force F (kN)")
    ax.grid(True, alpha=0.3)
    if 1 < res.size <= 8:
        ax.legend()
    paths.append(out_dir / "force_strain.png")
    fig.savefig(paths[-1], dpi=150, bbox_inches="tight")
    plt.close(fig)

    r0 = res.realisation(0)
    t = np.asarray(r0.series["time"])
    paths.append(
        plot.plot_series(
            t * 1e3,
            {"broken bonds": r0.series["n_broken"]},
            "time (ms)",
            "broken bonds",
            out_dir / "broken_bonds.png",
        )
    )
    paths.append(_crack_figure(r0.state, setup.material.thickness, out_dir / "cracks.png"))

    _, times = an.broken_bond_points(r0.state)
    sizes, _ = an.burst_sizes(times, window=float(t[1] - t[0]) if t.size > 1 else 1.0)
    sizes = sizes[sizes > 0]
    if sizes.size >= 10 and np.unique(sizes).size > 1:
        x, dens = an.log_histogram(sizes)
        fit = an.power_law_mle(sizes, 1)
        fig, ax = plt.subplots(figsize=(5, 4))
        ok = dens > 0
        ax.loglog(x[ok], dens[ok], "o", label="bursts")
        xs = np.geomspace(1, sizes.max(), 30)
        from scipy.special import zeta

        ax.loglog(
            xs,
            xs ** (-fit["alpha"]) / zeta(fit["alpha"], 1),
            "-",
            label=f"MLE alpha = {fit['alpha']:.2f} +- {fit['alpha_err']:.2f}",
        )
        ax.set_xlabel("broken bonds per window")
        ax.set_ylabel("probability")
        ax.legend()
        paths.append(out_dir / "bursts.png")
        fig.savefig(paths[-1], dpi=150, bbox_inches="tight")
        plt.close(fig)
    return paths


def _crack_figure(state, thickness: float, path: Path) -> Path:
    """The specimen with its broken bonds drawn as red segments."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    from .. import plot
    from ..io import world_vertices_np

    p = state.particles
    vw = world_vertices_np(p.verts, p.n_verts, p.pos, p.angle)
    fig, ax = plt.subplots(figsize=(6, 6))
    plot.draw_particles(ax, vw, p.n_verts, p.radius, p.active)
    seg = an.bond_segments(state, thickness, "broken") * 100.0  # cm, as draw_particles
    ax.add_collection(LineCollection(seg, colors="red", linewidths=1.5))
    ax.set_title(f"broken bonds: {len(seg)}")
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path


def _sweep_figure(out: dict, out_dir: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5, 4))
    for e, row in zip(out["eps_th"], out["tensile_strength_over_b_n"], strict=True):
        ax.plot(out["ratios_b_n_over_b_t"], row, "o-", label=f"eps_th = {e:g}")
    ax.set_xscale("log")
    ax.set_xlabel("B_n / B_t")
    ax.set_ylabel("sigma_t / B_n")
    ax.legend()
    ax.grid(True, alpha=0.3)
    path = out_dir / "sweep_tensile_strength.png"
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path
