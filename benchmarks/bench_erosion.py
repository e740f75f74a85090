"""Fragment erosion against the kinetic-energy spike and the mass loss of DSM breakage: the
Cantor pentagon oedometer (`oedometer-cantor`, paper 000 §III) with the fragments eroded
where neighbours overlap the parent (``erosion="local"``, the default of
:func:`jaxgran.breakage.replace.replace_particles`) and without erosion (``"none"``: pieces
eroded only by the sphero-radius r, the geometric minimum of the spheropolygon construction,
so fragments start overlapping the neighbours that overlapped their parent).

The mode is the scene's ``Config.erosion`` (``replace_particles(..., erosion=...)``; ``none``
erodes only by the sphero-radius plus the ``1e-9 x R`` clearance). For the duration of a run
the benchmark swaps the scene module's ``make_breakage`` for one that returns the same
:class:`DsmBreakage` as a subclass (``_ErosionProbe``) whose ``apply`` calls the scene's own
``DsmBreakage.apply`` and records per event: the KE of the state just before and just after
the replacement, the parent's largest overlap, the fragments' largest overlap and resultant
force right after, and the mass that each erosion mode would have removed from the same
parent at the same instant (a dry run of ``replace_particles``: a paired comparison that
does not depend on the trajectories, which diverge after the first breakage).

KE spike: :func:`jaxgran.breakage.metrics.kinetic_energy_spikes` on the loading stage's
``kinetic_energy`` series (sampled every ``record_every`` steps), with the scene's window;
events of the same check share one spike, so the per-run statistics count each breakage
check once. "KE jump (1 rec)": KE at the first record after the check minus KE at the last
one before it. Control: the same spike measure at record times with no breakage check
within a window, since at this bar speed the pile's KE fluctuates without breakage too.

    python benchmarks/bench_erosion.py                  # mid-size pile, 3 seeds x local, none
    python benchmarks/bench_erosion.py --quick --seeds 1
    python benchmarks/bench_erosion.py --modes local,none,uniform --raw /tmp/erosion_raw

Writes a markdown section (``--md``, default ``benchmarks/EROSION_RESULTS.md``) and the
chart ``docs/erosion_ke_mass.png``. Each run goes to a fresh Python process (so that every
wall time includes the same compilation; ``--same-process`` is faster but only the first run
pays it). With ``--raw DIR`` each run is cached as JSON there (with its config and jaxgran
commit; a file whose config differs is recomputed), so a repeated call only adds what is
missing.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import os
import statistics
import sys
import time
import traceback
from pathlib import Path

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import cpu_name, save_figure, write_markdown  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

MODES = ("local", "none", "uniform")
MODE_TEXT = {
    "local": "local (default: clipped where a neighbour overlaps)",
    "none": "none (sphero-radius only, overlap = 0)",
    "uniform": "uniform (largest overlap off all round)",
}

# The mid-size pile: 12 grains of 14-20 mm in a 7 cm box (3 per row), loaded at 0.1 m/s
# (QUICK's bar speed) for 13.5 mm of bar travel, the grains a third as strong as the paper's
# (Brazilian force 50 N instead of 150.79 N: at full strength the pile rearranges and only
# one grain breaks in 12 mm, two at 75 N), so that several grains break in a couple of
# minutes of CPU;
# snapshots only at the start (they cost a host transfer each).
MID = {
    "n_particles": 12,
    "box_width": 0.07,
    "min_diameter": 0.014,
    "max_diameter": 0.02,
    "min_fragment_fraction": 0.1,
    "settle_time": 0.2,
    "bar_speed": 0.1,
    "load_time": 0.135,
    "calibration_force": 50.0,
    "snapshot_times": (0.0,),
    "records_per_segment": 5,
    # the setting these benchmarks were measured with (the scene's defaults until the
    # fines-merging and the 0.5 mm sphero-radius became the defaults)
    "sphero_radius": 1.0e-3,
    "small_pieces": "fines",
    # settled with the contact friction, as until the frictionless settling became the
    # scene's default (2026-12-06)
    "settle_friction": math.nan,
}


def _jaxgran_commit() -> str:
    """Short commit of the checkout, ``+modified`` when jaxgran/ differs from it (the
    package may be edited while benchmarks run)."""
    import subprocess

    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout

    try:
        head = git("rev-parse", "--short", "HEAD").strip() or "unknown"
        return head + ("+modified" if git("status", "--porcelain", "jaxgran").strip() else "")
    except OSError:
        return "unknown"


@functools.cache
def _probe_class():
    """The ``DsmBreakage`` subclass (defined lazily: jaxgran is imported after x64 is set)."""
    from jaxgran.breakage.dsm import DsmBreakage
    from jaxgran.breakage.replace import Replacement, max_overlap, replace_particles
    from jaxgran.energy import kinetic_energy

    class _ErosionProbe(DsmBreakage):
        """The scene's DSM breakage (fragments eroded by ``self.erosion``, from
        ``Config.erosion``) that also gives every event a ``probe`` dict (module docstring)."""

        def _replace(self, state, decisions, mode):
            reps = [Replacement(d.slot, d.pieces, d.planes) for d in decisions]
            return replace_particles(
                state,
                reps,
                min_area=self.min_area,
                mean_initial_mass=self.mean_initial_mass,
                erosion=mode,
            )

        def apply(self, state, decisions):
            ke0 = float(kinetic_energy(state))
            ov0 = np.asarray(max_overlap(state))
            f0 = np.linalg.norm(np.asarray(state.particles.force), axis=1)
            # the same decisions replaced in every mode, by parent slot; a mode may merge
            # every piece back ("suppressed": no mass lost to compare), which reads NaN
            dry = {
                m: {int(e["parent_slot"]): e for e in self._replace(state, decisions, m)[1]}
                for m in MODES
            }
            n0 = len(self.events)
            new = super().apply(state, decisions)  # the scene's path, erosion=cfg.erosion
            ke1 = float(kinetic_energy(new))
            ov1 = np.asarray(max_overlap(new))
            f1 = np.linalg.norm(np.asarray(new.particles.force), axis=1)
            for ev in self.events[n0:]:
                k = int(ev["parent_slot"])
                slots = np.asarray(ev["fragment_slots"], int)
                ev["probe"] = {
                    "ke_before_J": ke0,
                    "ke_after_J": ke1,
                    "parent_max_overlap_m": float(ov0[k]),
                    "parent_max_force_N": float(f0[k]),
                    "fragment_max_overlap_m": float(ov1[slots].max()) if slots.size else 0.0,
                    "fragment_max_force_N": float(f1[slots].max()) if slots.size else 0.0,
                    "n_breaking_together": len(decisions),
                    **{f"dry_mass_lost_{m}": _dry(dry[m], k, "mass_lost") for m in MODES},
                    **{f"dry_fines_{m}": _dry(dry[m], k, "fines_mass") for m in MODES},
                }
            return new

    return _ErosionProbe


def _dry(events: dict, slot: int, key: str) -> float:
    """``key`` of the dry-run event of parent ``slot``; NaN where that mode left it whole."""
    ev = events.get(slot)
    return float(ev[key]) if ev is not None and key in ev else float("nan")


@contextlib.contextmanager
def _scene_breakage(mode: str):
    """Make the oedometer scene's ``simulate_test`` use an ``_ErosionProbe`` in ``mode``."""
    from jaxgran.breakage.dsm import DsmBreakage
    from jaxgran.scenes import oedometer_cantor as oc

    original = oc.make_breakage
    probe = _probe_class()

    def make(*args, **kwargs):
        brk = original(*args, **kwargs)
        if type(brk) is not DsmBreakage:
            raise TypeError(f"erosion probe needs method 'dsm', got {type(brk).__name__}")
        brk.__class__ = probe  # same state, the subclass only adds the probe to apply
        if brk.erosion != mode:
            raise ValueError(f"the scene built erosion {brk.erosion!r}, expected {mode!r}")
        return brk

    oc.make_breakage = make
    try:
        yield
    finally:
        oc.make_breakage = original


