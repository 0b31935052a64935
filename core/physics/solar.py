"""Sunlight reflected by the scene into the receiver: a background photon rate per pixel (docs/theory.md §8).

A surface lit by the sun (spectral irradiance E_λ on a plane facing it, direction ŝ towards the sun) has, in the
receiver's filter band Δλ, the radiance towards the sensor

    L = f_r · E_λ Δλ · cos θ_s            (θ_s: between the surface normal and ŝ; 0 when the surface is in shadow)

and a sub-ray of a pixel that sees it over the solid angle ω brings the detector

    Φ = L · A_r · ω · τ · exp(−α R) / (h ν)       photons per second

(A_r = π D²/4 the receiver aperture, τ the optical efficiency η_sys, α the one-way extinction at the laser
wavelength over the sensor–surface range R — with aerosol layers exp(−τ(R)), their optical depth —, hν = hc/λ).  The sun's own path through the atmosphere is part of
E_λ (the irradiance *at the scene*).  ω is the sub-ray's share of the pixel's solid angle: the pixel's
tan-space cell p_x p_y over its N sub-rays at the sub-ray's own direction, p_x p_y / N / (1 + x² + y²)^(3/2).
Rays that miss the scene (sky) add nothing: the sky's own radiance is not modelled.

f_r: the material's BRDF as the signal uses it (core/physics/brdf.py), which is monostatic (a function of one
angle); the sun → surface → sensor geometry is bistatic, and the BRDF is evaluated at the half-angle: the angle
between the normal and the bisector of ŝ and the direction to the sensor (the microfacet reading of the specular
lobe; exact for a Lambertian surface, ρ/π at every angle, and the monostatic value when the sun is behind the
sensor).  Whether the surface is lit: it faces the sun (cos θ_s > 0 on the side the sensor sees) and a shadow
ray from the hit towards the sun (Embree) meets nothing.
"""
from __future__ import annotations

import math

import numpy as np

from ..atmosphere.extinction import log_two_way_transmission
from .brdf import evaluate_materials
from .receiver.conversions import photons_per_joule

#: Shadow rays start this far off the surface (along its normal, on the side the sensor sees) plus
#: SHADOW_OFFSET_REL × the hit's distance from the traced geometry's centre: Embree traces in float32 about that
#: centre, whose step there is 6e-8 of the distance, so the ray never finds the surface it leaves.
SHADOW_OFFSET_M = 1e-4
SHADOW_OFFSET_REL = 1e-5


def solar_enabled(config) -> bool:
    """True when sunlight reflected by the scene is modelled (atmosphere.solar_irradiance_w_m2_nm > 0)."""
    return config.atmosphere.solar_irradiance_w_m2_nm > 0.0


def sun_direction(atmosphere) -> np.ndarray:
    """Unit vector towards the sun in the world frame (+Z up): elevation above XY, azimuth from +X towards +Y."""
    el, az = atmosphere.sun_elevation_rad, atmosphere.sun_azimuth_rad
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def radiance_to_rate(config) -> float:
    """E_λ Δλ A_r τ / (hν) (photons s⁻¹ sr⁻¹ per unit f_r cos θ_s): the factors common to every sub-ray (the
    extinction is applied per ray by :func:`subray_solar_rates`)."""
    rx, atm = config.receiver, config.atmosphere
    e_band = atm.solar_irradiance_w_m2_nm * (rx.filter_bandwidth_m * 1e9)  # W/m² in the filter band
    area = math.pi * (0.5 * rx.aperture_diameter_m) ** 2
    return float(e_band * area * rx.system_efficiency * photons_per_joule(config.laser.wavelength_m))


def tan_cell_solid_angles(x_tan, y_tan, pixel_pitch_tan, rays_in_pixel):
    """ω (sr) of each sub-ray of a pixel sampled over its tan-space cell (flash, profiler, gated viewing):
    p_x p_y / N / (1 + x² + y²)^(3/2), ``rays_in_pixel`` the number N of sub-rays of each ray's pixel."""
    x, y = np.asarray(x_tan, np.float64), np.asarray(y_tan, np.float64)
    return pixel_pitch_tan[0] * pixel_pitch_tan[1] / np.asarray(rays_in_pixel, np.float64) \
        / (1.0 + x * x + y * y) ** 1.5


