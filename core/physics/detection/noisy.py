"""Echo detection on noisy (digital) waveforms, docs/theory.md §9.

Per pixel: robust baseline and noise (median, 1.4826 × median absolute deviation) estimated from the
waveform itself; optional matched filter (correlation with the pulse shape, normalised so that a pulse of
amplitude A gives a filtered peak of A); fixed or noise-adaptive threshold (k σ); local maxima above the
threshold, taken greedily by amplitude with a minimum separation (multi-echo); 3-point sub-bin interpolation
(parabolic or Gaussian, the exact §9 formulas).  Vectorized over pixels; the only Python loop is over the
echo index (≤ max_echoes).  Bin j is centred at j + 0.5 bin widths after the gate opening (as in
``core/physics/waveform.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ...constants import SPEED_OF_LIGHT_M_S
from scipy import ndimage

#: σ of a normal distribution = MAD × this
MAD_TO_SIGMA = 1.482602218505602


# ----------------------------------------------------------------------------------------------------------
# §9 formulas
# ----------------------------------------------------------------------------------------------------------
def parabolic_offset(y_minus, y_0, y_plus):
    """Parabolic 3-point peak offset δ = (y₋ − y₊)/(2(y₋ − 2y₀ + y₊)) (docs/theory.md §9).
    (0.4296, 0.9560, 0.7827) → 0.2523.  Returns NaN where the curvature is not negative."""
    ym, y0, yp = (np.asarray(a, dtype=np.float64) for a in (y_minus, y_0, y_plus))
    den = ym - 2.0 * y0 + yp
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den < 0, (ym - yp) / (2.0 * den), np.nan)


def gaussian_offset(y_minus, y_0, y_plus):
    """Gaussian 3-point peak offset: the parabolic formula on ln y (docs/theory.md §9).
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
    """Cramér–Rao bound on the echo time for a Gaussian pulse in white noise (docs/theory.md §9):
    σ_t = √(2 σ_p Δt/√π)/SNR_peak.  τ_FWHM 5 ns, Δt 1 ns, SNR 10 → 154.8 ps."""
    return np.sqrt(2.0 * pulse_sigma_s * bin_width_s / np.sqrt(np.pi)) / np.asarray(snr_peak, dtype=np.float64)


def cramer_rao_range_std(pulse_sigma_s, bin_width_s, snr_peak):
    """σ_R = c σ_t/2 (docs/theory.md §9).  τ_FWHM 5 ns, Δt 1 ns, SNR 10 → 2.320 cm."""
    return 0.5 * SPEED_OF_LIGHT_M_S * cramer_rao_time_std(pulse_sigma_s, bin_width_s, snr_peak)


