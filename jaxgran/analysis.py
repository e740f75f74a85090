"""Post-processing of lab tests: fits, strength envelopes, invariants, burst statistics and
fracture orientation. Host-side numpy/scipy; nothing here is traced.

Sign conventions: stresses and strains are **compression positive** (geomechanics). In 2D
(plane stress, paper 002 Eq. 20-23 reduced to two principal directions) the invariants are
``p = (s1 + s3) / 2``, ``q = (s1 - s3) / 2`` (the Mohr-circle centre and radius),
``eps_v = e1 + e3`` and ``eps_d = e1 - e3``, a work-conjugate pair:
``p eps_v + q eps_d = s1 e1 + s3 e3``.
"""

from __future__ import annotations

import math

import numpy as np

# ------------------------------------------------------------------------------ fits


def linear_fit(x, y) -> dict[str, float]:
    """Ordinary least-squares line ``y = slope x + intercept``.

    Returns slope, intercept, their standard errors and covariance (``cov`` 2x2, order
    slope, intercept; from the residual variance with n - 2 degrees of freedom), ``r2``
    (coefficient of determination) and ``n``.
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = x.size
    if n < 2 or np.ptp(x) == 0:
        raise ValueError(f"a line needs at least 2 distinct x values, got {n} points")
    a = np.stack([x, np.ones_like(x)], axis=1)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = y - a @ coef
    ss_res = float(resid @ resid)
    ss_tot = float(((y - y.mean()) ** 2).sum())
    dof = max(n - 2, 1)
    cov = np.linalg.inv(a.T @ a) * ss_res / dof if n > 2 else np.full((2, 2), np.nan)
    return {
        "slope": float(coef[0]),
        "intercept": float(coef[1]),
        "slope_err": float(np.sqrt(cov[0, 0])),
        "intercept_err": float(np.sqrt(cov[1, 1])),
        "cov": cov.tolist(),
        "r2": 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0,
        "n": int(n),
    }


def fit_window(x, y, lo: float, hi: float) -> dict[str, float]:
    """:func:`linear_fit` of the points whose ``y`` lies between ``lo`` and ``hi`` times
    ``max(y)`` up to the peak (the elastic part of a loading curve, e.g. E_c, Eq. 25)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    k = int(np.nanargmax(y))
    top = y[k]
    sel = np.zeros_like(y, dtype=bool)
    sel[: k + 1] = (y[: k + 1] >= lo * top) & (y[: k + 1] <= hi * top)
    if sel.sum() < 3:
        sel[: k + 1] = True
    return linear_fit(x[sel], y[sel])


# ------------------------------------------------------------------------------ Brazilian


def brazilian_tensile_strength(f_max: float, diameter: float, thickness: float) -> float:
    """Tensile strength sigma_t = 2 F_max / (pi D T) (Pa), paper 002 Eq. 16; F_max (N),
    D and T (m)."""
    if not (diameter > 0 and thickness > 0):
        raise ValueError("diameter and thickness must be > 0 m")
    return 2.0 * f_max / (math.pi * diameter * thickness)


def brazilian_slope(strain, force, thickness: float) -> dict[str, float]:
    """Primary slope S = 2 F(eps_max / 2) / (eps_max T) (N/m^2 = Pa), paper 002 Eq. 17,
    with F interpolated at half the strain of the peak force; also returns F_max (N) and
    eps_max."""
    e = np.asarray(strain, float)
    f = np.asarray(force, float)
    k = int(np.nanargmax(f))
    e_max, f_max = float(e[k]), float(f[k])
    if e_max <= 0:
        raise ValueError("the peak force is at zero strain; load the specimen first")
    f_half = float(np.interp(0.5 * e_max, e[: k + 1], f[: k + 1]))
    return {
        "slope_S": 2.0 * f_half / (e_max * thickness),
        "force_max": f_max,
        "strain_at_max": e_max,
        "force_at_half_strain": f_half,
    }


# ------------------------------------------------------------------------------ invariants


def pq_invariants(sigma_1, sigma_3) -> tuple[np.ndarray, np.ndarray]:
    """2D mean and deviatoric stress ``p = (s1 + s3) / 2``, ``q = (s1 - s3) / 2`` (Pa)."""
    s1, s3 = np.asarray(sigma_1, float), np.asarray(sigma_3, float)
    return 0.5 * (s1 + s3), 0.5 * (s1 - s3)


