"""Calibration of bonded-Voronoi micro-parameters against measured macro-properties:
:mod:`calibration.fit` (run it as ``python -m calibration.fit``), :mod:`calibration.twin`
for a synthetic-twin check and :mod:`calibration.plots`.

The package imports none of them itself: ``python -m calibration.fit`` would otherwise find
``calibration.fit`` already imported when it starts it as ``__main__`` (runpy warns about
two copies of the module)."""
