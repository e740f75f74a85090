"""Energy balance of two loading tests (issue 9): the bonded Brazilian disc (paper 002,
`bonded-brazilian`) and the Cantor pentagon oedometer with DSM breakage (paper 000,
`oedometer-cantor`).

With an energy ledger attached (:mod:`jaxgran.energy`) every step books the work of the
walls and of gravity, the energy the contact dashpots and Coulomb slip dissipate, and the
energy breakage releases (bonds as they break, particle replacement on the host). The
stored energy (kinetic + contact elastic + bond elastic) is measured from the state. The
balance

    work of walls + gravity = stored change + dashpot + friction + damping + breakage

is checked after every segment; the closure error is ``|residual| / input``.

    python benchmarks/bench_energy_balance.py                 # defaults below
    python benchmarks/bench_energy_balance.py --quick         # small scenes, a minute

Writes ``benchmarks/ENERGY_RESULTS.md`` and ``docs/energy_balance.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_erosion import MID  # noqa: E402
from machine import cpu_name, save_figure, write_markdown  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# the mid-size pile of the erosion benchmark: 12 grains, weaker grains (50 N Brazilian
# strength instead of 150.79 N) and a faster bar, so that several break in about a minute
OEDOMETER = MID
TERMS = ("input", "stored_change", "dashpot", "friction", "damping", "breakage", "residual")


def brazilian(n_cells: int, seed: int, quick: bool, **overrides) -> dict:
    """The bonded Brazilian disc to its post-peak stop, with the balance per segment;
    ``overrides`` change the scene's Config (e.g. friction and damping off)."""
    from jaxgran import energy
    from jaxgran.scenes import bonded_brazilian as bb

    base = dataclasses.replace(bb.Config(), **bb.QUICK) if quick else bb.Config()
    cfg = dataclasses.replace(base, n_cells=n_cells, seed=seed, **overrides)
    setup = bb.build(cfg)
    params = setup.params
    setup.states[0] = energy.attach(setup.states[0], params, setup.grid)
    rows: list[dict] = []

    def callback(s, rec):
        force, _ = bb.platen_force(rec)
        rows.append(
            {"time": float(s.time), "force_N": float(force[-1]), **energy.balance(s, params)}
        )

    t0 = time.perf_counter()
    res, _ = bb.simulate_test(cfg, progress=True, setup=setup, callback=callback)
    wall = time.perf_counter() - t0
    final = energy.balance(res.state, params)
    i_peak = max(range(len(rows)), key=lambda i: rows[i]["force_N"])
    return {
        "scene": f"bonded-brazilian, {n_cells} cells, seed {seed}"
        + (", friction and dashpots off" if overrides else ""),
        "config": {"n_cells": n_cells, "seed": seed, "dt_safety": cfg.dt_safety, **overrides},
        "n_bonds_broken": int(bb.bd.n_broken(res.state)),
        "steps": int(res.steps),
        "dt_s": float(params.dt),
        "wall_time_s": wall,
        "peak": rows[i_peak],
        "final": final,
        "rows": rows,
        "max_error_after_1pct": _max_error(rows),
    }


def oedometer(overrides: dict, quick: bool) -> dict:
    """The Cantor oedometer (DSM) loading stage with the balance per segment."""
    from jaxgran.scenes import oedometer_cantor as oc

    base = dataclasses.replace(oc.Config(), **oc.QUICK) if quick else oc.Config()
    cfg = dataclasses.replace(base, **overrides)
    t0 = time.perf_counter()
    settle, load, brk, info = oc.simulate_test(cfg, progress=True, energy_ledger=True)
    wall = time.perf_counter() - t0
    rows = info["energy"]
    lost = sum(float(e["mass_lost"]) for e in brk.events)
    return {
        "scene": f"oedometer-cantor (dsm), {cfg.n_particles} grains, seed {cfg.seed}",
        "config": {
            k: getattr(cfg, k)
            for k in ("n_particles", "bar_speed", "load_time", "calibration_force", "seed")
        },
        "n_events": len(brk.events),
        "mass_lost_fraction": lost / info["initial_mass"],
        "steps": int(load.steps),
        "wall_time_s": wall,
        "final": rows[-1],
        "rows": rows,
        "max_error_after_1pct": _max_error(rows),
    }


def _max_error(rows: list[dict]) -> float:
    """Largest |residual| / input once the input exceeds 1 % of its final value (the first
    segments divide round-off by almost nothing)."""
    final = abs(rows[-1]["input"])
    errs = [abs(r["residual"]) / abs(r["input"]) for r in rows if abs(r["input"]) > 0.01 * final]
    return max(errs) if errs else float("nan")


