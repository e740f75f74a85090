"""Scene settings are checked when a configuration is made (jaxgran.scenes.limits): every
setting of every scene has a rule, each rule refuses the values just outside it and accepts
its closed ends, relations between settings are enforced, and the command line reports a
refused value as an error, not a traceback. No JAX compilation: these run in milliseconds."""

import dataclasses
import math

import pytest

from jaxgran.cli import main
from jaxgran.scenes import SCENES
from jaxgran.scenes import deposit as dp
from jaxgran.scenes import interface_tension as it
from jaxgran.scenes import oedometer_cantor as oc
from jaxgran.scenes.limits import OneOf, Range, describe_settings, rule_for

CONFIGS = {name: mod.Config for name, mod in SCENES.items()}


def _ruled_fields(cls):
    cfg = cls()
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if not isinstance(value, bool):
            yield f.name, value, rule_for(cfg, f.name)


def _outside(rule: Range, value):
    """Values just outside ``rule`` (in the type of the setting's default)."""
    out = []
    if math.isfinite(rule.low):
        out.append(rule.low - 1 if rule.integer else rule.low - max(1.0, abs(rule.low)))
        if rule.low_open:
            out.append(rule.low if rule.integer else float(rule.low))
    if math.isfinite(rule.high):
        out.append(rule.high + 1 if rule.integer else rule.high + max(1.0, abs(rule.high)))
        if rule.high_open:
            out.append(float(rule.high))
    if not rule.nan and not rule.integer:
        out.append(math.nan)
    if rule.integer:
        out.append(float(max(rule.low, 0)) + 2.5)  # not an integer
    if isinstance(value, tuple):
        return [(v,) for v in out]
    return out


def _closed_ends(rule: Range, value):
    pairs = ((rule.low, rule.low_open), (rule.high, rule.high_open))
    ends = [int(e) if rule.integer else float(e) for e, o in pairs if not o and math.isfinite(e)]
    return [(e,) for e in ends] if isinstance(value, tuple) else ends


@pytest.mark.parametrize("scene", sorted(CONFIGS))
def test_every_setting_has_a_rule_and_the_defaults_pass(scene):
    cls = CONFIGS[scene]
    missing = [name for name, _, rule in _ruled_fields(cls) if rule is None]
    assert not missing, f"{scene}: settings without a rule: {missing}"
    quick = dataclasses.replace(cls(), **SCENES[scene].QUICK)  # QUICK passes too
    assert dataclasses.asdict(quick)


@pytest.mark.parametrize("scene", sorted(CONFIGS))
def test_each_rule_refuses_values_just_outside_and_names_the_setting(scene):
    cls = CONFIGS[scene]
    checked = 0
    for name, value, rule in _ruled_fields(cls):
        bad = _outside(rule, value) if isinstance(rule, Range) else ["no-such-choice", 3]
        if isinstance(rule, OneOf) and rule.many:
            bad.append(f"{value},no-such-choice")
        for v in bad:
            with pytest.raises(ValueError, match=f"setting {name}="):
                dataclasses.replace(cls(), **{name: v})
            checked += 1
    assert checked >= 2 * len(dataclasses.fields(cls)) - 20  # most settings, several values


@pytest.mark.parametrize("scene", sorted(CONFIGS))
def test_each_range_accepts_its_closed_ends(scene):
    cls = CONFIGS[scene]
    for name, value, rule in _ruled_fields(cls):
        if isinstance(rule, Range):
            for v in _closed_ends(rule, value):
                assert getattr(dataclasses.replace(cls(), **{name: v}), name) == v


def test_relations_between_settings():
    with pytest.raises(ValueError, match="min_diameter must be below max_diameter"):
        dp.Config(min_diameter=0.03, max_diameter=0.02)
    with pytest.raises(ValueError, match="min_time must be below max_time"):
        dp.Config(min_time=2.0, max_time=1.0)
    with pytest.raises(ValueError, match="d_min must not exceed d_max"):
        it.Config(d_min=6e-3)
    assert it.Config(d_min=5e-3, d_max=5e-3).d_min == 5e-3  # equal sizes: monodisperse


def test_a_list_setting_is_checked_entry_by_entry():
    from jaxgran.scenes import bonded_biaxial as bx

    assert bx.Config(p_values=(50e6, 1e8)).p_values == (50e6, 1e8)
    with pytest.raises(ValueError, match=r"p_values=\(50000000.0, -1.0\) is refused: every entry"):
        bx.Config(p_values=(50e6, -1.0))
    # a list, as a configuration read from JSON gives it, is the same setting as a tuple
    from_json = oc.Config(snapshot_times=[0.0, 0.5])
    assert from_json.snapshot_times == (0.0, 0.5)
    assert from_json == oc.Config(snapshot_times=(0.0, 0.5))
    hash(from_json)  # still usable as a static (hashed) configuration
    with pytest.raises(ValueError, match=r"snapshot_times=\(0.0, -1.0\) is refused: every entry"):
        oc.Config(snapshot_times=[0.0, -1.0])


@pytest.mark.parametrize(
    "scene, setting, message",
    [
        ("oedometer-cantor", "load_time=-1", "load_time=-1.0 is refused: it must be a number > 0"),
        ("bonded-brazilian", "strain_rate=0", "strain_rate=0.0 is refused"),
        ("bonded-brazilian", "n_cells=1", "n_cells=1 is refused: it must be an integer >= 2"),
        ("bonded-biaxial", "p_values=-5e6", "p_values=(-5000000.0,) is refused"),
        ("interface-compression", "confinements=-1", "confinements=(-1.0,) is refused"),
        ("brazilian-dsm", "plane=strian", "it must be one of stress, strain"),
        ("deposit", "restitution=0", "restitution=0.0 is refused: it must be a number in (0, 1]"),
    ],
)
def test_the_command_line_reports_a_refused_value(capsys, scene, setting, message):
    assert main(["run", scene, "--no-progress", "--set", setting]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: setting ") and message in err
    assert "Traceback" not in err


@pytest.mark.parametrize("scene", sorted(CONFIGS))
def test_settings_are_described_with_their_rule_and_comment(scene):
    cls = CONFIGS[scene]
    rows = describe_settings(cls)
    assert [r["name"] for r in rows] == [f.name for f in dataclasses.fields(cls)]
    assert all(r["allowed"] for r in rows)
    # every setting says what it is (units, meaning): a comment in the source or MEANINGS
    assert [r["name"] for r in rows if not r["meaning"]] == []


def test_comments_are_read_from_the_line_and_the_lines_above():
    rows = {r["name"]: r for r in describe_settings(oc.Config)}
    assert rows["normal_stiffness"]["meaning"] == "N/m, Table I"
    assert rows["sphero_radius"]["meaning"].startswith("m; paper 000 does not give it.")
    assert rows["snapshot_times"]["allowed"] == "a list, each a number >= 0"
    assert rows["conserve_mass"]["allowed"] == "true or false"
    inherited = {r["name"]: r for r in describe_settings(it.Config)}
    assert inherited["d_min"]["meaning"] == "m, smallest elementary disc diameter"  # from Common


def test_the_settings_command_lists_a_scene(capsys):
    assert main(["settings", "deposit"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("normal_stiffness "))
    assert "600000.0" in line and "a number > 0" in line and "N/m, Table I" in line
    assert main(["settings", "no-such-scene"]) == 2
