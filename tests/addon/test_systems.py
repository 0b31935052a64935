"""Every system type through the add-on: scanner (with a moving, animated sensor: sampled trajectory), gated
viewing (slices as an image sequence), range profiler (waveform view by default); results imported with their
attributes."""
import json
import math

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_plate


def _fcurves(obj):
    action = obj.animation_data.action
    if hasattr(action, "fcurves"):
        return action.fcurves
    from bpy_extras import anim_utils
    return anim_utils.action_get_channelbag_for_slot(action, obj.animation_data.action_slot).fcurves


def _attribute(obj, name, dtype=np.float32):
    attr = obj.data.attributes[name]
    out = np.empty(len(attr.data), dtype)
    attr.data.foreach_get("value", out)
    return out


def _scanner(cam):
    cam.ladar.system_type = "scanner"
    sc = cam.ladar.scanner
    sc.pattern, sc.n_lines, sc.pulse_rate_khz, sc.scan_rate_hz = "raster", 5, 2.0, 100.0  # 0.05 s, 100 pulses
    sc.scan_width_rad = sc.scan_height_rad = 0.1
    sc.beam_subray_rings = 0
    cam.ladar.laser.beam_divergence_mrad = 1.0
    cam.ladar.gate.gate_start_ns = 600.0   # 90 m …
    cam.ladar.gate.n_bins = 200            # … 120 m


def test_scanner_with_an_animated_sensor_samples_its_trajectory(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.2)
    add_plate(scene, size=60.0, location=(0, 0, -100))
    _scanner(cam)
    scene.render.fps, scene.render.fps_base = 24, 1.0
    cam.keyframe_insert("location", frame=1)
    cam.location.x = 2.0
    cam.keyframe_insert("location", frame=3)
    for fc in _fcurves(cam):
        for key in fc.keyframe_points:
            key.interpolation = "LINEAR"
    run, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "scan", frame=1)
    meta = json.loads((run / "metadata.json").read_text())
    # 0.05 s at 24 fps: min(1000 Hz × 0.05 s, 16 per frame × 1.2 frames) = 20 intervals → 21 poses
    assert meta["blender"]["export"]["motion_samples"] == 21
    assert result.range_image is None and not (run / "range.exr").exists()
    pulses = np.load(run / "pulses.npz")
    # the sensor moves 1 m per frame = 24 m/s: every pulse fired from x = 24 m/s × t (start of frame 1: t = 0)
    np.testing.assert_allclose(pulses["origin_world"][:, 0], 24.0 * pulses["time_s"], atol=1e-6)
    obj = bpy.data.objects["scan"]
    pos = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(-1, 3)
    assert len(pos) == 100
    np.testing.assert_allclose(pos[:, 2], -100.0, atol=1e-3)  # registered on the wall, not smeared
    # scanner attributes: pulse index, channel, GPS time (relative to the object's offset, float64 kept)
    np.testing.assert_array_equal(np.sort(_attribute(obj, "pulse_index", np.int32)), np.arange(100))
    gps = _attribute(obj, "gps_time_s").astype(np.float64) + obj["gps_time_offset_s"]
    start_s = 1 / 24  # scene time of frame 1
    np.testing.assert_allclose(np.sort(gps), start_s + np.arange(100) / 2000.0, atol=1e-7)
    assert obj["gps_time_offset_s"] == pytest.approx(start_s)
    assert set(_attribute(obj, "channel", np.int32)) == {0}


def test_static_scanner_has_no_trajectory(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.2)
    add_plate(scene, size=60.0, location=(0, 0, -100))
    _scanner(cam)
    run, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "scan")
    meta = json.loads((run / "metadata.json").read_text())
    assert meta["blender"]["export"]["motion_samples"] == 0
    assert lad.frames.motion_sample_count(0.05, 1000.0, 24.0) == 21
    assert lad.frames.motion_sample_count(100.0, 1000.0, 24.0) == lad.frames.MAX_MOTION_SAMPLES
    assert lad.frames.motion_sample_count(1e-6, 1000.0, 24.0) == 2


def test_gated_slices_load_as_an_image_sequence(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=4.0, location=(0, 0, -150))
    cam.ladar.system_type = "gated"
    g = cam.ladar.gated
    g.n_slices, g.first_delay_ns, g.delay_step_ns, g.gate_width_ns = 6, 2e9 * 145 / 299_792_458.0, 10.0, 20.0
    run, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "gated")
    names = sorted(p.name for p in (run / "slices").iterdir())
    assert names == [f"slice_{k:04d}.{ext}" for k in range(1, 7) for ext in ("exr", "png")]
    img = bpy.data.images["gated.slices"]
    assert img.source == "SEQUENCE" and img.filepath == str(run / "slices" / "slice_0001.exr")
    assert img.colorspace_settings.name == "Non-Color"
    assert bpy.data.images["gated.slices.png"].source == "SEQUENCE"
    assert (run / "range.png").is_file()
    np.testing.assert_allclose(np.nanmedian(result.range_image), 150.0, atol=0.5)


def test_profiler_waveform_view(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.01)
    cam.ladar.system_type = "profiler"
    cam.ladar.receiver.subsamples = 16
    cam.ladar.gate.gate_start_ns = 2e9 * 95 / 299_792_458.0
    cam.ladar.gate.n_bins = 128
    add_plate(scene, size=4.0, location=(0, 0, -100), rotation=(math.radians(30), 0, 0))
    run, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "prof")
    assert result.waveforms.shape == (1, 1, 128)
    assert (run / "waveform.png").is_file() and (run / "profile.csv").is_file()
    scene.ladar.last_run = str(run)
    assert bpy.ops.ladar.waveform_view() == {"FINISHED"}
    img = bpy.data.images["prof.waveform"]
    assert img.filepath == str(run / "previews" / "waveform_x0000_y0000.png")
    assert tuple(img.size) == (640, 360)
    path, what = lad.waveform_view.waveform_plot(run)
    assert what["energy_j"] == pytest.approx(float(result.waveforms.sum()), rel=1e-6)
    assert what["echo_ranges_m"] == pytest.approx(sorted(result.points["range_m"].tolist()), rel=1e-9)
    with pytest.raises(lad.config.ConfigError, match="pixel_x"):
        lad.waveform_view.waveform_plot(run, pixel_x=1)


def test_gated_sequence_loads_each_frames_slices(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=4, height_px=4, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=4.0, location=(0, 0, -150))
    cam.ladar.system_type = "gated"
    g = cam.ladar.gated
    g.n_slices, g.first_delay_ns, g.delay_step_ns, g.gate_width_ns = 3, 2e9 * 145 / 299_792_458.0, 20.0, 40.0
    run, _ = lad.simulate.simulate_sequence(scene, [1, 2], out_dir=tmp_path / "gseq", clouds="FRAME")
    for f in (1, 2):
        img = bpy.data.images[f"gseq_frame_{f:04d}.slices"]
        assert img.source == "SEQUENCE"
        assert img.filepath == str(run / f"frame_{f:04d}" / "slices" / "slice_0001.exr")
    assert bpy.data.images["gseq.range"].filepath == str(run / "images" / "range_0001.exr")
    # the names are reserved: a second import of the same run without Replace is refused before anything changes
    with pytest.raises(lad.errors.LadarError, match="already exists"):
        lad.results.import_run(run, scene, clouds="FRAME")
