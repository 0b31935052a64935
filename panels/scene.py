"""Scene tab: the ladar sensor choice, output and atmosphere; a 3D-viewport sidebar tab with Simulate."""
import bpy

from ..ladar_addon.properties import ATMOSPHERE_FIELDS
from .common import draw_fields, simulate_button


def _draw_scene_settings(layout, scene):
    props = scene.ladar
    layout.prop(props, "sensor")
    if props.sensor is None:
        layout.label(text=f"Using the scene camera: {scene.camera.name if scene.camera else 'none'}",
                     icon="INFO")
    layout.prop(props, "output_dir")
    layout.prop(props, "seed")
    layout.prop(props, "overwrite")
    layout.prop(props, "import_results")
    layout.prop(props, "point_radius")


class LADAR_PT_scene(bpy.types.Panel):
    bl_label = "Ladar"
    bl_idname = "LADAR_PT_scene"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "scene"

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        _draw_scene_settings(layout, context.scene)
        simulate_button(layout)


class LADAR_PT_atmosphere(bpy.types.Panel):
    bl_label = "Ladar Atmosphere"
    bl_idname = "LADAR_PT_atmosphere"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "scene"

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        draw_fields(layout, context.scene.ladar_atmosphere, ATMOSPHERE_FIELDS)


class LADAR_PT_view3d(bpy.types.Panel):
    bl_label = "Ladar"
    bl_idname = "LADAR_PT_view3d"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Ladar"

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        layout.prop(context.scene.ladar, "sensor")
        layout.prop(context.scene.ladar, "output_dir")
        simulate_button(layout)