def _row(run: dict, b: dict, label: str) -> str:
    inp = b["input"]
    pct = lambda k: f"{100 * b[k] / inp:.2f}"  # noqa: E731
    return (
        f"| {run['scene']} | {label} | {inp:.4g} | {pct('stored_change')} | {pct('dashpot')} | "
        f"{pct('friction')} | {pct('breakage')} | "
        f"{100 * b['residual'] / inp:+.3f} |"
    )


def _figure(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_col = min(3, len(runs))
    n_row = -(-len(runs) // n_col)
    fig, axes = plt.subplots(n_row, n_col, figsize=(5.2 * n_col, 4.0 * n_row), squeeze=False)
    for ax in axes.flat[len(runs) :]:
        ax.set_visible(False)
    for ax, run in zip(axes.flat, runs, strict=False):
        rows = run["rows"]
        t = [1e3 * (r["time"] - rows[0]["time"]) for r in rows]
        for k in TERMS:
            if k == "damping" and not any(r[k] for r in rows):
                continue
            color, lw, ls = {"input": ("k", 2.0, "-"), "residual": ("m", 1.8, "--")}.get(
                k, (None, 1.2, "-")
            )
            ax.plot(t, [r[k] for r in rows], color=color, lw=lw, ls=ls, label=k)
        ax.set_xlabel("time since loading started (ms)")
        ax.set_ylabel("cumulative energy (J)")
        ax.set_title(
            f"{run['scene']}\nclosure error {100 * run['max_error_after_1pct']:.2f} % (max)",
            fontsize=9,
        )
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small scenes (QUICK configs)")
    ap.add_argument("--cells", type=int, default=200, help="Voronoi cells of the disc")
    ap.add_argument("--seeds", default="0,1,2", help="Voronoi seeds of the disc")
    ap.add_argument(
        "--oedometer",
        default=json.dumps(OEDOMETER),
        help="JSON overrides of the oedometer Config",
    )
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "ENERGY_RESULTS.md"))
    ap.add_argument("--png", default=str(ROOT / "docs" / "energy_balance.png"))
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "energy_balance.json"))
    ap.add_argument("--replot", action="store_true", help="tables and figure from --json")
    args = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    if args.replot:
        runs = json.loads(Path(args.json).read_text())
    else:
        over = {} if args.quick else json.loads(args.oedometer)
        cells = 150 if args.quick else args.cells
        seeds = [int(x) for x in args.seeds.split(",")]
        runs = [brazilian(cells, s, args.quick) for s in seeds]
        # the same disc with friction and dashpots off: nothing is dissipated, so the
        # residual is what the model itself does not conserve
        runs.append(brazilian(cells, seeds[0], args.quick, friction=0.0, normal_damping=0.0))
        runs.append(oedometer(over, args.quick))
        Path(args.json).write_text(json.dumps(runs, indent=1, default=float))
    _figure(runs, Path(args.png))
    cmd = "python benchmarks/bench_energy_balance.py" + (" --quick" if args.quick else "")
    lines = [
        "# Energy balance of a loading test",
        "",
        f"`{cmd}` on {cpu_name()} ({os.cpu_count()} cores), jax {jax.__version__} on the "
        f"CPU, float64, {datetime.date.today().isoformat()}.",
        "",
        "work of walls + gravity = stored change (kinetic + contact + bond elastic) + dashpot "
        "+ friction + damping + breakage; each term measured on its own (`jaxgran.energy`). "
        "Terms in % of the input; residual = input - the rest. Background damping: "
        f"{max(abs(r['final']['damping']) for r in runs):.3g} J at most (no scene here "
        "uses it).",
        "",
        "| run | when | input (J) | stored change % | dashpot % | friction % | breakage % "
        "| residual % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        if "peak" in run:
            lines.append(_row(run, run["peak"], "at the peak force"))
        lines.append(_row(run, run["final"], "end of the run"))
    lines += ["", "| run | config | steps | wall (s) | max closure error |"]
    lines += ["|---|---|---|---|---|"]
    for run in runs:
        extra = (
            f", {run['n_bonds_broken']} bonds broken"
            if "n_bonds_broken" in run
            else f", {run['n_events']} breakage events, mass lost "
            f"{100 * run['mass_lost_fraction']:.2f} %"
        )
        lines.append(
            f"| {run['scene']} | {json.dumps(run['config'])}{extra} | {run['steps']} | "
            f"{run['wall_time_s']:.1f} | {100 * run['max_error_after_1pct']:.3f} % |"
        )
    lines += [
        "",
        "Max closure error: the largest |residual| / input over the segments once the input "
        "exceeds 1 % of its final value.",
    ]
    write_markdown(args.md, lines, "../docs/energy_balance.png", "energy balance")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
