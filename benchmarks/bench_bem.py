"""BEM stress-field speed, and speed versus accuracy on the Brazilian disc.

(a) time to build the per-particle operators (``bem.build_operators``) of 1,000 Voronoi
    spheropolygons (mostly pentagons and hexagons), N = 64 elements, about 100 sample points;
(b) time of one psi screening (``bem.psi_batched``, jitted) of those particles loaded by four
    contacts each, float32 and float64;
(c) error against the closed-form Brazilian disc versus time per particle, for
    N in {32, 48, 64, 96, 128, 192} and several sample densities, both load models.

Timings exclude compilation (reported separately) and are the median of ``--repeats`` runs.
Threads: XLA's default (all cores). jax's CPU LU (the operator build) calls scipy's OpenBLAS,
whose own threads can fight XLA's; ``--blas-threads 1`` sets OPENBLAS_NUM_THREADS=1 to compare.
Writes a markdown section and a chart:

    python benchmarks/bench_bem.py                  # everything, several minutes on 2 cores
    python benchmarks/bench_bem.py --quick          # smaller sweep
    python benchmarks/bench_bem.py --blas-threads 1 --sections ab --append
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, repeats):
    """(seconds of the first call, median seconds of ``repeats`` further calls)."""
    import jax

    t = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t)
    return first, statistics.median(runs)


def voronoi_particles(n: int, seed: int = 0):
    """Body-frame cores [n, V, 2], vertex counts and radii of Voronoi spheropolygons (~2 cm)."""
    import numpy as np

    from jaxgran import geometry as geo

    cell, r = 0.02, 1e-3
    side = cell * math.sqrt(n)
    cells = geo.voronoi_rectangle(side, side, n, seed, lloyd_iterations=2)
    cores = [geo.offset_polygon(c, r) for c in cells]
    cores = [c - geo.polygon_centroid(c) for c in cores]
    verts, n_verts = geo.pad_polygons(cores)
    return verts, n_verts, np.full(n, r)


def random_contacts(ops, n_contacts: int, seed: int = 1):
    """Contacts at random places on each outline, forces ~ 100 N pointing inwards."""
    import numpy as np

    rng = np.random.default_rng(seed)
    nodes = np.asarray(ops.nodes, dtype=np.float64)
    P, N = nodes.shape[:2]
    e = rng.integers(0, N, (P, n_contacts))
    s = rng.random((P, n_contacts, 1))
    rows = np.arange(P)[:, None]
    a, b = nodes[rows, e], nodes[rows, (e + 1) % N]
    cp = a + s * (b - a)
    normal = np.asarray(ops.normals, dtype=np.float64)[rows, e]
    tangent = np.stack([-normal[..., 1], normal[..., 0]], -1)
    cf = -100.0 * normal + 20.0 * rng.normal(size=(P, n_contacts, 1)) * tangent
    return cp, cf, np.ones((P, n_contacts), bool)


def cast(tree, dtype):
    import jax
    import jax.numpy as jnp

    return jax.tree_util.tree_map(
        lambda x: (
            x.astype(dtype)
            if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.floating)
            else x
        ),
        tree,
    )


def throughput(args, lines):
    import jax
    import jax.numpy as jnp

    from jaxgran import bem

    verts, n_verts, radius = voronoi_particles(args.particles)
    lines += [
        f"### (a) operators for {args.particles} Voronoi particles",
        "",
        f"{args.particles} cells of a Lloyd-relaxed Voronoi tessellation, cores eroded by "
        f"r = 1 mm (spheropolygons of about 2 cm), {int(n_verts.min())}-{int(n_verts.max())} "
        f"vertices (mean {n_verts.mean():.1f}); N = {args.n_elements} elements, at most "
        f"M = {args.n_points} sample points each; `load_model='flamant'`.",
        "",
        "| dtype | compile + first call (s) | build, median (s) | per particle (ms) |",
        "|---|---|---|---|",
    ]
    ops = {}
    for dtype in ("float64", "float32"):
        v, r = jnp.asarray(verts, dtype), jnp.asarray(radius, dtype)

        def build(v=v, r=r):
            return bem.build_operators(
                v,
                n_verts,
                r,
                n_elements=args.n_elements,
                n_points=args.n_points,
                poisson_ratio=0.3,
            )

        first, med = timed(build, args.repeats)
        ops[dtype] = build()
        lines.append(f"| {dtype} | {first:.2f} | {med:.2f} | {1e3 * med / args.particles:.2f} |")
        print(lines[-1], flush=True)
    m = ops["float64"].point_mask.sum(1)
    lines += [
        "",
        f"Sample points per particle: {int(m.min())}-{int(m.max())} (mean {float(m.mean()):.0f}).",
        "",
        f"### (b) one psi screening of {args.particles} loaded particles",
        "",
        "Four contacts per particle at random places on the outline; `psi_batched` under "
        "`jax.jit` (operators built in float64 and cast for float32).",
        "",
        "| dtype | compile + first call (s) | screening, median (ms) | per particle (us) |",
        "|---|---|---|---|",
    ]
    cp, cf, mask = random_contacts(ops["float64"], 4)
    psi_jit = jax.jit(bem.psi_batched)
    for dtype in ("float64", "float32"):
        o = cast(ops["float64"], dtype)
        c, f = jnp.asarray(cp, dtype), jnp.asarray(cf, dtype)
        first, med = timed(lambda o=o, c=c, f=f: psi_jit(o, c, f, mask), max(args.repeats, 10))
        lines.append(
            f"| {dtype} | {first:.2f} | {1e3 * med:.2f} | {1e6 * med / args.particles:.2f} |"
        )
        print(lines[-1], flush=True)
    lines.append("")


def brazilian_exact(x, y, radius, load, thickness):
    import numpy as np

    r1 = x**2 + (radius - y) ** 2
    r2 = x**2 + (radius + y) ** 2
    c = 2.0 * load / (math.pi * thickness)
    sxx = -c * ((radius - y) * x**2 / r1**2 + (radius + y) * x**2 / r2**2 - 0.5 / radius)
    syy = -c * ((radius - y) ** 3 / r1**2 + (radius + y) ** 3 / r2**2 - 0.5 / radius)
    sxy = c * ((radius - y) ** 2 * x / r1**2 - (radius + y) ** 2 * x / r2**2)
    return np.stack([sxx, syy, sxy], -1)


def sweep(args, lines):
    """Brazilian disc R = 1 cm, t = 1 cm, P = 150.79 N (paper 000): error vs time."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxgran import bem

    radius, thickness, load = 0.01, 0.01, 150.79
    p = load / (math.pi * radius * thickness)  # 2P / (pi D t)
    batch = args.batch
    psi_jit = jax.jit(bem.psi_batched)
    rows = []
    densities = args.densities
    ref_density = densities[min(1, len(densities) - 1)]  # the element model runs at this one
    for model in ("flamant", "element"):
        for n_points in densities if model == "flamant" else [ref_density]:
            for n in args.sizes:
                verts = jnp.zeros((batch, 1, 2))
                n_verts = np.ones(batch, np.int32)
                rad = np.full(batch, radius)

                def build(verts=verts, n_verts=n_verts, rad=rad, n=n, n_points=n_points, m=model):
                    return bem.build_operators(
                        verts,
                        n_verts,
                        rad,
                        n_elements=n,
                        n_points=n_points,
                        poisson_ratio=0.3,
                        load_model=m,
                    )

                _, t_build = timed(build, args.repeats)
                ops = build()
                cp = jnp.broadcast_to(jnp.array([[0.0, radius], [0.0, -radius]]), (batch, 2, 2))
                cf = jnp.broadcast_to(jnp.array([[0.0, -load], [0.0, load]]), (batch, 2, 2))
                mask = jnp.ones((batch, 2), bool)
                _, t_psi = timed(
                    lambda ops=ops, cp=cp, cf=cf, mask=mask: psi_jit(
                        ops, cp, cf, mask, thickness=thickness
                    ),
                    max(args.repeats, 10),
                )
                sigma, psi = psi_jit(ops, cp, cf, mask, thickness=thickness)
                keep = np.asarray(ops.point_mask[0])
                pts = np.asarray(ops.points[0])[keep]
                got = np.asarray(sigma[0])[keep]
                exact = brazilian_exact(pts[:, 0], pts[:, 1], radius, load, thickness)
                far = np.minimum(
                    np.linalg.norm(pts - [0, radius], axis=1),
                    np.linalg.norm(pts + [0, radius], axis=1),
                )
                err = np.abs(got - exact)[far > 0.3 * radius].max() / p
                centre = np.argmin(np.linalg.norm(pts, axis=1))
                psi_err = float(psi[0][keep][centre]) / (3.4351 * p) - 1.0
                row = dict(
                    model=model,
                    n=n,
                    n_points=n_points,
                    m=int(keep.sum()),
                    build_ms=1e3 * t_build / batch,
                    psi_us=1e6 * t_psi / batch,
                    err=err,
                    psi_err=psi_err,
                )
                rows.append(row)
                print(row, flush=True)
    lines += [
        "### (c) speed versus accuracy: Brazilian disc",
        "",
        f"Disc R = 1 cm, t = 1 cm, diametral point loads P = 150.79 N (paper 000), plane "
        f"stress, nu = 0.3, float64. Error = max |sigma - closed form| over the sample points "
        f"more than 0.3 R from the loads, in units of 2P/(pi D t); psi_c = psi at the centre "
        f"vs 3.4351 F/(pi R t) (PHYSICS.md C). Times per particle from a batch of {batch} "
        f"discs: operator build (once per shape) and one screening.",
        "",
        "| load model | N | M (max) | M (disc) | error | psi_c error | build (ms/particle) | "
        "screening (us/particle) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['model']} | {r['n']} | {r['n_points']} | {r['m']} | {100 * r['err']:.3f} % | "
            f"{100 * r['psi_err']:+.3f} % | {r['build_ms']:.2f} | {r['psi_us']:.1f} |"
        )
    for model, pts in (("flamant", ref_density), ("element", ref_density)):
        sel = [r for r in rows if r["model"] == model and r["n_points"] == pts]
        if len(sel) >= 2:
            order = -np.polyfit(np.log([r["n"] for r in sel]), np.log([r["err"] for r in sel]), 1)[
                0
            ]
            lines.append("")
            lines.append(
                f"Measured convergence order ({model}, M = {pts}): error ~ N^-{order:.2f}."
            )
    lines.append("")
    return rows


