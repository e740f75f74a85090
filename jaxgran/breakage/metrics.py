"""Post-processing of breakage runs (paper 000 §III-IV): particle size distribution,
fracture-plane orientations, breakage types, the locking effect, force-chain intensity and
the kinetic-energy spikes of breakage events.

Host-side numpy on event lists (the dicts of :func:`~jaxgran.breakage.replace.
replace_particles`, as kept by the breakage callbacks and stored in run.h5) and on arrays.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from .criteria import breakage_type, principal_stresses

__all__ = [
    "BREAKAGE_TYPES",
    "averaged_stresses",
    "breakage_type_percentages",
    "equivalent_diameters",
    "event_breakage_type",
    "force_chain_intensity",
    "fracture_plane_histogram",
    "kinetic_energy_spikes",
    "locking_effect",
    "particle_size_distribution",
    "plane_angles",
]

BREAKAGE_TYPES = ("splitting", "fragmentation", "chipping")


# ---------------------------------------------------------------------------- sizes


def equivalent_diameters(areas: npt.ArrayLike) -> np.ndarray:
    """Diameter of the disc of the same area, ``d = 2 sqrt(A / pi)`` (m), for areas (m^2)."""
    a = np.asarray(areas, dtype=np.float64)
    if np.any(a < 0):
        raise ValueError("areas must be >= 0 (m^2)")
    return 2.0 * np.sqrt(a / math.pi)


def particle_size_distribution(
    diameters: npt.ArrayLike, masses: npt.ArrayLike | None = None
) -> dict[str, Any]:
    """Mass-weighted PSD by equivalent diameter (paper 000 Fig. 16).

    Args:
        diameters: ``[n]`` equivalent diameters (m) of the particles.
        masses: ``[n]`` weights (kg); default: the areas ``pi d^2 / 4`` (same density).

    Returns:
        ``diameter`` (sorted, m), ``passing`` (mass fraction finer than or equal, -),
        ``d10``, ``d50`` (m, linear interpolation of the cumulative curve), ``n``.
    """
    d = np.asarray(diameters, dtype=np.float64).ravel()
    if d.size == 0:
        raise ValueError("no particles to make a size distribution of")
    w = (math.pi / 4) * d**2 if masses is None else np.asarray(masses, float).ravel()
    if w.shape != d.shape or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("masses must be [n], >= 0, with a positive sum")
    order = np.argsort(d, kind="stable")
    d, w = d[order], w[order]
    passing = np.cumsum(w) / w.sum()

    def quantile(q: float) -> float:
        return float(np.interp(q, passing, d))

    return {
        "diameter": d,
        "passing": passing,
        "d10": quantile(0.1),
        "d50": quantile(0.5),
        "n": d.size,
    }


# ---------------------------------------------------------------------------- planes


def plane_angles(events: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """Orientation (degrees, in ``[0, 180)``) of every fracture plane of ``events`` (each
    plane ``[2, 2]`` as two points, m)."""
    out = []
    for ev in events:
        planes = np.asarray(ev.get("planes", np.zeros((0, 2, 2))), float).reshape(-1, 2, 2)
        d = planes[:, 1] - planes[:, 0]
        out.append(np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0)
    return np.concatenate(out) if out else np.zeros(0)


def fracture_plane_histogram(
    events: Sequence[Mapping[str, Any]], bin_width: float = 10.0
) -> dict[str, Any]:
    """Polar histogram of fracture-plane orientations over 0-360 degrees (paper 000 Fig. 15).

    A plane is a line, so each is counted at its orientation ``a`` in ``[0, 180)`` and at
    ``a + 180``: the histogram is point-symmetric and a bin's count is the number of planes
    with that orientation (``max_frequency`` compares with the paper's "highest frequency").

    Returns ``edges`` ``[n_bins + 1]`` (deg), ``counts`` ``[n_bins]``, ``max_frequency``,
    ``dominant_deg`` (centre of the fullest bin in ``[0, 180)``), ``n_planes``.
    """
    if not 0 < bin_width <= 180 or abs(360.0 / bin_width - round(360.0 / bin_width)) > 1e-9:
        raise ValueError(f"bin_width must divide 360 degrees, got {bin_width}")
    a = plane_angles(events)
    edges = np.arange(0.0, 360.0 + 0.5 * bin_width, bin_width)
    both = np.concatenate([a, (a + 180.0) % 360.0])
    counts, _ = np.histogram(both, bins=edges)
    k = int(np.argmax(counts)) if counts.size else 0
    return {
        "edges": edges,
        "counts": counts,
        "max_frequency": int(counts.max()) if counts.size else 0,
        "dominant_deg": float((edges[k] + 0.5 * bin_width) % 180.0),
        "n_planes": int(a.size),
    }


# ---------------------------------------------------------------------------- types


def event_breakage_type(event: Mapping[str, Any], mean_initial_mass: float) -> str:
    """Table III type of one event. Pieces dropped as fines count as fragments of mass
    ``fines_mass / n_fines``: a chip too thin to survive the erosion is still a chip."""
    masses = list(np.asarray(event.get("fragment_masses", []), float).ravel())
    n_fines = int(event.get("n_fines", 0))
    if n_fines > 0:
        masses += [float(event.get("fines_mass", 0.0)) / n_fines] * n_fines
    if not masses:
        return "chipping"
    return breakage_type(masses, mean_initial_mass)


def breakage_type_percentages(
    events: Sequence[Mapping[str, Any]], mean_initial_mass: float
) -> dict[str, Any]:
    """Share of splitting / fragmentation / chipping events (paper 000 Table III), in %, with
    the counts; the thresholds on ``m_r = min fragment mass / mean_initial_mass`` are 0.4
    and 0.1."""
    types = [event_breakage_type(ev, mean_initial_mass) for ev in events]
    n = len(types)
    counts = {t: types.count(t) for t in BREAKAGE_TYPES}
    pct = {t: (100.0 * c / n if n else 0.0) for t, c in counts.items()}
    return {"counts": counts, "percent": pct, "n_events": n}


# ---------------------------------------------------------------------------- locking


def locking_effect(
    events: Sequence[Mapping[str, Any]],
    *,
    angle_tolerance: float = 15.0,
    min_repeats: int = 2,
) -> dict[str, Any]:
    """Detect the split-cell "locking effect" (paper 000 §IV.A, Fig. 10): a fragment that
    keeps the parent's load breaks again along (nearly) the same direction, shaving strips.

    A *repeat* is an event whose parent is a fragment of an earlier event and whose plane
    (any of them) lies within ``angle_tolerance`` degrees of a plane of that earlier event.
    Repeats are chained through generations; a chain of at least ``min_repeats`` repeats
    (i.e. ``min_repeats + 1`` parallel cuts in one lineage) is a locking chain.

    An event with several planes matches by chance more often than one with a single plane
    (two planes against two match within 15 deg about half the time), so counts of
    methods that cut differently are compared with ``repeats_by_chance``: over the
    *candidates* (events whose parent is a fragment of an earlier event), the sum of the
    probability that the candidate's planes, turned as one rigid set by an angle drawn
    uniformly, come within the tolerance of a plane of the earlier event (exact for that
    null model: the measure of the union of the ``n_k x n_j`` angle intervals that match).

    Returns ``n_repeats``, ``repeat_fraction`` (of all events), ``chains`` (lists of event
    indices, root first), ``n_locking_chains``, ``locked`` (any locking chain),
    ``max_chain`` (most parallel cuts in one lineage), ``n_candidates`` and
    ``repeats_by_chance``.
    """
    by_fragment: dict[int, int] = {}
    for k, ev in enumerate(events):
        for u in np.asarray(ev.get("fragment_uids", []), int).ravel().tolist():
            by_fragment[u] = k
    angles = [plane_angles([ev]) for ev in events]

    def parallel(a: np.ndarray, b: np.ndarray) -> bool:
        if a.size == 0 or b.size == 0:
            return False
        diff = np.abs(a[:, None] - b[None, :]) % 180.0
        return bool(np.any(np.minimum(diff, 180.0 - diff) <= angle_tolerance))

    prev: dict[int, int] = {}  # event -> the earlier event it repeats
    n_candidates, by_chance = 0, 0.0
    for k, ev in enumerate(events):
        j = by_fragment.get(int(ev.get("parent_uid", -1)))
        if j is None or j >= k:
            continue
        n_candidates += 1
        by_chance += _chance_of_parallel(angles[k], angles[j], angle_tolerance)
        if parallel(angles[k], angles[j]):
            prev[k] = j
    chains = []
    ends = set(prev) - set(prev.values())
    for k in sorted(ends):
        chain = [k]
        while chain[-1] in prev:
            chain.append(prev[chain[-1]])
        chains.append(chain[::-1])
    locking = [c for c in chains if len(c) - 1 >= min_repeats]
    n = len(events)
    return {
        "n_repeats": len(prev),
        "repeat_fraction": len(prev) / n if n else 0.0,
        "chains": locking,
        "n_locking_chains": len(locking),
        "locked": bool(locking),
        "max_chain": max((len(c) for c in chains), default=1 if n else 0),
        "n_candidates": n_candidates,
        "repeats_by_chance": by_chance,
    }


def _chance_of_parallel(a: np.ndarray, b: np.ndarray, tolerance: float) -> float:
    """Probability that the planes ``a`` (deg), turned together by an angle uniform in
    ``[0, 180)``, come within ``tolerance`` (deg) of a plane ``b``: the measure of the
    union of the intervals ``b_m - a_i +- tolerance`` on the circle of 180 deg, over 180."""
    if a.size == 0 or b.size == 0:
        return 0.0
    if tolerance >= 90.0:
        return 1.0
    start = np.sort(((b[None, :] - a[:, None]).ravel() - tolerance) % 180.0)
    # arcs of one length 2 x tolerance: between two consecutive starts (around the circle)
    # the arc of the first covers min(length, gap), and no earlier arc reaches further
    gap = np.diff(np.concatenate([start, start[:1] + 180.0]))
    return float(np.sum(np.minimum(gap, 2.0 * tolerance)) / 180.0)


# ---------------------------------------------------------------------------- force chains


def force_chain_intensity(stress: npt.ArrayLike, axis_points: bool = False) -> np.ndarray:
    """Photoelastic intensity ``I = sigma_1 - sigma_2`` (Pa) per particle (paper 000 Fig. 17).

    Args:
        stress: averaged stresses ``[P, 2, 2]`` (Pa), or with ``axis_points`` the BEM field
            ``[P, M, 3]`` (``sxx, syy, sxy`` per sample point, zero rows where masked), whose
            ``I`` is averaged over each particle's non-zero points.
    """
    s = np.asarray(stress, dtype=np.float64)
    if axis_points:
        if s.ndim != 3 or s.shape[-1] != 3:
            raise ValueError(f"BEM stresses must be [P, M, 3], got {s.shape}")
        sxx, syy, sxy = s[..., 0], s[..., 1], s[..., 2]
        i_pt = 2.0 * np.hypot(0.5 * (sxx - syy), sxy)
        used = np.any(s != 0.0, axis=-1)
        return np.where(used.any(-1), (i_pt * used).sum(-1) / np.maximum(used.sum(-1), 1), 0.0)
    if s.shape[-2:] != (2, 2):
        raise ValueError(f"averaged stresses must be [P, 2, 2], got {s.shape}")
    flat = s.reshape(-1, 2, 2)
    out = np.array([principal_stresses(x)[0] - principal_stresses(x)[1] for x in flat])
    return out.reshape(s.shape[:-2])


def averaged_stresses(state, params, thickness: float | None = None, max_contacts: int = 32):
    """Averaged stress ``[P, 2, 2]`` (Pa, world frame, tension positive) of every particle
    from its current contact forces (zero for particles without contacts)."""
    import jax.numpy as jnp

    from .dsm import _spheropolygon_area_padded, contact_table

    t = float(params.thickness if thickness is None else thickness)
    dt = state.particles.pos.dtype
    one = jnp.asarray(1.0, dt)
    tab = contact_table(state, params, one, one, one, jnp.asarray(t, dt), max_contacts)
    p = state.particles
    pts = np.asarray(tab["points"])
    frc = np.asarray(tab["forces"])
    mask = np.asarray(tab["mask"])
    area = np.asarray(_spheropolygon_area_padded(p.verts, p.n_verts, p.radius))
    sig_b = (
        np.einsum("pk,pki,pkj->pij", mask, pts, frc) / np.maximum(area * t, 1e-300)[:, None, None]
    )
    sig_b = 0.5 * (sig_b + np.swapaxes(sig_b, 1, 2))
    a = np.asarray(p.angle)
    rot = np.stack(
        [np.stack([np.cos(a), -np.sin(a)], -1), np.stack([np.sin(a), np.cos(a)], -1)], -2
    )
    sig = rot @ sig_b @ np.swapaxes(rot, 1, 2)
    return np.where(np.asarray(p.active)[:, None, None], sig, 0.0)


# ---------------------------------------------------------------------------- energy


def kinetic_energy_spikes(
    time: npt.ArrayLike,
    kinetic_energy: npt.ArrayLike,
    event_times: npt.ArrayLike,
    *,
    window: float,
) -> list[dict[str, float]]:
    """Kinetic-energy spike of each breakage event (paper 000 Fig. 8b).

    For an event at ``t_e``: ``baseline`` is the last KE sample at or before ``t_e`` (J),
    ``peak`` the largest KE in ``(t_e, t_e + window]`` (J), ``ratio = peak / baseline``,
    ``rise_s`` the time from ``t_e`` to the peak and ``decay_s`` the time after the peak for
    the excess ``KE - baseline`` to fall below ``1/e`` of ``peak - baseline`` (NaN if it
    does not within the window). The window ends at the next later event, if that comes
    first, so that an event is not given the spike of the one after it (events at the same
    time share one spike).
    """
    t = np.asarray(time, float).ravel()
    ke = np.asarray(kinetic_energy, float).ravel()
    times = np.asarray(event_times, float).ravel()
    out = []
    for te in times.tolist():
        before = np.flatnonzero(t <= te)
        base = float(ke[before[-1]]) if before.size else float(ke[0])
        later = times[times > te]
        end = min(te + window, float(later.min())) if later.size else te + window
        win = np.flatnonzero((t > te) & (t <= end))
        if win.size == 0:
            out.append(
                {
                    "time": te,
                    "baseline": base,
                    "peak": float("nan"),
                    "ratio": float("nan"),
                    "rise_s": float("nan"),
                    "decay_s": float("nan"),
                }
            )
            continue
        k = win[int(np.argmax(ke[win]))]
        peak = float(ke[k])
        excess = peak - base
        after = win[win > k]
        decay = float("nan")
        if excess > 0:
            below = after[ke[after] - base <= excess / math.e]
            if below.size:
                decay = float(t[below[0]] - t[k])
        out.append(
            {
                "time": te,
                "baseline": base,
                "peak": peak,
                "ratio": peak / base if base > 0 else float("inf"),
                "rise_s": float(t[k] - te),
                "decay_s": decay,
            }
        )
    return out


def quiet_speeds(
    time: npt.ArrayLike,
    speed: npt.ArrayLike,
    event_times: npt.ArrayLike,
    *,
    window: float,
    limit: float,
) -> dict[str, float]:
    """Mean particle speed away from breakage events (paper 000 Fig. 8b).

    The records at least ``window`` (s) after every event (and any time before the first)
    are the quiet ones; returns their count ``n``, ``median`` and ``p95`` speed (m/s), the
    ``fraction_above`` ``limit`` (m/s, e.g. the bar speed), and the ``max``. The same count
    and fraction are split at the first event (``n_before_first_event``,
    ``fraction_above_before_first_event``, ``n_after_first_event``,
    ``fraction_above_after_first_event``; NaN fractions where a part has no record): the
    rearrangements of an intact packing under a moving bar are told from the aftermath of
    breakage.
    """
    t = np.asarray(time, float).ravel()
    v = np.asarray(speed, float).ravel()
    te = np.asarray(event_times, float).ravel()
    quiet = np.ones(t.shape, bool)
    for e in te.tolist():
        quiet &= ~((t > e) & (t < e + window))
    q = v[quiet]
    nan = float("nan")
    first = te.min() if te.size else np.inf
    split = {}
    for name, part in (("before", quiet & (t <= first)), ("after", quiet & (t > first))):
        split[f"n_{name}_first_event"] = int(part.sum())
        split[f"fraction_above_{name}_first_event"] = (
            float(np.mean(v[part] > limit)) if part.any() else nan
        )
    if q.size == 0:
        return {"n": 0, "median": nan, "p95": nan, "max": nan, "fraction_above": nan} | split
    return {
        "n": int(q.size),
        "median": float(np.median(q)),
        "p95": float(np.quantile(q, 0.95)),
        "max": float(q.max()),
        "fraction_above": float(np.mean(q > limit)),
    } | split
