# Ladar Simulator material preset: glossy paint (a specular lobe over a diffuse base), Steinvall model.
# Representative parameters of the Steinvall (2000) monostatic model, eq. 3-3: A = 0.05 1/sr, s = 0.2,
# B = 0.08 1/sr, m = 1 (the worked example of docs/theory.md §10: f_r(0°) = 0.130, f_r(30°) = 0.069 1/sr,
# ρ_DH = 0.23).  Illustrative of a glossy painted surface; not fitted to a measurement.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "steinvall", "specular_a": 0.05, "slope_s": 0.2, "diffuse_b": 0.08, "diffuse_m": 1.0},
                              origin="Preset Paint (glossy): representative Steinvall parameters, not a measurement")
