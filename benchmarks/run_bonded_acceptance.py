"""Acceptance numbers of the bonded Voronoi scenes (issue 6, paper 002), regenerated.

Each part runs its realisations one after another (on a 2-core CPU the vmapped ensemble is
slower than sequential runs) and stores the raw series of every run (``<out>/raw/*.npz``),
so the analysis and the figures can be redone without simulating (``--analyse-only``):

    python benchmarks/run_bonded_acceptance.py biaxial      # Hoek-Brown, residual line, p drift
    python benchmarks/run_bonded_acceptance.py cantilever   # deflection vs Euler-Bernoulli
    python benchmarks/run_bonded_acceptance.py brazilian    # sigma_t over 8 seeds, bursts
    python benchmarks/run_bonded_acceptance.py sweep        # sigma_t/B_n, S/K_n calibration
    python benchmarks/run_bonded_acceptance.py p-drift --seed 2 --pressures 100e6  # p vs rate
    python benchmarks/run_bonded_acceptance.py p-drift --rates 10 --servo-max-speed 50  # cap
    python benchmarks/run_bonded_acceptance.py p-drift --rates 10 --record-every 10  # a burst

Results go to ``<out>/<part>.json`` (default ``benchmarks/bonded_acceptance``), figures to
``docs/`` (``hoek_brown.png``, ``cantilever.png``, ``bursts.png``, ``bonded_sweeps.png``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _release_compiled() -> None:
    """Drop this process's compiled executables between seeds (each seed's specimen has its
    own capacities, so nothing carries over): see ``benchmarks/machine.py``."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import release_compiled

    release_compiled()


def _dump(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1, default=float))


def _floats(csv: str) -> list[float]:
    return [float(x) for x in csv.split(",") if x]


# ------------------------------------------------------------------------------ biaxial


def biaxial(args) -> dict:
    """Constant-p shearing at every pressure for every seed, plus unconfined compression;
    Hoek-Brown fits of the peak envelope and the residual frictional line."""
    from jaxgran import analysis as an
    from jaxgran.scenes import bonded_biaxial as bx

    raw = Path(args.out) / "raw"
    cfg = dataclasses.replace(
        bx.Config(),
        n_cells=args.cells,
        strain_rate=args.strain_rate,
        max_strain=args.max_strain,
        record_every=args.record_every,
        **({"eps_th": args.eps_th} if args.eps_th else {}),
        shear_damping=args.shear_damping,
    )
    pressures = _floats(args.pressures)
    seeds = list(range(args.seeds))
    T = cfg.thickness
    wall = {}
    if not args.analyse_only:
        raw.mkdir(parents=True, exist_ok=True)
        for seed in seeds:
            for p in pressures:
                path = raw / f"biaxial_s{seed}_p{p / 1e6:g}.npz"
                if path.exists():
                    continue
                t0 = time.perf_counter()
                shear, iso, setup, _ = bx.isotropic_then_shear(cfg, [seed], (p,))
                r = shear.realisation(0)
                _, times = an.broken_bond_points(r.state)
                np.savez(
                    path,
                    **{k: np.asarray(r.series[k]) for k in ("wall_force", "wall_point", "time")},
                    n_broken=np.asarray(r.series["n_broken"]),
                    break_times=times,
                    dt=float(setup.params.dt),
                    steps=shear.steps + iso.steps,
                    wall_time_s=time.perf_counter() - t0,
                )
                print(
                    f"seed {seed} p {p / 1e6:g} MPa: {time.perf_counter() - t0:.0f} s", flush=True
                )
            path = raw / f"unconfined_s{seed}.npz"
            if not path.exists():
                t0 = time.perf_counter()
                res, setup = bx.unconfined(cfg, [seed])
                r = res.realisation(0)
                el = bx.measure_elastic(r, setup.gauge0[0], T, 1.0)
                np.savez(
                    path,
                    **{k: np.asarray(r.series[k]) for k in ("wall_force", "wall_point", "time")},
                    strength=el["strength_Pa"],
                    modulus=el.get("modulus_Pa", np.nan),
                    poisson=el.get("poisson_ratio", np.nan),
                    wall_time_s=time.perf_counter() - t0,
                )
                print(f"seed {seed} unconfined: {time.perf_counter() - t0:.0f} s", flush=True)
            _release_compiled()
    rows, bursts = [], []
    for seed in seeds:
        for p in pressures:
            path = raw / f"biaxial_s{seed}_p{p / 1e6:g}.npz"
            if not path.exists():
                continue
            d = np.load(path)
            run = _Run({k: d[k] for k in ("wall_force", "wall_point", "time", "n_broken")})
            m = bx.measure_shear(run, p, T, cfg.residual_fraction)
            m.update(seed=seed, wall_time_s=float(d["wall_time_s"]), steps=int(d["steps"]))
            rows.append(m)
            t = np.asarray(d["time"], float)
            counts, _ = an.burst_sizes(d["break_times"], float(t[1] - t[0]))
            bursts.append(counts[counts > 0])
            wall[(seed, p)] = float(d["wall_time_s"])
    ucs = []
    for seed in seeds:
        path = raw / f"unconfined_s{seed}.npz"
        if path.exists():
            d = np.load(path)
            ucs.append({"seed": seed, "strength_Pa": float(d["strength"])})
            ucs[-1].update(modulus_Pa=float(d["modulus"]), poisson_ratio=float(d["poisson"]))
    out = _biaxial_fits(rows, ucs, pressures, cfg)
    sizes = np.concatenate(bursts) if bursts else np.zeros(0)
    if sizes.size >= 10:
        fit = an.power_law_mle(sizes, 1)
        out["bursts_pooled"] = {k: fit[k] for k in ("alpha", "alpha_err", "n", "ks")}
    out["config"] = dataclasses.asdict(cfg)
    out["runs"] = rows
    out["unconfined"] = ucs
    out["wall_time_s_total"] = float(sum(wall.values()))
    _dump(Path(args.out) / "biaxial.json", out)
    from jaxgran import plot_bonded

    plot_bonded.hoek_brown_figure(out, DOCS / args.figure)
    return out


