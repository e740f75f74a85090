"""The `jaxgran` command end to end on a small deposit: outputs exist and reopen."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from jaxgran import io
from jaxgran.cli import main


@pytest.fixture(scope="module")
def deposit_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("deposit")
    code = main(
        [
            "run",
            "deposit",
            "--quick",
            "--no-progress",
            "--out",
            str(out),
            "--set",
            "n_cells=30",
            "--set",
            "max_time=0.6",
            "--set",
            "box_width=0.12",
        ]
    )
    assert code == 0
    return out


def test_deposit_writes_summary_h5_and_figures(deposit_run):
    summary = json.loads((deposit_run / "summary.json").read_text())
    for key in (
        "n_particles",
        "steps",
        "wall_time_s",
        "final_kinetic_energy_J",
        "packing_fraction",
        "bottom_reaction_over_weight",
    ):
        assert key in summary
    assert summary["n_particles"] > 10
    assert 0.3 < summary["packing_fraction"] < 1.0
    # walls are frictional in the deposit, so the floor carries most but not all the weight
    assert 0.8 < summary["bottom_reaction_over_weight"] < 1.05
    for png in ("packing.png", "kinetic_energy.png"):
        assert (deposit_run / png).stat().st_size > 1000
    run = io.read_run(deposit_run / "run.h5")
    assert run["frames"]["pos"].shape[0] >= 2
    assert np.all(np.isfinite(run["series"]["kinetic_energy"]))
    assert run["metadata"]["scene"] == "deposit"


def test_plot_command_redraws(deposit_run, tmp_path):
    assert main(["plot", str(deposit_run / "run.h5"), "--out", str(tmp_path)]) == 0
    assert (tmp_path / "packing.png").exists()
    # another record file of a run (run_sigma3_5MPa.h5 beside run.h5) draws into a folder
    # named after it, leaving the figures beside it alone
    other = tmp_path / "run_sigma3_5MPa.h5"
    other.write_bytes((deposit_run / "run.h5").read_bytes())
    before = (tmp_path / "packing.png").stat().st_mtime_ns
    assert main(["plot", str(other)]) == 0
    assert (tmp_path / "run_sigma3_5MPa" / "packing.png").exists()
    assert (tmp_path / "packing.png").stat().st_mtime_ns == before


def test_bad_setting_is_refused(capsys, tmp_path):
    assert main(["run", "deposit", "--set", "no_such_key=1"]) == 2
    assert "valid settings" in capsys.readouterr().err
    assert main(["run", "no-such-scene"]) == 2
    not_a_run = tmp_path / "notes.h5"
    not_a_run.write_text("not HDF5")
    capsys.readouterr()
    assert main(["plot", str(not_a_run)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "is not an HDF5 file" in err


def test_a_scene_that_cannot_be_built_is_one_error_line(capsys, tmp_path, monkeypatch):
    """Settings every rule accepts but no scene can be built from (two cells: none within
    the circumdiameter range) end as an ``error:`` line and exit code 2 before anything is
    compiled; any other ValueError is an internal error and keeps its traceback."""
    out = tmp_path / "dep"
    assert main(["run", "deposit", "--quick", "--set", "n_cells=2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no Voronoi cell within the circumdiameter range")
    assert not (out / "summary.json").exists()
    from jaxgran.scenes import SCENES

    def broken(*args, **kwargs):
        raise ValueError("an internal fault")

    monkeypatch.setattr(SCENES["deposit"], "run", broken)
    with pytest.raises(ValueError, match="an internal fault"):
        main(["run", "deposit", "--quick", "--out", str(out)])


def test_resume_is_refused_where_a_scene_has_no_checkpoints(capsys):
    assert main(["run", "deposit", "--resume"]) == 2
    assert "no checkpoints" in capsys.readouterr().err
    # a negative interval is refused before the (long) oedometer builds anything
    assert main(["run", "oedometer-voronoi", "--checkpoint-minutes", "-1"]) == 2
    assert "checkpoint_minutes" in capsys.readouterr().err


def test_a_finished_run_is_recognised_by_its_configuration(deposit_run):
    """``--resume`` skips a long run that already finished in its folder, and only one with
    the same scene and configuration (here the deposit's summary, written as every scene
    writes it)."""
    import dataclasses

    from jaxgran.scenes import deposit as dp
    from jaxgran.scenes.base import finished_summary

    summary = json.loads((deposit_run / "summary.json").read_text())
    cfg = dp.Config(**{**dataclasses.asdict(dp.Config()), **summary["config"]})
    assert finished_summary(deposit_run, "deposit", cfg) == summary
    assert (
        finished_summary(deposit_run, "deposit", dataclasses.replace(cfg, seed=cfg.seed + 1))
        is None
    )
    assert finished_summary(deposit_run, "oedometer-voronoi", cfg) is None
    assert finished_summary(deposit_run / "nowhere", "deposit", cfg) is None


def test_oedometer_summaries_carry_the_cli_name_and_older_ones_still_match(tmp_path):
    """Every scene's summary names it as ``jaxgran run`` does; summaries written before
    2026-12-06 named the oedometers by module (``oedometer_cantor``) and still count."""
    import dataclasses

    from jaxgran.scenes import SCENES
    from jaxgran.scenes import oedometer_cantor as oc
    from jaxgran.scenes import oedometer_voronoi as ov
    from jaxgran.scenes.base import finished_summary

    assert SCENES[oc.SCENE] is oc and SCENES[ov.SCENE] is ov
    cfg = oc.Config()
    old = {"scene": "oedometer_cantor", "config": dataclasses.asdict(cfg)}
    (tmp_path / "summary.json").write_text(json.dumps(old, default=float))
    found = finished_summary(tmp_path, oc.SCENE, cfg)
    assert found is not None and found["scene"] == "oedometer_cantor"
    assert finished_summary(tmp_path, ov.SCENE, cfg) is None


def test_a_finished_runs_figures_are_found_after_the_folder_moved(
    deposit_run, tmp_path, monkeypatch
):
    """A finished run read from another working directory, or after its folder moved,
    names figures that exist there (its summary stored them relative to where it ran)."""
    import dataclasses
    import shutil

    from jaxgran.scenes import deposit as dp
    from jaxgran.scenes.base import finished_summary

    moved = tmp_path / "elsewhere" / "run"
    shutil.copytree(deposit_run, moved)
    summary = json.loads((moved / "summary.json").read_text())
    summary["figures"] = [f"runs/old_place/{Path(f).name}" for f in summary["figures"]]
    (moved / "summary.json").write_text(json.dumps(summary))
    monkeypatch.chdir(tmp_path)
    cfg = dp.Config(**{**dataclasses.asdict(dp.Config()), **summary["config"]})
    found = finished_summary(Path("elsewhere/run"), "deposit", cfg)["figures"]
    assert len(found) == len(summary["figures"]) >= 1
    assert all(Path(f).is_file() and Path(f).parent == Path("elsewhere/run") for f in found)


def test_list_settings_take_any_number_of_values():
    """A list setting (confinements, snapshot times) is read with any number of values of its
    element type, brackets optional; a value of the wrong type is an error naming it."""
    from jaxgran.scenes import interface_compression as ic
    from jaxgran.scenes.base import apply_overrides

    cfg = apply_overrides(ic.Config(), {"confinements": "10e6"})
    assert cfg.confinements == (10.0e6,)
    cfg = apply_overrides(ic.Config(), {"confinements": "(2e6, 40e6, 80e6)"})
    assert cfg.confinements == (2.0e6, 40.0e6, 80.0e6)
    for bad in ("2e6,x", "", "()"):
        with pytest.raises(ValueError, match=f"confinements='{re.escape(bad)}'"):
            apply_overrides(ic.Config(), {"confinements": bad})


def test_a_run_is_repeated_from_its_summary(deposit_run, tmp_path, capsys):
    """``--config summary.json`` gives back the configuration of that run (every scene's, as
    its summary stores it), ``--set`` applies on top of it, and a file that is not JSON or
    the summary of another scene is refused before anything is built."""
    import dataclasses

    from jaxgran.scenes import SCENES
    from jaxgran.scenes import deposit as dp
    from jaxgran.scenes import oedometer_cantor as oc
    from jaxgran.scenes.base import apply_overrides, read_config_file, unrecorded_settings

    summary = deposit_run / "summary.json"
    cfg = apply_overrides(dp.Config(), read_config_file(summary, "deposit"))
    assert (cfg.n_cells, cfg.box_width, cfg.max_time) == (30, 0.12, 0.6)  # the run's --set
    assert cfg.normal_stiffness == dp.QUICK["normal_stiffness"]  # and its --quick
    for name, mod in SCENES.items():  # a summary's config (tuples, inf, nan) round-trips
        quick = dataclasses.replace(mod.Config(), **mod.QUICK)
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"scene": name, "config": dataclasses.asdict(quick)}))
        back = apply_overrides(mod.Config(), read_config_file(path, name))
        assert json.dumps(dataclasses.asdict(back)) == json.dumps(dataclasses.asdict(quick))
    # the file's max_time (0.6 s) is in force: min_time = 0.7 s on top breaks min < max
    assert main(["run", "deposit", "--config", str(summary), "--set", "min_time=0.7"]) == 2
    assert "min_time=0.7 and max_time=0.6" in capsys.readouterr().err
    assert main(["run", "oedometer-cantor", "--config", str(summary)]) == 2
    assert "summary of a 'deposit' run" in capsys.readouterr().err
    # the oedometer scenes and brazilian-dsm store the module's name in their summaries
    (tmp_path / "cantor.json").write_text(
        json.dumps({"scene": "oedometer_cantor", "config": {"seed": 4}})
    )
    assert read_config_file(tmp_path / "cantor.json", "oedometer-cantor") == {"seed": 4}
    # a summary from before a setting existed: the setting's value now is named on stderr
    # (here every setting but seed; the run then stops on the unknown --set)
    assert main(["run", "oedometer-cantor", "--config", str(tmp_path / "cantor.json"),
                 "--set", "no_such_setting=1"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "does not record" in err and "settle_friction=0.0" in err and "seed=" not in err
    assert "unknown setting 'no_such_setting'" in err
    assert (
        unrecorded_settings(tmp_path / "cantor.json", oc.Config(), {"seed": 4})["load_time"]
        == oc.Config().load_time
    )
    full = dataclasses.asdict(oc.Config())
    assert unrecorded_settings(tmp_path / "cantor.json", oc.Config(), full) == {}
    (tmp_path / "plain.json").write_text(json.dumps({"seed": 4}))  # not a summary: no gaps
    assert unrecorded_settings(tmp_path / "plain.json", oc.Config(), {"seed": 4}) == {}
    (tmp_path / "bad.json").write_text("{not json")
    assert main(["run", "deposit", "--config", str(tmp_path / "bad.json")]) == 2
    assert "is not JSON" in capsys.readouterr().err


def test_compare_names_the_file_a_run_folder_lacks(tmp_path, capsys):
    """``jaxgran compare`` reads each run's summary.json and its events from run.h5: a folder
    without either is one ``error:`` line naming the file (the stored benchmark folders keep
    summary.json and figures but not run.h5)."""
    only_summary = tmp_path / "summary_only"
    only_summary.mkdir()
    (only_summary / "summary.json").write_text(json.dumps({"scene": "oedometer-cantor"}))
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["compare", str(only_summary), "--out", str(tmp_path / "cmp")]) == 2
    assert f"error: no run.h5 in {only_summary}" in capsys.readouterr().err
    assert main(["compare", str(empty), str(only_summary)]) == 2
    assert f"error: no summary.json in {empty}" in capsys.readouterr().err
    assert not (tmp_path / "cmp").exists()


def test_progress_of_a_file_that_is_not_a_checkpoint_is_one_error_line(tmp_path, capsys):
    """A truncated or foreign file given to ``jaxgran progress`` is named, not unpickled
    into a traceback or an unrelated message."""
    import pickle

    bad = tmp_path / "checkpoint.pkl"
    bad.write_bytes(b"garbage\n")
    assert main(["progress", str(bad)]) == 2
    assert "not a jaxgran checkpoint (it cannot be unpickled" in capsys.readouterr().err
    half = tmp_path / "half.pkl"
    half.write_bytes(pickle.dumps({"format": 0, "key": 1, "payload": list(range(100))})[:40])
    assert main(["progress", str(half)]) == 2
    assert "not a jaxgran checkpoint" in capsys.readouterr().err
    other = tmp_path / "other.pkl"
    other.write_bytes(pickle.dumps({"format": -1}))
    assert main(["progress", str(other)]) == 2
    assert "not a jaxgran checkpoint of format" in capsys.readouterr().err
