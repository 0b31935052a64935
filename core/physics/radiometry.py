"""Laser radar equation per sub-ray (paper eq. 3-1, 3-4; docs/theory.md §10).

For a sub-ray carrying the fraction F of the pulse energy E_T onto a surface at range R, hit at incidence θ:

    E_r = E_T · F · η_sys · f_r(θ) cos θ · (π r_a² / (R² + r_a²)) · exp(−2 σ_atm R)             (3-1), (3-4)

with f_r the monostatic BRDF (ρ = f_r cos θ in the paper's notation, docs/theory.md §10).  For a Lambertian
surface this is E_T F η ρ_d cos θ r_a²/(R² + r_a²) e^(−2σR).

The aperture factor is the *projected* solid angle of the aperture disc (radius r_a) seen on axis from the
surface point, ∫ cos θ_e dΩ = π sin²α = π r_a²/(R² + r_a²): the radiance f_r E cos θ leaves the surface towards
the aperture at emission angle θ_e, and the energy crossing the disc carries cos θ_e.  It is the paper's far-field
π r_a²/R² to a relative (r_a/R)² (6e-8 for the default 5 cm aperture at 200 m: the four README examples change in
their last bits), and it stays bounded at contact: π, so a Lambertian plate of reflectance ρ returns at most ρ·F
of the pulse energy (F: the fraction it intercepts) at every range down to R = 0 (issue 31: the far-field form
returned 2.2× the pulse energy at 1 cm and 222× at 1 mm).  The plain solid angle 2π(1 − R/√(R² + r_a²)) is not
used: without the cos θ_e it tends to 2π, twice the energy a Lambertian surface sends into the hemisphere.

One compiled pass over the rays (:func:`energy_at`) forms E_r as the product of its factors, with the BRDF of
each ray's material (core/physics/brdf.py): no logarithm per ray (beyond the Steinvall lobe's own), one
exponential when σ_atm ≠ 0.  Its guarantees are those of a log-space sum: a zero factor (E_T, F, η, f_r,
cos θ ≤ 0, aperture) gives an exact 0, never NaN; where the product would leave the normal float64 range on the
way (an intermediate below 2.2e-308 or infinite: a very long range, thick fog, a grazing ray on a tiny BRDF) that
ray alone is evaluated in log space, exp(ln(E_T η π r_a²) + ln F + ln f_r + ln cos θ − 2 ln R − ln(1 + r_a²/R²)
− 2σR), so long
ranges and thick fog give a tiny positive number or an exact 0, never NaN.  The product agrees with the
log-space sum it replaced to rounding: within 1e-12 relative, 1.4e-13 measured, most of it the sum's own
rounding (tests/core/physics/test_radiometry_product.py).
"""
from __future__ import annotations

import math

import numpy as np

from ..atmosphere.extinction import LayeredExtinction
from ..jit import kernel
from .brdf import bad_material, material_brdf_at, material_table

#: Smallest normal float64: products below it have lost precision (or underflowed), so the log form is used.
_TINY = 2.2250738585072014e-308


@kernel(inline=True)
def energy_at(scale, fraction, f_r, cos_theta, range_m, two_sigma, aperture_r2):
    """E_r (J) of one ray: scale·F·f_r·cos θ/(R² + r_a²) · exp(−2σR), with ``scale`` = E_T η_sys π r_a²,
    ``two_sigma`` = 2σ_atm and ``aperture_r2`` = r_a² (module docstring for the zeros and the log form)."""
    c = min(max(cos_theta, 0.0), 1.0)
    if scale == 0.0 or fraction == 0.0 or f_r == 0.0 or c == 0.0:
        return 0.0
    num = scale * fraction * f_r * c
    r2 = range_m * range_m + aperture_r2
    e = num / r2
    if two_sigma != 0.0:
        e *= math.exp(-two_sigma * range_m)
    if num >= _TINY and r2 >= _TINY and _TINY <= e < math.inf:
        return e
    log_e = math.log(scale) + math.log(fraction) + math.log(f_r) + math.log(c)
    ra = math.sqrt(aperture_r2)  # ln(R² + r_a²) without overflow or underflow: the larger one squared, log1p
    big, small = (range_m, ra) if range_m >= ra else (ra, range_m)
    log_e -= 2.0 * math.log(big) + math.log1p((small / big) * (small / big))
    if two_sigma != 0.0:
        log_e -= two_sigma * range_m
    return math.exp(log_e)


