"""Echo detection on noisy (digital) waveforms, physics.md §9.

Per pixel: robust baseline and noise (median, 1.4826 × median absolute deviation) estimated from the
waveform itself; optional matched filter (correlation with the pulse shape, normalised so that a pulse of
amplitude A gives a filtered peak of A); fixed or noise-adaptive threshold (k σ); local maxima above the
threshold, taken greedily by amplitude with a minimum separation (multi-echo); 3-point sub-bin interpolation
(parabolic or Gaussian, the exact §9 formulas).  Vectorized over pixels; the only Python loop is over the
echo index (≤ max_echoes).  Bin j is centred at j + 0.5 bin widths after the gate opening (as in
``core/waveform.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

C_LIGHT_M_S = 299_792_458.0
#: σ of a normal distribution = MAD × this
MAD_TO_SIGMA = 1.482602218505602


# ----------------------------------------------------------------------------------------------------------
# §9 formulas
# ----------------------------------------------------------------------------------------------------------
def parabolic_offset(y_minus, y_0, y_plus):
    """Parabolic 3-point peak offset δ = (y₋ − y₊)/(2(y₋ − 2y₀ + y₊)) (physics.md §9).
    (0.4296, 0.9560, 0.7827) → 0.2523.  Returns NaN where the curvature is not negative."""
    ym, y0, yp = (np.asarray(a, dtype=np.float64) for a in (y_minus, y_0, y_plus))
    den = ym - 2.0 * y0 + yp
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den < 0, (ym - yp) / (2.0 * den), np.nan)


def gaussian_offset(y_minus, y_0, y_plus):
    """Gaussian 3-point peak offset: the parabolic formula on ln y (physics.md §9).
    (0.4296, 0.9560, 0.7827) → 0.3000 (exact for a sampled Gaussian).  NaN where a sample is ≤ 0."""
    ym, y0, yp = (np.asarray(a, dtype=np.float64) for a in (y_minus, y_0, y_plus))
    pos = (ym > 0) & (y0 > 0) & (yp > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lm, l0, lp = (np.log(np.where(pos, a, 1.0)) for a in (ym, y0, yp))
        return np.where(pos, parabolic_offset(lm, l0, lp), np.nan)


def parabolic_peak(y_minus, y_0, y_plus, delta):
    """Interpolated peak value of the parabola through the 3 samples at offset δ: y₀ − (y₋ − y₊)δ/4."""
    return np.asarray(y_0, dtype=np.float64) - 0.25 * (np.asarray(y_minus) - np.asarray(y_plus)) * delta


def gaussian_peak(y_minus, y_0, y_plus, delta):
    """Interpolated peak value of the Gaussian through the 3 (positive) samples at offset δ."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.exp(parabolic_peak(np.log(y_minus), np.log(y_0), np.log(y_plus), delta))


def cramer_rao_time_std(pulse_sigma_s, bin_width_s, snr_peak):
    """Cramér–Rao bound on the echo time for a Gaussian pulse in white noise (physics.md §9):
    σ_t = √(2 σ_p Δt/√π)/SNR_peak.  τ_FWHM 5 ns, Δt 1 ns, SNR 10 → 154.8 ps."""
    return np.sqrt(2.0 * pulse_sigma_s * bin_width_s / np.sqrt(np.pi)) / np.asarray(snr_peak, dtype=np.float64)


def cramer_rao_range_std(pulse_sigma_s, bin_width_s, snr_peak):
    """σ_R = c σ_t/2 (physics.md §9).  τ_FWHM 5 ns, Δt 1 ns, SNR 10 → 2.320 cm."""
    return 0.5 * C_LIGHT_M_S * cramer_rao_time_std(pulse_sigma_s, bin_width_s, snr_peak)


def photon_limited_range_std(pulse_sigma_s, n_photons):
    """Photon-limited range precision σ_R = (c/2) σ_p/√N (physics.md §9).  N = 100, 5 ns FWHM → 3.183 cm."""
    return 0.5 * C_LIGHT_M_S * pulse_sigma_s / np.sqrt(np.asarray(n_photons, dtype=np.float64))


def gaussian_pulse_kernel(fwhm_s, bin_width_s, half_width_sigmas=4.0):
    """Gaussian pulse shape sampled at bin centres (peak 1, odd length) for the matched filter."""
    sigma_bins = fwhm_s / (2.0 * np.sqrt(2.0 * np.log(2.0))) / bin_width_s
    h = max(1, int(np.ceil(half_width_sigmas * sigma_bins)))
    x = np.arange(-h, h + 1, dtype=np.float64)
    return np.exp(-0.5 * (x / sigma_bins) ** 2)


