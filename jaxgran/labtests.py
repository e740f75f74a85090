"""Differentiable lab tests: micro-parameters in, macroscopic figures out (DESIGN §7).

A *lab* (:class:`Lab`) is a bonded Voronoi test prepared on the host (specimens of K
Voronoi seeds padded to common capacities and stacked, walls, loading control, time step,
run length); :func:`figures` is a pure, jitted, differentiable function of the log of the
micro-parameters (:data:`PARAMETERS`, paper 002 Table 1)

    log [K_n (N/m), K_t (N/m), B_n (Pa), B_t (Pa), eps_th (-), mu (-)]

to the figures of each realisation ``[K]``:

* ``"brazilian"`` (:func:`brazilian_lab`): tensile strength ``sigma_t = 2 F_max / (pi D T)``
  (paper 002 Eq. 16) and slope ``S = 2 F(eps_max / 2) / (eps_max T)`` (Eq. 17), Pa;
* ``"biaxial"`` (:func:`biaxial_lab`): from unconfined compression the modulus
  ``E_c = d s1 / d e1`` (Eq. 24, Pa), the Poisson ratio ``nu = -d e3 / d e1`` (Eq. 25), both
  from the strain-gauge bands, and the unconfined strength ``ucs`` (Pa); from constant-p
  shearing at each of the lab's p values the peak deviator ``q_peak = max (s1 - s3) / 2``
  (Pa, ``[n_p, K]``), after a fixed-length isotropic stage. Unconfined and constant-p
  members run in one batch, so one compilation serves all biaxial figures.

What makes them differentiable:

* **Bond breakage** uses the smooth surrogate of :func:`jaxgran.bonds.health_limit` with the
  lab's ``surrogate_width`` w (health falls from 1 to 0 as the Eq. 15 measure goes from 1 to
  1 + w, never recovers); ``w = 0`` is the hard model.
* **Peaks** are smooth maxima: the softmax-weighted mean ``sum_r s_r F_r`` with weights
  ``s = softmax(F / tau)`` over the records, ``tau`` the lab's ``peak_width`` (N or Pa; set
  at build time as a fraction of the reference peak, so it does not move with the
  parameters); ``tau -> 0`` is the maximum. The strain of the peak is weighted the same way.
* **Fixed run lengths and windows**: the loading is prescribed (platen speeds), so every
  record's platen strain is known in advance; the run length and the record window of the
  E_c / nu fit (10-50 % of the reference peak stress) are chosen at build time from a
  reference run with the lab's own parameters and stay fixed, so the figures are smooth in
  the parameters (a data-dependent window would jump).
* **Time step** stays that of the reference material (0.5 of the Gershgorin bound,
  :func:`jaxgran.scenes.bonded.stable_dt`): stiffnesses up to 4x the reference stay stable.

**Memory.** The run is an outer ``lax.scan`` over segments whose body (``records_per_segment
x record_every`` steps) is wrapped in :func:`jax.checkpoint`, and so is every record
interval inside it (:func:`jaxgran.ensemble.batched_segment` with ``remat``): reverse mode
stores one state per segment, recomputes a segment keeping one state per record, and
recomputes a record's ``record_every`` steps keeping their residuals, so memory grows like
``n_segments + records_per_segment + record_every`` states instead of the number of steps
(with the default ``sqrt`` split, like the square root of the number of records), for about
two extra forward passes of compute.

**Ensembles.** The K stacked realisations step together with one pair-list rebuild decision
per step (:func:`jaxgran.ensemble.batched_step`); :func:`figures` returns ``[K]`` arrays and
the caller averages them (:mod:`calibration`). It is also ``vmap``-able over parameter sets
(``jax.vmap(figures, in_axes=(0, None))``), e.g. for finite differences.

**Capacities** are fixed when the lab is built (pair list with ``pair_headroom``); a full
list, NaN or a skin violation sets the error bits that :func:`figures` returns next to the
figures; :func:`check_errors` turns them into an exception that says what to rebuild.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import ensemble as ens
from .integrate import initial_forces
from .scenes import bonded as bd
from .scenes import bonded_biaxial as bx
from .scenes import bonded_brazilian as bz
from .state import (
    ERR_CELL_OVERFLOW,
    ERR_PAIR_OVERFLOW,
    WALL_FIXED,
    WALL_SERVO,
    WALL_VELOCITY,
    Grid,
    Params,
    SimState,
    describe_errors,
    replace,
)

PARAMETERS = ("K_n", "K_t", "B_n", "B_t", "eps_th", "mu")
"""Order of the micro-parameters in a log-parameter vector."""

FIGURES = {
    "brazilian": ("sigma_t", "slope_S"),
    "biaxial": ("E_c", "nu", "ucs", "q_peak"),
}
"""Figures that :func:`figures` can return for each lab kind (``[K]``; ``q_peak``
``[n_p, K]``); all Pa except nu. A biaxial lab returns the unconfined ones only when built
with ``unconfined`` and ``q_peak`` only with ``p_values``."""


def log_params(material: bd.Material) -> Array:
    """``log [K_n, K_t, B_n, B_t, eps_th, mu]`` of a material (see :data:`PARAMETERS`)."""
    m = material
    vals = [
        m.normal_stiffness,
        m.tangential_stiffness,
        m.b_n,
        m.b_t,
        m.eps_th,
        m.friction,
    ]
    return jnp.log(jnp.asarray(vals, dtype=jnp.result_type(float)))


def material_with(material: bd.Material, log_p) -> bd.Material:
    """``material`` (a :class:`jaxgran.scenes.bonded.Material`, or any scene config with the
    same fields) with the six micro-parameters of ``log_p`` (host values)."""
    v = np.exp(np.asarray(log_p, float))
    return dataclasses.replace(
        material,
        normal_stiffness=float(v[0]),
        tangential_stiffness=float(v[1]),
        b_n=float(v[2]),
        b_t=float(v[3]),
        eps_th=float(v[4]),
        friction=float(v[5]),
    )


class Lab(eqx.Module):
    """A prepared, differentiable lab test of K stacked realisations (module docstring).

    Attributes:
        kind: ``"brazilian"`` or ``"biaxial"`` (static).
        state: initial states ``[K, ...]`` (members, for biaxial: unconfined ones first).
        controls: loading control ``[K, ...]`` of the (main) stage.
        params: shared :class:`Params`: dt, skin, damping, thickness; K_n, K_t and mu are
            replaced by the parameters at each call.
        grid: broad-phase grid (its shape static, its origin and cell size values).
        real_bond: ``[K, B]`` bool, real particle-particle bonds.
        ref: per realisation reference length ``[K]`` (m): the initial platen gap
            (brazilian) or the block height (biaxial).
        gauge0: initial mean positions of the four gauge bands ``[K, 4, 2]`` (m).
        window: weights of the records in the E_c / nu fit ``[R]`` (unconfined).
        surrogate_width: w of the bond-health surrogate (-), 0 = hard breakage.
        peak_width: tau of the smooth maximum (N for brazilian; ``[2]`` Pa for biaxial:
            unconfined strength, q_peak).
        diameter: disc diameter D (m, brazilian).
        thickness: slab thickness T (m).
        n_segments, records_per_segment, record_every: run layout of the main stage
            (static); ``n_segments x records_per_segment`` records.
        lead_segments: segments of the isotropic stage (biaxial with p values; static).
        n_unconfined: the first members that are unconfined tests (static).
        p_values: p of the constant-p members (Pa, static), p-major after the unconfined.
        shear_controls: control of the shearing stage ``[K, ...]`` (biaxial).
        shear_modes: wall modes of the shearing stage ``[K, 4]`` (biaxial).
        shear_velocity: wall velocities of the shearing stage ``[K, 4, 2]`` (m/s).
    """

    kind: str = eqx.field(static=True)
    state: SimState
    controls: bd.Control
    params: Params
    grid: Grid
    real_bond: Array
    ref: Array
    gauge0: Array
    window: Array
    surrogate_width: Array
    peak_width: Array
    diameter: Array
    thickness: Array
    n_segments: int = eqx.field(static=True)
    records_per_segment: int = eqx.field(static=True)
    record_every: int = eqx.field(static=True)
    lead_segments: int = eqx.field(static=True, default=0)
    n_unconfined: int = eqx.field(static=True, default=0)
    p_values: tuple = eqx.field(static=True, default=())
    shear_controls: bd.Control | None = None
    shear_modes: Array | None = None
    shear_velocity: Array | None = None

    @property
    def realisations(self) -> int:
        return int(self.state.time.shape[0])

    @property
    def n_steps(self) -> int:
        per = self.records_per_segment * self.record_every
        return (self.n_segments + self.lead_segments) * per


# ------------------------------------------------------------------------------ parameters


def _with_parameters(lab: Lab, log_p: Array) -> tuple[SimState, Params]:
    """Stacked states and shared params carrying the micro-parameters ``exp(log_p)``."""
    kn, kt, bn, bt, eps, mu = (jnp.exp(log_p[k]) for k in range(6))
    params = replace(
        lab.params, normal_stiffness=kn, tangential_stiffness=kt, friction=mu, wall_friction=mu
    )
    b = lab.state.bonds
    real = lab.real_bond
    bonds = replace(
        b,
        b_n=jnp.where(real, bn, 0.0),
        b_t=jnp.where(real, bt, 0.0),
        eps_th=jnp.where(real, eps, 1.0),
        wall_b_n=jnp.where(b.wall_active, bn, 0.0),
        surrogate_width=jnp.broadcast_to(lab.surrogate_width, b.surrogate_width.shape),
    )
    return replace(lab.state, bonds=bonds), params


# ------------------------------------------------------------------------------ running


def _stage(states, params, controls, grid, n_segments, records_per_segment, record_every):
    """``n_segments`` checkpointed segments; returns the states, the wall forces and points
    and the gauge positions with the record axis first ``[R, K, ...]``, and errors ``[K]``."""

    @jax.checkpoint
    def seg(s):
        s, recs, extra, err = ens.batched_segment(
            s, params, controls, grid, records_per_segment, record_every, remat=True
        )
        return s, (recs.wall_force, recs.wall_point, extra["gauge_position"], err)

    def body(carry, _):
        s, err = carry
        s, (wf, wp, gp, e) = seg(s)
        return (s, err | e), (wf, wp, gp)

    err0 = jnp.zeros(states.time.shape, jnp.int32)
    (states, err), (wf, wp, gp) = jax.lax.scan(body, (states, err0), None, length=n_segments)
    flat = lambda x: x.reshape((-1,) + x.shape[2:])
    return states, flat(wf), flat(wp), flat(gp), err


def _start(states: SimState, params: Params, grid: Grid):
    return jax.vmap(lambda s: initial_forces(s, params, grid))(states)


def simulate(log_p: Array, lab: Lab) -> tuple[dict[str, Array], Array]:
    """Run the lab with the micro-parameters ``exp(log_p)``; returns the curves
    (``wall_force``, ``wall_point`` ``[R, K, W, 2]`` in N and m, ``gauge_position``
    ``[R, K, 4, 2]`` m, record averages of the main stage) and the error bits ``[K]``."""
    states, params = _with_parameters(lab, log_p)
    states, err = _start(states, params, lab.grid)
    layout = (lab.records_per_segment, lab.record_every)
    if lab.kind == "biaxial":
        if lab.lead_segments:
            states, *_, e = _stage(
                states, params, lab.controls, lab.grid, lab.lead_segments, *layout
            )
            err = err | e
        walls = replace(states.walls, mode=lab.shear_modes, vel=lab.shear_velocity)
        states = replace(states, walls=walls)
        controls = lab.shear_controls
    else:
        controls = lab.controls
    _, wf, wp, gp, e = _stage(states, params, controls, lab.grid, lab.n_segments, *layout)
    return {"wall_force": wf, "wall_point": wp, "gauge_position": gp}, err | e


# ------------------------------------------------------------------------------ figures


def smooth_max(values: Array, width: Array, axis: int = 0) -> tuple[Array, Array]:
    """Smooth maximum of ``values`` along ``axis``: ``sum s v`` with ``s = softmax(v /
    width)``; returns it and the weights ``s`` (so other series can be read at the smooth
    peak). ``width -> 0`` gives the maximum; it never exceeds it."""
    s = jax.nn.softmax(values / width, axis=axis)
    return jnp.sum(s * values, axis=axis), s


def _slope(x: Array, y: Array, w: Array) -> Array:
    """Weighted least-squares slope of y on x over the record axis 0 (weights ``[R]``)."""
    w = w[:, None] / jnp.sum(w)
    xm, ym = jnp.sum(w * x, axis=0), jnp.sum(w * y, axis=0)
    return jnp.sum(w * (x - xm) * (y - ym), axis=0) / jnp.sum(w * (x - xm) ** 2, axis=0)


def platen_curves(curves: dict, lab: Lab) -> tuple[Array, Array]:
    """Brazilian platen force (N, compressive mean of the two platens) and axial strain
    (``1 - gap / gap0``) per record ``[R, K]``."""
    f, x = curves["wall_force"], curves["wall_point"]
    force = 0.5 * (-f[..., 0, 1] + f[..., 1, 1])
    strain = 1.0 - (x[..., 1, 1] - x[..., 0, 1]) / lab.ref
    return force, strain


def box_curves(curves: dict, lab: Lab) -> dict[str, Array]:
    """Biaxial axial / lateral stress (Pa, compression positive, current block size as
    length) and gauge strains e1, e3 per record ``[R, K]``."""
    f, x, g = curves["wall_force"], curves["wall_point"], curves["gauge_position"]
    normal = jnp.asarray([[0.0, 1.0], [1.0, 0.0], [-1.0, 0.0], [0.0, -1.0]], f.dtype)
    fn = -jnp.sum(f * normal, axis=-1)
    height = x[..., bd.TOP, 1] - x[..., bd.BOTTOM, 1]
    width = x[..., bd.RIGHT, 0] - x[..., bd.LEFT, 0]
    t = lab.thickness
    s_ax = 0.5 * (fn[..., bd.BOTTOM] + fn[..., bd.TOP]) / (width * t)
    s_lat = 0.5 * (fn[..., bd.LEFT] + fn[..., bd.RIGHT]) / (height * t)
    g0 = lab.gauge0
    h0 = g0[:, bd.TOP, 1] - g0[:, bd.BOTTOM, 1]
    w0 = g0[:, bd.RIGHT, 0] - g0[:, bd.LEFT, 0]
    e1 = 1.0 - (g[..., bd.TOP, 1] - g[..., bd.BOTTOM, 1]) / h0
    e3 = 1.0 - (g[..., bd.RIGHT, 0] - g[..., bd.LEFT, 0]) / w0
    return {"s_ax": s_ax, "s_lat": s_lat, "e1": e1, "e3": e3}


def figures_of(curves: dict, lab: Lab) -> dict[str, Array]:
    """The figures of :data:`FIGURES` from the curves of :func:`simulate`, ``[K]`` each."""
    if lab.kind == "brazilian":
        force, strain = platen_curves(curves, lab)
        f_max, s = smooth_max(force, lab.peak_width)
        e_max = jnp.sum(s * strain, axis=0)
        half = jax.vmap(jnp.interp, in_axes=(0, 1, 1))(0.5 * e_max, strain, force)
        t = lab.thickness
        return {
            "sigma_t": 2.0 * f_max / (jnp.pi * lab.diameter * t),  # Eq. 16
            "slope_S": 2.0 * half / (e_max * t),  # Eq. 17
        }
    c = box_curves(curves, lab)
    out = {}
    n_u = lab.n_unconfined
    if n_u:
        e1, e3, s_ax = c["e1"][:, :n_u], c["e3"][:, :n_u], c["s_ax"][:, :n_u]
        out["E_c"] = _slope(e1, s_ax, lab.window)  # Eq. 24
        out["nu"] = -_slope(e1, e3, lab.window)  # Eq. 25
        out["ucs"], _ = smooth_max(s_ax, lab.peak_width[0])
    if lab.p_values:
        q = 0.5 * (c["s_ax"] - c["s_lat"])[:, n_u:]
        q_peak, _ = smooth_max(q, lab.peak_width[1])
        out["q_peak"] = q_peak.reshape(len(lab.p_values), -1)
    return out


@eqx.filter_jit
def run(log_p: Array, lab: Lab) -> tuple[dict[str, Array], dict[str, Array], Array]:
    """Figures (:data:`FIGURES`), curves (:func:`simulate`) and error bits ``[K]`` of the
    lab for ``log_p`` = log of :data:`PARAMETERS`. Pure, jitted, differentiable."""
    curves, err = simulate(log_p, lab)
    return figures_of(curves, lab), curves, err


def figures(log_p: Array, lab: Lab) -> tuple[dict[str, Array], Array]:
    """Figures ``[K]`` of the lab (:data:`FIGURES`) and the error bits ``[K]``: :func:`run`
    without the curves (same compiled function)."""
    figs, _, err = run(log_p, lab)
    return figs, err


def check_errors(err) -> None:
    """Raise if any realisation of a lab run set an error bit, saying what to change."""
    e = np.atleast_1d(np.asarray(err))
    bad = int(np.bitwise_or.reduce(e))
    if not bad:
        return
    k = int(np.nonzero(e)[0][0])
    hint = "reduce the loading rate or the stiffness range, or check the parameters"
    if bad & (ERR_PAIR_OVERFLOW | ERR_CELL_OVERFLOW):
        hint = "rebuild the lab with a larger pair_headroom (capacities are fixed under grad)"
    raise RuntimeError(
        f"lab run failed in realisation {k}: {', '.join(describe_errors(int(e[k])))}; {hint}"
    )


# ------------------------------------------------------------------------------ builders


def _layout(n_steps: int, record_every: int, records_per_segment: int | None):
    """Segments of about sqrt(records) records each, covering ``n_steps`` steps."""
    n_rec = max(1, -(-int(n_steps) // record_every))
    rps = records_per_segment or max(1, round(math.sqrt(n_rec)))
    return -(-n_rec // rps), rps


def _finish(setup_states, *, pair_headroom: float, skin: float):
    cap = int(math.ceil(pair_headroom * bd.fit_pair_capacity(setup_states, skin)))
    return [bd.with_pair_capacity(s, cap) for s in setup_states]


def _time_step(params: Params, dt: float | None, safety: float) -> tuple[Params, float]:
    """``params`` with the time step ``dt`` (s) if given (at most the stability bound, i.e.
    ``params.dt / safety``), and that step."""
    if dt is None:
        return params, float(params.dt)
    bound = float(params.dt) / safety
    if not 0 < dt <= bound:
        raise ValueError(f"dt = {dt:.3e} s must lie in (0, {bound:.3e}] s (stability bound)")
    return replace(params, dt=jnp.asarray(dt, params.dt.dtype)), float(dt)


def _real_bonds(state: SimState) -> Array:
    return state.bonds.i < state.bonds.j


def _lab(kind, states, controls, params, grid, **kw) -> Lab:
    contact_damping = kw.pop("contact_damping", None)
    if contact_damping is not None:
        params = replace(params, normal_damping=jnp.asarray(contact_damping, params.dt.dtype))
    stacked = ens.stack(states)
    fd = stacked.particles.pos.dtype
    f = lambda x: jnp.asarray(x, fd)
    return Lab(
        kind=kind,
        state=stacked,
        controls=ens.stack(controls),
        params=params,
        grid=grid,
        real_bond=_real_bonds(stacked),
        ref=f(kw.pop("ref")),
        gauge0=f(kw.pop("gauge0", np.zeros((len(states), 4, 2)))),
        window=f(kw.pop("window", np.ones(1))),
        surrogate_width=f(kw.pop("surrogate_width")),
        peak_width=f(kw.pop("peak_width", 1.0)),
        diameter=f(kw.pop("diameter", 0.0)),
        thickness=f(kw.pop("thickness")),
        **kw,
    )


def brazilian_lab(
    cfg: bz.Config,
    seeds: list[int],
    *,
    surrogate_width: float = 0.2,
    peak_fraction: float = 0.02,
    max_strain: float | None = None,
    records_per_segment: int | None = None,
    pair_headroom: float = 1.5,
    damping: float = 0.0,
    contact_damping: float | None = None,
    dt: float | None = None,
) -> Lab:
    """A Brazilian lab of the discs of ``seeds`` (:mod:`jaxgran.scenes.bonded_brazilian`
    geometry, loading and material of ``cfg``), loaded to ``max_strain`` (default
    ``cfg.max_strain``). The smooth-maximum width is ``peak_fraction`` x the mean F_max of
    a reference run with ``cfg``'s parameters. ``damping`` (1/s) is a global viscous
    damping of the cells (:class:`jaxgran.scenes.bonded.Control`): it damps the dynamic
    fragmentation after the peak, whose sensitivity to the parameters is chaotic.
    ``contact_damping`` (1/s) replaces the material's normal contact damping G_n: the
    dashpot acts only while cells overlap, so a contact that opens or closes one step
    earlier makes the force jump by ``G_n m v_n``, and the figures become discontinuous in
    the parameters; 0 with a global ``damping`` keeps them smooth. ``dt`` (s) replaces the
    time step of ``cfg``'s material (0.5 of its stability bound), e.g. to give labs of
    different materials the same time discretisation; it may not exceed the bound."""
    setup = bz.build(cfg, seeds=list(seeds))
    states = _finish(setup.states, pair_headroom=pair_headroom, skin=float(setup.params.skin))
    controls = [bd.make_control(s, damping=damping) for s in states]
    params, dt = _time_step(setup.params, dt, cfg.dt_safety)
    n_steps = int(math.ceil((max_strain or cfg.max_strain) / cfg.strain_rate / dt))
    n_seg, rps = _layout(n_steps, cfg.record_every, records_per_segment)
    lab = _lab(
        "brazilian",
        states,
        controls,
        params,
        setup.grid,
        ref=np.asarray(setup.gap0),
        contact_damping=contact_damping,
        surrogate_width=surrogate_width,
        diameter=cfg.diameter,
        thickness=cfg.thickness,
        n_segments=n_seg,
        records_per_segment=rps,
        record_every=cfg.record_every,
    )
    _, curves, err = run(log_params(setup.material), lab)
    check_errors(err)
    force, _ = platen_curves(curves, lab)
    f_max = float(np.mean(np.max(np.asarray(force), axis=0)))
    return replace(lab, peak_width=jnp.asarray(peak_fraction * f_max, lab.peak_width.dtype))


def _axial_velocity(cfg: bx.Config) -> np.ndarray:
    v = 0.5 * cfg.strain_rate * cfg.height  # m/s, both walls closing
    return np.array([[0.0, v], [0.0, 0.0], [0.0, 0.0], [0.0, -v]])


def biaxial_lab(
    cfg: bx.Config,
    seeds: list[int],
    *,
    unconfined: bool = True,
    p_values=(),
    surrogate_width: float = 0.2,
    peak_fraction: float = 0.02,
    iso_time: float | None = None,
    max_strain: float | None = None,
    fit_range: tuple[float, float] = (0.1, 0.5),
    fit_strains: tuple[float, float] | None = None,
    records_per_segment: int | None = None,
    pair_headroom: float = 1.5,
    damping: float = 0.0,
    contact_damping: float | None = None,
    dt: float | None = None,
    require_peak: bool = False,
) -> Lab:
    """Biaxial lab (:mod:`jaxgran.scenes.bonded_biaxial` geometry, loading and material of
    ``cfg``) of the blocks of ``seeds``: with ``unconfined`` an unconfined compression of
    each block (lateral walls removed; E_c, nu, strength), and for every p of ``p_values``
    (Pa) a constant-p test of each block (q_peak): an isotropic stage of fixed length
    ``iso_time`` (s, default ``cfg.iso_max_time``) with four servo walls at p, then
    shearing with the lateral walls holding ``s3 = 2 p - s1``, all walls bonded to the block
    (paper 002 §4.3). All members run in one batch (one compilation): the unconfined blocks
    wait at rest during the isotropic stage, then every member's axial walls close at
    ``cfg.strain_rate`` up to ``max_strain`` (default ``cfg.max_strain``). E_c and nu are
    fitted over the records where the reference run's mean unconfined axial stress lies in
    ``fit_range`` x its peak (fixed afterwards), or, with ``fit_strains``, over the records
    whose nominal platen strain (``strain_rate x time`` of shearing) lies in that range (the
    same window for every parameter set and seed, as a laboratory would use).
    ``damping``, ``contact_damping`` and ``dt`` as for :func:`brazilian_lab`.
    With ``require_peak`` (for a ``ucs`` figure) the reference run's mean unconfined axial
    stress must peak before the last record, or ``ucs`` would only be the stress at
    ``max_strain`` (the lab raises ValueError then)."""
    p_values = tuple(float(p) for p in p_values)
    members = ([(s, 0.0) for s in seeds] if unconfined else []) + [
        (s, p) for p in p_values for s in seeds
    ]
    if not members:
        raise ValueError("nothing to run: unconfined=False and no p_values")
    n_u = len(seeds) if unconfined else 0
    walls = (bd.BOTTOM, bd.LEFT, bd.RIGHT, bd.TOP) if p_values else ()
    setup = bx.build(cfg, members, bond_walls=walls)
    skin = float(setup.params.skin)
    states = _finish(setup.states, pair_headroom=pair_headroom, skin=skin)
    vel = _axial_velocity(cfg)
    servo = [WALL_VELOCITY, WALL_SERVO, WALL_SERVO, WALL_VELOCITY]
    uncon = [WALL_VELOCITY, WALL_FIXED, WALL_FIXED, WALL_VELOCITY]
    first, controls, shear, modes = [], [], [], []
    for k, (s, (_, p)) in enumerate(zip(states, members, strict=True)):
        g = setup.gauges[k]
        if k < n_u:  # at rest (walls fixed, lateral ones removed, no wall bonds) until shearing
            w = replace(
                s.walls,
                mode=jnp.full((4,), WALL_FIXED, jnp.int32),
                vel=jnp.zeros_like(s.walls.vel),
                active=jnp.asarray([True, False, False, True]),
            )
            b = replace(s.bonds, wall_active=jnp.zeros_like(s.bonds.wall_active))
            s = replace(s, walls=w, bonds=b)
            controls.append(bd.make_control(s, box=True, gauges=g, damping=damping))
            shear.append(controls[-1])
            modes.append(uncon)
        else:
            kw = {"p_target": p, "box": True, "gauges": g, "damping": damping}
            controls.append(bd.make_control(s, **kw))
            shear.append(bd.make_control(s, p_constant=True, **kw))
            modes.append(servo)
        first.append(s)
    params, dt = _time_step(setup.params, dt, cfg.dt_safety)
    n_steps = int(math.ceil((max_strain or cfg.max_strain) / cfg.strain_rate / dt))
    n_seg, rps = _layout(n_steps, cfg.record_every, records_per_segment)
    per_seg = rps * cfg.record_every
    lead = 0
    if p_values:
        lead = max(1, -(-int(math.ceil((iso_time or cfg.iso_max_time) / dt)) // per_seg))
    fd = states[0].walls.vel.dtype
    lab = _lab(
        "biaxial",
        first,
        controls,
        params,
        setup.grid,
        ref=np.full(len(first), cfg.height),
        contact_damping=contact_damping,
        gauge0=np.asarray(setup.gauge0),
        window=np.ones(n_seg * rps),
        peak_width=np.ones(2),
        surrogate_width=surrogate_width,
        thickness=cfg.thickness,
        n_segments=n_seg,
        records_per_segment=rps,
        record_every=cfg.record_every,
        lead_segments=lead,
        n_unconfined=n_u,
        p_values=p_values,
        shear_controls=ens.stack(shear),
        shear_modes=jnp.asarray(np.array(modes), jnp.int32),
        shear_velocity=jnp.asarray(np.broadcast_to(vel, (len(first), 4, 2)), fd),
    )
    _, curves, err = run(log_params(setup.material), lab)
    check_errors(err)
    c = box_curves(curves, lab)
    window = np.ones(n_seg * rps)
    ucs = q = 1.0
    if n_u:
        s_ax = np.asarray(c["s_ax"][:, :n_u]).mean(axis=1)
        k = int(np.argmax(s_ax))
        if require_peak and k == s_ax.size - 1:
            raise ValueError(
                "the unconfined stress still rises at max_strain = "
                f"{max_strain or cfg.max_strain:g} ({s_ax[k] / 1e6:.4g} MPa at the last "
                "record): 'ucs' would be the final stress, not a strength; raise max_strain "
                "(scene option) or drop the ucs target"
            )
        lo, hi = fit_range
        window[:] = 0.0
        window[: k + 1] = (s_ax[: k + 1] >= lo * s_ax[k]) & (s_ax[: k + 1] <= hi * s_ax[k])
        if window.sum() < 3:
            raise ValueError(
                f"only {int(window.sum())} records in the E_c fit window; lower record_every "
                "or the strain rate"
            )
        ucs = float(s_ax[k])
        if fit_strains is not None:
            nominal = cfg.strain_rate * dt * cfg.record_every * np.arange(1, window.size + 1)
            window = ((nominal >= fit_strains[0]) & (nominal <= fit_strains[1])).astype(float)
    if p_values:
        qs = np.asarray(0.5 * (c["s_ax"] - c["s_lat"])[:, n_u:])
        q = float(qs.max(axis=0).mean())
    return replace(
        lab,
        window=jnp.asarray(window, fd),
        peak_width=jnp.asarray([peak_fraction * ucs, peak_fraction * q], fd),
    )


def with_surrogate_width(lab: Lab, width: float) -> Lab:
    """The same lab with another bond-health surrogate width (0: hard breakage)."""
    return replace(lab, surrogate_width=jnp.asarray(width, lab.surrogate_width.dtype))
