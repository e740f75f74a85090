"""Breakage-check interval against the error in breakage load and time, and wall time
(issue 9): the DSM Brazilian disc (`brazilian-dsm`, paper 000 §II) with the DSM check every
``check_every`` steps.

The disc breaks at the first check where psi at the saddle reaches eps; psi is linear in the
load, so the load at which psi = eps exactly is ``F_detected x eps / psi_saddle`` (the
scene's "interpolated" force). The error of a check interval is the overshoot
``F_detected / F_exact - 1`` and the delay ``t_detected - t_exact`` (the platens close at
constant speed, so the force grows linearly once they touch: ``t_exact = t_detected -
(F_detected - F_exact) / (dF/dt)`` with dF/dt from the last two checks). Wall time: the whole
run (load to breakage and ``post_break_time`` after it), compilation of the first segment
included once per interval (each interval is a new segment length).

    python benchmarks/bench_check_interval.py            # default intervals, scene defaults
    python benchmarks/bench_check_interval.py --intervals 10,50,200 --quick

Writes a markdown section (``--md``, default ``benchmarks/CHECK_INTERVAL_RESULTS.md``) and
the chart ``docs/check_interval.png`` with the scene's default interval marked.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name, save_figure, write_markdown  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def one(check_every: int, quick: bool) -> dict:
    from jaxgran.scenes import brazilian_dsm as bz

    base = dataclasses.replace(bz.Config(), **bz.QUICK) if quick else bz.Config()
    cfg = dataclasses.replace(base, check_every=check_every, record_every=min(10, check_every))
    t0 = time.perf_counter()
    result, dsm, meas = bz.simulate_test(cfg)
    wall = time.perf_counter() - t0
    s = bz.summarize(result, dsm, meas, cfg)
    out = {
        "check_every": check_every,
        "wall_time_s": wall,
        "steps": s["steps"],
        "dt_s": s["dt_s"],
        "dsm_checks": s["dsm_checks"],
        "broke": s["broke"],
        "load": os.getloadavg()[0],
    }
    if not s["broke"]:
        return out
    f_det, f_exact = s["critical_force_N"], s["critical_force_interpolated_N"]
    f_prev = s["force_previous_check_N"]
    rate = (f_det - f_prev) / (check_every * s["dt_s"])  # N/s between the last two checks
    out.update(
        {
            "force_detected_N": f_det,
            "force_exact_N": f_exact,
            "predicted_force_N": s["predicted_critical_force_N"],
            "load_error": f_det / f_exact - 1.0,
            "delay_s": (f_det - f_exact) / rate if rate > 0 else float("nan"),
            "break_time_s": s["break_time_s"],
        }
    )
    return out


def chart(rows: list[dict], default: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["broke"]]
    n = [r["check_every"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    ax[0].loglog(n, [max(r["load_error"], 1e-12) * 100 for r in rows], "o-", label="load")
    ax[0].set_xlabel("steps between two DSM checks")
    ax[0].set_ylabel("breakage load overshoot (%)")
    ax0 = ax[0].twinx()
    ax0.loglog(n, [r["delay_s"] * 1e6 for r in rows], "s--", color="C1", label="delay")
    ax0.set_ylabel("breakage delay (us)", color="C1")
    ax[1].loglog(n, [r["wall_time_s"] for r in rows], "o-")
    ax[1].set_xlabel("steps between two DSM checks")
    ax[1].set_ylabel("wall time of the test (s)")
    for a in ax:
        a.axvline(default, color="k", ls=":", lw=1)
    ax[1].text(default, ax[1].get_ylim()[0], " default", va="bottom")
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--intervals", default="10,20,50,100,200,500,1000")
    ap.add_argument("--quick", action="store_true", help="the scene's QUICK settings")
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "CHECK_INTERVAL_RESULTS.md"))
    ap.add_argument("--png", default=str(ROOT / "docs" / "check_interval.png"))
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxgran.scenes import brazilian_dsm as bz

    default = (bz.QUICK if args.quick else {}).get("check_every", bz.Config().check_every)
    load0 = os.getloadavg()[0]
    rows = []
    for n in [int(x) for x in args.intervals.split(",") if x]:
        rows.append(one(n, args.quick))
        print(rows[-1], flush=True)
    lines = [
        "## Breakage-check interval (`python benchmarks/bench_check_interval.py"
        + (" --quick" if args.quick else "")
        + "`)",
        "",
        f"Machine: {cpu_name()}, {os.cpu_count()} cores; jax {jax.__version__} "
        f"({jax.default_backend()}); float64; {time.strftime('%Y-%m-%d')}; load average "
        f"{load0:.1f} at the start"
        + (
            " (other jobs were running: wall times are pessimistic and noisy)."
            if load0 > 0.5 * (os.cpu_count() or 1)
            else "."
        )
        + " The `brazilian-dsm` disc (paper 000 §II) with the DSM checked every n steps; "
        "one run per n; wall time includes the compilation of that segment length (the "
        "first row also compiles the BEM), so on this one-grain test it mostly shows that "
        "the interval barely changes the cost. BEM checks: particles that passed the "
        "load screen and went to the BEM.",
        "",
        "| n (steps) | BEM checks | F detected (N) | F at psi = eps (N) | load overshoot "
        "| delay (us) | steps | wall (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        mark = " (default)" if r["check_every"] == default else ""
        if r["broke"]:
            lines.append(
                f"| {r['check_every']}{mark} | {r['dsm_checks']} | {r['force_detected_N']:.2f} "
                f"| {r['force_exact_N']:.2f} | {100 * r['load_error']:.3f} % "
                f"| {1e6 * r['delay_s']:.1f} | {r['steps']} | {r['wall_time_s']:.1f} |"
            )
        else:
            lines.append(
                f"| {r['check_every']}{mark} | {r['dsm_checks']} | no break | | | "
                f"| {r['steps']} | {r['wall_time_s']:.1f} |"
            )
    write_markdown(args.md, lines, "../docs/check_interval.png", "check interval")
    chart(rows, default, Path(args.png))
    print(f"wrote {args.md} and {args.png}")


if __name__ == "__main__":
    main()