class _Run:
    """The fields of a RunResult that the measuring functions read."""

    def __init__(self, series: dict):
        self.series = series


def _biaxial_fits(rows: list[dict], ucs: list[dict], pressures, cfg) -> dict:
    from jaxgran import analysis as an
    from jaxgran.scenes import bonded_biaxial as bx

    out: dict = {"pressures_Pa": pressures}
    by_p = []
    for p in pressures:
        rs = [r for r in rows if r["p_target_Pa"] == p]
        if not rs:
            continue
        st = an.summary_stats(rs)
        by_p.append(
            {"p_Pa": p, "n": len(rs), "n_true_peaks": sum(r["true_peak"] for r in rs)}
            | {k: st[k] for k in st if k in _KEYS}
        )
    out["by_pressure"] = by_p
    true = [r for r in rows if r["true_peak"]]
    out["n_true_peaks"] = len(true)
    out["n_runs"] = len(rows)
    if rows:
        dev = [r["p_max_relative_deviation_to_peak"] for r in rows]
        out["p_max_relative_deviation_to_peak"] = float(np.max(dev))
        out["p_mean_relative_deviation"] = float(
            np.mean([r["p_mean_relative_deviation"] for r in rows])
        )
    u = [v["strength_Pa"] for v in ucs]
    out["fits"] = {
        "with_unconfined": bx.envelope_fits(rows, u),
        "peaks_only": bx.envelope_fits(rows),
        "means_with_unconfined": bx.envelope_fits(rows, u, means=True),
    }
    return out


_KEYS = (
    "q_peak_Pa",
    "p_at_peak_Pa",
    "sigma_1_peak_Pa",
    "sigma_3_peak_Pa",
    "axial_strain_at_peak",
    "q_residual_Pa",
    "p_residual_Pa",
    "q_drop_after_peak",
    "p_max_relative_deviation",
    "p_max_relative_deviation_to_peak",
    "p_mean_relative_deviation",
)


# ------------------------------------------------------------------------------ cantilever

