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
centre's time (:func:`core.physics.laser.pulse_box_cdf`, exact piecewise); energy and centroid are unchanged, and the
cells of a pixel tile its range extent continuously instead of as S separate spikes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config.settings import LaserSettings, RangeGateSettings
from ..constants import SPEED_OF_LIGHT_M_S
from ..jit import kernel
from .detection.peaks import INTERPOLATION, Echoes, detect_row
from .laser import (GAUSS_BOX_FOLD, boxes_cdf, gaussian_box1_cdf4, gaussian_box2_cdf4, gaussian_box_params,
                    gaussian_cdf4, pulse_box_cdf, pulse_cdf, pulse_half_support_s, pulse_sigma_s,
                    sorted_spread_pair, spread_drop_s)

#: Largest number of (ray, bin) terms evaluated at once by the exact method (bounds memory, ~100 MB).
MAX_TERMS = 4_000_000


def round_trip_time_s(range_m):
    """t = 2R/c (float64)."""
    return 2.0 * np.asarray(range_m, dtype=np.float64) / SPEED_OF_LIGHT_M_S


def binning_method(laser: LaserSettings, gate: RangeGateSettings) -> str:
    """``splat`` for pulses much wider than a bin (Gaussian σ > 8 bins), else ``exact``."""
    if laser.pulse_shape == "gaussian" and pulse_sigma_s(laser) > 8.0 * gate.bin_width_s:
        return "splat"
    return "exact"


@dataclass
class WaveformWindows:
    """Waveforms of n pixels stored as one window per pixel: pixel k's bins [start[k], start[k] + length[k])
    of the gate are ``values[offset[k]:offset[k + 1]]`` (J per bin, float64); every bin outside its window is
    exactly 0 (no return reaches it).  A pulse of a few bins in a gate of thousands costs its window only."""

    start: np.ndarray   # (n,) int64
    length: np.ndarray  # (n,) int64
    offset: np.ndarray  # (n + 1,) int64
    values: np.ndarray  # (offset[-1],) float64
    n_bins: int

    @property
    def n_pixels(self) -> int:
        return len(self.start)

    def bins(self):
        """(row, bin) of every stored value."""
        row = np.repeat(np.arange(self.n_pixels), self.length)
        return row, self.start[row] + (np.arange(len(self.values)) - self.offset[row])

    def dense(self) -> np.ndarray:
        """The (n, n_bins) float64 waveforms."""
        out = np.zeros((self.n_pixels, self.n_bins))
        row, col = self.bins()
        out[row, col] = self.values
        return out

    def write_rows(self, cube, rows) -> None:
        """Write the waveforms into rows ``rows`` (n,) of a (pixels, n_bins) cube (float32 or float64), whole
        rows: zeros outside the windows (the cube may be uninitialised memory, np.empty: a zeroed cube would
        be paid again in page faults when its rows are first written)."""
        _write_rows(self.start, self.length, self.offset, self.values, np.ascontiguousarray(rows, dtype=np.int64),
                    cube)


@kernel
def _write_rows(start, length, offset, values, rows, cube):
    for k in range(start.shape[0]):
        row = cube[rows[k]]
        s, n = start[k], length[k]
        row[:s] = 0.0
        for m in range(n):
            row[s + m] = values[offset[k] + m]
        row[s + n:] = 0.0


def _windows_for(pixel_local, lo, hi, n_pixels, n_bins):
    """Per pixel the smallest window covering its rays' bins [lo_i, hi_i] (rays sorted by pixel; rays with
    hi < lo touch nothing)."""
    ok = hi >= lo
    start = np.zeros(n_pixels, np.int64)
    stop = np.zeros(n_pixels, np.int64)
    if ok.any():
        p, lo_ok, hi_ok = pixel_local[ok], lo[ok], hi[ok]
        seg = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
        start[p[seg]] = np.minimum.reduceat(lo_ok, seg)
        stop[p[seg]] = np.maximum.reduceat(hi_ok, seg) + 1
    length = stop - start
    offset = np.zeros(n_pixels + 1, np.int64)
    np.cumsum(length, out=offset[1:])
    return WaveformWindows(start, length, offset, np.zeros(int(offset[-1])), n_bins)


