"""Bonded Voronoi scenes (paper 002): Brazilian disc, constant-p biaxial, loading control,
and ensembles under jax.vmap. Tiny specimens (40-50 cells) and fast loading keep it short."""

import dataclasses
import math
import types

import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import ensemble as ens
from jaxgran.analysis import brazilian_tensile_strength
from jaxgran.scenes import bonded as bd
from jaxgran.scenes import bonded_biaxial as bx
from jaxgran.scenes import bonded_brazilian as bz
from jaxgran.scenes import bonded_cantilever as bc
from jaxgran.state import replace

TINY_DISC = {
    "n_cells": 50,
    "strain_rate": 40.0,
    "record_every": 25,
    "records_per_segment": 8,
    "realisations": 2,
}


def _single(setup, k, n_steps, cfg, control=None, state=None):
    return ens.drive(
        setup.states[k] if state is None else state,
        setup.params,
        setup.controls[k] if control is None else control,
        setup.grid,
        n_steps=n_steps,
        record_every=cfg.record_every,
        records_per_segment=cfg.records_per_segment,
        progress=False,
    )


@pytest.fixture(scope="module")
def brazil():
    """Two discs (seeds 0, 1) padded to common capacities: both under vmap until both have
    failed, then each alone for the same number of steps."""
    cfg = dataclasses.replace(bz.Config(), **TINY_DISC)
    setup = bz.build(cfg)
    cap = setup.states[0].contacts.capacity
    setup.states = [bd.with_pair_capacity(s, cap + cap % 2) for s in setup.states]  # even
    traces = (ens.run_segments._cached._cache_size(), ens._run_single._cached._cache_size())
    batch, _ = bz.simulate_test(cfg, setup=setup)
    singles = [_single(setup, k, batch.steps, cfg) for k in range(2)]
    new = (ens.run_segments._cached._cache_size(), ens._run_single._cached._cache_size())
    # every segment of both paths, and both single realisations, share one compilation each
    assert new[0] - traces[0] == 1 and new[1] - traces[1] == 1
    return cfg, setup, batch, singles


def test_brazilian_tiny_disc_splits_along_the_loading_diameter(brazil):
    cfg, setup, batch, singles = brazil
    assert batch.stopped_early and batch.size == 2
    for k, run in enumerate(singles):
        m = bz.measure(run, setup.gap0[k], cfg.diameter, setup.material)
        force, gap = bz.platen_force(run.series)
        strain = 1.0 - gap / setup.gap0[k]
        peak = int(np.argmax(force))
        # elastic rise: linear (R^2 of 10-70 % of F_max) after the platens have seated on the
        # polygonal poles (which stiffens the very start); few bonds broken early (at the
        # platens)
        assert m["rising_branch_r2"] > 0.95
        half = np.interp(0.5 * strain[peak], strain, force)
        assert 0.3 < half / force[peak] < 0.7
        n_half = run.series["n_broken"][np.searchsorted(strain, 0.5 * strain[peak])]
        assert n_half <= 0.25 * run.series["n_broken"][-1]
        # then a sudden drop (the run stops below drop_fraction x F_max): each disc's force
        # falls below it within 0.3 x its peak strain of the peak (the run itself goes on
        # until both discs have failed, so its end is the later disc's)
        assert force[-1] < cfg.drop_fraction * force[peak]
        below = np.flatnonzero(
            (np.arange(force.size) > peak) & (force < cfg.drop_fraction * force[peak])
        )
        assert strain[below[0]] - strain[peak] < 0.3 * strain[peak]
        # Eq. 16
        assert m["tensile_strength_Pa"] > 0
        assert m["tensile_strength_Pa"] == pytest.approx(
            brazilian_tensile_strength(force[peak], cfg.diameter, cfg.thickness)
        )
        assert m["slope_S_Pa"] > 0
        # the crack: broken bonds along the loading (vertical) diameter
        assert m["n_broken"] >= 10
        assert m["crack_angle_from_loading_axis_deg"] < 20.0
        assert m["crack_elongation"] > 1.5
        # a uniform cloud over the disc would have mean |x| = 4 R / (3 pi) = 0.21 D
        assert m["broken_mean_distance_from_loading_axis_over_D"] < 0.15


