"""Subset separation method (paper 000, Algorithm 1): property tests and degenerate cases."""

import time

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from jaxgran.breakage.ssm import split_convex

PROPERTY = settings(
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow],
)

# ---------------------------------------------------------------- independent helpers


def _signed_area(poly):
    rel = poly - poly[0]  # relative coordinates: no round-off from a far-away origin
    x, y = rel[:, 0], rel[:, 1]
    return 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _hull(points):
    """Andrew's monotone chain, CCW, collinear points dropped."""
    pts = sorted(set(map(tuple, np.asarray(points, dtype=float))))
    if len(pts) < 3:
        return np.zeros((0, 2))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _diameter(poly):
    return float(np.max(np.linalg.norm(poly[:, None] - poly[None], axis=-1)))


def _line_frame(lines):
    """Unit normals [k, 2] and offsets [k] of lines given by two points."""
    d = lines[:, 1] - lines[:, 0]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    return n, np.einsum("kd,kd->k", n, lines[:, 0])


def _inward(poly, xy):
    """Signed distance [m, n_edges] of points to the edges of a CCW polygon, positive inside."""
    e = np.roll(poly, -1, axis=0) - poly
    n = np.stack([-e[:, 1], e[:, 0]], axis=1) / np.linalg.norm(e, axis=1)[:, None]
    return np.einsum("ed,med->me", n, np.asarray(xy)[:, None, :] - poly[None])


def _crossing_lines(poly, lines, tol):
    n, c = _line_frame(lines)
    d = poly @ n.T - c
    keep = (d.max(axis=0) > tol) & (d.min(axis=0) < -tol)
    return lines[keep]


def _cells_euler(poly, lines, tol):
    """Number of cells of a line arrangement inside a convex polygon (Euler's formula):
    1 + (distinct lines crossing the interior) + sum over distinct interior crossing points
    of (number of lines through the point - 1). Lines cutting less than split_convex's
    default min_cut (1e-9 diameter) deep do not count."""
    lines = _crossing_lines(poly, lines, 1e-9 * _diameter(poly))
    distinct = []
    for ln in lines:
        n, c = _line_frame(ln[None])
        if not any(np.all(np.abs(ln_i @ n[0] - c[0]) <= tol) for ln_i in distinct):
            distinct.append(ln)
    if not distinct:
        return 1
    n, c = _line_frame(np.array(distinct))
    clusters = []  # [point, set of lines]
    for i in range(len(distinct)):
        for j in range(i + 1, len(distinct)):
            a = np.array([n[i], n[j]])
            if abs(np.linalg.det(a)) < 1e-12:
                continue
            x = np.linalg.solve(a, [c[i], c[j]])
            if _inward(poly, x[None]).min() <= tol:
                continue
            for cl in clusters:
                if np.linalg.norm(cl[0] - x) <= 10 * tol:
                    cl[1].update((i, j))
                    break
            else:
                clusters.append([x, {i, j}])
    return 1 + len(distinct) + sum(len(cl[1]) - 1 for cl in clusters)


def _near_degenerate(poly, lines, scale):
    """True if some incidence is almost but not exactly degenerate (ambiguous to count)."""
    lo, hi = 1e-14 * scale, 1e-6 * scale
    lines = _crossing_lines(poly, lines, lo)
    n, c = _line_frame(lines) if len(lines) else (np.zeros((0, 2)), np.zeros(0))
    d = np.abs(poly @ n.T - c)
    if np.any((d > lo) & (d < hi)):
        return True
    pts = []
    for i in range(len(lines)):
        for j in range(i + 1, len(lines)):
            det = n[i, 0] * n[j, 1] - n[i, 1] * n[j, 0]
            if abs(det) < 1e-5:
                return True  # nearly parallel: tiny slivers or far crossings
            x = np.linalg.solve(np.array([n[i], n[j]]), [c[i], c[j]])
            b = np.abs(_inward(poly, x[None])).min()
            if lo < b < hi:
                return True
            pts.append(x)
    if len(pts) > 1:
        pts = np.array(pts)
        dd = np.linalg.norm(pts[:, None] - pts[None], axis=-1)[np.triu_indices(len(pts), 1)]
        if np.any((dd > lo) & (dd < hi)):
            return True
    return False


