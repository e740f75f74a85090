"""Breakage scenes: the breakage type of each method under N = 2, 3, 4 loads (paper 000
Fig. 12) and the quick oedometric test of breakable pentagons (paper 000 §III)."""

import contextlib
import dataclasses
import logging
import math

import jax
import numpy as np
import pytest

from jaxgran import io
from jaxgran.breakage import metrics
from jaxgran.breakage.averaged import method_name
from jaxgran.scenes import brazilian_dsm as bd
from jaxgran.scenes import breakage_types as bt
from jaxgran.scenes import deposit as dp
from jaxgran.scenes import oedometer_cantor as oc
from jaxgran.scenes import oedometer_voronoi as ov

BT = dataclasses.replace(bt.Config(), **bt.QUICK)


@pytest.fixture(scope="module")
def types_table():
    return {(r["configuration"], r["method"]): r for r in bt.run_table(BT)}


def test_dsm_breakage_type_follows_the_loading(types_table):
    got = {c: types_table[(c, "dsm")]["breakage_type"] for c in ("N2", "N3", "N4")}
    assert got == {"N2": "splitting", "N3": "fragmentation", "N4": "chipping"}
    # the Brazilian test breaks at the calibration force (within one load step)
    f = types_table[("N2", "dsm")]["breaking_load_N"]
    assert 150.79 / BT.ramp <= f <= 150.79 * BT.ramp


def test_averaged_methods_cut_through_the_centroid_whatever_the_loading(types_table):
    for conf in ("N2", "N3", "N4"):
        cc = types_table[(conf, "cross-cut")]
        assert cc["broke"] and cc["n_fragments"] == 4
        assert cc["breakage_type"] == "fragmentation"  # four quarters: m_r = 0.25
        mc = types_table[(conf, "mohr-coulomb")]
        assert mc["broke"] and mc["n_fragments"] == 2 and mc["breakage_type"] == "splitting"
    # split-cell needs (3 s1 - s2) / 2 > sigma_T: a nearly isotropic average (the pinched
    # N4 grain) never reaches it; where it breaks, it halves the grain
    for conf in ("N2", "N3"):
        r = types_table[(conf, "split-cell")]
        assert r["broke"] and r["n_fragments"] == 2 and r["breakage_type"] == "splitting"
    assert not types_table[("N4", "split-cell")]["broke"]
    md = bt.markdown_table(list(types_table.values()))
    assert md.count("\n") == 5 and "chipping" in md


@contextlib.contextmanager
def compiles_of(name: str):
    """Collects the messages of every XLA compilation of ``jit(name)`` inside the block."""
    seen = []

    class Catch(logging.Handler):
        def emit(self, record):
            msg = record.getMessage()
            if msg.startswith(f"Compiling jit({name})"):
                seen.append(msg)

    handler = Catch(level=logging.DEBUG)
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            yield seen
    finally:
        logger.removeHandler(handler)


def test_scene_time_steps_are_strongly_typed():
    """A weakly typed dt (``jnp.asarray`` of a Python float) differs in type from the dt that
    breakage sets later, and the segment would recompile at the first breakage."""
    built = [
        oc.build(dataclasses.replace(oc.Config(), **oc.QUICK)),
        ov.build(dataclasses.replace(ov.Config(), **ov.QUICK)),
        dp.build(dataclasses.replace(dp.Config(), **dp.QUICK)),
        bd.build(dataclasses.replace(bd.Config(), **bd.QUICK)),
        bt.build(BT, "N2", 1.0),
    ]
    for parts in built:
        params = parts[1]
        assert not params.dt.weak_type
        assert params.dt.dtype == params.normal_stiffness.dtype


QUICK_SPLIT = dataclasses.replace(oc.Config(), **oc.QUICK, method="split-cell")


@pytest.fixture(scope="module")
def quick_split(tmp_path_factory):
    """The quick Cantor oedometer (split-cell), checkpointed after every segment: the run,
    the compilations of its segment, and the bytes of every checkpoint written."""
    path = tmp_path_factory.mktemp("checkpoint") / "checkpoint.pkl"
    saved = []
    real = io.save_checkpoint

    def keep(*args):
        real(*args)
        saved.append(path.read_bytes())

    stages = []  # (desc, grains' and walls' friction) of each simulate call
    real_simulate = oc.simulate

    def simulate(state, params, *args, **kwargs):
        mu = (np.asarray(params.friction), np.asarray(params.wall_friction))
        stages.append((kwargs.get("desc"), mu))
        return real_simulate(state, params, *args, **kwargs)

    with contextlib.ExitStack() as stack:
        mp = stack.enter_context(pytest.MonkeyPatch.context())
        mp.setattr(io, "save_checkpoint", keep)
        mp.setattr(oc, "simulate", simulate)
        compiled = stack.enter_context(compiles_of("run_segment"))
        run = oc.simulate_test(QUICK_SPLIT, checkpoint=path, checkpoint_every_s=0.0)
    return run, list(compiled), saved, path, stages


