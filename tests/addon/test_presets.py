"""Shipped presets (atmosphere, detector), user presets (add + re-apply) and the derived panel figures."""
import math
import types
from pathlib import Path

import bpy
import pytest

from blender_scenes import add_camera
from test_panels import _draw

PRESETS = Path(__file__).resolve().parents[2] / "presets" / "ladar_simulator"

ATMOSPHERE = {
    "Clear_(23_km)": {"visibility_m": 23000.0, "visibility_model": "kim"},
    "Haze_(5_km)": {"visibility_m": 5000.0, "visibility_model": "kim"},
    "Fog_(0.5_km)": {"visibility_m": 500.0, "visibility_model": "kim"},
    "Weak_turbulence": {"cn2_m_23": 1e-16},
    "Medium_turbulence": {"cn2_m_23": 1e-14},
    "Strong_turbulence": {"cn2_m_23": 1e-13},
    "Weather_clear": {"weather": "none", "visibility_m": 23000.0, "rain_rate_mm_h": 0.0},
    "Weather_haze_(5_km)": {"weather": "haze", "visibility_m": 5000.0, "rain_rate_mm_h": 0.0},
    "Weather_fog_(200_m)": {"weather": "fog", "visibility_m": 200.0, "rain_rate_mm_h": 0.0},
    "Weather_fog_(50_m)": {"weather": "fog", "visibility_m": 50.0, "rain_rate_mm_h": 0.0},
    "Weather_light_rain_(2.5_mm_h)": {"weather": "rain", "visibility_m": 0.0, "rain_rate_mm_h": 2.5},
    "Weather_heavy_rain_(25_mm_h)": {"weather": "rain", "visibility_m": 0.0, "rain_rate_mm_h": 25.0},
    "Weather_snow_(1_mm_h)": {"weather": "snow", "visibility_m": 0.0, "rain_rate_mm_h": 1.0},
}
DETECTOR = {
    "Si_APD_905_nm": {"detector_type": "apd", "quantum_efficiency": 0.8, "apd_gain": 100.0, "apd_k_eff": 0.02,
                      "dark_current_bulk_a": 1e-11, "dark_current_surface_a": 5e-9},
    "Si_APD_532_nm": {"detector_type": "apd", "quantum_efficiency": 0.75, "apd_gain": 100.0, "apd_k_eff": 0.02,
                      "dark_current_bulk_a": 5e-12, "dark_current_surface_a": 2e-9},
    "InGaAs_APD_1550_nm": {"detector_type": "apd", "quantum_efficiency": 0.8, "apd_gain": 15.0, "apd_k_eff": 0.4,
                           "dark_current_bulk_a": 1e-9, "dark_current_surface_a": 1e-8},
    "Geiger-mode_array": {"detector_type": "geiger", "quantum_efficiency": 0.25, "geiger_dead_time_bins": 100,
                          "dark_current_bulk_a": 1e-15},
}


def _run(menu, path):
    assert bpy.ops.script.execute_preset(filepath=str(path), menu_idname=menu) == {"FINISHED"}


def test_shipped_files_and_menus(lad, scene):
    assert {p.stem for p in (PRESETS / "atmosphere").glob("*.py")} == set(ATMOSPHERE)
    assert {p.stem for p in (PRESETS / "detector").glob("*.py")} == set(DETECTOR)
    for path in PRESETS.glob("*/*.py"):
        assert "not" in path.read_text().split("import bpy")[0]  # "typical ..., not a specific product/site"
    # Blender finds the shipped presets (the extension registers its preset path).
    for menu, sub in [("LADAR_MT_atmosphere_presets", "atmosphere"), ("LADAR_MT_detector_presets", "detector")]:
        cls = getattr(bpy.types, menu)
        assert cls.preset_operator == "script.execute_preset"
        dirs = [Path(d).resolve() for d in bpy.utils.preset_paths(cls.preset_subdir)]
        assert (PRESETS / sub).resolve() in dirs


