"""Ensembles: K realisations of one lab test in one ``jax.vmap``-ed call (DESIGN §7).

Realisations (different Voronoi seeds, or one specimen with different parameters) are built
to common capacities (particles, vertices, bonds, wall bonds, pairs; see
:class:`jaxgran.scenes.bonded.Capacities`), stacked on a leading axis K, and the jitted
segment runs under ``vmap``; the host loop checks every realisation's error bits after each
segment, grows a full pair list or cell list for all of them at once and repeats the
segment, so the stacked shapes stay common. Parameters are either shared or stacked too
(``params_batched``: a sweep over K_n, ...); per-bond moduli and thresholds are stacked
with the states. The same loop runs a single realisation without ``vmap``
(``batched=False``), so one code path serves both and K = 2 under ``vmap`` reproduces two
single runs to round-off.

**One rebuild decision per batch.** Under ``vmap`` a ``lax.cond`` whose predicate is
batched becomes a ``select`` that evaluates both branches, so a naively vmapped step would
rebuild the pair list at every step. :func:`batched_step` instead vmaps the loading control,
predicts every realisation's drifted positions (the kick and drift of
:func:`jaxgran.integrate.step`), takes ``any`` over the batch of
:func:`jaxgran.partition.needs_rebuild`, and passes that one unbatched flag to
:func:`jaxgran.integrate.step` (its ``rebuild`` argument), so the cond stays a branch: the
whole batch rebuilds when any member needs it, which changes the others by round-off only
(a rebuild carries the spring history over).

**Sharding over devices.** :func:`ensemble_mesh` makes a one-axis
:class:`jax.sharding.Mesh` (axis ``"realisation"``) over all devices and :func:`shard`
places a stacked pytree with its leading axis K split over it
(:class:`jax.sharding.NamedSharding` with ``PartitionSpec("realisation")``; K must be a
multiple of the device count); shared parameters are replicated (:func:`replicate`). The
jitted segment then runs each device's realisations where they live; only the batch-wide
rebuild flag (one boolean per step) crosses devices. :func:`drive` does this when given
``mesh``. On a CPU the same code is exercised with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` set before JAX starts.

**Several hosts.** Call ``jax.distributed.initialize(coordinator_address, num_processes,
process_id)`` in every process before anything else touches JAX (on SLURM / TPU pods the
arguments are found automatically); ``jax.devices()`` then lists the devices of all hosts
and ``ensemble_mesh()`` spans them. Each process builds only its own share of the
realisations (e.g. seeds ``process_index() * K_local + k``) and the global stacked arrays
are formed with ``jax.make_array_from_process_local_data(NamedSharding(mesh,
PartitionSpec("realisation")), local_stack)``; host-side reads of batched results (error
bits, records) go through :func:`to_host`, which gathers over processes
(``jax.experimental.multihost_utils.process_allgather``) when an array is not fully
addressable. Every process runs the same host loop, so all take the same decisions.
"""

from __future__ import annotations

import dataclasses
import logging
import time as _time
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .analysis import summary_stats
from .integrate import initial_forces, step
from .partition import needs_rebuild
from .scenes.bonded import Control, apply_control, n_broken, segment
from .simulate import Record, RunResult, SimulationError, grow_capacities, record
from .state import (
    ERR_CELL_OVERFLOW,
    ERR_LEFT_DOMAIN,
    ERR_NAN,
    ERR_PAIR_OVERFLOW,
    ERR_SKIN_EXCEEDED,
    Grid,
    Params,
    SimState,
    describe_errors,
    replace,
)

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ stacking


def stack(trees: list):
    """Stack pytrees of identical structure and shapes on a new leading axis K."""
    if not trees:
        raise ValueError("nothing to stack")
    shapes = [jax.tree.map(lambda x: jnp.shape(x), t) for t in trees]
    for k, s in enumerate(shapes[1:], start=1):
        if s != shapes[0]:
            raise ValueError(
                f"realisation {k} has other array shapes than realisation 0; build all of "
                "them with the same Capacities (jaxgran.scenes.bonded.Capacities.covering)"
            )
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def take(tree, k: int):
    """Realisation ``k`` of a stacked pytree."""
    return jax.tree.map(lambda x: x[k], tree)


def n_realisations(tree) -> int:
    return int(jax.tree.leaves(tree)[0].shape[0])


# ------------------------------------------------------------------------------ jitted parts


def drifted_positions(state: SimState, params: Params) -> Array:
    """Particle positions after the coming step's half kick and drift ``[P, 2]`` (m), the
    positions at which :func:`jaxgran.integrate.step` decides whether to rebuild."""
    p = state.particles
    dt = params.dt
    free = p.active & ~p.fixed
    inv_m = jnp.where(free, 1.0 / p.mass, 0.0)
    vel = p.vel + 0.5 * dt * p.force * inv_m[:, None]
    return jnp.where(p.active[:, None], p.pos + dt * vel, p.pos)


