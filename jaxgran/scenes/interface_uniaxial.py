"""Uniaxial (unconfined) compression of an interface-bonded specimen (paper 003 §4, Fig. 5-6).

A rectangle ``width x height`` of bonded discs or Voronoi cells (the gypsum-like material of
:mod:`jaxgran.scenes.interface`) between two frictional platens closing at ``strain_rate``;
no lateral walls. Stress = mean platen force / (width x T) (Pa, compression positive). The
run stops once the stress has fallen below ``drop_fraction x`` its peak. Reported: the
unconfined compressive strength (UCS), the strain at the peak, the rising branch's modulus
and linearity, element failures by mode, and, with ``with_tension`` (default), the direct
tensile strength of the same specimen (:mod:`jaxgran.scenes.interface_tension`) and the
ratio UCS / sigma_t (gypsum-like: about 8-12).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .. import interface as itf
from . import interface as si
from .base import write_outputs

SCENE = "interface-uniaxial"


@dataclasses.dataclass(frozen=True)
class Config(si.Common):
    width: float = 0.025  # m
    height: float = 0.05  # m
    strain_rate: float = 2.0  # 1/s
    max_strain: float = 0.02
    drop_fraction: float = 0.6
    with_tension: bool = True  # also run direct tension on the same specimen


QUICK = {"width": 0.015, "height": 0.03, "record_every": 25, "records_per_segment": 8}


def build(cfg: Config) -> si.Setup:
    mat = si.material_from(cfg)
    region = ("rect", (0.0, 0.0), (cfg.width, cfg.height))
    spec = si.make_specimen(cfg, region, mat)
    walls = si.axial_walls(spec, 0.5 * cfg.strain_rate * cfg.height, cfg.width)
    return si.prepare(spec, mat, walls, cfg, margin=0.5 * cfg.height)


def axial_stress(series: dict, cfg) -> tuple[np.ndarray, np.ndarray]:
    force, gap = si.axial_load(series)
    return force / (cfg.width * cfg.thickness), gap


def simulate_test(cfg: Config, *, progress: bool = False, setup: si.Setup | None = None):
    setup = setup or build(cfg)
    n_steps = int(math.ceil(cfg.max_strain / cfg.strain_rate / float(setup.params.dt)))
    stop = si.peak_stopper(lambda rec: axial_stress(rec, cfg)[0], cfg.drop_fraction)
    return si.drive(setup, n_steps, cfg, stop, progress=progress, desc=SCENE), setup


def measure(res, setup: si.Setup, cfg: Config) -> dict:
    stress, gap = axial_stress(res.series, cfg)
    w = np.asarray(setup.state.walls.point)
    strain = 1.0 - gap / float(w[-1, 1] - w[0, 1])
    k = int(np.argmax(stress))
    out = {"ucs_Pa": float(stress[k]), "strain_at_peak": float(strain[k])}
    out.update(si.linearity(strain, stress, upto=0.5))
    out.update(itf.element_summary(res.state.bonds))
    return out


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    res, setup = simulate_test(cfg, progress=progress)
    summary = measure(res, setup, cfg)
    summary.update(si.run_facts(res, setup, cfg))
    if cfg.with_tension:
        from . import interface_tension as tn

        names = {f.name for f in dataclasses.fields(tn.Config)}
        tcfg = tn.Config(**{k: v for k, v in dataclasses.asdict(cfg).items() if k in names})
        tcfg = dataclasses.replace(tcfg, max_strain=0.004, drop_fraction=0.3)
        tres, tsetup = tn.simulate_test(tcfg, progress=progress)
        sig_t = tn.measure(tres, tsetup, tcfg)["tensile_strength_Pa"]
        summary["tensile_strength_Pa"] = sig_t
        summary["ucs_over_tensile_strength"] = summary["ucs_Pa"] / sig_t
    summary = write_outputs(out_dir, SCENE, cfg, res.realisation(0), setup.params, summary, vtk=vtk)
    from .. import plot_interface as pi

    stress, gap = axial_stress(res.series, cfg)
    strain = 1.0 - gap / gap[0]
    figs = [
        pi.plot_curve(
            {cfg.bond: (100 * strain, stress / 1e6)},
            "axial strain (%)",
            "axial stress (MPa)",
            Path(out_dir) / "stress_strain.png",
        ),
        pi.plot_cracks(res.state, si.element_table(res.state), Path(out_dir) / "cracks.png"),
    ]
    return si.finish(out_dir, summary, figs)
