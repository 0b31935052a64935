"""Material BRDF in Blender: measured tables (import, validation, .blend round trip, config), the Principled BSDF
starting values, the plot image and the material panel."""
import importlib
import math
import types

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera, add_plate, brdf_material
from test_panels import RecordingLayout, _draw

CSV = """# Measured monostatic BRDF of a green paint (test data)
# wavelength = 1550 nm
angle_deg,brdf_per_sr
0,0.80
10,0.30
20,0.125
45,0.05
80,0.01
"""
ANGLES = [0.0, 10.0, 20.0, 45.0, 80.0]
VALUES = [0.80, 0.30, 0.125, 0.05, 0.01]


class PlotLayout(RecordingLayout):
    def template_icon(self, icon_value=0, scale=1.0):
        self.log.append(("icon", icon_value))


def _materials(lad):
    """The installed add-on's ladar_addon.materials module."""
    return importlib.import_module(f"{lad.package.__name__}.ladar_addon.materials")


def _op(name, material, **kwargs):
    with bpy.context.temp_override(material=material):
        return getattr(bpy.ops.ladar, name)(**kwargs)


def _table_material(tmp_path, name="Paint"):
    path = tmp_path / "paint.csv"
    path.write_text(CSV)
    mat = bpy.data.materials.new(name)
    assert _op("brdf_table_import", mat, filepath=str(path)) == {"FINISHED"}
    return mat


def test_import_table_stores_rows_and_enables(lad, scene, tmp_path):
    mat = _table_material(tmp_path)
    props = mat.ladar_brdf
    assert props.enabled and props.model == "table" and props.table_source == "paint.csv"
    assert [r.angle_deg for r in props.table] == pytest.approx(ANGLES)
    brdf = lad.blend_config.brdf_from_material(mat)
    # float32 storage, read back as the shortest decimal: exactly the file's numbers.
    assert brdf.table_angle_deg == ANGLES and brdf.table_brdf_per_sr == VALUES
    assert brdf.table_wavelength_m == pytest.approx(1.55e-6, rel=1e-9)
    lad.config.validate(brdf)
    # The file states no wavelength: the operator's value (nm) is used.
    path = tmp_path / "plain.txt"
    path.write_text("0 0.2\n90 0.1\n")
    assert _op("brdf_table_import", mat, filepath=str(path), wavelength=905.0) == {"FINISHED"}
    brdf = lad.blend_config.brdf_from_material(mat)
    assert brdf.table_wavelength_m == pytest.approx(9.05e-7, rel=1e-6) and brdf.table_angle_deg == [0.0, 90.0]