CANTILEVER_CASES = {
    # Table 1 material (E_t ~ 0.6 E_c), the scene's beam: L / s = 6
    "table1": {},
    # tension and compression moduli matched (B_n = B_t = 33 GPa gives E_t ~ E_c), a more
    # slender beam L / s = 9 with about as many cells across the depth (7)
    "matched_slender": {
        "b_n": 33.0e9,
        "b_t": 33.0e9,
        "length": 0.45,
        "n_cells": 440,
        "hold_periods": 1.5,
    },
}
# the same beam with a straight clamp face: the clamp stretch tessellated apart
# (bonded_cantilever.Config.clamp = "straight", paper 002's fixed plate)
CANTILEVER_CASES["matched_slender_straight_clamp"] = {
    **CANTILEVER_CASES["matched_slender"],
    "clamp": "straight",
}
# the matched beam at L / s = 15, same cell size (733 cells): the clamp's root rotation
# falls as s / L and the shear deflection as (s / L)^2 relative to the bending
CANTILEVER_CASES["matched_slender15"] = {
    **CANTILEVER_CASES["matched_slender"],
    "length": 0.75,
    "n_cells": 733,
}

# and at L / s = 20 (978 cells): the root rotation's share falls further, as s / L
CANTILEVER_CASES["matched_slender20"] = {
    **CANTILEVER_CASES["matched_slender"],
    "length": 1.0,
    "n_cells": 978,
}


def cantilever(args) -> dict:
    """Each case: E_c, nu and E_t measured on a block of the beam's material and cell size,
    then the beam loaded, relaxed and compared with Eq. 29 (E_c and the bimodular flexural
    modulus) and with Timoshenko."""
    from jaxgran.scenes import bonded_cantilever as bc

    raw = Path(args.out) / "raw"
    raw.mkdir(parents=True, exist_ok=True)
    cases = args.cases.split(",") if args.cases else list(CANTILEVER_CASES)
    results, curves = {}, []
    prev = Path(args.out) / "cantilever.json"
    if prev.exists():
        results = json.loads(prev.read_text()).get("cases", {})
    for name in cases:
        cfg = dataclasses.replace(bc.Config(), **CANTILEVER_CASES[name])
        path = raw / f"cantilever_{name}.npz"
        if not args.analyse_only:
            t0 = time.perf_counter()
            mod = bc.measure_moduli(cfg, [cfg.seed])[0]
            t_mod = time.perf_counter() - t0
            e_b = bc.flexural_modulus(mod["E_t_Pa"], mod["E_c_Pa"])
            res, setup = bc.simulate_test(cfg, [cfg.seed], modulus=e_b)
            r = res.realisation(0)
            g = setup.geos[0]
            x, w = bc.deflection(r.state, g, cfg)
            np.savez(
                path,
                x=x,
                w=w,
                kinetic_energy=np.asarray(r.series["kinetic_energy"]),
                force_N=g["force_N"],
                arm_m=g["arm_m"],
                second_moment_m4=g["second_moment_m4"],
                E_c_Pa=mod["E_c_Pa"],
                E_t_Pa=mod["E_t_Pa"],
                poisson_ratio=mod["poisson_ratio"],
                steps=res.steps,
                dt=float(setup.params.dt),
                wall_time_moduli_s=t_mod,
                wall_time_beam_s=res.wall_time_s,
                n_broken=int(np.asarray(r.series["n_broken"])[-1]),
            )
        d = np.load(path)
        geo = {k: float(d[k]) for k in ("force_N", "arm_m", "second_moment_m4")}
        mod = {k: float(d[k]) for k in ("E_c_Pa", "E_t_Pa", "poisson_ratio")}
        c = bc.compare_deflection(d["x"], d["w"], geo, cfg, mod)
        ke = np.asarray(d["kinetic_energy"], float)
        c.update(mod)
        c.update(
            config=CANTILEVER_CASES[name],
            slenderness_L_over_s=cfg.length / cfg.depth,
            n_cells=cfg.n_cells,
            steps=int(d["steps"]),
            dt_s=float(d["dt"]),
            final_over_max_kinetic_energy=float(ke[-1] / ke.max()),
            n_broken=int(d["n_broken"]),
            wall_time_s=float(d["wall_time_moduli_s"] + d["wall_time_beam_s"]),
        )
        results[name] = c
        x, w, f, a, i = d["x"], d["w"], geo["force_N"], geo["arm_m"], geo["second_moment_m4"]
        e_f = c["E_flexural_Pa"]
        curves.append(
            {
                "label": f"{name}: L/s = {cfg.length / cfg.depth:.0f}, E_t/E_c = "
                f"{mod['E_t_Pa'] / mod['E_c_Pa']:.2f}",
                "x": x,
                "w": w,
                "theory": {
                    f"Eq. 29, E_c ({c['tip_error_E_c']:+.0%} at tip)": bc.euler_bernoulli(
                        x, f, a, mod["E_c_Pa"], i
                    ),
                    f"Eq. 29, E_flexural ({c['tip_error_E_flexural']:+.0%})": bc.euler_bernoulli(
                        x, f, a, e_f, i
                    ),
                    f"Timoshenko, E_flexural ({c['tip_error_timoshenko_E_flexural']:+.0%})": (
                        bc.timoshenko(
                            x, f, a, e_f, i, cfg.depth * cfg.thickness, mod["poisson_ratio"]
                        )
                    ),
                },
            }
        )
    out = {"cases": results}
    _dump(Path(args.out) / "cantilever.json", out)
    from jaxgran import plot_bonded

    plot_bonded.cantilever_figure(curves, DOCS / "cantilever.png")
    return out


