"""The extension installs from a local extension repository and registers/unregisters cleanly, twice."""
import sys

import bpy
import pytest

import blender_env

PROPERTY_HOMES = [(bpy.types.Object, "ladar"), (bpy.types.Scene, "ladar"), (bpy.types.Scene, "ladar_atmosphere"),
                  (bpy.types.Material, "ladar_brdf")]
OPERATORS = ["LADAR_OT_simulate", "LADAR_OT_export_config", "LADAR_OT_load_config"]
PANELS = ["LADAR_PT_sensor", "LADAR_PT_sensor_laser", "LADAR_PT_scene", "LADAR_PT_atmosphere", "LADAR_PT_brdf"]


def _registered():
    props = [hasattr(owner, name) for owner, name in PROPERTY_HOMES]
    ops = [hasattr(bpy.types, name) for name in OPERATORS]
    panels = [hasattr(bpy.types, name) for name in PANELS]
    return props, ops, panels


def _enabled_modules():
    return {a.module for a in bpy.context.preferences.addons}


def test_installed_as_an_extension(addon):
    assert addon.__name__ == "bl_ext.ladar_dev.ladar_simulator"
    assert blender_env.ADDON_MODULE in _enabled_modules()
    # the add-on's core is the package-relative one, never the top-level `core`
    assert "bl_ext.ladar_dev.ladar_simulator.core.config" in sys.modules
    assert (addon.ladar_addon.blend_config.SimulationConfig.__module__
            == "bl_ext.ladar_dev.ladar_simulator.core.config.settings")
    repo = next(r for r in bpy.context.preferences.extensions.repos if r.module == blender_env.REPO_MODULE)
    assert (blender_env.Path(repo.directory) / "ladar_simulator" / "blender_manifest.toml").is_file()


def test_enable_disable_twice(addon, scene):
    assert _registered() == ([True] * 4, [True] * 3, [True] * 5)
    try:
        for _ in range(2):
            blender_env.disable_addon()
            assert blender_env.ADDON_MODULE not in _enabled_modules()
            assert _registered() == ([False] * 4, [False] * 3, [False] * 5)
            assert addon._cli_handle is None
            with pytest.raises(AttributeError):
                bpy.ops.ladar.simulate()

            blender_env.enable_addon()
            assert blender_env.ADDON_MODULE in _enabled_modules()
            assert _registered() == ([True] * 4, [True] * 3, [True] * 5)
            assert addon._cli_handle is not None
            # the properties work again on new data
            cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
            cam.ladar.receiver.width_px = 32
            assert cam.ladar.receiver.width_px == 32
            bpy.data.objects.remove(cam)
    finally:
        if blender_env.ADDON_MODULE not in _enabled_modules():
            blender_env.enable_addon()


def test_settings_survive_save_and_reload(addon, scene, tmp_path):
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.ladar.laser.pulse_energy_uj = 2000.0
    scene.ladar.seed = 1234
    scene.ladar_atmosphere.extinction_per_km = 0.1
    path = tmp_path / "saved.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    cam = bpy.data.objects["cam"]
    assert cam.ladar.laser.pulse_energy_uj == 2000.0
    assert bpy.context.scene.ladar.seed == 1234
    assert abs(bpy.context.scene.ladar_atmosphere.extinction_per_km - 0.1) < 1e-7


def test_old_core_paths_resolve_inside_the_installed_package(addon):
    """The moved-module finder works relative to the add-on's own copy of core (bl_ext.<repo>.<id>.core)."""
    import importlib
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = importlib.import_module(f"{addon.__name__}.core.runio")
        split = importlib.import_module(f"{addon.__name__}.core.pipeline")
    new = f"{addon.__name__}.core.fileio.run_folder"
    assert old is importlib.import_module(new)
    assert old.__spec__.name == new
    assert split.run_simulation is importlib.import_module(f"{addon.__name__}.core.run").run_simulation
    assert any(issubclass(w.category, DeprecationWarning) and new in str(w.message) for w in caught)
