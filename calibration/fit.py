"""Fit bonded-Voronoi micro-parameters to measured macro-properties by gradient.

    python -m calibration.fit --targets targets.json --scene bonded-brazilian \\
        [--scene bonded-biaxial] --realisations K [--out calibration_out] [--baseline]

``targets.json`` (see ``calibration/targets_example.json``)::

    {
      "targets": {                                   # measured figures, uncertainty = 1 sigma
        "sigma_t": {"value": 1.1e8, "uncertainty": 5e6},          # Pa, Brazilian Eq. 16
        "slope_S": {"value": 4.8e8, "uncertainty": 3e7},          # Pa, Brazilian Eq. 17
        "E_c":     {"value": 3.0e10, "uncertainty": 1.5e9},       # Pa, unconfined Eq. 24
        "nu":      {"value": 0.05, "uncertainty": 0.01},          # -, unconfined Eq. 25
        "q_peak":  [{"p": 3e8, "value": 3.8e8, "uncertainty": 2e7}]  # Pa at p (Pa)
      },
      "initial": {"K_n": 1e8, "K_n/K_t": 1, "B_n": 2e10, "B_n/B_t": 1, "eps_th": 0.02, "mu": 0.3},
      "free": ["K_n", "B_n/B_t", "eps_th"],
      "seeds": [0, 1],                        # optional (default 0 .. K-1)
      "bonded-brazilian": {"n_cells": 30, "lab": {"max_strain": 0.045}},   # scene overrides
      "bonded-biaxial": {"n_cells": 30, "lab": {"fit_strains": [0.002, 0.008]}},
      "adam": {"learning_rate": 0.05, "steps": 60}     # optional "gradient": "reverse"
    }

**Parameters** are optimised in log space in the dimensionless groups of paper 002
(Eq. 18-19): ``z = log [K_n, K_n/K_t, B_n, B_n/B_t, eps_th, mu]`` (:data:`GROUPS`), so the
stiffness ratios and the strength threshold move independently of the stiffness level;
``free`` names the groups that move, the others stay at ``initial``. Every free group is
kept within a factor :data:`BOUND` of its initial value (the labs' time step stays stable
for stiffnesses up to 4x the initial ones, :mod:`jaxgran.labtests`).

**Loss**: ``L = mean_f ((m_f - t_f) / u_f)^2``, the weighted relative misfit of the ensemble
means ``m_f`` (mean over the K realisations) against the targets ``t_f`` with uncertainties
``u_f`` (equal to ``((m_f / t_f - 1) / (u_f / t_f))^2``: relative misfit over relative
uncertainty). Gradients come from automatic differentiation through the whole lab tests
(:func:`jaxgran.labtests.figures`), optimised with optax Adam: by default in forward mode
(one run that carries one tangent per free group), or in reverse mode with ``--gradient
reverse`` (:data:`GRADIENTS`, :func:`make_functions`); with ``--gauss-newton``
also by Levenberg-Marquardt on the Jacobian from forward mode (:func:`gauss_newton`, a few
Jacobian evaluations instead of tens of gradient steps when there are few free groups); a
gradient-free baseline (scipy Nelder-Mead on the same loss, :func:`nelder_mead`) runs with
``--baseline``.

**Uncertainty** of the fitted groups: with the Jacobian ``J = d m / d z`` at the optimum
and per-figure variances ``s_f^2 = u_f^2 + sd_f^2 / K`` (target uncertainty plus the
sampling error of the ensemble mean, ``sd_f`` the spread over the realisations), the
covariance is ``(J^T W J)^-1`` with ``W = diag(1 / s_f^2)``; the part due to the ensemble
alone (``u_f = 0``) is reported too. Standard deviations of ``log`` groups are relative
uncertainties.

Outputs in ``--out``: ``fit.json`` (fitted parameters and groups, uncertainties, history,
simulations and wall time, final simulated-vs-target table), ``convergence.png``
(:func:`calibration.plots.plot_convergence`), and the table printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

GROUPS = ("K_n", "K_n/K_t", "B_n", "B_n/B_t", "eps_th", "mu")
"""Optimisation variables (log of each), paper 002's dimensionless groups plus K_n, B_n."""

BOUND = 3.0
"""Each free group stays within [initial / BOUND, initial x BOUND]."""

SCENES = ("bonded-brazilian", "bonded-biaxial")
FIGURE_SCENE = {
    "sigma_t": "bonded-brazilian",
    "slope_S": "bonded-brazilian",
    "E_c": "bonded-biaxial",
    "nu": "bonded-biaxial",
    "ucs": "bonded-biaxial",
    "q_peak": "bonded-biaxial",
}


# ------------------------------------------------------------------------------ groups


def groups_to_log_params(z):
    """``log [K_n, K_t, B_n, B_t, eps_th, mu]`` (:data:`jaxgran.labtests.PARAMETERS`) from
    the log groups ``z`` (:data:`GROUPS`); works on numpy and jax arrays."""
    import jax.numpy as jnp

    z = jnp.asarray(z)
    return jnp.stack([z[0], z[0] - z[1], z[2], z[2] - z[3], z[4], z[5]])


