"""Bonded cantilever: a Voronoi beam clamped at one end with a tip load, against
Euler-Bernoulli (paper 002 §4.2, Eq. 29, Fig. 14-15, in 2D plane stress).

A beam of length L and depth s (slab thickness T) of bonded Voronoi cells (the material of
:mod:`jaxgran.scenes.bonded`) is clamped by fixing the cells whose centroids lie within
``clamp_length`` of its left end (``Particles.fixed``, zero velocity); the clamp line x_c is
that distance from the end. A downward force F acts on the cells within ``tip_length`` of the
right end, shared in proportion to their masses (a body force; the state has no external
force field, so :class:`jaxgran.scenes.bonded.Control` applies it as an impulse per step). F
is ramped up over one period of the first bending mode and then held, with a global viscous
damping (critical for that mode) so the beam relaxes to its static shape; there is no
gravity.

The deflection w(x) of the middle line (the centroids of the cells within ``band`` of
y = s/2) is compared with Euler-Bernoulli for a load at distance a = x_F - x_c from the
clamp (x_F the load's centre of mass): ``w = F x^2 (3 a - x) / (6 E I)`` for x <= a and its
straight continuation beyond (Eq. 29 with L -> a), ``I = T s^3 / 12``. E is the unconfined
compression modulus E_c measured on the same material (same cell size) by
:func:`jaxgran.scenes.bonded_biaxial.unconfined` with strain-gauge bands (the run is cited in
the summary: its configuration and seed), unless ``youngs_modulus`` is given. A beam in
bending is also stretched on its tension side, whose modulus E_t (B_n-controlled) differs
from E_c (K_n-controlled; E_t ~ 0.6 E_c with Table 1), so the bimodular flexural modulus
``E_f = 4 E_t E_c / (sqrt(E_t) + sqrt(E_c))^2`` is the one that Euler-Bernoulli needs; the
comparison is reported with E_c (Eq. 29 as the paper writes it), with E_f, and with
Timoshenko's shear deflection added (a beam of L / s ~ 6 is short). The middle line is also
fitted with Eq. 29 plus a rigid rotation and drop of the root (``E_bending_Pa``,
``root_rotation_rad``): the fixed cells end in an irregular Voronoi line, and the cells just
beyond it turn a little, which adds a straight-line deflection that Eq. 29 (a perfectly
built-in end) does not have and that shrinks, relative to the bending, as 1 / L.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .. import ensemble as ens
from ..errors import SceneError
from ..state import replace
from . import bonded as bd
from . import bonded_biaxial as bx
from .base import write_outputs

SCENE = "bonded-cantilever"


@dataclasses.dataclass(frozen=True)
class Config(bd.Material):
    """Scene settings after the material ones of :class:`jaxgran.scenes.bonded.Material`
    (paper 002 Table 1, SI units)."""

    length: float = 0.30  # m, L
    depth: float = 0.05  # m, s
    n_cells: int = 400  # Voronoi cells of the beam
    seed: int = 0  # Voronoi seed of realisation 0 (realisation k uses seed + k)
    realisations: int = 1  # K > 1: K beams under jax.vmap, mean +- std reported
    lloyd_iterations: int = 2
    clamp_length: float = 0.02  # m, the clamped stretch at the left end
    # "straight": the clamp [0, clamp_length] and the beam are tessellated apart, so the
    # clamp face x = clamp_length is a straight line of shared edges (paper 002's fixed
    # plate); "cells": one tessellation, the cells whose centroids lie in the clamp fixed
    clamp: str = "cells"
    tip_length: float = 0.02  # m, loaded cells' centroids within this of the right end
    max_bending_stress: float = 10.0e6  # Pa, sets F = sigma T s^2 / (6 a)
    band: float = 0.25  # middle-line cells: |y - s/2| < band x s
    ramp_periods: float = 1.0  # load ramp, in periods of the first bending mode
    hold_periods: float = 2.0  # then held this long
    damping_ratio: float = 1.0  # global damping / critical damping of the first mode
    youngs_modulus: float = 0.0  # Pa; 0 = measure E_c (and E_t) on the same material
    measure_cells: int = 0  # cells of the measuring block (0: same cell size, W = s, H = 2 s)
    dt_safety: float = 0.5
    skin_fraction: float = 0.1
    record_every: int = 100
    records_per_segment: int = 10


QUICK = {"length": 0.15, "depth": 0.03, "n_cells": 90, "clamp_length": 0.015, "tip_length": 0.015}


def cell_size(cfg: Config) -> float:
    return math.sqrt(cfg.length * cfg.depth / cfg.n_cells)


def measure_moduli(cfg: Config, seeds: list[int], *, progress: bool = False) -> list[dict]:
    """E_c and nu (unconfined compression) and E_t (tension) of the beam's material for each
    seed, on a block W = s, H = 2 s with the beam's cell size (paper 002 Eq. 24-25), all
    seeds in one vmapped batch."""
    h = cell_size(cfg)
    n = cfg.measure_cells or max(30, int(round(2.0 * cfg.depth**2 / h**2)))
    names = {f.name for f in dataclasses.fields(bx.Config)}
    common = {k: getattr(cfg, k) for k in names if hasattr(cfg, k) and k != "n_cells"}
    bcfg = dataclasses.replace(
        bx.Config(),
        **(common | {"width": cfg.depth, "height": 2.0 * cfg.depth, "n_cells": n}),
    )
    res_c, set_c = bx.unconfined(bcfg, seeds, progress=progress)
    res_t, set_t = bx.tension(bcfg, seeds, progress=progress)
    out = []
    for k, seed in enumerate(seeds):
        c = bx.measure_elastic(res_c.realisation(k), set_c.gauge0[k], cfg.thickness, 1.0)
        t = bx.measure_elastic(res_t.realisation(k), set_t.gauge0[k], cfg.thickness, -1.0)
        out.append(
            {
                "E_c_Pa": c.get("modulus_Pa", c["modulus_platens_Pa"]),
                "E_c_platens_Pa": c["modulus_platens_Pa"],
                "poisson_ratio": c.get("poisson_ratio", float("nan")),
                "E_t_Pa": t.get("modulus_Pa", t["modulus_platens_Pa"]),
                "measured_on": {
                    "scene": bx.SCENE,
                    "tests": "unconfined compression (gauge bands) and tension",
                    "seed": seed,
                    "config": dataclasses.asdict(bcfg),
                },
            }
        )
    return out


def beam_specimen(cfg: Config, seed: int, mat) -> bd.Specimen:
    """The beam's Voronoi specimen (m). With ``clamp = "straight"`` the clamp stretch
    ``[0, clamp_length]`` and the free beam ``[clamp_length, length]`` are tessellated
    apart (cells in proportion to their areas, the clamp's listed first), so every free cell
    at the root meets the clamp along the straight line ``x = clamp_length``; their shared
    edges (T-junctions included) are bonded like any other. With ``"cells"`` the whole beam
    is one tessellation and the clamp is the set of cells whose centroids lie in it, so the
    root is a zigzag of cell edges."""
    if cfg.clamp == "cells":
        return bd.rectangle_specimen(
            cfg.length, cfg.depth, cfg.n_cells, seed, mat, lloyd_iterations=cfg.lloyd_iterations
        )
    if cfg.clamp != "straight":
        raise SceneError(f"clamp must be 'straight' or 'cells', got {cfg.clamp!r}")
    if not 0.0 < cfg.clamp_length < cfg.length:
        raise SceneError(
            f"clamp_length must be in (0, length) = (0, {cfg.length}) m, got {cfg.clamp_length}"
        )
    from .. import geometry as geo

    n_clamp = max(2, int(round(cfg.n_cells * cfg.clamp_length / cfg.length)))
    lloyd = cfg.lloyd_iterations
    clamp = geo.voronoi_rectangle(
        cfg.clamp_length, cfg.depth, n_clamp, seed, lloyd_iterations=lloyd
    )
    beam = geo.voronoi_rectangle(
        cfg.length - cfg.clamp_length,
        cfg.depth,
        max(1, cfg.n_cells - n_clamp),
        seed,
        origin=(cfg.clamp_length, 0.0),
        lloyd_iterations=lloyd,
    )
    return bd.specimen_from_cells(clamp + beam, cfg.length * cfg.depth, mat)


@dataclasses.dataclass
class Setup:
    """Beams of common shapes (one per seed), shared parameters and grid."""

    states: list
    controls: list
    geos: list
    params: object
    grid: object


def build(cfg: Config, seeds: list[int], modulus: float | None = None) -> Setup:
    """Beam states (clamp cells fixed) padded to common capacities, their controls (tip load,
    damping) and the geometry used to compare with beam theory. ``modulus`` (Pa) is the
    bending modulus used for the first-mode period (ramp, hold and critical damping); by
    default the estimate ``K_n / T``, which is some 2.5x too soft for Table 1, so the hold is
    longer and the damping lighter than planned."""
    mat = bd.material_from(cfg)
    specs = [beam_specimen(cfg, s, mat) for s in seeds]
    caps = bd.Capacities.covering(specs)
    states, loads, geos = [], [], []
    for spec in specs:
        state = bd.assemble(spec, mat, [], capacities=caps)
        n = spec.n_particles
        pos0 = np.asarray(state.particles.pos)[:n]
        clamp = pos0[:, 0] < cfg.clamp_length  # with a straight clamp: its own cells
        tip = pos0[:, 0] > cfg.length - cfg.tip_length
        if not clamp.any() or not tip.any():
            raise SceneError("no cell in the clamp or tip region; enlarge clamp/tip_length")
        fixed = np.zeros(state.particles.capacity, bool)
        fixed[:n] = clamp
        state = replace(state, particles=replace(state.particles, fixed=jnp.asarray(fixed)))
        mass = np.asarray(state.particles.mass)[:n]
        x_f = float(np.sum(mass[tip] * pos0[tip, 0]) / mass[tip].sum())
        arm = x_f - cfg.clamp_length
        force = cfg.max_bending_stress * cfg.thickness * cfg.depth**2 / (6.0 * arm)
        ext = np.zeros((state.particles.capacity, 2))
        ext[:n][tip, 1] = -force * mass[tip] / mass[tip].sum()
        states.append(state)
        loads.append(ext)
        geos.append(
            {
                "centroids": pos0,
                "force_N": force,
                "arm_m": arm,
                "x_clamp_m": cfg.clamp_length,
                "x_load_m": x_f,
                "second_moment_m4": cfg.thickness * cfg.depth**3 / 12.0,
                "n_fixed": int(clamp.sum()),
                "n_loaded": int(tip.sum()),
            }
        )
    dt = min(bd.stable_dt(s.particles, s.bonds, mat, cfg.dt_safety) for s in states)
    skin = cfg.skin_fraction * cell_size(cfg)
    params = bd.make_bonded_params(mat, dt, skin)
    grid = bd.grid_around(states, 0.3 * cfg.length, skin)
    cap = bd.fit_pair_capacity(states, skin)
    states = [bd.with_pair_capacity(s, cap) for s in states]
    # first bending mode of the clamped beam (estimated modulus K_n / T), for the time scales
    e_est = modulus if modulus else bx.estimated_modulus(mat)
    i_area = cfg.thickness * cfg.depth**3 / 12.0
    m_line = mat.areal_density * cfg.depth
    arm = max(g["arm_m"] for g in geos)
    omega1 = 1.875**2 * math.sqrt(e_est * i_area / (m_line * arm**4))
    period = 2.0 * math.pi / omega1
    controls = []
    for s, ext, g in zip(states, loads, geos, strict=True):
        g["period_s"] = period
        controls.append(
            bd.make_control(
                s,
                external_force=ext,
                ramp_time=cfg.ramp_periods * period,
                damping=2.0 * cfg.damping_ratio * omega1,
            )
        )
    return Setup(states, controls, geos, params, grid)


def euler_bernoulli(x, force: float, arm: float, modulus: float, i_area: float) -> np.ndarray:
    """Deflection (m, positive down) of a cantilever under a point load F (N) at distance
    ``arm`` (m) from the clamp, paper 002 Eq. 29 (with L = arm), straight beyond the load."""
    x = np.clip(np.asarray(x, float), 0.0, None)
    xa = np.minimum(x, arm)
    w = force * xa**2 * (3.0 * arm - xa) / (6.0 * modulus * i_area)
    slope = force * arm**2 / (2.0 * modulus * i_area)
    return w + slope * np.maximum(x - arm, 0.0)


def deflection(state, geo: dict, cfg: Config):
    """Middle-line cells: distance from the clamp (m) and downward displacement (m)."""
    c0 = geo["centroids"]  # initial particle positions (m)
    n = len(c0)
    mid = np.abs(c0[:, 1] - 0.5 * cfg.depth) < cfg.band * cfg.depth
    mid &= c0[:, 0] > geo["x_clamp_m"]
    pos = np.asarray(state.particles.pos)[:n]
    x = c0[mid, 0] - geo["x_clamp_m"]
    w = -(pos[mid, 1] - c0[mid, 1])
    order = np.argsort(x)
    return x[order], w[order]


def simulate_test(
    cfg: Config, seeds: list[int], *, progress: bool = False, modulus: float | None = None
):
    """Load and relax the beams of ``seeds`` (vmapped when more than one); ``modulus`` as in
    :func:`build`."""
    setup = build(cfg, seeds, modulus)
    total = (cfg.ramp_periods + cfg.hold_periods) * setup.geos[0]["period_s"]
    n_steps = int(math.ceil(total / float(setup.params.dt)))
    batched = len(seeds) > 1
    res = ens.drive(
        ens.stack(setup.states) if batched else setup.states[0],
        setup.params,
        ens.stack(setup.controls) if batched else setup.controls[0],
        setup.grid,
        n_steps=n_steps,
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        batched=batched,
        progress=progress,
        desc=SCENE,
        frame_every=max(1, n_steps // (cfg.record_every * cfg.records_per_segment * 10)),
    )
    return res, setup


def flexural_modulus(e_t: float, e_c: float) -> float:
    """Bending modulus (Pa) of a rectangular beam of a bimodular material (tension modulus
    E_t, compression modulus E_c): the neutral axis moves to the stiffer side and the
    moment-curvature relation is ``M = E_f I kappa`` with
    ``E_f = 4 E_t E_c / (sqrt(E_t) + sqrt(E_c))^2`` (E_f = E when E_t = E_c)."""
    return 4.0 * e_t * e_c / (math.sqrt(e_t) + math.sqrt(e_c)) ** 2


def shear_coefficient(poisson_ratio: float) -> float:
    """Timoshenko shear coefficient of a rectangular section (Cowper 1966):
    ``10 (1 + nu) / (12 + 11 nu)`` (5/6 at nu = 0)."""
    nu = poisson_ratio if math.isfinite(poisson_ratio) else 0.0
    return 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu)


def timoshenko(x, force, arm, modulus, i_area, area, poisson_ratio) -> np.ndarray:
    """Deflection (m, down) of a clamped Timoshenko cantilever with a point load F (N) at
    ``arm`` (m): Eq. 29 (:func:`euler_bernoulli`) plus the shear deflection
    ``F min(x, a) / (k G A)`` with ``G = E / (2 (1 + nu))`` (plane stress, isotropic) and
    ``k`` from :func:`shear_coefficient`; A = s T (m^2)."""
    nu = poisson_ratio if math.isfinite(poisson_ratio) else 0.0
    g = modulus / (2.0 * (1.0 + nu))
    x = np.clip(np.asarray(x, float), 0.0, None)
    shear = force * np.minimum(x, arm) / (shear_coefficient(nu) * g * area)
    return euler_bernoulli(x, force, arm, modulus, i_area) + shear


def compare(res, geo: dict, cfg: Config, moduli: dict, *, from_fraction: float = 0.25) -> dict:
    """:func:`compare_deflection` of the middle line of ``res.state``."""
    x, w = deflection(res.state, geo, cfg)
    return compare_deflection(x, w, geo, cfg, moduli, from_fraction=from_fraction)


def compare_deflection(
    x, w, geo: dict, cfg: Config, moduli: dict, *, from_fraction: float = 0.25
) -> dict:
    """DEM middle-line deflection ``w`` (m, down) at distances ``x`` (m) from the clamp
    against beam theory; ``geo`` gives ``force_N``, ``arm_m`` and ``second_moment_m4``.

    Cases: Eq. 29 with E_c (``E_c``), Eq. 29 with the bimodular flexural modulus of the
    measured E_t and E_c (``E_flexural``) and Timoshenko with that modulus
    (``timoshenko_E_flexural``). For each: the tip error, the RMS error over the middle line
    (over the largest theoretical deflection) and ``max_error_along_<case>``, the largest
    |w_DEM / w_theory - 1| of the middle-line cells from ``from_fraction`` of the arm to the
    tip (nearer the clamp w is a few percent of the tip's and set by single cells at the
    irregular clamp), plus the binned profile ``error_profile_<case>`` (x / a, mean error).
    ``E_fitted_Pa`` is the modulus that makes Eq. 29 fit the middle line best, and
    ``E_bending_Pa`` the same with a rigid rotation (``root_rotation_rad``) and drop
    (``root_drop_m``) of the root as free parameters: the beam's own bending modulus, apart
    from the compliance of the irregular clamp (its share of the tip deflection is
    ``root_share_of_tip_deflection``)."""
    x, w = np.asarray(x, float), np.asarray(w, float)
    i_area, f, a = geo["second_moment_m4"], geo["force_N"], geo["arm_m"]
    out = {}
    e_c = moduli["E_c_Pa"]
    nu = float(moduli.get("poisson_ratio", 0.0))
    cases = {"E_c": euler_bernoulli(x, f, a, e_c, i_area)}
    if moduli.get("E_t_Pa", 0.0) > 0:
        e_f = flexural_modulus(moduli["E_t_Pa"], e_c)
        out["E_flexural_Pa"] = e_f
        cases["E_flexural"] = euler_bernoulli(x, f, a, e_f, i_area)
        area = cfg.depth * cfg.thickness
        cases["timoshenko_E_flexural"] = timoshenko(x, f, a, e_f, i_area, area, nu)
    near = x > 0.9 * a
    w_tip = float(np.mean(w[near])) if near.any() else float(w[-1])
    out["tip_deflection_m"] = w_tip
    along = x >= from_fraction * a
    edges = np.linspace(from_fraction, 1.0, 7) * a
    for name, theory in cases.items():
        tip_theory = float(np.mean(theory[near])) if near.any() else float(theory[-1])
        out[f"tip_deflection_theory_{name}_m"] = tip_theory
        out[f"tip_error_{name}"] = w_tip / tip_theory - 1.0
        out[f"rms_error_{name}"] = float(
            np.sqrt(np.mean((w - theory) ** 2)) / max(np.max(np.abs(theory)), 1e-300)
        )
        ratio = w[along] / theory[along] - 1.0
        out[f"max_error_along_{name}"] = float(np.max(np.abs(ratio))) if ratio.size else np.nan
        out[f"mean_error_along_{name}"] = float(np.mean(ratio)) if ratio.size else np.nan
        prof = []
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            sel = (x >= lo) & (x < hi)
            if sel.any():
                prof.append([0.5 * (lo + hi) / a, float(np.mean(w[sel] / theory[sel] - 1.0))])
        out[f"error_profile_{name}"] = prof
    # the modulus that makes Eq. 29 fit the DEM middle line best
    shape = euler_bernoulli(x, f, a, 1.0, i_area)
    out["E_fitted_Pa"] = float(np.sum(shape * shape) / np.sum(shape * w))
    # the same with a rigid rotation and drop at the clamp as free parameters: the bending
    # stiffness of the beam itself, apart from the compliance of its irregular root
    basis = np.stack([shape, x, np.ones_like(x)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, w, rcond=None)
    out["E_bending_Pa"] = float(1.0 / coef[0]) if coef[0] > 0 else float("nan")
    out["root_rotation_rad"] = float(coef[1])
    out["root_drop_m"] = float(coef[2])
    out["root_share_of_tip_deflection"] = float((coef[1] * a + coef[2]) / w_tip)
    out["n_middle_cells"] = int(x.size)
    out["n_middle_cells_compared"] = int(along.sum())
    return out


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    out_dir = Path(out_dir)
    seeds = [cfg.seed + k for k in range(max(1, cfg.realisations))]
    if cfg.youngs_modulus > 0:
        moduli = [{"E_c_Pa": cfg.youngs_modulus, "measured_on": "given (youngs_modulus)"}] * len(
            seeds
        )
    else:
        moduli = measure_moduli(cfg, seeds, progress=progress)
    # time scales of the loading from the measured bending stiffness
    e_t = [m.get("E_t_Pa", 0.0) for m in moduli]
    e_b = [
        flexural_modulus(t, m["E_c_Pa"]) if t > 0 else m["E_c_Pa"]
        for t, m in zip(e_t, moduli, strict=True)
    ]
    res, setup = simulate_test(cfg, seeds, progress=progress, modulus=float(np.mean(e_b)))
    per = []
    for k in range(res.size):
        rk = res.realisation(k)
        g = setup.geos[k]
        per.append(
            {
                "force_N": g["force_N"],
                "arm_m": g["arm_m"],
                "n_fixed_cells": g["n_fixed"],
                "n_loaded_cells": g["n_loaded"],
                "n_broken": int(np.asarray(rk.series["n_broken"])[-1]),
                "final_kinetic_energy_J": float(rk.series["kinetic_energy"][-1]),
                **moduli[k],
                **compare(rk, g, cfg, moduli[k]),
            }
        )
    summary = ens.ensemble_summary(per)
    summary.update(
        {
            "second_moment_m4": setup.geos[0]["second_moment_m4"],
            "first_mode_period_s": setup.geos[0]["period_s"],
            "steps": int(res.steps),
            "dt_s": float(setup.params.dt),
            "wall_time_s": float(res.wall_time_s),
        }
    )
    r0 = res.realisation(0)
    summary = write_outputs(out_dir, SCENE, cfg, r0, setup.params, summary, vtk=vtk)
    figs = _figures(r0, setup.geos[0], cfg, moduli[0], out_dir)
    summary["figures"] = list(summary.get("figures", [])) + [str(p) for p in figs]
    from .. import io

    io.write_summary(out_dir / "summary.json", summary)
    return summary


def _figures(res, geo: dict, cfg: Config, moduli: dict, out_dir: Path) -> list[Path]:
    """Middle-line deflection against Euler-Bernoulli, and the tip deflection against time
    (Agg backend, imported here only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, w = deflection(res.state, geo, cfg)
    xs = np.linspace(0.0, x.max(), 100)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(100 * x, 1e3 * w, "o", ms=3, label="DEM middle line")
    args = (geo["force_N"], geo["arm_m"])
    i_area = geo["second_moment_m4"]
    ax.plot(
        100 * xs,
        1e3 * euler_bernoulli(xs, *args, moduli["E_c_Pa"], i_area),
        "-",
        label="Eq. 29, E_c",
    )
    if "E_t_Pa" in moduli:
        e_t, e_c = moduli["E_t_Pa"], moduli["E_c_Pa"]
        e_f = flexural_modulus(e_t, e_c)
        ax.plot(100 * xs, 1e3 * euler_bernoulli(xs, *args, e_f, i_area), "--", label="E_flexural")
    ax.set_xlabel("distance from the clamp (cm)")
    ax.set_ylabel("deflection w (mm, down)")
    ax.invert_yaxis()
    ax.legend()
    ax.grid(True, alpha=0.3)
    path = out_dir / "deflection.png"
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return [path, *_history(res, out_dir)]


def _history(res, out_dir: Path) -> list[Path]:
    from .. import plot

    t = np.asarray(res.series["time"])
    return [
        plot.plot_series(
            t * 1e3,
            {"kinetic energy": res.series["kinetic_energy"]},
            "time (ms)",
            "kinetic energy (J)",
            out_dir / "relaxation.png",
            logy=True,
        )
    ]
