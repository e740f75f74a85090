"""Damage separation model end to end: calibration, screening, the Brazilian disc between
platens (critical force, fracture plane, halves), and no recompiles across breakage."""

import dataclasses
import math
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran.breakage.dsm import (
    DsmBreakage,
    brazilian_factor,
    calibrate_eps,
    calibration_report,
    critical_load,
)
from jaxgran.scenes import brazilian_dsm as bz
from jaxgran.simulate import prepare, run_segment
from jaxgran.state import replace

CFG = dataclasses.replace(bz.Config(), **bz.QUICK)


# ----------------------------------------------------------------------------- calibration


def test_brazilian_factor_and_calibration_match_physics_c():
    # PHYSICS §C table: k = psi_c / (F / (pi R t))
    assert brazilian_factor(0.3, "stress") == pytest.approx(3.4351, abs=1e-4)
    assert brazilian_factor(0.3, "strain") == pytest.approx(3.3823, abs=1e-4)
    assert brazilian_factor(0.2, "stress") == pytest.approx(3.3466, abs=1e-4)
    eps = calibrate_eps(150.79, 0.01, thickness=0.01)
    assert eps == pytest.approx(1.649e6, rel=1e-3)
    assert critical_load(eps, 0.01, 0.01) == pytest.approx(150.79, rel=1e-12)
    rep = calibration_report(150.79, 0.01, thickness=0.01, bem_check=False)
    # the paper's 2.80251 MPa implies a 5.88 mm thick disc (PHYSICS §C)
    assert rep["thickness_for_paper_eps_m"] == pytest.approx(5.88e-3, abs=0.01e-3)
    # with the paper's eps and t = 1 cm the disc would break at 256.3 N
    assert critical_load(2.80251e6, 0.01, 0.01) == pytest.approx(256.3, abs=0.1)


# ----------------------------------------------------------------------------- static disc


def _pressed_disc(force, rotation=0.0):
    """The scene's disc between fixed platens, each contact vertex pressed with ``force``
    (N): one vertex per platen unless the rotation puts an edge on it."""
    state, params, grid = bz.build(CFG, rotation)
    delta = force / CFG.normal_stiffness
    w = state.walls
    point = w.point + jnp.array([[0.0, delta], [0.0, -delta]])
    state = replace(state, walls=replace(w, point=point, vel=jnp.zeros_like(w.vel)))
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    return state, params, grid


def _dsm(params, grid, **kw):
    eps = calibrate_eps(CFG.target_force, CFG.disc_radius, thickness=CFG.thickness)
    return DsmBreakage(
        params,
        grid,
        eps=eps,
        thickness=CFG.thickness,
        n_elements=CFG.n_elements,
        n_points=CFG.n_points,
        batch_size=1,
        mean_initial_mass=1.0,
        **kw,
    )


@pytest.fixture(scope="module")
def quick_run():
    return bz.simulate_test(CFG)


def test_screening_and_criterion_bracket_the_critical_load(quick_run):
    f_c = CFG.target_force
    state, params, grid = _pressed_disc(0.3 * f_c)
    dsm = _dsm(params, grid, screen="force")
    tab = dsm._table(state)
    assert int(tab["n_neighbours"][0]) == 2
    assert float(tab["max_force"][0]) == pytest.approx(0.3 * f_c, rel=1e-9)
    area = float(state.particles.mass[0]) / CFG.areal_density
    f_eq = critical_load(dsm.eps, math.sqrt(area / math.pi), CFG.thickness)
    assert float(tab["critical_load"][0]) == pytest.approx(f_eq, rel=1e-12)
    assert not bool(tab["flag"][0])  # below screen_fraction x F_c: no BEM
    assert dsm.check(state) == [] and dsm.n_checked == 0
    # the psi bound of the disc at 0.3 F_c is below eps too (about 2.6 x 0.3 eps)
    bound = _dsm(params, grid)
    assert bound.screen == "bound"
    assert bound.check(state) == [] and bound.n_checked == 0
    dsm = bound
    uid = int(state.particles.uid[0])
    for ratio, breaks in ((0.99, False), (1.01, True)):
        state, *_ = _pressed_disc(ratio * f_c)
        decisions = dsm.check(state)
        assert bool(decisions) == breaks
        # psi at the saddle is the Brazilian centre value k F / (pi R t), within 0.5 %
        assert dsm.last_saddle[uid] == pytest.approx(ratio * dsm.eps, rel=5e-3)
    # a pickled handler (a checkpoint) drops its per-shape operators and screening tables,
    # rebuilds them on demand and decides exactly as before
    assert dsm._cache and dsm._bound_rows
    again = pickle.loads(pickle.dumps(dsm))
    assert not again._cache and not again._bound_rows and again._bound_stack is None
    redo = again.check(state)
    assert len(redo) == len(decisions) == 1
    for a, b in zip(redo, decisions, strict=True):
        assert a.slot == b.slot
        np.testing.assert_array_equal(np.asarray(a.planes), np.asarray(b.planes))


