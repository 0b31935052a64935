"""bpy.ops.ladar.simulate and simulate_scene on tiny scenes: numbers, results in Blender, errors write nothing."""
import json
import math

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_mesh, add_plate, brdf_material

FOV = 0.004  # rad: a 16×16 receiver sees 0.4 m × 0.4 m at 100 m, slant ranges within 0.2 mm of the axis range


def _plate_scene(scene, tmp_path, distance=100.0):
    cam = add_camera(scene, width_px=16, height_px=16, fov_rad=FOV)
    cam.ladar.receiver.subsamples = 2
    add_plate(scene, size=2.0, location=(0, 0, -distance))
    scene.ladar.output_dir = str(tmp_path / "runs")
    return cam


def _attribute(obj, name, dtype=np.float32):
    attr = obj.data.attributes[name]
    out = np.empty(len(attr.data), dtype)
    attr.data.foreach_get("value", out)
    return out


def test_operator_plate_at_100_m(lad, scene, tmp_path):
    _plate_scene(scene, tmp_path)
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    run = tmp_path / "runs" / "Ladar_f0001"
    assert {"range.exr", "intensity.exr", "energy.exr", "points.ply", "points.npz", "metadata.json",
            "waveforms.npy"} <= {p.name for p in run.iterdir()}
    obj = bpy.data.objects["Ladar_f0001"]
    assert obj[lad.export.RESULT_TAG] == str(run)
    assert len(obj.data.vertices) == 16 * 16 and len(obj.data.polygons) == 0
    range_m = _attribute(obj, "range_m")
    assert np.all(np.abs(range_m - 100.0) < 1e-3), (range_m.min(), range_m.max())
    # positions are the world points: 100 m down the −Z axis, within the 0.4 m footprint
    pos = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", pos)
    pos = pos.reshape(-1, 3)
    np.testing.assert_allclose(pos[:, 2], -100.0, atol=1e-3)
    assert np.abs(pos[:, :2]).max() < 0.2
    for name, dtype in (("echo_index", np.int32), ("n_echoes", np.int32), ("frame", np.int32)):
        assert set(_attribute(obj, name, dtype)) == {1}
    px, py = _attribute(obj, "pixel_x", np.int32), _attribute(obj, "pixel_y", np.int32)
    assert sorted(zip(py, px)) == [(y, x) for y in range(16) for x in range(16)]
    np.testing.assert_allclose(_attribute(obj, "time_s"), 2 * 100.0 / 299_792_458.0, rtol=1e-5)
    norm = _attribute(obj, "intensity_norm")
    assert norm.max() == pytest.approx(1.0) and norm.min() > 0.0
    # display set-up: Geometry Nodes points + the intensity material
    mod = obj.modifiers["Ladar Points"]
    assert mod.type == "NODES" and mod.node_group.name == "Ladar Point Cloud"
    node_types = {n.bl_idname for n in mod.node_group.nodes}
    assert {"GeometryNodeMeshToPoints", "GeometryNodeSetMaterial"} <= node_types
    mat = obj.data.materials[0]
    attr_nodes = [n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeAttribute"]
    assert attr_nodes[0].attribute_name == "ladar_color"
    assert any(n.bl_idname == "ShaderNodeValToRGB" for n in mat.node_tree.nodes)
    # coloured by intensity (the default): 0 … the 99th percentile of the intensities, clipped
    intensity = _attribute(obj, "intensity")
    assert obj["ladar_color_by"] == "INTENSITY" and obj["ladar_color_min"] == 0.0
    assert obj["ladar_color_max"] == pytest.approx(np.percentile(intensity.astype(np.float64), 99), rel=1e-6)
    np.testing.assert_allclose(_attribute(obj, "ladar_color"),
                               np.clip(intensity / obj["ladar_color_max"], 0, 1), rtol=1e-5)
    # a false-colour PNG beside each EXR, loaded next to the data images
    assert {"range.png", "intensity.png", "energy.png"} <= {p.name for p in run.iterdir()}
    assert bpy.data.images["Ladar_f0001.range.png"].filepath == str(run / "range.png")
    # the images
    img = bpy.data.images["Ladar_f0001.range"]
    assert tuple(img.size) == (16, 16)
    pixels = np.array(img.pixels[:]).reshape(16, 16, -1)[:, :, 0]
    np.testing.assert_allclose(pixels, 100.0, atol=1e-3)
    assert {"Ladar_f0001.intensity", "Ladar_f0001.energy"} <= set(bpy.data.images.keys())
    meta = json.loads((run / "metadata.json").read_text())
    assert meta["blender"]["sensor"] == "Ladar" and meta["blender"]["export"]["triangles"] == 2


def test_rerun_needs_overwrite_and_never_duplicates(lad, scene, tmp_path):
    _plate_scene(scene, tmp_path)
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    meta = tmp_path / "runs" / "Ladar_f0001" / "metadata.json"
    first = meta.read_text()
    with pytest.raises(RuntimeError, match="does not exist yet"):
        bpy.ops.ladar.simulate()
    assert meta.read_text() == first
    # an existing result object of that name blocks too (results would be duplicated)
    with pytest.raises(lad.errors.LadarError, match="already exists"):
        lad.simulate.simulate_scene(scene, out_dir=tmp_path / "elsewhere" / "Ladar_f0001")
    assert not (tmp_path / "elsewhere").exists()
    scene.ladar.if_exists = "REPLACE"
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    assert meta.read_text() != first
    assert [o.name for o in bpy.data.objects if o.name.startswith("Ladar_f0001")] == ["Ladar_f0001"]
    assert sorted(i.name for i in bpy.data.images if i.name.startswith("Ladar_f0001.range")) == \
        ["Ladar_f0001.range", "Ladar_f0001.range.png"]
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["Ladar_f0001"]  # no leftovers
    # keep what exists: the next free name for the folder and the results
    replaced = meta.read_text()
    scene.ladar.if_exists = "NEW"
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    assert meta.read_text() == replaced
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["Ladar_f0001", "Ladar_f0001_2", "Ladar_f0001_3"]
    assert sorted(o.name for o in bpy.data.objects if o.name.startswith("Ladar_f0001")) == \
        ["Ladar_f0001", "Ladar_f0001_2", "Ladar_f0001_3"]
    assert bpy.data.objects["Ladar_f0001_3"][lad.export.RESULT_TAG] == str(tmp_path / "runs" / "Ladar_f0001_3")
    assert scene.ladar.last_run == str(tmp_path / "runs" / "Ladar_f0001_3")


def test_frame_seed_and_config_file(lad, scene, tmp_path, capsys):
    _plate_scene(scene, tmp_path)
    scene.ladar.write_previews = False  # (0.2-0.5 s of CPU a PNG; the operator tests above check the previews)
    plate = bpy.data.objects["Plate"]
    plate.keyframe_insert("location", frame=1)
    plate.location.z = -120.0
    plate.keyframe_insert("location", frame=10)
    config = tmp_path / "small.toml"
    config.write_text("schema_version = 1\n[receiver]\nwidth_px = 8\nheight_px = 4\n")
    run_path, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "f10", frame=10, seed=77,
                                                   config_path=config)
    assert scene.frame_current == 10
    assert run_path == (tmp_path / "f10").resolve()
    assert result.range_image.shape == (4, 8)  # the config file's receiver, fov re-derived from the camera
    np.testing.assert_allclose(result.points["range_m"], 120.0, atol=1e-3)
    assert set(result.points["frame"]) == {10}
    meta = json.loads((run_path / "metadata.json").read_text())
    assert meta["seed"] == 77 and meta["frame"] == 10
    rx = meta["settings"]["receiver"]
    assert rx["fov_x_rad"] == pytest.approx(FOV, rel=1e-6)
    assert rx["fov_y_rad"] == pytest.approx(2 * math.atan(math.tan(FOV / 2) * 4 / 8), rel=1e-6)
    assert set(_attribute(bpy.data.objects["f10"], "frame", np.int32)) == {10}
    out = capsys.readouterr().out
    assert "ladar: exported 2 triangles" in out and "ladar: 100.0%" in out and "ladar: wrote" in out