def test_ensemble_under_vmap_equals_sequential_runs(brazil):
    _, _, batch, singles = brazil
    for k, one in enumerate(singles):
        many = batch.realisation(k)
        np.testing.assert_allclose(
            np.asarray(many.state.particles.pos),
            np.asarray(one.state.particles.pos),
            rtol=0,
            atol=1e-10 * 0.05,
        )
        np.testing.assert_allclose(
            np.asarray(many.state.particles.angle),
            np.asarray(one.state.particles.angle),
            atol=1e-10,
        )
        np.testing.assert_array_equal(
            np.asarray(many.state.bonds.intact), np.asarray(one.state.bonds.intact)
        )
        bt_many, bt_one = (
            np.asarray(many.state.bonds.break_time),
            np.asarray(one.state.bonds.break_time),
        )
        np.testing.assert_array_equal(np.isfinite(bt_many), np.isfinite(bt_one))
        fin = np.isfinite(bt_one)
        np.testing.assert_allclose(bt_many[fin], bt_one[fin], rtol=1e-10)
        for key in ("wall_force", "kinetic_energy", "n_broken", "time"):
            ref = np.asarray(one.series[key], float)
            np.testing.assert_allclose(
                np.asarray(many.series[key], float), ref, rtol=0, atol=1e-10 * np.abs(ref).max()
            )
        assert int(one.series["n_broken"][-1]) > 0  # the comparison went through fracture


