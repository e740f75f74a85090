"""Biaxial compression at constant confinement, and the Mohr strength envelope of the
interface bond vs the parallel bond (paper 003 §3, Fig. 3-4, in 2D).

A rectangle ``width x height`` of bonded discs or Voronoi cells (the gypsum-like material of
:mod:`jaxgran.scenes.interface`, plane stress) sits in a box of four walls: bottom and top
platens with ``wall_friction`` (nan: ``contact_friction``, as in the unconfined test) and
frictionless side walls (``side_friction = 0``: they stand for the membrane; side-wall friction
would carry part of the axial load, up to ``2 mu sigma3 height / width``). For every confinement
``sigma3`` in ``confinements`` (default 2, 5, 10, 20 and 40 MPa, paper 003's values): all four
walls servo to sigma3 (isotropic stage; a warning if it has not converged within
``iso_max_time``), then the axial walls close at ``strain_rate`` (strain control) while the
lateral servo walls hold sigma3. In the shearing the lateral servo is proportional-integral
(integral time ``servo_integral`` loop time constants): a proportional servo alone trails a
specimen that dilates while it is sheared, by ``dilation rate / gain`` (on Voronoi cells it held
4.7 MPa for a 2 MPa target at the peak). Its time constant (``shear_servo_response`` wave
transits) and speed cap (``servo_max_speed`` x strain_rate x height) are the shearing's own: a
cap below the specimen's rate of dilation holds the walls back and the lateral stress runs
above sigma3 (:func:`lateral_control` measures it). The shearing ends at ``max_strain``, or once the
deviator q has stayed below ``drop_fraction`` of its peak for ``post_peak_strain`` of axial
strain after elements failed and q passed ``drop_min_q x sigma3`` (a stick-slip dip that
recovers does not end it, nor does a collapse of the fabric at a small q). Stresses are
compression positive, each the mean of its two walls' ``-F . n / (l T)`` with l the current
specimen size. Reported per confinement: the peak axial stress s1 (at the largest q of the run),
the lateral stress there, whether the run ended on a drop after the peak (``peaked``; otherwise
it ran to ``max_strain``), the post-peak ratio (mean
q over the last 20 % of the strain over the peak: near 1 is a plateau or hardening, low is
brittle) and ``post_peak_behaviour`` (:func:`post_peak_behaviour`): brittle (ended on the
drop), or, judged on the slope of q over the last ``plateau_strain`` of the run, hardening,
plateau or softening; all but hardening count as real peaks in the peaks-only envelope.
``max_strain`` is 10 % since 2026-12-06 (3 % before: too short for the confined disc
specimens to show what follows their peak; ``benchmarks/INTERFACE_ENVELOPE_RESULTS.md``).
The stress-strain record of every confinement, with the lateral and volumetric strain of
the box (figure ``volumetric_strain.png``), is in ``curves.h5`` (:func:`read_curves` reads
it back). Each confinement also reports how well the lateral servo held sigma3
(:func:`lateral_control`). ``run.h5`` is the whole record (series, frames, final state with
its bonds) of the last confinement, ``run_sigma3_<MPa>.h5`` that of each other one (read
either with :func:`jaxgran.io.read_run`), and ``cracks_sigma3_<MPa>.png`` draws the failed
elements of each at the end of its shearing.

With ``with_tension`` and ``with_uniaxial`` (default) the direct tension and unconfined tests
of the same specimen (with the same platen friction) add their Mohr circles, and the peak
circles are fitted with the linear Mohr-Coulomb line and the quadratic parabola
(:func:`jaxgran.scenes.interface.mohr_envelope_fits`): R^2 of each, for ``--set bond=...``,
on all circles (``envelope_*``) and on the real peaks only (``envelope_peaks_only_*``).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .. import interface as itf
from ..integrate import servo_gain_for
from ..state import WALL_SERVO, WALL_VELOCITY, box_walls, replace
from . import bonded as bd
from . import interface as si
from .base import environment, write_outputs
from .limits import Range

SCENE = "interface-compression"


@dataclasses.dataclass(frozen=True)
class Config(si.Common):
    LIMITS: ClassVar[dict] = si.Common.LIMITS | {
        "servo_response": Range(0.0, note="0: 3 wave transits for discs, 10 for Voronoi cells"),
        "shear_servo_response": Range(0.0, low_open=True, note="wave transits"),
    }

    width: float = 0.025  # m
    height: float = 0.05  # m
    confinements: tuple = (2.0e6, 5.0e6, 10.0e6, 20.0e6, 40.0e6)  # Pa, sigma3
    strain_rate: float = 2.0  # 1/s
    max_strain: float = 0.10
    drop_fraction: float = 0.7  # stop below this x the peak deviator (after the peak)
    iso_tolerance: float = 0.02  # isotropic stage ends when every wall is this close
    # (s) the stage ends as soon as every wall is within iso_tolerance. A packing that
    # collapses under the isotropic load (76 discs at 40 MPa: 53-111 of 129 bonds broken)
    # needs its walls to close in at their cap for longer: 6.8-7.3 ms on the four seeds that
    # did not make it in the earlier 6 ms
    iso_max_time: float = 2.0e-2
    # servo time constant of the isotropic stage in wave transits across the block; 0: 3 for
    # discs, 10 for Voronoi cells (their face contacts are stiffer: at 3 the platens chatter
    # at full speed and the stage stalls 16 % under 5 MPa)
    servo_response: float = 0.0
    # the lateral servo's time constant while the specimen is sheared, in wave transits: its
    # contacts are then all closed and a slow loop trails the bursts of dilation (Voronoi
    # cells at 2 MPa: 1.40 x sigma3 at 10 transits, 1.02 at 3)
    shear_servo_response: float = 3.0
    # integral time of the lateral servo in units of its shearing time constant (4: critically
    # damped); inf = proportional servo alone, which trails the dilation of the specimen
    servo_integral: float = 4.0
    # speed cap of the lateral servo walls while the specimen is sheared, in units of
    # strain_rate x height (each platen moves at 0.5 of that): a cap below the specimen's
    # rate of dilation lets the lateral stress run above sigma3 (2: the earlier cap, at which
    # the Voronoi specimen at 2 MPa held 1.3-1.6 x sigma3 with its walls at the cap for over
    # half the run; at 10 they still met it in 8-10 % of the records, in the collapse after
    # the peak; at 50 never). The isotropic stage has its own cap, iso_max_speed.
    servo_max_speed: float = 50.0
    # speed cap of the four servo walls in the isotropic stage, in the same units (at 10 a
    # collapsing packing, parallel-bond seed 5 at 40 MPa, settles in 1.5 ms instead of 7.2,
    # its lateral stress overshooting to 1.04 x sigma3 on the way)
    iso_max_speed: float = 2.0
    side_friction: float = 0.0  # side walls (the membrane: frictionless)
    post_peak_strain: float = 0.005  # stop once q stays below drop_fraction x peak this long
    # the drop stops a run only once q has passed drop_min_q x sigma3: below that no
    # Mohr-Coulomb material with phi >= 19.5 deg (sin phi >= 1/3) has failed, so a drop
    # there is a collapse of the fabric that the specimen recovers from, not its strength
    # (seed 3 at 40 MPa: q 2 MPa, then -10 MPa, rising again; 0 arms it from the start)
    drop_min_q: float = 1.0
    # the last plateau_strain of a run that reaches max_strain: q changing across it by under
    # plateau_band x its largest value is a plateau, more is hardening or softening
    plateau_strain: float = 0.02
    plateau_band: float = 0.1  # fraction of the largest q: plateau, hardening or softening
    with_tension: bool = True  # also direct tension of the same specimen (a circle)
    with_uniaxial: bool = True  # also unconfined compression (a circle)


QUICK = {
    "width": 0.015,
    "height": 0.03,
    "confinements": (5.0e6, 20.0e6),
    "max_strain": 0.03,
    "record_every": 25,
    "records_per_segment": 8,
    "with_tension": False,
    "with_uniaxial": False,
}


def _servo_tau(mat: si.Material, cfg: Config) -> float:
    """Time constant (s) of the servo loop in the isotropic stage: ``servo_response`` wave
    transits across the block."""
    transits = cfg.servo_response or (3.0 if cfg.particles == "discs" else 10.0)
    return _transit_time(mat, cfg) * transits


def _shear_servo_tau(mat: si.Material, cfg: Config) -> float:
    """Time constant (s) of the lateral servo loop while the specimen is sheared:
    ``shear_servo_response`` wave transits."""
    return _transit_time(mat, cfg) * cfg.shear_servo_response


def _transit_time(mat: si.Material, cfg: Config) -> float:
    """Time (s) a compression wave takes across the block's larger side (its modulus taken
    as half the element modulus, its density the solid's x solid_fraction)."""
    e = 0.5 * mat.modulus
    rho = mat.density * cfg.solid_fraction
    return max(cfg.width, cfg.height) / math.sqrt(e / rho)


