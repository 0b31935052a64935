"""Drawing helpers shared by the panels."""


def draw_fields(layout, props, fields, skip=()):
    """One row per generated property (labels, units and ranges come from the property definitions)."""
    for f in fields:
        if f.attr not in skip:
            layout.prop(props, f.attr)


def simulate_button(layout, sensor_name=""):
    """The Simulate button, or while a run is going its progress bar and a cancel button."""
    from ..ladar_addon.background import current_job

    row = layout.row(align=True)
    row.scale_y = 1.4
    job = current_job()
    if job is not None:
        row.progress(factor=job.fraction, type="BAR", text=job.status_text())
        row.operator("ladar.simulate_cancel", text="", icon="CANCEL")
        return
    op = row.operator("ladar.simulate", text="Simulate", icon="RENDER_STILL")
    op.sensor = sensor_name
    return op


def simulate_options(layout, scene):
    """The frame range switch, with the frames it simulates."""
    props = scene.ladar
    col = layout.column()
    col.prop(props, "use_frame_range")
    if props.use_frame_range:
        step = max(1, scene.frame_step)
        n = len(range(scene.frame_start, scene.frame_end + 1, step))
        col.label(text=f"Frames {scene.frame_start} … {scene.frame_end}" + (f", step {step}" if step > 1 else "")
                  + f": {n} frame{'s' if n != 1 else ''} into one sequence folder", icon="SEQUENCE")
    else:
        col.label(text=f"Frame {scene.frame_current}", icon="TIME")


def active_sensor(scene):
    """The scene's ladar sensor (Scene.ladar.sensor, else the scene camera) if it is a camera, else None."""
    obj = scene.ladar.sensor or scene.camera
    return obj if obj is not None and obj.type == "CAMERA" else None


def reference_range_m(scene):
    from ..ladar_addon.blend_config import unit_scale
    return scene.ladar.reference_range_m * unit_scale(scene)


def sensor_config(scene, obj):
    """The core config of ``obj`` (a camera) or None when it cannot be read."""
    from ..ladar_addon.blend_config import config_from_blender
    try:
        return config_from_blender(scene, obj)
    except Exception:  # noqa: BLE001 - draw must never fail
        return None


def atmosphere_settings(scene):
    from ..core.config.settings import AtmosphereSettings
    from ..ladar_addon.blend_config import read_group, read_tables, unit_scale
    from ..ladar_addon.fields import ATMOSPHERE_FIELDS
    return AtmosphereSettings(**read_group(scene.ladar_atmosphere, ATMOSPHERE_FIELDS, unit_scale(scene)),
                              **read_tables(scene, "atmosphere"))


def draw_lines(layout, lines, icon="INFO"):
    col = layout.column(align=True)
    for i, text in enumerate(lines):
        col.label(text=text, icon=icon if i == 0 else "BLANK1")
