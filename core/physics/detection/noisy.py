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

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ...constants import SPEED_OF_LIGHT_M_S
from ...jit import kernel

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
@kernel
def _select(a, lo, hi, k):
    """Partially sort a[lo:hi] in place so that a[k] is its k-th smallest element (quickselect, median of three
    pivots); everything before k is ≤ a[k], everything after ≥."""
    while hi - lo > 1:
        mid = (lo + hi - 1) // 2
        x, y, z = a[lo], a[mid], a[hi - 1]
        pivot = max(min(x, y), min(max(x, y), z))
        i, j = lo, hi - 1
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j + 1
        elif k >= i:
            lo = i
        else:
            return


@kernel
def _median32(a, n):
    """The median of a[:n] (float32, reordered in place) as NumPy computes it: the middle element, or the mean
    of the two middle ones rounded to float32."""
    k = n // 2
    _select(a, 0, n, k)
    if n % 2:
        return a[k]
    below = a[0]
    for i in range(1, k):
        below = max(below, a[i])
    return np.float32(a[k] + below) * np.float32(0.5)


@kernel
def _pairwise_leaf(a, lo, n):
    if n < 8:
        res = 0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@kernel
def pairwise_sum(a, lo, n):
    """Σ a[lo:lo + n] in NumPy's pairwise order (halves split at multiples of 8 down to blocks of ≤ 128 summed
    in 8 lanes): bit for bit np.sum.  The recursion runs on an explicit stack (numba's cache cannot hold
    recursive kernels)."""
    los, ns, stage, vals = np.empty(64, np.int64), np.empty(64, np.int64), np.empty(64, np.int64), np.empty(64)
    sp = 0
    los[0], ns[0], stage[0] = lo, n, 0
    result = 0.0
    while sp >= 0:
        m = ns[sp]
        if m > 128:  # descend into the left half
            stage[sp] = 1
            half = m // 2
            half -= half % 8
            los[sp + 1], ns[sp + 1], stage[sp + 1] = los[sp], half, 0
            sp += 1
            continue
        v = _pairwise_leaf(a, los[sp], m)
        sp -= 1
        while sp >= 0:  # hand v up: a finished left half starts its right half; a right half is added
            if stage[sp] == 1:
                vals[sp] = v
                stage[sp] = 2
                half = ns[sp] // 2
                half -= half % 8
                los[sp + 1], ns[sp + 1], stage[sp + 1] = los[sp] + half, ns[sp] - half, 0
                sp += 1
                break
            v = vals[sp] + v
            sp -= 1
        if sp < 0:
            result = v
    return result


#: Integer-valued rows (A/D counts) spanning fewer values than this take the counting median.
_COUNTING_RANGE = 1 << 16


@kernel
def _kth_from_counts(counts, span, k):
    """Index of the k-th smallest (0-based) of indices i repeated counts[i] times (i < span)."""
    seen = 0
    for i in range(span):
        seen += counts[i]
        if seen > k:
            return i
    return span - 1


@kernel
def _counting_median_mad(y, lo, span, counts):
    """(median, MAD) as float32 of a row of integer values in [lo, lo + span): the same order statistics as
    sorting, in O(n + span).  The deviations |y − median| (exact: small integers or half-integers) are walked
    outward from the median in increasing order."""
    n = y.shape[0]
    counts[:span] = 0
    for i in range(n):
        counts[int(y[i] - lo)] += 1
    k = n // 2
    vk = np.float32(lo + _kth_from_counts(counts, span, k))
    if n % 2:
        base = vk
    else:
        base = np.float32(np.float32(lo + _kth_from_counts(counts, span, k - 1)) + vk) * np.float32(0.5)
    i_dn = int(math.floor(base - lo))
    i_up = i_dn + 1
    taken = 0
    d_km1, d_k = np.float32(0.0), np.float32(0.0)
    while True:
        while i_dn >= 0 and counts[i_dn] == 0:
            i_dn -= 1
        while i_up < span and counts[i_up] == 0:
            i_up += 1
        d_dn = abs(np.float32(lo + i_dn) - base) if i_dn >= 0 else np.float32(np.inf)
        d_up = abs(np.float32(lo + i_up) - base) if i_up < span else np.float32(np.inf)
        if d_dn <= d_up:
            d, c = d_dn, counts[i_dn]
            i_dn -= 1
        else:
            d, c = d_up, counts[i_up]
            i_up += 1
        if taken <= k - 1 < taken + c:
            d_km1 = d
        if k < taken + c:
            d_k = d
            break
        taken += c
    if n % 2:
        return base, d_k
    return base, np.float32(d_km1 + d_k) * np.float32(0.5)


