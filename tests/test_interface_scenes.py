"""Interface-bond scenes (paper 003): direct tension is linear up to a brittle peak, both bond
models run, and the plate-contact disc (the default Voronoi mesh) carries the closed-form
splitting stress on its axis, splits along it and has its shear failures under the plates;
confined compression runs end to end under its servo walls. Quick specimens (28 elementary
discs, in tension and in compression; 120 Voronoi cells; 120 discs for the packing's xfail)
keep the compilations few."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from jaxgran import interface as itf
from jaxgran.io import read_run
from jaxgran.scenes import SCENES
from jaxgran.scenes import interface as si
from jaxgran.scenes import interface_plate as pc
from jaxgran.scenes import interface_tension as tn


def test_scenes_are_registered_with_quick_modes():
    for name in (
        "interface-tension",
        "interface-compression",
        "interface-uniaxial",
        "interface-brazilian",
        "plate-contact",
    ):
        mod = SCENES[name]
        cfg = dataclasses.replace(mod.Config(), **mod.QUICK)
        assert cfg.bond == "interface" and dataclasses.replace(cfg, bond="parallel")


@pytest.mark.parametrize("seed", [10, 11])
def test_disc_specimen_is_one_bonded_cluster(seed):
    """The packings of these seeds leave a few discs bonded to each other but to nothing
    else, including the disc at a pole (a plate then pushes that loose cluster in without
    resistance and the specimen is never loaded): the specimen keeps the largest bonded
    cluster only, so every disc is tied to every other through bonds."""
    from jaxgran.analysis import fragments

    cfg = dataclasses.replace(pc.Config(), seed=seed, particles="discs")
    region = ("disc", 0.5 * cfg.diameter, (0.0, 0.0))
    x, r = si.disc_packing(region, cfg.d_min, cfg.d_max, seed, cfg.solid_fraction)
    raw = itf.disc_interfaces(x, r, cfg.bond_gap * r.min())["pairs"]
    clusters = fragments(raw[:, 0], raw[:, 1], len(x))
    bonded = [c for c in clusters if len(c) > 1]
    assert len(bonded) >= 2  # the raw packing has a loose cluster
    spec = si.make_specimen(cfg, region, si.material_from(cfg))
    pairs = spec.interfaces["pairs"]
    assert len(fragments(pairs[:, 0], pairs[:, 1], spec.n_particles)) == 1
    assert spec.n_particles == len(bonded[0])
    assert len(pairs) == sum(np.isin(raw, bonded[0]).all(axis=1))


def test_mohr_envelope_fits_recover_both_shapes():
    s3 = np.array([-2.0, 0.0, 2.0, 5.0, 10.0, 20.0, 40.0]) * 1e6
    c, sb = 12e6, 4e6
    # circles tangent to the parabola tau^2 = c^2 (1 + sigma / sigma_b): q^2 linear in p,
    # q^2 = c^2 - c^4 / (4 sb^2) + (c^2 / sb) p with p = s3 + q: solve for q
    b1, b0 = c * c / sb, c * c - c**4 / (4 * sb * sb)
    q = 0.5 * (b1 + np.sqrt(b1 * b1 + 4 * (b0 + b1 * s3)))
    fits = si.mohr_envelope_fits(s3 + 2 * q, s3)
    assert fits["parabola_r2"] == pytest.approx(1.0, abs=1e-12)
    assert fits["parabola_cohesion_Pa"] == pytest.approx(c, rel=1e-9)
    assert fits["parabola_tensile_strength_Pa"] == pytest.approx(sb, rel=1e-9)
    assert fits["linear_r2"] < 0.99
    # circles tangent to a straight line: q = c cos(phi) + p sin(phi)
    phi = np.radians(35.0)
    q = (c * np.cos(phi) + s3 * np.sin(phi)) / (1 - np.sin(phi))
    fits = si.mohr_envelope_fits(s3 + 2 * q, s3)
    assert fits["linear_r2"] == pytest.approx(1.0, abs=1e-12)
    assert fits["linear_friction_angle_deg"] == pytest.approx(35.0, rel=1e-9)
    assert fits["linear_cohesion_Pa"] == pytest.approx(c, rel=1e-9)


def test_confined_run_ends_on_a_sustained_drop_not_on_a_stick_slip_dip():
    """The biaxial run's stop rule: a dip below the drop fraction that recovers within the
    post-peak window does not end the run (stick-slip under confinement), a drop that lasts
    the window does, and no drop counts before an element has failed."""
    from jaxgran.scenes import interface_compression as ic

    strain = np.linspace(0.0, 0.03, 301)
    q = np.where(strain < 0.01, 3e9 * strain, 30e6)  # rise to 30 MPa at 1 % ...
    q = np.where((strain > 0.012) & (strain < 0.014), 10e6, q)  # ... a 0.2 % dip ...
    q = np.where(strain > 0.02, 5e6, q)  # ... and the collapse at 2 %
    track = ic.new_drop_track()
    assert not ic.sustained_drop(track, q, strain, False, 0.7, 0.005)  # nothing failed yet
    stops = []
    track = ic.new_drop_track()
    for k in range(0, strain.size, 10):  # segments of 10 records
        seg = slice(k, k + 10)
        if ic.sustained_drop(track, q[seg], strain[seg], True, 0.7, 0.005):
            stops.append(strain[seg][-1])
    assert track["best"] == pytest.approx(30e6)
    assert stops and 0.025 <= stops[0] < 0.0265  # 0.5 % of strain after the collapse
    assert track["peaked"]
    # with a floor of 40 MPa (sigma3 = 40 MPa, drop_min_q = 1) that 30 MPa peak is not a
    # strength: the same record runs on; a peak above the floor arms the stop again
    track = ic.new_drop_track()
    assert not ic.sustained_drop(track, q, strain, True, 0.7, 0.005, 40e6)
    assert not track["peaked"]
    later = np.concatenate([strain, 0.03 + strain[1:]])
    q2 = np.concatenate([q, np.where(strain[1:] < 0.01, 50e6, 20e6)])  # 50 MPa, then 20
    track = ic.new_drop_track()
    assert ic.sustained_drop(track, q2, later, True, 0.7, 0.005, 40e6)
    assert track["best"] == pytest.approx(50e6)


def test_post_peak_behaviour_tells_brittle_plateau_softening_and_hardening_apart(tmp_path):
    """A peak followed by a drop that lasts the drop window is brittle; otherwise the slope
    of q over the last 2 % of strain decides: a change under 10 % of the peak across it is a
    plateau (whatever the stick-slip dips), a rise is hardening (not a strength), a fall
    softening. The records go to curves.h5 with the measures as attributes."""
    import h5py

    from jaxgran.scenes import interface_compression as ic

    strain = np.linspace(0.0, 0.10, 1001)

    def behaviour(q):
        track = ic.new_drop_track()
        stop, ended = strain.size, False
        for k in range(0, strain.size, 10):
            seg = slice(k, k + 10)
            if ic.sustained_drop(track, q[seg], strain[seg], True, 0.7, 0.005):
                stop, ended = k + 10, True
                break
        return ic.post_peak_behaviour(strain[:stop], q[:stop], ended, 0.02, 0.1)

    rise = np.minimum(3e9 * strain, 150e6)  # linear to 150 MPa at 5 %
    plateau = np.where(strain > 0.06, 0.85 * 150e6, rise)
    plateau = np.where((strain > 0.09) & (strain < 0.093), 0.5 * 150e6, plateau)  # a dip
    assert behaviour(plateau) == "plateau"
    assert behaviour(np.where(strain > 0.06, 0.3 * 150e6, rise)) == "brittle"
    assert behaviour(3e9 * strain) == "hardening"  # still rising at the limit
    # a slow change from 6 % on: 5 % of 150 MPa across the window is a plateau, 20 % is
    # hardening, -11 % softening (q ends at 0.78 of its peak: no sustained drop)
    for per_window, expected in ((0.05, "plateau"), (0.2, "hardening"), (-0.11, "softening")):
        q = rise + np.where(strain > 0.06, per_window * 150e6 * (strain - 0.06) / 0.02, 0.0)
        assert behaviour(q) == expected
    # the stored record reads back
    per = [
        {"sigma3_target_Pa": 4e7, "strain_at_peak": None, "notes": ["a", "b"]},
        {"sigma3_target_Pa": 2e7, "post_peak_behaviour": "plateau", "peaked": False},
    ]
    rec = [(s3, strain, strain, plateau + s3, np.full(strain.size, s3)) for s3 in (4e7, 2e7)]
    ic.write_curves(tmp_path / "curves.h5", rec, per)
    with h5py.File(tmp_path / "curves.h5", "r") as f:
        assert list(f) == ["sigma3_40MPa", "sigma3_20MPa"]  # in the order run
        g = f["sigma3_20MPa"]
        assert np.allclose(g["deviator"][()], plateau) and g["deviator"].attrs["units"] == "Pa"
        assert g.attrs["post_peak_behaviour"] == "plateau" and not g.attrs["peaked"]
    back = ic.read_curves(tmp_path / "curves.h5")
    np.testing.assert_array_equal(back["sigma3_40MPa"]["axial_strain"], strain)
    np.testing.assert_allclose(back["sigma3_40MPa"]["deviator"], plateau, rtol=1e-12)
    assert list(back) == ["sigma3_40MPa", "sigma3_20MPa"]
    assert back["sigma3_40MPa"]["measures"] == per[0]  # None and lists survive, as JSON
    assert back["sigma3_20MPa"]["measures"] == per[1]


def test_particles_thrown_towards_the_grid_edge_are_taken_out():
    """A fragment flying off an unconfined specimen is deactivated once it comes within half
    the grid margin of the grid's edge (the run would otherwise stop on it); nothing else
    changes."""
    from jaxgran.scenes import interface_uniaxial as ux
    from jaxgran.state import replace

    setup = ux.build(dataclasses.replace(ux.Config(), **ux.QUICK))
    state, grid, guard = setup.state, setup.grid, 0.5 * setup.margin
    same, out = si.eject_escaping(state, grid, guard)
    assert out.size == 0 and same is state
    p = state.particles
    k = int(np.flatnonzero(np.asarray(p.active))[3])
    edge = grid.origin[0] + grid.cell_size * grid.nx
    moved = replace(p, pos=p.pos.at[k].set([edge - 0.4 * guard, float(p.pos[k, 1])]))
    new, out = si.eject_escaping(replace(state, particles=moved), grid, guard)
    assert out.tolist() == [k]
    act0, act1 = np.asarray(p.active), np.asarray(new.particles.active)
    assert not act1[k] and np.array_equal(np.delete(act1, k), np.delete(act0, k))


@pytest.fixture(scope="module")
def tension(tmp_path_factory):
    """Quick direct tension with both bond models (one compilation: same shapes)."""
    out = {}
    for bond in ("interface", "parallel"):
        cfg = dataclasses.replace(tn.Config(), **tn.QUICK, bond=bond)
        folder = tmp_path_factory.mktemp(f"tension_{bond}")
        summary = tn.run(cfg, folder, progress=False)
        out[bond] = (cfg, summary, folder)
    return out


def test_direct_tension_is_linear_to_a_brittle_peak(tension):
    for bond, (cfg, summary, folder) in tension.items():
        run = read_run(folder / "run.h5")
        force, gap = si.axial_load(run["series"])
        stress = -force / (cfg.width * cfg.thickness)
        strain = gap / gap[0] - 1.0
        k = int(np.argmax(stress))
        # linear elastic rise: straight line up to 90 % of the peak, secant = tangent
        assert summary["rising_branch_r2"] > 0.995, bond
        assert summary["secant_over_tangent_at_peak"] == pytest.approx(1.0, abs=0.05), bond
        # brittle: at most a few elements fail before the peak, then the load collapses
        # within a small fraction of the peak strain
        assert summary["elements_failed_before_peak"] <= 0.05 * summary["n_elements"]
        assert stress[-1] < cfg.drop_fraction * stress[k]
        assert strain[-1] - strain[k] < 0.5 * strain[k]
        # an opening crack: every failed element ends open, wider than any intact one
        opening, failed = _element_openings(run["final"])
        assert failed.any(), bond
        assert opening[failed].min() > max(opening[~failed].max(), 0.0), bond
        # the parallel bond's straight envelope keeps a shear strength at sigma_b, so those
        # elements fail in tension; the parabola's vanishes there, so an element pulled to
        # sigma_b with any shear is booked as shear (9:5 or 7:7 of 14 with the time step)
        if bond == "parallel":
            assert summary["n_failed_tension"] > summary["n_failed_shear"]
        # the strength is below the element strength
        assert 0.1 * cfg.tensile_strength < summary["tensile_strength_Pa"] < cfg.tensile_strength
        s = json.loads((folder / "summary.json").read_text())
        assert s["bond"] == bond and any(f.endswith("cracks.png") for f in s["figures"])
    # the envelopes differ only off the tension axis: the same specimen has nearly the same
    # tensile strength with either model
    a = tension["interface"][1]["tensile_strength_Pa"]
    b = tension["parallel"][1]["tensile_strength_Pa"]
    assert abs(a - b) < 0.25 * a


def _element_openings(final: dict) -> tuple[np.ndarray, np.ndarray]:
    """Opening ``u_n`` (m) of every element of the live interfaces of a run file's final
    state (:func:`jaxgran.interface.interface_kinematics` on the stored arrays), and which of
    them failed."""
    from types import SimpleNamespace

    import jax.numpy as jnp

    b = final["bonds"]
    p = SimpleNamespace(**{k: jnp.asarray(final[k]) for k in ("pos", "angle", "active")})
    keys = ("i", "j", "normal_i", "theta0", "elem_point_i", "elem_point_j")
    kin = itf.interface_kinematics(p, SimpleNamespace(**{k: jnp.asarray(b[k]) for k in keys}))
    live = np.asarray(kin["live"])
    failed = np.isfinite(np.asarray(b["elem_break_time"]))[live]
    return np.asarray(kin["u_n"])[live], failed


@pytest.fixture(scope="module")
def plate():
    """The default plate-contact scene: the disc meshed as ~120 bonded Voronoi cells."""
    cfg = dataclasses.replace(pc.Config(), **pc.QUICK)
    assert cfg.particles == "voronoi"
    res, setup = pc.simulate_test(cfg)
    return cfg, res, setup, pc.measure(res, setup, cfg)


@pytest.fixture(scope="module")
def plate_discs():
    """The same disc as a packing of ~120 bonded elementary discs of 2.5-5 mm."""
    cfg = dataclasses.replace(pc.Config(), **pc.QUICK, particles="discs")
    res, setup = pc.simulate_test(cfg)
    return cfg, res, setup, pc.measure(res, setup, cfg)


def _check_axis_stress(cfg, m):
    """Before the first element fails, the horizontal stress in the measurement circles of the
    middle third is the closed form 2P / (pi D T) (averaged over each circle) within 10 %
    (mean over those circles), in tension in the middle and lower next to the plates."""
    prof = m["axis_before_first_failure"]
    assert prof["force_N"] > 0
    assert prof["middle_third_mean_error"] < 0.10
    y = np.asarray(prof["y_m"])
    sxx = np.asarray(prof["sigma_xx_Pa"])
    assert sxx[np.abs(y) < cfg.diameter / 6].mean() > 0
    assert sxx[np.argmax(np.abs(y))] < sxx[np.argmin(np.abs(y))]


def test_plate_contact_axis_stress_matches_the_disc_solution(plate):
    """The Voronoi mesh (over 32 seeds: axis ratio 0.96 +- 0.04, 30 of them within 10 %;
    benchmarks/plate_acceptance/seeds_voronoi.json); seed 0 reads 0.96."""
    cfg, res, setup, m = plate
    _check_axis_stress(cfg, m)


@pytest.mark.xfail(
    strict=True,
    reason="a random packing of ~120 bonded discs (solid fraction 0.7) is not a homogeneous "
    "elastic disc at the scale of the measurement circles: its middle-third axis stress is "
    "0.63 +- 0.08 (mean +- s.e., std 0.46) of the closed form over 32 seeds, 5 within 10 % "
    "(benchmarks/plate_acceptance/seeds.json), 0.85 +- 0.11 (std 0.38) over 12 seeds of "
    "~740 discs; seed 0 reads 1.65. The scene's default Voronoi mesh meets it (test above)",
)
def test_plate_contact_axis_stress_on_a_disc_packing(plate_discs):
    """The disc packing: the same check as on the Voronoi mesh."""
    cfg, res, setup, m = plate_discs
    _check_axis_stress(cfg, m)


def test_plate_contact_axis_is_in_tension_between_compressed_ends(plate):
    """Before the first failure the loaded axis is in tension in its middle third and in
    compression next to both plates, as in the disc solution."""
    cfg, res, setup, m = plate
    prof = m["axis_before_first_failure"]
    y = np.asarray(prof["y_m"])
    sxx = np.asarray(prof["sigma_xx_Pa"])
    assert prof["force_N"] > 0.2 * m["force_max_N"]
    assert sxx[np.abs(y) < cfg.diameter / 6].mean() > 0
    assert sxx[np.argmin(y)] < 0 and sxx[np.argmax(y)] < 0


def test_plate_contact_tension_cracks_follow_the_loading_axis(plate):
    """The default specimen (seed 0) fails (the load drops) by tension cracks along the
    loading axis, and the interfaces exert no net force through the whole run."""
    cfg, res, setup, m = plate
    assert m["final_force_over_max"] < cfg.drop_fraction
    assert m["n_failed_tension"] > 0
    assert m["tension_cracks_axis_angle_deg"] < 25.0
    # Newton's third law through the whole run: the interfaces exert no net force
    f, _, _ = itf.interface_forces(res.state.particles, res.state.bonds, res.state.walls, 0.0)
    f = np.asarray(f)
    assert np.abs(f.sum(axis=0)).max() < 1e-9 * np.abs(f).max()


def test_fragments_count_slots_and_leave_out_particles_taken_out_of_the_run():
    """A particle taken out of the run (interface.eject_escaping: inactive, its slot kept)
    belongs to no fragment, and the fragments of the others use their slots. The count of
    active particles used to be taken as the slot count: a disc packing (seed 16) that had
    thrown one disc out stopped with "edge ends must lie in [0, 115)"."""
    from types import SimpleNamespace as NS

    active = np.array([True, False, True, True, True, True])  # slot 1 taken out
    i = np.array([0, 2, 0, 4, 1, 5])
    j = np.array([2, 3, 3, 5, 5, 5])  # the last one is padding (i = j)
    state = NS(particles=NS(active=active), bonds=NS(i=i, j=j, intact=np.ones(6, bool)))
    frags = [sorted(f.tolist()) for f in pc._fragments(state)]
    assert frags == [[0, 2, 3], [4], [5]]  # the 4-5 link is a bridge, split
    frags = [sorted(f.tolist()) for f in pc._fragments(state, split_bridges=False)]
    assert frags == [[0, 2, 3], [4, 5]]


def test_plate_contact_splits_the_disc_into_two_fragments(plate):
    """The final break splits the disc along the loading axis into two large fragments
    (fragments: held together by more than a single chain of bonds; 32 of 32 seeds of the
    mesh, split angles 0.1-24.9 deg, benchmarks/plate_acceptance/seeds_voronoi.json)."""
    cfg, res, setup, m = plate
    assert m["split_angle_from_loading_axis_deg"] < 25.0
    assert m["fragment_sizes"][1] >= 0.2 * setup.spec.n_particles


def test_plate_contact_shear_failures_concentrate_under_the_plates(plate):
    """The cone cores: the share of shear failures within D / 6 of a plate is well above the
    share of all interface elements there (32 of 32 seeds of the mesh)."""
    cfg, res, setup, m = plate
    assert m["n_shear"] > 10
    assert m["shear_share_near_plates"] > 1.5 * m["element_share_near_plates"]


def test_interface_step_is_stable_with_the_element_and_contact_dashpots():
    """``stable_dt`` counts the dashpots: at ``safety = 1`` the step linearised about the
    quick tension specimen is inside the scheme's stability region (criterion 0.44, radius
    no larger than without the dashpots), while the springs-only limit it gave before puts
    the same specimen outside it (criterion 1.18, radius 1.43)."""
    from jaxgran.integrate import linear_step_radius
    from jaxgran.simulate import prepare

    setup = tn.build(dataclasses.replace(tn.Config(), **tn.QUICK))
    state, _ = prepare(setup.state, setup.params, setup.grid)
    dt = si.stable_dt(setup.state, setup.material, 1.0)
    now = linear_step_radius(state, setup.params, dt=dt)
    assert now["criterion"] < 0.6
    assert now["radius"] <= now["radius_without_dashpots"] * (1 + 1e-9)
    old = si.stable_dt(setup.state, setup.material, 1.0, dashpots=False)
    before = linear_step_radius(state, setup.params, dt=old)
    assert before["criterion"] > 1.0 and before["radius"] > 1.2
    # the scene runs at dt_safety of the limit
    assert float(setup.params.dt) == pytest.approx(tn.Config().dt_safety * dt, rel=1e-12)


def test_confined_compression_runs_end_to_end_with_the_servo_at_sigma3(tmp_path):
    """The whole `interface-compression` scene on the quick specimen at two confinements,
    sheared to 1 % (still elastic): the lateral walls hold sigma3, q rises on a straight
    line, and summary.json, curves.h5, the run files of both confinements and the figures
    agree with each other."""
    import h5py

    from jaxgran.scenes import interface_compression as ic

    quick = {**ic.QUICK, "confinements": (5.0e6, 20.0e6), "max_strain": 0.01}
    cfg = dataclasses.replace(ic.Config(), **quick)
    summary = ic.run(cfg, tmp_path, progress=False)
    assert json.loads((tmp_path / "summary.json").read_text())["steps"] == summary["steps"]
    low, conf = summary["per_confinement"]
    # run.h5 is the last confinement's record, run_sigma3_5MPa.h5 the first one's: their
    # walls' targets and their shearing records are those of curves.h5
    for name, path, s3 in (
        ("sigma3_5MPa", tmp_path / "run_sigma3_5MPa.h5", 5.0e6),
        ("sigma3_20MPa", tmp_path / "run.h5", 20.0e6),
    ):
        rec = read_run(path)
        np.testing.assert_allclose(rec["final"]["walls"]["target_stress"][[1, 2]], s3)
        t = ic.read_curves(tmp_path / "curves.h5")[name]["time"]
        np.testing.assert_array_equal(rec["series"]["time"][-len(t) :], t)
        assert (tmp_path / f"cracks_{name}.png").stat().st_size > 0
    assert not (tmp_path / "run_sigma3_20MPa.h5").exists()
    assert low["sigma3_target_Pa"] == 5.0e6
    # the elements that failed while sheared, found from the frames (none at 20 MPa)
    assert low["n_shear_failures_recorded"] + low["n_tension_failures_recorded"] <= sum(
        low[f"n_failed_{m}"] for m in ("shear", "tension")
    )
    assert conf["n_shear_failures_recorded"] == 0
    assert conf["shear_failure_compression_median_Pa"] is None
    assert (tmp_path / "element_failures.png").stat().st_size > 0
    with h5py.File(tmp_path / "curves.h5", "r") as f:
        g = f["sigma3_20MPa"]
        strain, q = g["axial_strain"][:], g["deviator"][:]
        axial, lateral = g["sigma_axial"][:], g["sigma_lateral"][:]
        assert g.attrs["post_peak_behaviour"] == conf["post_peak_behaviour"]
    # stress control: within 0.5 % of sigma3 from the start of shearing (the isotropic
    # stage ends within iso_tolerance = 2 %), within 0.01 % once the servo has caught up
    assert np.abs(lateral / 20.0e6 - 1.0).max() < 0.005
    assert np.abs(lateral[len(lateral) // 4 :] / 20.0e6 - 1.0).max() < 1e-4
    np.testing.assert_allclose(q, axial - lateral, rtol=1e-12, atol=1e-3)
    # intact and elastic: no element failed, q is a straight line in the strain with a
    # block modulus below the element modulus
    assert conf["n_bonds_broken"] == 0 and conf["mean_damage"] == 0.0
    late = strain > 0.1 * cfg.max_strain
    slope, icpt = np.polyfit(strain[late], q[late], 1)
    resid = q[late] - (slope * strain[late] + icpt)
    assert 1.0 - resid.var() / q[late].var() > 0.9999
    assert 0.2 * cfg.modulus < slope < cfg.modulus
    # still rising at max_strain: no peak, no strength, and the envelope says so
    assert conf["post_peak_behaviour"] == "hardening" and not conf["peaked"]
    assert conf["final_strain"] == pytest.approx(cfg.max_strain, rel=0.01)
    assert conf["sigma1_peak_Pa"] == pytest.approx(axial.max(), rel=1e-12)
    assert summary["envelope_peaks_only_n_circles"] == 0
    assert all(Path(p).stat().st_size > 0 for p in summary["figures"])
    # elastic under a constant lateral stress: the lateral strain is -nu_block x the axial
    # strain (it shortens and widens). A hexagonal packing of discs bonded with k_s / k_n =
    # 1 / stiffness_ratio = 0.4 has nu = (1 - 0.4) / (3 + 0.4) = 0.18; this disordered one
    # gives 0.15. Volumetric strain = 1 - (1 - e_a)(1 - e_l).
    back = ic.read_curves(tmp_path / "curves.h5")["sigma3_20MPa"]
    lat, vol = back["lateral_strain"], back["volumetric_strain"]
    np.testing.assert_allclose(vol, 1.0 - (1.0 - strain) * (1.0 - lat), rtol=1e-12)
    nu_block = -np.polyfit(strain[late], lat[late], 1)[0]
    assert 0.08 < nu_block < 0.3
    # the lateral walls shear under their own speed cap and were never held back by it
    with h5py.File(tmp_path / "run.h5", "r") as f:
        cap = f["final/walls/max_speed"][:]
    assert cap[[1, 2]] == pytest.approx(cfg.servo_max_speed * cfg.strain_rate * cfg.height)
    assert conf["servo_at_cap_fraction"] == conf["servo_at_cap_fraction_to_peak"] == 0.0
    assert conf["sigma3_over_target_median"] == pytest.approx(1.0, abs=1e-4)
    assert conf["sigma3_over_target_p95"] == pytest.approx(1.0, abs=5e-3)


def test_lateral_control_counts_the_records_with_a_wall_at_its_speed_cap():
    """A lateral wall that moves out at its cap for the first 15 of the 29 shearing
    intervals, then at 0.3 x the cap (the isotropic records before them do not count):
    15 / 29 of the records at the cap, 15 / 20 up to a peak at record 20; the lateral
    stress's median and 95th percentile over its target."""
    from types import SimpleNamespace

    from jaxgran.scenes import interface_compression as ic

    n, start, dt, cap = 40, 10, 1e-4, 0.2
    t = np.arange(n) * dt
    x = np.zeros((n, 4, 2))
    x[:, 2, 0] = 0.03  # the right wall stands
    moving = np.arange(n) - start
    # the left wall closes in at the cap in the isotropic stage, moves out at the cap for
    # the first 15 shearing intervals, then at 0.3 x the cap
    x[:, 1, 0] = (
        cap * dt * np.clip(-moving, 0, None)
        - cap * dt * np.clip(moving, 0, 15)
        - 0.3 * cap * dt * np.clip(moving - 15, 0, None)
    )
    walls = SimpleNamespace(target_stress=np.full(4, 2e6), max_speed=np.full(4, cap))
    out = {
        "state": SimpleNamespace(walls=walls),
        "start": start,
        "series": {"time": t, "wall_point": x},
    }
    s_lat = np.linspace(2e6, 4e6, n - start)
    m = ic.lateral_control(out, s_lat, peak=20)
    assert m["servo_at_cap_fraction"] == pytest.approx(15 / (n - start - 1))
    assert m["servo_at_cap_fraction_to_peak"] == pytest.approx(15 / 20)
    assert m["sigma3_over_target_median"] == pytest.approx(1.5)
    assert m["sigma3_over_target_p95"] == pytest.approx(1.95)