@pytest.mark.parametrize("text, message", [
    ("0 1\n20 0.5\n10 0.2\n", "table_angle_deg[2] (line 3)"),
    ("0 1\n10 -0.2\n", "table_brdf_per_sr[1] (line 2)"),
    ("0 1\n95 0.2\n", "[0, 90] degrees"),
    ("0 1\n", "at least 2 rows"),
    ("0 1\n5 abc\n", "bad.csv line 2"),
    ("0 1\n10.0000001 0.5\n10.0000002 0.4\n", "strictly increasing"),  # equal after float32 storage
])
def test_bad_table_is_rejected_and_changes_nothing(lad, scene, tmp_path, text, message):
    mat = _table_material(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    with pytest.raises(RuntimeError, match=message.replace("[", r"\[").replace("]", r"\]")
                       .replace("(", r"\(").replace(")", r"\)")):
        _op("brdf_table_import", mat, filepath=str(bad))
    brdf = lad.blend_config.brdf_from_material(mat)
    assert brdf.table_angle_deg == ANGLES and mat.ladar_brdf.table_source == "paint.csv"


def test_table_round_trip_through_the_blend_file(lad, scene, tmp_path):
    mat = _table_material(tmp_path)
    add_plate(scene, materials=[mat])  # a used material (orphan data is not saved)
    assert _op("brdf_plot", mat) == {"FINISHED"}
    before = lad.blend_config.brdf_from_material(mat)
    blend = tmp_path / "table.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    (tmp_path / "paint.csv").unlink()  # the .blend must not need the source file
    bpy.ops.wm.read_homefile(use_empty=True)
    assert "Paint" not in bpy.data.materials
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    mat = bpy.data.materials["Paint"]
    after = lad.blend_config.brdf_from_material(mat)
    assert after == before
    assert after.table_angle_deg == ANGLES and after.table_brdf_per_sr == VALUES
    image = mat.ladar_brdf.plot
    assert image is not None and image.packed_file is not None and tuple(image.size) == (500, 340)


def test_table_through_config_apply_and_read(lad, scene, tmp_path):
    cam = add_camera(scene)
    mat = bpy.data.materials.new("Board")
    cfg = lad.blend_config.config_from_blender(scene, cam)
    cfg.materials = {"Board": lad.config.BRDFSettings(model="table", table_wavelength_m=1.064e-6,
                                                      table_angle_deg=[0.0, 30.0, 90.0],
                                                      table_brdf_per_sr=[0.5, 0.25, 0.0])}
    lad.blend_config.apply_config_to_blender(cfg, scene, cam)
    assert mat.ladar_brdf.enabled and len(mat.ladar_brdf.table) == 3
    back = lad.blend_config.config_from_blender(scene, cam)
    assert back.materials == cfg.materials
    # TOML config file → Blender → TOML: the table survives.
    text = lad.config.dump_config_toml(back)
    assert "table_brdf_per_sr = [0.5, 0.25, 0.0]" in text
    cfg.materials["Board"] = lad.config.BRDFSettings(model="table", table_angle_deg=[0.0, 10.0],
                                                     table_brdf_per_sr=[0.5, -1.0])
    with pytest.raises(lad.config.ConfigError, match=r"materials.Board.table_brdf_per_sr\[1\]"):
        lad.blend_config.apply_config_to_blender(cfg, scene, cam)
    assert lad.blend_config.brdf_from_material(mat).table_brdf_per_sr == [0.5, 0.25, 0.0]  # unchanged


def test_table_material_simulates_like_its_lambertian_equal(lad, scene, tmp_path):
    """A table constant at ρ/π returns the energy of a Lambertian ρ pixel by pixel (eq. 3-1 is linear in f_r)."""
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 2
    mat = brdf_material("Board", model="lambertian", reflectance=0.4)
    add_plate(scene, size=2.0, location=(0, 0, -100.0), rotation=(0.3, 0.0, 0.0), materials=[mat])
    _, lam = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "lam", import_results=False)
    rho_over_pi = float(np.float32(0.4 / math.pi))
    _materials(lad).write_table(mat.ladar_brdf, [0.0, 90.0], [rho_over_pi, rho_over_pi])
    mat.ladar_brdf.model = "table"
    _, tab = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "tab", import_results=False)
    assert lam.energy_image.sum() > 0
    np.testing.assert_allclose(tab.energy_image, lam.energy_image, rtol=1e-6)


