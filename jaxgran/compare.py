"""Compare breakage runs (e.g. the four methods of the same oedometric test, paper 000
§IV.B): number and types of events, mass lost, fracture-plane polarisation, the locking
effect and the final particle size distribution.

``compare(run_dirs)`` reads each directory's ``summary.json`` and ``run.h5`` (as written by
the scenes) and returns ``(markdown, data, figure)`` for ``jaxgran compare RUN_DIR...``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from . import geometry as geo
from . import io
from .breakage import metrics

__all__ = ["compare", "summarize_run"]


def _final_areas(run: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Areas (m^2) and masses (kg) of the active particles of the run's final state."""
    fin = run["final"]
    parts = fin.get("particles", fin)
    act = np.asarray(parts["active"], bool)
    verts = np.asarray(parts["verts"])[act]
    n = np.asarray(parts["n_verts"])[act]
    r = np.asarray(parts["radius"])[act]
    mass = np.asarray(parts["mass"])[act]
    area = np.array(
        [
            geo.spheropolygon_mass_properties(v[:k], rr, 1.0)[0]
            for v, k, rr in zip(verts, n, r, strict=True)
        ]
    )
    return area, mass


def summarize_run(run_dir: str | Path) -> dict[str, Any]:
    """Breakage statistics of one run directory (JSON-ready)."""
    d = Path(run_dir)
    summary = json.loads((d / "summary.json").read_text())
    run = io.read_run(d / "run.h5")
    events = [e for e in run["events"] if e.get("kind", "breakage") == "breakage"]
    m0 = summary.get("breakage_types", {}).get("mean_initial_mass")
    if m0 is None:
        fr = run["frames"]
        act = np.asarray(fr["active"][0], bool)
        m0 = float(np.asarray(fr["mass"][0])[act].mean()) if "mass" in fr else None
    if m0 is None and events:
        m0 = float(np.mean([float(e["parent_mass"]) for e in events]))
    hist = metrics.fracture_plane_histogram(events)
    lock = metrics.locking_effect(events)
    out: dict[str, Any] = {
        "run_dir": str(d),
        "scene": summary.get("scene", ""),
        "method": summary.get("method", summary.get("config", {}).get("method", "")),
        "n_events": len(events),
        "types_percent": metrics.breakage_type_percentages(events, m0)["percent"]
        if events and m0
        else {},
        "mass_lost_fraction": summary.get("mass_lost_fraction"),
        "planes_max_frequency": hist["max_frequency"],
        "planes_dominant_deg": hist["dominant_deg"],
        "plane_counts": hist["counts"].tolist(),
        "locking_chains": lock["n_locking_chains"],
        "locking_repeat_fraction": lock["repeat_fraction"],
    }
    try:
        area, mass = _final_areas(run)
        psd = metrics.particle_size_distribution(metrics.equivalent_diameters(area), mass)
        out["d10_m"], out["d50_m"] = psd["d10"], psd["d50"]
        out["psd"] = {"diameter": psd["diameter"].tolist(), "passing": psd["passing"].tolist()}
    except (KeyError, ValueError):
        out["d10_m"] = out["d50_m"] = None
    return out


def compare(run_dirs: Sequence[str | Path]):
    """``(markdown, data, figure)`` comparing breakage runs: a table per run, the JSON-ready
    data (one dict per run, see :func:`summarize_run`) and a matplotlib figure with the PSDs
    and the polar histograms of fracture planes."""
    if not run_dirs:
        raise ValueError("give at least one run directory")
    rows = [summarize_run(d) for d in run_dirs]
    head = (
        "| run | method | events | split % | frag % | chip % | mass lost % | "
        "plane max freq | dominant (deg) | locking chains | d10 (cm) | d50 (cm) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        pct = r["types_percent"]
        fmt = lambda v, s=1.0, p=1: "-" if v is None else f"{s * v:.{p}f}"  # noqa: E731
        lines.append(
            f"| {Path(r['run_dir']).name} | {r['method']} | {r['n_events']} | "
            f"{fmt(pct.get('splitting'))} | {fmt(pct.get('fragmentation'))} | "
            f"{fmt(pct.get('chipping'))} | {fmt(r['mass_lost_fraction'], 100, 3)} | "
            f"{r['planes_max_frequency']} | {r['planes_dominant_deg']:.0f} | "
            f"{r['locking_chains']} | {fmt(r['d10_m'], 100, 2)} | {fmt(r['d50_m'], 100, 2)} |"
        )
    markdown = head + "\n".join(lines) + "\n"
    from . import plot

    plt = plot.plt
    fig = plt.figure(figsize=(4 + 3 * len(rows), 4))
    ax = fig.add_subplot(1, len(rows) + 1, 1)
    for r in rows:
        if "psd" in r:
            ax.plot(np.asarray(r["psd"]["diameter"]) * 100, r["psd"]["passing"], label=r["method"])
    ax.set_xlabel("equivalent diameter (cm)")
    ax.set_ylabel("mass fraction passing")
    ax.legend(fontsize=7)
    for k, r in enumerate(rows):
        axp = fig.add_subplot(1, len(rows) + 1, k + 2, projection="polar")
        counts = np.asarray(r["plane_counts"], float)
        width = 2 * np.pi / counts.size
        axp.bar(np.arange(counts.size) * width + width / 2, counts, width=width)
        axp.set_title(f"{r['method']} planes", fontsize=8)
    fig.tight_layout()
    return markdown, rows, fig
