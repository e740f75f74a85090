"""Lab tests, one module per scene. ``SCENES`` maps the CLI name to the module."""

from . import brazilian_dsm as brazilian_dsm
from . import breakage_types as breakage_types
from . import deposit as deposit
from . import oedometer_cantor as oedometer_cantor
from . import oedometer_voronoi as oedometer_voronoi

SCENES = {
    "deposit": deposit,
    "brazilian-dsm": brazilian_dsm,
    "breakage-types": breakage_types,
    "oedometer-cantor": oedometer_cantor,
    "oedometer-voronoi": oedometer_voronoi,
}
