"""DSM connection points and averaged-stress breakage criteria (paper 000 §II.B, Tables II-III)."""

import numpy as np
import pytest
from scipy import ndimage

from jaxgran.breakage.criteria import (
    averaged_stress,
    breakage_type,
    connection_points,
    cross_cut_criterion,
    fracture_planes,
    mohr_coulomb_criterion,
    principal_stresses,
    split_cell_criterion,
)
from jaxgran.breakage.ssm import split_convex

# ---------------------------------------------------------------- helpers


def _grid(n, h):
    """Square grid of (2n+1)^2 samples with spacing h, centred on the origin."""
    k = np.arange(-n, n + 1)
    i, j = np.meshgrid(k, k, indexing="ij")
    ij = np.stack([i.ravel(), j.ravel()], axis=1)
    return ij, ij * h


def _index_of(ij, i, j):
    return int(np.flatnonzero((ij[:, 0] == i) & (ij[:, 1] == j))[0])


def _seeds_around(ij, i, j):
    """The sample at (i, j) and its 4 neighbours."""
    near = np.abs(ij[:, 0] - i) + np.abs(ij[:, 1] - j) <= 1
    return np.flatnonzero(near)


def _bottleneck_by_labelling(psi, ij, seeds, a, b):
    """Reference (PHYSICS.md §A7): bisection on the level with scipy.ndimage.label."""
    lo = ij.min(axis=0)
    shape = tuple(ij.max(axis=0) - lo + 1)
    level = psi.copy()
    for s in seeds:
        level[s] = np.inf

    def connected(threshold):
        mask = np.zeros(shape, bool)
        keep = level >= threshold
        mask[tuple((ij[keep] - lo).T)] = True
        labels, _ = ndimage.label(mask)  # default structure: 4-connectivity
        la = set(labels[tuple((ij[seeds[a]] - lo).T)].tolist()) - {0}
        lb = set(labels[tuple((ij[seeds[b]] - lo).T)].tolist()) - {0}
        return bool(la & lb)

    levels = np.unique(np.append(level, np.inf))  # ascending
    if not connected(levels[0]):
        return -np.inf
    lo_i, hi_i = 0, len(levels) - 1  # connected at lo_i; find the largest such
    while lo_i < hi_i:
        mid = (lo_i + hi_i + 1) // 2
        if connected(levels[mid]):
            lo_i = mid
        else:
            hi_i = mid - 1
    return levels[lo_i]


def _angle_mod_pi(line):
    d = line[1] - line[0]
    return np.mod(np.arctan2(d[1], d[0]), np.pi)


def _same_angles(lines, expected):
    got = np.sort([_angle_mod_pi(ln) for ln in lines])
    want = np.sort(np.mod(expected, np.pi))
    diff = np.abs(got - want)
    return np.all(np.minimum(diff, np.pi - diff) < 1e-12)


# ---------------------------------------------------------------- connection points


def _two_peaks(xy, a=0.5, width=0.3, height=2.0e6):
    r1 = (xy[:, 0] - a) ** 2 + xy[:, 1] ** 2
    r2 = (xy[:, 0] + a) ** 2 + xy[:, 1] ** 2
    return height * (np.exp(-r1 / (2 * width**2)) + np.exp(-r2 / (2 * width**2)))


def test_two_peaks_saddle_is_the_connection_point():
    ij, xy = _grid(20, 0.05)
    psi = _two_peaks(xy)
    seeds = [_seeds_around(ij, 10, 0), _seeds_around(ij, -10, 0)]
    centre = _index_of(ij, 0, 0)
    saddle = 2.0e6 * 2.0 * np.exp(-(0.5**2) / (2 * 0.3**2))  # analytic psi at (0, 0)

    res = connection_points(psi, ij, seeds, eps=0.9e6)
    assert res.bottleneck[0, 1] == res.bottleneck[1, 0] == psi[centre]
    assert res.bottleneck[0, 1] == pytest.approx(saddle, rel=1e-14)
    assert res.location[0, 1] == res.location[1, 0] == centre
    assert np.isinf(res.bottleneck[0, 0]) and res.location[0, 0] == -1
    np.testing.assert_array_equal(res.saddle_index, [centre])
    np.testing.assert_array_equal(res.connection_index, [centre])
    assert res.breaks