def _check_fragments(poly, lines, frags, rel_area=1e-10):
    scale = _diameter(poly)
    tol = 1e-12 * scale  # split_convex's default
    parent_area = abs(_signed_area(poly))
    assert all(f.dtype == np.float64 and f.ndim == 2 and f.shape[1] == 2 for f in frags)
    total = sum(_signed_area(f) for f in frags)
    assert abs(total - parent_area) <= rel_area * parent_area
    n, c = _line_frame(lines)
    depth = poly @ n.T - c
    used = (depth.max(axis=0) > 1e-9 * scale) & (depth.min(axis=0) < -1e-9 * scale)
    for f in frags:
        assert f.shape[0] >= 3
        assert _signed_area(f) > 0.0  # counter-clockwise
        prev, nxt = np.roll(f, 1, axis=0), np.roll(f, -1, axis=0)
        chord = nxt - prev
        rel = f - prev
        height = (rel[:, 0] * chord[:, 1] - rel[:, 1] * chord[:, 0]) / np.linalg.norm(chord, axis=1)
        # strictly convex; only the parent's own (exact) corners may be flatter than tol
        corner = np.any(np.all(f[:, None, :] == poly[None, :, :], axis=2), axis=1)
        assert height.min() > 0.0
        assert np.all(height[~corner] > 0.5 * tol)
        step = np.linalg.norm(nxt - f, axis=1)
        assert np.all((step > tol) | (corner & np.roll(corner, -1)))  # no duplicates
        assert _inward(poly, f).min() >= -2 * tol  # inside the parent
        # one side of every line; lines cutting less than min_cut deep are ignored by design
        d = f @ n.T - c
        slack = np.where(used, 2 * tol, 1e-9 * scale)
        assert np.all((d.min(axis=0) >= -slack) | (d.max(axis=0) <= slack))


def _sample_inside(poly, rng, n):
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    x = rng.uniform(lo, hi, size=(8 * n, 2))
    x = x[_inward(poly, x).min(axis=1) > 0]
    return x[:n]


def _check_partition_by_sampling(poly, lines, frags, seed):
    """Random interior points away from every cut lie in exactly one fragment, and the
    fragments are at least as many as the distinct sign vectors the samples show."""
    scale = _diameter(poly)
    x = _sample_inside(poly, np.random.default_rng(seed), 300)
    n, c = _line_frame(lines)
    d = x @ n.T - c
    clear = (np.abs(d).min(axis=1) > 1e-7 * scale) & (_inward(poly, x).min(axis=1) > 1e-7 * scale)
    x, d = x[clear], d[clear]
    inside = np.stack([_inward(f, x).min(axis=1) > 0 for f in frags], axis=1)
    assert np.all(inside.sum(axis=1) == 1)
    assert len(np.unique(np.sign(d), axis=0)) <= len(frags)


# ---------------------------------------------------------------- strategies

_unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
_wide = st.floats(-1.5, 1.5, allow_nan=False, allow_infinity=False)


@st.composite
def _scene(draw, max_lines=8):
    """A random convex polygon (hull of 3-12 points) and 1..max_lines random lines, then a
    common scale (1 mm .. 100 m) and shift, so tolerances are tested relative to size."""
    scale = draw(st.sampled_from([1e-3, 1e-2, 1.0, 1e2]))
    shift = np.array(draw(st.tuples(_unit, _unit))) * 10.0 * scale
    pts = np.array(draw(st.lists(st.tuples(_unit, _unit), min_size=3, max_size=12)))
    poly = _hull(pts * scale + shift)
    assume(poly.shape[0] >= 3 and _signed_area(poly) > 0.05 * scale**2)
    # edges far below the tolerance make the reference checks themselves ill-posed
    assume(np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1).min() > 1e-6 * scale)
    raw = draw(st.lists(st.tuples(_wide, _wide, _wide, _wide), min_size=1, max_size=max_lines))
    lines = np.array(raw, dtype=float).reshape(-1, 2, 2) * scale + shift
    assume(np.all(np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1) > 1e-2 * scale))
    return poly, lines


# ---------------------------------------------------------------- property tests


@settings(PROPERTY, max_examples=1000)
@given(_scene(), st.booleans())
def test_fragments_partition_the_parent(scene, clockwise):
    poly, lines = scene
    frags = split_convex(poly[::-1] if clockwise else poly, lines)
    _check_fragments(poly, lines, frags)


