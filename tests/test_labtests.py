"""Differentiable lab tests (jaxgran.labtests): gradients of the Brazilian figures (reverse
mode) and of the biaxial ones (forward mode) against finite differences, NaN-free gradients
with padded entries and touching cells, and the hard model recovered as the surrogate width
goes to 0.

Tiny specimens (30 cells), fast loading. The Brazilian lab runs two realisations of different
seeds as one batch (so bond, vertex, wall-bond and pair slots are padded); the biaxial lab runs
one seed (its unconfined and constant-p members still step as one batch), which halves its
run time; padding is the disc's test.

The finite differences are one-sided, (f(x + h e_j) - f(x)) / h with h = 1e-5 in log space:
one run per parameter instead of two. Measured against central differences on the biaxial
lab (2026-12-05), the one-sided ones differ by at most 2e-3 (relative, q_peak against eps_th)
and by 1.4e-5 or less on E_c and nu, far inside the 5 % that the checks allow; autodiff
matched the central ones to 1.4e-3 at worst."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgran import labtests as lt
from jaxgran.scenes import bonded as bd
from jaxgran.scenes import bonded_biaxial as bx
from jaxgran.scenes import bonded_brazilian as bz

TINY_DISC = {"n_cells": 30, "strain_rate": 40.0, "record_every": 25}
TINY_BLOCK = {
    "n_cells": 30,
    "strain_rate": 40.0,
    "record_every": 25,
    "max_strain": 0.025,
    "iso_max_time": 3.0e-4,
}
H = 1.0e-5  # finite-difference step in log space
# Bond breakage is smoothed over a width of 1 (health from 1 to 0 as the Eq. 15 measure goes
# from 1 to 2), and a global damping of 2e4 1/s replaces the contact dashpot (whose force
# jumps when a contact opens or closes a step earlier, a discontinuity in the parameters) and
# calms the fragments; with narrower widths the post-fracture dynamics is chaotic and finite
# differences lose meaning (see the labtests docstring).
WIDTH = 1.0
DAMPING = 2.0e4


@pytest.fixture(scope="module")
def disc():
    cfg = dataclasses.replace(bz.Config(), **TINY_DISC)
    lab = lt.brazilian_lab(
        cfg, [0, 1], surrogate_width=WIDTH, damping=DAMPING, contact_damping=0.0, max_strain=0.05
    )
    return lab, lt.log_params(bd.material_from(cfg))


@pytest.fixture(scope="module")
def block():
    cfg = dataclasses.replace(bx.Config(), **TINY_BLOCK)
    lab = lt.biaxial_lab(
        cfg,
        [0],
        p_values=(300.0e6,),
        surrogate_width=WIDTH,
        damping=DAMPING,
        contact_damping=0.0,
    )
    return lab, lt.log_params(bd.material_from(cfg))


def _means_of(figs, names):
    return jnp.stack([jnp.mean(figs[n]) for n in names])


def _means(log_p, lab, names):
    figs, _ = lt.figures(log_p, lab)
    return _means_of(figs, names)


def _jacobian_fn(lab, names, mode=jax.jacrev):
    """Jitted Jacobian of the ensemble means of ``names`` (reverse mode by default)."""
    return jax.jit(mode(lambda x: _means(x, lab, names)))


def _jacobians(lab, log_p, names, jac=None, figs=None, mode=jax.jacrev):
    """Jacobian of the ensemble means by ``mode`` (``jac`` if given) and its one-sided
    finite differences (see the module docstring) from the figures at ``log_p`` (``figs``
    if given)."""
    jac = np.asarray(_jacobian_fn(lab, names, mode)(log_p) if jac is None else jac)
    assert np.all(np.isfinite(jac))
    base = np.asarray(_means(log_p, lab, names) if figs is None else _means_of(figs, names))
    fd = np.zeros_like(jac)
    for j in range(log_p.size):
        e = jnp.zeros_like(log_p).at[j].set(H)
        fd[:, j] = (np.asarray(_means(log_p + e, lab, names)) - base) / H
    return jac, fd


def _assert_close(jac, fd, names):
    scale = np.abs(fd).max(axis=1, keepdims=True)
    # 5 % of each derivative; sensitivities below 1 % of the figure's largest one (physically
    # negligible, e.g. a modulus against eps_th before any bond breaks) to 5 % of that 1 %
    tol = 0.05 * np.maximum(np.abs(fd), 0.01 * scale)
    bad = np.abs(jac - fd) > tol
    assert not bad.any(), (
        f"AD vs FD mismatch at {[(names[i], lt.PARAMETERS[j]) for i, j in np.argwhere(bad)]}"
        f"\nAD={jac}\nFD={fd}"
    )
    significant = np.abs(fd) >= 0.01 * scale
    assert significant.sum() >= 2 * len(names)  # the check is not vacuous


def _check_jacobian(lab, log_p, names, jac=None, figs=None):
    jac, fd = _jacobians(lab, log_p, names, jac, figs)
    _assert_close(jac, fd, names)
    return jac, fd


DISC_FIGURES = ("sigma_t", "slope_S")


@pytest.fixture(scope="module")
def disc_jacobian(disc):
    """One compiled Jacobian of the disc's figures and its value at the base point, for the
    tests of the class below."""
    fn = _jacobian_fn(disc[0], DISC_FIGURES)
    return fn, np.asarray(fn(disc[1]))


@pytest.fixture(scope="module")
def block_jacobians(block):
    """The block's Jacobian by forward mode (``jax.jacfwd``, which the calibration's
    Gauss-Newton fit, its uncertainty and Adam's gradient use): 26 s to trace, compile and
    run against 55 s for reverse mode (which the disc's tests cover; on this block the two
    agreed to 3.5e-11 relative, 2026-12-06), on one CPU core."""
    lab, log_p = block
    figs, err = lt.figures(log_p, lab)
    lt.check_errors(err)
    return figs, *_jacobians(lab, log_p, ("E_c", "nu", "q_peak"), figs=figs, mode=jax.jacfwd)


class TestBrazilianDisc:
    """The Brazilian lab: gradients, padding, the hard-model limit (one worker under
    ``--dist loadscope``; the biaxial block runs beside it on the other)."""

    def test_brazilian_gradients_match_finite_differences(self, disc, disc_jacobian):
        lab, log_p = disc
        figs, err = lt.figures(log_p, lab)
        lt.check_errors(err)
        assert np.all(np.asarray(figs["sigma_t"]) > 0) and np.all(np.asarray(figs["slope_S"]) > 0)
        jac, _ = _check_jacobian(lab, log_p, DISC_FIGURES, disc_jacobian[1], figs)
        # physics: stiffer contacts and a higher strain threshold make the disc stronger
        assert jac[0, 0] > 0 and jac[0, 4] > 0

    def test_gradients_are_finite_with_padding_and_touching_cells(self, disc, disc_jacobian):
        """The two discs have different bond counts and vertex counts (padded slots with
        sentinel indices), the pair list and the wall-bond slots are padded, and every cell
        starts exactly touching its neighbours (zero overlap). The gradient through a whole
        run must be finite: it sums every segment's partial derivatives, from the start (all
        cells touching, nothing broken) on, and a NaN in any of them (0 * NaN included, the
        masked-branch case) would make it NaN."""
        lab, log_p = disc
        real = np.asarray(lab.real_bond)
        assert (~real).any() and real.sum(axis=1)[0] != real.sum(axis=1)[1]
        assert not np.asarray(lab.state.bonds.wall_active).any()
        jac_fn, jac = disc_jacobian
        assert np.all(np.isfinite(jac))
        # a parameter vector with a vanishing friction and equal moduli (touching, degenerate)
        odd = log_p.at[5].set(jnp.log(1e-12))
        assert np.all(np.isfinite(np.asarray(jac_fn(odd))))

    def test_zero_width_recovers_the_hard_model(self, disc):
        """The health surrogate with width w -> 0 converges to hard breakage: the platen force
        curve differs from the hard model's by less and less, and at w = 1e-9 by round-off
        only."""
        lab, log_p = disc
        _, hard, _ = lt.run(log_p, lt.with_surrogate_width(lab, 0.0))
        f_hard, _ = lt.platen_curves(hard, lab)
        f_hard = np.asarray(f_hard)
        diffs = []
        for w in (1e-1, 1e-3, 1e-9):
            _, soft, _ = lt.run(log_p, lt.with_surrogate_width(lab, w))
            f, _ = lt.platen_curves(soft, lab)
            diffs.append(np.abs(np.asarray(f) - f_hard).max() / np.abs(f_hard).max())
        assert diffs[0] > 1e-3  # the surrogate does change the run
        assert diffs[2] < diffs[1] < diffs[0]
        assert diffs[2] < 1e-6


class TestBiaxialBlock:
    """The biaxial lab: unconfined and constant-p gradients from one forward-mode
    Jacobian."""

    def test_unconfined_gradients_match_finite_differences(self, block_jacobians):
        figs, jac, fd = block_jacobians
        assert np.all(np.asarray(figs["E_c"]) > 0)
        assert np.all(np.abs(np.asarray(figs["nu"])) < 0.5)
        _assert_close(jac[:2], fd[:2], ("E_c", "nu"))
        # physics: the modulus grows with the contact stiffness (compression is carried by contacts)
        assert jac[0, 0] > 0

    def test_constant_p_gradients_match_finite_differences(self, block_jacobians):
        """d q_peak / d (K_n, B_t, eps_th, mu) of the constant-p test by autodiff against finite
        differences. Until the corner weights of the contact law (``contact.corner_weight``)
        the run sat on a discontinuity at the base point (every difference saw the same jump
        of ~7e4 Pa, 2e-4 of q_peak): two cell corners switching between one and two contacts."""
        figs, jac, fd = block_jacobians
        assert np.all(np.asarray(figs["q_peak"]) > 0)
        _assert_close(jac[2:], fd[2:], ("q_peak",))
