"""The full Voronoi oedometer of paper 000 §IV.B with the four breakage methods (issue 5),
resumable across sessions.

Each method runs the ``oedometer-voronoi`` configuration (600 cells, 137 cm box, float64)
into ``--runs/<method>`` with a checkpoint every few minutes; rerunning the script goes on
from the checkpoints and skips the finished runs (``oedometer_voronoi.run(...,
resume=True)``). Methods run one after another, or with ``--parallel`` one process per
method, each pinned to its own CPU core (``os.sched_setaffinity``): on this machine's 2 cores
two unpinned processes ran at a quarter of the speed of one each, while two pinned ones ran
at 100 and 133 steps/s at once (DSM and Mohr-Coulomb, 30 mm runs after breakage began).
Once a method has finished, its summary.json and figures are copied to ``--dest/<method>/``
(committed; the run.h5 stays in runs/), and once all four have,
``jaxgran compare`` writes ``--dest/compare.{md,json}`` and
``docs/voronoi_oedometer_methods.png``.

The paper's loading (1 mm/s for 10 s, the Config default) broke no grain of our packing
(benchmarks/voronoi_oedometer/dsm: bar force at most 110 N; the loose top layer takes the
first ~9 mm), so the comparison uses 3 mm/s for 10 s (30 mm of travel; inertial number
about 1e-5, still quasi-static): ``--bar-speed 0.003``. ``--fork-from dsm`` starts the other
methods from the DSM run's checkpoint taken before any breakage (all methods share the run
up to the first breakage; :func:`jaxgran.scenes.oedometer_cantor.fork_checkpoint`), which
also gives them one packing where the settling is not reproducible (GPU).
``benchmarks/device_voronoi_oedometer.sh`` runs the four at once on a GPU.

    python benchmarks/run_voronoi_oedometer.py --runs runs/voronoi_30mm \
        --dest benchmarks/voronoi_oedometer/travel_30mm --bar-speed 0.003 --fork-from dsm
    python benchmarks/run_voronoi_oedometer.py --methods dsm   # one method, paper loading
    python benchmarks/run_voronoi_oedometer.py --collect-only  # copy and compare, no runs
    python benchmarks/run_voronoi_oedometer.py --runs runs/voronoi_30mm \
        --dest benchmarks/voronoi_oedometer/travel_30mm --bar-speed 0.003 --parallel
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


def run_parallel(methods: list[str], args) -> int:
    """Each method in its own process on its own core (round robin over the cores this
    process may use), the forks first; then collect and compare in this process."""
    import subprocess

    if not hasattr(os, "sched_setaffinity"):
        print("error: --parallel pins processes to cores, which needs Linux", file=sys.stderr)
        return 2
    cores = sorted(os.sched_getaffinity(0))
    common = ["--runs", str(args.runs), "--dest", str(args.dest)]
    common += ["--checkpoint-minutes", str(args.checkpoint_minutes)]
    for flag in ("bar_speed", "load_time"):
        if getattr(args, flag) is not None:
            common += [f"--{flag.replace('_', '-')}", str(getattr(args, flag))]
    common += ["--quick"] if args.quick else []
    me = [sys.executable, str(Path(__file__).resolve())]
    if args.fork_from:
        forks = me + common + ["--collect-only", "--fork-from", args.fork_from]
        subprocess.run(forks + ["--methods", ",".join(methods)], check=True)
    args.runs.mkdir(parents=True, exist_ok=True)
    procs = []
    for i, method in enumerate(methods):
        core = cores[i % len(cores)]
        log_file = open(args.runs / f"{method}.log", "a")
        procs.append(
            (
                method,
                log_file,
                subprocess.Popen(
                    me + common + ["--methods", method],
                    stdout=log_file,
                    stderr=subprocess.STDOUT,
                    preexec_fn=lambda c=core: os.sched_setaffinity(0, {c}),
                ),
            )
        )
        print(f"{method}: pid {procs[-1][2].pid} on core {core}, log {log_file.name}", flush=True)
    rc = 0
    for method, log_file, proc in procs:
        rc = max(rc, proc.wait())
        log_file.close()
        print(f"{method}: exit {proc.returncode}", flush=True)
    if rc == 0:
        collect_only = me + common + ["--collect-only", "--methods", ",".join(methods)]
        rc = subprocess.run(collect_only).returncode
    return rc


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
    ap.add_argument(
        "--fork-from",
        default=None,
        help="start each method without a checkpoint of its own from this method's "
        "checkpoint, taken before any breakage (oedometer_cantor.fork_checkpoint)",
    )
    ap.add_argument(
        "--parallel",
        action="store_true",
        help="one process per method, each pinned to its own CPU core (Linux), logs in "
        "--runs/<method>.log; then collect and compare",
    )
    args = ap.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = sorted(set(methods) - set(METHODS))
    if bad:
        print(f"error: unknown methods {bad}; choose from {list(METHODS)}", file=sys.stderr)
        return 2
    if args.parallel and not args.collect_only:
        return run_parallel(methods, args)

    import dataclasses

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxgran.scenes import oedometer_voronoi as ov

    over = dict(ov.QUICK) if args.quick else {}
    if args.bar_speed is not None:
        over["bar_speed"] = args.bar_speed
    if args.load_time is not None:
        over["load_time"] = args.load_time
    from jaxgran.scenes import oedometer_cantor as oc

    source = args.runs / str(args.fork_from) / "checkpoint.pkl"
    for method in methods if args.fork_from and source.exists() else []:
        # all forks before any run goes on (the source must not have broken a grain yet)
        ckpt = args.runs / method / "checkpoint.pkl"
        if method == args.fork_from or ckpt.exists() or (ckpt.parent / "summary.json").exists():
            continue
        cfg = dataclasses.replace(ov.Config(), method=method, **over)
        cfg_src = dataclasses.replace(cfg, method=args.fork_from)
        origin = oc.fork_checkpoint(source, ckpt, cfg_src, cfg, build_fn=ov.build)
        print(f"{method}: forked from {origin}", flush=True)
    for method in methods:
        cfg = dataclasses.replace(ov.Config(), method=method, **over)
        if not args.collect_only:
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
