"""Breakage metrics: PSD quantiles, polar histogram of fracture planes, Table III types,
the locking-effect detector, force-chain intensity and kinetic-energy spikes."""

import math

import numpy as np
import pytest

from jaxgran.breakage import metrics


def test_psd_quantiles_of_equal_masses_interpolate_the_cumulative_curve():
    d = np.array([4.0, 1.0, 3.0, 2.0]) * 1e-2
    psd = metrics.particle_size_distribution(d, masses=np.ones(4))
    assert psd["diameter"].tolist() == pytest.approx([0.01, 0.02, 0.03, 0.04])
    assert psd["passing"].tolist() == pytest.approx([0.25, 0.5, 0.75, 1.0])
    assert psd["d50"] == pytest.approx(0.02)
    assert psd["d10"] == pytest.approx(0.01)  # below the first point: clamped
    # equivalent diameter of a unit-radius disc's area is 2
    assert metrics.equivalent_diameters([math.pi])[0] == pytest.approx(2.0)


def _ev(angle_deg, parent, frags, time=0.0, masses=(0.5, 0.5), n_fines=0, fines=0.0):
    a = math.radians(angle_deg)
    plane = np.array([[[0.0, 0.0], [math.cos(a), math.sin(a)]]])
    return {
        "planes": plane,
        "parent_uid": parent,
        "fragment_uids": np.array(frags),
        "time": time,
        "fragment_masses": np.array(masses),
        "n_fines": n_fines,
        "fines_mass": fines,
    }


def test_polar_histogram_counts_each_plane_at_both_orientations():
    evs = [_ev(95.0, 0, [1, 2]), _ev(275.0, 3, [4, 5]), _ev(15.0, 6, [7, 8])]
    h = metrics.fracture_plane_histogram(evs, 10.0)
    assert h["counts"].size == 36 and h["counts"].sum() == 6
    assert h["counts"][9] == 2 and h["counts"][27] == 2  # 90-100 and 270-280
    assert h["counts"][1] == 1 and h["counts"][19] == 1
    assert h["max_frequency"] == 2 and h["dominant_deg"] == pytest.approx(95.0)
    with pytest.raises(ValueError, match="divide 360"):
        metrics.fracture_plane_histogram(evs, 7.0)


def test_breakage_types_follow_table_iii_thresholds_and_count_fines_as_chips():
    m0 = 1.0
    evs = [
        _ev(0, 0, [1, 2], masses=(0.45, 0.5)),  # m_r = 0.45 > 0.4: splitting
        _ev(0, 3, [4, 5], masses=(0.4, 0.6)),  # 0.4: fragmentation (0.1 <= m_r <= 0.4)
        _ev(0, 6, [7, 8], masses=(0.1, 0.9)),  # 0.1: fragmentation
        _ev(0, 9, [10, 11], masses=(0.09, 0.9)),  # chipping
        _ev(0, 12, [13], masses=(0.95,), n_fines=1, fines=0.03),  # chip lost as fines
    ]
    types = [metrics.event_breakage_type(e, m0) for e in evs]
    assert types == ["splitting", "fragmentation", "fragmentation", "chipping", "chipping"]
    pct = metrics.breakage_type_percentages(evs, m0)
    assert pct["counts"] == {"splitting": 1, "fragmentation": 2, "chipping": 2}
    assert sum(pct["percent"].values()) == pytest.approx(100.0)


def test_locking_detector_finds_repeated_parallel_cuts_in_one_lineage():
    # uid 0 splits at 90 deg; its fragment 2 splits again at 92; then 4 again at 88:
    # a chain of three parallel cuts (two repeats). An unrelated lineage cuts at 90 once,
    # and a fragment cut at 45 deg is no repeat.
    evs = [
        _ev(90.0, 0, [1, 2], 0.1),
        _ev(90.0, 10, [11, 12], 0.15),
        _ev(92.0, 2, [3, 4], 0.2),
        _ev(45.0, 1, [5, 6], 0.25),
        _ev(88.0, 4, [7, 8], 0.3),
    ]
    res = metrics.locking_effect(evs)
    assert res["locked"] and res["n_locking_chains"] == 1
    assert res["chains"] == [[0, 2, 4]]
    assert res["n_repeats"] == 2 and res["max_chain"] == 3
    assert not metrics.locking_effect(evs[:3])["locked"]  # one repeat only
    assert metrics.locking_effect(evs[:3], min_repeats=1)["locked"]


def _planes_ev(angles_deg, parent, frags):
    """An event cut by several planes through the origin at ``angles_deg``."""
    ev = _ev(0.0, parent, frags)
    a = np.radians(np.asarray(angles_deg, float))
    ends = np.stack([np.cos(a), np.sin(a)], axis=-1)
    ev["planes"] = np.stack([np.zeros_like(ends), ends], axis=1)
    return ev


