"""Fragment replacement: erosion geometry, mass bookkeeping, momentum, no overlap at
creation, tangential history, capacity growth (paper 000 §II.D)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import geometry as geo
from jaxgran.breakage.replace import (
    dilated_outline,
    fit_vertex_capacity,
    max_overlap,
    merge_small_pieces,
    replace_particle,
)
from jaxgran.breakage.ssm import split_convex
from jaxgran.contact import pair_forces
from jaxgran.partition import make_grid
from jaxgran.simulate import prepare, run_segment
from jaxgran.state import make_params, make_state, make_walls, particles_from_polygons, replace

RHO = 12.0
R = 1e-3  # sphero-radius (m)
A = 0.02  # square core side (m)


def _square(center=(0.0, 0.0), side=A):
    return geo.regular_polygon(4, side / math.sqrt(2), math.pi / 4, center)


def _world_core(state, k):
    p = state.particles
    n = int(p.n_verts[k])
    c, s = math.cos(float(p.angle[k])), math.sin(float(p.angle[k]))
    return np.asarray(p.verts[k, :n]) @ np.array([[c, s], [-s, c]]) + np.asarray(p.pos[k])


def _state(polys, capacity=None, vertex_capacity=None, velocities=None):
    parts = particles_from_polygons(
        polys, R, RHO, capacity=capacity, vertex_capacity=vertex_capacity, velocities=velocities
    )
    return make_state(parts, make_walls([]))


def _cut(state, k, lines, r=R):
    return split_convex(dilated_outline(_world_core(state, k), r), np.asarray(lines, float))


# ----------------------------------------------------------------------------- geometry


@pytest.mark.parametrize("n", [3, 5, 32])
def test_dilated_outline_erodes_back_to_the_core(n):
    core = geo.regular_polygon(n, 0.01, 0.3, (0.1, -0.2))
    out = dilated_outline(core, R, n_arc=64)
    back = geo.offset_polygon(out, R)
    assert len(back) == n
    dist = np.linalg.norm(back[:, None, :] - core[None, :, :], axis=-1).min(axis=1)
    assert dist.max() < 1e-14
    exact = geo.spheropolygon_mass_properties(core, R, 1.0)[0]
    excess = geo.polygon_area(out) - exact
    assert 0 < excess <= 1.1 * math.pi**3 * R**2 / (3 * 64**2)


def test_dilated_outline_of_a_core_with_a_collinear_vertex():
    """A vertex in the middle of a straight edge (Voronoi cells and clipped pieces have
    them) adds no arc: the outline is that of the square without it."""
    a = 0.01
    square = np.array([[0, 0], [a, 0], [a, a], [0, a]], float)
    with_mid = np.array([[0, 0], [a / 2, 0], [a, 0], [a, a], [0, a]], float)
    out = dilated_outline(with_mid, R, n_arc=64)
    ref = dilated_outline(square, R, n_arc=64)
    assert geo.polygon_area(out) == pytest.approx(geo.polygon_area(ref), rel=1e-12)
    assert np.allclose(out.min(axis=0), -R) and np.allclose(out.max(axis=0), a + R)


# ----------------------------------------------------------------------------- bookkeeping


def test_straight_cut_rounds_only_the_new_corners():
    """A square cut through its centre, no overlap: each fragment is the half rectangle
    eroded by r and swept again, so the loss is the four new corners, r^2 (1 - pi/4) each."""
    state = _state([_square()], capacity=2)
    pieces = _cut(state, 0, [[[0, -1], [0, 1]]])
    state, ev = replace_particle(state, 0, pieces, overlap=0.0, clearance=0.0)
    m0 = ev["parent_mass"]
    assert ev["fragment_masses"].size == 2
    assert ev["mass_lost"] == pytest.approx(RHO * 4 * R**2 * (1 - math.pi / 4), rel=1e-6)
    assert ev["fines_mass"] == 0.0
    total = ev["fragment_masses"].sum() + ev["fines_mass"] + ev["eroded_mass"]
    assert total == pytest.approx(m0, rel=1e-14)
    # nothing in the way: the whole loss is the rounding of the new corners
    assert ev["caps_mass"] == 0.0 and ev["caps_area"] == 0.0
    assert ev["rounding_mass"] == ev["eroded_mass"]
    p = state.particles
    assert np.asarray(p.active).tolist() == [True, True]
    assert np.asarray(p.parent_uid).tolist() == [0, 0]
    assert len(set(np.asarray(p.uid).tolist())) == 2 and int(p.uid.min()) > 1
    assert "breakage_type" not in ev  # no mean initial mass given


def test_erosion_by_the_overlap_is_exact_and_areas_add_up():
    """Fragment = (half piece eroded by r + delta) swept by r: for the square cut in half
    the core is a (A/2 - r - 2 delta) x (A - 2 delta) rectangle."""
    delta = 2e-4
    state = _state([_square()], capacity=2)
    state, ev = replace_particle(
        state, 0, _cut(state, 0, [[[0, -1], [0, 1]]]), overlap=delta, clearance=0.0
    )
    w, h = A / 2 - R - 2 * delta, A - 2 * delta
    expected = RHO * (w * h + 2 * R * (w + h) + math.pi * R**2)
    np.testing.assert_allclose(ev["fragment_masses"], expected, rtol=1e-12)
    assert ev["erosion"] == delta
    assert ev["eroded_mass"] == pytest.approx(ev["parent_mass"] - 2 * expected, rel=1e-12)


def _sliver_cut(state, angle):
    """Pieces of the square's outline cut by a line that leaves the right face at its lower
    end at ``angle`` (rad) to it: a sliver between the line and the face, and the rest."""
    x0, y0 = A / 2 + R, -A / 2
    d = np.array([-math.sin(angle), math.cos(angle)])
    start = np.array([x0, y0]) - 0.1 * d
    return _cut(state, 0, [[start, start + 0.2 * d]])


def _fragments(state, ev):
    p = state.particles
    out = []
    for s in ev["fragment_slots"]:
        core = _world_core(state, int(s))
        out.append((core, float(p.radius[s])))
    return out


def test_adaptive_fragment_radius_keeps_the_tip_of_a_sliver():
    """A plane at a = 20 deg to a face cuts a sliver whose core tip recedes r / sin(a / 2)
    under the parent's radius: the fragment loses 6 % of the sliver, about
    r^2 (1 / tan(a / 2) - (pi - a) / 2) at the tip. With ``min_radius``
    the sliver takes the largest radius that keeps 99.9 % of its piece (a 1 % larger one
    keeps less), the other piece keeps the parent's, every fragment lies inside its piece
    and the masses add up."""
    a = math.radians(20.0)
    plain_state = _state([_square()], capacity=2)
    pieces = _sliver_cut(plain_state, a)
    piece_area = sorted(abs(geo.polygon_area(q)) for q in pieces)
    plain_state, plain = replace_particle(plain_state, 0, pieces, overlap=0.0, clearance=0.0)
    frag_area = sorted(plain["fragment_areas"])
    assert 1.0 - frag_area[0] / piece_area[0] > 0.05  # the sliver's tip is lost

    state = _state([_square()], capacity=2)
    pieces = _sliver_cut(state, a)
    state, ev = replace_particle(state, 0, pieces, overlap=0.0, clearance=0.0, min_radius=R / 10)
    radii = ev["fragment_radii"]
    order = np.argsort(ev["fragment_areas"])
    assert R / 10 < radii[order[0]] < R and radii[order[1]] == R
    assert ev["area_lost"] < 0.2 * plain["area_lost"]
    total = ev["fragment_masses"].sum() + ev["fines_mass"] + ev["eroded_mass"]
    assert total == pytest.approx(ev["parent_mass"], rel=1e-14)
    by_piece = {}
    for core, r in _fragments(state, ev):
        c = core.mean(axis=0)
        q = next(q for q in pieces if geo.point_in_convex_polygon(c, q)[0])
        by_piece[id(q)] = (core, r, q)
    assert len(by_piece) == 2
    for core, r, q in by_piece.values():
        kept = geo.spheropolygon_mass_properties(core, r, 1.0)[0]
        assert kept >= (1 - 1e-3) * abs(geo.polygon_area(q)) * (1 - 1e-9)
        outline = geo.spheropolygon_outline(core, r, n_arc=64)
        assert geo.point_in_convex_polygon(outline, q, tol=1e-12).all()
        if r < R:  # the largest such radius: 1 % more keeps less than 99.9 %
            bigger = geo.offset_polygon(q, 1.01 * r)
            kept_b = geo.spheropolygon_mass_properties(bigger, 1.01 * r, 1.0)[0]
            assert kept_b < (1 - 1e-3) * abs(geo.polygon_area(q))
    assert np.asarray(state.particles.radius)[ev["fragment_slots"]].tolist() == radii.tolist()


@pytest.mark.parametrize("bad", [0.0, -1e-4, float("nan")])
def test_adaptive_fragment_radius_needs_a_positive_floor(bad):
    state = _state([_square()], capacity=2)
    with pytest.raises(ValueError, match="min_radius"):
        replace_particle(state, 0, _cut(state, 0, [[[0, -1], [0, 1]]]), min_radius=bad)


def test_density_compensation_keeps_the_mass_of_each_piece():
    """conserve_mass: the square cut in half and eroded keeps half the parent's mass in
    each fragment (density raised by the eroded fraction); the area lost is the same as
    without compensation, and mass and inertia stay consistent (I = rho_f J)."""
    delta = 2e-4
    events = {}
    for conserve in (False, True):
        state = _state([_square()], capacity=2)
        state, ev = replace_particle(
            state,
            0,
            _cut(state, 0, [[[0, -1], [0, 1]]]),
            overlap=delta,
            clearance=0.0,
            conserve_mass=conserve,
        )
        events[conserve] = (state, ev)
    (_, plain), (state, comp) = events[False], events[True]
    np.testing.assert_allclose(comp["fragment_masses"], comp["parent_mass"] / 2, rtol=1e-12)
    assert abs(comp["mass_lost"]) < 1e-14 * comp["parent_mass"]
    assert comp["area_lost"] == pytest.approx(plain["area_lost"], rel=1e-12)
    assert plain["eroded_mass"] == pytest.approx(RHO * plain["area_lost"], rel=1e-9)
    # the caps (here the uniform erosion by delta) cost area either way, mass only without
    # compensation
    assert (
        comp["caps_area"] == pytest.approx(plain["caps_area"], rel=1e-12) and comp["caps_area"] > 0
    )
    assert comp["caps_mass"] == 0.0
    assert plain["caps_mass"] == pytest.approx(RHO * plain["caps_area"], rel=1e-12)
    p = state.particles
    for s, m in zip(comp["fragment_slots"], comp["fragment_masses"], strict=True):
        core = np.asarray(p.verts[s, : int(p.n_verts[s])])
        area, _, polar = geo.spheropolygon_mass_properties(core, R, 1.0)
        assert float(p.mass[s]) == pytest.approx(m, rel=1e-12)
        assert float(p.inertia[s]) == pytest.approx(m / area * polar, rel=1e-12)


def test_fines_are_counted_and_mass_adds_up():
    """A hexagon cut by three lines, one of them chipping a corner below min_area."""
    core = geo.regular_polygon(6, 0.01)
    state = _state([core], capacity=4)
    lines = [[[0, -1], [0, 1]], [[-1, 0.002], [1, 0.002]], [[0.0085, -1], [0.0095, 1]]]
    pieces = _cut(state, 0, lines)
    areas = np.array([geo.polygon_area(q) for q in pieces])
    assert len(pieces) == 6 and np.sum(areas < 2e-5) == 2  # two chips, four large pieces
    small = areas[areas < 2e-5].sum()
    state, ev = replace_particle(
        state, 0, pieces, overlap=1e-5, min_area=2e-5, small_pieces="fines"
    )
    assert ev["n_fines"] == 2
    assert ev["fragment_masses"].size == len(pieces) - ev["n_fines"]
    total = ev["fragment_masses"].sum() + ev["fines_mass"] + ev["eroded_mass"]
    assert total == pytest.approx(ev["parent_mass"], rel=1e-14)
    assert ev["eroded_mass"] > 0
    # the fines are the dropped pieces (circumscribed outline: a hair above the true area)
    assert ev["fines_mass"] == pytest.approx(RHO * small, rel=1e-9)
    # fragments in the state carry exactly the event's masses
    p = state.particles
    slots = ev["fragment_slots"]
    np.testing.assert_allclose(np.asarray(p.mass)[slots], ev["fragment_masses"], rtol=1e-15)
    for s, m in zip(slots, ev["fragment_masses"], strict=True):
        assert geo.spheropolygon_mass_properties(_world_core(state, s), R, RHO)[0] == (
            pytest.approx(m, rel=1e-12)
        )


def test_small_pieces_merge_into_their_neighbour_and_no_mass_becomes_fines():
    """The same two chips, merged (the default): each joins the piece across its longest
    edge, the union is exact, and the parent's mass = fragments + erosion."""
    core = geo.regular_polygon(6, 0.01)
    lines = [[[0, -1], [0, 1]], [[-1, 0.002], [1, 0.002]], [[0.0085, -1], [0.0095, 1]]]
    state = _state([core], capacity=4)
    pieces = _cut(state, 0, lines)
    state, ev = replace_particle(state, 0, pieces, overlap=1e-5, min_area=2e-5)
    assert ev["kind"] == "breakage"
    assert ev["n_merged"] == 2 and ev["n_fines"] == 0 and ev["fines_mass"] == 0.0
    assert ev["fragment_masses"].size == 4
    total = ev["fragment_masses"].sum() + ev["eroded_mass"]
    assert total == pytest.approx(ev["parent_mass"], rel=1e-14)
    # what the merge keeps: against dropping the chips, the fragments gain the chips' mass
    # less their erosion
    state2 = _state([core], capacity=4)
    _, ev2 = replace_particle(
        state2, 0, _cut(state2, 0, lines), overlap=1e-5, min_area=2e-5, small_pieces="fines"
    )
    gain = ev["fragment_masses"].sum() - ev2["fragment_masses"].sum()
    assert 0.5 * ev2["fines_mass"] < gain <= ev2["fines_mass"]
    for s in ev["fragment_slots"]:
        assert geo.is_convex(_world_core(state, s))


