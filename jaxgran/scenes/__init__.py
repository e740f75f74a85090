"""Lab tests, one module per scene. ``SCENES`` maps the CLI name to the module."""

from . import brazilian_dsm as brazilian_dsm
from . import deposit as deposit

SCENES = {"deposit": deposit, "brazilian-dsm": brazilian_dsm}
