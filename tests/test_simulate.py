"""Host loop: capacity regrowth is exact, segments do not recompile, a pile settles under
its weight, bad input is refused with a message naming the fix."""

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import geometry as geo
from jaxgran.contact import damping_from_restitution
from jaxgran.integrate import stable_time_step
from jaxgran.partition import candidate_pairs, cell_count_max, make_grid
from jaxgran.simulate import SimulationError, simulate
from jaxgran.state import (
    ERR_CELL_OVERFLOW,
    Grid,
    box_walls,
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
)

RHO = 12.0


def _pile(n_cells=24, seed=3, wall_friction=0.0, k=2e4):
    width = 0.08
    cells = geo.voronoi_rectangle(width, 0.06, n_cells, seed, lloyd_iterations=2)
    r = 5e-4
    cores = []
    for c in cells:
        cen = geo.polygon_centroid(c)
        c = cen + 0.9 * (c - cen)
        cores.append(geo.offset_polygon(c, r + 1e-4) + [0.0, 0.2 * cen[1] + 0.002])
    parts = particles_from_polygons(cores, r, RHO, vertex_capacity=10)
    m = float(np.median(np.asarray(parts.mass)))
    params = make_params(
        normal_stiffness=k,
        tangential_stiffness=k / 3,
        friction=0.5,
        wall_friction=wall_friction,
        normal_damping=damping_from_restitution(0.2, k, m / 2),
        tangential_damping=damping_from_restitution(0.2, k, m / 2),
        skin=1e-3,
    )
    # 0.3 x the one-contact limit of springs and dashpots: the rested pile's linearised step
    # is then at 0.70 of its stability criterion (test_linearised_step_of_the_rested_pile...)
    params = replace(params, dt=jnp.asarray(stable_time_step(parts, params, 0.3)))
    walls = make_walls(box_walls((0.0, 0.0), (width, 0.12), top=False))
    grid = make_grid((-0.01, -0.01), (width + 0.01, 0.13), float(parts.bound_radius.max()), 1e-3)
    return parts, walls, params, grid


def _run_pile(parts, walls, params, grid, n_steps):
    """The pile from its start in the module's segment layout (5 records of 100 steps, pair
    capacity 400), so that runs share one compiled segment."""
    state = make_state(parts, walls, pair_capacity=400)
    kw = dict(record_every=100, records_per_segment=5, progress=False)
    return simulate(state, params, grid, n_steps=n_steps, **kw)


@pytest.fixture(scope="module")
def pile():
    return _pile()


def test_small_pair_capacity_grows_and_gives_identical_results(pile):
    parts, walls, params, grid = pile
    kw = dict(n_steps=2000, record_every=100, records_per_segment=5, progress=False)
    ample = simulate(make_state(parts, walls, pair_capacity=400), params, grid, **kw)
    small = simulate(make_state(parts, walls, pair_capacity=4), params, grid, **kw)
    assert not ample.regrows
    # one regrowth (one compilation), straight to the doubling that holds what the builds needed
    assert small.regrows == [f"pair capacity 4 exceeded; grown to {small.state.contacts.capacity}"]
    need = int(ample.state.contacts.n_pairs)
    assert small.state.contacts.capacity // 2 < need <= small.state.contacts.capacity
    np.testing.assert_allclose(
        np.asarray(small.state.particles.pos), np.asarray(ample.state.particles.pos), atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(small.state.particles.vel), np.asarray(ample.state.particles.vel), atol=1e-12
    )


def test_small_cell_capacity_grows(pile):
    parts, walls, params, grid = pile
    tight = dataclasses.replace(grid, cell_capacity=1)
    res = _run_pile(parts, walls, params, tight, 500)
    # one regrowth, straight to the doubling that holds the fullest cell
    assert res.regrows == [f"cell capacity 1 exceeded; grown to {res.grid.cell_capacity}"]
    need = max(cell_count_max(parts, grid), cell_count_max(res.state.particles, grid))
    assert res.grid.cell_capacity // 2 < need <= res.grid.cell_capacity