def test_quick_cantor_oedometer_keeps_mass_bookkeeping_and_particles_inside(quick_split):
    cfg = QUICK_SPLIT
    (settle, load, brk, info), compiled, _, _, stages = quick_split
    # breakage and the adaptive time step never recompile the segment; a capacity growth
    # may, once per growth: the particle slots (logged in the event) or the contact
    # search's cells and pairs (logged in regrows; the settled pile, denser than the lattice
    # it fell from, can fill a cell beyond the starting capacity)
    growths = sum("capacity_growth" in e for e in brk.events)
    growths += len(settle.regrows) + len(load.regrows)
    assert len(compiled) <= 1 + growths
    s = oc.summarize(settle, load, brk, info, cfg)
    assert s["finite"] and not s["escaped"]
    assert s["n_events"] >= 1
    # the pile settled with frictionless grains and walls, came to rest with Table I's mu,
    # and was loaded with it
    assert cfg.settle_friction == 0.0
    assert [d for d, _ in stages] == [
        "oedometer settle",
        "oedometer settle (contact friction)",
        "oedometer split-cell",
    ]
    assert all(np.all(m == 0.0) for m in stages[0][1])
    assert all(np.all(m == cfg.friction) for _, mu in stages[1:] for m in mu)
    assert settle.stopped_early  # at rest by settle_ke_ratio
    # mass: final active mass = initial - sum of the events' losses (fines + erosion)
    assert s["mass_bookkeeping_error"] < 1e-12
    # quick mode drops pieces under a tenth of the mean grain as fines; what local erosion
    # takes (caps where neighbours overlap, rounded new corners) stays near 1 %
    eroded = sum(float(e["eroded_mass"]) for e in brk.events) / info["initial_mass"]
    assert 0.0 <= eroded < 0.02
    # one areal density and no compensation: the mass lost is the area lost
    assert s["area_lost_fraction"] == pytest.approx(s["mass_lost_fraction"], rel=1e-9)
    assert s["mass_fines_fraction"] + s["mass_eroded_fraction"] == pytest.approx(
        s["mass_lost_fraction"], rel=1e-9
    )
    # the erosion splits into the caps clear of the neighbours and the corner rounding
    assert s["mass_caps_fraction"] >= 0.0 and s["mass_rounding_fraction"] > 0.0
    assert s["mass_caps_fraction"] + s["mass_rounding_fraction"] == pytest.approx(
        s["mass_eroded_fraction"], rel=1e-9
    )
    m0 = info["mean_initial_mass"]
    for ev in brk.events:
        # pieces dropped as fines count as fragments of the mean fines mass (metrics docstring)
        pieces = list(np.asarray(ev["fragment_masses"], float))
        if ev["n_fines"] > 0:
            pieces += [float(ev["fines_mass"]) / ev["n_fines"]] * int(ev["n_fines"])
        m_r = min(pieces) / m0
        want = "splitting" if m_r > 0.4 else "fragmentation" if m_r >= 0.1 else "chipping"
        assert metrics.event_breakage_type(ev, m0) == want
        assert np.asarray(ev["planes"]).shape[0] == 1  # split-cell: one plane
    assert len(s["ke_spikes"]) == s["n_events"]
    assert len(s["speed_spikes"]) == s["n_events"]
    q = s["quiet_speed"]
    assert 0 < q["n"] < len(load.series["time"]) and 0.0 <= q["fraction_above"] <= 1.0
    assert s["snapshot_times_s"][0] == 0.0 and len(s["snapshot_times_s"]) == 4
    rel = oc.relative_mass(load.series["time"], brk.events, info["initial_mass"])
    assert rel[-1] == pytest.approx(1.0 - s["mass_lost_fraction"])
    assert np.all(np.diff(rel) <= 0)
    # adaptive time step: never above safety x the limit of the lightest particle present
    from jaxgran.integrate import critical_time_step

    limit = critical_time_step(load.state.particles, load.params)
    assert s["dt_final_s"] <= cfg.dt_safety * limit * (1 + 1e-12)
    assert s["dt_final_s"] <= s["dt_s"]
    segment = cfg.record_every * cfg.records_per_segment * s["dt_s"]
    assert abs(s["load_time_s"] - cfg.load_time) <= segment


