"""Add-on tests run through the ``bpy`` module with the extension installed the way Blender installs it.

``import bpy`` happens once per process: the session fixture ``addon`` isolates Blender's user resources in a
temporary folder (before importing bpy), installs the repository as an extension in a local extension
repository and enables ``bl_ext.ladar_dev.ladar_simulator``.  Each test starts from an empty file
(``scene`` fixture).  Tests reach the add-on's modules through ``lad`` (the installed package), never as
top-level imports: the installed add-on has its own copy of ``core``.
"""
from __future__ import annotations

import importlib
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
import blender_env  # noqa: E402

# Before any test module (or helper) imports bpy: Blender's preferences and extensions go to a temporary folder.
RESOURCES = blender_env.isolate_user_resources()  # a temporary folder, removed at exit


@pytest.fixture(scope="session")
def addon():
    """The enabled add-on package (installed once per test session)."""
    import bpy  # noqa: F401

    return blender_env.install_extension()


@pytest.fixture(scope="session")
def lad(addon):
    """The installed add-on's modules: lad.properties, lad.export, ..., lad.config (its core.config)."""
    name = addon.__name__
    ns = types.SimpleNamespace(package=addon)
    for short, mod in [("properties", "ladar_addon.properties"), ("blend_config", "ladar_addon.blend_config"),
                       ("fields", "ladar_addon.fields"), ("export", "ladar_addon.export"),
                       ("results", "ladar_addon.results"), ("colors", "ladar_addon.colors"),
                       ("waveform_view", "ladar_addon.waveform_view"), ("simulate", "ladar_addon.simulate"), ("job", "ladar_addon.job"),
                       ("frames", "ladar_addon.frames"), ("run_inputs", "ladar_addon.run_inputs"),
                       ("cli", "ladar_addon.cli"), ("sensor", "ladar_addon.sensor"),
                       ("errors", "ladar_addon.errors"), ("config", "core.config"), ("scene", "core.geometry.scene"),
                       ("flash", "core.systems.flash"), ("staging", "core.fileio.staging")]:
        setattr(ns, short, importlib.import_module(f"{name}.{mod}"))
    return ns


@pytest.fixture
def scene(addon):
    """A fresh, empty file and its scene (the add-on stays enabled)."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True)
    return bpy.context.scene