@kernel
def _baseline_noise_row(y, scratch, dev, d64, counts):
    """(median, σ) of one float32 row: σ = 1.4826 × MAD, or where the MAD is 0 the rms deviation of the quietest
    90 % of the samples (NumPy's linear quantile, its pairwise sum)."""
    n = y.shape[0]
    lo, hi, integral = y[0], y[0], True
    for i in range(n):
        v = y[i]
        lo, hi = min(lo, v), max(hi, v)
        integral = integral and v == math.floor(v)
    if integral and hi - lo < _COUNTING_RANGE:  # A/D counts: the median and MAD by counting
        base, mad = _counting_median_mad(y, lo, int(hi - lo) + 1, counts)
        for i in range(n):
            dev[i] = abs(y[i] - base)
    else:
        scratch[:n] = y
        base = _median32(scratch, n)
        for i in range(n):
            dev[i] = abs(y[i] - base)
        scratch[:n] = dev[:n]
        mad = _median32(scratch, n)
    sigma = np.float64(mad) * MAD_TO_SIGMA
    if sigma == 0:
        # A/D-quantized noise below one count: fall back to the rms deviation of the quietest 90 % of the
        # samples (np.quantile(d, 0.9), method "linear")
        for i in range(n):
            d64[i] = dev[i]
        virtual = n * 0.9 + (1.0 + 0.9 * (1.0 - 1.0 - 1.0)) - 1.0
        prev = int(math.floor(virtual))
        gamma = virtual - prev
        prev = min(max(prev, 0), n - 1)
        nxt = min(prev + 1, n - 1)
        srt = np.empty(n)
        srt[:] = d64[:n]
        _select(srt, 0, n, nxt)
        b = srt[nxt]
        a = srt[prev] if prev == nxt else srt[0]
        if prev != nxt:
            for i in range(1, nxt):
                a = max(a, srt[i])
        diff = b - a
        q = b - diff * (1.0 - gamma) if gamma >= 0.5 else a + diff * gamma
        count = 0
        for i in range(n):
            if d64[i] <= q:
                count += 1
                srt[i] = d64[i] * d64[i] * 1.0
            else:
                srt[i] = d64[i] * d64[i] * 0.0
        sigma = math.sqrt(pairwise_sum(srt, 0, n) / max(count, 1))
    return base, sigma


@kernel
def _baseline_noise_rows(y, base, sigma):
    n = y.shape[1]
    scratch, dev, d64 = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n)
    counts = np.empty(_COUNTING_RANGE, np.int64)
    for r in range(y.shape[0]):
        base[r], sigma[r] = _baseline_noise_row(y[r], scratch, dev, d64, counts)


def robust_baseline_noise(waveforms):
    """Per-pixel baseline (median) and noise σ = 1.4826 × median(|y − median|) along the last axis (float32
    arithmetic, as NumPy on float32 rows).  Robust to the echoes themselves as long as they occupy well under half
    of the bins.  Where the MAD is 0 (noise below one A/D count), σ is the rms deviation of the quietest 90 % of
    the samples."""
    y = np.ascontiguousarray(waveforms, dtype=np.float32)
    rows = y.reshape(-1, y.shape[-1])
    base, sigma = np.empty(len(rows), np.float32), np.empty(len(rows))
    _baseline_noise_rows(rows, base, sigma)
    return base.astype(np.float64).reshape(y.shape[:-1]), sigma.reshape(y.shape[:-1])


@kernel
def _correlate_row(y, w, out):
    """SciPy's correlate1d of one row with a symmetric odd kernel ``w`` (float64), 'nearest' edges, summed in
    float64 in SciPy's order and rounded to float32."""
    n, h = y.shape[0], w.shape[0] // 2
    for i in range(n):
        acc = np.float64(y[i]) * w[h]
        if h <= i < n - h:  # interior: no edge clamping
            for jj in range(-h, 0):
                acc += (np.float64(y[i + jj]) + np.float64(y[i - jj])) * w[h + jj]
        else:
            for jj in range(-h, 0):
                lo = min(max(i + jj, 0), n - 1)
                hi = min(max(i - jj, 0), n - 1)
                acc += (np.float64(y[lo]) + np.float64(y[hi])) * w[h + jj]
        out[i] = acc


@kernel
def _correlate_rows(y, w, out):
    for r in range(y.shape[0]):
        _correlate_row(y[r], w, out[r])


def matched_filter(waveforms, pulse):
    """Correlate each waveform (last axis) with the pulse shape, normalised by Σ pulse² so that A·pulse
    (centred on a bin) gives a filtered peak of exactly A.  White noise σ becomes σ/‖pulse‖.  The pulse must
    be symmetric (odd length, as :func:`gaussian_pulse_kernel`)."""
    k = np.asarray(pulse, dtype=np.float64)
    k = (k / np.sum(k * k)).astype(np.float32)
    if len(k) % 2 == 0 or not np.array_equal(k, k[::-1]):
        raise ValueError("matched_filter: the pulse must be symmetric with an odd number of samples")
    y = np.ascontiguousarray(waveforms, dtype=np.float32)
    out = np.empty(y.shape, np.float32)
    _correlate_rows(y.reshape(-1, y.shape[-1]), k.astype(np.float64), out.reshape(-1, y.shape[-1]))
    return out


