"""Echo detection on noisy (digital) waveforms, docs/theory.md §9.

Per pixel: robust baseline and noise (median, 1.4826 × median absolute deviation) estimated from the
waveform itself; optional matched filter (correlation with the pulse shape, normalised so that a pulse of
amplitude A gives a filtered peak of A); fixed or noise-adaptive threshold (k σ); local maxima above the
threshold, taken greedily by amplitude with a minimum separation (multi-echo); 3-point sub-bin interpolation
(parabolic or Gaussian, the exact §9 formulas).  One compiled pass per row (threads split the rows); the
interpolation is vectorised over the detected (pixel, echo) slots.  Bin j is centred at j + 0.5 bin widths after the
gate opening (as in ``core/physics/waveform.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...constants import SPEED_OF_LIGHT_M_S
from ...jit import kernel
from ...threads import map_list
from .matched_filter import (EXACT_PAIR_VALUE, FILTER_BLOCK, approx_row, correlate_row, exact_output, pad_row,
                             screen_margin)
from .row_statistics import baseline_noise_row, row_scratch



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
# Detection
# ----------------------------------------------------------------------------------------------------------
#: A row with a known threshold is screened (filtered in float32, exact outputs near the threshold only) when at
#: most 1/SCREEN_FRACTION of its outputs are near the threshold; otherwise it is filtered in full.
SCREEN_FRACTION = 16


@kernel
def _noisy_rows(y, integral, given_base, given_sig, estimate_base, estimate_sig, filtered, w, norm, adaptive,
                k_sigma, threshold, min_sep, min_sig, base, sig, thr, pos, samples):
    """Per row (of any real type, taken as float32; ``integral``: of an integer type): baseline and raw noise
    (robust estimates unless given), the detection waveform yd = y − baseline (float32) correlated with the
    pulse ``w`` when ``filtered``, its noise, the threshold, and up to pos.shape[1] echoes: the strongest local
    maximum above the threshold (interior bins; ties: the earliest), then the next outside ``min_sep`` bins of
    those taken, …; positions in time order, −1 for none, and the three detection-waveform samples around each
    (``samples``, for the interpolation).  The raw noise σ is at least ``min_sig``, the filtered one's estimate
    at least ``min_sig``/``norm``.  One row's scratch buffers serve all rows of the call."""
    n_rows, n = y.shape
    keys, s1, s2, cast, dev, d1, d2, counts = row_scratch(n)
    ypad, acc = np.empty(n + w.shape[0] - 1, np.float32), np.empty(FILTER_BLOCK)
    yr, yd = np.empty(n, np.float32), np.empty(n, np.float32)
    w32, acc32, ya = w.astype(np.float32), np.empty(FILTER_BLOCK, np.float32), np.empty(n, np.float32)
    h = w.shape[0] // 2
    cj, alive = np.empty(n, np.int64), np.empty(n, np.bool_)
    for r in range(n_rows):
        row = y[r]
        lo, hi = np.float32(0.0), np.float32(0.0)
        if integral:  # the row as float32, and its extremes
            i_lo, i_hi = row[0], row[0]
            for i in range(n):
                v = row[i]
                yr[i] = np.float32(v)
                i_lo, i_hi = min(i_lo, v), max(i_hi, v)
            lo, hi = np.float32(i_lo), np.float32(i_hi)
        else:
            for i in range(n):
                yr[i] = np.float32(row[i])
        b_est, s_est = np.float32(0.0), 0.0
        if estimate_base or estimate_sig:
            b_est, s_est = baseline_noise_row(yr, integral, lo, hi, 0.0, 0.0, keys, s1, s2, cast, dev, d1, d2,
                                              counts)
        base[r] = np.float64(b_est) if estimate_base else given_base[r]
        s_raw = s_est if estimate_sig else given_sig[r]
        sig[r] = min_sig if s_raw < min_sig else s_raw  # NaN stays NaN, as np.maximum
        b32 = np.float32(base[r])
        screened = False
        if filtered and integral and not estimate_sig:  # a threshold known before the row is filtered: screen it
            pad_row(yr, b32, h, ypad)  # (|y − b32| ≤ max(hi − b32, b32 − lo): the row's extremes, rounded alike)
            margin = screen_margin(w, max(abs(np.float64(hi - b32)), abs(np.float64(b32 - lo))))
            thr[r] = k_sigma * (sig[r] / norm) if adaptive else threshold
            screened = margin < np.inf  # (an infinite baseline: filtered in full below)
        near = 0
        if screened:
            # the row filtered in float32 (twice the lanes); the exact outputs (correlate_row's, bit for bit) only
            # where the float32 one is within the margin of the threshold, and at their neighbours: every output
            # above the threshold is among them, so the maxima, their order and their samples are the same.  A
            # row with many such outputs (a long signal stretch) is filtered in full instead (vectorised).
            approx_row(ypad, w32, n, acc32, ya)
            t32 = np.float32(thr[r])
            t_lo = np.float64(t32) - margin
            for j in range(1, n - 1):  # (vectorised: most rows have no output near the threshold)
                near += ya[j] >= t_lo
            screened = near * SCREEN_FRACTION <= n
        if screened:
            nc = 0
            if near:
                done = -2  # the last output computed exactly (and the one before it)
                for j in range(1, n - 1):
                    if ya[j] >= t_lo:
                        for i in range(max(j - 1, done + 1), j + 2):
                            yd[i] = exact_output(ypad, w, i)
                        done = j + 1
                        c = yd[j]
                        if c > t32 and c > yd[j - 1] and c >= yd[j + 1]:
                            cj[nc] = j
                            alive[nc] = True
                            nc += 1
            _greedy_maxima(yd, cj, alive, nc, min_sep, pos, samples, r)
            continue
        if filtered:
            exact_pairs = integral and 2 * b32 == np.floor(2 * b32) and max(hi - b32, b32 - lo) < EXACT_PAIR_VALUE
            correlate_row(yr, b32, w, ypad, acc, yd, exact_pairs)
            if estimate_sig:  # (filtered noise: median near 0, σ near the raw one / ‖pulse‖)
                sig_det = baseline_noise_row(yd, False, lo, hi, 0.0, sig[r] / norm, keys, s1, s2, cast, dev, d1,
                                             d2, counts)[1]
                floor = min_sig / norm
                if sig_det < floor:
                    sig_det = floor
            else:
                sig_det = sig[r] / norm
        else:
            for i in range(n):
                yd[i] = yr[i] - b32
            sig_det = sig[r]
        thr[r] = k_sigma * sig_det if adaptive else threshold
        t32 = np.float32(thr[r])
        above = 0
        for j in range(1, n - 1):  # (vectorised: most rows of a frame have no sample above the threshold)
            above += yd[j] > t32
        nc = 0
        if above:
            for j in range(1, n - 1):
                c = yd[j]
                if c > t32 and c > yd[j - 1] and c >= yd[j + 1]:  # (the threshold first: rarely passed)
                    cj[nc] = j
                    alive[nc] = True
                    nc += 1
        _greedy_maxima(yd, cj, alive, nc, min_sep, pos, samples, r)


