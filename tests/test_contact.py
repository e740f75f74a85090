"""Contact geometry and law: Newton's third law, invariances, corner double counting."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import geometry as geo
from jaxgran.contact import closest_features, damping_from_restitution, pair_forces
from jaxgran.partition import make_grid
from jaxgran.simulate import prepare
from jaxgran.state import (
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
)


def _forces(polys, radius=1e-3, params=None, perm=None):
    params = params or make_params(gravity=(0.0, 0.0), friction=0.5, dt=1e-6)
    parts = particles_from_polygons(polys, radius, 12.0, vertex_capacity=8)
    state = make_state(parts, make_walls([]), pair_capacity=64)
    # one domain for every scene that fits in it: the grid's origin and cell size are static
    # (a moved domain recompiles), so scenes of equal particle sizes share one compilation
    lo = np.minimum(np.min([np.min(p, axis=0) for p in polys], axis=0) - 0.1, -0.5)
    hi = np.maximum(np.max([np.max(p, axis=0) for p in polys], axis=0) + 0.1, 0.5)
    grid = make_grid(tuple(lo), tuple(hi), float(jnp.max(parts.bound_radius)), 2e-3)
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    return state


def _packing(seed=0):
    """A few overlapping pentagons/hexagons around the origin (static configuration)."""
    rng = np.random.default_rng(seed)
    polys = []
    centers = [(0, 0), (0.021, 0.002), (-0.002, 0.0205), (0.02, 0.022), (-0.0215, -0.003)]
    for k, c in enumerate(centers):
        polys.append(
            geo.regular_polygon(5 + k % 3, 0.011, rotation=rng.uniform(0, 2 * np.pi), center=c)
        )
    return polys


def test_newton_third_law_and_zero_net_torque():
    state = _forces(_packing())
    p = state.particles
    f, t = np.asarray(p.force), np.asarray(p.torque)
    assert np.abs(f).max() > 1.0, "the test scene must have contacts"
    # internal forces sum to zero; so does the total moment about any point
    scale = np.abs(f).max()
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-12 * scale)
    x = np.asarray(p.pos)
    moment = np.sum(x[:, 0] * f[:, 1] - x[:, 1] * f[:, 0]) + t.sum()
    assert abs(moment) < 1e-12 * scale


def test_forces_rotate_and_translate_with_the_scene():
    polys = _packing(1)
    phi = 0.7
    rot = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    shift = np.array([0.3, -0.2])
    a = _forces(polys).particles
    b = _forces([q @ rot.T + shift for q in polys]).particles
    np.testing.assert_allclose(
        np.asarray(b.force), np.asarray(a.force) @ rot.T, atol=1e-9 * np.abs(a.force).max()
    )
    np.testing.assert_allclose(np.asarray(b.torque), np.asarray(a.torque), atol=1e-12)


def test_forces_permute_with_particle_order():
    polys = _packing(2)
    perm = np.array([3, 0, 4, 1, 2])
    a = _forces(polys).particles
    b = _forces([polys[k] for k in perm]).particles
    np.testing.assert_allclose(np.asarray(b.force), np.asarray(a.force)[perm], atol=1e-12)
    np.testing.assert_allclose(np.asarray(b.torque), np.asarray(a.torque)[perm], atol=1e-14)


def test_aligned_squares_edge_contact_has_twice_not_four_times_the_stiffness():
    # two unit-ish squares stacked exactly, corners coinciding, overlap delta
    h, r, delta = 0.01, 1e-3, 1e-5
    sq = np.array([[0, 0], [h, 0], [h, h], [0, h]], dtype=float)
    top = sq + [0.0, h + 2 * r - delta]
    k_n = 6e5
    params = make_params(normal_stiffness=k_n, gravity=(0, 0), dt=1e-6, friction=0.0)
    state = _forces([sq, top], radius=r, params=params)
    f = np.asarray(state.particles.force)
    # two contacts (one per corner column), each k_n * delta
    np.testing.assert_allclose(f[1], [0.0, 2 * k_n * delta], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f[0], -f[1], rtol=1e-12)


def test_offset_squares_edge_contact_acts_at_overlap_ends():
    h, r, delta = 0.01, 1e-3, 2e-5
    sq = np.array([[0, 0], [h, 0], [h, h], [0, h]], dtype=float)
    top = sq + [0.4 * h, h + 2 * r - delta]
    k_n = 1e5
    params = make_params(normal_stiffness=k_n, gravity=(0, 0), dt=1e-6, friction=0.0)
    state = _forces([sq, top], radius=r, params=params)
    f = np.asarray(state.particles.force)
    t = np.asarray(state.particles.torque)
    np.testing.assert_allclose(f[1], [0.0, 2 * k_n * delta], rtol=1e-9, atol=1e-12)
    # contacts at x = 0.4h (top's corner) and x = h (bottom's corner); top centroid at 0.9h
    xs = np.array([0.4 * h, h])
    torque_top = np.sum((xs - 0.9 * h) * k_n * delta)
    np.testing.assert_allclose(t[1], torque_top, rtol=1e-9, atol=1e-15)


def test_disc_disc_contact_counted_once():
    r1, r2, delta = 0.01, 0.02, 1e-5
    a = np.array([[0.0, 0.0]])
    b = np.array([[r1 + r2 - delta, 0.0]])
    parts = particles_from_polygons([a, b], [r1, r2], 12.0)
    params = make_params(normal_stiffness=1e5, gravity=(0, 0), dt=1e-6)
    state = make_state(parts, make_walls([]), pair_capacity=4)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.02, 1e-3)
    state, _ = prepare(state, params, grid)
    f = np.asarray(state.particles.force)
    np.testing.assert_allclose(f[1], [1e5 * delta, 0.0], rtol=1e-9, atol=1e-15)


def test_closest_feature_classification():
    sq = jnp.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    pts = jnp.array([[0.5, -0.1], [-0.1, -0.1], [1.2, 0.5], [0.5, 0.1]])
    gap, normal, q, vert, ok = closest_features(pts, 4, sq, 4)
    np.testing.assert_allclose(gap, [0.1, np.sqrt(0.02), 0.2, -0.1], atol=1e-12)
    np.testing.assert_array_equal(vert, [-1, 0, -1, -1])
    np.testing.assert_allclose(normal[0], [0, -1], atol=1e-12)
    np.testing.assert_allclose(normal[1], [-1 / np.sqrt(2), -1 / np.sqrt(2)], atol=1e-12)


def test_damping_from_restitution_limits():
    assert damping_from_restitution(1.0, 1e5, 1e-3) == 0.0
    with pytest.raises(ValueError, match="restitution"):
        damping_from_restitution(0.0, 1e5, 1e-3)


def test_pair_forces_are_nan_free_with_padding_and_touching():
    # exactly touching particles (zero overlap) and padded slots must not produce NaN
    r = 1e-3
    a = geo.regular_polygon(4, 0.01)
    b = a + [0.0, np.ptp(a[:, 1]) + 2 * r]
    parts = particles_from_polygons([a, b], r, 12.0, capacity=4, vertex_capacity=6)
    params = make_params(gravity=(0, 0), dt=1e-6)
    state = make_state(parts, make_walls([]), pair_capacity=8)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.02, 2e-3)
    state, _ = prepare(state, params, grid)
    f, t, xi, info = pair_forces(state.particles, state.contacts, params)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(t)) and np.all(np.isfinite(xi))


@pytest.mark.parametrize("fraction", [0.0, 0.05, 0.5, 1.0])
def test_compaction_matches_nonzero(fraction):
    """The matmul prefix sum that compacts the touching slots is exact: the same indices as
    jnp.nonzero, in order, padded with the size sentinel, and the full count even when the
    list is too short (the overflow the host grows on)."""
    from jaxgran.contact import _compact

    rng = np.random.default_rng(1)
    flags = jnp.asarray(rng.random(5000) < fraction)
    size = 300
    idx, count = _compact(flags, size)
    want = jnp.nonzero(flags, size=size, fill_value=flags.size)[0]
    np.testing.assert_array_equal(np.asarray(idx), np.asarray(want))
    assert int(count) == int(np.sum(np.asarray(flags)))


def _corner_state(phi, x, h=0.01, r=1e-3, k_n=1e5):
    """Two squares whose corners meet: B (turned by ``phi``) sits up and to the right of A
    with its corner at (h + x, h + 1.7 r), 0.3 r of overlap with A's corner (h, h)."""
    from jaxgran import energy

    params = make_params(normal_stiffness=k_n, gravity=(0.0, 0.0), friction=0.0, dt=1e-6)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.02, 2e-3)
    a = np.array([[0, 0], [h, 0], [h, h], [0, h]], float)
    c, s = np.cos(phi), np.sin(phi)
    b = a @ np.array([[c, -s], [s, c]]).T + [h + x, h + 1.7 * r]
    parts = particles_from_polygons([a, b], r, 12.0, vertex_capacity=4)
    state, err = prepare(make_state(parts, make_walls([]), pair_capacity=8), params, grid)
    assert int(err) == 0

    def at(dx=0.0, dy=0.0, dtheta=0.0):
        p = state.particles
        moved = replace(
            p, pos=p.pos.at[1].add(jnp.array([dx, dy])), angle=p.angle.at[1].add(dtheta)
        )
        st, e = prepare(replace(state, particles=moved), params, grid)
        assert int(e) == 0
        return st, energy.stored_energy(st, params)["contact"]

    return at