@settings(PROPERTY, max_examples=800)
@given(_scene(), st.integers(0, 2**31 - 1))
def test_fragment_count_equals_cells(scene, seed):
    poly, lines = scene
    scale = _diameter(poly)
    assume(not _near_degenerate(poly, lines, scale))
    frags = split_convex(poly, lines)
    assert len(frags) == _cells_euler(poly, lines, 1e-12 * scale)
    _check_partition_by_sampling(poly, lines, frags, seed)


@settings(PROPERTY, max_examples=100)
@given(_scene(max_lines=16), st.floats(0.0, 2.0 * np.pi))
def test_many_lines_and_rotation_invariance(scene, angle):
    poly, lines = scene
    frags = split_convex(poly, lines)
    _check_fragments(poly, lines, frags)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    frags_rot = split_convex(poly @ rot.T, lines @ rot.T)
    areas = np.sort([_signed_area(f) for f in frags])
    areas_rot = np.sort([_signed_area(f) for f in frags_rot])
    if not _near_degenerate(poly, lines, _diameter(poly)):
        assert len(frags_rot) == len(frags)
        np.testing.assert_allclose(areas_rot, areas, rtol=1e-7, atol=1e-9 * areas.sum())


def _chord_cells(n_vertices, position, pairs):
    """Exact cell count for chords between boundary points of a convex polygon, from the
    combinatorics alone: position = edge index + fraction along the edge (fraction 0 is a
    corner). A chord with both ends on one edge does not cut; two chords with four distinct
    ends cross inside iff their ends interleave along the boundary; chords sharing an end
    meet on the boundary. Assumes no three chords meet at one interior point."""

    def edges(x):
        e = int(np.floor(x))
        return {e % n_vertices, (e - 1) % n_vertices} if x == e else {e % n_vertices}

    chords = {tuple(sorted((position[a], position[b]))) for a, b in pairs}
    chords = [ch for ch in chords if ch[0] != ch[1] and not edges(ch[0]) & edges(ch[1])]
    crossings = 0
    for i, (a, b) in enumerate(chords):
        for c, d in chords[i + 1 :]:
            if len({a, b, c, d}) == 4:
                crossings += (a < c < b) != (a < d < b)
    return 1 + len(chords) + crossings


@settings(PROPERTY, max_examples=500)
@given(
    _scene(max_lines=1),
    st.lists(
        st.tuples(st.integers(0, 11), st.one_of(st.just(0.0), st.floats(0.0, 0.999))),
        min_size=2,
        max_size=6,
    ),
    st.data(),
)
def test_chords_between_contact_points(scene, contacts, data):
    """The DSM case: fracture planes join contact points on the boundary, so planes share
    end points, pass through corners, run along edges and meet on the boundary."""
    poly, _ = scene
    nv = poly.shape[0]
    position = np.array([e % nv + t for e, t in contacts])
    edge = np.floor(position).astype(int)
    frac = position - edge
    points = poly[edge] + frac[:, None] * (np.roll(poly, -1, axis=0)[edge] - poly[edge])
    at_corner = np.all(points[:, None] == poly[None], axis=2)
    hit = np.any(at_corner, axis=1)
    position[hit] = np.argmax(at_corner[hit], axis=1)  # rounded onto a corner
    all_pairs = [
        (a, b)
        for a in range(len(points))
        for b in range(a + 1, len(points))
        if np.any(points[a] != points[b])
    ]
    assume(all_pairs)
    pairs = data.draw(st.lists(st.sampled_from(all_pairs), min_size=1, max_size=8, unique=True))
    lines = np.array([[points[a], points[b]] for a, b in pairs])
    frags = split_convex(poly, lines)
    _check_fragments(poly, lines, frags)
    # contacts closer than the tolerances blur the combinatorics; only count clean cases
    gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)[np.triu_indices(len(points), 1)]
    gaps = np.concatenate([gaps, np.linalg.norm(points[:, None] - poly[None], axis=-1).ravel()])
    prev, nxt = np.roll(poly, 1, axis=0), np.roll(poly, -1, axis=0)
    rel, chord = poly - prev, nxt - prev
    flat = (rel[:, 0] * chord[:, 1] - rel[:, 1] * chord[:, 0]) / np.linalg.norm(chord, axis=1)
    clean = np.all((gaps == 0) | (gaps > 1e-6 * _diameter(poly)))
    if clean and flat.min() > 1e-6 * _diameter(poly):
        event("cell count checked")
        assert len(frags) == _chord_cells(nv, position, pairs)


