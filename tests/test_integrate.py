"""Integrator physics: conservation, convergence order, restitution, friction on an incline."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import geometry as geo
from jaxgran.contact import damping_from_restitution, pair_forces
from jaxgran.integrate import check_time_step, critical_time_step, stable_time_step
from jaxgran.partition import make_grid
from jaxgran.simulate import prepare, run_segment
from jaxgran.state import (
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
    wall,
)

RHO = 12.0  # kg/m^2, paper 000 Table I (1.2 g/cm^2)


def _momenta(p):
    m, i = np.asarray(p.mass), np.asarray(p.inertia)
    x, v, w = np.asarray(p.pos), np.asarray(p.vel), np.asarray(p.omega)
    lin = (m[:, None] * v).sum(axis=0)
    ang = np.sum(m * (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0]) + i * w)
    ke = 0.5 * np.sum(m * (v**2).sum(axis=1) + i * w**2)
    return lin, ang, ke


def _collision(dt_factor, friction, n_steps_contact=None):
    """Two pentagons in an oblique collision; returns (initial, final) momenta/energy."""
    a = geo.regular_polygon(5, 0.01, rotation=0.1)
    b = geo.regular_polygon(6, 0.012, rotation=0.4, center=(0.035, 0.006))
    parts = particles_from_polygons(
        [a, b], 1e-3, RHO, vertex_capacity=6, velocities=[[1.0, 0.0], [-0.5, 0.1]]
    )
    parts = replace(parts, omega=jnp.array([3.0, -2.0]))
    params = make_params(
        normal_stiffness=6e5, tangential_stiffness=2.2e4, friction=friction, gravity=(0, 0)
    )
    dt = stable_time_step(parts, params, safety=dt_factor)
    params = replace(params, dt=jnp.asarray(dt))
    state = make_state(parts, make_walls([]), pair_capacity=4)
    grid = make_grid((-0.2, -0.2), (0.25, 0.2), float(jnp.max(parts.bound_radius)), 2e-3)
    state, _ = prepare(state, params, grid)
    t_end = 0.03  # contact starts at ~0.011 s and lasts < 1 ms
    n = int(round(t_end / dt))
    n_rec = 10
    per = -(-n // n_rec)
    final, _, err = run_segment(state, params, grid, n_rec, per)
    assert int(err) == 0
    return _momenta(state.particles), _momenta(final.particles), final


@pytest.mark.parametrize("friction", [0.0, 0.5])
def test_collision_conserves_momentum(friction):
    (l0, a0, _), (l1, a1, _), final = _collision(0.1, friction)
    assert np.linalg.norm(l1 - l0) <= 1e-10 * np.linalg.norm(l0)
    assert abs(a1 - a0) <= 1e-10 * abs(a0)
    # the collision did happen: both bodies changed velocity
    v = np.asarray(final.particles.vel)
    assert abs(v[0, 0] - 1.0) > 0.1


def test_frictionless_collision_restores_kinetic_energy():
    (_, _, e0), (_, _, e1), _ = _collision(0.1, 0.0)
    assert abs(e1 - e0) / e0 < 0.01


def _energy_during_contact(n_steps):
    """Square and pentagon touching at t = 0 (zero overlap), oblique and spinning, run to a
    fixed time inside the contact; returns kinetic + elastic energy relative error."""
    h, r, big_r, k = 0.01, 1e-3, 0.009, 6e5
    a = np.array([[-h, -h], [h, -h], [h, h], [-h, h]], dtype=float) / 2
    b = geo.regular_polygon(5, big_r, rotation=-np.pi / 2, center=(0.002, h / 2 + 2 * r + big_r))
    parts = particles_from_polygons([a, b], r, RHO, velocities=[[0.1, 0.2], [-0.1, -0.6]])
    parts = replace(parts, omega=jnp.array([1.0, 5.0]))
    params = make_params(normal_stiffness=k, friction=0.0, gravity=(0, 0))
    t_end = 1.0e-4  # the contact lasts ~2.5e-4 s
    params = replace(params, dt=jnp.asarray(t_end / n_steps))
    state = make_state(parts, make_walls([]), pair_capacity=4)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.012, 2e-3)
    state, _ = prepare(state, params, grid)
    final = state
    for _ in range(n_steps // 25):  # segments of 25 steps: one compilation for every dt
        final, _, err = run_segment(final, params, grid, 1, 25)
        assert int(err) == 0
    _, _, ke0 = _momenta(state.particles)
    _, _, ke1 = _momenta(final.particles)
    *_, info = pair_forces(final.particles, final.contacts, params)
    fn = np.asarray(info["normal_force"])
    assert fn.max() > 0, "still in contact at t_end"
    pe1 = 0.5 * np.sum(fn**2) / k
    return abs(ke1 + pe1 - ke0) / ke0


def test_energy_error_converges_at_order_two_in_dt():
    errors = np.array([_energy_during_contact(n) for n in (25, 50, 100)])
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all(orders > 1.8), (errors, orders)


@pytest.mark.parametrize("target", [0.9, 0.5, 0.1])
def test_restitution_matches_target(target):
    r = 0.01
    k = 1e5
    parts = particles_from_polygons(
        [np.array([[0.0, 0.0]]), np.array([[2 * r + 1e-4, 0.0]])],
        r,
        RHO,
        velocities=[[0.5, 0.0], [-0.5, 0.0]],
    )
    m = float(parts.mass[0])
    g_n = damping_from_restitution(target, k, m / 2)
    params = make_params(normal_stiffness=k, normal_damping=g_n, gravity=(0, 0), friction=0.0)
    dt = 0.02 * np.sqrt(m / k)
    params = replace(params, dt=jnp.asarray(dt))
    state = make_state(parts, make_walls([]), pair_capacity=2)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), r, 2e-3)
    state, _ = prepare(state, params, grid)
    n = int(0.02 / dt)
    final, _, err = run_segment(state, params, grid, 1, n)
    assert int(err) == 0
    v = np.asarray(final.particles.vel)
    e = (v[1, 0] - v[0, 0]) / 1.0
    assert e == pytest.approx(target, rel=0.02)


def incline_block(theta, mu):
    """A square block resting on a floor with gravity tilted by theta (== an incline), at
    its static overlap so it does not bounce: ``(state, params, grid, weight m g)``."""
    h, r, k = 0.01, 5e-4, 2e4
    block = np.array([[0, 0], [h, 0], [h, h], [0, h]], dtype=float) + [0.0, r]
    parts = particles_from_polygons([block], r, RHO)
    g = 9.81
    m = float(parts.mass[0])
    walls = make_walls([wall((0.0, 0.0), (0.0, 1.0))])
    params = make_params(
        normal_stiffness=k,
        tangential_stiffness=k,
        friction=mu,
        gravity=(g * np.sin(theta), -g * np.cos(theta)),
        normal_damping=damping_from_restitution(0.3, k, m),
        tangential_damping=damping_from_restitution(0.3, k, m),
    )
    dt = stable_time_step(parts, params, safety=0.1)
    params = replace(params, dt=jnp.asarray(dt))
    d0 = m * g * np.cos(theta) / (2 * k)
    parts = replace(parts, pos=parts.pos - jnp.array([0.0, d0]))
    state = make_state(parts, walls, pair_capacity=1)
    grid = make_grid((-0.5, -0.5), (3.0, 0.5), float(parts.bound_radius[0]), 2e-3)
    return state, params, grid, m * g


def _incline(theta, mu, t_end):
    state, params, grid, weight = incline_block(theta, mu)
    state, _ = prepare(state, params, grid)
    n = int(t_end / float(params.dt))
    final, rec, err = run_segment(state, params, grid, 20, -(-n // 20))
    assert int(err) == 0
    return state, final, rec, 9.81


def test_block_sticks_below_friction_angle():
    mu = 0.74
    state, final, _, _ = _incline(np.arctan(0.5), mu, 1.0)
    x0 = float(state.particles.pos[0, 0])
    # after the elastic tangential settle (mg sin / 2K_t ~ 1e-7 m) the block does not creep
    assert abs(float(final.particles.pos[0, 0]) - x0) < 1e-6


def test_block_slides_with_coulomb_acceleration():
    mu, theta = 0.3, np.arctan(0.6)
    _, final, rec, g = _incline(theta, mu, 0.3)
    t = np.asarray(rec.time)
    # acceleration from the centroid velocity between two late times (transient gone)
    v = float(final.particles.vel[0, 0])
    a_expected = g * (np.sin(theta) - mu * np.cos(theta))
    assert v / float(t[-1]) == pytest.approx(a_expected, rel=0.02)


def _bouncing_pentagon(damping: float, dt_fraction: float):
    """A pentagon resting on its flat face on a floor (two corner contacts, preloaded by a
    strong gravity so the springs stay compressed), kicked upwards at 1 um/s and run for
    1,000 steps at ``dt_fraction`` of the step at which its vertical mode
    ``y'' = -Omega^2 y - Gamma y'`` (``Omega^2 = 2 K_n / m``, ``Gamma = 2 G_n``: two
    contacts, ``m_e = m`` on a wall) leaves the scheme's stability region
    ``(Omega dt / 2)^2 + Gamma dt <= 1``. Returns the kinetic energy of every 25th step over
    the kick's, and the boundary step (s)."""
    k, g, v0 = 6e5, 1000.0, 1e-6
    core = geo.regular_polygon(5, 0.01, np.pi / 2)
    parts = particles_from_polygons([core], 1e-3, RHO, vertex_capacity=5)
    m = float(parts.mass[0])
    # resting overlap m g / (2 K_n) (2.6 um) against a step's travel of ~1e-10 m
    y = float(parts.pos[0, 1]) - float(core[:, 1].min()) + 1e-3 - m * g / (2 * k)
    parts = replace(parts, pos=parts.pos.at[0, 1].set(y), vel=parts.vel.at[0, 1].set(v0))
    # K_t / 10 and no tangential dashpot keep the sliding-rocking mode far from its limit
    params = make_params(
        normal_stiffness=k,
        tangential_stiffness=k / 10,
        normal_damping=damping,
        gravity=(0.0, -g),
    )
    omega2, gamma = 2 * k / m, 2 * damping
    boundary = 2 / (gamma + np.sqrt(gamma**2 + omega2))
    params = replace(params, dt=jnp.asarray(dt_fraction * boundary))
    state = make_state(parts, make_walls([wall((-0.05, 0.0), (0.0, 1.0), length=0.1)]))
    grid = make_grid((-0.06, -0.03), (0.06, 0.05), float(parts.bound_radius[0]), 2e-3)
    state, _ = prepare(state, params, grid)
    _, rec, err = run_segment(state, params, grid, 40, 25)
    assert int(err) == 0
    return np.asarray(rec.kinetic_energy) / (0.5 * m * v0**2), boundary, parts, params


