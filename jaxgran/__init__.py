"""jaxgran: a differentiable, vectorised 2D DEM of breakable grains, written in JAX."""

__version__ = "0.1.0"
