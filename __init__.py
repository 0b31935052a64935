"""Ladar Simulator: a ray-tracing 3D ladar simulator as a Blender extension.

The repository root is the extension root.  ``core/`` is the simulator (numpy, never bpy); ``ladar_addon/``
the Blender-side model; ``operators/`` and ``panels/`` thin UI wrappers.  Imports are relative because the
installed package is ``bl_ext.<repository>.ladar_simulator``.
"""
from . import operators, panels
from .ladar_addon import cli, presets, properties

_cli_handle = None


def register():
    global _cli_handle
    properties.register()
    presets.register()
    operators.register()
    panels.register()
    _cli_handle = cli.register()


def unregister():
    global _cli_handle
    cli.unregister(_cli_handle)
    _cli_handle = None
    panels.unregister()
    operators.unregister()
    presets.unregister()
    properties.unregister()
