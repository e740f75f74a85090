"""Interface bonds (paper 003 §2): element law, failure envelopes, partial damage, friction
after failure, exact forces and Newton's third law, on one bonded pair of discs."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import interface as itf
from jaxgran.bonds import attach_to_walls, force_on_walls
from jaxgran.integrate import step
from jaxgran.partition import make_grid
from jaxgran.state import make_params, make_state, make_walls, particles_from_polygons, replace
from jaxgran.state import wall as make_wall

R = 2.0e-3  # disc radius (m)
G = 1.0e-4  # gap between the discs at bonding (m)
L = 2 * R + G  # centre distance (m)
T = 0.01  # slab thickness (m)
KN, KS = 1.0e12, 4.0e11  # Pa/m
SB, C = 4.0e6, 12.0e6  # Pa
PHI = math.radians(35.0)
MU = 0.5
W = 2 * R  # interface width (lambda = 1)
NE = 4
AE = W * T / NE  # element area (m^2)
NO_WALLS = make_walls([])
EPS = 1e-9  # relative distance to the envelope on either side


def _pair(bond="interface", **kw):
    parts = particles_from_polygons([np.zeros((1, 2)), np.array([[L, 0.0]])], R, 20.0)
    faces = itf.disc_interfaces(np.asarray(parts.pos), R, gap=2 * G)
    args = dict(
        thickness=T,
        normal_stiffness=KN,
        shear_stiffness=KS,
        tensile_strength=SB,
        cohesion=C,
        residual_friction=MU,
        friction_angle=PHI,
        bond=bond,
    )
    return parts, itf.make_interface_bonds(parts, faces, **(args | kw))


def _move(parts, dx=0.0, dy=0.0, rot=0.0, k=1):
    pos = parts.pos.at[k].add(jnp.array([dx, dy]))
    return replace(parts, pos=pos, angle=parts.angle.at[k].add(rot))


def _cross2(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


_forces = jax.jit(itf.interface_forces)


def _eval(parts, bonds):
    f, t, new = _forces(parts, bonds, NO_WALLS, 0.0)
    return np.asarray(f), np.asarray(t), new


# ------------------------------------------------------------------------------ elastic law


def test_construction_and_reference_state_is_unstressed():
    parts, b = _pair()
    assert b.capacity == 1 and b.n_elements == NE
    assert float(b.width[0]) == pytest.approx(W)
    assert float(b.length[0]) == pytest.approx(L)
    f, t, new = _eval(parts, b)
    assert np.abs(f).max() == 0 and np.abs(t).max() == 0
    assert np.all(np.asarray(new.health) == 1) and bool(new.intact[0])
    # elements spread evenly over the width, centred on the middle of the gap
    x = np.asarray(itf.element_positions(parts, b))[0]
    np.testing.assert_allclose(x[:, 0], R + G / 2, rtol=1e-12)
    np.testing.assert_allclose(x[:, 1], W * (np.arange(NE) + 0.5) / NE - W / 2, atol=1e-15)


def test_forces_match_hand_computed_translation():
    parts, b = _pair()
    dx, dy = 1.0e-6, -2.0e-6  # 1 MPa of tension, -0.8 MPa of shear per element
    f, t, new = _eval(_move(parts, dx, dy), b)
    fx, fy = -NE * AE * KN * dx, -NE * AE * KS * dy
    np.testing.assert_allclose(f[1], [fx, fy], rtol=1e-12)
    np.testing.assert_allclose(f[0], [-fx, -fy], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(new.sigma)[0], KN * dx, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(new.tau)[0], KS * dy, rtol=1e-12)
    # every element acts at the midpoint of its two copies, x = R + G/2 + dx/2 (abs. frame)
    lever_j = (R + G / 2 + dx / 2) - (L + dx)
    lever_i = R + G / 2 + dx / 2
    s = W * (np.arange(NE) + 0.5) / NE - W / 2 + dy / 2
    fe = np.array([fx, fy]) / NE
    tj = sum(lever_j * fe[1] - (s_e - dy) * fe[0] for s_e in s)
    ti = sum(lever_i * -fe[1] - s_e * -fe[0] for s_e in s)
    np.testing.assert_allclose(t, [ti, tj], rtol=1e-10)


def test_elastic_energy_is_the_potential_of_the_bonded_law():
    """For a translation of one disc the element energy is A (k_n u_n^2 + k_s u_s^2) / 2 and
    its gradient with respect to that disc's position is minus the interface force on it."""
    parts, b = _pair()
    dx, dy = 2.0e-7, -1.5e-7  # opening and sliding (m), well inside the envelope
    moved = _move(parts, dx=dx, dy=dy)
    e = float(itf.elastic_energy(moved, b))
    assert e == pytest.approx(0.5 * W * T * (KN * dx * dx + KS * dy * dy), rel=1e-9)
    f, _, _ = _eval(moved, b)

    def energy_at(x):
        return itf.elastic_energy(replace(moved, pos=moved.pos.at[1].set(x)), b)

    grad = np.asarray(jax.grad(energy_at)(moved.pos[1]))
    np.testing.assert_allclose(grad, -f[1], rtol=1e-9, atol=1e-12 * np.abs(f).max())
    assert float(itf.elastic_energy(parts, b)) == 0.0


