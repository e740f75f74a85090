"""Breakage criteria for one particle: the DSM strain-energy connection points and the three
averaged-stress baselines of paper 000 (Jiang et al., PRE 104, 045311, 2021).

Host-side numpy, one particle per call (the BEM that produces ``psi`` is batched JAX).

* DSM (paper 000 §II.B, Eq. 3): the damaged domains are ``{psi >= eps}``; the domains grown
  from two contacts first coalesce at a saddle of ``psi`` (the *connection point*), and the
  particle breaks iff the highest such saddle reaches ``eps``. Each connection point picks the
  contact-to-contact line nearest to it as a fracture plane.
* Averaged stress (paper 000 Table II): split-cell (Cantor, Estrada & Azéma 2015), cross-cut
  (Eliáš 2014) and Mohr-Coulomb (Gladky & Kuna 2017), each with its cutting planes through
  the centroid. The fragments are then cut by ``ssm.split_convex`` for every method alike.

Sign convention: tension positive throughout; ``sigma_1 >= sigma_2`` are the principal
stresses and ``theta_p`` (rad, in ``(-pi/2, pi/2]``) is the direction of ``sigma_1``, the most
tensile (least compressive) principal direction. ``theta_p + pi/2`` is then the direction of
the largest compression, along which a grain splits.
"""

from __future__ import annotations

import dataclasses
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt

__all__ = [
    "ConnectionPoints",
    "CriterionResult",
    "averaged_stress",
    "breakage_type",
    "connection_points",
    "cross_cut_criterion",
    "fracture_planes",
    "mohr_coulomb_criterion",
    "principal_stresses",
    "split_cell_criterion",
]

# ---------------------------------------------------------------------------------------
# DSM: connection points on the strain-energy field


@dataclasses.dataclass(frozen=True)
class ConnectionPoints:
    """Where the damaged domains of a particle's contacts coalesce (paper 000 §II.B, Eq. 3).

    Attributes:
        bottleneck: ``[n_contacts, n_contacts]`` psi (Pa) of the saddle joining each pair: the
            largest level at which both contacts lie in one 4-connected component of
            ``{psi >= level}`` (seed samples count as ``+inf``, except ``finite`` ones).
            ``+inf`` on the diagonal and where infinite seeds touch, ``-inf`` where the
            samples never connect them.
        location: ``[n_contacts, n_contacts]`` sample index of that saddle, ``-1`` where none
            (diagonal, never connected).
        saddle_level: ``[n_saddles]`` psi (Pa) at each merge of two seeded domains, highest
            first; at most ``n_contacts - 1`` of them.
        saddle_index: ``[n_saddles]`` sample index of each merge.
        saddle_pair: ``[n_saddles, 2]`` one contact from each side of each merge.
        eps: the damage threshold (Pa) the result was asked for.
        breaks: ``max(bottleneck off the diagonal) >= eps``.
    """

    bottleneck: np.ndarray
    location: np.ndarray
    saddle_level: np.ndarray
    saddle_index: np.ndarray
    saddle_pair: np.ndarray
    eps: float
    breaks: bool

    @property
    def connection_index(self) -> np.ndarray:
        """``[n_connections]`` sample indices of the connection points at ``eps``: the saddles
        whose level reaches ``eps``. One fracture plane per connection point."""
        return self.saddle_index[self.saddle_level >= self.eps]


