"""Echo detection on waveforms: local maxima above a threshold, up to N per pixel, with 3-point sub-bin
interpolation (docs/theory.md §9):

    parabolic  δ = (y₋ − y₊) / (2 (y₋ − 2y₀ + y₊))
    Gaussian   the same on ln y (exact for a sampled Gaussian pulse)

One compiled pass per waveform row (:func:`detect_row`), on dense rows or on the windows of core/waveform.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...config.settings import DetectionSettings
from ...jit import kernel

#: Two bins closer than this (relative) count as one flat top (rounding in the bin integrals).
_FLAT_RTOL = 1e-7


@dataclass
class Echoes:
    """Detected echoes of a block of pixels, ordered by pixel then by time (echo_index 0 = first)."""

    pixel: np.ndarray        # (K,) int64 local pixel index
    position_bins: np.ndarray  # (K,) float64 peak position in bins, bin j centred at j + 0.5
    amplitude: np.ndarray    # (K,) float64 interpolated peak value (J per bin)
    echo_index: np.ndarray   # (K,) int16, 0-based, in time order within the pixel
    n_echoes: np.ndarray     # (K,) int16 echoes of that pixel
    snr: np.ndarray | None = None  # (K,) detection SNR (noisy receiver only)


#: Interpolation setting → the kernels' mode number.
INTERPOLATION = {"none": 0, "parabolic": 1, "gaussian": 2}


@kernel
def interpolate_at(ym, y0, yp, mode):
    """(δ, peak) of :func:`interpolate_peak` for one maximum (mode 0: none, 1: parabolic, 2: Gaussian)."""
    if mode == 0:
        return 0.0, y0
    delta, peak = 0.0, y0
    denom = ym - 2 * y0 + yp
    if denom < 0:
        delta = 0.5 * (ym - yp) / denom
        peak = y0 - 0.25 * (ym - yp) * delta
    if mode == 2 and ym > 0 and y0 > 0 and yp > 0:
        lm, l0, lp = math.log(ym), math.log(y0), math.log(yp)
        dl = lm - 2 * l0 + lp
        if dl < 0:
            delta = 0.5 * (lm - lp) / dl
            peak = math.exp(l0 - 0.25 * (lm - lp) * delta)
    return min(max(delta, -0.5), 0.5), peak


@kernel
def _interpolate_many(ym, y0, yp, mode, delta, peak):
    for i in range(ym.shape[0]):
        delta[i], peak[i] = interpolate_at(ym[i], y0[i], yp[i], mode)


def interpolate_peak(y_minus, y_0, y_plus, method: str = "gaussian"):
    """Sub-bin offset δ ∈ [−0.5, 0.5] and interpolated peak value for 3 samples around a maximum (arrays
    broadcast together; :func:`interpolate_at`).  Gaussian interpolation falls back to parabolic where a
    neighbour is not positive."""
    ym, y0, yp = (np.array(a, dtype=np.float64, order="C") for a in np.broadcast_arrays(y_minus, y_0, y_plus))
    delta, peak = np.empty(ym.shape), np.empty(ym.shape)
    _interpolate_many(ym.reshape(-1), y0.reshape(-1), yp.reshape(-1), INTERPOLATION[method], delta.reshape(-1),
                      peak.reshape(-1))
    return delta, peak


@kernel
def _compact(cand, mask, nc):
    """Move the first ``nc`` candidates with ``mask`` set to the front of ``cand``, in order; returns how many."""
    m = 0
    for k in range(nc):
        if mask[k]:
            cand[m] = cand[k]
            m += 1
    return m


@kernel
def detect_row(y, lo, n, bin0, threshold_j, relative_threshold, min_dip, max_echoes, mode, cand, out_pix, row,
               out_pos, out_amp, out_idx, out_n, k0):
    """Echoes of one waveform ``y[lo:lo + n]`` (zero outside) whose first value is gate bin ``bin0``, written
    from slot ``k0`` of the output arrays (pixel ``row``); returns the next free slot.  ``cand`` is scratch of
    at least n int64.  The rules of :func:`detect_echoes`: local maxima strictly above max(threshold_j,
    relative_threshold × peak, 0) with a rise on the left and none on the right (differences below _FLAT_RTOL
    are rounding: one candidate per flat top); peaks not resolved by a dip of ``min_dip`` merged into the
    larger; the ``max_echoes`` strongest kept in time order; 3-point interpolation; flat tops located at their
    centre corrected by the partial edge bins."""
    if n <= 0:
        return k0
    peak_max = y[lo]
    for j in range(1, n):
        peak_max = max(peak_max, y[lo + j])
    thr = max(max(threshold_j, relative_threshold * peak_max), 0.0)
    nc = 0
    for j in range(n):
        v = y[lo + j]
        if not v > thr:
            continue
        if j > 0 and not (v - y[lo + j - 1]) > _FLAT_RTOL * abs(v):
            continue
        if j < n - 1 and not (y[lo + j + 1] - v) <= _FLAT_RTOL * abs(v):
            continue
        cand[nc] = j
        nc += 1
    if nc == 0:
        return k0
    if min_dip > 0 and nc > 1:
        # valley[k]: min of y over [cand[k], cand[k + 1]); drop the smaller peak of every unresolved pair of
        # consecutive survivors at once, until all pairs are resolved
        valley = np.empty(nc - 1)
        for k in range(nc - 1):
            m = y[lo + cand[k]]
            for j in range(cand[k] + 1, cand[k + 1]):
                m = min(m, y[lo + j])
            valley[k] = m
        keep = np.ones(nc, np.bool_)
        while True:
            prev = -1
            n_alive = 0
            changed = False
            drop = np.zeros(nc, np.bool_)
            v = np.inf
            for k in range(nc):
                if not keep[k]:
                    continue
                n_alive += 1
                if prev >= 0:
                    v = valley[prev]
                    for q in range(prev + 1, k):
                        v = min(v, valley[q])
                    left, right = y[lo + cand[prev]], y[lo + cand[k]]
                    if v >= (1.0 - min_dip) * min(left, right):
                        drop[prev if left < right else k] = True
                        changed = True
                prev = k
            if n_alive < 2 or not changed:
                break
            for k in range(nc):
                if drop[k]:
                    keep[k] = False
        nc = _compact(cand, keep, nc)
    # the max_echoes strongest (ties: the earlier bin), then in time order
    n_keep = min(nc, max_echoes)
    if nc > n_keep:
        chosen = np.zeros(nc, np.bool_)
        for r in range(n_keep):
            best = -1
            for k in range(nc):
                if not chosen[k] and (best < 0 or y[lo + cand[k]] > y[lo + cand[best]]):
                    best = k
            chosen[best] = True
        _compact(cand, chosen, nc)
    for r in range(n_keep):
        j = cand[r]
        y0 = y[lo + j]
        ym = y[lo + j - 1] if j > 0 else 0.0
        yp = y[lo + j + 1] if j < n - 1 else 0.0
        delta, amp = interpolate_at(ym, y0, yp, mode)
        jg = j + bin0
        position = jg + 0.5 + delta
        if mode != 0 and j < n - 1 and abs(yp - y0) <= _FLAT_RTOL * y0:
            end = j
            while end < n - 1 and abs(y[lo + end + 1] - y0) <= _FLAT_RTOL * y0:
                end += 1
            y_right = y[lo + end + 1] if end < n - 1 else 0.0
            position = 0.5 * (jg - ym / y0 + (end + bin0) + 1 + y_right / y0)
            amp = y0
        out_pix[k0 + r] = row
        out_pos[k0 + r] = position
        out_amp[k0 + r] = amp
        out_idx[k0 + r] = r
        out_n[k0 + r] = n_keep
    return k0 + n_keep


@kernel
def _detect_rows(values, offset, length, bin0, threshold_j, relative_threshold, min_dip, max_echoes, mode,
                 out_pix, out_pos, out_amp, out_idx, out_n):
    cand = np.empty(max(1, int(length.max()) if length.shape[0] else 1), np.int64)
    k = 0
    for i in range(length.shape[0]):
        k = detect_row(values, offset[i], length[i], bin0[i], threshold_j, relative_threshold, min_dip,
                       max_echoes, mode, cand, out_pix, i, out_pos, out_amp, out_idx, out_n, k)
    return k


def detect_rows(values, offset, length, bin0, settings: DetectionSettings) -> Echoes:
    """Echoes of waveform rows stored flat: row i is ``values[offset[i]:offset[i] + length[i]]`` (zero outside),
    its first value at gate bin ``bin0[i]`` (positions are in gate bins)."""
    n_rows = len(length)
    cap = n_rows * settings.max_echoes
    pix, pos, amp = np.empty(cap, np.int64), np.empty(cap), np.empty(cap)
    idx, cnt = np.empty(cap, np.int16), np.empty(cap, np.int16)
    k = _detect_rows(np.ascontiguousarray(values, dtype=np.float64), np.asarray(offset, np.int64),
                     np.asarray(length, np.int64), np.asarray(bin0, np.int64), float(settings.threshold_j),
                     float(settings.relative_threshold), float(settings.min_dip), int(settings.max_echoes),
                     INTERPOLATION[settings.interpolation], pix, pos, amp, idx, cnt)
    return Echoes(pixel=pix[:k], position_bins=pos[:k], amplitude=amp[:k], echo_index=idx[:k], n_echoes=cnt[:k])


def detect_echoes(waveforms, settings: DetectionSettings, *, bin_offset=None) -> Echoes:
    """Find up to ``settings.max_echoes`` echoes per waveform row (n_pixels, n_bins) (:func:`detect_row`).

    ``bin_offset`` (n_pixels,) int, optional: the gate bin of each row's first column (rows that are windows
    of longer waveforms, zero outside); positions are then in gate bins."""
    w = np.ascontiguousarray(waveforms, dtype=np.float64)
    n_pix, n_bins = w.shape
    bin0 = np.zeros(n_pix, np.int64) if bin_offset is None else np.asarray(bin_offset, np.int64)
    return detect_rows(w.reshape(-1), np.arange(n_pix, dtype=np.int64) * n_bins, np.full(n_pix, n_bins, np.int64),
                       bin0, settings)


def detect_echoes_windows(windows, settings: DetectionSettings) -> Echoes:
    """:func:`detect_echoes` on waveforms stored as windows (core.physics.waveform.WaveformWindows): the same echoes.

    Every bin outside a pixel's window is exactly zero, which is what the detector assumes beyond the gate,
    so each window is detected on its own and positions are in gate bins."""
    return detect_rows(windows.values, windows.offset[:-1], windows.length, windows.start, settings)