def _convex_union(a, b):
    from scipy.spatial import ConvexHull

    pts = np.concatenate([a, b])
    hull = abs(geo.polygon_area(pts[ConvexHull(pts).vertices]))
    return hull <= (1 + 1e-9) * (abs(geo.polygon_area(a)) + abs(geo.polygon_area(b)))


def test_merge_of_random_arrangements_keeps_area_and_convexity():
    """Random convex polygons cut by 1-6 random lines: merging keeps the total area (1e-12)
    and convexity, and a piece left below the threshold has no neighbour with which its
    union would be convex (after earlier merges that can happen, rarely)."""
    rng = np.random.default_rng(3)
    n_cases = n_stuck = 0
    for _ in range(150):
        poly = geo.regular_polygon(int(rng.integers(3, 9)), 1.0, rng.uniform(0, 6.3))
        lines = rng.uniform(-1.0, 1.0, (int(rng.integers(1, 7)), 2, 2))
        pieces = split_convex(poly, lines)
        if len(pieces) < 2:
            continue
        areas = np.array([abs(geo.polygon_area(q)) for q in pieces])
        thresh = float(np.quantile(areas, 0.4))
        out, n = merge_small_pieces(pieces, lambda q: abs(geo.polygon_area(q)), thresh)
        n_cases += n > 0
        assert len(out) == len(pieces) - n
        new_areas = np.array([abs(geo.polygon_area(q)) for q in out])
        assert new_areas.sum() == pytest.approx(areas.sum(), rel=1e-12)
        assert all(geo.is_convex(q) for q in out)
        if len(out) > 1:
            dust = new_areas < 1e-3 * thresh  # neither merged nor merged into
            for i in np.flatnonzero((new_areas < thresh) & ~dust):
                n_stuck += 1
                nbrs = [b if a == i else a for a, b, _, _ in geo.shared_edges(out) if i in (a, b)]
                assert not any(_convex_union(out[i], out[j]) for j in nbrs if not dust[j])
    assert n_cases > 50 and n_stuck < 0.1 * n_cases


