"""Compare breakage runs (e.g. the four methods of the same oedometric test, paper 000
§IV.B): number of events and fragments, breakage types, mass lost, fracture-plane
polarisation, the locking effect, the final particle size distribution, stability (NaN,
escaped particles, kinetic-energy spikes) and wall time.

``compare(run_dirs)`` reads each directory's ``summary.json`` and ``run.h5`` (as written by
the scenes) and returns ``(markdown, data, figure)`` for ``jaxgran compare RUN_DIR...``; the
figure has the final breakage patterns with the fragments' centroids (paper 000 Figs. 13-14)
above the PSDs and the polar histograms of fracture planes (Figs. 15-16).
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


def _spike_stats(spikes: list[dict[str, float]]) -> dict[str, float | None]:
    """Largest kinetic-energy peak (J) and ratio to the baseline, and the median decay time
    (s), over the events' spikes (:func:`jaxgran.breakage.metrics.kinetic_energy_spikes`)."""
    peaks = np.array([s["peak"] for s in spikes], float)
    ratios = np.array([s["ratio"] for s in spikes], float)
    decay = np.array([s["decay_s"] for s in spikes], float)
    ok = np.isfinite(peaks)
    return {
        "ke_peak_max_J": float(peaks[ok].max()) if ok.any() else None,
        "ke_ratio_max": float(ratios[ok].max()) if ok.any() else None,
        "ke_decay_median_s": float(np.median(decay[np.isfinite(decay)]))
        if np.isfinite(decay).any()
        else None,
    }


def _final_pattern(run: dict[str, Any]):
    """World outlines of the final particles, whether each is a fragment (its uid is not
    among the first frame's), and the fragments' centroids (m)."""
    from .io import world_vertices_np

    fin = run["final"]
    parts = fin.get("particles", fin)
    uid0 = np.asarray(run["frames"]["uid"][0])[np.asarray(run["frames"]["active"][0], bool)]
    act = np.asarray(parts["active"], bool)
    wv = world_vertices_np(
        np.asarray(parts["verts"]),
        np.asarray(parts["n_verts"]),
        np.asarray(parts["pos"]),
        np.asarray(parts["angle"]),
    )
    new = ~np.isin(np.asarray(parts["uid"]), uid0)
    centroids = np.asarray(parts["pos"])[act & new]
    return wv, np.asarray(parts["n_verts"]), np.asarray(parts["radius"]), act, new, centroids


