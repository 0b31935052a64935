"""Read-only derived figures shown in the panels (pure functions on core settings; no bpy).

Everything is SI in and out.  The panels call :func:`atmosphere_figures` / :func:`detector_figures` and show
:func:`atmosphere_lines` / :func:`detector_lines`; those never raise (a failure becomes one text line).
"""
from __future__ import annotations

import math

from ..core.atmosphere.extinction import extinction_from_visibility, two_way_transmission
from ..core.atmosphere.derived import derived_turbulence
from ..core.physics.laser import pulse_cdf
from ..core.physics.propagation import with_aerosol_layers
from ..core.physics.receiver.conversions import (adc_step_e, background_photons, bin_moments, current_to_electrons,
                                                 mcintyre_excess_noise, photons_per_joule)

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
    """Extinction, two-way transmission at ``range_m`` (through the aerosol layers too) and (when Cn² > 0) the spherical-wave turbulence figures
    of :func:`core.atmosphere.derived.derived_turbulence`."""
    sigma = extinction_per_m(atmosphere, wavelength_m)
    path = with_aerosol_layers(sigma, atmosphere)  # with atmosphere.aerosol_layers: exp(−2τ(R)), τ with the layers
    out = {"wavelength_m": float(wavelength_m), "range_m": float(range_m), "extinction_per_m": sigma,
           "extinction_per_km": sigma * 1e3,
           "two_way_transmission": (math.exp(-2.0 * sigma * range_m) if path is sigma
                                    else float(two_way_transmission(path, range_m)))}
    if atmosphere.cn2_m_23 > 0.0:
        out["turbulence"] = derived_turbulence(
            atmosphere.cn2_m_23, wavelength_m, range_m, wave="spherical",
            statistics=atmosphere.scintillation_statistics, inner_scale_m=atmosphere.inner_scale_m,
            outer_scale_m=atmosphere.outer_scale_m if atmosphere.outer_scale_m > 0.0 else math.inf)
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


def peak_bin_fraction(laser, bin_width_s: float) -> float:
    """Fraction of the pulse energy in the time bin the pulse is centred on: P(Δt/2) − P(−Δt/2)."""
    return float(pulse_cdf(laser, 0.5 * bin_width_s) - pulse_cdf(laser, -0.5 * bin_width_s))


def detector_snr(cfg, peak_bin_energy_j: float) -> dict:
    """Peak-bin figures of the linear-mode receiver for ``peak_bin_energy_j`` of signal in one bin, with every
    switch exactly as the chain applies it (:func:`core.physics.receiver.bin_moments`, docs/theory.md §7, §8):

        SNR = G N_s / √var(N_s),  var = G²F(N_s + N_b + N_db) + N_ds + G²N_s²/M + σ_read² + Δ²/12  (shot noise on)

    with τ = the bin width (the chain's integration time per sample), the signal clipped at the A/D full scale.
    Returns signal electrons, mean/σ of a signal-free bin (the noise floor) in electrons and counts, the SNR and
    whether the A/D saturates.  Ideal mode: no noise (σ 0, SNR ∞)."""
    det = cfg.detector
    tau = cfg.gate.bin_width_s
    n_s = peak_bin_energy_j * float(photons_per_joule(cfg.laser.wavelength_m)) * det.quantum_efficiency
    out = {"peak_signal_electrons": n_s, "bin_width_s": tau}
    if det.mode == "ideal":
        out.update(ideal=True, snr=math.inf, noise_floor_e=0.0, noise_floor_counts=0.0, adc_saturated=False)
        return out
    mean0, var0, parts = bin_moments(det, 0.0, tau)
    mean_s, var_s, _ = bin_moments(det, n_s, tau)
    signal_e = float(mean_s - mean0)  # G N_s
    out.update(ideal=False, gain=parts["gain"], excess_noise_factor=parts["excess_noise"],
               noise_floor_e=math.sqrt(float(var0)), noise_mean_e=float(mean0), adc_saturated=False)
    if det.enable_adc:
        step = adc_step_e(det.adc_bits, det.adc_full_scale_e)
        top_e = (2 ** int(det.adc_bits) - 1 - det.adc_offset_counts) * step  # electrons at the top code
        out["noise_floor_counts"] = out["noise_floor_e"] / step
        if float(mean_s) > top_e:  # §8: clip at the A/D full scale
            out["adc_saturated"] = True
            signal_e = max(top_e - float(mean0), 0.0)
    out["snr"] = signal_e / math.sqrt(float(var_s)) if var_s > 0 else math.inf
    return out