def test_forces_match_hand_computed_rotation():
    """Relative rotation theta of j about its centre: element copies separate by
    (R(theta) - I) v with v the element point relative to j; the normal is the bisector."""
    parts, b = _pair()
    theta = 2.0e-4
    f, t, _ = _eval(_move(parts, rot=theta), b)
    n = np.array([math.cos(theta / 2), math.sin(theta / 2)])
    tan = np.array([-n[1], n[0]])
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    fj, tj, ti = np.zeros(2), 0.0, 0.0
    for s_e in W * (np.arange(NE) + 0.5) / NE - W / 2:
        x_e = np.array([R + G / 2, s_e])
        v = x_e - np.array([L, 0.0])
        d = rot @ v - v
        fe = -AE * (KN * (d @ n) * n + KS * (d @ tan) * tan)
        c = x_e + 0.5 * d
        fj += fe
        tj += _cross2(c - [L, 0.0], fe)
        ti += _cross2(c, -fe)
    np.testing.assert_allclose(f[1], fj, rtol=1e-9, atol=1e-12 * np.abs(fj).max())
    np.testing.assert_allclose(t, [ti, tj], rtol=1e-9)
    # small-angle bending stiffness of the flat joint: k_n A_e sum s_e^2 (+ shear lever)
    s = W * (np.arange(NE) + 0.5) / NE - W / 2
    lever = L / 2
    k_bend = KN * AE * np.sum(s**2) + KS * AE * NE * lever * (L - lever)
    assert tj == pytest.approx(-k_bend * theta, rel=2e-3)


def test_newtons_third_law_and_rigid_motion():
    parts, b = _pair()
    rng = np.random.default_rng(3)
    for _ in range(5):
        dx, dy = rng.normal(0, 2e-7, 2)
        p2 = _move(_move(parts, *rng.normal(0, 2e-7, 2), rot=rng.normal(0, 1e-4), k=0), dx, dy)
        p2 = _move(p2, rot=rng.normal(0, 1e-4))
        f, t, _ = _eval(p2, b)
        pos = np.asarray(p2.pos)
        assert np.abs(f.sum(axis=0)).max() <= 1e-12 * np.abs(f).max()
        moment = t.sum() + _cross2(pos, f).sum()
        assert abs(moment) <= 1e-12 * np.abs(f).max() * L
    # a rigid rotation + translation of the pair stresses nothing
    a = 0.7
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    pos = np.asarray(parts.pos) @ rot.T + np.array([0.3, -0.1])
    p3 = replace(parts, pos=jnp.asarray(pos), angle=parts.angle + a)
    f, t, new = _eval(p3, b)
    assert np.abs(f).max() < 1e-9 * KN * AE * 1e-9 + 1e-6  # round-off of 0.3 m positions
    assert np.abs(np.asarray(new.sigma)).max() < 1e3  # Pa, vs MPa strengths


# ------------------------------------------------------------------------------ envelopes