def _walls(spec: si.Specimen, mat: si.Material, cfg: Config, sigma3: float) -> list[dict]:
    """Four servo walls for the isotropic stage (proportional: the specimen is at rest, so the
    proportional servo has no offset there, and an integral term would wind up while the
    walls close in and overshoot)."""
    x0, x1, y0, y1 = si.extent(spec)
    walls = box_walls((x0, y0), (x1, y1))
    e = 0.5 * mat.modulus  # order of the block's modulus (Pa)
    tau = _servo_tau(mat, cfg)
    for k, d in enumerate(walls):
        span = (y1 - y0) if k in (bd.BOTTOM, bd.TOP) else (x1 - x0)
        gain = servo_gain_for(
            d["length"], mat.thickness, e * mat.thickness * d["length"] / span, tau
        )
        d.update(
            mode=WALL_SERVO,
            target_stress=float(sigma3),
            servo_gain=gain,
            max_speed=cfg.iso_max_speed * cfg.strain_rate * cfg.height,
        )
    return walls


def build(cfg: Config, sigma3: float, spec: si.Specimen | None = None) -> si.Setup:
    mat = si.material_from(cfg)
    region = ("rect", (0.0, 0.0), (cfg.width, cfg.height))
    spec = spec or si.make_specimen(cfg, region, mat)
    setup = si.prepare(spec, mat, _walls(spec, mat, cfg, sigma3), cfg, margin=0.5 * cfg.height)
    setup.control = bd.make_control(setup.state, box=True)
    platen = float(setup.params.wall_friction)
    mu = [platen, cfg.side_friction, cfg.side_friction, platen]  # bottom, left, right, top
    setup.params = replace(setup.params, wall_friction=jnp.asarray(mu, setup.params.dt.dtype))
    return setup


