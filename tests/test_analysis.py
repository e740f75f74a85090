"""Post-processing: fits with uncertainties, Hoek-Brown, invariants, burst statistics (maximum
likelihood), avalanche onset and crack orientation."""

import math

import numpy as np
import pytest
from scipy.special import zeta

from jaxgran import analysis as an


def test_linear_fit_exact_and_noisy():
    x = np.linspace(0.0, 1.0, 11)
    fit = an.linear_fit(x, 3.0 * x - 2.0)
    assert fit["slope"] == pytest.approx(3.0, abs=1e-12)
    assert fit["intercept"] == pytest.approx(-2.0, abs=1e-12)
    assert fit["r2"] == pytest.approx(1.0)
    rng = np.random.default_rng(0)
    x = np.linspace(0.0, 1.0, 200)
    y = 3.0 * x - 2.0 + rng.normal(0.0, 0.1, x.size)
    fit = an.linear_fit(x, y)
    assert abs(fit["slope"] - 3.0) < 3.0 * fit["slope_err"]
    # the textbook standard error sigma / sqrt(sum (x - mean)^2)
    expect = 0.1 / math.sqrt(((x - x.mean()) ** 2).sum())
    assert fit["slope_err"] == pytest.approx(expect, rel=0.15)
    with pytest.raises(ValueError, match="2 distinct"):
        an.linear_fit([1.0, 1.0], [0.0, 1.0])


def test_brazilian_eq16_and_slope_eq17():
    d, t = 0.1, 0.01
    assert an.brazilian_tensile_strength(1000.0, d, t) == pytest.approx(2000.0 / (math.pi * d * t))
    # a linear rise F = k eps up to eps_max then a drop: S = 2 k (eps_max / 2) / (eps_max T)
    eps = np.linspace(0.0, 0.03, 301)
    k = 5.0e6
    force = np.where(eps <= 0.02, k * eps, k * 0.02 * np.exp(-(eps - 0.02) / 1e-3))
    s = an.brazilian_slope(eps, force, t)
    assert s["strain_at_max"] == pytest.approx(0.02)
    assert s["force_max"] == pytest.approx(k * 0.02)
    assert s["slope_S"] == pytest.approx(k / t, rel=1e-12)


def test_invariants_are_work_conjugate():
    rng = np.random.default_rng(1)
    s1, s3, e1, e3 = rng.normal(size=(4, 50))
    p, q = an.pq_invariants(s1, s3)
    ev, ed = an.strain_invariants(e1, e3)
    np.testing.assert_allclose(p * ev + q * ed, s1 * e1 + s3 * e3, atol=1e-14)
    np.testing.assert_allclose(p + q, s1, atol=1e-15)
    np.testing.assert_allclose(p - q, s3, atol=1e-15)


def _hoek_brown_data(noise: float, seed: int):
    """PHYSICS §F: intact rock, sigma_ci = 50 MPa, m_i = 12 (A = m sigma_ci, B = sigma_ci)."""
    sigma_ci, m_i = 50.0, 12.0
    s3 = np.linspace(0.0, 30.0, 12)
    s1 = an.hoek_brown_sigma1(s3, m_i * sigma_ci, sigma_ci)
    rng = np.random.default_rng(seed)
    return s1 * (1.0 + noise * rng.normal(size=s1.size)), s3, m_i * sigma_ci, sigma_ci