def accumulate_waveforms(pixel_local, time_s, energy_j, n_pixels, laser: LaserSettings,
                         gate: RangeGateSettings, method: str | None = None, *, spread_s=None):
    """Waveforms (n_pixels, n_bins) float64 in J per bin for rays of the given pixels (local indices, sorted).

    ``spread_s`` (n, 2), optional: the full widths (s) of the two boxes of round-trip times each ray's cell
    spans (module docstring); rays whose boxes are all negligible take the impulse path unchanged.
    """
    return accumulate_waveform_windows(pixel_local, time_s, energy_j, n_pixels, laser, gate, method,
                                       spread_s=spread_s).dense()


def accumulate_waveform_windows(pixel_local, time_s, energy_j, n_pixels, laser: LaserSettings,
                                gate: RangeGateSettings, method: str | None = None, *,
                                spread_s=None) -> WaveformWindows:
    """:func:`accumulate_waveforms` as one window per pixel (:class:`WaveformWindows`): the same values, bit
    for bit, without the (n_pixels × n_bins) array."""
    method = method or binning_method(laser, gate)
    pixel_local = np.asarray(pixel_local, dtype=np.int64)
    if method == "exact":
        return _exact_windows(pixel_local, time_s, energy_j, n_pixels, laser, gate, spread_s)
    keep = energy_j > 0
    pixel_local, time_s, energy_j = pixel_local[keep], time_s[keep], energy_j[keep]
    # position of each return in bin units, relative to the gate opening
    u = (time_s - gate.gate_start_s) / gate.bin_width_s
    spread = None
    if spread_s is not None:  # boxes narrower than 1 % of a bin are below the method's own O(Δ²) error
        spread = np.sort(np.abs(np.asarray(spread_s, dtype=np.float64)[keep]), axis=1)[:, ::-1].copy()
        spread[spread < 1e-2 * gate.bin_width_s] = 0.0
    boxed = np.zeros(len(u), bool) if spread is None else spread[:, 0] > 0
    impulse = ~boxed
    imp = _splat_impulse_terms(u[impulse], laser, gate)
    box = _splat_spread_terms(u[boxed], spread[boxed], laser, gate) if boxed.any() else None
    lo = np.empty(len(u), np.int64)
    hi = np.empty(len(u), np.int64)
    lo[impulse], hi[impulse] = imp["lo"], imp["hi"]
    if box is not None:
        lo[boxed], hi[boxed] = box["lo"], box["hi"]
    win = _windows_for(pixel_local, lo, hi, n_pixels, gate.n_bins + 2 * _splat_pad(laser, gate))
    _add_impulses_splat(win, pixel_local[impulse], energy_j[impulse], imp)
    if box is not None:
        _add_spread(win, pixel_local[boxed], energy_j[boxed], box, laser, gate, method)
    return _splat_convolve(win, laser, gate)


def _exact_windows(pixel_local, time_s, energy_j, n_pixels, laser, gate, spread_s) -> WaveformWindows:
    """The exact method in one compiled pass (:func:`_exact_kernel`); only the rectangular pulse's boxed returns
    are binned afterwards (:func:`_add_spread`)."""
    gaussian = laser.pulse_shape == "gaussian"
    sigma = pulse_sigma_s(laser) if gaussian else 0.0
    dt = gate.bin_width_s
    half_s = pulse_half_support_s(laser)
    spread = (np.zeros((0, 2)) if spread_s is None
              else np.ascontiguousarray(np.asarray(spread_s, dtype=np.float64).reshape(-1, 2)))
    time_s = np.ascontiguousarray(time_s, dtype=np.float64)
    energy_j = np.ascontiguousarray(energy_j, dtype=np.float64)
    start, length, offset, values, u, lo, hi, box_a, box_b, rect_boxed = _exact_kernel(
        np.ascontiguousarray(pixel_local), time_s, energy_j, spread, n_pixels, gate.gate_start_s, dt,
        gate.n_bins, sigma, half_s / sigma if gaussian else 0.0, GAUSS_BOX_FOLD * sigma, half_s,
        spread_drop_s(laser), 0.0 if gaussian else laser.pulse_fwhm_s)
    win = WaveformWindows(start, length, offset, values, gate.n_bins)
    if rect_boxed.any():  # rectangular pulse ⊛ boxes, after the impulses (as they always were)
        sel = np.flatnonzero(rect_boxed)
        terms = {"lo": lo[sel], "hi": hi[sel], "c": u[sel], "kind": np.zeros(len(sel), np.int64),
                 "spread": np.stack([box_a[sel], box_b[sel]], axis=1)}
        _add_spread(win, pixel_local[sel], energy_j[sel], terms, laser, gate, "exact")
    return win


