"""Is each damped scene's time step inside the scheme's stability region? The step
linearised about the scene's own packings (``jaxgran.integrate.linear_step_radius``).

For every scene with contact dashpots a representative packing is made with the scene's
own rules (quick configurations: the settled and the loaded pile of the oedometers, the
settled deposit, the grain squeezed between the Brazilian platens, the intact
interface-bonded specimen). About it the step is linearised at the scene's time step and at
the step the springs-only rule gave before the dashpots counted (``dt_safety_before`` x
``sqrt(2 m_min / K_n)``). Reported per row: the one-mode criterion ``(Omega dt / 2)^2 +
Gamma dt`` (stable for <= 1) with the largest ``Omega^2`` and ``Gamma`` of the packing, and
the spectral radius of the linearised step with and without the dashpots (above the undamped
radius: the dashpots amplify a perturbation at every step).

    python benchmarks/diagnose_linear_stability.py      # ~6 min on 2 cores
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name  # noqa: E402

OUT = Path(__file__).resolve().parent / "LINEAR_STABILITY_RESULTS.md"


def springs_only_step(particles, params, safety: float) -> float:
    """The step of the rule before 2026-12-05 (s): ``safety x sqrt(2 m_min / K_n)``."""
    from jaxgran.integrate import critical_time_step

    return safety * critical_time_step(particles, params, dashpots=False)


def packings():
    """Yield ``(scene, packing, state, params, dt_safety now, dt_safety before)``."""
    import jax
    import numpy as np

    from jaxgran.scenes import brazilian_dsm as bz
    from jaxgran.scenes import deposit
    from jaxgran.scenes import interface_tension as it
    from jaxgran.scenes import oedometer_cantor as oc
    from jaxgran.scenes import oedometer_voronoi as ov
    from jaxgran.simulate import prepare
    from jaxgran.state import replace

    cfg = deposit.Config(**deposit.QUICK)
    res, params, _ = deposit.pour(cfg, progress=False)
    yield "deposit (QUICK)", f"settled, {res.steps} steps", res.state, params, cfg.dt_safety, 0.25
    for name, mod in (("oedometer-cantor", oc), ("oedometer-voronoi", ov)):
        cfg = mod.Config(**mod.QUICK)
        settle, load, brk, _ = oc.simulate_test(cfg, build_fn=mod.build)
        yield f"{name} (QUICK)", "settled", settle.state, settle.params, cfg.dt_safety, 0.15
        yield f"{name} (QUICK)", "end of loading", load.state, brk.params, cfg.dt_safety, 0.15
    cfg = bz.Config()
    state, params, grid = bz.build(cfg)
    walls = state.walls
    top = np.asarray(walls.normal)[:, 1] < -0.5
    point = np.asarray(walls.point).copy()
    point[top, 1] -= 2e-5  # both platens press into the grain
    state = replace(state, walls=replace(walls, point=jax.numpy.asarray(point)))
    state, _ = prepare(state, params, grid)
    yield "brazilian-dsm", "grain squeezed 20 um", state, params, cfg.dt_safety, 0.15
    cfg = it.Config(**it.QUICK)
    setup = it.build(cfg)
    state, _ = prepare(setup.state, setup.params, setup.grid)
    yield "interface-tension (QUICK)", "intact specimen", state, setup.params, cfg.dt_safety, None


def main() -> None:
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from jaxgran.integrate import critical_time_step, linear_step_radius

    t0 = time.perf_counter()
    rows = []
    for scene, packing, state, params, safety, before in packings():
        n = int(np.asarray(state.particles.active).sum())
        steps = [(f"scene's (dt_safety {safety:g})", float(params.dt))]
        if before is not None:
            old = springs_only_step(state.particles, params, before)
            steps.append((f"springs-only rule ({before:g})", old))
        crit = critical_time_step(state.particles, params)
        for label, dt in steps:
            r = linear_step_radius(state, params, dt=dt)
            rows.append((scene, packing, n, label, dt, dt / crit, r))
            print(scene, packing, label, f"{dt:.3e}", r, flush=True)
    wall = time.perf_counter() - t0
    lines = [
        "## Linearised step about the damped scenes' packings",
        "",
        f"`python benchmarks/diagnose_linear_stability.py` ({time.strftime('%Y-%m-%d')},"
        f' "{cpu_name()}", {os.cpu_count()} cores, float64, {wall:.0f} s). dt / limit: the step'
        " over `critical_time_step` (one contact, springs and dashpots) of the packing's"
        " particles. Criterion `(Omega dt / 2)^2 + Gamma dt`: the step is stable for <= 1.",
        "",
        "| scene | packing | particles | step | dt (s) | dt / limit | Omega^2 max (1/s^2) |"
        " Gamma max (1/s) | criterion | radius | radius without dashpots |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for scene, packing, n, label, dt, frac, r in rows:
        lines.append(
            f"| {scene} | {packing} | {n} | {label} | {dt:.3e} | {frac:.3f} | {r['omega2']:.3e} |"
            f" {r['gamma']:.3e} | {r['criterion']:.3f} | {r['radius']:.4f} |"
            f" {r['radius_without_dashpots']:.4f} |"
        )
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