# ---------------------------------------------------------------- named cases

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def _areas(frags):
    return sorted(round(_signed_area(f), 12) for f in frags)


def test_single_cut_gives_two_halves():
    frags = split_convex(SQUARE, [[[0.5, -3.0], [0.5, 7.0]]])
    assert _areas(frags) == [0.5, 0.5]
    _check_fragments(SQUARE, np.array([[[0.5, -3.0], [0.5, 7.0]]]), frags)


def test_line_through_two_vertices_diagonal():
    lines = np.array([[[0.0, 0.0], [1.0, 1.0]]])
    frags = split_convex(SQUARE, lines)
    assert len(frags) == 2 and all(f.shape == (3, 2) for f in frags)
    _check_fragments(SQUARE, lines, frags)


def test_both_diagonals_meet_in_the_centre():
    lines = np.array([[[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.0], [0.0, 1.0]]])
    frags = split_convex(SQUARE, lines)
    assert _areas(frags) == [0.25] * 4
    assert all(np.any(np.all(np.isclose(f, 0.5), axis=1)) for f in frags)


def test_line_through_one_vertex_and_an_edge():
    lines = np.array([[[0.0, 0.0], [1.0, 0.5]]])
    frags = split_convex(SQUARE, lines)
    assert _areas(frags) == [0.25, 0.75]
    assert sorted(f.shape[0] for f in frags) == [3, 4]


def test_line_touching_only_one_vertex_is_ignored():
    lines = np.array([[[1.0, 1.0], [2.0, 0.5]], [[0.0, 0.0], [-1.0, 1.0]]])
    frags = split_convex(SQUARE, lines)
    assert len(frags) == 1
    assert abs(_signed_area(frags[0]) - 1.0) < 1e-15


def test_line_along_an_edge_is_ignored():
    lines = np.array([[[0.0, 0.0], [2.0, 0.0]], [[1.0, 5.0], [1.0, -5.0]]])
    frags = split_convex(SQUARE, lines)
    assert len(frags) == 1 and frags[0].shape == (4, 2)


def test_line_along_an_edge_with_a_real_cut():
    lines = np.array([[[0.0, 0.0], [2.0, 0.0]], [[0.3, 5.0], [0.3, -5.0]]])
    frags = split_convex(SQUARE, lines)
    assert _areas(frags) == [0.3, 0.7]


def test_lines_missing_the_polygon_are_ignored():
    lines = np.array([[[2.0, 0.0], [2.0, 1.0]], [[-5.0, -1.0], [5.0, -1.1]]])
    frags = split_convex(SQUARE, lines)
    assert len(frags) == 1


def test_no_lines_returns_the_polygon_ccw():
    frags = split_convex(SQUARE[::-1], np.zeros((0, 2, 2)))
    assert len(frags) == 1 and _signed_area(frags[0]) == pytest.approx(1.0)


def test_coincident_lines_count_once():
    # the same line three times: twice as given, once reversed, once by other points
    lines = np.array(
        [
            [[0.0, 0.2], [1.0, 0.7]],
            [[1.0, 0.7], [0.0, 0.2]],
            [[2.0, 1.2], [-2.0, -0.8]],
        ]
    )
    frags = split_convex(SQUARE, lines)
    assert len(frags) == 2
    _check_fragments(SQUARE, lines, frags)


def test_parallel_lines_give_strips():
    lines = np.array([[[x, 0.0], [x, 1.0]] for x in (0.2, 0.5, 0.9)])
    frags = split_convex(SQUARE, lines)
    assert _areas(frags) == [0.1, 0.2, 0.3, 0.4]


def test_nearly_coincident_lines_within_tolerance_merge():
    lines = np.array([[[0.5, 0.0], [0.5, 1.0]], [[0.5 + 1e-13, 0.0], [0.5, 1.0]]])
    frags = split_convex(SQUARE, lines)
    assert _areas(frags) == [0.5, 0.5]


def test_fan_of_lines_through_one_vertex():
    k = 7
    ang = np.linspace(0.0, np.pi / 2.0, k + 2)[1:-1]
    lines = np.stack([np.zeros((k, 2)), np.stack([np.cos(ang), np.sin(ang)], 1)], axis=1)
    frags = split_convex(SQUARE, lines)
    assert len(frags) == k + 1
    _check_fragments(SQUARE, lines, frags)


