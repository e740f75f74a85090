"""Tests for jaxgran.geometry: analytic values, properties (hypothesis) and jax twins."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.integrate import quad
from scipy.spatial import ConvexHull

from jaxgran import geometry as g

PROPERTY = settings(max_examples=200, deadline=None)


def edge_lengths(p):
    return np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)


def rotation(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


@st.composite
def convex_polygons(draw, max_points=16):
    """Random convex CCW polygon: hull of random points, stretched, rotated, scaled, moved."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.integers(3, max_points))
    pts = rng.uniform(-1.0, 1.0, (n, 2)) * [1.0, draw(st.floats(0.05, 1.0))]
    pts = pts @ rotation(draw(st.floats(0.0, 2 * math.pi))).T
    scale = draw(st.sampled_from([1e-3, 1.0, 50.0]))
    shift = np.array([draw(st.floats(-10.0, 10.0)), draw(st.floats(-10.0, 10.0))])
    try:
        hull = ConvexHull(pts)
    except Exception:  # noqa: BLE001 - collinear draws
        assume(False)
    poly = scale * (pts[hull.vertices] + shift)
    assume(g.polygon_area(poly) > 1e-3 * scale**2)
    return poly


def dist_to_segment(x, a, b):
    """Distance (m) from points x [..., 2] to segments a -> b (broadcast)."""
    ab = b - a
    t = np.clip(((x - a) * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[..., None] * ab), axis=-1)


def dist_to_boundary(x, p):
    """Distance (m) from points x [k, 2] to the boundary of polygon p [n, 2]."""
    d = dist_to_segment(x[:, None, :], p[None, :, :], np.roll(p, -1, axis=0)[None, :, :])
    return d.min(axis=1)


def inside_ccw(x, p, tol=0.0):
    """Points x [k, 2] in the closed CCW convex polygon p, by edge cross products only."""
    e = np.roll(p, -1, axis=0) - p
    c = e[None, :, 0] * (x[:, None, 1] - p[None, :, 1]) - e[None, :, 1] * (
        x[:, None, 0] - p[None, :, 0]
    )
    return (c >= -tol * np.linalg.norm(e, axis=1)[None, :]).all(axis=1)


# ---------------------------------------------------------------------------------------------
# area, centroid, moments
# ---------------------------------------------------------------------------------------------


def test_area_centroid_moment_of_rectangle_and_triangle():
    b, h = 3.0, 2.0
    rect = np.array([[0, 0], [b, 0], [b, h], [0, h]], float) + [5.0, -7.0]
    assert g.polygon_area(rect) == pytest.approx(b * h, rel=1e-14)
    assert g.polygon_area(rect[::-1]) == pytest.approx(-b * h, rel=1e-14)
    np.testing.assert_allclose(g.polygon_centroid(rect), [5 + b / 2, -7 + h / 2], rtol=1e-14)
    assert g.polygon_polar_moment(rect) == pytest.approx(b * h * (b * b + h * h) / 12, rel=1e-13)
    assert g.polygon_polar_moment(rect[::-1]) == pytest.approx(g.polygon_polar_moment(rect))

    a = 0.7  # equilateral triangle of side a: J = sqrt(3) a^4 / 48
    tri = g.regular_polygon(3, a / math.sqrt(3), rotation=0.3, center=(1.0, 2.0))
    assert g.polygon_area(tri) == pytest.approx(math.sqrt(3) / 4 * a * a, rel=1e-13)
    np.testing.assert_allclose(g.polygon_centroid(tri), [1.0, 2.0], rtol=1e-13)
    assert g.polygon_polar_moment(tri) == pytest.approx(math.sqrt(3) * a**4 / 48, rel=1e-12)


def test_centroid_of_non_convex_l_shape_and_degenerate_fallback():
    # L made of a 2x1 bar and a 1x1 square on top of its left end
    ell = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float)
    np.testing.assert_allclose(g.polygon_centroid(ell), [(1.0 * 2 + 0.5) / 3] * 2, rtol=1e-14)
    np.testing.assert_allclose(g.polygon_centroid([[0, 0], [2, 2]]), [1, 1])
    assert g.polygon_area([[0, 0], [1, 1]]) == 0.0