def connection_points(
    psi: npt.ArrayLike,
    ij: npt.ArrayLike,
    seeds: list[npt.ArrayLike],
    eps: float,
    finite: npt.ArrayLike | None = None,
) -> ConnectionPoints:
    """Bottlenecks and connection points of the strain-energy field of one particle.

    Samples are visited from the highest ``psi`` down and joined to their already visited
    4-neighbours with a union-find (a merge tree of the superlevel sets); when two components
    that each hold seeds meet, every pair of contacts across them is connected at the current
    level, at the current sample (the saddle). One sweep gives all pairs, which is what
    PHYSICS.md §A7 obtains by bisection on ``eps`` with connected-component labelling.

    Args:
        psi: ``[n_samples]`` strain-energy equivalent stress (Pa, paper 000 Eq. 2) at interior
            sample points.
        ij: ``[n_samples, 2]`` integer grid indices of the samples (any subset of a regular
            grid, e.g. the grid points inside the particle); neighbours differ by one in one
            index (4-connectivity).
        seeds: one index array per contact: the samples next to that contact. Their ``psi`` is
            treated as ``+inf`` (the load point is singular).
        eps: damage threshold ``epsilon`` (Pa) of paper 000 Eq. 3.
        finite: seed samples that keep their ``psi`` instead of ``+inf`` (where the seeds of
            two contacts touch, see :func:`jaxgran.breakage.dsm._touching_seeds`).

    Returns:
        A :class:`ConnectionPoints`.
    """
    psi = np.asarray(psi, dtype=np.float64)
    ij = np.asarray(ij)
    n = psi.shape[0]
    if psi.ndim != 1 or ij.shape != (n, 2):
        raise ValueError(
            f"psi must be [n_samples] and ij [n_samples, 2]; got {psi.shape} and {ij.shape}"
        )
    if not np.issubdtype(ij.dtype, np.integer):
        raise ValueError("ij must hold integer grid indices")
    if np.any(np.isnan(psi)):
        raise ValueError("psi contains NaN; check the BEM solve of this particle")
    n_contacts = len(seeds)
    if n_contacts < 1:
        raise ValueError("need at least one contact (one seed array per contact)")

    level = psi.copy()
    contact_bits = [0] * n
    for c, idx in enumerate(seeds):
        idx = np.asarray(idx, dtype=np.int64).ravel()
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n:
            raise ValueError(
                f"seeds[{c}] must be a non-empty array of sample indices in [0, {n}); "
                "give every contact at least the sample nearest to it"
            )
        level[idx] = np.inf
        for s in idx.tolist():
            contact_bits[s] |= 1 << c
    if finite is not None:
        keep = np.asarray(finite, dtype=np.int64).ravel()
        level[keep] = psi[keep]

    # Dense lookup grid: sample index at each (i, j), -1 where there is no sample.
    lo = ij.min(axis=0)
    cell = ij - lo
    grid = np.full(tuple(cell.max(axis=0) + 1), -1, dtype=np.int64)
    grid[cell[:, 0], cell[:, 1]] = np.arange(n)
    if np.count_nonzero(grid >= 0) != n:
        raise ValueError("ij holds duplicate grid indices; each sample needs its own (i, j)")
    shape = grid.shape

    bottleneck = np.full((n_contacts, n_contacts), -np.inf)
    np.fill_diagonal(bottleneck, np.inf)
    location = np.full((n_contacts, n_contacts), -1, dtype=np.int64)
    saddles: list[tuple[float, int, int, int]] = []

    parent = list(range(n))
    size = [1] * n
    bits = list(contact_bits)
    active = np.zeros(n, dtype=bool)

    def find(a: int) -> int:
        root = a
        while parent[root] != root:
            root = parent[root]
        while parent[a] != root:  # path compression
            parent[a], a = root, parent[a]
        return root

    def connect(mask_a: int, mask_b: int, lvl: float, at: int) -> None:
        # A saddle is a merge that connects at least one new pair of contacts (domains of
        # one contact's several seed samples meeting do not count).
        members_a = [c for c in range(n_contacts) if mask_a >> c & 1]
        members_b = [c for c in range(n_contacts) if mask_b >> c & 1]
        first = None
        for a in members_a:
            for b in members_b:
                if a != b and bottleneck[a, b] == -np.inf:
                    bottleneck[a, b] = bottleneck[b, a] = lvl
                    location[a, b] = location[b, a] = at
                    first = (a, b) if first is None else first
        if first is not None:
            saddles.append((lvl, at, *first))

    # Highest first; stable so that ties resolve by sample order (deterministic).
    order = np.argsort(-level, kind="stable")
    for s in order.tolist():
        active[s] = True
        own, joined = bits[s], 0
        while own:  # one sample seeding several contacts joins them here, at +inf
            bit = own & -own
            if joined:
                connect(joined, bit, float(level[s]), s)
            joined, own = joined | bit, own ^ bit
        i, j = cell[s]
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            a, b = i + di, j + dj
            if not (0 <= a < shape[0] and 0 <= b < shape[1]):
                continue
            nb = grid[a, b]
            if nb < 0 or not active[nb]:
                continue
            ra, rb = find(s), find(int(nb))
            if ra == rb:
                continue
            if bits[ra] and bits[rb]:
                connect(bits[ra], bits[rb], float(level[s]), s)
            if size[ra] < size[rb]:
                ra, rb = rb, ra
            parent[rb] = ra
            size[ra] += size[rb]
            bits[ra] |= bits[rb]

    saddle_level = np.array([t[0] for t in saddles], dtype=np.float64)
    saddle_index = np.array([t[1] for t in saddles], dtype=np.int64)
    saddle_pair = np.array([t[2:] for t in saddles], dtype=np.int64).reshape(-1, 2)
    off = ~np.eye(n_contacts, dtype=bool)
    breaks = bool(n_contacts > 1 and np.max(bottleneck[off]) >= eps)
    return ConnectionPoints(
        bottleneck=bottleneck,
        location=location,
        saddle_level=saddle_level,
        saddle_index=saddle_index,
        saddle_pair=saddle_pair,
        eps=float(eps),
        breaks=breaks,
    )