@kernel
def _exact_kernel(pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold,
                  half_s, drop, rect_width):
    """The exact method's windows and values: per return (energy > 0; rays sorted by pixel) its position u in
    bins, its boxes (:func:`core.physics.laser.sorted_spread_pair`, :func:`~core.physics.laser.gaussian_box_params`)
    and its bins [lo, hi] within the pulse's support; per pixel the window covering its returns; then each
    return's CDF differences added in ray order (:func:`_bin_return`).  Impulses with a rectangular pulse of
    full width ``rect_width`` are binned here; its boxed returns are flagged (``rect_boxed``) and left."""
    n = time_s.shape[0]
    u = np.empty(n)
    lo = np.zeros(n, np.int64)
    hi = np.full(n, -1, np.int64)
    binned_hi = np.full(n, -1, np.int64)
    sig = np.empty(n)
    box_a = np.zeros(n)
    box_b = np.zeros(n)
    kind = np.zeros(n, np.int64)
    rect_boxed = np.zeros(n, np.bool_)
    start = np.zeros(n_pixels, np.int64)
    stop = np.zeros(n_pixels, np.int64)
    imp_half = half_s / dt
    imp_k = int(math.ceil(2 * imp_half)) + 2  # bins touched by one impulse
    has_spread = spread.shape[0] > 0
    for i in range(n):
        if not energy[i] > 0:
            continue
        c = (time_s[i] - gate_start_s) / dt
        u[i] = c
        a, b = 0.0, 0.0
        if has_spread:
            a, b = sorted_spread_pair(spread[i, 0], spread[i, 1], drop)
        if a > 0:
            if rect_width > 0:
                half = (half_s + 0.5 * (a + b)) / dt
                rect_boxed[i] = True
            else:
                sig[i], a, b, kind[i] = gaussian_box_params(a, b, sigma, fold)
                half = (half_ratio * sig[i] + 0.5 * (a + b)) / dt
            box_a[i], box_b[i] = a, b
            lo[i] = int(max(math.floor(c - half), 0.0))
            hi[i] = int(min(math.floor(c + half), n_bins - 1.0))
            if not rect_boxed[i]:
                binned_hi[i] = hi[i]
        else:
            sig[i] = sigma
            first = int(math.floor(c - imp_half))
            lo[i] = max(first, 0)
            hi[i] = min(first + imp_k - 1, n_bins - 1)
            if c + imp_half >= 0 and c - imp_half < n_bins:  # impulses outside the gate add nothing
                binned_hi[i] = hi[i]
            else:
                binned_hi[i] = lo[i] - 1
        if hi[i] >= lo[i]:
            p = pixel[i]
            if stop[p] == 0:
                start[p], stop[p] = lo[i], hi[i] + 1
            else:
                start[p], stop[p] = min(start[p], lo[i]), max(stop[p], hi[i] + 1)
    length = stop - start
    offset = np.zeros(n_pixels + 1, np.int64)
    for p in range(n_pixels):
        offset[p + 1] = offset[p] + length[p]
    values = np.zeros(offset[n_pixels])
    buf = np.empty(64)
    for i in range(n):
        b0, b1 = lo[i], binned_hi[i]
        if b1 < b0:
            continue
        if b1 - b0 + 5 > buf.shape[0]:  # (the edges in whole groups of four: _bin_return)
            buf = np.empty(2 * (b1 - b0 + 5))
        _bin_return(values, offset[pixel[i]] - start[pixel[i]], b0, b1, u[i], energy[i], sig[i], box_a[i],
                    box_b[i], kind[i], dt, rect_width, buf)
    return start, length, offset, values, u, lo, hi, box_a, box_b, rect_boxed