def test_repeats_by_chance_is_the_matching_share_of_rotations():
    """The chance level of a repeat is the share of rotations of the later event's planes
    (as one rigid set) that bring one of them within the tolerance of the earlier event's:
    1/6 for one plane against one at 15 deg, 1/3 for a cross against one plane, 40/180 for
    two planes 10 deg apart against one; and the repeat detector, run on the same pattern
    turned by many random angles, matches in that share of the turns."""

    def chance(later, earlier):
        evs = [_planes_ev(earlier, 0, [1, 2]), _planes_ev(later, 1, [3, 4])]
        res = metrics.locking_effect(evs)
        assert res["n_candidates"] == 1
        return res["repeats_by_chance"]

    assert chance([37.0], [120.0]) == pytest.approx(1.0 / 6.0)
    assert chance([37.0, 127.0], [5.0]) == pytest.approx(1.0 / 3.0)
    assert chance([0.0, 10.0], [100.0]) == pytest.approx(40.0 / 180.0)
    assert chance([0.0, 60.0, 120.0], [0.0, 90.0]) == pytest.approx(1.0)  # arcs cover all
    rng = np.random.default_rng(3)
    for _ in range(5):
        earlier = rng.uniform(0.0, 180.0, rng.integers(1, 4))
        pattern = rng.uniform(0.0, 180.0, rng.integers(1, 4))
        p = chance(pattern, earlier)
        turns = rng.uniform(0.0, 180.0, 4000)
        hits = [
            metrics.locking_effect(
                [_planes_ev(earlier, 0, [1, 2]), _planes_ev(pattern + t, 1, [3, 4])]
            )["n_repeats"]
            for t in turns
        ]
        se = math.sqrt(max(p * (1.0 - p), 1e-12) / len(turns))
        assert abs(np.mean(hits) - p) < 4.0 * se + 1e-12
    # an event whose parent is no fragment of an earlier one is no candidate
    assert metrics.locking_effect([_ev(90.0, 0, [1, 2]), _ev(90.0, 7, [8, 9])])["n_candidates"] == 0


def test_force_chain_intensity_is_the_principal_stress_difference():
    s = np.array([[[-3.0, 0.0], [0.0, -1.0]], [[0.0, 2.0], [2.0, 0.0]]])
    assert metrics.force_chain_intensity(s).tolist() == pytest.approx([2.0, 4.0])
    # BEM field [P, M, 3]: mean over the used points, zero rows ignored
    bem = np.array([[[-3.0, -1.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]]])
    assert metrics.force_chain_intensity(bem, axis_points=True).tolist() == pytest.approx([3.0])


def test_kinetic_energy_spike_peak_and_exponential_decay():
    t = np.linspace(0.0, 1.0, 1001)
    base, amp, tau, te = 1e-3, 9e-3, 0.05, 0.3
    ke = base + np.where(t > te + 0.01, amp * np.exp(-(t - te - 0.01) / tau), 0.0)
    ke[(t > te) & (t <= te + 0.01)] = base + amp  # rise to the peak
    (sp,) = metrics.kinetic_energy_spikes(t, ke, [te], window=0.5)
    assert sp["baseline"] == pytest.approx(base)
    assert sp["peak"] == pytest.approx(base + amp)
    assert sp["ratio"] == pytest.approx(10.0)
    assert sp["decay_s"] == pytest.approx(tau + 0.01, abs=2e-3)


def test_each_event_gets_its_own_spike_when_the_next_comes_within_the_window():
    """Two events 0.25 s apart, the second's spike ten times the first's: with a 0.5 s
    window the first event keeps its own peak and decay (its window ends where the second
    event begins); two events at the same time share one spike."""
    t = np.linspace(0.0, 2.0, 2001)
    base, tau = 1e-3, 0.02
    ke = np.full_like(t, base)
    for te, amp in ((0.5, 4e-3), (0.75, 4e-2)):
        ke += np.where(t > te + 0.005, amp * np.exp(-(t - te - 0.005) / tau), 0.0)
        ke[(t > te) & (t <= te + 0.005)] += amp
    first, second = metrics.kinetic_energy_spikes(t, ke, [0.5, 0.75], window=0.5)
    assert first["peak"] == pytest.approx(base + 4e-3, rel=1e-3)
    assert first["rise_s"] <= 0.25 and first["decay_s"] == pytest.approx(tau + 0.005, abs=2e-3)
    assert second["peak"] == pytest.approx(base + 4e-2, rel=1e-2)
    together = metrics.kinetic_energy_spikes(t, ke, [0.75, 0.75], window=0.5)
    assert together[0] == together[1] == second


def test_quiet_speeds_leave_out_the_window_after_each_event():
    """A steady 0.5 mm/s with 2 mm/s bursts right after two events: the quiet records are
    those outside the windows, all at 0.5 mm/s, none above 1 mm/s; a burst outside a
    window counts."""
    t = np.linspace(0.0, 10.0, 1001)
    v = np.full_like(t, 5e-4)
    for te in (2.0, 6.0):
        v[(t > te) & (t < te + 0.3)] = 2e-3
    q = metrics.quiet_speeds(t, v, [2.0, 6.0], window=0.5, limit=1e-3)
    assert q["n"] == 1001 - 2 * 49
    assert q["median"] == pytest.approx(5e-4) and q["max"] == pytest.approx(5e-4)
    assert q["fraction_above"] == 0.0
    q = metrics.quiet_speeds(t, v, [2.0], window=0.5, limit=1e-3)
    assert q["fraction_above"] == pytest.approx(29 / (1001 - 49))
    # the burst after 6.0 s lies after the first event: split there
    assert q["n_before_first_event"] == 201 and q["fraction_above_before_first_event"] == 0.0
    assert q["n_after_first_event"] == 1001 - 49 - 201
    assert q["fraction_above_after_first_event"] == pytest.approx(29 / (1001 - 49 - 201))
    # a stick-slip before any event counts before it; no event: everything is before
    v[(t > 1.0) & (t < 1.1)] = 3e-3
    q = metrics.quiet_speeds(t, v, [2.0], window=0.5, limit=1e-3)
    assert q["fraction_above_before_first_event"] == pytest.approx(9 / 201)
    q = metrics.quiet_speeds(t, v, [], window=0.5, limit=1e-3)
    assert q["n_before_first_event"] == 1001 and q["n_after_first_event"] == 0
    assert np.isnan(q["fraction_above_after_first_event"])
