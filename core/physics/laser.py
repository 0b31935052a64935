"""Laser source: spatial beam profile and temporal pulse shape (paper §3.1, "laser source" settings).

Spatial: the fraction of the pulse energy that leaves the (monostatic) transmitter inside each sub-ray cell
of the receiver's tan-plane grid.  For the Gaussian TEM00 beam the far-field intensity in tan-plane
coordinates is p(x, y) = 2/(π w²) exp(−2(x² + y²)/w²), w = tan(θ_div/2) (1/e² half-angle), normalised over the
whole plane; the energy of a rectangular cell is exact and separable:

    F = ¼ [erf(√2 x₁/w) − erf(√2 x₀/w)] · [erf(√2 y₁/w) − erf(√2 y₀/w)].

The uniform profile spreads the energy evenly over the receiver field of view.

Temporal: the pulse shape's cumulative distribution; integrating it over each time bin is how the waveform
avoids point-sampling a pulse narrower than a bin.
"""
from __future__ import annotations

import numpy as np
from scipy.special import erf, ndtr

from ..config.settings import LaserSettings
from ..geometry.rays import Detector

FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def beam_half_angle_tan(laser: LaserSettings, det: Detector) -> float:
    """1/e² beam radius w in tan-plane units (fills the FOV diagonal if asked)."""
    if laser.divergence_fills_fov:
        return float(np.hypot(det.half_width_tan, det.half_height_tan))
    return float(np.tan(laser.beam_divergence_rad / 2))


def cell_energy_fractions(laser: LaserSettings, det: Detector, center_offset_tan=(0.0, 0.0), width_scale=1.0):
    """Per-axis factors (fx (W·S,), fy (H·S,)) whose outer product is the fraction of the pulse energy in each
    sub-ray cell: fraction[sub_y, sub_x] = fy[sub_y]·fx[sub_x].

    ``center_offset_tan`` displaces the beam centre (beam wander / pointing) in tan-plane units;
    ``width_scale`` widens the Gaussian beam (turbulent broadening), keeping its total energy.
    """
    x_edges, y_edges = det.sub_cell_edges()
    if laser.beam_profile == "uniform":
        nx, ny = len(x_edges) - 1, len(y_edges) - 1
        return np.full(nx, 1.0 / nx), np.full(ny, 1.0 / ny)
    w = beam_half_angle_tan(laser, det) * width_scale
    k = np.sqrt(2.0) / w
    ex = erf(k * (x_edges - center_offset_tan[0]))
    ey = erf(k * (y_edges - center_offset_tan[1]))
    fx = 0.5 * np.abs(np.diff(ex))
    fy = 0.5 * np.abs(np.diff(ey))
    return fx, fy


def pulse_sigma_s(laser: LaserSettings) -> float:
    """Standard deviation of the Gaussian pulse (s)."""
    return laser.pulse_fwhm_s * FWHM_TO_SIGMA


def pulse_half_support_s(laser: LaserSettings) -> float:
    """Half-width beyond which the pulse carries < 1e-9 of its energy (Gaussian: 6.1σ)."""
    if laser.pulse_shape == "gaussian":
        return 6.1 * pulse_sigma_s(laser)
    return 0.5 * laser.pulse_fwhm_s


def pulse_cdf(laser: LaserSettings, t_s):
    """Fraction of the pulse energy emitted before time t (the pulse is centred on t = 0)."""
    t_s = np.asarray(t_s, dtype=np.float64)
    if laser.pulse_shape == "gaussian":
        return ndtr(t_s / pulse_sigma_s(laser))
    return np.clip(t_s / laser.pulse_fwhm_s + 0.5, 0.0, 1.0)