@kernel
def _greedy_maxima(yd, cj, alive, nc, min_sep, pos, samples, r):
    """Row r's echoes from its nc candidate maxima cj (alive: all True): the strongest (ties: the earliest), then
    the next outside ``min_sep`` bins of those taken, …; positions in time order, and their three samples."""
    n_slots = pos.shape[1]
    n_found = 0
    for k in range(n_slots):
        best = -1
        for q in range(nc):
            if alive[q] and (best < 0 or yd[cj[q]] > yd[cj[best]]):
                best = q
        if best < 0:
            break
        j = cj[best]
        pos[r, k] = j
        n_found += 1
        for q in range(nc):
            if alive[q] and abs(cj[q] - j) < min_sep:
                alive[q] = False
    for k in range(1, n_found):  # time order
        v = pos[r, k]
        q = k - 1
        while q >= 0 and pos[r, q] > v:
            pos[r, q + 1] = pos[r, q]
            q -= 1
        pos[r, q + 1] = v
    for k in range(n_found):
        j = pos[r, k]
        samples[r, k, 0], samples[r, k, 1], samples[r, k, 2] = yd[j - 1], yd[j], yd[j + 1]


def run_row_chunks(run, n_rows: int, threads: int) -> None:
    """``run(a, b)`` over chunks of ≥ 256 rows (about four a thread), on ``threads`` threads of the shared pool
    (core/threads.py) when there are several chunks.  The rows' results do not depend on the chunks, so neither
    on the thread count."""
    step = max(256, -(-n_rows // (4 * max(1, threads))))
    chunks = [(a, min(a + step, n_rows)) for a in range(0, n_rows, step)]
    map_list(lambda c: run(*c), chunks, threads)


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
                        interpolation="gaussian", noise_sigma=None, baseline=None, threads=1, min_noise_sigma=0.0):
    """Detect up to ``max_echoes`` echoes per pixel on noisy waveforms (docs/theory.md §9).

    waveforms      : (..., B) digital counts or any real waveform, of any integer or float type (processed as
                     float32, one row at a time).
    threshold_mode : "adaptive" (k_sigma × per-pixel noise σ of the detection waveform, estimated by MAD),
                     "calibrated" (k_sigma × the σ of the filtered noise from the noise model: ``noise_sigma``
                     and ``baseline`` required; white raw noise of σ_n through the taps w = pulse/Σpulse² gives
                     σ_det² = Σ w_k² σ_n² = σ_n²/‖pulse‖²) or "fixed" (``threshold`` in input units above the
                     baseline).
    pulse          : pulse shape samples for the matched filter (None: no filter).
    min_separation_bins : smallest distance between two echoes of a pixel (default: pulse length or 3).
    interpolation  : "gaussian" (falls back to parabolic where a sample ≤ 0 — counted), "parabolic", "none";
                     computed for the detected echoes only.
    noise_sigma, baseline : known per-pixel values instead of the robust estimates.
    threads        : rows are processed in chunks on this many threads (never changes the result).
    min_noise_sigma : floor of the raw noise σ (and σ/‖pulse‖ after the matched filter): the receiver's
                     signal-free σ (core.receiver.noise_sigma_floor), so that a waveform whose noise is below
                     one A/D count (MAD 0) gets neither a zero threshold nor infinite SNRs.
    Edge bins 0 and B−1 are never peaks (no 3-point neighbourhood).
    Per row, one compiled pass (:func:`_noisy_rows`): baseline and noise, matched filter, threshold, the greedy
    choice of maxima; the interpolation of the chosen ones is vectorised over the detected slots.
    """
    y = np.asarray(waveforms)
    shape = y.shape[:-1]
    B = y.shape[-1]
    y = y.reshape(-1, B)
    P = y.shape[0]
    if threshold_mode not in ("adaptive", "calibrated", "fixed"):
        raise ValueError(f"threshold_mode must be 'adaptive', 'calibrated' or 'fixed', got {threshold_mode!r}")
    if threshold_mode == "calibrated":  # k σ of the filtered noise from the noise model: given σ and baseline
        if noise_sigma is None or baseline is None:
            raise ValueError("threshold_mode 'calibrated' needs the noise model's noise_sigma and baseline (the "
                             "receiver chain report's noise_sigma and noise_mean)")
        threshold_mode = "adaptive"  # (with both given, the kernel's σ is σ_n/‖pulse‖: no row statistics)
    if min_separation_bins is None:
        min_separation_bins = max(3, len(pulse) // 2) if pulse is not None else 3
    given_base = np.zeros(P) if baseline is None else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(baseline, np.float64), shape).reshape(-1))
    given_sig = np.zeros(P) if noise_sigma is None else \
        np.ascontiguousarray(np.broadcast_to(np.asarray(noise_sigma, np.float64), shape).reshape(-1))
    w = np.zeros(1)
    norm = 1.0
    if pulse is not None:
        k = np.asarray(pulse, dtype=np.float64)
        w = (k / np.sum(k * k)).astype(np.float32)
        if len(w) % 2 == 0 or not np.array_equal(w, w[::-1]):
            raise ValueError("detect_echoes_noisy: the pulse must be symmetric with an odd number of samples")
        w = w.astype(np.float64)
        norm = float(np.sqrt(np.sum(k * k)))
    K = int(max_echoes)
    base, sig, thr = np.empty(P), np.empty(P), np.empty(P)
    pos = np.full((P, K), -1, dtype=np.int64)
    samples = np.zeros((P, K, 3), np.float32)  # detection waveform at j − 1, j, j + 1 of each echo

    if y.dtype.kind not in "biu" and y.dtype not in (np.float32, np.float64):
        y = y.astype(np.float32)
    integral = y.dtype.kind in "biu"

    def run(a, b):  # (rows of A/D codes are taken as float32 one at a time: no float32 copy of the cube)
        _noisy_rows(np.ascontiguousarray(y[a:b]), integral, given_base[a:b], given_sig[a:b], baseline is None,
                    noise_sigma is None, pulse is not None, w, norm, threshold_mode == "adaptive", float(k_sigma),
                    float(threshold), int(min_separation_bins), float(min_noise_sigma), base[a:b], sig[a:b],
                    thr[a:b], pos[a:b], samples[a:b])

    run_row_chunks(run, P, threads)
    return echoes_from_slots(pos, samples, base, sig, thr, shape, bin_width_s, gate_start_s, interpolation)


