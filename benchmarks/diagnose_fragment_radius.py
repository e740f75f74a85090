"""Where the mass of a DSM replacement goes, and what an adaptive fragment radius saves
(issue 4), on the same parents cut by the same planes.

Runs the 12-grain Cantor pile of ``benchmarks/bench_mass_loss.py`` (variant ``merge-r05``:
r = 0.5 mm, small pieces merged, local erosion) and keeps, for every breakage event, the
parent's dilated outline pieces as the DSM cut them. For those same pieces it then measures
the area that the sphero-radius construction alone takes (the pieces below the smallest
fragment merged as the replacement merges them, then each piece eroded by its radius and swept
again; no caps):

* with the parent's radius ``r`` for every fragment (the default), and
* with the adaptive radius of ``replace_particles(min_radius=f r)`` for f = 0.5 and 0.25
  (each fragment the largest radius in ``[f r, r]`` whose rounding keeps 99.9 % of its
  piece, ``jaxgran.breakage.replace._PieceCut.radius_for``);

and splits the default's loss by the smallest interior angle of each piece's core (slivers
cut by a plane nearly parallel to a face lose their tips, about ``r^2 (1 / tan(a / 2) - (pi
- a) / 2)``). The logged loss of each event (caps and merges included) is given for
reference. This is a paired, geometric comparison: it does not say how the runs would go on
with sharper fragments (see ``docs/stability.md``).

    python benchmarks/diagnose_fragment_radius.py            # seeds 0, 1, 2, ~4 min

Writes ``benchmarks/FRAGMENT_RADIUS_RESULTS.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_erosion import MID  # noqa: E402
from bench_mass_loss import VARIANTS  # noqa: E402
from machine import cpu_name, write_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FLOORS = (0.5, 0.25)
ANGLE_BINS = (0.0, 30.0, 60.0, 180.0)  # deg, smallest interior angle of a piece's core


def capture(seed: int) -> list[dict]:
    """Breakage events of one run, each with its parent and the pieces as cut (world, m)."""
    import numpy as np

    from jaxgran.breakage import dsm
    from jaxgran.breakage import replace as rp
    from jaxgran.scenes import oedometer_cantor as oc

    kept: list[dict] = []
    original = dsm.replace_particles

    def spy(state, replacements, **kw):
        names = ("verts", "n_verts", "pos", "angle", "radius")
        arr = {k: np.asarray(getattr(state.particles, k)) for k in names}
        parents = [
            (rp._parent_core_world(arr, int(rep.index)), float(arr["radius"][int(rep.index)]),
             [np.asarray(q, float) for q in rep.pieces])
            for rep in replacements
        ]  # fmt: skip
        state, events = original(state, replacements, **kw)
        for (core, r, pieces), ev in zip(parents, events, strict=True):
            if ev["kind"] == "breakage":
                kept.append({"core": core, "r": r, "pieces": pieces,
                             "min_area": float(kw.get("min_area", 0.0)),
                             "area_lost": float(ev["area_lost"]),
                             "parent_area": float(ev["parent_area"])})  # fmt: skip
        return state, events

    cfg = dataclasses.replace(oc.Config(), **{**MID, **VARIANTS["merge-r05"]}, seed=seed)
    dsm.replace_particles = spy
    try:
        oc.simulate_test(cfg)
    finally:
        dsm.replace_particles = original
    return kept


def _min_angle(poly) -> float:
    import numpy as np

    u = np.roll(poly, 1, axis=0) - poly
    v = np.roll(poly, -1, axis=0) - poly
    c = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).min())


def rounding(pieces, r: float, floor: float | None, min_area: float):
    """[(piece area, area kept, radius, smallest core angle)] of the pieces (m^2, m, deg),
    after the merge of those below ``min_area`` as the replacement does it."""
    from jaxgran.breakage import replace as rp

    cut = rp._PieceCut(None, None, r, 0.0, r_min=None if floor is None else floor * r)
    pieces, _ = rp.merge_small_pieces(pieces, cut.kept_area, min_area)
    if len(pieces) == 1:  # all merged back: the replacement would be suppressed
        return []
    out = []
    for q in pieces:
        a = rp._area(q)
        core, rf = cut.core(q)
        kept = 0.0 if core is None else rp._spheropolygon_area(core, rf)
        out.append((a, kept, rf, 0.0 if core is None else _min_angle(core)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "FRAGMENT_RADIUS_RESULTS.md"))
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    seeds = [int(s) for s in args.seeds.split(",")]
    rows, by_angle = [], np.zeros((len(ANGLE_BINS) - 1, 2))
    radii = {f: [] for f in FLOORS}
    for seed in seeds:
        events = capture(seed)
        parent = sum(e["parent_area"] for e in events)
        row = {"seed": seed, "events": len(events),
               "logged": 100 * sum(e["area_lost"] for e in events) / parent}  # fmt: skip
        for floor in (None, *FLOORS):
            lost = 0.0
            for e in events:
                for a, kept, rf, ang in rounding(e["pieces"], e["r"], floor, e["min_area"]):
                    lost += a - kept
                    if floor is None:
                        b = np.searchsorted(ANGLE_BINS, ang, side="right") - 1
                        by_angle[min(b, len(by_angle) - 1)] += (a - kept, 1)
                    else:
                        radii[floor].append(rf / e["r"])
            row[floor] = 100 * lost / parent
        rows.append(row)
        print(row, flush=True)
    total = by_angle[:, 0].sum()
    cmd = "python benchmarks/diagnose_fragment_radius.py"
    if args.seeds != "0,1,2":
        cmd += f" --seeds {args.seeds}"
    lines = [
        "# Mass of a DSM replacement: corner rounding and the adaptive fragment radius",
        "",
        f"`{cmd}` on {cpu_name()} ({os.cpu_count()} cores), jax {jax.__version__} on the CPU, "
        f"float64, {datetime.date.today().isoformat()}. Scene: `oedometer-cantor` (DSM) with "
        f"the `merge-r05` variant of `benchmarks/bench_mass_loss.py` (12 grains, r = 0.5 mm). "
        "Every breakage event's outline pieces, as cut, are eroded again offline: the area "
        "the rounding takes, as a percentage of the parents' area summed over the events "
        "(same parents, same planes for every column; small pieces merged as the "
        "replacement merges them; no caps). `logged`: what the run's replacements lost "
        "(caps included).",
        "",
        "| seed | events | logged % | rounding, radius r % | "
        + " | ".join(f"rounding, adaptive down to {f} r %" for f in FLOORS)
        + " |",
        "|---|---|---|---|" + "---|" * len(FLOORS),
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['events']} | {r['logged']:.3f} | {r[None]:.3f} | "
            + " | ".join(f"{r[f]:.3f}" for f in FLOORS)
            + " |"
        )
    lines += [
        "",
        "Fragment radius of the adaptive rule, over all pieces: "
        + "; ".join(
            f"floor {f} r: median {np.median(radii[f]):.2f} r, at the floor "
            f"{100 * np.mean(np.isclose(radii[f], f)):.0f} %, below r "
            f"{100 * np.mean(np.asarray(radii[f]) < 1 - 1e-12):.0f} %"
            for f in FLOORS
            if radii[f]
        )
        + ".",
        "",
        "The rounding at radius r split by the smallest interior angle of each piece's core:",
        "",
        "| smallest angle (deg) | pieces | share of the rounding loss % |",
        "|---|---|---|",
    ]
    for k in range(len(by_angle)):
        lines.append(
            f"| {ANGLE_BINS[k]:.0f}-{ANGLE_BINS[k + 1]:.0f} | {int(by_angle[k, 1])} | "
            f"{100 * by_angle[k, 0] / max(total, 1e-300):.1f} |"
        )
    write_table(args.md, lines)


if __name__ == "__main__":
    main()