def groups_from_values(values: dict) -> np.ndarray:
    """Log groups from a dict of group values (keys of :data:`GROUPS`)."""
    missing = [g for g in GROUPS if g not in values]
    if missing:
        raise ValueError(f"initial values missing for {missing}; give all of {list(GROUPS)}")
    return np.log(np.array([float(values[g]) for g in GROUPS]))


def parameters_from_groups(z) -> dict[str, float]:
    """Physical micro-parameters (K_n, K_t in N/m; B_n, B_t in Pa; eps_th, mu) and the
    groups, from log groups ``z``."""
    v = np.exp(np.asarray(z, float))
    return {
        "K_n": v[0],
        "K_t": v[0] / v[1],
        "B_n": v[2],
        "B_t": v[2] / v[3],
        "eps_th": v[4],
        "mu": v[5],
        "K_n/K_t": v[1],
        "B_n/B_t": v[3],
    }


# ------------------------------------------------------------------------------ problem


@dataclasses.dataclass
class Target:
    """One measured figure: ``name`` (:data:`FIGURE_SCENE`), value and 1-sigma uncertainty
    (Pa, or - for nu), and for q_peak the mean stress ``p`` (Pa)."""

    name: str
    value: float
    uncertainty: float
    p: float | None = None

    @property
    def label(self) -> str:
        return self.name if self.p is None else f"{self.name}@p={self.p:.4g}"


def _number(where: str, entry: dict, key: str, positive: bool = False) -> float:
    if key not in entry:
        raise ValueError(f"{where}: {key!r} is missing")
    v = entry[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{where}: {key} must be a finite number, got {v!r}")
    if positive and not v > 0:
        raise ValueError(f"{where}: {key} must be > 0, got {v!r}")
    return float(v)


def parse_targets(spec: dict) -> list[Target]:
    """Targets from the ``targets`` object of a spec (module docstring): per figure one
    ``{"value", "uncertainty"}`` entry, or for q_peak a list of them with ``p`` (Pa).
    Values are finite, uncertainties and p > 0, every figure but nu > 0 (by definition);
    ValueError names the entry otherwise."""
    if not isinstance(spec, dict):
        raise ValueError(f"targets must be an object of figures, got {type(spec).__name__}")
    out = []
    for name, entry in spec.items():
        if name not in FIGURE_SCENE:
            raise ValueError(f"unknown target {name!r}; known: {sorted(FIGURE_SCENE)}")
        for e in entry if isinstance(entry, list) else [entry]:
            if not isinstance(e, dict):
                raise ValueError(f"target {name}: expected an object, got {e!r}")
            keys = {"value", "uncertainty"} | ({"p"} if name == "q_peak" else set())
            extra = sorted(set(e) - keys)
            if extra:
                raise ValueError(f"target {name}: unknown key(s) {extra}; expected {sorted(keys)}")
            if name == "q_peak" and "p" not in e:
                raise ValueError("a q_peak target needs the mean stress p (Pa) it was measured at")
            p = _number(f"target {name}", e, "p", positive=True) if "p" in e else None
            t = Target(
                name,
                _number(f"target {name}", e, "value", positive=name != "nu"),
                _number(f"target {name}", e, "uncertainty", positive=True),
                p,
            )
            out.append(t)
    if not out:
        raise ValueError("no targets given")
    return out


SPEC_KEYS = ("targets", "initial", "free", "seeds", "surrogate_width", "adam") + SCENES


def check_spec(spec: dict, scenes: Sequence[str], realisations: int) -> list[Target]:
    """Check a calibration spec (module docstring) before anything is built: known keys
    (``_``-prefixed ones are comments), the targets (:func:`parse_targets`), positive
    initial groups, free groups, enough non-negative integer seeds, the scene options (the
    scene's ``Config`` checks its own settings; lab options must be arguments of the lab
    builder) and the Adam options. Returns the targets; ValueError says what is wrong."""
    import inspect

    from jaxgran import labtests as lt

    if not isinstance(spec, dict):
        raise ValueError("the targets file must hold a JSON object")
    unknown = [k for k in spec if k not in SPEC_KEYS and not k.startswith("_")]
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in the spec; known: {list(SPEC_KEYS)}")
    targets = parse_targets(spec.get("targets", {}))
    for g, v in (spec.get("initial") or {}).items():
        if g not in GROUPS:
            raise ValueError(f"initial: unknown group {g!r}; groups: {list(GROUPS)}")
        _number("initial", {g: v}, g, positive=True)
    if spec.get("initial"):
        groups_from_values(spec["initial"])  # all groups given
    bad = [g for g in spec.get("free", []) if g not in GROUPS]
    if bad:
        raise ValueError(f"unknown free groups {bad}; choose from {list(GROUPS)}")
    if not (isinstance(realisations, int) and realisations >= 1):
        raise ValueError(f"realisations must be an integer >= 1, got {realisations!r}")
    seeds = spec.get("seeds") or list(range(realisations))
    if not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in seeds):
        raise ValueError(f"seeds must be non-negative integers, got {seeds!r}")
    if len(seeds) < realisations:
        raise ValueError(f"{realisations} realisations asked but only {len(seeds)} seeds given")
    if "surrogate_width" in spec:
        _number("spec", spec, "surrogate_width")
        if spec["surrogate_width"] < 0:
            raise ValueError("surrogate_width must be >= 0 (0: hard breakage)")
    builders = {"bonded-brazilian": lt.brazilian_lab, "bonded-biaxial": lt.biaxial_lab}
    for scene in scenes:
        if scene not in SCENES:
            raise ValueError(f"unknown scene {scene!r}; calibration knows {list(SCENES)}")
        options = spec.get(scene, {})
        if not isinstance(options, dict):
            raise ValueError(f"{scene}: options must be an object")
        lab_args = set(inspect.signature(builders[scene]).parameters) - {"cfg", "seeds"}
        extra = sorted(set(options.get("lab", {})) - lab_args)
        if extra:
            raise ValueError(f"{scene} lab: unknown option(s) {extra}; known: {sorted(lab_args)}")
        try:
            _scene_config(scene, options)
        except TypeError as exc:  # a key that is no setting of the scene
            raise ValueError(f"{scene}: {exc}") from None
    adam_opts = spec.get("adam", {})
    extra = sorted(set(adam_opts) - {"learning_rate", "steps", "tol", "gradient"})
    if extra:
        raise ValueError(
            f"adam: unknown option(s) {extra}; known: learning_rate, steps, tol, gradient"
        )
    for key in (k for k in adam_opts if k != "gradient"):
        _number("adam", adam_opts, key, positive=True)
    if "gradient" in adam_opts:
        _check_gradient(adam_opts["gradient"], "adam: ")
    return targets


