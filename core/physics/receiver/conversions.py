"""Elementary detector conversions (docs/theory.md §8): photons per joule, electrons, excess noise, A/D step,
moments and SNR of a linear detector.  Pure and vectorized."""
from __future__ import annotations

import math

import numpy as np

from ...config.settings import DetectorSettings
from ...constants import H_PLANCK_J_S, Q_ELECTRON_C, SPEED_OF_LIGHT_M_S


def photons_per_joule(wavelength_m):
    """Photons per joule, λ/(hc) (docs/theory.md §8).  1 fJ = 2678 / 5356 / 7803 photons at 532/1064/1550 nm."""
    return np.asarray(wavelength_m, dtype=np.float64) / (H_PLANCK_J_S * SPEED_OF_LIGHT_M_S)


def energy_to_photons(energy_j, wavelength_m, quantum_efficiency=1.0):
    """Mean photo-electrons N = η E λ/(hc) (docs/theory.md §8)."""
    return np.asarray(energy_j, dtype=np.float64) * photons_per_joule(wavelength_m) * quantum_efficiency


def current_to_electrons(current_a, time_s):
    """Mean electrons I τ / q delivered by a current during τ (dark current, docs/theory.md §8)."""
    return np.asarray(current_a, dtype=np.float64) * np.asarray(time_s, dtype=np.float64) / Q_ELECTRON_C


def background_photons(rate_photons_per_s, bin_width_s):
    """Mean background (solar) photons per bin: constant rate × bin width (docs/theory.md §8)."""
    return np.asarray(rate_photons_per_s, dtype=np.float64) * bin_width_s


def mcintyre_excess_noise(gain, k_eff):
    """McIntyre excess noise factor F = k G + (1 − k)(2 − 1/G) (docs/theory.md §8).  G = 100, k = 0.02 → 3.950."""
    g = np.asarray(gain, dtype=np.float64)
    return k_eff * g + (1.0 - k_eff) * (2.0 - 1.0 / g)


def adc_step_e(bits, full_scale_e):
    """A/D quantization step Δ in electrons: full scale / 2**bits (docs/theory.md §8)."""
    return float(full_scale_e) / float(2 ** int(bits))


def linear_detector_moments(n_signal_e, n_background_e=0.0, gain=1.0, excess_noise=1.0,
                            bulk_dark_e=0.0, surface_dark_e=0.0, read_noise_e=0.0, adc_step=0.0):
    """Mean and variance (electrons²) of one bin at the A/D output, in electrons (docs/theory.md §8).

    mean = G (N_s + N_b + N_db) + N_ds;  var = G² F (N_s + N_b + N_db) + N_ds + σ_read² + Δ²/12.
    ``n_*`` are primary photo-electrons (after η); the A/D offset is not included.
    """
    n_mult = np.asarray(n_signal_e, dtype=np.float64) + n_background_e + bulk_dark_e
    mean = gain * n_mult + surface_dark_e
    var = gain ** 2 * excess_noise * n_mult + surface_dark_e + read_noise_e ** 2 + adc_step ** 2 / 12.0
    return mean, var


def snr_linear(energy_j, wavelength_m, quantum_efficiency, gain, k_eff, dark_current_bulk_a,
               dark_current_surface_a, integration_time_s, n_background_e, read_noise_e, adc_step=0.0):
    """Linear-mode (PIN: G = 1, k = 0 → F = 1; APD) SNR of docs/theory.md §8:

    SNR = G N_s / √[G² F (N_s + N_b + I_db τ/q) + I_ds τ/q + σ_read² + Δ²/12].
    Test: η 0.4, G 100, k 0.02, 1 pA, 1 nA, 10 ns, N_b 2, 300 e⁻, Δ 500 e⁻ → 2.102 / 7.282 / 23.26 at
    1e-17 / 1e-16 / 1e-15 J (1064 nm).
    """
    n_s = energy_to_photons(energy_j, wavelength_m, quantum_efficiency)
    f = mcintyre_excess_noise(gain, k_eff)
    _, var = linear_detector_moments(n_s, n_background_e, gain, f,
                                     current_to_electrons(dark_current_bulk_a, integration_time_s),
                                     current_to_electrons(dark_current_surface_a, integration_time_s),
                                     read_noise_e, adc_step)
    return gain * n_s / np.sqrt(var)


def background_rate(det: DetectorSettings, pixel_rate=None):
    """Background photon rate per pixel at the detector, before η (photons/s): the detector's fixed
    ``background_rate_photons_per_s`` plus ``pixel_rate`` (an array, one value per pixel: the sunlight the scene
    reflects into each pixel, core/physics/solar.py) when given; a number without it."""
    if pixel_rate is None:
        return det.background_rate_photons_per_s
    return det.background_rate_photons_per_s + np.asarray(pixel_rate, dtype=np.float64)


