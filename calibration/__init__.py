"""Calibration of bonded-Voronoi micro-parameters against measured macro-properties
(``python -m calibration.fit``; :mod:`calibration.twin` for a synthetic-twin check)."""

from .fit import GROUPS as GROUPS
from .fit import Problem as Problem
from .fit import Target as Target
from .fit import adam as adam
from .fit import make_problem as make_problem
from .fit import nelder_mead as nelder_mead
from .fit import parameters_from_groups as parameters_from_groups
from .fit import uncertainty as uncertainty
