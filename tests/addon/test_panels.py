"""Panels: registered in the right Properties tabs, poll on the right data, every drawn property exists, and the
system type chooses what shows; the status bar and panels show a running simulation.

Headless Blender draws no UI, so each panel's ``draw`` runs against a recording layout that checks each
``layout.prop(data, name)`` against the data's RNA and each ``layout.operator(idname)`` (and the properties set
on it) against the registry.
"""
import importlib
import types

import bpy
import pytest

from blender_scenes import add_camera, brdf_material


class RecordingLayout:
    """A stand-in for ``UILayout`` that records what a panel draws and checks it against the registered RNA."""

    def __init__(self, log):
        self.__dict__["log"] = log

    def __setattr__(self, key, value):  # use_property_split, active, scale_y, ...
        self.__dict__[key] = value

    def _child(self, *args, **kwargs):
        return RecordingLayout(self.log)

    row = column = box = split = _child

    def label(self, text="", **kwargs):
        self.log.append(("label", text))

    def separator(self, **kwargs):
        self.log.append(("separator", ""))

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.log.append(("prop", name))

    def menu(self, menu, **kwargs):
        assert hasattr(bpy.types, menu), menu
        self.log.append(("menu", menu))

    def operator(self, idname, **kwargs):
        module, name = idname.split(".")
        cls = getattr(bpy.types, f"{module.upper()}_OT_{name}", None)
        assert cls is not None, idname
        self.log.append(("operator", idname))
        props = {p.identifier for p in getattr(getattr(bpy.ops, module), name).get_rna_type().properties}
        return _OperatorProps(props)

    def progress(self, factor=0.0, type="BAR", text=""):
        assert 0.0 <= factor <= 1.0 and type in ("BAR", "RING")
        self.log.append(("progress", text))

    def template_color_ramp(self, data, name, **kwargs):
        assert data.bl_rna.properties[name].type == "POINTER", name
        self.log.append(("color_ramp", data.name))


class _OperatorProps:
    """Operator properties returned by ``layout.operator``: only registered properties may be set."""

    def __init__(self, names):
        self.__dict__["names"] = names

    def __setattr__(self, key, value):
        assert key in self.names, f"the operator has no property {key!r}"


def _draw(cls, context, method="draw"):
    """Run a panel method on a stand-in instance (Panel subclasses cannot be instantiated outside Blender)."""
    log = []
    fake = types.SimpleNamespace(layout=RecordingLayout(log))
    for klass in reversed(cls.__mro__):
        for key, value in vars(klass).items():
            if key.startswith("__"):
                continue
            if isinstance(value, classmethod):
                value = types.MethodType(value.__func__, cls)
            setattr(fake, key, types.MethodType(value, fake) if isinstance(value, types.FunctionType) else value)
    getattr(fake, method)(context)
    return log


def _props(log):
    return {name for kind, name in log if kind == "prop"}


def _context(scene, cam, mat=None, active=None):
    return types.SimpleNamespace(object=cam, camera=cam.data, scene=scene, material=mat,
                                 active_object=active if active is not None else cam)


def test_panels_draw_every_setting(lad, scene):
    panels = lad.package.panels
    cam = add_camera(scene)
    mat = brdf_material("Paint", model="steinvall")
    ctx = _context(scene, cam, mat)
    props = lad.properties

    log = _draw(panels.sensor.LADAR_PT_sensor, ctx)
    assert ("operator", "ladar.simulate") in log and ("prop", "system_type") in log
    assert ("prop", "use_frame_range") in log
    assert any(kind == "label" and "Field of view" in text for kind, text in log)
    assert ("menu", "LADAR_MT_sensor_presets") in _draw(panels.sensor.LADAR_PT_sensor, ctx, "draw_header_preset")
    group_panels = {cls.group: cls for cls in panels.CLASSES if getattr(cls, "group", "")}
    assert set(group_panels) == set(props.SENSOR_FIELDS)  # a sub-panel for every sensor settings group
    for group, cls in group_panels.items():
        assert cls.bl_parent_id == "LADAR_PT_sensor" and cls.bl_context == "data"
    assert "seed" in _props(_draw(panels.sensor.LADAR_PT_sensor_run, ctx))

    drawn = _props(_draw(panels.scene.LADAR_PT_atmosphere, ctx))
    assert drawn == {f.attr for f in props.ATMOSPHERE_FIELDS} | {"reference_range_m"}
    assert {"sensor", "output_dir", "seed", "use_frame_range"} <= _props(_draw(panels.scene.LADAR_PT_scene, ctx))
    assert {"if_exists", "write_previews", "import_results", "clouds"} <= \
        _props(_draw(panels.scene.LADAR_PT_scene_output, ctx))
    _draw(panels.scene.LADAR_PT_view3d, ctx)

    drawn = _props(_draw(panels.LADAR_PT_brdf, ctx))
    assert {"model", "specular_a", "slope_s", "diffuse_b", "diffuse_m"} <= drawn
    assert "reflectance" not in drawn
    mat.ladar_brdf.model = "lambertian"
    drawn = _props(_draw(panels.LADAR_PT_brdf, ctx))
    assert {"model", "reflectance"} <= drawn and "specular_a" not in drawn
    assert _draw(panels.LADAR_PT_brdf, ctx, "draw_header") == [("prop", "enabled")]


