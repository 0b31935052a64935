"""Scene export: world-space triangles after modifiers, instances flattened, a material per triangle."""
import math

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_cube, add_mesh, brdf_material


def _export(lad, scene, **kwargs):
    depsgraph = bpy.context.evaluated_depsgraph_get()
    stats = {}
    geometry = lad.export.scene_geometry_from_depsgraph(depsgraph, stats=stats, **kwargs)
    geometry.check()
    return geometry, stats


def _material_counts(geometry):
    names = np.array(geometry.material_names)
    values, counts = np.unique(names[geometry.material_ids], return_counts=True)
    return dict(zip(values.tolist(), counts.tolist()))


@pytest.fixture
def modifier_and_instances(lad, scene):
    """A cube with an Array modifier (3 copies), rotated 90° about Z at x = 10 m, with two materials on
    faces 0–1 (Blue) and 2–5 (Red); plus two collection instances (scale 2) of a red cube at y = ±50 m."""
    red = brdf_material("Red", reflectance=0.5)
    blue = bpy.data.materials.new("Blue")  # no ladar BRDF: the default
    cube = add_cube(scene, "Arrayed", location=(10, 0, 0), rotation=(0, 0, math.pi / 2), materials=(red, blue),
                    face_materials=[1, 1, 0, 0, 0, 0])
    array = cube.modifiers.new("Array", "ARRAY")
    array.count = 3
    array.use_relative_offset = True
    array.relative_offset_displace = (1.0, 0.0, 0.0)
    proto = bpy.data.collections.new("Proto")  # not linked to the scene: only its instances are visible
    add_cube(scene, "ProtoCube", collection=proto, materials=(red,))
    for y in (50.0, -50.0):
        inst = bpy.data.objects.new(f"Instance{y:+.0f}", None)
        inst.instance_type = "COLLECTION"
        inst.instance_collection = proto
        inst.location = (0.0, y, 0.0)
        inst.scale = (2.0, 2.0, 2.0)
        scene.collection.objects.link(inst)
    add_camera(scene)  # cameras are not geometry
    return scene


def test_modifier_instances_bbox_and_materials(lad, modifier_and_instances):
    geometry, stats = _export(lad, modifier_and_instances)
    assert geometry.n_triangles == 3 * 12 + 2 * 12
    assert stats["objects"] == 1 and stats["instances"] == 2 and stats["unique_meshes"] == 2
    v = geometry.vertices_m
    np.testing.assert_allclose(v.min(axis=0), [-2.0, -52.0, -2.0], atol=1e-6)
    np.testing.assert_allclose(v.max(axis=0), [11.0, 52.0, 2.0], atol=1e-6)
    # the arrayed cube alone: x ∈ [9, 11] (its local y), y ∈ [-1, 5] (its local x after 3 copies)
    arrayed = v[np.unique(geometry.triangles[:36])]
    np.testing.assert_allclose(arrayed.min(axis=0), [9.0, -1.0, -1.0], atol=1e-6)
    np.testing.assert_allclose(arrayed.max(axis=0), [11.0, 5.0, 1.0], atol=1e-6)
    # per-triangle materials: Blue on 2 faces × 2 triangles × 3 copies, Red elsewhere (arrayed and instances)
    assert _material_counts(geometry) == {"Blue": 12, "Red": 24 + 24}
    brdfs = dict(zip(geometry.material_names, geometry.materials))
    assert brdfs["Red"].reflectance == pytest.approx(0.5)
    assert brdfs["Blue"] == lad.config.DEFAULT_BRDF
    # the instance triangles are where the instances are: 4 m cubes at y = ±50
    inst_tris = geometry.triangles[36:]
    centroids = v[inst_tris].mean(axis=1)
    assert set(np.round(np.sign(centroids[:, 1]) * 50).astype(int)) == {50, -50}
    assert np.all(np.abs(np.abs(centroids[:, 1]) - 50) <= 2.0 + 1e-9)


