"""Tests for jaxgran.bem: element integrals, analytic stress states, Brazilian disc, psi,
invariance, batched vs single-particle API, gradients, bad input."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import bem

NU = 0.3
SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
HEXAGON = np.array([[1.0, 0.0], [0.5, 0.9], [-0.5, 0.85], [-1.1, 0.0], [-0.5, -0.9], [0.6, -0.8]])
DISC = np.zeros((1, 2))
outline_depth = jax.jit(bem._outline_depth)


def rotation(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def tensor(sigma):
    """[..., 3] (xx, yy, xy) -> [..., 2, 2]."""
    return np.stack(
        [
            np.stack([sigma[..., 0], sigma[..., 2]], -1),
            np.stack([sigma[..., 2], sigma[..., 1]], -1),
        ],
        -2,
    )


def brazilian(x, y, radius, load, thickness=1.0):
    """Closed-form stress (Pa) of a disc under diametral point loads at (0, +-R)
    (Timoshenko & Goodier; PHYSICS.md B)."""
    r1 = x**2 + (radius - y) ** 2
    r2 = x**2 + (radius + y) ** 2
    c = 2.0 * load / (math.pi * thickness)
    sxx = -c * ((radius - y) * x**2 / r1**2 + (radius + y) * x**2 / r2**2 - 0.5 / radius)
    syy = -c * ((radius - y) ** 3 / r1**2 + (radius + y) ** 3 / r2**2 - 0.5 / radius)
    sxy = c * ((radius - y) ** 2 * x / r1**2 - (radius + y) ** 2 * x / r2**2)
    return np.stack([sxx, syy, sxy], -1)


def element_forces(vertices, radius, n_elements, sigma):
    """Midpoints and forces sigma . n L of a uniform stress state on every element."""
    mid, _, length, normal = bem._boundary_elements(vertices, radius, n_elements, len(vertices))
    forces = np.einsum("ij,nj->ni", sigma, np.asarray(normal)) * np.asarray(length)[:, None]
    return np.asarray(mid), forces


# ---------------------------------------------------------------------------------------------
# boundary elements and closed-form element integrals
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "verts, radius",
    [(SQUARE, 0.0), (DISC, 1.0), (HEXAGON, 0.2), (np.array([[-1.0, 0.0], [1.0, 0.0]]), 0.5)],
    ids=["square", "disc", "spheropolygon", "stadium"],
)
def test_boundary_elements_lie_on_the_outline(verts, radius):
    n = 48
    padded = np.concatenate([verts, np.repeat(verts[-1:], 8 - len(verts), axis=0)])
    elements = bem._boundary_elements(padded, radius, n, n_verts=len(verts))
    mid, ends, length, normal = (np.asarray(x) for x in elements)
    nodes = ends[:, 0]
    # closed, CCW chain of straight elements whose ends lie on the outline
    np.testing.assert_allclose(ends[:, 1], np.roll(nodes, -1, axis=0), atol=1e-14)
    depth = np.asarray(outline_depth(jnp.asarray(nodes), jnp.asarray(padded), len(verts), radius))
    np.testing.assert_allclose(depth, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0)
    np.testing.assert_allclose((length[:, None] * normal).sum(0), 0.0, atol=1e-13)
    assert np.all(np.einsum("ij,ij->i", mid - mid.mean(0), normal) > 0)  # outward
    assert length.max() < 1.6 * length.sum() / n  # spread by length
    if len(verts) == 4:  # padding with copies of the last vertex changes nothing
        unpadded = bem._boundary_elements(verts, radius, n)
        np.testing.assert_allclose(np.asarray(unpadded[1]), ends, atol=1e-14)


def test_square_corners_are_element_ends():
    _, ends, length, _ = bem._boundary_elements(SQUARE, 0.0, 40)
    nodes = np.asarray(ends)[:, 0]
    for corner in SQUARE:
        assert np.min(np.linalg.norm(nodes - corner, axis=1)) < 1e-14
    np.testing.assert_allclose(np.asarray(length), 0.2)


def test_element_allocation_is_exact_in_batches():
    """Every particle's N elements close its outline with none much longer than nominal, also
    under lax.map (a regression: a largest-remainder rounding, recomputed differently in two
    XLA fusions, lost an element, and one chord spanned a whole edge)."""
    from jaxgran.geometry import offset_polygon, pad_polygons, polygon_centroid, voronoi_rectangle

    cells = voronoi_rectangle(0.3, 0.3, 200, 0, lloyd_iterations=2)
    cores = [offset_polygon(c, 1e-3) - polygon_centroid(c) for c in cells]
    verts, n_verts = pad_polygons(cores)
    radius = np.full(len(cores), 1e-3)

    def lengths(args):
        v, n, r = args
        nodes = bem._elements_padded(v, n, r, 64)
        return jnp.linalg.norm(jnp.roll(nodes, -1, axis=0) - nodes, axis=1)

    got = jax.jit(lambda *a: jax.lax.map(lengths, a, batch_size=8))(verts, n_verts, radius)
    got = np.asarray(got)
    perimeter = np.array(
        [np.linalg.norm(np.roll(c, -1, 0) - c, axis=1).sum() + 2 * np.pi * 1e-3 for c in cores]
    )
    assert np.all(got.max(axis=1) < 1.3 * perimeter / 64)  # measured 1.2
    ratio = got.sum(axis=1) / perimeter  # arcs become chords
    assert np.all((ratio > 0.99) & (ratio <= 1.0 + 1e-12))


def point_kernels(r, n, nu):
    """U, T [..., 2, 2] and D, S [..., 2 (k), 2, 2] at offsets r = x - xi (PHYSICS.md A1)."""
    rr = np.linalg.norm(r, axis=-1)[..., None]
    d = r / rr
    drdn = (d * n).sum(-1)[..., None, None]
    eye = np.eye(2)
    dd = d[..., :, None] * d[..., None, :]
    u = ((3 - 4 * nu) * np.log(1 / rr)[..., None] * eye + dd) / (8 * math.pi * (1 - nu))
    dn = d[..., :, None] * n[..., None, :]
    t = -(drdn * ((1 - 2 * nu) * eye + 2 * dd) - (1 - 2 * nu) * (dn - np.swapaxes(dn, -1, -2)))
    t = t / (4 * math.pi * (1 - nu) * rr[..., None])
    dk = d[..., :, None, None]
    di = d[..., None, :, None]
    dj = d[..., None, None, :]
    nk, ni, nj = n[..., :, None, None], n[..., None, :, None], n[..., None, None, :]
    e_ij, e_ik, e_jk = eye[None], eye[:, :, None], eye[:, None, :]
    big_d = (1 - 2 * nu) * (e_ik * dj + e_jk * di - e_ij * dk) + 2 * di * dj * dk
    big_d = big_d / (4 * math.pi * (1 - nu) * rr[..., None, None])
    big_s = (
        2
        * drdn[..., None]
        * ((1 - 2 * nu) * e_ij * dk + nu * (e_ik * dj + e_jk * di) - 4 * di * dj * dk)
        + 2 * nu * (ni * dj * dk + nj * di * dk)
        + (1 - 2 * nu) * (2 * nk * di * dj + nj * e_ik + ni * e_jk)
        - (1 - 4 * nu) * nk * e_ij
    ) / (2 * math.pi * (1 - nu) * rr[..., None, None] ** 2)
    return u, t, big_d, big_s


def gauss_integral(src, a, b, nu, n_sub=64):
    """Composite Gauss integrals over segments a -> b of the point kernels from src."""
    x, w = np.polynomial.legendre.leggauss(8)
    s = ((np.arange(n_sub)[:, None] + (x + 1) / 2).ravel()) / n_sub
    w = np.tile(w / 2, n_sub) / n_sub
    ab = b - a
    length = np.linalg.norm(ab, axis=-1)
    normal = np.stack([ab[:, 1], -ab[:, 0]], -1) / length[:, None]
    pts = a[:, None, :] + s[None, :, None] * ab[:, None, :]  # [E, Q, 2]
    r = pts[None] - src[:, None, None, :]
    out = point_kernels(r, np.broadcast_to(normal[None, :, None, :], r.shape), nu)
    return [np.einsum("seq...,q,e->se...", k, w, length) for k in out]


def test_closed_form_element_integrals_match_quadrature():
    """Closed-form U*, T*, D, S integrals vs 512-point composite Gauss of the point kernels,
    including near-singular pairs (neighbouring elements, points close to an element)."""
    _, ends, _, _ = bem._boundary_elements(HEXAGON, 0.1, 24)
    a, b = np.asarray(ends).transpose(1, 0, 2)
    mid = 0.5 * (a + b)
    nu = 0.25
    u_ref, t_ref, _, _ = gauss_integral(mid, a, b, nu)
    ut = np.asarray(jax.jit(lambda *x: bem._kelvin_ut(bem._pair(*x), nu))(mid, a, b))
    off = ~np.eye(len(mid), dtype=bool)
    np.testing.assert_allclose(ut[0].transpose(2, 3, 0, 1)[off], u_ref[off], atol=1e-13)
    np.testing.assert_allclose(ut[1].transpose(2, 3, 0, 1)[off], t_ref[off], atol=1e-13)
    # interior points, two of them within 0.1 element lengths of the boundary
    inward = mid[3] - 0.02 * (mid[3] - mid.mean(0))
    points = np.array([[0.0, 0.0], [0.4, -0.3], inward, 0.5 * (a[7] + mid[7]) * 0.995])
    _, _, d_ref, s_ref = gauss_integral(points, a, b, nu, n_sub=512)
    ds = np.asarray(jax.jit(lambda *x: bem._kelvin_ds(bem._pair(*x), nu))(points, a, b))
    ij = ([0, 1, 0], [0, 1, 1])
    for got, ref in ((ds[0], d_ref), (ds[1], s_ref)):
        ref = ref[..., ij[0], ij[1]].transpose(2, 3, 0, 1)  # -> [k, c, S, E]
        np.testing.assert_allclose(got, ref, atol=2e-9 * np.abs(ref).max())


# ---------------------------------------------------------------------------------------------
# analytic stress states
# ---------------------------------------------------------------------------------------------

UNIFORM = {
    "uniaxial": np.array([[1.0, 0.0], [0.0, 0.0]]),
    "biaxial": np.array([[1.0, 0.0], [0.0, -0.6]]),
    "shear": np.array([[0.0, 1.0], [1.0, 0.0]]),
}


@pytest.mark.parametrize("state", list(UNIFORM))
@pytest.mark.parametrize("shape", ["disc", "square"])
def test_uniform_traction(shape, state):
    """Uniform traction sigma . n on every element gives that uniform stress inside; error
    <= 0.5 % at N = 80 for |x| <= 0.8 R (disc) or 0.8 half-width (square)."""
    verts, radius = (DISC, 1.0) if shape == "disc" else (SQUARE, 0.0)
    sigma = UNIFORM[state]
    g = np.linspace(-0.8, 0.8, 17)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pts = pts[np.linalg.norm(pts, axis=1) <= 0.8 + 1e-12]
    mid, forces = element_forces(verts, radius, 80, sigma)
    got = bem.stress_field(
        verts,
        mid,
        forces,
        pts,
        poisson_ratio=NU,
        radius=radius,
        n_elements=80,
        load_model="element",
    )
    err = np.abs(got - [sigma[0, 0], sigma[1, 1], sigma[0, 1]]).max() / np.abs(sigma).max()
    assert err <= 5e-3, err


@pytest.fixture(scope="module")
def brazilian_runs():
    """Brazilian disc (R = 2 cm, P = 150 N, t = 1 cm) at several N: (N, points, sigma)."""
    radius, load, t = 0.02, 150.0, 0.01
    runs = {}
    for n in (32, 64, 128):
        pts, _ = bem.sample_points(DISC, radius, n, n_points=400)
        runs[n] = (
            pts,
            bem.stress_field(
                DISC,
                [[0.0, radius], [0.0, -radius]],
                [[0.0, -load], [0.0, load]],
                pts,
                poisson_ratio=NU,
                radius=radius,
                n_elements=n,
                thickness=t,
            ),
        )
    return radius, load, t, runs


def brazilian_error(radius, load, t, pts, sigma):
    """Max error over points > 0.3 R from the loads, in units of 2P/(pi D t)."""
    far = np.minimum(
        np.linalg.norm(pts - [0, radius], axis=1), np.linalg.norm(pts + [0, radius], axis=1)
    )
    keep = far > 0.3 * radius
    exact = brazilian(pts[:, 0], pts[:, 1], radius, load, t)
    return np.abs(sigma - exact)[keep].max() / (load / (math.pi * radius * t))


def test_brazilian_disc_against_closed_form(brazilian_runs):
    radius, load, t, runs = brazilian_runs
    pts, sigma = runs[128]
    assert len(pts) > 300
    # acceptance: 1 %; measured 0.10 % (a load moved by the chord sagitta already gives 0.7 %)
    assert brazilian_error(radius, load, t, pts, sigma) <= 0.003


def test_brazilian_convergence_order(brazilian_runs):
    radius, load, t, runs = brazilian_runs
    ns = sorted(runs)
    errors = [brazilian_error(radius, load, t, *runs[n]) for n in ns]
    order = -np.polyfit(np.log(ns), np.log(errors), 1)[0]
    # measured: errors 4.8e-3, 2.2e-3, 1.0e-3 of 2P/(pi D t), order about 1.1 (constant elements)
    assert order > 1.0, (errors, order)


@pytest.mark.parametrize("plane, k", [("stress", 3.4351), ("strain", 3.3823)])
def test_brazilian_connection_value(brazilian_runs, plane, k):
    """psi at the centre = k F / (pi R t) (PHYSICS.md C), within 1 % at N = 128."""
    radius, load, t, runs = brazilian_runs
    pts, sigma = runs[128]
    centre = np.argmin(np.linalg.norm(pts, axis=1))
    assert np.linalg.norm(pts[centre]) < 1e-15  # the grid contains the centre
    psi = bem.equivalent_stress(sigma[centre], NU, plane)
    assert abs(psi / (k * load / (math.pi * radius * t)) - 1.0) <= 0.01


def test_element_load_model_is_the_paper_traction(brazilian_runs):
    """load_model='element' spreads F over the loaded element (paper 000, Fig. 1c); it is much
    less accurate near point loads (PHYSICS.md A5: 3.7 % of 2P/(pi D t) at (0, R/2), N = 120)."""
    radius, load, t, runs = brazilian_runs
    pts, flamant = runs[128]
    elem = bem.stress_field(
        DISC,
        [[0.0, radius], [0.0, -radius]],
        [[0.0, -load], [0.0, load]],
        pts,
        poisson_ratio=NU,
        radius=radius,
        n_elements=128,
        thickness=t,
        load_model="element",
    )
    err = brazilian_error(radius, load, t, pts, elem)
    assert 0.03 < err < 0.2  # measured 0.145 (max over the grid, > 0.3 R from the loads)
    centre = np.argmin(np.linalg.norm(pts, axis=1))
    assert abs(elem[centre, 0] / flamant[centre, 0] - 1.0) < 0.02


# ---------------------------------------------------------------------------------------------
# psi
# ---------------------------------------------------------------------------------------------


def test_equivalent_stress():
    sigma = np.array([[-3.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, -3.0, 0.5], [0.0, 0.0, 0.0]])
    psi = bem.equivalent_stress(sigma, 0.25, "stress")
    assert isinstance(psi, np.ndarray)
    np.testing.assert_allclose(psi[:2], [3.0, 2.0])  # uniaxially psi = |sigma|
    assert psi[3] == 0.0
    for plane in ("stress", "strain"):
        # paper 000 Eq. 2 through the von Mises and hydrostatic stresses
        s = np.zeros((len(sigma), 3, 3))
        s[:, 0, 0], s[:, 1, 1], s[:, 0, 1], s[:, 1, 0] = sigma.T[[0, 1, 2, 2]]
        if plane == "strain":
            s[:, 2, 2] = 0.25 * (sigma[:, 0] + sigma[:, 1])
        mean = np.trace(s, axis1=1, axis2=2) / 3
        dev = s - mean[:, None, None] * np.eye(3)
        vm = np.sqrt(1.5 * (dev**2).sum((1, 2)))
        eq2 = np.sqrt(2 / 3 * 1.25 * vm**2 + 3 * 0.5 * mean**2)
        np.testing.assert_allclose(bem.equivalent_stress(sigma, 0.25, plane), eq2, atol=1e-14)
    g = jax.grad(lambda s: bem.equivalent_stress(s, 0.3)[3])(jnp.asarray(sigma))
    assert np.isfinite(np.asarray(g)).all()  # safe at zero stress


# ---------------------------------------------------------------------------------------------
# invariance
# ---------------------------------------------------------------------------------------------

LOADS_POINTS = np.array([[1.0, 0.0], [-0.5, 0.85], [-0.5, -0.9], [0.8, -0.4]])
LOADS_FORCES = np.array([[-2.0, 0.3], [1.1, -1.6], [0.7, 1.4], [0.2, -0.1]])


@pytest.fixture(scope="module")
def probes():
    """~400 points in the hexagon (as many as the Brazilian runs: the same compiled shapes)."""
    return bem.sample_points(HEXAGON, 0.05, 64, n_points=400)[0]


def hexagon_field(pts, verts=HEXAGON, cp=LOADS_POINTS, cf=LOADS_FORCES, **kw):
    kw = dict(poisson_ratio=NU, n_elements=64, radius=0.05) | kw
    return bem.stress_field(verts, cp, cf, pts, **kw)


def test_rotation_and_translation_invariance(probes):
    ref = hexagon_field(probes)
    q = rotation(0.7)
    shift = np.array([3.0, -2.0])
    moved = hexagon_field(
        probes @ q.T + shift, HEXAGON @ q.T + shift, LOADS_POINTS @ q.T + shift, LOADS_FORCES @ q.T
    )
    expect = q @ tensor(ref) @ q.T
    np.testing.assert_allclose(tensor(moved), expect, atol=1e-8 * np.abs(ref).max())


@pytest.mark.parametrize("scale", [1e-3, 50.0])
def test_length_unit_independence(probes, scale):
    """Lengths x c, same forces: stress / c, to round-off (Lagrange constraints)."""
    ref = hexagon_field(probes)
    got = hexagon_field(
        probes * scale, HEXAGON * scale, LOADS_POINTS * scale, LOADS_FORCES, radius=0.05 * scale
    )
    np.testing.assert_allclose(got * scale, ref, atol=1e-9 * np.abs(ref).max())


def test_unbalanced_loads_are_equilibrated(brazilian_runs):
    """Top 1.00 P + a small tangential force, bottom 0.98 P: after the minimum-norm correction
    this is the balanced Brazilian load 0.99 P, so the field equals it (and the closed form)."""
    radius, load, t, runs = brazilian_runs
    pts = runs[128][0]
    kw = dict(poisson_ratio=NU, radius=radius, n_elements=128, thickness=t)
    cp = [[0.0, radius], [0.0, -radius]]
    forces = np.array([[0.02, -1.0], [0.0, 0.98]]) * load
    unbalanced = bem.stress_field(DISC, cp, forces, pts, **kw)
    balanced = bem.stress_field(DISC, cp, [[0.0, -0.99 * load], [0.0, 0.99 * load]], pts, **kw)
    np.testing.assert_allclose(unbalanced, balanced, atol=1e-12 * np.abs(balanced).max())
    p = 0.99 * load / (math.pi * radius * t)
    assert brazilian_error(radius, 0.99 * load, t, pts, balanced) * load / (0.99 * load) < 0.01
    assert abs(balanced[np.argmin(np.linalg.norm(pts, axis=1)), 0] / p - 1.0) < 3e-3
    # one contact: no static state, nothing to equilibrate; the Lagrange multipliers absorb it
    single = bem.stress_field(DISC, cp[:1], forces[:1], pts, **kw)
    assert np.isfinite(single).all()


def test_unbalanced_imbalance_changes_little(probes):
    """An imbalance of 3 % (dynamic DEM forces) changes the field by about as much."""
    base = hexagon_field(probes)
    noisy = hexagon_field(
        probes, cf=LOADS_FORCES + [[0.03, 0.0], [0.0, 0.0], [0.0, 0.02], [0.0, 0.0]]
    )
    assert np.abs(noisy - base).max() < 0.05 * np.abs(base).max()


def test_plane_and_poisson_only_through_discretisation(probes):
    """In-plane stress of a traction-loaded body does not depend on nu or plane (Michell)."""
    a = hexagon_field(probes, poisson_ratio=0.0)
    b = hexagon_field(probes, poisson_ratio=0.45, plane="strain")
    assert np.abs(a - b).max() < 0.02 * np.abs(a).max()


# ---------------------------------------------------------------------------------------------
# batched operators
# ---------------------------------------------------------------------------------------------

PARTICLES = [
    (HEXAGON * 0.01, 0.0),
    (np.array([[0.0, -1.0], [1.0, 0.0], [0.3, 1.0], [-0.9, 0.4]]) * 0.02, 0.001),
    (DISC, 0.015),
    (np.array([[-1.0, 0.0], [1.0, 0.2]]) * 0.01, 0.004),
    (np.zeros((0, 2)), 0.0),  # empty slot
]


@pytest.fixture(scope="module")
def batch():
    from jaxgran.geometry import pad_polygons

    polys = [p if len(p) else np.zeros((1, 2)) for p, _ in PARTICLES]
    verts, n_verts = pad_polygons(polys, 6)
    n_verts[-1] = 0
    radius = np.array([r for _, r in PARTICLES])
    ops = bem.build_operators(
        verts, n_verts, radius, n_elements=64, n_points=400, poisson_ratio=NU, batch_size=2
    )
    # three contacts per particle on the outline, one of them between two element midpoints
    rng = np.random.default_rng(1)
    nodes = np.asarray(ops.nodes)
    mid = np.asarray(ops.midpoints)
    cp = np.stack([mid[:, 5], mid[:, 30], 0.7 * nodes[:, 50] + 0.3 * nodes[:, 51]], axis=1)
    cf = rng.normal(size=cp.shape) * 10.0
    mask = np.ones(cp.shape[:2], bool)
    mask[0, 2] = False
    return verts, n_verts, radius, ops, cp, cf, mask


def test_build_operators_shapes_and_points(batch):
    verts, n_verts, radius, ops, *_ = batch
    P = len(PARTICLES)
    assert ops.stress_per_force.shape == (P, 64, 2, 400, 3)
    assert ops.points.shape == (P, 400, 2) and ops.point_mask.shape == (P, 400)
    np.testing.assert_array_equal(np.asarray(ops.valid), [True] * (P - 1) + [False])
    counts = np.asarray(ops.point_mask).sum(1)
    assert np.all(counts[:-1] >= 300) and counts[-1] == 0
    for p in range(P - 1):
        pts = np.asarray(ops.points[p])[np.asarray(ops.point_mask[p])]
        depth = outline_depth(jnp.asarray(pts), jnp.asarray(verts[p]), n_verts[p], radius[p])
        assert np.min(np.asarray(depth)) >= 1.5 * float(ops.lengths[p].max()) * (1 - 1e-12)
        # the grid: points = centroid + spacing * ij
        ij = np.asarray(ops.grid_index[p])[np.asarray(ops.point_mask[p])]
        anchor = pts - float(ops.spacing[p]) * ij
        np.testing.assert_allclose(anchor, np.broadcast_to(anchor[0], anchor.shape), atol=1e-15)


def test_contact_element_lookup_brackets_each_contact(batch):
    """The angular-sector lookup puts each contact between the midpoints of the element that
    holds it and a neighbour, with the hat weight of its arc-length position between them."""
    _, _, _, ops, *_ = batch
    rng = np.random.default_rng(3)
    nodes = np.asarray(ops.nodes)
    P, N = nodes.shape[:2]
    rows = np.arange(P - 1)  # the last slot is invalid
    e = rng.integers(0, N, (P - 1, 50))
    s = rng.random((P - 1, 50, 1))
    a, b = nodes[rows[:, None], e], nodes[rows[:, None], (e + 1) % N]
    cp = a + s * (b - a)
    lo, w = jax.vmap(bem._assign_contacts)(
        jnp.asarray(cp), ops.nodes[:-1], ops.centres[:-1], ops.node_angles[:-1]
    )
    lo, w = np.asarray(lo), np.asarray(w)
    near = (lo == e) | ((lo + 1) % N == e)
    assert near.all()
    # the hat weight is the contact's arc-length position between the two midpoints
    length = np.asarray(ops.lengths)[rows]  # [P', N]
    start = np.cumsum(length, axis=1) - length
    perim = length.sum(axis=1, keepdims=True)
    arc = np.take_along_axis(start, e, 1) + s[..., 0] * np.take_along_axis(length, e, 1)
    m_lo = np.take_along_axis(start + 0.5 * length, lo, 1)
    m_hi = np.take_along_axis(start + 0.5 * length, (lo + 1) % N, 1)
    m_hi = np.where(m_hi < m_lo, m_hi + perim, m_hi)
    arc = np.where(arc < m_lo, arc + perim, arc)
    np.testing.assert_allclose(w, (arc - m_lo) / (m_hi - m_lo), atol=1e-9)


def test_sample_points_matches_batched_grid(batch):
    verts, n_verts, radius, ops, *_ = batch
    pts, ij = bem.sample_points(verts[1, : n_verts[1]], radius[1], 64, n_points=400)
    np.testing.assert_allclose(pts, np.asarray(ops.points[1])[np.asarray(ops.point_mask[1])])
    np.testing.assert_array_equal(ij, np.asarray(ops.grid_index[1])[np.asarray(ops.point_mask[1])])
    spaced, ij2 = bem.sample_points(verts[1, : n_verts[1]], radius[1], 64, spacing=0.004)
    assert len(spaced) > 20
    anchor = spaced - 0.004 * ij2
    np.testing.assert_allclose(anchor, np.broadcast_to(anchor[0], anchor.shape), atol=1e-15)


def test_batched_equals_single_particle_api(batch):
    verts, n_verts, radius, ops, cp, cf, mask = batch
    sigma, psi = jax.jit(bem.psi_batched)(ops, cp, cf, mask, thickness=0.01)
    sigma, psi = np.asarray(sigma), np.asarray(psi)
    for p in range(len(PARTICLES) - 1):
        keep = np.asarray(ops.point_mask[p])
        ref = bem.stress_field(
            verts[p, : n_verts[p]],
            cp[p][mask[p]],
            cf[p][mask[p]],
            np.asarray(ops.points[p])[keep],
            poisson_ratio=NU,
            n_elements=64,
            thickness=0.01,
            radius=radius[p],
        )
        np.testing.assert_allclose(sigma[p][keep], ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
        np.testing.assert_allclose(psi[p][keep], bem.equivalent_stress(ref, NU), rtol=1e-9)
        assert np.all(sigma[p][~keep] == 0)
    assert np.all(sigma[-1] == 0) and np.all(psi[-1] == 0)


def test_update_operators_rebuilds_slots(batch):
    """Writing the particles back in reverse order gives the reversed operators."""
    verts, n_verts, radius, ops, *_ = batch
    order = np.arange(len(PARTICLES))[::-1]
    moved = bem.update_operators(ops, order, verts, n_verts, radius, batch_size=2)
    leaves = zip(jax.tree_util.tree_leaves(ops), jax.tree_util.tree_leaves(moved), strict=True)
    for old, new in leaves:
        if np.ndim(old):
            np.testing.assert_array_equal(np.asarray(new)[order], np.asarray(old))
    with pytest.raises(ValueError, match="slots"):
        bem.update_operators(ops, [0, 0], verts[:2], n_verts[:2], radius[:2])


def test_psi_batched_float32_and_no_recompile(batch):
    *_, ops, cp, cf, mask = batch
    f = jax.jit(eqx.debug.assert_max_traces(bem.psi_batched, max_traces=1))
    ref = np.asarray(f(ops, cp, cf, mask)[1])
    np.testing.assert_allclose(np.asarray(f(ops, cp, 2.0 * cf, mask)[1]), 2.0 * ref)
    ops32 = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, ops
    )
    cp32, cf32 = (jnp.asarray(x, jnp.float32) for x in (cp, cf))
    psi32 = jax.jit(bem.psi_batched)(ops32, cp32, cf32, mask)[1]
    assert psi32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(psi32), ref, rtol=1e-4, atol=1e-5 * ref.max())


def test_gradient_wrt_force_magnitude(batch):
    *_, ops, cp, cf, mask = batch
    direction = cf[1, 1] / np.linalg.norm(cf[1, 1])
    m = int(np.argmax(np.asarray(ops.point_mask[1]) * np.abs(np.asarray(ops.points[1, :, 0]))))

    @jax.jit
    def psi_at(magnitude):
        forces = jnp.asarray(cf).at[1, 1].set(magnitude * direction)
        return bem.psi_batched(ops, cp, forces, mask)[1][1, m]

    f0 = float(np.linalg.norm(cf[1, 1]))
    grad = float(jax.jit(jax.grad(psi_at))(f0))
    h = 1e-4 * f0
    fd = (float(psi_at(f0 + h)) - float(psi_at(f0 - h))) / (2 * h)
    assert grad != 0.0
    assert abs(grad - fd) <= 1e-6 * abs(fd)


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(vertices=[[0, 0], [1, 0], [0.2, 0.2], [0, 1]]), "not convex"),
        (dict(contact_points=[[1.0, 0.0], [3.0, 0.0]]), "off the particle boundary"),
        (dict(contact_forces=[[-1.0, 0.0], [np.nan, 0.0]]), "NaN"),
        (dict(vertices=[[0, 0], [1, 0]]), "no area"),
        (dict(vertices=[[0, 0]]), "no area"),
        (dict(points=[[5.0, 5.0]]), "not inside the particle"),
        (dict(plane="strian"), "plane must be"),
        (dict(poisson_ratio=0.5), "poisson_ratio"),
        (dict(n_elements=4), "n_elements"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = dict(
        vertices=SQUARE,
        contact_points=[[1.0, 0.0], [-1.0, 0.0]],
        contact_forces=[[-1.0, 0.0], [1.0, 0.0]],
        points=[[0.0, 0.0]],
        poisson_ratio=NU,
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        bem.stress_field(
            args.pop("vertices"),
            args.pop("contact_points"),
            args.pop("contact_forces"),
            args.pop("points"),
            **args,
        )


def test_bad_input_batched_and_sampling():
    with pytest.raises(ValueError, match="shape"):
        bem.build_operators(np.zeros((3, 2)), [1], [1.0], poisson_ratio=NU)
    with pytest.raises(ValueError, match="load_model"):
        bem.build_operators(np.zeros((1, 1, 2)), [1], [1.0], poisson_ratio=NU, load_model="x")
    with pytest.raises(ValueError, match="either spacing or n_points"):
        bem.sample_points(SQUARE, 0.0, 32, spacing=0.1, n_points=10)


def random_loads(ops, n_contacts, seed, offset=0.1):
    """Contacts on random elements, moved off the chord by up to ``offset`` element lengths
    (out: like points on corner arcs; in: like overlapping contacts), with forces of random
    direction and size and some contacts masked."""
    rng = np.random.default_rng(seed)
    nodes, normals = np.asarray(ops.nodes), np.asarray(ops.normals)
    length = np.asarray(ops.lengths)
    P, N = nodes.shape[:2]
    rows = np.arange(P)[:, None]
    e = rng.integers(0, N, (P, n_contacts))
    s = rng.random((P, n_contacts, 1))
    a, b = nodes[rows, e], nodes[rows, (e + 1) % N]
    dn = offset * rng.uniform(-1, 1, (P, n_contacts, 1)) * length[rows, e][..., None]
    cp = a + s * (b - a) + dn * normals[rows, e]
    cf = rng.normal(size=cp.shape) * rng.lognormal(3.0, 1.0, (P, n_contacts, 1))
    mask = rng.random((P, n_contacts)) < 0.8
    return cp, cf, mask


def test_psi_bound_bounds_the_field(batch):
    """psi_bound is never below the largest psi of the field it bounds (200 random loadings of
    every particle shape, float64 and float32), is zero for the invalid slot, and is not
    vacuous (median ratio to the field under 2, 95th percentile under 4)."""
    *_, ops, _, _, _ = batch
    ops32 = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, ops
    )
    field = jax.jit(lambda o, c, f, m: bem.psi_batched(o, c, f, m, thickness=0.01)[1].max(1))
    bound = jax.jit(lambda o, c, f, m: bem.psi_bound(o, c, f, m, thickness=0.01))
    ratios = []
    for seed in range(200):
        # 1-6 loaded contacts, padded to 6 slots (masked, zero force): one compilation
        cp, cf, mask = random_loads(ops, 1 + seed % 6, seed)
        pad = ((0, 0), (0, 6 - mask.shape[1]))
        cp = np.pad(cp, pad + ((0, 0),), mode="edge")
        cf, mask = np.pad(cf, pad + ((0, 0),)), np.pad(mask, pad)
        psi, b = np.asarray(field(ops, cp, cf, mask)), np.asarray(bound(ops, cp, cf, mask))
        assert b[-1] == 0.0 and psi[-1] == 0.0
        assert np.all(b[:-1] >= psi[:-1]), seed
        loaded = psi[:-1] > 0
        ratios.append(b[:-1][loaded] / psi[:-1][loaded])
        if seed % 20 == 0:
            args = [jnp.asarray(x, jnp.float32) for x in (cp, cf)] + [jnp.asarray(mask)]
            p32, b32 = np.asarray(field(ops32, *args)), np.asarray(bound(ops32, *args))
            assert np.all(b32 >= p32), seed
    ratios = np.concatenate(ratios)
    # measured: median 1.83, 95th percentile 3.53 (2.13 and 4.06 with operator norms and the
    # geometric Flamant bound instead of the directional tables; the largest ratios come
    # from nearly cancelling forces, which the triangle inequality cannot see)
    assert np.median(ratios) < 2.0 and np.percentile(ratios, 95) < 4.0


def test_psi_bound_flags_a_contact_pushed_inside(batch):
    """A contact moved deep inside (further than the sample points are) cannot be bounded from
    the tables: the bound is +inf, so the particle is never screened out."""
    *_, ops, cp, cf, mask = batch
    cp = np.array(cp)
    cp[1, 0] = 0.2 * cp[1, 0] + 0.8 * np.asarray(ops.centres[1])
    b = np.asarray(bem.psi_bound(ops, cp, cf, mask))
    assert np.isinf(b[1]) and np.all(np.isfinite(np.delete(b, 1)))


@pytest.mark.parametrize("fine_slots", [None, 1])
@pytest.mark.parametrize("quantile", [100.0, 75.0, 30.0])
def test_screen_matches_thresholding_the_full_field(batch, quantile, fine_slots):
    """The screening returns exactly the particles whose full field reaches the threshold,
    with their field; a candidate list that is too short is regrown, not cut, and so is the
    list of contacts that the coarse level passes to the fine bound (``fine_slots=1``)."""
    *_, ops, _, _, _ = batch
    cp, cf, mask = random_loads(ops, 5, 7)
    sigma, psi = bem.psi_batched(ops, cp, cf, mask)
    psi_max = np.asarray(psi).max(1)
    # just below a particle's value: a threshold equal to it would be decided by rounding
    thr = np.percentile(psi_max[:-1], quantile) * (1.0 - 1e-9)
    res = bem.screen(ops, cp, cf, mask, thr, max_candidates=1, fine_slots=fine_slots)
    assert bool(res.complete) and int(res.n_candidates) <= res.candidates.shape[0]
    if fine_slots is not None:
        assert int(res.n_coarse) >= int(res.n_candidates) >= 1
    idx = np.asarray(res.candidates)
    got = set(idx[np.asarray(res.reaches)].tolist())
    assert got == set(np.flatnonzero(psi_max >= thr).tolist())
    cand = idx[np.asarray(res.is_candidate)]
    assert set(cand.tolist()) == set(np.flatnonzero(np.asarray(res.bound) >= thr).tolist())
    np.testing.assert_allclose(np.asarray(res.psi), np.asarray(psi)[idx], rtol=1e-12, atol=0)
    # the same field up to rounding: summation order differs between the two paths (and
    # between CPUs), so components that nearly cancel are compared on the field's scale
    ref = np.asarray(sigma)[idx]
    scale = np.abs(ref).max()
    np.testing.assert_allclose(np.asarray(res.sigma), ref, rtol=1e-12, atol=1e-13 * scale)


def test_direction_weights_rebuild_the_force():
    """The directional weights are >= 0, at most two of them (neighbours) are non-zero, and
    sum_k w_k u_k = +-f: the interpolation of the screening tables rests on that."""
    rng = np.random.default_rng(4)
    u = np.asarray(bem._half_turn_directions(jnp.float64))
    angles = np.concatenate([rng.uniform(-np.pi, np.pi, 500), np.arange(-8, 9) * np.pi / 8])
    for a in angles:
        f = 3.7 * np.array([np.cos(a), np.sin(a)])
        w = np.asarray(bem._direction_weights(jnp.asarray(f)))
        assert np.all(w >= 0) and np.count_nonzero(w) <= 2
        back = w @ u
        if w[0] > 0 and w[-1] > 0:  # the last sector, from u_(K-1) to u_K = -u_0
            back = w[-1] * u[-1] - w[0] * u[0]
        assert min(np.abs(back - f).max(), np.abs(back + f).max()) < 1e-12, a
    np.testing.assert_array_equal(np.asarray(bem._direction_weights(jnp.zeros(2))), 0.0)


def test_coarse_bound_is_never_below_the_fine_bound(batch):
    """The coarse bound (one row per contact) is never below the fine one, so never below
    the field; without its rows (``bound_operators``) it is +inf, so the coarse level then
    passes every loaded particle on to the fine bound."""
    *_, ops, _, _, _ = batch
    P, C = ops.lengths.shape[0], 6
    both = eqx.filter_jit(lambda o, *f: (bem.psi_bound_flat(o, *f), bem.psi_bound_coarse(o, *f)))
    ratios = []
    for seed in range(40):
        cp, cf, mask = random_loads(ops, 1 + seed % C, 100 + seed)
        pad = ((0, 0), (0, C - mask.shape[1]))  # one list length: one compilation
        cp, cf = (np.pad(x, (*pad, (0, 0))) for x in (cp, cf))
        mask = np.pad(mask, pad)
        flat = (np.repeat(np.arange(P), C), cp.reshape(-1, 2), cf.reshape(-1, 2), mask.reshape(-1))
        fine, coarse = (np.asarray(x) for x in both(ops, *flat))
        assert np.all(coarse >= fine), seed
        loaded = fine > 0
        ratios.append(coarse[loaded] / fine[loaded])
    # measured: median 1.37, largest 2.18
    assert np.median(np.concatenate(ratios)) < 1.6
    light = bem.bound_operators(
        **{k: getattr(ops, k) for k in bem.BOUND_FIELDS},
        poisson_ratio=ops.poisson_ratio,
        plane=ops.plane,
        load_model=ops.load_model,
    )
    got = np.asarray(bem.psi_bound_coarse(light, *flat))
    assert np.all(np.isinf(got[loaded])) and np.all(got[~loaded] == 0.0)


def test_coarse_level_gives_the_fine_bound_of_the_particles_it_passes(batch):
    """The coarse level moves the contacts of the particles it passes into its own slots:
    their bound equals the fine bound, the others keep the coarse one, and too few slots
    are reported (``complete`` False), not cut silently."""
    *_, ops, _, _, _ = batch
    cp, cf, mask = random_loads(ops, 6, 21)
    P = ops.lengths.shape[0]
    flat = tuple(jnp.asarray(x) for x in bem._flat_contacts(cp, cf, mask))
    fine = np.asarray(bem.psi_bound_flat(ops, *flat))
    coarse = np.asarray(bem.psi_bound_coarse(ops, *flat))
    thr = 0.5 * np.max(fine[:-1])
    s1 = 16
    res = bem._screen_jit(ops, cp, cf, mask, thr, 1.0, P, flat, 8, s1)
    passed = coarse / thr >= 1.0
    assert 0 < passed.sum() < P  # the coarse level rules some particles out, not all
    want = np.where(passed, np.minimum(coarse, fine), coarse)
    np.testing.assert_allclose(np.asarray(res.bound), want, rtol=1e-12)
    assert int(res.n_coarse) == int(passed.sum())
    assert int(res.n_fine_contacts) == int(mask[passed].sum())
    assert bool(res.complete) == (int(mask[passed].sum()) <= s1)
    short = bem._screen_jit(ops, cp, cf, mask, thr, 1.0, P, flat, 8, 1)
    assert not bool(short.complete)
    full = bem.screen(ops, cp, cf, mask, thr, max_candidates=1, fine_slots=1)
    assert bool(full.complete)
    assert set(np.asarray(full.candidates)[np.asarray(full.is_candidate)].tolist()) == set(
        np.flatnonzero(fine >= thr).tolist()
    )


def test_screen_rejects_bad_threshold(batch):
    *_, ops, cp, cf, mask = batch
    for thr in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="threshold"):
            bem.screen(ops, cp, cf, mask, thr)
    with pytest.raises(ValueError, match="fine_slots"):
        bem.screen(ops, cp, cf, mask, 1.0, fine_slots=0)


def test_flat_bound_equals_padded_bound(batch):
    """The flat contact list (shuffled, padded with masked entries) gives the padded lists'
    bound, and its per-particle equilibration is ``_equilibrate`` of each particle."""
    *_, ops, _, _, _ = batch
    cp, cf, mask = random_loads(ops, 4, 11)
    P, C = mask.shape
    ref = np.asarray(bem.psi_bound(ops, cp, cf, mask))
    rng = np.random.default_rng(0)
    order = rng.permutation(P * C)
    particle = np.repeat(np.arange(P), C)[order]
    flat = (cp.reshape(-1, 2)[order], cf.reshape(-1, 2)[order], mask.reshape(-1)[order])
    got = bem.psi_bound_flat(ops, particle, *flat)
    np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12)
    eq_flat = np.asarray(
        bem._equilibrate_flat(
            *(jnp.asarray(x) for x in flat[:2]), jnp.asarray(flat[2]), jnp.asarray(particle), P
        )
    )
    eq = np.asarray(jax.vmap(bem._equilibrate)(cp, np.where(mask[..., None], cf, 0.0), mask))
    np.testing.assert_allclose(eq_flat, eq.reshape(-1, 2)[order], atol=1e-12 * np.abs(cf).max())


def test_bound_operators_give_the_bound_of_the_full_operators(batch):
    """Operators holding only ``BOUND_FIELDS`` (what the DSM keeps for every particle) give
    the full operators' bound, on stacked rows in another order too."""
    *_, ops, _, _, _ = batch
    cp, cf, mask = random_loads(ops, 4, 3)
    ref = np.asarray(bem.psi_bound(ops, cp, cf, mask))
    rows = {k: getattr(ops, k) for k in bem.BOUND_FIELDS}
    light = bem.bound_operators(
        **rows, poisson_ratio=ops.poisson_ratio, plane=ops.plane, load_model=ops.load_model
    )
    assert light.stress_per_force.size == 6 * ops.lengths.shape[0]
    np.testing.assert_array_equal(np.asarray(bem.psi_bound(light, cp, cf, mask)), ref)
    order = np.arange(ops.lengths.shape[0])[::-1]
    turned = bem.bound_operators(
        **{k: v[order] for k, v in rows.items()},
        poisson_ratio=ops.poisson_ratio,
        plane=ops.plane,
        load_model=ops.load_model,
    )
    got = np.asarray(bem.psi_bound(turned, cp[order], cf[order], mask[order]))
    np.testing.assert_array_equal(got, ref[order])