@pytest.mark.parametrize("damping", [2e3, 1e4])  # Gamma dt at the boundary: 0.35, 0.85
def test_dashpot_stability_boundary_is_where_the_scheme_predicts(damping):
    """The dashpots see the end-of-step velocity predicted with the previous force, so for
    one mode the step is stable for ``(Omega dt / 2)^2 + Gamma dt <= 1`` (with ``Gamma = 0``,
    Verlet's ``Omega dt <= 2``; docs/stability.md). 5 % below that step the kick dies out
    (measured: the kinetic energy falls below 4e-9 of the kick's within 25 steps), 5 %
    above it grows (measured: 1e4 and 6e5 times the kick's, until the grain hops), and the
    bound of :func:`critical_time_step` (one contact at the worst lever arm) lies below."""
    below, boundary, parts, params = _bouncing_pentagon(damping, 0.95)
    assert below.max() < 1e-6
    above, _, _, _ = _bouncing_pentagon(damping, 1.05)
    assert above.max() > 1e3
    assert critical_time_step(parts, params) < boundary


def test_time_step_limit_is_enforced():
    parts = particles_from_polygons([geo.regular_polygon(5, 0.01)], 1e-3, RHO)
    params = make_params(normal_stiffness=6e5)
    crit = critical_time_step(parts, params)
    check_time_step(parts, replace(params, dt=jnp.asarray(0.5 * crit)))
    with pytest.raises(ValueError, match="stability limit"):
        check_time_step(parts, replace(params, dt=jnp.asarray(1.01 * crit)))


def test_float32_state_stays_float32_and_finite():
    # float32 must work too (benchmarks report both): no silent promotion to float64
    a = geo.regular_polygon(5, 0.01)
    b = geo.regular_polygon(5, 0.01, center=(0.0205, 0.0))
    parts = particles_from_polygons([a, b], 1e-3, RHO, dtype=jnp.float32)
    params = make_params(dtype=jnp.float32, gravity=(0, 0))
    params = replace(params, dt=jnp.float32(stable_time_step(parts, params)))
    state = make_state(parts, make_walls([], dtype=jnp.float32), pair_capacity=2)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.012, 2e-3)
    state, _ = prepare(state, params, grid)
    final, _, err = run_segment(state, params, grid, 2, 50)
    leaves = [x for x in jax.tree_util.tree_leaves(final) if jnp.issubdtype(x.dtype, jnp.floating)]
    assert all(x.dtype == jnp.float32 for x in leaves)
    assert int(err) == 0 and np.all(np.isfinite(np.asarray(final.particles.pos)))