def test_breaks_iff_eps_reaches_the_bottleneck():
    ij, xy = _grid(20, 0.05)
    psi = _two_peaks(xy)
    seeds = [_seeds_around(ij, 10, 0), _seeds_around(ij, -10, 0)]
    b = psi[_index_of(ij, 0, 0)]
    assert connection_points(psi, ij, seeds, eps=b).breaks  # equality: the domains touch
    assert connection_points(psi, ij, seeds, eps=0.999 * b).breaks
    above = connection_points(psi, ij, seeds, eps=1.001 * b)
    assert not above.breaks
    assert above.connection_index.size == 0
    assert above.bottleneck[0, 1] == b  # the bottleneck does not depend on eps


def test_three_seeds_merge_tree_matches_labelling():
    ij, xy = _grid(24, 0.05)
    peaks = [((-0.6, -0.4), 3.0, 0.30), ((0.6, -0.4), 2.0, 0.25), ((0.0, 0.6), 2.5, 0.35)]
    psi = sum(h * np.exp(-np.sum((xy - c) ** 2, axis=1) / (2 * w**2)) for c, h, w in peaks)
    seeds = [_seeds_around(ij, round(c[0] / 0.05), round(c[1] / 0.05)) for c, _, _ in peaks]
    res = connection_points(psi, ij, seeds, eps=0.0)
    for a in range(3):
        for b in range(a + 1, 3):
            ref = _bottleneck_by_labelling(psi, ij, seeds, a, b)
            assert res.bottleneck[a, b] == ref
            assert psi[res.location[a, b]] == ref
    # merge tree: 2 saddles for 3 contacts, ultrametric bottlenecks
    assert res.saddle_level.size == 2 and res.saddle_level[0] >= res.saddle_level[1]
    off = np.sort(res.bottleneck[np.triu_indices(3, 1)])
    assert off[0] == off[1] <= off[2]
    # between the two saddle levels only the higher one is a connection point
    mid = 0.5 * (res.saddle_level[0] + res.saddle_level[1])
    res_mid = connection_points(psi, ij, seeds, eps=mid)
    np.testing.assert_array_equal(res_mid.connection_index, res.saddle_index[:1])


@pytest.mark.parametrize("seed", range(12))
def test_random_fields_on_a_disc_match_labelling(seed):
    rng = np.random.default_rng(seed)
    ij, xy = _grid(15, 1.0 / 15)
    inside = np.hypot(xy[:, 0], xy[:, 1]) <= 1.0
    ij, xy = ij[inside], xy[inside]
    # smooth random field: a few random Gaussian bumps, plus independent noise for no ties
    psi = sum(
        rng.uniform(0.5, 2.0)
        * np.exp(-np.sum((xy - rng.uniform(-0.8, 0.8, 2)) ** 2, 1) / rng.uniform(0.02, 0.2))
        for _ in range(6)
    )
    psi = psi + 1e-6 * rng.uniform(size=psi.shape)
    n_contacts = rng.integers(2, 6)
    seeds = [
        rng.choice(len(psi), size=rng.integers(1, 4), replace=False) for _ in range(n_contacts)
    ]
    res = connection_points(psi, ij, seeds, eps=1.0)
    for a in range(n_contacts):
        for b in range(a + 1, n_contacts):
            ref = _bottleneck_by_labelling(psi, ij, seeds, a, b)
            assert res.bottleneck[a, b] == ref
            if np.isfinite(ref):
                assert psi[res.location[a, b]] == ref
    off = res.bottleneck[~np.eye(n_contacts, dtype=bool)]
    assert res.breaks == (off.max() >= 1.0)
    # scattered seeds of one contact can give more saddles than a tree, never more than pairs
    assert res.saddle_level.size <= n_contacts * (n_contacts - 1) // 2
    np.testing.assert_array_equal(res.saddle_level, np.sort(res.saddle_level)[::-1])


def test_touching_and_shared_seeds_connect_at_infinity():
    ij, xy = _grid(5, 0.1)
    psi = np.ones(len(ij))
    a, b, c = _index_of(ij, 0, 0), _index_of(ij, 0, 1), _index_of(ij, 3, 3)
    res = connection_points(psi, ij, [[a], [b], [b, c]], eps=1e12)
    assert res.bottleneck[0, 1] == np.inf and res.bottleneck[1, 2] == np.inf
    assert res.location[1, 2] == b  # the shared sample
    assert res.breaks


