"""Particle breakage: criteria, subset separation, replacement."""
