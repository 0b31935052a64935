"""Results in Blender: colour by a chosen attribute (values checked), point size, import of an existing run folder,
the preview render (Cycles CPU) and the waveform view of a flash pixel."""
import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_mesh

FOV = 0.004


def _attribute(obj, name, dtype=np.float32):
    attr = obj.data.attributes[name]
    out = np.empty(len(attr.data), dtype)
    attr.data.foreach_get("value", out)
    return out


def _staircase_run(lad, scene, tmp_path, name="stairs", noisy=False, previews=False):
    """Two steps (left half at 100 m, right half at 103 m): two ranges, two intensities.  ``previews``: the
    scene's "PNG Previews" setting, off where a test uses no preview (three PNGs a run, 0.2-0.5 s of CPU each:
    most of this file's time); :func:`test_import_an_existing_run_folder` imports them."""
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=FOV)
    cam.ladar.receiver.subsamples = 1
    cam.ladar.gate.gate_start_ns = 2e9 * 90 / 299_792_458.0
    cam.ladar.gate.n_bins = 200
    if noisy:
        cam.ladar.detector.mode = "noisy"
    add_mesh(scene, "Near", [(-1, -1, 0), (0, -1, 0), (0, 1, 0), (-1, 1, 0)], [(0, 1, 2, 3)], location=(0, 0, -100))
    add_mesh(scene, "Far", [(0, -1, 0), (1, -1, 0), (1, 1, 0), (0, 1, 0)], [(0, 1, 2, 3)], location=(0, 0, -103))
    scene.ladar.output_dir = str(tmp_path)
    scene.ladar.write_previews = previews
    return lad.simulate.simulate_scene(scene, out_dir=tmp_path / name)


def test_colour_by_each_attribute(lad, scene, tmp_path):
    run, result = _staircase_run(lad, scene, tmp_path)
    obj = bpy.data.objects["stairs"]
    rng = _attribute(obj, "range_m").astype(np.float64)
    assert set(np.round(rng)) == {100.0, 103.0}
    assert lad.colors.available_color_by(obj) == ["INTENSITY", "RANGE", "ECHO", "FRAME"]

    scene.ladar.color_by = "RANGE"  # the property update recolours every result cloud of the scene
    assert obj["ladar_color_by"] == "RANGE" and obj["ladar_color_label"] == "Range (m)"
    assert obj["ladar_color_min"] == pytest.approx(rng.min()) and obj["ladar_color_max"] == pytest.approx(rng.max())
    value = _attribute(obj, "ladar_color")
    np.testing.assert_allclose(value[rng < 101], 0.0, atol=1e-3)   # near step → start of the ramp (slant: < 0.3 mm)
    np.testing.assert_allclose(value[rng > 102], 1.0, atol=1e-3)   # far step → end
    rgb = np.empty(len(value) * 4, np.float32)
    obj.data.color_attributes["ladar_rgb"].data.foreach_get("color", rgb)
    rgb = rgb.reshape(-1, 4)
    np.testing.assert_allclose(rgb[rng > 102][:, :3] - lad.colors.RAMP[-1][1], 0.0, atol=2e-3)
    np.testing.assert_allclose(rgb[rng < 101][:, :3] - lad.colors.RAMP[0][1], 0.0, atol=2e-3)

    scene.ladar.color_by = "ECHO"  # one echo per pixel: every point at the ramp's start (echo 1 of 1 … 2)
    assert obj["ladar_color_min"] == 1.0 and obj["ladar_color_max"] == 2.0
    np.testing.assert_allclose(_attribute(obj, "ladar_color"), 0.0)

    scene.ladar.color_by = "SNR"  # the ideal receiver gives no SNR: the cloud keeps its colouring
    assert obj["ladar_color_by"] == "ECHO"
    with pytest.raises(lad.errors.LadarError, match="no detection snr attribute"):
        lad.colors.apply_color(obj, "SNR")


def test_snr_colouring_with_the_noisy_receiver(lad, scene, tmp_path):
    run, result = _staircase_run(lad, scene, tmp_path, "noisy", noisy=True)
    obj = bpy.data.objects["noisy"]
    assert "SNR" in lad.colors.available_color_by(obj)
    lo, hi = lad.colors.apply_color(obj, "SNR")
    snr = _attribute(obj, "snr").astype(np.float64)
    np.testing.assert_allclose(snr, np.sort(result.points["snr"])[np.argsort(np.argsort(snr))], rtol=1e-6)
    assert lo == 0.0 and hi == pytest.approx(np.percentile(snr, 99), rel=1e-6)
    np.testing.assert_allclose(_attribute(obj, "ladar_color"), np.clip(snr / hi, 0, 1), rtol=1e-5, atol=1e-7)


