"""Ladar BRDF panel in the Material tab: model and parameters, the measured table, the Principled BSDF starting
values, material presets and a plot of the BRDF vs incidence angle."""
import bpy

from ..ladar_addon.fields import BRDF_FIELDS

#: Settings drawn for each model (the table's rows are drawn as a read-only list).
_MODEL_FIELDS = {"lambertian": {"reflectance"}, "steinvall": {"specular_a", "slope_s", "diffuse_b", "diffuse_m"},
                 "table": {"table_wavelength_m"}}
#: Settings drawn only for their own model (any other new BRDF setting is drawn for every model).
_MODEL_ONLY = set().union(*_MODEL_FIELDS.values())


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

    def draw_header_preset(self, context):
        from ..ladar_addon.presets import LADAR_MT_material_presets, draw_preset_header
        draw_preset_header(self.layout, LADAR_MT_material_presets, "ladar.material_preset_add")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.material.ladar_brdf
        col = layout.column()
        col.active = props.enabled
        col.prop(props, "model")
        shown = _MODEL_FIELDS.get(props.model, set())
        for f in BRDF_FIELDS:
            if f.attr != "model" and (f.attr in shown or f.attr not in _MODEL_ONLY):
                col.prop(props, f.attr)
        if props.model == "table":
            self.draw_table(context, col, props)
        self.draw_figures(col, props)
        row = layout.row(align=True)
        row.operator("ladar.brdf_table_import", text="Import Table", icon="IMPORT")
        row.operator("ladar.brdf_from_principled", text="Initialise from Principled BSDF", icon="SHADING_RENDERED")
        if props.origin:
            layout.label(text=f"Values from: {props.origin}", icon="INFO")
        layout.operator("ladar.brdf_plot", text="Plot BRDF vs Angle", icon="GRAPH")
        if props.plot is not None:
            self.draw_plot(layout, props.plot)
        if not props.enabled:
            layout.label(text="Off: the simulator uses a grey Lambertian BRDF (30 %)", icon="INFO")

    def draw_table(self, context, layout, props):
        from ..ladar_addon.materials import scene_laser_wavelength_m, table_summary_lines
        box = layout.box()
        lines = table_summary_lines(props, scene_laser_wavelength_m(getattr(context, "scene", None)))
        for i, text in enumerate(lines):
            warn = text.startswith(("Invalid", "Measured at", "No table"))
            box.label(text=text, icon="ERROR" if warn else ("PRESET" if i == 0 else "BLANK1"))

    def draw_figures(self, layout, props):
        """π f_r(0°) and π f_r(60°): the Lambertian reflectance that returns the same energy at that angle."""
        from ..core.physics.brdf import lambertian_equivalent_reflectance
        from ..ladar_addon.materials import material_brdf_settings
        try:
            brdf = material_brdf_settings(props.id_data)
            from ..core.config.validate import validate
            validate(brdf)
            rho = lambertian_equivalent_reflectance(brdf, [0.0, 60.0])
        except Exception:  # noqa: BLE001 - draw must never fail; the table lines say what is wrong
            return
        layout.label(text=f"Lambertian equivalent π·f_r: {rho[0]:.3g} at 0°, {rho[1]:.3g} at 60°")

    def draw_plot(self, layout, image):
        layout.label(text=f"Plot: image '{image.name}' (open it in an Image Editor)", icon="IMAGE_DATA")
        try:
            preview = image.preview_ensure() or image.preview
            icon_id = preview.icon_id if preview is not None else 0
        except Exception:  # noqa: BLE001 - no previews without a window (background mode)
            icon_id = 0
        if icon_id:
            layout.template_icon(icon_value=icon_id, scale=10.0)
