"""Lab tests, one module per scene. ``SCENES`` maps the CLI name to the module."""

from . import deposit as deposit

SCENES = {"deposit": deposit}