def chart(rows, path: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    styles = {}
    for r in rows:
        styles.setdefault((r["model"], r["n_points"]), []).append(r)
    for (model, n_points), sel in styles.items():
        ls = "-" if model == "flamant" else "--"
        label = f"{model}, M <= {n_points}"
        for a, key in ((ax[0], "build_ms"), (ax[1], "psi_us")):
            a.loglog([r[key] for r in sel], [100 * r["err"] for r in sel], ls, marker="o",
                     label=label)  # fmt: skip
            for r in sel:
                a.annotate(str(r["n"]), (r[key], 100 * r["err"]), fontsize=7,
                           textcoords="offset points", xytext=(3, 3))  # fmt: skip
    ax[0].set_xlabel("operator build time per particle (ms)")
    ax[1].set_xlabel("psi screening time per particle (us)")
    for a in ax:
        a.set_ylabel("max error, % of 2P/(pi D t)")
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle("BEM Brazilian disc: accuracy vs cost (labels: N elements)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--n-elements", type=int, default=64)
    parser.add_argument("--n-points", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch", type=int, default=64, help="discs per batch in the sweep")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 48, 64, 96, 128, 192])
    parser.add_argument("--densities", type=int, nargs="+", default=[50, 100, 400])
    parser.add_argument("--quick", action="store_true", help="200 particles, smaller sweep")
    parser.add_argument("--sections", default="abc", help="which of (a), (b), (c) to run")
    parser.add_argument("--blas-threads", type=int, default=None, help="OPENBLAS_NUM_THREADS")
    parser.add_argument("--append", action="store_true", help="append to --md")
    parser.add_argument("--md", type=Path, default=ROOT / "benchmarks" / "BEM_RESULTS.md")
    parser.add_argument("--png", type=Path, default=ROOT / "docs" / "bem_speed_vs_accuracy.png")
    args = parser.parse_args()
    if args.quick:
        args.particles, args.sizes, args.densities = 200, [32, 64, 128], [50, 100]
    if args.blas_threads is not None:  # before numpy / jax load OpenBLAS
        os.environ["OPENBLAS_NUM_THREADS"] = str(args.blas_threads)

    import jax

    jax.config.update("jax_enable_x64", True)
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    load = os.getloadavg()
    lines = [] if args.append else ["## BEM stress field (`jaxgran.bem`)", ""]
    lines += [
        f"Machine: {cpu_name()}, {os.cpu_count()} cores; jax {jax.__version__} "
        f"({jax.default_backend()}), XLA default threads, OPENBLAS_NUM_THREADS={blas}; "
        f"{datetime.date.today().isoformat()}; load average at start {load[0]:.1f}"
        + (
            " (other jobs were running: timings are pessimistic and noisy). "
            if load[0] > 0.5 * (os.cpu_count() or 1)
            else ". "
        )
        + "Command: `python benchmarks/bench_bem.py"
        + (f" --blas-threads {args.blas_threads}" if args.blas_threads is not None else "")
        + (f" --sections {args.sections}" if args.sections != "abc" else "")
        + "`.",
        "",
    ]
    if "a" in args.sections or "b" in args.sections:
        throughput(args, lines)
    if "c" in args.sections:
        rows = sweep(args, lines)
        chart(rows, args.png)
        lines += [f"![speed vs accuracy]({os.path.relpath(args.png, args.md.parent)})", ""]
    lines.append(f"Load average at the end: {os.getloadavg()[0]:.1f}.")
    lines.append("")
    text = "\n".join(lines)
    if args.append and args.md.exists():
        text = args.md.read_text().rstrip("\n") + "\n\n" + text
    args.md.write_text(text)
    print(f"wrote {args.md}" + (f" and {args.png}" if "c" in args.sections else ""))


if __name__ == "__main__":
    main()
