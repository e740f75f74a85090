"""Per-op profile of one contact step (`jax.profiler` trace, durations summed per XLA op).

Builds the dense Voronoi packing of ``bench_contacts.py``, warms up a jitted
:func:`jaxgran.integrate.step`, traces ``--steps`` steps and prints the summed op time per
step and the largest ops with the JAX operation each comes from (BENCHMARKS.md, "Where the
time goes").

    python benchmarks/profile_step.py --particles 4000 --dtype float32
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--particles", type=int, default=4000)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--top", type=int, default=15)
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", args.dtype == "float64")
    import jax.numpy as jnp
    from bench_contacts import packing

    from jaxgran import integrate
    from jaxgran.simulate import _grow_until_ok, prepare

    state, params, grid = packing(args.particles, getattr(jnp, args.dtype))
    state, err = prepare(state, params, grid)
    state, grid, err = _grow_until_ok(state, params, grid, int(err), [], 8)
    step = jax.jit(lambda s: integrate.step(s, params, grid)[0])
    s = jax.block_until_ready(step(state))
    source = {}
    for line in step.lower(state).compile().as_text().splitlines():
        m = re.match(r"\s*%?([\w.\-]+) = ", line)
        o = re.search(r'op_name="([^"]*)"', line)
        if m and o:
            source[m.group(1)] = o.group(1)
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d, create_perfetto_trace=True):
            for _ in range(args.steps):
                s = step(s)
            jax.block_until_ready(s)
        trace = glob.glob(d + "/**/*.trace.json.gz", recursive=True)[0]
        events = json.load(gzip.open(trace))["traceEvents"]
    per_op = collections.Counter()
    for e in events:
        if e.get("ph") == "X" and not e["name"].startswith(("Thunk", "$", "Pjit")):
            per_op[e["name"]] += e.get("dur", 0)
    n = args.steps
    print(f"summed op time per step: {sum(per_op.values()) / n / 1000:.2f} ms")
    for name, us in per_op.most_common(args.top):
        print(f"{us / n / 1000:7.3f} ms  {name:36s} {source.get(name, '')[:80]}")


if __name__ == "__main__":
    main()
