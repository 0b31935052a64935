"""Frame ranges: one sequence run folder, geometry and BVH reused while static, points registered in world
coordinates, image sequences, per-run or per-frame clouds; and the CLI's --frames."""
import json
import os

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_plate

FOV = 0.004


def _scene(scene, tmp_path, width=8, previews=False):
    """The plate under the sensor.  ``previews``: the scene's "PNG Previews" setting, off where a test checks no
    preview (three PNGs a frame, 0.2-0.5 s of CPU each: most of this file's time); a sequence's previews are
    checked by :func:`test_static_scene_exports_once_and_builds_one_bvh` (the ``simulate`` command writes them
    whatever the setting: :func:`test_cli_frames` still does)."""
    cam = add_camera(scene, width_px=width, height_px=width, fov_rad=FOV)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=4.0, location=(0, 0, -100))
    scene.ladar.output_dir = str(tmp_path / "runs")
    scene.ladar.write_previews = previews
    return cam


def _attribute(obj, name, dtype=np.float32):
    attr = obj.data.attributes[name]
    out = np.empty(len(attr.data), dtype)
    attr.data.foreach_get("value", out)
    return out


def _positions(obj):
    pos = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", pos)
    return pos.reshape(-1, 3)


def _fcurves(obj):
    """The F-curves of an object's action (Blender ≥ 4.4 layered actions, or the legacy list)."""
    action = obj.animation_data.action
    if hasattr(action, "fcurves"):
        return action.fcurves
    from bpy_extras import anim_utils
    return anim_utils.action_get_channelbag_for_slot(action, obj.animation_data.action_slot).fcurves


def test_static_scene_exports_once_and_builds_one_bvh(lad, scene, tmp_path):
    _scene(scene, tmp_path, previews=True)
    scene.frame_set(7)
    job = lad.job.SimulationJob(scene, frames=[1, 2, 3]).run()
    run = tmp_path / "runs" / "Ladar_f0001-0003"
    assert job.run_path == run and job.state == "done"
    assert scene.frame_current == 7  # the scene returns to its frame
    assert job.source.exports == 1 and job.source.time_dependent == {}
    meta = json.loads((run / "metadata.json").read_text())
    assert meta["format"] == "ladar-sequence" and meta["frames"] == [1, 2, 3]
    assert meta["bvh_builds"] == 1 and meta["blender"]["geometry_exports"] == 1
    assert {f"frame_{f:04d}" for f in (1, 2, 3)} <= {p.name for p in run.iterdir()}
    for f in (1, 2, 3):
        frame_meta = json.loads((run / f"frame_{f:04d}" / "metadata.json").read_text())
        assert frame_meta["frame"] == f
        assert (run / f"frame_{f:04d}" / "range.png").is_file()
        # image sequences: hard links numbered by scene frame
        link = run / "images" / f"range_{f:04d}.exr"
        assert os.path.samefile(link, run / f"frame_{f:04d}" / "range.exr")
        assert (run / "images" / f"intensity_{f:04d}.png").is_file()
    # one merged cloud: 64 points per frame, registered in world coordinates on the plate
    obj = bpy.data.objects["Ladar_f0001-0003"]
    frames = _attribute(obj, "frame", np.int32)
    assert np.bincount(frames, minlength=4)[1:].tolist() == [64, 64, 64]
    np.testing.assert_allclose(_positions(obj)[:, 2], -100.0, atol=1e-3)
    merged = lad.flash.np.load(run / "points_merged.npz")
    assert len(merged["range_m"]) == 192
    img = bpy.data.images["Ladar_f0001-0003.range"]
    assert img.source == "SEQUENCE" and bpy.path.abspath(img.filepath) == str(run / "images" / "range_0001.exr")
    assert bpy.data.images["Ladar_f0001-0003.range.png"].source == "SEQUENCE"
    assert not [p for p in (tmp_path / "runs").iterdir() if p.name.startswith(".")]  # no staging left


