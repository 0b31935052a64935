# Ladar Simulator material preset: green vegetation at 532 nm (green lasers).
# Representative value: green leaves reflect about 0.08–0.15 at 532 nm (the green reflectance peak).
# Lambertian; not a measurement of a specific plant.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "lambertian", "reflectance": 0.1},
                              origin="Preset Vegetation (532 nm): representative value, not a measurement")