@dataclasses.dataclass
class Problem:
    """Labs (one per scene), targets and the free groups of a calibration.

    The compiled programs of a problem (:func:`_program`) are kept in ``compiled`` and
    shared by every optimiser and report that runs on it; a program is rebuilt when the labs,
    initial groups or free groups it was traced with (and, for the reverse-mode loss, the
    targets) have changed since. The figures and their Jacobian do not depend on the
    targets: new targets reuse them."""

    labs: dict
    targets: list[Target]
    z0: np.ndarray
    free: list[int]
    seeds: list[int]
    compiled: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @property
    def n_free(self) -> int:
        return len(self.free)

    def full(self, x):
        """Log groups with the free ones replaced by ``x``."""
        import jax.numpy as jnp

        return jnp.asarray(self.z0).at[jnp.asarray(self.free)].set(x)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        x0 = self.z0[self.free]
        return x0 - math.log(BOUND), x0 + math.log(BOUND)


def _scene_config(scene: str, overrides: dict):
    from jaxgran.scenes import bonded_biaxial as bx
    from jaxgran.scenes import bonded_brazilian as bz

    base = bz.Config() if scene == "bonded-brazilian" else bx.Config()
    kw = {k: v for k, v in overrides.items() if k != "lab"}
    if "p_values" in kw:
        kw["p_values"] = tuple(kw["p_values"])
    return dataclasses.replace(base, **kw), dict(overrides.get("lab", {}))


def build_labs(
    scenes: list[str],
    targets: list[Target],
    initial: dict,
    seeds: list[int],
    scene_options: dict,
    *,
    surrogate_width: float = 0.2,
    peak_from_targets: bool = True,
) -> dict:
    """One lab per scene for the ``seeds``, its material set to the ``initial`` groups;
    the biaxial lab runs the unconfined test when E_c / nu / ucs are targets and a
    constant-p test for every p of the q_peak targets. With ``peak_from_targets`` the width
    of the smooth maxima is ``peak_fraction`` (lab option, default 0.02) of the target peak
    (sigma_t, ucs, q_peak) instead of the initial guess's, so it does not depend on the
    starting point."""
    from jaxgran import labtests as lt

    z0 = groups_from_values(initial)
    log_p = np.asarray(groups_to_log_params(z0))
    labs = {}
    for scene in scenes:
        if scene not in SCENES:
            raise ValueError(f"unknown scene {scene!r}; calibration knows {list(SCENES)}")
        mine = [t for t in targets if FIGURE_SCENE[t.name] == scene]
        if not mine:
            raise ValueError(f"scene {scene} was asked for but no target belongs to it")
        cfg, opts = _scene_config(scene, scene_options.get(scene, {}))
        cfg = lt.material_with(cfg, log_p)
        opts.setdefault("surrogate_width", surrogate_width)
        if scene == "bonded-brazilian":
            labs[scene] = lt.brazilian_lab(cfg, seeds, **opts)
        else:
            ps = sorted({t.p for t in mine if t.name == "q_peak"})
            unconf = any(t.name in ("E_c", "nu", "ucs") for t in mine)
            if "fit_strains" in opts:
                opts["fit_strains"] = tuple(opts["fit_strains"])
            opts.setdefault("require_peak", any(t.name == "ucs" for t in mine))
            labs[scene] = lt.biaxial_lab(cfg, seeds, unconfined=unconf, p_values=ps, **opts)
    if peak_from_targets:
        labs = _peak_widths(labs, targets, scene_options)
    missing = {FIGURE_SCENE[t.name] for t in targets} - set(labs)
    if missing:
        raise ValueError(f"targets need the scene(s) {sorted(missing)}: add --scene for them")
    return labs