def test_cell_count_max_is_what_the_broad_phase_checks(pile):
    """The host's count of the fullest cell (numpy) sets the cell-overflow bit of the
    jitted broad phase exactly: a capacity one below it overflows, the count itself not."""
    parts, _, params, grid = pile
    need = cell_count_max(parts, grid)
    assert need > 1
    for cap in (need - 1, need):
        _, err = candidate_pairs(parts, params.skin, dataclasses.replace(grid, cell_capacity=cap))
        assert bool(int(err) & ERR_CELL_OVERFLOW) == (cap < need)


def test_progress_note_follows_the_callback_and_shows_on_the_bar(pile, capsys):
    """``progress_note`` runs after each segment's callback (it sees what the callback
    counted) and its text reaches the progress bar; the bar changes no number."""
    parts, walls, params, grid = pile
    seen, notes = [], []

    def callback(state, rec):
        seen.append(float(rec["time"][-1]))
        return state, len(seen) == 2  # stop after the second segment

    def note(rec):
        notes.append(len(seen))
        return f"segments checked={len(seen)}"

    kw = dict(record_every=100, records_per_segment=5, callback=callback)
    state = make_state(parts, walls, pair_capacity=400)
    shown = simulate(state, params, grid, n_steps=1500, progress=True, progress_note=note, **kw)
    assert notes == [1, 2] and shown.stopped_early and shown.steps == 1000
    assert "segments checked=2" in capsys.readouterr().err
    seen.clear()
    quiet = simulate(state, params, grid, n_steps=1500, progress=False, **kw)
    np.testing.assert_array_equal(
        np.asarray(shown.state.particles.pos), np.asarray(quiet.state.particles.pos)
    )


def test_segments_do_not_recompile(pile):
    from jaxgran import simulate as sim

    parts, walls, params, grid = pile
    state = make_state(parts, walls, pair_capacity=400)
    counted = eqx.debug.assert_max_traces(sim.run_segment.__wrapped__, max_traces=1)
    jitted = eqx.filter_jit(counted)
    state, _ = sim.prepare(state, params, grid)
    for _ in range(3):
        # new values (time, positions, parameters) but the same shapes: one trace only
        state, _, err = jitted(state, params, grid, 2, 50)
        params = replace(params, friction=params.friction * 1.01)
        assert int(err) == 0


def test_moved_grid_reuses_the_compiled_segment_and_the_run_translates(pile):
    """The grid's origin and cell size are values, not static: a scene shifted by d, with
    its grid shifted by d and cells 10 % larger (same nx, ny), steps with the segment
    compiled for the original, and its trajectory is the original's shifted by d
    (translation invariance; only rounding at the larger coordinates differs)."""
    from jaxgran import simulate as sim

    parts, walls, params, grid = pile
    counted = eqx.debug.assert_max_traces(sim.run_segment.__wrapped__, max_traces=1)
    jitted = eqx.filter_jit(counted)

    def run(parts, walls, grid):
        state, err0 = sim.prepare(make_state(parts, walls, pair_capacity=400), params, grid)
        state, _, err = jitted(state, params, grid, 16, 500)
        assert int(err0) == 0 and int(err) == 0
        return state

    a = run(parts, walls, grid)
    d = np.array([0.25, -0.5])
    moved = Grid(
        origin=grid.origin + d,
        cell_size=1.1 * grid.cell_size,
        nx=grid.nx,
        ny=grid.ny,
        cell_capacity=grid.cell_capacity,
    )
    b = run(replace(parts, pos=parts.pos + d), replace(walls, point=walls.point + d), moved)
    # after 8,000 steps the grains have landed and collide (they spin): rounding at the
    # larger coordinates, amplified by the collisions, measured 8e-13 m in the positions and
    # 7e-10 and 3e-9 of the largest speed and spin
    speed = float(np.max(np.abs(np.asarray(a.particles.vel))))
    spin = float(np.max(np.abs(np.asarray(a.particles.omega))))
    assert speed > 0.05 and spin > 1.0
    np.testing.assert_allclose(np.asarray(b.particles.pos) - d, a.particles.pos, atol=1e-11)
    np.testing.assert_allclose(b.particles.vel, a.particles.vel, atol=1e-7 * speed)
    np.testing.assert_allclose(b.particles.omega, a.particles.omega, atol=1e-7 * spin)
    np.testing.assert_array_equal(b.contacts.pairs, a.contacts.pairs)


