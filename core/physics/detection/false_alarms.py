"""False alarms of noisy echo detection (paper §3.1 products; docs/theory.md §9): which reported echoes have no
true return nearby, and how many a Gaussian noise model expects above each pixel's threshold.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from .noisy import NoisyEchoes, matched_filter


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