def test_dust_where_three_lines_nearly_meet_stays_and_the_rest_merges():
    """Three lines nearly concurrent cut a square into six sectors and a 2.5e-9 triangle
    (dust). The dust is left alone (it becomes fines, a negligible mass); the two small
    sectors merge into their big neighbours."""
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    lines = [[[0, 0], [0, 1]], [[0, 0.5], [1, 1.5]], [[1e-4, 0.5], [1 + 1e-4, -0.5]]]
    pieces = split_convex(square, np.asarray(lines, float))
    areas = sorted(abs(geo.polygon_area(q)) for q in pieces)
    assert len(pieces) == 7 and areas[0] < 1e-8 and areas[2] < 0.13
    out, n = merge_small_pieces(pieces, lambda q: abs(geo.polygon_area(q)), 0.3)
    got = sorted(abs(geo.polygon_area(q)) for q in out)
    assert n == 2 and got[0] == pytest.approx(areas[0], rel=1e-9)
    assert min(got[1:]) >= 0.3 and sum(got) == pytest.approx(4.0, rel=1e-12)


def test_dust_covered_by_a_merge_joins_it():
    """Pieces recorded from a Cantor-oedometer breakage (outline of a fragment cut by three
    lines that nearly meet at its boundary): a 0.35 x min_area piece, a 0.11 x min_area
    piece, 6e-6 x min_area of dust and a large piece. Merging the 0.11 piece into the large
    one leaves a notch of dust; the 0.35 piece then joins the large one with the dust it
    covers, so nothing above the dust's size is lost and the grain stays whole."""
    from pathlib import Path

    data = np.load(Path(__file__).parent / "data" / "dust_pieces.npz")
    min_area = float(data["min_area"])
    pieces = [data[f"piece{i}"] for i in range(4)]
    areas = np.array([abs(geo.polygon_area(q)) for q in pieces]) / min_area
    assert np.sum(areas < 1e-3) == 1 and np.sum((areas >= 1e-3) & (areas < 1)) == 2
    out, n = merge_small_pieces(pieces, lambda q: abs(geo.polygon_area(q)), min_area)
    assert n == 3 and len(out) == 1 and geo.is_convex(out[0])
    # the part of the dust outside the hull is all that is lost
    lost = areas.sum() - abs(geo.polygon_area(out[0])) / min_area
    assert 0.0 <= lost < areas.min()