def test_hoek_brown_fit_recovers_parameters():
    s1, s3, a, b = _hoek_brown_data(0.0, 0)
    fit = an.hoek_brown_fit(s1, s3)
    assert fit["A"] == pytest.approx(a, rel=1e-10)
    assert fit["B"] == pytest.approx(b, rel=1e-10)
    assert fit["r2"] == pytest.approx(1.0) and fit["m_i"] == pytest.approx(12.0)
    # 2 % noise (PHYSICS §F: 49.75, 12.30): within the reported uncertainty
    s1, s3, a, b = _hoek_brown_data(0.02, 0)
    fit = an.hoek_brown_fit(s1, s3)
    assert abs(fit["A"] - a) < 3.0 * fit["A_err"]
    assert abs(fit["B"] - b) < 3.0 * fit["B_err"]
    assert 0.0 < fit["A_err"] < 0.2 * a and 0.0 < fit["B_err"] < 0.1 * b
    assert fit["r2"] > 0.98
    cov = np.asarray(fit["cov"])
    assert cov[0, 0] == pytest.approx(fit["A_err"] ** 2)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # the uncertainty is not over-optimistic: over many noisy data sets the truth lies within
    # 2 standard errors nearly always (the regression's errors are heteroscedastic, so the
    # coverage is only approximately the Gaussian 95 %)
    hits = np.zeros(2)
    for seed in range(200):
        s1, s3, a, b = _hoek_brown_data(0.02, seed)
        f = an.hoek_brown_fit(s1, s3)
        hits += [abs(f["A"] - a) < 2.0 * f["A_err"], abs(f["B"] - b) < 2.0 * f["B_err"]]
    assert np.all(hits / 200 >= 0.85)


def test_hoek_brown_in_2d_invariants():
    a, b = 600.0, 50.0
    s3 = np.linspace(-2.0, 40.0, 9)
    s1 = an.hoek_brown_sigma1(s3, a, b)
    p, q = an.pq_invariants(s1, s3)
    np.testing.assert_allclose(an.hoek_brown_q(p, a, b), q, rtol=1e-12)


def test_hoek_brown_fit_pq_recovers_parameters_and_their_errors():
    """Eq. 31 (2D) fitted to q(p) with q noisy and p exact, as in a constant-p test."""
    a, b = 600.0, 50.0
    p = np.linspace(5.0, 80.0, 10)
    q = an.hoek_brown_q(p, a, b)
    fit = an.hoek_brown_fit_pq(p, q)
    assert fit["A"] == pytest.approx(a, rel=1e-6)
    assert fit["B"] == pytest.approx(b, rel=1e-6)
    assert fit["r2"] == pytest.approx(1.0) and not fit["at_bound"]
    # with exact data both regressions agree (same envelope, Eq. 30 <=> Eq. 31)
    s = an.hoek_brown_fit(p + q, p - q)
    assert s["A"] == pytest.approx(fit["A"], rel=1e-6)
    hits = np.zeros(2)
    for seed in range(100):
        rng = np.random.default_rng(seed)
        f = an.hoek_brown_fit_pq(p, q + rng.normal(0.0, 1.0, q.size))
        hits += [abs(f["A"] - a) < 2.0 * f["A_err"], abs(f["B"] - b) < 2.0 * f["B_err"]]
    assert np.all(hits / 100 >= 0.85)


def test_hoek_brown_fit_pq_tresca_limit():
    """q independent of p is Hoek-Brown with A = 0 (m_i = 0, Tresca): exact data put the
    fit on its bound and it says so; with scatter A is consistent with 0 and R^2 of q is
    near 0, as nothing in q is explained by p."""
    p = np.repeat([50.0, 100.0, 150.0, 200.0], 4)
    flat = an.hoek_brown_fit_pq(p, np.full(p.size, 240.0))
    assert flat["at_bound"] and flat["A"] == pytest.approx(0.0, abs=1e-6)
    assert flat["B"] == pytest.approx(480.0, rel=1e-9)
    q = 240.0 + np.random.default_rng(7).normal(0.0, 5.0, p.size)
    fit = an.hoek_brown_fit_pq(p, q)
    assert abs(fit["A"]) < 2.0 * fit["A_err"]
    assert fit["B"] == pytest.approx(2.0 * q.mean(), rel=0.02)
    assert fit["r2"] < 0.2


