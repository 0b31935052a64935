"""Monostatic BRDF models (paper §3.3, eq. 3-3; physics.md §10)."""
from __future__ import annotations

import numpy as np

from .config import BRDFSettings


def steinvall_brdf(cos_theta, specular_a, slope_s, diffuse_b, diffuse_m):
    """Steinvall (2000) monostatic BRDF, paper eq. 3-3, in 1/sr.

    f_r(θ) = A cos⁻⁶θ exp(−tan²θ/s²) + B cosᵐθ.

    The specular term is evaluated as A·exp(−tan²θ/s² − 6 ln cosθ) (physics.md §10) with cosθ clamped to
    [1e-150, 1], so grazing incidence gives a finite value (→ 0 for the specular lobe) instead of 0·∞.
    """
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 1e-150, 1.0)
    c2 = c * c
    tan2 = np.maximum((1.0 - c2) / c2, 0.0)
    with np.errstate(over="ignore"):
        exponent = -tan2 / (slope_s * slope_s) - 6.0 * np.log(c)
    specular = specular_a * np.exp(np.minimum(exponent, 700.0)) if specular_a else np.zeros_like(c)
    diffuse = diffuse_b * c ** diffuse_m
    return specular + diffuse


def lambertian_brdf(cos_theta, reflectance):
    """Lambertian BRDF f_r = ρ_d/π (1/sr), independent of angle (physics.md §10)."""
    return np.full(np.shape(cos_theta), reflectance / np.pi, dtype=np.float64)


def evaluate_brdf(brdf: BRDFSettings, cos_theta):
    """f_r(θ) for one material's settings."""
    if brdf.model == "lambertian":
        return lambertian_brdf(cos_theta, brdf.reflectance)
    return steinvall_brdf(cos_theta, brdf.specular_a, brdf.slope_s, brdf.diffuse_b, brdf.diffuse_m)


def evaluate_materials(materials, material_ids, cos_theta):
    """f_r per ray for rays hitting triangles of the given material indices (vectorized per material)."""
    out = np.zeros(np.shape(cos_theta), dtype=np.float64)
    for index in np.unique(material_ids):
        sel = material_ids == index
        out[sel] = evaluate_brdf(materials[int(index)], cos_theta[sel])
    return out


def directional_hemispherical_reflectance(brdf: BRDFSettings) -> float:
    """ρ_DH(0) at normal incidence (physics.md §10): 4πs²A(1 − e^(−1/s²)) + 4πB/(m + 4) (Steinvall), ρ_d
    (Lambertian).  A physically plausible material has ρ_DH ≤ 1."""
    if brdf.model == "lambertian":
        return brdf.reflectance
    s2 = brdf.slope_s ** 2
    return 4 * np.pi * s2 * brdf.specular_a * (1 - np.exp(-1 / s2)) + 4 * np.pi * brdf.diffuse_b / (
        brdf.diffuse_m + 4)
