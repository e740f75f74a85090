"""The full Voronoi oedometer of paper 000 §IV.B with the four breakage methods (issue 5),
resumable across sessions.

Each method runs the default ``oedometer-voronoi`` configuration (600 cells, 137 cm box,
1 mm/s for 10 s, float64) into ``runs/voronoi_full/<method>`` with a checkpoint every few
minutes; rerunning the script goes on from the checkpoints and skips the finished runs
(``oedometer_voronoi.run(..., resume=True)``). Methods run one after another: two at once
on 2 cores ran at a quarter of the speed of one each. Once a method has finished, its
summary.json and figures are copied to ``benchmarks/voronoi_oedometer/<method>/``
(committed; the run.h5 stays in runs/), and once all four have, ``jaxgran compare`` writes
``benchmarks/voronoi_oedometer/compare.{md,json}`` and ``docs/voronoi_oedometer_methods.png``.

    python benchmarks/run_voronoi_oedometer.py                 # all four, resumable
    python benchmarks/run_voronoi_oedometer.py --methods dsm   # one of them
    python benchmarks/run_voronoi_oedometer.py --collect-only  # copy and compare, no runs
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("dsm", "split-cell", "cross-cut", "mohr-coulomb")


def collect(method: str, runs: Path, dest: Path) -> bool:
    """Copy a finished run's summary and figures to ``dest/method``; False if not finished."""
    src = runs / method
    if not (src / "summary.json").exists():
        return False
    out = dest / method
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src / "summary.json", out / "summary.json")
    for png in sorted(src.glob("*.png")):
        shutil.copy2(png, out / png.name)
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "voronoi_full")
    ap.add_argument("--dest", type=Path, default=ROOT / "benchmarks" / "voronoi_oedometer")
    ap.add_argument("--checkpoint-minutes", type=float, default=5.0)
    ap.add_argument("--collect-only", action="store_true", help="no simulation")
    ap.add_argument("--bar-speed", type=float, default=None, help="m/s (default: Config's, 1 mm/s)")
    ap.add_argument("--load-time", type=float, default=None, help="s (default: Config's, 10 s)")
    ap.add_argument("--quick", action="store_true", help="the small QUICK scene (smoke test)")
    args = ap.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = sorted(set(methods) - set(METHODS))
    if bad:
        print(f"error: unknown methods {bad}; choose from {list(METHODS)}", file=sys.stderr)
        return 2

    import dataclasses

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxgran.scenes import oedometer_voronoi as ov

    over = dict(ov.QUICK) if args.quick else {}
    if args.bar_speed is not None:
        over["bar_speed"] = args.bar_speed
    if args.load_time is not None:
        over["load_time"] = args.load_time
    for method in methods:
        if not args.collect_only:
            cfg = dataclasses.replace(ov.Config(), method=method, **over)
            s = ov.run(
                cfg,
                args.runs / method,
                progress=True,
                checkpoint_minutes=args.checkpoint_minutes,
                resume=True,
            )
            print(
                f"{method}: {s['n_events']} events, mass lost "
                f"{100 * s['mass_lost_fraction']:.3f} %, wall {s['wall_time_s']:.0f} s",
                flush=True,
            )
        got = collect(method, args.runs, args.dest)
        print(f"{method}: {'collected' if got else 'not finished'}")

    done = [m for m in METHODS if (args.runs / m / "summary.json").exists()]
    if len(done) == len(METHODS):
        from jaxgran.compare import compare

        markdown, rows, fig = compare([args.runs / m for m in METHODS])
        (args.dest / "compare.md").write_text(markdown)
        (args.dest / "compare.json").write_text(json.dumps(rows, indent=2, default=float))
        fig.savefig(ROOT / "docs" / "voronoi_oedometer_methods.png", dpi=120)
        print(markdown)
    else:
        print(f"finished: {done or 'none'}; the comparison waits for all four")
    return 0


if __name__ == "__main__":
    sys.exit(main())
