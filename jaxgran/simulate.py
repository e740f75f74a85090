"""The time loop: a jit-compiled segment of steps, and the host loop around it.

``run_segment`` is one ``lax.scan`` over ``n_records x record_every`` steps; it returns the new
state, one record every ``record_every`` steps and the OR of the per-step error bits. The host
loop (:func:`simulate`) checks the bits after each segment: a full cell or pair list is grown
and the segment repeated from its start (so results do not depend on the initial capacity),
NaN or an escaped particle stops the run with an error that says what to do. Between segments
a callback may change the state on the host (breakage, loading stages) and decide to stop.
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

from .contact import pair_forces, wall_forces
from .integrate import initial_forces, step
from .partition import cell_count_max
from .state import (
    ERR_CELL_OVERFLOW,
    ERR_LEFT_DOMAIN,
    ERR_NAN,
    ERR_PAIR_OVERFLOW,
    ERR_SKIN_EXCEEDED,
    Contacts,
    Grid,
    Params,
    SimState,
    describe_errors,
    replace,
)

log = logging.getLogger(__name__)


class SimulationError(RuntimeError):
    """A run cannot continue (NaN, particle escaped, step too large)."""


class Record(eqx.Module):
    """Time series sampled every ``record_every`` steps (leading axis = record)."""

    time: Array
    kinetic_energy: Array  # J (translational + rotational), per unit thickness slab
    rotational_energy: Array  # J
    mean_speed: Array  # m/s over active particles
    mean_angular_speed: Array  # rad/s
    wall_point: Array  # [W, 2] m
    wall_force: Array  # [W, 2] N, force of the particles on each wall, mean over the interval
    n_active: Array


def record(state: SimState, wall_force_mean: Array | None = None) -> Record:
    """Sample the time series; ``wall_force_mean`` is the wall force averaged over the steps
    since the last record (an instantaneous sample would alias the packing's vibrations)."""
    p = state.particles
    act = p.active
    ke_t = 0.5 * jnp.sum(jnp.where(act, p.mass * jnp.sum(p.vel**2, axis=-1), 0.0))
    ke_r = 0.5 * jnp.sum(jnp.where(act, p.inertia * p.omega**2, 0.0))
    n = jnp.maximum(jnp.sum(act), 1)
    speed = jnp.sum(jnp.where(act, jnp.linalg.norm(p.vel, axis=-1), 0.0)) / n
    ang = jnp.sum(jnp.where(act, jnp.abs(p.omega), 0.0)) / n
    return Record(
        time=state.time,
        kinetic_energy=ke_t + ke_r,
        rotational_energy=ke_r,
        mean_speed=speed,
        mean_angular_speed=ang,
        wall_point=state.walls.point,
        wall_force=state.walls.force if wall_force_mean is None else wall_force_mean,
        n_active=jnp.sum(act).astype(jnp.int32),
    )


@eqx.filter_jit
def run_segment(
    state: SimState, params: Params, grid: Grid, n_records: int, record_every: int
) -> tuple[SimState, Record, Array]:
    """Run ``n_records * record_every`` steps in one compiled scan.

    Returns the final state, ``n_records`` records and the error bitmask (OR over steps).
    """

    def inner(carry, _):
        s, err, wf = carry
        s, e = step(s, params, grid)
        return (s, err | e, wf + s.walls.force), None

    def outer(carry, _):
        s, err = carry
        wf0 = jnp.zeros_like(s.walls.force)
        (s, err, wf), _ = jax.lax.scan(inner, (s, err, wf0), None, length=record_every)
        return (s, err), record(s, wf / record_every)

    (state, err), recs = jax.lax.scan(
        outer, (state, jnp.zeros((), jnp.int32)), None, length=n_records
    )
    return state, recs, err


@eqx.filter_jit
def prepare(state: SimState, params: Params, grid: Grid) -> tuple[SimState, Array]:
    """Build the pair list and the forces of the initial configuration."""
    return initial_forces(state, params, grid)


def grow_pairs(contacts: Contacts, new_capacity: int) -> Contacts:
    """Return ``contacts`` with room for ``new_capacity`` pairs (sentinel padding)."""
    c = contacts.pairs.shape[0]
    if new_capacity <= c:
        return contacts
    extra = new_capacity - c
    sentinel = int(contacts.ref_pos.shape[0])
    pairs = jnp.concatenate(
        [contacts.pairs, jnp.full((extra, 2), sentinel, contacts.pairs.dtype)], axis=0
    )
    shape = list(contacts.xi.shape)
    shape[1] = extra
    xi = jnp.concatenate([contacts.xi, jnp.zeros(shape, contacts.xi.dtype)], axis=1)
    return replace(contacts, pairs=pairs, xi=xi)


@dataclasses.dataclass
class RunResult:
    """What :func:`simulate` returns: final state, time series, frames, timing."""

    state: SimState
    series: dict[str, np.ndarray]
    frames: list[dict[str, np.ndarray]]
    grid: Grid
    steps: int
    wall_time_s: float
    regrows: list[str]
    stopped_early: bool = False
    params: Params | None = None


def pair_capacity_needed(contacts: Contacts) -> int:
    """Pair capacity to grow to after a pair overflow: the capacity doubled as often as it
    takes to hold the largest count a build needed (``contacts.n_pairs``, which after an
    overflow keeps the largest count found; the largest over the realisations of a batch),
    at least once. The capacities are those repeated doubling reaches, so compiled shapes
    are shared, in one regrowth (one compilation) instead of one per doubling."""
    return _doubled_to_hold(int(contacts.capacity), int(np.max(np.asarray(contacts.n_pairs))))


def cell_capacity_needed(grid: Grid, *states: SimState) -> int:
    """Cell capacity to grow to after a cell overflow: doubled as often as it takes to hold
    the fullest cell of ``states`` (the segment's start and the overflowing run's end;
    :func:`jaxgran.partition.cell_count_max`), at least once. A cell that filled up only
    in between is caught by the next try."""
    return _doubled_to_hold(
        grid.cell_capacity, max(cell_count_max(s.particles, grid) for s in states)
    )


def _doubled_to_hold(capacity: int, need: int) -> int:
    """``capacity`` doubled at least once and until it is at least ``need``."""
    new = 2 * capacity
    while new < need:
        new *= 2
    return new


def grow_capacities(
    start: SimState, overflowed: SimState, grid: Grid, err: int, regrows: list[str]
) -> tuple[SimState, Grid]:
    """``start`` and ``grid`` with the capacities that ``overflowed`` (the run from ``start``
    that set the overflow bits ``err``) needed, in one regrowth each
    (:func:`pair_capacity_needed`, :func:`cell_capacity_needed`); each change is logged in
    ``regrows``. States may carry a leading realisation axis (an ensemble batch)."""
    if err & ERR_CELL_OVERFLOW:
        new_cap = cell_capacity_needed(grid, start, overflowed)
        msg = f"cell capacity {grid.cell_capacity} exceeded; grown to {new_cap}"
        grid = dataclasses.replace(grid, cell_capacity=new_cap)
        regrows.append(msg)
        log.info(msg)
    if err & ERR_PAIR_OVERFLOW:
        c = start.contacts.capacity
        new_c = pair_capacity_needed(overflowed.contacts)
        msg = f"pair capacity {c} exceeded; grown to {new_c}"

        def grow(cts):
            return grow_pairs(cts, new_c)

        start = replace(
            start,
            contacts=jax.vmap(grow)(start.contacts)
            if start.contacts.pairs.ndim == 3
            else grow(start.contacts),
        )
        regrows.append(msg)
        log.info(msg)
    return start, grid


def _fatal(err: int, state: SimState) -> None:
    if err & ERR_NAN:
        raise SimulationError(
            "NaN or inf appeared in the state; the time step is probably too large for the "
            "stiffness (use jaxgran.integrate.stable_time_step) or a particle has zero mass"
        )
    if err & ERR_LEFT_DOMAIN:
        raise SimulationError(
            "a particle left the simulation domain; enlarge the domain (grid bounds) or check "
            "that walls enclose the particles"
        )
    if err & ERR_SKIN_EXCEEDED:
        raise SimulationError(
            "a particle moved more than half the Verlet skin in one step, so contacts could be "
            "missed; reduce dt or increase params.skin"
        )


@eqx.filter_jit
def contact_force_magnitude(state: SimState, params: Params) -> Array:
    """Sum over each particle's contacts (pairs and walls) of |F| ``[P]`` (N)."""
    p = state.particles
    _, _, _, info = pair_forces(p, state.contacts, params)
    mag = jnp.linalg.norm(info["force"], axis=-1).sum(axis=2)  # [C, 2]
    n_p = p.pos.shape[0]
    i, j = state.contacts.pairs[:, 0], state.contacts.pairs[:, 1]
    tot = mag.sum(axis=1)
    out = jax.ops.segment_sum(tot, i, num_segments=n_p) + jax.ops.segment_sum(
        tot, j, num_segments=n_p
    )
    *_, winfo = wall_forces(p, state.walls, state.contacts.wall_xi, params)
    return out + jnp.linalg.norm(winfo["force"], axis=-1).sum(axis=(1, 2))


def frame_of(state: SimState, params: Params | None = None) -> dict[str, np.ndarray]:
    """Host copy of what a frame stores (positions, angles, velocities, forces, and with
    ``params`` the contact-force magnitude per particle)."""
    p = state.particles
    extra = {}
    if params is not None:
        extra["contact_force"] = np.asarray(contact_force_magnitude(state, params))
    return extra | {
        "time": np.asarray(state.time),
        "pos": np.asarray(p.pos),
        "angle": np.asarray(p.angle),
        "vel": np.asarray(p.vel),
        "omega": np.asarray(p.omega),
        "force": np.asarray(p.force),
        "active": np.asarray(p.active),
        "wall_point": np.asarray(state.walls.point),
        "wall_force": np.asarray(state.walls.force),
        # shapes change when particles break, so every frame keeps its own
        "verts": np.asarray(p.verts),
        "n_verts": np.asarray(p.n_verts),
        "radius": np.asarray(p.radius),
        "uid": np.asarray(p.uid),
    }


def simulate(
    state: SimState,
    params: Params,
    grid: Grid,
    *,
    n_steps: int,
    record_every: int = 100,
    records_per_segment: int = 10,
    frame_every: int = 1,
    callback: Callable[[SimState, dict[str, np.ndarray]], tuple] | None = None,
    progress: bool = True,
    max_regrows: int = 8,
    prepared: bool = False,
    desc: str = "simulate",
    checkpoint: Callable[[dict], None] | None = None,
    checkpoint_every_s: float = 600.0,
    resume: dict | None = None,
    progress_note: Callable[[dict[str, np.ndarray]], str] | None = None,
) -> RunResult:
    """Run ``n_steps`` steps (rounded up to whole segments) with host checks between segments.

    Args:
        record_every: steps between two records of the time series.
        records_per_segment: records per compiled segment (segment length =
            ``record_every * records_per_segment`` steps).
        frame_every: keep a frame every this many segments (and always the last).
        callback: ``callback(state, last_records) -> (state, stop)`` or ``(state, stop,
            params)`` run on the host after each segment (breakage, stage changes, stopping
            criteria). It may change values but not capacities (or it must also rebuild
            contacts); returned ``params`` (e.g. a smaller ``dt`` once fragments appear) are
            used from the next segment on, without recompiling. ``RunResult.params`` holds
            the last ones.
        prepared: the state already carries a pair list and forces (skip :func:`prepare`).
        progress_note: ``progress_note(last_records) -> str``, called after each segment's
            callback, is shown after the simulated time and kinetic energy on the progress
            bar (how close a run that stops on a criterion is to stopping).
        checkpoint: ``checkpoint(payload)`` is called after a segment's callback once
            ``checkpoint_every_s`` seconds (wall clock) have passed since the start or the
            last call; ``payload`` holds what ``resume`` needs (``state``, ``params``,
            ``grid``, ``series``, ``frames``, ``segment``, ``done``, ``regrows``, the wall
            time so far). The caller saves it with whatever its callback needs (e.g. a
            pickle, see :func:`jaxgran.io.save_checkpoint`).
        resume: a ``payload`` given to ``checkpoint`` by an earlier call with the same
            ``n_steps`` and segment length: the run continues from it (its ``state``,
            ``params`` and ``grid`` replace the arguments) and returns what the uninterrupted
            run would have returned. Must be used with the same callback state as when it
            was saved.
    """
    from tqdm.auto import tqdm

    counts = {
        "n_steps": n_steps,
        "record_every": record_every,
        "records_per_segment": records_per_segment,
        "frame_every": frame_every,
    }
    for name, value in counts.items():
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"simulate: {name} must be an integer >= 1, got {value!r}")
    if not checkpoint_every_s >= 0:  # 0: a checkpoint after every segment
        raise ValueError(f"simulate: checkpoint_every_s must be >= 0, got {checkpoint_every_s!r}")
    seg_steps = record_every * records_per_segment
    n_seg = max(1, -(-int(n_steps) // seg_steps))
    t0 = _time.perf_counter()
    regrows: list[str] = []
    series: dict[str, list] = {}
    first, done, wall_before = 0, 0, 0.0
    if resume is not None:
        if int(resume["n_seg"]) != n_seg or int(resume["seg_steps"]) != seg_steps:
            raise ValueError(
                f"resume: the checkpoint was taken in a run of {resume['n_seg']} segments of "
                f"{resume['seg_steps']} steps, this run has {n_seg} of {seg_steps}"
            )
        state, params, grid = resume["state"], resume["params"], resume["grid"]
        regrows = list(resume["regrows"])
        series = {k: list(v) for k, v in resume["series"].items()}
        frames = list(resume["frames"])
        first, done = int(resume["segment"]), int(resume["done"])
        wall_before = float(resume["wall_time_s"])
    else:
        if not prepared:
            state, err = prepare(state, params, grid)
            state, grid, err = _grow_until_ok(state, params, grid, int(err), regrows, max_regrows)
            _fatal(err, state)
        frames = [frame_of(state, params)]
    stopped = False
    bar = tqdm(total=n_seg * seg_steps, initial=done, desc=desc, disable=not progress, unit="step")
    t_saved = _time.perf_counter()
    for k in range(first, n_seg):
        start = state
        tries = 0
        while True:
            new, recs, err = run_segment(start, params, grid, records_per_segment, record_every)
            err = int(err)
            if err & (ERR_CELL_OVERFLOW | ERR_PAIR_OVERFLOW):
                if tries >= max_regrows:
                    raise SimulationError(f"capacity still exceeded after {tries} regrowths")
                # the list fitted at the segment start, so padding it and repeating the
                # segment reproduces exactly what an ample capacity would have given
                start, grid = grow_capacities(start, new, grid, err, regrows)
                tries += 1
                continue
            break
        _fatal(err, new)
        state = new
        rec = {f.name: np.asarray(getattr(recs, f.name)) for f in dataclasses.fields(recs)}
        for key, val in rec.items():
            series.setdefault(key, []).append(val)
        done += seg_steps
        # simulated time and kinetic energy: runs that stop on a criterion (settling, a
        # post-peak drop) end before the bar does, and these show how close they are
        note = f"t={float(rec['time'][-1]):.4g} s, KE={float(rec['kinetic_energy'][-1]):.3g} J"
        if (k + 1) % frame_every == 0 or k == n_seg - 1:
            frames.append(frame_of(state, params))
        stop = False
        if callback is not None:
            out = callback(state, rec)
            if len(out) == 3:
                state, stop, params = out
            else:
                state, stop = out
        if progress_note is not None:
            note += ", " + progress_note(rec)
        bar.set_postfix_str(note, refresh=False)
        bar.update(seg_steps)
        if stop:
            stopped = True
            if (k + 1) % frame_every != 0:
                frames.append(frame_of(state, params))
            break
        if checkpoint is not None and k + 1 < n_seg:
            now = _time.perf_counter()
            if now - t_saved >= checkpoint_every_s:
                checkpoint(
                    {
                        "state": state,
                        "params": params,
                        "grid": grid,
                        "series": series,
                        "frames": frames,
                        "segment": k + 1,
                        "done": done,
                        "regrows": regrows,
                        "n_seg": n_seg,
                        "seg_steps": seg_steps,
                        "wall_time_s": wall_before + now - t0,
                    }
                )
                t_saved = _time.perf_counter()
    bar.close()
    jax.block_until_ready(state)
    out = {k: np.concatenate(v, axis=0) for k, v in series.items()}
    return RunResult(
        state=state,
        series=out,
        frames=frames,
        grid=grid,
        steps=done,
        wall_time_s=wall_before + _time.perf_counter() - t0,
        regrows=regrows,
        stopped_early=stopped,
        params=params,
    )


def _grow_until_ok(state, params, grid, err, regrows, max_regrows):
    tries = 0
    while err & (ERR_CELL_OVERFLOW | ERR_PAIR_OVERFLOW):
        if tries >= max_regrows:
            raise SimulationError(f"capacity still exceeded after {tries} regrowths")
        state, grid = grow_capacities(state, state, grid, err, regrows)
        state, e = prepare(state, params, grid)
        err = int(e)
        tries += 1
    return state, grid, err


def describe(err: int) -> str:
    """Human-readable error bits."""
    return ", ".join(describe_errors(err)) or "ok"
