"""Forward against reverse mode for the calibration loss's gradient (`calibration.fit`).

`fit.make_functions(problem, gradient)` gives the value and gradient of the loss of the
free log groups, either by forward mode (the jitted Jacobian of the ensemble means by
``jax.jacfwd``, one run of every lab that carries one tangent per free group, and the
loss's chain rule on the host) or by reverse mode (jitted ``jax.value_and_grad``: a forward
and a checkpointed reverse pass). For each case and mode, in a fresh subprocess: the time
to compile that jitted program (lower + compile), the median wall time of several
evaluations of the value and gradient after it, the peak resident memory (the program is
compiled twice, once ahead of time to be timed and once by its first call), and the
gradient, so that the two modes can be compared.

Cases:

* ``disc20-freeN``: one 20-cell Brazilian disc (seed 3) with the twin's smooth lab
  (``calibration.twin.scene_options``: surrogate width 1, global damping, 5 % platen
  strain), as in ``tests/test_calibration.py``, N = 1, 3, 6 free groups;
* ``twin-free3``: the defaults of ``python -m calibration.twin`` (both labs, four 30-cell
  realisations, free K_n, B_n/B_t, eps_th).

    python benchmarks/bench_gradient_modes.py                 # every case, 5 repeats
    python benchmarks/bench_gradient_modes.py --cases disc20-free1 --repeats 3

Writes ``benchmarks/GRADIENT_MODES_RESULTS.md`` and the numbers as JSON next to it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import choices, cpu_name, write_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT_MD = ROOT / "benchmarks" / "GRADIENT_MODES_RESULTS.md"
CASES = ("disc20-free1", "disc20-free3", "disc20-free6", "twin-free3")
MODES = ("forward", "reverse")
ALL_GROUPS = ["K_n", "B_n/B_t", "eps_th", "mu", "K_n/K_t", "B_n"]


def _problem(case: str):
    from calibration import fit, twin

    if case.startswith("disc20-free"):
        n_free = int(case.removeprefix("disc20-free"))
        initial = {"K_n": 1.0e8, "K_n/K_t": 1.0, "B_n": 2.0e10, "B_n/B_t": 1.0}
        initial |= {"eps_th": 0.02, "mu": 0.3}
        spec = {
            "targets": {
                n: {"value": v, "uncertainty": 0.01 * v}
                for n, v in (("sigma_t", 2.6e8), ("slope_S", 5.0e8))
            },
            "initial": initial,
            "free": ALL_GROUPS[:n_free],
            "bonded-brazilian": twin.scene_options(20, 80.0, 1.0, 2.0e4)["bonded-brazilian"],
        }
        return fit.make_problem(spec, ["bonded-brazilian"], 1, seeds=[3])
    if case == "twin-free3":
        opts = twin.scene_options(30, 80.0, 1.0, 2.0e4)
        spec = {
            "targets": {n: {"value": 1.0, "uncertainty": 1.0} for n in twin.FIGURES},
            "initial": twin.START,
            "free": twin.FREE,
            "seeds": [0, 1, 2, 3],
        } | opts
        return fit.make_problem(spec, list(fit.SCENES), 4)
    raise ValueError(case)


def child(case: str, mode: str, repeats: int) -> dict:
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from calibration import fit

    t0 = time.perf_counter()
    problem = _problem(case)
    build_s = time.perf_counter() - t0
    rss_build = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    vg, _ = fit.make_functions(problem, mode)
    x = jax.numpy.asarray(problem.z0[problem.free])
    # the compiled program behind vg: the Jacobian of the means in forward mode (vg applies
    # the loss's chain rule to it on the host), value_and_grad of the loss in reverse mode
    program = fit._program(problem, "jacobian" if mode == "forward" else "reverse")
    t0 = time.perf_counter()
    compiled = program.lower(x).compile()
    compile_s = time.perf_counter() - t0
    del compiled
    jax.block_until_ready(vg(x))  # vg's own jit compiles once more: not timed
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        (val, _), g = jax.block_until_ready(vg(x))
        times.append(time.perf_counter() - t0)
    return {
        "case": case,
        "mode": mode,
        "n_free": problem.n_free,
        "build_s": build_s,
        "compile_s": compile_s,
        "gradient_s": times,
        "gradient_median_s": statistics.median(times),
        "loss": float(val),
        "gradient": np.asarray(g).tolist(),
        "peak_rss_after_build_mb": rss_build,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--child", nargs=2, metavar=("CASE", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise SystemExit("--repeats must be >= 1")
    if args.child:
        print("RESULT " + json.dumps(child(*args.child, args.repeats)))
        return 0
    cases = choices(args.cases, CASES, "--cases")
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_ENABLE_COMPILATION_CACHE="false")
    rows = []
    for case in cases:
        for mode in MODES:
            cmd = [sys.executable, __file__, "--child", case, mode, "--repeats", str(args.repeats)]
            out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
            line = [s for s in out.stdout.splitlines() if s.startswith("RESULT ")]
            if out.returncode or not line:
                raise SystemExit(f"{case} {mode} failed:\n{out.stderr[-3000:]}")
            rows.append(json.loads(line[0][len("RESULT ") :]))
            r = rows[-1]
            print(
                f"{case} {mode}: compile {r['compile_s']:.1f} s, "
                f"gradient {r['gradient_median_s']:.2f} s, peak {r['peak_rss_mb']:.0f} MB"
            )
    import jax
    import numpy as np

    lines = [
        "# Forward against reverse mode for the calibration gradient",
        "",
        f"`python benchmarks/bench_gradient_modes.py --repeats {args.repeats}` on "
        f"{cpu_name()} ({os.cpu_count()} cores), jax {jax.__version__} on the CPU, float64, "
        f"{datetime.date.today().isoformat()}. Each case and mode in a fresh process, "
        "compilation cache off. `compile`: lower + compile of the jitted program behind "
        "the gradient (forward: the Jacobian of the ensemble means, which the loss's chain "
        "rule turns into the gradient on the host; reverse: value_and_grad of the loss). "
        "`gradient`: median of the evaluations after compilation (value and gradient of the "
        "loss, `calibration.fit.make_functions`); `peak memory`: the process's peak "
        "resident set (building the labs included; in brackets after the build alone); "
        "`agreement`: largest relative difference between the two modes' gradients.",
        "",
        "| case | free groups | mode | compile (s) | gradient (s) | forward / reverse time "
        "| peak memory (MB) | agreement |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case in cases:
        f, r = (next(x for x in rows if x["case"] == case and x["mode"] == m) for m in MODES)
        gf, gr = np.asarray(f["gradient"]), np.asarray(r["gradient"])
        agree = float(np.max(np.abs(gf - gr) / np.maximum(np.abs(gr), 1e-300)))
        ratio = f["gradient_median_s"] / r["gradient_median_s"]
        for x in (f, r):
            lines.append(
                f"| {case} | {x['n_free']} | {x['mode']} | {x['compile_s']:.1f} | "
                f"{x['gradient_median_s']:.2f} | {ratio:.2f} | {x['peak_rss_mb']:.0f} "
                f"({x['peak_rss_after_build_mb']:.0f}) | {agree:.1e} |"
            )
    write_table(OUT_MD, lines)
    OUT_MD.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
