"""False alarms of noisy echo detection (paper §3.1 products; docs/theory.md §9): which reported echoes have no
true return nearby, and how many a Gaussian noise model expects above each pixel's threshold.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np

from ...jit import kernel
from .noisy import NoisyEchoes, run_row_chunks
from .row_statistics import matched_filter


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


def eligible_bins(truth, guard_bins, rel_level=1e-3, abs_level=0.0, threads=1):
    """(P, B) bool: the bins where a detection would be a false alarm (outside ``guard_bins`` of every bin with
    signal above max(rel_level × peak, abs_level)); all bins of a pixel without signal.

    The levels from the rows' peaks, then one compiled pass per row (:func:`_eligible_rows`: the signal bins'
    neighbourhoods of ±guard bins cleared), rows in chunks on ``threads`` threads (never changes the result)."""
    t = np.ascontiguousarray(truth)
    level = np.maximum(rel_level * t.max(axis=1), abs_level)
    if t.dtype != level.dtype or t.dtype not in (np.float32, np.float64):  # e.g. integer waveforms: compared
        t, level = t.astype(np.float64), level.astype(np.float64)        # with float64 levels, exactly
    P, B = t.shape
    el = np.empty((P, B), dtype=np.bool_)
    run_row_chunks(lambda a, b: _eligible_rows(t[a:b], level[a:b], int(guard_bins), el[a:b]), P, threads)
    return el


@kernel
def _eligible_rows(t, level, guard, el):
    """Per row: the bins with t > level and t > 0 are signal; ``el`` is False within ``guard`` bins of a signal
    bin, True elsewhere.  Blocks of 64 bins are first tested with one vectorised count: those without signal
    (most of a row) are passed over."""
    n_rows, n = t.shape
    for r in range(n_rows):
        for j in range(n):
            el[r, j] = True
        lv = level[r]
        if lv != lv:  # NaN level (a NaN in the row): no signal bin
            continue
        if lv < 0:
            lv = 0  # t > level and t > 0  <=>  t > max(level, 0)
        end = 0  # bins below ``end`` are already cleared
        for q in range(n // 64 + 1):
            j0 = q * 64
            if j0 + 64 <= n:
                c = 0
                for k in range(64):  # fixed trip count: compiled to SIMD compares
                    c += t[r, j0 + k] > lv
                if c == 0:
                    continue
            for j in range(j0, min(j0 + 64, n)):
                if t[r, j] > lv:
                    a = max(j - guard, end)
                    b = min(j + guard + 1, n)
                    for i in range(a, b):
                        el[r, i] = False
                    end = max(end, b)


@kernel
def _eligible_counts(el, lo, hi, cols, n_range, n_all, at_cols):
    """Per row of the bool (P, B) ``el``: the number of True in [lo, hi), in the whole row, and the values at
    the columns ``cols``."""
    n_rows, n = el.shape
    for r in range(n_rows):
        c_range = 0
        c_all = 0
        for j in range(n):
            if el[r, j]:
                c_all += 1
                if lo <= j < hi:
                    c_range += 1
        n_range[r] = c_range
        n_all[r] = c_all
        for k in range(cols.size):
            at_cols[r, k] = el[r, cols[k]]


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


@lru_cache(maxsize=4)
def _gauss_legendre(n_nodes):
    """Gauss–Legendre nodes and weights on [−1, 1] (computed once per order: an eigenvalue problem)."""
    x, w = np.polynomial.legendre.leggauss(n_nodes)
    x.flags.writeable = w.flags.writeable = False
    return x, w


def local_max_probability(u, cov3, n_nodes=96):
    """P(Z0 > u, Z0 > Z−, Z0 ≥ Z+) for a zero-mean Gaussian (Z−, Z0, Z+) with covariance ``cov3`` (3×3):
    the probability that a bin is a local maximum above the threshold u (Rice's argument for a sampled
    process).  Conditional on Z0 = y the two differences D± = Z0 − Z± are bivariate normal with means linear in
    y; the y-integral is done by Gauss–Legendre over [u, max(u, 0) + 12σ0].  ``u`` array (same units as Z).
    ``cov3`` may be a stack (..., 3, 3): one array operation for all (the result is (..., len(u)), each row the
    same numbers as a call with that covariance alone)."""
    C = np.asarray(cov3, dtype=np.float64)
    stack = C.shape[:-2]
    v0 = C[..., 1, 1]
    c1 = v0 - C[..., 1, 0]  # Cov(Z0, D−)
    c2 = v0 - C[..., 1, 2]  # Cov(Z0, D+)
    vd1 = v0 + C[..., 0, 0] - 2 * C[..., 1, 0]
    vd2 = v0 + C[..., 2, 2] - 2 * C[..., 1, 2]
    cd = v0 - C[..., 1, 0] - C[..., 1, 2] + C[..., 0, 2]
    s1 = np.sqrt(np.maximum(vd1 - c1 * c1 / v0, 1e-300))
    s2 = np.sqrt(np.maximum(vd2 - c2 * c2 / v0, 1e-300))
    rho = np.clip((cd - c1 * c2 / v0) / (s1 * s2), -1 + 1e-12, 1 - 1e-12)
    sig0 = np.sqrt(v0)
    x, w = _gauss_legendre(n_nodes)

    def per_cov(a):  # (..., 1) for the thresholds, (..., 1, 1) for the nodes
        return np.asarray(a)[(...,) + (None,) * a_dims]

    a_dims = 1
    u = np.atleast_1d(np.asarray(u, dtype=np.float64)) / per_cov(sig0)
    half = 0.5 * (np.maximum(u, 0.0) + 12.0 - u)  # standardized y over [u, max(u, 0) + 12]
    t = u[..., None] + half[..., None] * (x + 1.0)
    a_dims = 2
    y = t * per_cov(sig0)
    from scipy.special import ndtr
    dens = np.exp(-0.5 * t * t) / np.sqrt(2 * np.pi)
    h1, h2 = per_cov(c1 / v0) * y / per_cov(s1), per_cov(c2 / v0) * y / per_cov(s2)
    pos = (h1 > 0) & (h2 > 0)
    rho = np.broadcast_to(per_cov(rho), pos.shape)
    cond = np.empty(pos.shape)
    cond[pos] = _bvn_upper_orthant(h1[pos], h2[pos], rho[pos])
    neg = ~pos  # (non-positive arguments only for degenerate edges; product bound)
    if neg.any():
        cond[neg] = ndtr(h1[neg]) * ndtr(h2[neg])
    r = half * np.sum(w * dens * cond, axis=-1)
    return r if stack else r.reshape(-1)


def expected_false_alarms(threshold, sigma_raw, eligible, pulse=None, n_grid=64, threads=1):
    """Expected number of noise detections per pixel for white Gaussian raw noise of σ ``sigma_raw`` (the
    detector's threshold/noise model, docs/theory.md §9): Σ_j eligible[p, j] · P(bin j is a local maximum of the
    detection waveform above threshold[p]).  Exact for Gaussian noise per bin; the greedy minimum separation
    and the ``max_echoes`` cap (which only lower the count) are ignored.  Bins 1 … h and B−2−h … B−2 (the
    matched filter's 'nearest' edges) are computed position by position, the interior once.

    threshold : (P,) in detection-waveform units; eligible : (P, B) bool (:func:`eligible_bins`).
    Returns (P,) float64."""
    el = np.asarray(eligible, dtype=bool)
    return _expected_from_counts(threshold, sigma_raw, _eligible_summary(el, pulse, threads), pulse, n_grid,
                                 threads)


def _positions(n_bins, pulse):
    """(edge positions, first interior position or None, interior range [lo, hi)) of a waveform of ``n_bins``:
    the matched filter's 'nearest' edges make bins 1 … h and B−2−h … B−2 differ from the interior."""
    h = 0 if pulse is None else len(pulse) // 2
    lo_edge = list(range(1, min(h + 1, n_bins - 1)))
    hi_edge = [j for j in range(max(n_bins - 1 - h, h + 1), n_bins - 1)]
    interior = (h + 1, n_bins - 1 - h) if h + 1 < n_bins - 1 - h else None
    return lo_edge + hi_edge, interior


def _eligible_summary(el, pulse, threads=1):
    """One pass over the eligible bins (P, B): per pixel, the number of eligible interior bins, of eligible bins
    in all, and the flags at the edge positions (:func:`_positions`)."""
    el = np.ascontiguousarray(el)
    P, B = el.shape
    edges, interior = _positions(B, pulse)
    lo, hi = interior if interior else (0, 0)
    cols = np.array(edges, dtype=np.int64)
    n_int, n_all = np.empty(P, np.int64), np.empty(P, np.int64)
    at_cols = np.empty((P, cols.size), dtype=np.bool_)
    run_row_chunks(lambda a, b: _eligible_counts(el[a:b], lo, hi, cols, n_int[a:b], n_all[a:b], at_cols[a:b]),
                   P, threads)
    return {"n_bins": B, "n_interior": n_int, "n_eligible": n_all, "at_edges": at_cols}


def _expected_from_counts(threshold, sigma_raw, summary, pulse=None, n_grid=64, threads=1):
    """:func:`expected_false_alarms` from the per-pixel counts of :func:`_eligible_summary`."""
    thr = np.asarray(threshold, dtype=np.float64).reshape(-1)
    B = summary["n_bins"]
    P = summary["n_eligible"].size
    out = np.zeros(P)
    if B < 3 or not sigma_raw > 0:
        return out
    edges, interior = _positions(B, pulse)
    positions = edges + ([interior[0]] if interior else [])
    finite = np.isfinite(thr) & (thr > 0)
    if not finite.any():
        return out
    lo_u, hi_u = thr[finite].min(), thr[finite].max()
    grid = np.linspace(lo_u, hi_u, n_grid) if hi_u > lo_u else np.array([lo_u])
    covs = []
    for j in positions:
        rows = _filter_rows(B, pulse, [j - 1, j, j + 1])
        covs.append(sigma_raw ** 2 * rows @ rows.T)
    covs = np.array(covs)
    parts = np.array_split(np.arange(len(covs)), max(1, min(threads, len(covs))))
    if len(parts) > 1:  # (SciPy's special functions release the GIL)
        with ThreadPoolExecutor(max_workers=len(parts)) as pool:
            r_all = np.concatenate(list(pool.map(lambda i: local_max_probability(grid, covs[i]), parts)))
    else:
        r_all = local_max_probability(grid, covs)  # every position in one evaluation
    if grid.size > 1:  # interpolate log-rate in u (smooth, nearly quadratic): np.interp, every position at once
        log_r = np.log(np.maximum(r_all, 1e-300))
        rates = np.empty((len(positions), P))
        _interp_rows(thr, grid, log_r, np.diff(log_r, axis=1) / np.diff(grid), rates)
        np.exp(rates, out=rates)
    else:
        rates = np.repeat(r_all[:, :1], P, axis=1)
    rates = np.where(finite, rates, 0.0)
    if interior:
        out += summary["n_interior"] * rates[-1]
    for k in range(len(edges)):
        out += summary["at_edges"][:, k] * rates[k]
    return out


@kernel
def _interp_rows(x, xp, fp, slopes, out):
    """out[s] = np.interp(x, xp, fp[s]) for every row s of fp, bit for bit: NumPy's arithmetic (``slopes`` =
    (fp[:, j+1] − fp[:, j]) / (xp[j+1] − xp[j]), then slope·(x − xp[j]) + fp[j], the other end's form when that
    is NaN; fp[j] at a grid point and beyond the ends; NaN for a NaN x).  xp increasing, ≥ 2 points."""
    G = xp.size
    S = fp.shape[0]
    for p in range(x.size):
        xv = x[p]
        if xv != xv:
            for s in range(S):
                out[s, p] = xv
            continue
        if xv < xp[0]:
            j = -1
        elif xv > xp[G - 1]:
            j = G
        else:  # the last j with xp[j] <= x
            lo, hi = 0, G
            while hi - lo > 1:
                mid = (lo + hi) >> 1
                if xp[mid] <= xv:
                    lo = mid
                else:
                    hi = mid
            j = lo
        for s in range(S):
            if j == -1:
                out[s, p] = fp[s, 0]
            elif j >= G - 1:
                out[s, p] = fp[s, G - 1]
            elif xp[j] == xv:
                out[s, p] = fp[s, j]
            else:
                r = slopes[s, j] * (xv - xp[j]) + fp[s, j]
                if r != r:
                    r = slopes[s, j] * (xv - xp[j + 1]) + fp[s, j + 1]
                    if r != r and fp[s, j] == fp[s, j + 1]:
                        r = fp[s, j]
                out[s, p] = r


def gaussian_false_alarm_summary(n_detected_fa, expected_per_pixel, n_eligible_bins, empty_pixels, fa_per_pixel):
    """Run-metadata record of false alarms (counts, rates per pixel/gate and per bin, Gaussian expectation)."""
    n_pix = int(expected_per_pixel.size)
    n_bins_el = int(n_eligible_bins)
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
                          abs_level=0.0, rel_level=FALSE_ALARM_REL_LEVEL, guard_fwhm=FALSE_ALARM_GUARD_FWHM,
                          threads=1):
    """False alarms of a detection run against the noise-free waveforms ``truth`` (P, B), and their expected
    number for Gaussian noise of σ ``noise_sigma`` (raw-waveform units; None: no expectation).

    A detection is a false alarm when no bin within ``guard_fwhm`` pulse widths of it holds signal above
    max(rel_level × the pixel's peak, abs_level) (:func:`false_alarm_mask`).  Expectation: Σ over pixels and
    eligible bins (outside those guard regions) of the probability that the bin is a local maximum of the
    detection waveform above the pixel's threshold (:func:`expected_false_alarms`).  ``threads``: the passes over
    the waveforms run in row chunks on that many threads (never changes the result).
    Returns ``(mask (P, K) bool, summary dict)``."""
    det = np.asarray(echoes.detected)
    P, K = det.shape[0], det.shape[-1]
    det = det.reshape(P, K)
    truth = np.asarray(truth).reshape(P, -1)
    guard = int(np.ceil(guard_fwhm * pulse_fwhm_bins))
    pix, slot = np.nonzero(det)
    eligible = eligible_bins(truth, guard, rel_level, abs_level, threads)
    counts = _eligible_summary(eligible, pulse, threads)
    fa = np.zeros((P, K), dtype=bool)
    j = np.clip(np.floor(np.asarray(echoes.position_bins).reshape(P, K)[pix, slot]).astype(np.int64), 0,
                truth.shape[1] - 1)
    fa[pix, slot] = eligible[pix, j]  # no signal within the guard of the detection's bin (= false_alarm_mask)
    if noise_sigma is not None and noise_sigma > 0:
        expected = _expected_from_counts(np.asarray(echoes.threshold).reshape(P), noise_sigma, counts, pulse,
                                         threads=threads)
    else:
        expected = np.full(P, np.nan)
    n_el = counts["n_eligible"]
    summary = gaussian_false_alarm_summary(int(fa.sum()), expected, int(n_el.sum()), n_el == truth.shape[1],
                                           fa.sum(axis=1))
    summary.update({"guard_bins": guard, "signal_level_relative": rel_level, "signal_level_absolute": abs_level,
                    "noise_sigma": noise_sigma,
                    "expectation_model": "white Gaussian noise of the signal-free bins' sigma; local maxima of the "
                                         "detection waveform above each pixel's threshold (Rice, per bin); "
                                         "minimum separation and max_echoes ignored"})
    return fa, summary