def _needs_rebuild(state: SimState, params: Params) -> Array:
    p = replace(state.particles, pos=drifted_positions(state, params))
    return needs_rebuild(p, state.contacts, params.skin)


def batched_step(
    states: SimState,
    params: Params,
    controls: Control,
    grid: Grid,
    params_batched: bool = False,
) -> tuple[SimState, Array]:
    """One controlled step (:func:`jaxgran.scenes.bonded.apply_control`, then
    :func:`jaxgran.integrate.step`) of K stacked realisations, with one pair-list rebuild
    decision for the whole batch (``any`` over K; see the module docstring). Returns the
    stacked states and the error bits ``[K]``. Not jitted; differentiable."""
    pax = 0 if params_batched else None
    states = jax.vmap(apply_control, in_axes=(0, pax, 0))(states, params, controls)
    rebuild = jnp.any(jax.vmap(_needs_rebuild, in_axes=(0, pax))(states, params))
    one = lambda s, p: step(s, p, grid, rebuild)
    return jax.vmap(one, in_axes=(0, pax))(states, params)


def batched_segment(
    states: SimState,
    params: Params,
    controls: Control,
    grid: Grid,
    n_records: int,
    record_every: int,
    params_batched: bool = False,
    remat: bool = False,
) -> tuple[SimState, Record, dict[str, Array], Array]:
    """:func:`jaxgran.scenes.bonded.segment` for K stacked realisations, stepping with
    :func:`batched_step`. Returns the stacked states, records and extra series with the
    record axis first (``[n_records, K, ...]``) and the error bits ``[K]``. Not jitted.
    With ``remat`` every record interval is a :func:`jax.checkpoint` (reverse mode keeps
    one state per record and recomputes the ``record_every`` steps; no effect on a forward
    run)."""

    def inner(carry, _):
        s, err, wf = carry
        s, e = batched_step(s, params, controls, grid, params_batched)
        return (s, err | e, wf + s.walls.force), None

    def outer(carry, _):
        s, err = carry
        wf0 = jnp.zeros_like(s.walls.force)
        (s, err, wf), _ = jax.lax.scan(inner, (s, err, wf0), None, length=record_every)
        rec = jax.vmap(record)(s, wf / record_every)
        extra = {
            "n_broken": jax.vmap(n_broken)(s),
            "gauge_position": jnp.einsum("kgp,kpd->kgd", controls.gauges, s.particles.pos),
        }
        return (s, err), (rec, extra)

    if remat:
        outer = jax.checkpoint(outer)
    k = states.time.shape[0]
    (states, err), (recs, extra) = jax.lax.scan(
        outer, (states, jnp.zeros((k,), jnp.int32)), None, length=n_records
    )
    return states, recs, extra, err


@eqx.filter_jit
def run_segments(
    states: SimState,
    params: Params,
    controls: Control,
    grid: Grid,
    n_records: int,
    record_every: int,
    params_batched: bool = False,
):
    """:func:`jaxgran.scenes.bonded.segment` over the leading axis K of ``states`` and
    ``controls`` (and of ``params`` when ``params_batched``), with one rebuild decision per
    step for the batch (:func:`batched_segment`). Returns stacked states, records
    ``[K, n_records, ...]``, extra series ``[K, n_records, ...]``, errors ``[K]``. Sharded
    inputs (:func:`shard`) keep their sharding."""
    out = batched_segment(states, params, controls, grid, n_records, record_every, params_batched)
    new, recs, extra, err = out
    k_first = lambda t: jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), t)
    return new, k_first(recs), k_first(extra), err


@eqx.filter_jit
def run_segments_naive(
    states: SimState,
    params: Params,
    controls: Control,
    grid: Grid,
    n_records: int,
    record_every: int,
    params_batched: bool = False,
):
    """``vmap`` of the single-realisation segment, each member deciding its own rebuild
    (so every step rebuilds under ``vmap``); kept for the benchmark's comparison."""

    def one(s, p, c):
        return segment(s, p, c, grid, n_records, record_every)

    return jax.vmap(one, in_axes=(0, 0 if params_batched else None, 0))(states, params, controls)


# ------------------------------------------------------------------------------ sharding

ENSEMBLE_AXIS = "realisation"


def ensemble_mesh(devices=None) -> Mesh:
    """A one-axis mesh (axis ``"realisation"``) over ``devices`` (default: all devices of
    all processes, ``jax.devices()``)."""
    devs = np.asarray(jax.devices() if devices is None else list(devices))
    return Mesh(devs.reshape(-1), (ENSEMBLE_AXIS,))


