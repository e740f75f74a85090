"""calibration.fit: an identical-twin fit (targets simulated with known K_n on the same
seed) converges to the known value by Adam on the forward-mode gradient, which equals the
reverse-mode one and the finite differences of the loss; the groups map
back to the micro-parameters; bad input fails with a message. Tiny disc (20 cells) loaded
past its peak with the smooth lab configuration (surrogate width 1, global damping instead
of the contact dashpot; see tests/test_labtests.py)."""

import numpy as np
import pytest

from calibration import fit
from jaxgran.state import replace

SCENE = {
    "n_cells": 20,
    "strain_rate": 80.0,
    "record_every": 25,
    "lab": {"max_strain": 0.05, "damping": 2.0e4, "contact_damping": 0.0},
}

TRUE = {"K_n": 1.3e8, "K_n/K_t": 1.0, "B_n": 2.0e10, "B_n/B_t": 1.0, "eps_th": 0.02, "mu": 0.3}


def test_groups_round_trip():
    z = fit.groups_from_values(TRUE)
    p = fit.parameters_from_groups(z)
    assert p["K_t"] == pytest.approx(1.3e8) and p["B_t"] == pytest.approx(2.0e10)
    lp = np.asarray(fit.groups_to_log_params(z))
    np.testing.assert_allclose(np.exp(lp), [1.3e8, 1.3e8, 2e10, 2e10, 0.02, 0.3], rtol=1e-12)


def test_twin_refuses_overlapping_seed_sets_and_unknown_methods(tmp_path, capsys):
    """The synthetic twin fits on seeds other than the truth's (else the sampling error it
    is about vanishes) and runs only the fits it knows."""
    from calibration import twin

    for argv in (
        ["--realisations", "4", "--truth-seeds-from", "2", "--fit-seeds-from", "0"],
        ["--methods", "newton"],
        ["--methods", ""],
    ):
        with pytest.raises(SystemExit) as exc:
            twin.main([*argv, "--out", str(tmp_path)])
        assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "overlap" in err and "--methods" in err


def test_common_time_step_is_the_smallest_over_every_seed_and_material():
    """The step that a twin's truth and fit share is the smallest default step over the
    materials and the specimens of all seeds (each seed's own step can be too long for
    another seed: a 256-specimen twin stopped on that). Building the specimens once and
    setting each material's bond moduli on them gives what each scene build gives."""
    from jaxgran import labtests as lt
    from jaxgran.scenes import bonded_brazilian as bz

    mats = [TRUE, TRUE | {"K_n": 1.0e8, "B_n/B_t": 2.0}]
    seeds = [0, 1, 2, 3, 4, 5]
    dt = fit.common_time_step("bonded-brazilian", SCENE, mats, seeds=seeds)
    cfg, _ = fit._scene_config("bonded-brazilian", SCENE)
    each = [
        float(
            bz.build(
                lt.material_with(cfg, fit.groups_to_log_params(fit.groups_from_values(m))),
                seeds=[s],
            ).params.dt
        )
        for m in mats
        for s in seeds
    ]
    assert dt == pytest.approx(min(each), rel=1e-12)
    assert dt < max(each)  # the specimens differ: not every seed's step would do
    with pytest.raises(ValueError, match="at least one seed"):
        fit.common_time_step("bonded-brazilian", SCENE, mats, seeds=[])


def test_bad_targets_are_refused():
    with pytest.raises(ValueError, match="unknown target"):
        fit.parse_targets({"strength": {"value": 1.0, "uncertainty": 0.1}})
    with pytest.raises(ValueError, match="needs the mean stress"):
        fit.parse_targets({"q_peak": [{"value": 1.0, "uncertainty": 0.1}]})
    for entry, message in [
        ({"value": -1.0, "uncertainty": 0.1}, "value must be > 0"),
        ({"value": 1.0, "uncertainty": 0.0}, "uncertainty must be > 0"),
        ({"value": 1.0, "sigma": 0.1}, r"unknown key\(s\) \['sigma'\]"),
        ({"value": "1e8", "uncertainty": 0.1}, "value must be a finite number"),
        ({"value": float("nan"), "uncertainty": 0.1}, "value must be a finite number"),
    ]:
        with pytest.raises(ValueError, match=message):
            fit.parse_targets({"sigma_t": entry})
    assert fit.parse_targets({"nu": {"value": -0.1, "uncertainty": 0.1}})[0].value == -0.1