# ------------------------------------------------------------------------------ Brazilian


def brazilian_run(cfg, seed: int) -> dict:
    """One bonded Brazilian disc (``cfg``, Voronoi ``seed``) to failure: the scene's measured
    figures plus seed, steps, dt (s), wall time (s) and the burst sizes."""
    from jaxgran import analysis as an
    from jaxgran.scenes import bonded_brazilian as bz

    t0 = time.perf_counter()
    setup = bz.build(cfg, seeds=[seed])
    res, _ = bz.simulate_test(cfg, setup=setup)
    r = res.realisation(0)
    m = bz.measure(r, setup.gap0[0], cfg.diameter, setup.material)
    t = np.asarray(r.series["time"], float)
    _, times = an.broken_bond_points(r.state)
    counts, _ = an.burst_sizes(times, float(t[1] - t[0]))
    m.update(
        seed=seed,
        steps=int(res.steps),
        dt_s=float(setup.params.dt),
        wall_time_s=time.perf_counter() - t0,
        burst_sizes=counts[counts > 0].tolist(),
    )
    return m


def brazilian(args) -> dict:
    """``--seeds`` discs of ``--cells`` cells one after another: sigma_t mean +- std, the
    crack angle, and the burst exponent pooled over all discs (discrete ML)."""
    from jaxgran import analysis as an
    from jaxgran.scenes import bonded_brazilian as bz

    raw = Path(args.out) / "raw"
    raw.mkdir(parents=True, exist_ok=True)
    cfg = dataclasses.replace(bz.Config(), n_cells=args.cells)
    per, sizes = [], []
    for seed in range(args.seeds):
        path = raw / f"brazilian_c{args.cells}_s{seed}.json"
        if not path.exists() and not args.analyse_only:
            m = brazilian_run(cfg, seed)
            _dump(path, m)
            print(f"brazilian seed {seed}: {m['wall_time_s']:.0f} s", flush=True)
            _release_compiled()
        if path.exists():
            m = json.loads(path.read_text())
            sizes.append(np.asarray(m.pop("burst_sizes"), int))
            per.append(m)
    st = an.summary_stats(per)
    keys = (
        "tensile_strength_Pa",
        "force_max_N",
        "strain_at_force_max",
        "slope_S_Pa",
        "rising_branch_r2",
        "crack_angle_from_loading_axis_deg",
        "n_broken",
        "burst_exponent",
        "wall_time_s",
        "steps",
    )
    out = {
        "n_cells": args.cells,
        "realisations": len(per),
        "stats": {k: st[k] for k in keys if k in st},
    }
    pooled = np.concatenate(sizes) if sizes else np.zeros(0, int)
    if pooled.size >= 10:
        fit = an.power_law_mle(pooled, 1)
        out["bursts_pooled"] = {k: fit[k] for k in ("alpha", "alpha_err", "n", "ks")}
        # spread between realisations: the per-disc exponents' standard error of the mean
        alphas = [m["burst_exponent"] for m in per if "burst_exponent" in m]
        if len(alphas) > 1:
            out["bursts_pooled"]["alpha_sem_over_discs"] = float(
                np.std(alphas, ddof=1) / np.sqrt(len(alphas))
            )
        try:
            scan = an.power_law_scan(pooled)
            out["bursts_pooled_xmin_scan"] = {
                k: scan[k] for k in ("alpha", "alpha_err", "n", "x_min", "ks")
            }
        except ValueError as exc:
            out["bursts_pooled_xmin_scan"] = {"error": str(exc)}
    out["per_realisation"] = per
    _dump(Path(args.out) / f"brazilian_c{args.cells}.json", out)
    from jaxgran import plot_bonded

    plot_bonded.bursts_figure({f"Brazilian, {len(per)} discs": pooled}, DOCS / "bursts.png")
    return out