def shard(tree, mesh: Mesh):
    """Place a stacked pytree (leading axis K on every leaf) with K split over the mesh's
    ensemble axis. K must be a multiple of the number of devices of the mesh."""
    n_dev = mesh.shape[ENSEMBLE_AXIS]
    k = n_realisations(tree)
    if k % n_dev:
        raise ValueError(
            f"{k} realisations cannot be split evenly over {n_dev} devices; use a multiple of "
            f"{n_dev} realisations (e.g. {n_dev * -(-k // n_dev)}) or a mesh of fewer devices"
        )
    spec = NamedSharding(mesh, PartitionSpec(ENSEMBLE_AXIS))
    return jax.tree.map(lambda x: jax.device_put(x, spec), tree)


def replicate(tree, mesh: Mesh):
    """Place a pytree shared by all realisations (e.g. :class:`Params`) on every device."""
    spec = NamedSharding(mesh, PartitionSpec())
    return jax.tree.map(lambda x: jax.device_put(x, spec), tree)


def to_host(x) -> np.ndarray:
    """Host copy of a (possibly sharded, possibly multi-host) array."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


@eqx.filter_jit
def _prepare_single(state: SimState, params: Params, grid: Grid):
    return initial_forces(state, params, grid)


@eqx.filter_jit
def _prepare_batched(states: SimState, params: Params, grid: Grid, params_batched: bool):
    f = lambda s, p: initial_forces(s, p, grid)
    return jax.vmap(f, in_axes=(0, 0 if params_batched else None))(states, params)


@eqx.filter_jit
def _run_single(state, params, control, grid, n_records, record_every):
    return segment(state, params, control, grid, n_records, record_every)


# ------------------------------------------------------------------------------ host loop


def frame(state: SimState) -> dict[str, np.ndarray]:
    """Host copy of a frame of a bonded run (stacked arrays keep their K axis): the
    simulator's frame plus the bond state."""
    from .simulate import frame_of

    return frame_of(state) | {"bond_intact": np.asarray(state.bonds.intact)}


@dataclasses.dataclass
class EnsembleResult:
    """What :func:`drive` returns. With ``batched`` every array has the realisation axis K
    first (series: ``[R, K, ...]``, record axis first as in :class:`RunResult`)."""

    state: SimState
    series: dict[str, np.ndarray]
    frames: list[dict[str, np.ndarray]]
    grid: Grid
    steps: int
    wall_time_s: float
    regrows: list[str]
    stopped_early: bool
    batched: bool

    @property
    def size(self) -> int:
        return int(self.state.time.shape[0]) if self.batched else 1

    def realisation(self, k: int = 0) -> RunResult:
        """Realisation ``k`` as a plain :class:`jaxgran.simulate.RunResult` (for io)."""
        if not self.batched:
            if k != 0:
                raise IndexError("a single run has only realisation 0")
            return RunResult(
                self.state,
                self.series,
                self.frames,
                self.grid,
                self.steps,
                self.wall_time_s,
                self.regrows,
                self.stopped_early,
            )
        series = {key: v[:, k] for key, v in self.series.items()}
        frames = [{key: v[k] for key, v in fr.items()} for fr in self.frames]
        return RunResult(
            take(self.state, k),
            series,
            frames,
            self.grid,
            self.steps,
            self.wall_time_s,
            self.regrows,
            self.stopped_early,
        )


def _fatal(err: np.ndarray) -> None:
    bad = np.nonzero(err & (ERR_NAN | ERR_LEFT_DOMAIN | ERR_SKIN_EXCEEDED))[0]
    if not bad.size:
        return
    k = int(bad[0])
    names = ", ".join(describe_errors(int(err[k])))
    hint = {
        ERR_NAN: "reduce dt (dt_safety) or check the stiffnesses",
        ERR_LEFT_DOMAIN: "enlarge the grid margin or check the walls",
        ERR_SKIN_EXCEEDED: "reduce dt or the loading speed, or increase the skin",
    }
    what = "; ".join(v for b, v in hint.items() if int(err[k]) & b)
    raise SimulationError(f"realisation {k}: {names}; {what}")


def _bar_note(rec: dict) -> str:
    """Progress-bar note after a segment: simulated time (s) and bonds broken so far (the
    range over the realisations of a batched run)."""
    t = float(np.max(rec["time"][-1]))
    nb = np.atleast_1d(rec["n_broken"][-1])
    lo, hi = int(np.min(nb)), int(np.max(nb))
    broken = f"{lo}" if lo == hi else f"{lo}-{hi}"
    return f"t={t:.4g} s, bonds broken={broken}"