@kernel(inline=True)
def _bin_return(values, base, b0, b1, c, e, s, a, b, k, dt, rect_width, buf):
    """One return's pulse CDF differences over its bins [b0, b1] added at ``values[base + j]``: the CDF at the
    b1 − b0 + 2 edges into ``buf``, one loop per kind (no branch inside), then the differences.  A Gaussian
    pulse (``rect_width`` 0) ⊛ the return's boxes (the kinds of :func:`core.physics.laser.gaussian_box_cdf_at`,
    on its cubic tail tables: they are compiled into this kernel, whose cache numba keys on this file only, so a
    change of the tables must touch this file too), or a rectangular pulse of full width ``rect_width``
    (impulses only).  The Gaussian kinds run four edges at a time (``gaussian_cdf4``, ``gaussian_box1_cdf4``,
    ``gaussian_box2_cdf4``: bit for bit the scalar kernel; ``buf`` holds b1 − b0 + 5 values).  Bins whose weight
    is not positive add +0.0 (the windows start at +0.0 and only grow: the same values)."""
    n = b1 - b0 + 2
    inv_s = 1.0 / s if s > 0 else 0.0
    inv_a = 1.0 / a if a > 0 else 0.0
    inv_ab = 1.0 / (a * b) if b > 0 else 0.0
    if rect_width > 0:
        inv_w = 1.0 / rect_width
        for j in range(n):
            buf[j] = min(max((b0 + j - c) * dt * inv_w + 0.5, 0.0), 1.0)
    elif k == 0:  # four edges at a time (the last group's extra edges are computed and not used)
        for j in range(0, n, 4):
            gaussian_cdf4(buf, j, np.float64(b0 + j), c, dt, inv_s)
    elif k == 1:
        for j in range(0, n, 4):
            gaussian_box1_cdf4(buf, j, np.float64(b0 + j), c, dt, s, inv_s, a, inv_a)
    else:
        for j in range(0, n, 4):
            gaussian_box2_cdf4(buf, j, np.float64(b0 + j), c, dt, s, inv_s, a, b, inv_ab)
    dst = values[base + b0:base + b0 + n - 1]
    for j in range(n - 1):  # (no branch: vectorised)
        w = (buf[j + 1] - buf[j]) * e
        dst[j] += w if w > 0 else 0.0


def _ragged_add(win, pixel, col, weight, valid):
    """Add ``weight`` at bins ``col`` of pixels ``pixel`` (a run of whole pixels, sorted) into the windows."""
    p0, p1 = int(pixel[0]), int(pixel[-1]) + 1
    base = win.offset[p0]
    flat = win.offset[pixel].reshape(-1, 1) - base + col - win.start[pixel].reshape(-1, 1)
    win.values[base:win.offset[p1]] += np.bincount(flat[valid], weights=weight[valid],
                                                   minlength=int(win.offset[p1] - base))


def _splat_impulse_terms(u, laser, gate):
    """Bins of the padded splat histogram touched by impulse returns: [lo, hi] per ray."""
    pad = _splat_pad(laser, gate)
    n_ext = gate.n_bins + 2 * pad
    c = u - 0.5 + pad  # impulse at position u (bin units, bin centres at j + 0.5) in the padded index space
    j0 = np.floor(c).astype(np.int64)
    return {"c": c, "j0": j0, "lo": np.maximum(j0, 0), "hi": np.minimum(j0 + 1, n_ext - 1)}


def _splat_pad(laser, gate) -> int:
    return int(np.ceil(pulse_half_support_s(laser) / gate.bin_width_s)) + 1


def _add_impulses_splat(win, pixel_local, energy_j, terms):
    """Impulses split linearly between the two nearest bin centres (the padded histogram)."""
    j0, frac = terms["j0"], terms["c"] - terms["j0"]
    n_ext = win.n_bins
    for j, w in ((j0, 1.0 - frac), (j0 + 1, frac)):
        ok = (j >= 0) & (j < n_ext)
        if ok.any():
            _ragged_add(win, pixel_local[ok], j[ok, None], (energy_j * w)[ok, None], np.ones((ok.sum(), 1), bool))


