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

Note on cost: ``vmap`` turns the pair-list rebuild's ``lax.cond`` (inside
:func:`jaxgran.integrate.step`) into a ``select``, so a batched segment rebuilds the pair
list every step. Bonded solids hardly move, so single runs rebuild rarely, and on a 2-core
CPU the batch runs at 0.5-0.6x the realisation-steps per second of sequential runs
(``benchmarks/bench_bonded.py``, 200-cell discs, K = 1-32). Passing the rebuild decision
into the step from outside the vmap (``any`` over the batch) would keep the cond a cond.
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

from .analysis import summary_stats
from .integrate import initial_forces
from .scenes.bonded import Control, segment
from .simulate import RunResult, SimulationError, grow_pairs
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
    ``controls`` (and of ``params`` when ``params_batched``). Returns stacked states,
    records ``[K, n_records, ...]``, extra series ``[K, n_records, ...]``, errors ``[K]``."""

    def one(s, p, c):
        return segment(s, p, c, grid, n_records, record_every)

    return jax.vmap(one, in_axes=(0, 0 if params_batched else None, 0))(states, params, controls)


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


def _grow(states, grid: Grid, err: int, regrows: list[str], batched: bool):
    if err & ERR_CELL_OVERFLOW:
        new = grid.cell_capacity * 2
        regrows.append(f"cell capacity {grid.cell_capacity} exceeded; grown to {new}")
        grid = dataclasses.replace(grid, cell_capacity=new)
    if err & ERR_PAIR_OVERFLOW:
        c = states.contacts.pairs.shape[-2]
        regrows.append(f"pair capacity {c} exceeded; grown to {2 * c}")
        grow = lambda cts: grow_pairs(cts, 2 * c)
        contacts = jax.vmap(grow)(states.contacts) if batched else grow(states.contacts)
        states = replace(states, contacts=contacts)
    log.info(regrows[-1])
    return states, grid


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
) -> EnsembleResult:
    """Run a bonded test (one realisation, or K stacked ones with ``batched``) for up to
    ``n_steps`` steps in segments of ``record_every x records_per_segment`` steps.

    ``callback(state, records) -> (state, stop)`` runs on the host after each segment;
    ``records`` holds the Record fields, ``n_broken`` and ``gauge_position``
    (``[n_records, ...]`` or ``[n_records, K, ...]``). A stop ends the run for all
    realisations.
    """
    from tqdm.auto import tqdm

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
        err_all = int(np.bitwise_or.reduce(np.atleast_1d(np.asarray(err))))
        if err_all & (ERR_CELL_OVERFLOW | ERR_PAIR_OVERFLOW) and tries < max_regrows:
            state, grid = _grow(state, grid, err_all, regrows, batched)
            tries += 1
            continue
        _fatal(np.atleast_1d(np.asarray(err)))
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
            err = np.atleast_1d(np.asarray(err))
            err_all = int(np.bitwise_or.reduce(err))
            if err_all & (ERR_CELL_OVERFLOW | ERR_PAIR_OVERFLOW):
                if tries >= max_regrows:
                    raise SimulationError(f"capacity still exceeded after {tries} regrowths")
                start, grid = _grow(start, grid, err_all, regrows, batched)
                tries += 1
                continue
            break
        _fatal(err)
        state = new
        rec = {f.name: np.asarray(getattr(recs, f.name)) for f in dataclasses.fields(recs)}
        rec.update({key: np.asarray(v) for key, v in extra.items()})
        if batched:  # [K, R, ...] -> [R, K, ...] (record axis first, as in simulate)
            rec = {key: np.swapaxes(v, 0, 1) for key, v in rec.items()}
        for key, val in rec.items():
            series.setdefault(key, []).append(val)
        done += seg
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