def bin_moments(det: DetectorSettings, n_signal_e, bin_width_s, pixel_rate=None):
    """Mean and variance [electrons] of one bin at the A/D output for ``n_signal_e`` mean signal photo-electrons
    (after η) with the switches exactly as :func:`apply_receiver_chain` uses them (PIN/APD, linear mode):

        shot noise on : mean = G(N_s + N_b + N_db) + N_ds,  var = G²F(N_s + N_b + N_db) + N_ds + G²N_s²/M + σ² + Δ²/12
        shot noise off: mean the same,                       var = G²(F − 1)(N_s + N_b + N_db) + G²N_s²/M + σ² + Δ²/12

    G = 1 for PIN; F = McIntyre F for an APD with excess noise on, else 1; N_b = η · background rate · Δt and
    N_db, N_ds = I Δt/q only when switched on; M the speckle degrees of freedom (term absent when 0); σ the read
    noise when on; Δ the A/D step when the A/D is on (docs/theory.md §7, §8).  The A/D offset is not included.
    ``pixel_rate``: the per-pixel background added to the detector's (:func:`background_rate`): N_b, the mean
    and the variance are then arrays, one value per pixel.
    Returns ``(mean, var, parts)`` with ``parts`` the terms used (gain, F, N_b, N_db, N_ds, σ, Δ, M)."""
    if det.detector_type == "geiger":
        raise ValueError("bin_moments: Geiger mode counts detections, not electrons")
    gain = det.apd_gain if det.detector_type == "apd" else 1.0
    F = float(mcintyre_excess_noise(gain, det.apd_k_eff)) if (det.detector_type == "apd"
                                                               and det.enable_excess_noise) else 1.0
    n_b = (background_photons(background_rate(det, pixel_rate), bin_width_s) * det.quantum_efficiency
           if det.enable_background else 0.0)
    n_b = float(n_b) if np.ndim(n_b) == 0 else n_b
    n_db = float(current_to_electrons(det.dark_current_bulk_a, bin_width_s)) if det.enable_dark_current else 0.0
    n_ds = float(current_to_electrons(det.dark_current_surface_a, bin_width_s)) if det.enable_dark_current else 0.0
    sigma_r = det.read_noise_e if det.enable_read_noise else 0.0
    step = adc_step_e(det.adc_bits, det.adc_full_scale_e) if det.enable_adc else 0.0
    M = det.speckle_dof
    n_s = np.asarray(n_signal_e, dtype=np.float64)
    n_mult = n_s + n_b + n_db
    mean = gain * n_mult + n_ds
    var = (gain * gain * F * n_mult + n_ds) if det.enable_shot_noise else gain * gain * (F - 1.0) * n_mult
    if M > 0:
        var = var + gain * gain * n_s * n_s / M
    var = var + sigma_r ** 2 + step ** 2 / 12.0
    parts = {"gain": gain, "excess_noise": F, "n_background_e": n_b, "n_dark_bulk_e": n_db, "n_dark_surface_e": n_ds,
             "read_noise_e": sigma_r, "adc_step_e": step, "speckle_dof": M}
    return mean, var, parts



def noise_sigma_floor(det: DetectorSettings, bin_width_s, pixel_rate=None):
    """The smallest noise σ echo detection may assume for a bin without signal, in output units (A/D counts,
    electrons without the A/D, detections in Geiger mode); never 0.

    Linear mode: the signal-free σ of :func:`bin_moments` with every term — shot noise on background and
    dark current, surface dark, read noise and the A/D's Δ²/12 (so ≥ 1/√12 count with the A/D: a waveform
    whose electronic noise is below one count has no usable MAD, and a zero σ would put the threshold at 0
    and every SNR at infinity).  Without the A/D and with every noise term off, the σ of one primary
    electron (G√F electrons), the signal's own granularity.  Geiger mode: integer detection counts over
    ``geiger_pulses`` pulses, √(λ + 1/12) with λ the expected noise detections per bin.
    ``pixel_rate``: per-pixel background (:func:`bin_moments`): one floor per pixel (an array)."""
    if det.detector_type == "geiger":
        noise = 0.0
        if det.enable_background:
            noise = noise + background_photons(background_rate(det, pixel_rate), bin_width_s) * \
                det.quantum_efficiency
        if det.enable_dark_current:
            noise = noise + float(current_to_electrons(det.dark_current_bulk_a + det.dark_current_surface_a,
                                                       bin_width_s))
        lam = det.geiger_pulses * -np.expm1(-np.asarray(noise, dtype=np.float64))
        floor = np.sqrt(lam + 1.0 / 12.0)
        return float(floor) if floor.ndim == 0 else floor
    _, var0, parts = bin_moments(det, 0.0, bin_width_s, pixel_rate)
    step = parts["adc_step_e"]
    var0 = np.asarray(var0, dtype=np.float64)
    floor = np.where(var0 > 0, np.sqrt(var0) / (step if step > 0 else 1.0),
                     parts["gain"] * math.sqrt(parts["excess_noise"]))
    return float(floor) if floor.ndim == 0 else floor