def _splat_convolve(hist: WaveformWindows, laser, gate) -> WaveformWindows:
    """Each pixel's histogram window convolved with the bin-integrated pulse, cut to the gate: pixels grouped
    by window length, one FFT convolution per group (a row's result does not depend on the others)."""
    pad = _splat_pad(laser, gate)
    n_bins = gate.n_bins
    # bin-integrated pulse for an impulse at a bin centre: kernel[m] = P((m + 0.5)Δ) − P((m − 0.5)Δ)
    m = np.arange(-pad, pad + 1)
    kernel = np.diff(pulse_cdf(laser, (np.append(m, pad + 1) - 0.5) * gate.bin_width_s))
    # output window in gate bins: [start − 2·pad, start + length) ∩ [0, n_bins)
    g0 = hist.start - 2 * pad
    g_lo = np.clip(g0, 0, n_bins)
    g_hi = np.clip(hist.start + hist.length, 0, n_bins)
    has = (hist.length > 0) & (g_hi > g_lo)
    out_len = np.where(has, g_hi - g_lo, 0)
    offset = np.zeros(hist.n_pixels + 1, np.int64)
    np.cumsum(out_len, out=offset[1:])
    out = WaveformWindows(np.where(has, g_lo, 0), out_len, offset, np.zeros(int(offset[-1])), n_bins)
    size = bucket_size(np.maximum(hist.length, 1))
    for lb in np.unique(size[has]):
        rows = np.flatnonzero(has & (size == lb))
        dense = np.zeros((len(rows), int(lb)))
        rr = np.repeat(np.arange(len(rows)), hist.length[rows])
        src = np.concatenate([np.arange(hist.offset[r], hist.offset[r + 1]) for r in rows])
        dense[rr, src - hist.offset[rows][rr]] = hist.values[src]
        from scipy.signal import fftconvolve  # imported where used: scipy.signal costs 0.7 s of start-up

        conv = fftconvolve(dense, kernel[None, :], mode="full", axes=1)  # index 0 ↔ gate bin start − 2·pad
        conv = np.maximum(conv, 0.0)
        for i, r in enumerate(rows):
            a = g_lo[r] - g0[r]
            out.values[offset[r]:offset[r + 1]] = conv[i, a:a + out_len[r]]
    return out


