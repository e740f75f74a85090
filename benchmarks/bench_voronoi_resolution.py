"""Voronoi resolution against the scatter of the Brazilian tensile strength and wall time
(issue 9): the bonded Brazilian disc (`bonded-brazilian`, paper 002 §3) meshed with n cells,
several seeds per n, each run to failure one after another (float64).

Each run is cached as ``benchmarks/voronoi_resolution/raw/brazilian_c<n>_s<seed>.json`` (the
fields of ``benchmarks/run_bonded_acceptance.py brazilian``; ``--raw`` elsewhere), so a
repeated call only adds what is missing (delete the folder to rerun after a model change):

    python benchmarks/bench_voronoi_resolution.py          # 100, 200, 500, 800 cells, ~45 min
    python benchmarks/bench_voronoi_resolution.py --cells 100,200,400 --seeds 6

Writes ``benchmarks/VORONOI_RESOLUTION_RESULTS.md`` and ``docs/voronoi_resolution.png``
(sigma_t per run, mean and standard deviation against n; wall time against n; the scene's
default n marked).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name, save_figure, write_markdown  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def one(cells: int, seed: int, raw: Path) -> dict:
    path = raw / f"brazilian_c{cells}_s{seed}.json"
    if path.exists():
        return json.loads(path.read_text())
    from run_bonded_acceptance import brazilian_run

    from jaxgran.scenes import bonded_brazilian as bz

    m = brazilian_run(dataclasses.replace(bz.Config(), n_cells=cells), seed)
    m["load_average"] = os.getloadavg()[0]
    raw.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(m, indent=1, default=float))
    return m


def chart(table: dict, default: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for n, runs in table.items():
        s = [r["tensile_strength_Pa"] / 1e6 for r in runs]
        ax[0].plot([n] * len(s), s, "o", color="C0", alpha=0.5)
        ax[0].errorbar(n, statistics.mean(s), statistics.stdev(s), fmt="s", color="k", capsize=4)
        ax[1].plot([n] * len(runs), [r["wall_time_s"] for r in runs], "o", color="C1", alpha=0.6)
    from matplotlib.ticker import NullFormatter

    ticks = sorted(set(table) | {default})
    for a in ax:
        a.set_xscale("log")
        a.set_xticks(ticks, [str(n) for n in ticks])
        a.xaxis.set_minor_formatter(NullFormatter())
        a.axvline(default, color="k", ls=":", lw=1)
        a.set_xlabel("Voronoi cells")
    ax[0].set_ylabel("sigma_t = 2 F_max / (pi D T) (MPa)")
    ax[1].set_yscale("log")
    ax[1].set_ylabel("wall time to failure (s)")
    ax[1].text(default, ax[1].get_ylim()[0], " default", va="bottom")
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default="100,200,500,800")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--raw", default=str(ROOT / "benchmarks" / "voronoi_resolution" / "raw"))
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "VORONOI_RESOLUTION_RESULTS.md"))
    ap.add_argument("--png", default=str(ROOT / "docs" / "voronoi_resolution.png"))
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxgran.scenes import bonded_brazilian as bz

    load0 = os.getloadavg()[0]
    table = {}
    for n in [int(x) for x in args.cells.split(",") if x]:
        table[n] = [one(n, s, Path(args.raw)) for s in range(args.seeds)]
        print(n, [round(r["tensile_strength_Pa"] / 1e6, 1) for r in table[n]], flush=True)
    default = bz.Config().n_cells
    lines = [
        "## Voronoi resolution (`python benchmarks/bench_voronoi_resolution.py`)",
        "",
        f"Machine: {cpu_name()}, {os.cpu_count()} cores; jax {jax.__version__}; float64; "
        f"{time.strftime('%Y-%m-%d')}; load average {load0:.1f} when this table was made "
        "(each run's own load average, where recorded, is in its raw file; runs made while "
        "other jobs ran have pessimistic wall times). The `bonded-brazilian` disc "
        f"(D = 10 cm, paper 002 Table 1 material) with n cells, {args.seeds} seeds per n, "
        f"one after another; the scene's default is n = {default}.",
        "",
        "| cells | runs | sigma_t mean (MPa) | std (MPa) | std / mean | crack angle, mean (deg) "
        "| wall time, median (s) | steps, median |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, runs in table.items():
        s = [r["tensile_strength_Pa"] / 1e6 for r in runs]
        ang = [r["crack_angle_from_loading_axis_deg"] for r in runs]
        lines.append(
            f"| {n} | {len(runs)} | {statistics.mean(s):.1f} | {statistics.stdev(s):.1f} "
            f"| {statistics.stdev(s) / statistics.mean(s):.3f} | {statistics.mean(ang):.1f} "
            f"| {statistics.median(r['wall_time_s'] for r in runs):.0f} "
            f"| {statistics.median(r['steps'] for r in runs):.0f} |"
        )
    write_markdown(args.md, lines, "../docs/voronoi_resolution.png", "voronoi resolution")
    chart(table, default, Path(args.png))
    print(f"wrote {args.md} and {args.png}")


if __name__ == "__main__":
    main()
