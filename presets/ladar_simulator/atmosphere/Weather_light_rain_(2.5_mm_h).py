# Ladar Simulator atmosphere preset: weather, light rain, 2.5 mm/h: extinction plus drop returns.
# Typical value for this weather class, not a measurement of a specific site or day.
# Sets only the weather fields (weather, visibility, precipitation rate); the turbulence presets set only the
# turbulence fields, so one of each combines.
import bpy

scene = bpy.context.scene
atmosphere = scene.ladar_atmosphere
unit_scale = 1.0 if scene.unit_settings.system == "NONE" else scene.unit_settings.scale_length

atmosphere.weather = "rain"
# visibility_m is a DISTANCE property: stored in Blender units (metres / unit scale); 0 = no aerosol.
atmosphere.visibility_m = 0.0 / unit_scale
atmosphere.visibility_model = "kim"
atmosphere.rain_rate_mm_h = 2.5
