# Ladar Simulator material preset: diffuse white reference panel, 99 %.
# Sintered PTFE reference panels (e.g. Labsphere Spectralon SRS-99) are near-Lambertian with a directional-
# hemispherical reflectance of about 0.99 from 400 to 1500 nm (~0.95 at 2 µm), per the manufacturer's data.
# Nominal, not a calibration of a panel.  Modelled as Lambertian; real panels lose some Lambertian behaviour
# beyond ~60° incidence.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "lambertian", "reflectance": 0.99},
                              origin="Preset Reference panel 99 %: Lambertian, manufacturer's nominal reflectance")
