"""Read-only derived figures shown in the panels (pure functions on core settings; no bpy).

Everything is SI in and out.  The panels call :func:`atmosphere_figures` / :func:`detector_figures` and show
:func:`atmosphere_lines` / :func:`detector_lines`; those never raise (a failure becomes one text line).
"""
from __future__ import annotations

import math

from ..core.atmosphere.extinction import extinction_from_visibility
from ..core.atmosphere.turbulence import derived_turbulence
from ..core.receiver import mcintyre_excess_noise, photons_per_joule, snr_linear

#: Wavelength used when there is no sensor (the core default laser, Nd:YAG).
DEFAULT_WAVELENGTH_M = 1.064e-6
#: Reflectance of the reference target of the SNR estimate (Lambertian).
REFERENCE_REFLECTANCE = 0.1


def extinction_per_m(atmosphere, wavelength_m: float) -> float:
    """One-way aerosol extinction σ [1/m] the simulator uses: from the visibility when it is > 0."""
    if atmosphere.visibility_m > 0.0:
        return float(extinction_from_visibility(atmosphere.visibility_m, wavelength_m,
                                                 atmosphere.visibility_model))
    return float(atmosphere.extinction_per_m)


def atmosphere_figures(atmosphere, wavelength_m: float, range_m: float) -> dict:
    """Extinction, two-way transmission at ``range_m`` and (when Cn² > 0) the spherical-wave turbulence figures
    of :func:`core.atmosphere.turbulence.derived_turbulence`."""
    sigma = extinction_per_m(atmosphere, wavelength_m)
    out = {"wavelength_m": float(wavelength_m), "range_m": float(range_m), "extinction_per_m": sigma,
           "extinction_per_km": sigma * 1e3, "two_way_transmission": math.exp(-2.0 * sigma * range_m)}
    if atmosphere.cn2_m_23 > 0.0:
        out["turbulence"] = derived_turbulence(atmosphere.cn2_m_23, wavelength_m, range_m, wave="spherical")
    return out


def received_pixel_energy_j(cfg, range_m: float, reflectance: float = REFERENCE_REFLECTANCE,
                            transmission: float = 1.0) -> float:
    """Energy one pixel receives from a Lambertian target of ``reflectance`` filling its footprint at
    ``range_m``, with the beam spread evenly over the field of view (pixel share = pulse energy / (W·H)):
    E = E_px T² (ρ/π) (π D²/4) / R² η_sys."""
    rx = cfg.receiver
    e_px = cfg.laser.pulse_energy_j / (rx.width_px * rx.height_px)
    area = math.pi * rx.aperture_diameter_m ** 2 / 4.0
    return e_px * transmission * reflectance / math.pi * area / range_m ** 2 * rx.system_efficiency


def detector_figures(cfg, range_m: float, transmission: float = 1.0,
                     reflectance: float = REFERENCE_REFLECTANCE) -> dict:
    """Photons per fJ, APD excess noise F, received energy and signal photo-electrons per pixel, and the linear
    mode SNR (physics.md §8; integration time = the pulse FWHM) for the reference target at ``range_m``."""
    det, lam = cfg.detector, cfg.laser.wavelength_m
    apd = det.detector_type == "apd"
    gain = det.apd_gain if apd else 1.0
    k_eff = det.apd_k_eff if apd else 0.0
    f = float(mcintyre_excess_noise(gain, k_eff)) if apd else 1.0
    energy = received_pixel_energy_j(cfg, range_m, reflectance, transmission)
    tau = cfg.laser.pulse_fwhm_s
    n_s = energy * float(photons_per_joule(lam)) * det.quantum_efficiency
    out = {"photons_per_fj": float(photons_per_joule(lam)) * 1e-15, "excess_noise_factor": f,
           "received_energy_j": energy, "signal_electrons": n_s, "integration_time_s": tau}
    if det.detector_type == "geiger":
        out["detection_probability"] = -math.expm1(-n_s)
        return out
    n_b = det.background_rate_photons_per_s * tau * det.quantum_efficiency if det.enable_background else 0.0
    dark = det.enable_dark_current
    adc_step = det.adc_full_scale_e / 2 ** det.adc_bits if det.enable_adc else 0.0
    out["snr"] = float(snr_linear(energy, lam, det.quantum_efficiency, gain, k_eff, det.dark_current_bulk_a if dark else 0.0,
                                  det.dark_current_surface_a if dark else 0.0, tau, n_b,
                                  det.read_noise_e if det.enable_read_noise else 0.0, adc_step))
    return out


def _km(x):
    return "∞" if x is None else f"{x:.4g}"


def atmosphere_lines(atmosphere, wavelength_m: float, range_m: float) -> list[str]:
    """Panel text lines for :func:`atmosphere_figures`; never raises."""
    try:
        fig = atmosphere_figures(atmosphere, wavelength_m, range_m)
    except Exception as exc:  # noqa: BLE001 - draw must never fail
        return [f"Derived figures unavailable: {exc}"]
    lines = [f"Extinction {fig['extinction_per_km']:.4g} /km at {wavelength_m * 1e9:.0f} nm",
             f"Two-way transmission {fig['two_way_transmission']:.4g} at {range_m:.4g} m"]
    t = fig.get("turbulence")
    if t:
        lines += [f"Rytov variance σ_R² {t['rytov_variance_plane']:.4g} (spherical β0² "
                  f"{t['rytov_variance_spherical']:.4g}), {t['regime']}",
                  f"ρ0 {_km(t['rho0_spherical_m'])} m, r0 {_km(t['r0_spherical_m'])} m (spherical)",
                  f"Cell radius (eq. 3-6) {t['cell_radius_m']:.4g} m",
                  f"σ_lnI² {t['sigma2_lnI']:.4g}, scintillation index {t['scintillation_index']:.4g}"]
    return lines


def detector_lines(cfg, range_m: float, transmission: float = 1.0) -> list[str]:
    """Panel text lines for :func:`detector_figures`; never raises."""
    try:
        fig = detector_figures(cfg, range_m, transmission)
    except Exception as exc:  # noqa: BLE001 - draw must never fail
        return [f"Derived figures unavailable: {exc}"]
    lines = [f"{fig['photons_per_fj']:.4g} photons per fJ at {cfg.laser.wavelength_m * 1e9:.0f} nm"]
    if cfg.detector.detector_type == "apd":
        lines.append(f"APD excess noise factor F {fig['excess_noise_factor']:.4g}")
    target = f"10 % Lambertian at {range_m:.4g} m, beam filling the FOV"
    lines.append(f"Signal {fig['signal_electrons']:.4g} e⁻/pixel ({target})")
    if "snr" in fig:
        lines.append(f"SNR {fig['snr']:.4g} per pixel (pulse energy / pixels, τ = pulse FWHM)")
    else:
        lines.append(f"Detection probability {fig['detection_probability']:.3g} per pulse")
    return lines