@pytest.mark.parametrize("bond", ["interface", "parallel"])
def test_tension_failure_exactly_at_sigma_b(bond):
    parts, b = _pair(bond)
    u = SB / KN
    _, _, below = _eval(_move(parts, u * (1 - EPS)), b)
    assert np.all(np.asarray(below.health) == 1) and np.all(np.asarray(below.mode) == 0)
    f, _, above = _eval(_move(parts, u * (1 + EPS)), b)
    assert np.all(np.asarray(above.health) == 0)
    assert np.all(np.asarray(above.mode) == itf.MODE_TENSION)
    assert not bool(above.intact[0]) and np.isfinite(float(above.break_time[0]))
    # a failed element carries no tension: the open pair is force-free
    assert np.abs(f).max() == 0


def _tau_c(sigma, bond):
    if bond == "interface":
        return C * math.sqrt(1 - sigma / SB)  # paper 003 Eq. 3
    return C - sigma * math.tan(PHI)


@pytest.mark.parametrize("bond", ["interface", "parallel"])
@pytest.mark.parametrize("sigma", [2.0e6, 0.0, -5.0e6, -20.0e6, -40.0e6])
def test_shear_failure_exactly_on_the_envelope(bond, sigma):
    parts, b = _pair(bond)
    tau_c = _tau_c(sigma, bond)
    ux = sigma / KN
    for side, sign in ((1 - EPS, 1.0), (1 - EPS, -1.0)):
        _, _, new = _eval(_move(parts, ux, sign * side * tau_c / KS), b)
        assert np.all(np.asarray(new.health) == 1), (sigma, sign)
    for sign in (1.0, -1.0):
        _, _, new = _eval(_move(parts, ux, sign * (1 + EPS) * tau_c / KS), b)
        assert np.all(np.asarray(new.mode) == itf.MODE_SHEAR), (sigma, sign)
        # after failure only friction under compression remains (nothing in tension)
        tau = np.asarray(new.tau)[0]
        np.testing.assert_allclose(np.abs(tau), MU * max(-sigma, 0.0), atol=1e-6)


@pytest.mark.parametrize("factor", [0.5, 1.5])
def test_above_the_friction_crossover_a_shear_failure_costs_the_interface_nothing(factor):
    """The parabola meets the friction line of a failed element at s* (friction_crossover).
    Sheared to failure at a compression below s*, an element drops to mu_b |sigma|; above s*
    it keeps the stress it failed at and, sheared on, carries up to mu_b |sigma|, more than
    its bonded strength. The parallel bond (tan(phi) > mu_b) always drops."""
    s_star = itf.friction_crossover(C, SB, MU)
    assert C * math.sqrt(1 + s_star / SB) == pytest.approx(MU * s_star, rel=1e-12)
    sigma = -factor * s_star
    cap = MU * factor * s_star
    for bond in ("interface", "parallel"):
        parts, b = _pair(bond)
        tau_c = _tau_c(sigma, bond)
        _, _, new = _eval(_move(parts, sigma / KN, (1 + EPS) * tau_c / KS), b)
        assert np.all(np.asarray(new.mode) == itf.MODE_SHEAR)
        at_failure = np.abs(np.asarray(new.tau)[0])
        np.testing.assert_allclose(at_failure, min((1 + EPS) * tau_c, cap), rtol=1e-9)
        # sheared on by twice the cap's elastic displacement: friction at mu_b |sigma|
        _, _, new = _eval(_move(parts, sigma / KN, (tau_c + 2 * cap) / KS), new)
        np.testing.assert_allclose(np.abs(np.asarray(new.tau)[0]), cap, rtol=1e-9)
        gains = bond == "interface" and factor > 1
        assert (cap > tau_c) == gains
        assert np.all(at_failure >= tau_c) == gains
    assert itf.friction_crossover(C, SB, 0.0) == math.inf


def test_host_element_stresses_match_the_jitted_kinematics():
    """bonded_element_stresses (numpy, for run files) is k_n u_n and k_s u_s of
    interface_kinematics for any placement of the pair (moved, turned, both bodies)."""
    from jaxgran.scenes import interface as si

    parts, b = _pair()
    rng = np.random.default_rng(3)
    for _ in range(5):
        dx, dy = rng.normal(0.0, 1e-5, 2)
        moved = _move(_move(parts, dx, dy, rng.normal(0.0, 0.05)), *rng.normal(0, 1e-5, 2), k=0)
        moved = replace(moved, angle=moved.angle.at[0].add(rng.normal(0.0, 0.05)))
        k = itf.interface_kinematics(moved, b)
        sig, tau = si.bonded_element_stresses(
            np.asarray(moved.pos), np.asarray(moved.angle), si._host_bonds(b)
        )
        np.testing.assert_allclose(sig, KN * np.asarray(k["u_n"]), rtol=1e-12, atol=1e-6)
        np.testing.assert_allclose(tau, KS * np.asarray(k["u_s"]), rtol=1e-12, atol=1e-6)