def strain_invariants(eps_1, eps_3) -> tuple[np.ndarray, np.ndarray]:
    """2D volumetric and deviatoric strain ``eps_v = e1 + e3``, ``eps_d = e1 - e3``."""
    e1, e3 = np.asarray(eps_1, float), np.asarray(eps_3, float)
    return e1 + e3, e1 - e3


# ------------------------------------------------------------------------------ Hoek-Brown


def hoek_brown_sigma1(sigma_3, a: float, b: float) -> np.ndarray:
    """Hoek-Brown peak strength s1 = s3 + sqrt(A s3 + B^2) (Pa), paper 002 Eq. 30."""
    s3 = np.asarray(sigma_3, float)
    return s3 + np.sqrt(np.maximum(a * s3 + b * b, 0.0))


def hoek_brown_q(p, a: float, b: float) -> np.ndarray:
    """Eq. 30 in the 2D invariants (s1 = p + q, s3 = p - q): ``4 q^2 = A (p - q) + B^2``,
    i.e. ``q = (sqrt(A^2 + 16 (A p + B^2)) - A) / 8`` (Pa); the 3D form is Eq. 31."""
    p = np.asarray(p, float)
    return (np.sqrt(np.maximum(a * a + 16.0 * (a * p + b * b), 0.0)) - a) / 8.0


def hoek_brown_fit(sigma_1, sigma_3) -> dict[str, float]:
    """Fit Eq. 30 to peak strengths by the linear regression of Hoek & Brown (1997):
    ``(s1 - s3)^2 = A s3 + B^2`` (PHYSICS §F; A = m_i sigma_ci, B = sigma_ci).

    Returns A (Pa) and B (Pa) with standard errors and covariance (``cov``, order A, B,
    propagated from the regression: dB = d(B^2) / (2 B)), ``r2_regression`` of the line,
    ``r2`` of s1 predicted by Eq. 30, and ``sigma_ci`` = B, ``m_i`` = A / B.
    """
    s1 = np.asarray(sigma_1, float).ravel()
    s3 = np.asarray(sigma_3, float).ravel()
    if s1.size < 3:
        raise ValueError("a Hoek-Brown fit needs at least 3 (sigma_1, sigma_3) points")
    line = linear_fit(s3, (s1 - s3) ** 2)
    a, b2 = line["slope"], line["intercept"]
    if not b2 > 0:
        raise ValueError(
            f"Hoek-Brown regression gave B^2 = {b2:.3g} Pa^2 <= 0: the envelope is not "
            "concave; check the peak strengths (compression positive)"
        )
    b = math.sqrt(b2)
    jac = np.array([[1.0, 0.0], [0.0, 0.5 / b]])
    cov = jac @ np.asarray(line["cov"]) @ jac.T
    pred = hoek_brown_sigma1(s3, a, b)
    ss_tot = float(((s1 - s1.mean()) ** 2).sum())
    r2 = 1.0 - float(((s1 - pred) ** 2).sum()) / ss_tot if ss_tot > 0 else 1.0
    return {
        "A": a,
        "B": b,
        "A_err": float(np.sqrt(cov[0, 0])),
        "B_err": float(np.sqrt(cov[1, 1])),
        "cov": cov.tolist(),
        "r2_regression": line["r2"],
        "r2": r2,
        "sigma_ci": b,
        "m_i": a / b,
        "n": int(s1.size),
    }