@pytest.fixture(scope="module")
def rested_pile(pile):
    """The fixture pile after 20,000 steps (0.16 s): landed, kinetic energy 2e-13 J."""
    parts, walls, params, grid = pile
    return _run_pile(parts, walls, params, grid, 20_000).state, params, grid


def _spring_only_step(parts, params) -> float:
    """The fixture's step under the rule before the dashpots counted (s): 0.2 x the springs'
    two-body limit ``sqrt(2 m_min / K_n)``, 4.5 times the present step."""
    from jaxgran.integrate import critical_time_step

    return 0.2 * critical_time_step(parts, params, dashpots=False)


def _hold(rested_pile, dt: float) -> tuple[dict, float]:
    """The rested pile held for 1,000 steps of ``dt`` with the energy ledger: the balance
    and the energy held at the start (J)."""
    from jaxgran import energy
    from jaxgran.simulate import run_segment

    state, params, grid = rested_pile
    params = replace(params, dt=jnp.asarray(dt))
    s = energy.attach(state, params, grid)
    for _ in range(2):  # segments of 500 steps: one compilation for every dt
        s, _, err = run_segment(s, params, grid, 1, 500)
        assert int(err) == 0
    return energy.balance(s, params), float(s.energy.stored0)


def test_a_pile_at_rest_dissipates_no_more_than_it_was_given(rested_pile):
    """Held at rest, a pile cannot dissipate more than gravity's work on it plus the
    kinetic and elastic energy it held at the start: more would be energy created by the
    scheme. At the fixture's step (0.3 x :func:`critical_time_step`, springs and dashpots)
    it holds (measured: 7.5e-13 J dissipated against 1.25e-6 J); at the step of the
    springs-only rule the dashpots drive an oscillation at the scheme's Nyquist frequency
    and the same hold books 2.1e-4 J against 4.7e-6 J (docs/stability.md)."""
    state, params, grid = rested_pile
    b, stored0 = _hold(rested_pile, float(params.dt))
    assert b["dissipated"] <= b["input"] + stored0, b
    b, stored0 = _hold(rested_pile, _spring_only_step(state.particles, params))
    assert b["dissipated"] > 10 * (b["input"] + stored0), b


def test_linearised_step_of_the_rested_pile_is_stable_at_the_fixture_step(rested_pile):
    """The step linearised about the rested pile (:func:`jaxgran.integrate.linear_step_radius`):
    at the fixture's step the dashpots add no growth to the undamped step's and the one-mode
    criterion is below 1 (measured: radius 0.9992 against 1 + 9e-15 undamped, criterion
    0.70); at the springs-only rule's step they amplify every step (radius 4.2, criterion
    3.2)."""
    from jaxgran.integrate import linear_step_radius

    state, params, _ = rested_pile
    r = linear_step_radius(state, params)
    assert r["criterion"] < 1.0
    assert r["radius"] <= r["radius_without_dashpots"] + 1e-9
    r = linear_step_radius(state, params, dt=_spring_only_step(state.particles, params))
    assert r["criterion"] > 1.0 and r["radius"] > 1.5


