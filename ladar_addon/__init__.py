"""Blender side of the ladar simulator: properties, scene export, results import, simulate, CLI.

Everything here is a plain function usable from scripts; ``operators/`` and ``panels/`` are thin wrappers.
Modules, bottom to top: ``names`` (shared names, no imports) and ``fields`` (the core setting ↔ Blender property
mapping, no bpy); ``sensor`` (receiver field of view from the camera); ``properties`` (the PropertyGroups
generated from the field maps); ``blend_config`` (Blender ↔ SimulationConfig); ``materials`` (BRDF tables,
Principled mapping, plots); ``export`` (depsgraph → ``core.geometry.scene.SceneGeometry``); ``colors`` and
``results`` (point clouds + images into Blender), ``waveform_view``; ``run_inputs`` (sensor, run folder name,
settings), ``frames`` (frame ranges, each frame's inputs), ``job`` (one run: worker thread, main-thread
requests, import), ``simulate`` (script entry points); ``presets``; ``cli`` (``blender -c ladar``).
``operators/`` and ``panels/`` import these, never the reverse.
"""
