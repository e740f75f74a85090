"""Plate contact: a 50 mm disc of bonded elementary discs crushed between two plates to
overall breakage (paper 003 §5, the 2D analogue of its ball-plane test), and the Brazilian
splitting test of the same disc (paper 003 §4).

The disc (diameter ``diameter``) is meshed by default as ~120 Voronoi cells bonded along
their shared edges (``--set particles=discs`` for a packing of elementary discs of 2.5-5 mm,
paper 003's balls in 2D) by interface bonds (``--set bond=parallel`` for the baseline). The
default is the mesh because the stress field inside the disc is what this scene measures:
a packing of discs at solid fraction 0.7 carries the load along its own force chains, and
its axis stress scatters from -0.4 to 1.7 of the disc solution between packings (0.63 on
average over 32 seeds), while the mesh reads 0.96 +- 0.04 (docs/speed_vs_accuracy.md
section 4); the discs are 3.0x cheaper per step. With the gypsum-like material of
:mod:`jaxgran.scenes.interface` (plane stress, slab thickness T). Two frictional plates
close at ``strain_rate x D`` in total; the run stops once the force has fallen below
``drop_fraction x F_max``.

Outputs (``plate-contact``): the force-displacement curve; cracks coloured by failure mode at
50 % and 90 % of the peak (before it), at the peak and at the end; the horizontal stress along
the loading axis from ``n_circles`` measurement circles (paper 003's measurement balls;
Love-Weber stress of the interface forces, :func:`jaxgran.scenes.interface.circle_stresses`)
against the closed-form disc solution (two point loads P, PHYSICS §B: on the loaded diameter
``sigma_xx = 2 P / (pi D T)`` in tension, constant), at the last record before the first
element failure and at ``compare_fraction`` of the peak; the error in the middle third; the
velocity field at the moment of breakage (the first record after the peak where the force
has dropped below ``break_fraction x F_max``); compression and tension force chains before
the peak; the split angle (the line between the two largest fragments' centroids, from the
horizontal, i.e. the fracture plane's angle from the loading axis; fragments are held
together by more than one chain of bonds, so a thread of bonded grains left between two
halves does not join them; and the principal axis of the tension failures); where the
shear failures are (share within ``D / 6`` of a plate against the share of all interfaces
there) and the cone-core half-angle (median angle from the loading axis of the shear
failures seen from the nearer plate contact). Speed: wall time
and particle-steps/s of the compiled segments, for the disc and the Voronoi specimen.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np

from .. import analysis as an
from .. import interface as itf
from . import interface as si
from .base import write_outputs

SCENE = "plate-contact"


@dataclasses.dataclass(frozen=True)
class Config(si.Common):
    particles: str = "voronoi"  # space filling (module docstring), or "discs" (paper 003)
    diameter: float = 0.05  # m, D
    strain_rate: float = 2.0  # 1/s, plate closing speed / D
    max_strain: float = 0.02
    drop_fraction: float = 0.3
    break_fraction: float = 0.8  # velocity field when F first drops below this x F_max
    n_circles: int = 10  # measurement circles along the loading axis
    circle_diameter: float = 0.01  # m (paper 003: 5 mm balls in 3D; 2D needs more grains)
    compare_fraction: float = 0.5  # also compare the axis stress at this x F_max
    detailed: bool = True  # stress profiles, force chains, velocity field, cone core


QUICK = {"record_every": 25, "records_per_segment": 8}


def build(cfg: Config) -> si.Setup:
    mat = si.material_from(cfg)
    region = ("disc", 0.5 * cfg.diameter, (0.0, 0.0))
    spec = si.make_specimen(cfg, region, mat)
    walls = si.axial_walls(spec, 0.5 * cfg.strain_rate * cfg.diameter, cfg.diameter)
    return si.prepare(spec, mat, walls, cfg, margin=0.6 * cfg.diameter)


def plate_force(series: dict) -> tuple[np.ndarray, np.ndarray]:
    """Mean compressive plate force (N) and plate distance (m) per record."""
    return si.axial_load(series)


def circle_centres(cfg: Config) -> np.ndarray:
    """Centres of the measurement circles on the loading axis ``[n, 2]`` (m), spread evenly."""
    n = cfg.n_circles
    y = cfg.diameter * ((np.arange(n) + 0.5) / n - 0.5)
    return np.stack([np.zeros(n), y], axis=1)


def closed_form_sigma_xx(force: float, cfg: Config, x=0.0, y=0.0):
    """sigma_xx of a disc under two point loads P at (0, +-R) (Pa, tension positive; PHYSICS
    §B, Timoshenko & Goodier): ``-(2P / (pi T)) [(R - y) x^2 / r1^4 + (R + y) x^2 / r2^4 -
    1 / D]``, which is ``2 P / (pi D T)`` all along the loaded diameter."""
    r = 0.5 * cfg.diameter
    x, y = np.asarray(x, float), np.asarray(y, float)
    r1 = x * x + (r - y) ** 2
    r2 = x * x + (r + y) ** 2
    s = (r - y) * x * x / r1**2 + (r + y) * x * x / r2**2 - 1.0 / cfg.diameter
    return -2.0 * force / (math.pi * cfg.thickness) * s


def closed_form_circle_mean(force: float, cfg: Config, centre, radius: float) -> float:
    """The closed-form sigma_xx averaged over a measurement circle (Pa): what the circle
    should read (polar midpoint rule, 40 x 64 points)."""
    rho = radius * np.sqrt((np.arange(40) + 0.5) / 40)  # equal-area rings
    phi = 2 * math.pi * (np.arange(64) + 0.5) / 64
    x = centre[0] + rho[:, None] * np.cos(phi)[None, :]
    y = centre[1] + rho[:, None] * np.sin(phi)[None, :]
    return float(np.mean(closed_form_sigma_xx(force, cfg, x, y)))


_normal_force = jax.jit(itf.interface_normal_force)


def _snapshot_callback(cfg: Config, setup: si.Setup):
    """Host-side probes after every segment: instantaneous plate force, failed elements,
    axis stress in the circles, interface forces (force chains) and, once, the velocity
    field at breakage; stops after the drop like the other scenes."""
    probes: list[dict] = []
    centres = circle_centres(cfg)
    best = {"f": 0.0, "broke": None}

    def callback(state, rec):
        f, _ = plate_force(rec)
        wf = np.asarray(state.walls.force)
        f_now = 0.5 * (-wf[0, 1] + wf[-1, 1])
        b = state.bonds
        n_failed = int(np.sum((np.asarray(b.health) == 0) & np.asarray(b.i < b.j)[:, None]))
        entry = {"time": float(state.time), "force": float(f_now), "n_failed": n_failed}
        if cfg.detailed:
            sig = si.circle_stresses(
                state, setup.spec, centres, 0.5 * cfg.circle_diameter, cfg.thickness
            )
            entry["sigma_xx"] = sig[:, 0, 0]
            real = np.asarray(b.i < b.j)
            pos = np.asarray(state.particles.pos)
            entry["chain_i"] = pos[np.asarray(b.i)[real]]
            entry["chain_j"] = pos[np.asarray(b.j)[real]]
            entry["chain_force"] = np.asarray(_normal_force(b))[real]
        probes.append(entry)
        prev = best["f"]
        best["f"] = max(best["f"], float(f.max()))
        past = best["f"] > 0 and float(f.max()) <= prev
        split = False
        if past and f[-1] < cfg.break_fraction * best["f"] and n_failed > 0:
            # a local crush under a plate also drops the force: breakage is a split
            frags = _fragments(state)
            split = len(frags) >= 2 and len(frags[1]) >= 0.2 * len(frags[0])
        if best["broke"] is None and split:
            p = state.particles
            act = np.asarray(p.active)
            best["broke"] = {
                "time": float(state.time),
                "pos": np.asarray(p.pos)[act],
                "vel": np.asarray(p.vel)[act],
            }
        drop = split and f[-1] < cfg.drop_fraction * best["f"]
        return state, bool(drop)

    return callback, probes, best


def simulate_test(cfg: Config, *, progress: bool = False, setup: si.Setup | None = None):
    setup = setup or build(cfg)
    n_steps = int(math.ceil(cfg.max_strain / cfg.strain_rate / float(setup.params.dt)))
    callback, probes, best = _snapshot_callback(cfg, setup)
    res = si.drive(setup, n_steps, cfg, callback, progress=progress, desc=SCENE)
    res.probes = probes
    res.breakage = best["broke"]
    return res, setup


def _fragments(state, split_bridges: bool = True) -> list[np.ndarray]:
    """Particle index sets of the fragments, largest first: particles linked by bonds with
    a bonded element, and with ``split_bridges`` (default) not through a single chain of
    bonds only (:func:`jaxgran.analysis.fragments`: the two halves of a split disc that a
    thread of bonded grains still joins are two fragments). Particles taken out of the run
    are in none; the indices are particle slots."""
    b = state.bonds
    active = np.asarray(state.particles.active, bool)
    keep = np.asarray(b.intact) & np.asarray(b.i < b.j)
    i, j = np.asarray(b.i)[keep], np.asarray(b.j)[keep]
    # slots, not a count of the active particles: a particle taken out of the run
    # (interface.eject_escaping) keeps its slot, and the slots after it keep theirs
    live = active[i] & active[j]
    frags = an.fragments(i[live], j[live], active.size, split_bridges=split_bridges)
    return [f for f in frags if active[f].all()]


def axis_profile(probe: dict, cfg: Config) -> dict:
    """Measured and closed-form sigma_xx on the axis for one probe, and the errors in the
    middle third (circles with |y| < D / 6)."""
    c = circle_centres(cfg)
    y = c[:, 1]
    meas = np.asarray(probe["sigma_xx"])
    f = probe["force"]
    ref = np.array([closed_form_circle_mean(f, cfg, ck, 0.5 * cfg.circle_diameter) for ck in c])
    mid = np.abs(y) < cfg.diameter / 6
    err = np.abs(meas[mid] - ref[mid]) / np.abs(ref[mid])
    return {
        "y_m": y.tolist(),
        "sigma_xx_Pa": meas.tolist(),
        "closed_form_circle_Pa": ref.tolist(),
        "closed_form_Pa": float(closed_form_sigma_xx(f, cfg)),
        "force_N": f,
        "middle_third_mean_error": float(abs(meas[mid].mean() - ref[mid].mean()) / ref[mid].mean()),
        "middle_third_max_error": float(err.max()),
    }


def measure(res, setup: si.Setup, cfg: Config) -> dict:
    force, gap = plate_force(res.series)
    w = np.asarray(setup.state.walls.point)
    disp = float(w[-1, 1] - w[0, 1]) - gap
    k = int(np.argmax(force))
    t = np.asarray(res.series["time"])
    out = {
        "force_max_N": float(force[k]),
        "displacement_at_peak_m": float(disp[k]),
        "tensile_strength_Pa": an.brazilian_tensile_strength(
            float(force[k]), cfg.diameter, cfg.thickness
        ),
        "final_force_over_max": float(force[-1] / force[k]),
    }
    out.update(itf.element_summary(res.state.bonds))
    el = si.element_table(res.state)
    failed = el["mode"] > 0
    out["elements_failed_before_peak"] = int(np.sum(el["time"] < t[k]))
    first = np.min(el["time"][failed]) if failed.any() else np.inf
    out["first_failure_force_over_max"] = (
        float(np.interp(first, t, force) / force[k]) if np.isfinite(first) else math.nan
    )
    frags = _fragments(res.state)
    pos = np.asarray(res.state.particles.pos)
    if len(frags) >= 2 and len(frags[1]) >= 3:
        c0, c1 = pos[frags[0]].mean(axis=0), pos[frags[1]].mean(axis=0)
        d = c1 - c0
        out["split_angle_from_loading_axis_deg"] = float(
            math.degrees(math.atan2(abs(d[1]), abs(d[0])))
        )
        out["fragment_sizes"] = [int(len(f)) for f in frags[:4]]
    out["bond_connected_fragment_sizes"] = [
        int(len(f)) for f in _fragments(res.state, split_bridges=False)[:4]
    ]
    tens = el["mode"] == itf.MODE_TENSION
    if tens.sum() >= 3:
        ax = an.principal_axis_angle(el["pos"][tens])
        out["tension_cracks_axis_angle_deg"] = ax["angle_deg"]
    # shear failures under the plates: the reference positions are the final ones
    r = 0.5 * cfg.diameter
    ref_y = el["pos"][:, 1]
    near = np.abs(ref_y) > r - cfg.diameter / 6
    shear = el["mode"] == itf.MODE_SHEAR
    out["n_shear"] = int(shear.sum())
    if shear.any():
        out["shear_share_near_plates"] = float(near[shear].mean())
        out["element_share_near_plates"] = float(near.mean())
        x = el["pos"][shear]
        apex = np.where(x[:, 1] > 0, r, -r)
        ang = np.degrees(np.arctan2(np.abs(x[:, 0]), np.abs(apex - x[:, 1])))
        cap = np.abs(x[:, 1]) > 0  # every shear failure, seen from the nearer contact
        out["cone_half_angle_deg"] = float(np.median(ang[cap]))
    if cfg.detailed and res.probes:
        probes = res.probes
        before = [p for p in probes if p["n_failed"] == 0 and p["force"] > 0]
        if before:
            out["axis_before_first_failure"] = axis_profile(before[-1], cfg)
        fk = float(force[k])
        pre = [p for p in probes if p["time"] <= t[k]]
        if pre:
            best = min(pre, key=lambda p: abs(p["force"] - cfg.compare_fraction * fk))
            out["axis_at_compare_fraction"] = axis_profile(best, cfg)
    return out


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    res, setup = simulate_test(cfg, progress=progress)
    summary = measure(res, setup, cfg)
    summary.update(si.run_facts(res, setup, cfg))
    summary["n_interfaces"] = setup.spec.n_bonds
    summary.update(si.steady_rate(res, setup.spec.n_particles, cfg))
    summary = write_outputs(out_dir, SCENE, cfg, res.realisation(0), setup.params, summary, vtk=vtk)
    return si.finish(out_dir, summary, figures(res, setup, cfg, summary, Path(out_dir)))


def figures(res, setup: si.Setup, cfg: Config, summary: dict, out_dir: Path) -> list[Path]:
    from .. import plot_interface as pi

    force, gap = plate_force(res.series)
    w = np.asarray(setup.state.walls.point)
    disp = float(w[-1, 1] - w[0, 1]) - gap
    t = np.asarray(res.series["time"])
    k = int(np.argmax(force))
    figs = [
        pi.plot_curve(
            {cfg.bond: (1e3 * disp, force / 1e3)},
            "plate displacement (mm)",
            "plate force (kN)",
            out_dir / "force_displacement.png",
        )
    ]
    el = si.element_table(res.state)
    t50 = t[: k + 1][np.argmin(np.abs(force[: k + 1] - 0.5 * force[k]))]
    t90 = t[: k + 1][np.argmin(np.abs(force[: k + 1] - 0.9 * force[k]))]
    stages = [("50 % F_max", t50), ("90 % F_max", t90), ("peak", t[k]), ("final", np.inf)]
    figs.append(pi.plot_cracks(res.state, el, out_dir / "cracks_stages.png", stages))
    if not cfg.detailed:
        return figs
    for key, name in (
        ("axis_before_first_failure", "axis_stress_before_failure.png"),
        ("axis_at_compare_fraction", "axis_stress.png"),
    ):
        prof = summary.get(key)
        if prof:
            yy = np.linspace(-0.5, 0.5, 101) * cfg.diameter
            figs.append(
                pi.plot_axis_stress(
                    prof["y_m"],
                    prof["sigma_xx_Pa"],
                    yy,
                    np.full_like(yy, prof["closed_form_Pa"]),
                    out_dir / name,
                    f"F = {prof['force_N']:.0f} N; middle-third error "
                    f"{100 * prof['middle_third_mean_error']:.1f} %",
                )
            )
    if res.breakage is not None:
        figs.append(
            pi.plot_velocity(
                res.state,
                res.breakage["pos"],
                res.breakage["vel"],
                out_dir / "velocity_at_breakage.png",
                f"t = {1e3 * res.breakage['time']:.3f} ms",
            )
        )
    pre = [p for p in res.probes if p["time"] <= t[k]]
    if pre:
        p = min(pre, key=lambda p: abs(p["force"] - 0.9 * force[k]))
        figs.append(
            pi.plot_force_chains(
                res.state,
                p["chain_i"],
                p["chain_j"],
                p["chain_force"],
                out_dir / "force_chains.png",
                f"(F = {p['force']:.0f} N)",
            )
        )
    return figs