def fracture_planes(
    connection_xy: npt.ArrayLike,
    contact_points: npt.ArrayLike,
    pairs: npt.ArrayLike | None = None,
    *,
    metric: Literal["segment", "line"] = "segment",
) -> np.ndarray:
    """Fracture planes from connection points (paper 000 §II.B).

    Every pair of contact points defines a candidate plane; each connection point selects the
    candidate with the smallest point-to-line distance to it. Planes selected more than once
    (or by two pairs with the same end points) are kept once, in order of first selection.

    Args:
        connection_xy: ``[n_connections, 2]`` connection points (m).
        contact_points: ``[n_contacts, 2]`` contact points (m).
        pairs: ``[n_pairs, 2]`` contact index pairs allowed as planes; default all pairs.
        metric: ``"segment"`` (default) measures the distance to the chord between the two
            contacts, i.e. to the part of the plane inside a convex particle; ``"line"`` to
            the infinite line, the literal reading of the paper. They differ only when the
            foot of the perpendicular falls outside the chord. Ties go to the first pair.

    Returns:
        ``[n_planes, 2, 2]`` planes as their two contact points (m), ``n_planes <=
        n_connections``; ready for ``ssm.split_convex``.
    """
    q = np.asarray(connection_xy, dtype=np.float64).reshape(-1, 2)
    x = np.asarray(contact_points, dtype=np.float64).reshape(-1, 2)
    if pairs is None:
        pairs = np.stack(np.triu_indices(x.shape[0], k=1), axis=1)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if q.shape[0] == 0:
        return np.zeros((0, 2, 2))
    if pairs.shape[0] == 0:
        raise ValueError("need at least two contact points to form a fracture plane")
    a, b = x[pairs[:, 0]], x[pairs[:, 1]]
    ab = b - a
    length2 = np.einsum("pd,pd->p", ab, ab)
    if np.any(length2 == 0.0):
        raise ValueError("two contacts of a pair coincide; drop duplicate contact points")
    t = np.einsum("qpd,pd->qp", q[:, None, :] - a[None], ab) / length2
    if metric == "segment":
        t = np.clip(t, 0.0, 1.0)
    elif metric != "line":
        raise ValueError(f"metric must be 'segment' or 'line'; got {metric!r}")
    foot = a[None] + t[..., None] * ab[None]
    dist = np.linalg.norm(q[:, None, :] - foot, axis=-1)
    chosen = np.argmin(dist, axis=1)

    planes: list[np.ndarray] = []
    seen: set[tuple[float, ...]] = set()
    for p in chosen.tolist():
        ends = sorted([tuple(a[p]), tuple(b[p])])
        key = (*ends[0], *ends[1])
        if key not in seen:
            seen.add(key)
            planes.append(np.stack([a[p], b[p]]))
    return np.asarray(planes, dtype=np.float64).reshape(-1, 2, 2)