def config(quick: bool, seed: int, mode: str):
    from jaxgran.scenes import oedometer_cantor as oc

    base = oc.QUICK if quick else MID
    return dataclasses.replace(oc.Config(), **base, seed=seed, erosion=mode)


def _spike_window(cfg, dt_final: float) -> float:
    """The window of the scene's summary (oedometer_cantor.summarize)."""
    return max(0.05 * cfg.load_time, 20 * cfg.record_every * dt_final)


def one(mode: str, seed: int, quick: bool) -> dict:
    """One loading run; returns the per-run numbers, the per-event records and the KE
    series (time from the start of loading)."""
    from jaxgran.breakage import metrics
    from jaxgran.scenes import oedometer_cantor as oc

    cfg = config(quick, seed, mode)
    out = {
        "mode": mode,
        "seed": seed,
        "ok": False,
        "load_average": os.getloadavg()[0],
        "config": _config_dict(cfg),
        "jaxgran_commit": _jaxgran_commit(),
    }
    t0 = time.perf_counter()
    try:
        with _scene_breakage(mode):
            settle, load, brk, info = oc.simulate_test(cfg)
    except Exception as exc:  # an unstable run is a result too
        out["wall_time_s"] = time.perf_counter() - t0
        out["error"] = f"{type(exc).__name__}: {exc}"
        traceback.print_exc()
        return out
    out["wall_time_s"] = time.perf_counter() - t0
    s = oc.summarize(settle, load, brk, info, cfg)
    mass0 = info["initial_mass"]
    t = np.asarray(load.series["time"], float)
    ke = np.asarray(load.series["kinetic_energy"], float)
    ev = brk.events
    times = sorted({float(e["time"]) for e in ev})
    spikes = metrics.kinetic_energy_spikes(
        t, ke, times, window=_spike_window(cfg, float(info["dt_log"][-1][1]))
    )
    checks = []
    for te, sp in zip(times, spikes, strict=True):
        after = np.flatnonzero(t > te)
        first = float(ke[after[0]]) if after.size else float("nan")
        sp = dict(sp)
        sp["t_load"] = te - info["load_start_time"]
        sp["excess_J"] = sp["peak"] - sp["baseline"]
        sp["jump_1rec_J"] = first - sp["baseline"]
        sp["n_events"] = sum(float(e["time"]) == te for e in ev)
        checks.append(sp)
    events = []
    for e in ev:
        pr = e["probe"]
        events.append(
            {
                "t_load": float(e["time"]) - info["load_start_time"],
                "parent_mass": float(e["parent_mass"]),
                "mass_lost": float(e["mass_lost"]),
                "fines_mass": float(e["fines_mass"]),
                "eroded_mass": float(e["eroded_mass"]),
                "n_fragments": len(e["fragment_masses"]),
                "erosion_m": float(e["erosion"]),
                "erosion_mode": e["erosion_mode"],
                "type": e.get("breakage_type", ""),
                **pr,
            }
        )
    finite = bool(np.all(np.isfinite(ke)))
    out.update(
        {
            "ok": True,
            "finite": finite and s["finite"],
            "escaped": s["escaped"],
            "n_initial": s["n_particles_initial"],
            "n_final": s["n_particles_final"],
            "steps": s["steps"],
            "sim_wall_time_s": s["wall_time_s"],
            "dt_s": s["dt_s"],
            "dt_final_s": s["dt_final_s"],
            "bar_travel_m": s["bar_travel_m"],
            "bar_force_max_N": s["bar_force_max_N"],
            "initial_mass_kg": mass0,
            "n_events": len(ev),
            "n_checks": len(checks),
            "mass_lost_pct": 100 * sum(e["mass_lost"] for e in events) / mass0,
            "eroded_pct": 100 * sum(e["eroded_mass"] for e in events) / mass0,
            "fines_pct": 100 * sum(e["fines_mass"] for e in events) / mass0,
            "mass_bookkeeping_error": s["mass_bookkeeping_error"],
            "ke_max_J": float(np.nanmax(ke)) if ke.size else float("nan"),
            "checks": checks,
            "events": events,
            "series_t": (t - info["load_start_time"]).tolist(),
            "series_ke": ke.tolist(),
        }
    )
    return out