def hoek_brown_fit_pq(p, q) -> dict[str, float]:
    """Fit Eq. 31 in the 2D invariants, ``q(p) = (sqrt(A^2 + 16 (A p + B^2)) - A) / 8``
    (:func:`hoek_brown_q`), to peak deviatoric stresses q (Pa) at mean stresses p (Pa) by
    nonlinear least squares in q.

    In a constant-p test p is the controlled variable and q_peak the measured one, so this is
    the regression with the error where it belongs (paper 002 fits Eq. 31 to its p-q
    envelope, Fig. 22); :func:`hoek_brown_fit` regresses on s3 = p - q, which carries the
    scatter of q. A >= 0 (m_i >= 0) is enforced.

    Returns A, B (Pa) with standard errors and covariance (``cov``, order A, B; from the
    Jacobian at the optimum and the residual variance with n - 2 degrees of freedom), ``r2``
    of q, ``rmse`` (Pa), ``at_bound`` (True when A = 0, the Tresca limit: q independent of
    p), ``sigma_ci`` = B, ``m_i`` = A / B and ``n``.
    """
    from scipy.optimize import least_squares

    p = np.asarray(p, float).ravel()
    q = np.asarray(q, float).ravel()
    ok = np.isfinite(p) & np.isfinite(q)
    p, q = p[ok], q[ok]
    n = p.size
    if n < 3:
        raise ValueError(f"a Hoek-Brown fit needs at least 3 (p, q) points, got {n}")
    scale = float(np.max(np.abs(q)))
    if not scale > 0:
        raise ValueError("all q are zero: no envelope to fit")
    # start from the Hoek & Brown regression when it is valid, else from a Tresca envelope
    try:
        start = hoek_brown_fit(p + q, p - q)
        x0 = [max(start["A"], 0.0) / scale, start["B"] / scale]
    except ValueError:
        x0 = [0.0, 2.0 * float(np.mean(q)) / scale]
    pn = p / scale
    fun = lambda x: hoek_brown_q(pn, x[0], x[1]) - q / scale
    res = least_squares(fun, x0, bounds=([0.0, 1e-12], [np.inf, np.inf]), x_scale=1.0)
    a, b = res.x * scale
    resid = res.fun * scale
    ss_res = float(resid @ resid)
    ss_tot = float(((q - q.mean()) ** 2).sum())
    jac = res.jac  # d(q / scale) / d(x), x = (A, B) / scale: same as dq / d(A, B)
    dof = max(n - 2, 1)
    try:
        cov = np.linalg.inv(jac.T @ jac) * ss_res / dof
    except np.linalg.LinAlgError:
        cov = np.full((2, 2), np.nan)
    return {
        "A": float(a),
        "B": float(b),
        "A_err": float(np.sqrt(cov[0, 0])),
        "B_err": float(np.sqrt(cov[1, 1])),
        "cov": cov.tolist(),
        "r2": 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0,
        "rmse": math.sqrt(ss_res / n),
        "at_bound": bool(a <= 1e-9 * scale),
        "sigma_ci": float(b),
        "m_i": float(a / b),
        "n": int(n),
    }


def frictional_line(p, q) -> dict[str, float]:
    """Straight envelope ``q = M p + c`` of residual (critical) states (Pa): :func:`linear_fit`
    plus the 2D friction angle ``phi = asin(M)`` (deg) and cohesion ``c / cos(phi)`` (Pa) of
    the Mohr-Coulomb line that the 2D invariants give (``q = p sin phi + c cos phi``)."""
    fit = linear_fit(p, q)
    m = fit["slope"]
    out = dict(fit)
    if abs(m) < 1.0:
        phi = math.asin(m)
        out["friction_angle_deg"] = math.degrees(phi)
        out["cohesion_Pa"] = fit["intercept"] / math.cos(phi)
    return out


# ------------------------------------------------------------------------------ bursts


def burst_sizes(break_times, window: float, *, t_start=None, t_end=None):
    """Broken bonds per time window (paper 002 §4.6): counts ``[n_windows]`` and window
    edges ``[n_windows + 1]`` (s). ``break_times`` (s) may contain +inf (intact bonds,
    ignored)."""
    t = np.asarray(break_times, float).ravel()
    t = t[np.isfinite(t)]
    if not window > 0:
        raise ValueError(f"window must be > 0 s, got {window}")
    if t.size == 0:
        return np.zeros(0, int), np.zeros(1)
    t0 = float(t.min()) if t_start is None else float(t_start)
    t1 = float(t.max()) if t_end is None else float(t_end)
    n = max(1, int(math.ceil((t1 - t0) / window - 1e-9)))
    edges = t0 + window * np.arange(n + 1)
    counts, _ = np.histogram(np.clip(t, t0, edges[-1]), bins=edges)
    return counts, edges