def photon_limited_range_std(pulse_sigma_s, n_photons):
    """Photon-limited range precision σ_R = (c/2) σ_p/√N (docs/theory.md §9).  N = 100, 5 ns FWHM → 3.183 cm."""
    return 0.5 * SPEED_OF_LIGHT_M_S * pulse_sigma_s / np.sqrt(np.asarray(n_photons, dtype=np.float64))


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
                        interpolation="gaussian", noise_sigma=None, baseline=None, min_noise_sigma=0.0):
    """Detect up to ``max_echoes`` echoes per pixel on noisy waveforms (docs/theory.md §9).

    waveforms      : (..., B) digital counts or any real waveform.
    threshold_mode : "adaptive" (k_sigma × per-pixel noise σ of the detection waveform, estimated by MAD) or
                     "fixed" (``threshold`` in input units above the baseline).
    pulse          : pulse shape samples for the matched filter (None: no filter).
    min_separation_bins : smallest distance between two echoes of a pixel (default: pulse length or 3).
    interpolation  : "gaussian" (falls back to parabolic where a sample ≤ 0 — counted), "parabolic", "none".
    noise_sigma, baseline : known per-pixel values instead of the robust estimates.
    min_noise_sigma : floor of the raw noise σ (and σ/‖pulse‖ after the matched filter): the receiver's
                     signal-free σ (core.receiver.noise_sigma_floor), so that a waveform whose noise is below
                     one A/D count (MAD 0) gets neither a zero threshold nor infinite SNRs.
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
    sig = np.maximum(sig, float(min_noise_sigma))
    yd = y.astype(np.float32) - base.astype(np.float32)[:, None]
    if pulse is not None:
        yd = matched_filter(yd, pulse)
        k = np.asarray(pulse, np.float64)
        if noise_sigma is None:
            _, sig_det = robust_baseline_noise(yd)
            sig_det = np.maximum(sig_det, float(min_noise_sigma) / np.sqrt(np.sum(k * k)))
        else:
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
    return NoisyEchoes(time_s=t.reshape(out_shape), range_m=(0.5 * SPEED_OF_LIGHT_M_S * t).reshape(out_shape),
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


# ----------------------------------------------------------------------------------------------------------
# False alarms (paper §3.1 products; docs/theory.md §9): which detections are noise, and how many to expect
# ----------------------------------------------------------------------------------------------------------
def false_alarm_mask(pixel, position_bins, truth, guard_bins, rel_level=1e-3, abs_level=0.0):
    """True for each detection with no true return nearby: no bin within ``guard_bins`` of the detection where
    the noise-free waveform ``truth`` (P, B) of its pixel exceeds max(rel_level × the pixel's peak, abs_level)
    (a pixel with no such bin has no signal at all: every detection there is a false alarm).

    pixel, position_bins : (K,) detection pixel (row of ``truth``) and position in bins (bin j ↔ [j, j + 1)).
    Returns (K,) bool.  Cost: one pass over the rows that hold detections."""
    pixel = np.asarray(pixel, dtype=np.int64)
    if pixel.size == 0:
        return np.zeros(0, dtype=bool)
    truth = np.asarray(truth)
    B = truth.shape[-1]
    rows, r = np.unique(pixel, return_inverse=True)
    t = truth[rows]
    level = np.maximum(rel_level * t.max(axis=1), abs_level)
    sup = (t > level[:, None]) & (t > 0)
    cum = np.zeros((rows.size, B + 1), dtype=np.int32)
    np.cumsum(sup, axis=1, out=cum[:, 1:])
    j = np.clip(np.floor(np.asarray(position_bins, dtype=np.float64)).astype(np.int64), 0, B - 1)
    lo = np.clip(j - guard_bins, 0, B)
    hi = np.clip(j + guard_bins + 1, 0, B)
    return (cum[r, hi] - cum[r, lo]) == 0


def eligible_bins(truth, guard_bins, rel_level=1e-3, abs_level=0.0):
    """(P, B) bool: the bins where a detection would be a false alarm (outside ``guard_bins`` of every bin with
    signal above max(rel_level × peak, abs_level)); all bins of a pixel without signal."""
    t = np.asarray(truth)
    level = np.maximum(rel_level * t.max(axis=1), abs_level)
    sup = (t > level[:, None]) & (t > 0)
    # support dilated by ±guard bins along time (a running maximum, O(P·B))
    near = ndimage.maximum_filter1d(sup.view(np.uint8), size=2 * int(guard_bins) + 1, axis=1, mode="constant")
    return near == 0


def _filter_rows(n_bins, pulse, rows):
    """Rows of the linear map raw → detection waveform (matched filter with 'nearest' edges, as in
    :func:`matched_filter`; the identity without a pulse) for the given output positions."""
    A = np.zeros((len(rows), n_bins))
    if pulse is None:
        A[np.arange(len(rows)), rows] = 1.0
        return A
    k = np.asarray(pulse, dtype=np.float64)
    k = k / np.sum(k * k)
    h = len(k) // 2
    for i, j in enumerate(rows):
        np.add.at(A[i], np.clip(j + np.arange(-h, len(k) - h), 0, n_bins - 1), k)
    return A


def _bvn_upper_orthant(h, k, rho):
    """P(X > −h, Y > −k) = Φ2(h, k; ρ) for standard bivariate normal, h, k > 0 (Owen's T form)."""
    from scipy.special import ndtr, owens_t
    s = np.sqrt(np.maximum(1.0 - rho * rho, 1e-300))
    return 0.5 * (ndtr(h) + ndtr(k)) - owens_t(h, (k - rho * h) / (h * s)) - owens_t(k, (h - rho * k) / (k * s))


def local_max_probability(u, cov3, n_nodes=96):
    """P(Z0 > u, Z0 > Z−, Z0 ≥ Z+) for a zero-mean Gaussian (Z−, Z0, Z+) with covariance ``cov3`` (3×3):
    the probability that a bin is a local maximum above the threshold u (Rice's argument for a sampled
    process).  Conditional on Z0 = y the two differences D± = Z0 − Z± are bivariate normal with means linear in
    y; the y-integral is done by Gauss–Legendre over [u, max(u, 0) + 12σ0].  ``u`` array (same units as Z)."""
    C = np.asarray(cov3, dtype=np.float64)
    v0 = C[1, 1]
    c1 = v0 - C[1, 0]  # Cov(Z0, D−)
    c2 = v0 - C[1, 2]  # Cov(Z0, D+)
    vd1 = v0 + C[0, 0] - 2 * C[1, 0]
    vd2 = v0 + C[2, 2] - 2 * C[1, 2]
    cd = v0 - C[1, 0] - C[1, 2] + C[0, 2]
    s1 = np.sqrt(max(vd1 - c1 * c1 / v0, 1e-300))
    s2 = np.sqrt(max(vd2 - c2 * c2 / v0, 1e-300))
    rho = np.clip((cd - c1 * c2 / v0) / (s1 * s2), -1 + 1e-12, 1 - 1e-12)
    sig0 = np.sqrt(v0)
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    u = np.atleast_1d(np.asarray(u, dtype=np.float64)) / sig0
    half = 0.5 * (np.maximum(u, 0.0) + 12.0 - u)  # standardized y over [u, max(u, 0) + 12]
    t = u[:, None] + half[:, None] * (x[None, :] + 1.0)
    y = t * sig0
    from scipy.special import ndtr
    dens = np.exp(-0.5 * t * t) / np.sqrt(2 * np.pi)
    h1, h2 = (c1 / v0) * y / s1, (c2 / v0) * y / s2
    pos = (h1 > 0) & (h2 > 0)
    cond = np.where(pos, _bvn_upper_orthant(np.where(pos, h1, 1.0), np.where(pos, h2, 1.0), rho),
                    ndtr(h1) * ndtr(h2))  # (non-positive arguments only for degenerate edges; product bound)
    return half * np.sum(w[None, :] * dens * cond, axis=1)


def expected_false_alarms(threshold, sigma_raw, eligible, pulse=None, n_grid=64):
    """Expected number of noise detections per pixel for white Gaussian raw noise of σ ``sigma_raw`` (the
    detector's threshold/noise model, docs/theory.md §9): Σ_j eligible[p, j] · P(bin j is a local maximum of the
    detection waveform above threshold[p]).  Exact for Gaussian noise per bin; the greedy minimum separation
    and the ``max_echoes`` cap (which only lower the count) are ignored.  Bins 1 … h and B−2−h … B−2 (the
    matched filter's 'nearest' edges) are computed position by position, the interior once.

    threshold : (P,) in detection-waveform units; eligible : (P, B) bool (:func:`eligible_bins`).
    Returns (P,) float64."""
    thr = np.asarray(threshold, dtype=np.float64).reshape(-1)
    el = np.asarray(eligible, dtype=bool)
    P, B = el.shape
    out = np.zeros(P)
    if B < 3 or not sigma_raw > 0:
        return out
    h = 0 if pulse is None else len(pulse) // 2
    lo_edge = list(range(1, min(h + 1, B - 1)))
    hi_edge = [j for j in range(max(B - 1 - h, h + 1), B - 1)]
    interior = [j for j in range(h + 1, B - 1 - h)]
    positions = lo_edge + hi_edge + ([interior[0]] if interior else [])
    finite = np.isfinite(thr) & (thr > 0)
    if not finite.any():
        return out
    lo_u, hi_u = thr[finite].min(), thr[finite].max()
    grid = np.linspace(lo_u, hi_u, n_grid) if hi_u > lo_u else np.array([lo_u])
    rates = {}
    for j in positions:
        rows = _filter_rows(B, pulse, [j - 1, j, j + 1])
        cov = sigma_raw ** 2 * rows @ rows.T
        r = local_max_probability(grid, cov)
        if grid.size > 1:  # interpolate log-rate in u (smooth, nearly quadratic)
            rates[j] = np.exp(np.interp(thr, grid, np.log(np.maximum(r, 1e-300))))
        else:
            rates[j] = np.full(P, r[0])
    rates = {j: np.where(finite, v, 0.0) for j, v in rates.items()}
    if interior:
        out += el[:, interior[0]:interior[-1] + 1].sum(axis=1) * rates[interior[0]]
    for j in lo_edge + hi_edge:
        out += el[:, j] * rates[j]
    return out


def gaussian_false_alarm_summary(n_detected_fa, expected_per_pixel, eligible, empty_pixels, fa_per_pixel):
    """Run-metadata record of false alarms (counts, rates per pixel/gate and per bin, Gaussian expectation)."""
    n_pix = int(expected_per_pixel.size)
    n_bins_el = int(np.count_nonzero(eligible))
    n_empty = int(np.count_nonzero(empty_pixels))
    exp_total = float(np.sum(expected_per_pixel))
    if not np.isfinite(exp_total):  # no noise model (Geiger mode): counts only
        return {"n_false_alarms": int(n_detected_fa),
                "false_alarms_per_pixel": n_detected_fa / n_pix if n_pix else 0.0,
                "false_alarm_probability_per_bin": n_detected_fa / n_bins_el if n_bins_el else 0.0,
                "expected_false_alarms_gaussian": None, "n_eligible_bins": n_bins_el, "n_empty_pixels": n_empty,
                "n_false_alarms_in_empty_pixels": int(np.sum(fa_per_pixel[empty_pixels]))}
    return {"n_false_alarms": int(n_detected_fa),
            "false_alarms_per_pixel": n_detected_fa / n_pix if n_pix else 0.0,
            "false_alarm_probability_per_bin": n_detected_fa / n_bins_el if n_bins_el else 0.0,
            "expected_false_alarms_gaussian": exp_total,
            "expected_false_alarms_per_pixel_gaussian": exp_total / n_pix if n_pix else 0.0,
            "expected_false_alarm_probability_per_bin_gaussian": exp_total / n_bins_el if n_bins_el else 0.0,
            "n_eligible_bins": n_bins_el,
            "n_empty_pixels": n_empty,
            "n_false_alarms_in_empty_pixels": int(np.sum(fa_per_pixel[empty_pixels])),
            "expected_false_alarms_in_empty_pixels_gaussian": float(np.sum(expected_per_pixel[empty_pixels]))}


#: A detection is a true echo when the noise-free waveform has signal within this many pulse FWHMs of it.
FALSE_ALARM_GUARD_FWHM = 2.0
#: Signal bins: above this fraction of the pixel's noise-free peak ...
FALSE_ALARM_REL_LEVEL = 1e-3
#: ... and above this mean number of signal photo-electrons per bin (below it a pixel has no signal at all).
FALSE_ALARM_ABS_PRIMARIES = 1e-2


def classify_false_alarms(echoes: NoisyEchoes, truth, pulse_fwhm_bins, *, noise_sigma=None, pulse=None,
                          abs_level=0.0, rel_level=FALSE_ALARM_REL_LEVEL, guard_fwhm=FALSE_ALARM_GUARD_FWHM):
    """False alarms of a detection run against the noise-free waveforms ``truth`` (P, B), and their expected
    number for Gaussian noise of σ ``noise_sigma`` (raw-waveform units; None: no expectation).

    A detection is a false alarm when no bin within ``guard_fwhm`` pulse widths of it holds signal above
    max(rel_level × the pixel's peak, abs_level) (:func:`false_alarm_mask`).  Expectation: Σ over pixels and
    eligible bins (outside those guard regions) of the probability that the bin is a local maximum of the
    detection waveform above the pixel's threshold (:func:`expected_false_alarms`).
    Returns ``(mask (P, K) bool, summary dict)``."""
    det = np.asarray(echoes.detected)
    P, K = det.shape[0], det.shape[-1]
    det = det.reshape(P, K)
    truth = np.asarray(truth).reshape(P, -1)
    guard = int(np.ceil(guard_fwhm * pulse_fwhm_bins))
    pix, slot = np.nonzero(det)
    eligible = eligible_bins(truth, guard, rel_level, abs_level)
    fa = np.zeros((P, K), dtype=bool)
    j = np.clip(np.floor(np.asarray(echoes.position_bins).reshape(P, K)[pix, slot]).astype(np.int64), 0,
                truth.shape[1] - 1)
    fa[pix, slot] = eligible[pix, j]  # no signal within the guard of the detection's bin (= false_alarm_mask)
    if noise_sigma is not None and noise_sigma > 0:
        expected = expected_false_alarms(np.asarray(echoes.threshold).reshape(P), noise_sigma, eligible, pulse)
    else:
        expected = np.full(P, np.nan)
    summary = gaussian_false_alarm_summary(int(fa.sum()), expected, eligible, eligible.all(axis=1), fa.sum(axis=1))
    summary.update({"guard_bins": guard, "signal_level_relative": rel_level, "signal_level_absolute": abs_level,
                    "noise_sigma": noise_sigma,
                    "expectation_model": "white Gaussian noise of the signal-free bins' sigma; local maxima of the "
                                         "detection waveform above each pixel's threshold (Rice, per bin); "
                                         "minimum separation and max_echoes ignored"})
    return fa, summary