def test_isotropic_and_shearing_stages_have_their_own_wall_speed_caps():
    """The four servo walls of the isotropic stage move under their own cap,
    ``iso_max_speed`` x strain_rate x height (the shearing stage's lateral walls take
    ``servo_max_speed``, checked end to end above), each at the target sigma3; a cap of 0
    is refused."""
    from jaxgran.scenes import interface_compression as ic

    cfg = dataclasses.replace(ic.Config(), **ic.QUICK, iso_max_speed=3.0, servo_max_speed=7.0)
    walls = ic.build(cfg, 5.0e6).state.walls
    unit = cfg.strain_rate * cfg.height
    np.testing.assert_allclose(np.asarray(walls.max_speed), 3.0 * unit, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(walls.target_stress), 5.0e6, rtol=1e-12)
    with pytest.raises(ValueError, match="iso_max_speed"):
        ic.Config(iso_max_speed=0.0)


def test_confinements_given_twice_are_refused_before_anything_runs():
    """curves.h5 and the run files are named by the confinement: the same one twice (or two
    that print alike) is a clear error up front, not an HDF5 error after the runs."""
    from jaxgran.scenes import interface_compression as ic

    for twice in ((5.0e6, 5.0e6), (2.0e6, 2.0000001e6)):
        cfg = dataclasses.replace(ic.Config(), **{**ic.QUICK, "confinements": twice})
        with pytest.raises(ValueError, match="same group twice"):
            ic.envelope(cfg)
