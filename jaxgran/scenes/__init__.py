"""Lab tests, one module per scene. ``SCENES`` maps the CLI name to the module."""

from . import bonded_biaxial as bonded_biaxial
from . import bonded_brazilian as bonded_brazilian
from . import bonded_cantilever as bonded_cantilever
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
    "bonded-brazilian": bonded_brazilian,
    "bonded-biaxial": bonded_biaxial,
    "bonded-cantilever": bonded_cantilever,
}
