"""False alarms of noisy echo detection (paper §3.1 products; docs/theory.md §9): which reported echoes have no
true return nearby, and how many a Gaussian noise model expects above each pixel's threshold.
"""
from __future__ import annotations

import math
import threading
from functools import lru_cache

import numpy as np

from ...jit import kernel
from ...threads import map_list
from .noisy import NoisyEchoes, run_row_chunks
from .matched_filter import matched_filter


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

    Rows in chunks on ``threads`` threads (never changes the result): one compiled pass per row, its level
    from its peak (:func:`_row_level`) then its guarded runs (:func:`_guarded_runs`)."""
    t = _as_float_rows(truth)
    P, B = t.shape
    el = np.empty((P, B), dtype=np.bool_)
    rel, absl = t.dtype.type(rel_level), t.dtype.type(abs_level)

    def run(a, b):
        _eligible_rows(t[a:b], rel, absl, int(guard_bins), el[a:b])

    run_row_chunks(run, P, threads)
    return el


def _as_float_rows(truth):
    """The waveforms as C-contiguous float32 or float64 rows (any other type as float64: exact for integers)."""
    t = np.ascontiguousarray(truth)
    return t if t.dtype in (np.float32, np.float64) else t.astype(np.float64)


@kernel
def _row_level(t, rel, absl):
    """Signal level of the row t: max(rel × the row's peak, absl) in the row's float type (rel and absl given
    in it), NaN for a row holding a NaN — NumPy's ``np.maximum(rel * t.max(), absl)`` to the bit, in two
    vectorised passes over the row (which the guarded runs then read from cache)."""
    peak = t[0]
    for j in range(t.shape[0]):
        v = t[j]
        peak = v if v > peak else peak
    n_nan = 0
    for j in range(t.shape[0]):
        n_nan += t[j] != t[j]
    if n_nan:
        return rel * np.float32(np.nan)  # (NaN in the row's type)
    lv = rel * peak
    return lv if lv >= absl else absl


@kernel
def _guarded_runs(t, lv, guard, starts, ends):
    """The bins within ``guard`` of a signal bin of the row t (t > lv and t > 0), as merged runs
    [starts[i], ends[i]) in order; returns how many (none for a NaN level).  Blocks of 64 bins are first tested
    with one vectorised count: those without signal (most of a row) are passed over."""
    n = t.shape[0]
    if lv != lv:
        return 0
    if lv < 0:
        lv = 0  # t > level and t > 0  <=>  t > max(level, 0)
    m = 0
    for q in range(n // 64 + 1):
        j0 = q * 64
        if j0 + 64 <= n:
            c = 0
            for k in range(64):  # fixed trip count: compiled to SIMD compares
                c += t[j0 + k] > lv
            if c == 0:
                continue
        for j in range(j0, min(j0 + 64, n)):
            if t[j] > lv:
                a = max(j - guard, 0)
                b = min(j + guard + 1, n)
                if m > 0 and a <= ends[m - 1]:  # joins the last run
                    ends[m - 1] = max(ends[m - 1], b)
                else:
                    starts[m], ends[m] = a, b
                    m += 1
    return m


@kernel
def _eligible_rows(t, rel, absl, guard, el):
    """Per row: ``el`` False on the guarded runs of :func:`_guarded_runs` (level: :func:`_row_level`), True
    elsewhere."""
    n = t.shape[1]
    starts, ends = np.empty(n, np.int64), np.empty(n, np.int64)
    for r in range(t.shape[0]):
        for j in range(n):
            el[r, j] = True
        for i in range(_guarded_runs(t[r], _row_level(t[r], rel, absl), guard, starts, ends)):
            for j in range(starts[i], ends[i]):
                el[r, j] = False


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


@kernel
def _outside_runs(j, starts, ends, m):
    """True when bin j lies in none of the m runs [starts, ends)."""
    for i in range(m):
        if starts[i] <= j < ends[i]:
            return False
    return True


@kernel
def _tally_row(r, starts, ends, m, lo, hi, n, cols, det_bin, n_range, n_all, at_cols, fa):
    """Row ``r`` of :func:`_classify_rows` from its ``m`` guarded runs [starts, ends) (the ineligible bins): the
    eligible bins in [lo, hi) and in all ``n``, the flags at ``cols`` and each detection's flag."""
    c_range, c_all = hi - lo, n
    for i in range(m):
        c_all -= ends[i] - starts[i]
        c_range -= max(0, min(ends[i], hi) - max(starts[i], lo))
    n_range[r], n_all[r] = c_range, c_all
    for k in range(cols.size):
        at_cols[r, k] = _outside_runs(cols[k], starts, ends, m)
    for k in range(det_bin.shape[1]):
        j = det_bin[r, k]
        fa[r, k] = _outside_runs(j, starts, ends, m) if j >= 0 else False


@kernel
def _classify_rows(t, rel, absl, guard, lo, hi, cols, det_bin, n_range, n_all, at_cols, fa):
    """What :func:`_eligible_rows` then :func:`_eligible_counts` give, from the guarded runs of each row without
    writing its flags: the eligible bins in [lo, hi) and in all, the flags at ``cols``, and each detection's
    flag fa[r, k] = eligible[r, det_bin[r, k]] for det_bin ≥ 0 (False for none)."""
    n = t.shape[1]
    starts, ends = np.empty(n, np.int64), np.empty(n, np.int64)
    for r in range(t.shape[0]):
        m = _guarded_runs(t[r], _row_level(t[r], rel, absl), guard, starts, ends)
        _tally_row(r, starts, ends, m, lo, hi, n, cols, det_bin, n_range, n_all, at_cols, fa)


@kernel
def _row_extents(truth, level, first, last, peak, bad, span_lo, span_hi):
    """Per row: the first and last bin above ``level`` (−1 when none), the row's largest value when it has such a
    bin (else −inf) and whether it holds a NaN.  One pass over each bin: 64-bin blocks tested with one vectorised
    count from the front up to the first signal bin and from the back down to the last, the bins between them
    (the signal stretch) in one vectorised max.  ``span_lo``/``span_hi`` (non-empty: one per row): every bin of
    row r outside [span_lo[r], span_hi[r]) is known to be exactly 0 (and ``level`` ≥ 0), so only the span is
    read — the same results."""
    n_rows = truth.shape[0]
    for r in range(n_rows):
        if span_lo.size:
            o = span_lo[r]
            t = truth[r, o:max(o, span_hi[r])]
        else:
            o = 0
            t = truth[r]
        n = t.shape[0]
        nan = 0
        f = -1
        j = 0
        while j + 64 <= n:
            c = 0
            d = 0
            for k in range(64):  # fixed trip count: compiled to SIMD compares
                v = t[j + k]
                c += v > level
                d += v != v
            nan += d
            if c:
                break
            j += 64
        for i in range(j, n):
            v = t[i]
            nan += v != v
            if v > level:
                f = i
                break
        first[r] = f
        last[r] = -1
        peak[r] = -np.inf
        if f >= 0:
            j = n
            while j - 64 > f:
                c = 0
                d = 0
                for k in range(j - 64, j):
                    v = t[k]
                    c += v > level
                    d += v != v
                nan += d
                if c:
                    break
                j -= 64
            lst = f
            for i in range(j - 1, f, -1):
                v = t[i]
                nan += v != v
                if v > level:
                    lst = i
                    break
            last[r] = lst
            pk = t[f]
            for i in range(f, lst + 1):
                v = t[i]
                pk = v if v > pk else pk
                nan += v != v
            peak[r] = pk
        if first[r] >= 0:  # (bins of the span → of the row)
            first[r] += o
            last[r] += o
        bad[r] = nan > 0


def row_extents(truth, level, threads=1, spans=None):
    """(first, last, peak, has_nan) per row of ``truth`` for the signal level ``level`` in the rows' float type
    (:func:`_row_extents`), in row chunks on ``threads`` threads.  ``spans``: (lo, hi) int64 per row when every bin
    of row r outside [lo[r], hi[r]) is exactly 0 (the flash frame's waveform windows): only the spans are read,
    for the same results; ignored when the level is not above 0 (zeros would then count)."""
    n_rows = len(truth)
    first, last = np.empty(n_rows, np.int64), np.empty(n_rows, np.int64)
    peak, bad = np.empty(n_rows, truth.dtype), np.empty(n_rows, np.bool_)
    lv = truth.dtype.type(level)
    lo = hi = np.zeros(0, np.int64)
    if spans is not None and lv > 0:
        lo, hi = (np.ascontiguousarray(np.clip(x, 0, truth.shape[1]), dtype=np.int64) for x in spans)
    run_row_chunks(lambda a, b: _row_extents(truth[a:b], lv, first[a:b], last[a:b], peak[a:b], bad[a:b],
                                             lo[a:b], hi[a:b]), n_rows, threads)
    return first, last, peak, bad


@kernel
def _guarded_runs_in(t, lv, guard, j_lo, j_hi, starts, ends):
    """:func:`_guarded_runs` of the row t when no bin outside [j_lo, j_hi) exceeds max(lv, 0): the same runs, from
    a scan of those bins alone (64-bin blocks tested with one vectorised count)."""
    n = t.shape[0]
    if lv < 0:
        lv = 0
    m = 0
    j0 = j_lo
    while j0 < j_hi:
        j1 = min(j0 + 64, j_hi)
        if j1 - j0 == 64:
            c = 0
            for k in range(j0, j0 + 64):
                c += t[k] > lv
            if c == 0:
                j0 = j1
                continue
        for j in range(j0, j1):
            if t[j] > lv:
                a = max(j - guard, 0)
                b = min(j + guard + 1, n)
                if m > 0 and a <= ends[m - 1]:
                    ends[m - 1] = max(ends[m - 1], b)
                else:
                    starts[m], ends[m] = a, b
                    m += 1
        j0 = j1
    return m


@kernel
def _classify_rows_in(t, rel, absl, guard, lo, hi, cols, det_bin, first, last, peak, level, n_range, n_all, at_cols,
                      fa):
    """:func:`_classify_rows` given each row's extent at a signal level (no bin outside [first, last] above
    ``level``; first −1 when no bin is; ``peak`` the row's largest value when first ≥ 0; no NaN in the rows): a row
    whose false-alarm level max(rel × peak, absl, 0) is at least ``level`` is scanned over [first, last] only
    (its signal bins all lie there), any other row whole, as :func:`_classify_rows` does."""
    n = t.shape[1]
    starts, ends = np.empty(n, np.int64), np.empty(n, np.int64)
    zero = absl - absl
    for r in range(t.shape[0]):
        if first[r] >= 0:
            lv = rel * peak[r]
            lv = lv if lv >= absl else absl
        else:
            lv = absl
        lv0 = lv if lv >= zero else zero
        if lv0 >= level:
            m = _guarded_runs_in(t[r], lv, guard, first[r], last[r] + 1, starts, ends) if first[r] >= 0 else 0
        else:
            m = _guarded_runs(t[r], _row_level(t[r], rel, absl), guard, starts, ends)
        _tally_row(r, starts, ends, m, lo, hi, n, cols, det_bin, n_range, n_all, at_cols, fa)


def filter_rows(n_bins, pulse, rows):
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


def expected_false_alarms(threshold, sigma_raw, eligible, pulse=None, threads=1):
    """Expected number of noise detections per pixel for white Gaussian raw noise of σ ``sigma_raw`` (the
    detector's threshold/noise model, docs/theory.md §9): Σ_j eligible[p, j] · P(bin j is a local maximum of the
    detection waveform above threshold[p]).  Exact for Gaussian noise per bin; the greedy minimum separation
    and the ``max_echoes`` cap (which only lower the count) are ignored.  Bins 1 … h and B−2−h … B−2 (the
    matched filter's 'nearest' edges) are computed position by position, the interior once.

    threshold : (P,) in detection-waveform units; eligible : (P, B) bool (:func:`eligible_bins`).
    Returns (P,) float64."""
    el = np.asarray(eligible, dtype=bool)
    return _expected_from_counts(threshold, sigma_raw, _eligible_summary(el, pulse, threads), pulse, threads)


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


def _expected_from_counts(threshold, sigma_raw, summary, pulse=None, threads=1):
    """:func:`expected_false_alarms` from the per-pixel counts of :func:`_eligible_summary`: each position's
    rate at each pixel's threshold, interpolated on the lattice of :class:`_RateLattice` (kept between calls).
    ``sigma_raw``: one σ, or one per pixel (an array)."""
    thr = np.asarray(threshold, dtype=np.float64).reshape(-1)
    B = summary["n_bins"]
    P = summary["n_eligible"].size
    out = np.zeros(P)
    sig = np.asarray(sigma_raw, dtype=np.float64)
    if B < 3 or not np.all(sig > 0):
        return out
    finite = np.isfinite(thr) & (thr > 0)
    if not finite.any():
        return out
    sig = sig.reshape(-1) if sig.ndim else float(sig)
    t = np.where(finite, thr / sig, 0.0)  # thresholds in units of the raw noise σ
    lattice = _rate_lattice(B, None if pulse is None else np.asarray(pulse, np.float64).tobytes())
    node = np.floor(t[finite] * _LATTICE_DIVISIONS).astype(np.int64)
    lo, g = lattice.values(np.unique(node), threads)
    n_int = summary["n_interior"] if lattice.has_interior else np.zeros(P, np.int64)
    at_edges = np.ascontiguousarray(summary["at_edges"])
    run_row_chunks(lambda a, b: _lattice_expectation(t[a:b], finite[a:b], _LATTICE_DIVISIONS, lo, g, lattice.inv_2v0,
                                                     n_int[a:b], at_edges[a:b], out[a:b]), P, threads)
    return out


#: The local-maximum rates are evaluated at thresholds t = i/_LATTICE_DIVISIONS raw-noise σ (the lattice) and
#: interpolated between them: 4-point Lagrange of log-rate + t²/(2 v₀), a smooth, slowly varying function
#: (v₀: the detection waveform's variance per unit raw variance).  Relative error of a rate ≤ 1e-7 (tested
#: against the quadrature at the threshold itself).
_LATTICE_DIVISIONS = 32


class _RateLattice:
    """The local-maximum rates of one waveform layout (bin count, pulse) for unit raw noise σ: position by
    position (the matched filter's edge positions, then the interior, as :func:`_positions`), at the lattice
    thresholds a frame needs; every value computed once and kept (a run's frames share their layout)."""

    def __init__(self, n_bins, pulse):
        self.edges, interior = _positions(n_bins, pulse)
        self.has_interior = interior is not None
        positions = self.edges + ([interior[0]] if interior else [])
        self.covs = np.array([(r := filter_rows(n_bins, pulse, [j - 1, j, j + 1])) @ r.T for j in positions])
        self.inv_2v0 = 0.5 / self.covs[:, 1, 1]
        self._known = {}
        self._lock = threading.Lock()

    def values(self, nodes, threads=1):
        """(lo, g): g[s, i − lo + 1] = log rate + t²/(2 v₀) of position s at t = i/_LATTICE_DIVISIONS for every
        lattice node i ∈ [n − 1, n + 2] of each of the (sorted) ``nodes`` n; lo = nodes[0].  Unneeded columns NaN."""
        need = np.unique((nodes[:, None] + np.arange(-1, 3)).reshape(-1))
        with self._lock:
            missing = [i for i in need.tolist() if i not in self._known]
            if missing:
                t = np.array(missing, dtype=np.float64) / _LATTICE_DIVISIONS
                parts = np.array_split(np.arange(len(self.covs)), max(1, min(threads, len(self.covs))))
                if len(parts) > 1:  # (SciPy's special functions release the GIL)
                    r = np.concatenate(map_list(lambda k: local_max_probability(t, self.covs[k]), parts,
                                                len(parts)))
                else:
                    r = local_max_probability(t, self.covs)
                g = np.log(np.maximum(r, 1e-300)) + t * t * self.inv_2v0[:, None]
                for c, i in enumerate(missing):
                    self._known[i] = g[:, c]
            lo = int(nodes[0])
            table = np.full((len(self.covs), int(nodes[-1]) - lo + 4), np.nan)
            for i in need.tolist():
                table[:, i - lo + 1] = self._known[i]
        return lo, table


@lru_cache(maxsize=8)
def _rate_lattice(n_bins, pulse_bytes):
    return _RateLattice(n_bins, None if pulse_bytes is None else np.frombuffer(pulse_bytes, np.float64))


@kernel
def _lattice_expectation(t, finite, divisions, lo, g, inv_2v0, n_interior, at_edges, out):
    """out[p] = n_interior[p] × rate of the interior + Σ_k at_edges[p, k] × rate of edge position k, each rate at
    the threshold t[p] (raw-σ units; nothing where not ``finite``) from the lattice values g (rows: the edge
    positions, then the interior; :meth:`_RateLattice.values`) by 4-point Lagrange interpolation of
    log-rate + t²/(2 v₀).  Each position's rate is computed once per run of pixels with the same threshold (a
    calibrated or fixed threshold: one for the frame) and added in the same order: the same numbers."""
    n_edges, n_pos = at_edges.shape[1], g.shape[0]
    rate = np.empty(n_pos)
    t_prev = np.nan
    for p in range(t.size):
        if not finite[p]:
            continue
        if not t[p] == t_prev:  # (the rates of this threshold)
            t_prev = t[p]
            x = t[p] * divisions
            n = math.floor(x)
            f = x - n
            c = int(n) - lo  # column of node n − 1
            w0 = -f * (f - 1.0) * (f - 2.0) / 6.0
            w1 = (f + 1.0) * (f - 1.0) * (f - 2.0) / 2.0
            w2 = -(f + 1.0) * f * (f - 2.0) / 2.0
            w3 = (f + 1.0) * f * (f - 1.0) / 6.0
            tt = t[p] * t[p]
            for s in range(n_pos):
                v = w0 * g[s, c] + w1 * g[s, c + 1] + w2 * g[s, c + 2] + w3 * g[s, c + 3]
                rate[s] = math.exp(v - tt * inv_2v0[s])
        acc = out[p]
        for s in range(n_edges, n_pos):  # the interior (none for short rows)
            if n_interior[p]:
                acc += n_interior[p] * rate[s]
        for s in range(n_edges):
            if at_edges[p, s]:
                acc += rate[s]
        out[p] = acc


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
                          threads=1, extents=None):
    """False alarms of a detection run against the noise-free waveforms ``truth`` (P, B), and their expected
    number for Gaussian noise of σ ``noise_sigma`` (raw-waveform units, one number or one per pixel; None: no
    expectation).

    A detection is a false alarm when no bin within ``guard_fwhm`` pulse widths of it holds signal above
    max(rel_level × the pixel's peak, abs_level) (:func:`false_alarm_mask`).  Expectation: Σ over pixels and
    eligible bins (outside those guard regions) of the probability that the bin is a local maximum of the
    detection waveform above the pixel's threshold (:func:`expected_false_alarms`).  ``threads``: the passes over
    the waveforms run in row chunks on that many threads (never changes the result).  ``extents``: the rows'
    signal extents (:func:`row_extents`: ``first``, ``last``, ``peak``, ``has_nan``, at ``level`` in the rows'
    type) known from an earlier pass (the statistical route's, core.physics.detection.stretches): rows whose
    false-alarm level is at least that level are then scanned over their signal stretch only, the others whole
    (the same result; ignored when a row holds a NaN).  (Without them the rows are read whole: computing the
    extents here first measured no faster, each row's passes then reading it from cache.)
    Returns ``(mask (P, K) bool, summary dict)``."""
    det = np.asarray(echoes.detected)
    P, K = det.shape[0], det.shape[-1]
    det = det.reshape(P, K)
    truth = np.asarray(truth).reshape(P, -1)
    guard = int(np.ceil(guard_fwhm * pulse_fwhm_bins))
    t = _as_float_rows(truth)
    B = t.shape[1]
    det_bin = np.where(det, np.clip(np.floor(np.asarray(echoes.position_bins).reshape(P, K)), 0, B - 1), -1)
    det_bin = det_bin.astype(np.int64)  # (NaN positions of undetected slots: −1 by the mask above)
    edges, interior = _positions(B, pulse)
    lo, hi = interior if interior else (0, 0)
    cols = np.array(edges, dtype=np.int64)
    n_int, n_all = np.empty(P, np.int64), np.empty(P, np.int64)
    at_cols = np.empty((P, cols.size), dtype=np.bool_)
    fa = np.empty((P, K), dtype=bool)  # no signal within the guard of the detection's bin (= false_alarm_mask)

    rel, absl = t.dtype.type(rel_level), t.dtype.type(abs_level)

    if extents is not None and not np.any(extents["has_nan"]) and np.asarray(extents["peak"]).dtype == t.dtype:
        first, last, peak = extents["first"], extents["last"], extents["peak"]
        level = t.dtype.type(extents["level"])

        def run(a, b):
            _classify_rows_in(t[a:b], rel, absl, guard, lo, hi, cols, det_bin[a:b], first[a:b], last[a:b], peak[a:b],
                              level, n_int[a:b], n_all[a:b], at_cols[a:b], fa[a:b])
    else:
        def run(a, b):
            _classify_rows(t[a:b], rel, absl, guard, lo, hi, cols, det_bin[a:b], n_int[a:b], n_all[a:b],
                           at_cols[a:b], fa[a:b])

    run_row_chunks(run, P, threads)
    counts = {"n_bins": B, "n_interior": n_int, "n_eligible": n_all, "at_edges": at_cols}
    if noise_sigma is not None and np.all(np.asarray(noise_sigma) > 0):
        expected = _expected_from_counts(np.asarray(echoes.threshold).reshape(P), noise_sigma, counts, pulse,
                                         threads=threads)
    else:
        expected = np.full(P, np.nan)
    n_el = counts["n_eligible"]
    summary = gaussian_false_alarm_summary(int(fa.sum()), expected, int(n_el.sum()), n_el == B,
                                           fa.sum(axis=1))
    summary.update({"guard_bins": guard, "signal_level_relative": rel_level, "signal_level_absolute": abs_level,
                    "noise_sigma": noise_sigma if noise_sigma is None or not np.ndim(noise_sigma) else
                    {"min": float(np.min(noise_sigma)), "max": float(np.max(noise_sigma))},
                    "expectation_model": "white Gaussian noise of the signal-free bins' sigma; local maxima of the "
                                         "detection waveform above each pixel's threshold (Rice, per bin); "
                                         "minimum separation and max_echoes ignored"})
    return fa, summary