def detector_figures(cfg, range_m: float, transmission: float = 1.0,
                     reflectance: float = REFERENCE_REFLECTANCE) -> dict:
    """Photons per fJ, APD excess noise F (1 when switched off), received energy and signal photo-electrons per
    pixel and in the peak time bin, the noise floor and the peak-bin SNR (:func:`detector_snr`) for the
    reference target at ``range_m``; Geiger mode: the detection probability per pulse (with speckle) and the
    noise primaries per bin.  Every figure follows the detector's switches as the chain does."""
    det, lam = cfg.detector, cfg.laser.wavelength_m
    energy = received_pixel_energy_j(cfg, range_m, reflectance, transmission)
    n_s = energy * float(photons_per_joule(lam)) * det.quantum_efficiency
    frac = peak_bin_fraction(cfg.laser, cfg.gate.bin_width_s)
    apd_f = det.detector_type == "apd" and det.enable_excess_noise
    out = {"photons_per_fj": float(photons_per_joule(lam)) * 1e-15,
           "excess_noise_factor": float(mcintyre_excess_noise(det.apd_gain, det.apd_k_eff)) if apd_f else 1.0,
           "received_energy_j": energy, "signal_electrons": n_s, "peak_bin_fraction": frac}
    if det.detector_type == "geiger":
        m = det.speckle_dof
        out["detection_probability"] = (-math.expm1(-m * math.log1p(n_s / m)) if m > 0 else -math.expm1(-n_s))
        tau = cfg.gate.bin_width_s
        noise = 0.0
        if det.enable_background:
            noise += float(background_photons(det.background_rate_photons_per_s, tau)) * det.quantum_efficiency
        if det.enable_dark_current:
            noise += float(current_to_electrons(det.dark_current_bulk_a + det.dark_current_surface_a, tau))
        out["noise_primaries_per_bin"] = noise
        out["ideal"] = det.mode == "ideal"
        return out
    out.update(detector_snr(cfg, energy * frac))
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
             f"Two-way transmission {fig['two_way_transmission']:.4g} at {range_m:.4g} m"
             + (" (aerosol layers included)" if atmosphere.aerosol_layers else "")]
    t = fig.get("turbulence")
    if t:
        lines += [f"Rytov variance σ_R² {t['rytov_variance_plane']:.4g} (spherical β0² "
                  f"{t['rytov_variance_spherical']:.4g}), {t['regime']}",
                  f"ρ0 {_km(t['rho0_spherical_m'])} m, r0 {_km(t['r0_spherical_m'])} m (spherical)",
                  (f"Cell radius (eq. 3-6) {t['cell_radius_m']:.4g} m" if t["scintillation_statistics"] == "paper"
                   else f"Cell radius (wave-optics 1/e) {t['cell_radius_m']:.4g} m"),
                  f"σ_lnI² {t['sigma2_lnI']:.4g}, scintillation index {t['scintillation_index']:.4g} "
                  f"({t['scintillation_statistics'].replace('_', ' ')})"]
    return lines


#: Layers the Atmosphere panel lists one by one (the summary line counts them all).
PREVIEW_LAYERS = 4


def aerosol_layer_lines(atmosphere) -> list[str]:
    """What the Atmosphere panel shows of ``atmosphere.aerosol_layers`` (set by a config file or preset, kept on
    the scene): a count and the first layers in the panel's units (range in m, extinction α in 1/km as the
    Extinction field, backscatter β in 1/(m sr), "α/S" when the row has no β column), or the validation error;
    never raises."""
    from ..core.config.tables import aerosol_layer_table

    rows = atmosphere.aerosol_layers
    if isinstance(rows, (list, tuple)) and not rows:
        return ["No aerosol layers (homogeneous atmosphere)"]
    try:
        table = aerosol_layer_table(atmosphere)
    except Exception as exc:  # noqa: BLE001 - draw must never fail
        return [f"Aerosol layers: error: {exc}"]
    n = len(table)
    lines = [f"{n} aerosol layer{'s' if n != 1 else ''} (from a config file or preset)"]
    for row, (start, end, alpha, beta) in zip(rows, table[:PREVIEW_LAYERS]):
        b = (f"β {beta:.4g} /(m sr)" if len(row) > 3
             else f"β = α/S = {beta:.4g} /(m sr)")
        lines.append(f"  {start:.4g}–{end:.4g} m: α {alpha * 1e3:.4g} /km, {b}")
    if n > PREVIEW_LAYERS:
        lines.append(f"  … {n - PREVIEW_LAYERS} more")
    return lines


def detector_lines(cfg, range_m: float, transmission: float = 1.0) -> list[str]:
    """Panel text lines for :func:`detector_figures`; never raises."""
    try:
        fig = detector_figures(cfg, range_m, transmission)
    except Exception as exc:  # noqa: BLE001 - draw must never fail
        return [f"Derived figures unavailable: {exc}"]
    det = cfg.detector
    lines = [f"{fig['photons_per_fj']:.4g} photons per fJ at {cfg.laser.wavelength_m * 1e9:.0f} nm"]
    if det.detector_type == "apd":
        lines.append(f"APD gain {det.apd_gain:.4g}, excess noise factor F {fig['excess_noise_factor']:.4g}"
                     + ("" if det.enable_excess_noise else " (excess noise off)"))
    target = f"10 % Lambertian at {range_m:.4g} m, beam filling the FOV"
    lines.append(f"Signal {fig['signal_electrons']:.4g} e⁻/pixel ({target})")
    if det.detector_type == "geiger":
        lines.append(f"Detection probability {fig['detection_probability']:.3g} per pulse"
                     + (f" (speckle M = {det.speckle_dof:.3g})" if det.speckle_dof > 0 else ""))
        lines.append(f"Noise {fig['noise_primaries_per_bin']:.3g} primaries per bin")
        return lines
    lines.append(f"Peak bin {fig['peak_signal_electrons']:.4g} e⁻ ({fig['peak_bin_fraction'] * 100:.3g} % of the pulse "
                 f"in {cfg.gate.bin_width_s * 1e9:.3g} ns)")
    if fig["ideal"]:
        lines.append("Ideal receiver (mode = ideal): noise-free, SNR unbounded")
        return lines
    floor = f"Noise floor {fig['noise_floor_e']:.4g} e⁻ rms per bin"
    if "noise_floor_counts" in fig:
        floor += f" ({fig['noise_floor_counts']:.3g} counts)"
    lines.append(floor)
    lines.append(f"SNR {fig['snr']:.4g} in the peak bin" + (" — A/D saturates" if fig["adc_saturated"] else ""))
    return lines
