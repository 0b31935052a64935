"""Blender side of the ladar simulator: properties, scene export, results import, simulate, CLI.

Everything here is a plain function usable from scripts; ``operators/`` and ``panels/`` are thin wrappers.
Modules: ``properties`` (PropertyGroups generated from ``core.config`` and the Blender ↔ core mapping),
``sensor`` (receiver field of view from the camera), ``export`` (depsgraph → ``core.geometry.scene.SceneGeometry``),
``results`` (point cloud + images into Blender), ``simulate`` (the whole run), ``cli`` (``blender -c ladar``).
"""
