"""Does a settled deposit stay at rest? The energy ledger of a resting pile, at the scene's
time step and at smaller ones.

A deposit (``jaxgran.scenes.deposit``, the quick configuration by default) is poured until it
settles; from the settled state the same stretch of simulated time (``--hold`` s) is run with
the energy ledger attached, at the scene's ``dt``, at ``dt / 2`` and at the step of the
springs-only rule the scene had before the limit counted the dashpots (docs/stability.md),
once with the scene's dashpots and once without them. A pile at rest takes almost no work
from gravity, so the dashpot and friction terms it books must be almost zero and the
balance residual must stay at round-off. Reported per run: kinetic energy at the end, the
ledger's terms, the residual, and the largest change of a grain's contact force from one
step to the next (a force that flips every step is an oscillation at the Nyquist frequency
of the scheme, which no physical mode of the pile has).

    python benchmarks/diagnose_dashpot_stability.py            # quick deposit, ~2 min
    python benchmarks/diagnose_dashpot_stability.py --full     # the default deposit
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from diagnose_linear_stability import springs_only_step  # noqa: E402
from machine import cpu_name  # noqa: E402

OUT = Path(__file__).resolve().parent / "DASHPOT_STABILITY_RESULTS.md"


def hold(state, params, grid, n_steps: int) -> dict:
    """Run ``n_steps`` from ``state`` with the ledger; the balance and the force flips."""
    import jax
    import numpy as np

    from jaxgran import energy
    from jaxgran.integrate import step

    one = jax.jit(lambda s: step(s, params, grid))
    s = energy.attach(state, params, grid)
    flip = 0.0
    prev = np.asarray(s.particles.force)
    for _ in range(n_steps):
        s, err = one(s)
        assert int(err) == 0, int(err)
        f = np.asarray(s.particles.force)
        flip = max(flip, float(np.abs(f - prev).max()))
        prev = f
    b = energy.balance(s, params)
    keys = ("kinetic", "body_work", "dashpot", "friction", "residual")
    return {k: b[k] for k in keys} | {"max_force_change_N": flip}


def settled_scene(scene: str, full: bool):
    """The scene's pile after its own settling: ``(result, params, grid, cfg, label)``.
    ``deposit`` (QUICK unless ``full``) pours until its stop rule; ``cantor`` (the default
    24-pentagon oedometer) settles for its ``settle_time`` before any loading."""
    import math

    from jaxgran.simulate import simulate

    if scene == "deposit":
        from jaxgran.scenes import deposit

        cfg = deposit.Config()
        if not full:
            cfg = dataclasses.replace(cfg, **deposit.QUICK)
        result, params, _ = deposit.pour(cfg, progress=False)
        return result, params, result.grid, cfg, f"deposit ({'default' if full else 'QUICK'})"
    from jaxgran.scenes import oedometer_cantor as oc

    cfg = oc.Config()
    state, params, grid = oc.build(cfg)
    n = int(math.ceil(cfg.settle_time / float(params.dt)))
    kw = dict(record_every=cfg.record_every, records_per_segment=cfg.records_per_segment)
    result = simulate(state, params, grid, n_steps=n, progress=False, **kw)
    return result, params, result.grid, cfg, "Cantor oedometer before loading (default)"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", choices=["deposit", "cantor"], default="deposit")
    ap.add_argument("--full", action="store_true", help="the default deposit, not QUICK")
    ap.add_argument("--hold", type=float, default=0.02, help="simulated seconds held (s)")
    args = ap.parse_args()

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from jaxgran.state import replace

    t0 = time.perf_counter()
    result, params, grid, cfg, scene_label = settled_scene(args.scene, args.full)
    peak = float(np.max(result.series["kinetic_energy"]))
    settled = result.state
    p = settled.particles
    weight = float(jnp.sum(jnp.where(p.active, p.mass, 0.0))) * 9.81
    # the scene's step, half of it, and the step of the springs-only rule it had before the
    # limit counted the dashpots (0.25 x for the deposit, 0.15 x for the oedometer)
    before = springs_only_step(p, params, 0.25 if args.scene == "deposit" else 0.15)
    rows = []
    for label, prm0 in (
        ("dashpots", params),
        (
            "no dashpots",
            replace(
                params,
                normal_damping=jnp.zeros_like(params.normal_damping),
                tangential_damping=jnp.zeros_like(params.tangential_damping),
            ),
        ),
    ):
        for which, dt in (
            ("scene's", float(params.dt)),
            ("scene's / 2", float(params.dt) / 2),
            ("springs-only rule", before),
        ):
            prm = replace(prm0, dt=jnp.asarray(dt, params.dt.dtype))
            n = int(round(args.hold / dt))
            r = hold(settled, prm, grid, n)
            rows.append({"damping": label, "step": which, "dt_s": dt, "steps": n} | r)
            print(json.dumps(rows[-1]), flush=True)
    wall = time.perf_counter() - t0
    flags = (f" --scene {args.scene}" if args.scene != "deposit" else "") + (
        " --full" if args.full else ""
    )
    title = f"## {scene_label}, held at rest: the energy ledger against the time step"
    lines = [
        title,
        "",
        f"`python benchmarks/diagnose_dashpot_stability.py{flags}`"
        f' ({time.strftime("%Y-%m-%d")}, "{cpu_name()}", {os.cpu_count()} cores, float64,'
        f" {wall:.0f} s). {int(np.asarray(p.active).sum())} grains, restitution"
        f" {cfg.restitution}, K_n = {cfg.normal_stiffness:g} N/m, settled by the scene's own"
        f" rule ({result.steps} steps, kinetic energy"
        f" {float(result.series['kinetic_energy'][-1]):.2e} J against a peak of {peak:.3g} J),"
        f" then held for {args.hold} s of simulated time with the ledger attached. Weight of"
        f" the pile {weight:.3g} N.",
        "",
        "| dashpots | step | dt (s) | steps | kinetic energy at the end (J) | gravity's work (J) |"
        " dashpot booked (J) | friction booked (J) | balance residual (J) |"
        " largest step-to-step change of a grain's force (N) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['damping']} | {r['step']} | {r['dt_s']:.3e} | {r['steps']} |"
            f" {r['kinetic']:.2e} |"
            f" {r['body_work']:.2e} | {r['dashpot']:.2e} | {r['friction']:.2e} |"
            f" {r['residual']:.2e} | {r['max_force_change_N']:.2e} |"
        )
    # one section per scene: this run's replaces its own, the others stay
    kept = []
    if OUT.exists():
        for sec in OUT.read_text().split("\n## "):
            sec = sec if sec.startswith("## ") else "## " + sec
            if sec.strip() and not sec.startswith(title):
                kept.append(sec.rstrip())
    OUT.write_text("\n\n".join(kept + ["\n".join(lines)]) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
