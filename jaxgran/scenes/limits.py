"""The allowed values of every scene setting, checked when a configuration is made.

A scene's ``Config`` derives from :class:`Checked`, so ``Config(...)``,
``dataclasses.replace`` and ``jaxgran run --set key=value`` all refuse a value out of range
with a ValueError that names the setting, the value and what is allowed, before anything is
built or compiled (a negative load time or strain rate used to run to an empty or
meaningless result, and some bad values surfaced only as a traceback deep in a build).

A setting name means the same in every scene (``friction`` is a Coulomb coefficient, ``dt``
a time step in s with 0 for automatic, ``max_strain`` a strain), so the rules live in one
table, :data:`SETTINGS`; a scene whose field departs from it says so in its ``LIMITS``, and
checks relations between fields (``min_diameter < max_diameter``) in ``relations``.
``tests/test_limits.py`` asserts that every numeric and text field of every scene has a
rule, so a new setting cannot go unchecked.
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import math
import numbers
import tokenize
from typing import Any, ClassVar

from ..bem import LOAD_MODELS, PLANES
from ..breakage.averaged import METHODS
from ..breakage.replace import EROSION_MODES, SMALL_PIECE_MODES
from ..interface import ENVELOPES


@dataclasses.dataclass(frozen=True)
class Range:
    """A number in ``[low, high]`` (``low_open`` / ``high_open`` exclude the ends); with
    ``integer`` an int. Tuples of numbers (``p_values``) are checked entry by entry. NaN is
    refused unless ``nan`` names what it stands for."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    integer: bool = False
    nan: str = ""
    note: str = ""  # what a special value means, for the error message

    def describe(self) -> str:
        kind = "an integer" if self.integer else "a number"
        if self.high == math.inf:
            text = f"{kind} {'>' if self.low_open else '>='} {self.low:g}"
        else:
            lo, hi = "(" if self.low_open else "[", ")" if self.high_open else "]"
            text = f"{kind} in {lo}{self.low:g}, {self.high:g}{hi}"
        extras = [e for e in (self.note, self.nan and f"nan: {self.nan}") if e]
        return text + (f" ({'; '.join(extras)})" if extras else "")

    def allows(self, value: Any) -> bool:
        if isinstance(value, tuple):
            return all(self.allows(v) for v in value)
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if self.integer and not isinstance(value, numbers.Integral):
            return False
        if math.isnan(value):
            return bool(self.nan)
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below


@dataclasses.dataclass(frozen=True)
class OneOf:
    """One of ``choices``; with ``many`` a comma-separated list of them (at least one)."""

    choices: tuple[str, ...]
    many: bool = False

    def describe(self) -> str:
        head = "a comma-separated list of" if self.many else "one of"
        return f"{head} {', '.join(self.choices)}"

    def allows(self, value: Any) -> bool:
        if not isinstance(value, str):
            return False
        items = [v.strip() for v in value.split(",")] if self.many else [value]
        return bool(items) and all(v in self.choices for v in items)


Rule = Range | OneOf

POSITIVE = Range(0.0, low_open=True)
NON_NEGATIVE = Range(0.0)
FRACTION = Range(0.0, 1.0, low_open=True, high_open=True)  # (0, 1)
UNIT = Range(0.0, 1.0, low_open=True)  # (0, 1]
PART = Range(0.0, 1.0, high_open=True)  # [0, 1)
COUNT = Range(1, integer=True)
COUNT_OR_AUTO = Range(0, integer=True, note="0: automatic")

