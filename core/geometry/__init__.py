"""Geometry layer: triangle scenes, ray tracing (embreex + float64 refinement), frustum culling, sensor motion and
receiver rays.  Imports only the settings layer, ``core.constants`` and ``core.errors``."""
