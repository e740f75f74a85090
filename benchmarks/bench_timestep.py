"""Time step against energy error and wall time, and where a bonded scene becomes unstable
(issue 9): the chart ``docs/timestep_vs_energy_error.png`` and the table "largest stable dt
against the theoretical limit".

Each scene is a small bonded specimen made conservative: no gravity, no walls, every
dashpot off (contact G_n = G_t = 0; interface-element dashpots 0), bonds that cannot break
(thresholds / strengths infinite or 1e30) and frictionless contacts (K_t = 0, mu = 0: a
Cundall-Strack spring loses its stored energy when its contact opens, so with K_t > 0 the
energy below would not be an invariant). Every cell gets a seeded random velocity and
angular velocity (``--speed`` rms per component, ``--speed / h`` rad/s, h the mean cell
size; zero net momentum). Then ``T = --default-steps x dt_default`` of physical time is run
with ``dt = f x dt_theory`` for each factor f (``--factors``), where ``dt_theory`` is the
scene's springs-only stability bound at safety 1 (the Gershgorin bound
:func:`jaxgran.scenes.bonded.stable_dt`; :func:`jaxgran.scenes.interface.stable_dt` with
``dashpots=False``) and ``dt_default = f_default x dt_theory`` is what the scene runs with
(the bonded scene: ``f_default = dt_safety``; the interface scene counts its element and
contact dashpots in its step, so ``f_default = dt_safety x`` that bound's ratio to the
springs' one).

Measured per f: the relative energy error ``max_t |E(t) - E(0)| / E(0)`` over every step,
with ``E`` = kinetic (translation + rotation) + bond elastic + contact elastic energy; the
wall time of the run (one jitted segment of ``--chunk`` steps,
:func:`jaxgran.simulate.run_segment`, called in a host loop; compilation excluded, median of
``--repeats``); unstable = error bits from the step (NaN, particle left the grid, Verlet skin
exceeded, overflow) or an energy error above 100 %. The largest stable factor on the grid is
then refined by ``--refine`` bisections. As a reference the exact limit of the linearised
system, ``2 / omega_max`` (Verlet is stable for ``omega dt < 2``), is computed from the
Hessian of the elastic energy at rest (``jax.hessian``) and the diagonal mass matrix. The
paper-002 bonds resist tension only (compression goes to the cell contacts), so that
Hessian has a tension branch (bonds only) and a compression branch (bond shear and
rotation + the contacts' normal springs, taken from ``jax.jacfwd`` of the contact forces at
a slight precompression); their sum bounds every mixture from above.

Scenes (``--scenes``):

* ``bonded``: a Voronoi disc of ``--cells`` cells with the paper-002 bonds and material of
  :mod:`jaxgran.scenes.bonded_brazilian` (D = 10 cm, T = 1 cm); the cells tile the disc, so
  neighbouring cells touch at rest and every compressed bond is a contact.
* ``interface``: the interface-bonded disc of elementary discs of
  :mod:`jaxgran.scenes.interface_plate` with D = 5 cm and paper 003's discs of 2.5-5 mm
  (pinned here, about 120 discs), whose 5 % clearance keeps the contact law out of bonded
  pairs.

    python benchmarks/bench_timestep.py                   # both scenes, about 3-5 min on 2 cores
    python benchmarks/bench_timestep.py --scenes bonded --factors 0.1,0.5,1,2 --refine 0
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FACTORS = "0.05,0.1,0.2,0.3,0.5,0.7,0.85,1.0,1.2,1.5,2.0,2.5,3.0,4.0"
FACTOR_GRID = {float(f) for f in FACTORS.split(",")}  # x ticks of the chart
UNSTABLE_ERROR = 1.0  # energy error above which a run counts as unstable
BIG = 1.0e30  # a strength that is never reached


@dataclasses.dataclass
class Case:
    """A conservative scene ready to step: state (with its initial velocities), parameters
    (``dt`` replaced per run), grid, the scene's bound ``dt_theory`` (s, safety 1) and
    default ``dt_safety``, and ``energy(state, params) -> [kinetic, bond, contact]`` (J)."""

    name: str
    label: str
    state: object
    params: object
    grid: object
    dt_theory: float
    dt_safety: float
    energy: Callable
    n_particles: int
    n_bonds: int
    cell_size: float
    limits: dict = dataclasses.field(default_factory=dict)


# ------------------------------------------------------------------------------ energies


def _contact_energy(state, params):
    """Elastic energy of the particle contacts (J), as the contact law books it: ``w (K_n
    delta^2 + K_t |xi|^2) / 2`` per vertex contact, ``w`` its corner weight
    (:func:`jaxgran.contact.corner_weight`). ``F_n^2 / (2 K_n)``, used here until
    2026-12-03, is that only where ``w = 1``: where two corners meet (``w`` = 1/2 to 1) it is
    not, and it showed a dt-independent energy error of 3.8e-3 in the bonded Voronoi
    disc."""
    from jaxgran.contact import pair_forces

    *_, info = pair_forces(state.particles, state.contacts, params)
    return info["energy"]["elastic"]


def _kinetic(state):
    from jaxgran.simulate import record

    return record(state).kinetic_energy


def bonded_energy(state, params):
    """[kinetic, paper-002 bond elastic (:func:`jaxgran.bonds.bond_energy`), contact] (J)."""
    import jax.numpy as jnp

    from jaxgran.bonds import bond_energy

    return jnp.stack(
        [_kinetic(state), bond_energy(state.particles, state.bonds), _contact_energy(state, params)]
    )


def interface_energy(state, params):
    """[kinetic, interface elastic (:func:`jaxgran.interface.elastic_energy`), contact] (J)."""
    import jax.numpy as jnp

    from jaxgran import interface as itf

    return jnp.stack(
        [
            _kinetic(state),
            itf.elastic_energy(state.particles, state.bonds),
            _contact_energy(state, params),
        ]
    )


# ------------------------------------------------------------------------------ scenes


def _kick(state, speed: float, cell_size: float, seed: int):
    """``state`` with seeded random velocities (m/s, rms ``speed`` per component) and angular
    velocities (rad/s, rms ``speed / cell_size``), zero net momentum."""
    import jax.numpy as jnp
    import numpy as np

    from jaxgran.state import replace

    p = state.particles
    rng = np.random.default_rng(seed)
    act = np.asarray(p.active)
    m = np.where(act, np.asarray(p.mass), 0.0)
    v = rng.normal(0.0, speed, (p.capacity, 2)) * act[:, None]
    v -= (m[:, None] * v).sum(axis=0) / m.sum()
    w = rng.normal(0.0, speed / cell_size, p.capacity) * act
    fd = p.pos.dtype
    p = replace(p, vel=jnp.asarray(v * act[:, None], fd), omega=jnp.asarray(w, fd))
    return replace(state, particles=p)


def bonded_case(cells: int, seed: int, speed: float, dtype, conservative: bool = True) -> Case:
    """The Voronoi disc of :mod:`jaxgran.scenes.bonded_brazilian`, free, unbreakable;
    undamped with frictionless contacts, or (``conservative=False``) with the scene's own
    contact law (K_t, mu, G_n) for a stability-only sweep."""
    from jaxgran.scenes import bonded as bd
    from jaxgran.scenes import bonded_brazilian as bz

    cfg = dataclasses.replace(bz.Config(), n_cells=cells, seed=seed)
    scene = bd.material_from(cfg)
    mat = dataclasses.replace(scene, eps_th=math.inf, theta_th=math.inf)
    if conservative:
        mat = dataclasses.replace(
            mat, normal_damping=0.0, tangential_damping=0.0, tangential_stiffness=0.0, friction=0.0
        )
    spec = bd.disc_specimen(
        cfg.diameter,
        cells,
        seed,
        mat,
        lloyd_iterations=cfg.lloyd_iterations,
        n_boundary=bz.n_boundary_for(cells),
    )
    state = bd.assemble(spec, mat, [], dtype=dtype)
    # the bound of the scene as it runs (K_t = K_n there), at safety 1
    dt_theory = bd.stable_dt(state.particles, state.bonds, scene, 1.0)
    h = math.sqrt(math.pi * cfg.diameter**2 / 4 / cells)
    skin = cfg.skin_fraction * h
    params = bd.make_bonded_params(mat, cfg.dt_safety * dt_theory, skin, dtype=dtype)
    grid = bd.grid_around([state], 0.6 * cfg.diameter, skin)
    state = bd.with_pair_capacity(state, bd.fit_pair_capacity([state], skin, headroom=2.0))
    return _case(
        "bonded" if conservative else "bonded-as-run",
        f"bonded Voronoi disc, {spec.n_particles} cells (paper 002)",
        _kick(state, speed, h, seed + 1),
        (params, grid, dt_theory, cfg.dt_safety),
        bonded_energy,
        spec,
        h,
    )


def _case(name, label, state, run, energy, spec, h, limits=None) -> Case:
    """A Case from the kicked state, ``run = (params, grid, dt_theory, dt_safety)``, the
    energy function, the specimen (counts), the cell size h (m) and ``limits`` known at
    build (as f)."""
    params, grid, dt_theory, dt_safety = run
    return Case(
        name=name,
        label=label,
        state=state,
        params=params,
        grid=grid,
        dt_theory=dt_theory,
        dt_safety=dt_safety,
        energy=energy,
        n_particles=spec.n_particles,
        n_bonds=spec.n_bonds,
        cell_size=h,
        limits=dict(limits or {}),
    )


def interface_case(seed: int, speed: float, dtype, conservative: bool = True) -> Case:
    """The interface-bonded disc of :mod:`jaxgran.scenes.interface_plate` (elementary
    discs), free, strengths 1e30; element dashpots, contact damping and friction off, or
    (``conservative=False``) the scene's own dashpots and contact law."""
    from jaxgran.scenes import bonded as bd
    from jaxgran.scenes import interface as si
    from jaxgran.scenes import interface_plate as pc
    from jaxgran.state import replace

    # pinned, not the plate scene's current defaults: paper 003's elementary discs, ~120 of them
    cfg = dataclasses.replace(
        pc.Config(), seed=seed, particles="discs", diameter=0.05, d_min=2.5e-3, d_max=5.0e-3
    )
    scene = si.material_from(cfg)
    mat = dataclasses.replace(scene, tensile_strength=BIG, cohesion=BIG)
    if conservative:
        mat = dataclasses.replace(mat, damping_ratio=0.0, restitution=1.0, contact_friction=0.0)
    region = ("disc", 0.5 * cfg.diameter, (0.0, 0.0))
    spec = si.make_specimen(cfg, region, mat)
    state = si.assemble(spec, mat, [], dtype=dtype)
    # f is measured against the springs' bound (the scene's rule before it counted the
    # dashpots); the scene's step, with its dashpots, is a smaller f
    dt_theory = si.stable_dt(state, scene, 1.0, dashpots=False)
    damped = si.stable_dt(si.assemble(spec, scene, [], dtype=dtype), scene, 1.0) / dt_theory
    default_f = cfg.dt_safety * damped
    skin = 0.2 * float(spec.radius.min())
    params = si.make_run_params(state, mat, default_f * dt_theory, skin)
    if conservative:
        params = replace(params, tangential_stiffness=params.tangential_stiffness * 0.0)
    grid = bd.grid_around([state], 0.6 * cfg.diameter, skin)
    state = bd.with_pair_capacity(state, bd.fit_pair_capacity([state], skin, headroom=2.0))
    h = float(math.sqrt(spec.tile_area.mean()))
    return _case(
        "interface" if conservative else "interface-as-run",
        f"interface-bonded disc, {spec.n_particles} discs (paper 003)",
        _kick(state, speed, h, seed + 1),
        (params, grid, dt_theory, default_f),
        interface_energy,
        spec,
        h,
        {"dashpots": damped},
    )