def test_materials_change_the_intensity(lad, scene, tmp_path):
    """Two halves of a plate, Lambertian 10 % and 50 %, at normal incidence: intensities in ratio 1 : 5."""
    cam = add_camera(scene, width_px=16, height_px=16, fov_rad=FOV)
    cam.ladar.receiver.subsamples = 2
    cam.ladar.laser.beam_profile = "uniform"
    scene.ladar.write_previews = False  # (see test_frame_seed_and_config_file)
    dark, bright = brdf_material("Dark", reflectance=0.1), brdf_material("Bright", reflectance=0.5)
    add_mesh(scene, "Halves", [(-1, -1, 0), (0, -1, 0), (0, 1, 0), (-1, 1, 0), (1, -1, 0), (1, 1, 0)],
             [(0, 1, 2, 3), (1, 4, 5, 2)], location=(0, 0, -100), materials=(dark, bright),
             face_materials=[0, 1])
    _, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "halves")
    energy = result.energy_image
    left, right = energy[:, :8], energy[:, 8:]
    assert right.mean() / left.mean() == pytest.approx(5.0, rel=1e-6)


def test_zero_echoes_import_an_empty_cloud(lad, scene, tmp_path):
    cam = _plate_scene(scene, tmp_path)
    cam.ladar.detection.threshold_fj = 1e15  # nothing reaches 1 J per bin
    _, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "none")
    assert len(result.points["range_m"]) == 0
    assert len(bpy.data.objects["none"].data.vertices) == 0