def test_regular_polygon():
    p = g.regular_polygon(9, 2.0, rotation=0.1, center=(3.0, 4.0))
    assert p.shape == (9, 2)
    np.testing.assert_allclose(np.linalg.norm(p - [3, 4], axis=1), 2.0, rtol=1e-15)
    assert g.polygon_area(p) == pytest.approx(9 / 2 * 4 * math.sin(2 * math.pi / 9), rel=1e-13)
    assert g.circumradius(p) == pytest.approx(2.0, rel=1e-13)
    assert g.inradius(p) == pytest.approx(2.0 * math.cos(math.pi / 9), rel=1e-13)
    with pytest.raises(ValueError, match="n >= 3"):
        g.regular_polygon(2, 1.0)


# ---------------------------------------------------------------------------------------------
# spheropolygon mass properties
# ---------------------------------------------------------------------------------------------


def test_mass_properties_of_disc():
    rho, r = 2650.0 * 0.01, 0.004
    m, c, inertia = g.spheropolygon_mass_properties([[0.1, -0.2]], r, rho)
    assert m == pytest.approx(rho * math.pi * r * r, rel=1e-14)
    np.testing.assert_allclose(c, [0.1, -0.2])
    assert inertia == pytest.approx(0.5 * m * r * r, rel=1e-14)


def test_mass_properties_of_stadium():
    rho, length, r = 3.0, 2.0, 0.3
    a = np.array([0.5, 0.5])
    d = np.array([math.cos(0.4), math.sin(0.4)])
    m, c, inertia = g.spheropolygon_mass_properties([a, a + length * d], r, rho)
    area = 2 * r * length + math.pi * r * r
    # rectangle (length x 2r) + two half-discs moved out by length/2 (their flat-edge centres)
    e = 4 * r / (3 * math.pi)
    j_half = math.pi * r**4 / 4 + (math.pi * r * r / 2) * ((length / 2 + e) ** 2 - e**2)
    j = 2 * r * length * (length**2 + 4 * r * r) / 12 + 2 * j_half
    assert m == pytest.approx(rho * area, rel=1e-14)
    np.testing.assert_allclose(c, a + 0.5 * length * d, rtol=1e-14)
    assert inertia == pytest.approx(rho * j, rel=1e-13)


def test_mass_properties_of_rounded_square_against_quadrature():
    # rounded square |x|,|y| <= s/2 swept by r: integrate exactly in y, numerically in x
    s, r, rho = 2.0, 0.3, 1.7

    def half(x):  # half-height of the vertical chord at x
        over = max(abs(x) - s / 2, 0.0)
        return s / 2 + math.sqrt(max(r * r - over * over, 0.0))

    lim = s / 2 + r
    kinks = [-s / 2, s / 2]
    area = quad(lambda x: 2 * half(x), -lim, lim, points=kinks, epsabs=0, epsrel=1e-13)[0]
    j = quad(
        lambda x: 2 * half(x) * x * x + 2 * half(x) ** 3 / 3,
        -lim,
        lim,
        points=kinks,
        epsabs=0,
        epsrel=1e-13,
    )[0]
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * s / 2
    shift = np.array([0.3, -1.1])
    m, c, inertia = g.spheropolygon_mass_properties(square @ rotation(0.7).T + shift, r, rho)
    assert m == pytest.approx(rho * (s * s + 4 * s * r + math.pi * r * r), rel=1e-14)
    assert m == pytest.approx(rho * area, rel=1e-11)
    np.testing.assert_allclose(c, shift, atol=1e-14)
    assert inertia == pytest.approx(rho * j, rel=1e-11)