# ----------------------------------------------------------------------------------------------------------
# Noise estimation and matched filter
# ----------------------------------------------------------------------------------------------------------
def robust_baseline_noise(waveforms):
    """Per-pixel baseline (median) and noise σ = 1.4826 × median(|y − median|) along the last axis.
    Robust to the echoes themselves as long as they occupy well under half of the bins.  Where the MAD is 0
    (noise below one A/D count), σ is the rms deviation of the quietest 90 % of the samples."""
    y = np.asarray(waveforms, dtype=np.float32)
    base = np.median(y, axis=-1)
    dev = np.abs(y - base[..., None])
    sigma = np.median(dev, axis=-1).astype(np.float64) * MAD_TO_SIGMA
    flat = sigma == 0
    if flat.any():
        # A/D-quantized noise below one count: over half the samples equal the median and the MAD is 0.
        # Fall back to the rms deviation of the quietest 90 % of the samples (the echoes excluded).
        d = dev[flat].astype(np.float64)
        keep = d <= np.quantile(d, 0.9, axis=-1, keepdims=True)
        sigma[flat] = np.sqrt(np.sum(d * d * keep, axis=-1) / np.maximum(keep.sum(axis=-1), 1))
    return base.astype(np.float64), sigma


def matched_filter(waveforms, pulse):
    """Correlate each waveform (last axis) with the pulse shape, normalised by Σ pulse² so that A·pulse
    (centred on a bin) gives a filtered peak of exactly A.  White noise σ becomes σ/‖pulse‖."""
    k = np.asarray(pulse, dtype=np.float64)
    k = k / np.sum(k * k)
    y = np.asarray(waveforms, dtype=np.float32)
    return ndimage.correlate1d(y, k.astype(np.float32), axis=-1, mode="nearest")


# ----------------------------------------------------------------------------------------------------------
# Detection
# ----------------------------------------------------------------------------------------------------------
@dataclass
class NoisyEchoes:
    """Echoes per pixel, shape (..., max_echoes), ordered in time (index 0 first); undetected slots are NaN
    (times, ranges, amplitudes, SNR) and ``detected`` False."""

    time_s: np.ndarray        # float64 round-trip time of the echo
    range_m: np.ndarray       # float64 c t / 2
    position_bins: np.ndarray  # float64 position in bins from the gate opening (bin j centred at j + 0.5)
    amplitude: np.ndarray     # float64 interpolated peak above the baseline, input units
    snr: np.ndarray           # float64 amplitude / raw-waveform noise σ (peak SNR of §9)
    detected: np.ndarray      # bool
    n_echoes: np.ndarray      # (...,) int
    baseline: np.ndarray      # (...,) per-pixel baseline (median)
    noise_sigma: np.ndarray   # (...,) per-pixel raw noise σ (MAD)
    threshold: np.ndarray     # (...,) threshold used, in amplitude units above the baseline
    n_interp_fallback: int    # Gaussian interpolation fell back to parabolic (non-positive sample)