def common_time_step(
    scene: str, overrides: dict, materials: list[dict], seeds: Sequence[int] = (0,)
) -> float:
    """The smallest default time step (s) of ``scene`` (with ``overrides``) over the group
    values of ``materials`` and the specimens of ``seeds``: give it to every lab (lab option
    ``dt``) that must share one time discretisation, e.g. a synthetic twin's truth and fit,
    and pass the seeds of all of them (the stable step is set by each specimen's stiffest,
    lightest cell, so one seed's step can be too long for another's)."""
    from jaxgran import labtests as lt
    from jaxgran.scenes import bonded as bd
    from jaxgran.scenes import bonded_biaxial as bx
    from jaxgran.scenes import bonded_brazilian as bz
    from jaxgran.state import replace

    seeds = sorted({int(s) for s in seeds})
    if not seeds or not materials:
        raise ValueError("common_time_step needs at least one seed and one material")
    cfg, _ = _scene_config(scene, overrides)
    cfgs = [
        lt.material_with(cfg, np.asarray(groups_to_log_params(groups_from_values(m))))
        for m in materials
    ]
    # the specimens once; each material's bond moduli are set on them (masses and shapes
    # do not depend on the fitted groups)
    if scene == "bonded-brazilian":
        states = bz.build(cfgs[0], seeds=seeds).states
    else:
        states = bx.build(cfgs[0], [(s, 0.0) for s in seeds]).states
    dts = []
    for c in cfgs:
        mat = bd.material_from(c)
        for st in states:
            b = st.bonds
            bonds = replace(b, b_n=np.full(b.b_n.shape, mat.b_n), b_t=np.full(b.b_t.shape, mat.b_t))
            dts.append(bd.stable_dt(st.particles, bonds, mat, c.dt_safety))
    return min(dts)


def _peak_widths(labs: dict, targets: list[Target], scene_options: dict) -> dict:
    from jaxgran.state import replace

    def frac(scene):
        return float(scene_options.get(scene, {}).get("lab", {}).get("peak_fraction", 0.02))

    val = {t.name: t.value for t in targets}
    out = dict(labs)
    lab = labs.get("bonded-brazilian")
    if lab is not None and "sigma_t" in val:  # Eq. 16 back to a force
        force = val["sigma_t"] * np.pi * float(lab.diameter) * float(lab.thickness) / 2.0
        width = frac("bonded-brazilian") * force
        out["bonded-brazilian"] = replace(lab, peak_width=lab.peak_width * 0 + width)
    lab = labs.get("bonded-biaxial")
    if lab is not None:
        w = np.asarray(lab.peak_width, float).copy()
        if "ucs" in val:
            w[0] = frac("bonded-biaxial") * val["ucs"]
        qs = [t.value for t in targets if t.name == "q_peak"]
        if qs:
            w[1] = frac("bonded-biaxial") * float(np.mean(qs))
        out["bonded-biaxial"] = replace(lab, peak_width=lab.peak_width * 0 + w)
    return out


def figure_values(figs: dict, labs: dict, targets: list[Target]):
    """Per target, the figure of every realisation ``[K]`` (jax arrays)."""
    out = []
    for t in targets:
        lab = labs[FIGURE_SCENE[t.name]]
        f = figs[FIGURE_SCENE[t.name]][t.name]
        if t.name == "q_peak":
            f = f[list(lab.p_values).index(float(t.p))]
        out.append(f)
    return out


def simulate_all(problem: Problem, x):
    """Figures per target ``[n_targets, K]`` and the error bits of every lab, for the free
    log groups ``x`` (jax-traceable)."""
    import jax.numpy as jnp

    from jaxgran import labtests as lt

    log_p = groups_to_log_params(problem.full(x))
    figs, errs = {}, []
    for scene, lab in problem.labs.items():
        figs[scene], err = lt.figures(log_p, lab)
        errs.append(err)
    return jnp.stack(figure_values(figs, problem.labs, problem.targets)), errs


