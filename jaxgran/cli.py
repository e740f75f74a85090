"""The ``jaxgran`` command: run a scene, redraw figures, print environment information.

jaxgran run deposit [--out DIR] [--set key=value ...] [--quick] [--vtk] [--no-progress]
jaxgran run deposit --config runs/deposit/summary.json --set seed=1   (repeat, varied)
jaxgran run oedometer-voronoi --out DIR --resume   (continue an interrupted long run)
jaxgran plot runs/deposit/run.h5 [--out DIR]
jaxgran info
jaxgran scenes
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _enable_x64(flag: bool) -> None:
    import jax

    jax.config.update("jax_enable_x64", flag)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="jaxgran", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    run_p = sub.add_parser("run", help="run a scene and write summary.json, run.h5, figures")
    run_p.add_argument("scene", help="scene name (see `jaxgran scenes`)")
    run_p.add_argument("--out", type=Path, default=None, help="output folder (runs/<scene>)")
    run_p.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a configuration value (repeatable)",
    )
    run_p.add_argument(
        "--config",
        type=Path,
        default=None,
        metavar="FILE",
        help="settings from a JSON file: a run's summary.json (repeat that run) or an "
        "object of settings; --set applies on top",
    )
    run_p.add_argument("--quick", action="store_true", help="small, fast version")
    run_p.add_argument("--vtk", action="store_true", help="also write VTK files for ParaView")
    run_p.add_argument("--no-progress", action="store_true", help="no progress bar")
    run_p.add_argument("--float32", action="store_true", help="run in float32 (default float64)")
    run_p.add_argument(
        "--resume",
        action="store_true",
        help="continue from OUT/checkpoint.pkl of an interrupted run (long scenes only)",
    )
    run_p.add_argument(
        "--checkpoint-minutes",
        type=float,
        default=None,
        help="save OUT/checkpoint.pkl this often during a long scene (default 10; 0: never)",
    )

    plot_p = sub.add_parser("plot", help="redraw the figures of a run.h5")
    plot_p.add_argument("path", type=Path)
    plot_p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for the figures (default: run.h5's folder; for any other file, a "
        "folder named after it beside it)",
    )
    plot_p.add_argument("--vtk", action="store_true", help="also write VTK files")

    cal = sub.add_parser(
        "calibrate-eps",
        help="critical strain-energy level eps (Pa) from a Brazilian critical force",
    )
    cal.add_argument("--force", type=float, required=True, help="critical force F (N)")
    cal.add_argument("--radius", type=float, required=True, help="disc radius R (m)")
    cal.add_argument("--thickness", type=float, default=0.01, help="thickness t (m)")
    cal.add_argument("--poisson-ratio", type=float, default=0.3)
    cal.add_argument("--plane", choices=["stress", "strain"], default="stress")
    cal.add_argument("--no-bem", action="store_true", help="skip the BEM check (analytic only)")

    cmp_p = sub.add_parser("compare", help="lay several runs side by side (table + figure)")
    cmp_p.add_argument(
        "runs", nargs="+", type=Path, help="run folders (with summary.json and run.h5)"
    )
    cmp_p.add_argument("--out", type=Path, default=Path("compare"), help="output folder")

    prog_p = sub.add_parser(
        "progress", help="how far an interrupted or running long scene has got (its checkpoint)"
    )
    prog_p.add_argument("path", type=Path, help="OUT folder of the run, or its checkpoint.pkl")

    sub.add_parser("info", help="versions, devices, precision")
    sub.add_parser("scenes", help="list the scenes")
    set_p = sub.add_parser(
        "settings", help="a scene's settings: default, allowed values, units and meaning"
    )
    set_p.add_argument("scene", help="scene name (see `jaxgran scenes`)")

    args = parser.parse_args(argv)
    if args.command == "run":
        return _run(args)
    if args.command == "plot":
        return _plot(args)
    if args.command == "compare":
        return _compare(args)
    if args.command == "calibrate-eps":
        return _calibrate(args)
    if args.command == "progress":
        return _progress(args.path)
    if args.command == "info":
        return _info()
    if args.command == "settings":
        return _settings(args.scene)
    if args.command == "scenes":
        from .scenes import SCENES

        for name, mod in SCENES.items():
            doc = (mod.__doc__ or "").strip().split("\n")[0]
            print(f"{name:24s} {doc}")
        return 0
    return 2


def _progress(path: Path) -> int:
    import json

    _enable_x64(True)  # the arrays are read, not computed with
    from .scenes.oedometer_cantor import checkpoint_progress

    ckpt = path / "checkpoint.pkl" if path.is_dir() else path
    if not ckpt.exists():
        done = path / "summary.json" if path.is_dir() else None
        state = "finished (summary.json, no checkpoint)" if done and done.exists() else "none"
        print(f"{path}: no checkpoint; {state}", file=sys.stderr)
        return 1
    try:
        info = checkpoint_progress(ckpt)
    except (ValueError, KeyError, EOFError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(info, indent=2))
    return 0


def _run(args) -> int:
    import dataclasses

    _enable_x64(not args.float32)
    from .errors import SceneError
    from .scenes import SCENES
    from .scenes.base import (
        apply_overrides,
        dumps,
        parse_sets,
        read_config_file,
        unrecorded_settings,
    )

    if args.scene not in SCENES:
        print(f"unknown scene {args.scene!r}; available: {', '.join(SCENES)}", file=sys.stderr)
        return 2
    mod = SCENES[args.scene]
    cfg = mod.Config()
    try:
        if args.quick:
            cfg = dataclasses.replace(cfg, **mod.QUICK)
        sets = parse_sets(args.sets)
        if args.config is not None:
            stored = read_config_file(args.config, args.scene)
            cfg = apply_overrides(cfg, stored)
            gaps = unrecorded_settings(args.config, cfg, {**stored, **sets})
            if gaps:
                told = ", ".join(f"{k}={v!r}" for k, v in gaps.items())
                print(
                    f"warning: {args.config} does not record {told}; they take the values "
                    "shown, which may differ from what that run used (settings added since; "
                    "--set them to be sure)",
                    file=sys.stderr,
                )
        cfg = apply_overrides(cfg, sets)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = args.out or Path("runs") / args.scene
    extra = {}
    if args.resume or args.checkpoint_minutes is not None:
        import inspect

        if "resume" not in inspect.signature(mod.run).parameters:
            print(f"error: scene {args.scene!r} has no checkpoints", file=sys.stderr)
            return 2
        extra["resume"] = args.resume
        if args.checkpoint_minutes is not None:
            extra["checkpoint_minutes"] = args.checkpoint_minutes
    try:
        summary = mod.run(cfg, out, progress=not args.no_progress, vtk=args.vtk, **extra)
    except SceneError as exc:  # settings the scene cannot be built from; other errors keep
        print(f"error: {exc}", file=sys.stderr)  # their traceback
        return 2
    print(dumps(summary))
    print(f"outputs in {out}/")
    return 0


def _plot(args) -> int:
    from . import io, plot

    if not args.path.exists():
        print(f"error: {args.path} does not exist", file=sys.stderr)
        return 2
    try:
        run = io.read_run(args.path)
    except (OSError, ValueError, KeyError) as exc:  # not a run file, or a truncated one
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # a run's other record files (e.g. run_sigma3_5MPa.h5 beside run.h5) draw into a folder
    # of their own, not over the figures of run.h5
    default = args.path.parent if args.path.name == "run.h5" else args.path.with_suffix("")
    out = args.out or default
    for p in plot.plot_run(run, out):
        print(p)
    if args.vtk:
        for p in io.write_vtk(out / "vtk" / "frame", run):
            print(p)
    return 0


def _compare(args) -> int:
    import json

    from .compare import compare

    for name in ("summary.json", "run.h5"):  # compare reads the events from run.h5
        missing = [str(r) for r in args.runs if not (r / name).exists()]
        if missing:
            print(f"error: no {name} in {', '.join(missing)}", file=sys.stderr)
            return 2
    markdown, rows, fig = compare(args.runs)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compare.md").write_text(markdown)
    (args.out / "compare.json").write_text(json.dumps(rows, indent=2, default=float))
    fig.savefig(args.out / "compare.png", dpi=120)
    print(markdown)
    return 0


def _calibrate(args) -> int:
    import json

    _enable_x64(True)
    from .breakage.dsm import calibration_report

    if args.force <= 0 or args.radius <= 0 or args.thickness <= 0:
        print("error: force, radius and thickness must be positive", file=sys.stderr)
        return 2
    report = calibration_report(
        args.force,
        args.radius,
        poisson_ratio=args.poisson_ratio,
        plane=args.plane,
        thickness=args.thickness,
        bem_check=not args.no_bem,
    )
    print(json.dumps(report, indent=2, default=float))
    return 0


def _settings(scene: str) -> int:
    from .scenes import SCENES
    from .scenes.limits import describe_settings

    if scene not in SCENES:
        print(f"unknown scene {scene!r}; available: {', '.join(SCENES)}", file=sys.stderr)
        return 2
    rows = describe_settings(SCENES[scene].Config)
    width = {k: max(len(k), *(len(r[k]) for r in rows)) for k in ("name", "default")}
    print(f"{'name':<{width['name']}}  {'default':<{width['default']}}  allowed; meaning")
    for r in rows:
        meaning = f"; {r['meaning']}" if r["meaning"] else ""
        head = f"{r['name']:<{width['name']}}  {r['default']:<{width['default']}}"
        print(f"{head}  {r['allowed']}{meaning}")
    print(f"\nset any of them with: jaxgran run {scene} --set NAME=VALUE")
    return 0


def _info() -> int:
    import jax

    from . import __version__

    print(f"jaxgran {__version__}")
    print(f"jax {jax.__version__}, backend {jax.default_backend()}")
    print(f"devices: {jax.devices()}")
    print(f"x64 enabled: {jax.config.jax_enable_x64}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