def test_frictional_line_gives_the_mohr_coulomb_angle():
    phi, c = math.radians(30.0), 10.0
    p = np.linspace(50.0, 300.0, 8)
    q = p * math.sin(phi) + c * math.cos(phi)
    line = an.frictional_line(p, q)
    assert line["friction_angle_deg"] == pytest.approx(30.0, rel=1e-10)
    assert line["cohesion_Pa"] == pytest.approx(c, rel=1e-10)
    assert line["r2"] == pytest.approx(1.0)


def _continuous_power_law(alpha, x_min, n, rng):
    return x_min * (1.0 - rng.random(n)) ** (-1.0 / (alpha - 1.0))


def _discrete_power_law(alpha, x_min, n, rng, k_max=10**6):
    k = np.arange(x_min, k_max + 1, dtype=float)
    cdf = np.cumsum(k**-alpha) / zeta(alpha, x_min)
    return k[np.minimum(np.searchsorted(cdf, rng.random(n)), k.size - 1)]


@pytest.mark.parametrize("alpha", [1.5, 2.5])
def test_power_law_mle_continuous_recovers_exponent(alpha):
    rng = np.random.default_rng(2)
    s = _continuous_power_law(alpha, 1.0, 4000, rng)
    fit = an.power_law_mle(s, 1.0, discrete=False)
    assert abs(fit["alpha"] - alpha) < 3.0 * fit["alpha_err"]
    assert fit["alpha_err"] == pytest.approx((alpha - 1) / math.sqrt(4000), rel=0.05)
    assert fit["ks"] < 0.03


def test_power_law_mle_discrete_recovers_exponent_and_its_error():
    alpha = 2.5  # global-load-sharing fibre bundle (PHYSICS §F)
    rng = np.random.default_rng(3)
    fit = an.power_law_mle(_discrete_power_law(alpha, 1, 3000, rng), 1)
    assert abs(fit["alpha"] - alpha) < 3.0 * fit["alpha_err"]
    assert fit["ks"] < 0.03
    # the standard error matches the scatter of the estimate over repeated samples
    est = [an.power_law_mle(_discrete_power_law(alpha, 1, 500, rng), 1) for _ in range(60)]
    spread = np.std([e["alpha"] for e in est], ddof=1)
    assert np.mean([e["alpha_err"] for e in est]) == pytest.approx(spread, rel=0.3)
    # the continuous formula applied to discrete data is biased (why the discrete MLE)
    cont = an.power_law_mle(_discrete_power_law(alpha, 1, 3000, rng), 1, discrete=False)
    assert abs(cont["alpha"] - alpha) > 5 * cont["alpha_err"]


def test_power_law_scan_finds_x_min():
    rng = np.random.default_rng(4)
    tail = _discrete_power_law(2.0, 10, 1500, rng)
    body = rng.integers(1, 10, 1500).astype(float)  # flat, not a power law
    fit = an.power_law_scan(np.concatenate([body, tail]))
    assert 8 <= fit["x_min"] <= 14
    assert abs(fit["alpha"] - 2.0) < 3.0 * fit["alpha_err"] + 0.05


def test_burst_sizes_and_log_histogram():
    t = np.array([0.05, 0.15, 0.16, 0.17, 0.35, np.inf, 0.36])
    counts, edges = an.burst_sizes(t, 0.1, t_start=0.0, t_end=0.4)
    np.testing.assert_array_equal(counts, [1, 3, 0, 2])
    np.testing.assert_allclose(edges, [0.0, 0.1, 0.2, 0.3, 0.4])
    x, dens = an.log_histogram(_discrete_power_law(2.0, 1, 2000, np.random.default_rng(5)))
    assert np.all(np.diff(x) > 0) and dens[0] > dens[-1]