def test_binned_element_lookup_equals_the_full_comparison(batch):
    """The binned lookup of the contact's element (a few node angles read) gives the element
    of the full comparison with every node angle, and without bins (-1, a particle whose bin
    holds too many nodes) the flat bound falls back to the full comparison unchanged."""
    *_, ops, _, _, _ = batch
    P = ops.lengths.shape[0] - 1  # the last slot is invalid
    assert np.all(np.asarray(ops.angle_bins[:P, 0]) >= 0)
    cp, cf, mask = random_loads(ops, 6, 5, offset=0.5)
    rows = np.repeat(np.arange(P), 6)
    pts = jnp.asarray(cp[:P].reshape(-1, 2))

    def binned(i, x):
        return bem._binned_element(
            x, ops.centres[i], lambda k: ops.node_angles[i, k], ops.angle_bins[i]
        )

    def compared(i, x):
        return bem._contact_elements(x[None], ops.nodes[i], ops.centres[i], ops.node_angles[i])[0][
            0
        ]

    np.testing.assert_array_equal(
        np.asarray(jax.vmap(binned)(rows, pts)), np.asarray(jax.vmap(compared)(rows, pts))
    )
    no_bins = eqx.tree_at(lambda o: o.angle_bins, ops, -jnp.ones_like(ops.angle_bins))
    np.testing.assert_allclose(
        np.asarray(bem.psi_bound(no_bins, cp, cf, mask)),
        np.asarray(bem.psi_bound(ops, cp, cf, mask)),
        rtol=1e-12,
    )