# ------------------------------------------------------------------------------ runs


def _with_dt(params, dt: float):
    import jax.numpy as jnp

    from jaxgran.state import replace

    return replace(params, dt=jnp.asarray(dt, params.dt.dtype))


_CHUNKS: dict = {}


def _energy_chunk(case: Case, chunk: int):
    """Jitted ``chunk`` steps that return the energies after every step ``[chunk, 3]``
    and the OR of the error bits (one compilation per case; dt is traced)."""
    key = (case.name, chunk)
    if key not in _CHUNKS:
        import equinox as eqx
        import jax
        import jax.numpy as jnp

        from jaxgran.integrate import step

        grid, energy = case.grid, case.energy

        @eqx.filter_jit
        def run(state, params):
            def body(carry, _):
                s, err = carry
                s, e = step(s, params, grid)
                return (s, err | e), energy(s, params)

            (state, err), es = jax.lax.scan(
                body, (state, jnp.zeros((), jnp.int32)), None, length=chunk
            )
            return state, es, err

        _CHUNKS[key] = run
    return _CHUNKS[key]


def n_steps_for(case: Case, factor: float, default_steps: int, chunk: int) -> int:
    """Steps of ``factor x dt_theory`` that cover ``default_steps`` default steps, rounded up
    to whole chunks."""
    t_phys = default_steps * case.dt_safety * case.dt_theory
    n = math.ceil(t_phys / (factor * case.dt_theory) - 1e-9)
    return chunk * max(1, math.ceil(n / chunk))