def test_element_failures_take_the_stresses_of_the_last_frame_before_the_failure():
    """Two frames (at rest; pressed by sigma and sheared to half its strength), then a shear
    past the envelope that fails all four elements at t = 2 s: element_failures finds each
    with the stresses of the second frame (k_n u_n, k_s u_s), its strength and friction
    there; the summary's compression and strength lost follow."""
    from jaxgran.scenes import interface as si

    parts, b = _pair()
    sigma = -20.0e6
    tau_c = _tau_c(sigma, "interface")
    p1 = _move(parts, sigma / KN, 0.5 * tau_c / KS)
    _, _, b = _forces(p1, b, NO_WALLS, 1.0)
    _, _, b = _forces(_move(parts, sigma / KN, 1.01 * tau_c / KS), b, NO_WALLS, 1.0)
    assert np.all(np.asarray(b.mode) == itf.MODE_SHEAR)
    frames = {
        "time": np.array([0.0, 1.0]),
        "pos": np.stack([np.asarray(parts.pos), np.asarray(p1.pos)]),
        "angle": np.stack([np.asarray(parts.angle), np.asarray(p1.angle)]),
    }
    f = si.element_failures(frames, b)
    assert f["sigma"].size == NE and np.all(f["time"] == 2.0) and np.all(f["bond"] == 0)
    np.testing.assert_allclose(f["sigma"], sigma, rtol=1e-9)
    np.testing.assert_allclose(np.abs(f["tau"]), 0.5 * tau_c, rtol=1e-9)
    np.testing.assert_allclose(f["tau_c"], tau_c, rtol=1e-12)
    np.testing.assert_allclose(f["friction"], MU * 20.0e6, rtol=1e-9)
    m = si.failure_stress_summary(f, b)
    assert m["n_shear_failures_recorded"] == NE and m["n_tension_failures_recorded"] == 0
    assert m["shear_failure_compression_median_Pa"] == pytest.approx(20.0e6, rel=1e-9)
    assert m["strength_lost_on_failing_median"] == pytest.approx(
        1.0 - MU * 20.0e6 / tau_c, rel=1e-9
    )
    assert m["friction_crossover_Pa"] == pytest.approx(itf.friction_crossover(C, SB, MU))
    assert m["shear_failures_above_crossover"] == 0.0
    # a failure before the first frame (the isotropic stage) is not counted
    frames["time"] = frames["time"] + 5.0
    assert si.element_failures(frames, b)["sigma"].size == 0


def test_envelopes_meet_at_zero_stress_and_differ_under_compression():
    s = jnp.array([SB, 0.0, -10e6, -40e6])
    par = itf.shear_strength(s, C, SB, math.tan(PHI), itf.ENVELOPE_PARABOLIC)
    lin = itf.shear_strength(s, C, SB, math.tan(PHI), itf.ENVELOPE_LINEAR)
    np.testing.assert_allclose(par, [0.0, C, C * math.sqrt(3.5), C * math.sqrt(11.0)])
    np.testing.assert_allclose(
        lin, [C - SB * math.tan(PHI), C, C + 10e6 * math.tan(PHI), C + 40e6 * math.tan(PHI)]
    )
    g = jax.grad(lambda x: itf.shear_strength(x, C, SB, 0.0, 0).sum())(s)
    assert np.all(np.isfinite(np.asarray(g)))  # also at the apex sigma = sigma_b


def test_compressive_strain_limit_when_enabled():
    eps_u = 0.01
    parts, b = _pair(compressive_strain=eps_u)
    u = -eps_u * L
    _, _, below = _eval(_move(parts, u * (1 - EPS)), b)
    assert np.all(np.asarray(below.health) == 1)
    _, _, above = _eval(_move(parts, u * (1 + EPS)), b)
    assert np.all(np.asarray(above.mode) == itf.MODE_COMPRESSION)
    # default: inactive, even far beyond
    parts, b = _pair()
    _, _, new = _eval(_move(parts, 10 * u), b)
    assert np.all(np.asarray(new.health) == 1)