def sweep(args) -> dict:
    """Paper 002 Fig. 8-9 calibration curves, each one vmapped batch over the parameters."""
    from jaxgran.scenes import bonded_brazilian as bz

    cfg = dataclasses.replace(bz.Config(), n_cells=args.sweep_cells)
    path = Path(args.out) / "sweep.json"
    out = json.loads(path.read_text()) if path.exists() else {}
    if not args.analyse_only:
        if "tensile" not in out:
            out["tensile"] = bz.sweep(cfg)
            _dump(path, out)
        if "slope" not in out:
            out["slope"] = bz.sweep_stiffness(cfg)
            _dump(path, out)
    out["n_cells"] = args.sweep_cells
    _dump(path, out)
    from jaxgran import plot_bonded

    if "tensile" in out and "slope" in out:
        plot_bonded.sweeps_figure(out, DOCS / "bonded_sweeps.png")
    return out


# ------------------------------------------------------------------------------ p drift


def p_drift(args) -> dict:
    """How far p strays from its target up to the peak against the strain rate, for one
    seed (``--seed``) and the first of ``--pressures``: does a slower, more quasi-static
    shearing hold p closer (``--rates``)?"""
    from jaxgran.scenes import bonded_biaxial as bx

    seed, p = int(args.seed), _floats(args.pressures)[0]
    ti = float(args.servo_integral)
    tag = "" if math.isinf(ti) else f"_pi{ti:g}"
    response = float(args.servo_response) or bx.Config().servo_response
    if args.servo_response:
        tag += f"_tau{response:g}"
    cap = float(args.servo_max_speed) or bx.Config().servo_max_speed
    if args.servo_max_speed:
        tag += f"_cap{cap:g}"
    if args.record_every != 50:
        tag += f"_rec{args.record_every}"
    path = Path(args.out) / f"p_drift_s{seed}_p{p / 1e6:g}{tag}.json"
    rows = json.loads(path.read_text())["runs"] if path.exists() else []
    done = {r["strain_rate"] for r in rows}
    for rate in _floats(args.rates):
        if rate in done or args.analyse_only:
            continue
        cfg = dataclasses.replace(
            bx.Config(), n_cells=args.cells, strain_rate=rate, max_strain=args.max_strain,
            record_every=args.record_every, servo_integral=ti, servo_response=response,
            servo_max_speed=cap,
        )  # fmt: skip
        t0 = time.perf_counter()
        shear, iso, setup, _ = bx.isotropic_then_shear(cfg, [seed], (p,))
        m = bx.measure_shear(shear.realisation(0), p, cfg.thickness, cfg.residual_fraction)
        keys = ("q_peak_Pa", "p_at_peak_Pa", "axial_strain_at_peak", "true_peak")
        rows.append(
            {"strain_rate": rate, "wall_time_s": time.perf_counter() - t0,
             "steps": shear.steps + iso.steps,
             "p_max_relative_deviation_to_peak": m["p_max_relative_deviation_to_peak"],
             "p_max_relative_deviation": m["p_max_relative_deviation"],
             **{k: m[k] for k in keys},
             **_largest_excursion(shear.realisation(0), p, cfg.thickness)}
        )  # fmt: skip
        print(json.dumps(rows[-1], default=float), flush=True)
        _dump(path, {"seed": seed, "p_target_Pa": p, "runs": rows})
    out = {"seed": seed, "p_target_Pa": p, "runs": rows}
    _dump(path, out)
    return out