def test_point_radius_follows_the_scene_setting(lad, scene, tmp_path):
    _staircase_run(lad, scene, tmp_path)
    obj = bpy.data.objects["stairs"]
    mod = obj.modifiers["Ladar Points"]
    ident = lad.colors.socket_identifier(mod.node_group, "Point Radius")
    assert mod[ident] == pytest.approx(0.05)
    scene.ladar.point_radius = 0.2
    assert mod[ident] == pytest.approx(0.2)
    # the evaluated point cloud carries that radius
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    geometry = evaluated.evaluated_geometry()  # Blender ≥ 4.3
    cloud = geometry.pointcloud
    radius = np.empty(len(cloud.points), np.float32)
    cloud.attributes["radius"].data.foreach_get("value", radius)
    assert len(radius) == len(obj.data.vertices) == 64
    np.testing.assert_allclose(radius, 0.2, rtol=1e-6)


def test_import_an_existing_run_folder(lad, scene, tmp_path):
    run, result = _staircase_run(lad, scene, tmp_path, previews=True)
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.ladar.color_by = "RANGE"
    assert bpy.ops.ladar.import_run(directory=str(run)) == {"FINISHED"}
    obj = bpy.data.objects["stairs"]
    np.testing.assert_allclose(np.sort(_attribute(obj, "range_m")), np.sort(result.points["range_m"]), rtol=1e-6)
    assert obj["ladar_color_by"] == "RANGE"
    assert {"stairs.range", "stairs.range.png", "stairs.intensity", "stairs.energy"} <= set(bpy.data.images.keys())
    with pytest.raises(RuntimeError, match="already exists"):  # never duplicated silently
        bpy.ops.ladar.import_run(directory=str(run))
    assert [o.name for o in bpy.data.objects if o.name.startswith("stairs")] == ["stairs"]
    scene.ladar.if_exists = "REPLACE"
    assert bpy.ops.ladar.import_run(directory=str(run)) == {"FINISHED"}
    assert [o.name for o in bpy.data.objects if o.name.startswith("stairs")] == ["stairs"]


def test_waveform_view_of_a_flash_pixel(lad, scene, tmp_path):
    run, result = _staircase_run(lad, scene, tmp_path)
    path, what = lad.waveform_view.waveform_plot(run, pixel_x=6, pixel_y=3)
    assert path == run / "previews" / "waveform_x0006_y0003.png"
    assert what["echo_ranges_m"] == pytest.approx([float(result.range_image[3, 6])], rel=1e-6)  # image: float32
    assert what["echo_ranges_m"][0] == pytest.approx(103.0, abs=0.01)  # right half: the far step
    assert what["energy_j"] == pytest.approx(float(result.waveforms[3, 6].sum()), rel=1e-6)
    stamp = path.stat().st_mtime_ns
    assert lad.waveform_view.waveform_plot(run, pixel_x=6, pixel_y=3)[0].stat().st_mtime_ns == stamp  # not rewritten
    with pytest.raises(lad.config.ConfigError, match="pixel_y"):
        lad.waveform_view.waveform_plot(run, pixel_x=0, pixel_y=8)


def _capture_raw_renders(lad, monkeypatch, tmp_path):
    """Keep a copy of each raw Cycles render (before the legend is laid around it)."""
    import shutil
    render = lad.package.ladar_addon.render
    original = render.compose
    raws = []

    def keep(raw, out, **kw):
        raws.append(shutil.copy(raw, tmp_path / f"raw_{len(raws)}.png"))
        return original(raw, out, **kw)
    monkeypatch.setattr(render, "compose", keep)
    return raws


def _raw_pixels(path):
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = img.size
        return np.array(img.pixels[:]).reshape(h, w, 4)
    finally:
        bpy.data.images.remove(img)