def drive(
    state: SimState,
    params: Params,
    control: Control,
    grid: Grid,
    *,
    n_steps: int,
    record_every: int = 50,
    records_per_segment: int = 10,
    batched: bool = False,
    params_batched: bool = False,
    callback: Callable | None = None,
    frame_every: int = 1,
    progress: bool = True,
    desc: str = "bonded",
    max_regrows: int = 8,
    mesh: Mesh | None = None,
) -> EnsembleResult:
    """Run a bonded test (one realisation, or K stacked ones with ``batched``) for up to
    ``n_steps`` steps in segments of ``record_every x records_per_segment`` steps.

    ``callback(state, records) -> (state, stop)`` runs on the host after each segment;
    ``records`` holds the Record fields, ``n_broken`` and ``gauge_position``
    (``[n_records, ...]`` or ``[n_records, K, ...]``). A stop ends the run for all
    realisations. With ``mesh`` (:func:`ensemble_mesh`) a batched run is sharded over the
    mesh's devices along K (:func:`shard`); the result is the same to round-off.
    """
    from tqdm.auto import tqdm

    if mesh is not None and batched:
        state, control = shard(state, mesh), shard(control, mesh)
        params = shard(params, mesh) if params_batched else replicate(params, mesh)

    t0 = _time.perf_counter()
    regrows: list[str] = []
    seg = record_every * records_per_segment
    n_seg = max(1, -(-int(n_steps) // seg))

    def prep(s, g):
        if batched:
            return _prepare_batched(s, params, g, params_batched)
        return _prepare_single(s, params, g)

    tries = 0
    while True:
        ready, err = prep(state, grid)
        err_all = int(np.bitwise_or.reduce(np.atleast_1d(to_host(err))))
        if err_all & (ERR_CELL_OVERFLOW | ERR_PAIR_OVERFLOW) and tries < max_regrows:
            state, grid = grow_capacities(state, ready, grid, err_all, regrows)
            if mesh is not None and batched:
                state = shard(state, mesh)
            tries += 1
            continue
        _fatal(np.atleast_1d(to_host(err)))
        break
    state = ready
    frames = [frame(state)]
    series: dict[str, list] = {}
    stopped = False
    done = 0
    bar = tqdm(total=n_seg * seg, desc=desc, disable=not progress, unit="step")
    for k in range(n_seg):
        start, tries = state, 0
        while True:
            if batched:
                out = run_segments(
                    start,
                    params,
                    control,
                    grid,
                    records_per_segment,
                    record_every,
                    params_batched,
                )
            else:
                out = _run_single(start, params, control, grid, records_per_segment, record_every)
            new, recs, extra, err = out
            err = np.atleast_1d(to_host(err))
            err_all = int(np.bitwise_or.reduce(err))
            if err_all & (ERR_CELL_OVERFLOW | ERR_PAIR_OVERFLOW):
                if tries >= max_regrows:
                    raise SimulationError(f"capacity still exceeded after {tries} regrowths")
                start, grid = grow_capacities(start, new, grid, err_all, regrows)
                if mesh is not None and batched:
                    start = shard(start, mesh)
                tries += 1
                continue
            break
        _fatal(err)
        state = new
        rec = {f.name: to_host(getattr(recs, f.name)) for f in dataclasses.fields(recs)}
        rec.update({key: to_host(v) for key, v in extra.items()})
        if batched:  # [K, R, ...] -> [R, K, ...] (record axis first, as in simulate)
            rec = {key: np.swapaxes(v, 0, 1) for key, v in rec.items()}
        for key, val in rec.items():
            series.setdefault(key, []).append(val)
        done += seg
        bar.set_postfix_str(_bar_note(rec), refresh=False)
        bar.update(seg)
        if (k + 1) % frame_every == 0:
            frames.append(frame(state))
        if callback is not None:
            state, stop = callback(state, rec)
            if stop:
                stopped = True
                break
    bar.close()
    if (k + 1) % frame_every != 0:
        frames.append(frame(state))
    jax.block_until_ready(state)
    return EnsembleResult(
        state=state,
        series={key: np.concatenate(v, axis=0) for key, v in series.items()},
        frames=frames,
        grid=grid,
        steps=done,
        wall_time_s=_time.perf_counter() - t0,
        regrows=regrows,
        stopped_early=stopped,
        batched=batched,
    )


def ensemble_summary(per_realisation: list[dict]) -> dict:
    """One summary from the realisations' summaries: for one realisation its own; for K > 1
    the mean of every numeric figure under its key, the standard deviation (n - 1) under
    ``<key>_std``, ``realisations`` = K and the individual values under
    ``per_realisation``."""
    if len(per_realisation) == 1:
        return dict(per_realisation[0])
    out: dict = {"realisations": len(per_realisation)}
    for key, s in summary_stats(per_realisation).items():
        out[key] = s["mean"]
        out[key + "_std"] = s["std"]
    out["per_realisation"] = per_realisation
    return out