def test_laser_panel_adds_the_readable_energy_under_a_field_its_unit_does_not_suit(lad, scene):
    """0.1 J in the µJ field: the panel draws "= 100 mJ" right under it; 50 µJ reads well: nothing added."""
    cam = add_camera(scene)
    lad.blend_config.set_settings(scene, cam, {"laser.pulse_energy_j": 0.1})
    log = _draw(lad.package.panels.sensor.LADAR_PT_sensor_laser, _context(scene, cam))
    at = log.index(("prop", "pulse_energy_uj"))
    assert log[at + 1] == ("label", "= 100 mJ")
    lad.blend_config.set_settings(scene, cam, {"laser.pulse_energy_j": 5e-5})
    log = _draw(lad.package.panels.sensor.LADAR_PT_sensor_laser, _context(scene, cam))
    assert not any(kind == "label" and text.startswith("= ") for kind, text in log)


#: What each system type must show and hide (paper §2; issue 6: "show only what the system type uses").
EXPECTED = {
    "flash": ({"laser", "receiver", "gate", "detection", "detector", "run"}, {"scanner", "gated"},
              {"width_px", "height_px", "subsamples"}, set()),
    "profiler": ({"laser", "receiver", "gate", "detection", "detector", "run"}, {"scanner", "gated"},
                 {"subsamples", "aperture_diameter_m"}, {"width_px", "height_px"}),
    "scanner": ({"laser", "receiver", "gate", "scanner", "detection", "detector", "run"}, {"gated"},
                {"aperture_diameter_m", "system_efficiency"}, {"width_px", "height_px", "subsamples"}),
    "gated": ({"laser", "receiver", "gated", "detector", "run"}, {"gate", "detection", "scanner"},
              {"width_px", "height_px", "subsamples"}, set()),
}


@pytest.mark.parametrize("system_type", list(EXPECTED))
def test_every_panel_draws_for_every_system_type(lad, scene, tmp_path, system_type):
    """Every panel's poll, draw, draw_header and draw_header_preset run without error for every system type, and
    the sensor sub-panels show exactly the settings the system type uses."""
    panels = lad.package.panels
    sensor = lad.package.ladar_addon.sensor
    cam = add_camera(scene)
    cam.ladar.system_type = system_type
    mat = brdf_material("Paint")
    shown, hidden, receiver_shown, receiver_hidden = EXPECTED[system_type]
    for cls in panels.CLASSES:
        ctx = _context(scene, cam, mat)
        for method in ("draw", "draw_header", "draw_header_preset"):
            if hasattr(cls, method):
                _draw(cls, ctx, method)  # never raises, whatever the poll says
        group = getattr(cls, "group", "")
        if group:
            assert cls.poll(ctx) == (group in shown or group not in shown | hidden), (group, system_type)
            if cls.poll(ctx):
                fields = lad.fields.SENSOR_FIELDS[group]
                drawn = _props(_draw(cls, ctx)) & {f.attr for f in fields}
                want = {f.attr for f in fields
                        if sensor.field_used(system_type, group, f.name, cam.ladar.scanner.pattern)}
                assert drawn == want, (group, system_type)
    receiver = _props(_draw(panels.sensor.LADAR_PT_sensor_receiver, _context(scene, cam)))
    assert receiver_shown <= receiver and not (receiver_hidden & receiver)
    laser = _props(_draw(panels.sensor.LADAR_PT_sensor_laser, _context(scene, cam)))
    assert ("divergence_fills_fov" in laser) == (system_type != "scanner")
    labels = " ".join(text for kind, text in _draw(panels.sensor.LADAR_PT_sensor, _context(scene, cam))
                      if kind == "label")
    assert {"flash": "Field of view", "profiler": "One detector element", "scanner": "pulses in",
            "gated": "30 slices"}[system_type] in labels