def test_principled_starting_values(lad, scene):
    """Base colour 0.8 grey, roughness 0.5, IOR 1.5 (core worked values): A = 0.050930, s = 0.25,
    B = 0.244462, m = 0; labelled as starting values."""
    mat = bpy.data.materials.new("Grey")
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    node = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    node.inputs["Base Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    node.inputs["Roughness"].default_value = 0.5
    node.inputs["Metallic"].default_value = 0.0
    node.inputs["IOR"].default_value = 1.5
    if "Specular IOR Level" in node.inputs:
        node.inputs["Specular IOR Level"].default_value = 0.5
    assert _op("brdf_from_principled", mat) == {"FINISHED"}
    brdf = lad.blend_config.brdf_from_material(mat)
    assert brdf.model == "steinvall" and brdf.diffuse_m == 0.0
    assert brdf.specular_a == pytest.approx(0.050930, rel=1e-4)
    assert brdf.slope_s == pytest.approx(0.25, rel=1e-6)
    assert brdf.diffuse_b == pytest.approx(0.244462, rel=1e-5)
    assert "starting values" in mat.ladar_brdf.origin and "not a measurement" in mat.ladar_brdf.origin
    # A texture on the base colour: its unlinked value is used, and the inputs say so.
    tex = mat.node_tree.nodes.new("ShaderNodeTexNoise")
    mat.node_tree.links.new(tex.outputs["Color"], node.inputs["Base Color"])
    brdf2, inputs = _materials(lad).initialise_from_principled(mat)
    assert inputs["linked"] == ["Base Color"] and brdf2 == brdf
    # No Principled BSDF node: the viewport display colour, roughness and metallic.
    plain = bpy.data.materials.new("Plain")
    if plain.node_tree is not None:
        for n in [n for n in plain.node_tree.nodes if n.type == "BSDF_PRINCIPLED"]:
            plain.node_tree.nodes.remove(n)
    plain.diffuse_color = (0.0, 1.0, 0.0, 1.0)
    plain.roughness = 1.0
    plain.metallic = 0.0
    brdf3, inputs = _materials(lad).initialise_from_principled(plain)
    assert inputs["source"].startswith("viewport display")
    assert brdf3.diffuse_b == pytest.approx(0.96 * 0.7152 / math.pi, rel=1e-5)  # Y of pure green = 0.7152
    assert brdf3.specular_a == pytest.approx(0.04 / (4 * math.pi), rel=1e-5)


def test_plot_image_replaced_not_duplicated(lad, scene, tmp_path):
    mat = brdf_material("Paint", model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08)
    assert _op("brdf_plot", mat) == {"FINISHED"}
    first = mat.ladar_brdf.plot
    assert first.name == "Ladar BRDF Paint" and first.packed_file is not None
    assert tuple(first.size) == (500, 340)
    pixels = np.empty(500 * 340 * 4, np.float32)
    first.pixels.foreach_get(pixels)
    assert pixels.min() < 0.5 < pixels.max()  # a drawn plot, not a blank image
    assert _op("brdf_plot", mat) == {"FINISHED"}
    assert [im.name for im in bpy.data.images] == ["Ladar BRDF Paint"]
    # An invalid table: error, the previous plot stays.
    mat.ladar_brdf.model = "table"
    with pytest.raises(RuntimeError, match="at least 2 rows"):
        _op("brdf_plot", mat)
    assert mat.ladar_brdf.plot.name == "Ladar BRDF Paint"


def _draw_material(panels, ctx):
    log = []
    fake = types.SimpleNamespace(layout=PlotLayout(log))
    for klass in reversed(panels.LADAR_PT_brdf.__mro__):
        for key, value in vars(klass).items():
            if not key.startswith("__"):
                setattr(fake, key, types.MethodType(value, fake) if isinstance(value, types.FunctionType)
                        else value)
    fake.draw(ctx)
    return log


def test_material_panel_table_and_tools(lad, scene, tmp_path):
    panels = lad.package.panels
    cam = add_camera(scene)
    cam.ladar.laser.wavelength_m = 1064.0  # nm (stored unit)
    mat = _table_material(tmp_path)
    ctx = types.SimpleNamespace(object=cam, scene=scene, material=mat)
    log = _draw_material(panels, ctx)
    props = {name for kind, name in log if kind == "prop"}
    labels = [text for kind, text in log if kind == "label"]
    assert props == {"model", "table_wavelength_m"}
    assert labels[0].startswith("5 rows at 1550 nm, from paint.csv")
    assert any(t.startswith("θ = 45°") and "0.05 1/sr" in t for t in labels)
    assert any("Measured at 1550 nm, the laser is at 1064 nm" in t for t in labels)
    assert any(t.startswith("Lambertian equivalent π·f_r: 2.51 at 0°") for t in labels)  # π·0.8
    ops = {name for kind, name in log if kind == "operator"}
    assert ops == {"ladar.brdf_table_import", "ladar.brdf_from_principled", "ladar.brdf_plot"}
    assert ("menu", "LADAR_MT_material_presets") in _draw(panels.LADAR_PT_brdf, ctx, "draw_header_preset")
    _op("brdf_plot", mat)
    labels = [text for kind, text in _draw_material(panels, ctx) if kind == "label"]
    assert any("Plot: image 'Ladar BRDF Paint'" in t for t in labels)
    # Long tables are elided; a broken table says why.
    _materials(lad).write_table(mat.ladar_brdf, list(range(0, 90, 3)), [1.0] * 30)
    labels = [text for kind, text in _draw_material(panels, ctx) if kind == "label"]
    assert any("… 20 more rows …" in t for t in labels)
    _materials(lad).write_table(mat.ladar_brdf, [0.0, 0.0], [1.0, 1.0])
    labels = [text for kind, text in _draw_material(panels, ctx) if kind == "label"]
    assert any(t.startswith("Invalid table:") and "strictly increasing" in t for t in labels)
    assert not any(t.startswith("Lambertian equivalent") for t in labels)
