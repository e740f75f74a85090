"""Brazilian splitting of an interface-bonded disc (paper 003 §4, Fig. 5-6).

The disc of :mod:`jaxgran.scenes.interface_plate` (bonded elementary discs or Voronoi cells,
gypsum-like material, ``--set bond=parallel`` for the baseline) between two platens, without
the detailed probes: the peak force, the Brazilian tensile strength ``2 F / (pi D T)``, the
split angle and the failures by mode.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from . import interface as si
from . import interface_plate as pc
from .base import write_outputs

SCENE = "interface-brazilian"


@dataclasses.dataclass(frozen=True)
class Config(pc.Config):
    particles: str = "discs"  # paper 003's elementary balls; the peak force needs no field
    detailed: bool = False


QUICK = dict(pc.QUICK)


def run(cfg: Config, out_dir: Path, *, progress: bool = True, vtk: bool = False) -> dict:
    res, setup = pc.simulate_test(cfg, progress=progress)
    summary = pc.measure(res, setup, cfg)
    summary.update(si.run_facts(res, setup, cfg))
    summary = write_outputs(out_dir, SCENE, cfg, res.realisation(0), setup.params, summary, vtk=vtk)
    return si.finish(out_dir, summary, pc.figures(res, setup, cfg, summary, Path(out_dir)))
