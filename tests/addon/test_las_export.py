"""bpy.ops.ladar.export_las: a simulated run's point cloud as LAS 1.4, read back with laspy."""
import bpy
import laspy
import numpy as np
import pytest

from blender_scenes import add_camera, add_plate


def test_export_las_operator(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 2
    add_plate(scene, size=2.0, location=(0, 0, -100.0))
    run, result = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "run", import_results=False)
    out = tmp_path / "cloud.las"
    assert bpy.ops.ladar.export_las(filepath=str(out), run_dir=str(run)) == {"FINISHED"}
    f = laspy.read(str(out))
    pts = result.points
    assert f.header.point_count == len(pts["range_m"]) == 64
    np.testing.assert_allclose(np.asarray(f.z), pts["position_world"][:, 2], atol=0.5e-4 * (1 + 1e-9), rtol=0)
    np.testing.assert_allclose(np.asarray(f.range_m), pts["range_m"], rtol=0, atol=0)
    np.testing.assert_array_equal(np.asarray(f.return_number), pts["echo_index"])
    # Never overwritten silently; the active result object names its run.
    with pytest.raises(RuntimeError, match="does not exist yet"):
        bpy.ops.ladar.export_las(filepath=str(out), run_dir=str(run))
    holder = bpy.data.objects.new("Result", None)
    scene.collection.objects.link(holder)
    holder[lad.export.RESULT_TAG] = str(run)
    with bpy.context.temp_override(active_object=holder):
        assert bpy.ops.ladar.export_las(filepath=str(out), overwrite=True, coordinates="sensor") == {"FINISHED"}
    np.testing.assert_allclose(np.asarray(laspy.read(str(out)).z), pts["position_sensor"][:, 2], atol=1e-4)
    with pytest.raises(RuntimeError, match="No run to export"):
        bpy.ops.ladar.export_las(filepath=str(tmp_path / "none.las"))


def test_export_las_is_in_the_file_export_menu(lad):
    draw_funcs = getattr(bpy.types.TOPBAR_MT_file_export, "_dyn_ui_initialize", lambda: [])()
    names = [getattr(f, "__name__", "") for f in draw_funcs]
    assert "menu_export" in names