# ---------------------------------------------------------------------------------------
# Averaged stress and the three baseline criteria (paper 000 Table II)


class CriterionResult(NamedTuple):
    """Outcome of an averaged-stress criterion for one particle.

    Attributes:
        value: the criterion's stress measure (Pa).
        threshold: what it is compared with (Pa).
        breaks: whether the particle breaks.
        lines: ``[n_planes, 2, 2]`` cutting planes through the centroid, each as two points
            (m): the centroid and the centroid plus a unit vector (1 m) along the plane.
    """

    value: float
    threshold: float
    breaks: bool
    lines: np.ndarray


def averaged_stress(
    contact_points: npt.ArrayLike,
    forces: npt.ArrayLike,
    centroid: npt.ArrayLike,
    area: float,
    thickness: float = 1.0,
) -> np.ndarray:
    """Average stress of a particle from its contact forces, tension positive.

    ``sigma = (1 / V) sum_c (x_c - x_G) (x) F_c``, ``V = area * thickness``, symmetrised
    (exact when the moments balance). ``F_c`` is the force acting **on** the particle.
    Paper 000 Table II writes ``(x^c - x^p_n) F_n`` (centroid minus contact), i.e. the same
    tensor with the opposite sign: compression positive for forces on the particle. Example:
    a disc of radius R loaded by P at ``(0, +-R)`` gives ``diag(0, -2P / (pi R t))``.

    Args:
        contact_points: ``[n_contacts, 2]`` contact positions (m).
        forces: ``[n_contacts, 2]`` contact forces on the particle (N; N/m with
            ``thickness=1`` for per-unit-thickness 2D forces).
        centroid: ``[2]`` particle centroid (m).
        area: particle area (m^2).
        thickness: out-of-plane thickness (m).

    Returns:
        ``[2, 2]`` symmetric stress tensor (Pa).
    """
    x = np.asarray(contact_points, dtype=np.float64).reshape(-1, 2)
    f = np.asarray(forces, dtype=np.float64).reshape(-1, 2)
    if x.shape != f.shape:
        raise ValueError(f"contact_points {x.shape} and forces {f.shape} must match")
    if not (area > 0.0 and thickness > 0.0):
        raise ValueError(f"area and thickness must be positive; got {area}, {thickness}")
    branch = x - np.asarray(centroid, dtype=np.float64)
    sigma = np.einsum("ci,cj->ij", branch, f) / (area * thickness)
    return 0.5 * (sigma + sigma.T)


def principal_stresses(stress: npt.ArrayLike) -> tuple[float, float, float]:
    """``(sigma_1, sigma_2, theta_p)`` of a 2D stress (Pa, Pa, rad): ``sigma_1 >= sigma_2``
    and ``theta_p`` in ``(-pi/2, pi/2]`` the direction of ``sigma_1`` (0 for an isotropic
    stress)."""
    s = np.asarray(stress, dtype=np.float64)
    sxx, syy, sxy = s[0, 0], s[1, 1], 0.5 * (s[0, 1] + s[1, 0])
    centre = 0.5 * (sxx + syy)
    radius = float(np.hypot(0.5 * (sxx - syy), sxy))
    theta = 0.5 * float(np.arctan2(2.0 * sxy, sxx - syy))
    if theta <= -0.5 * np.pi:
        theta += np.pi
    return centre + radius, centre - radius, theta


