"""Figures of a calibration (the only calibration module that imports matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_convergence(histories: dict[str, dict], path: Path) -> Path:
    """Loss against simulations (left) and against wall time (right, s) for every
    optimiser of ``histories`` (name -> ``{"loss": [...], "time_s": [...]}``), log scale;
    the running minimum is drawn for each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    for name, h in histories.items():
        loss = np.minimum.accumulate(np.asarray(h["loss"], float))
        n = np.arange(1, loss.size + 1)
        a1.semilogy(n, loss, label=name)
        a2.semilogy(np.asarray(h["time_s"], float), loss, label=name)
    a1.set_xlabel(
        "evaluations (Adam: one gradient each, Gauss-Newton: one Jacobian, Nelder-Mead: one run)"
    )
    a2.set_xlabel("wall time (s)")
    for a in (a1, a2):
        a.set_ylabel("loss (best so far)")
        a.grid(True, which="both", alpha=0.3)
        a.legend()
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path