def test_a_chip_below_the_resolution_does_not_replace_the_particle():
    """One line clipping a corner below min_area: with merging nothing breaks off, the
    particle is left as it was and the event says so."""
    core = geo.regular_polygon(6, 0.01)
    state = _state([core], capacity=3)
    pieces = _cut(state, 0, [[[0.0085, -1], [0.0095, 1]]])
    assert len(pieces) == 2
    new, ev = replace_particle(state, 0, pieces, min_area=2e-5)
    assert ev["kind"] == "suppressed" and ev["n_merged"] == 1
    for name in ("pos", "verts", "mass", "active", "uid"):
        np.testing.assert_array_equal(
            np.asarray(getattr(new.particles, name)), np.asarray(getattr(state.particles, name))
        )
    _, ev_f = replace_particle(state, 0, pieces, min_area=2e-5, small_pieces="fines")
    assert ev_f["kind"] == "breakage" and ev_f["n_fines"] == 1
    with pytest.raises(ValueError, match="small_pieces"):
        replace_particle(state, 0, pieces, small_pieces="drop")


# ----------------------------------------------------------------------------- momentum


def test_fragments_inherit_the_rigid_body_velocity_field():
    v, w = np.array([0.3, -0.2]), 5.0
    core = geo.regular_polygon(7, 0.01, 0.2, (0.05, 0.02))
    state = _state([core], capacity=6, velocities=[v])
    state = replace(state, particles=replace(state.particles, omega=jnp.array([w, 0, 0, 0, 0, 0])))
    p0 = state.particles
    x0, m0, i0 = np.asarray(p0.pos[0]), float(p0.mass[0]), float(p0.inertia[0])
    c = x0
    lines = [[c, c + [0.3, 1]], [c + [0, 0.003], c + [1, 0.004]]]
    state, ev = replace_particle(state, 0, _cut(state, 0, lines), overlap=5e-5)
    p = state.particles
    s = ev["fragment_slots"]
    assert s.size == 4
    m = np.asarray(p.mass)[s]
    x = np.asarray(p.pos)[s]
    vf = np.asarray(p.vel)[s]
    d = x - x0
    np.testing.assert_allclose(vf, v + w * np.stack([-d[:, 1], d[:, 0]], 1), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(p.omega)[s], w)
    lost = ev["mass_lost"]
    assert 0 < lost / m0 < 0.05
    bound = float(p0.bound_radius[0])
    dp = (m[:, None] * vf).sum(0) - m0 * v
    assert np.linalg.norm(dp) <= lost * (np.linalg.norm(v) + abs(w) * bound) * (1 + 1e-9)
    # angular momentum about the origin, same bound with the lever arm
    cross = lambda a, b: a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    l0 = m0 * cross(x0, v) + i0 * w
    lf = (m * cross(x, vf)).sum() + (np.asarray(p.inertia)[s] * w).sum()
    lever = np.linalg.norm(x0) + bound
    assert abs(lf - l0) <= lost * (lever * (np.linalg.norm(v) + abs(w) * bound) + w * bound**2)