@pytest.mark.parametrize("pattern, shown, hidden", [
    ("raster", {"n_lines", "scan_width_rad", "scan_height_rad"},
     {"n_channels", "cone_half_angle_rad", "cone_half_angle_y_rad"}),
    ("oscillating", {"scan_width_rad"},
     {"n_lines", "n_channels", "scan_height_rad", "cone_half_angle_rad", "cone_half_angle_y_rad"}),
    ("rotating", {"n_channels", "scan_width_rad", "scan_height_rad"},
     {"n_lines", "cone_half_angle_rad", "cone_half_angle_y_rad"}),
    ("palmer", {"cone_half_angle_rad", "cone_half_angle_y_rad"},
     {"n_lines", "n_channels", "scan_width_rad", "scan_height_rad"}),
])
def test_scan_pattern_settings(lad, scene, pattern, shown, hidden):
    panels = lad.package.panels
    cam = add_camera(scene)
    cam.ladar.system_type = "scanner"
    cam.ladar.scanner.pattern = pattern
    drawn = _props(_draw(panels.sensor.LADAR_PT_sensor_scanner, _context(scene, cam)))
    assert shown <= drawn and not (hidden & drawn)
    assert {"pattern", "pulse_rate_khz", "scan_rate_hz", "beam_subray_rings", "motion_samples_per_s"} <= drawn


def test_results_panel_legend_and_running_job(lad, scene, tmp_path):
    panels = lad.package.panels
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    from blender_scenes import add_plate
    add_plate(scene, location=(0, 0, -100))
    log = _draw(panels.scene.LADAR_PT_scene_results, _context(scene, cam))
    assert ("label", "No result point clouds yet") in log
    lad.simulate.simulate_scene(scene, out_dir=tmp_path / "r")
    obj = bpy.data.objects["r"]
    scene.ladar.color_by = "RANGE"
    log = _draw(panels.scene.LADAR_PT_scene_results, _context(scene, cam, active=obj))
    assert ("color_ramp", "Ladar Legend") in log and ("label", "Range (m)") in log
    assert ("label", f"{obj['ladar_color_min']:.4g}") in log and ("label", f"{obj['ladar_color_max']:.4g}") in log
    assert {("operator", "ladar.waveform_view"), ("operator", "ladar.render_preview")} <= set(log)
    # while a run is going: a progress bar and a cancel button instead of Simulate, also in the status bar
    assert _draw_status(lad) == []
    job = lad.job.SimulationJob(scene, out_dir=tmp_path / "running")
    lad.job.set_current_job(job)
    try:
        job.fraction, job.text = 0.25, "block 3/12"
        log = _draw(panels.scene.LADAR_PT_scene, _context(scene, cam))
        assert ("progress", "Ladar running: 25% block 3/12") in log and ("operator", "ladar.simulate_cancel") in log
        assert ("operator", "ladar.simulate") not in log
        assert _draw_status(lad) == [("progress", "Ladar running: 25% block 3/12"),
                                     ("operator", "ladar.simulate_cancel")]
    finally:
        lad.job.set_current_job(None)


def _draw_status(lad):
    log = []
    lad.package.panels.status.draw_status(types.SimpleNamespace(layout=RecordingLayout(log)), None)
    return log


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
    cam.ladar.laser.pulse_energy_uj = 6000.0
    path = tmp_path / "sensor.toml"
    assert bpy.ops.ladar.export_config(filepath=str(path)) == {"FINISHED"}
    text = path.read_text()
    assert "pulse_energy_j = 0.006" in text
    path.write_text(text.replace("pulse_energy_j = 0.006", "pulse_energy_j = 0.002"))
    assert bpy.ops.ladar.load_config(filepath=str(path)) == {"FINISHED"}
    assert cam.ladar.laser.pulse_energy_uj == pytest.approx(2000.0)
    path.write_text("[laser]\npulse_energy_j = -5.0\n")
    with pytest.raises(RuntimeError, match="laser.pulse_energy_j"):
        bpy.ops.ladar.load_config(filepath=str(path))
    assert cam.ladar.laser.pulse_energy_uj == pytest.approx(2000.0)  # unchanged