def _target_arrays(problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Target values ``t_f`` and uncertainties ``u_f``."""
    return (
        np.array([tt.value for tt in problem.targets], float),
        np.array([tt.uncertainty for tt in problem.targets], float),
    )


def loss_of(means, problem: Problem, xp=None):
    """``mean_f ((m_f - t_f) / u_f)^2`` (see the module docstring), in ``xp`` (numpy on the
    host, ``jax.numpy`` by default: traceable)."""
    if xp is None:
        import jax.numpy as xp
    t, u = _target_arrays(problem)
    return xp.mean(((means - t) / u) ** 2)


def _snapshot(problem: Problem, kind: str) -> tuple:
    """What the traced program ``kind`` of ``problem`` depends on (the labs by identity;
    the targets only where the loss is traced, i.e. in reverse mode)."""
    targets = tuple(dataclasses.astuple(t) for t in problem.targets) if kind == "reverse" else ()
    return (
        tuple(problem.labs.items()),
        targets,
        np.asarray(problem.z0).tobytes(),
        tuple(problem.free),
    )


def _same_snapshot(a: tuple, b: tuple) -> bool:
    labs_a, labs_b = a[0], b[0]
    return (
        len(labs_a) == len(labs_b)
        and all(ka == kb and la is lb for (ka, la), (kb, lb) in zip(labs_a, labs_b, strict=True))
        and a[1:] == b[1:]
    )


def _program(problem: Problem, kind: str):
    """The jitted program ``kind`` of ``problem``, traced once and shared:

    * ``"figures"``: ``x -> (figures [n_targets, K], error bits)``;
    * ``"jacobian"``: ``x -> (d means / d x [n_targets, n_free], (figures, error bits))`` by
      forward mode (``jax.jacfwd``: one run of every lab carrying one tangent per free
      group), from which Adam's forward gradient, the Gauss-Newton residual Jacobian and the
      uncertainty all follow by the chain rule on the host;
    * ``"reverse"``: ``x -> ((loss, (figures, error bits)), d loss / d x)`` by reverse mode.

    Adam, Levenberg-Marquardt, the uncertainty and the tables of one problem thus compile
    one forward-mode program between them instead of one each."""
    import jax

    snap = _snapshot(problem, kind)
    hit = problem.compiled.get(kind)
    if hit is not None and _same_snapshot(hit[0], snap):
        return hit[1]
    frozen = dataclasses.replace(
        problem,
        labs=dict(problem.labs),
        targets=list(problem.targets),
        z0=np.array(problem.z0),
        free=list(problem.free),
        compiled={},
    )
    if kind == "figures":
        fn = jax.jit(lambda x: simulate_all(frozen, x))
    elif kind == "jacobian":

        def ensemble_means(x):  # compiled as jit(ensemble_means)
            vals, errs = simulate_all(frozen, x)
            return vals.mean(axis=1), (vals, errs)

        fn = jax.jit(jax.jacfwd(ensemble_means, has_aux=True))
    elif kind == "reverse":

        def loss(x):
            vals, errs = simulate_all(frozen, x)
            return loss_of(vals.mean(axis=1), frozen), (vals, errs)

        fn = jax.jit(jax.value_and_grad(loss, has_aux=True))
    else:
        raise ValueError(f"unknown program {kind!r}")
    problem.compiled[kind] = (snap, fn)
    return fn


GRADIENTS = ("forward", "reverse")
"""How :func:`make_functions` differentiates the loss. ``"forward"`` (the default): one run
of every lab that carries one tangent per free group (``jax.jacfwd``), so its cost grows
with the number of free groups (at most the six of :data:`GROUPS`) and it keeps no
trajectory. ``"reverse"``: one forward and one reverse pass (``jax.value_and_grad``,
checkpointed per record interval), whatever the number of free groups. Measured on 2 CPU
cores (float64, 2026-12-06, ``benchmarks/GRADIENT_MODES_RESULTS.md``): on a 20-cell
Brazilian disc, one realisation, forward mode takes 0.54, 0.79 and 1.21 s per gradient with
1, 3 and 6 free groups, reverse mode 1.43-1.45 s, and forward mode compiles in 10-12 s
against 23-24 s; on the twin's two labs with four 30-cell realisations and three free
groups, 6.6 s against 10.9 s per gradient, 25 s against 55 s to compile and a peak of 1.8
against 3.0 GB. The two gradients agree to round-off (``tests/test_calibration.py``)."""


def _check_gradient(gradient, where: str = "") -> None:
    if gradient not in GRADIENTS:
        raise ValueError(f"{where}gradient must be one of {GRADIENTS}, got {gradient!r}")


def make_functions(problem: Problem, gradient: str = "forward"):
    """``value_and_grad`` and the forward loss of the free log groups; both return the
    figures ``[n_targets, K]`` and error bits too. ``gradient`` picks forward or reverse
    mode (:data:`GRADIENTS`); the value and the figures are the same in both. Forward mode
    takes the Jacobian of the ensemble means (the problem's shared ``"jacobian"`` program,
    :func:`_program`) and applies the chain rule of the loss on the host, ``dL/dx =
    (2 / n) sum_f (m_f - t_f) / u_f^2 dm_f/dx``; the loss's value is computed on the host
    from the figures in both modes' forward loss."""
    _check_gradient(gradient)
    # each call looks its program up, so a changed lab or target set is never run stale

    def loss(x):
        vals, errs = _program(problem, "figures")(x)
        return loss_of(np.asarray(vals).mean(axis=1), problem, np), (vals, errs)

    if gradient == "reverse":
        return lambda x: _program(problem, "reverse")(x), loss

    def value_and_grad(x):
        jac, (vals, errs) = _program(problem, "jacobian")(x)
        t, u = _target_arrays(problem)
        m = np.asarray(vals).mean(axis=1)
        jac = np.asarray(jac)
        g = (2.0 / t.size) * (((m - t) / u**2) @ jac)
        return (loss_of(m, problem, np), (vals, errs)), g.astype(jac.dtype)

    return value_and_grad, loss


def _check(errs):
    from jaxgran import labtests as lt

    for e in errs:
        lt.check_errors(e)


# ------------------------------------------------------------------------------ optimisers


def adam(
    problem: Problem,
    *,
    learning_rate: float = 0.05,
    steps: int = 60,
    tol: float = 1e-3,
    x0=None,
    gradient: str = "forward",
    log=print,
) -> dict:
    """Adam (optax; learning rate decaying as a cosine from ``learning_rate`` to 5 % of it
    over ``steps``) on the free log groups, projected onto the bounds; stops after
    ``steps`` iterations or once the loss is below ``tol``. The gradient comes from forward
    or reverse mode (``gradient``, :data:`GRADIENTS`). Returns the best point, its loss, the
    history and the count of simulations (one run of every lab with its tangents, or one
    forward and one reverse pass, per iteration), the gradient mode and the wall time (s,
    compilation included)."""
    import jax.numpy as jnp
    import optax

    vg, _ = make_functions(problem, gradient)
    lo, hi = problem.bounds()
    x = jnp.asarray(problem.z0[problem.free] if x0 is None else x0)
    # cosine decay to 5 % of the rate: Adam's steps do not shrink near the optimum otherwise
    opt = optax.adam(optax.cosine_decay_schedule(learning_rate, max(steps, 1), alpha=0.05))
    state = opt.init(x)
    hist = {"loss": [], "x": [], "time_s": []}
    best = (np.inf, np.asarray(x))
    t0 = time.perf_counter()
    for it in range(steps):
        (val, (_, errs)), g = vg(x)
        _check(errs)
        val = float(val)
        hist["loss"].append(val)
        hist["x"].append(np.asarray(x).tolist())
        hist["time_s"].append(time.perf_counter() - t0)
        if val < best[0]:
            best = (val, np.asarray(x))
        log(f"adam {it:3d}  loss {val:.4g}  x {np.round(np.exp(np.asarray(x)), 5).tolist()}")
        if val < tol:
            break
        upd, state = opt.update(g, state, x)
        x = jnp.clip(optax.apply_updates(x, upd), lo, hi)
    return {
        "x": best[1],
        "loss": best[0],
        "history": hist,
        "simulations": len(hist["loss"]),
        "gradient_evaluations": len(hist["loss"]),
        "gradient": gradient,
        "wall_time_s": time.perf_counter() - t0,
    }


def nelder_mead(
    problem: Problem, *, max_evaluations: int = 200, tol: float = 1e-3, x0=None, log=print
) -> dict:
    """Gradient-free baseline: scipy Nelder-Mead on the same loss (forward runs only), in
    the same log groups, with an initial simplex of +-10 % steps and the same bounds."""
    from scipy.optimize import minimize

    _, fwd = make_functions(problem)
    lo, hi = problem.bounds()
    hist = {"loss": [], "x": [], "time_s": []}
    t0 = time.perf_counter()

    def f(x):
        val, (_, errs) = fwd(np.clip(x, lo, hi))
        _check(errs)
        val = float(val)
        hist["loss"].append(val)
        hist["x"].append(np.asarray(x).tolist())
        hist["time_s"].append(time.perf_counter() - t0)
        if len(hist["loss"]) % 10 == 0:
            log(f"nelder-mead {len(hist['loss']):4d}  loss {min(hist['loss']):.4g}")
        return val

    start = np.asarray(problem.z0[problem.free] if x0 is None else x0, float)
    simplex = [start] + [start + 0.1 * np.eye(start.size)[k] for k in range(start.size)]
    res = minimize(
        f,
        start,
        method="Nelder-Mead",
        options={
            "maxfev": max_evaluations,
            "fatol": tol,
            "xatol": 1e-3,
            "initial_simplex": np.array(simplex),
        },
    )
    k = int(np.argmin(hist["loss"]))
    return {
        "x": np.clip(np.asarray(hist["x"][k]), lo, hi),
        "loss": hist["loss"][k],
        "history": hist,
        "simulations": len(hist["loss"]),
        "wall_time_s": time.perf_counter() - t0,
        "message": str(res.message),
    }


def gauss_newton(
    problem: Problem,
    *,
    iterations: int = 12,
    tol: float = 1e-3,
    rtol: float = 0.02,
    max_rejections: int = 2,
    max_step: float = 0.5,
    x0=None,
    log=print,
) -> dict:
    """Levenberg-Marquardt on the weighted residuals (same loss as :func:`adam`), with the
    Jacobian of the ensemble means by forward mode (``jax.jacfwd``: one run of every lab
    carrying one tangent per free group, no reverse pass and no checkpointing).

    Each iteration solves ``(J^T J + lambda diag(J^T J)) dx = -J^T r`` (steps capped at
    ``max_step`` in every log group, i.e. a factor e^0.5, and projected onto the bounds)
    and evaluates the Jacobian at the trial point; a trial that lowers the loss is taken and
    ``lambda`` shrinks 3x, otherwise ``lambda`` grows 4x and the step is redone from the same
    point. Stops after ``iterations`` evaluations, once the loss is below ``tol``, or once
    the linear model predicts a decrease below ``rtol`` of the loss (the loss of a small
    ensemble is rough at the percent level: contact and bond events that the surrogate does
    not smooth move it by a few % between nearby points, so smaller predicted gains are
    noise), or after ``max_rejections`` trials in a row that did not lower it (for the same
    reason). The Jacobian program is the problem's shared one (:func:`_program`), so a
    Gauss-Newton fit after Adam (or before the uncertainty) compiles nothing new. Returns
    what :func:`adam` returns; ``simulations`` counts the Jacobian evaluations."""
    import jax

    lo, hi = problem.bounds()
    t, u = _target_arrays(problem)
    scale = u * math.sqrt(len(problem.targets))
    x = np.asarray(problem.z0[problem.free] if x0 is None else x0, float)
    hist = {"loss": [], "x": [], "time_s": []}
    t0 = time.perf_counter()

    def evaluate(xx):
        jac, (vals, errs) = _program(problem, "jacobian")(jax.numpy.asarray(xx))
        _check(errs)
        # the weighted residuals r_f = (m_f - t_f) / (u_f sqrt(n)), |r|^2 = the loss
        r = (np.asarray(vals, float).mean(axis=1) - t) / scale
        jac = np.asarray(jac, float) / scale[:, None]
        val = float(r @ r)
        hist["loss"].append(val)
        hist["x"].append(np.asarray(xx).tolist())
        hist["time_s"].append(time.perf_counter() - t0)
        return val, r, jac

    val, r, jac = evaluate(x)
    lam, rejected = 1e-2, 0
    log(f"gauss-newton   0  loss {val:.4g}  x {np.round(np.exp(x), 5).tolist()}")
    while len(hist["loss"]) < iterations and val >= tol:
        jtj = jac.T @ jac
        a = jtj + lam * np.diag(np.diag(jtj)) + 1e-12 * np.trace(jtj) * np.eye(x.size)
        dx = np.linalg.solve(a, -jac.T @ r)
        dx *= min(1.0, max_step / max(np.abs(dx).max(), 1e-300))
        trial = np.clip(x + dx, lo, hi)
        lin = r + jac @ (trial - x)
        if val - float(lin @ lin) < rtol * val:
            log(f"gauss-newton: predicted decrease below {rtol:g} of the loss, stop")
            break
        v2, r2, j2 = evaluate(trial)
        log(
            f"gauss-newton {len(hist['loss']) - 1:3d}  loss {v2:.4g}  lambda {lam:.2g}  "
            f"x {np.round(np.exp(trial), 5).tolist()}"
        )
        if v2 < val:
            x, val, r, jac, lam, rejected = trial, v2, r2, j2, lam / 3.0, 0
        else:
            lam, rejected = lam * 4.0, rejected + 1
            if rejected >= max_rejections:
                log(f"gauss-newton: {rejected} trials in a row did not lower the loss, stop")
                break
    return {
        "x": x,
        "loss": val,
        "history": hist,
        "simulations": len(hist["loss"]),
        "jacobian_evaluations": len(hist["loss"]),
        "wall_time_s": time.perf_counter() - t0,
    }


# ------------------------------------------------------------------------------ report


def mean_jacobian(problem: Problem, x) -> tuple[np.ndarray, np.ndarray]:
    """``d m / d x`` ``[n_targets, n_free]`` of the ensemble means with respect to the free
    log groups (forward mode, one run carrying one tangent per group) and the figures of
    every realisation ``[n_targets, K]`` at ``x``."""
    import jax

    jac, (vals, _) = _program(problem, "jacobian")(jax.numpy.asarray(x))
    return np.asarray(jac), np.asarray(vals)


def uncertainty(problem: Problem, x) -> dict:
    """Covariance of the free log groups from the Jacobian of the ensemble means and the
    ensemble spread (module docstring); standard deviations of the log groups, i.e.
    relative uncertainties of the groups."""
    jac, vals = mean_jacobian(problem, x)
    k = vals.shape[1]
    spread = vals.std(axis=1, ddof=1) if k > 1 else np.zeros(vals.shape[0])
    u = np.array([t.uncertainty for t in problem.targets])
    out = {"jacobian_dlog": jac.tolist(), "ensemble_std": spread.tolist()}
    for name, var in (("total", u**2 + spread**2 / k), ("ensemble_only", spread**2 / k)):
        if np.all(var > 0):
            w = 1.0 / var
            try:
                cov = np.linalg.inv(jac.T @ (w[:, None] * jac))
                out[f"relative_std_{name}"] = np.sqrt(np.diag(cov)).tolist()
                out[f"covariance_log_{name}"] = cov.tolist()
            except np.linalg.LinAlgError:
                out[f"relative_std_{name}"] = None
    return out


def table(problem: Problem, x) -> list[dict]:
    """Final simulated (ensemble mean and std) against target, per target."""
    _, fwd = make_functions(problem)
    _, (vals, _) = fwd(x)
    vals = np.asarray(vals)
    rows = []
    for t, v in zip(problem.targets, vals, strict=True):
        m = float(v.mean())
        rows.append(
            {
                "figure": t.label,
                "target": t.value,
                "uncertainty": t.uncertainty,
                "simulated_mean": m,
                "simulated_std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                "relative_misfit": m / t.value - 1.0,
            }
        )
    return rows


def format_table(rows: list[dict]) -> str:
    lines = [
        f"{'figure':<18}{'target':>14}{'+-':>12}{'simulated':>14}{'std':>12}{'misfit':>9}",
    ]
    for r in rows:
        lines.append(
            f"{r['figure']:<18}{r['target']:>14.4g}{r['uncertainty']:>12.3g}"
            f"{r['simulated_mean']:>14.4g}{r['simulated_std']:>12.3g}"
            f"{100 * r['relative_misfit']:>8.2f}%"
        )
    return "\n".join(lines)


def make_problem(
    spec: dict, scenes: list[str], realisations: int, seeds=None, peak_from_targets: bool = True
) -> Problem:
    """A :class:`Problem` from a targets spec (module docstring), checked first
    (:func:`check_spec`)."""
    targets = check_spec(spec, scenes, realisations)
    initial = spec.get("initial") or {
        "K_n": 1.0e8,
        "K_n/K_t": 1.0,
        "B_n": 2.0e10,
        "B_n/B_t": 1.0,
        "eps_th": 0.02,
        "mu": 0.3,
    }
    free = spec.get("free", ["K_n", "B_n/B_t", "eps_th"])
    if seeds is None:
        seeds = spec.get("seeds") or list(range(realisations))
    seeds = list(seeds)[:realisations]
    if len(seeds) < realisations:
        raise ValueError(f"{realisations} realisations asked but only {len(seeds)} seeds given")
    opts = {s: spec.get(s, {}) for s in SCENES}
    width = float(spec.get("surrogate_width", 0.2))
    labs = build_labs(
        scenes,
        targets,
        initial,
        seeds,
        opts,
        surrogate_width=width,
        peak_from_targets=peak_from_targets,
    )
    z0 = groups_from_values(initial)
    return Problem(labs, targets, z0, [GROUPS.index(g) for g in free], seeds)


def report(problem: Problem, result: dict, method: str) -> dict:
    z = np.asarray(problem.full(result["x"]))
    free_names = [GROUPS[i] for i in problem.free]
    out = {
        "method": method,
        "parameters": parameters_from_groups(z),
        "free": free_names,
        "loss": result["loss"],
        "simulations": result["simulations"],
        "wall_time_s": result["wall_time_s"],
        "seeds": problem.seeds,
        "history": result["history"],
        "table": table(problem, result["x"]),
    }
    if "gradient" in result:  # Adam: the mode its gradient came from
        out["gradient"] = result["gradient"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m calibration.fit", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--targets", required=True, type=Path)
    ap.add_argument("--scene", action="append", choices=SCENES, required=True)
    ap.add_argument("--realisations", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("calibration_out"))
    ap.add_argument("--steps", type=int, default=None, help="Adam iterations")
    ap.add_argument("--learning-rate", type=float, default=None)
    ap.add_argument("--baseline", action="store_true", help="also run Nelder-Mead")
    ap.add_argument(
        "--gauss-newton", action="store_true", help="also run Levenberg-Marquardt (jacfwd)"
    )
    ap.add_argument(
        "--gradient",
        choices=GRADIENTS,
        default=None,
        help="Adam's gradient: forward mode (default; one run with one tangent per free "
        "group) or reverse mode",
    )
    ap.add_argument("--max-evaluations", type=int, default=200)
    ap.add_argument("--float32", action="store_true", help="single precision (default x64)")
    args = ap.parse_args(argv)

    import os

    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import jax

    jax.config.update("jax_enable_x64", not args.float32)
    try:
        spec = json.loads(args.targets.read_text())
        check_spec(spec, args.scene, args.realisations)
    except (OSError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
        print(f"error: {args.targets}: {exc}", file=sys.stderr)
        return 2
    return run(spec, args.scene, args.realisations, args.out, args)


def run(spec: dict, scenes, realisations: int, out_dir: Path, args=None) -> int:
    from .plots import plot_convergence

    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    problem = make_problem(spec, list(scenes), realisations)
    build_s = time.perf_counter() - t0
    a = spec.get("adam", {})
    steps = getattr(args, "steps", None) or a.get("steps", 60)
    lr = getattr(args, "learning_rate", None) or a.get("learning_rate", 0.05)
    gradient = getattr(args, "gradient", None) or a.get("gradient", "forward")
    res = adam(problem, learning_rate=lr, steps=steps, tol=a.get("tol", 1e-3), gradient=gradient)
    summary = {"adam": report(problem, res, "adam"), "build_s": build_s}
    summary["adam"]["uncertainty"] = uncertainty(problem, res["x"])
    histories = {"Adam (gradient)": res["history"]}
    if getattr(args, "gauss_newton", False):
        gn = gauss_newton(problem, tol=a.get("tol", 1e-3))
        summary["gauss_newton"] = report(problem, gn, "gauss-newton")
        histories["Gauss-Newton (forward-mode Jacobian)"] = gn["history"]
    if getattr(args, "baseline", False):
        nm = nelder_mead(problem, max_evaluations=args.max_evaluations, tol=a.get("tol", 1e-3))
        summary["nelder_mead"] = report(problem, nm, "nelder-mead")
        histories["Nelder-Mead"] = nm["history"]
    summary["convergence_plot"] = str(plot_convergence(histories, out_dir / "convergence.png"))
    (out_dir / "fit.json").write_text(json.dumps(summary, indent=2, default=_json))
    print(format_table(summary["adam"]["table"]))
    p = summary["adam"]["parameters"]
    rel = summary["adam"]["uncertainty"].get("relative_std_total") or []
    for name, s in zip(summary["adam"]["free"], rel, strict=False):
        print(f"{name:>10} = {p[name]:.5g}  (+- {100 * s:.2f} %)")
    print(f"wrote {out_dir / 'fit.json'} and {summary['convergence_plot']}")
    return 0


def _json(o):
    if isinstance(o, np.ndarray | np.generic):
        return o.tolist()
    raise TypeError(f"{type(o)} is not JSON serialisable")


if __name__ == "__main__":
    raise SystemExit(main())