# ----------------------------------------------------------------------------- overlap


def _row_of_three(overlap):
    """Three squares in a row, the middle one overlapping both neighbours by ``overlap``."""
    step = A + 2 * R - overlap
    polys = [_square((-step, 0)), _square(), _square((step, 0))]
    parts = particles_from_polygons(polys, R, RHO, capacity=6, vertex_capacity=8)
    params = make_params(normal_stiffness=1e6, tangential_stiffness=3e5, gravity=(0, 0), dt=1e-6)
    # a fixed cell size: the same grid (so compiled code) for every overlap
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), A / math.sqrt(2) + R, 2e-3)
    state, err = prepare(make_state(parts, make_walls([])), params, grid)
    assert int(err) == 0
    return state, params, grid


def _max_force_on(state, params, slots):
    _, _, _, info = pair_forces(state.particles, state.contacts, params)
    pairs = np.asarray(state.contacts.pairs)
    act = np.asarray(info["active"])
    f = np.linalg.norm(np.asarray(info["force"]), axis=-1)
    hit = np.isin(pairs[:, 0], slots) | np.isin(pairs[:, 1], slots)
    return float(np.max(np.where(act & hit[:, None, None], f, 0.0), initial=0.0))


def _max_pair_force_on(state, params, slots):
    """Largest resultant force (N) between two particles, over the pairs that involve
    ``slots``: the sum of the pair's vertex contacts (a flat face gives two, at its ends)."""
    _, _, _, info = pair_forces(state.particles, state.contacts, params)
    pairs = np.asarray(state.contacts.pairs)
    f = np.asarray(info["force"])  # on the vertex owner: i for direction 0, j for 1
    on_i = f[:, 0].sum(axis=1) - f[:, 1].sum(axis=1)
    hit = np.isin(pairs[:, 0], slots) | np.isin(pairs[:, 1], slots)
    return float(np.max(np.where(hit, np.linalg.norm(on_i, axis=-1), 0.0), initial=0.0))


@pytest.mark.parametrize("erosion", ["local", "uniform"])
def test_fragments_start_without_overlap_and_without_force(erosion):
    overlap = 3e-5
    state, params, grid = _row_of_three(overlap)
    # each face contact of the middle square: two contacts (at the face's ends), K delta each
    before = _max_pair_force_on(state, params, [1])
    assert before == pytest.approx(2 * 1e6 * overlap, rel=1e-6)
    assert float(max_overlap(state)[1]) == pytest.approx(overlap, rel=1e-9)
    # a diagonal cut and a horizontal one: fragments touch both neighbours' faces
    lines = [[[-1, -1], [1, 1]], [[-1, 0.001], [1, 0.001]]]
    state, ev = replace_particle(state, 1, _cut(state, 1, lines), erosion=erosion)
    if erosion == "uniform":
        assert ev["erosion"] >= overlap
    else:
        assert ev["n_contact_clips"] == 2  # the two neighbours, nothing else
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    frags = ev["fragment_slots"].tolist()
    assert len(frags) == 4
    assert np.all(np.asarray(max_overlap(state))[frags] == 0.0)
    assert _max_force_on(state, params, frags) == 0.0
    # a few hundred steps later nothing has pushed them together: no force spike
    state, _, err = run_segment(state, params, grid, 4, 50)
    assert int(err) == 0
    assert _max_pair_force_on(state, params, frags + [0, 2]) < 1e-9 * before