#: One rule per setting name, shared by the scenes (SI units).
SETTINGS: dict[str, Rule] = {
    # lengths (m)
    **dict.fromkeys(
        (
            "box_width",
            "box_height",
            "fill_height",
            "width",
            "height",
            "length",
            "depth",
            "diameter",
            "disc_radius",
            "calibration_radius",
            "cell_size",
            "min_diameter",
            "max_diameter",
            "d_min",
            "d_max",
            "sphero_radius",
            "thickness",
            "skin",
            "circle_diameter",
            "wall_half_width",
            "clamp_length",
            "tip_length",
        ),
        POSITIVE,
    ),
    "gap": NON_NEGATIVE,
    "bar_gap": NON_NEGATIVE,
    "spread": Range(1.0, note="1: cells keep their spacing"),
    "shrink": UNIT,
    "irregularity": PART,
    # contact law and material
    "normal_stiffness": POSITIVE,
    "tangential_stiffness": NON_NEGATIVE,
    "friction": NON_NEGATIVE,
    "contact_friction": NON_NEGATIVE,
    "side_friction": NON_NEGATIVE,
    "wall_friction": Range(0.0, nan="the contact friction"),
    "residual_friction": NON_NEGATIVE,
    "restitution": UNIT,
    "normal_damping": NON_NEGATIVE,
    "tangential_damping": NON_NEGATIVE,
    "damping_ratio": NON_NEGATIVE,
    "areal_density": POSITIVE,
    "density": POSITIVE,
    "poisson_ratio": Range(-1.0, 0.5, low_open=True, high_open=True),
    "modulus": POSITIVE,
    "youngs_modulus": Range(0.0, note="0: measured on the same material"),
    # bonds (paper 002 Eq. 11-15) and interfaces (paper 003)
    "b_n": NON_NEGATIVE,
    "b_t": NON_NEGATIVE,
    "b_m": NON_NEGATIVE,
    "eps_th": POSITIVE,
    "theta_th": POSITIVE,
    "sphero_fraction": Range(0.0, 0.3, low_open=True, high_open=True),
    "bond": OneOf(tuple(sorted(ENVELOPES))),
    "particles": OneOf(("discs", "voronoi")),
    "solid_fraction": FRACTION,
    "bond_gap": NON_NEGATIVE,
    "clearance": PART,
    "stiffness_ratio": POSITIVE,
    "tensile_strength": POSITIVE,
    "cohesion": NON_NEGATIVE,
    "friction_angle_deg": Range(0.0, 90.0, high_open=True),
    "compressive_strain": Range(0.0, low_open=True, note="inf: no compressive limit"),
    "n_elements": COUNT,
    "radius_multiplier": POSITIVE,
    # time stepping and records
    "dt": Range(0.0, note="0: dt_safety x the stable time step"),
    "dt_max": POSITIVE,
    "dt_safety": Range(0.0, 1.0, low_open=True, note="above 1 the explicit scheme is unstable"),
    "max_time": POSITIVE,
    "min_time": NON_NEGATIVE,
    "ke_stop_ratio": FRACTION,
    "settle_time": POSITIVE,
    "settle_ke_ratio": FRACTION,
    "settle_friction": Range(0.0, nan="the contact friction"),
    "record_every": COUNT,
    "records_per_segment": COUNT,
    "check_every": COUNT,
    "skin_fraction": POSITIVE,
    # loading
    "strain_rate": POSITIVE,
    "max_strain": FRACTION,
    "drop_fraction": FRACTION,
    "residual_fraction": FRACTION,
    "break_fraction": FRACTION,
    "compare_fraction": UNIT,
    "post_peak_strain": POSITIVE,
    "drop_min_q": NON_NEGATIVE,
    "plateau_strain": POSITIVE,
    "plateau_band": POSITIVE,
    "platen_speed": POSITIVE,
    "bar_speed": POSITIVE,
    "load_time": POSITIVE,
    "snapshot_times": NON_NEGATIVE,
    "post_break_time": NON_NEGATIVE,
    "max_force_ratio": POSITIVE,
    "iso_tolerance": FRACTION,
    "iso_max_time": POSITIVE,
    "servo_response": POSITIVE,
    "servo_integral": Range(0.0, low_open=True, note="inf: proportional servo alone"),
    "servo_max_speed": POSITIVE,
    "iso_max_speed": POSITIVE,
    "shear_damping": Range(0.0, note="0: none (paper 002: contact dashpots only)"),
    "p_values": POSITIVE,
    "confinements": POSITIVE,
    "band_fraction": Range(0.0, 0.5, low_open=True, high_open=True),
    "band": Range(0.0, 0.5, low_open=True),
    "max_bending_stress": POSITIVE,
    "ramp_periods": POSITIVE,
    "hold_periods": NON_NEGATIVE,
    "clamp": OneOf(("straight", "cells")),
    # specimens and ensembles
    "n_cells": Range(2, integer=True),
    "n_particles": COUNT,
    "n_circles": COUNT,
    "measure_cells": COUNT_OR_AUTO,
    "realisations": COUNT,
    "lloyd_iterations": Range(0, integer=True),
    "seed": Range(0, integer=True),
    # breakage (paper 000)
    "method": OneOf(METHODS),
    "methods": OneOf(METHODS, many=True),
    "target_force": POSITIVE,
    "calibration_force": POSITIVE,
    "eps": Range(0.0, note="0: calibrated from the Brazilian force"),
    "plane": OneOf(PLANES),
    "load_model": OneOf(LOAD_MODELS),
    "n_vertices": Range(4, integer=True),
    "n_points": COUNT,
    "screen": OneOf(("bound", "force")),
    "screen_fraction": UNIT,
    "erosion": OneOf(EROSION_MODES),
    "small_pieces": OneOf(SMALL_PIECE_MODES),
    "min_area_fraction": PART,
    "min_fragment_fraction": PART,
    "fragment_radius_floor": Range(0.0, 1.0, note="0: fragments keep the parent's radius"),
    "capacity_factor": Range(1.0),
    "vertex_capacity": COUNT_OR_AUTO,
    "start_fraction": POSITIVE,
    "ramp": Range(1.0, low_open=True),
    "max_fraction": POSITIVE,
}


