# Ladar Simulator atmosphere preset: medium turbulence, Cn² = 1e-14 m^-2/3 (constant along the path).
# Typical near-ground value for this turbulence strength, not a measurement of a specific site or day.
# Sets only the turbulence fields (the visibility presets set only the visibility fields, so one of each
# combines) and switches the turbulence effects A, B, D and E on.
import bpy

atmosphere = bpy.context.scene.ladar_atmosphere

# cn2_m_23 is stored in units of 1e-14 m^-2/3 (the panel shows "Cn² (×1e-14 m^-2/3)"): 1e-14 -> 1.0.
atmosphere.cn2_m_23 = 1.0
atmosphere.beam_broadening = True
atmosphere.scintillation = True
atmosphere.scintillation_model = "auto"
atmosphere.beam_wander = True
atmosphere.turbulence_blur = "long"
