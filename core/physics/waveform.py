"""Time: the scene's impulse response accumulated into waveform bins, convolved with the pulse (paper §3.1,
"the scene as an impulse response to the three-dimensional energy distribution of the laser illumination").

Each sub-ray returns the energy E_i at the round-trip time t_i = 2R_i/c.  The energy bin j collects is the pulse
integrated over the bin (no point sampling, so pulses narrower than a bin are exact):

    w_j = Σ_i E_i [P(t_{j+1} − t_i) − P(t_j − t_i)],   t_j = t_gate + jΔ,   P the pulse CDF.

Three methods (exact in energy):

* ``exact``: the sum above, evaluated over the bins within the pulse's support (Gaussian ±6.1σ);
* ``table`` (flash frames' default, ``gate.binning``): the exact method's sum from a table of the bin-integrated
  pulse and its integrals over the position (:class:`BoxTable`), within its stated bound of ``exact``;
* ``splat``: when the pulse spans many bins (σ > 8Δ), each impulse is split linearly between the two nearest
  bin centres (energy and centroid preserved) and the per-pixel impulse histogram is convolved with the
  bin-integrated pulse by FFT.  Its relative error is O(Δ²/8σ²) < 0.2 %.

Cell range spread (``spread_s``): a sub-ray stands for a cell of the pixel, and the surface inside the cell
spans a range interval (a tilted or grazing surface).  To first order the range is linear over the cell, so
the cell's round-trip times are uniform over a box of width a = (2/c)|∂R/∂x|δx convolved with one of width
b = (2/c)|∂R/∂y|δy (a trapezoid).  The return is then the pulse ⊛ U(a) ⊛ U(b) instead of the pulse at the cell
centre's time (:func:`core.physics.laser.pulse_box_cdf`, exact piecewise); energy and centroid are unchanged, and the
cells of a pixel tile its range extent continuously instead of as S separate spikes.

A frame that keeps no waveform (points only) bins each pixel only where its echo detection reads
(:func:`detection_windows`): the same echoes, bit for bit.
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


#: The table binning needs the pulse's σ to span this many bins at least (narrower pulses are binned exactly: the
#: table would need more than 64 rows a bin, :func:`box_table_rows`).
TABLE_MIN_SIGMA_BINS = 1.0


def flash_binning_method(laser: LaserSettings, gate: RangeGateSettings) -> str:
    """The flash frames' binning: :func:`binning_method`, with ``gate.binning`` = ``table`` turning ``exact`` into
    ``table`` (:class:`BoxTable`) for a Gaussian pulse of σ ≥ ``TABLE_MIN_SIGMA_BINS`` bins."""
    method = binning_method(laser, gate)
    if (method == "exact" and gate.binning == "table" and laser.pulse_shape == "gaussian"
            and pulse_sigma_s(laser) >= TABLE_MIN_SIGMA_BINS * gate.bin_width_s):
        return "table"
    return method


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
    if method == "table":
        return _table_windows(pixel_local, time_s, energy_j, n_pixels, laser, gate, spread_s)
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


@kernel(inline=True)
def _plan_returns(pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold, half_s,
                  imp_half, drop, rect_width):
    """The planning pass the exact and the table methods share: per return (energy > 0; rays sorted by pixel) its
    position u in bins, its boxes (:func:`core.physics.laser.sorted_spread_pair`,
    :func:`~core.physics.laser.gaussian_box_params`: σ_eff ``sig``, ``box_a``, ``box_b`` and the ``kind``) and its
    bins [lo, hi] within the pulse's support (impulses: ``imp_half`` bins either side), ``binned_hi`` the last bin
    it adds to (lo − 1 for none: an impulse outside the gate, a boxed return of the rectangular pulse of full width
    ``rect_width`` > 0, flagged ``rect_boxed``, whose half-support is ``half_s``); per pixel the window covering its
    returns' bins (start, length) and the windows' offsets."""
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
    return u, lo, hi, binned_hi, sig, box_a, box_b, kind, rect_boxed, start, length, offset


@kernel
def _exact_kernel(pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold,
                  half_s, drop, rect_width):
    """The exact method's windows and values: per return its plan (:func:`_plan_returns`: position u in bins, boxes,
    σ_eff and bins [lo, hi] within the pulse's support; per pixel the window covering its returns), then each
    return's CDF differences added in ray order (:func:`_bin_return`).  Impulses with a rectangular pulse of
    full width ``rect_width`` are binned here; its boxed returns are flagged (``rect_boxed``) and left."""
    u, lo, hi, binned_hi, sig, box_a, box_b, kind, rect_boxed, start, length, offset = _plan_returns(
        pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold, half_s,
        half_s / dt, drop, rect_width)
    n = time_s.shape[0]
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


# ----------------------------------------------------------------------------------------------------------
# The tabulated pulse ⊛ box ("table" binning of flash frames, Gaussian pulse)
# ----------------------------------------------------------------------------------------------------------
#: Rows per pulse σ of the tabulated pulse ⊛ box (:class:`BoxTable`): its step h = 1/N bin in the return's
#: position, N the power of two ≥ 64/σ (σ in bins) and ≥ 16: 16 rows a bin for σ ≥ 4 bins, 64 at σ = 1 bin
#: (a table of ≈ 0.1 MB: small enough to stay in the cache beside a block's windows).
BOX_TABLE_ROWS_PER_SIGMA = 64


def box_table_rows(sigma_bins: float) -> int:
    """The rows per bin of the :class:`BoxTable` of a pulse σ (bins): h/σ ≤ 1/64."""
    return max(16, 1 << int(math.ceil(math.log2(BOX_TABLE_ROWS_PER_SIGMA / sigma_bins))))
#: Half-width of the tabulated range in pulse σ: beyond it each function takes its limit (the pulse's energy
#: beyond 7.5σ, 3e-14, is not carried; the bins a return touches are the exact method's, within 6.1σ_eff).
BOX_TABLE_HALF_SIGMAS = 7.5
#: The functions of a :class:`BoxTable`, by row block: A₀ and its derivatives A₀⁽ⁿ⁾ (n = 1 … 7), A₁, A₂.
_A0, _A1, _A2 = 0, 8, 9


def _gauss_derivative(n, z):
    """φ⁽ⁿ⁾(z) = (−1)ⁿ Heₙ(z) φ(z), the n-th derivative of the standard normal density."""
    from numpy.polynomial.hermite_e import hermeval

    return (-1) ** n * hermeval(z, [0] * n + [1]) * np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)


class BoxTable:
    """The Gaussian pulse (σ = ``sigma_bins`` bins) integrated over a bin, its derivatives and its first and second
    integrals over the return's position, tabulated against u = j − c (bin index minus return position, in bins),
    for :func:`_table_kernel` (the ``table`` binning).

    A return at c (bins from the gate opening) of energy E puts into bin j = c + u

    * an impulse: E·A₀(u), A₀(u) = Φ((u + 1)/σ) − Φ(u/σ);
    * spread over a box of a bins: E/a · [A₁(u − a/2) − A₁(u + a/2)], A₁(u) = ∫_u^∞ A₀ (A₁' = −A₀; 1 on the
      left, 0 on the right);
    * over a ⊛ b: E/(ab) · [A₂(u − (a+b)/2) − A₂(u − (a−b)/2) − A₂(u + (a−b)/2) + A₂(u + (a+b)/2)],
      A₂(u) = ∫_u^∞ A₁ (A₂' = −A₁; −u − ½ on the left, 0 on the right).

    The exact method folds a box narrower than ``GAUSS_BOX_FOLD``·σ into the pulse (σ_eff² = σ² + w²/12,
    :func:`core.physics.laser.gaussian_box_params`); here the same wider pulse is the table's σ moved along the
    heat equation, ∂A/∂(σ²) = ½ ∂²A/∂u², by δ = σ_eff² − σ² (bins²): A + (δ/2)A'' + (δ²/8)A⁗ + (δ³/48)A⁽⁶⁾
    (δ ≤ 2·0.3²σ²/12 = 0.015σ²; the next term, (δ⁴/384)A⁽⁸⁾, is the truncation: :meth:`error_bound`).  So the
    returns, their kinds and their bins are the exact method's, and only the tabulation and this series differ.

    Rows: u = u_min + q + i/N (column q, row i = 0 … N).  Between rows, cubic Hermite interpolation with the exact
    derivatives for the main term and the δ term (A₀ with A₀', A₁ with −A₀, A₂ with −A₁, A₀'' with A₀''', −A₀' with
    −A₀''), linear interpolation for the δ² and δ³ terms.  A table is ≈ 0.1 MB (11 functions × 17 rows × ≈ 70
    columns), every return at the same fraction of a bin reads the same rows, contiguous across its bins: no
    special function and no table search per bin edge."""

    def __init__(self, sigma_bins: float, rows: int | None = None):
        from scipy.special import ndtr

        s = float(sigma_bins)
        self.sigma_bins, self.rows = s, int(rows or box_table_rows(s))
        k = int(math.ceil(BOX_TABLE_HALF_SIGMAS * s))
        self.u_min = -k - 2
        self.n_col = 2 * k + 4
        u = self.u_min + np.arange(self.n_col)[None, :] + np.arange(self.rows + 1)[:, None] / self.rows
        right = u >= -0.5  # A₀(u) = A₀(−1 − u): evaluated where both CDFs are small (the upper tails), then mirrored
        m = np.where(right, u, -1.0 - u)

        def phi(z):
            return np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)

        def psi(z):  # ∫_{-∞}^z Φ = zΦ(z) + φ(z)
            return z * ndtr(z) + phi(z)

        def chi(z):  # ∫_{-∞}^z ψ = ((z² + 1)Φ(z) + zφ(z))/2
            return 0.5 * ((z * z + 1.0) * ndtr(z) + z * phi(z))

        tab = np.empty((11, self.rows + 1, self.n_col))
        tab[_A0] = ndtr(-m / s) - ndtr(-(m + 1.0) / s)
        for n in range(1, 8):  # A₀⁽ⁿ⁾(u) = [φ⁽ⁿ⁻¹⁾((u + 1)/σ) − φ⁽ⁿ⁻¹⁾(u/σ)]/σⁿ
            tab[_A0 + n] = (_gauss_derivative(n - 1, (u + 1.0) / s) - _gauss_derivative(n - 1, u / s)) / s ** n
        a1 = s * (psi(-m / s) - psi(-(m + 1.0) / s))
        a2 = s * s * (chi(-m / s) - chi(-(m + 1.0) / s))
        tab[_A1] = np.where(right, a1, 1.0 - a1)  # A₁(u) = 1 − A₁(−1 − u)
        tab[_A2] = np.where(right, a2, a2 - u - 0.5)  # A₂(u) = A₂(−1 − u) − u − ½
        tab[10] = 0.0  # (unused)
        self.flat = np.ascontiguousarray(tab.ravel())

    def function(self, n) -> np.ndarray:
        """The (rows + 1, columns) block of function ``n`` (0 … 7: A₀⁽ⁿ⁾; 8: A₁; 9: A₂)."""
        return self.flat.reshape(11, self.rows + 1, self.n_col)[n]

    def error_bound(self, delta_max: float) -> dict:
        """Per unit energy, the largest error of one term of each kind's value from this table (h = 1/N):
        Hermite h⁴/384·max|F⁗| for the main term and, times δ/2, for the δ term; linear h²/8·max|F''| for the δ²
        and δ³ terms; and the series' truncation (δ⁴/384)·max|A⁽⁸⁾| at δ = ``delta_max`` (bins²).  ``impulse``:
        the kind-0 value; ``box``: one of kind 1's two terms (its value: two over a); ``trapezoid``: one of kind
        2's four terms (its value: four over ab; δ = 0)."""
        s = self.sigma_bins
        u = np.linspace(self.u_min, -self.u_min, 100_001)
        d = {n: np.abs((_gauss_derivative(n - 1, (u + 1.0) / s) - _gauss_derivative(n - 1, u / s)) / s ** n).max()
             for n in range(1, 9)}  # max|A₀⁽ⁿ⁾|
        h = 1.0 / self.rows
        herm, lin, dm = h ** 4 / 384.0, h * h / 8.0, float(delta_max)

        def series(n):  # F with max|F⁽ᵏ⁾| = d[n + k]: F Hermite, δ/2·F'' Hermite, δ²/8·F⁗ and δ³/48·F⁽⁶⁾ linear
            return (herm * d[n + 4] + 0.5 * dm * herm * d[n + 6] + dm ** 2 / 8 * lin * d[n + 6]
                    + dm ** 3 / 48 * lin * d[n + 8] + dm ** 4 / 384 * d[n + 8])

        return {"impulse": series(0), "box": series(-1), "trapezoid": herm * d[2]}


_BOX_TABLES: dict = {}


def box_table(sigma_bins: float, rows: int | None = None) -> BoxTable:
    """The :class:`BoxTable` of a pulse σ (bins) (``rows``: default :func:`box_table_rows`), kept for later frames
    (a few; built in a few ms)."""
    key = (float(sigma_bins), int(rows or box_table_rows(sigma_bins)))
    t = _BOX_TABLES.get(key)
    if t is None:
        if len(_BOX_TABLES) > 8:
            _BOX_TABLES.clear()
        t = _BOX_TABLES[key] = BoxTable(sigma_bins, rows)
    return t


def _table_windows(pixel_local, time_s, energy_j, n_pixels, laser, gate, spread_s, rows=None):
    """The table method (:class:`BoxTable`) in one compiled pass, as :func:`_exact_windows` for the exact one."""
    dt = gate.bin_width_s
    sigma = pulse_sigma_s(laser)
    tab = box_table(sigma / dt, rows)
    spread = (np.zeros((0, 2)) if spread_s is None
              else np.ascontiguousarray(np.asarray(spread_s, dtype=np.float64).reshape(-1, 2)))
    start, length, offset, values = _table_kernel(
        np.ascontiguousarray(pixel_local), np.ascontiguousarray(time_s, dtype=np.float64),
        np.ascontiguousarray(energy_j, dtype=np.float64), spread, n_pixels, gate.gate_start_s, dt, gate.n_bins,
        sigma, pulse_half_support_s(laser) / sigma, GAUSS_BOX_FOLD * sigma, spread_drop_s(laser), tab.flat,
        tab.u_min, tab.n_col, tab.rows)
    return WaveformWindows(start, length, offset, values, gate.n_bins)


@kernel
def _table_kernel(pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold, drop,
                  flat, u_min, n_col, rows):
    """Windows and values of the table method: the exact method's returns, kinds, σ_eff and bins
    (:func:`_plan_returns`, Gaussian pulse; its impulses' half-support ``half_ratio``·σ), each return's value
    from the :class:`BoxTable` ``flat``."""
    u, lo, _, hi, sig, box_a, box_b, kind, _, start, length, offset = _plan_returns(
        pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold, 0.0,
        half_ratio * sigma / dt, drop, 0.0)
    n = time_s.shape[0]
    values = np.zeros(offset[n_pixels])
    buf = np.empty(64)
    inv_dt = 1.0 / dt
    stride = (rows + 1) * n_col
    sigma2 = (sigma * inv_dt) ** 2
    for i in range(n):
        b0, b1 = lo[i], hi[i]
        if b1 < b0:
            continue
        m = b1 - b0 + 1
        base = offset[pixel[i]] - start[pixel[i]] + b0
        if m > buf.shape[0]:
            buf = np.empty(2 * m)
        _table_return(values[base:base + m], buf, 0, m, m, b0 - u[i], kind[i], energy[i], sig[i], box_a[i],
                      box_b[i], inv_dt, sigma2, flat, stride, u_min, n_col, rows)
    return start, length, offset, values


#: The detection windows (:func:`detection_windows`): each pixel's bins within this many σ_eff (bins) of its
#: returns' boxes are binned.  Issue 28's terrain frame (session 32; pixels binned whole in brackets): 3.5: 554k
#: bins (11), 3.0: 499k (14), 2.75: 472k (16), 2.5: 446k (57), 2.25: 546k (3931); the whole windows 837k.
DETECTION_CORE_SIGMAS = 2.75
#: Per unit energy, a bound on the table's error in a bin's value: ≥ 50 times BoxTable.error_bound over the kinds
#: and pulse widths (2e-8 at σ = 1 bin; tests/core/physics/test_detection_windows.py asserts ≥ 10 times).
DETECTION_TABLE_SLACK = 1e-6
#: A bin left out must lie below the detection threshold by this fraction (a flat top's bins are within 1e-7 of
#: its peak: core/physics/detection/peaks.py ``_FLAT_RTOL``).
DETECTION_THRESHOLD_MARGIN = 1e-6


def detection_windows(pixel_local, time_s, energy_j, n_pixels, laser: LaserSettings, gate: RangeGateSettings,
                      method: str, detection, *, spread_s=None) -> tuple[WaveformWindows, int]:
    """The waveforms of :func:`accumulate_waveform_windows` binned only where the ideal receiver's echo detection
    (:func:`core.physics.detection.peaks.detect_echoes_windows` with ``detection``, DetectionSettings) reads them:
    the same echoes, bit for bit, for frames that keep no waveform (points only).

    Table binning only (another ``method``, or no threshold at all, bins the whole windows).  Each pixel's window
    is cut to the bins within K = ``DETECTION_CORE_SIGMAS`` σ_eff of its returns' boxes, and only those bins are
    binned (each one's value is the whole window's, bit for bit: :func:`_table_return`).  The cut stands when its
    edge bins lie below the threshold the detection derives from the cut's largest bin,
    thr = max(threshold_j, relative_threshold·peak), by ``DETECTION_THRESHOLD_MARGIN``, after adding twice the
    table's error bound (E·``DETECTION_TABLE_SLACK`` summed over the pixel's returns): every return's pulse —
    Gaussian, Gaussian ⊛ box, Gaussian ⊛ box ⊛ box — is symmetric and unimodal about its centre c, so its bin
    integrals do not grow from bin j to bin j − 1 when j ≤ c − ½ (nor to j + 1 when j ≥ c − ½); the left edge
    lies left of every c by ½ bin at least (K·σ ≥ ½: the table needs σ ≥ 1 bin) and the right edge right of
    them, so no bin left out exceeds its edge bin, nor the threshold.  Then no bin left out can be a candidate, a
    neighbour the detection reads, a valley between candidates or the peak, and every candidate's neighbours lie
    inside the cut.  Otherwise the pixel's whole window is binned.  Returns the windows and the number of
    pixels binned whole."""
    pixel_local = np.asarray(pixel_local, dtype=np.int64)
    if method != "table" or (detection.threshold_j <= 0.0 and detection.relative_threshold <= 0.0):
        return accumulate_waveform_windows(pixel_local, time_s, energy_j, n_pixels, laser, gate, method,
                                           spread_s=spread_s), 0
    dt = gate.bin_width_s
    sigma = pulse_sigma_s(laser)
    tab = box_table(sigma / dt)
    spread = (np.zeros((0, 2)) if spread_s is None
              else np.ascontiguousarray(np.asarray(spread_s, dtype=np.float64).reshape(-1, 2)))
    start, length, offset, values, n_whole = _table_detection_kernel(
        np.ascontiguousarray(pixel_local), np.ascontiguousarray(time_s, dtype=np.float64),
        np.ascontiguousarray(energy_j, dtype=np.float64), spread, n_pixels, gate.gate_start_s, dt, gate.n_bins,
        sigma, pulse_half_support_s(laser) / sigma, GAUSS_BOX_FOLD * sigma, spread_drop_s(laser), tab.flat,
        tab.u_min, tab.n_col, tab.rows, DETECTION_CORE_SIGMAS, DETECTION_TABLE_SLACK, float(detection.threshold_j),
        float(detection.relative_threshold), DETECTION_THRESHOLD_MARGIN)
    return WaveformWindows(start, length, offset, values, gate.n_bins), int(n_whole)


@kernel
def _table_detection_kernel(pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio,
                            fold, drop, flat, u_min, n_col, rows, k_sigmas, slack, threshold_j, relative_threshold,
                            margin):
    """:func:`detection_windows`' table binning: the plan of :func:`_table_kernel`, each pixel's cut [cut_a, cut_b),
    the returns binned over the cuts in ray order, the cuts checked, and the pixels whose cut does not stand
    binned over their whole windows."""
    u, lo, _, hi, sig, box_a, box_b, kind, _, start, length, offset = _plan_returns(
        pixel, time_s, energy, spread, n_pixels, gate_start_s, dt, n_bins, sigma, half_ratio, fold, 0.0,
        half_ratio * sigma / dt, drop, 0.0)
    n = time_s.shape[0]
    inv_dt = 1.0 / dt
    stride = (rows + 1) * n_col
    sigma2 = (sigma * inv_dt) ** 2
    left = np.full(n_pixels, np.inf)  # the cut's edges (bins) before rounding
    right = np.full(n_pixels, -np.inf)
    c_min = np.full(n_pixels, np.inf)  # the returns' centres (bins)
    c_max = np.full(n_pixels, -np.inf)
    e_sum = np.zeros(n_pixels)
    for i in range(n):
        if hi[i] < lo[i]:
            continue
        p = pixel[i]
        reach = 0.5 * (box_a[i] + box_b[i]) * inv_dt + k_sigmas * sig[i] * inv_dt
        left[p] = min(left[p], u[i] - reach)
        right[p] = max(right[p], u[i] + reach)
        c_min[p] = min(c_min[p], u[i])
        c_max[p] = max(c_max[p], u[i])
        e_sum[p] += energy[i]
    cut_a = np.zeros(n_pixels, np.int64)
    cut_len = np.zeros(n_pixels, np.int64)
    cut_off = np.zeros(n_pixels + 1, np.int64)
    for p in range(n_pixels):
        cut_a[p] = start[p]
        if length[p] > 0 and left[p] <= right[p]:  # (else no return adds to the window: it is all zeros)
            a = max(start[p], int(math.floor(max(left[p], -1.0))))
            b = min(start[p] + length[p], int(math.ceil(min(right[p], n_bins + 1.0))))
            cut_a[p], cut_len[p] = a, max(b - a, 0)
        cut_off[p + 1] = cut_off[p] + cut_len[p]
    values = np.zeros(cut_off[n_pixels])
    buf = np.empty(64)
    for i in range(n):
        b0, b1 = lo[i], hi[i]
        if b1 < b0:
            continue
        p = pixel[i]
        m = b1 - b0 + 1
        ja = max(cut_a[p] - b0, 0)
        jb = min(cut_a[p] + cut_len[p] - b0, m)
        if jb <= ja:
            continue
        if m > buf.shape[0]:
            buf = np.empty(2 * m)
        base = cut_off[p] - cut_a[p] + b0
        _table_return(values[base + ja:base + jb], buf, ja, jb, m, b0 - u[i], kind[i], energy[i], sig[i], box_a[i],
                      box_b[i], inv_dt, sigma2, flat, stride, u_min, n_col, rows)
    whole = np.zeros(n_pixels, np.bool_)
    n_whole = 0
    for p in range(n_pixels):
        a, c = cut_a[p], cut_len[p]
        clipped_left, clipped_right = a > start[p], a + c < start[p] + length[p]
        if not (clipped_left or clipped_right):
            continue
        peak = 0.0
        for j in range(c):
            peak = max(peak, values[cut_off[p] + j])
        limit = max(max(threshold_j, relative_threshold * peak), 0.0) * (1.0 - margin) - 2.0 * slack * e_sum[p]
        ok = c > 0
        if ok and clipped_left:  # bin a: left of every centre by ½ bin, and below the threshold
            ok = a + 0.5 <= c_min[p] and values[cut_off[p]] <= limit
        if ok and clipped_right:  # bin a + c − 1: right of every centre by ½ bin
            ok = a + c - 0.5 >= c_max[p] and values[cut_off[p] + c - 1] <= limit
        if not ok:
            whole[p] = True
            n_whole += 1
    if n_whole == 0:
        return cut_a, cut_len, cut_off, values, 0
    # the pixels whose cut does not stand: their whole windows, binned again
    w_start = np.where(whole, start, cut_a)
    w_len = np.where(whole, length, cut_len)
    w_off = np.zeros(n_pixels + 1, np.int64)
    for p in range(n_pixels):
        w_off[p + 1] = w_off[p] + w_len[p]
    out = np.zeros(w_off[n_pixels])
    for p in range(n_pixels):
        if not whole[p]:
            out[w_off[p]:w_off[p + 1]] = values[cut_off[p]:cut_off[p + 1]]
    for i in range(n):
        b0, b1 = lo[i], hi[i]
        p = pixel[i]
        if b1 < b0 or not whole[p]:
            continue
        m = b1 - b0 + 1
        if m > buf.shape[0]:
            buf = np.empty(2 * m)
        base = w_off[p] - start[p] + b0
        _table_return(out[base:base + m], buf, 0, m, m, b0 - u[i], kind[i], energy[i], sig[i], box_a[i], box_b[i],
                      inv_dt, sigma2, flat, stride, u_min, n_col, rows)
    return w_start, w_len, w_off, out, n_whole


@kernel(inline=True)
def _table_return(dst, buf, ja, jb, m, v0, k, e, sig, box_a, box_b, inv_dt, sigma2, flat, stride, u_min, n_col,
                  rows):
    """One return's table values over its bins j ∈ [ja, jb) of its m bins (``v0``: u of its first bin, j = 0)
    added into ``dst`` (``dst[0]`` is bin ja); ``buf``: scratch of at least m.  Each bin's value is computed the
    same way whatever [ja, jb) holds it (a sub-range gives the whole range's values there, bit for bit)."""
    if k == 2:  # σ_eff = σ
        buf[ja:jb] = 0.0
        a, b = box_a * inv_dt, box_b * inv_dt
        hp, hm = 0.5 * (a + b), 0.5 * (a - b)
        for x, sg in ((v0 - hp, 1.0), (v0 - hm, -1.0), (v0 + hm, -1.0), (v0 + hp, 1.0)):
            _table_term(buf, ja, jb, m, x, sg, flat, _A2, _A1, -1.0, 0.0, 0.0, 0.0, 0.0, stride, u_min, n_col, rows,
                        2)
        _add_positive(dst, buf[ja:jb], jb - ja, e / (a * b))
    else:
        dl = (sig * inv_dt) ** 2 - sigma2  # δ = σ_eff² − σ² (bins²)
        c2, c4, c6 = 0.5 * dl, dl * dl / 8.0, dl * dl * dl / 48.0
        if k == 0:  # the σ_eff pulse: A₀ + (δ/2)A₀'' + (δ²/8)A₀⁗ + (δ³/48)A₀⁽⁶⁾
            _impulse(dst, buf, ja, jb, m, v0, e, flat, c2, c4, c6, stride, u_min, n_col, rows)
        else:  # A₁ of σ_eff: A₁'' = −A₀', A₁⁗ = −A₀''', A₁⁽⁶⁾ = −A₀⁽⁵⁾
            buf[ja:jb] = 0.0
            a = box_a * inv_dt
            _table_term(buf, ja, jb, m, v0 - 0.5 * a, 1.0, flat, _A1, _A0, -1.0, c2, c4, c6, -1.0, stride, u_min,
                        n_col, rows, 1)
            _table_term(buf, ja, jb, m, v0 + 0.5 * a, -1.0, flat, _A1, _A0, -1.0, c2, c4, c6, -1.0, stride, u_min,
                        n_col, rows, 1)
            _add_positive(dst, buf[ja:jb], jb - ja, e / a)


@kernel(inline=True)
def _add_positive(dst, buf, m, scale):
    """dst[j] += buf[j]·scale where positive (as the exact method adds each return's CDF differences)."""
    for j in range(m):  # (no branch: vectorised)
        w = buf[j] * scale
        dst[j] += w if w > 0 else 0.0


@kernel(inline=True)
def _hermite(x, rows, u_min, n_col, m):
    """Where a term F(v0 + j), j < m, reads the table: its row r and fraction s between rows r and r + 1, the
    column q0 of j = 0 and the bins [j_lo, j_hi) whose columns are in the table."""
    fl = math.floor(x)
    y = (x - fl) * rows
    r = min(int(y), rows - 1)
    s = y - r
    q0 = int(fl) - u_min
    j_lo = min(max(-q0, 0), m)
    j_hi = max(min(n_col - q0, m), j_lo)
    return r, s, q0, j_lo, j_hi


@kernel(inline=True)
def _rows(flat, fn, r, q, n, stride, n_col):
    """Function ``fn``'s rows r and r + 1 of the table, columns [q, q + n)."""
    o = fn * stride + r * n_col + q
    return flat[o:o + n], flat[o + n_col:o + n_col + n]


@kernel(inline=True)
def _add4(out, w0, w1, w2, w3, x0, x1, x2, x3):
    """out += w0·x0 + w1·x1 + w2·x2 + w3·x3 (five arrays: the compiler vectorises it with a few alias tests)."""
    for k in range(out.shape[0]):
        out[k] += (w0 * x0[k] + w1 * x1[k]) + (w2 * x2[k] + w3 * x3[k])


@kernel(inline=True)
def _impulse(dst, buf, ja, jb, m, x0, e, flat, c2, c4, c6, stride, u_min, n_col, rows):
    """dst[j − ja] += e·max(0, A₀ + c2·A₀'' + c4·A₀⁗ + c6·A₀⁽⁶⁾) at u = x0 + j, ja ≤ j < jb, of a return of m bins
    (:func:`_table_term` for A₀, in three passes: the first writes ``buf``, the last adds into ``dst``; A₀ is 0
    beyond the table's columns)."""
    r, s, q0, j_lo, j_hi = _hermite(x0, rows, u_min, n_col, m)
    if j_hi - j_lo < m:  # (the table spans 7.5σ, the impulse's bins 6.1σ_eff: not reached; decided on all m bins)
        buf[ja:jb] = 0.0
        _table_term(buf, ja, jb, m, x0, 1.0, flat, _A0, _A0 + 1, 1.0, c2, c4, c6, 1.0, stride, u_min, n_col, rows, 0)
        _add_positive(dst, buf[ja:jb], jb - ja, e)
        return
    n = jb - ja
    q = q0 + ja
    s1 = 1.0 - s
    h00, h01 = (1.0 + 2.0 * s) * s1 * s1, s * s * (3.0 - 2.0 * s)
    h10, h11 = s * s1 * s1 / rows, -s * s * s1 / rows
    out = buf[ja:jb]
    f0, f1 = _rows(flat, _A0, r, q, n, stride, n_col)
    d0, d1 = _rows(flat, _A0 + 1, r, q, n, stride, n_col)
    x0, x1 = _rows(flat, _A0 + 2, r, q, n, stride, n_col)
    y0, y1 = _rows(flat, _A0 + 3, r, q, n, stride, n_col)
    g00, g01, g10, g11 = c2 * h00, c2 * h01, c2 * h10, c2 * h11
    for k in range(n):  # (eight arrays read, one written: vectorised)
        out[k] = (((h00 * f0[k] + h01 * f1[k]) + (h10 * d0[k] + h11 * d1[k]))
                  + ((g00 * x0[k] + g01 * x1[k]) + (g10 * y0[k] + g11 * y1[k])))
    f0, f1 = _rows(flat, _A0 + 4, r, q, n, stride, n_col)
    d0, d1 = _rows(flat, _A0 + 6, r, q, n, stride, n_col)
    w0, w1, w2, w3 = c4 * s1, c4 * s, c6 * s1, c6 * s
    for k in range(n):  # (six arrays; vectorised)
        w = (out[k] + ((w0 * f0[k] + w1 * f1[k]) + (w2 * d0[k] + w3 * d1[k]))) * e
        dst[k] += w if w > 0 else 0.0


@kernel(inline=True)
def _table_term(buf, ja, jb, m, x0, sign, flat, fn, dfn, dsign, c2, c4, c6, ddf, stride, u_min, n_col, rows, order):
    """buf[j] += sign·G(x0 + j), ja ≤ j < jb (of a return's m bins), with G = F + c2·F'' + c4·F⁗ + c6·F⁽⁶⁾ and F
    the table's function ``fn`` (its derivative dsign·``dfn``): cubic Hermite for F and for c2·F'' (= ddf·A₀⁽ⁿ⁾ with its derivative next in the
    table), linear for c4·F⁗ and c6·F⁽⁶⁾ (ddf·A₀⁽ⁿ⁺²⁾, ddf·A₀⁽ⁿ⁺⁴⁾): for A₀ n = 2, ddf = 1; for A₁ n = 1,
    ddf = −1; for A₂ the c are 0.  Beyond the table's columns G takes F's limits (``order`` 1: 1 on the left; 2:
    −u − ½ on the left; 0 on the right and for order 0)."""
    r, s, q0, j_lo, j_hi = _hermite(x0, rows, u_min, n_col, m)
    s1 = 1.0 - s
    h00, h01 = (1.0 + 2.0 * s) * s1 * s1 * sign, s * s * (3.0 - 2.0 * s) * sign
    h10, h11 = s * s1 * s1 * sign / rows, -s * s * s1 * sign / rows
    if order == 1:
        for j in range(ja, min(j_lo, jb)):
            buf[j] += sign
    elif order == 2:
        for j in range(ja, min(j_lo, jb)):
            buf[j] += sign * (-(x0 + j) - 0.5)
    j_lo, j_hi = max(j_lo, ja), min(j_hi, jb)
    n = j_hi - j_lo
    if n <= 0:
        return
    q = q0 + j_lo
    out = buf[j_lo:j_hi]
    f0, f1 = _rows(flat, fn, r, q, n, stride, n_col)
    d0, d1 = _rows(flat, dfn, r, q, n, stride, n_col)
    _add4(out, h00, h01, h10 * dsign, h11 * dsign, f0, f1, d0, d1)
    if c2 != 0.0:
        k = _A0 + (2 if fn == _A0 else 1)  # F'' = ddf·A₀⁽ᵏ⁾
        g = c2 * ddf
        f0, f1 = _rows(flat, k, r, q, n, stride, n_col)
        d0, d1 = _rows(flat, k + 1, r, q, n, stride, n_col)
        _add4(out, g * h00, g * h01, g * h10, g * h11, f0, f1, d0, d1)
        f0, f1 = _rows(flat, k + 2, r, q, n, stride, n_col)
        d0, d1 = _rows(flat, k + 4, r, q, n, stride, n_col)
        g4, g6 = c4 * ddf * sign, c6 * ddf * sign
        _add4(out, g4 * s1, g4 * s, g6 * s1, g6 * s, f0, f1, d0, d1)


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


@kernel(inline=True)
def window_echoes(buf, cand, a, b, pulse, u, energy, rows, wide, k, half, n_bins, threshold_j, relative_threshold,
                  min_dip, max_echoes, mode, out_pix, out_pos, out_amp, out_idx, out_n, n_out):
    """The waveform of the returns ``a`` … ``b`` − 1 (one pulse) over the bins they touch, in ``buf``, and its
    echoes (:func:`detect_row`) appended from ``n_out`` on; returns the new ``n_out``.  :func:`_table_echoes`'s
    step for each pulse, and the sub-ray sum of core.physics.pulse_table's centroid route where a pulse falls back
    to it (one implementation, so the two routes' sums stay the same bit for bit)."""
    n_tab = rows.shape[0] - 1
    ncol, wcol = rows.shape[1], wide.shape[1]
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
    return n_out


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
    wcol = wide.shape[1]
    buf = np.zeros(n_bins + wcol)
    cand = np.empty(n_bins, np.int64)
    n_out = 0
    a = 0
    n = u.shape[0]
    while a < n:
        b = a
        while b < n and pulse[b] == pulse[a]:
            b += 1
        n_out = window_echoes(buf, cand, a, b, pulse, u, energy, rows, wide, k, half, n_bins, threshold_j,
                              relative_threshold, min_dip, max_echoes, mode, out_pix, out_pos, out_amp, out_idx, out_n,
                              n_out)
        a = b
    return n_out