def rule_for(cfg: Any, name: str) -> Rule | None:
    """The rule of setting ``name`` of ``cfg``: the scene's ``LIMITS`` first, then
    :data:`SETTINGS`; None where there is none (bool settings need none: any bool is
    allowed)."""
    limits = getattr(type(cfg), "LIMITS", {})
    return limits.get(name, SETTINGS.get(name))


def check(cfg: Any) -> None:
    """Raise ValueError at the first setting of the dataclass ``cfg`` that its rule refuses,
    then at the first broken relation (``cfg.relations()``)."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, bool):
            continue
        rule = rule_for(cfg, f.name)
        if rule is None:
            raise ValueError(f"setting {f.name} has no rule in jaxgran.scenes.limits")
        if not rule.allows(value):
            what = "every entry must be" if isinstance(value, tuple) else "it must be"
            raise ValueError(f"setting {f.name}={value!r} is refused: {what} {rule.describe()}")
    relations = getattr(cfg, "relations", None)
    if relations is not None:
        relations()


class Checked:
    """Base of the scene configurations: every setting is checked (:func:`check`) when a
    configuration is made. ``LIMITS`` overrides :data:`SETTINGS` for this scene;
    ``relations`` raises ValueError where two settings do not fit together."""

    LIMITS: ClassVar[dict[str, Rule]] = {}

    def __post_init__(self) -> None:
        # a list (a configuration read from JSON) is taken as the tuple it stands for, so
        # that the configuration stays hashable and the entries are checked one by one
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, list):
                object.__setattr__(self, f.name, tuple(value))
        check(self)

    def relations(self) -> None:
        """Checks between settings (none by default)."""


def require_less(cfg: Any, low: str, high: str) -> None:
    """ValueError unless setting ``low`` is below setting ``high``."""
    a, b = getattr(cfg, low), getattr(cfg, high)
    if not a < b:
        raise ValueError(f"settings {low}={a!r} and {high}={b!r}: {low} must be below {high}")


def _field_comments(cls) -> dict[str, str]:
    """The comments of the fields of a dataclass and of its dataclass bases, read from the
    source: the text after ``#`` on a field's line, after the comment lines just above it."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass is object:
            continue
        try:
            src = inspect.getsource(klass)
        except (OSError, TypeError):  # no source (e.g. a frozen application)
            continue
        above: list[str] = []
        lines: dict[int, str] = {}
        for tok in tokenize.generate_tokens(io.StringIO(src).readline):
            if tok.type == tokenize.COMMENT:
                lines[tok.start[0]] = tok.string.lstrip("#").strip()
        for k, line in enumerate(src.splitlines(), start=1):
            code = line.split("#", 1)[0].strip()
            if not code:  # a comment line (or blank): kept for the next field
                above = above + [lines[k]] if k in lines else []
                continue
            name = code.split(":", 1)[0].strip()
            if ":" in code and name.isidentifier() and not code.startswith(("def ", "class ")):
                text = " ".join(above + ([lines[k]] if k in lines else []))
                if text:
                    out[name] = text
            above = []
    return out


#: What the settings every scene has mean, for those whose field carries no comment.
MEANINGS: dict[str, str] = {
    "record_every": "steps between two records of the time series",
    "records_per_segment": "records per compiled segment (host checks between segments)",
    "seed": "random seed of the specimen (Voronoi seeds, packing)",
    "dt_safety": "time step as a fraction of the stable one",
    "lloyd_iterations": "Lloyd relaxation sweeps of the Voronoi seeds",
    "skin_fraction": "Verlet skin / mean cell size",
}


def describe_settings(cls) -> list[dict[str, str]]:
    """One row per setting of the scene configuration class ``cls``: ``name``, ``default``,
    ``allowed`` (the rule, :func:`check`) and ``meaning`` (the field's comment in the
    source: units, paper references, special values; else :data:`MEANINGS`)."""
    cfg = cls()
    comments = _field_comments(cls)
    rows = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, bool):
            allowed = "true or false"
        else:
            allowed = rule_for(cfg, f.name).describe()
            allowed = f"a list, each {allowed}" if isinstance(value, tuple) else allowed
        rows.append(
            {
                "name": f.name,
                "default": repr(value),
                "allowed": allowed,
                "meaning": comments.get(f.name, MEANINGS.get(f.name, "")),
            }
        )
    return rows
