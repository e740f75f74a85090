"""Averaged-stress breakage callbacks (paper 000 Table II) end to end on one grain with known
contact forces: calibration against the Brazilian test, criterion value, cutting planes
through the centroid, the shared replacement and mass bookkeeping."""

import dataclasses
import math

import numpy as np
import pytest

from jaxgran.breakage.averaged import (
    AveragedStressBreakage,
    calibrate_strengths,
    make_breakage,
)
from jaxgran.breakage.dsm import DsmBreakage
from jaxgran.geometry import spheropolygon_mass_properties
from jaxgran.scenes import breakage_types as bt

CFG = dataclasses.replace(bt.Config(), **bt.QUICK)
F_CAL = 150.79
P_CAL = F_CAL / (math.pi * 0.01 * 0.01)  # Brazilian pressure F / (pi R t), Pa


def test_strengths_break_the_calibration_disc_at_its_force():
    s = calibrate_strengths(F_CAL, 0.01, 0.01)
    assert s["brazilian_pressure"] == pytest.approx(P_CAL, rel=1e-12)
    assert s["tensile_strength"] == pytest.approx(P_CAL, rel=1e-12)  # (3*0 + 2p) / 2
    assert s["compressive_strength"] == pytest.approx(2 * P_CAL, rel=1e-12)
    assert s["von_mises_strength"] == pytest.approx(2 * P_CAL, rel=1e-12)
    with pytest.raises(ValueError, match="method must be one of"):
        make_breakage("voronoi", *bt.build(CFG, "N2", 1.0)[1:3])


def _grain_area():
    core = np.asarray(bt.build(CFG, "N2", 1.0)[0].particles.verts[0])
    return spheropolygon_mass_properties(core, CFG.sphero_radius, 1.0)[0]


def _loaded(load, method):
    state, params, grid, _ = bt.build(CFG, "N2", load)
    brk = make_breakage(method, params, grid, thickness=CFG.thickness, mean_initial_mass=1.0)
    return state, brk


# hand values for the Brazilian disc (loads F at (0, +-R)): sigma = diag(0, -2 F R / (A t)),
# theta_p = 0; split-cell (3 s1 - s2) / 2 = F R / (A t), cross-cut sigma_v = 2 F R / (A t),
# Mohr-Coulomb -s2 = 2 F R / (A t). Planes: 90 deg; +-45 deg; 45 deg.
CASES = {
    "split-cell": (1.0, [90.0], 2),
    "cross-cut": (2.0, [45.0, 135.0], 4),
    "mohr-coulomb": (2.0, [45.0], 2),
}


@pytest.mark.parametrize("method", list(CASES))
def test_brazilian_disc_breaks_at_calibration_with_hand_computed_value_and_planes(method):
    factor, angles, n_frag = CASES[method]
    area = _grain_area()
    # below: no break; the value is linear in the load
    state, brk = _loaded(0.9 * F_CAL, method)
    assert isinstance(brk, AveragedStressBreakage)
    new, stop = brk(state, None)
    assert not stop and brk.events == []
    (val,) = brk.last_value.values()
    hand = factor * 0.9 * F_CAL * 0.01 / (area * CFG.thickness)
    assert val == pytest.approx(hand, rel=0.02)  # contact points within r of (0, +-R)
    # the polygonal disc has ~1% less area than pi R^2: it breaks just below F
    assert hand / 0.9 * 0.97 < factor * P_CAL < hand / 0.9 * 1.03
    state, brk = _loaded(1.02 * F_CAL, method)
    new, _ = brk(state, None)
    (ev,) = brk.events
    assert ev["method"] == method
    assert ev["criterion_value"] > ev["criterion_threshold"]
    planes = np.asarray(ev["planes"])
    d = planes[:, 1] - planes[:, 0]
    got = sorted(np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0)
    assert got == pytest.approx(angles, abs=1e-6)
    # every plane passes through the centroid (the origin here)
    cross = planes[:, 0, 0] * d[:, 1] - planes[:, 0, 1] * d[:, 0]
    assert np.abs(cross).max() < 1e-12
    masses = np.asarray(ev["fragment_masses"])
    assert masses.size == n_frag
    assert masses.min() / masses.max() > 0.999  # halves / quarters
    assert ev["parent_mass"] == pytest.approx(masses.sum() + ev["mass_lost"], rel=1e-12)
    p = new.particles
    assert int(np.asarray(p.active).sum()) == n_frag
    assert float(np.asarray(p.mass)[np.asarray(p.active)].sum()) == pytest.approx(masses.sum())


def test_factory_gives_the_dsm_with_the_same_calibration():
    _, params, grid, _ = bt.build(CFG, "N2", 1.0)
    dsm = make_breakage("dsm", params, grid, thickness=0.01)
    assert type(dsm) is DsmBreakage
    # eps = k F / (pi R t): the DSM's critical load of the 1 cm disc is the calibration force
    assert dsm.critical_load(0.01) == pytest.approx(F_CAL, rel=1e-12)