@pytest.mark.parametrize("unit_scale", [1.0, 2.0])
def test_atmosphere_presets(lad, scene, unit_scale):
    cam = add_camera(scene)
    if unit_scale != 1.0:
        scene.unit_settings.system = "METRIC"
        scene.unit_settings.scale_length = unit_scale
    for name, expected in ATMOSPHERE.items():
        _run("LADAR_MT_atmosphere_presets", PRESETS / "atmosphere" / f"{name}.py")
        atm = lad.blend_config.config_from_blender(scene, cam).atmosphere
        for key, value in expected.items():
            assert getattr(atm, key) == (value if isinstance(value, str) else pytest.approx(value, rel=1e-6)), name
        if "cn2_m_23" in expected:
            assert atm.beam_broadening and atm.scintillation and atm.beam_wander and atm.turbulence_blur != "none"
    # Visibility and turbulence presets leave each other's fields alone.
    _run("LADAR_MT_atmosphere_presets", PRESETS / "atmosphere" / "Fog_(0.5_km).py")
    atm = lad.blend_config.config_from_blender(scene, cam).atmosphere
    assert atm.visibility_m == pytest.approx(500.0) and atm.cn2_m_23 == pytest.approx(1e-13)
    _run("LADAR_MT_atmosphere_presets", PRESETS / "atmosphere" / "Haze_(5_km).py")
    atm = lad.blend_config.config_from_blender(scene, cam).atmosphere
    assert atm.visibility_m == pytest.approx(5000.0) and atm.cn2_m_23 == pytest.approx(1e-13)
    lad.config.validate(lad.blend_config.config_from_blender(scene, cam))


def test_detector_presets(lad, scene):
    cam = add_camera(scene)
    for name, expected in DETECTOR.items():
        _run("LADAR_MT_detector_presets", PRESETS / "detector" / f"{name}.py")
        cfg = lad.blend_config.config_from_blender(scene, cam)
        lad.config.validate(cfg)
        assert cfg.detector.mode == "noisy"
        for key, value in expected.items():
            assert getattr(cfg.detector, key) == (value if isinstance(value, str) else
                                                  pytest.approx(value, rel=1e-6)), (name, key)


def test_user_preset_round_trip(lad, scene):
    cam = add_camera(scene)
    cam.ladar.detector.apd_gain = 42.0
    cam.ladar.detector.dark_current_bulk_a = 3.0  # 3 pA
    assert bpy.ops.ladar.detector_preset_add(name="My Detector") == {"FINISHED"}
    scene.ladar_atmosphere.cn2_m_23 = 2.5
    scene.ladar_atmosphere.visibility_m = 1234.0
    assert bpy.ops.ladar.atmosphere_preset_add(name="My Air") == {"FINISHED"}
    det_path = bpy.utils.preset_find("My_Detector", "ladar_simulator/detector")
    atm_path = bpy.utils.preset_find("My_Air", "ladar_simulator/atmosphere")
    assert det_path and atm_path
    try:
        _run("LADAR_MT_detector_presets", PRESETS / "detector" / "InGaAs_APD_1550_nm.py")
        _run("LADAR_MT_atmosphere_presets", PRESETS / "atmosphere" / "Clear_(23_km).py")
        _run("LADAR_MT_atmosphere_presets", PRESETS / "atmosphere" / "Weak_turbulence.py")
        assert cam.ladar.detector.apd_gain == pytest.approx(15.0)
        _run("LADAR_MT_detector_presets", det_path)
        _run("LADAR_MT_atmosphere_presets", atm_path)
        cfg = lad.blend_config.config_from_blender(scene, cam)
        assert cfg.detector.apd_gain == pytest.approx(42.0)
        assert cfg.detector.dark_current_bulk_a == pytest.approx(3e-12)
        assert cfg.atmosphere.cn2_m_23 == pytest.approx(2.5e-14)
        assert cfg.atmosphere.visibility_m == pytest.approx(1234.0)
        # Removing a user preset works; shipped presets cannot be removed.
        bpy.types.LADAR_MT_detector_presets.bl_label = "My Detector"
        assert bpy.ops.ladar.detector_preset_add(remove_active=True) == {"FINISHED"}
        assert not Path(det_path).exists()
    finally:
        for p in (det_path, atm_path):
            Path(p).unlink(missing_ok=True)