def _assert_same_particles(resumed, p):
    """A resumed run's particles are the uninterrupted run's, bit for bit; it steps at the
    vertex capacity its particles need but no lower than the configured start
    (fit_vertex_capacity), and the slots it dropped were padding."""
    for name in ("pos", "vel", "angle", "omega", "mass", "n_verts", "uid", "active"):
        np.testing.assert_array_equal(
            np.asarray(getattr(resumed, name)), np.asarray(getattr(p, name))
        )
    v = resumed.verts.shape[1]
    assert max(int(np.asarray(p.n_verts).max()), QUICK_SPLIT.vertex_capacity) <= v
    assert v <= p.verts.shape[1]
    np.testing.assert_array_equal(np.asarray(resumed.verts), np.asarray(p.verts)[:, :v])


def test_an_interrupted_oedometer_resumes_to_the_same_run(quick_split, tmp_path):
    (_, load, brk, info), _, saved, path, _ = quick_split
    n_final = len(brk.events)
    assert n_final >= 1 and len(saved) >= 3
    # the last checkpoint with a breakage still to come (so that the resumed run breaks)
    events_at = []
    for blob in saved:
        path.write_bytes(blob)
        ctx = io.load_checkpoint(path, oc.checkpoint_key(QUICK_SPLIT))["context"]
        events_at.append(len(ctx["brk"].events))
    pick = max(i for i, n in enumerate(events_at) if n < n_final)
    path.write_bytes(saved[pick])
    with compiles_of("run_segment") as compiled:
        settle2, load2, brk2, info2 = oc.simulate_test(
            QUICK_SPLIT, checkpoint=path, checkpoint_every_s=1e9, resume=True
        )
    # it keeps the uninterrupted run's shapes, so it steps with that run's compiled segment
    assert not compiled, compiled
    # CPU runs are deterministic: the resumed run is the uninterrupted one, bit for bit
    _assert_same_particles(load2.state.particles, load.state.particles)
    assert load2.steps == load.steps and load2.state.step == load.state.step
    for key, val in load.series.items():
        np.testing.assert_array_equal(load2.series[key], val)
    assert [e["time"] for e in brk2.events] == [e["time"] for e in brk.events]
    assert [e["parent_uid"] for e in brk2.events] == [e["parent_uid"] for e in brk.events]
    assert [s["t_load"] for s in info2["snapshots"]] == [s["t_load"] for s in info["snapshots"]]
    assert info2["dt_log"] == info["dt_log"]
    # a checkpoint of other settings is refused before anything runs
    other = dataclasses.replace(QUICK_SPLIT, seed=QUICK_SPLIT.seed + 1)
    with pytest.raises(ValueError, match="other settings"):
        oc.simulate_test(other, checkpoint=path, resume=True)
    # and a float64 checkpoint is not continued in float32
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(ValueError, match="written in float64"):
            oc.simulate_test(QUICK_SPLIT, checkpoint=path, resume=True)
    finally:
        jax.config.update("jax_enable_x64", True)


def test_a_run_forked_before_its_first_breakage_goes_on_as_the_run(quick_split, tmp_path):
    (_, load, brk, _), _, saved, _, _ = quick_split
    key = oc.checkpoint_key(QUICK_SPLIT)
    src = tmp_path / "source.pkl"
    n_events = []
    for blob in saved:
        src.write_bytes(blob)
        n_events.append(len(io.load_checkpoint(src, key)["context"]["brk"].events))
    assert 0 in n_events and n_events[-1] >= 1
    # the last checkpoint before the first breakage
    pick = max(i for i, n in enumerate(n_events) if n == 0)
    src.write_bytes(saved[pick])
    # a fresh handler at the fork (what another method gets) continues the run bit for bit:
    # before the first breakage the handler holds nothing the run depends on
    dst = tmp_path / "fork.pkl"
    origin = oc.fork_checkpoint(src, dst, QUICK_SPLIT, QUICK_SPLIT)
    assert origin["method"] == "split-cell" and origin["t_load"] > 0.0
    # `jaxgran progress` reads where a checkpoint stands
    got = oc.checkpoint_progress(src)
    assert got["method"] == "split-cell" and got["events"] == 0 and got["x64"]
    assert got["t_load_s"] == origin["t_load"] and 0 < got["done_fraction"] < 1
    assert got["load_time_s"] == QUICK_SPLIT.load_time and got["forked_from"] is None
    assert oc.checkpoint_progress(dst)["forked_from"] == origin
    from jaxgran.cli import main

    assert main(["progress", str(src)]) == 0
    assert main(["progress", str(tmp_path / "nowhere")]) == 1
    settle2, load2, brk2, info2 = oc.simulate_test(
        QUICK_SPLIT, checkpoint=dst, checkpoint_every_s=1e9, resume=True
    )
    _assert_same_particles(load2.state.particles, load.state.particles)
    assert [e["time"] for e in brk2.events] == [e["time"] for e in brk.events]
    assert [e["parent_uid"] for e in brk2.events] == [e["parent_uid"] for e in brk.events]
    assert info2["forked_from"] == origin
    # another method's run starts from the same state with its own handler
    mc = dataclasses.replace(QUICK_SPLIT, method="mohr-coulomb")
    oc.fork_checkpoint(src, dst, QUICK_SPLIT, mc)
    got = io.load_checkpoint(dst, oc.checkpoint_key(mc))
    assert method_name(got["context"]["brk"]) == "mohr-coulomb" and not got["context"]["brk"].events
    np.testing.assert_array_equal(
        np.asarray(got["simulate"]["state"].particles.pos),
        np.asarray(io.load_checkpoint(src, key)["simulate"]["state"].particles.pos),
    )
    # refused: a source that has broken grains, a configuration that differs otherwise
    src.write_bytes(saved[-1])
    with pytest.raises(ValueError, match="breakage events"):
        oc.fork_checkpoint(src, dst, QUICK_SPLIT, mc)
    with pytest.raises(ValueError, match="more than the method"):
        oc.fork_checkpoint(src, dst, QUICK_SPLIT, dataclasses.replace(mc, seed=1))


