# Ladar Simulator atmosphere preset: haze, meteorological visibility 5 km.
# Typical value for this weather class, not a measurement of a specific site or day.
# Sets only the visibility fields: the turbulence presets set only the turbulence fields, so one of each combines.
import bpy

scene = bpy.context.scene
atmosphere = scene.ladar_atmosphere
unit_scale = 1.0 if scene.unit_settings.system == "NONE" else scene.unit_settings.scale_length

# visibility_m is a DISTANCE property: stored in Blender units (metres / unit scale).
atmosphere.visibility_m = 5000.0 / unit_scale
atmosphere.visibility_model = "kim"