def test_mass_properties_of_swept_triangle_against_grid():
    # rotated by an irrational angle: grid-aligned edges would bias the count
    tri = np.array([[0.0, 0.0], [1.0, 0.1], [0.3, 0.8]]) @ rotation(0.123).T + [3e-4, 7e-4]
    r, h = 0.15, 1e-3
    lo, hi = tri.min(0) - r - 0.01, tri.max(0) + r + 0.01
    xs = np.arange(lo[0], hi[0], h) + h / 2
    ys = np.arange(lo[1], hi[1], h) + h / 2
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    inside = g.point_in_convex_polygon(pts, tri) | (dist_to_boundary(pts, tri) <= r)
    x = pts[inside]
    area = inside.sum() * h * h
    c_grid = x.mean(axis=0)
    j_grid = ((x - c_grid) ** 2).sum() * h * h
    m, c, inertia = g.spheropolygon_mass_properties(tri, r, 1.0)
    assert m == pytest.approx(area, rel=5e-5)
    np.testing.assert_allclose(c, c_grid, atol=2e-5)
    assert inertia == pytest.approx(j_grid, rel=1e-4)


@PROPERTY
@given(convex_polygons(), st.floats(0.0, 0.5), st.floats(0.0, 2 * math.pi))
def test_mass_properties_invariants(poly, r_rel, angle):
    r = r_rel * g.circumradius(poly)
    m, c, inertia = g.spheropolygon_mass_properties(poly, r, 2.0)
    # r = 0: the polygon itself; CW input: same body; rigid motion: same mass and inertia
    m0, c0, i0 = g.spheropolygon_mass_properties(poly, 0.0, 2.0)
    assert m0 == pytest.approx(2.0 * g.polygon_area(poly), rel=1e-12)
    np.testing.assert_allclose(c0, g.polygon_centroid(poly), atol=1e-12 * g.circumradius(poly))
    assert i0 == pytest.approx(2.0 * g.polygon_polar_moment(poly), rel=1e-10)
    m_cw, c_cw, i_cw = g.spheropolygon_mass_properties(poly[::-1], r, 2.0)
    assert (m_cw, i_cw) == pytest.approx((m, inertia), rel=1e-12)
    moved = poly @ rotation(angle).T + [1.0, -2.0]
    m2, c2, i2 = g.spheropolygon_mass_properties(moved, r, 2.0)
    assert (m2, i2) == pytest.approx((m, inertia), rel=1e-9)
    np.testing.assert_allclose(
        c2, rotation(angle) @ c + [1.0, -2.0], atol=1e-9 * (1 + abs(c).max())
    )
    # Steiner formula for a convex body dilated by r: A + P r + pi r^2
    perimeter = edge_lengths(poly).sum()
    assert m == pytest.approx(2.0 * (g.polygon_area(poly) + perimeter * r + math.pi * r * r))
    assert inertia >= i0 * (1 - 1e-12)


def test_mass_properties_errors():
    with pytest.raises(ValueError, match="radius > 0"):
        g.spheropolygon_mass_properties([[0.0, 0.0]], 0.0, 1.0)
    with pytest.raises(ValueError, match="radius > 0"):
        g.spheropolygon_mass_properties([[0.0, 0.0], [1.0, 0.0]], 0.0, 1.0)
    with pytest.raises(ValueError, match="radius must be"):
        g.spheropolygon_mass_properties([[0.0, 0.0]], -1.0, 1.0)
    with pytest.raises(ValueError, match="convex hull"):
        ell = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]
        g.spheropolygon_mass_properties(ell, 0.1, 1.0)


# ---------------------------------------------------------------------------------------------
# convexity and validation
# ---------------------------------------------------------------------------------------------


def test_is_convex():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert g.is_convex(square) and g.is_convex(square[::-1])
    assert g.is_convex([[0, 0], [0.5, 0], [1, 0], [1, 1], [0, 1]])  # collinear vertex
    assert not g.is_convex([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]])
    assert not g.is_convex([[0, 0], [1, 0], [2, 0]])
    assert not g.is_convex(np.concatenate([square, square]))  # winds twice
    assert not g.is_convex(g.regular_polygon(5, 1.0)[[0, 2, 4, 1, 3]])  # pentagram


