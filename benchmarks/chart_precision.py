"""float32 against float64 (issue 9): one chart from numbers already recorded, no new runs.

Left: contact + integration throughput of both precisions against the packing size (the
table of ``BENCHMARKS.md`` written from ``benchmarks/bench_contacts.py``). Right: energy
error of the conservative bonded Voronoi disc against the time-step factor f = dt /
dt_theory in both precisions (``benchmarks/TIMESTEP_RESULTS.md`` and
``benchmarks/TIMESTEP_RESULTS_float32.md`` from ``benchmarks/bench_timestep.py``). The
default f is marked. Regenerate the inputs first if they are stale:

    python benchmarks/chart_precision.py            # writes docs/precision.png
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import save_figure  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def table_rows(text: str, header_start: str) -> list[list[str]]:
    """Cells of the markdown table whose header row starts with ``header_start``."""
    lines = text.splitlines()
    for k, line in enumerate(lines):
        if line.startswith(header_start):
            rows = []
            for row in lines[k + 2 :]:
                if not row.startswith("|"):
                    break
                rows.append([c.strip() for c in row.strip("|").split("|")])
            return rows
    raise ValueError(f"no table starting with {header_start!r}")


def _num(cell: str) -> float:
    return float(re.sub(r"[^0-9.e+-]", "", cell.split()[0]))


def contacts(path: Path) -> dict[str, tuple[list[int], list[float]]]:
    out: dict[str, tuple[list[int], list[float]]] = {}
    for n, dtype, _, _, rate in table_rows(path.read_text(), "| particles | dtype |")[:8]:
        xs, ys = out.setdefault(dtype, ([], []))
        xs.append(int(n.replace(",", "")))
        ys.append(float(rate.replace(",", "")))
    return out


def energy(path: Path) -> tuple[list[float], list[float], list[bool]]:
    """(f, energy error, stable) of the first (bonded) table of a time-step results file."""
    rows = table_rows(path.read_text(), "| f = dt / dt_theory |")
    return (
        [_num(r[0]) for r in rows],
        [_num(r[3]) for r in rows],
        [r[-1].startswith("yes") for r in rows],
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--png", default=str(ROOT / "docs" / "precision.png"))
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rates = contacts(ROOT / "BENCHMARKS.md")
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    color = {"float32": "C0", "float64": "C1"}
    for dtype, (n, r) in rates.items():
        ax[0].plot(n, [x / 1e3 for x in r], "o-", label=dtype, color=color[dtype])
    ax[0].set_xscale("log")
    ax[0].set_xlabel("particles (dense Voronoi packing)")
    ax[0].set_ylabel("contacts + integration\n(1000 particle-steps / s)")
    ax[0].legend(fontsize=8)
    for dtype, name in (
        ("float64", "TIMESTEP_RESULTS.md"),
        ("float32", "TIMESTEP_RESULTS_float32.md"),
    ):
        f, err, ok = energy(ROOT / "benchmarks" / name)
        keep = [k for k in range(len(f)) if ok[k]]
        label = dtype + (" (default)" if dtype == "float64" else "")
        ax[1].loglog(
            [f[k] for k in keep], [err[k] for k in keep], "o-", label=label, color=color[dtype]
        )
    ax[1].axvline(0.5, color="k", ls=":", lw=1)
    ax[1].text(0.5, ax[1].get_ylim()[0], " default", va="bottom")
    ax[1].set_xlabel("f = dt / dt_theory")
    ax[1].set_ylabel("energy error, conservative\nbonded disc (stable runs)")
    ax[1].legend(fontsize=8)
    save_figure(fig, args.png)
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