def test_without_erosion_fragments_inherit_the_parents_overlap():
    overlap = 3e-5
    state, params, grid = _row_of_three(overlap)
    lines = [[[-1, -1], [1, 1]], [[-1, 0.001], [1, 0.001]]]
    state, ev = replace_particle(state, 1, _cut(state, 1, lines), erosion="none")
    # nothing taken off beyond the sphero-radius but the 1e-9 x R clearance
    assert ev["erosion"] < 1e-6 * overlap and ev["erosion_mode"] == "none"
    state, err = prepare(state, params, grid)
    assert int(err) == 0
    frags = ev["fragment_slots"].tolist()
    # the fragments touching a neighbour press on it as hard as the parent did
    assert _max_force_on(state, params, frags) == pytest.approx(1e6 * overlap, rel=1e-3)


def test_unknown_erosion_mode_is_an_error():
    state, _, _ = _row_of_three(3e-5)
    lines = [[[-1, 0.001], [1, 0.001]]]
    with pytest.raises(ValueError, match="erosion must be one of"):
        replace_particle(state, 1, _cut(state, 1, lines), erosion="some")


def test_local_erosion_removes_only_the_overlap_caps():
    """The fragments' outline is the opening of the clipped pieces, so the parent's core loses
    a layer delta only on the faces that neighbours penetrate (area of a convex K dilated by
    R: |K| + R per(K) + pi R^2): local erosion takes 2 delta (A + 2 R) beyond what the cut's
    own corner rounding takes (no overlap); uniform erosion shrinks the core all round."""
    overlap = 3e-5
    lines = [[[-1, -1], [1, 1]], [[-1, 0.001], [1, 0.001]]]
    lost, caps, rounding = {}, {}, {}
    for mode in ("none", "local", "uniform"):
        state, _, _ = _row_of_three(overlap)
        _, ev = replace_particle(state, 1, _cut(state, 1, lines), clearance=0.0, erosion=mode)
        lost[mode] = ev["mass_lost"] / RHO  # m^2
        caps[mode], rounding[mode] = ev["caps_area"], ev["rounding_mass"] / RHO
        assert ev["caps_mass"] == pytest.approx(RHO * ev["caps_area"], rel=1e-12)
        assert ev["caps_mass"] + ev["rounding_mass"] == pytest.approx(ev["eroded_mass"], rel=1e-14)
    # the logged caps are what each mode loses beyond the cut's own corner rounding, and the
    # rounding is the same in every mode: it depends on the planes, not on the neighbours
    assert caps["none"] == 0.0
    for mode in ("local", "uniform"):
        assert caps[mode] == pytest.approx(lost[mode] - lost["none"], rel=1e-9)
        assert rounding[mode] == pytest.approx(lost["none"], rel=1e-9)
    d = overlap
    assert lost["local"] - lost["none"] == pytest.approx(2 * d * (A + 2 * R), rel=0.01)
    # uniform erosion also opens a gap 2 delta along both cuts (chords A + 2R and
    # sqrt(2) A + 2R); O(delta^2) corner terms are left out, hence 2 %
    cuts = 2 * d * ((A + 2 * R) + (math.sqrt(2) * A + 2 * R))
    assert lost["uniform"] - lost["none"] == pytest.approx(4 * d * (A + 2 * R) + cuts, rel=0.02)


def _square_under_a_wedge(overlap, half_angle=math.pi / 6):
    """The square (slot 0) with the apex of a wedge (slot 1) pressed into the middle of its
    top face by ``overlap``."""
    h = 0.01
    tip = A / 2 + 2 * R - overlap
    wedge = [[0, tip], [h * math.tan(half_angle), tip + h], [-h * math.tan(half_angle), tip + h]]
    parts = particles_from_polygons(
        [_square(), np.array(wedge)], R, RHO, capacity=4, vertex_capacity=8
    )
    params = make_params(normal_stiffness=1e6, tangential_stiffness=3e5, gravity=(0, 0), dt=1e-6)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.02, 2e-3)
    state, err = prepare(make_state(parts, make_walls([])), params, grid)
    assert int(err) == 0
    return state, params, grid


