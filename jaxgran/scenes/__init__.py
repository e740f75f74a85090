"""Lab tests, one module per scene. ``SCENES`` maps the CLI name to the module."""

from . import bonded_biaxial as bonded_biaxial
from . import bonded_brazilian as bonded_brazilian
from . import bonded_cantilever as bonded_cantilever
from . import brazilian_dsm as brazilian_dsm
from . import breakage_types as breakage_types
from . import deposit as deposit
from . import interface_brazilian as interface_brazilian
from . import interface_compression as interface_compression
from . import interface_plate as interface_plate
from . import interface_tension as interface_tension
from . import interface_uniaxial as interface_uniaxial
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
    "interface-tension": interface_tension,
    "interface-compression": interface_compression,
    "interface-uniaxial": interface_uniaxial,
    "interface-brazilian": interface_brazilian,
    "plate-contact": interface_plate,
}
