# Ladar Simulator material preset: green vegetation (leaves, canopy) in the near-infrared plateau, 800–1300 nm.
# Representative value: green leaves reflect about 0.45–0.5 on the NIR plateau (the 'red edge' lies at ~700 nm);
# canopies somewhat less.  Much lower at 532 nm (~0.1) and 1550 nm (~0.25, water absorption): use the other
# vegetation presets there.  Lambertian; not a measurement of a specific plant.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "lambertian", "reflectance": 0.45},
                              origin="Preset Vegetation (NIR): representative value, not a measurement")