@kernel
def _received_energy(scale, two_sigma, aperture_r2, model, params, start, angle_deg, brdf_per_sr, material,
                     cos_theta, range_m, fraction, fraction_step, out):
    for i in range(cos_theta.shape[0]):
        if material[i] < 0 or material[i] >= model.shape[0]:
            return i
        f_r = material_brdf_at(model, params, start, angle_deg, brdf_per_sr, material[i], cos_theta[i])
        out[i] = energy_at(scale, fraction[i * fraction_step], f_r, cos_theta[i], range_m[i], two_sigma,
                           aperture_r2)
    return -1


def energy_scale(laser, receiver) -> float:
    """E_T η_sys π r_a² (J m²): the factors of eq. 3-1 common to every ray."""
    return laser.pulse_energy_j * receiver.system_efficiency * (np.pi * (0.5 * receiver.aperture_diameter_m) ** 2)


def aperture_r2(receiver) -> float:
    """r_a² (m²): the aperture radius squared, of the projected solid angle π r_a²/(R² + r_a²)."""
    return float((0.5 * receiver.aperture_diameter_m) ** 2)


def energy_terms(laser, receiver, extinction_per_m: float) -> tuple[float, float, float]:
    """The arguments of :func:`energy_at` common to every ray: (E_T η_sys π r_a², 2σ, r_a²), for σ a number (the
    uniform part of a layered extinction; its layers are applied after the kernel)."""
    return float(energy_scale(laser, receiver)), 2.0 * float(extinction_per_m), aperture_r2(receiver)


def received_energy(laser, receiver, extinction_per_m, materials, material_ids, cos_theta, range_m,
                    cell_fraction):
    """E_r (J, float64) per ray of eq. 3-1 for the settings groups: rays hitting materials
    ``materials[material_ids]`` at incidence ``cos_theta`` and range ``range_m`` (1-D, one per ray), each
    carrying the fraction ``cell_fraction`` (per ray, or one number for all) of the pulse energy.
    ``extinction_per_m``: σ (a number: e^(−2σR)) or a :class:`~core.atmosphere.extinction.LayeredExtinction`
    (e^(−2τ(R)): e^(−2σ₀R) in the kernel times e^(−2 Σ α_i L_i(R)) of the layers)."""
    cos_theta = np.asarray(cos_theta, dtype=np.float64)
    range_m = np.asarray(range_m, dtype=np.float64)
    fraction = np.asarray(cell_fraction, dtype=np.float64)
    step = 1 if fraction.ndim else 0
    fraction = fraction.reshape(-1)
    if step and fraction.shape != cos_theta.shape or range_m.shape != cos_theta.shape:
        raise ValueError("cos_theta, range_m and cell_fraction need one value per ray")
    table = material_table(materials)
    ids = np.asarray(material_ids)
    if ids.shape != cos_theta.shape:
        raise ValueError("material_ids needs one value per ray")
    out = np.empty(cos_theta.shape[0])
    layered = isinstance(extinction_per_m, LayeredExtinction)
    sigma = extinction_per_m.base_per_m if layered else extinction_per_m
    bad_material(_received_energy(*energy_terms(laser, receiver, sigma), *table, ids, cos_theta, range_m, fraction,
                                  step, out),
                 ids, len(materials))
    if layered:
        out *= np.exp(-2.0 * extinction_per_m.layer_depth(range_m))
    return out