# ----------------------------------------------------------------------------------------------------------------
# Pulse convolved with boxes: the return of a sub-ray cell whose surface spans a range interval
# ----------------------------------------------------------------------------------------------------------------
def _trapezoid_cdf(x, a, b):
    """CDF of U(a) ⊛ U(b) (a ≥ b ≥ 0 full widths) at x measured from the left end of its support [0, a + b].

    Piecewise exact: x²/(2ab), (x − b/2)/a, 1 − (a + b − x)²/(2ab) on [0, b], [b, a], [a, a + b]."""
    x, a, b = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x, a, b)))
    out = np.zeros(x.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = (x > 0) & (x <= b)
        out[rise] = x[rise] ** 2 / (2 * a[rise] * b[rise])
        mid = (x > b) & (x <= a)
        out[mid] = (x[mid] - 0.5 * b[mid]) / a[mid]
        fall = (x > a) & (x < a + b)
        out[fall] = 1.0 - (a[fall] + b[fall] - x[fall]) ** 2 / (2 * a[fall] * b[fall])
    out[x >= a + b] = 1.0
    return out


def _trapezoid_cdf_integral(x, a, b):
    """∫₀ˣ of :func:`_trapezoid_cdf` (a ≥ b ≥ 0): x³/(6ab); b²/(6a) + ((x − b/2)² − b²/4)/(2a);
    I(a) + (x − a) − (b³ − (a + b − x)³)/(6ab); (a + b)/2 + (x − a − b) on the same pieces and beyond."""
    x, a, b = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x, a, b)))
    out = np.zeros(x.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = (x > 0) & (x <= b)
        out[rise] = x[rise] ** 3 / (6 * a[rise] * b[rise])
        mid = (x > b) & (x <= a)
        xm, am, bm = x[mid], a[mid], b[mid]
        out[mid] = bm * bm / (6 * am) + ((xm - 0.5 * bm) ** 2 - 0.25 * bm * bm) / (2 * am)
        fall = (x > a) & (x < a + b)
        xf, af, bf = x[fall], a[fall], b[fall]
        out[fall] = (bf * bf / (6 * af) + 0.5 * (af - bf) + (xf - af)
                     - (bf ** 3 - (af + bf - xf) ** 3) / (6 * af * bf))
    beyond = x >= a + b
    out[beyond] = 0.5 * (a[beyond] + b[beyond]) + (x[beyond] - a[beyond] - b[beyond])
    return out


def boxes_cdf(t_s, widths_s):
    """CDF at t of the sum of up to three independent uniform variables centred on 0 with full widths
    ``widths_s`` (..., 3) sorted in decreasing order, zeros for absent boxes, the first > 0.

    One box: clip(t/w₁ + ½); two: the trapezoid; three: the trapezoid averaged over the third box,
    [I(x + w₃/2) − I(x − w₃/2)]/w₃ with I its integral.  Exact piecewise polynomials, no differences of large
    numbers beyond relative size w₁/w₃ (callers drop boxes narrower than 1e-6 of the widest)."""
    t = np.asarray(t_s, dtype=np.float64)
    w = np.asarray(widths_s, dtype=np.float64)
    w1, w2, w3 = w[..., 0], w[..., 1], w[..., 2]
    # the distribution is symmetric: evaluate on the left half only, F(t) = 1 − F(−t) on the right, so the
    # far tail is exactly 0 or 1 and small values keep their relative accuracy
    tl = -np.abs(t)
    x = tl + 0.5 * (w1 + w2)  # from the left end of the trapezoid of the two widest boxes
    with np.errstate(divide="ignore", invalid="ignore"):
        three = (_trapezoid_cdf_integral(x + 0.5 * w3, w1, w2) - _trapezoid_cdf_integral(x - 0.5 * w3, w1, w2)) / w3
    left = np.clip(np.where(w3 > 0, three, _trapezoid_cdf(x, w1, w2)), 0.0, 0.5)
    return np.where(t > 0, 1.0 - left, left)


_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


#: Beyond this many σ, e₁ < 1e-18 σ: taken as 0 (the box part of the CDF is O(1)).
_E1_CUTOFF = 8.5


def _gauss_e1(u, sigma):
    """P₁(u) − max(u, 0) for the Gaussian pulse, P₁ = ∫P: σ[φ(z) − |z|Φ(−|z|)], even and decaying.

    Evaluated only where |u| < 8.5σ when that is under half of the points (long boxes: most bin edges are
    far from both box edges); 0 beyond (< 1e-18 σ)."""
    m = np.abs(u) / sigma
    near = m < _E1_CUTOFF
    if near.mean() > 0.5:
        return sigma * (np.exp(-0.5 * m * m) * _INV_SQRT_2PI - m * ndtr(-m))
    out = np.zeros(np.broadcast(m, sigma).shape)
    sig = np.broadcast_to(sigma, out.shape)[near]
    mn = m[near]
    out[near] = sig * (np.exp(-0.5 * mn * mn) * _INV_SQRT_2PI - mn * ndtr(-mn))
    return out


def _gauss_e2(u, sigma):
    """P₂(u) − max(u, 0)²/2 for the Gaussian pulse, P₂ = ∫∫P = σ²[(z² + 1)Φ(z)/2 + zφ(z)/2]:
    σ² g(|z|) below 0 and σ²(½ − g(z)) above, g(m) = (m² + 1)Φ(−m)/2 − mφ(m)/2 ≥ 0 (bounded, no cancellation
    against the growing polynomial)."""
    z = u / sigma
    m = np.abs(z)
    g = 0.5 * (m * m + 1.0) * ndtr(-m) - 0.5 * m * np.exp(-0.5 * m * m) * _INV_SQRT_2PI
    return sigma * sigma * np.where(z > 0, 0.5 - g, g)


#: A box narrower than this fraction of the Gaussian pulse's σ is dropped: the shape changes by
#: ≈ w²/(24σ²) < 5e-6 of the peak (second order).
GAUSS_BOX_DROP = 1e-2
#: A box narrower than this fraction of the Gaussian pulse's σ is folded into the pulse (:func:`gaussian_box_terms`).
GAUSS_BOX_FOLD = 0.3
#: A box narrower than this fraction of the widest box is dropped (rectangular pulse: first-order edge change).
RECT_BOX_DROP = 1e-6


def sorted_spreads(laser: LaserSettings, spread_s):
    """Time spreads (n, 2) of sub-ray cells, sorted widest first, with boxes too narrow to matter set to 0
    (``GAUSS_BOX_DROP``·σ for the Gaussian pulse, ``RECT_BOX_DROP``·width for the rectangular one)."""
    s = np.sort(np.abs(np.asarray(spread_s, dtype=np.float64)), axis=1)[:, ::-1]
    if laser.pulse_shape == "gaussian":
        s[s < GAUSS_BOX_DROP * pulse_sigma_s(laser)] = 0.0
    else:
        s[s < RECT_BOX_DROP * max(laser.pulse_fwhm_s, 1e-300)] = 0.0
    return np.ascontiguousarray(s)


def gaussian_box_terms(laser: LaserSettings, spread_s):
    """Per ray (σ_eff, a, b, kind) for a Gaussian pulse and sorted cell spreads (n, 2) (:func:`sorted_spreads`).

    A box narrower than ``GAUSS_BOX_FOLD``·σ is folded into the pulse as a wider Gaussian,
    σ_eff² = σ² + w²/12 (same energy, centroid and variance; the shape differs by the box's fourth cumulant,
    w⁴/(960σ⁴) per box, below 2e-5 of the peak).  kind = number of boxes left (0, 1 or 2)."""
    s = np.asarray(spread_s, dtype=np.float64)
    sigma = pulse_sigma_s(laser)
    fold = s < GAUSS_BOX_FOLD * sigma
    var = sigma * sigma + np.sum(np.where(fold, s * s, 0.0), axis=1) / 12.0
    boxes = np.where(fold, 0.0, s)
    kind = (boxes > 0).sum(axis=1)
    return np.sqrt(var), boxes[:, 0], boxes[:, 1], kind


def gaussian_box_cdf(t_s, sigma_s, a_s, b_s, kind: int):
    """CDF at t of a Gaussian pulse (σ) ⊛ U(a) ⊛ U(b), all rays of one ``kind`` (0: no box, 1: a only, 2: both,
    a ≥ b), arguments broadcast together.

    P = Φ(t/σ) = H + (P − H): the box part is exact (trapezoid) and the smooth rest enters through its bounded
    integrals e₁, e₂ (one box: Δ_a e₁/a; two: Δ_a Δ_b e₂/(ab)).  Symmetric: evaluated on the left half,
    F(t) = 1 − F(−t) on the right, so the tails are exact."""
    t_signed = np.asarray(t_s, dtype=np.float64)
    t = -np.abs(t_signed)
    if kind == 0:
        out = ndtr(t / sigma_s)
    elif kind == 1:
        box = np.clip(t / a_s + 0.5, 0.0, 1.0)
        out = box + (_gauss_e1(t + 0.5 * a_s, sigma_s) - _gauss_e1(t - 0.5 * a_s, sigma_s)) / a_s
    else:
        t, a_s, b_s, sigma_s = np.broadcast_arrays(t, a_s, b_s, sigma_s)
        box = _trapezoid_cdf(t + 0.5 * (a_s + b_s), a_s, b_s)
        ha, hb = 0.5 * a_s, 0.5 * b_s
        smooth = (_gauss_e2(t + ha + hb, sigma_s) - _gauss_e2(t + ha - hb, sigma_s)
                  - _gauss_e2(t - ha + hb, sigma_s) + _gauss_e2(t - ha - hb, sigma_s)) / (a_s * b_s)
        out = box + smooth
    out = np.clip(out, 0.0, 0.5)
    return np.where(t_signed > 0, 1.0 - out, out)


def pulse_box_cdf(laser: LaserSettings, t_s, spread_s):
    """Fraction of the energy of a return spread uniformly over a box (or a trapezoid, two boxes) of round-trip
    times that arrives before t: the pulse CDF convolved with U(a) ⊛ U(b).

    ``t_s`` (n, k): times relative to each box centre; ``spread_s`` (n, 2): full widths (a, b) sorted a ≥ b,
    zeros for absent boxes (:func:`sorted_spreads`).  Gaussian pulse: :func:`gaussian_box_terms` and
    :func:`gaussian_box_cdf`; rectangular pulse of width τ: the CDF of three boxes (τ, a, b), exact."""
    t = np.asarray(t_s, dtype=np.float64)
    s = np.asarray(spread_s, dtype=np.float64)
    if laser.pulse_shape != "gaussian":
        w = np.concatenate([np.full((len(s), 1), laser.pulse_fwhm_s), s], axis=1)
        w = np.sort(w, axis=1)[:, ::-1]
        return boxes_cdf(t, w[:, None, :])
    sigma, a, b, kind = gaussian_box_terms(laser, s)
    out = np.empty(t.shape)
    for kd in (0, 1, 2):
        sel = kind == kd
        if sel.any():
            out[sel] = gaussian_box_cdf(t[sel], sigma[sel, None], a[sel, None], b[sel, None], kd)
    return out
