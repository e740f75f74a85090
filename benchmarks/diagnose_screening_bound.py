"""Where the screening bound ``bem.psi_bound`` loses, factor by factor, on a settled pile.

For every loaded particle of the ``deposit`` pile of ``bench_screening.py`` with two or more
contacts, four upper bounds of its largest psi are compared, each at least the one before:

1. ``triangle``: max over the sample points of the sum over contacts of each contact's psi
   (its equilibrated force alone), the tightest that the triangle inequality over contacts
   allows;
2. ``split``: the same with each contact's smooth BEM remainder and its Flamant near field
   bounded apart, psi(S + F) <= psi(S) + psi(F);
3. ``grouped``: each contact's two parts maximised over each angular group of sample points
   (``bem._SCREEN_GROUPS``) before the sum over contacts, the maximum over the groups;
4. ``bound``: ``bem.psi_bound``, which replaces the exact group maxima of (3) by the numbers
   of its per-element tables (maxima over the element's load positions, interpolation
   between force directions, the Lipschitz margin of the Flamant field).

The ratios of consecutive bounds (median, 90th percentile) say what each step costs.

    python benchmarks/diagnose_screening_bound.py --cache /tmp/pile.pkl   # ~3 min with a pile

Prints the ratios; writes nothing.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_screening import _to_device, settled_pile  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=1100)
    ap.add_argument("--width", type=float, default=0.7, help="box width (m)")
    ap.add_argument("--cache", default=None, help="pickle of the settled pile, reused if present")
    args = ap.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    from jaxgran import bem
    from jaxgran.breakage import dsm

    state, params, grid, cfg = settled_pile(args.cells, args.width, args.cache)
    state, params, grid = (jax.tree_util.tree_map(_to_device, t) for t in (state, params, grid))
    p, thick, nu = state.particles, cfg.thickness, 0.3

    def table(k):
        return dsm.contact_table(
            state, params, jnp.asarray(1.0), jnp.asarray(0.0), jnp.asarray(3.4351),
            jnp.asarray(thick), k,
        )  # fmt: skip

    # lists long enough for the particle with most contacts (none is cut)
    count = int(np.asarray(table(8)["count"]).max())
    tab = table(max(8, 1 << (count - 1).bit_length()))
    act = np.flatnonzero(np.asarray(p.active))
    cp, cf, cm = (np.asarray(tab[k])[act] for k in ("points", "forces", "mask"))
    ops = bem.build_operators(
        p.verts[act], p.n_verts[act], p.radius[act], n_elements=64, n_points=100,
        poisson_ratio=nu,
    )  # fmt: skip
    psi_max = np.asarray(bem.psi_batched(ops, cp, cf, cm, thickness=thick)[1]).max(axis=1)
    bound = np.asarray(bem.psi_bound(ops, cp, cf, cm, thickness=thick))
    n_el = ops.nodes.shape[1]

    @jax.jit
    def parts(i, x, f, m):
        """psi of each contact's smooth part and of its Flamant part, ``[C, M]`` each."""
        f = bem._equilibrate(x, jnp.where(m[:, None], f, 0.0), m)
        lo, w = bem._assign_contacts(x, ops.nodes[i], ops.centres[i], ops.node_angles[i])
        k = ops.stress_per_force[i]
        w = w[:, None, None, None]
        col = (1.0 - w) * k[lo] + w * k[(lo + 1) % n_el]
        smooth = jnp.einsum("ckmj,ck->cmj", col, f)
        near = jax.vmap(lambda y, g: bem._flamant_field(ops.points[i], y[None], g[None]))(x, f)
        keep = ops.point_mask[i][None] & m[:, None]

        def psi(s):
            return jnp.where(keep, bem.equivalent_stress(s, nu, "stress"), 0.0) / thick

        return psi(smooth + near), psi(smooth), psi(near)

    n_groups = bem._SCREEN_GROUPS
    rows = []
    for i in np.flatnonzero((cm.sum(axis=1) >= 2) & (psi_max > 0)):
        both, smooth, near = (np.asarray(a) for a in parts(i, cp[i], cf[i], cm[i]))
        rel = np.asarray(ops.points[i]) - np.asarray(ops.centres[i])
        ang = np.arctan2(rel[:, 1], rel[:, 0])
        grp = np.clip(np.floor((ang + math.pi) / (2 * math.pi) * n_groups), 0, n_groups - 1)
        real = np.asarray(ops.point_mask[i])
        grouped = 0.0
        for g in range(n_groups):
            sel = (grp == g) & real
            if sel.any():
                grouped = max(grouped, float((smooth[:, sel].max(1) + near[:, sel].max(1)).sum()))
        rows.append(
            (psi_max[i], both.sum(0).max(), (smooth + near).sum(0).max(), grouped, bound[i])
        )
    r = np.array(rows)
    names = ["field", "triangle", "split", "grouped", "bound"]
    print(f"{len(r)} particles with 2 or more contacts; {n_groups} groups")
    for k in range(1, len(names)):
        q = r[:, k] / r[:, k - 1]
        if np.any(q < 1.0 - 1e-9):
            raise AssertionError(f"{names[k]} fell below {names[k - 1]}: a bug")
        print(
            f"{names[k]:>8} / {names[k - 1]:<8} median {np.median(q):.3f}, "
            f"90th percentile {np.percentile(q, 90):.3f}"
        )
    q = r[:, 4] / r[:, 0]
    print(
        f"   bound / field    median {np.median(q):.3f}, 90th percentile {np.percentile(q, 90):.3f}"
    )


if __name__ == "__main__":
    main()