@pytest.mark.parametrize("phi", [0.0, 0.2, -0.2])
def test_contact_energy_is_continuous_and_conservative_where_two_corners_meet(phi):
    """A corner sliding past another corner: every vertex keeps its contact, weighted so that
    the pair counts once (``contact.corner_weight``). Counting the pair once by a discrete
    rule made the energy jump by ``K_n delta^2 / 2`` as the corners passed (the bonded
    Brazilian of seed 0 gained 2.7 % of its input before any bond broke). The energy must
    vary smoothly along the path, and the force and torque on B must be minus its gradient
    (central differences), also at the corners' crossing."""
    r, k_n = 1e-3, 1e5
    jump = 0.5 * k_n * (0.3 * r) ** 2  # what one spurious contact stores
    xs = np.linspace(-0.5 * r, 0.5 * r, 61)
    energies = np.array([_corner_state(phi, x)()[1] for x in xs])
    # a jump shows in the second differences at its full size; a smooth energy gives
    # K (dx)^2, 0.6 % of the jump here
    assert np.abs(np.diff(energies, 2)).max() < 0.03 * jump
    eps = 1e-8
    for x in (-0.2 * r, -0.01 * r, 0.0, 0.01 * r, 0.2 * r):
        at = _corner_state(phi, x)
        st, _ = at()
        f = np.asarray(st.particles.force)[1]
        tq = float(np.asarray(st.particles.torque)[1])
        grad = [
            (at(dx=eps)[1] - at(dx=-eps)[1]) / (2 * eps),
            (at(dy=eps)[1] - at(dy=-eps)[1]) / (2 * eps),
        ]
        dtheta = eps / 0.01
        g_rot = (at(dtheta=dtheta)[1] - at(dtheta=-dtheta)[1]) / (2 * dtheta)
        scale = k_n * 0.3 * r
        np.testing.assert_allclose(f, -np.array(grad), atol=1e-5 * scale)
        assert tq == pytest.approx(-g_rot, abs=1e-5 * scale * 0.01)