def test_validate_polygon_cleans_input():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], int)
    out = g.validate_polygon(square[::-1])
    assert out.dtype == np.float64 and g.polygon_area(out) == pytest.approx(1.0)
    dup = np.array([[0, 0], [1, 0], [1, 0], [1, 1], [1 + 1e-14, 1], [0, 1], [0, 0]], float)
    assert len(g.validate_polygon(dup)) == 4
    near = np.array([[0, 0], [1, 0], [1, 1e-6], [1, 1], [0, 1]], float)  # kept: a real vertex
    assert len(g.validate_polygon(near)) == 5


@pytest.mark.parametrize(
    ("verts", "match"),
    [
        ([[0, 0], [1, 0]], "at least 3"),
        ([[0, 0], [1, 0], [1, 0], [0, 0]], "at least 3"),
        ([[0, 0], [1, 0], [np.nan, 1]], "NaN or inf at vertex 2"),
        ([[0, 0], [1, 0], [np.inf, 1]], "NaN or inf"),
        ([[0, 0], [1, 1], [2, 2]], "zero area.*collinear"),
        ([[0, 0], [1, 0], [0.5, 1e-13]], "zero area"),
        ([[0, 0], [1, 1], [1, 0], [0, 1]], "self-intersecting.*convex hull"),
        ([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], "not convex.*convex hull.*split"),
        ([[0, 0], [1, 0], [1, 1], [0, 1]] * 2, "turns 2.00 times"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], r"shape \[n_vertices, 2\]"),
    ],
)
def test_validate_polygon_errors(verts, match):
    with pytest.raises(ValueError, match=match) as err:
        g.validate_polygon(np.asarray(verts, float), name="grain 7")
    assert "grain 7" in str(err.value)


# ---------------------------------------------------------------------------------------------
# offsetting, inradius, outline
# ---------------------------------------------------------------------------------------------


def test_offset_and_inradius_analytic():
    rect = np.array([[0, 0], [3, 0], [3, 1], [0, 1]], float)
    np.testing.assert_allclose(
        g.offset_polygon(rect, 0.25), [[0.25, 0.25], [2.75, 0.25], [2.75, 0.75], [0.25, 0.75]]
    )
    assert g.inradius(rect) == pytest.approx(0.5, rel=1e-14)
    tri = np.array([[0, 0], [4, 0], [1, 3]], float)
    r_in = 2 * g.polygon_area(tri) / edge_lengths(tri).sum()
    assert g.inradius(tri) == pytest.approx(r_in, rel=1e-13)
    # the inward offset of a triangle is a similar triangle about the incentre
    shrunk = g.offset_polygon(tri, 0.4 * r_in)
    assert len(shrunk) == 3
    assert g.polygon_area(shrunk) == pytest.approx(0.36 * g.polygon_area(tri), rel=1e-12)
    # a hexagon with one very short edge loses that edge
    hexagon = np.array([[0, 0], [4, 0], [4, 2], [2.05, 3.0], [1.95, 3.0], [0, 2]])
    eroded = g.offset_polygon(hexagon, 0.5)
    assert len(eroded) == 5
    assert eroded[3, 0] == pytest.approx(2.0, rel=1e-14)


def test_offset_errors():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    with pytest.raises(ValueError, match=r"largest admissible distance is its inradius 0\.5 m"):
        g.offset_polygon(square, 0.5)
    with pytest.raises(ValueError, match="erodes only.*spheropolygon radius"):
        g.offset_polygon(square, -0.1)
    np.testing.assert_array_equal(g.offset_polygon(square, 0.0), square)


@PROPERTY
@given(convex_polygons(), st.floats(0.0, 0.999), st.floats(0.0, 1.0))
def test_offset_polygon_properties(poly, frac, frac2):
    r_in = g.inradius(poly)
    size = g.circumradius(poly)
    d = frac * r_in
    out = g.offset_polygon(poly, d)
    assert g.is_convex(out) and g.polygon_area(out) > 0
    assert g.point_in_convex_polygon(out, poly).all()
    normals = np.stack(
        [-(np.roll(poly, -1, 0) - poly)[:, 1], (np.roll(poly, -1, 0) - poly)[:, 0]], 1
    )
    normals /= np.linalg.norm(normals, axis=1)[:, None]  # inward unit normals
    depth = ((out[:, None, :] - poly[None, :, :]) * normals[None]).sum(-1)
    assert (depth >= d - 1e-9 * size).all()
    # the offset is the set of points at depth >= d: its inradius drops by exactly d
    if frac < 0.99:
        assert g.inradius(out) == pytest.approx(r_in - d, abs=1e-9 * size)
    smaller = g.offset_polygon(poly, d * frac2)
    assert g.polygon_area(out) <= g.polygon_area(smaller) * (1 + 1e-12)


