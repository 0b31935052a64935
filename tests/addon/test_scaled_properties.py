"""Properties whose Blender storage differs from the core's SI value (issues 14, 27): panel units (nm, ns, µJ, fJ,
mrad, 1/km, kHz, pA, ...), Blender units, MiB.  Each is set in SI through the Python API (``properties.set_settings``), simulated, and read back from the
run's metadata.json exactly."""
import json

import bpy
import pytest

from blender_scenes import add_camera, add_plate

C = 299_792_458.0
SCALE_LENGTH = 0.5  # metres per Blender unit: the distances' stored values differ from SI too

#: Every setting stored scaled → a valid SI value other than its default (exact through float32 storage).
SCALED = {
    "laser.wavelength_m": 532e-9,
    "laser.beam_waist_radius_m": 0.02,
    "laser.beam_focus_range_m": 150.0,
    "receiver.aperture_diameter_m": 0.08,
    "receiver.filter_bandwidth_m": 2e-8,
    "detector.dark_current_bulk_a": 3e-12,
    "detector.dark_current_surface_a": 2e-9,
    "run.max_memory_bytes": 512 * 2**20,
    "atmosphere.visibility_m": 12000.0,
    "atmosphere.cn2_m_23": 5e-15,
    "atmosphere.inner_scale_m": 0.005,
    "atmosphere.outer_scale_m": 50.0,
    "materials.Paint.table_wavelength_m": 905e-9,
    # issue 27: stored and shown in panel units (ns, µJ, fJ, mrad, 1/km, kHz)
    "laser.pulse_energy_j": 0.0025,
    "laser.pulse_fwhm_s": 3e-9,
    "laser.beam_divergence_rad": 2.2e-4,
    "gate.gate_start_s": 6.1e-7,
    "gate.bin_width_s": 1.5e-9,
    "scanner.pulse_rate_hz": 50_000.0,
    "gated.first_delay_s": 6.5e-7,
    "gated.delay_step_s": 2.5e-9,
    "gated.gate_width_s": 3e-8,
    "gated.shutter_edge_s": 1e-9,
    "gated.min_signal_j": 1e-18,
    "detection.threshold_j": 1e-18,
    "atmosphere.extinction_per_m": 1e-4,
    # issues 29, 30: an elliptical beam's second axis (mrad), the weather's distances, the scanner's range quantum
    "laser.beam_divergence_y_rad": 3e-4,
    "atmosphere.tx_rx_offset_m": 0.1,
    "atmosphere.backscatter_min_range_m": 1.5,
    "scanner.range_quantum_m": 0.004,
}


def _fields(lad):
    p = lad.properties
    out = {f.path: f for fs in p.SENSOR_FIELDS.values() for f in fs}
    out.update({f.path: f for f in p.ATMOSPHERE_FIELDS + p.TOP_FIELDS})
    out.update({f"materials.Paint.{f.name}": f for f in p.BRDF_FIELDS})
    out[p.SEED_FIELD.path] = p.SEED_FIELD
    return out


def test_the_scaled_properties_are_these(lad):
    """A setting that gets a scaled storage later must join SCALED (and so get its round-trip test)."""
    assert {path for path, f in _fields(lad).items() if f.conversion} == set(SCALED)


def _owner(scene, cam, path):
    head = path.split(".")[0]
    if head == "atmosphere":
        return scene.ladar_atmosphere
    if head == "materials":
        return bpy.data.materials["Paint"].ladar_brdf
    return getattr(cam.ladar, head)


@pytest.mark.parametrize("path", SCALED)
def test_si_value_set_through_the_python_api_reaches_the_run(lad, scene, tmp_path, path):
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = SCALE_LENGTH
    paint = bpy.data.materials.new("Paint")
    paint.ladar_brdf.enabled = True
    cam = add_camera(scene, width_px=4, height_px=4, fov_rad=0.004)
    add_plate(scene, size=20.0, location=(0.0, 0.0, -200.0), materials=(paint,))  # 100 m away
    lad.blend_config.set_settings(scene, cam, {"gate.gate_start_s": 2 * 90.0 / C, "gate.n_bins": 128})
    value = SCALED[path]
    cfg = lad.blend_config.set_settings(scene, cam, {path: value})
    field = _fields(lad)[path]
    stored = getattr(_owner(scene, cam, path), field.attr)
    assert stored != pytest.approx(value, rel=1e-3)  # stored scaled: an SI value written there would be wrong
    run, _ = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "run", import_results=False, previews=False)
    settings = json.loads((run / "metadata.json").read_text())["settings"]
    if path.startswith("materials."):
        got = settings["materials"]["Paint"][path.rsplit(".", 1)[1]]
    else:
        group, name = path.split(".")
        got = settings[group][name]
    assert got == value
    assert lad.blend_config.config_from_blender(scene, cam) == cfg


def test_set_settings_refuses_unknown_paths_and_bad_values_changing_nothing(lad, scene):
    cam = add_camera(scene)
    before = lad.blend_config.config_from_blender(scene, cam)
    with pytest.raises(lad.config.ConfigError, match="atmosphere.cn2"):
        lad.blend_config.set_settings(scene, cam, {"atmosphere.cn2": 5e-15})
    with pytest.raises(lad.config.ConfigError, match="atmosphere.cn2_m_23"):
        lad.blend_config.set_settings(scene, cam, {"laser.wavelength_m": 532e-9, "atmosphere.cn2_m_23": 1.0})
    with pytest.raises(lad.config.ConfigError, match="materials.Nope.reflectance"):
        lad.blend_config.set_settings(scene, cam, {"materials.Nope.reflectance": 0.5})
    assert lad.blend_config.config_from_blender(scene, cam) == before