def summarize_run(run_dir: str | Path) -> dict[str, Any]:
    """Breakage statistics of one run directory (JSON-ready)."""
    d = Path(run_dir)
    summary = json.loads((d / "summary.json").read_text())
    run = io.read_run(d / "run.h5")
    events = [e for e in run["events"] if e.get("kind", "breakage") == "breakage"]
    # Table III's m_r is relative to the mean initial particle mass: the scene's own
    # classification (with that mass) when it covers these events, else recomputed from
    # the mass the summary records; never from the parents' masses (fragments of fragments
    # would shift the reference)
    types = summary.get("breakage_types", {})
    m0 = summary.get("mean_initial_mass_kg", types.get("mean_initial_mass"))
    if "percent" in types and types.get("n_events") == len(events):
        types_percent = dict(types["percent"])
    elif events and m0:
        types_percent = metrics.breakage_type_percentages(events, m0)["percent"]
    else:
        types_percent = {}
    hist = metrics.fracture_plane_histogram(events)
    lock = metrics.locking_effect(events)
    out: dict[str, Any] = {
        "run_dir": str(d),
        "scene": summary.get("scene", ""),
        "method": summary.get("method", summary.get("config", {}).get("method", "")),
        "n_events": len(events),
        "types_percent": types_percent,
        "mass_lost_fraction": summary.get("mass_lost_fraction"),
        "planes_max_frequency": hist["max_frequency"],
        "planes_dominant_deg": hist["dominant_deg"],
        "plane_counts": hist["counts"].tolist(),
        "locking_chains": lock["n_locking_chains"],
        "locking_repeat_fraction": lock["repeat_fraction"],
        "locking_repeats": lock["n_repeats"],
        "locking_repeats_by_chance": lock["repeats_by_chance"],
        "n_fragments": int(sum(len(np.atleast_1d(e["fragment_uids"])) for e in events)),
        "finite": summary.get("finite"),
        "escaped": summary.get("escaped"),
        "wall_time_s": summary.get("wall_time_s"),
        "forked_from": summary.get("forked_from"),
        **_spike_stats(summary.get("ke_spikes") or []),
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
        "| run | method | events | fragments | split % | frag % | chip % | mass lost % | "
        "plane max freq | dominant (deg) | locking chains | repeats (by chance) | d10 (cm) | "
        "d50 (cm) | finite | escaped | KE peak max (J) | KE decay median (s) | wall (s) |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        pct = r["types_percent"]
        fmt = lambda v, s=1.0, p=1: "-" if v is None else f"{s * v:.{p}f}"  # noqa: E731
        lines.append(
            f"| {Path(r['run_dir']).name} | {r['method']} | {r['n_events']} | "
            f"{r['n_fragments']} | "
            f"{fmt(pct.get('splitting'))} | {fmt(pct.get('fragmentation'))} | "
            f"{fmt(pct.get('chipping'))} | {fmt(r['mass_lost_fraction'], 100, 3)} | "
            f"{r['planes_max_frequency']} | {r['planes_dominant_deg']:.0f} | "
            f"{r['locking_chains']} | {r['locking_repeats']} "
            f"({r['locking_repeats_by_chance']:.1f}) | "
            f"{fmt(r['d10_m'], 100, 2)} | {fmt(r['d50_m'], 100, 2)} | "
            f"{r['finite']} | {r['escaped']} | {fmt(r['ke_peak_max_J'], 1, 3)} | "
            f"{fmt(r['ke_decay_median_s'], 1, 4)} | {fmt(r['wall_time_s'], 1, 0)} |"
        )
    markdown = head + "\n".join(lines) + "\n"
    forks = [r for r in rows if r.get("forked_from")]
    if forks:
        markdown += (
            "\nForked runs (same state up to the fork, taken before any breakage; their wall "
            "time includes the source's): "
            + "; ".join(
                f"{Path(r['run_dir']).name} from {r['forked_from']['method']} at t = "
                f"{r['forked_from']['t_load']:.3f} s of loading"
                for r in forks
            )
            + "\n"
        )
    from . import plot

    plt = plot.plt
    n = len(rows) + 1
    fig = plt.figure(figsize=(4 + 3.2 * len(rows), 7.5))
    for k, d in enumerate(run_dirs):
        try:
            wv, nv, rad, act, new, cen = _final_pattern(io.read_run(Path(d) / "run.h5"))
        except (KeyError, OSError):
            continue
        axb = fig.add_subplot(2, n, k + 2)
        plot.draw_particles(
            axb, wv, nv, rad, act, values=new.astype(float), cmap="coolwarm", colorbar=False
        )
        for coll in axb.collections:
            coll.set_clim(0.0, 1.0)
        if len(cen):
            axb.plot(cen[:, 0] * 100, cen[:, 1] * 100, "k.", ms=2)
        axb.set_title(f"{rows[k]['method']}: fragments (red), centroids", fontsize=8)
    ax = fig.add_subplot(2, n, n + 1)
    for r in rows:
        if "psd" in r:
            ax.plot(np.asarray(r["psd"]["diameter"]) * 100, r["psd"]["passing"], label=r["method"])
    ax.set_xlabel("equivalent diameter (cm)")
    ax.set_ylabel("mass fraction passing")
    ax.legend(fontsize=7)
    for k, r in enumerate(rows):
        axp = fig.add_subplot(2, n, n + k + 2, projection="polar")
        counts = np.asarray(r["plane_counts"], float)
        width = 2 * np.pi / counts.size
        axp.bar(np.arange(counts.size) * width + width / 2, counts, width=width)
        axp.set_title(f"{r['method']} planes", fontsize=8)
    fig.tight_layout()
    return markdown, rows, fig
