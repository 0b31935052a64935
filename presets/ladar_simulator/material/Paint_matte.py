# Ladar Simulator material preset: matte paint (weak, broad specular lobe), Steinvall model.
# Representative parameters of the Steinvall (2000) monostatic model, eq. 3-3: a weak broad specular lobe
# (A = 0.005 1/sr, s = 0.5) over a near-Lambertian base (B = 0.1 1/sr, m = 0.5); ρ_DH ≈ 0.29.  Illustrative of a
# flat painted surface; not fitted to a measurement.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "steinvall", "specular_a": 0.005, "slope_s": 0.5, "diffuse_b": 0.1, "diffuse_m": 0.5},
                              origin="Preset Paint (matte): representative Steinvall parameters, not a measurement")