def test_disc_between_platens_splits_in_halves_at_the_predicted_load(quick_run):
    result, dsm, meas = quick_run
    s = bz.summarize(result, dsm, meas, CFG)
    assert s["broke"] and s["n_events"] >= 1
    assert s["critical_force_N"] == pytest.approx(s["predicted_critical_force_N"], rel=0.02)
    assert s["force_previous_check_N"] < s["predicted_critical_force_N"] * 1.005
    assert all(a < 5.0 for a in s["fracture_plane_angles_deg"])
    assert s["n_fragments"] == 2 and s["fragment_mass_ratio"] > 0.99
    assert 0 < s["mass_lost_fraction"] < 0.02
    ev = dsm.events[0]
    total = ev["fragment_masses"].sum() + ev["fines_mass"] + ev["eroded_mass"]
    assert total == pytest.approx(ev["parent_mass"], rel=1e-12)
    assert ev["breakage_type"] == "splitting"
    # the connection point is the disc centre
    np.testing.assert_allclose(ev["connection_points"], [[0.0, 0.0]], atol=1e-3 * CFG.disc_radius)


def test_no_recompiles_across_breakage_events(quick_run, compile_log):
    """After one breakage has compiled everything, another breakage (a new DSM, a turned
    disc) and the segment after it compile nothing."""
    _, params, grid = _pressed_disc(0.5 * CFG.target_force)
    state, *_ = _pressed_disc(1.05 * CFG.target_force, rotation=0.05)
    dsm = _dsm(params, grid)
    compile_log.clear()
    state, stop = dsm(state, None)
    assert len(dsm.events) == 1 and not stop
    state, _, err = run_segment(state, params, grid, CFG.check_every // CFG.record_every, 10)
    assert int(err) == 0
    assert compile_log == []
    jax.jit(lambda x: x + 1)(jnp.zeros(3))  # the log does see compiles
    assert compile_log
    # the halves start without force
    ids = dsm.events[0]["fragment_slots"]
    assert np.all(np.linalg.norm(np.asarray(state.particles.force)[ids], axis=1) < 1e-6)


def test_two_neighbours_on_one_corner_do_not_break_a_lightly_loaded_particle():
    """A Voronoi pile under its own weight, every particle checked (screening off): the
    contacts of two neighbours at a shared corner have touching seeds. Counted as singular
    loads they joined at psi = inf, and every particle broke under any load. Their psi is
    finite now, proportional to the load (the BEM is linear: doubling K_n and K_t at fixed
    positions doubles every contact force and every saddle), and far below eps."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_contacts import packing

    state, params, grid = packing(12, jnp.float64)
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    state, _, err = run_segment(state, params, grid, 1, 500)
    assert int(err) == 0
    # at rest (no dashpot force), so that scaling both stiffnesses scales every force
    p = state.particles
    state = replace(state, particles=replace(p, vel=0 * p.vel, omega=0 * p.omega))
    eps = calibrate_eps(150.79, 0.01, thickness=float(params.thickness))
    saddles = []
    for scale in (1.0, 2.0):
        prm = replace(
            params,
            normal_stiffness=scale * params.normal_stiffness,
            tangential_stiffness=scale * params.tangential_stiffness,
        )
        brk = DsmBreakage(prm, grid, eps=eps, screen_fraction=0.0, cache_size=64)
        assert brk.check(state) == []
        saddles.append(np.array([brk.last_saddle[k] for k in sorted(brk.last_saddle)]))
    assert saddles[0].size >= 8 and np.all(np.isfinite(saddles[0]))
    assert saddles[0].max() < 0.2 * eps
    np.testing.assert_allclose(saddles[1], 2.0 * saddles[0], rtol=1e-6)
    # an operator cache smaller than one check's candidates grows to hold them (an LRU
    # cache cycled through a larger set would rebuild every operator at every check); the
    # cache changes no number
    small = DsmBreakage(prm, grid, eps=eps, screen_fraction=0.0, cache_size=4)
    assert small.check(state) == []
    assert small.cache_size >= saddles[1].size and len(small._cache) == saddles[1].size
    assert any("operator cache grown from 4" in m for m in small.log)
    again = np.array([small.last_saddle[k] for k in sorted(small.last_saddle)])
    np.testing.assert_array_equal(again, saddles[1])


# ----------------------------------------------------------------------------- screening


def _pinched_square(force, a=2.0e-3):
    """A 2 cm square grain (sphero-radius 0.2 mm, sharp corners) pinched at two opposite
    corners: four 1 mm discs press its faces at distance ``a`` (m) from the corners, each
    with ``force`` (N) along the face normal (balanced in force and moment)."""
    from jaxgran.partition import make_grid
    from jaxgran.state import make_params, make_state, make_walls, particles_from_polygons

    k_n, r, r_d, half = 2.0e7, 2.0e-4, 1.0e-3, 0.01
    h = half - r
    d = r + r_d - force / k_n  # disc centre to the core face
    core = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    discs = [
        np.array([[half - a, h + d]]),
        np.array([[h + d, half - a]]),
        np.array([[a - half, -h - d]]),
        np.array([[-h - d, a - half]]),
    ]
    parts = particles_from_polygons(
        [core, *discs], [r] + [r_d] * 4, 12.0, capacity=8, vertex_capacity=4
    )
    params = make_params(
        normal_stiffness=k_n,
        tangential_stiffness=0.3 * k_n,
        friction=0.74,
        gravity=(0.0, 0.0),
        thickness=0.01,
        poisson_ratio=0.3,
        skin=2.0e-4,
    )
    state = make_state(parts, make_walls([]), pair_capacity=32)
    grid = make_grid((-0.03, -0.03), (0.03, 0.03), 0.01, 2.0e-4, cell_capacity=16)
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    return state, params, grid


def test_bound_screening_catches_a_corner_chip_that_the_force_heuristic_misses():
    """Loads pinching two corners break the grain far below the load that splits a
    Brazilian disc of its area, so the force heuristic (largest neighbour force >= 0.5 of that load)
    never sends it to the BEM. The psi bound is proven (psi <= bound), so it sends every
    particle that the BEM would break, and none whose bound is below eps."""
    eps = calibrate_eps(150.79, 0.01, thickness=0.01)

    def dsm(params, grid, **kw):
        return DsmBreakage(params, grid, eps=eps, n_elements=64, n_points=200, batch_size=1, **kw)

    state, params, grid = _pinched_square(0.4 * 150.79)
    force, bound, every = (
        dsm(params, grid, screen="force"),
        dsm(params, grid, screen="bound"),
        dsm(params, grid, screen_fraction=0.0),
    )
    tab = force._table(state)
    assert int(tab["n_neighbours"][0]) == 4
    assert float(tab["max_force"][0]) < 0.4 * float(tab["critical_load"][0])
    assert force.check(state) == [] and force.n_checked == 0  # missed
    truth = every.check(state)
    assert len(truth) == 1 and truth[0].slot == 0  # the BEM breaks it
    found = bound.check(state)
    assert len(found) == 1 and bound.n_checked == 1
    np.testing.assert_array_equal(found[0].planes, truth[0].planes)
    uid = int(state.particles.uid[0])
    assert bound.last_saddle[uid] == pytest.approx(every.last_saddle[uid], rel=1e-12)
    assert bound.last_saddle[uid] >= eps
    # each plane joins two of the four contact points
    contacts = np.array([[0.008, 0.01], [0.01, 0.008], [-0.008, -0.01], [-0.01, -0.008]])
    ends = np.asarray(found[0].planes).reshape(-1, 2)
    assert np.all(np.min(np.linalg.norm(ends[:, None] - contacts[None], axis=-1), 1) < 1e-4)
    # a quarter of the load: psi is a quarter (linear BEM), below eps; the bound is below
    # eps too, so the particle is not solved at all
    state, *_ = _pinched_square(0.1 * 150.79)
    light = dsm(params, grid, screen="bound")
    assert light.check(state) == [] and light.n_checked == 0
    assert every.check(state) == []
    assert every.last_saddle[uid] == pytest.approx(0.25 * bound.last_saddle[uid], rel=0.02)


def test_force_chain_field_follows_the_brazilian_disc_solution():
    # Brazilian disc (Hondros): on the loaded diameter, at y from the centre,
    # sigma_1 - sigma_2 = (2 F / (pi t)) (2 / (D - 2y) + 2 / (D + 2y)), 8 F / (pi D t) at 0
    from jaxgran.breakage.photoelastic import force_chain_field

    force, d, t = 100.0, 2.0 * CFG.disc_radius, CFG.thickness
    centre_i = []
    for rotation in (0.0, 0.3):
        state, params, _ = _pressed_disc(force, rotation)
        field = force_chain_field(
            state,
            params,
            poisson_ratio=CFG.poisson_ratio,
            thickness=t,
            n_elements=CFG.n_elements,
            n_points=200,
        )
        assert field["n_loaded"] == 1 and np.all(field["slot"] == 0) and not field["skipped"]
        assert field["mean"][0] == pytest.approx(field["intensity"].mean())
        if rotation == 0.0:
            # a contact list too short for the particle grows instead of dropping forces
            short = force_chain_field(
                state, params, poisson_ratio=CFG.poisson_ratio, thickness=t,
                n_elements=CFG.n_elements, n_points=200, max_contacts=1,
            )  # fmt: skip
            np.testing.assert_array_equal(short["intensity"], field["intensity"])
            # too few elements for the core are raised to twice its vertices, not refused
            nv = int(state.particles.n_verts[0])
            assert 2 * nv > 8
            few, enough = (
                force_chain_field(
                    state,
                    params,
                    poisson_ratio=CFG.poisson_ratio,
                    thickness=t,
                    n_elements=n_el,
                    n_points=200,
                )  # fmt: skip
                for n_el in (8, 2 * nv)
            )
            assert not few["skipped"]
            np.testing.assert_array_equal(few["intensity"], enough["intensity"])
        xy = field["points"] - np.asarray(state.particles.pos[0])
        near = np.linalg.norm(xy, axis=1) < 0.15 * CFG.disc_radius
        assert near.sum() >= 3
        centre_i.append(float(field["intensity"][near].mean()))
        if rotation == 0.0:
            # the sample grid holds the centroid: its column is the loaded diameter
            axis = (np.abs(xy[:, 0]) < 1e-6 * d) & (np.abs(xy[:, 1]) < 0.3 * d)
            assert axis.sum() >= 9
            y = xy[axis, 1]
            want = 2 * force / (np.pi * t) * (2 / (d - 2 * y) + 2 / (d + 2 * y))
            np.testing.assert_allclose(field["intensity"][axis], want, rtol=5e-3)
    # a chip thinner than the band kept clear of its outline (1.5 element lengths) has no
    # sample point inside: it is skipped, not averaged over nothing (a NaN mean)
    from jaxgran.breakage import photoelastic

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(photoelastic.bem, "sample_points", lambda *a, **k: (np.zeros((0, 2)), None))
        chip = force_chain_field(state, params, poisson_ratio=CFG.poisson_ratio, thickness=t)
    assert chip["n_loaded"] == 0 and chip["intensity"].size == 0
    assert [s for s, _ in chip["skipped"]] == [0] and np.all(chip["mean"] == 0.0)
    # the mean over r < 0.15 R is within 2 % of the centre value
    assert centre_i[0] == pytest.approx(8 * force / (np.pi * d * t), rel=0.05)
    # invariance: a rotated disc under the same platen load shows the same intensity
    assert centre_i[1] == pytest.approx(centre_i[0], rel=0.03)
