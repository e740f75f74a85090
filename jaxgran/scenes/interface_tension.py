"""Direct tension of a bonded specimen with interface bonds (paper 003 §3, Fig. 2, in 2D).

A rectangle ``width x height`` of bonded elementary discs (2.5-5 mm) or Voronoi cells, with
the gypsum-like material of :mod:`jaxgran.scenes.interface` (plane stress, slab thickness T),
is tied to two end walls by normal wall bonds (:func:`jaxgran.bonds.attach_to_walls`) and
pulled apart at ``strain_rate`` (the paper moves its end particles at constant speed). The
tensile stress is the mean wall force over ``width x T`` (Pa), the strain the wall separation
over its initial value. The run stops once the stress has fallen below ``drop_fraction x``
its peak. Reported: the direct tensile strength, the strain at the peak, how linear the rise
is (R^2 up to 90 % of the peak, secant/tangent modulus at the peak), the post-peak strain
until the drop (brittleness), element failures by mode; ``--set bond=parallel`` runs the
baseline.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .. import interface as itf
from . import interface as si
from .base import write_outputs

SCENE = "interface-tension"


@dataclasses.dataclass(frozen=True)
class Config(si.Common):
    width: float = 0.025  # m
    height: float = 0.05  # m
    strain_rate: float = 2.0  # 1/s
    max_strain: float = 0.004
    drop_fraction: float = 0.3


QUICK = {"width": 0.015, "height": 0.03, "record_every": 25, "records_per_segment": 8}


def build(cfg: Config) -> si.Setup:
    mat = si.material_from(cfg)
    region = ("rect", (0.0, 0.0), (cfg.width, cfg.height))
    spec = si.make_specimen(cfg, region, mat)
    walls = si.axial_walls(spec, -0.5 * cfg.strain_rate * cfg.height, cfg.width)
    reach = 0.5 * cfg.d_max * (2.0 * cfg.clearance + 0.05)
    if spec.kind == "voronoi":
        reach = 2.0 * float(spec.radius.max())
    return si.prepare(
        spec,
        mat,
        walls,
        cfg,
        margin=0.5 * cfg.height,
        bond_walls=(0, 1),
        wall_bond_distance=reach,
    )


def tensile_stress(series: dict, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """Tensile stress (Pa) and strain per record from the wall forces and positions."""
    force, gap = si.axial_load(series)
    return -force / (cfg.width * cfg.thickness), gap


def simulate_test(cfg: Config, *, progress: bool = False, setup: si.Setup | None = None):
    setup = setup or build(cfg)
    dt = float(setup.params.dt)
    n_steps = int(math.ceil(cfg.max_strain / cfg.strain_rate / dt))
    stop = si.peak_stopper(lambda rec: tensile_stress(rec, cfg)[0], cfg.drop_fraction)
    res = si.drive(setup, n_steps, cfg, stop, progress=progress, desc=SCENE)
    return res, setup


def measure(res, setup: si.Setup, cfg: Config) -> dict:
    stress, gap = tensile_stress(res.series, cfg)
    strain = np.asarray(gap, float) / _gap0(setup) - 1.0
    k = int(np.argmax(stress))
    out = {
        "tensile_strength_Pa": float(stress[k]),
        "strain_at_peak": float(strain[k]),
        "final_stress_over_peak": float(stress[-1] / stress[k]) if stress[k] > 0 else math.nan,
        "post_peak_strain_over_peak_strain": float((strain[-1] - strain[k]) / strain[k])
        if strain[k] > 0
        else math.nan,
    }
    out.update(si.linearity(strain, stress))
    out.update(itf.element_summary(res.state.bonds))
    times = np.asarray(res.state.bonds.elem_break_time)
    t_peak = float(np.asarray(res.series["time"])[k])
    out["elements_failed_before_peak"] = int(np.sum(times < t_peak))
    return out


def _gap0(setup: si.Setup) -> float:
    w = np.asarray(setup.state.walls.point)
    return float(w[-1, 1] - w[0, 1])


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    res, setup = simulate_test(cfg, progress=progress)
    summary = measure(res, setup, cfg)
    summary.update(si.run_facts(res, setup, cfg))
    summary.update(si.steady_rate(res, setup.spec.n_particles, cfg))
    r0 = res.realisation(0)
    summary = write_outputs(out_dir, SCENE, cfg, r0, setup.params, summary, vtk=vtk)
    from .. import plot_interface as pi

    stress, gap = tensile_stress(res.series, cfg)
    strain = gap / _gap0(setup) - 1.0
    figs = [
        pi.plot_curve(
            {cfg.bond: (100 * strain, stress / 1e6)},
            "axial strain (%)",
            "tensile stress (MPa)",
            Path(out_dir) / "stress_strain.png",
        ),
        pi.plot_cracks(res.state, si.element_table(res.state), Path(out_dir) / "cracks.png"),
    ]
    return si.finish(out_dir, summary, figs)
