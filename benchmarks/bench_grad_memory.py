"""Peak memory of reverse-mode gradients through long lab tests (issue 8).

The gradient of the Brazilian tensile strength sigma_t (`jaxgran.labtests`) with respect to
the six micro-parameters, on a 150-cell disc (two realisations), for runs of about 5,000 and
20,000 steps. Each configuration runs in a fresh subprocess, which reports its peak resident
memory (`ru_maxrss`) after (a) building the lab (compiles and runs the reference forward
pass), (b) one more forward pass of the figures, and (c) the gradient. Also reported: the
bytes of one stacked state, and what reverse mode would keep without checkpointing (one
state per step, a lower bound, since the residuals of a step are larger than the state).

The labs store one state per segment, one per record of the segment being recomputed and
the residuals of one record's steps (`jaxgran.labtests` docstring), so memory should grow
like the square root of the number of records, not like the number of steps.

    python benchmarks/bench_grad_memory.py               # 5,000 and 20,000 steps
    python benchmarks/bench_grad_memory.py --steps 5000,10000,20000

Writes ``benchmarks/GRAD_MEMORY_RESULTS.md`` (and the numbers as JSON next to it).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name, write_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DISC = {"n_cells": 150, "record_every": 50}
SEEDS = [0, 1]


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def child(n_steps: int) -> dict:
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from jaxgran import labtests as lt
    from jaxgran.scenes import bonded as bd
    from jaxgran.scenes import bonded_brazilian as bz

    cfg = dataclasses.replace(bz.Config(), **DISC)
    dt = float(bz.build(cfg, seeds=SEEDS[:1]).params.dt)
    max_strain = n_steps * cfg.strain_rate * dt
    rss0 = _rss_mb()
    t0 = time.perf_counter()
    lab = lt.brazilian_lab(
        cfg, SEEDS, surrogate_width=0.5, damping=2.0e4, contact_damping=0.0, max_strain=max_strain
    )
    log_p = lt.log_params(bd.material_from(cfg))
    rss_lab = _rss_mb()
    figs, err = lt.figures(log_p, lab)
    lt.check_errors(err)
    jax.block_until_ready(figs)
    rss_fwd = _rss_mb()
    t1 = time.perf_counter()

    def sigma_t(lp):
        f, _ = lt.figures(lp, lab)
        return f["sigma_t"].mean()

    g = jax.grad(sigma_t)(log_p)
    g = np.asarray(jax.block_until_ready(g))
    t2 = time.perf_counter()
    rss_grad = _rss_mb()
    leaves = jax.tree_util.tree_leaves(lab.state)
    state_bytes = sum(int(x.size) * x.dtype.itemsize for x in leaves if hasattr(x, "dtype"))
    return {
        "n_steps": int(lab.n_steps),
        "n_segments": int(lab.n_segments),
        "records_per_segment": int(lab.records_per_segment),
        "record_every": int(lab.record_every),
        "realisations": int(lab.realisations),
        "rss_start_MB": rss0,
        "rss_after_lab_MB": rss_lab,
        "rss_after_forward_MB": rss_fwd,
        "rss_after_grad_MB": rss_grad,
        "grad_extra_MB": rss_grad - rss_fwd,
        "state_MB": state_bytes / 2**20,
        "no_checkpoint_lower_bound_MB": lab.n_steps * state_bytes / 2**20,
        "grad_finite": bool(np.all(np.isfinite(g))),
        "sigma_t_Pa": float(np.mean(np.asarray(figs["sigma_t"]))),
        "forward_wall_s": t1 - t0,
        "grad_wall_s": t2 - t1,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", default="5000,20000")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "GRAD_MEMORY_RESULTS.md"))
    args = ap.parse_args()
    if args.child is not None:
        print("RESULT " + json.dumps(child(args.child)), flush=True)
        return

    import jax

    rows = []
    for n in [int(s) for s in args.steps.split(",")]:
        out = subprocess.run(
            [sys.executable, __file__, "--child", str(n)],
            capture_output=True,
            text=True,
            check=False,
        )
        line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
        if out.returncode != 0 or not line:
            raise SystemExit(f"child for {n} steps failed:\n{out.stderr[-3000:]}")
        r = json.loads(line[0][len("RESULT ") :])
        print(r, flush=True)
        rows.append(r)
    Path(args.md).with_suffix(".json").write_text(json.dumps(rows, indent=1))
    cmd = "python benchmarks/bench_grad_memory.py"
    if args.steps != "5000,20000":
        cmd += f" --steps {args.steps}"
    lines = [
        "# Peak memory of gradients through long lab tests",
        "",
        f"`{cmd}` on {cpu_name()} ({os.cpu_count()} cores), jax {jax.__version__} on the "
        f"CPU, float64, {datetime.date.today().isoformat()}. `jax.grad` of the mean "
        f"Brazilian sigma_t (`jaxgran.labtests.figures`) with respect to the six "
        f"log-parameters; bonded Brazilian {json.dumps(DISC)}, seeds {SEEDS} stacked, "
        "surrogate width 0.5, global damping 2e4 1/s; each row a fresh process. Peak "
        "resident memory (ru_maxrss) after building the lab (compiles and runs the reference "
        "forward pass), after one more forward pass, and after the gradient. "
        "`no checkpoint, lower bound`: one stacked state per step, what reverse mode would "
        "keep at least without `jax.checkpoint`.",
        "",
        "| steps | segments x records x steps | peak after lab (MB) | after forward (MB) | "
        "after grad (MB) | grad adds (MB) | one state (MB) | no checkpoint, lower bound "
        "(MB) | grad finite | forward (s) | grad (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n_steps']} | {r['n_segments']} x {r['records_per_segment']} x "
            f"{r['record_every']} | {r['rss_after_lab_MB']:.0f} | "
            f"{r['rss_after_forward_MB']:.0f} | {r['rss_after_grad_MB']:.0f} | "
            f"{r['grad_extra_MB']:.0f} | {r['state_MB']:.3f} | "
            f"{r['no_checkpoint_lower_bound_MB']:.0f} | {r['grad_finite']} | "
            f"{r['forward_wall_s']:.0f} | {r['grad_wall_s']:.0f} |"
        )
    write_table(args.md, lines)


if __name__ == "__main__":
    main()