def energy_run(case: Case, factor: float, default_steps: int, chunk: int) -> dict:
    """One run at ``factor x dt_theory`` with the energies after every step; stops early
    once it has gone unstable."""
    import numpy as np

    from jaxgran.simulate import prepare
    from jaxgran.state import describe_errors

    params = _with_dt(case.params, factor * case.dt_theory)
    n = n_steps_for(case, factor, default_steps, chunk)
    state, err0 = prepare(case.state, params, case.grid)
    e0 = np.asarray(case.energy(state, params), float)
    total0 = float(e0.sum())
    run = _energy_chunk(case, chunk)
    err, worst, worst_kb, contact_max, done = int(err0), 0.0, 0.0, 0.0, 0
    while done < n:
        state, es, e = run(state, params)
        es = np.asarray(es, float)
        err |= int(e)
        done += chunk
        with np.errstate(invalid="ignore"):
            tot = es.sum(axis=1)
            dev = np.abs(tot - total0) / total0
            dev_kb = np.abs(es[:, 0] + es[:, 1] - e0[0] - e0[1]) / total0
        worst = max(worst, float(np.max(np.where(np.isfinite(dev), dev, np.inf))))
        worst_kb = max(worst_kb, float(np.nanmax(dev_kb)) if np.isfinite(dev_kb).any() else 0.0)
        contact_max = max(contact_max, float(np.nanmax(es[:, 2])) / total0)
        if err or worst > UNSTABLE_ERROR:
            break
    return {
        "factor": factor,
        "dt_s": factor * case.dt_theory,
        "steps": n,
        "steps_run": done,
        "energy_error": worst,
        "energy_error_without_contacts": worst_kb,
        "contact_share_max": contact_max,
        "errors": ", ".join(describe_errors(err)),
        "stable": not err and worst <= UNSTABLE_ERROR,
    }