def test_derived_physics_numbers(lad, scene):
    import importlib
    derived = importlib.import_module(f"{lad.package.__name__}.ladar_addon.derived")
    atm = lad.config.AtmosphereSettings(cn2_m_23=1e-14)
    fig = derived.atmosphere_figures(atm, 1.064e-6, 2000.0)
    t = fig["turbulence"]
    assert t["rytov_variance_plane"] == pytest.approx(1.100, rel=1e-3)
    assert t["rho0_spherical_m"] == pytest.approx(0.02832, rel=1e-3)
    assert fig["two_way_transmission"] == 1.0 and "turbulence" not in derived.atmosphere_figures(
        lad.config.AtmosphereSettings(), 1.064e-6, 2000.0)
    lines = derived.atmosphere_lines(atm, 1.064e-6, 2000.0)
    assert any("1.1" in line and "Rytov" in line for line in lines)
    # Visibility: extinction from Kim at the wavelength, T² = exp(-2σR).
    haze = lad.config.AtmosphereSettings(visibility_m=5000.0)
    fig = derived.atmosphere_figures(haze, 1.064e-6, 1000.0)
    assert fig["two_way_transmission"] == pytest.approx(math.exp(-2 * fig["extinction_per_m"] * 1000.0))
    assert 0.3 < fig["extinction_per_km"] < 3.912 / 5.0
    # Detector: 1 fJ at 1064 nm = 5356 photons; McIntyre F(100, 0.02) = 3.950.
    cfg = lad.config.SimulationConfig()
    d = derived.detector_figures(cfg, 1000.0)
    assert d["photons_per_fj"] == pytest.approx(5356, rel=1e-3)
    assert d["excess_noise_factor"] == pytest.approx(3.950, rel=1e-3)
    rx = cfg.receiver
    expected_e = (cfg.laser.pulse_energy_j / (rx.width_px * rx.height_px) * 0.1 / math.pi
                  * math.pi * rx.aperture_diameter_m ** 2 / 4 / 1000.0 ** 2 * rx.system_efficiency)
    assert d["received_energy_j"] == pytest.approx(expected_e)
    assert d["snr"] > 0
    assert derived.detector_lines(None, 1000.0)[0].startswith("Derived figures unavailable")


def test_panels_draw_presets_and_figures(lad, scene):
    panels = lad.package.panels
    cam = add_camera(scene)
    ctx = types.SimpleNamespace(object=cam, camera=cam.data, scene=scene, material=None)
    scene.ladar_atmosphere.cn2_m_23 = 1.0
    scene.ladar_atmosphere.visibility_m = 5000.0
    for system_type in lad.fields.SYSTEM_TYPE_FIELD.meta["choices"]:
        cam.ladar.system_type = system_type
        for det_type in ("pin", "apd", "geiger"):
            cam.ladar.detector.detector_type = det_type
            log = _draw(panels.LADAR_PT_sensor_detector, ctx)
            texts = [text for kind, text in log if kind == "label"]
            assert any("photons per fJ" in t for t in texts), texts
            assert any(("SNR" in t) if det_type != "geiger" else ("Detection probability" in t) for t in texts)
            log = _draw(panels.LADAR_PT_atmosphere, ctx)
            texts = [text for kind, text in log if kind == "label"]
            assert any("Extinction" in t for t in texts) and any("Rytov" in t for t in texts), texts
    assert ("menu", "LADAR_MT_atmosphere_presets") in _draw(panels.LADAR_PT_atmosphere, ctx, "draw_header_preset")
    assert ("menu", "LADAR_MT_detector_presets") in _draw(panels.LADAR_PT_sensor_detector, ctx,
                                                           "draw_header_preset")
    # No sensor at all: the atmosphere panel still draws (1064 nm).
    bpy.data.objects.remove(cam)
    texts = [t for k, t in _draw(panels.LADAR_PT_atmosphere, types.SimpleNamespace(scene=scene)) if k == "label"]
    assert any("1064 nm" in t for t in texts)