def test_finite_seeds_connect_at_their_computed_level():
    """Seeds marked finite keep their psi: two touching seeds connect at the lower of their
    two levels, not at infinity."""
    ij, xy = _grid(5, 0.1)
    psi = np.linspace(1.0, 2.0, len(ij))
    a, b = _index_of(ij, 0, 0), _index_of(ij, 0, 1)
    res = connection_points(psi, ij, [[a], [b]], eps=1e12, finite=[a, b])
    assert res.bottleneck[0, 1] == min(psi[a], psi[b])
    assert not res.breaks


def test_disconnected_samples_never_connect():
    ij = np.array([[0, 0], [0, 1], [0, 3], [0, 4]])  # gap at (0, 2)
    psi = np.array([1.0, 2.0, 2.0, 1.0])
    res = connection_points(psi, ij, [[0], [3]], eps=0.0)
    assert res.bottleneck[0, 1] == -np.inf and res.location[0, 1] == -1
    assert not res.breaks and res.saddle_index.size == 0


def test_connection_points_reject_bad_input():
    ij = np.array([[0, 0], [0, 1]])
    with pytest.raises(ValueError, match="duplicate"):
        connection_points([1.0, 2.0], [[0, 0], [0, 0]], [[0], [1]], 0.0)
    with pytest.raises(ValueError, match="NaN"):
        connection_points([1.0, np.nan], ij, [[0], [1]], 0.0)
    with pytest.raises(ValueError, match="seeds"):
        connection_points([1.0, 2.0], ij, [[0], []], 0.0)


# ---------------------------------------------------------------- fracture planes


def test_fracture_plane_is_the_nearest_contact_line():
    contacts = np.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.5], [-1.0, -0.5]])
    # (0.05, 0.1): 0.05 from x = 0 (contacts 0-1), 0.067 from y = x/2 (contacts 2-3)
    # (0.5, 0.3): 0.5 from x = 0, 0.045 from y = x/2; the third repeats the first plane
    conn = np.array([[0.05, 0.1], [0.5, 0.3], [-0.02, -0.5]])
    planes = fracture_planes(conn, contacts)
    np.testing.assert_array_equal(planes, [contacts[[0, 1]], contacts[[2, 3]]])
    # restricted candidate pairs
    only = fracture_planes(conn[:1], contacts, pairs=[[2, 3], [0, 2]])
    np.testing.assert_array_equal(only, [contacts[[2, 3]]])


def test_fracture_plane_segment_versus_line_distance():
    contacts = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 1.0], [3.0, -1.0]])
    x = np.array([[2.0, 0.05]])  # 0.05 from the line through 0-1 but 1.001 from its chord
    pairs = [[0, 1], [2, 3]]  # 1.0 from the chord 2-3
    line = fracture_planes(x, contacts, pairs, metric="line")
    np.testing.assert_array_equal(line, [contacts[[0, 1]]])
    np.testing.assert_array_equal(fracture_planes(x, contacts, pairs), [contacts[[2, 3]]])


def test_dsm_pipeline_splits_a_square_in_halves():
    """Synthetic psi with a saddle at the centre -> plane between the two contacts -> SSM."""
    ij, xy = _grid(10, 0.1)
    top, bottom = np.array([0.0, 1.05]), np.array([0.0, -1.05])
    psi = 1e5 / np.linalg.norm(xy - top, axis=1) + 1e5 / np.linalg.norm(xy - bottom, axis=1)
    seeds = [_seeds_around(ij, 0, 10), _seeds_around(ij, 0, -10)]
    res = connection_points(psi, ij, seeds, eps=1.5e5)
    assert res.breaks
    np.testing.assert_array_equal(xy[res.connection_index], [[0.0, 0.0]])  # the saddle
    planes = fracture_planes(xy[res.connection_index], np.stack([top, bottom]))
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    frags = split_convex(square, planes)
    assert sorted(_area(f) for f in frags) == pytest.approx([2.0, 2.0])


def _area(f):
    r = f - f[0]
    return 0.5 * abs(np.dot(r[:, 0], np.roll(r[:, 1], -1)) - np.dot(r[:, 1], np.roll(r[:, 0], -1)))


# ---------------------------------------------------------------- averaged stress


def _brazilian(p=100.0, r=0.01):
    contacts = np.array([[0.0, r], [0.0, -r]])
    forces = np.array([[0.0, -p], [0.0, p]])  # on the particle, compressive
    return contacts, forces


