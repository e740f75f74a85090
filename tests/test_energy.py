"""Energy ledger (jaxgran.energy): each term against an analytic value, and the balance."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import energy
from jaxgran import geometry as geo
from jaxgran.bonds import make_bonds
from jaxgran.contact import damping_from_restitution
from jaxgran.integrate import stable_time_step
from jaxgran.interface import InterfaceBonds
from jaxgran.partition import make_grid
from jaxgran.simulate import prepare, run_segment
from jaxgran.state import (
    WALL_VELOCITY,
    make_params,
    make_state,
    make_walls,
    particles_from_polygons,
    replace,
    wall,
)

RHO = 12.0  # kg/m^2


def _run(state, params, grid, n_steps, n_rec=10, every=None):
    """``n_steps`` steps in one segment of ``n_rec`` records; with ``every`` given, segments
    of ``n_rec x every`` steps repeated until at least ``n_steps`` have run (runs of any dt
    then share one compilation)."""
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    state = energy.attach(state, params)
    start = final = state
    every = every or -(-n_steps // n_rec)
    for _ in range(-(-n_steps // (n_rec * every))):
        final, _, err = run_segment(final, params, grid, n_rec, every)
        assert int(err) == 0
    return start, final


def _collision(dt_factor):
    """Two discs colliding head-on with restitution 0.5; returns (start, final, params)."""
    r, k = 0.01, 1e5
    parts = particles_from_polygons(
        [np.array([[0.0, 0.0]]), np.array([[2 * r + 1e-4, 0.0]])],
        r,
        RHO,
        velocities=[[0.5, 0.0], [-0.5, 0.0]],
    )
    m = float(parts.mass[0])
    g_n = damping_from_restitution(0.5, k, m / 2)
    params = make_params(normal_stiffness=k, normal_damping=g_n, gravity=(0, 0), friction=0.0)
    params = replace(params, dt=jnp.asarray(dt_factor * np.sqrt(m / k)))
    state = make_state(parts, make_walls([]), pair_capacity=2)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), r, 2e-3)
    start, final = _run(state, params, grid, int(0.02 / float(params.dt)), every=50)
    return start, final, params


def test_dashpot_term_is_the_kinetic_energy_a_collision_loses():
    start, final, params = _collision(0.02)
    ke0 = float(energy.kinetic_energy(start))
    ke1 = float(energy.kinetic_energy(final))
    bal = energy.balance(final, params)
    # apart again: nothing stored, the relative speed is e = 0.5 times the initial one
    assert bal["contact"] == 0.0
    assert ke1 == pytest.approx(0.25 * ke0, rel=0.03)
    assert bal["dashpot"] == pytest.approx(ke0 - ke1, abs=1e-3 * ke0)
    assert bal["friction"] == 0.0 and bal["boundary_work"] == 0.0


def test_balance_residual_converges_at_order_two_in_dt():
    res = []
    for f in (0.04, 0.02, 0.01):
        start, final, params = _collision(f)
        res.append(abs(energy.balance(final, params)["residual"]))
    res = np.array(res) / float(energy.kinetic_energy(start))
    orders = np.log2(res[:-1] / res[1:])
    assert res[1] < 1e-3
    assert np.all(orders > 1.8), (res, orders)


def _slide(mu, theta, t_end):
    """The block on an incline of tests/test_integrate.py: (start, final, params, m g)."""
    from test_integrate import incline_block

    state, params, grid, weight = incline_block(theta, mu)
    start, final = _run(state, params, grid, int(t_end / float(params.dt)), n_rec=20)
    return start, final, params, weight


def test_friction_term_is_coulomb_force_times_sliding_distance():
    mu, theta = 0.3, np.arctan(0.6)
    start, final, params, weight = _slide(mu, theta, 0.3)
    dist = float(final.particles.pos[0, 0] - start.particles.pos[0, 0])
    assert dist > 0.05  # it slid
    bal = energy.balance(final, params)
    assert bal["friction"] == pytest.approx(mu * weight * np.cos(theta) * dist, rel=1e-3)
    # gravity's work is the drop in potential energy; the balance closes
    assert bal["body_work"] == pytest.approx(weight * np.sin(theta) * dist, rel=1e-3)
    assert abs(bal["residual"]) < 1e-3 * bal["input"]


def test_piston_work_is_stored_in_the_two_contacts():
    """A disc squeezed between a fixed floor and a slow piston (no gravity): the piston's
    work is stored as K d^2 / 4 (two equal contacts in series) plus a little dashpot loss."""
    r, k, speed = 0.01, 1e5, 0.01
    parts = particles_from_polygons([np.array([[0.0, r]])], r, RHO)
    m = float(parts.mass[0])
    walls = make_walls(
        [
            wall((0.0, 0.0), (0.0, 1.0)),
            wall((0.0, 2 * r), (0.0, -1.0), velocity=(0.0, -speed), mode=WALL_VELOCITY),
        ]
    )
    g_n = damping_from_restitution(0.3, k, m)
    params = make_params(normal_stiffness=k, normal_damping=g_n, gravity=(0, 0), friction=0.0)
    params = replace(params, dt=jnp.asarray(0.02 * np.sqrt(m / k)))
    state = make_state(parts, walls, pair_capacity=1)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), r, 2e-3)
    t_end = 0.05
    start, final = _run(state, params, grid, int(t_end / float(params.dt)))
    d = speed * float(final.time)
    bal = energy.balance(final, params)
    assert bal["boundary_work"] > 0
    assert bal["contact"] == pytest.approx(k * d**2 / 4, rel=0.01)
    assert bal["boundary_work"] == pytest.approx(bal["contact"] + bal["dashpot"], rel=1e-3)
    assert abs(bal["residual"]) < 1e-3 * bal["input"]


H, R, T = 0.01, 1e-3, 0.02  # cell size, sphero-radius, thickness (m)
BN = 2.0e7  # Pa


def _bonded_pair(eps_th, v0=0.05, width=0.0):
    cells = [
        np.array([[0, 0], [H, 0], [H, H], [0, H]], float),
        np.array([[H, 0], [2 * H, 0], [2 * H, H], [H, H]], float),
    ]
    cores = [geo.offset_polygon(c, R) for c in cells]
    parts = particles_from_polygons(cores, R, RHO, velocities=[[-v0, 0.0], [v0, 0.0]])
    bonds = make_bonds(
        cells,
        parts,
        thickness=T,
        b_n=BN,
        b_t=1.5e7,
        b_m=0.8e7,
        eps_th=eps_th,
        theta_th=1.0,
        surrogate_width=width,
    )
    m = float(parts.mass[0])
    k_bond = BN * float(bonds.area[0]) / float(bonds.length[0])
    omega = np.sqrt(2.0 * k_bond / m)
    params = make_params(gravity=(0.0, 0.0))
    dt = min(stable_time_step(parts, params), 2 * np.pi / omega / 400)
    params = replace(params, dt=jnp.asarray(dt))
    grid = make_grid((-0.02, -0.02), (0.05, 0.03), float(jnp.max(parts.bound_radius)), 2e-3)
    state = replace(make_state(parts, make_walls([]), pair_capacity=4), bonds=bonds)
    return state, params, grid, k_bond, dt


def test_breakage_term_is_the_bond_energy_at_the_break():
    eps_th, v0 = 2e-4, 0.05
    state, params, grid, k_bond, dt = _bonded_pair(eps_th, v0)
    start, final = _run(state, params, grid, 400)
    assert not bool(final.bonds.intact[0])
    bal = energy.balance(final, params)
    # the bond broke between openings delta_b and delta_b + 2 v0 dt; the loss is booked at
    # the mid-step opening (jaxgran.integrate._ledger_step)
    delta_b = eps_th * H
    lo, hi = 0.5 * k_bond * (delta_b - v0 * dt) ** 2, 0.5 * k_bond * (delta_b + v0 * dt) ** 2
    assert lo <= bal["breakage"] <= hi
    ke0 = float(energy.kinetic_energy(start))
    assert bal["kinetic"] == pytest.approx(ke0 - bal["breakage"], rel=1e-4)
    assert abs(bal["residual"]) < 1e-4 * ke0


def test_softening_bond_releases_what_the_balance_misses_without_it():
    """The smooth surrogate loses bond energy gradually; the breakage term books it, so
    kinetic + bond + released stays at the initial kinetic energy."""
    state, params, grid, _, _ = _bonded_pair(2e-4, 0.05, width=2.0)
    start, final = _run(state, params, grid, 600)
    bal = energy.balance(final, params)
    ke0 = float(energy.kinetic_energy(start))
    assert bal["breakage"] > 0.05 * ke0  # softening took a visible share
    assert abs(bal["residual"]) < 1e-3 * ke0


def test_attach_refuses_a_bond_model_it_cannot_account_for():
    state, params, grid, _, _ = _bonded_pair(2e-4)
    fake = object.__new__(InterfaceBonds)
    with pytest.raises(TypeError, match="not accounted"):
        energy.attach(replace(state, bonds=fake), params)


def test_balance_without_ledger_is_an_error():
    state, params, _, _, _ = _bonded_pair(2e-4)
    with pytest.raises(ValueError, match="attach"):
        energy.balance(state, params)


def test_control_books_background_damping_and_body_force_work():
    """A bonded pair under the bonded scenes' control: velocity damping and a constant pair
    of opposite body forces. The damping term is the kinetic energy the decay removes, the
    body work is F . dx of each cell, and the balance closes."""
    from jaxgran.scenes.bonded import make_control, run_segment

    state, params, grid, _, _ = _bonded_pair(1.0, v0=0.02)
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    state = energy.attach(state, params)
    force = np.array([[-0.5, 0.2], [0.5, -0.2]])  # N
    control = make_control(state, damping=5000.0, external_force=force)
    final, *_, err = run_segment(state, params, control, grid, 4, 100)
    assert int(err) == 0
    bal = energy.balance(final, params)
    dx = np.asarray(final.particles.pos - state.particles.pos)
    # the control applies the force as a velocity kick before each step and books the
    # kick's kinetic-energy change; that differs from F . dx by F . (v_half - v) dt per step,
    # 0.3 % here (first order in dt)
    assert bal["body_work"] == pytest.approx(float(np.sum(force * dx)), rel=1e-2)
    assert bal["damping"] > 0.1 * bal["input"]
    assert abs(bal["residual"]) < 1e-3 * (bal["input"] + bal["stored0"])