def test_wall_friction_can_differ_per_wall():
    """A square pressed into a floor and a side wall and sliding along both: each wall's
    tangential force is its own mu times its normal force; a scalar mu equals the same mu
    given per wall."""
    from jaxgran.contact import wall_forces
    from jaxgran.state import wall

    sq = geo.regular_polygon(4, 1.0e-3 * np.sqrt(2.0), rotation=np.pi / 4, center=(1.4e-3, 1.3e-3))
    parts = particles_from_polygons([sq], 1.0e-3, 2500.0, vertex_capacity=4)
    parts = replace(parts, vel=jnp.asarray([[-0.5, -0.4]]))  # 0.5 mm / step along each wall
    walls = make_walls([wall((0.0, 0.0), (0.0, 1.0)), wall((0.0, 0.0), (1.0, 0.0))])
    xi = jnp.zeros((2, 1, 2, 4))
    out = {}
    for name, mu in {"per wall": (0.2, 0.6), "scalar": 0.3, "scalar per wall": (0.3, 0.3)}.items():
        params = make_params(
            gravity=(0.0, 0.0),
            normal_stiffness=1.0e6,
            tangential_stiffness=1.0e6,
            friction=0.9,
            wall_friction=mu,
            dt=1.0e-3,
        )
        out[name] = np.asarray(wall_forces(parts, walls, xi, params)[3])
    f = out["per wall"]  # force on each wall [W, 2]: floor (n = +y), side wall (n = +x)
    assert f[0, 1] < 0 and f[1, 0] < 0  # pressed into both
    np.testing.assert_allclose(abs(f[0, 0]), 0.2 * abs(f[0, 1]), rtol=1e-12)
    np.testing.assert_allclose(abs(f[1, 1]), 0.6 * abs(f[1, 0]), rtol=1e-12)
    np.testing.assert_array_equal(out["scalar"], out["scalar per wall"])
    with pytest.raises(ValueError, match="wall_friction"):
        make_params(wall_friction=(0.2, -0.1))
    with pytest.raises(ValueError, match="3 values for 2 walls"):
        wall_forces(parts, walls, xi, make_params(wall_friction=(0.2, 0.3, 0.4)))