def test_screen_compacts_long_contact_lists(batch):
    """With 12 contact slots and at most 8 real contacts, scattered, the candidates' field
    runs over the real contacts moved to 8 slots and equals the full field; one particle
    with 12 regrows the slots."""
    *_, ops, _, _, _ = batch
    cp, cf, mask = random_loads(ops, 12, 13)
    mask[:, ::3] = False  # holes between the real contacts: at most 8 per particle
    for full_row in (False, True):
        if full_row:
            mask[1, :] = True
        psi = np.asarray(bem.psi_batched(ops, cp, cf, mask)[1])
        thr = np.percentile(psi.max(1)[:-1], 10.0) * (1.0 - 1e-9)
        k = ops.lengths.shape[0]  # all five slots
        res = bem._screen_jit(ops, cp, cf, mask, thr, 1.0, k, None, 8)
        assert bool(res.complete) != full_row
        res = bem.screen(ops, cp, cf, mask, thr, max_candidates=k)
        assert bool(res.complete) and int(res.max_contacts) == (12 if full_row else 8)
        idx = np.asarray(res.candidates)
        np.testing.assert_allclose(
            np.asarray(res.psi), psi[idx], rtol=1e-12, atol=1e-12 * psi.max()
        )
        got = set(idx[np.asarray(res.reaches)].tolist())
        assert got == set(np.flatnonzero(psi.max(1) >= thr).tolist())