def echoes_from_slots(pos, samples, base, sig, thr, shape, bin_width_s, gate_start_s, interpolation):
    """:class:`NoisyEchoes` from the chosen maxima: ``pos`` (P, K) bins in time order (−1: none), ``samples``
    (P, K, 3) the detection waveform at j − 1, j, j + 1; per pixel baseline, raw σ and threshold.  The
    interpolation runs on the detected slots only."""
    P, K = pos.shape
    detected = pos >= 0
    sel = np.flatnonzero(detected)  # the interpolation runs on the detected slots only
    jj = pos.reshape(-1)[sel]
    ym, y0, yp = (samples.reshape(-1, 3)[sel, i].astype(np.float64) for i in range(3))
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
            n_fallback = int(np.count_nonzero(~okg))
            with np.errstate(divide="ignore", invalid="ignore"):
                a_g = gaussian_peak(np.where(okg, ym, 1.0), np.where(okg, y0, 1.0), np.where(okg, yp, 1.0),
                                    np.where(okg, d_g, 0.0))
            delta = np.where(okg, d_g, d_par)
            amp = np.where(okg, a_g, a_par)
    else:
        raise ValueError(f"interpolation must be 'gaussian', 'parabolic' or 'none', got {interpolation!r}")

    position, amplitude = np.full(P * K, np.nan), np.full(P * K, np.nan)
    position[sel], amplitude[sel] = jj + 0.5 + delta, amp
    position, amp = position.reshape(P, K), amplitude.reshape(P, K)
    t = gate_start_s + position * bin_width_s
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
