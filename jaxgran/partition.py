"""Broad phase: a cell list builds a Verlet pair list of fixed capacity.

Every pair whose bounding circles (circumradius + sphero-radius) are closer than the skin goes
into the list; the list is rebuilt when some particle has moved more than half the skin since
the last build, so no contact can be missed in between (paper 000 Table I, Verlet distance).
Capacities are static. A full cell or a full pair list raises a flag in the error bitmask and
never truncates silently: the host grows the capacity and repeats the segment.

The list is kept sorted lexicographically by (i, j), so the tangential spring history is
carried over a rebuild by binary search of each new pair in the old list.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .state import (
    ERR_CELL_OVERFLOW,
    ERR_LEFT_DOMAIN,
    ERR_PAIR_OVERFLOW,
    Contacts,
    Grid,
    Particles,
)


def cell_coordinates(pos: Array, grid: Grid) -> tuple[Array, Array, Array]:
    """Integer cell coordinates ``[P]`` x2 (clamped) and an in-domain mask ``[P]``."""
    origin = jnp.asarray(grid.origin, dtype=pos.dtype)
    f = jnp.floor((pos - origin) / jnp.asarray(grid.cell_size, dtype=pos.dtype))
    inside = (f[:, 0] >= 0) & (f[:, 0] < grid.nx) & (f[:, 1] >= 0) & (f[:, 1] < grid.ny)
    f = jnp.where(jnp.isfinite(f), f, 0.0)
    cx = jnp.clip(f[:, 0], 0, grid.nx - 1).astype(jnp.int32)
    cy = jnp.clip(f[:, 1], 0, grid.ny - 1).astype(jnp.int32)
    return cx, cy, inside


def candidate_pairs(p: Particles, skin: Array, grid: Grid) -> tuple[Array, Array]:
    """For every particle, its neighbours j > i within the skin, sorted ascending.

    Returns ``[P, 9 * cell_capacity]`` int32 indices padded with the sentinel ``P`` and the
    error bits (cell overflow, particle outside the domain).
    """
    n_p = p.pos.shape[0]
    cap = grid.cell_capacity
    cx, cy, inside = cell_coordinates(p.pos, grid)
    cell = jnp.where(p.active, cx + grid.nx * cy, grid.n_cells)
    order = jnp.argsort(cell, stable=True).astype(jnp.int32)
    start = jnp.searchsorted(cell[order], jnp.arange(grid.n_cells + 2), side="left")
    count = start[1:] - start[:-1]
    errors = jnp.where(jnp.max(count[: grid.n_cells]) > cap, ERR_CELL_OVERFLOW, 0)
    errors = errors | jnp.where(jnp.any(p.active & ~inside), ERR_LEFT_DOMAIN, 0)
    errors = errors.astype(jnp.int32)

    d = jnp.array([-1, 0, 1])
    dx = jnp.repeat(d, 3)
    dy = jnp.tile(d, 3)
    ncx = cx[:, None] + dx[None, :]  # [P, 9]
    ncy = cy[:, None] + dy[None, :]
    cell_ok = (ncx >= 0) & (ncx < grid.nx) & (ncy >= 0) & (ncy < grid.ny)
    ncell = jnp.where(cell_ok, ncx + grid.nx * ncy, grid.n_cells)
    slot = start[ncell][:, :, None] + jnp.arange(cap)[None, None, :]  # [P, 9, cap]
    slot_ok = cell_ok[:, :, None] & (slot < start[ncell + 1][:, :, None])
    cand = order[jnp.clip(slot, 0, n_p - 1)]
    ii = jnp.arange(n_p)[:, None, None]
    dist = jnp.linalg.norm(p.pos[cand] - p.pos[:, None, None, :], axis=-1)
    reach = p.bound_radius[cand] + p.bound_radius[:, None, None] + skin
    ok = slot_ok & (cand > ii) & p.active[:, None, None] & p.active[cand] & (dist < reach)
    cand = jnp.where(ok, cand, n_p).reshape(n_p, -1)
    return jnp.sort(cand, axis=1), errors


def cell_count_max(particles: Particles, grid: Grid) -> int:
    """Largest number of active particles in one cell of ``grid`` (host side), over every
    realisation of a batch: what the cell capacity must hold. Counts as
    :func:`candidate_pairs` does (a particle outside the domain in the border cell)."""
    n_p = particles.pos.shape[-2]
    pos = np.asarray(particles.pos, float).reshape(-1, n_p, 2)
    active = np.asarray(particles.active).reshape(pos.shape[:2])
    f = np.floor((pos - np.asarray(grid.origin, float)) / grid.cell_size)
    f = np.where(np.isfinite(f), f, 0.0)
    cx = np.clip(f[..., 0], 0, grid.nx - 1).astype(np.int64)
    cy = np.clip(f[..., 1], 0, grid.ny - 1).astype(np.int64)
    cell = cx + grid.nx * cy + grid.n_cells * np.arange(pos.shape[0])[:, None]
    return int(np.bincount(cell[active], minlength=1).max())


def _lex_search(old: Array, new: Array) -> Array:
    """Index of each row of ``new`` [K, 2] in the lexicographically sorted ``old`` [C, 2],
    or -1. Fixed number of bisection steps, so it is jit friendly."""
    c = old.shape[0]
    steps = max(1, math.ceil(math.log2(c + 1)))
    lo = jnp.zeros(new.shape[0], dtype=jnp.int32)
    hi = jnp.full(new.shape[0], c, dtype=jnp.int32)

    def body(_, carry):
        lo, hi = carry
        mid = (lo + hi) // 2
        m = old[jnp.clip(mid, 0, c - 1)]
        less = (m[:, 0] < new[:, 0]) | ((m[:, 0] == new[:, 0]) & (m[:, 1] < new[:, 1]))
        less = less & (mid < hi)
        return jnp.where(less, mid + 1, lo), jnp.where(less, hi, mid)

    lo, _ = jax.lax.fori_loop(0, steps, body, (lo, hi))
    hit = old[jnp.clip(lo, 0, c - 1)]
    found = (lo < c) & (hit[:, 0] == new[:, 0]) & (hit[:, 1] == new[:, 1])
    return jnp.where(found, lo, -1)


def build_pairs(
    p: Particles, contacts: Contacts, skin: Array, grid: Grid
) -> tuple[Contacts, Array]:
    """Rebuild the pair list, carrying every surviving pair's spring history over.

    Returns the new :class:`Contacts` and the error bits (cell overflow, pair overflow,
    particle outside the domain). On overflow the list holds the first ``C`` pairs only and
    must not be used: the host grows the capacity (to :func:`jaxgran.simulate.pair_capacity_needed`)
    and repeats the segment. ``n_pairs`` is then the largest count any build since the
    overflow found, above ``C``.
    """
    n_p = p.pos.shape[0]
    cap = contacts.pairs.shape[0]
    cand, errors = candidate_pairs(p, skin, grid)
    valid = cand < n_p
    n_pairs = jnp.sum(valid).astype(jnp.int32)
    errors = (errors | jnp.where(n_pairs > cap, ERR_PAIR_OVERFLOW, 0)).astype(jnp.int32)
    flat = jnp.nonzero(valid.ravel(), size=cap, fill_value=valid.size)[0]
    row = flat // cand.shape[1]
    ok = flat < valid.size
    pi = jnp.where(ok, row, n_p).astype(jnp.int32)
    pj = jnp.where(ok, cand.ravel()[jnp.clip(flat, 0, valid.size - 1)], n_p).astype(jnp.int32)
    pairs = jnp.stack([pi, pj], axis=1)
    where_old = _lex_search(contacts.pairs, pairs)
    xi = jnp.where(
        ((where_old >= 0) & ok)[None, :, None, None],
        contacts.xi[:, jnp.clip(where_old, 0)],
        0.0,
    )
    # after an overflow the count stays at the largest one found, so the host can grow the
    # capacity to what the segment needed in one step (the segment is repeated anyway)
    overflowed = contacts.n_pairs > cap
    new = Contacts(
        pairs=pairs,
        n_pairs=jnp.where(overflowed, jnp.maximum(contacts.n_pairs, n_pairs), n_pairs),
        xi=xi,
        wall_xi=contacts.wall_xi,
        ref_pos=p.pos,
        ref_angle=p.angle,
        n_builds=contacts.n_builds + 1,
    )
    return new, errors


def needs_rebuild(p: Particles, contacts: Contacts, skin: Array) -> Array:
    """True when some active particle moved more than skin/2 since the last build."""
    disp = jnp.linalg.norm(p.pos - contacts.ref_pos, axis=-1)
    return jnp.any(p.active & (disp > 0.5 * skin))


def make_grid(
    lower: tuple[float, float],
    upper: tuple[float, float],
    max_bound_radius: float,
    skin: float,
    *,
    cell_capacity: int | None = None,
) -> Grid:
    """A cell grid covering ``[lower, upper]`` (m) with cells of side
    ``2 * max_bound_radius + skin`` (so neighbours are within the 3x3 block)."""
    size = 2.0 * float(max_bound_radius) + float(skin)
    if not (size > 0 and math.isfinite(size)):
        raise ValueError(f"cell size must be positive and finite, got {size}")
    nx = max(1, math.ceil((upper[0] - lower[0]) / size))
    ny = max(1, math.ceil((upper[1] - lower[1]) / size))
    if cell_capacity is None:
        cell_capacity = 8
    return Grid(
        origin=(float(lower[0]), float(lower[1])),
        cell_size=size,
        nx=nx,
        ny=ny,
        cell_capacity=int(cell_capacity),
    )