def test_averaged_stress_brazilian_disc():
    p, r, t = 100.0, 0.01, 0.005
    contacts, forces = _brazilian(p, r)
    sigma = averaged_stress(contacts, forces, [0.0, 0.0], np.pi * r**2, t)
    np.testing.assert_allclose(sigma, np.diag([0.0, -2.0 * p / (np.pi * r * t)]), rtol=1e-14)


def test_averaged_stress_is_objective_and_ignores_the_reference_point():
    rng = np.random.default_rng(0)
    contacts = rng.normal(size=(4, 2))
    forces = rng.normal(size=(4, 2))
    forces[-1] = -forces[:-1].sum(axis=0)  # balanced forces
    centroid = np.array([0.1, -0.2])
    sigma = averaged_stress(contacts, forces, centroid, 2.0, 0.5)
    np.testing.assert_allclose(sigma, sigma.T)
    # with sum F = 0 the reference point does not matter
    np.testing.assert_allclose(averaged_stress(contacts, forces, [5.0, 7.0], 2.0, 0.5), sigma)
    # rotating the configuration rotates the tensor
    a = 0.7
    q = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rotated = averaged_stress(contacts @ q.T, forces @ q.T, q @ centroid, 2.0, 0.5)
    np.testing.assert_allclose(rotated, q @ sigma @ q.T, atol=1e-14)


def test_principal_stresses():
    s1, s2, th = principal_stresses(np.diag([-2.0, -4.0]))
    assert (s1, s2, th) == (-2.0, -4.0, 0.0)
    a = np.deg2rad(30.0)
    q = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    s1, s2, th = principal_stresses(q @ np.diag([3.0, -1.0]) @ q.T)
    assert (s1, s2) == pytest.approx((3.0, -1.0)) and th == pytest.approx(a)
    s1, s2, th = principal_stresses(np.diag([-1.0, 3.0]))
    assert (s1, s2) == (3.0, -1.0) and th == pytest.approx(np.pi / 2)


# ---------------------------------------------------------------- criteria, by hand

