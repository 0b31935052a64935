"""Ladar Simulator: a ray-tracing 3D ladar simulator as a Blender extension.

The repository root is the extension root.  ``core/`` is the simulator (numpy, never bpy); ``ladar_addon/``
the Blender-side model; ``operators/`` and ``panels/`` thin UI wrappers.  Imports are relative because the
installed package is ``bl_ext.<repository>.ladar_simulator``.
"""
import importlib.util

#: Python packages the add-on needs beyond Blender's own (numpy): the built zips bundle them as wheels.
REQUIRED_MODULES = ("scipy", "embreex", "OpenEXR", "matplotlib")


def missing_modules(find_spec=importlib.util.find_spec) -> list:
    """The required packages this Python cannot import."""
    return [name for name in REQUIRED_MODULES if find_spec(name) is None]


def missing_message(missing) -> str:
    """What to do when Blender's Python lacks ``missing`` (a checkout installed as a local repository)."""
    return (f"Ladar Simulator needs the Python package(s) {', '.join(missing)}, which this Blender does not have. "
            "Install the extension from its built zip, which bundles them: in the repository run "
            "'python scripts/build_extension.py --platforms linux-x64' (or windows-x64, macos-arm64, macos-x64), "
            "then Edit > Preferences > Get Extensions > Install from Disk on "
            "dist/ladar_simulator-<version>-<platform>.zip. To use a checkout directly, install them into "
            "Blender's Python at the versions pinned in requirements.txt "
            "(<blender>/<version>/python/bin/python3.11 -m pip install scipy==... ).")


_missing = missing_modules()
if _missing:
    raise ImportError(missing_message(_missing))

from . import operators, panels  # noqa: E402 - after the dependency check
from .ladar_addon import cli, presets, properties  # noqa: E402

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