def test_compare_tallies_what_the_runs_did(quick_split, tmp_path):
    from jaxgran.compare import compare
    from jaxgran.scenes.base import write_outputs

    (settle, load, brk, info), _, _, _, _ = quick_split
    summary = oc.summarize(settle, load, brk, info, QUICK_SPLIT)
    run_dir = tmp_path / "split-cell"
    write_outputs(
        run_dir,
        oc.SCENE,
        QUICK_SPLIT,
        load,
        brk.params,
        summary,
        events=brk.events,
        figures=False,
    )
    markdown, rows, fig = compare([run_dir, run_dir])
    r = rows[0]
    assert r["n_events"] == len(brk.events) >= 1
    # each event takes its parent out and puts its fragments in
    n0 = int(np.asarray(settle.state.particles.active).sum())
    n1 = int(np.asarray(load.state.particles.active).sum())
    assert n1 - n0 == r["n_fragments"] - r["n_events"]
    # split-cell: one plane per event, counted at a and a + 180 deg in the polar histogram
    assert sum(r["plane_counts"]) == 2 * r["n_events"]
    assert r["finite"] is True and r["escaped"] is False
    assert r["ke_peak_max_J"] == max(s["peak"] for s in summary["ke_spikes"])
    # Table III types relative to the mean initial mass, as the scene classified them
    assert r["types_percent"] == summary["breakage_types"]["percent"]
    assert summary["mean_initial_mass_kg"] == info["mean_initial_mass"]
    # without the scene's percentages, compare classifies the events with the summary's mass
    import json
    import shutil

    recount = shutil.copytree(run_dir, tmp_path / "recount")
    saved = json.loads((recount / "summary.json").read_text())
    del saved["breakage_types"]
    (recount / "summary.json").write_text(json.dumps(saved))
    again = compare([recount])[1][0]["types_percent"]
    assert again == pytest.approx(r["types_percent"], abs=1e-12)
    assert rows[1] == rows[0]  # the analysis reads the files alone
    assert markdown.count("| split-cell | split-cell |") == 2
    # two rows of panels: patterns above, PSD and polar histograms below
    assert len(fig.axes) == 2 + 3


@pytest.mark.parametrize("floor", [-0.1, 1.5, float("nan")])
def test_oedometer_rejects_a_bad_fragment_radius_floor_before_settling(floor):
    with pytest.raises(ValueError, match="fragment_radius_floor"):
        oc.simulate_test(dataclasses.replace(oc.Config(), fragment_radius_floor=floor))


def test_settling_friction_is_set_for_the_settling_only():
    """``settle_friction`` replaces the Coulomb coefficient of grains and walls; nan keeps
    the contact friction (the loosely settled pile); a negative value is refused."""
    cfg = dataclasses.replace(oc.Config(), **oc.QUICK)
    _, params, _ = oc.build(cfg)
    dense = oc.settling_params(dataclasses.replace(cfg, settle_friction=0.1), params)
    assert np.all(np.asarray(dense.friction) == 0.1)
    assert np.all(np.asarray(dense.wall_friction) == 0.1)
    assert np.asarray(dense.wall_friction).shape == np.asarray(params.wall_friction).shape
    assert dense.normal_stiffness is params.normal_stiffness and dense.dt is params.dt
    loose = dataclasses.replace(cfg, settle_friction=math.nan)
    assert oc.settling_params(loose, params) is params
    with pytest.raises(ValueError, match="settle_friction"):
        dataclasses.replace(cfg, settle_friction=-0.1)
