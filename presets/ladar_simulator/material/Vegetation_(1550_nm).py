# Ladar Simulator material preset: green vegetation at 1550 nm (eye-safe lasers).
# Representative value: leaf water absorbs near 1450 nm; green leaves reflect about 0.2–0.3 at 1550 nm.
# Lambertian; not a measurement of a specific plant.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "lambertian", "reflectance": 0.25},
                              origin="Preset Vegetation (1550 nm): representative value, not a measurement")