def box_size(series: dict) -> tuple[np.ndarray, np.ndarray]:
    """Width and height (m) of the box of the four walls per record."""
    pts = np.asarray(series["wall_point"], float)
    return pts[:, bd.RIGHT, 0] - pts[:, bd.LEFT, 0], pts[:, bd.TOP, 1] - pts[:, bd.BOTTOM, 1]


def box_stress(series: dict, thickness: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axial and lateral stress (Pa, compression positive) and height (m) per record."""
    f = np.asarray(series["wall_force"], float)
    nrm = np.array([[0.0, 1.0], [1.0, 0.0], [-1.0, 0.0], [0.0, -1.0]])
    fn = -np.einsum("rwk,wk->rw", f, nrm)
    width, height = box_size(series)
    s_ax = 0.5 * (fn[:, bd.BOTTOM] + fn[:, bd.TOP]) / (width * thickness)
    s_lat = 0.5 * (fn[:, bd.LEFT] + fn[:, bd.RIGHT]) / (height * thickness)
    return s_ax, s_lat, height


def new_drop_track() -> dict:
    """State of :func:`sustained_drop` for one run."""
    return {"best": -np.inf, "below_since": None, "peaked": False}


def sustained_drop(
    track: dict, q, strain, failed: bool, fraction: float, window: float, floor: float = 0.0
) -> bool:
    """Feed the records of one segment (deviator ``q`` in Pa and axial ``strain``, in order);
    True once q has stayed below ``fraction`` of its running peak over at least ``window`` of
    strain (a dip that recovers within ``window`` resets the count). Drops count only when
    ``failed`` (some element broke) and the peak is above ``floor`` (Pa, at least 0).
    Updates ``track`` (also its ``peaked`` flag)."""
    floor = max(float(floor), 0.0)
    for qk, ek in zip(np.asarray(q, float), np.asarray(strain, float), strict=True):
        track["best"] = max(track["best"], float(qk))
        low = failed and track["best"] > floor and qk < fraction * track["best"]
        if not low:
            track["below_since"] = None
        elif track["below_since"] is None:
            track["below_since"] = float(ek)
    since = track["below_since"]
    track["peaked"] = since is not None and float(strain[-1]) - since >= window
    return track["peaked"]


def post_peak_behaviour(strain, q, ended_on_drop: bool, window: float, band: float) -> str:
    """What the deviator does after its largest value in one shearing record (axial
    ``strain`` and ``q`` in Pa, in order): ``"brittle"`` where the run ended on a sustained
    drop (:func:`sustained_drop`); otherwise the straight line fitted to q over the last
    ``window`` of axial strain changes, across that window, by ``delta`` (a fraction of the
    largest q): ``"hardening"`` for ``delta >= band`` (q still rising at the end: the largest
    q is a lower bound of the strength), ``"softening"`` for ``delta <= -band`` and
    ``"plateau"`` in between (the ductile residual state; its level is the post-peak ratio).
    A record shorter than ``window`` is judged on all of it."""
    strain, q = np.asarray(strain, float), np.asarray(q, float)
    if ended_on_drop:
        return "brittle"
    peak = float(np.max(q))
    tail = strain >= strain[-1] - window
    if tail.sum() < 2 or not peak > 0:
        return "hardening"
    slope = np.polyfit(strain[tail], q[tail], 1)[0]
    delta = slope * min(window, float(strain[-1] - strain[0])) / peak
    if delta >= band:
        return "hardening"
    return "softening" if delta <= -band else "plateau"


def run_confined(cfg: Config, sigma3: float, spec=None, *, progress: bool = False) -> dict:
    """Isotropic stage to sigma3, then strain-controlled axial loading; returns the series
    (both stages), the final state, the setup and the record index where shearing began."""
    setup = build(cfg, sigma3, spec)
    T = setup.material.thickness

    def iso_done(state, rec):
        s_ax, s_lat, _ = box_stress(rec, T)
        ok = abs(s_ax[-1] - sigma3) < cfg.iso_tolerance * sigma3
        return state, bool(ok and abs(s_lat[-1] - sigma3) < cfg.iso_tolerance * sigma3)

    dt = float(setup.params.dt)
    iso = si.drive(setup, int(math.ceil(cfg.iso_max_time / dt)), cfg, iso_done, progress=progress)
    state = iso.state
    s_ax, s_lat, _ = box_stress(iso.series, T)
    off = max(abs(s_ax[-1] - sigma3), abs(s_lat[-1] - sigma3)) / sigma3
    if off > cfg.iso_tolerance:
        warnings.warn(
            f"isotropic stage to {sigma3 / 1e6:g} MPa ended after iso_max_time = "
            f"{cfg.iso_max_time:g} s at s_axial = {s_ax[-1] / 1e6:.2f} and s_lateral = "
            f"{s_lat[-1] / 1e6:.2f} MPa ({100 * off:.1f} % off); raise iso_max_time",
            stacklevel=2,
        )
    v = 0.5 * cfg.strain_rate * cfg.height
    w = state.walls
    mode = jnp.asarray([WALL_VELOCITY, WALL_SERVO, WALL_SERVO, WALL_VELOCITY], jnp.int32)
    vel = jnp.asarray([[0.0, v], [0.0, 0.0], [0.0, 0.0], [0.0, -v]], w.vel.dtype)
    # the lateral walls hold sigma3 while the specimen dilates: proportional-integral, with
    # the shearing stage's own time constant (the gain scales as its inverse)
    tau = _shear_servo_tau(setup.material, cfg)
    ti = cfg.servo_integral * tau
    servo_time = jnp.asarray([math.inf, ti, ti, math.inf], w.servo_time.dtype)
    faster = np.ones(4)
    faster[[bd.LEFT, bd.RIGHT]] = _servo_tau(setup.material, cfg) / tau
    setup.state = replace(
        state,
        walls=replace(
            w,
            mode=mode,
            vel=vel,
            servo_time=servo_time,
            servo_integral=jnp.zeros_like(w.servo_integral),
            servo_gain=w.servo_gain * jnp.asarray(faster, w.servo_gain.dtype),
            max_speed=jnp.full_like(
                w.max_speed, cfg.servo_max_speed * cfg.strain_rate * cfg.height
            ),
        ),
    )
    h0 = float(w.point[bd.TOP, 1] - w.point[bd.BOTTOM, 1])
    w0 = float(w.point[bd.RIGHT, 0] - w.point[bd.LEFT, 0])

    damaged0 = si.n_damaged(state)
    track = new_drop_track()

    def shear_stop(state, rec):
        # a drop counts only once elements have failed during shearing (not in the isotropic
        # stage); see sustained_drop
        s_ax, s_lat, h = box_stress(rec, T)
        failed = si.n_damaged(state) > damaged0
        past = sustained_drop(
            track,
            s_ax - s_lat,
            1.0 - h / h0,
            failed,
            cfg.drop_fraction,
            cfg.post_peak_strain,
            cfg.drop_min_q * sigma3,
        )
        return state, bool(past or 1.0 - h[-1] / h0 >= cfg.max_strain)

    n = int(math.ceil(cfg.max_strain / cfg.strain_rate / dt)) + 1
    shear = si.drive(setup, n, cfg, shear_stop, progress=progress)
    series = si.concat_series([iso.series, shear.series])
    return {
        "series": series,
        "state": shear.state,
        "setup": setup,
        "start": len(iso.series["time"]),
        "height0": h0,
        "width0": w0,
        "steps": iso.steps + shear.steps,
        "wall_time_s": iso.wall_time_s + shear.wall_time_s,
        "result": shear,
        "peaked": track["peaked"],
    }


def shear_record(out: dict, thickness: float) -> dict[str, np.ndarray]:
    """The shearing records of one :func:`run_confined` result: ``time`` (s),
    ``sigma_axial`` and ``sigma_lateral`` (Pa, compression positive), ``axial_strain`` and
    ``lateral_strain`` (-, shortening positive, from the box at the start of shearing)."""
    k0 = out["start"]
    s_ax, s_lat, _ = box_stress(out["series"], thickness)
    width, height = box_size(out["series"])
    return {
        "time": np.asarray(out["series"]["time"], float)[k0:],
        "sigma_axial": s_ax[k0:],
        "sigma_lateral": s_lat[k0:],
        "axial_strain": 1.0 - height[k0:] / out["height0"],
        "lateral_strain": 1.0 - width[k0:] / out["width0"],
    }


def volumetric_strain(axial, lateral) -> np.ndarray:
    """Volumetric (areal) strain of the box, ``1 - area / area0`` (compaction positive),
    from its axial and lateral strains (each ``1 - length / length0``)."""
    return 1.0 - (1.0 - np.asarray(axial, float)) * (1.0 - np.asarray(lateral, float))


def measure_confined(
    out: dict, thickness: float, plateau_strain: float = 0.02, plateau_band: float = 0.1
) -> dict:
    rec = shear_record(out, thickness)
    s_ax, s_lat, strain = rec["sigma_axial"], rec["sigma_lateral"], rec["axial_strain"]
    q = s_ax - s_lat
    k = int(np.argmax(q))
    tail = strain >= strain[-1] - 0.2 * (strain[-1] - strain[0])
    res = {
        "sigma1_peak_Pa": float(s_ax[k]),
        "sigma3_at_peak_Pa": float(s_lat[k]),
        "strain_at_peak": float(strain[k]),
        "final_strain": float(strain[-1]),
        "post_peak_ratio": float(q[tail].mean() / q[k]) if q[k] > 0 else math.nan,
        # True: the run ended on a sustained drop after the peak (a brittle peak); False: on
        # max_strain (sigma1_peak is a lower bound where post_peak_behaviour is hardening)
        "peaked": bool(out.get("peaked", False)),
        # axial strain run after the largest q, and what the record did there
        "post_peak_strain_span": float(strain[-1] - strain[k]),
        "post_peak_behaviour": post_peak_behaviour(
            strain, q, bool(out.get("peaked", False)), plateau_strain, plateau_band
        ),
    }
    res.update(lateral_control(out, s_lat, k))
    res.update(itf.element_summary(out["state"].bonds))
    res.update(si.failure_stress_summary(failures(out), out["state"].bonds))
    return res


def failures(out: dict) -> dict[str, np.ndarray]:
    """:func:`jaxgran.scenes.interface.element_failures` of the shearing stage of one
    :func:`run_confined` result (its frames and final bonds); found once and kept in
    ``out["failures"]`` (the summary and the figure both use them)."""
    if "failures" not in out:
        from .. import io

        state = out["state"]
        frames = io.stack_frames(out["result"].realisation(0).frames, state.particles)
        out["failures"] = si.element_failures(frames, state.bonds)
    return out["failures"]


def lateral_control(out: dict, s_lat: np.ndarray, peak: int | None = None) -> dict:
    """How well the lateral servo walls held sigma3 while the specimen was sheared: the
    lateral stress over its target (median and 95th percentile of the shearing records) and
    the fraction of records in which a lateral wall moved at its speed cap (``max_speed``):
    there the specimen dilated faster than the wall may follow, and the lateral stress runs
    above sigma3 (raise ``servo_max_speed``). With ``peak`` (the index of the largest q in
    the shearing records) the fraction is also given for the records up to the peak, the
    ones that set the strength."""
    walls = out["state"].walls
    target = float(walls.target_stress[bd.LEFT])
    k0 = out["start"]
    t = np.asarray(out["series"]["time"], float)[k0:]
    x = np.asarray(out["series"]["wall_point"], float)[k0:, (bd.LEFT, bd.RIGHT), 0]
    cap = np.asarray(walls.max_speed, float)[[bd.LEFT, bd.RIGHT]]
    # each record's mean wall speed over the interval before it: a wall at its cap
    # throughout moves cap x the interval
    speed = np.abs(np.diff(x, axis=0)) / np.diff(t)[:, None] if len(t) > 1 else np.zeros((0, 2))
    at_cap = np.any(speed >= 0.99 * cap, axis=1)
    ratio = np.asarray(s_lat, float) / target
    res = {
        "sigma3_over_target_median": float(np.median(ratio)),
        "sigma3_over_target_p95": float(np.percentile(ratio, 95)),
        "servo_at_cap_fraction": float(at_cap.mean()) if len(at_cap) else 0.0,
    }
    if peak is not None:
        before = at_cap[: int(peak)]
        res["servo_at_cap_fraction_to_peak"] = float(before.mean()) if len(before) else 0.0
    return res


def envelope(cfg: Config, *, progress: bool = False) -> dict:
    """All confinements (and tension / unconfined if asked) on one specimen; peak circles and
    both envelope fits."""
    names = [group_name(s3) for s3 in cfg.confinements]
    if len(set(names)) != len(names):
        raise ValueError(
            f"confinements {list(cfg.confinements)} name the same group twice ({names}); "
            "give each confinement once (a repeat is another seed: --set seed=...)"
        )
    mat = si.material_from(cfg)
    region = ("rect", (0.0, 0.0), (cfg.width, cfg.height))
    spec = si.make_specimen(cfg, region, mat)
    runs, per = [], []
    for s3 in cfg.confinements:
        out = run_confined(cfg, float(s3), spec, progress=progress)
        runs.append(out)
        m = measure_confined(out, mat.thickness, cfg.plateau_strain, cfg.plateau_band)
        if m["servo_at_cap_fraction"] > 0.05 or m["servo_at_cap_fraction_to_peak"] > 0.01:
            warnings.warn(
                f"at sigma3 = {s3 / 1e6:g} MPa a lateral wall moved at its speed cap in "
                f"{100 * m['servo_at_cap_fraction']:.0f} % of the shearing records "
                f"({100 * m['servo_at_cap_fraction_to_peak']:.0f} % up to the peak): the "
                "specimen dilated faster than the servo may follow, and the lateral stress "
                f"was {m['sigma3_over_target_median']:.2f} x sigma3 (median; 95th percentile "
                f"{m['sigma3_over_target_p95']:.2f}); raise servo_max_speed",
                stacklevel=2,
            )
        per.append({"sigma3_target_Pa": float(s3), **m})
    s1 = [p["sigma1_peak_Pa"] for p in per]
    s3 = [p["sigma3_at_peak_Pa"] for p in per]
    extra = {}
    common = dataclasses.asdict(cfg)
    if cfg.with_uniaxial:
        from . import interface_uniaxial as ux

        ucfg = ux.Config(**{k: v for k, v in common.items() if k in _names(ux.Config)})
        # the unconfined test's own stop rule (not the biaxial runs' drop and strain limit)
        base = ux.Config()
        ucfg = dataclasses.replace(
            ucfg, drop_fraction=base.drop_fraction, max_strain=base.max_strain
        )
        ures, usetup = ux.simulate_test(ucfg, progress=progress)
        extra["ucs_Pa"] = ux.measure(ures, usetup, ucfg)["ucs_Pa"]
        extra["unconfined_n_ejected"] = si.ejection_facts(ures, usetup)["n_ejected"]
        s1.append(extra["ucs_Pa"])
        s3.append(0.0)
    if cfg.with_tension:
        from . import interface_tension as tn

        tcfg = tn.Config(**{k: v for k, v in common.items() if k in _names(tn.Config)})
        tcfg = dataclasses.replace(tcfg, max_strain=0.004, drop_fraction=0.3)
        tres, tsetup = tn.simulate_test(tcfg, progress=progress)
        extra["tensile_strength_Pa"] = tn.measure(tres, tsetup, tcfg)["tensile_strength_Pa"]
        extra["tension_n_ejected"] = si.ejection_facts(tres, tsetup)["n_ejected"]
        s1.append(0.0)
        s3.append(-extra["tensile_strength_Pa"])
    if "ucs_Pa" in extra and "tensile_strength_Pa" in extra:
        extra["ucs_over_tensile_strength"] = extra["ucs_Pa"] / extra["tensile_strength_Pa"]
    fits = si.mohr_envelope_fits(s1, s3)
    # the same fits on the circles of real peaks only (the confined runs that did not end
    # still hardening, plus tension and unconfined)
    keep = [p["post_peak_behaviour"] != "hardening" for p in per] + [True] * (len(s1) - len(per))
    peaks = si.mohr_envelope_fits(
        [a for a, k in zip(s1, keep, strict=True) if k],
        [a for a, k in zip(s3, keep, strict=True) if k],
    )
    return {
        "runs": runs,
        "per_confinement": per,
        "sigma1": s1,
        "sigma3": s3,
        "fits": fits,
        "fits_peaks": peaks,
        "peaked": keep,  # per circle: confinements, then unconfined and tension (True)
        **extra,
    }


def group_name(sigma3: float) -> str:
    """Name of a confinement's group in curves.h5 and of its files: ``sigma3_<MPa>MPa``."""
    return f"sigma3_{sigma3 / 1e6:g}MPa"


def write_curves(path: Path, records: list, per: list[dict]) -> Path:
    """The shearing record of every confinement in one HDF5 file, a group per confinement
    (``sigma3_<MPa>``, in the order run) with ``time`` (s), ``axial_strain`` (-),
    ``sigma_axial``, ``sigma_lateral`` and ``deviator`` (Pa, compression positive), where a
    record carries it (a sixth entry) ``lateral_strain`` and ``volumetric_strain`` (-,
    compaction positive: ``1 - width / width0`` between the lateral walls, and ``1 - area /
    area0`` of the box; negative is dilation), and the
    confinement's measures (``per_confinement`` of summary.json) as attributes: numbers and
    strings as they are, None, lists and dicts as JSON (listed in the group's ``_json``
    attribute; :func:`read_curves` decodes them). Long records are stored compressed, as in
    run.h5."""
    import h5py

    from .. import io

    with h5py.File(path, "w", track_order=True) as f:
        for rec, m in zip(records, per, strict=True):
            s3, t, strain, s_ax, s_lat = rec[:5]
            g = f.create_group(group_name(s3))
            cols = [
                ("time", t, "s"),
                ("axial_strain", strain, "1"),
                ("sigma_axial", s_ax, "Pa"),
                ("sigma_lateral", s_lat, "Pa"),
                ("deviator", np.asarray(s_ax, float) - np.asarray(s_lat, float), "Pa"),
            ]
            if len(rec) > 5:
                lat = np.asarray(rec[5], float)
                vol = volumetric_strain(strain, lat)
                cols += [("lateral_strain", lat, "1"), ("volumetric_strain", vol, "1")]
            for name, val, unit in cols:
                io._put(g, name, np.asarray(val, float), units=unit)
            io._set_attrs(g, m)
    return path


def read_curves(path: str | Path) -> dict[str, dict]:
    """A ``curves.h5`` of :func:`write_curves` back: per group (``sigma3_<MPa>``, in the order
    run) the arrays ``time`` (s), ``axial_strain`` (-), ``sigma_axial``, ``sigma_lateral``,
    ``deviator`` (Pa), ``lateral_strain`` and ``volumetric_strain`` (-) where written, and
    ``measures`` (the confinement's ``per_confinement`` entry of
    summary.json, JSON-stored values decoded)."""
    import h5py

    from .. import io

    out: dict[str, dict] = {}
    with h5py.File(path, "r") as f:
        for name, g in f.items():
            rec = io._read_group(g, {}, name)
            rec["measures"] = io._get_attrs(g)
            out[name] = rec
    return out


def _names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    env = envelope(cfg, progress=progress)
    runs = env["runs"]
    summary = {
        "bond": cfg.bond,
        "particles": cfg.particles,
        "n_particles": runs[0]["setup"].spec.n_particles,
        "per_confinement": env["per_confinement"],
        "peak_sigma1_Pa": env["sigma1"],
        "peak_sigma3_Pa": env["sigma3"],
        **{f"envelope_{k}": v for k, v in env["fits"].items()},
        **{f"envelope_peaks_only_{k}": v for k, v in env["fits_peaks"].items()},
        **{
            k: v
            for k, v in env.items()
            if k.endswith(("_Pa", "_n_ejected")) or k.startswith("ucs_over")
        },
        "steps": int(sum(r["steps"] for r in runs)),
        "wall_time_s": float(sum(r["wall_time_s"] for r in runs)),
        "dt_s": float(runs[0]["setup"].params.dt),
    }
    last = runs[-1]
    r0 = last["result"].realisation(0)
    summary = write_outputs(out_dir, SCENE, cfg, r0, last["setup"].params, summary, vtk=vtk)
    from .. import io
    from .. import plot_interface as pi

    curves, dilation = {}, {}
    T = cfg.thickness
    records = []
    for s3, out in zip(cfg.confinements, runs, strict=True):
        r = shear_record(out, T)
        strain, s_ax, s_lat = r["axial_strain"], r["sigma_axial"], r["sigma_lateral"]
        label = f"sigma3 = {s3 / 1e6:g} MPa"
        curves[label] = (100 * strain, (s_ax - s_lat) / 1e6)
        dilation[label] = (100 * strain, 100 * volumetric_strain(strain, r["lateral_strain"]))
        records.append((float(s3), r["time"], strain, s_ax, s_lat, r["lateral_strain"]))
    write_curves(Path(out_dir) / "curves.h5", records, env["per_confinement"])
    peaked = env["peaked"]
    some = "linear_r2" in env["fits_peaks"] and not all(peaked)
    shown, which = (env["fits_peaks"], "the black (peak)") if some else (env["fits"], "all")
    figs = [
        pi.plot_curve(
            curves, "axial strain (%)", "deviator s1 - s3 (MPa)", Path(out_dir) / "deviator.png"
        ),
        pi.plot_curve(
            dilation,
            "axial strain (%)",
            "volumetric strain (%, compaction positive)",
            Path(out_dir) / "volumetric_strain.png",
        ),
        pi.plot_mohr(
            env["sigma1"],
            env["sigma3"],
            shown,
            Path(out_dir) / "mohr_envelope.png",
            f"bond = {cfg.bond}, {cfg.particles}; envelopes fitted to {which} circles",
            peaked=peaked,
        ),
    ]
    figs.append(
        pi.plot_element_failures(
            {
                f"sigma3 = {s3 / 1e6:g} MPa": failures(out)
                for s3, out in zip(cfg.confinements, runs, strict=True)
            },
            si.bond_material(runs[0]["state"].bonds),
            Path(out_dir) / "element_failures.png",
            f"bond = {cfg.bond}, {cfg.particles}: failed elements at the last frame before "
            "failure (dots shear, crosses tension)",
        )
    )
    for s3, out in zip(cfg.confinements, runs, strict=True):
        name = group_name(s3)
        figs.append(
            pi.plot_cracks(
                out["state"],
                si.element_table(out["state"]),
                Path(out_dir) / f"cracks_{name}.png",
                stages=[(f"sigma3 = {s3 / 1e6:g} MPa, end of shearing", np.inf)],
            )
        )
        if out is not last:  # run.h5 holds the last one
            io.write_run(
                Path(out_dir) / f"run_{name}.h5",
                out["result"].realisation(0),
                out["setup"].params,
                metadata={
                    "scene": SCENE,
                    "config": dataclasses.asdict(cfg),
                    "sigma3_Pa": s3,
                    **environment(),
                },
            )
    return si.finish(out_dir, summary, figs)