def bucket_size(k):
    """Round term counts up to a few sizes (≤ 25 % waste) so rays of similar support are evaluated together."""
    k = np.maximum(np.asarray(k, dtype=np.int64), 1)
    step = np.maximum(4, 2 ** np.maximum(np.floor(np.log2(k)).astype(np.int64) - 2, 0))
    return (-(-k // step)) * step


def _pixel_chunks(pixel_local, n_terms_per_ray, budget=MAX_TERMS, whole_pixels=False):
    """Ray ranges [a, b) of about ``budget`` terms that end on pixel boundaries (a pixel's rays are split only
    when they alone exceed the budget — at offsets fixed relative to the pixel — unless ``whole_pixels``), so
    every pixel's sum runs over the same rays in the same order whatever the caller's block size."""
    n = len(pixel_local)
    if n == 0:
        return []
    per = max(1, budget // max(int(n_terms_per_ray), 1))
    starts = np.flatnonzero(np.r_[True, pixel_local[1:] != pixel_local[:-1]])
    ends = np.r_[starts[1:], n]
    chunks = []
    i = 0
    while i < len(starts):
        s, e = int(starts[i]), int(ends[i])
        if e - s > per:  # one pixel alone over budget
            chunks += [(s, e)] if whole_pixels else [(x, min(x + per, e)) for x in range(s, e, per)]
            i += 1
            continue
        # as many whole pixels as fit
        j = int(np.searchsorted(ends, s + per, side="right")) - 1
        j = max(j, i)
        chunks.append((s, int(ends[j])))
        i = j + 1
    return chunks


def _splat_spread_terms(u, spread_s, laser, gate):
    """Bins of the padded splat histogram touched by returns spread over a box of times: per ray [lo, hi]."""
    pad = _splat_pad(laser, gate)
    half = 1.0 + 0.5 * (spread_s[:, 0] + spread_s[:, 1]) / gate.bin_width_s  # trapezoid ⊛ U(1) + the bin's half
    c = u + (pad - 0.5)  # centre index space of the splat histogram
    return {"kind": np.zeros(len(u), np.int64), "spread": spread_s, "c": c,
            "lo": np.maximum(np.floor(c - half), 0).astype(np.int64),
            "hi": np.minimum(np.floor(c + half), gate.n_bins + 2 * pad - 1).astype(np.int64)}


def _add_spread(win, pixel_local, energy_j, terms, laser, gate, method):
    """Returns whose cell spans a range interval: the rectangular pulse ⊛ trapezoid integrated over each bin
    (exact), or the trapezoid ⊛ U(Δ) over each bin of the padded histogram (splat, convolved with the pulse afterwards)."""
    dt = gate.bin_width_s
    lo, hi, c, kind = terms["lo"], terms["hi"], terms["c"], terms["kind"]
    size = bucket_size(hi - lo + 1)
    inside = hi >= lo
    # fixed order over (kind, bucket size): every pixel's sum is independent of the caller's blocks
    for kd in np.unique(kind[inside]):
        for kb in np.unique(size[inside & (kind == kd)]):
            sel = np.flatnonzero(inside & (kind == kd) & (size == kb))
            offsets = np.arange(kb + 1)
            for a, b in _pixel_chunks(pixel_local[sel], kb + 1):
                idx = sel[a:b]
                edges = lo[idx, None] + offsets[None, :]  # bin edges j (bins span [j, j + 1) in this index space)
                if method == "exact":  # rectangular pulse (the Gaussian one is binned by _exact_kernel)
                    cdf = pulse_box_cdf(laser, (edges - c[idx, None]) * dt, terms["spread"][idx])
                else:
                    # the splat's linear split between centres is a box of one bin: widths (a, b, Δ) in bins
                    w3 = np.sort(np.concatenate([terms["spread"][idx] / dt, np.ones((len(idx), 1))], axis=1),
                                 axis=1)
                    cdf = boxes_cdf(edges - 0.5 - c[idx, None], w3[:, None, ::-1])
                weight = np.diff(cdf, axis=1) * energy_j[idx, None]
                bins = edges[:, :-1]
                valid = (bins <= hi[idx, None]) & (weight > 0)
                _ragged_add(win, pixel_local[idx], bins, weight, valid)


# ----------------------------------------------------------------------------------------------------------
# The tabulated pulse (scanners: millions of pulses of a few returns each)
# ----------------------------------------------------------------------------------------------------------
class PulseTable:
    """The bin-integrated Gaussian pulse tabulated against the return's position inside its bin.

    A return at u = j + f bins (0 ≤ f < 1) puts w_m(f) = P((m + 1 − f)Δ) − P((m − f)Δ) into bin j + m,
    m = −K … K (K covers the pulse's ±6.1σ support).  Rows are tabulated at f = i/N (N = 512) and interpolated
    linearly in f: each row sums to the same energy, so energy is kept exactly, and the interpolation error is
    ≈ (1/N)²/8 · |∂²w/∂f²| ≈ 5·10⁻⁷/σ² (σ in bins) of the bin value — far below the waveform's own precision,
    at a fraction of the cost of evaluating the CDF for every ray and bin (scanners fire millions of pulses).
    """

    N = 512

    def __init__(self, laser, bin_width_s):
        half = pulse_half_support_s(laser) / bin_width_s
        self.half = half
        self.k = int(np.ceil(half)) + 1
        m = np.arange(-self.k, self.k + 1)
        f = np.arange(self.N + 1) / self.N
        edges = (m[None, :] - f[:, None]) * bin_width_s
        self.rows = np.diff(pulse_cdf(laser, np.concatenate([edges, edges[:, -1:] + bin_width_s], axis=1)), axis=1)
        self.offsets = m
        # the rows padded with zero columns to a multiple of 8 (:func:`_table_echoes`' whole-support path)
        self.wide = np.zeros((self.N + 1, -(-(2 * self.k + 1) // 8) * 8))
        self.wide[:, :2 * self.k + 1] = self.rows

    def waveforms(self, pulse_local, u, energy_j, n_pulses, n_bins):
        """(n_pulses, n_bins) float64 J per bin; u in bins of the (window) gate; pulse_local sorted ascending."""
        out = np.zeros((n_pulses, n_bins))
        _table_waveforms(np.asarray(pulse_local, np.int64), np.asarray(u, np.float64),
                         np.asarray(energy_j, np.float64), self.rows, self.k, out)
        return out

    def echoes(self, pulse_local, u, energy_j, n_pulses, n_bins, detection) -> Echoes:
        """Echoes of each pulse's waveform over the gate's ``n_bins`` bins (returns at u bins, pulse_local in
        [0, n_pulses) sorted ascending; returns outside the gate or without energy add nothing), built over the
        bins its returns touch and detected there (:func:`core.echoes.detect_row`: zero outside, as beyond the
        gate).  The echo arrays are sized for the echoes found (a pulse has at most ``max_echoes``)."""
        cap = min(len(u), n_pulses) * detection.max_echoes
        pix, pos, amp = np.empty(cap, np.int64), np.empty(cap), np.empty(cap)
        idx, cnt = np.empty(cap, np.int16), np.empty(cap, np.int16)
        k = _table_echoes(np.asarray(pulse_local, np.int64), np.asarray(u, np.float64),
                          np.asarray(energy_j, np.float64), self.rows, self.wide, self.k, self.half, n_bins,
                          float(detection.threshold_j), float(detection.relative_threshold),
                          float(detection.min_dip), int(detection.max_echoes), INTERPOLATION[detection.interpolation],
                          pix, pos, amp, idx, cnt)
        return Echoes(pixel=pix[:k].copy(), position_bins=pos[:k].copy(), amplitude=amp[:k].copy(),
                      echo_index=idx[:k].copy(), n_echoes=cnt[:k].copy())


@kernel
def table_add_return(buf, b0, length, u, energy, rows, k):
    """Add one return at u (gate bins) of ``energy`` to ``buf`` holding gate bins [b0, b0 + length) — bins
    outside dropped — from the tabulated pulse ``rows`` ((N + 1, 2k + 1), linear in the position in the bin)."""
    n_tab = rows.shape[0] - 1
    j = math.floor(u)
    x = (u - j) * n_tab
    i = min(int(x), n_tab - 1)
    w = x - i
    first = int(j) - k - b0
    m0, m1 = max(0, -first), min(rows.shape[1], length - first)  # the table columns that land in the buffer
    if m1 <= m0:
        return
    out, r0, r1 = buf[first + m0:first + m1], rows[i, m0:m1], rows[i + 1, m0:m1]
    v = 1.0 - w
    for q in range(m1 - m0):  # (no test inside: the compiler vectorises it)
        out[q] += (r0[q] * v + r1[q] * w) * energy


@kernel
def _table_waveforms(pulse, u, energy, rows, k, out):
    for r in range(u.shape[0]):
        table_add_return(out[pulse[r]], 0, out.shape[1], u[r], energy[r], rows, k)


@kernel
def _table_echoes(pulse, u, energy, rows, wide, k, half, n_bins, threshold_j, relative_threshold, min_dip, max_echoes,
                  mode, out_pix, out_pos, out_amp, out_idx, out_n):
    """Each pulse's waveform over the bins its returns touch, then its echoes (:func:`detect_row`).  A return
    whose whole support lies inside the pulse's window (the usual case: a pulse's sub-rays land within a few bins
    of each other) is added from ``wide`` — the rows padded with zero columns to a multiple of 8 — over the
    padded width, a loop of a fixed multiple of the vector width with no clipping.  Its zero columns add terms of
    +0.0 (finite energy, interpolation weights ≥ +0) to the bins after its support, up to 7 bins past the window
    (``buf`` has room; those bins are never read), and x + (+0.0) = x for every x but −0.0, which the buffer
    never holds (it starts at +0.0; a rounded sum is −0.0 only when both terms are): bit for bit
    :func:`table_add_return`'s sums, in the same order.  An infinite energy (whose padded terms would be NaN)
    takes the clipped path."""
    n_tab = rows.shape[0] - 1
    ncol, wcol = rows.shape[1], wide.shape[1]
    buf = np.zeros(n_bins + wcol)
    cand = np.empty(n_bins, np.int64)
    n_out = 0
    a = 0
    n = u.shape[0]
    while a < n:
        b = a
        while b < n and pulse[b] == pulse[a]:
            b += 1
        lo, hi = n_bins, -1
        for r in range(a, b):
            if energy[r] > 0 and u[r] + half >= 0 and u[r] - half < n_bins:
                j = int(math.floor(u[r]))
                lo = min(lo, max(j - k, 0))
                hi = max(hi, min(j + k, n_bins - 1))
        if hi >= lo:
            length = hi - lo + 1
            buf[:length + wcol - ncol] = 0.0
            for r in range(a, b):
                e = energy[r]
                if e > 0 and u[r] + half >= 0 and u[r] - half < n_bins:
                    j = math.floor(u[r])
                    first = int(j) - k - lo
                    if first >= 0 and first + ncol <= length and e < math.inf:
                        x = (u[r] - j) * n_tab  # (table_add_return's interpolation)
                        i = min(int(x), n_tab - 1)
                        w = x - i
                        v = 1.0 - w
                        out, r0, r1 = buf[first:first + wcol], wide[i], wide[i + 1]
                        for q in range(wcol):
                            out[q] += (r0[q] * v + r1[q] * w) * e
                    else:
                        table_add_return(buf, lo, length, u[r], e, rows, k)
            n_out = detect_row(buf, 0, length, lo, threshold_j, relative_threshold, min_dip, max_echoes, mode,
                               cand, out_pix, pulse[a], out_pos, out_amp, out_idx, out_n, n_out)
        a = b
    return n_out
