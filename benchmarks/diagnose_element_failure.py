"""At what normal stress do the interface elements of an `interface-compression` run fail,
and does failing cost them strength?

A bonded element fails in shear at ``tau_c(sigma)`` and then carries friction only, up to
``mu_b |sigma|`` (:mod:`jaxgran.interface`). For the parallel bond's straight envelope
``c + |sigma| tan(phi)`` with ``tan(phi) > mu_b`` the drop at failure, ``c + |sigma|
(tan(phi) - mu_b)``, grows with the compression. The interface bond's parabola ``c sqrt(1 +
|sigma| / sigma_b)`` grows more slowly than the friction line and meets it at a compression
``sigma*`` (:func:`jaxgran.interface.friction_crossover`): above it an element loses
nothing by failing (it was weaker bonded than sliding), so the bond adds no strength there.

For every element that failed while the specimen was sheared this script takes the last
frame recorded before its failure and the element's normal stress there (``k_n u_n`` from
the particles' positions and angles, as :func:`jaxgran.interface.interface_kinematics`
computes it), and reports per run file (``run.h5`` and ``run_sigma3_<MPa>.h5``): the number
of failures by mode, the median and 90th percentile of ``-sigma`` of the shear failures,
the fraction of them above ``sigma*`` (interface bond) and the strength each lost on
failing as a fraction of ``tau_c`` (median). Frames are decimated, so the stresses are those
of up to one frame interval before the failure.

    python benchmarks/diagnose_element_failure.py runs/vorcap_interface runs/vorcap_parallel

Prints one JSON object per run file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxgran import interface as itf
from jaxgran.io import read_run


def _rot(v: np.ndarray, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def element_normal_stress(frame_pos, frame_angle, b: dict) -> np.ndarray:
    """``k_n u_n`` (Pa, tension positive) of every element ``[B, E]`` at one frame."""
    i, j = b["i"], b["j"]
    a_i, a_j = frame_angle[i], frame_angle[j]
    theta = (a_j - a_i) - b["theta0"]
    normal = _rot(b["normal_i"], a_i + 0.5 * theta)
    x_i = frame_pos[i][:, None, :] + _rot(b["elem_point_i"], a_i[:, None])
    x_j = frame_pos[j][:, None, :] + _rot(b["elem_point_j"], a_j[:, None])
    u_n = np.einsum("bek,bk->be", x_j - x_i, normal)
    return b["normal_stiffness"][:, None] * u_n


def diagnose(path: Path) -> dict:
    run = read_run(path)
    b = {k: np.asarray(v) for k, v in run["final"]["bonds"].items() if k != "wall_bonds"}
    real = b["i"] < b["j"]
    b = {k: (v[real] if np.ndim(v) and len(v) == len(real) else v) for k, v in b.items()}
    fr = run["frames"]
    t_frames = np.asarray(fr["time"], float)
    t_fail, mode = b["elem_break_time"], b["mode"]
    parabolic = bool(np.all(b["envelope"] == itf.ENVELOPE_PARABOLIC))
    c, sb = float(b["cohesion"][0]), float(b["tensile_strength"][0])
    tphi, mu = float(b["tan_friction_angle"][0]), float(b["residual_friction"][0])
    # failures recorded after the first frame (the shearing stage's frames)
    failed = np.isfinite(t_fail) & (t_fail > t_frames[0])
    k_frame = np.searchsorted(t_frames, t_fail, side="right") - 1
    sig = np.full(t_fail.shape, np.nan)
    for k in np.unique(k_frame[failed]):
        sel = failed & (k_frame == k)
        s = element_normal_stress(fr["pos"][k], fr["angle"][k], b)
        sig[sel] = s[sel]
    shear = failed & (mode == itf.MODE_SHEAR)
    comp = np.maximum(-sig[shear], 0.0)
    if parabolic:
        tau_c = c * np.sqrt(1.0 + comp / sb)
    else:
        tau_c = c + comp * tphi
    lost = (tau_c - mu * comp) / tau_c
    out = {
        "file": str(path),
        "sigma3_Pa": float(np.asarray(run["final"]["walls"]["target_stress"])[1]),
        "envelope": "parabola" if parabolic else "line",
        "n_failed": int(failed.sum()),
        "n_failed_shear": int(shear.sum()),
        "n_failed_tension": int((failed & (mode == itf.MODE_TENSION)).sum()),
        "shear_failure_compression_median_Pa": float(np.median(comp)) if comp.size else None,
        "shear_failure_compression_p90_Pa": float(np.percentile(comp, 90)) if comp.size else None,
        "strength_lost_on_failing_median": float(np.median(lost)) if lost.size else None,
    }
    if parabolic:
        s_star = itf.friction_crossover(c, sb, mu)
        out["crossover_compression_Pa"] = s_star
        out["shear_failures_above_crossover"] = float((comp > s_star).mean()) if comp.size else None
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="interface-compression output folders")
    args = ap.parse_args(argv)
    for folder in args.runs:
        files = sorted(folder.glob("run_sigma3_*.h5")) + [folder / "run.h5"]
        for f in files:
            print(json.dumps(diagnose(f)))


if __name__ == "__main__":
    main()