def test_triangulation_fast_paths_and_ngon_fallback(lad, scene):
    # a triangle, a quad and (in a second mesh) a pentagon, all planar in z = 0
    mixed = add_mesh(scene, "Mixed", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0)],
                     [(0, 1, 2, 3), (1, 4, 2)])
    pent = [(math.cos(a), math.sin(a), 0.0) for a in np.linspace(0, 2 * math.pi, 6)[:-1]]
    ngon = add_mesh(scene, "Ngon", pent, [(0, 1, 2, 3, 4)], location=(0, 0, 5))
    grid_verts = [(x, y, 0) for y in range(11) for x in range(11)]
    grid_faces = [(y * 11 + x, y * 11 + x + 1, (y + 1) * 11 + x + 1, (y + 1) * 11 + x)
                  for y in range(10) for x in range(10)]
    add_mesh(scene, "Grid", grid_verts, grid_faces, location=(0, 0, 10))
    for obj, n_tri in ((mixed, 3), (ngon, 3)):
        verts, tris, mats = lad.export.mesh_arrays(obj.data)
        assert len(tris) == n_tri and len(mats) == n_tri
        area = 0.5 * np.linalg.norm(np.cross(verts[tris[:, 1]] - verts[tris[:, 0]],
                                             verts[tris[:, 2]] - verts[tris[:, 0]]), axis=1).sum()
        assert area == pytest.approx(sum(p.area for p in obj.data.polygons), rel=1e-6)
    geometry, _ = _export(lad, scene)
    assert geometry.n_triangles == 3 + 3 + 200


def test_what_is_left_out(lad, scene):
    add_cube(scene, "Visible")
    add_cube(scene, "NoRender", location=(5, 0, 0)).hide_render = True
    add_cube(scene, "EyeHidden", location=(10, 0, 0)).hide_set(True)
    add_cube(scene, "ViewportDisabled", location=(15, 0, 0)).hide_viewport = True
    add_cube(scene, "Excluded", location=(20, 0, 0))
    result = add_mesh(scene, "OldRun", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
    result[lad.export.RESULT_TAG] = "/runs/old"
    geometry, stats = _export(lad, scene, exclude={"Excluded"})
    assert geometry.n_triangles == 12 and stats["objects"] == 1
    np.testing.assert_allclose(geometry.vertices_m.max(axis=0), [1, 1, 1])


def _evaluated_triangles(obj):
    ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = ev.to_mesh()
    n = len(mesh.loop_triangles)
    ev.to_mesh_clear()
    return n


def test_curves_text_and_metaballs_once_each(lad, scene):
    """Curve-like objects export their evaluated mesh exactly once, also when instanced."""
    red = brdf_material("Red", reflectance=0.5)
    font = bpy.data.curves.new("Label", "FONT")
    font.body = "L"
    font.materials.append(red)
    text = bpy.data.objects.new("Label", font)
    scene.collection.objects.link(text)
    path = bpy.data.curves.new("Path", "CURVE")
    path.dimensions, path.bevel_depth = "3D", 0.1
    spline = path.splines.new("POLY")
    spline.points.add(1)
    spline.points[1].co = (5, 0, 0, 1)
    tube = bpy.data.objects.new("Path", path)
    tube.location = (0, 5, 0)
    scene.collection.objects.link(tube)
    ball = bpy.data.objects.new("Ball", bpy.data.metaballs.new("Ball"))
    ball.data.elements.new()
    ball.location = (0, -5, 0)
    scene.collection.objects.link(ball)
    n_text, n_tube, n_ball = (_evaluated_triangles(o) for o in (text, tube, ball))
    assert n_text >= 2 and n_tube >= 8 and n_ball >= 100
    geometry, stats = _export(lad, scene)
    assert geometry.n_triangles == n_text + n_tube + n_ball
    assert stats["objects"] == 3 and stats["instances"] == 0
    assert _material_counts(geometry)["Red"] == n_text
    # the text in a collection instanced twice: twice its triangles, not more
    proto = bpy.data.collections.new("Words")
    scene.collection.objects.unlink(text)
    proto.objects.link(text)
    for x in (10.0, 20.0):
        holder = bpy.data.objects.new(f"Words{x:.0f}", None)
        holder.instance_type, holder.instance_collection = "COLLECTION", proto
        holder.location = (x, 0, 0)
        scene.collection.objects.link(holder)
    geometry, stats = _export(lad, scene)
    assert geometry.n_triangles == 2 * n_text + n_tube + n_ball
    assert stats["instances"] == 2


def test_unit_scale(lad, scene):
    add_cube(scene, "Cube", location=(4, 0, 0))
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 0.5  # 1 Blender unit = 0.5 m
    geometry, stats = _export(lad, scene)
    assert stats["unit_scale_m"] == 0.5
    np.testing.assert_allclose(geometry.vertices_m.max(axis=0), [2.5, 0.5, 0.5])


def test_empty_scene_gives_no_triangles(lad, scene):
    add_camera(scene)
    geometry = lad.export.scene_geometry_from_depsgraph(bpy.context.evaluated_depsgraph_get())
    assert geometry.n_triangles == 0