def test_full_pair_list_is_grown_and_gives_the_same_run(brazil):
    """Half the needed pair capacity: the host loop doubles it (back to the fixture's
    capacity, so nothing recompiles but the start-up) and the run is the same."""
    cfg, setup, _, _ = brazil
    cap = setup.states[0].contacts.capacity
    small = bd.with_pair_capacity(setup.states[0], cap // 2)
    n = cfg.record_every * cfg.records_per_segment
    grown = _single(setup, 0, n, cfg, state=small)
    ample = _single(setup, 0, n, cfg)
    assert any("pair capacity" in msg for msg in grown.regrows) and not ample.regrows
    assert grown.state.contacts.capacity == cap
    np.testing.assert_array_equal(
        np.asarray(grown.state.particles.pos), np.asarray(ample.state.particles.pos)
    )


def test_stacking_needs_common_capacities(brazil):
    cfg, setup, _, _ = brazil
    spec = bd.disc_specimen(cfg.diameter, 30, 7, setup.material)
    other = bd.assemble(spec, setup.material, [])
    with pytest.raises(ValueError, match="Capacities"):
        ens.stack([setup.states[0], other])


def test_external_force_and_damping_of_the_control_are_exact(brazil):
    """A body force ramped from zero moves a free disc rigidly exactly as Verlet with that
    force would; a global damping c scales velocities by exp(-c dt) per step. Same shapes as
    the Brazilian disc, so the compiled segment is reused."""
    cfg, setup, _, _ = brazil
    state = setup.states[0]
    state = replace(state, walls=replace(state.walls, active=jnp.zeros(2, bool)))
    mass = np.asarray(state.particles.mass)
    act = np.asarray(state.particles.active)
    g = np.array([3.0e5, -2.0e5])  # m/s^2
    ramp = 2.0e-5  # s
    control = bd.make_control(
        state, external_force=mass[:, None] * g * act[:, None], ramp_time=ramp
    )
    n = cfg.record_every * cfg.records_per_segment
    run = _single(setup, 0, n, cfg, control=control, state=state)
    dt = float(setup.params.dt)
    x, v = 0.0, 0.0  # leap-frog with a(t_n) = g min(t_n / ramp, 1), v at half steps
    for k in range(n):
        v += dt * min(k * dt / ramp, 1.0)
        x += dt * v
    disp = np.asarray(run.state.particles.pos)[act] - np.asarray(state.particles.pos)[act]
    np.testing.assert_allclose(disp, np.broadcast_to(x * g, disp.shape), rtol=1e-9)

    c = 2.0e4  # 1/s
    v0 = np.where(act[:, None], np.array([0.1, 0.05]), 0.0)
    moving = replace(state, particles=replace(state.particles, vel=jnp.asarray(v0)))
    run = _single(setup, 0, n, cfg, control=bd.make_control(state, damping=c), state=moving)
    vel = np.asarray(run.state.particles.vel)[act]
    np.testing.assert_allclose(vel, v0[act] * math.exp(-c * dt * n), rtol=1e-9)


def test_biaxial_pair_capacity_floor_is_kept_and_the_fit_used_above_it():
    """``run`` starts the constant-p tests at the pair capacity the unconfined test of the
    same blocks grew to (so they do not grow and compile again): the floor is a floor."""
    cfg = dataclasses.replace(bx.Config(), width=0.03, height=0.06, n_cells=40)
    fitted = bx.build(cfg, [(0, 0.0)]).states[0].contacts.capacity
    floored = bx.build(cfg, [(0, 0.0)], pair_capacity=2 * fitted).states[0]
    assert floored.contacts.capacity == 2 * fitted
    assert floored.contacts.pairs.shape == (2 * fitted, 2)
    low = bx.build(cfg, [(0, 0.0)], pair_capacity=fitted // 2).states[0]
    assert low.contacts.capacity == fitted


def test_biaxial_holds_p_constant_while_shearing():
    cfg = dataclasses.replace(
        bx.Config(),
        width=0.03,
        height=0.06,
        n_cells=40,
        strain_rate=40.0,
        max_strain=0.02,
        record_every=25,
        records_per_segment=8,
    )
    p = 300.0e6
    # the pair list, fitted to the fresh block (140 slots), overflows as the block is pressed
    # to p; starting at the doubled capacity spares the regrowth's second compilation (the
    # regrowth itself is tested in tests/test_simulate.py)
    shear, iso, setup, _ = bx.isotropic_then_shear(cfg, [0], (p,), pair_capacity=280)
    assert not iso.regrows and not shear.regrows
    s_ax, s_lat, *_ = bx.stresses(iso.series, cfg.thickness)
    assert abs(s_ax[-1] / p - 1.0) < cfg.iso_tolerance
    assert abs(s_lat[-1] / p - 1.0) < cfg.iso_tolerance
    m = bx.measure_shear(shear.realisation(0), p, cfg.thickness, cfg.residual_fraction)
    assert m["p_max_relative_deviation"] < 0.02
    assert m["p_mean_relative_deviation"] < 0.005
    # a real shearing test: q grew well beyond p, bonds broke, s3 turned tensile (the wall
    # bonds pull) and the axial walls moved as prescribed
    assert m["q_peak_Pa"] > p
    assert m["n_broken_final"] > 10
    s_ax, s_lat, height, _ = bx.stresses(shear.series, cfg.thickness)
    assert s_lat.min() < 0.0
    e1 = 1.0 - height / height[0]
    assert e1[-1] == pytest.approx(cfg.max_strain, rel=0.1)


def test_shear_damping_reaches_the_shearing_stage_only():
    """``shear_damping`` damps the cells while shearing (0 by default, paper 002), not
    while the block is pressed to p; one step of the control scales free velocities by
    exp(-c dt)."""
    cfg = dataclasses.replace(bx.Config(), n_cells=40, width=0.03, height=0.06)
    setup = bx.build(cfg, [(0, 100.0e6)])
    iso = bd.make_control(setup.states[0], p_target=100.0e6, box=True)
    assert float(bx.shear_controls(iso, cfg).damping) == 0.0
    damped = bx.shear_controls(iso, dataclasses.replace(cfg, shear_damping=1.0e5))
    assert float(iso.damping) == 0.0 and float(damped.damping) == 1.0e5
    assert bool(damped.p_constant) and not bool(iso.p_constant)
    state = setup.states[0]
    p = state.particles
    state = replace(state, particles=replace(p, vel=jnp.ones_like(p.vel)))
    out = bd.apply_control(state, setup.params, damped)
    free = np.asarray(p.active & ~p.fixed)
    decay = np.exp(-1.0e5 * float(setup.params.dt))
    np.testing.assert_allclose(np.asarray(out.particles.vel)[free], decay, rtol=1e-12)


def test_servo_speed_cap_is_a_setting():
    cfg = dataclasses.replace(bx.Config(), servo_max_speed=50.0, strain_rate=10.0)
    walls = bx._walls(cfg, bd.material_from(cfg), 100.0e6)
    assert [w["max_speed"] for w in walls] == [50.0 * 10.0 * cfg.height] * 4
    default = bx._walls(bx.Config(), bd.material_from(bx.Config()), 100.0e6)
    assert default[0]["max_speed"] == 2.0 * bx.Config().strain_rate * bx.Config().height


def test_euler_bernoulli_cantilever_formula():
    f, a, e, i = 100.0, 0.2, 1.0e10, 1.0e-8
    x = np.linspace(0.0, 0.3, 301)
    w = bc.euler_bernoulli(x, f, a, e, i)
    assert w[0] == 0.0
    tip = f * a**3 / (3.0 * e * i)
    assert np.interp(a, x, w) == pytest.approx(tip, rel=1e-12)
    # straight beyond the load, with the slope F a^2 / (2 E I)
    assert (w[-1] - np.interp(a, x, w)) / (x[-1] - a) == pytest.approx(
        f * a**2 / (2 * e * i), rel=1e-9
    )
    # Eq. 29 with L = a: w'' = M / (E I) = F (a - x) / (E I)
    h = x[1] - x[0]
    curv = np.diff(w[:150], 2) / h**2
    np.testing.assert_allclose(curv, f * (a - x[1:149]) / (e * i), rtol=1e-6)


@pytest.mark.parametrize("clamp", ["straight", "cells"])
def test_cantilever_specimen_tiles_the_beam_and_the_clamp_face(clamp):
    """Both clamp kinds tile L x s exactly with bonded cells; with ``clamp = "straight"``
    every bond between a fixed and a free cell lies on the line x = clamp_length and those
    bonds cover the whole depth once (the straight face of a fixed plate)."""
    from jaxgran import geometry as geo

    cfg = dataclasses.replace(bc.Config(), **bc.QUICK, clamp=clamp)
    spec = bc.beam_specimen(cfg, 3, bd.material_from(cfg))
    area = sum(geo.polygon_area(c) for c in spec.cells)
    assert area == pytest.approx(cfg.length * cfg.depth, rel=1e-12)
    fixed = spec.centroids()[:, 0] < cfg.clamp_length
    assert 0 < fixed.sum() < spec.n_particles
    face = [(p, q) for i, j, p, q in geo.shared_edges(spec.cells) if fixed[i] != fixed[j]]
    xs = np.array([[p[0], q[0]] for p, q in face])
    length = sum(float(np.linalg.norm(q - p)) for p, q in face)
    if clamp == "straight":
        np.testing.assert_allclose(xs, cfg.clamp_length, rtol=0, atol=1e-12)
        assert length == pytest.approx(cfg.depth, rel=1e-9)
    else:  # a zigzag of cell edges: longer than the depth, off the line
        assert length > cfg.depth and np.abs(xs - cfg.clamp_length).max() > 1e-4


def test_bimodular_flexural_modulus_from_the_section():
    """Pure bending of a rectangular section of a bimodular material: the neutral axis sits
    where the tension and compression forces balance, and M / (kappa I) is E_f."""
    e_t, e_c, depth, kappa = 19.9e9, 32.5e9, 0.05, 1.0e-3
    y = np.linspace(-0.5 * depth, 0.5 * depth, 200_001)  # across the depth (m)
    dy = y[1] - y[0]

    def stress(y0):  # curvature about the axis y = y0; y > y0 in tension
        strain = kappa * (y - y0)
        return np.where(strain > 0, e_t, e_c) * strain

    lo, hi = -0.5 * depth, 0.5 * depth
    for _ in range(80):  # bisection on the axial force balance
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.trapezoid(stress(mid), dx=dy) > 0 else (lo, mid)
    y0 = 0.5 * (lo + hi)
    moment = np.trapezoid(stress(y0) * (y - y0), dx=dy)  # per unit width
    assert y0 < 0.0  # the neutral axis moves to the stiffer (compression) side
    assert moment / (kappa * depth**3 / 12) == pytest.approx(
        bc.flexural_modulus(e_t, e_c), rel=1e-6
    )
    assert bc.flexural_modulus(e_c, e_c) == pytest.approx(e_c, rel=1e-14)


def test_timoshenko_and_the_clamp_compliance_fit():
    f, a, e, i, area = 150.0, 0.27, 25.0e9, 1.0e-7, 5.0e-4
    x = np.linspace(0.005, 0.28, 120)
    # shear adds F x / (k G A), k = 5/6 and G = E / 2 at nu = 0
    shear = bc.timoshenko(x, f, a, e, i, area, 0.0) - bc.euler_bernoulli(x, f, a, e, i)
    np.testing.assert_allclose(shear, f * np.minimum(x, a) / (5.0 / 6.0 * 0.5 * e * area))
    # a beam that bends with E but whose root turns by theta0: the tip error against Eq. 29
    # is the root's share, and the fit with a free root rotation gives E back exactly
    theta0 = 1.0e-4
    w = bc.euler_bernoulli(x, f, a, e, i) + theta0 * x
    cfg = bc.Config()
    geo = {"force_N": f, "arm_m": a, "second_moment_m4": i}
    out = bc.compare_deflection(x, w, geo, cfg, {"E_c_Pa": e, "E_t_Pa": e, "poisson_ratio": 0.0})
    assert out["E_bending_Pa"] == pytest.approx(e, rel=1e-9)
    assert out["root_rotation_rad"] == pytest.approx(theta0, rel=1e-9)
    tip = bc.euler_bernoulli(x[-1], f, a, e, i)
    assert out["tip_error_E_c"] == pytest.approx(theta0 * x[-1] / tip, rel=0.05)
    assert out["E_flexural_Pa"] == pytest.approx(e)


def test_envelope_fits_use_only_softening_peaks():
    """Hoek-Brown data on the true peaks, frictional plateaus (no softening) at high p that
    lie off the envelope, and a residual line: the plateaus must not enter the fit."""
    a, b, m, c = 400.0e6, 450.0e6, 0.7, 40.0e6
    rows = []
    for p in (50e6, 100e6, 150e6, 200e6):
        q = float(an_q(p, a, b))
        rows.append(_row(p, q, True, m * p + c))
    for p in (300e6, 400e6):  # max q is the plateau, far below the envelope's continuation
        rows.append(_row(p, m * p + c, False, m * p + c))
    ucs = [b]  # Eq. 30 at s3 = 0: s1 = B
    out = bx.envelope_fits(rows, ucs)
    assert out["n_true_peaks"] == 4 and out["n_unconfined"] == 1
    assert out["hoek_brown"]["A"] == pytest.approx(a, rel=1e-6)
    assert out["hoek_brown"]["B"] == pytest.approx(b, rel=1e-6)
    assert out["hoek_brown_s1s3"]["r2"] == pytest.approx(1.0)
    line = out["residual_line"]
    assert line["slope"] == pytest.approx(m) and line["intercept"] == pytest.approx(c)
    means = bx.envelope_fits(rows + rows, ucs, means=True)
    assert means["hoek_brown"]["n"] == 5 and means["residual_line"]["n"] == 6


def an_q(p, a, b):
    from jaxgran.analysis import hoek_brown_q

    return hoek_brown_q(p, a, b)


def _row(p, q, true, q_res):
    return {
        "p_target_Pa": p,
        "p_at_peak_Pa": p,
        "q_peak_Pa": q,
        "true_peak": true,
        "p_residual_Pa": p,
        "q_residual_Pa": q_res,
    }


def _biaxial_series(e1, p, q, thickness=0.01, h0=0.08, w0=0.04):
    """Wall forces and positions of a biaxial block with axial strain ``e1``, no lateral
    strain and the invariants ``p``, ``q`` (Pa) per record (the layout :func:`bx.stresses`
    reads)."""
    e1, p, q = (np.asarray(a, float) for a in (e1, p, q))
    n = e1.size
    h, w = h0 * (1.0 - e1), np.full(n, w0)
    s_ax, s_lat = p + q, p - q
    normal = np.array([[0.0, 1.0], [1.0, 0.0], [-1.0, 0.0], [0.0, -1.0]])
    fn = np.zeros((n, 4))
    fn[:, bd.BOTTOM] = fn[:, bd.TOP] = s_ax * w * thickness
    fn[:, bd.LEFT] = fn[:, bd.RIGHT] = s_lat * h * thickness
    point = np.zeros((n, 4, 2))
    point[:, bd.TOP, 1], point[:, bd.RIGHT, 0] = h, w
    return {
        "wall_force": -fn[..., None] * normal[None],
        "wall_point": point,
        "time": np.arange(n) * 1e-6,
        "n_broken": np.zeros(n, int),
    }


def test_shear_peak_is_the_first_failure_not_a_later_reloading():
    """q rises to 200 MPa at 1 % strain with p held, fails (drops 40 %), and the block is
    re-loaded to 220 MPa while p drifts to 1.5 x its target: the peak at the target p is
    the first one; the largest q is kept apart with its own drift. A burst that costs
    10 % of q on the way up is not a failure."""
    e1 = np.linspace(0.0, 0.03, 301)
    p_t = 100e6
    knots = [0, 0.006, 0.0065, 0.01, 0.012, 0.02, 0.03]
    q = 1e6 * np.interp(e1, knots, [0, 150, 135, 200, 120, 220, 150])
    p = np.where(e1 > 0.012, 150e6, p_t)
    run = types.SimpleNamespace(series=_biaxial_series(e1, p, q))
    m = bx.measure_shear(run, p_t, 0.01, 0.2)
    assert m["q_peak_Pa"] == pytest.approx(200e6, rel=1e-9)
    assert m["axial_strain_at_peak"] == pytest.approx(0.01, abs=1e-12)
    assert m["p_at_peak_Pa"] == pytest.approx(p_t, rel=1e-9)
    assert m["p_max_relative_deviation_to_peak"] == pytest.approx(0.0, abs=1e-9)
    assert m["q_largest_Pa"] == pytest.approx(220e6, rel=1e-9)
    assert m["axial_strain_at_largest"] == pytest.approx(0.02, abs=1e-12)
    assert m["p_max_relative_deviation_to_largest"] == pytest.approx(0.5, rel=1e-9)
    # a tolerance below the burst's 10 % takes the burst for the failure
    early = bx.measure_shear(run, p_t, 0.01, 0.2, failure_drop=0.05)
    assert early["q_peak_Pa"] == pytest.approx(150e6, rel=1e-9)
    # without a drop the peak is the largest q
    mono = types.SimpleNamespace(series=_biaxial_series(e1, np.full_like(e1, p_t), 1e8 * e1))
    assert bx.measure_shear(mono, p_t, 0.01, 0.2)["q_peak_Pa"] == pytest.approx(3e6)
    with pytest.raises(ValueError, match="failure_drop"):
        bx.first_failure_peak(q, e1 > 0, 1.0)
