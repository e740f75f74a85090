"""The error a researcher's request raises when it cannot be run as given.

:class:`SceneError` is a ``ValueError`` for a configuration that every setting's rule in
:mod:`jaxgran.scenes.limits` accepts but from which a scene cannot be built or continued:
no Voronoi cell within the asked size range, a cell too thin for the sphero-radius, a
checkpoint written with other settings or in another precision. ``jaxgran run`` prints it
as one ``error:`` line and exits with code 2; any other exception is an internal error and
keeps its traceback.
"""

from __future__ import annotations


class SceneError(ValueError):
    """A scene cannot be built or continued from the given settings (the message says
    which setting to change)."""
