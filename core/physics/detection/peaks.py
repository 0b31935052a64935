"""Echo detection on waveforms: local maxima above a threshold, up to N per pixel, with 3-point sub-bin
interpolation (docs/theory.md §9):

    parabolic  δ = (y₋ − y₊) / (2 (y₋ − 2y₀ + y₊))
    Gaussian   the same on ln y (exact for a sampled Gaussian pulse)

Vectorized over pixels: candidates are found on the whole block at once, ranked per pixel by amplitude.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...config.settings import DetectionSettings
from ..waveform import bucket_size

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


def interpolate_peak(y_minus, y_0, y_plus, method: str = "gaussian"):
    """Sub-bin offset δ ∈ [−0.5, 0.5] and interpolated peak value for 3 samples around a maximum.

    Gaussian interpolation falls back to parabolic where a neighbour is not positive.
    """
    y_minus, y_0, y_plus = (np.asarray(a, dtype=np.float64) for a in (y_minus, y_0, y_plus))
    delta = np.zeros(np.broadcast(y_minus, y_0, y_plus).shape)
    peak = np.array(np.broadcast_to(y_0, delta.shape), dtype=np.float64)
    if method == "none":
        return delta, peak
    denom = y_minus - 2 * y_0 + y_plus
    ok = denom < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        d_par = np.where(ok, 0.5 * (y_minus - y_plus) / np.where(ok, denom, -1.0), 0.0)
        p_par = y_0 - 0.25 * (y_minus - y_plus) * d_par
        delta, peak = d_par, np.where(ok, p_par, peak)
        if method == "gaussian":
            pos = (y_minus > 0) & (y_0 > 0) & (y_plus > 0)
            lm = np.log(np.where(pos, y_minus, 1.0))
            l0 = np.log(np.where(pos, y_0, 1.0))
            lp = np.log(np.where(pos, y_plus, 1.0))
            dl = lm - 2 * l0 + lp
            okg = pos & (dl < 0)
            d_g = np.where(okg, 0.5 * (lm - lp) / np.where(okg, dl, -1.0), 0.0)
            p_g = np.exp(l0 - 0.25 * (lm - lp) * d_g)
            delta = np.where(okg, d_g, delta)
            peak = np.where(okg, p_g, peak)
    return np.clip(delta, -0.5, 0.5), peak


def _merge_shallow(w, pix, j, min_dip):
    """Drop candidate peaks not resolved from a neighbour: two time-adjacent peaks of a pixel are separate
    echoes only if the waveform between them falls below (1 − min_dip) × the smaller peak; otherwise the
    smaller one is part of the larger echo (a plateau's wiggles, a shoulder).  Candidates sorted by (pixel, bin).

    Each round drops the smaller peak of every unresolved pair at once (never a group's maximum); the valley
    between the survivors is the lowest of the valleys they enclosed."""
    n_bins = w.shape[1]
    flat = np.ascontiguousarray(w).reshape(-1)
    pos = pix.astype(np.int64) * n_bins + j
    peak = flat[pos]
    same = pix[1:] == pix[:-1]
    valley = np.full(len(pos) - 1, -np.inf)
    if same.any():
        # min over [pos_k, pos_k+1) of every consecutive pair (pairs across pixels are masked)
        mins = np.minimum.reduceat(flat, pos)[:-1] if len(pos) > 1 else np.zeros(0)
        valley = np.where(same, mins, -np.inf)
    keep = np.ones(len(pos), bool)
    idx = np.arange(len(pos))
    while True:
        k = idx[keep]
        if len(k) < 2:
            break
        # valley between consecutive survivors: min of the valleys in between
        v = np.minimum.reduceat(valley[:k[-1]], k[:-1])
        v = np.where(pix[k[1:]] == pix[k[:-1]], v, -np.inf)
        left, right = peak[k[:-1]], peak[k[1:]]
        unresolved = v >= (1.0 - min_dip) * np.minimum(left, right)
        if not unresolved.any():
            break
        victim = np.where(left < right, k[:-1], k[1:])[unresolved]
        keep[victim] = False
    return pix[keep], j[keep]


def detect_echoes(waveforms, settings: DetectionSettings, *, bin_offset=None) -> Echoes:
    """Find up to ``settings.max_echoes`` echoes per waveform row (n_pixels, n_bins).

    ``bin_offset`` (n_pixels,) int, optional: the gate bin of each row's first column (rows that are windows
    of longer waveforms, zero outside); positions are then in gate bins."""
    w = np.asarray(waveforms)
    n_pix, n_bins = w.shape
    peak_max = w.max(axis=1)
    threshold = np.maximum(settings.threshold_j, settings.relative_threshold * peak_max)
    # a rise on the left, no rise on the right (one candidate per flat top; differences below _FLAT_RTOL
    # are rounding, not structure), strictly above threshold; the waveform is zero outside the gate.
    cand = np.zeros((n_pix, n_bins), dtype=bool)
    if n_bins == 1:
        cand[:, 0] = True
    else:
        rise = w[:, 1:] - w[:, :-1]
        cand[:, 1:] = rise > _FLAT_RTOL * np.abs(w[:, 1:])
        cand[:, 0] = True
        cand[:, :-1] &= rise <= _FLAT_RTOL * np.abs(w[:, :-1])
        del rise
    cand &= w > np.maximum(threshold, 0.0)[:, None]
    pix, j = np.nonzero(cand)
    if settings.min_dip > 0 and len(pix) > 1:
        pix, j = _merge_shallow(w, pix, j, settings.min_dip)
    amp = w[pix, j]
    # rank per pixel by amplitude (strongest first) and keep max_echoes
    order = np.lexsort((-amp, pix))
    pix, j, amp = pix[order], j[order], amp[order]
    start = np.searchsorted(pix, pix, side="left")
    rank = np.arange(len(pix)) - start
    keep = rank < settings.max_echoes
    pix, j = pix[keep], j[keep]
    # time order within each pixel
    order = np.lexsort((j, pix))
    pix, j = pix[order], j[order]
    y0 = w[pix, j].astype(np.float64)
    ym = np.where(j > 0, w[pix, np.maximum(j - 1, 0)], 0.0).astype(np.float64)
    yp = np.where(j < n_bins - 1, w[pix, np.minimum(j + 1, n_bins - 1)], 0.0).astype(np.float64)
    delta, peak = interpolate_peak(ym, y0, yp, settings.interpolation)
    jg = j if bin_offset is None else j + np.asarray(bin_offset, dtype=np.int64)[pix]  # gate bins
    position = jg + 0.5 + delta
    # flat tops (a rectangular pulse spanning several bins): the centre of the pulse is the plateau's centre
    # corrected by the partial edge bins, exact for a rectangular pulse: (j − y₋/y₀ + end + 1 + y₊/y₀)/2
    flat = (j < n_bins - 1) & (np.abs(yp - y0) <= _FLAT_RTOL * y0)
    if flat.any() and settings.interpolation != "none":
        end = j.copy()
        grow = flat.copy()
        while grow.any():
            end[grow] += 1
            grow &= (end < n_bins - 1) & (np.abs(w[pix, np.minimum(end + 1, n_bins - 1)] - y0) <= _FLAT_RTOL * y0)
        y_right = np.where(end < n_bins - 1, w[pix, np.minimum(end + 1, n_bins - 1)], 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            centre = 0.5 * (jg - ym / y0 + (end + (jg - j)) + 1 + y_right / y0)
        position = np.where(flat, centre, position)
        peak = np.where(flat, y0, peak)
    start = np.searchsorted(pix, pix, side="left")
    stop = np.searchsorted(pix, pix, side="right")
    return Echoes(pixel=pix.astype(np.int64), position_bins=position, amplitude=peak,
                  echo_index=(np.arange(len(pix)) - start).astype(np.int16),
                  n_echoes=(stop - start).astype(np.int16))


def detect_echoes_windows(windows, settings: DetectionSettings) -> Echoes:
    """:func:`detect_echoes` on waveforms stored as windows (core.physics.waveform.WaveformWindows): the same echoes.

    Every bin outside a pixel's window is exactly zero, which is what the detector assumes beyond the gate,
    so each window is detected on its own (pixels grouped by window length, zero padding to the right) and the
    positions are shifted back by the window's first bin."""

    parts = []
    has = windows.length > 0
    size = bucket_size(np.maximum(windows.length, 1))
    for lb in np.unique(size[has]):
        rows = np.flatnonzero(has & (size == lb))
        lengths = windows.length[rows]
        dense = np.zeros((len(rows), int(lb)))
        rr = np.repeat(np.arange(len(rows)), lengths)
        col = np.arange(int(lengths.sum())) - np.repeat(np.cumsum(lengths) - lengths, lengths)
        src = windows.offset[rows][rr] + col
        dense[rr, col] = windows.values[src]
        found = detect_echoes(dense, settings, bin_offset=windows.start[rows])
        found.pixel = rows[found.pixel]
        parts.append(found)
    if not parts:
        empty = np.zeros(0)
        return Echoes(np.zeros(0, np.int64), empty, empty, np.zeros(0, np.int16), np.zeros(0, np.int16))
    pixel = np.concatenate([p.pixel for p in parts])
    order = np.argsort(pixel, kind="stable")
    return Echoes(pixel=pixel[order], position_bins=np.concatenate([p.position_bins for p in parts])[order],
                  amplitude=np.concatenate([p.amplitude for p in parts])[order],
                  echo_index=np.concatenate([p.echo_index for p in parts])[order],
                  n_echoes=np.concatenate([p.n_echoes for p in parts])[order])