def split_cell_criterion(
    stress: npt.ArrayLike,
    centroid: npt.ArrayLike,
    tensile_strength: float,
) -> CriterionResult:
    """Split-cell criterion (Cantor, Estrada & Azéma 2015), as tabulated in paper 000
    Table II.

    The contact forces are replaced by two perpendicular pairs of opposite forces through the
    centroid, along the principal directions, with magnitudes from the averaged stress of a
    disc of circumradius r: ``F_max = |sigma_2| pi r t / 2`` along the compression axis and
    ``F_min = |sigma_1| pi r t / 2`` across it (compression positive in the paper's table).
    The Brazilian-disc tension at the centre, ``sigma_t = (F_max - 3 F_min) / (pi r t)``,
    must exceed the tensile strength. In tension-positive principal stresses, ``r`` and ``t``
    cancel: ``sigma_t = (3 sigma_1 - sigma_2) / 2``. A Brazilian disc (``sigma_1 = 0``,
    ``sigma_2 = -2P / (pi R t)``) gives ``P / (pi R t)``, the exact centre tension.

    The grain splits in two along the plane of ``F_max``, i.e. the major compression
    direction ``theta_p + pi/2`` (Table II; paper 000 Fig. 9a).

    Args:
        stress: ``[2, 2]`` averaged stress (Pa, tension positive), see :func:`averaged_stress`.
        centroid: ``[2]`` particle centroid (m).
        tensile_strength: ``sigma_T`` (Pa).
    """
    s1, s2, theta = principal_stresses(stress)
    value = 0.5 * (3.0 * s1 - s2)
    return CriterionResult(
        value=value,
        threshold=float(tensile_strength),
        breaks=bool(value > tensile_strength),
        lines=_planes(centroid, [theta + 0.5 * np.pi]),
    )


def cross_cut_criterion(
    stress: npt.ArrayLike,
    centroid: npt.ArrayLike,
    area: float,
    strength: float,
    *,
    reference_radius: float | None = None,
) -> CriterionResult:
    """Cross-cut criterion (Eliáš 2014, YADE ``PolyhedraSplitter``), paper 000 Table II.

    ``sigma_v = sqrt(sxx^2 + syy^2 - sxx syy + 3 sxy^2)`` (the von Mises stress with the
    out-of-plane stress zero; Eliáš's 3D ``sigma_eq`` with ``sigma_3 = 0``) is compared with
    the strength (``sigma_v >= threshold`` breaks). Eliáš scales the strength with size as
    ``sigma_0 / r_eq``; here ``threshold = strength * reference_radius / r_eq`` with
    ``r_eq = sqrt(area / pi)``, so ``strength`` is the strength of a grain of equivalent
    radius ``reference_radius`` (``reference_radius = 1`` m gives ``sigma_0 / r_eq`` with
    ``sigma_0`` in Pa m). Without ``reference_radius`` there is no size effect (Table II).

    Two planes through the centroid at ``theta_p +- pi/4`` cut the grain into four.

    Args:
        stress: ``[2, 2]`` averaged stress (Pa, tension positive).
        centroid: ``[2]`` particle centroid (m).
        area: particle area (m^2).
        strength: ``sigma_c`` (Pa), see above.
        reference_radius: equivalent radius (m) at which ``strength`` holds; None for no
            size effect.
    """
    s = np.asarray(stress, dtype=np.float64)
    sxx, syy, sxy = s[0, 0], s[1, 1], 0.5 * (s[0, 1] + s[1, 0])
    value = float(np.sqrt(sxx * sxx + syy * syy - sxx * syy + 3.0 * sxy * sxy))
    if reference_radius is None:
        threshold = float(strength)
    else:
        if not area > 0.0:
            raise ValueError(f"area must be positive; got {area}")
        threshold = float(strength) * float(reference_radius) / float(np.sqrt(area / np.pi))
    _, _, theta = principal_stresses(s)
    return CriterionResult(
        value=value,
        threshold=threshold,
        breaks=bool(value >= threshold),
        lines=_planes(centroid, [theta + 0.25 * np.pi, theta - 0.25 * np.pi]),
    )