def test_channel_table_csv_in_the_scanner_panel(lad, scene, tmp_path):
    """The Scanner panel of a rotating head offers a CSV channel table: loading a good file sets the table and the
    channel count (the panel previews it, the config reads it); a bad file is refused with its row and column and
    changes nothing; a file spoiled after loading shows its error in the panel; clearing restores even spacing."""
    import bpy

    panels = lad.package.panels
    cam = add_camera(scene)
    cam.ladar.system_type = "scanner"
    cam.ladar.scanner.pattern = "rotating"
    bpy.context.view_layer.objects.active = cam

    def labels():
        return [text for kind, text in _draw(panels.sensor.LADAR_PT_sensor_scanner, _context(scene, cam))
                if kind == "label"]

    log = _draw(panels.sensor.LADAR_PT_sensor_scanner, _context(scene, cam))
    assert ("operator", "ladar.channel_table_load") in log and "Evenly spaced channels (no channel table)" in labels()
    good = tmp_path / "table.csv"
    good.write_text("elevation_deg,azimuth_offset_deg,fire_offset_s\n2.0,0.5,0\n# a comment\n-1.0,-0.25,1e-6\n"
                    "0.5,0,2e-6\n", encoding="utf-8")
    assert bpy.ops.ladar.channel_table_load(filepath=str(good)) == {"FINISHED"}
    assert cam.ladar.scanner.n_channels == 3
    text = labels()
    assert "File table.csv" in text
    assert ("3 channels, elevation -1.000° … +2.000°, azimuth offset -0.250° … +0.500°, fire offset ≤ 2 µs"
            in text)
    assert "  +2.0000, +0.5000, 0" in text
    cfg = lad.blend_config.config_from_blender(scene, cam)
    assert cfg.scanner.channel_table_file == str(good)
    tables = importlib.import_module(f"{lad.package.__name__}.core.config.tables")
    assert tables.channel_table_deg(cfg.scanner).tolist() == [[2.0, 0.5, 0.0], [-1.0, -0.25, 1e-6], [0.5, 0.0, 2e-6]]
    bad = tmp_path / "bad.csv"
    bad.write_text("1.0,0,0\n2.0,x,0\n", encoding="utf-8")
    with pytest.raises(RuntimeError, match=r"row 2 column 2.*'x'"):
        bpy.ops.ladar.channel_table_load(filepath=str(bad))
    assert lad.blend_config.read_tables(cam, "scanner") == {"channel_table_file": str(good)}  # nothing changed
    assert cam.ladar.scanner.n_channels == 3
    good.write_text("1.0,0,0\n2.0,0,5\n", encoding="utf-8")  # spoiled after loading: fire offset out of range
    errors = [t for t in labels() if t.startswith("Error")]
    assert len(errors) == 1 and "row 2 column 3" in errors[0] and "5" in errors[0]
    four = tmp_path / "four.csv"  # with the relative pulse energy column
    four.write_text("elevation_deg,azimuth_offset_deg,fire_offset_s,relative_pulse_energy\n2.0,0.5,0,0.5\n"
                    "-1.0,-0.25,1e-6,1\n", encoding="utf-8")
    assert bpy.ops.ladar.channel_table_load(filepath=str(four)) == {"FINISHED"}
    text = labels()
    assert any(t.endswith(", relative pulse energy 0.5 … 1") for t in text), text
    assert "  elevation_deg, azimuth_offset_deg, fire_offset_s, relative_pulse_energy" in text
    assert "  +2.0000, +0.5000, 0, 0.5" in text
    assert bpy.ops.ladar.channel_table_clear() == {"FINISHED"}
    assert lad.blend_config.read_tables(cam, "scanner") == {}
    assert "Evenly spaced channels (no channel table)" in labels()
