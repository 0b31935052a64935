# Ladar Simulator material preset: diffuse grey reference panel, 10 %.
# Grey sintered PTFE reference panels (e.g. Labsphere Spectralon SRS-10) have a nominal reflectance of about
# 0.10, nearly flat over 400–1500 nm, per the manufacturer's data (nominal, not a calibration of a panel).
# Modelled as Lambertian.
# Values in SI units (wavelengths in m); the add-on converts and validates them and enables the material's
# ladar BRDF.  A preset without a table keeps the material's measured table (unused unless model = "table").
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_material_preset({"model": "lambertian", "reflectance": 0.1},
                              origin="Preset Reference panel 10 %: Lambertian, manufacturer's nominal reflectance")