def test_tension_is_checked_before_shear():
    parts, b = _pair()
    _, _, new = _eval(_move(parts, 1.5 * SB / KN, 3 * C / KS), b)
    assert np.all(np.asarray(new.mode) == itf.MODE_TENSION)


# ------------------------------------------------------------------------------ damage


def test_partial_damage_reduces_stiffness_element_by_element():
    """Opening u0 plus a growing rotation of j about the interface centre: the outermost
    element fails first, then the next, ...; after each failure the tensile stiffness
    (k_n A_e per bonded element) drops by one element, in the force too."""
    parts, b = _pair()
    s = W * (np.arange(NE) + 0.5) / NE - W / 2
    u0 = 0.5 * SB / KN
    cx = R + G / 2
    thetas = []
    for m in range(NE):  # element NE-1-m reaches sigma_b at u0 + theta s = SB / KN (small angle)
        thetas.append((SB / KN - u0) / s[NE - 1 - m] if s[NE - 1 - m] > 0 else None)
    failed_before = 0
    for theta in np.linspace(0.0, 3.5 * thetas[0], 80):
        # rotate j clockwise by theta about the interface centre (s > 0 opens), open by u0
        a = -float(theta)
        rel = np.array([L - cx, 0.0])
        new_pos = np.array([cx, 0.0]) + np.array([math.cos(a) * rel[0], math.sin(a) * rel[0]])
        p2 = replace(
            parts,
            pos=parts.pos.at[1].set(jnp.asarray(new_pos + np.array([u0, 0.0]))),
            angle=parts.angle.at[1].set(a),
        )
        f, _, b = _eval(p2, b)
        n_failed = int((np.asarray(b.health)[0] == 0).sum())
        assert n_failed >= failed_before  # failures never heal
        assert n_failed - failed_before <= 1  # one element at a time
        failed_before = n_failed
        k_eff = float(itf.interface_normal_stiffness(b)[0])
        assert k_eff == pytest.approx(KN * AE * (NE - n_failed), rel=1e-12)
        # the failed elements are the most stretched ones (largest s), all in tension
        h = np.asarray(b.health)[0]
        assert np.all(h[: NE - n_failed] == 1) and np.all(h[NE - n_failed :] == 0)
        assert np.all(np.asarray(b.mode)[0][NE - n_failed :] == itf.MODE_TENSION)
        # the normal force is carried by the bonded elements only
        sig = np.asarray(b.sigma)[0]
        assert np.all(sig[NE - n_failed :] <= 0)
    assert failed_before >= 2  # the path failed at least two of the four elements
    # the measured stiffness under a further opening along n drops by the failed share
    extra = 1e-8
    f0, _, _ = _eval(p2, b)
    f1, _, _ = _eval(_move(p2, extra * math.cos(a / 2), extra * math.sin(a / 2)), b)
    k_meas = np.linalg.norm(f1[1] - f0[1]) / extra
    assert np.all(np.asarray(b.sigma)[0][NE - failed_before :] == 0)  # failed ones are open
    assert k_meas == pytest.approx(KN * AE * (NE - failed_before), rel=1e-6)


def test_friction_after_failure_obeys_mu_b():
    parts, b = _pair()
    _, _, b = _eval(_move(parts, 2 * SB / KN), b)  # break in tension, open
    assert np.all(np.asarray(b.mode) == itf.MODE_TENSION)
    sigma = -10.0e6
    un = sigma / KN
    us0 = 3.0e-7
    _, _, b = _eval(_move(parts, 1e-7, us0), b)  # slide while open: nothing to resist
    ratios = []
    for us in np.linspace(us0, us0 + 8 * MU * abs(sigma) / KS, 40):
        f, _, b = _eval(_move(parts, un, us), b)
        fn, ft = f[1]
        assert fn == pytest.approx(-NE * AE * sigma, rel=1e-12)  # pushes j back: +x
        stick = KS * (us - us0)
        expect = min(stick, MU * abs(sigma))
        assert -ft == pytest.approx(NE * AE * expect, rel=1e-9, abs=1e-12)
        ratios.append(abs(ft) / abs(fn))
    assert max(ratios) == pytest.approx(MU, rel=1e-12)
    # reversing: elastic unloading with k_s from the slipped state
    f, _, b = _eval(_move(parts, un, us - 0.5 * MU * abs(sigma) / KS), b)
    assert -f[1, 1] == pytest.approx(NE * AE * 0.5 * MU * abs(sigma), rel=1e-9)
    # opening again: no force, and the spring restarts from zero on re-closing
    f, _, b = _eval(_move(parts, 1e-7, us), b)
    assert np.abs(f).max() == 0
    f, _, b = _eval(_move(parts, un, us), b)
    assert abs(f[1, 1]) < 1e-12 * abs(f[1, 0])


