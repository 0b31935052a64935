"""Material BRDF operators: import a measured table, initialise from the Principled BSDF, plot the BRDF."""
import bpy
from bpy_extras.io_utils import ImportHelper

from ..core.errors import ConfigError
from ..ladar_addon import materials


def _material_poll(context):
    return getattr(context, "material", None) is not None


class LADAR_OT_brdf_table_import(bpy.types.Operator, ImportHelper):
    """Import a measured monostatic BRDF table (CSV/text: incidence angle in degrees, BRDF in 1/sr) into the
    active material; it is stored in the .blend (paper §3.3: measured data is used where it exists)"""

    bl_idname = "ladar.brdf_table_import"
    bl_label = "Import BRDF Table"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: bpy.props.StringProperty(default="*.csv;*.txt;*.dat;*.tsv", options={"HIDDEN"})
    wavelength: bpy.props.FloatProperty(
        name="Wavelength", subtype="WAVELENGTH", default=1064.0, min=200.0, max=12000.0,
        description="Wavelength of the measurement in nm, used when the file states none "
                    "(a line such as '# wavelength = 1064 nm')")

    @classmethod
    def poll(cls, context):
        return _material_poll(context)

    def execute(self, context):
        material = context.material
        try:
            brdf = materials.import_brdf_table(material, self.filepath, self.wavelength * 1e-9)
        except (ConfigError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"{material.name}: {len(brdf.table_angle_deg)}-row BRDF table at "
                              f"{brdf.table_wavelength_m * 1e9:.0f} nm from {material.ladar_brdf.table_source}")
        return {"FINISHED"}


class LADAR_OT_brdf_from_principled(bpy.types.Operator):
    """Set a starting Steinvall BRDF from the material's Principled BSDF (base colour, roughness, metallic, IOR).
    A visible-light appearance mapped by a documented formula: starting values, not a measurement"""

    bl_idname = "ladar.brdf_from_principled"
    bl_label = "Initialise from Principled BSDF"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _material_poll(context)

    def execute(self, context):
        material = context.material
        brdf, inputs = materials.initialise_from_principled(material)
        text = (f"{material.name}: starting BRDF from {inputs['source']}: A = {brdf.specular_a:.4g} 1/sr, "
                f"s = {brdf.slope_s:.3g}, B = {brdf.diffuse_b:.4g} 1/sr, m = 0")
        if inputs["linked"]:
            text += f" (linked inputs {', '.join(inputs['linked'])}: their unlinked values were used)"
        self.report({"WARNING"} if inputs["linked"] else {"INFO"}, text)
        return {"FINISHED"}


class LADAR_OT_brdf_plot(bpy.types.Operator):
    """Plot the material's BRDF vs incidence angle into an image (packed into the .blend)"""

    bl_idname = "ladar.brdf_plot"
    bl_label = "Plot BRDF"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _material_poll(context)

    def execute(self, context):
        material = context.material
        try:
            image = materials.plot_material_brdf(material, materials.scene_laser_wavelength_m(context.scene))
        except (ConfigError, ImportError, OSError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        screen = getattr(context, "screen", None)
        for area in (screen.areas if screen is not None else ()):
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
                break
        self.report({"INFO"}, f"BRDF plot in image '{image.name}'")
        return {"FINISHED"}


CLASSES = (LADAR_OT_brdf_table_import, LADAR_OT_brdf_from_principled, LADAR_OT_brdf_plot)