def _config_dict(cfg) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=float))


def _config_dict(cfg) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=float))


def fresh(mode: str, seed: int, quick: bool) -> dict:
    """``one`` in a new Python process, so that every run pays the same compilation (in
    one process the later runs reuse the kernels that the first compiled)."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        cmd = [sys.executable, __file__, "--run-one", f"{mode},{seed},{out}"]
        subprocess.run(cmd + (["--quick"] if quick else []), check=True)
        return json.loads(out.read_text())


def cached(mode: str, seed: int, quick: bool, raw: Path | None, same_process: bool) -> dict:
    """A run, cached in ``raw`` when given (a file whose config differs is recomputed)."""
    run = one if same_process else fresh
    if raw is None:
        return run(mode, seed, quick)
    path = raw / f"erosion_{'quick' if quick else 'mid'}_{mode}_s{seed}.json"
    if path.exists():
        r = json.loads(path.read_text())
        if r.get("config") == _config_dict(config(quick, seed, mode)):
            return r
    r = run(mode, seed, quick)
    raw.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(r, indent=1, default=float))
    return r


def _stat(values, fn, fmt: str) -> str:
    v = _finite(values)
    return format(fn(v), fmt) if v else "-"


CONTROL_EVERY = 5  # records between two control times


def _control_spikes(runs: list[dict]) -> list[dict]:
    """``kinetic_energy_spikes`` at record times of the loading stage with no breakage check
    within a window before or after (and at least a window after loading starts)."""
    from jaxgran.breakage import metrics
    from jaxgran.scenes import oedometer_cantor as oc

    out = []
    for r in runs:
        t = np.asarray(r["series_t"], float)
        cfg = dataclasses.replace(oc.Config(), **r["config"])
        cfg = dataclasses.replace(cfg, snapshot_times=tuple(cfg.snapshot_times))
        win = _spike_window(cfg, r["dt_final_s"])
        te = np.array([c["t_load"] for c in r["checks"]])
        cand = t[::CONTROL_EVERY]
        far = np.array([te.size == 0 or np.min(np.abs(te - x)) > win for x in cand], bool)
        cand = cand[far & (cand >= win) & (cand <= t[-1] - win)]
        sp = metrics.kinetic_energy_spikes(t, r["series_ke"], cand, window=win)
        out += [x for x in sp if math.isfinite(x["peak"]) and x["baseline"] > 0]
    return out


def _finite(values) -> list[float]:
    return [x for x in values if x is not None and math.isfinite(x)]


def _run_stats(r: dict) -> dict:
    """Spike statistics of one run over its breakage checks (checks too close to the end of
    the run to have a sample in the window are left out)."""
    c = [x for x in r.get("checks", []) if math.isfinite(x["excess_J"])]
    nan = float("nan")
    med = statistics.median
    return {
        "excess_max": max((x["excess_J"] for x in c), default=nan),
        "excess_med": med([x["excess_J"] for x in c]) if c else nan,
        "ratio_max": max((x["ratio"] for x in c), default=nan),
        "ratio_med": med([x["ratio"] for x in c]) if c else nan,
        "jump_med": med([x["jump_1rec_J"] for x in c]) if c else nan,
        "frag_ov_max": max((e["fragment_max_overlap_m"] for e in r.get("events", [])), default=nan),
        "late": len(r.get("checks", [])) - len(c),
    }


def chart(rows: list[dict], modes: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r["ok"]]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    seed0 = min((r["seed"] for r in ok), default=0)
    for i, m in enumerate(modes):
        for r in ok:
            if r["mode"] == m and r["seed"] == seed0:
                ax[0].semilogy(r["series_t"], r["series_ke"], color=f"C{i}", lw=1, label=m)
                for c in r["checks"]:
                    ax[0].axvline(c["t_load"], color=f"C{i}", ls=":", lw=0.8)
    ax[0].set_xlabel("time since loading started (s)")
    ax[0].set_ylabel("kinetic energy (J)")
    ax[0].set_title(f"seed {seed0}; dotted: breakage checks", fontsize=9)
    ax[0].legend(fontsize=8)
    x = 0
    ticks, labels = [], []
    for i, m in enumerate(modes):
        for r in sorted((r for r in ok if r["mode"] == m), key=lambda r: r["seed"]):
            ax[1].bar(x, r["eroded_pct"], color=f"C{i}")
            ax[1].bar(x, r["fines_pct"], bottom=r["eroded_pct"], color=f"C{i}", alpha=0.4)
            ticks.append(x)
            labels.append(f"{m}\ns{r['seed']}")
            x += 1
        x += 0.5
    ax[1].set_xticks(ticks, labels, fontsize=7)
    ax[1].set_ylabel("mass lost / initial mass (%)\nsolid: eroded, light: fines")
    for i, m in enumerate(modes):
        ex = [c["excess_J"] for r in ok if r["mode"] == m for c in r["checks"]]
        ratio = [c["ratio"] for r in ok if r["mode"] == m for c in r["checks"]]
        ax[2].loglog(ratio, ex, "o", color=f"C{i}", alpha=0.7, label=m)
    ax[2].set_xlabel("KE spike ratio peak / baseline")
    ax[2].set_ylabel("KE spike peak - baseline (J)")
    ax[2].legend(fontsize=8)
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the scene's QUICK settings")
    ap.add_argument("--seeds", type=int, default=3, help="seeds 0 .. n-1 per mode")
    ap.add_argument("--modes", default="local,none", help=f"comma list of {', '.join(MODES)}")
    ap.add_argument("--raw", default=None, help="folder caching each run as JSON")
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "EROSION_RESULTS.md"))
    ap.add_argument("--png", default=str(ROOT / "docs" / "erosion_ke_mass.png"))
    ap.add_argument(
        "--same-process",
        action="store_true",
        help="run everything in this process (faster; later runs reuse compiled kernels, "
        "so their wall times are not comparable with the first)",
    )
    ap.add_argument("--run-one", default=None, help=argparse.SUPPRESS)  # MODE,SEED,OUT
    args = ap.parse_args()
    if args.run_one:
        import jax

        jax.config.update("jax_enable_x64", True)
        mode, seed, out = args.run_one.split(",", 2)
        r = one(mode, int(seed), args.quick)
        Path(out).write_text(json.dumps(r, default=float))
        return
    modes = [m for m in args.modes.split(",") if m]
    for m in modes:
        if m not in MODES:
            raise SystemExit(f"--modes: {m!r} is not one of {', '.join(MODES)}")
    import jax

    jax.config.update("jax_enable_x64", True)
    raw = Path(args.raw) if args.raw else None
    load0 = os.getloadavg()[0]
    rows = []
    for seed in range(args.seeds):
        for m in modes:
            r = cached(m, seed, args.quick, raw, args.same_process)
            rows.append(r)
            brief = {k: r.get(k) for k in ("mode", "seed", "ok", "n_events", "mass_lost_pct")}
            print(brief, f"wall {r['wall_time_s']:.0f} s", r.get("error", ""), flush=True)
    loads = [r.get("load_average", load0) for r in rows] or [load0]
    cfg = config(args.quick, 0, "local")
    from jaxgran.scenes import oedometer_cantor as oc

    changed = oc.QUICK if args.quick else MID
    dtype = "float64" if jax.config.jax_enable_x64 else "float32"
    cmd = "python benchmarks/bench_erosion.py" + (" --quick" if args.quick else "")
    if args.seeds != 3:
        cmd += f" --seeds {args.seeds}"
    if modes != ["local", "none"]:
        cmd += f" --modes {','.join(modes)}"
    lines = [
        f"## Fragment erosion, KE spike and mass loss (`{cmd}`)",
        "",
        f"Machine: {cpu_name()}, {os.cpu_count()} cores; jax {jax.__version__} "
        f"({jax.default_backend()}); {dtype}; {time.strftime('%Y-%m-%d')}; load average "
        f"{min(loads):.1f}-{max(loads):.1f} at the start of the runs"
        + (
            " (other jobs were running: wall times are pessimistic and noisy)."
            if max(loads) > 0.5 * (os.cpu_count() or 1)
            else "."
        )
        + " jaxgran at commit "
        + ", ".join(sorted({r.get("jaxgran_commit", "unknown") for r in rows}))
        + ". The `oedometer-cantor` scene (DSM, paper 000 §III) run by "
        "`oedometer_cantor.simulate_test`, one run after another, seeds 0.."
        f"{args.seeds - 1} (the seed draws the pentagons) per erosion mode. Config: scene "
        "defaults with "
        + ", ".join(f"`{k}={v}`" for k, v in changed.items())
        + f" (bar travel {1e3 * cfg.bar_speed * cfg.load_time:.1f} mm; dt "
        f"{cfg.dt_safety} x the stability limit of the lightest particle present).",
        "",
        "Modes: " + "; ".join(f"**{MODE_TEXT[m]}**" for m in modes) + ". `none` is "
        "`replace_particles(overlap=0)` through a `DsmBreakage` subclass swapped into the "
        "scene (module docstring of this script); `local` is the scene's own code path.",
        "",
        "Per run. Mass: lost / initial mass, eroded (strip or caps removed by the erosion, "
        "incl. the corner rounding) + fines (pieces under `min_fragment_fraction` of the "
        "mean grain). KE spike per breakage check (`metrics.kinetic_energy_spikes`, the "
        "scene's window; events of one check count once, and a check too close to the end "
        "of the run to have a sample in its window is counted as late and left out): "
        "excess = peak - baseline (J), ratio = peak / baseline; jump "
        "(1 rec) = KE one record after the check - KE before. Fragment overlap: the largest "
        "overlap of a new fragment with a neighbour right after the replacement (mm; the "
        f"sphero-radius is {1e3 * cfg.sphero_radius:.1f} mm). Wall: the whole test, settling "
        "and compilation included"
        + (
            " (all runs in one process: the first compiles the kernels that later runs "
            "reuse, so wall times are not comparable)."
            if args.same_process
            else ", each run in a fresh process."
        ),
        "",
        "| mode | seed | events (checks) | mass lost % | eroded % | fines % | excess max (J) "
        "| excess median (J) | ratio max | ratio median | jump (1 rec) median (J) "
        "| fragment overlap max (mm) | steps | wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if not r["ok"]:
            lines.append(
                f"| {r['mode']} | {r['seed']} | failed: {r['error'][:120]} |"
                + " |" * 10
                + f" {r['wall_time_s']:.0f} |"
            )
            continue
        st = _run_stats(r)
        flags = "" if r["finite"] and not r["escaped"] else " (NaN or escaped)"
        lines.append(
            f"| {r['mode']} | {r['seed']}{flags} | {r['n_events']} ({r['n_checks']}"
            + (f"; {st['late']} late" if st["late"] else "")
            + ") "
            f"| {r['mass_lost_pct']:.3f} | {r['eroded_pct']:.3f} | {r['fines_pct']:.3f} "
            f"| {st['excess_max']:.3g} | {st['excess_med']:.3g} | {st['ratio_max']:.3g} "
            f"| {st['ratio_med']:.3g} | {st['jump_med']:.3g} | {1e3 * st['frag_ov_max']:.4f} "
            f"| {r['steps']} | {r['wall_time_s']:.0f} |"
        )
    lines += [
        "",
        "Mean per mode over the runs that finished (the spike columns: mean of the runs' "
        "values; per event: mass lost / parent mass).",
        "",
        "| mode | runs | events | mass lost % | eroded % | fines % | lost / parent, per "
        "event (%) | excess max (J) | excess median (J) | ratio max | ratio median "
        "| wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in modes:
        rs = [r for r in rows if r["mode"] == m and r["ok"]]
        if not rs:
            lines.append(f"| {m} | 0 |" + " |" * 10)
            continue
        st = [_run_stats(r) for r in rs]
        per_ev = [100 * e["mass_lost"] / e["parent_mass"] for r in rs for e in r["events"]]
        mean = statistics.mean
        lines.append(
            f"| {m} | {len(rs)} | {mean(r['n_events'] for r in rs):.1f} "
            f"| {mean(r['mass_lost_pct'] for r in rs):.3f} "
            f"| {mean(r['eroded_pct'] for r in rs):.3f} "
            f"| {mean(r['fines_pct'] for r in rs):.3f} | {_stat(per_ev, mean, '.3f')} "
            f"| {_stat([s['excess_max'] for s in st], mean, '.3g')} "
            f"| {_stat([s['excess_med'] for s in st], mean, '.3g')} "
            f"| {_stat([s['ratio_max'] for s in st], mean, '.3g')} "
            f"| {_stat([s['ratio_med'] for s in st], mean, '.3g')} "
            f"| {mean(r['wall_time_s'] for r in rs):.0f} |"
        )
    ev_all = [e for r in rows if r["ok"] for e in r["events"]]
    # events that every mode breaks (a mode may merge all the pieces back: NaN)
    ev_all = [e for e in ev_all if all(math.isfinite(e[f"dry_mass_lost_{m}"]) for m in MODES)]
    if ev_all:
        lines += [
            "",
            f"Paired mass loss: for each of the {len(ev_all)} events above that every mode "
            "breaks (a mode may merge all the pieces back, leaving the parent whole), the mass "
            "that each erosion mode removes from the same parent cut by the same planes at the "
            "same instant (a dry run of `replace_particles`), as a percentage of the parent "
            "mass: lost (fines included) and eroded (lost - fines); and the parent's largest "
            "overlap before the breakage.",
            "",
            "| | "
            + " | ".join(f"{m}: lost % | {m}: eroded %" for m in MODES)
            + " | parent max overlap (mm) |",
            "|---|" + "---|" * (2 * len(MODES) + 1),
        ]
        for name, fn in (("mean", statistics.mean), ("median", statistics.median), ("max", max)):
            cells = []
            for m in MODES:
                lost = [e[f"dry_mass_lost_{m}"] / e["parent_mass"] for e in ev_all]
                fines = [e[f"dry_fines_{m}"] / e["parent_mass"] for e in ev_all]
                cells.append(_stat([100 * x for x in lost], fn, ".3f"))
                eroded = [100 * (a - b) for a, b in zip(lost, fines, strict=True)]
                cells.append(_stat(eroded, fn, ".3f"))
            ov = _stat([1e3 * e["parent_max_overlap_m"] for e in ev_all], fn, ".4f")
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {ov} |")
    control = {m: _control_spikes([r for r in rows if r["mode"] == m and r["ok"]]) for m in modes}
    if any(control.values()):
        lines += [
            "",
            "Control: the same spike measure at times without breakage (every "
            f"{CONTROL_EVERY}th record of the loading stage whose window holds no breakage "
            "check and that is at least one window after the start of loading), since the "
            "pile rearranges and its KE fluctuates without breakage at this bar speed.",
            "",
            "| mode | control samples | excess median (J) | excess 90th pct (J) "
            "| ratio median | ratio 90th pct |",
            "|---|---|---|---|---|---|",
        ]
        for m, c in control.items():
            if not c:
                continue
            ex = np.array([x["peak"] - x["baseline"] for x in c])
            ratio = np.array([x["ratio"] for x in c])
            lines.append(
                f"| {m} | {len(c)} | {np.median(ex):.3g} | {np.percentile(ex, 90):.3g} "
                f"| {np.median(ratio):.3g} | {np.percentile(ratio, 90):.3g} |"
            )
    first = {}
    for r in rows:
        if r["ok"] and r["checks"]:
            first.setdefault(r["seed"], {})[r["mode"]] = r
    if any(len(v) > 1 for v in first.values()):
        lines += [
            "",
            "First breakage of each seed (identical state in every mode up to it): KE spike "
            "excess (J) / ratio, and the largest resultant force (N, contacts and walls) on "
            "a fragment right after the replacement against that on the parent just before "
            "(close to equilibrium, so small).",
            "",
            "| seed | "
            + " | ".join(f"{m}: excess (J) / ratio / F frag, F parent (N)" for m in modes)
            + " |",
            "|---|" + "---|" * len(modes),
        ]
        for seed, by in sorted(first.items()):
            cells = []
            for m in modes:
                if m not in by:
                    cells.append("-")
                    continue
                c = by[m]["checks"][0]
                e = [x for x in by[m]["events"] if abs(x["t_load"] - c["t_load"]) < 1e-12]
                f_frag = max(x["fragment_max_force_N"] for x in e)
                f_par = max(x["parent_max_force_N"] for x in e)
                cells.append(
                    f"t = {c['t_load'] * 1e3:.1f} ms: {c['excess_J']:.3g} / {c['ratio']:.3g} / "
                    f"{f_frag:.3g}, {f_par:.3g}"
                )
            lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    write_markdown(args.md, lines, "../docs/erosion_ke_mass.png", "erosion KE and mass")
    chart(rows, modes, Path(args.png))
    print(f"wrote {args.md} and {args.png}")


if __name__ == "__main__":
    main()
