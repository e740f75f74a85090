"""The three averaged-stress breakage methods of paper 000 §IV (Table II) as simulation
callbacks that share the DSM's replacement, so that only criterion and cutting planes differ.

:class:`AveragedStressBreakage` is a :func:`jaxgran.simulate.simulate` callback with the same
interface as :class:`~jaxgran.breakage.dsm.DsmBreakage` (it is a subclass): the same jitted
screening and contact table (:func:`~jaxgran.breakage.dsm.contact_table`), the same subset
separation of the dilated outline (:func:`~jaxgran.breakage.ssm.split_convex`), the same
erosion and slot bookkeeping (:func:`~jaxgran.breakage.replace.replace_particles`) and the
same :func:`~jaxgran.simulate.prepare`. Per flagged particle, instead of the BEM:

1. the averaged stress ``sigma = (1 / A t) sum_c (x_c - x_G) (x) F_c`` of its vertex contacts
   in the body frame (:func:`~jaxgran.breakage.criteria.averaged_stress`, tension positive);
2. the criterion of ``method``:

   * ``"split-cell"`` (Cantor et al. 2015): ``(3 sigma_1 - sigma_2) / 2 > sigma_T``; one plane
     through the centroid along the major compression, ``theta_p + pi/2`` (two halves);
   * ``"cross-cut"`` (Eliáš 2014): von Mises ``sigma_v >= sigma_c``; two planes through the
     centroid at ``theta_p +- pi/4`` (four quarters);
   * ``"mohr-coulomb"`` (Gladky & Kuna 2017): Mohr-Coulomb with ``sigma_T``, ``sigma_C``; one
     plane at ``theta_p + pi/4`` (two halves).

Strengths from the same Brazilian calibration as the DSM (:func:`calibrate_strengths`).
    The Brazilian disc of radius R, thickness t under the diametral force F has the averaged
    stress ``diag(0, -2p)``, ``p = F / (pi R t)`` (PHYSICS §E). Each threshold is set to the
    method's criterion value for that stress, so that *every* method breaks the calibration
    disc (F = 150.79 N, R = 1 cm, paper 000 §III) at F, as the DSM does with
    ``eps = k F / (pi R t)``:

    * split-cell: ``sigma_T = (3 * 0 + 2p) / 2 = p`` (= the exact centre tension);
    * cross-cut: ``sigma_c = sigma_v(diag(0, -2p)) = 2p`` (no size effect, as in paper 000
      §III; ``reference_radius`` = R restores Eliáš's ``1 / r_eq`` scaling);
    * Mohr-Coulomb: the Brazilian state lies in the compression-compression branch, so
      ``sigma_C = -sigma_2 = 2p``; ``sigma_T`` is not fixed by the average (it hides the
      tension at the centre) and is set to the Brazilian tensile strength ``p``. With it the
      mixed branch ``|sigma_1 - (sigma_T / sigma_C) sigma_2| = p`` gives the same break if
      round-off makes ``sigma_1`` slightly positive.

    For F = 150.79 N, R = t = 1 cm: p = 0.480 MPa, 2p = 0.960 MPa. A polygonal "disc" has a
    little less area than pi R^2, so it breaks a fraction of a percent below F.

Screening: the contact table flags a particle with at least two contacts whose largest
contact force exceeds ``screen_fraction`` times its Brazilian critical load (that of a disc
of its area, from the DSM eps of the same calibration). It only saves work: the default
fraction 0.2 is well below any load state that reaches a threshold with a few contacts.

:func:`make_breakage` builds the breakage callback for ``--method {dsm, split-cell,
cross-cut, mohr-coulomb}`` from one Brazilian calibration.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..geometry import spheropolygon_mass_properties
from ..state import Grid, Params, SimState
from .criteria import (
    CriterionResult,
    averaged_stress,
    cross_cut_criterion,
    mohr_coulomb_criterion,
    principal_stresses,
    split_cell_criterion,
)
from .dsm import (
    PAPER_FORCE,
    PAPER_RADIUS,
    DsmBreakage,
    _body_to_world,
    _Decision,
    calibrate_eps,
)
from .replace import dilated_outline
from .ssm import split_convex

__all__ = [
    "METHODS",
    "AveragedStressBreakage",
    "calibrate_strengths",
    "evaluate_criterion",
    "make_breakage",
]

METHODS = ("dsm", "split-cell", "cross-cut", "mohr-coulomb")
AVERAGED_METHODS = METHODS[1:]


def calibrate_strengths(
    force: float = PAPER_FORCE, radius: float = PAPER_RADIUS, thickness: float = 0.01
) -> dict[str, float]:
    """Strengths (Pa) that make each averaged method break a Brazilian disc of ``radius``
    R (m), ``thickness`` t (m) at the diametral ``force`` F (N); see the module docstring.

    Returns ``{"tensile_strength": p, "compressive_strength": 2p, "von_mises_strength": 2p,
    "brazilian_pressure": p}`` with ``p = F / (pi R t)``, each obtained by evaluating the
    criterion on the averaged stress of the ideal disc.
    """
    for name, v in (("force", force), ("radius", radius), ("thickness", thickness)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be positive and finite, got {v}")
    pts = np.array([[0.0, radius], [0.0, -radius]])
    frc = np.array([[0.0, -force], [0.0, force]])
    sigma = averaged_stress(pts, frc, np.zeros(2), math.pi * radius**2, thickness)
    s1, s2, _ = principal_stresses(sigma)
    p = force / (math.pi * radius * thickness)
    split = 0.5 * (3.0 * s1 - s2)
    vm = cross_cut_criterion(sigma, np.zeros(2), 1.0, 1.0).value
    return {
        "tensile_strength": split,
        "compressive_strength": -s2,
        "von_mises_strength": vm,
        "brazilian_pressure": p,
    }


def evaluate_criterion(
    method: str,
    stress: np.ndarray,
    centroid: np.ndarray,
    area: float,
    *,
    tensile_strength: float,
    compressive_strength: float,
    von_mises_strength: float,
    reference_radius: float | None = None,
) -> CriterionResult:
    """The Table II criterion ``method`` for one averaged ``stress`` ``[2, 2]`` (Pa, tension
    positive) of a particle with ``centroid`` ``[2]`` (m) and ``area`` (m^2)."""
    if method == "split-cell":
        return split_cell_criterion(stress, centroid, tensile_strength)
    if method == "cross-cut":
        return cross_cut_criterion(
            stress, centroid, area, von_mises_strength, reference_radius=reference_radius
        )
    if method == "mohr-coulomb":
        return mohr_coulomb_criterion(stress, centroid, tensile_strength, compressive_strength)
    raise ValueError(f"method must be one of {AVERAGED_METHODS}, got {method!r}")


class AveragedStressBreakage(DsmBreakage):
    """Split-cell, cross-cut or Mohr-Coulomb breakage as a simulate callback (paper 000
    Table II), replacing particles exactly as :class:`DsmBreakage` does.

    Usage::

        brk = AveragedStressBreakage(params, grid, method="cross-cut", mean_initial_mass=m0)
        result = simulate(state, params, grid, n_steps=..., callback=brk)
        brk.events  # replace_particle's event dicts plus method, criterion_value,
                    # criterion_threshold, principal_stresses (Pa), theta_p (rad),
                    # contact_points (world, m)

    Args:
        params, grid: those given to ``simulate``.
        method: ``"split-cell"``, ``"cross-cut"`` or ``"mohr-coulomb"``.
        tensile_strength, compressive_strength, von_mises_strength: sigma_T, sigma_C,
            sigma_c (Pa); None: :func:`calibrate_strengths` of ``calibration_force`` (N) and
            ``calibration_radius`` (m) at this thickness.
        reference_radius: cross-cut size effect (see ``cross_cut_criterion``); None: none.
        eps: DSM threshold (Pa) used only by the screening; None: ``calibrate_eps`` of the
            same calibration.
        thickness, poisson_ratio, plane, screen_fraction, min_area, mean_initial_mass,
        max_contacts, n_arc, max_events, erosion, small_pieces, conserve_mass, min_radius: as
        in :class:`DsmBreakage`.
    """

    def __init__(
        self,
        params: Params,
        grid: Grid,
        *,
        method: str,
        tensile_strength: float | None = None,
        compressive_strength: float | None = None,
        von_mises_strength: float | None = None,
        reference_radius: float | None = None,
        calibration_force: float = PAPER_FORCE,
        calibration_radius: float = PAPER_RADIUS,
        eps: float | None = None,
        poisson_ratio: float = 0.3,
        plane: str = "stress",
        thickness: float | None = None,
        screen_fraction: float = 0.2,
        min_area: float = 0.0,
        mean_initial_mass: float | None = None,
        max_contacts: int = 16,
        n_arc: int = 64,
        max_events: int | None = None,
        erosion: str = "local",
        small_pieces: str = "merge",
        conserve_mass: bool = False,
        min_radius: float | None = None,
    ) -> None:
        if method not in AVERAGED_METHODS:
            raise ValueError(f"method must be one of {AVERAGED_METHODS}, got {method!r}")
        t = float(params.thickness if thickness is None else thickness)
        if eps is None:
            eps = calibrate_eps(
                calibration_force,
                calibration_radius,
                poisson_ratio=poisson_ratio,
                plane=plane,
                thickness=t,
            )
        super().__init__(
            params,
            grid,
            eps=eps,
            poisson_ratio=poisson_ratio,
            plane=plane,
            thickness=t,
            screen_fraction=screen_fraction,
            min_area=min_area,
            mean_initial_mass=mean_initial_mass,
            max_contacts=max_contacts,
            n_arc=n_arc,
            max_events=max_events,
            erosion=erosion,
            small_pieces=small_pieces,
            conserve_mass=conserve_mass,
            min_radius=min_radius,
        )
        cal = calibrate_strengths(calibration_force, calibration_radius, t)
        self.method = method
        self.tensile_strength = float(
            cal["tensile_strength"] if tensile_strength is None else tensile_strength
        )
        self.compressive_strength = float(
            cal["compressive_strength"] if compressive_strength is None else compressive_strength
        )
        self.von_mises_strength = float(
            cal["von_mises_strength"] if von_mises_strength is None else von_mises_strength
        )
        self.reference_radius = reference_radius
        self.last_value: dict[int, float] = {}  # uid -> criterion value (Pa), last check

    def strengths(self) -> dict[str, Any]:
        """The method and its strengths (Pa), JSON-ready."""
        return {
            "method": self.method,
            "tensile_strength_Pa": self.tensile_strength,
            "compressive_strength_Pa": self.compressive_strength,
            "von_mises_strength_Pa": self.von_mises_strength,
            "reference_radius_m": self.reference_radius,
        }

    def prebuild(self, state: SimState) -> None:
        """Nothing to build (no BEM)."""

    def check(self, state: SimState) -> list[_Decision]:
        """The breakage decisions for ``state`` (no state change)."""
        found = self._candidates(state)
        if found is None:
            return []
        cand, host = found
        out = []
        for row, slot in enumerate(cand.tolist()):
            self.n_checked += 1
            d = self._check_one(state, slot, row, host)
            if d is not None:
                out.append(d)
        return out

    def apply(self, state: SimState, decisions: list[_Decision]) -> SimState:
        n0 = len(self.events)
        state = super().apply(state, decisions)
        for ev in self.events[n0:]:
            ev.pop("eps", None)
        return state

    def _check_one(self, state: SimState, slot: int, row: int, host) -> _Decision | None:
        p = state.particles
        m = host["mask"][row]
        pts, frc, nb = host["points"][row][m], host["forces"][row][m], host["neighbour"][row][m]
        if np.unique(nb).size < 2:
            return None
        n = int(np.asarray(p.n_verts)[slot])
        core_b = np.asarray(p.verts[slot, :n], dtype=np.float64)
        r = float(np.asarray(p.radius)[slot])
        area, _, _ = spheropolygon_mass_properties(core_b, r, 1.0)
        # body frame: the centroid is the origin
        sigma = averaged_stress(pts, frc, np.zeros(2), area, self.thickness)
        res = evaluate_criterion(
            self.method,
            sigma,
            np.zeros(2),
            area,
            tensile_strength=self.tensile_strength,
            compressive_strength=self.compressive_strength,
            von_mises_strength=self.von_mises_strength,
            reference_radius=self.reference_radius,
        )
        uid = int(np.asarray(p.uid)[slot])
        self.last_value[uid] = float(res.value)
        if not res.breaks:
            return None
        to_world = _body_to_world(state, slot)
        planes_w = to_world(res.lines.reshape(-1, 2)).reshape(-1, 2, 2)
        pieces = split_convex(dilated_outline(to_world(core_b), r, self.n_arc), planes_w)
        if len(pieces) < 2:
            return None
        s1, s2, theta = principal_stresses(sigma)
        centres = []
        for g in np.unique(nb).tolist():
            sel = nb == g
            w = np.linalg.norm(frc[sel], axis=1)
            w = w if w.sum() > 0 else np.ones_like(w)
            centres.append((w[:, None] * pts[sel]).sum(0) / w.sum())
        angle = float(np.asarray(p.angle)[slot])
        info = {
            "method": self.method,
            "criterion_value": float(res.value),
            "criterion_threshold": float(res.threshold),
            "principal_stresses": np.array([s1, s2]),
            "theta_p": theta + angle,  # world frame (rad)
            "contact_points": to_world(np.asarray(centres)),
            "n_contacts": int(len(centres)),
            "max_contact_force": float(host["max_force"][row]),
            "critical_load": float(host["critical_load"][row]),
        }
        return _Decision(slot, planes_w, pieces, info)


def make_breakage(
    method: str,
    params: Params,
    grid: Grid,
    *,
    calibration_force: float = PAPER_FORCE,
    calibration_radius: float = PAPER_RADIUS,
    thickness: float | None = None,
    poisson_ratio: float = 0.3,
    plane: str = "stress",
    min_area: float = 0.0,
    mean_initial_mass: float | None = None,
    dsm_options: dict[str, Any] | None = None,
    averaged_options: dict[str, Any] | None = None,
    erosion: str = "local",
    small_pieces: str = "merge",
    conserve_mass: bool = False,
    min_radius: float | None = None,
) -> DsmBreakage:
    """Breakage callback for ``--method``: ``"dsm"`` gives a :class:`DsmBreakage` with
    ``eps = calibrate_eps(F, R)``, the others an :class:`AveragedStressBreakage` with
    :func:`calibrate_strengths` of the same F (N), R (m); all break the Brazilian disc at F.
    Extra keyword arguments per family go in ``dsm_options`` / ``averaged_options``;
    ``erosion`` (``"local"``, ``"uniform"``, ``"none"``) is the fragments' erosion and
    ``small_pieces`` (``"merge"``, ``"fines"``) the fate of pieces below ``min_area`` and
    ``conserve_mass`` the density compensation of the erosion and ``min_radius`` the floor
    (m) of the adaptive fragment radius (None: fragments keep the parent's), for all."""
    t = float(params.thickness if thickness is None else thickness)
    common = dict(
        poisson_ratio=poisson_ratio,
        plane=plane,
        thickness=t,
        min_area=min_area,
        mean_initial_mass=mean_initial_mass,
        erosion=erosion,
        small_pieces=small_pieces,
        conserve_mass=conserve_mass,
        min_radius=min_radius,
    )
    if method == "dsm":
        eps = calibrate_eps(
            calibration_force,
            calibration_radius,
            poisson_ratio=poisson_ratio,
            plane=plane,
            thickness=t,
        )
        return DsmBreakage(params, grid, eps=eps, **common, **(dsm_options or {}))
    if method in AVERAGED_METHODS:
        return AveragedStressBreakage(
            params,
            grid,
            method=method,
            calibration_force=calibration_force,
            calibration_radius=calibration_radius,
            **common,
            **(averaged_options or {}),
        )
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def method_name(breakage: DsmBreakage) -> str:
    """``"dsm"`` or the averaged method of a breakage callback."""
    return getattr(breakage, "method", "dsm")