def detect_echoes_noisy(waveforms, bin_width_s, gate_start_s=0.0, *, threshold_mode="adaptive",
                        threshold=0.0, k_sigma=5.0, pulse=None, max_echoes=3, min_separation_bins=None,
                        interpolation="gaussian", noise_sigma=None, baseline=None):
    """Detect up to ``max_echoes`` echoes per pixel on noisy waveforms (physics.md §9).

    waveforms      : (..., B) digital counts or any real waveform.
    threshold_mode : "adaptive" (k_sigma × per-pixel noise σ of the detection waveform, estimated by MAD) or
                     "fixed" (``threshold`` in input units above the baseline).
    pulse          : pulse shape samples for the matched filter (None: no filter).
    min_separation_bins : smallest distance between two echoes of a pixel (default: pulse length or 3).
    interpolation  : "gaussian" (falls back to parabolic where a sample ≤ 0 — counted), "parabolic", "none".
    noise_sigma, baseline : known per-pixel values instead of the robust estimates.
    Edge bins 0 and B−1 are never peaks (no 3-point neighbourhood).
    """
    y = np.asarray(waveforms)
    shape = y.shape[:-1]
    B = y.shape[-1]
    y = y.reshape(-1, B)
    P = y.shape[0]
    if baseline is None or noise_sigma is None:
        b_est, s_est = robust_baseline_noise(y)
    base = (b_est if baseline is None else np.broadcast_to(np.asarray(baseline, np.float64), shape).reshape(-1))
    sig = (s_est if noise_sigma is None else np.broadcast_to(np.asarray(noise_sigma, np.float64),
                                                             shape).reshape(-1))
    yd = y.astype(np.float32) - base.astype(np.float32)[:, None]
    if pulse is not None:
        yd = matched_filter(yd, pulse)
        if noise_sigma is None:
            _, sig_det = robust_baseline_noise(yd)
        else:
            k = np.asarray(pulse, np.float64)
            sig_det = sig / np.sqrt(np.sum(k * k))
    else:
        sig_det = sig
    if min_separation_bins is None:
        min_separation_bins = max(3, len(pulse) // 2) if pulse is not None else 3
    if threshold_mode == "adaptive":
        thr = k_sigma * sig_det
    elif threshold_mode == "fixed":
        thr = np.full(P, float(threshold))
    else:
        raise ValueError(f"threshold_mode must be 'adaptive' or 'fixed', got {threshold_mode!r}")

    # local maxima above threshold (interior bins only)
    cand = np.full((P, B), -np.inf, dtype=np.float32)
    c = yd[:, 1:-1]
    is_peak = (c > yd[:, :-2]) & (c >= yd[:, 2:]) & (c > thr.astype(np.float32)[:, None])
    np.copyto(cand[:, 1:-1], c, where=is_peak)

    K = int(max_echoes)
    pos = np.full((P, K), -1, dtype=np.int64)
    rows = np.arange(P)
    idx = np.arange(B)
    for k in range(K):
        j = np.argmax(cand, axis=1)
        v = cand[rows, j]
        ok = np.isfinite(v)
        if not ok.any():
            break
        pos[ok, k] = j[ok]
        near = np.abs(idx[None, :] - j[:, None]) < min_separation_bins
        near &= ok[:, None]
        cand[near] = -np.inf

    detected = pos >= 0
    # time order within each pixel (undetected slots last)
    order = np.argsort(np.where(detected, pos, B + 1), axis=1, kind="stable")
    pos = np.take_along_axis(pos, order, axis=1)
    detected = pos >= 0
    jj = np.where(detected, pos, 1)
    r2 = rows[:, None]
    ym = yd[r2, jj - 1].astype(np.float64)
    y0 = yd[r2, jj].astype(np.float64)
    yp = yd[r2, jj + 1].astype(np.float64)
    n_fallback = 0
    if interpolation == "none":
        delta = np.zeros_like(y0)
        amp = y0
    elif interpolation in ("gaussian", "parabolic"):
        d_par = parabolic_offset(ym, y0, yp)
        d_par = np.where(np.isfinite(d_par), d_par, 0.0)  # flat top (y₋ = y₀ = y₊): centre of the bin
        a_par = parabolic_peak(ym, y0, yp, d_par)
        delta, amp = d_par, a_par
        if interpolation == "gaussian":
            d_g = gaussian_offset(ym, y0, yp)
            okg = np.isfinite(d_g)
            n_fallback = int(np.count_nonzero(detected & ~okg))
            with np.errstate(divide="ignore", invalid="ignore"):
                a_g = gaussian_peak(np.where(okg, ym, 1.0), np.where(okg, y0, 1.0), np.where(okg, yp, 1.0),
                                    np.where(okg, d_g, 0.0))
            delta = np.where(okg, d_g, d_par)
            amp = np.where(okg, a_g, a_par)
    else:
        raise ValueError(f"interpolation must be 'gaussian', 'parabolic' or 'none', got {interpolation!r}")

    position = np.where(detected, jj + 0.5 + delta, np.nan)
    t = gate_start_s + position * bin_width_s
    amp = np.where(detected, amp, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = amp / sig[:, None]
    out_shape = shape + (K,)
    return NoisyEchoes(time_s=t.reshape(out_shape), range_m=(0.5 * C_LIGHT_M_S * t).reshape(out_shape),
                       position_bins=position.reshape(out_shape), amplitude=amp.reshape(out_shape),
                       snr=snr.reshape(out_shape), detected=detected.reshape(out_shape),
                       n_echoes=detected.sum(axis=1).reshape(shape), baseline=base.reshape(shape),
                       noise_sigma=sig.reshape(shape), threshold=thr.reshape(shape),
                       n_interp_fallback=n_fallback)


def score_echoes(echoes: NoisyEchoes, true_range_m, tolerance_m):
    """Match detections to true echo ranges (..., Kt) (NaN = no echo) within ``tolerance_m``.

    Returns a dict: ``true_positives``, ``false_alarms`` (detections matching no true echo), ``missed`` (true
    echoes with no detection) and ``false_alarm_mask`` (..., max_echoes).  Vectorized (loops over echo slots).
    """
    det_r = echoes.range_m
    tr = np.asarray(true_range_m, dtype=np.float64)
    if tr.ndim == det_r.ndim - 1:
        tr = tr[..., None]
    tr = np.broadcast_to(tr, det_r.shape[:-1] + tr.shape[-1:])
    with np.errstate(invalid="ignore"):
        dist = np.abs(det_r[..., :, None] - tr[..., None, :])  # (..., K, Kt)
    close = dist <= tolerance_m
    close &= echoes.detected[..., :, None]
    det_matched = close.any(axis=-1)
    true_found = close.any(axis=-2)
    fa = echoes.detected & ~det_matched
    return {"true_positives": int(np.count_nonzero(det_matched)),
            "false_alarms": int(np.count_nonzero(fa)),
            "missed": int(np.count_nonzero(np.isfinite(tr) & ~true_found)),
            "false_alarm_mask": fa}
