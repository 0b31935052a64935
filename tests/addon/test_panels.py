"""Panels: registered in the right Properties tabs, poll on the right data, and every drawn property exists.

Headless Blender draws no UI, so each panel's ``draw`` runs against a recording layout that checks each
``layout.prop(data, name)`` against the data's RNA and each ``layout.operator(idname)`` against the registry.
"""
import types

import bpy
import pytest

from blender_scenes import add_camera, brdf_material


class RecordingLayout:
    def __init__(self, log):
        self.__dict__["log"] = log

    def __setattr__(self, key, value):  # use_property_split, active, scale_y, ...
        self.__dict__[key] = value

    def _child(self, *args, **kwargs):
        return RecordingLayout(self.log)

    row = column = box = split = _child

    def label(self, text="", **kwargs):
        self.log.append(("label", text))

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.log.append(("prop", name))

    def menu(self, menu, **kwargs):
        assert hasattr(bpy.types, menu), menu
        self.log.append(("menu", menu))

    def operator(self, idname, **kwargs):
        module, name = idname.split(".")
        assert hasattr(bpy.types, f"{module.upper()}_OT_{name}"), idname
        self.log.append(("operator", idname))
        return types.SimpleNamespace()


def _draw(cls, context, method="draw"):
    """Run a panel method on a stand-in instance (Panel subclasses cannot be instantiated outside Blender)."""
    log = []
    fake = types.SimpleNamespace(layout=RecordingLayout(log))
    for klass in reversed(cls.__mro__):
        for key, value in vars(klass).items():
            if key.startswith("__"):
                continue
            setattr(fake, key, types.MethodType(value, fake) if isinstance(value, types.FunctionType) else value)
    getattr(fake, method)(context)
    return log


def test_panels_draw_every_setting(lad, scene):
    panels = lad.package.panels
    cam = add_camera(scene)
    mat = brdf_material("Paint", model="steinvall")
    ctx = types.SimpleNamespace(object=cam, camera=cam.data, scene=scene, material=mat)
    props = lad.properties

    log = _draw(panels.LADAR_PT_sensor, ctx)
    assert ("operator", "ladar.simulate") in log and ("prop", "system_type") in log
    assert any(kind == "label" and "Field of view" in text for kind, text in log)
    group_panels = {cls.group: cls for cls in panels.CLASSES if getattr(cls, "group", "")}
    assert set(group_panels) == set(props.SENSOR_FIELDS)  # a sub-panel for every sensor settings group
    for group, cls in group_panels.items():
        assert cls.bl_parent_id == "LADAR_PT_sensor" and cls.bl_context == "data"
        drawn = {name for kind, name in _draw(cls, ctx) if kind == "prop"}
        assert {f.attr for f in props.SENSOR_FIELDS[group]} <= drawn, group
    assert "seed" in {name for kind, name in _draw(panels.LADAR_PT_sensor_run, ctx) if kind == "prop"}

    drawn = {name for kind, name in _draw(panels.LADAR_PT_atmosphere, ctx) if kind == "prop"}
    assert drawn == {f.attr for f in props.ATMOSPHERE_FIELDS} | {"reference_range_m"}
    drawn = {name for kind, name in _draw(panels.LADAR_PT_scene, ctx) if kind == "prop"}
    assert {"sensor", "output_dir", "seed", "if_exists"} <= drawn
    _draw(panels.LADAR_PT_view3d, ctx)

    drawn = {name for kind, name in _draw(panels.LADAR_PT_brdf, ctx) if kind == "prop"}
    assert drawn == {"model", "specular_a", "slope_s", "diffuse_b", "diffuse_m"}
    mat.ladar_brdf.model = "lambertian"
    assert {name for kind, name in _draw(panels.LADAR_PT_brdf, ctx) if kind == "prop"} == {"model", "reflectance"}
    assert _draw(panels.LADAR_PT_brdf, ctx, "draw_header") == [("prop", "enabled")]


def test_panel_polls(lad, scene):
    panels = lad.package.panels
    cam = add_camera(scene)
    plate = bpy.data.objects.new("Empty", None)
    assert panels.LADAR_PT_sensor.poll(types.SimpleNamespace(object=cam, camera=cam.data))
    assert not panels.LADAR_PT_sensor.poll(types.SimpleNamespace(object=plate, camera=None))
    assert panels.LADAR_PT_brdf.poll(types.SimpleNamespace(material=bpy.data.materials.new("m")))
    assert not panels.LADAR_PT_brdf.poll(types.SimpleNamespace(material=None))
    assert {(c.bl_space_type, c.bl_context) for c in (panels.LADAR_PT_sensor, panels.LADAR_PT_scene,
                                                       panels.LADAR_PT_atmosphere, panels.LADAR_PT_brdf)} == \
        {("PROPERTIES", "data"), ("PROPERTIES", "scene"), ("PROPERTIES", "material")}


def test_config_operators(lad, scene, tmp_path):
    cam = add_camera(scene)
    cam.ladar.laser.pulse_energy_j = 0.006
    path = tmp_path / "sensor.toml"
    assert bpy.ops.ladar.export_config(filepath=str(path)) == {"FINISHED"}
    text = path.read_text()
    assert "pulse_energy_j = 0.006" in text
    path.write_text(text.replace("pulse_energy_j = 0.006", "pulse_energy_j = 0.002"))
    assert bpy.ops.ladar.load_config(filepath=str(path)) == {"FINISHED"}
    assert cam.ladar.laser.pulse_energy_j == pytest.approx(0.002)
    path.write_text("[laser]\npulse_energy_j = -5.0\n")
    with pytest.raises(RuntimeError, match="laser.pulse_energy_j"):
        bpy.ops.ladar.load_config(filepath=str(path))
    assert cam.ladar.laser.pulse_energy_j == pytest.approx(0.002)  # unchanged
