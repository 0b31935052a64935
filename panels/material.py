"""Ladar BRDF panel in the Material tab."""
import bpy

from ..ladar_addon.properties import BRDF_FIELDS

_MODEL_FIELDS = {"lambertian": {"reflectance"}, "steinvall": {"specular_a", "slope_s", "diffuse_b", "diffuse_m"}}


class LADAR_PT_brdf(bpy.types.Panel):
    bl_label = "Ladar BRDF"
    bl_idname = "LADAR_PT_brdf"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "material"

    @classmethod
    def poll(cls, context):
        return getattr(context, "material", None) is not None

    def draw_header(self, context):
        self.layout.prop(context.material.ladar_brdf, "enabled", text="")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.material.ladar_brdf
        col = layout.column()
        col.active = props.enabled
        col.prop(props, "model")
        shown = _MODEL_FIELDS.get(props.model)
        for f in BRDF_FIELDS:
            if f.attr != "model" and (shown is None or f.attr in shown):
                col.prop(props, f.attr)
        if not props.enabled:
            layout.label(text="Off: the simulator uses a grey Lambertian BRDF (30 %)", icon="INFO")