def test_preview_render_from_the_sensor_with_a_legend(lad, scene, tmp_path, monkeypatch):
    """Issue 14: a flash run is rendered from the sensor's own pose and field of view with points as large as
    their pixels, so the plates fill the picture (before: a framing camera, the points on 0.15 % of a flash
    demo render); the PNG carries a title, angle axes and the colour-ramp legend with its unit, on a dark
    background whatever Blender's default world (5.0: grey)."""
    raws = _capture_raw_renders(lad, monkeypatch, tmp_path)
    _staircase_run(lad, scene, tmp_path)
    scene.ladar.point_radius = 0.02
    objects_before = set(bpy.data.objects.keys())
    scenes_before = set(bpy.data.scenes.keys())
    assert bpy.ops.ladar.render_preview(resolution_x=96, resolution_y=72, samples=4) == {"FINISHED"}
    out = tmp_path / "stairs" / "previews" / "render.png"
    img = bpy.data.images["stairs.render"]
    assert img.filepath == str(out) and img.size[0] == 740  # the composed figure (7.4 in at 100 dpi)
    raw = _raw_pixels(raws[0])
    assert raw.shape[:2] == (96, 96)  # the receiver's square field of view sets the aspect
    assert (raw[:, :, 3] > 0.5).mean() > 0.95  # the two plates fill the sensor's view
    from PIL import Image
    with Image.open(out) as im:
        text = dict(im.text)
        corner = np.array(im.convert("RGB"))[2, 2]
    assert text["Title"] == "stairs (sensor view): 64 points, coloured by Intensity (J per bin)"
    assert text["Description"] == ("x: horizontal angle (mrad); y: vertical angle (mrad); "
                                   "y: Intensity (J per bin)")
    np.testing.assert_array_equal(corner, [16, 16, 20])  # the dark background
    assert bpy.data.objects["stairs"].modifiers["Ladar Points"] is not None
    assert lad.colors.point_radius(bpy.data.objects["stairs"]) == pytest.approx(0.02)  # restored
    assert set(bpy.data.objects.keys()) == objects_before and set(bpy.data.scenes.keys()) == scenes_before
    assert bpy.ops.ladar.render_preview(resolution_x=32, resolution_y=24, samples=1) == {"FINISHED"}
    assert (tmp_path / "stairs" / "previews" / "render_2.png").is_file()  # the first render is kept


def test_preview_render_frames_clouds_of_several_runs(lad, scene, tmp_path, monkeypatch):
    raws = _capture_raw_renders(lad, monkeypatch, tmp_path)
    _staircase_run(lad, scene, tmp_path)
    lad.simulate.simulate_scene(scene, out_dir=tmp_path / "again")
    for name in ("stairs", "again"):
        bpy.data.objects[name].select_set(True)
    with bpy.context.temp_override(selected_objects=[bpy.data.objects["stairs"], bpy.data.objects["again"]]):
        assert bpy.ops.ladar.render_preview(resolution_x=96, resolution_y=72, samples=2) == {"FINISHED"}
    raw = _raw_pixels(raws[0])
    assert raw.shape[:2] == (72, 96)
    covered = (raw[:, :, 3] > 0.5).mean()
    assert 0.002 < covered < 0.9 and raw[0, 0, 3] == 0.0  # 64 spots of ~2.4 px, twice; transparent film around
    cam = np.asarray(lad.package.ladar_addon.render.framing_camera(np.array([[0, 0, 0], [2, 0, 0]]), 4 / 3)[0])
    assert np.linalg.norm(cam[:3, 3] - [1, 0, 0]) == pytest.approx(1.1 * 1.0 / np.sin(np.radians(20)), rel=1e-6)


def test_intensity_legend_carries_the_runs_unit(lad, scene, tmp_path):
    """Issue 14: the noisy receiver's intensity is in A/D counts, the ideal one's in J per bin; the legend says
    which (from the run's metadata.json units)."""
    _staircase_run(lad, scene, tmp_path, "noisy_units", noisy=True)
    obj = bpy.data.objects["noisy_units"]
    lad.colors.apply_color(obj, "INTENSITY")
    assert obj["ladar_color_label"] == "Intensity (counts)"
    bpy.ops.wm.read_homefile(use_empty=True)
    _staircase_run(lad, bpy.context.scene, tmp_path, "ideal_units")
    obj = bpy.data.objects["ideal_units"]
    assert obj["ladar_color_by"] == "INTENSITY" and obj["ladar_color_label"] == "Intensity (J per bin)"