def test_a_bad_spec_is_refused_before_anything_is_built(tmp_path, capsys):
    """Every part of a spec is checked up front (seconds, not the minutes of building and
    compiling the labs), and the script says what is wrong instead of a traceback."""
    good = {"targets": {"sigma_t": {"value": 1.0e8, "uncertainty": 1.0e6}}}
    assert fit.check_spec(good, ["bonded-brazilian"], 2)[0].name == "sigma_t"
    bad = [
        ({"targts": {}}, r"unknown key\(s\) \['targts'\]"),
        ({"initial": {"K_n": -1.0}}, "K_n must be > 0"),
        ({"initial": {"K_n": 1.0e8}}, "initial values missing"),
        ({"free": ["K_t"]}, "unknown free groups"),
        ({"seeds": [0, -1]}, "non-negative integers"),
        ({"seeds": [0]}, "2 realisations asked but only 1 seeds"),
        ({"surrogate_width": -1.0}, "surrogate_width must be >= 0"),
        ({"bonded-brazilian": {"n_cells": 1}}, "setting n_cells=1 is refused"),
        ({"bonded-brazilian": {"ncells": 30}}, "unexpected keyword argument 'ncells'"),
        ({"bonded-brazilian": {"lab": {"dampng": 1.0}}}, r"unknown option\(s\) \['dampng'\]"),
        ({"adam": {"steps": 0}}, "steps must be > 0"),
        ({"adam": {"gradient": "sideways"}}, "gradient must be one of"),
    ]
    for change, message in bad:
        with pytest.raises(ValueError, match=message):
            fit.check_spec(good | change, ["bonded-brazilian"], 2)
    path = tmp_path / "targets.json"
    path.write_text('{"targets": {"sigma_t": {"value": 1e8}}}')
    args = ["--targets", str(path), "--scene", "bonded-brazilian", "--out", str(tmp_path)]
    assert fit.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "'uncertainty' is missing" in err
    path.write_text("not json")
    assert fit.main(args) == 2
    assert "Expecting value" in capsys.readouterr().err


@pytest.fixture(scope="module")
def identical_twin():
    """The problem that starts 23 % low in K_n on seed 3, with targets sigma_t and S
    simulated by its own lab at the true K_n = 1.3e8 (1 % uncertainties): truth and fit
    share the lab (specimen, time step, smooth-max width), so the truth is an exact zero of
    the loss, and they share its compiled figures (targets are not part of them)."""
    spec = {
        "targets": {
            "sigma_t": {"value": 1.0, "uncertainty": 1.0},
            "slope_S": {"value": 1.0, "uncertainty": 1.0},
        },
        "initial": TRUE | {"K_n": 1.0e8},  # 23 % low
        "free": ["K_n"],
        "surrogate_width": 1.0,
        "bonded-brazilian": SCENE,
    }
    # one time step for truth and fit (the default one depends on K_n)
    dt = fit.common_time_step("bonded-brazilian", SCENE, [TRUE, spec["initial"]], seeds=[3])
    spec["bonded-brazilian"] = SCENE | {"lab": SCENE["lab"] | {"dt": dt}}
    problem = fit.make_problem(spec, ["bonded-brazilian"], 1, seeds=[3], peak_from_targets=False)
    _, fwd = fit.make_functions(problem)
    _, (vals, _) = fwd(fit.groups_from_values(TRUE)[problem.free])
    target = np.asarray(vals).mean(axis=1)
    problem.targets = fit.parse_targets(
        {
            name: {"value": float(v), "uncertainty": 0.01 * float(v)}
            for name, v in zip(("sigma_t", "slope_S"), target, strict=True)
        }
    )
    return problem


def _k_n(problem, res):
    return fit.parameters_from_groups(np.asarray(problem.full(res["x"])))["K_n"]