def test_animated_plate_reexports_and_rebuilds_only_when_it_moves(lad, scene, tmp_path):
    _scene(scene, tmp_path)
    plate = bpy.data.objects["Plate"]
    plate.keyframe_insert("location", frame=1)   # still until frame 9, then a jump
    plate.location.z = -130.0
    plate.keyframe_insert("location", frame=9)
    for fc in _fcurves(plate):
        for key in fc.keyframe_points:
            key.interpolation = "CONSTANT"
    job = lad.job.SimulationJob(scene, frames=[1, 2, 3, 9], out_dir=tmp_path / "seq").run()
    assert job.source.time_dependent == {"Plate": ["animated"]}
    assert job.source.exports == 4                 # animated: every frame exported …
    assert job.source.geometries == 2              # … but frames 1–3 give the same geometry
    meta = json.loads((tmp_path / "seq" / "metadata.json").read_text())
    assert meta["bvh_builds"] == 2
    obj = bpy.data.objects["seq"]
    rng, frames = _attribute(obj, "range_m"), _attribute(obj, "frame", np.int32)
    for f, want in ((1, 100.0), (2, 100.0), (3, 100.0), (9, 130.0)):
        np.testing.assert_allclose(rng[frames == f], want, atol=2e-3)


def test_moving_sensor_registers_points_in_world_coordinates(lad, scene, tmp_path):
    cam = _scene(scene, tmp_path)
    cam.location = (-1.0, 0.0, 0.0)
    cam.keyframe_insert("location", frame=1)
    cam.location = (1.0, 0.0, 0.0)
    cam.keyframe_insert("location", frame=3)
    lad.simulate.simulate_sequence(scene, [1, 3], out_dir=tmp_path / "moving", clouds="FRAME")
    coll = bpy.data.collections["moving"]
    assert sorted(o.name for o in coll.objects) == ["moving_frame_0001", "moving_frame_0003"]
    for f, x in ((1, -1.0), (3, 1.0)):
        obj = bpy.data.objects[f"moving_frame_{f:04d}"]
        assert set(_attribute(obj, "frame", np.int32)) == {f}
        pos = _positions(obj)
        np.testing.assert_allclose(pos[:, 2], -100.0, atol=1e-3)       # on the plate …
        assert abs(pos[:, 0].mean() - x) < 1e-3                          # … under the sensor of that frame
        assert obj[lad.export.RESULT_TAG] == str(tmp_path / "moving" / f"frame_{f:04d}")


def test_sequence_names_are_checked_before_running(lad, scene, tmp_path):
    _scene(scene, tmp_path)
    lad.simulate.simulate_sequence(scene, [1, 2], out_dir=tmp_path / "s")
    with pytest.raises(lad.config.ConfigError, match="does not exist yet"):
        lad.simulate.simulate_sequence(scene, [1, 2], out_dir=tmp_path / "s")
    path, _ = lad.simulate.simulate_sequence(scene, [1, 2], out_dir=tmp_path / "s", if_exists="NEW")
    assert path.name == "s_2" and bpy.data.objects.get("s_2") is not None
    # replacing a sequence imported per run by one imported per frame leaves no stale cloud behind
    lad.simulate.simulate_sequence(scene, [1, 2], out_dir=tmp_path / "s", if_exists="REPLACE", clouds="FRAME")
    assert bpy.data.objects.get("s") is None
    assert {"s_frame_0001", "s_frame_0002"} <= set(bpy.data.objects.keys())
    with pytest.raises(lad.config.ConfigError, match="frames"):
        lad.frames.parse_frames("5-1")
    assert lad.frames.parse_frames("1-10:4,20") == [1, 5, 9, 20]
    for bad in ("", "a-b", "1-", "3,3", "1-5:0"):
        with pytest.raises(lad.config.ConfigError, match="frames"):
            lad.frames.parse_frames(bad)