def _largest_excursion(run, p_target: float, thickness: float) -> dict:
    """Where p strays most before the peak: p's largest and rms deviation in the elastic
    part (before the first broken bond), and around the largest excursion the axial and
    lateral stresses before it and at it and the bonds broken in between (MPa, records)."""
    from jaxgran import analysis as an
    from jaxgran.scenes import bonded_biaxial as bx

    s_ax, s_lat, height, _ = bx.stresses(run.series, thickness)
    p, q = an.pq_invariants(s_ax, s_lat)
    e1 = 1.0 - height / height[0]
    nb = np.asarray(run.series["n_broken"])
    t = np.asarray(run.series["time"], float)
    k = int(np.argmax(q))
    dev = (p - p_target) / p_target
    idx = np.arange(p.size)
    pre = (e1 > 0.05 * e1[-1]) & (idx <= k)
    elastic = pre & (nb == 0)
    j = int(idx[pre][np.argmax(np.abs(dev[pre]))])
    before = int(idx[(idx < j) & (nb < nb[j])].max(initial=0))  # last record before the burst
    return {
        "record_interval_s": float(t[1] - t[0]),
        "p_max_relative_deviation_elastic": float(np.abs(dev[elastic]).max(initial=0.0)),
        "p_rms_relative_deviation_elastic": float(np.sqrt(np.mean(dev[elastic] ** 2)))
        if elastic.any()
        else float("nan"),
        "excursion": {
            "relative_deviation": float(dev[j]),
            "axial_strain": float(e1[j]),
            "time_after_burst_start_s": float(t[j] - t[before]),
            "bonds_broken_before_and_at": [int(nb[before]), int(nb[j])],
            "sigma_axial_before_and_at_MPa": [float(s_ax[before] / 1e6), float(s_ax[j] / 1e6)],
            "sigma_lateral_before_and_at_MPa": [
                float(s_lat[before] / 1e6),
                float(s_lat[j] / 1e6),
            ],
            "sigma_axial_lowest_in_between_MPa": float(s_ax[before : j + 1].min() / 1e6),
        },
    }


# ------------------------------------------------------------------------------ main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("part", choices=["biaxial", "cantilever", "brazilian", "sweep", "p-drift"])
    ap.add_argument("--cases", default="", help="cantilever cases (default: all)")
    ap.add_argument("--sweep-cells", type=int, default=150)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "bonded_acceptance"))
    ap.add_argument("--analyse-only", action="store_true", help="reuse <out>/raw, no runs")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--cells", type=int, default=0, help="default: 200 biaxial, 500 Brazilian")
    ap.add_argument("--pressures", default="50e6,100e6,150e6,200e6,250e6,300e6")
    ap.add_argument("--strain-rate", type=float, default=10.0)
    ap.add_argument("--max-strain", type=float, default=0.03)
    ap.add_argument("--record-every", type=int, default=50)
    ap.add_argument(
        "--figure", default="hoek_brown.png", help="biaxial: envelope figure's name in docs/"
    )
    ap.add_argument(
        "--eps-th",
        type=float,
        default=0.0,
        help="biaxial: bond strain threshold (default: the scene's, paper 002 Table 1)",
    )
    ap.add_argument(
        "--shear-damping",
        type=float,
        default=0.0,
        help="biaxial: viscous damping of the cells while shearing, 1/s (default 0: none, "
        "paper 002; bonded_biaxial.Config.shear_damping)",
    )
    ap.add_argument(
        "--servo-response",
        type=float,
        default=0.0,
        help="p-drift: servo time constant in wave transits (default: the scene's)",
    )
    ap.add_argument("--rates", default="10,5", help="p-drift: strain rates (1/s)")
    ap.add_argument("--seed", type=int, default=2, help="p-drift: the one seed")
    ap.add_argument(
        "--servo-integral",
        type=float,
        default=math.inf,
        help="p-drift: servo integral time in loop time constants (default inf: proportional)",
    )
    ap.add_argument(
        "--servo-max-speed",
        type=float,
        default=0.0,
        help="p-drift: servo walls' speed cap, x strain rate x height (default: the scene's)",
    )
    args = ap.parse_args()
    args.cells = args.cells or {"brazilian": 500}.get(args.part, 200)
    _x64()
    sys.path.insert(0, str(ROOT))
    parts = {
        "biaxial": biaxial,
        "cantilever": cantilever,
        "brazilian": brazilian,
        "sweep": sweep,
        "p-drift": p_drift,
    }
    out = parts[args.part](args)
    keys = [k for k in out if k not in ("runs", "config")]
    print(json.dumps({k: out[k] for k in keys}, indent=1, default=float))


if __name__ == "__main__":
    main()