def test_second_avalanche_onset():
    t = np.linspace(0.0, 10e-3, 201)
    n = (
        20.0 * np.clip(t / 1e-3, 0.0, 1.0)  # first breaking during loading, then quiet
        + 300.0 * np.clip((t - 6e-3) / 0.5e-3, 0.0, 1.0)  # the avalanche at the peak
    )
    out = an.second_avalanche(t, n, smooth=1)
    assert out["onset_time"] == pytest.approx(6e-3, abs=1e-4)
    assert out["first_onset_time"] == pytest.approx(0.0, abs=1e-4)
    assert out["n_before"] == pytest.approx(20.0, abs=1.0)
    quiet = an.second_avalanche(t, np.zeros_like(t))
    assert quiet["onset_time"] is None


def test_principal_axis_angle_of_a_crack():
    rng = np.random.default_rng(6)
    s = rng.uniform(-1.0, 1.0, 400)
    phi = math.radians(10.0)  # the crack runs 10 deg off the vertical
    pts = np.stack([s * math.sin(phi), s * math.cos(phi)], axis=1)
    pts += rng.normal(0.0, 0.05, pts.shape)
    out = an.principal_axis_angle(pts)
    assert out["angle_deg"] == pytest.approx(10.0, abs=2.0)
    assert out["elongation"] > 5.0
    # translation does not matter, a rotation by 90 deg gives the complement
    shifted = an.principal_axis_angle(pts + [3.0, -1.0])
    assert shifted["angle_deg"] == pytest.approx(out["angle_deg"], abs=1e-9)
    turned = an.principal_axis_angle(pts @ np.array([[0.0, 1.0], [-1.0, 0.0]]))
    assert turned["angle_deg"] == pytest.approx(90.0 - out["angle_deg"], abs=1e-9)


def test_summary_stats():
    out = an.summary_stats([{"a": 1.0, "b": "x"}, {"a": 3.0, "c": True}])
    assert out == {"a": {"mean": 2.0, "std": pytest.approx(math.sqrt(2.0)), "n": 2}}


def _n_components(i, j, n):
    return len(an.fragments(i, j, n))


def test_bridges_are_the_edges_whose_removal_disconnects_the_graph():
    """Against the definition, edge by edge, on random sparse multigraphs (parallel edges,
    isolated nodes, several components)."""
    rng = np.random.default_rng(3)
    for _ in range(60):
        n = int(rng.integers(1, 25))
        e = int(rng.integers(0, 2 * n))
        i = rng.integers(0, n, e)
        j = (i + rng.integers(1, n, e)) % n if n > 1 else i  # no self loops
        if n == 1:
            i = j = np.zeros(0, int)
        got = an.bridge_edges(i, j, n)
        base = _n_components(i, j, n)
        for k in range(len(i)):
            keep = np.arange(len(i)) != k
            assert got[k] == (_n_components(i[keep], j[keep], n) > base)


def test_two_blocks_joined_by_a_thread_are_two_fragments_only_with_split_bridges():
    """Two 4-cliques joined by a path through two extra nodes: one component by
    connectivity, the two cliques (and two singletons) once the bridges are removed; a
    second path between them makes the whole graph one 2-edge-connected fragment."""
    a = [(p, q) for p in range(4) for q in range(p + 1, 4)]
    b = [(p + 4, q + 4) for p, q in a]
    thread = [(0, 8), (8, 9), (9, 4)]
    i, j = np.array(a + b + thread).T
    assert [len(f) for f in an.fragments(i, j, 10)] == [10]
    parts = an.fragments(i, j, 10, split_bridges=True)
    assert [len(f) for f in parts] == [4, 4, 1, 1]
    assert {tuple(parts[0]), tuple(parts[1])} == {(0, 1, 2, 3), (4, 5, 6, 7)}
    i2, j2 = np.array(a + b + thread + [(1, 5)]).T
    assert [len(f) for f in an.fragments(i2, j2, 10, split_bridges=True)] == [10]
    with pytest.raises(ValueError, match="edge ends"):
        an.bridge_edges([0], [5], 3)
