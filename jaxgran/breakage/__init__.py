"""Particle breakage: criteria (DSM connection points, averaged-stress methods), the subset
separation method, and replacement."""

from .averaged import AveragedStressBreakage as AveragedStressBreakage
from .averaged import calibrate_strengths as calibrate_strengths
from .averaged import make_breakage as make_breakage
from .criteria import ConnectionPoints as ConnectionPoints
from .criteria import CriterionResult as CriterionResult
from .criteria import averaged_stress as averaged_stress
from .criteria import breakage_type as breakage_type
from .criteria import connection_points as connection_points
from .criteria import cross_cut_criterion as cross_cut_criterion
from .criteria import fracture_planes as fracture_planes
from .criteria import mohr_coulomb_criterion as mohr_coulomb_criterion
from .criteria import principal_stresses as principal_stresses
from .criteria import split_cell_criterion as split_cell_criterion
from .dsm import DsmBreakage as DsmBreakage
from .dsm import calibrate_eps as calibrate_eps
from .dsm import calibration_report as calibration_report
from .replace import dilated_outline as dilated_outline
from .replace import fit_vertex_capacity as fit_vertex_capacity
from .replace import max_overlap as max_overlap
from .replace import replace_particle as replace_particle
from .replace import replace_particles as replace_particles
from .ssm import split_convex as split_convex