def test_lines_crossing_on_the_boundary():
    lines = np.array([[[0.5, 0.0], [0.0, 1.0]], [[0.5, 0.0], [1.0, 1.0]]])
    frags = split_convex(SQUARE, lines)
    assert _areas(frags) == [0.25, 0.25, 0.5]


def test_three_concurrent_lines_and_a_fourth():
    c = np.array([0.4, 0.55])
    lines = [[c, c + [np.cos(a), np.sin(a)]] for a in (0.1, 1.2, 2.3)]
    lines.append([[0.0, 0.9], [1.0, 0.95]])
    lines = np.array(lines)
    frags = split_convex(SQUARE, lines)
    assert len(frags) == _cells_euler(SQUARE, lines, 1e-12) == 9
    _check_fragments(SQUARE, lines, frags)


def test_nearly_collinear_polygon_corners():
    # a corner 1e-14 off the edge through its neighbours, and a duplicated corner
    poly = np.array([[0.0, 0.0], [0.5, -1e-14], [1.0, 0.0], [1.0, 1.0], [1.0, 1.0], [0.0, 1.0]])
    lines = np.array([[[0.5, -1.0], [0.5, 2.0]], [[-1.0, 0.5], [2.0, 0.5]]])
    frags = split_convex(poly, lines)
    assert _areas(frags) == [0.25] * 4
    assert all(f.shape == (4, 2) for f in frags)


def test_crossing_nearly_on_a_third_line():
    # lines A, B cross at (0.5, 0.5); C passes 1e-13 away: treated as concurrent
    lines = np.array(
        [
            [[0.0, 0.0], [1.0, 1.0]],
            [[1.0, 0.0], [0.0, 1.0]],
            [[0.0, 0.5 + 1e-13], [1.0, 0.5]],
        ]
    )
    frags = split_convex(SQUARE, lines)
    assert len(frags) == 6
    _check_fragments(SQUARE, lines, frags)


def test_tiny_and_huge_particles_scale():
    lines = np.array([[[0.0, 0.0], [1.0, 1.0]], [[0.3, -1.0], [0.3, 2.0]]])
    base = _areas(split_convex(SQUARE, lines))
    for s, shift in ((1e-4, 1e3), (1e3, -5e4)):
        frags = split_convex(SQUARE * s + shift, lines * s + shift)
        np.testing.assert_allclose(sorted(_signed_area(f) / s**2 for f in frags), base)


def test_sixteen_concurrent_lines_are_fast():
    ang = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    disc = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    phi = np.linspace(0.0, np.pi, 16, endpoint=False)
    lines = np.stack([np.zeros((16, 2)), np.stack([np.cos(phi), np.sin(phi)], 1)], axis=1)
    t0 = time.perf_counter()
    frags = split_convex(disc, lines)
    assert time.perf_counter() - t0 < 1.0
    assert len(frags) == 32
    _check_fragments(disc, lines, frags)


def test_sixteen_random_lines_match_euler_count():
    rng = np.random.default_rng(7)
    ang = np.sort(rng.uniform(0.0, 2.0 * np.pi, 20))
    poly = np.stack([np.cos(ang), 0.6 * np.sin(ang)], axis=1)
    lines = rng.uniform(-1.0, 1.0, size=(16, 2, 2))
    frags = split_convex(poly, lines)
    assert len(frags) == _cells_euler(poly, lines, 1e-12 * _diameter(poly))
    _check_fragments(poly, lines, frags)
    _check_partition_by_sampling(poly, lines, frags, seed=3)


def test_bad_input_explains_itself():
    with pytest.raises(ValueError, match="convex"):
        split_convex(np.array([[0, 0], [2, 0], [1, 0.2], [1, 2]]), [[[0, 1], [1, 1]]])
    with pytest.raises(ValueError, match="identical points"):
        split_convex(SQUARE, [[[0.5, 0.5], [0.5, 0.5]]])
    with pytest.raises(ValueError, match="shape"):
        split_convex(SQUARE, [[0.5, 0.5], [0.5, 0.7]])
    with pytest.raises(ValueError, match="degenerate"):
        split_convex(np.array([[0, 0], [1, 0], [2, 0]]), [[[0.5, -1], [0.5, 1]]])