def timed_run(case: Case, factor: float, default_steps: int, chunk: int, repeats: int) -> float:
    """Median wall time (s) of the plain run (no energies): ``run_segment`` of ``chunk``
    steps in a host loop, compilation excluded."""
    import jax

    from jaxgran.simulate import prepare, run_segment

    params = _with_dt(case.params, factor * case.dt_theory)
    n = n_steps_for(case, factor, default_steps, chunk)
    start, _ = prepare(case.state, params, case.grid)
    jax.block_until_ready(run_segment(start, params, case.grid, 1, chunk))  # compile
    times = []
    for _ in range(repeats):
        state = start
        t0 = time.perf_counter()
        for _ in range(n // chunk):
            state, _, _ = run_segment(state, params, case.grid, 1, chunk)
        jax.block_until_ready(state)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def refine(case: Case, lo: float, hi: float, iters: int, default_steps: int, chunk: int):
    """Bisect between a stable ``lo`` and an unstable ``hi`` factor; returns the final
    bracket and the runs."""
    runs = []
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        r = energy_run(case, mid, default_steps, chunk)
        runs.append(r)
        lo, hi = (mid, hi) if r["stable"] else (lo, mid)
    return lo, hi, runs


# ------------------------------------------------------------------------------ linear limit


def _coords(state):
    import jax.numpy as jnp

    p = state.particles
    return jnp.concatenate([p.pos[:, 0], p.pos[:, 1], p.angle])


def _placed(state, q):
    from jaxgran.state import replace

    n = state.particles.capacity
    pos = q[: 2 * n].reshape(2, n).T
    return replace(state.particles, pos=pos, angle=q[2 * n :])


def _omega_max(state, stiffness) -> float:
    """Largest angular frequency (rad/s) of ``M q'' = -K q`` (M = diag(m, m, I))."""
    import numpy as np

    p = state.particles
    m = np.asarray(p.mass, float)
    inv = 1.0 / np.sqrt(np.concatenate([m, m, np.asarray(p.inertia, float)]))
    k = np.asarray(stiffness, float)
    k = 0.5 * (k + k.T)
    w2 = np.linalg.eigvalsh(inv[:, None] * k * inv[None, :])
    return float(math.sqrt(max(w2.max(), 0.0)))


def linear_limits(case: Case) -> dict:
    """Exact Verlet limit ``2 / omega_max`` of the linearised scene, as a factor of
    ``dt_theory``: ``{"bonds": ...}`` for the interface disc; ``{"tension", "compression",
    "sum"}`` branches for the paper-002 disc (module docstring)."""
    import jax
    import jax.numpy as jnp

    from jaxgran import interface as itf
    from jaxgran.bonds import bond_kinematics
    from jaxgran.contact import pair_forces
    from jaxgran.simulate import prepare
    from jaxgran.state import replace

    state = case.state
    q0 = _coords(state)
    to_f = lambda w: 2.0 / w / case.dt_theory
    if case.name == "interface":
        u = lambda q: itf.elastic_energy(_placed(state, q), state.bonds)
        w = _omega_max(state, jax.hessian(u)(q0))
        return {"bonds": to_f(w)}

    b = state.bonds

    def bond_u(q, normal: bool):
        k = bond_kinematics(_placed(state, q), b)
        e = b.b_t * k["eps_t"] ** 2 + b.b_m * k["theta"] ** 2
        if normal:
            e = e + b.b_n * k["eps_n"] ** 2  # both signs: the tension branch
        live = k["live"] & b.intact
        return jnp.sum(jnp.where(live, 0.5 * b.area * b.length * e, 0.0))

    h_full = jax.hessian(lambda q: bond_u(q, True))(q0)
    h_shear = jax.hessian(lambda q: bond_u(q, False))(q0)
    # contacts engaged everywhere: sphero-radii grown by 1e-4 r (2e-4 r of overlap per edge)
    p = state.particles
    grown = replace(state, particles=replace(p, radius=p.radius * (1.0 + 1e-4)))
    grown, _ = prepare(grown, case.params, case.grid)

    def contact_force(q):
        pq = _placed(grown, q)
        f, t, _, _ = pair_forces(pq, grown.contacts, case.params)
        return jnp.concatenate([f[:, 0], f[:, 1], t])

    k_c = -jax.jacfwd(contact_force)(q0)
    return {
        "tension": to_f(_omega_max(state, h_full)),
        "compression": to_f(_omega_max(state, h_shear + k_c)),
        "sum": to_f(_omega_max(state, h_full + k_c)),
    }


# ------------------------------------------------------------------------------ output


def sweep(case: Case, factors, args, timed: bool = True) -> dict:
    """Energy runs (and, with ``timed``, wall times) for every factor, then the bisection of
    the stability edge."""
    rows = []
    for f in factors:
        r = energy_run(case, f, args.default_steps, args.chunk)
        if timed:
            r["wall_s"] = timed_run(case, f, args.default_steps, args.chunk, args.repeats)
        r["load"] = os.getloadavg()[0]
        rows.append(r)
        wall = f", wall {r['wall_s']:.3f} s" if timed else ""
        print(
            f"{case.name} f={f:g}: {r['steps']} steps, energy error {r['energy_error']:.3g}"
            f"{wall}, {'stable' if r['stable'] else 'UNSTABLE'} {r['errors']} "
            f"(load {r['load']:.1f})",
            flush=True,
        )
    # from the top: a float32 run at a tiny dt can fail by rounding, not by instability
    stable_grid = max((r["factor"] for r in rows if r["stable"]), default=0.0)
    first_bad = min(
        (r["factor"] for r in rows if not r["stable"] and r["factor"] > stable_grid), default=None
    )
    out = {"rows": rows, "largest_stable_grid": stable_grid, "first_unstable_grid": first_bad}
    if first_bad is not None and stable_grid > 0 and args.refine > 0:
        lo, hi, runs = refine(
            case, stable_grid, first_bad, args.refine, args.default_steps, args.chunk
        )
        out.update(largest_stable=lo, smallest_unstable=hi, refine_runs=runs)
    else:
        out.update(largest_stable=stable_grid, smallest_unstable=first_bad, refine_runs=[])
    return out


COLOURS = {"bonded": "tab:blue", "interface": "tab:orange"}
MARKERS = {"bonded": "x", "interface": "+"}


def chart(cases: list[Case], results: dict, as_run: dict, path: Path) -> None:
    """Energy error (log) and wall time against f, unstable region shaded per scene, the
    scene default and f = 1 marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator

    fig, (ax_e, ax_t) = plt.subplots(2, 1, figsize=(7.5, 8.5), sharex=True)
    cap = 10.0
    for case in cases:
        res, c = results[case.name], COLOURS.get(case.name, "k")
        rows = res["rows"]
        ok = [r for r in rows if r["stable"]]
        bad = [r for r in rows if not r["stable"]]
        x_ok, x_bad = [r["factor"] for r in ok], [r["factor"] for r in bad]
        ax_e.loglog(x_ok, [r["energy_error"] for r in ok], "o-", color=c, label=case.label)
        ax_t.loglog(x_ok, [r["wall_s"] for r in ok], "o-", color=c, label=case.label)
        if bad:
            ax_e.loglog(
                x_bad,
                [min(r["energy_error"], cap) for r in bad],
                MARKERS.get(case.name, "x"),
                color=c,
                ms=10,
                mew=2,
                label=f"{case.name}: unstable runs (error clipped at {cap:g})",
            )
            ax_t.loglog(
                x_bad, [r["wall_s"] for r in bad], MARKERS.get(case.name, "x"), color=c, ms=9, mew=2
            )
        if res["smallest_unstable"] is not None:
            edge = res["smallest_unstable"]
            for a in (ax_e, ax_t):
                a.axvspan(edge, 100.0, color=c, alpha=0.13, lw=0)
            ax_e.axvspan(0, 0, color=c, alpha=0.13, label=f"{case.name}: unstable, f >= {edge:.2f}")
        run = as_run.get(case.name)
        if run is not None and run["smallest_unstable"] is not None:
            edge = run["smallest_unstable"]
            for a in (ax_e, ax_t):
                a.axvline(edge, color=c, ls="-.", lw=1.2)
            ax_e.plot(
                [],
                [],
                color=c,
                ls="-.",
                lw=1.2,
                label=f"{case.name} with its own dashpots / contact law: "
                f"unstable from f = {edge:.2f}",
            )
    for case in cases:
        c = COLOURS.get(case.name, "k")
        for a in (ax_e, ax_t):
            a.axvline(case.dt_safety, color=c, ls="--", lw=1)
        ax_e.plot(
            [], [], color=c, ls="--", lw=1, label=f"{case.name}: default, f = {case.dt_safety:.3g}"
        )
    for a in (ax_e, ax_t):
        a.axvline(1.0, color="grey", ls=":", lw=1.5)
        a.grid(True, which="major", alpha=0.3)
    ax_e.plot([], [], color="grey", ls=":", lw=1.5, label="theoretical limit, f = 1")
    defaults = {c.dt_safety for c in cases}
    factors = sorted({r["factor"] for res in results.values() for r in res["rows"]})
    factors = [f for f in factors if f in FACTOR_GRID or f not in defaults]  # ticks: the grid
    ax_t.set_xlim(0.85 * factors[0], 1.15 * factors[-1])
    ax_t.xaxis.set_major_locator(FixedLocator(factors))
    ax_t.xaxis.set_minor_locator(NullLocator())
    ax_t.xaxis.set_minor_formatter(NullFormatter())
    ax_t.set_xticklabels([f"{f:g}" for f in factors], fontsize=7)
    lo, hi = ax_e.get_ylim()
    ax_e.set_ylim(lo, max(hi, cap) * 1e3)  # room for the legend above the curves
    ax_e.set_ylabel("energy error  max_t |E(t) - E(0)| / E(0)")
    ax_e.legend(fontsize=7, loc="upper left")
    ax_t.set_ylabel("wall time of the run (s), same physical time")
    ax_t.set_xlabel("f = dt / dt_theory   (dt_theory: the springs' Gershgorin bound, safety 1)")
    ax_t.legend(fontsize=7, loc="lower left")
    fig.suptitle(
        "Time step vs energy error and wall time: undamped, unbreakable bonded discs", fontsize=10
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _order(rows) -> float | None:
    """Slope of log(energy error) against log(f) over the stable runs with f <= 1."""
    import numpy as np

    sel = [r for r in rows if r["stable"] and r["factor"] <= 1.0 and r["energy_error"] > 0]
    if len(sel) < 2:
        return None
    x = np.log([r["factor"] for r in sel])
    y = np.log([r["energy_error"] for r in sel])
    return float(np.polyfit(x, y, 1)[0])


def _status(r) -> str:
    if r["stable"]:
        return "yes"
    why = r["errors"] or "energy error > 100 %"
    return f"**no** ({why}, stopped after {r['steps_run']} steps)"


def _bisection(res) -> list[str]:
    if not res["refine_runs"]:
        return []
    return [
        "",
        "Bisection between the largest stable and the first unstable grid factor: "
        + ", ".join(
            f"f = {r['factor']:.4f} {'stable' if r['stable'] else 'unstable'} "
            f"(error {r['energy_error']:.2g})"
            for r in res["refine_runs"]
        )
        + ".",
    ]


LIMIT_NAMES = {
    "bonds": "bonds (linear in tension and compression)",
    "tension": "tension branch (bonds only, B_n both ways)",
    "compression": "compression branch (bond shear + rotation + the contacts' 2 K_n per edge)",
    "sum": "both branches summed (a bound for every mixture)",
}


def markdown(cases: list[Case], results: dict, as_run: dict, args, meta: dict) -> list[str]:
    busy = max(meta["load_start"], meta["load_end"]) > 0.5 * (os.cpu_count() or 1)
    lines = [
        "## Time step vs energy error and wall time (`benchmarks/bench_timestep.py`)",
        "",
        f"Machine: {meta['cpu']}, {os.cpu_count()} cores; jax {meta['jax']} ({meta['backend']}), "
        f"XLA default threads; {meta['date']}; {args.dtype}; load average (1 min) at start "
        f"{meta['load_start']:.1f}, at the end {meta['load_end']:.1f}"
        + (" (other jobs were running: wall times are pessimistic and noisy)" if busy else "")
        + f". Whole benchmark {meta['total_s']:.0f} s. Command: `{meta['command']}`.",
        "",
        "Set-up: no gravity, no walls, dashpots off, bonds unbreakable, "
        "frictionless contacts (K_t = 0, mu = 0), seeded random velocities (rms "
        f"{args.speed:g} m/s per component and {args.speed:g} / h rad/s, h the mean cell "
        "size; zero net momentum). "
        f"Physical time = {args.default_steps} steps at the scene's default dt, so a run at "
        f"factor f has {args.default_steps} x f_default / f steps (rounded up to whole "
        f"segments of {args.chunk}); dt = f x dt_theory, dt_theory = the scene's "
        "springs-only `stable_dt(..., safety=1)` (Gershgorin bound min_i sqrt(2 m_i / k_i); "
        "the interface scene's own step also counts its dashpots, a smaller f). Energy error "
        "= max over every step of |E(t) - E(0)| / E(0), E = kinetic + bond elastic + contact "
        "elastic. Wall time: the plain run (`jaxgran.simulate.run_segment` of "
        f"{args.chunk} steps in a host loop), compilation excluded, median of {args.repeats}; "
        "`load` is the 1-minute load average after the row. Unstable: error bits from the "
        "step (NaN, particle left the grid, skin exceeded, overflow) or energy error > 100 %.",
        "",
    ]
    if args.dtype == "float32":
        import numpy as np

        for case in cases:
            x = float(np.max(np.abs(np.asarray(case.state.particles.pos))))
            ulp = float(np.spacing(np.float32(x)))
            f_lo = min(r["factor"] for r in results[case.name]["rows"])
            step = args.speed * f_lo * case.dt_theory
            lines += [
                f"float32 resolution ({case.name}): positions up to {x:.3g} m are spaced "
                f"{ulp:.2g} m apart; an rms-speed particle moves {step:.2g} m a step at "
                f"f = {f_lo:g} ({step / ulp:.2g} spacings). Where that is below a few spacings "
                "the energy error measures rounding of the positions, not the time step.",
                "",
            ]
    for case in cases:
        res = results[case.name]
        chk = case.limits.get("check")
        lines += [
            f"### {case.label}",
            "",
            f"{case.n_particles} particles, {case.n_bonds} bonds; dt_theory = "
            f"{case.dt_theory:.4g} s; the scene's default step is f = {case.dt_safety:.3g} "
            f"(dt = {case.dt_safety * case.dt_theory:.4g} s).",
            "",
        ]
        if chk is not None:
            lines += [
                f"Conservation check first, at f = {chk['factor']:g} ({chk['steps']} steps): "
                f"energy error {chk['energy_error']:.2e} with the contact energy, "
                f"{chk['energy_error_without_contacts']:.2e} with kinetic + bond energy only "
                f"(the contacts hold up to {chk['contact_share_max']:.1%} of E(0)).",
                "",
            ]
        lines += [
            "| f = dt / dt_theory | dt (s) | steps | energy error | error of KE + bonds only "
            "| max contact energy / E(0) | wall (s) | ms / step | load | stable |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in res["rows"]:
            star = " (default)" if math.isclose(r["factor"], case.dt_safety) else ""
            lines.append(
                f"| {r['factor']:g}{star} | {r['dt_s']:.3g} | {r['steps']} | "
                f"{r['energy_error']:.2e} | {r['energy_error_without_contacts']:.2e} | "
                f"{r['contact_share_max']:.2e} | {r['wall_s']:.3f} | "
                f"{1e3 * r['wall_s'] / r['steps']:.2f} | {r['load']:.1f} | "
                f"{_status(r)} |"
            )
        lines += _bisection(res)
        order = _order(res["rows"])
        if order is not None:
            lines += [
                "",
                f"Measured order (stable runs with f <= 1): energy error ~ f^{order:.2f}.",
            ]
        lim = {k: v for k, v in case.limits.items() if k in LIMIT_NAMES}
        if lim:
            lines += [
                "",
                "Exact limit of the linearised specimen, 2 / omega_max, as f: "
                + "; ".join(f"{LIMIT_NAMES[k]} {v:.3f}" for k, v in lim.items())
                + ".",
            ]
        if "dashpots" in case.limits:
            lines += [
                "",
                "The scene's `stable_dt` with its dashpots (safety 1) is f = "
                f"{case.limits['dashpots']:.3f}; its default step (dt_safety "
                f"{case.dt_safety / case.limits['dashpots']:g} of that) is f = "
                f"{case.dt_safety:.3f}.",
            ]
        run = as_run.get(case.name)
        if run is not None:
            lines += [
                "",
                "Stability only, with the scene's own contact law and dashpots "
                f"({run['what']}; bonds still unbreakable; same criterion, E as above is then "
                "an indicator, not an invariant): "
                + ", ".join(
                    f"f = {r['factor']:g} {'stable' if r['stable'] else 'unstable'}"
                    for r in run["rows"]
                )
                + f"; largest stable f = {run['largest_stable']:.3f}.",
            ]
            lines += _bisection(run)
        lines += [
            "",
            f"**Largest stable f = {res['largest_stable']:.3f}** (smallest unstable "
            + (f"{res['smallest_unstable']:.3f}" if res["smallest_unstable"] else "none found")
            + f"): {res['largest_stable']:.2f}x the theoretical limit f = 1 and "
            f"{res['largest_stable'] / case.dt_safety:.2f}x the scene's default f = "
            f"{case.dt_safety:.3g}.",
            "",
        ]
    lines += [
        "### Largest stable dt against the theoretical limit",
        "",
        "| scene | dt_theory (s) | default f | largest stable f (undamped) | with the scene's "
        "contact law / dashpots | linearised 2 / omega_max (f) | energy error at the default |",
        "|---|---|---|---|---|---|---|",
    ]
    for case in cases:
        res, run = results[case.name], as_run.get(case.name)
        lim = case.limits
        lin = (
            f"{lim['bonds']:.2f}"
            if "bonds" in lim
            else (
                f"{lim['sum']:.2f}-{max(lim['tension'], lim['compression']):.2f}"
                if "sum" in lim
                else "-"
            )
        )
        default = next((r for r in res["rows"] if math.isclose(r["factor"], case.dt_safety)), None)
        lines.append(
            f"| {case.label} | {case.dt_theory:.4g} | {case.dt_safety:g} | "
            f"{res['largest_stable']:.3f} | "
            + (f"{run['largest_stable']:.3f}" if run is not None else "-")
            + f" | {lin} | "
            + (f"{default['energy_error']:.2e}" if default else "-")
            + " |"
        )
    if not args.no_chart:
        rel = os.path.relpath(args.png, args.md.parent)
        lines += ["", f"![time step vs energy error]({rel})"]
    return lines + [""]


def _command(argv: list[str]) -> str:
    return " ".join(["python benchmarks/bench_timestep.py", *argv])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="bonded,interface")
    ap.add_argument("--cells", type=int, default=100, help="Voronoi cells of the bonded disc")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--factors", default=FACTORS, help="dt / dt_theory, comma-separated")
    ap.add_argument(
        "--default-steps",
        type=int,
        default=400,
        help="physical time = this many steps at the default dt",
    )
    ap.add_argument("--speed", type=float, default=0.01, help="rms initial speed (m/s)")
    ap.add_argument("--chunk", type=int, default=10, help="steps per jitted segment")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--refine", type=int, default=6, help="bisections of the stability edge")
    ap.add_argument("--no-eigen", action="store_true", help="skip the linearised limit")
    ap.add_argument(
        "--no-as-run",
        action="store_true",
        help="skip the stability sweep with the scenes' own contact law",
    )
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument(
        "--check",
        type=float,
        default=0.01,
        help="factor of the conservation check run first (0: skip)",
    )
    ap.add_argument("--no-chart", action="store_true", help="markdown only (no PNG)")
    ap.add_argument("--md", type=Path, default=ROOT / "benchmarks" / "TIMESTEP_RESULTS.md")
    ap.add_argument("--png", type=Path, default=ROOT / "docs" / "timestep_vs_energy_error.png")
    args = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", args.dtype == "float64")
    import jax.numpy as jnp

    dtype = jnp.float64 if args.dtype == "float64" else jnp.float32
    t_start = time.perf_counter()
    load_start = os.getloadavg()[0]
    print(
        f"jax {jax.__version__}, backend {jax.default_backend()}, {os.cpu_count()} cores, "
        f"load {load_start:.1f}",
        flush=True,
    )
    factors = [float(x) for x in args.factors.split(",")]
    builders = {
        "bonded": lambda c: bonded_case(args.cells, args.seed, args.speed, dtype, c),
        "interface": lambda c: interface_case(args.seed, args.speed, dtype, c),
    }
    as_run_what = {
        "bonded": "K_t = K_n = 1e8 N/m, mu = 0.3, G_n = 2529.8 1/s",
        "interface": "element dashpots zeta = 0.3, contact restitution 0.3, mu = 0.5",
    }
    cases, results, as_run = [], {}, {}
    for name in args.scenes.split(","):
        case = builders[name](True)
        print(f"{case.label}: dt_theory {case.dt_theory:.4g} s", flush=True)
        if args.check > 0:
            # at a tiny dt, over a quarter of the physical time: the error is O(dt^2)
            steps = max(args.chunk, int(0.25 * args.default_steps))
            chk = energy_run(case, args.check, steps, args.chunk)
            case.limits["check"] = chk
            print(
                f"  check f={args.check:g}: energy error {chk['energy_error']:.3g}, without "
                f"contacts {chk['energy_error_without_contacts']:.3g}",
                flush=True,
            )
        if not args.no_eigen:
            lim = linear_limits(case)
            case.limits.update(lim)
            print(f"  linearised limits (f): {lim}", flush=True)
        grid_f = sorted(set(factors) | {case.dt_safety})  # the scene's default among them
        results[name] = sweep(case, grid_f, args)
        cases.append(case)
        if not args.no_as_run:
            real = builders[name](False)
            as_run[name] = sweep(real, grid_f, args, timed=False)
            as_run[name]["what"] = as_run_what[name]
    meta = {
        "cpu": cpu_name(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "date": datetime.date.today().isoformat(),
        "load_start": load_start,
        "load_end": os.getloadavg()[0],
        "total_s": time.perf_counter() - t_start,
        "command": _command(sys.argv[1:]),
    }
    if not args.no_chart:
        chart(cases, results, as_run, args.png)
    args.md.parent.mkdir(parents=True, exist_ok=True)
    args.md.write_text("\n".join(markdown(cases, results, as_run, args, meta)))
    print(f"wrote {args.md}" + ("" if args.no_chart else f" and {args.png}"))


if __name__ == "__main__":
    main()