# ----------------------------------------------------------------------------------------------------------
# Detection
# ----------------------------------------------------------------------------------------------------------
@kernel
def _noisy_rows(y, given_base, given_sig, estimate_base, estimate_sig, filtered, w, norm, adaptive, k_sigma,
                threshold, min_sep, min_sig, yd, base, sig, thr, pos):
    """Per row: baseline and raw noise (robust estimates unless given), the detection waveform yd = y − baseline
    (float32) correlated with the pulse ``w`` when ``filtered``, its noise, the threshold, and up to
    pos.shape[1] echoes: the strongest local maximum above the threshold (interior bins; ties: the earliest),
    then the next outside ``min_sep`` bins of those taken, …; positions in time order, −1 for none.  The raw
    noise σ is at least ``min_sig``, the filtered one's estimate at least ``min_sig``/``norm``."""
    n_rows, n = y.shape
    scratch, dev, d64 = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n)
    counts = np.empty(_COUNTING_RANGE, np.int64)
    raw = np.empty(n, np.float32)
    cj, alive = np.empty(n, np.int64), np.empty(n, np.bool_)
    n_slots = pos.shape[1]
    for r in range(n_rows):
        b_est, s_est = np.float32(0.0), 0.0
        if estimate_base or estimate_sig:
            b_est, s_est = _baseline_noise_row(y[r], scratch, dev, d64, counts)
        base[r] = np.float64(b_est) if estimate_base else given_base[r]
        s_raw = s_est if estimate_sig else given_sig[r]
        sig[r] = min_sig if s_raw < min_sig else s_raw  # NaN stays NaN, as np.maximum
        b32 = np.float32(base[r])
        if filtered:
            for i in range(n):
                raw[i] = y[r, i] - b32
            _correlate_row(raw, w, yd[r])
            if estimate_sig:
                sig_det = _baseline_noise_row(yd[r], scratch, dev, d64, counts)[1]
                floor = min_sig / norm
                if sig_det < floor:
                    sig_det = floor
            else:
                sig_det = sig[r] / norm
        else:
            for i in range(n):
                yd[r, i] = y[r, i] - b32
            sig_det = sig[r]
        thr[r] = k_sigma * sig_det if adaptive else threshold
        t32 = np.float32(thr[r])
        nc = 0
        for j in range(1, n - 1):
            c = yd[r, j]
            if c > yd[r, j - 1] and c >= yd[r, j + 1] and c > t32:
                cj[nc] = j
                alive[nc] = True
                nc += 1
        n_found = 0
        for k in range(n_slots):
            best = -1
            for q in range(nc):
                if alive[q] and (best < 0 or yd[r, cj[q]] > yd[r, cj[best]]):
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

    waveforms      : (..., B) digital counts or any real waveform.
    threshold_mode : "adaptive" (k_sigma × per-pixel noise σ of the detection waveform, estimated by MAD) or
                     "fixed" (``threshold`` in input units above the baseline).
    pulse          : pulse shape samples for the matched filter (None: no filter).
    min_separation_bins : smallest distance between two echoes of a pixel (default: pulse length or 3).
    interpolation  : "gaussian" (falls back to parabolic where a sample ≤ 0 — counted), "parabolic", "none".
    noise_sigma, baseline : known per-pixel values instead of the robust estimates.
    threads        : rows are processed in chunks on this many threads (never changes the result).
    min_noise_sigma : floor of the raw noise σ (and σ/‖pulse‖ after the matched filter): the receiver's
                     signal-free σ (core.receiver.noise_sigma_floor), so that a waveform whose noise is below
                     one A/D count (MAD 0) gets neither a zero threshold nor infinite SNRs.
    Edge bins 0 and B−1 are never peaks (no 3-point neighbourhood).
    Per row, one compiled pass (:func:`_noisy_rows`): baseline and noise, matched filter, threshold, the greedy
    choice of maxima; the interpolation of the chosen ones is vectorised over the (P, max_echoes) slots.
    """
    y = np.asarray(waveforms)
    shape = y.shape[:-1]
    B = y.shape[-1]
    y = y.reshape(-1, B)
    P = y.shape[0]
    if threshold_mode not in ("adaptive", "fixed"):
        raise ValueError(f"threshold_mode must be 'adaptive' or 'fixed', got {threshold_mode!r}")
    if min_separation_bins is None:
        min_separation_bins = max(3, len(pulse) // 2) if pulse is not None else 3
    y = np.ascontiguousarray(y, dtype=np.float32)
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
    yd = np.empty((P, B), np.float32)
    base, sig, thr = np.empty(P), np.empty(P), np.empty(P)
    pos = np.full((P, K), -1, dtype=np.int64)

    def run(a, b):
        _noisy_rows(y[a:b], given_base[a:b], given_sig[a:b], baseline is None, noise_sigma is None,
                    pulse is not None, w, norm, threshold_mode == "adaptive", float(k_sigma), float(threshold),
                    int(min_separation_bins), float(min_noise_sigma), yd[a:b], base[a:b], sig[a:b], thr[a:b], pos[a:b])

    step = max(256, -(-P // (4 * max(1, threads))))
    chunks = [(a, min(a + step, P)) for a in range(0, P, step)]
    if threads > 1 and len(chunks) > 1:
        with ThreadPoolExecutor(max_workers=min(threads, len(chunks))) as pool:
            list(pool.map(lambda c: run(*c), chunks))
    else:
        for c in chunks:
            run(*c)
    rows = np.arange(P)

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
