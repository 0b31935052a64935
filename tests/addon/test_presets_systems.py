"""Whole-sensor and material presets: every shipped preset applies, round-trips (apply → read the config → the
preset's values), validates; user presets (add → apply elsewhere) reproduce the settings."""
import ast
import math
import types
from pathlib import Path

import bpy
import pytest

from blender_scenes import add_camera

PRESETS = Path(__file__).resolve().parents[2] / "presets" / "ladar_simulator"
SENSOR_FILES = sorted((PRESETS / "sensor").glob("*.py"))
MATERIAL_FILES = sorted((PRESETS / "material").glob("*.py"))


def _preset_values(path: Path) -> dict:
    """The settings dict a shipped preset passes to apply_*_preset (evaluated independently of the add-on)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
             and n.func.attr in ("apply_sensor_preset", "apply_material_preset")]
    assert len(calls) == 1, path
    return eval(compile(ast.Expression(calls[0].args[0]), str(path), "eval"), {"math": math})


def _execute(menu, path, **override):
    with bpy.context.temp_override(**override):
        assert bpy.ops.script.execute_preset(filepath=str(path), menu_idname=menu) == {"FINISHED"}


def _same(actual, expected, where):
    if isinstance(expected, float):
        assert actual == pytest.approx(expected, rel=1e-6), where
    else:
        assert actual == expected, where


def test_shipped_system_and_material_presets_exist(lad, scene):
    stems = {p.stem for p in SENSOR_FILES}
    assert stems == {"InGaAs_3D_flash_128x128_1570_nm", "Gated_viewing_532_nm_at_1_km",
                     "Spinning_905_nm_automotive_16_channels", "Airborne_1064_nm_full_waveform"}
    assert {"Asphalt_(NIR)", "Concrete_(NIR)", "Vegetation_(NIR_800-1300_nm)", "Paint_glossy",
            "Retroreflective_sheeting"} <= {p.stem for p in MATERIAL_FILES}
    for path in SENSOR_FILES + MATERIAL_FILES:
        text = path.read_text(encoding="utf-8")
        assert "not a measurement" in text or "not the data sheet" in text or "not a calibration" in text, path
    for menu, sub in [("LADAR_MT_sensor_presets", "sensor"), ("LADAR_MT_material_presets", "material")]:
        cls = getattr(bpy.types, menu)
        assert (PRESETS / sub).resolve() in [Path(d).resolve() for d in bpy.utils.preset_paths(cls.preset_subdir)]


@pytest.mark.parametrize("path", SENSOR_FILES, ids=lambda p: p.stem)
@pytest.mark.parametrize("unit_scale", [1.0, 0.5])
def test_every_sensor_preset_applies_and_round_trips(lad, scene, path, unit_scale):
    cam = add_camera(scene)
    if unit_scale != 1.0:
        scene.unit_settings.system = "METRIC"
        scene.unit_settings.scale_length = unit_scale
    cam.ladar.run.chunk_rays = 5000  # not a sensor setting: the preset leaves it alone
    expected = _preset_values(path)
    _execute("LADAR_MT_sensor_presets", path, object=cam)
    cfg = lad.blend_config.config_from_blender(scene, cam)
    lad.config.validate(cfg)
    assert cfg.system_type == expected["system_type"]
    for group, values in expected.items():
        if group == "system_type":
            continue
        for name, value in values.items():
            _same(getattr(getattr(cfg, group), name), value, f"{path.stem}: {group}.{name}")
    rx = cfg.receiver
    if "fov_x_rad" in expected.get("receiver", {}):
        # Square pixels: fov_y = 2·atan(tan(fov_x/2)·H/W).
        want_y = 2 * math.atan(math.tan(0.5 * rx.fov_x_rad) * rx.height_px / rx.width_px)
        assert rx.fov_y_rad == pytest.approx(want_y, rel=1e-6)
    assert cfg.run.chunk_rays == 5000


def test_sensor_presets_replace_each_other_and_fail_cleanly(lad, scene):
    cam = add_camera(scene)
    presets = lad.package.ladar_addon.presets
    flash, spin = (PRESETS / "sensor" / f"{n}.py" for n in ("InGaAs_3D_flash_128x128_1570_nm",
                                                               "Spinning_905_nm_automotive_16_channels"))
    _execute("LADAR_MT_sensor_presets", flash, object=cam)
    _execute("LADAR_MT_sensor_presets", spin, object=cam)
    cfg = lad.blend_config.config_from_blender(scene, cam)
    assert cfg.system_type == "scanner" and cfg.scanner.n_channels == 16
    assert cfg.laser.wavelength_m == pytest.approx(9.05e-7) and cfg.receiver.width_px == 128  # kept from flash
    # An invalid value changes nothing; an unknown group is named.
    with bpy.context.temp_override(object=cam):
        with pytest.raises(lad.config.ConfigError, match="laser.pulse_energy_j"):
            presets.apply_sensor_preset({"system_type": "flash", "laser": {"pulse_energy_j": -1.0}})
        with pytest.raises(lad.config.ConfigError, match="preset.lasers"):
            presets.apply_sensor_preset({"lasers": {}})
    assert lad.blend_config.config_from_blender(scene, cam).system_type == "scanner"
    bpy.data.objects.remove(cam)
    scene.camera = None
    with pytest.raises(lad.errors.LadarError, match="no camera"):
        presets.apply_sensor_preset({"system_type": "flash"})


@pytest.mark.parametrize("path", MATERIAL_FILES, ids=lambda p: p.stem)
def test_every_material_preset_applies_and_round_trips(lad, scene, path):
    mat = bpy.data.materials.new("M")
    expected = _preset_values(path)
    _execute("LADAR_MT_material_presets", path, material=mat)
    assert mat.ladar_brdf.enabled and mat.ladar_brdf.origin.startswith("Preset ")
    brdf = lad.blend_config.brdf_from_material(mat)
    lad.config.validate(brdf)
    for name, value in expected.items():
        if isinstance(value, list):
            assert getattr(brdf, name) == pytest.approx(value, rel=1e-6), (path.stem, name)
        else:
            _same(getattr(brdf, name), value, f"{path.stem}: {name}")
    if brdf.model != "table":
        from importlib import import_module
        brdf_mod = import_module(f"{lad.package.__name__}.core.physics.brdf")
        assert 0.0 < brdf_mod.directional_hemispherical_reflectance(brdf) <= 1.0  # energy conservation


def test_material_preset_worked_values(lad, scene):
    """Glossy paint is docs/theory.md §10's worked example: f_r(0°) = 0.1300, f_r(30°) = 0.06931 1/sr.
    Retroreflective sheeting: f_r = R_A/cos²θ → 70 at 0°, 40 at 30° (ASTM D4956 Type I anchors)."""
    from importlib import import_module
    brdf_mod = import_module(f"{lad.package.__name__}.core.physics.brdf")
    mat = bpy.data.materials.new("M")
    _execute("LADAR_MT_material_presets", PRESETS / "material" / "Paint_glossy.py", material=mat)
    f = brdf_mod.evaluate_brdf(lad.blend_config.brdf_from_material(mat), [1.0, math.cos(math.radians(30))])
    assert f == pytest.approx([0.1300, 0.06931], rel=5e-4)
    _execute("LADAR_MT_material_presets", PRESETS / "material" / "Retroreflective_sheeting.py", material=mat)
    brdf = lad.blend_config.brdf_from_material(mat)
    f = brdf_mod.evaluate_brdf(brdf, [1.0, math.cos(math.radians(30)), math.cos(math.radians(25))])
    assert f == pytest.approx([70.0, 30.0 / math.cos(math.radians(30)) ** 2, 50.5], rel=1e-6)  # 25°: (61+40)/2
    assert brdf.table_wavelength_m == pytest.approx(5.55e-7)
    # A Lambertian preset after a table keeps the (now unused) table.
    _execute("LADAR_MT_material_presets", PRESETS / "material" / "Concrete_(NIR).py", material=mat)
    brdf = lad.blend_config.brdf_from_material(mat)
    assert brdf.model == "lambertian" and brdf.reflectance == pytest.approx(0.35) and len(brdf.table_angle_deg) == 10
    # Bad values and a missing material are errors that change nothing.
    presets = lad.package.ladar_addon.presets
    with pytest.raises(lad.config.ConfigError, match=r"materials.M.table_brdf_per_sr\[1\]"):
        presets.apply_material_preset({"model": "table", "table_angle_deg": [0.0, 9.0],
                                       "table_brdf_per_sr": [1.0, -1.0]}, "bad", context=types.SimpleNamespace(
                                           material=mat))
    assert lad.blend_config.brdf_from_material(mat).model == "lambertian"
    with pytest.raises(lad.errors.LadarError, match="no material"):
        presets.apply_material_preset({"model": "lambertian"}, "x", context=types.SimpleNamespace(material=None))


def test_user_sensor_and_material_presets_round_trip(lad, scene, tmp_path):
    cam = add_camera(scene)
    _execute("LADAR_MT_sensor_presets", PRESETS / "sensor" / "Airborne_1064_nm_full_waveform.py", object=cam)
    cam.ladar.scanner.scan_rate_hz = 37.0
    mat = bpy.data.materials.new("Sign")
    _execute("LADAR_MT_material_presets", PRESETS / "material" / "Retroreflective_sheeting.py", material=mat)
    mat.ladar_brdf.table[3].brdf_per_sr = 41.5
    with bpy.context.temp_override(object=cam, material=mat):
        assert bpy.ops.ladar.sensor_preset_add(name="My Scanner") == {"FINISHED"}
        assert bpy.ops.ladar.material_preset_add(name="My Sign") == {"FINISHED"}
    sensor_path = bpy.utils.preset_find("My_Scanner", "ladar_simulator/sensor")
    material_path = bpy.utils.preset_find("My_Sign", "ladar_simulator/material")
    assert sensor_path and material_path
    try:
        want_cfg = lad.blend_config.config_from_blender(scene, cam)
        want_brdf = lad.blend_config.brdf_from_material(mat)
        other = add_camera(scene, name="Other", set_scene_camera=False)
        other_mat = bpy.data.materials.new("Other")
        _execute("LADAR_MT_sensor_presets", sensor_path, object=other)
        _execute("LADAR_MT_material_presets", material_path, material=other_mat)
        got = lad.blend_config.config_from_blender(scene, other)
        for group in ("laser", "receiver", "gate", "scanner", "gated", "detection", "detector"):
            assert getattr(got, group) == getattr(want_cfg, group), group
        assert got.system_type == "scanner" and got.scanner.scan_rate_hz == pytest.approx(37.0)
        assert lad.blend_config.brdf_from_material(other_mat) == want_brdf
        assert lad.blend_config.brdf_from_material(other_mat).table_brdf_per_sr[3] == 41.5
    finally:
        for p in (sensor_path, material_path):
            Path(p).unlink(missing_ok=True)