def test_bad_grid_is_refused():
    for kw, match in (
        ({"origin": (0.0,), "cell_size": 0.1}, "origin must be two finite numbers"),
        ({"origin": (0.0, float("inf")), "cell_size": 0.1}, "origin must be two finite numbers"),
        ({"origin": (0.0, 0.0), "cell_size": 0.0}, "cell size must be one positive"),
        ({"origin": (0.0, 0.0), "cell_size": float("nan")}, "cell size must be one positive"),
    ):
        with pytest.raises(ValueError, match=match):
            Grid(nx=2, ny=2, cell_capacity=4, **kw)


def test_pile_settles_and_floor_carries_the_weight():
    parts, walls, params, grid = _pile(n_cells=30, seed=5, wall_friction=0.0)
    state = make_state(parts, walls, pair_capacity=200)
    peak = [0.0]

    def settled(s, rec):
        peak[0] = max(peak[0], float(rec["kinetic_energy"].max()))
        return s, bool(rec["kinetic_energy"][-1] < 1e-6 * peak[0] and rec["time"][-1] > 0.05)

    res = simulate(
        state,
        params,
        grid,
        n_steps=400_000,
        record_every=200,
        records_per_segment=10,
        callback=settled,
        progress=False,
    )
    assert res.stopped_early, "kinetic energy did not decay below 1e-6 of its peak"
    weight = float(jnp.sum(parts.mass) * 9.81)
    floor = -float(np.mean(res.series["wall_force"][-3:, 0, 1]))
    assert floor == pytest.approx(weight, rel=0.01)


def test_nan_in_the_state_stops_the_run_with_advice(pile):
    parts, walls, params, grid = pile
    bad = replace(parts, vel=parts.vel.at[0, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="NaN"):
        make_state(bad, walls)
    state = make_state(parts, walls, pair_capacity=400)
    state = replace(state, particles=replace(state.particles, vel=bad.vel))
    with pytest.raises(SimulationError, match="NaN"):  # the fixture runs' segment layout
        simulate(
            state,
            params,
            grid,
            n_steps=500,
            record_every=100,
            records_per_segment=5,
            progress=False,
        )


@pytest.mark.parametrize(
    "bad",
    [
        {"n_steps": 0},
        {"n_steps": -5},
        {"n_steps": 10.5},
        {"record_every": 0},
        {"records_per_segment": 0},
        {"frame_every": 0},
        {"checkpoint_every_s": -1.0},
        {"checkpoint_every_s": float("nan")},
    ],
)
def test_bad_run_lengths_are_refused_before_anything_runs(bad):
    """A zero segment length used to divide by zero and a non-positive n_steps ran one
    segment silently."""
    parts, walls, params, grid = _pile()
    args = {"n_steps": 100, "progress": False} | bad
    with pytest.raises(ValueError, match=next(iter(bad))):
        simulate(make_state(parts, walls, pair_capacity=64), params, grid, **args)


def test_escaping_particle_is_reported(pile):
    parts, walls, params, grid = pile
    # a particle above the pile flying up out of the domain (grid top at y = 0.13 m)
    fast = replace(
        parts,
        pos=parts.pos.at[-1].set(jnp.array([0.04, 0.115])),
        vel=parts.vel.at[-1].set(jnp.array([0.0, 2.0])),
    )
    state = make_state(fast, walls, pair_capacity=400)
    with pytest.raises(SimulationError, match="left the simulation domain"):
        simulate(  # the fixture runs' segment layout: their compiled segment serves
            state,
            params,
            grid,
            n_steps=20_000,
            record_every=100,
            records_per_segment=5,
            progress=False,
        )


@pytest.mark.parametrize(
    "polys, radius, match",
    [
        ([np.array([[0, 0], [1, 0], [1, 1], [0.5, 0.2], [0, 1]])], 0.0, "convex"),
        ([np.array([[0, 0], [1, 1], [1, 0], [0, 1]])], 0.0, "intersect"),
        ([np.array([[0.0, 0.0], [1.0, 0.0]])], 0.0, "at least 3 vertices"),
        ([geo.regular_polygon(4, 1.0)], -1.0, "sphero-radius"),
        ([np.array([[0.0, np.nan], [1, 0], [0, 1]])], 0.0, "NaN"),
    ],
)
def test_bad_particles_are_refused(polys, radius, match):
    with pytest.raises(ValueError, match=match):
        particles_from_polygons(polys, radius, RHO)


def test_zero_density_is_refused():
    with pytest.raises(ValueError, match="density"):
        particles_from_polygons([geo.regular_polygon(4, 1.0)], 0.1, 0.0)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="dt"):
        make_params(dt=-1.0)
    with pytest.raises(ValueError, match="friction"):
        make_params(friction=-0.1)