# Three balanced contact forces on a particle, by hand: branch vectors r_c = x_c - x_G
# (0, 1), (-1, -1), (1, -1) with forces (0, -2), (1, 1), (-1, 1) kN sum to
# sum r (x) F = [[-2, 0], [0, -4]] kN m, so with V = A t = 2 m^2 * 0.5 m = 1 m^3:
# sigma = diag(-2000, -4000) Pa, sigma_1 = -2000 Pa along x (theta_p = 0).
_R = np.array([[0.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
_F = 1e3 * np.array([[0.0, -2.0], [1.0, 1.0], [-1.0, 1.0]])
_G = np.array([0.3, -0.2])


def _hand_case(angle):
    q = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    sigma = averaged_stress(_G + _R @ q.T, _F @ q.T, _G, area=2.0, thickness=0.5)
    return sigma


@pytest.mark.parametrize("angle", [0.0, np.deg2rad(30.0), np.deg2rad(-100.0)])
def test_criteria_for_a_hand_computed_particle(angle):
    sigma = _hand_case(angle)
    q = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    np.testing.assert_allclose(sigma, q @ np.diag([-2000.0, -4000.0]) @ q.T, atol=1e-9)
    theta_p = angle  # direction of sigma_1 = -2000 Pa

    sc = split_cell_criterion(sigma, _G, tensile_strength=500.0)
    assert sc.value == pytest.approx((3 * -2000.0 + 4000.0) / 2)  # -1000 Pa: no tension
    assert not sc.breaks and sc.threshold == 500.0
    assert _same_angles(sc.lines, [theta_p + np.pi / 2])
    np.testing.assert_array_equal(sc.lines[:, 0], [_G])

    cc = cross_cut_criterion(sigma, _G, 2.0, strength=3000.0)
    assert cc.value == pytest.approx(np.sqrt(2000.0**2 + 4000.0**2 - 2000.0 * 4000.0))
    assert cc.threshold == 3000.0 and cc.breaks  # 3464 Pa >= 3000 Pa
    assert _same_angles(cc.lines, [theta_p + np.pi / 4, theta_p - np.pi / 4])
    sized = cross_cut_criterion(sigma, _G, 2.0, strength=3000.0, reference_radius=1.0)
    assert sized.threshold == pytest.approx(3000.0 / np.sqrt(2.0 / np.pi))  # 3760 Pa
    assert not sized.breaks

    mc = mohr_coulomb_criterion(sigma, _G, tensile_strength=300.0, compressive_strength=5000.0)
    assert mc.value == pytest.approx(4000.0) and mc.threshold == 5000.0  # both compressive
    assert not mc.breaks
    assert _same_angles(mc.lines, [theta_p + np.pi / 4])


def test_split_cell_on_the_brazilian_disc():
    p, r, t = 100.0, 0.01, 0.005
    contacts, forces = _brazilian(p, r)
    sigma = averaged_stress(contacts, forces, [0.0, 0.0], np.pi * r**2, t)
    tension = p / (np.pi * r * t)  # closed-form tension at the disc centre
    res = split_cell_criterion(sigma, [0.0, 0.0], tensile_strength=0.9 * tension)
    assert res.value == pytest.approx(tension, rel=1e-14) and res.breaks
    assert _same_angles(res.lines, [np.pi / 2])  # split along the loaded diameter
    assert not split_cell_criterion(sigma, [0.0, 0.0], 1.1 * tension).breaks
    # the plane cuts the disc (as a 64-gon) into two equal halves
    ang = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    disc = r * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    halves = split_convex(disc, res.lines)
    assert [_area(h) for h in halves] == pytest.approx([_area(disc) / 2] * 2, rel=1e-12)


def test_cross_cut_gives_four_quarters():
    sigma = np.diag([1e6, -3e6])
    res = cross_cut_criterion(sigma, [0.0, 0.0], 4.0, strength=1e6)
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    quarters = split_convex(square, res.lines)
    assert [_area(f) for f in quarters] == pytest.approx([1.0] * 4)


@pytest.mark.parametrize(
    ("s1", "s2", "value", "threshold"),
    [
        (-1e6, -3e6, 3e6, 20e6),  # both compressive: -sigma_2 vs sigma_C
        (3e6, 1e6, 3e6, 2e6),  # both tensile: sigma_1 vs sigma_T
        (1e6, -5e6, 1e6 + 0.1 * 5e6, 2e6),  # mixed: |s1 - (sT/sC) s2| vs sigma_T
        (0.0, -5e6, 5e6, 20e6),  # sigma_1 = 0 counts as compressive
    ],
)
def test_mohr_coulomb_cases(s1, s2, value, threshold):
    res = mohr_coulomb_criterion(np.diag([s2, s1]), [0.0, 0.0], 2e6, 20e6)
    assert res.value == pytest.approx(value) and res.threshold == threshold
    assert res.breaks == (value > threshold)
    assert _same_angles(res.lines, [np.pi / 2 + np.pi / 4])  # theta_p = pi/2 here


def test_mohr_coulomb_is_continuous_across_cases():
    st, sc = 2e6, 20e6
    for s2 in (-1e6, -7e6):
        below = mohr_coulomb_criterion(np.diag([-1e-9, s2]), [0, 0], st, sc)
        above = mohr_coulomb_criterion(np.diag([1e-9, s2]), [0, 0], st, sc)
        assert below.value / below.threshold == pytest.approx(above.value / above.threshold)
    for s1 in (1e6, 3e6):
        mixed = mohr_coulomb_criterion(np.diag([s1, -1e-9]), [0, 0], st, sc)
        tensile = mohr_coulomb_criterion(np.diag([s1, 1e-9]), [0, 0], st, sc)
        assert mixed.value / mixed.threshold == pytest.approx(tensile.value / tensile.threshold)


# ---------------------------------------------------------------- breakage type


@pytest.mark.parametrize(
    ("masses", "kind"),
    [
        ([0.5, 0.5], "splitting"),
        ([0.41, 0.59], "splitting"),
        ([0.4, 0.6], "fragmentation"),
        ([0.1, 0.2, 0.7], "fragmentation"),
        ([0.0999, 0.9], "chipping"),
        ([0.01, 0.99], "chipping"),
    ],
)
def test_breakage_type_thresholds(masses, kind):
    assert breakage_type(masses, 1.0) == kind
    assert breakage_type(np.array(masses) * 4.0, 4.0) == kind  # a ratio, not a mass


def test_breakage_type_rejects_bad_input():
    with pytest.raises(ValueError):
        breakage_type([], 1.0)
    with pytest.raises(ValueError):
        breakage_type([0.5], 0.0)
