"""Pool the Mohr circles of several `interface-compression` runs (seeds of one bond model)
and fit the linear Mohr-Coulomb line and the parabola to all of them, and to the real peaks
only (:func:`jaxgran.scenes.interface.mohr_envelope_fits`):

    for s in 0 1 2; do jaxgran run interface-compression --set bond=interface --set seed=$s \\
        --out runs/itf_s$s; done
    python benchmarks/pool_interface_envelopes.py runs/itf_s0 runs/itf_s1 runs/itf_s2

Prints one JSON object: circles, R^2 of both fits on all circles and on the peaks only, and
per run the UCS, the tensile strength and which confinements peaked (``post_peak_behaviour``
other than hardening). ``--circle S1,S3`` (Pa, compression positive; repeatable) adds a
circle measured elsewhere, e.g. the tension (``0,-T``) and unconfined (``UCS,0``) tests of
an earlier run of the same specimen when the runs pooled skipped them
(``--set with_tension=false --set with_uniaxial=false``); such circles count as peaks
(write ``--circle=S1,S3`` where S1 is negative).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _real_peak(r: dict) -> bool:
    """A confinement's largest q is a strength unless the run was still hardening."""
    if "post_peak_behaviour" in r:
        return r["post_peak_behaviour"] != "hardening"
    return bool(r["peaked"])


def _circle(text: str) -> tuple[float, float]:
    """``"S1,S3"`` (Pa) -> (S1, S3); one argument, so that a negative S3 is not an option."""
    parts = text.split(",")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected SIGMA1,SIGMA3 in Pa, got {text!r}")
    return float(parts[0]), float(parts[1])


def pool(folders: list[str], circles: list[tuple[float, float]] = ()) -> dict:
    from jaxgran.scenes.interface import mohr_envelope_fits

    s1, s3, s1p, s3p, runs = [], [], [], [], []
    for a, c in circles:  # measured elsewhere: peaks
        if not (a > c):
            raise ValueError(f"a circle needs sigma1 > sigma3, got {a} and {c} Pa")
    s1p += [float(a) for a, _ in circles]
    s3p += [float(c) for _, c in circles]
    s1, s3 = list(s1p), list(s3p)
    for folder in folders:
        d = json.loads((Path(folder) / "summary.json").read_text())
        a, c = d["peak_sigma1_Pa"], d["peak_sigma3_Pa"]
        per = d["per_confinement"]
        # confinements first, then the unconfined and tension circles (true peaks); a
        # confinement counts where it peaked (summaries before post_peak_behaviour: where it
        # ended on a drop)
        real = [_real_peak(r) for r in per]
        peaked = real + [True] * (len(a) - len(per))
        s1 += a
        s3 += c
        s1p += [x for x, k in zip(a, peaked, strict=True) if k]
        s3p += [x for x, k in zip(c, peaked, strict=True) if k]
        runs.append(
            {
                "folder": str(folder),
                "bond": d.get("bond"),
                "ucs_Pa": d.get("ucs_Pa"),
                "tensile_strength_Pa": d.get("tensile_strength_Pa"),
                "peaked": real,
                "post_peak_behaviour": [r.get("post_peak_behaviour") for r in per],
            }
        )
    return {
        "all": mohr_envelope_fits(s1, s3),
        "peaks_only": mohr_envelope_fits(s1p, s3p),
        "runs": runs,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", help="output folders of interface-compression runs")
    ap.add_argument(
        "--circle",
        type=_circle,
        action="append",
        default=[],
        metavar="SIGMA1,SIGMA3",
        help="a peak circle measured elsewhere (Pa, compression positive); repeatable",
    )
    args = ap.parse_args()
    out = pool(args.folders, args.circle)
    out["extra_circles"] = args.circle
    json.dump(out, sys.stdout, indent=1, default=float)
    print()


if __name__ == "__main__":
    main()