def test_local_erosion_at_a_contact_on_the_fracture_plane_costs_nothing_beyond_the_corners():
    """A fracture plane through the contact point (as DSM planes join contacts): each half
    has a corner under the wedge's apex, which the rounding of the new corner (radius R
    > overlap) already clears. The local rule finds a clipping line that costs nothing
    more; the least-penetration line of the earlier rule takes a strip overlap x (A + 2R)
    off the whole top face."""
    overlap = 2e-4
    lost, clips, caps = {}, {}, {}
    for mode in ("none", "local-axis", "local"):
        state, params, grid = _square_under_a_wedge(overlap)
        assert float(max_overlap(state)[0]) == pytest.approx(overlap, rel=1e-9)
        state, ev = replace_particle(state, 0, _cut(state, 0, [[[0, -1], [0, 1]]]), erosion=mode)
        lost[mode] = ev["mass_lost"] / RHO
        caps[mode] = ev["caps_area"]
        state, err = prepare(state, params, grid)
        assert int(err) == 0
        frags = ev["fragment_slots"].tolist()
        assert len(frags) == 2
        clips[mode] = float(np.max(np.asarray(max_overlap(state))[frags]))
    strip = overlap * (A + 2 * R)
    assert lost["local-axis"] - lost["none"] == pytest.approx(strip, rel=1e-3)
    assert lost["local"] - lost["none"] < 1e-6 * strip
    assert clips["local"] == 0.0 and clips["local-axis"] == 0.0
    # the logged caps: the strip for the earlier rule, nothing (to round-off) for the local one
    assert caps["local-axis"] == pytest.approx(strip, rel=1e-3)
    assert abs(caps["local"]) < 1e-6 * strip


@pytest.mark.parametrize("seed", range(6))
def test_local_erosion_never_overlaps_and_never_keeps_less_than_the_axis_rule(seed):
    """Random pile around a random parent: four random triangles to pentagons pressed into it
    by 0.1-0.4 R, 1-3 random fracture lines. The local rule's fragments overlap no
    neighbour, and together keep at least the mass the one-line-per-neighbour rule keeps."""

    def cross(x, y):
        return x[0] * y[1] - x[1] * y[0]

    rng = np.random.default_rng(seed)
    parent = geo.regular_polygon(6, 0.012, rng.uniform(0, 1), (0.0, 0.0))
    parent = parent * rng.uniform(0.7, 1.3, size=(1, 2))
    polys = [parent]
    for phi in np.sort(rng.uniform(0, 2 * math.pi, size=4)):
        n = rng.integers(3, 6)
        body = geo.regular_polygon(int(n), 0.006, rng.uniform(0, 2 * math.pi), (0.0, 0.0))
        u = np.array([math.cos(phi), math.sin(phi)])
        # the body's lowest vertex along u on the parent's boundary ray, 2 R out (touching
        # a face normal to u), then pressed in by 0.1-0.4 R
        edge_hit = [
            cross(a, b - a) / cross(u, b - a)
            for a, b in zip(parent, np.roll(parent, -1, axis=0), strict=True)
            if abs(cross(u, b - a)) > 1e-12
        ]
        s = min(t for t in edge_hit if t > 0)
        low = body[np.argmin(body @ u)]
        polys.append(body - low + u * (s + 2 * R - rng.uniform(0.1, 0.4) * R))
    parts = particles_from_polygons(polys, R, RHO, capacity=16, vertex_capacity=12)
    params = make_params(normal_stiffness=1e6, tangential_stiffness=3e5, gravity=(0, 0), dt=1e-6)
    grid = make_grid((-0.1, -0.1), (0.1, 0.1), 0.02, 2e-3, cell_capacity=32)
    state0, err = prepare(make_state(parts, make_walls([])), params, grid)
    assert int(err) == 0
    ov0 = np.asarray(max_overlap(state0))
    n_lines = int(rng.integers(1, 4))
    lines = [[rng.normal(0, 0.004, 2), rng.normal(0, 0.004, 2)] for _ in range(n_lines)]
    kept, worst = {}, {}
    for mode in ("local-axis", "local"):
        state, ev = replace_particle(state0, 0, _cut(state0, 0, lines), erosion=mode)
        kept[mode] = ev["fragment_masses"].sum()
        state, err = prepare(state, params, grid)
        assert int(err) == 0
        worst[mode] = float(np.max(np.asarray(max_overlap(state))[ev["fragment_slots"]]))
    assert ov0[0] > 0.05 * R  # the neighbours do press on the parent
    assert ov0[1:5].min() > 0.0
    assert worst["local"] == 0.0 and worst["local-axis"] == 0.0
    assert kept["local"] >= kept["local-axis"] * (1 - 1e-12)


def test_tangential_history_of_touched_slots_is_zeroed():
    state, params, grid = _row_of_three(1e-5)
    c = state.contacts
    state = replace(
        state, contacts=replace(c, xi=jnp.ones_like(c.xi), wall_xi=jnp.ones_like(c.wall_xi))
    )
    pairs = np.asarray(state.contacts.pairs)
    valid = pairs[:, 0] < 6
    assert valid.sum() >= 2
    state, _ = replace_particle(state, 0, _cut(state, 0, [[[-0.03, -1], [-0.03, 1]]]))
    xi = np.asarray(state.contacts.xi)
    wxi = np.asarray(state.contacts.wall_xi)
    touched = np.isin(pairs[:, 0], [0, 3]) | np.isin(pairs[:, 1], [0, 3])
    assert np.all(xi[:, touched] == 0) and np.all(xi[:, valid & ~touched] == 1)
    assert np.all(wxi[:, [0, 3]] == 0) and np.all(wxi[:, [1, 2]] == 1)