def mohr_coulomb_criterion(
    stress: npt.ArrayLike,
    centroid: npt.ArrayLike,
    tensile_strength: float,
    compressive_strength: float,
) -> CriterionResult:
    """Mohr-Coulomb criterion (Gladky & Kuna 2017, Eq. 6; YADE ``SplitPolyMohrCoulomb``),
    paper 000 Table II, in 2D (``sigma_1 >= sigma_2``, tension positive):

    * both principal stresses ``<= 0``: value ``-sigma_2`` against ``sigma_C``;
    * both ``> 0``: value ``sigma_1`` against ``sigma_T``;
    * otherwise: value ``|sigma_1 - (sigma_T / sigma_C) sigma_2|`` against ``sigma_T``.

    The three cases join continuously. Breaks if ``value > threshold``; one plane through the
    centroid at ``theta_p + pi/4`` (45 degrees between the major and minor principal
    directions) cuts the grain in two. Which of the two conjugate 45-degree planes is taken is
    a convention (YADE's normal ``e_1 + e_3`` depends on the eigenvector signs); we follow
    Table II literally.

    Args:
        stress: ``[2, 2]`` averaged stress (Pa, tension positive).
        centroid: ``[2]`` particle centroid (m).
        tensile_strength: ``sigma_T`` (Pa, > 0).
        compressive_strength: ``sigma_C`` (Pa, > 0, a magnitude).
    """
    if not (tensile_strength > 0.0 and compressive_strength > 0.0):
        raise ValueError(
            "tensile_strength and compressive_strength must be positive magnitudes (Pa); "
            f"got {tensile_strength}, {compressive_strength}"
        )
    s1, s2, theta = principal_stresses(stress)
    if s1 <= 0.0 and s2 <= 0.0:
        value, threshold = -s2, float(compressive_strength)
    elif s1 > 0.0 and s2 > 0.0:
        value, threshold = s1, float(tensile_strength)
    else:
        value = abs(s1 - tensile_strength / compressive_strength * s2)
        threshold = float(tensile_strength)
    return CriterionResult(
        value=float(value),
        threshold=threshold,
        breaks=bool(value > threshold),
        lines=_planes(centroid, [theta + 0.25 * np.pi]),
    )


def _planes(centroid: npt.ArrayLike, angles: list[float]) -> np.ndarray:
    """``[k, 2, 2]`` lines through the centroid at the given angles (rad)."""
    c = np.asarray(centroid, dtype=np.float64).reshape(2)
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return np.stack([np.broadcast_to(c, u.shape), c + u], axis=1)


# ---------------------------------------------------------------------------------------
# Breakage type (paper 000 Table III)


def breakage_type(
    fragment_masses: npt.ArrayLike, mean_initial_mass: float
) -> Literal["splitting", "fragmentation", "chipping"]:
    """Classify a breakage event by ``m_r = min(fragment mass) / mean initial particle mass``
    (paper 000 Table III): splitting if ``m_r > 0.4``, fragmentation if
    ``0.1 <= m_r <= 0.4``, chipping if ``m_r < 0.1``.

    Args:
        fragment_masses: ``[n_fragments]`` masses of the fragments of one event (kg).
        mean_initial_mass: mean particle mass of the sample at the initial time (kg).
    """
    m = np.asarray(fragment_masses, dtype=np.float64).ravel()
    if m.size == 0:
        raise ValueError("fragment_masses is empty; classify only events with fragments")
    if not mean_initial_mass > 0.0:
        raise ValueError(f"mean_initial_mass must be positive; got {mean_initial_mass}")
    ratio = float(m.min()) / float(mean_initial_mass)
    if ratio > 0.4:
        return "splitting"
    if ratio >= 0.1:
        return "fragmentation"
    return "chipping"
