"""Time: the scene's impulse response accumulated into waveform bins, convolved with the pulse (paper §3.1,
"the scene as an impulse response to the three-dimensional energy distribution of the laser illumination").

Each sub-ray returns the energy E_i at the round-trip time t_i = 2R_i/c.  The energy bin j collects is the pulse
integrated over the bin (no point sampling, so pulses narrower than a bin are exact):

    w_j = Σ_i E_i [P(t_{j+1} − t_i) − P(t_j − t_i)],   t_j = t_gate + jΔ,   P the pulse CDF.

Two exact-in-energy methods:

* ``exact``: the sum above, evaluated over the bins within the pulse's support (Gaussian ±6.1σ);
* ``splat``: when the pulse spans many bins (σ > 8Δ), each impulse is split linearly between the two nearest
  bin centres (energy and centroid preserved) and the per-pixel impulse histogram is convolved with the
  bin-integrated pulse by FFT.  Its relative error is O(Δ²/8σ²) < 0.2 %.

Cell range spread (``spread_s``): a sub-ray stands for a cell of the pixel, and the surface inside the cell
spans a range interval (a tilted or grazing surface).  To first order the range is linear over the cell, so
the cell's round-trip times are uniform over a box of width a = (2/c)|∂R/∂x|δx convolved with one of width
b = (2/c)|∂R/∂y|δy (a trapezoid).  The return is then the pulse ⊛ U(a) ⊛ U(b) instead of the pulse at the cell
centre's time (:func:`core.laser.pulse_box_cdf`, exact piecewise); energy and centroid are unchanged, and the
cells of a pixel tile its range extent continuously instead of as S separate spikes.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import fftconvolve

from .config import LaserSettings, RangeGateSettings
from .laser import (boxes_cdf, gaussian_box_cdf, gaussian_box_terms, pulse_box_cdf, pulse_cdf, pulse_half_support_s,
                    pulse_sigma_s, sorted_spreads)

SPEED_OF_LIGHT_M_S = 299_792_458.0
#: Largest number of (ray, bin) terms evaluated at once by the exact method (bounds memory, ~100 MB).
_MAX_TERMS = 4_000_000


def round_trip_time_s(range_m):
    """t = 2R/c (float64)."""
    return 2.0 * np.asarray(range_m, dtype=np.float64) / SPEED_OF_LIGHT_M_S


def binning_method(laser: LaserSettings, gate: RangeGateSettings) -> str:
    """``splat`` for pulses much wider than a bin (Gaussian σ > 8 bins), else ``exact``."""
    if laser.pulse_shape == "gaussian" and pulse_sigma_s(laser) > 8.0 * gate.bin_width_s:
        return "splat"
    return "exact"


def accumulate_waveforms(pixel_local, time_s, energy_j, n_pixels, laser: LaserSettings,
                         gate: RangeGateSettings, method: str | None = None, *, spread_s=None):
    """Waveforms (n_pixels, n_bins) float64 in J per bin for rays of the given pixels (local indices, sorted).

    ``spread_s`` (n, 2), optional: the full widths (s) of the two boxes of round-trip times each ray's cell
    spans (module docstring); rays whose boxes are all negligible take the impulse path unchanged.
    """
    method = method or binning_method(laser, gate)
    keep = energy_j > 0
    pixel_local, time_s, energy_j = pixel_local[keep], time_s[keep], energy_j[keep]
    # position of each return in bin units, relative to the gate opening
    u = (time_s - gate.gate_start_s) / gate.bin_width_s
    spread = None
    if spread_s is not None:
        spread_s = np.asarray(spread_s, dtype=np.float64)[keep]
        if method == "exact":
            spread = sorted_spreads(laser, spread_s)
        else:  # splat: boxes narrower than 1 % of a bin are below the method's own O(Δ²) error
            spread = np.sort(np.abs(spread_s), axis=1)[:, ::-1].copy()
            spread[spread < 1e-2 * gate.bin_width_s] = 0.0
    impulse = None if spread is None else spread[:, 0] == 0
    if impulse is not None and impulse.all():
        impulse = spread = None
    if spread is None:
        if method == "exact":
            return _accumulate_exact(pixel_local, u, energy_j, n_pixels, laser, gate)
        return _accumulate_splat(pixel_local, u, energy_j, n_pixels, laser, gate)
    boxed = ~impulse
    if method == "exact":
        out = _accumulate_exact(pixel_local[impulse], u[impulse], energy_j[impulse], n_pixels, laser, gate)
        _add_spread(out.reshape(-1), pixel_local[boxed], u[boxed], energy_j[boxed], spread[boxed], laser, gate,
                    method)
        return out
    hist = _splat_histogram(pixel_local[impulse], u[impulse], energy_j[impulse], n_pixels, laser, gate)
    _add_spread(hist, pixel_local[boxed], u[boxed], energy_j[boxed], spread[boxed], laser, gate, method)
    return _splat_convolve(hist, n_pixels, laser, gate)


def _bucket_size(k):
    """Round term counts up to a few sizes (≤ 25 % waste) so rays of similar support are evaluated together."""
    k = np.maximum(np.asarray(k, dtype=np.int64), 1)
    step = np.maximum(4, 2 ** np.maximum(np.floor(np.log2(k)).astype(np.int64) - 2, 0))
    return (-(-k // step)) * step


def _pixel_chunks(pixel_local, n_terms_per_ray, budget=_MAX_TERMS):
    """Ray ranges [a, b) of about ``budget`` terms that end on pixel boundaries (a pixel's rays are split only
    when they alone exceed the budget, and then at offsets fixed relative to the pixel), so every pixel's sum
    runs over the same rays in the same order whatever the caller's block size."""
    n = len(pixel_local)
    if n == 0:
        return []
    per = max(1, budget // max(int(n_terms_per_ray), 1))
    starts = np.flatnonzero(np.r_[True, pixel_local[1:] != pixel_local[:-1]])
    ends = np.r_[starts[1:], n]
    chunks, a = [], 0
    i = 0
    while i < len(starts):
        s, e = int(starts[i]), int(ends[i])
        if e - s > per:  # one pixel alone over budget: fixed sub-chunks of this pixel
            chunks += [(x, min(x + per, e)) for x in range(s, e, per)]
            i += 1
            continue
        # as many whole pixels as fit
        j = int(np.searchsorted(ends, s + per, side="right")) - 1
        j = max(j, i)
        chunks.append((s, int(ends[j])))
        i = j + 1
    return chunks


def _add_spread(out, pixel_local, u, energy_j, spread_s, laser, gate, method):
    """Add rays whose cell spans a range interval into ``out`` (flat): the pulse ⊛ trapezoid integrated over
    each bin (exact, out = waveforms), or the trapezoid ⊛ U(Δ) over each bin (splat, out = the padded impulse
    histogram that is then convolved with the bin-integrated pulse)."""
    n_bins = gate.n_bins
    dt = gate.bin_width_s
    n = len(u)
    gaussian_exact = method == "exact" and laser.pulse_shape == "gaussian"
    kind = np.zeros(n, np.int64)
    if gaussian_exact:  # narrow boxes folded into a per-ray σ (core.laser.gaussian_box_terms)
        sigma, box_a, box_b, kind = gaussian_box_terms(laser, spread_s)
        half = (pulse_half_support_s(laser) / pulse_sigma_s(laser) * sigma + 0.5 * (box_a + box_b)) / dt
    elif method == "exact":
        half = (pulse_half_support_s(laser) + 0.5 * (spread_s[:, 0] + spread_s[:, 1])) / dt
    if method == "exact":
        n_out, offset = n_bins, 0.0
    else:
        pad = _splat_pad(laser, gate)
        half = 1.0 + 0.5 * (spread_s[:, 0] + spread_s[:, 1]) / dt  # trapezoid ⊛ U(1) plus the bin's half
        n_out, offset = n_bins + 2 * pad, pad - 0.5  # centre index space of the splat histogram (c = u − ½ + pad)
    c = u + offset
    lo = np.maximum(np.floor(c - half), 0).astype(np.int64)
    hi = np.minimum(np.floor(c + half), n_out - 1).astype(np.int64)
    size = _bucket_size(hi - lo + 1)
    inside = hi >= lo
    # fixed order over (kind, bucket size): every pixel's sum is independent of the caller's blocks
    for kd in np.unique(kind[inside]):
        for kb in np.unique(size[inside & (kind == kd)]):
            sel = np.flatnonzero(inside & (kind == kd) & (size == kb))
            offsets = np.arange(kb + 1)
            for a, b in _pixel_chunks(pixel_local[sel], kb + 1):
                idx = sel[a:b]
                edges = lo[idx, None] + offsets[None, :]  # bin edges j (bins span [j, j + 1) in this index space)
                if gaussian_exact:
                    cdf = gaussian_box_cdf((edges - c[idx, None]) * dt, sigma[idx, None], box_a[idx, None],
                                           box_b[idx, None], int(kd))
                elif method == "exact":
                    cdf = pulse_box_cdf(laser, (edges - c[idx, None]) * dt, spread_s[idx])
                else:
                    # the splat's linear split between centres is a box of one bin: widths (a, b, Δ) in bins
                    w3 = np.sort(np.concatenate([spread_s[idx] / dt, np.ones((len(idx), 1))], axis=1), axis=1)
                    cdf = boxes_cdf(edges - 0.5 - c[idx, None], w3[:, None, ::-1])
                weight = np.diff(cdf, axis=1) * energy_j[idx, None]
                bins = edges[:, :-1]
                valid = (bins <= hi[idx, None]) & (weight > 0)
                p0, p1 = int(pixel_local[idx[0]]), int(pixel_local[idx[-1]]) + 1  # sorted: the chunk's pixels
                flat = (pixel_local[idx, None].astype(np.int64) - p0) * n_out + bins
                out[p0 * n_out:p1 * n_out] += np.bincount(flat[valid], weights=weight[valid],
                                                          minlength=(p1 - p0) * n_out)
    return out


def _accumulate_exact(pixel_local, u, energy_j, n_pixels, laser, gate, out=None):
    """Impulse returns, pulse CDF differences over the bins within the pulse's support; added into ``out``
    (flat, n_pixels·n_bins) when given."""
    n_bins = gate.n_bins
    half = pulse_half_support_s(laser) / gate.bin_width_s
    k = int(np.ceil(2 * half)) + 2  # bins touched by one pulse
    if out is None:
        out = np.zeros(n_pixels * n_bins)
    inside = (u + half >= 0) & (u - half < n_bins)
    pixel_local, u, energy_j = pixel_local[inside], u[inside], energy_j[inside]
    offsets = np.arange(k)
    # sub-chunks end on pixel boundaries so every pixel's sum runs over the same rays in the same order,
    # whatever the block size: products do not depend on chunking
    per_chunk = max(1, _MAX_TERMS // k)
    bounds = np.searchsorted(pixel_local, np.arange(n_pixels + 1), side="left")
    a = 0
    while a < len(u):
        p_end = int(np.searchsorted(bounds, a + per_chunk, side="right")) - 1
        b = int(bounds[max(p_end, int(pixel_local[a]) + 1)])
        uu = u[a:b]
        first = np.floor(uu - half).astype(np.int64)
        bins = first[:, None] + offsets[None, :]
        # bin j spans [j, j+1) in bin units; the pulse CDF is evaluated at the edges relative to the return
        lower = (bins - uu[:, None]) * gate.bin_width_s
        cdf = pulse_cdf(laser, np.concatenate([lower, lower[:, -1:] + gate.bin_width_s], axis=1))
        weight = np.diff(cdf, axis=1) * energy_j[a:b, None]
        valid = (bins >= 0) & (bins < n_bins) & (weight > 0)
        p0, p1 = int(pixel_local[a]), int(pixel_local[b - 1]) + 1  # the chunk's pixels (sorted)
        flat = (pixel_local[a:b, None].astype(np.int64) - p0) * n_bins + bins
        out[p0 * n_bins:p1 * n_bins] += np.bincount(flat[valid], weights=weight[valid], minlength=(p1 - p0) * n_bins)
        a = b
    return out.reshape(n_pixels, n_bins)


def _splat_pad(laser, gate) -> int:
    return int(np.ceil(pulse_half_support_s(laser) / gate.bin_width_s)) + 1


def _splat_histogram(pixel_local, u, energy_j, n_pixels, laser, gate):
    """Impulses split linearly between the two nearest bin centres, on the gate padded by the pulse support."""
    pad = _splat_pad(laser, gate)
    n_ext = gate.n_bins + 2 * pad
    # impulse at position u (bin units, bin centres at j + 0.5): split between the two nearest centres
    c = u - 0.5 + pad
    j0 = np.floor(c).astype(np.int64)
    frac = c - j0
    hist = np.zeros(n_pixels * n_ext)
    for j, w in ((j0, 1.0 - frac), (j0 + 1, frac)):
        ok = (j >= 0) & (j < n_ext)
        hist += np.bincount(pixel_local[ok].astype(np.int64) * n_ext + j[ok], weights=(energy_j * w)[ok],
                            minlength=n_pixels * n_ext)
    return hist


def _splat_convolve(hist, n_pixels, laser, gate):
    """The impulse histogram convolved with the bin-integrated pulse, cut to the gate."""
    pad = _splat_pad(laser, gate)
    n_bins = gate.n_bins
    hist = hist.reshape(n_pixels, n_bins + 2 * pad)
    # bin-integrated pulse for an impulse at a bin centre: kernel[m] = P((m + 0.5)Δ) − P((m − 0.5)Δ)
    m = np.arange(-pad, pad + 1)
    kernel = np.diff(pulse_cdf(laser, (np.append(m, pad + 1) - 0.5) * gate.bin_width_s))
    conv = fftconvolve(hist, kernel[None, :], mode="same", axes=1)
    return np.maximum(conv[:, pad:pad + n_bins], 0.0)


def _accumulate_splat(pixel_local, u, energy_j, n_pixels, laser, gate):
    return _splat_convolve(_splat_histogram(pixel_local, u, energy_j, n_pixels, laser, gate), n_pixels, laser, gate)