# ----------------------------------------------------------------------------- capacity


def test_full_capacity_grows_particles_and_restarts_the_pair_list():
    state, params, grid = _row_of_three(1e-5)
    cores = [_world_core(state, k) for k in range(3)]
    # no free slot; after growth the shapes equal _row_of_three's (compiled once)
    full = particles_from_polygons(cores, R, RHO, capacity=3, vertex_capacity=8)
    state = make_state(full, make_walls([]), pair_capacity=24)
    lines = [[[-1, -1], [1, 1]], [[-1, 0.001], [1, 0.001]]]
    state, ev = replace_particle(state, 1, _cut(state, 1, lines), overlap=1e-5)
    p = state.particles
    assert "particle capacity 3 -> 6" in ev["capacity_growth"]
    assert p.pos.shape == (6, 2) and p.verts.shape[0] == 6
    assert int(np.asarray(p.active).sum()) == 2 + 4
    assert sorted(ev["fragment_slots"].tolist()) == [1, 3, 4, 5]
    c = state.contacts
    assert np.all(np.asarray(c.pairs) == 6)  # fresh list with the new sentinel
    assert c.wall_xi.shape[1] == 6 and c.ref_pos.shape == (6, 2)
    state, err = prepare(state, params, grid)
    assert int(err) == 0 and int(state.contacts.n_pairs) > 0
    state, _, err = run_segment(state, params, grid, 4, 50)
    assert int(err) == 0


def test_fragment_with_more_vertices_grows_the_vertex_capacity():
    state = _state([_square()], capacity=2, vertex_capacity=4)
    # a corner chip: the big piece is a pentagon (5 > V = 4)
    state, ev = replace_particle(state, 0, _cut(state, 0, [[[0.004, 0.012], [0.012, 0.004]]]))
    p = state.particles
    assert "vertex capacity 4 -> 5" in ev["capacity_growth"]  # exactly the need
    assert p.verts.shape == (2, 5, 2)
    assert state.contacts.xi.shape[-1] == 5 and state.contacts.wall_xi.shape[-1] == 5
    assert sorted(np.asarray(p.n_verts).tolist()) == [3, 5]


def test_fitting_the_vertex_capacity_changes_no_number():
    """Three squares (4 vertices) held in 8 vertex slots, the middle one turned so its
    corners press the neighbours, and spinning so the tangential springs load: cut to 4
    slots, the run goes on bit for bit."""
    state, params, grid = _row_of_three(1e-5)
    p = state.particles
    p = replace(p, angle=p.angle.at[1].set(0.02), omega=p.omega.at[1].set(2.0))
    state, err = prepare(replace(state, particles=p), params, grid)
    assert int(err) == 0
    state, _, err = run_segment(state, params, grid, 2, 50)
    assert int(err) == 0 and float(jnp.abs(state.contacts.xi).max()) > 0
    fit = fit_vertex_capacity(state)
    assert fit.particles.verts.shape[1] == 4 and fit.contacts.xi.shape[-1] == 4
    assert fit_vertex_capacity(fit) is fit  # nothing left to cut
    # a configured floor keeps spare slots: 5 of the 8, and none cut at 8 or more
    assert fit_vertex_capacity(state, minimum=5).particles.verts.shape[1] == 5
    assert fit_vertex_capacity(state, minimum=8) is state
    runs = [run_segment(s, params, grid, 2, 50) for s in (state, fit)]
    assert all(int(err) == 0 for _, _, err in runs)
    (a, _, _), (b, _, _) = runs
    for name in ("pos", "angle", "vel", "omega", "force", "torque"):
        np.testing.assert_array_equal(getattr(a.particles, name), getattr(b.particles, name))
    np.testing.assert_array_equal(a.contacts.xi[..., :4], b.contacts.xi)


def test_bonds_of_a_replaced_particle_break_and_follow_the_capacity():
    from jaxgran.bonds import make_bonds

    cells = [_square((x, 0.0)) for x in (-A, 0.0, A)]
    parts = particles_from_polygons(
        [geo.offset_polygon(c, R) for c in cells], R, RHO, capacity=3, vertex_capacity=8
    )
    bonds = make_bonds(
        cells,
        parts,
        thickness=0.01,
        b_n=1e8,
        b_t=1e8,
        b_m=1e8,
        eps_th=1e-3,
        theta_th=1e-2,
        capacity=4,
    )
    assert np.asarray(bonds.intact).tolist() == [True, True, False, False]
    state = replace(make_state(parts, make_walls([])), bonds=bonds)
    state, ev = replace_particle(state, 2, _cut(state, 2, [[[A, -1], [A, 1]]]), overlap=0.0)
    assert "particle capacity 3 -> 6" in ev["capacity_growth"]
    b = state.bonds
    assert np.asarray(b.intact).tolist() == [True, False, False, False]  # (1, 2) broke
    assert np.asarray(b.i).tolist()[2:] == [6, 6] and np.asarray(b.j).tolist()[2:] == [6, 6]