ERROR_CASES = {
    "no sensor": ("no ladar sensor", lambda scene, cam: bpy.data.objects.remove(cam)),
    "not a camera": ("not a camera", lambda scene, cam: setattr(scene.ladar, "sensor", None) or
                     setattr(scene, "camera", bpy.data.objects["Plate"])),
    "no geometry": ("no geometry", lambda scene, cam: bpy.data.objects.remove(bpy.data.objects["Plate"])),
    "sees nothing": ("sees nothing", lambda scene, cam: setattr(cam, "rotation_euler", (math.pi, 0, 0))),
    "bad setting": ("laser.pulse_energy_j", lambda scene, cam: setattr(cam.ladar.laser, "pulse_energy_uj", 0.0)),
    "memory": ("gate.n_bins", lambda scene, cam: (setattr(cam.ladar.gate, "n_bins", 1_000_000),
                                                  setattr(cam.ladar.receiver, "width_px", 1024),
                                                  setattr(cam.ladar.receiver, "height_px", 1024))),
    "relative path, unsaved file": ("not saved", lambda scene, cam: setattr(scene.ladar, "output_dir",
                                                                            "//ladar_runs")),
}


@pytest.mark.parametrize("case", list(ERROR_CASES))
def test_errors_are_reported_and_write_nothing(lad, scene, tmp_path, case):
    message, breaker = ERROR_CASES[case]
    cam = _plate_scene(scene, tmp_path)
    breaker(scene, cam)
    n_objects, n_images = len(bpy.data.objects), len(bpy.data.images)
    with pytest.raises(RuntimeError, match=message.replace(".", r"\.")):  # bpy.ops turns ERROR reports into this
        bpy.ops.ladar.simulate()
    assert not (tmp_path / "runs").exists()
    assert (len(bpy.data.objects), len(bpy.data.images)) == (n_objects, n_images)
    assert list(tmp_path.iterdir()) == []
