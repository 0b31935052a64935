"""Scene tab: the ladar sensor choice, output and atmosphere; a 3D-viewport sidebar tab with Simulate."""
import bpy

from ..ladar_addon.presets import LADAR_MT_atmosphere_presets, draw_preset_header
from ..ladar_addon.fields import ATMOSPHERE_FIELDS
from .common import (active_sensor, atmosphere_settings, draw_fields, draw_lines, reference_range_m,
                     sensor_config, simulate_button, simulate_options)


def draw_atmosphere_figures(layout, scene):
    """Read-only extinction, transmission and turbulence figures at the reference range (never raises)."""
    from ..ladar_addon import derived  # (at the first draw: it imports the simulator's physics, numba included)

    try:
        obj = active_sensor(scene)
        cfg = sensor_config(scene, obj) if obj is not None else None
        wavelength = cfg.laser.wavelength_m if cfg is not None else derived.DEFAULT_WAVELENGTH_M
        lines = derived.atmosphere_lines(atmosphere_settings(scene), wavelength, reference_range_m(scene))
        if cfg is None:
            lines.append("No ladar sensor: figures at 1064 nm")
    except Exception as exc:  # noqa: BLE001 - draw must never fail
        lines = [f"Derived figures unavailable: {exc}"]
    draw_lines(layout.box(), lines)


def draw_aerosol_layers(layout, scene):
    """The read-only Aerosol Layers box (``atmosphere.aerosol_layers``: set by loading a config file) with a clear
    button (never raises)."""
    box = layout.box()
    row = box.row()
    row.label(text="Aerosol Layers")
    row.operator("ladar.aerosol_layers_clear", text="", icon="X")
    try:
        from ..ladar_addon import derived

        lines = derived.aerosol_layer_lines(atmosphere_settings(scene))
    except Exception as exc:  # noqa: BLE001 - draw must never fail
        lines = [f"Aerosol layers unavailable: {exc}"]
    draw_lines(box, lines)


def _draw_scene_settings(layout, scene):
    props = scene.ladar
    layout.prop(props, "sensor")
    if props.sensor is None:
        layout.label(text=f"Using the scene camera: {scene.camera.name if scene.camera else 'none'}",
                     icon="INFO")
    layout.prop(props, "output_dir")
    layout.prop(props, "seed")


class _ScenePanel:
    """Shared placement of the Scene-tab panels."""

    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "scene"

    @classmethod
    def poll(cls, context):
        return context.scene is not None


class LADAR_PT_scene(_ScenePanel, bpy.types.Panel):
    bl_label = "Ladar"
    bl_idname = "LADAR_PT_scene"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        _draw_scene_settings(layout, context.scene)
        simulate_options(layout, context.scene)
        simulate_button(layout)


class LADAR_PT_scene_output(_ScenePanel, bpy.types.Panel):
    bl_label = "Output"
    bl_idname = "LADAR_PT_scene_output"
    bl_parent_id = "LADAR_PT_scene"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.ladar
        layout.prop(props, "if_exists")
        layout.prop(props, "write_previews")
        layout.prop(props, "import_results")
        col = layout.column()
        col.active = props.import_results
        col.prop(props, "clouds")
        layout.operator("ladar.import_run", text="Import Run Folder", icon="IMPORT")
        layout.operator("ladar.sweep", text="Run Sweep…", icon="GRAPH")


def draw_results(layout, scene, obj=None):
    """Colouring, legend and point size of the result point clouds; waveform view and preview render."""
    from ..ladar_addon.names import RESULT_TAG
    from ..ladar_addon.colors import COLOR_BY, result_objects
    from ..ladar_addon.results import legend_ramp_node

    props = scene.ladar
    layout.prop(props, "color_by")
    legend_obj = obj if obj is not None and obj.get(RESULT_TAG) is not None else None
    if legend_obj is None:
        clouds = result_objects(scene)
        legend_obj = clouds[-1] if clouds else None
    ramp = legend_ramp_node()
    if ramp is not None:
        layout.template_color_ramp(ramp, "color_ramp", expand=False)
    if legend_obj is not None and legend_obj.get("ladar_color_by") is not None:
        lo, hi = legend_obj["ladar_color_min"], legend_obj["ladar_color_max"]
        row = layout.row()
        row.label(text=f"{lo:.4g}")
        row.label(text=str(legend_obj.get("ladar_color_label", "")))
        row.label(text=f"{hi:.4g}")
        if legend_obj["ladar_color_by"] != props.color_by:
            layout.label(text=f"{legend_obj.name}: no {COLOR_BY[props.color_by][1].lower()} attribute",
                         icon="INFO")
    else:
        layout.label(text="No result point clouds yet", icon="INFO")
    layout.prop(props, "point_radius")
    row = layout.row(align=True)
    row.operator("ladar.waveform_view", text="Waveform", icon="GRAPH")
    row.operator("ladar.render_preview", text="Preview Render", icon="RENDER_RESULT")
    row.operator("ladar.export_las", text="Export LAS", icon="EXPORT")
    if props.last_run:
        layout.label(text=f"Last run: {props.last_run}", icon="FILE_FOLDER")


class LADAR_PT_scene_results(_ScenePanel, bpy.types.Panel):
    bl_label = "Results"
    bl_idname = "LADAR_PT_scene_results"
    bl_parent_id = "LADAR_PT_scene"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        draw_results(layout, context.scene, getattr(context, "active_object", None))


class LADAR_PT_atmosphere(_ScenePanel, bpy.types.Panel):
    bl_label = "Ladar Atmosphere"
    bl_idname = "LADAR_PT_atmosphere"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        draw_fields(layout, context.scene.ladar_atmosphere, ATMOSPHERE_FIELDS)
        draw_aerosol_layers(layout, context.scene)
        layout.prop(context.scene.ladar, "reference_range_m")
        draw_atmosphere_figures(layout, context.scene)

    def draw_header_preset(self, context):
        draw_preset_header(self.layout, LADAR_MT_atmosphere_presets, "ladar.atmosphere_preset_add")


class _View3DPanel:
    """Placement shared by the 3D-viewport sidebar panels (tab "Ladar")."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Ladar"

    @classmethod
    def poll(cls, context):
        return context.scene is not None


class LADAR_PT_view3d(_View3DPanel, bpy.types.Panel):
    bl_label = "Ladar"
    bl_idname = "LADAR_PT_view3d"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        layout.prop(context.scene.ladar, "sensor")
        layout.prop(context.scene.ladar, "output_dir")
        simulate_options(layout, context.scene)
        simulate_button(layout)


class LADAR_PT_view3d_results(_View3DPanel, bpy.types.Panel):
    bl_label = "Results"
    bl_idname = "LADAR_PT_view3d_results"
    bl_parent_id = "LADAR_PT_view3d"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        draw_results(layout, context.scene, getattr(context, "active_object", None))