@pytest.mark.parametrize("n_arc", [3, 8, 64, 1024])
def test_outline_of_disc_and_stadium(n_arc):
    r = 0.5
    disc = g.spheropolygon_outline([[1.0, 2.0]], r, n_arc=n_arc)
    assert len(disc) == n_arc
    assert g.polygon_area(disc) == pytest.approx(n_arc / 2 * r * r * math.sin(2 * math.pi / n_arc))
    stadium = g.spheropolygon_outline([[0.0, 0.0], [1.0, 0.0]], r, n_arc=n_arc)
    assert g.is_convex(stadium) and g.polygon_area(stadium) > 0
    np.testing.assert_allclose(dist_to_segment(stadium, np.zeros(2), np.array([1.0, 0.0])), r)
    exact = 2 * r + math.pi * r * r
    assert g.polygon_area(stadium) <= exact
    if n_arc == 1024:
        assert g.polygon_area(stadium) == pytest.approx(exact, rel=1e-4)


@PROPERTY
@given(convex_polygons(max_points=8), st.floats(0.01, 0.5), st.integers(3, 40))
def test_outline_properties(poly, r_rel, n_arc):
    r = r_rel * g.circumradius(poly)
    out = g.spheropolygon_outline(poly, r, n_arc=n_arc)
    assert g.is_convex(out) and g.polygon_area(out) > 0
    np.testing.assert_allclose(dist_to_boundary(out, poly), r, rtol=1e-9)
    m, _, _ = g.spheropolygon_mass_properties(poly, r, 1.0)
    assert g.polygon_area(out) <= m * (1 + 1e-12)
    assert len(out) <= len(poly) + n_arc + len(poly)


# ---------------------------------------------------------------------------------------------
# clipping and point location
# ---------------------------------------------------------------------------------------------


def test_clip_convex_cases():
    square = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], float)
    np.testing.assert_allclose(g.polygon_area(g.clip_convex(square, square)), 4.0)
    inner = square * 0.25 + 0.5
    np.testing.assert_allclose(g.clip_convex(inner, square), inner)
    assert g.clip_convex(square + 5.0, square).shape == (0, 2)
    assert g.clip_convex(square + [2.0, 0.0], square).shape == (0, 2)  # touching only
    half = g.clip_convex(square, square + [1.0, 1.0])
    assert g.polygon_area(half) == pytest.approx(1.0)


@PROPERTY
@given(convex_polygons(max_points=10), convex_polygons(max_points=10))
def test_clip_convex_properties(a, b):
    ab = g.clip_convex(a, b)
    ba = g.clip_convex(b, a)
    assert g.polygon_area(ab) == pytest.approx(
        g.polygon_area(ba), abs=1e-9 * (1 + g.polygon_area(a) + g.polygon_area(b))
    )
    if len(ab):
        tol = 1e-9 * max(g.circumradius(a), g.circumradius(b))
        assert g.is_convex(ab) and g.polygon_area(ab) > 0
        assert g.point_in_convex_polygon(ab, a, tol=tol).all()
        assert g.point_in_convex_polygon(ab, b, tol=tol).all()
        ra, rb = g.circumradius(a), g.circumradius(b)
        round_off = 1e-11 * max(ra, rb) * min(ra, rb)  # vertex error ~ eps x the larger size
        assert g.polygon_area(ab) <= min(g.polygon_area(a), g.polygon_area(b)) + round_off
    # the intersection's area matches a Monte-Carlo estimate of |A and B|
    rng = np.random.default_rng(0)
    lo, hi = a.min(0), a.max(0)
    x = rng.uniform(lo, hi, (4000, 2))
    both = g.point_in_convex_polygon(x, a) & g.point_in_convex_polygon(x, b)
    estimate = both.mean() * np.prod(hi - lo)
    assert abs(g.polygon_area(ab) - estimate) <= 0.1 * np.prod(hi - lo)


