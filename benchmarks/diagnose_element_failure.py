"""At what normal stress do the interface elements of an `interface-compression` run fail,
and does failing cost them strength?

A bonded element fails in shear at ``tau_c(sigma)`` and then carries friction only, up to
``mu_b |sigma|`` (:mod:`jaxgran.interface`). For the parallel bond's straight envelope
``c + |sigma| tan(phi)`` with ``tan(phi) > mu_b`` the drop at failure, ``c + |sigma|
(tan(phi) - mu_b)``, grows with the compression. The interface bond's parabola ``c sqrt(1 +
|sigma| / sigma_b)`` grows more slowly than the friction line and meets it at a compression
``sigma*`` (:func:`jaxgran.interface.friction_crossover`): above it an element loses
nothing by failing (it was weaker bonded than sliding), so the bond adds no strength there.

For every element that failed while the specimen was sheared,
:func:`jaxgran.scenes.interface.element_failures` takes its stresses at the last frame
recorded before the failure; this script prints, per run file of each folder (``run.h5``
and ``run_sigma3_<MPa>.h5``), :func:`jaxgran.scenes.interface.failure_stress_summary`: the
failures by mode, the median and 90th percentile of the compression of the shear failures,
the median strength lost on failing and, for the interface bond, the fraction above
``sigma*``. (Runs made since 2026-12-07 report the same per confinement in summary.json.)

    python benchmarks/diagnose_element_failure.py runs/vorcap_interface runs/vorcap_parallel

Prints one JSON object per run file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from jaxgran.io import read_run
from jaxgran.scenes import interface as si


def diagnose(path: Path) -> dict:
    run = read_run(path)
    bonds = run["final"]["bonds"]
    fails = si.element_failures(run["frames"], bonds)
    return {
        "file": str(path),
        "sigma3_Pa": float(np.asarray(run["final"]["walls"]["target_stress"])[1]),
        **si.failure_stress_summary(fails, bonds),
    }


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
