# Ladar Simulator material preset: asphalt road surface, dry, near infrared (~0.9–1.1 µm).
# Representative value: spectral libraries (e.g. the JPL/USGS ECOSTRESS library) give a hemispherical
# reflectance of roughly 0.08–0.15 for asphalt near 1 µm (fresh dark asphalt lower, aged grey asphalt higher).
# Lambertian; not a measurement of a specific surface.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "lambertian", "reflectance": 0.12},
                              origin="Preset Asphalt (NIR): representative value, not a measurement")