def test_operator_frame_range(lad, scene, tmp_path):
    _scene(scene, tmp_path)
    scene.frame_start, scene.frame_end, scene.frame_step = 2, 6, 2
    scene.ladar.use_frame_range = True
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    meta = json.loads((tmp_path / "runs" / "Ladar_f0002-0006" / "metadata.json").read_text())
    assert meta["frames"] == [2, 4, 6]
    assert bpy.ops.ladar.simulate(frames="10-11") == {"FINISHED"}
    assert json.loads((tmp_path / "runs" / "Ladar_f0010-0011" / "metadata.json").read_text())["frames"] == [10, 11]


def test_cli_frames(lad, scene, tmp_path, capsys):
    _scene(scene, tmp_path)
    code = lad.cli.cli_handler(["simulate", "--frames", "1-3", "--out", str(tmp_path / "cli_seq"), "--seed", "4"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "frames   3 (1 … 3), 192 points, 1 BVH build(s), 1 geometry export(s)" in out
    # the figures a single run prints, over the frames (the ideal receiver: none possible, no SNR)
    assert "echoes   192 points (64 – 64 per frame), 192 pixels with an echo" in out
    assert "false    none possible: ideal receiver" in out and "summed over 3 frames" in out
    assert "\nsnr " not in out  # no SNR line (it said "no true return": a key absent from every frame merged)
    assert "holds 100.0 % of the hit energy" in out and "(all 3 frames)" in out
    assert "frame 2 (2/3)" in out  # progress lines name the frame
    meta = json.loads((tmp_path / "cli_seq" / "metadata.json").read_text())
    assert meta["seed"] == 4 and meta["frames"] == [1, 2, 3]
    code = lad.cli.cli_handler(["simulate", "--frames", "3-1"])
    assert code == 1 and "frames = '3-1'" in capsys.readouterr().err


def test_one_bvh_with_ladar_materials_and_the_full_settings_recorded(lad, scene, tmp_path):
    """Materials with ladar BRDFs (and a config file's override) are applied to the geometry by the add-on, so the
    core sees one scene object and builds one BVH; metadata still records the complete material table."""
    from blender_scenes import brdf_material
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=FOV)
    cam.ladar.receiver.subsamples = 1
    scene.ladar.write_previews = False  # (see _scene)
    paint = brdf_material("Paint", reflectance=0.2)
    add_plate(scene, size=4.0, location=(0, 0, -100), materials=(paint,))
    config = tmp_path / "bright.toml"
    config.write_text('schema_version = 1\n[materials."Paint"]\nreflectance = 0.8\n')
    run, stats = lad.simulate.simulate_sequence(scene, [1, 2, 3], out_dir=tmp_path / "mat", config_path=config)
    meta = json.loads((run / "metadata.json").read_text())
    assert meta["bvh_builds"] == 1
    assert meta["settings"]["materials"]["Paint"]["reflectance"] == 0.8
    frame = json.loads((run / "frame_0002" / "metadata.json").read_text())
    assert frame["settings"]["materials"]["Paint"]["reflectance"] == 0.8
    # the override is what the simulation used: received energy ∝ reflectance (0.8 from the file, not 0.2)
    _, single = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "plain", frame=2, import_results=False)
    assert stats[1]["received_energy_j"] / single.stats["received_energy_j"] == pytest.approx(4.0, rel=1e-9)


def test_sequence_report_counts_false_alarms(lad, scene, tmp_path):
    """Blender's report of a noisy sequence says how many of its points are false alarms (points_merged.npz's
    flags), as a single run's does."""
    cam = _scene(scene, tmp_path)
    cam.ladar.detector.mode = "noisy"
    cam.ladar.detector.background_rate_photons_per_s = 5e9
    cam.ladar.detection.k_sigma = 3.0
    job = lad.job.SimulationJob(scene, frames=[1, 2], previews=False, import_results=False).run()
    fa = np.load(job.run_path / "points_merged.npz")["false_alarm"]
    assert fa.sum() > 0
    assert job.summary() == f"{len(fa)} points ({int(fa.sum())} false alarms) in 2 frames in {job.run_path}"