def beam_solid_angle(laser) -> float:
    """Ω (sr) a scanner's receiver sees for one pulse: the cone (elliptical: both axes) of the beam's full 1/e²
    divergence, π θ_x θ_y / 4 (small angles), shared equally by the pulse's sub-rays."""
    theta_x = laser.beam_divergence_rad
    theta_y = laser.beam_divergence_y_rad or theta_x
    return math.pi * theta_x * theta_y / 4.0


def subray_solar_rates(config, extinction_per_m, materials, material_ids, normal, to_surface, range_m, lit, omega):
    """Φ (photons/s) per sub-ray hit (module docstring).  ``normal`` (n, 3) unit normals of the hit triangles
    (either side), ``to_surface`` (n, 3) unit directions sensor → hit, ``range_m`` (n,), ``lit`` (n,) bool (the
    shadow ray found nothing), ``omega`` (n,) or one number: each sub-ray's solid angle (sr)."""
    v = -np.asarray(to_surface, np.float64)  # towards the sensor
    s = sun_direction(config.atmosphere)
    n_f = seen_normal(normal, to_surface)
    cos_s = n_f @ s
    h = v + s
    h /= np.maximum(np.linalg.norm(h, axis=1), 1e-300)[:, None]
    cos_h = np.clip(np.einsum("ij,ij->i", n_f, h), 0.0, 1.0)
    f_r = evaluate_materials(materials, np.asarray(material_ids), cos_h)
    rate = radiance_to_rate(config) * f_r * np.maximum(cos_s, 0.0) * np.asarray(omega, np.float64)
    # one way: exp(−τ(R)), τ = αR or, with aerosol layers, their optical depth (half the two-way log: exact)
    rate *= np.exp(0.5 * log_two_way_transmission(extinction_per_m, np.asarray(range_m, np.float64)))
    return np.where(np.asarray(lit, bool) & (cos_s > 0.0), rate, 0.0)


def seen_normal(normal, to_surface):
    """(n, 3) the unit normals ``normal`` turned to the side the sensor sees (``to_surface``: sensor → hit)."""
    normal = np.asarray(normal, np.float64)
    side = np.where(np.einsum("ij,ij->i", normal, -np.asarray(to_surface, np.float64)) >= 0.0, 1.0, -1.0)
    return normal * side[:, None]


def lit_by_sun(tracer, points, normal, to_surface, sun):
    """(n,) bool: the hits ``points`` (world) see the sun — they face it on the side the sensor sees
    (``to_surface`` the sensor → hit directions) and a shadow ray from just off the surface towards ``sun`` meets
    no triangle of ``tracer`` (traced for the facing hits only)."""
    lit = np.zeros(len(points), bool)
    if len(points) == 0:
        return lit
    n_f = seen_normal(normal, to_surface)
    facing = np.flatnonzero(n_f @ sun > 0.0)
    if len(facing):
        p = np.asarray(points, np.float64)[facing]
        off = SHADOW_OFFSET_M + SHADOW_OFFSET_REL * np.linalg.norm(p - tracer.reference_m, axis=1)
        start = p + n_f[facing] * off[:, None]
        prim, _, _ = tracer.intersect(start, np.broadcast_to(sun, start.shape))
        lit[facing] = prim < 0
    return lit


def pixel_solar_rates(config, extinction_per_m, tracer, materials, material_ids, origin, directions, prim,
                      range_m, index, pixel_local, omega, n_pixels):
    """Solar background rate (photons/s, before η) per pixel (flash) or pulse (scanner) of a block of
    ``n_pixels``: the sum of :func:`subray_solar_rates` over its sub-rays.  ``origin`` (3,) or one per ray (all
    rays, world), ``directions``/``prim``/``range_m`` (all rays), ``index`` the hit rays, ``pixel_local`` their
    pixel in the block, ``omega`` their solid angles (sr; one number: all the same)."""
    out = np.zeros(n_pixels)
    if not len(index) or config.atmosphere.sun_elevation_rad <= 0.0:
        return out
    origin = np.asarray(origin, np.float64)
    d = np.asarray(directions, np.float64)[index]
    r = np.asarray(range_m)[index]
    nrm = tracer.unit_normal[np.asarray(prim)[index]]
    sun = sun_direction(config.atmosphere)
    lit = lit_by_sun(tracer, (origin if origin.ndim == 1 else origin[index]) + d * r[:, None], nrm, d, sun)
    rate = subray_solar_rates(config, extinction_per_m, materials, material_ids, nrm, d, r, lit, omega)
    return np.bincount(pixel_local, weights=rate, minlength=n_pixels)