def test_forward_and_reverse_gradients_agree_with_finite_differences(identical_twin):
    """The loss's gradient at the start by forward mode (Adam's default) and by reverse mode
    through the whole lab: the two are the same derivative, so they agree to round-off, and
    both match central differences of the loss. The step is 1e-6 in log K_n: the run sits
    near an event that the surrogate does not smooth (a step of +1e-4 crosses it and moves
    the central difference by 2.9 %), while steps of 1e-6 and 1e-5 give the derivative to
    1e-9 and 7e-6 (2026-12-06)."""
    problem = identical_twin
    x = np.asarray(problem.z0[problem.free])
    (val_f, (vals_f, _)), g_f = fit.make_functions(problem, "forward")[0](x)
    (val_r, (vals_r, _)), g_r = fit.make_functions(problem, "reverse")[0](x)
    assert float(val_f) == pytest.approx(float(val_r), rel=1e-12)
    np.testing.assert_allclose(np.asarray(vals_f), np.asarray(vals_r), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(g_f), np.asarray(g_r), rtol=1e-8)
    _, loss = fit.make_functions(problem)
    h = 1.0e-6
    fd = (float(loss(x + h)[0]) - float(loss(x - h)[0])) / (2 * h)
    assert abs(float(g_f[0])) > 100.0  # 23 % low in K_n: a steep loss, not a flat one
    assert float(g_f[0]) == pytest.approx(fd, rel=1e-4)
    with pytest.raises(ValueError, match="gradient must be one of"):
        fit.make_functions(problem, "sideways")


def test_identical_twin_recovers_normal_stiffness(identical_twin):
    problem = identical_twin
    # stop once the misfit is a third of the targets' uncertainty (loss = mean squared
    # z-score < 0.1); Adam's momentum carries it past the optimum otherwise, and it would
    # spend the remaining steps coming back
    res = fit.adam(problem, learning_rate=0.06, steps=20, tol=0.1, log=lambda *_: None)
    assert res["gradient"] == "forward"  # the default
    assert res["loss"] < 0.1 and res["simulations"] < 20
    assert res["history"]["loss"][0] > 100 * res["loss"]
    # sigma_t and S move by ~0.7 % per % of K_n, so the 1 % target uncertainties resolve K_n
    # to ~1 % (1 sigma); the fit must land within 2 sigma of the truth
    assert _k_n(problem, res) == pytest.approx(1.3e8, rel=0.02)


def test_gauss_newton_recovers_normal_stiffness_in_a_few_jacobians(identical_twin, compile_log):
    """Levenberg-Marquardt on the forward-mode Jacobian: the same twin, with the truth an
    exact zero of the residuals (same seed), so the fit must reach it to well below the
    1 % resolution and its loss must fall quadratically (each step removes most of it)."""
    problem = identical_twin
    # Adam's forward gradient (the tests above), this fit and the uncertainty share one
    # compiled Jacobian of the problem: compiled by now, it is not compiled again
    fit.mean_jacobian(problem, np.asarray(problem.z0[problem.free]))
    compile_log.clear()
    res = fit.gauss_newton(problem, iterations=6, tol=1e-2, log=lambda *_: None)
    fit.uncertainty(problem, res["x"])
    # nothing compiled but a few small host-to-device conversions (milliseconds each)
    assert not [c for c in compile_log if c[1] > 0.2 or "cache hit" in c[0]], compile_log
    losses = res["history"]["loss"]
    assert res["simulations"] <= 6 and res["loss"] < 1e-2
    assert losses[1] < 0.1 * losses[0]
    assert _k_n(problem, res) == pytest.approx(1.3e8, rel=2e-3)
    jac = fit._program(problem, "jacobian")
    # a changed lab gets a program of its own (the old one would run the old lab)
    lab = problem.labs["bonded-brazilian"]
    problem.labs["bonded-brazilian"] = replace(lab, peak_width=lab.peak_width)
    try:
        assert fit._program(problem, "jacobian") is not jac
    finally:
        problem.labs["bonded-brazilian"] = lab


def test_a_ucs_target_needs_a_peak_before_max_strain():
    """An unconfined test stopped before the peak has no strength to fit."""
    spec = {
        "targets": {"ucs": {"value": 3.0e8, "uncertainty": 1.0e7}},
        "initial": TRUE,
        "free": ["K_n"],
        "bonded-biaxial": {"n_cells": 20, "strain_rate": 80.0, "max_strain": 0.004},
    }
    with pytest.raises(ValueError, match="still rises at max_strain"):
        fit.make_problem(spec, ["bonded-biaxial"], 1, seeds=[0])
