# Ladar Simulator material preset: retroreflective sheeting (road signs, licence plates), as a BRDF table.
# Representative table, not a measurement.  Anchors: ASTM D4956 Type I (engineering grade) white sheeting has
# minimum coefficients of retroreflection R_A = 70 cd·lx⁻¹·m⁻² at −4° entrance and 30 at 30° entrance
# (0.2° observation angle).  The monostatic BRDF of a retroreflector is f_r = R_A / cos²θ (1/sr; R_A is
# referred to the illuminance normal to the beam and the sample's area, f_r to the surface): 70 at 0°, 40 at
# 30°.  The other rows follow a smooth fall-off to 0 at 90° (representative shape).  R_A is photometric
# (visible light, ~555 nm), so the table states 555 nm: the panel flags a different laser wavelength.  A ladar's
# observation angle is ~0° (monostatic), where sheeting returns more than at 0.2°: these values are a floor.
# Higher grades (ASTM Type III, prismatic) return ~3–10× more.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "table", "table_wavelength_m": 5.55e-7,
                               "table_angle_deg": [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 90.0],
                               "table_brdf_per_sr": [70.0, 68.0, 61.0, 40.0, 24.0, 12.0, 6.0, 3.4, 1.7, 0.0]},
                              origin="Preset Retroreflective sheeting: representative table (ASTM D4956 Type I "
                                     "anchors), not a measurement")