@PROPERTY
@given(convex_polygons(max_points=12), st.integers(0, 2**32 - 1))
def test_halfplane_clip_areas_match_the_clipped_polygons(poly, seed):
    """The vectorised areas equal the areas of the polygons clip_halfplanes returns, from
    half-planes that miss the polygon (area 0) to ones that contain it (its area)."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(24, 2))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    c = poly.mean(axis=0)
    size = g.circumradius(poly)
    offsets = normals @ c + rng.uniform(-1.3, 1.3, 24) * size
    got = g.halfplane_clip_areas(poly, normals, offsets)
    ref = []
    for n, o in zip(normals, offsets, strict=True):
        q = g.clip_halfplanes(poly, n[None], [o])
        ref.append(abs(g.polygon_area(q)) if len(q) else 0.0)
    area = abs(g.polygon_area(poly))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * area)
    assert np.all(got >= 0) and np.all(got <= area * (1 + 1e-12))


def test_point_in_convex_polygon():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    pts = np.array([[0.5, 0.5], [1.0, 0.5], [1.1, 0.5], [-1e-3, 0.2], [0.0, 0.0]])
    np.testing.assert_array_equal(g.point_in_convex_polygon(pts, square), [1, 1, 0, 0, 1])
    np.testing.assert_array_equal(g.point_in_convex_polygon(pts, square[::-1]), [1, 1, 0, 0, 1])
    assert g.point_in_convex_polygon(pts, square, tol=2e-3)[3]


def test_circumradius():
    assert g.circumradius([[0, 0], [2, 0], [2, 2], [0, 2]]) == pytest.approx(math.sqrt(2))
    assert g.circumradius([[0, 0], [4, 0]]) == pytest.approx(2.0)


# ---------------------------------------------------------------------------------------------
# Voronoi tessellations and shared edges
# ---------------------------------------------------------------------------------------------


def check_tiling(cells, region):
    area = g.polygon_area(region)
    size = g.circumradius(region)
    assert sum(g.polygon_area(c) for c in cells) == pytest.approx(area, rel=1e-9)
    for c in cells:
        assert g.polygon_area(c) > 0 and g.is_convex(c)
        assert inside_ccw(c, region, tol=1e-12 * size).all()
    # each centroid lies in its own cell and in no other (no overlaps)
    centroids = np.array([g.polygon_centroid(c) for c in cells])
    hits = np.array([inside_ccw(centroids, c) for c in cells])
    np.testing.assert_array_equal(hits, np.eye(len(cells), dtype=bool))


def check_shared_edges(cells, region, n_check=None):
    edges = g.shared_edges(cells)
    size = 2 * g.circumradius(region)
    pairs = [(i, j) for i, j, _, _ in edges]
    assert len(set(pairs)) == len(pairs) and pairs == sorted(pairs)
    for i, j, p, q in edges[:: max(1, len(edges) // (n_check or len(edges) or 1))]:
        assert i < j and np.linalg.norm(q - p) > 1e-9 * size
        seg = np.stack([p, q, 0.5 * (p + q)])
        assert dist_to_boundary(seg, cells[i]).max() <= 1e-9 * size
        assert dist_to_boundary(seg, cells[j]).max() <= 1e-9 * size
        # p -> q runs CCW along cell i: cell i lies to its left
        assert g._cross(q - p, g.polygon_centroid(cells[i]) - p) > 0
    # every interior edge length is counted exactly once
    interior = (sum(edge_lengths(c).sum() for c in cells) - edge_lengths(region).sum()) / 2
    shared = sum(np.linalg.norm(q - p) for _, _, p, q in edges)
    assert shared == pytest.approx(interior, rel=1e-9, abs=1e-12 * size)


@PROPERTY
@given(
    st.floats(0.01, 10.0),
    st.floats(0.1, 10.0),
    st.integers(1, 40),
    st.integers(0, 2**32 - 1),
    st.integers(0, 2),
)
def test_voronoi_rectangle_properties(width, aspect, n_cells, seed, lloyd):
    height = width * aspect
    origin = (-0.3 * width, 2.0)
    cells = g.voronoi_rectangle(width, height, n_cells, seed, origin=origin, lloyd_iterations=lloyd)
    assert len(cells) == n_cells
    region = np.array(origin) + [[0, 0], [width, 0], [width, height], [0, height]]
    check_tiling(cells, region)
    check_shared_edges(cells, region)


@PROPERTY
@given(
    st.floats(0.01, 10.0),
    st.integers(1, 40),
    st.integers(0, 2**32 - 1),
    st.integers(3, 64),
    st.integers(0, 2),
)
def test_voronoi_disc_properties(radius, n_cells, seed, n_boundary, lloyd):
    center = (1.0, -2.0)
    cells = g.voronoi_disc(
        radius, n_cells, seed, center=center, n_boundary=n_boundary, lloyd_iterations=lloyd
    )
    assert len(cells) == n_cells
    region = g.regular_polygon(n_boundary, radius, center=center)
    check_tiling(cells, region)
    check_shared_edges(cells, region)


def test_voronoi_is_deterministic_and_lloyd_evens_cells():
    a = g.voronoi_rectangle(1.0, 1.0, 50, 123)
    b = g.voronoi_rectangle(1.0, 1.0, 50, 123)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    c = g.voronoi_rectangle(1.0, 1.0, 50, 124)
    assert not all(len(x) == len(y) and np.allclose(x, y) for x, y in zip(a, c, strict=True))

    def spread(cells):
        areas = np.array([g.polygon_area(x) for x in cells])
        return areas.std() / areas.mean()

    relaxed = g.voronoi_rectangle(1.0, 1.0, 50, 123, lloyd_iterations=10)
    assert spread(relaxed) < 0.5 * spread(a)
    disc = g.voronoi_disc(1.0, 50, 123)
    assert spread(g.voronoi_disc(1.0, 50, 123, lloyd_iterations=10)) < 0.5 * spread(disc)


def test_shared_edges_t_junction_and_large_tessellation():
    # a wide bottom cell under two top cells: T-junction at (1, 1)
    cells = [
        np.array([[0, 0], [2, 0], [2, 1], [1, 1], [0, 1]], float),
        np.array([[0, 1], [1, 1], [1, 2], [0, 2]], float),
        np.array([[1, 1], [2, 1], [2, 2], [1, 2]], float),
    ]
    edges = g.shared_edges(cells)
    assert [(i, j) for i, j, _, _ in edges] == [(0, 1), (0, 2), (1, 2)]
    np.testing.assert_allclose(edges[0][2:], [[1, 1], [0, 1]])
    np.testing.assert_allclose(edges[1][2:], [[2, 1], [1, 1]])
    np.testing.assert_allclose(edges[2][2:], [[1, 1], [1, 2]])
    # the bottom edge of cell 0 given as two collinear edges: still one merged segment
    cells[0] = np.array([[0, 0], [2, 0], [2, 1], [1.5, 1], [1, 1], [0, 1]], float)
    edges = g.shared_edges(cells)
    np.testing.assert_allclose(edges[1][2:], [[2, 1], [1, 1]])
    assert g.shared_edges(cells[:1]) == []

    cells = g.voronoi_rectangle(0.1, 0.05, 5000, 7, lloyd_iterations=1)
    region = np.array([[0, 0], [0.1, 0], [0.1, 0.05], [0, 0.05]])
    check_shared_edges(cells, region, n_check=200)


# ---------------------------------------------------------------------------------------------
# padded arrays and jax twins
# ---------------------------------------------------------------------------------------------


def test_pad_polygons():
    polys = [g.regular_polygon(3, 1.0), g.regular_polygon(5, 1.0)]
    verts, n_verts = g.pad_polygons(polys)
    assert verts.shape == (2, 5, 2) and list(n_verts) == [3, 5]
    np.testing.assert_array_equal(verts[0, 3:], np.repeat(polys[0][-1:], 2, axis=0))
    verts, _ = g.pad_polygons(polys, n_vertex_capacity=8)
    assert verts.shape == (2, 8, 2)
    with pytest.raises(ValueError, match="polygon 1 has 5 vertices.*n_vertex_capacity>=5"):
        g.pad_polygons(polys, n_vertex_capacity=4)


area_jit = jax.jit(eqx.debug.assert_max_traces(g.polygon_area_padded, max_traces=1))
centroid_jit = jax.jit(eqx.debug.assert_max_traces(g.polygon_centroid_padded, max_traces=1))
CAPACITY = 16


@PROPERTY
@given(convex_polygons(max_points=CAPACITY), st.booleans())
def test_jax_twins_match_numpy(poly, garbage):
    verts, n_verts = g.pad_polygons([poly, poly[:2], poly[::-1]], n_vertex_capacity=CAPACITY)
    if garbage:  # padded slots must not contribute whatever they hold
        verts[:, n_verts.max() :] = 1e3
        verts[0, len(poly) :] = -7.0
    area = np.asarray(area_jit(jnp.asarray(verts), jnp.asarray(n_verts)))
    centroid = np.asarray(centroid_jit(jnp.asarray(verts), jnp.asarray(n_verts)))
    scale = g.circumradius(poly) + np.abs(poly).max()
    assert area[0] == pytest.approx(g.polygon_area(poly), rel=1e-12)
    assert area[1] == 0.0
    assert area[2] == pytest.approx(-g.polygon_area(poly), rel=1e-12)
    np.testing.assert_allclose(centroid[0], g.polygon_centroid(poly), atol=1e-12 * scale)
    np.testing.assert_allclose(centroid[1], poly[:2].mean(0), atol=1e-12 * scale)
    np.testing.assert_allclose(centroid[2], g.polygon_centroid(poly), atol=1e-12 * scale)


def test_jax_twins_gradients():
    poly = np.array([[0.0, 0.0], [2.0, 0.1], [1.5, 1.2], [0.2, 1.0]])
    # a real polygon, an empty slot and a two-vertex (zero-area) slot
    verts, n_verts = g.pad_polygons([poly, np.zeros((0, 2)), poly[:2]], n_vertex_capacity=6)
    verts, n_verts = jnp.asarray(verts), jnp.asarray(n_verts)
    area_grad = jax.jit(jax.grad(lambda v: g.polygon_area_padded(v, n_verts).sum()))
    centroid = jax.jit(jax.vmap(lambda v: g.polygon_centroid_padded(v, n_verts)))
    centroid_jac = jax.jit(jax.jacobian(lambda v: g.polygon_centroid_padded(v, n_verts)))

    # dA/dv_k = perp(v_{k+1} - v_{k-1}) / 2 for a CCW polygon, zero on padding
    grad = area_grad(verts)
    span = np.roll(poly, -1, 0) - np.roll(poly, 1, 0)
    np.testing.assert_allclose(
        grad[0, :4], 0.5 * np.stack([span[:, 1], -span[:, 0]], 1), atol=1e-14
    )
    np.testing.assert_array_equal(grad[0, 4:], 0.0)
    np.testing.assert_array_equal(grad[1:], 0.0)
    # centroid Jacobian against central finite differences
    jac = centroid_jac(verts)[0, :, 0]  # [2, V, 2]
    h = 1e-6
    steps = h * jnp.eye(36).reshape(36, 3, 6, 2)[:8]  # the 8 real coordinates of polygon 0
    fd = (centroid(verts + steps) - centroid(verts - steps))[:, 0] / (2 * h)
    np.testing.assert_allclose(jac[:, :4].reshape(2, 8), fd.T, atol=1e-8)
    # the zero-area slots fall back to the vertex mean with finite derivatives
    c = centroid(verts[None])[0]
    np.testing.assert_allclose(c[2], poly[:2].mean(0), atol=1e-15)
    assert np.isfinite(c).all() and np.isfinite(centroid_jac(verts)).all()
    zeros = jnp.zeros_like(verts)
    assert np.isfinite(centroid_jac(zeros)).all() and np.isfinite(area_grad(zeros)).all()