def log_histogram(sizes, n_bins: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Probability density of positive sizes in logarithmic bins: centres and density
    (for plotting a power law; the exponent comes from :func:`power_law_mle`)."""
    s = np.asarray(sizes, float)
    s = s[s > 0]
    if s.size == 0:
        return np.zeros(0), np.zeros(0)
    edges = np.unique(np.floor(np.geomspace(s.min(), s.max() + 1, n_bins + 1)))
    if edges.size < 2:
        edges = np.array([s.min(), s.min() + 1])
    counts, edges = np.histogram(s, bins=edges)
    width = np.diff(edges)
    centres = np.sqrt(edges[:-1] * np.maximum(edges[1:] - 1, edges[:-1]))
    return centres, counts / (width * s.size)


def _discrete_nll(alpha: float, s: np.ndarray, x_min: int) -> float:
    from scipy.special import zeta

    return float(alpha * np.log(s).sum() + s.size * np.log(zeta(alpha, x_min)))


def power_law_mle(sizes, x_min: float = 1, *, discrete: bool = True) -> dict[str, float]:
    """Maximum-likelihood exponent alpha of ``P(s) ~ s^-alpha`` for ``s >= x_min``
    (Clauset, Shalizi & Newman 2009, SIAM Rev. 51:661), not a least-squares fit.

    Continuous: ``alpha = 1 + n / sum(ln(s / x_min))``, standard error ``(alpha - 1) /
    sqrt(n)``. Discrete: the exact likelihood ``-alpha sum(ln s) - n ln zeta(alpha, x_min)``
    (Hurwitz zeta) is maximised numerically; the standard error is ``1 / sqrt(n I)`` with the
    Fisher information ``I`` = the second derivative of ``ln zeta`` in alpha.

    Returns alpha, alpha_err, n (sizes used), x_min and the KS distance between the data and
    the fitted law (for choosing x_min, see :func:`power_law_scan`).
    """
    s = np.asarray(sizes, float).ravel()
    s = s[np.isfinite(s) & (s >= x_min)]
    n = s.size
    if n < 2:
        raise ValueError(f"a power-law fit needs at least 2 sizes >= x_min = {x_min}, got {n}")
    if not discrete:
        if not x_min > 0:
            raise ValueError("continuous power law needs x_min > 0")
        total = float(np.log(s / x_min).sum())
        if total <= 0:
            raise ValueError("all sizes equal x_min: the exponent is undefined")
        alpha = 1.0 + n / total
        err = (alpha - 1.0) / math.sqrt(n)
        xs = np.unique(s)
        cdf_fit = 1.0 - (xs / x_min) ** (1.0 - alpha)
    else:
        from scipy.optimize import minimize_scalar
        from scipy.special import zeta

        x_min = int(round(x_min))
        if x_min < 1:
            raise ValueError("discrete power law needs x_min >= 1")
        if np.all(s == x_min):
            raise ValueError("all sizes equal x_min: the exponent is undefined")
        res = minimize_scalar(
            _discrete_nll,
            bounds=(1.0 + 1e-6, 8.0),
            args=(s, x_min),
            method="bounded",
            options={"xatol": 1e-10},
        )
        alpha = float(res.x)
        h = 1e-4 * alpha
        lz = lambda a: math.log(zeta(a, x_min))
        fisher = (lz(alpha + h) - 2.0 * lz(alpha) + lz(alpha - h)) / (h * h)
        err = 1.0 / math.sqrt(n * fisher) if fisher > 0 else float("nan")
        xs = np.unique(s)
        cdf_fit = 1.0 - zeta(alpha, xs + 1.0) / zeta(alpha, x_min)
    emp = np.searchsorted(np.sort(s), xs, side="right") / n
    ks = float(np.max(np.abs(emp - cdf_fit)))
    return {"alpha": alpha, "alpha_err": err, "n": int(n), "x_min": float(x_min), "ks": ks}


def power_law_scan(sizes, *, discrete: bool = True, min_tail: int = 20) -> dict[str, float]:
    """:func:`power_law_mle` with the x_min that minimises the KS distance (CSN 2009 §3.3),
    over the distinct sizes that leave at least ``min_tail`` data in the tail."""
    s = np.asarray(sizes, float)
    s = s[np.isfinite(s) & (s > 0)]
    best = None
    for x in np.unique(s):
        if (s >= x).sum() < min_tail or np.all(s[s >= x] == x):
            continue
        fit = power_law_mle(s, x, discrete=discrete)
        if best is None or fit["ks"] < best["ks"]:
            best = fit
    if best is None:
        raise ValueError(f"fewer than {min_tail} sizes: too few bursts for a power-law fit")
    return best


def second_avalanche(times, n_broken, *, smooth: int = 3, fraction: float = 0.2):
    """Onset of the breaking avalanche that comes with the peak (paper 002 Fig. 23).

    ``n_broken`` is the cumulative count of broken bonds at ``times`` (s). The breaking rate
    is smoothed over ``smooth`` records; the main avalanche is the one with the highest
    rate, and its onset the last record before it where the rate was below ``fraction`` of
    that maximum. Bonds broken before the onset belong to the initial breaking during
    loading (the first increment of Fig. 23).

    Returns ``onset_time``, ``onset_index``, ``max_rate_time``, ``max_rate`` (1/s),
    ``first_onset_time`` (first break before the onset, None if there was none) and
    ``n_before`` (bonds broken before the onset).
    """
    t = np.asarray(times, float)
    n = np.asarray(n_broken, float)
    if t.size < 3:
        raise ValueError("need at least 3 records to find an avalanche")
    rate = np.diff(n) / np.maximum(np.diff(t), 1e-300)
    if smooth > 1:
        rate = np.convolve(rate, np.ones(smooth) / smooth, mode="same")
    if not np.any(rate > 0):
        return {
            "onset_time": None,
            "onset_index": None,
            "max_rate_time": None,
            "max_rate": 0.0,
            "first_onset_time": None,
            "n_before": int(n[-1]),
        }
    k_max = int(np.argmax(rate))
    level = fraction * rate[k_max]
    k = k_max
    while k > 0 and rate[k - 1] >= level:
        k -= 1
    earlier = np.nonzero(np.diff(n[: k + 1]) > 0)[0]
    first = float(t[earlier[0]]) if earlier.size else None
    return {
        "onset_time": float(t[k]),
        "onset_index": int(k),
        "max_rate_time": float(t[k_max + 1]),
        "max_rate": float(rate[k_max]),
        "first_onset_time": first,
        "n_before": int(n[k]),
    }


# ------------------------------------------------------------------------------ fractures


def principal_axis_angle(points, weights=None, reference=(0.0, 1.0)) -> dict[str, float]:
    """Orientation of a point cloud (e.g. broken-bond midpoints, m): the angle (deg, in
    [0, 90]) between its principal axis (largest eigenvalue of the weighted covariance) and
    ``reference`` (default vertical, the Brazilian loading diameter), and the elongation
    ``sqrt(l1 / l2)`` (1 for an isotropic cloud)."""
    x = np.asarray(points, float).reshape(-1, 2)
    if x.shape[0] < 2:
        raise ValueError("need at least 2 points to find a principal axis")
    w = np.ones(len(x)) if weights is None else np.asarray(weights, float).ravel()
    w = w / w.sum()
    c = (w[:, None] * x).sum(axis=0)
    d = x - c
    cov = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(axis=0)
    val, vec = np.linalg.eigh(cov)
    axis = vec[:, 1]
    ref = np.asarray(reference, float) / np.linalg.norm(reference)
    angle = math.degrees(math.acos(min(1.0, abs(float(axis @ ref)))))
    ratio = math.sqrt(val[1] / val[0]) if val[0] > 0 else float("inf")
    return {"angle_deg": angle, "elongation": ratio, "centre": c.tolist()}


def bridge_edges(i, j, n: int) -> np.ndarray:
    """Which edges of the undirected graph on ``n`` nodes with edges ``(i[k], j[k])`` are
    bridges (removing one disconnects its component), ``[E]`` bool.

    Iterative depth-first search with low links (Tarjan 1974), parallel edges allowed (two
    parallel edges are never bridges: only the edge the search came by is skipped)."""
    i = np.asarray(i, dtype=np.int64).ravel()
    j = np.asarray(j, dtype=np.int64).ravel()
    if i.shape != j.shape:
        raise ValueError(f"i and j must have one entry per edge, got {i.shape} and {j.shape}")
    if i.size and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
        raise ValueError(f"edge ends must lie in [0, {n})")
    e = i.size
    ends = np.concatenate([j, i])  # half-edge h (h < e: i -> j, else j -> i) ends here
    start = np.concatenate([i, j])
    order = np.argsort(start, kind="stable")
    first = np.searchsorted(start[order], np.arange(n + 1))
    disc = np.full(n, -1, dtype=np.int64)
    low = np.zeros(n, dtype=np.int64)
    bridge = np.zeros(e, dtype=bool)
    clock = 0
    for root in range(n):
        if disc[root] >= 0:
            continue
        disc[root] = low[root] = clock
        clock += 1
        stack = [(root, -1, first[root])]  # node, edge it was reached by, next half-edge
        while stack:
            v, via, nxt = stack[-1]
            if nxt < first[v + 1]:
                stack[-1] = (v, via, nxt + 1)
                h = order[nxt]
                edge = h % e if e else 0
                if edge == via:
                    continue
                w = ends[h]
                if disc[w] < 0:
                    disc[w] = low[w] = clock
                    clock += 1
                    stack.append((w, edge, first[w]))
                else:
                    low[v] = min(low[v], disc[w])
                continue
            stack.pop()
            if stack:
                u = stack[-1][0]
                low[u] = min(low[u], low[v])
                if low[v] > disc[u]:
                    bridge[via] = True
    return bridge


def fragments(i, j, n: int, *, split_bridges: bool = False) -> list[np.ndarray]:
    """Node index sets of the connected components of the graph ``(i[k], j[k])`` on ``n``
    nodes (e.g. particles linked by intact bonds), largest first.

    With ``split_bridges`` the bridges are removed first: the components are then the
    2-edge-connected ones, so that two pieces joined by nothing but a chain of single links
    (a thread of bonded grains left between the two halves of a split disc) count as two
    fragments, and the grains of the chain as pieces of their own."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    i = np.asarray(i, dtype=np.int64).ravel()
    j = np.asarray(j, dtype=np.int64).ravel()
    if split_bridges:
        keep = ~bridge_edges(i, j, n)
        i, j = i[keep], j[keep]
    g = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    _, label = connected_components(g, directed=False)
    groups = [np.nonzero(label == k)[0] for k in np.unique(label)]
    return sorted(groups, key=len, reverse=True)


def broken_bond_points(state) -> tuple[np.ndarray, np.ndarray]:
    """World positions (m) of the common points of the broken bonds ``[n, 2]`` (midpoint
    of the two bodies' copies) and their break times (s)."""
    from .bonds import bond_kinematics, broken_mask

    k = bond_kinematics(state.particles, state.bonds)
    mid = 0.5 * (np.asarray(k["x_i"]) + np.asarray(k["x_j"]))
    mask = np.asarray(broken_mask(state.bonds))
    return mid[mask], np.asarray(state.bonds.break_time)[mask]


def bond_segments(state, thickness: float, which: str = "broken") -> np.ndarray:
    """Shared edges of the bonds as segments ``[n, 2, 2]`` (m) in the current configuration,
    for drawing cracks: the edge of length ``A / T`` centred on the common point, along the
    bond tangent. ``which`` is "broken" or "intact"."""
    from .bonds import bond_kinematics, broken_mask

    if which not in ("broken", "intact"):
        raise ValueError(f"which must be 'broken' or 'intact', got {which!r}")
    b = state.bonds
    k = bond_kinematics(state.particles, b)
    mid = 0.5 * (np.asarray(k["x_i"]) + np.asarray(k["x_j"]))
    broken = np.asarray(broken_mask(b))
    mask = broken if which == "broken" else np.asarray(b.i < b.j) & ~broken
    half = 0.5 * np.asarray(b.area)[mask] / thickness
    tan = np.asarray(k["tangent"])[mask]
    m = mid[mask]
    return np.stack([m - half[:, None] * tan, m + half[:, None] * tan], axis=1)


def summary_stats(values: list[dict]) -> dict[str, dict[str, float]]:
    """Mean, standard deviation (n - 1) and count of every finite numeric key over a list of
    summaries (one per realisation)."""
    keys = sorted({k for v in values for k, x in v.items() if _is_number(x)})
    out = {}
    for k in keys:
        xs = np.array([float(v[k]) for v in values if _is_number(v.get(k))])
        xs = xs[np.isfinite(xs)]
        if xs.size:
            std = float(xs.std(ddof=1)) if xs.size > 1 else 0.0
            out[k] = {"mean": float(xs.mean()), "std": std, "n": int(xs.size)}
    return out


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