def test_surrogate_width_smooths_failure_and_has_gradients():
    parts, b = _pair(surrogate_width=0.1)
    u = SB / KN
    _, _, mid = _eval(_move(parts, 1.05 * u), b)
    h = np.asarray(mid.health)[0]
    assert np.all((h > 0) & (h < 1))
    _, _, gone = _eval(_move(parts, 1.11 * u), b)
    assert np.all(np.asarray(gone.health)[0] == 0)

    @jax.jit
    def pull_force(sigma_b):
        bb = eqx.tree_at(
            lambda m: m.tensile_strength, b, jnp.full_like(b.tensile_strength, sigma_b)
        )
        f, _, _ = itf.interface_forces(_move(parts, 1.05 * u), bb, NO_WALLS, 0.0)
        return f[1, 0]

    g = float(jax.jit(jax.grad(pull_force))(SB))
    h_ = 1e-5 * SB
    fd = (float(pull_force(SB + h_)) - float(pull_force(SB - h_))) / (2 * h_)
    assert g == pytest.approx(fd, rel=1e-5)


# ------------------------------------------------------------------------------ in the simulator


def test_step_uses_the_interface_hook_and_conserves_momentum():
    parts, b = _pair(damping_ratio=0.0)
    parts = replace(parts, vel=parts.vel.at[1].set(jnp.array([0.05, -0.02])))
    params = make_params(normal_stiffness=1e7, gravity=(0.0, 0.0), dt=2e-8, skin=1e-4, thickness=T)
    grid = make_grid((-0.01, -0.01), (0.02, 0.01), 2 * R, 1e-4)
    state = replace(make_state(parts, NO_WALLS, pair_capacity=8), bonds=b)
    p0 = np.asarray(parts.mass)[:, None] * np.asarray(parts.vel)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(s):
        def body(s, _):
            s, e = step(s, params, grid)
            return s, e

        return jax.lax.scan(body, s, None, length=200)

    s1, errs = run(state)
    s2, _ = run(s1)  # same shapes: no retrace
    assert int(np.bitwise_or.reduce(np.asarray(errs))) == 0
    p1 = np.asarray(s2.particles.mass)[:, None] * np.asarray(s2.particles.vel)
    np.testing.assert_allclose(p1.sum(axis=0), p0.sum(axis=0), atol=1e-15)
    assert isinstance(s2.bonds, itf.InterfaceBonds)
    assert float(s2.bonds.time) == pytest.approx(400 * 2e-8)
    # the pair oscillates: the elements saw tension and compression, bond intact
    assert bool(s2.bonds.intact[0])
    assert np.abs(np.asarray(s2.bonds.sigma)).max() > 0


def test_wall_bonds_are_the_normal_wall_bonds():
    parts, b = _pair()
    walls = make_walls([make_wall((0.0, -R), (0.0, 1.0), length=0.01)])
    wb = attach_to_walls(b.wall_bonds, parts, walls, distance=1e-6, b_n=1e9, thickness=T)
    b = itf.with_wall_bonds(b, wb)
    assert int(np.asarray(b.wall_active).sum()) == 2
    p2 = replace(parts, pos=parts.pos + jnp.array([0.0, 1e-6]))
    f, _, new = itf.interface_forces(p2, b, walls, 0.0)
    on_wall = np.asarray(force_on_walls(new, 1))
    np.testing.assert_allclose(on_wall[0], -np.asarray(f).sum(axis=0), rtol=1e-12)
    assert on_wall[0, 1] > 0  # the wall is pulled up by the particles it holds