def _servo_block():
    """A 2 cm square block (sphero-radius 1 mm) and contact parameters for the servo tests:
    (h, r, k, particles, mass, width of the box, params, thickness)."""
    h, r, k = 0.02, 1e-3, 2e4
    block = np.array([[0, 0], [h, 0], [h, h], [0, h]], dtype=float) + [0.03, r]
    parts = particles_from_polygons([block], r, RHO)
    m = float(parts.mass[0])
    width = 0.08
    params = make_params(
        normal_stiffness=k,
        tangential_stiffness=k,
        friction=0.5,
        normal_damping=damping_from_restitution(0.1, k, m),
        tangential_damping=damping_from_restitution(0.1, k, m),
        skin=1e-3,
    )
    # 0.25 x the one-contact limit: two contacts on the floor and two under the lid damp the
    # block about 4 times as much as one contact; the linearised step of the loaded block is
    # then at 0.70 of its stability criterion (1.41 at 0.5, radius 1.57)
    params = replace(params, dt=jnp.asarray(stable_time_step(parts, params, 0.25)))
    thickness = float(params.thickness)
    return h, r, k, parts, m, width, params, thickness


def test_servo_wall_holds_target_stress_and_bar_moves_at_its_velocity():
    from jaxgran.state import WALL_SERVO, WALL_VELOCITY, wall

    h, r, _, parts, m, width, params, thickness = _servo_block()
    target = 40.0  # Pa over width x thickness: 3.2 N, ~10x the block's weight
    walls = make_walls(
        box_walls((0.0, 0.0), (width, 0.12), top=False)
        + [
            wall(
                (0.0, h + 2 * r + 2e-3),
                (0.0, -1.0),
                mode=WALL_SERVO,
                target_stress=target,
                servo_gain=2e-4,
                max_speed=0.05,
                length=width,
            ),
            wall((-0.005, 0.0), (1.0, 0.0), mode=WALL_VELOCITY, velocity=(0.0, 0.01)),
        ]
    )
    grid = make_grid((-0.01, -0.01), (width + 0.01, 0.13), float(parts.bound_radius[0]), 1e-3)
    state = make_state(parts, walls, pair_capacity=4)
    res = simulate(
        state,
        params,
        grid,
        n_steps=128_000,
        record_every=3_200,
        records_per_segment=10,
        progress=False,
    )
    wf = res.series["wall_force"]
    stress = wf[:, 3, 1] / (width * thickness)  # the block pushes the lid up (+y)
    assert np.mean(stress[-3:]) == pytest.approx(target, rel=0.01)
    # momentum balance: the floor carries the lid's load plus the weight
    floor = -np.mean(wf[-3:, 0, 1])
    assert floor == pytest.approx(target * width * thickness + m * 9.81, rel=0.01)
    # the velocity-driven wall moved at its prescribed speed
    pts = res.series["wall_point"][:, 4]
    t = res.series["time"]
    assert (pts[-1, 1] - pts[0, 1]) / (t[-1] - t[0]) == pytest.approx(0.01, rel=1e-9)


