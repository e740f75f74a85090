"""Cohesive bonds (paper 002 §2.2, Eq. 11-15) and wall bonds (§4.3)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import geometry as geo
from jaxgran.bonds import (
    attach_to_walls,
    bond_energy,
    bond_forces,
    bond_kinematics,
    bond_summary,
    broken_mask,
    force_on_walls,
    health_limit,
    make_bonds,
    wall_bond_energy,
)
from jaxgran.integrate import stable_time_step
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

RHO = 12.0  # kg/m^2
H = 0.01  # cell size (m)
R = 1e-3  # sphero-radius (m)
T = 0.02  # thickness (m)
BN, BT, BM = 2.0e7, 1.5e7, 0.8e7  # Pa
NO_WALLS = make_walls([])


def _rect(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def _pair_scene(cells=None, capacity=None, particle_capacity=None, **kw):
    """Two bonded cells: a square and a rectangle shifted up, so the shared edge is off the
    line of centres (forces then give torques)."""
    if cells is None:
        cells = [_rect(0, 0, H, H), _rect(H, 0.3 * H, 2 * H, 1.3 * H)]
    cores = [geo.offset_polygon(c, R) for c in cells]
    parts = particles_from_polygons(cores, R, RHO, capacity=particle_capacity)
    args = dict(thickness=T, b_n=BN, b_t=BT, b_m=BM, eps_th=0.05, theta_th=0.1) | kw
    bonds = make_bonds(cells, parts, capacity=capacity, **args)
    return parts, bonds


def _eval(parts, bonds, dt=0.0):
    f, t, new = bond_forces(parts, bonds, NO_WALLS, dt)
    return np.asarray(f), np.asarray(t), new


def _rotate_np(v, a):
    c, s = np.cos(a), np.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _move_j(parts, bonds, d=(0.0, 0.0), theta=0.0):
    """Rotate particle 1 by ``theta`` about the common point, then translate it by ``d``."""
    m = np.asarray(bonds.point_i[0]) + np.asarray(parts.pos[0])  # common point (world)
    pos = np.asarray(parts.pos).copy()
    ang = np.asarray(parts.angle).copy()
    pos[1] = m + _rotate_np(pos[1] - m, theta) + np.asarray(d)
    ang[1] += theta
    return replace(parts, pos=jnp.asarray(pos), angle=jnp.asarray(ang))


def _frame(theta=0.0):
    n = _rotate_np(np.array([1.0, 0.0]), 0.5 * theta)  # mean normal (angle_i = 0)
    return n, np.array([-n[1], n[0]])


def test_reference_geometry():
    parts, bonds = _pair_scene()
    assert int(bonds.i[0]) == 0 and int(bonds.j[0]) == 1
    np.testing.assert_allclose(float(bonds.area[0]), 0.7 * H * T, rtol=1e-12)
    np.testing.assert_allclose(float(bonds.length[0]), np.hypot(H, 0.3 * H), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(bonds.normal_i[0]), [1.0, 0.0], atol=1e-15)
    k = bond_kinematics(parts, bonds)
    np.testing.assert_allclose(np.asarray(k["x_i"][0]), [H, 0.65 * H], atol=1e-15)
    np.testing.assert_allclose(np.asarray(k["x_j"][0]), [H, 0.65 * H], atol=1e-15)
    f, t, _ = _eval(parts, bonds)
    assert np.all(f == 0.0) and np.all(t == 0.0)


def _check_pair(parts, bonds, f_on_j, moment_j):
    """Forces/torques of the two-cell scene against the expected force on j (at the midpoint
    of the common points) and the Eq. 14 moment on j."""
    f, t, _ = _eval(parts, bonds)
    k = bond_kinematics(parts, bonds)
    c = 0.5 * (np.asarray(k["x_i"][0]) + np.asarray(k["x_j"][0]))
    pos = np.asarray(parts.pos)
    scale = max(np.abs(f_on_j).max(), 1e-30)
    np.testing.assert_allclose(f[1], f_on_j, rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(f[0], -np.asarray(f_on_j), rtol=1e-12, atol=1e-12 * scale)
    arm = lambda x: x[0] * f_on_j[1] - x[1] * f_on_j[0]
    tscale = scale * H + abs(moment_j)
    np.testing.assert_allclose(t[1], arm(c - pos[1]) + moment_j, rtol=1e-11, atol=1e-12 * tscale)
    np.testing.assert_allclose(t[0], -arm(c - pos[0]) - moment_j, rtol=1e-11, atol=1e-12 * tscale)


def test_pure_opening_eq11():
    parts, bonds = _pair_scene()
    a, ell = float(bonds.area[0]), float(bonds.length[0])
    delta = 1e-5
    moved = _move_j(parts, bonds, d=(delta, 0.0))
    k = bond_kinematics(moved, bonds)
    assert float(k["eps_n"][0]) == pytest.approx(delta / ell, rel=1e-12)
    assert abs(float(k["eps_t"][0])) < 1e-14
    _check_pair(moved, bonds, np.array([-BN * a * delta / ell, 0.0]), 0.0)
    # the off-centre edge makes the opening force turn the bodies
    f, t, _ = _eval(moved, bonds)
    assert abs(t[1]) > 0.1 * abs(f[1, 0]) * H


def test_pure_sliding_eq13():
    parts, bonds = _pair_scene()
    a, ell = float(bonds.area[0]), float(bonds.length[0])
    for delta in (2e-5, -3e-5):
        moved = _move_j(parts, bonds, d=(0.0, delta))
        k = bond_kinematics(moved, bonds)
        assert float(k["eps_t"][0]) == pytest.approx(delta / ell, rel=1e-12)
        _check_pair(moved, bonds, np.array([0.0, -BT * a * delta / ell]), 0.0)


def test_pure_rotation_eq14():
    parts, bonds = _pair_scene()
    a, ell = float(bonds.area[0]), float(bonds.length[0])
    theta = 0.01
    moved = _move_j(parts, bonds, theta=theta)
    k = bond_kinematics(moved, bonds)
    assert abs(float(k["eps_n"][0])) < 1e-14 and abs(float(k["eps_t"][0])) < 1e-14
    assert float(k["theta"][0]) == pytest.approx(theta, rel=1e-12)
    _check_pair(moved, bonds, np.zeros(2), -BM * a * ell * theta)
    f, t, _ = _eval(moved, bonds)
    assert t[1] == pytest.approx(-BM * a * ell * theta, rel=1e-12)
    assert t[0] == pytest.approx(BM * a * ell * theta, rel=1e-12)


def test_compression_carried_by_contacts_not_bond():
    parts, bonds = _pair_scene()
    moved = _move_j(parts, bonds, d=(-2e-5, 0.0))
    f, t, new = _eval(moved, bonds)
    assert float(bond_kinematics(moved, bonds)["eps_n"][0]) < 0
    assert np.all(f == 0.0) and np.all(t == 0.0)
    assert bool(new.intact[0])
    # but Eq. 15 counts |eps_n|: a large compression breaks the bond
    _, _, new = _eval(_move_j(parts, bonds, d=(-0.06 * float(bonds.length[0]), 0.0)), bonds)
    assert not bool(new.intact[0])


def _random_motion(parts, seed):
    rng = np.random.default_rng(seed)
    pos = np.asarray(parts.pos).copy()
    ang = np.asarray(parts.angle).copy()
    pos[:2] += rng.normal(scale=2e-5, size=(2, 2))
    ang[:2] += rng.normal(scale=4e-3, size=2)
    return replace(parts, pos=jnp.asarray(pos), angle=jnp.asarray(ang))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_newton_third_law(seed):
    parts, bonds = _pair_scene()
    moved = _random_motion(parts, seed)
    f, t, new = _eval(moved, bonds)
    assert bool(new.intact[0])
    pos = np.asarray(moved.pos)
    fscale = np.abs(f).max()
    assert fscale > 0
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-14 * fscale)
    moment = np.sum(pos[:, 0] * f[:, 1] - pos[:, 1] * f[:, 0] + t)
    assert abs(moment) <= 1e-13 * fscale * H


@pytest.mark.parametrize("seed", [3, 4])
def test_invariance_under_rigid_motion(seed):
    parts, bonds = _pair_scene()
    moved = _random_motion(parts, seed)
    f0, t0, b0 = _eval(moved, bonds)
    phi, shift, centre = 0.7, np.array([0.3, -0.2]), np.array([0.05, 0.02])

    def rigid(p):
        pos = np.asarray(p.pos)
        new = np.stack([centre + _rotate_np(x - centre, phi) + shift for x in pos])
        return replace(p, pos=jnp.asarray(new), angle=p.angle + phi)

    # a rigid motion of the reference configuration strains nothing
    f_ref, t_ref, b_ref = _eval(rigid(parts), bonds)
    fs = np.abs(f0).max()
    assert np.abs(f_ref).max() < 1e-9 * fs and np.abs(t_ref).max() < 1e-9 * fs * H
    assert float(b_ref.strain_measure[0]) < 1e-9
    # a strained configuration moved rigidly: forces rotate, torques and strains stay
    f1, t1, b1 = _eval(rigid(moved), bonds)
    rot = np.stack([_rotate_np(x, phi) for x in f0])
    np.testing.assert_allclose(f1, rot, rtol=1e-7, atol=1e-9 * fs)
    np.testing.assert_allclose(t1, t0, rtol=1e-7, atol=1e-9 * fs * H)
    assert float(b1.strain_measure[0]) == pytest.approx(float(b0.strain_measure[0]), rel=1e-8)


def test_symmetric_in_bond_orientation():
    """Bonding (1, 0) instead of (0, 1) gives the same forces."""
    cells = [_rect(0, 0, H, H), _rect(H, 0.3 * H, 2 * H, 1.3 * H)]
    parts, bonds = _pair_scene(cells)
    moved = _random_motion(parts, 5)
    f0, t0, _ = _eval(moved, bonds)
    swapped, bonds_s = _pair_scene(cells[::-1])
    perm = replace(swapped, pos=moved.pos[::-1], angle=moved.angle[::-1])
    f1, t1, _ = _eval(perm, bonds_s)
    np.testing.assert_allclose(f1[::-1], f0, rtol=1e-10, atol=1e-12 * np.abs(f0).max())
    np.testing.assert_allclose(t1[::-1], t0, rtol=1e-10, atol=1e-12 * np.abs(f0).max() * H)


# ------------------------------------------------------------------------------ breakage

EPS_TH, THETA_TH = 1e-3, 2e-3


def _mode_config(parts, bonds, ratios):
    """Move j so that (eps_n, eps_t, theta) = ratios x (eps_th, eps_th, theta_th)."""
    en, et, th = ratios[0] * EPS_TH, ratios[1] * EPS_TH, ratios[2] * THETA_TH
    n, t = _frame(th)
    ell = float(bonds.length[0])
    return _move_j(parts, bonds, d=ell * (en * n + et * t), theta=th)


MODES = {
    "opening": (1.0, 0.0, 0.0),
    "sliding": (0.0, -1.0, 0.0),
    "rotation": (0.0, 0.0, 1.0),
    "combined": (0.3, 0.25, -0.45),
}


@pytest.mark.parametrize("mode", list(MODES))
def test_breaks_exactly_at_eq15(mode):
    parts, bonds = _pair_scene(eps_th=EPS_TH, theta_th=THETA_TH)
    base = np.asarray(MODES[mode])
    for factor, intact in ((1 - 1e-7, True), (1 + 1e-7, False)):
        moved = _mode_config(parts, bonds, factor * base)
        f, t, new = _eval(moved, bonds, dt=1e-6)
        assert float(new.strain_measure[0]) == pytest.approx(factor, rel=1e-9)
        assert bool(new.intact[0]) is intact
        assert bool(broken_mask(new)[0]) is not intact
        if intact:
            assert np.abs(f).max() + np.abs(t).max() > 0
            assert float(new.health[0]) == 1.0 and np.isinf(float(new.break_time[0]))
        else:
            assert np.all(f == 0.0) and np.all(t == 0.0)
            assert float(new.health[0]) == 0.0
            assert float(new.break_time[0]) == pytest.approx(1e-6)


def test_broken_bond_never_heals():
    parts, bonds = _pair_scene(eps_th=EPS_TH, theta_th=THETA_TH)
    _, _, broken = _eval(_mode_config(parts, bonds, (1.2, 0, 0)), bonds, dt=1e-6)
    f, t, again = _eval(parts, broken, dt=1e-6)  # back to the reference configuration
    assert not bool(again.intact[0])
    assert np.all(f == 0.0) and np.all(t == 0.0)
    assert float(again.break_time[0]) == pytest.approx(1e-6)
    assert float(again.time) == pytest.approx(2e-6)
    assert bond_summary(again)["n_broken"] == 1 and bond_summary(again)["n_intact"] == 0


def test_surrogate_tends_to_hard_model():
    parts, bonds = _pair_scene(eps_th=EPS_TH, theta_th=THETA_TH)
    base = np.asarray(MODES["combined"])
    widths = (1e-1, 1e-2, 1e-3, 1e-4)
    for factor in (0.95, 0.999, 1.0005, 1.002, 1.05):
        moved = _mode_config(parts, bonds, factor * base)
        f_hard, t_hard, _ = _eval(moved, bonds)
        for w in widths:
            f_w, t_w, new = _eval(moved, replace(bonds, surrogate_width=jnp.asarray(w)))
            exact = factor < 1 or factor > 1 + w  # outside (1, 1 + w) it is the hard model
            if exact:
                assert np.all(f_w == f_hard) and np.all(t_w == t_hard)
                assert bool(new.intact[0]) is (factor < 1)
            else:
                assert 0 < float(new.health[0]) < 1 and bool(new.intact[0])
    # and the L1 distance between the health curves shrinks like w / 2
    measure = jnp.linspace(0.5, 1.5, 20001)
    hard = health_limit(measure, jnp.asarray(0.0))
    for w in widths[:3]:
        dist = float(jnp.mean(jnp.abs(health_limit(measure, jnp.asarray(w)) - hard)))
        assert dist == pytest.approx(0.5 * w, rel=0.1)


def test_surrogate_health_never_recovers():
    parts, bonds = _pair_scene(eps_th=EPS_TH, theta_th=THETA_TH, surrogate_width=0.1)
    _, _, damaged = _eval(_mode_config(parts, bonds, (1.05, 0, 0)), bonds)
    h = float(damaged.health[0])
    assert h == pytest.approx(0.5, abs=1e-6) and bool(damaged.intact[0])
    moved = _mode_config(parts, bonds, (0.5, 0, 0))
    f_full, _, _ = _eval(moved, bonds)
    f_dam, _, again = _eval(moved, damaged)
    assert float(again.health[0]) == pytest.approx(h, rel=1e-14)
    np.testing.assert_allclose(f_dam, h * f_full, rtol=1e-12)


def test_gradient_wrt_bn_and_threshold_matches_finite_differences():
    parts, bonds = _pair_scene(eps_th=EPS_TH, theta_th=THETA_TH, surrogate_width=0.2)
    moved = _mode_config(parts, bonds, (0.5, 0.4, 0.2))  # measure 1.1: half-way down the ramp

    def fx(b_n, eps_th):
        b = replace(
            bonds, b_n=jnp.full_like(bonds.b_n, b_n), eps_th=jnp.full_like(bonds.eps_th, eps_th)
        )
        f, t, _ = bond_forces(moved, b, NO_WALLS, 0.0)
        return f[1, 0] + t[1] / H

    x0 = (jnp.asarray(BN), jnp.asarray(EPS_TH))
    g = jax.grad(fx, argnums=(0, 1))(*x0)
    for k, step in ((0, 1e-3 * BN), (1, 1e-4 * EPS_TH)):
        hi = list(x0)
        lo = list(x0)
        hi[k] = hi[k] + step
        lo[k] = lo[k] - step
        fd = (fx(*hi) - fx(*lo)) / (2 * step)
        assert float(g[k]) == pytest.approx(float(fd), rel=1e-6)
        assert abs(float(g[k])) > 0


def test_padded_bonds_finite_gradients_and_no_recompile():
    parts, bonds = _pair_scene(
        capacity=5, particle_capacity=4, eps_th=EPS_TH, theta_th=THETA_TH, surrogate_width=0.1
    )
    assert bonds.capacity == 5 and int(bonds.i[1]) == 4
    walls = make_walls([wall((0.0, 0.0), (0.0, 1.0))])
    bonds = attach_to_walls(bonds, parts, walls, distance=1e-6, b_n=BN, thickness=T, capacity=3)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def forces(p, b):
        return bond_forces(p, b, walls, 1e-6)

    def loss(pb):
        f, t, new = bond_forces(*pb, walls, 1e-6)
        return jnp.sum(f**2) + jnp.sum((t / H) ** 2) + jnp.sum(new.health)

    grad = eqx.filter_jit(eqx.filter_grad(loss))
    for p in (parts, _mode_config(parts, bonds, (0.5, 0.2, 0.1)), _random_motion(parts, 7)):
        f, t, _ = forces(p, bonds)  # new values, same shapes: no retrace
        assert np.all(np.isfinite(np.asarray(f))) and np.all(np.isfinite(np.asarray(t)))
        assert np.all(np.asarray(f[2:]) == 0.0)  # padded particle slots get nothing
        for leaf in jax.tree_util.tree_leaves(grad((p, bonds))):
            assert np.all(np.isfinite(np.asarray(leaf)))


def test_vmap_over_moduli():
    parts, bonds = _pair_scene()
    moved = _random_motion(parts, 8)
    scales = jnp.array([0.5, 1.0, 2.0])

    def f_of(s):
        b = replace(bonds, b_n=bonds.b_n * s, b_t=bonds.b_t * s, b_m=bonds.b_m * s)
        return bond_forces(moved, b, NO_WALLS, 0.0)[0]

    out = np.asarray(jax.vmap(f_of)(scales))
    np.testing.assert_allclose(out[0], 0.5 * out[1], rtol=1e-12)
    np.testing.assert_allclose(out[2], 2.0 * out[1], rtol=1e-12)


# ------------------------------------------------------------------------------ dynamics


def _dynamic_run(eps_th, n_chunks, chunk):
    """Two bonded squares pulled apart along the bond normal; damping and gravity off.
    Returns (omega, v_rel0, list of (time, gap, kinetic+bond energy), final state)."""
    cells = [_rect(0, 0, H, H), _rect(H, 0, 2 * H, H)]
    cores = [geo.offset_polygon(c, R) for c in cells]
    v0 = 0.05
    parts = particles_from_polygons(cores, R, RHO, velocities=[[-v0, 0.0], [v0, 0.0]])
    bonds = make_bonds(
        cells, parts, thickness=T, b_n=BN, b_t=BT, b_m=BM, eps_th=eps_th, theta_th=1.0
    )
    m = float(parts.mass[0])
    k_bond = BN * float(bonds.area[0]) / float(bonds.length[0])
    omega = np.sqrt(2.0 * k_bond / m)
    params = make_params(gravity=(0.0, 0.0))
    dt = min(stable_time_step(parts, params), 2 * np.pi / omega / 400)
    params = replace(params, dt=jnp.asarray(dt))
    grid = make_grid((-0.02, -0.02), (0.05, 0.03), float(jnp.max(parts.bound_radius)), 2e-3)
    state = replace(make_state(parts, make_walls([]), pair_capacity=4), bonds=bonds)
    state, err = prepare(state, params, grid)
    assert int(err) == 0

    @jax.jit
    def sample(s):
        p = s.particles
        ke = 0.5 * jnp.sum(p.mass * jnp.sum(p.vel**2, axis=1) + p.inertia * p.omega**2)
        return jnp.stack([s.time, p.pos[1, 0] - p.pos[0, 0] - H, ke + bond_energy(p, s.bonds)])

    out = [sample(state)]
    for _ in range(n_chunks):
        state, _, err = run_segment(state, params, grid, 1, chunk)
        assert int(err) == 0
        out.append(sample(state))
    return omega, 2 * v0, np.asarray(out), state, dt


def test_bonded_pair_oscillates_and_conserves_energy():
    omega, v_rel, samples, state, dt = _dynamic_run(1.0, 60, 20)
    t, gap, energy = samples.T
    assert bool(state.bonds.intact[0])
    # in tension only the bond acts: gap = (v_rel / omega) sin(omega t) for the first half
    first = t < np.pi / omega
    np.testing.assert_allclose(
        gap[first], v_rel / omega * np.sin(omega * t[first]), atol=2e-3 * v_rel / omega
    )
    assert gap.min() < 0 < gap.max()  # it came back and bounced off the contact
    tension = gap > 0
    assert tension.sum() > 10
    np.testing.assert_allclose(energy[tension], energy[0], rtol=2e-3)


def test_weak_bond_breaks_and_cells_separate():
    eps_th = 2e-4
    omega, v_rel, samples, state, dt = _dynamic_run(eps_th, 20, 20)
    assert not bool(state.bonds.intact[0])
    ell = H
    amplitude = v_rel / omega
    delta_b = eps_th * ell
    t_break = np.arcsin(delta_b / amplitude) / omega
    assert float(state.bonds.break_time[0]) == pytest.approx(t_break, abs=1.5 * dt)
    v = np.asarray(state.particles.vel)
    # the bond's elastic energy is lost; a discrete break lands within a step of delta_b
    v_hi = np.sqrt(v_rel**2 - (omega * (delta_b - v_rel * dt)) ** 2)
    v_lo = np.sqrt(v_rel**2 - (omega * (delta_b + v_rel * dt)) ** 2)
    assert v_lo * (1 - 1e-3) <= v[1, 0] - v[0, 0] <= v_hi * (1 + 1e-3)
    gaps = samples[:, 1]
    assert np.all(np.diff(gaps) > 0)


# ------------------------------------------------------------------------------ construction


def test_make_bonds_on_voronoi_rectangle():
    w, h = 0.05, 0.03
    cells = geo.voronoi_rectangle(w, h, 15, seed=3)
    cores = [geo.offset_polygon(c, 2e-4) for c in cells]
    parts = particles_from_polygons(cores, 2e-4, RHO, capacity=20)
    bonds = make_bonds(
        cells, parts, thickness=T, b_n=BN, b_t=BT, b_m=BM, eps_th=0.01, theta_th=0.02, capacity=64
    )
    edges = geo.shared_edges(cells)
    s = bond_summary(bonds)
    assert s["n_bonds"] == len(edges) == s["n_intact"] and s["n_broken"] == 0
    n = len(edges)
    lengths = np.array([np.linalg.norm(q - p) for _, _, p, q in edges])
    np.testing.assert_allclose(np.asarray(bonds.area[:n]), lengths * T, rtol=1e-12)
    # every interior edge is shared by two cells: sum of perimeters = 2 x bonds + boundary
    perim = sum(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1).sum() for c in cells)
    assert perim == pytest.approx(2 * lengths.sum() + 2 * (w + h), rel=1e-9)
    pos = np.asarray(parts.pos)
    i, j = np.asarray(bonds.i[:n]), np.asarray(bonds.j[:n])
    np.testing.assert_allclose(
        np.asarray(bonds.length[:n]), np.linalg.norm(pos[j] - pos[i], axis=1), rtol=1e-12
    )
    assert np.all(np.sum((pos[j] - pos[i]) * np.asarray(bonds.normal_i[:n]), axis=1) > 0)
    assert np.all(np.asarray(bonds.i[n:]) == 20) and not np.any(np.asarray(bonds.intact[n:]))
    # the tessellation as built is unstrained
    f, t, new = _eval(parts, bonds)
    assert np.all(np.abs(f) < 1e-6) and np.all(np.abs(t) < 1e-8)
    assert float(jnp.max(new.strain_measure)) < 1e-10
    # random thresholds, one per bond
    rand = np.random.default_rng(0).uniform(0.005, 0.02, n)
    b2 = make_bonds(cells, parts, thickness=T, b_n=BN, b_t=BT, b_m=BM, eps_th=rand, theta_th=0.02)
    np.testing.assert_allclose(np.asarray(b2.eps_th), rand)


def test_make_bonds_rejects_small_capacity_and_bad_parameters():
    cells = geo.voronoi_rectangle(0.05, 0.03, 8, seed=1)
    parts = particles_from_polygons([geo.offset_polygon(c, 1e-4) for c in cells], 1e-4, RHO)
    kw = dict(thickness=T, b_n=BN, b_t=BT, b_m=BM, eps_th=0.01, theta_th=0.02)
    n = len(geo.shared_edges(cells))
    with pytest.raises(ValueError, match=f"capacity>={n}"):
        make_bonds(cells, parts, capacity=n - 1, **kw)
    with pytest.raises(ValueError, match="eps_th"):
        make_bonds(cells, parts, **(kw | {"eps_th": 0.0}))
    with pytest.raises(ValueError, match="one value per bond"):
        make_bonds(cells, parts, **(kw | {"b_n": np.ones(n + 1)}))
    with pytest.raises(ValueError, match="same order"):
        make_bonds(cells[::-1], parts, **kw)


def test_wall_bonds_pull_but_never_push_or_break():
    cells = [_rect(0, 0, H, H), _rect(H, 0, 2 * H, H)]
    parts, bonds = _pair_scene(cells, b_n=0.0, b_t=0.0, b_m=0.0)  # wall bonds only
    walls = make_walls([wall((0.0, 0.0), (0.0, 1.0)), wall((0.0, H), (0.0, -1.0))])
    bonds = attach_to_walls(bonds, parts, walls, distance=1e-9, b_n=BN, thickness=T)
    assert bonds.wall_capacity == 4  # both cells touch both walls
    np.testing.assert_allclose(np.asarray(bonds.wall_area), (H - 2 * R) * T, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(bonds.wall_length), H / 2, rtol=1e-12)
    only_bottom = replace(walls, active=jnp.array([True, False]))
    a = (H - 2 * R) * T
    for lift, expect in ((1e-5, -BN * a * 1e-5 / (H / 2)), (-1e-5, 0.0)):
        pos = np.asarray(parts.pos) + np.array([[0.0, lift], [0.0, 0.0]])
        moved = replace(parts, pos=jnp.asarray(pos))
        f, t, new = bond_forces(moved, bonds, only_bottom, 0.0)
        np.testing.assert_allclose(np.asarray(f[0]), [0.0, expect], atol=1e-9)
        assert abs(float(t[0])) < 1e-12 and np.all(np.abs(np.asarray(f[1])) < 1e-9)
        on_wall = np.asarray(force_on_walls(new, 2))
        np.testing.assert_allclose(on_wall[0], -np.asarray(f[0]), atol=1e-12)
        u = float(wall_bond_energy(moved, bonds, only_bottom))
        assert u == pytest.approx(0.5 * BN * a * (H / 2) * (max(lift, 0) / (H / 2)) ** 2)
    # sliding along the wall: no tangential wall-bond force; a huge pull: still bonded
    pos = np.asarray(parts.pos) + np.array([[3e-4, 5e-3], [0.0, 0.0]])
    f, _, new = bond_forces(replace(parts, pos=jnp.asarray(pos)), bonds, only_bottom, 0.0)
    np.testing.assert_allclose(float(f[0, 0]), 0.0, atol=1e-9)
    assert float(f[0, 1]) == pytest.approx(-BN * a * 5e-3 / (H / 2), rel=1e-12)
    assert int(new.wall_active.sum()) == 4
