"""Laser radar equation per sub-ray (paper eq. 3-1, 3-4; docs/theory.md §10).

For a sub-ray carrying the fraction F of the pulse energy E_T onto a surface at range R, hit at incidence θ:

    E_r = E_T · F · η_sys · f_r(θ) cos θ · (π r_a² / R²) · exp(−2 σ_atm R)                      (3-1), (3-4)

with f_r the monostatic BRDF (ρ = f_r cos θ in the paper's notation, docs/theory.md §10).  For a Lambertian
surface this is E_T F η ρ_d cos θ r_a²/R² e^(−2σR).  The product is formed in log space so that long ranges
and thick fog give a tiny positive number or an exact, reported zero — never NaN.
"""
from __future__ import annotations

import numpy as np

from .brdf import evaluate_materials


def log_received_energy(pulse_energy_j, cell_fraction, system_efficiency, brdf_per_sr, cos_theta,
                        aperture_diameter_m, range_m, extinction_per_m):
    """ln E_r (J) of eq. 3-1 per ray.  Zero factors give −inf (no energy), never NaN."""
    aperture_area = np.pi * (0.5 * aperture_diameter_m) ** 2
    with np.errstate(divide="ignore"):
        log_e = (np.log(pulse_energy_j) + np.log(cell_fraction) + np.log(system_efficiency)
                 + np.log(brdf_per_sr) + np.log(np.clip(cos_theta, 0.0, 1.0))
                 + np.log(aperture_area) - 2.0 * np.log(range_m) - 2.0 * extinction_per_m * range_m)
    return log_e


def received_energy(laser, receiver, extinction_per_m, materials, material_ids, cos_theta, range_m,
                    cell_fraction):
    """E_r (J, float64) per ray of eq. 3-1 for the settings groups."""
    f_r = evaluate_materials(materials, material_ids, cos_theta)
    log_e = log_received_energy(laser.pulse_energy_j, cell_fraction, receiver.system_efficiency, f_r,
                                cos_theta, receiver.aperture_diameter_m, range_m, extinction_per_m)
    return np.exp(log_e)