def test_full_contact_list_grows_with_the_pair_capacity():
    """A square pressed into a box corner touches the floor and the wall with three vertex
    slots; with a pair capacity of 1 the compacted contact list (2 x pair capacity) is full,
    the host grows it and the run equals one with ample capacity."""
    side, r = 0.01, 5e-4
    core = np.array([[0, 0], [side, 0], [side, side], [0, side]], float) + r - 1e-5
    parts = particles_from_polygons([core], r, RHO)
    params = make_params(normal_stiffness=2e4, tangential_stiffness=1e4, friction=0.3)
    params = replace(params, dt=jnp.asarray(0.2 * stable_time_step(parts, params)))
    walls = make_walls(box_walls((0.0, 0.0), (0.05, 0.05)))
    grid = make_grid((-0.01, -0.01), (0.06, 0.06), float(parts.bound_radius[0]), 2e-3)
    kw = dict(n_steps=200, record_every=50, records_per_segment=2, progress=False)
    small = simulate(make_state(parts, walls, pair_capacity=1), params, grid, **kw)
    ample = simulate(make_state(parts, walls, pair_capacity=64), params, grid, **kw)
    assert any("pair capacity 1 exceeded" in msg for msg in small.regrows)
    assert not ample.regrows
    np.testing.assert_allclose(
        np.asarray(small.state.particles.pos), np.asarray(ample.state.particles.pos), atol=1e-12
    )
    # the overlapped side wall pushes the square out
    assert float(small.state.particles.pos[0, 0]) > float(parts.pos[0, 0])


@pytest.mark.parametrize("integral", [False, True])
def test_servo_integral_term_removes_the_offset_of_a_moving_specimen(integral):
    """A block rides up on a floor that moves at v; the servo lid must retreat at v. The
    proportional servo does so only at the stress offset v / g (its steady state); with the
    integral term (T_i = 4 loop time constants) the lid holds the target itself."""
    from jaxgran.state import WALL_SERVO, WALL_VELOCITY, wall

    g, v = 2e-4, 2e-3  # servo gain (m/(s Pa)), floor speed (m/s)
    h, r, k, parts, _, width, params, thickness = _servo_block()
    tau = width * thickness / (g * k)  # the loop's time constant against the block (s)
    target = 40.0  # Pa
    walls = make_walls(
        [
            wall((0.0, 0.0), (0.0, 1.0), mode=WALL_VELOCITY, velocity=(0.0, v), length=width),
            wall(
                (0.0, h + 2 * r + 2e-3),
                (0.0, -1.0),
                mode=WALL_SERVO,
                target_stress=target,
                servo_gain=g,
                max_speed=0.05,
                length=width,
                servo_time=4.0 * tau if integral else np.inf,
            ),
        ]
    )
    grid = make_grid((-0.01, -0.01), (width + 0.01, 0.3), float(parts.bound_radius[0]), 1e-3)
    res = simulate(
        make_state(parts, walls, pair_capacity=4),
        params,
        grid,
        n_steps=192_000,
        record_every=3_200,
        records_per_segment=10,
        progress=False,
    )
    stress = res.series["wall_force"][:, 1, 1] / (width * thickness)
    expected = target if integral else target + v / g  # 40 or 50 Pa
    assert np.mean(stress[-10:]) == pytest.approx(expected, rel=0.01)
    # the lid retreats with the floor
    pts = res.series["wall_point"][:, 1, 1]
    t = res.series["time"]
    assert (pts[-1] - pts[-11]) / (t[-1] - t[-11]) == pytest.approx(v, rel=0.02)


def test_bad_servo_time_is_refused():
    from jaxgran.state import wall

    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="servo_time"):
            wall((0.0, 0.0), (0.0, 1.0), servo_time=bad)


def test_resume_refuses_a_checkpoint_of_another_segment_layout(pile):
    """A payload saved by a run of other length or segment size would silently shift the
    records: refused before any step."""
    parts, walls, params, grid = pile
    state = make_state(parts, walls, pair_capacity=400)
    payload = {"n_seg": 5, "seg_steps": 100}
    with pytest.raises(ValueError, match="checkpoint was taken in a run of 5 segments"):
        simulate(state, params, grid, n_steps=1000, record_every=10, records_per_segment=10,
                 resume=payload, progress=False)  # fmt: skip
