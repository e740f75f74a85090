"""Breakage screening of a settled pile against one contact step of the same pile.

The pile is the ``deposit`` scene (Voronoi spheropolygons poured into a box under gravity)
with ``--cells`` cells, run until it settles; its contact forces are real (force chains, a
wide force distribution), not synthetic loads. For that state:

* the per-particle contact lists (``breakage.dsm.contact_table``) and the BEM operators of
  every particle (N = 64 elements, about 100 sample points, plane stress, nu = 0.3);
* the largest psi of every particle (``bem.psi_batched``) and the thresholds at which the
  first particle (or the top 1 %, 10 %) reaches it, i.e. eps just at the onset of breakage;
* for each threshold, how many particles pass the bound (``bem.psi_bound``) and so need the
  full field, and that the two-level screening (``bem.screen``) finds exactly the particles
  that the full field finds;
* times, float32 and float64, compilation excluded, median of ``--repeats``: one contact step
  (``simulate.run_segment``), the full field of every particle, the bound alone and the
  two-level screening; each both as one jitted call and as the marginal cost of one more
  evaluation inside a jitted loop (what it adds to a step it is fused into: no dispatch).

    python benchmarks/bench_screening.py                  # ~10 min on 2 cores
    python benchmarks/bench_screening.py --cells 300      # smaller pile

Writes ``benchmarks/SCREENING_RESULTS.md`` and ``benchmarks/SCREENING_RESULTS.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_bem import cast  # noqa: E402
from machine import cpu_name  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LOOP = 20  # evaluations per jitted loop for the marginal cost


def median_ms(fn, repeats):
    import jax

    jax.block_until_ready(fn())
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t)
    return 1e3 * statistics.median(runs)


def settled_pile(cells: int, width: float, cache: str | None = None):
    """The deposit scene run until it settles: (state, params, grid, config), float64.

    With ``cache``, the settled pile is pickled there and reused by later runs with the same
    arguments (timing the screening again needs no new pour)."""
    import pickle

    import jax
    import numpy as np

    from jaxgran.scenes import deposit

    cfg = deposit.Config(n_cells=cells, box_width=width)
    if cache and Path(cache).exists():
        with open(cache, "rb") as fh:
            key, pile = pickle.load(fh)
        if key == (cells, width) and _same_layout(pile[0]):
            return (*pile, cfg)
    state, params, grid = _pour(cfg)
    if cache:
        pile = jax.tree_util.tree_map(
            lambda x: np.asarray(x) if isinstance(x, jax.Array) else x, (state, params, grid)
        )
        with open(cache, "wb") as fh:
            pickle.dump(((cells, width), pile), fh)
    return state, params, grid, cfg


def _same_layout(state) -> bool:
    """Whether a pickled state has the fields of today's state classes (a pile pickled
    before a field was added is poured again)."""
    import dataclasses

    from jaxgran.state import Particles, SimState, Walls

    def fields(cls):
        return {f.name for f in dataclasses.fields(cls)}

    def have(obj):
        return set(vars(obj))

    return (
        have(state) >= fields(SimState)
        and have(state.particles) >= fields(Particles)
        and have(state.walls) >= fields(Walls)
    )


def _pour(cfg):
    from jaxgran.scenes import deposit

    res, _, _ = deposit.pour(cfg, frame_every=10**9)
    return res.state, res.params, res.grid


def _to_device(x):
    import jax.numpy as jnp
    import numpy as np

    if isinstance(x, np.ndarray):
        return x.item() if x.dtype == object else jnp.asarray(x)
    return x


def time_dtype(dt, ops64, state, params, grid, cp, cf, cm, thick, rows, args):
    import jax
    import jax.numpy as jnp
    from jax import lax

    from jaxgran import bem
    from jaxgran.simulate import run_segment

    dname = jnp.dtype(dt).name
    ops = cast(ops64, dt)
    fl = bem._flat_contacts(cp, cf, cm)
    a = (
        jnp.asarray(cp, dt), jnp.asarray(cf, dt), jnp.asarray(cm), jnp.asarray(fl[0]),
        jnp.asarray(fl[1], dt), jnp.asarray(fl[2], dt), jnp.asarray(fl[3]),
    )  # fmt: skip
    th = jnp.asarray(thick, dt)
    st, pr = cast(state, dt), cast(params, dt)
    step = median_ms(lambda st=st, pr=pr: run_segment(st, pr, grid, 1, args.steps), 5)
    step /= args.steps

    def full(o, c, f, m, *_, th=th):
        return bem.psi_batched(o, c, f, m, thickness=th)[1]

    def bnd_padded(o, c, f, m, *_, th=th):
        return bem.psi_bound(o, c, f, m, thickness=th)

    def bnd(o, c, f, m, fp, fx, ff, fm, th=th):
        return bem.psi_bound_flat(o, fp, fx, ff, fm, thickness=th)

    def coarse(o, c, f, m, fp, fx, ff, fm, th=th):
        return bem.psi_bound_coarse(o, fp, fx, ff, fm, thickness=th)

    def scr(k, thr, c_keep, s1):
        def fn(o, c, f, m, *flat, th=th):
            t = jnp.asarray(thr, dt)
            return bem._screen_core(o, c, f, m, t, th, k, flat, c_keep, s1).psi

        return fn

    def looped(fn):
        @jax.jit
        def run(o, c, f, m, fp, fx, ff, fm):
            def body(i, acc):
                s = 1 + 1e-3 * i.astype(dt)
                x = 1 + 1e-6 * (s - 1)
                out = fn(o, c * x, f * s, m, fp, fx * x, ff * s, fm)
                return acc + jnp.sum(out)

            return lax.fori_loop(0, LOOP, body, jnp.zeros((), dt))

        return run

    res = {"contact_step_ms": step}
    kinds = {
        "full field": full,
        "bound, padded contact lists": bnd_padded,
        "bound, flat list of real contacts": bnd,
        "coarse bound, flat list of real contacts": coarse,
    }
    for r in rows:
        label = (
            f"screening, {r['threshold']} (S1 = {r['S1']}, K = {r['K']}, "
            f"{r['c_keep']} contact slots)"
        )
        kinds[label] = scr(r["K"], r["eps_Pa"], r["c_keep"], r["S1"])

    def segment():
        return run_segment(st, pr, grid, 1, args.steps)

    for name, fn in kinds.items():
        once, loop = jax.jit(fn), looped(fn)
        one = median_ms(lambda f=once: f(ops, *a), args.repeats)
        marg = median_ms(lambda f=loop: f(ops, *a), max(3, args.repeats // 3)) / LOOP
        # the same marginal cost timed right after a contact segment, repeat by repeat: on a
        # shared machine the load drifts between the separate medians above, and the median
        # of these paired ratios is not biased by that drift
        ratios = []
        jax.block_until_ready(loop(ops, *a))
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(segment())
            t1 = time.perf_counter()
            jax.block_until_ready(loop(ops, *a))
            t2 = time.perf_counter()
            ratios.append(((t2 - t1) / LOOP) / ((t1 - t0) / args.steps))
        res[name] = {
            "call_ms": one,
            "marginal_ms": marg,
            "marginal_over_step_paired": statistics.median(ratios),
        }
        print(dname, name, f"{one:.2f} ms, marginal {marg:.2f} ms, paired "
              f"{100 * statistics.median(ratios):.0f} % of a step", flush=True)  # fmt: skip
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=1100)
    ap.add_argument("--width", type=float, default=0.7, help="box width (m)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--steps", type=int, default=200, help="contact steps per timed segment")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "SCREENING_RESULTS"))
    ap.add_argument("--cache", default=None, help="pickle of the settled pile, reused if present")
    args = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from jaxgran import bem
    from jaxgran.breakage import dsm

    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    state, params, grid, cfg = settled_pile(args.cells, args.width, args.cache)
    state, params, grid = (jax.tree_util.tree_map(_to_device, t) for t in (state, params, grid))
    t_pile = time.perf_counter() - t0
    p = state.particles
    n_act = int(p.active.sum())
    print(f"pile: {n_act} particles settled in {t_pile:.0f} s", flush=True)
    thick = cfg.thickness

    def table(k):
        return dsm.contact_table(
            state, params, jnp.asarray(1.0), jnp.asarray(0.0), jnp.asarray(3.4351),
            jnp.asarray(thick), k,
        )  # fmt: skip

    # the contact list is sized as the DSM sizes it: a power of two holding the longest one
    count = np.asarray(table(8)["count"])
    max_contacts = max(8, 1 << (int(count.max()) - 1).bit_length())
    tab = table(max_contacts)
    act = np.flatnonzero(np.asarray(p.active))
    cp, cf, cm = (np.asarray(tab[k])[act] for k in ("points", "forces", "mask"))
    n_flat = bem._flat_contacts(cp, cf, cm)[0].shape[0]
    ops64 = bem.build_operators(
        p.verts[act], p.n_verts[act], p.radius[act], n_elements=64, n_points=100,
        poisson_ratio=0.3,
    )  # fmt: skip
    _, psi = bem.psi_batched(ops64, cp, cf, cm, thickness=thick)
    psi_max = np.asarray(psi).max(axis=1)
    bound = np.asarray(bem.psi_bound(ops64, cp, cf, cm, thickness=thick))
    loaded = psi_max > 0
    if np.any(bound[loaded] < psi_max[loaded]):
        raise AssertionError("the bound fell below the field: a bug")
    ratio = bound[loaded] / psi_max[loaded]
    n_contacts = cm.sum(axis=1)
    # where the bound loses: the sum over contacts of each contact's own psi (its
    # equilibrated force alone) at each point, maximised over the points, is the tightest
    # bound that the triangle inequality over contacts allows; bound / that is what the
    # per-group tables (operator norms, the Flamant near-field bound) add on top
    feq = np.asarray(jax.vmap(bem._equilibrate)(jnp.asarray(cp), jnp.asarray(cf), jnp.asarray(cm)))
    tri = np.zeros_like(np.asarray(psi))
    for c in range(cm.shape[1]):
        one = np.zeros_like(cm)
        one[:, c] = cm[:, c]
        if one.any():
            tri += np.asarray(bem.psi_batched(ops64, cp, feq * one[..., None], one,
                                              thickness=thick)[1])  # fmt: skip
    tri_max = tri.max(axis=1)
    multi = loaded & (n_contacts >= 2)

    rows = []
    for label, q in (("first particle", None), ("top 1 %", 99.0), ("top 10 %", 90.0)):
        thr = float(psi_max.max() if q is None else np.percentile(psi_max, q))
        thr *= 1.0 - 1e-6  # just below: equality would be decided by rounding
        ref = set(np.flatnonzero(psi_max >= thr).tolist())
        s = bem.screen(ops64, cp, cf, cm, thr, thickness=thick, max_candidates=8, fine_slots=8)
        got = set(np.asarray(s.candidates)[np.asarray(s.reaches)].tolist())
        if got != ref:
            raise AssertionError(f"screening missed or added particles at {label}")
        rows.append(
            {
                "threshold": label,
                "eps_Pa": thr,
                "reaching": len(ref),
                "coarse": int(s.n_coarse),
                "fine_contacts": int(s.n_fine_contacts),
                "S1": fine_slots(int(s.n_fine_contacts), n_flat),
                "candidates": int(s.n_candidates),
                "K": int(s.candidates.shape[0]),
                "c_keep": min(max_contacts, max(8, 1 << (int(s.max_contacts) - 1).bit_length())),
            }
        )
        print(rows[-1], flush=True)
    # the common case while a packing is loaded: nothing near breakage, no particle passes the
    # bound and the candidates' field is skipped (K = 64 slots)
    thr = 1.5 * float(bound.max())
    s = bem.screen(ops64, cp, cf, cm, thr, thickness=thick, max_candidates=64, fine_slots=8)
    if int(s.n_candidates) or bool(np.any(np.asarray(s.reaches))):
        raise AssertionError("a particle passed a threshold above every bound")
    rows.append(
        {"threshold": "none (eps = 1.5 x the largest bound)", "eps_Pa": thr, "reaching": 0,
         "coarse": int(s.n_coarse), "fine_contacts": int(s.n_fine_contacts),
         "S1": fine_slots(int(s.n_fine_contacts), n_flat),
         "candidates": 0, "K": 64, "c_keep": 8}
    )  # fmt: skip

    timing = {
        jnp.dtype(dt).name: time_dtype(
            dt, ops64, state, params, grid, cp, cf, cm, thick, rows, args
        )
        for dt in (jnp.float32, jnp.float64)
    }

    out = {
        "machine": cpu_name(),
        "cores": os.cpu_count(),
        "date": datetime.date.today().isoformat(),
        "jax": jax.__version__,
        "load_average": [load0, os.getloadavg()[0]],
        "particles": n_act,
        "pile_seconds": t_pile,
        "contacts_per_particle": float(n_contacts.mean()),
        "contact_list_length": max_contacts,
        "bound_over_field": {
            "min": float(ratio.min()),
            "median": float(np.median(ratio)),
            "max": float(ratio.max()),
        },
        "triangle_over_field": {
            "median": float(np.median(tri_max[multi] / psi_max[multi])),
            "p90": float(np.percentile(tri_max[multi] / psi_max[multi], 90)),
        },
        "bound_over_triangle": {
            "median": float(np.median(bound[multi] / tri_max[multi])),
            "p90": float(np.percentile(bound[multi] / tri_max[multi], 90)),
        },
        "thresholds": rows,
        "timing": timing,
    }
    Path(args.out + ".json").write_text(json.dumps(out, indent=1))
    write_markdown(out, Path(args.out + ".md"), args)


def fine_slots(n_fine: int, n_flat: int, first: int = 8) -> int | None:
    """The fine level's contact slots ``bem.screen(..., fine_slots=first)`` settles on, as K
    is sized: ``first``, or the next power of two holding the contacts of every particle
    passing the coarse bound (None: no coarse level, when that reaches the flat list's
    ``n_flat`` slots)."""
    from jaxgran import bem

    s1 = bem._pow2(n_fine, first)
    return None if s1 >= n_flat else s1


def write_markdown(out, path: Path, args) -> None:
    b = out["bound_over_field"]
    lines = [
        "## Breakage screening of a settled pile (`python benchmarks/bench_screening.py`)",
        "",
        f"Machine: {out['machine']}, {out['cores']} cores; jax {out['jax']} (cpu); "
        f"{out['date']}; load average {out['load_average'][0]:.1f} at the start, "
        f"{out['load_average'][1]:.1f} at the end. Compilation excluded, medians of "
        f"{args.repeats} runs (marginal costs: {LOOP} evaluations in one jitted loop, median "
        f"of {max(3, args.repeats // 3)}).",
        "",
        f"Pile: the `deposit` scene with {args.cells} cells in a {args.width} m box, settled "
        f"under gravity: {out['particles']} particles, {out['contacts_per_particle']:.1f} "
        f"vertex contacts per particle on average (lists padded to {out['contact_list_length']}, "
        "as the DSM pads them). BEM: N = 64, at most M = 100 sample points, "
        "plane stress, nu = 0.3, Flamant load model.",
        "",
        f"Bound / largest psi of each loaded particle: min {b['min']:.2f}, median "
        f"{b['median']:.2f}, max {b['max']:.2f} (a bound below 1 would be a bug; the "
        "benchmark stops if it sees one).",
        "",
        "Where the bound loses (particles with 2 or more contacts): the sum over contacts of "
        "each contact's own psi, maximised over the points (the tightest bound the triangle "
        "inequality over contacts allows), over the largest psi: median "
        f"{out['triangle_over_field']['median']:.2f}, 90th percentile "
        f"{out['triangle_over_field']['p90']:.2f}; the bound over that sum: median "
        f"{out['bound_over_triangle']['median']:.2f}, 90th percentile "
        f"{out['bound_over_triangle']['p90']:.2f} (what the per-group tables add: the "
        "maxima over groups of points and over the loads' positions on an element, the "
        "interpolation between force directions, and the Flamant near field and the smooth "
        "remainder bounded apart).",
        "",
        "| threshold eps at which | particles reaching eps | passing the coarse bound "
        "| their contacts | S1 | passing the bound | K |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in out["thresholds"]:
        what = r["threshold"]
        what = what if what.startswith("none") else f"{what} reaches it"
        lines.append(
            f"| {what} | {r['reaching']} | {r['coarse']} | {r['fine_contacts']} | {r['S1']} "
            f"| {r['candidates']} | {r['K']} |"
        )
    lines += [
        "",
        "At each threshold the screening returned exactly the particles whose full field "
        "reaches eps. Its levels: the coarse bound of every particle (one table row per "
        "contact), the finer bound of the particles passing the coarse one (their contacts "
        "moved into S1 slots), the field of those passing the finer bound (K slots). S1 and "
        "K are the sizes `bem.screen` settles on from 8 (`fine_slots=8`, `max_candidates=8`): "
        "the next power of two holding what passes, as a loop that screens every step and "
        "passes on its last sizes would use them. When no particle passes the bound the "
        "candidates' field is skipped (`lax.cond`).",
        "",
        "`paired`: the marginal cost timed right after a contact segment of "
        f"{args.steps} steps, repeat by repeat, as a percentage of that segment's step; the "
        f"median of {args.repeats} such ratios (the machine's load drifts between the "
        "separate medians of the other columns).",
        "",
        "| dtype | part | one call (ms) | marginal (ms) | % of one contact step | paired % |",
        "|---|---|---|---|---|---|",
    ]
    for dname, res in out["timing"].items():
        step = res["contact_step_ms"]
        lines.append(f"| {dname} | contact step of the pile | {step:.2f} | | 100 | |")
        for name, v in res.items():
            if name == "contact_step_ms":
                continue
            lines.append(
                f"| {dname} | {name} | {v['call_ms']:.2f} | {v['marginal_ms']:.2f} | "
                f"{100 * v['call_ms'] / step:.0f} (marginal {100 * v['marginal_ms'] / step:.0f}) "
                f"| {100 * v['marginal_over_step_paired']:.0f} |"
            )
    path.write_text("\n".join(lines) + "\n")
    print(path.read_text())


if __name__ == "__main__":
    main()
