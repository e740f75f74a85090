"""The accuracy numbers of the BEM acceptance (issue 3), printed: uniform traction on a disc
and a square at N = 80, the Brazilian disc against its closed form at N = 32, 64, 128 with
the measured order, and the connection value k at the disc centre.

The scenes and closed forms are those of ``tests/test_bem.py`` (imported from there, so the
numbers are those the tests assert on). About 30 s on 2 cores:
``python benchmarks/bem_acceptance.py``."""

import math
import os
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402
import test_bem as tb  # noqa: E402

from jaxgran import bem  # noqa: E402


def uniform_errors(n_elements: int = 80) -> None:
    g = np.linspace(-0.8, 0.8, 17)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    pts = pts[np.linalg.norm(pts, axis=1) <= 0.8 + 1e-12]
    for shape, (verts, radius) in {"disc": (tb.DISC, 1.0), "square": (tb.SQUARE, 0.0)}.items():
        for state, sigma in tb.UNIFORM.items():
            mid, forces = tb.element_forces(verts, radius, n_elements, sigma)
            got = bem.stress_field(
                verts, mid, forces, pts, poisson_ratio=tb.NU, radius=radius,
                n_elements=n_elements, load_model="element",
            )  # fmt: skip
            exact = [sigma[0, 0], sigma[1, 1], sigma[0, 1]]
            err = np.abs(np.asarray(got) - exact).max() / np.abs(sigma).max()
            print(f"uniform traction, {shape}, {state}, N = {n_elements}: {100 * err:.3f} %")


def brazilian(radius: float = 0.02, load: float = 150.0, t: float = 0.01) -> None:
    errors = {}
    for n in (32, 64, 128):
        pts, _ = bem.sample_points(tb.DISC, radius, n, n_points=400)
        sigma = np.asarray(
            bem.stress_field(
                tb.DISC, [[0.0, radius], [0.0, -radius]], [[0.0, -load], [0.0, load]], pts,
                poisson_ratio=tb.NU, radius=radius, n_elements=n, thickness=t,
            )
        )  # fmt: skip
        errors[n] = tb.brazilian_error(radius, load, t, pts, sigma)
        print(f"Brazilian disc, N = {n}: max error {100 * errors[n]:.3f} % of 2P/(pi D t)")
    ns = sorted(errors)
    order = -np.polyfit(np.log(ns), np.log([errors[n] for n in ns]), 1)[0]
    print(f"measured order of convergence: {order:.2f}")
    centre = np.argmin(np.linalg.norm(pts, axis=1))
    for plane, k in (("stress", 3.4351), ("strain", 3.3823)):
        psi = float(bem.equivalent_stress(sigma[centre], tb.NU, plane))
        got = psi / (load / (math.pi * radius * t))
        print(f"k at the centre, plane {plane}, N = 128: {got:.4f} (reference {k}, "
              f"{100 * (got / k - 1):+.3f} %)")  # fmt: skip


if __name__ == "__main__":
    uniform_errors()
    brazilian()
