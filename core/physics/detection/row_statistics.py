"""Robust statistics and the matched filter of one waveform row: the compiled per-row kernels of noisy echo
detection (core/physics/detection/noisy.py), docs/theory.md §9.

Baseline and noise of a row: median and 1.4826 × median absolute deviation — exact order statistics (float
rows: selection on integer keys that sort like the floats; integer A/D rows: counting histograms), equal to
NumPy's ``np.median`` to the bit; the quiet-90 % rms where the MAD of integer codes is 0.  Matched filter:
SciPy ``correlate1d``'s summation order, vectorised across outputs.
"""
from __future__ import annotations

import math

import numpy as np

from ...jit import kernel

#: σ of a normal distribution = MAD × this
MAD_TO_SIGMA = 1.482602218505602


@kernel
def _select(a, b, n, k):
    """(k-th, (k−1)-th) smallest of a[:n] (0-based; the second is meaningless for k = 0), exact: quickselect
    whose partition is branch-free (three-way, into the other buffer: a and b are both overwritten), so that
    noise-like data costs no mispredicted branches.  Terminates on any input (the pivot is an element of the
    current part, which always leaves the part; NaN compares as equal to everything)."""
    src, dst = a, b
    lo, m = 0, n
    below = a[0]  # the largest element known to lie below the current part (set before it is ever needed)
    while True:
        x, y, z = src[lo], src[lo + m // 2], src[lo + m - 1]
        p = max(min(x, y), min(max(x, y), z))
        nl, ng = 0, 0
        for i in range(lo, lo + m):
            v = src[i]
            dst[nl] = v
            dst[m - 1 - ng] = v
            nl += v < p
            ng += v > p
        if k < nl:
            lo, m = 0, nl
        elif k >= m - ng:
            k -= m - ng
            lo, m = m - ng, ng
            below = p
        else:  # k falls on the elements equal to the pivot
            if k > nl:
                return p, p
            if nl == 0:
                return p, below
            mx = dst[0]
            for i in range(1, nl):
                mx = max(mx, dst[i])
            return p, mx
        src, dst = dst, src


#: Bits of float32 → order keys (int32 whose order is the float order: −0 just below +0); NaN keys lie
#: beyond those of ±inf.
_KEY_POS_INF, _KEY_NEG_INF = 0x7F800000, -0x7F800001
#: Order statistics of float32 rows: a strided sample of this many values brackets the wanted rank, ...
_SAMPLE = 32
#: ... then the bracket is halved (counting passes, vectorised) until it holds at most this many values.
_BRACKET = 64


@kernel
def _key32(b):
    """The order key of float32 bits b (int32), and back (the map is its own inverse)."""
    return b ^ ((b >> 31) & 0x7FFFFFFF)


@kernel
def _order_stats32(x, k_lo, k_hi, keys, s1, s2, cast):
    """(x₍k_lo₎, x₍k_hi₎): order statistics (0-based ranks, k_lo ≤ k_hi ≤ k_lo + 1) of the float32 row x,
    exact; NaN if x holds a NaN (as np.median).  On the order keys of the values: two ranks of a strided
    sample propose a bracket, which is narrowed by bisection in value (each step one vectorised counting pass)
    until it holds ≤ _BRACKET values; those are gathered and selected (:func:`_select`).  Equal values
    −0.0 and +0.0 are ordered −0.0 first.  keys, s1, s2 (int32, len(x)) and cast (int32, ≥ 1) are scratch."""
    n = x.shape[0]
    bits = x.view(np.int32)
    mn, mx = np.int32(0x7FFFFFFF), np.int32(-0x7FFFFFFF - 1)
    for i in range(n):
        kk = _key32(bits[i])
        keys[i] = kk
        mn, mx = min(mn, kk), max(mx, kk)
    if mx > _KEY_POS_INF or mn < _KEY_NEG_INF:
        return np.float32(np.nan), np.float32(np.nan)
    vals = cast.view(np.float32)
    # invariant: #(keys ≤ lo) = n_lo ≤ k_lo and #(keys ≤ hi) = n_hi > k_hi
    lo, hi, n_lo, n_hi = np.int64(mn) - 1, np.int64(mx), 0, n
    n_proposed = 0
    p1, p2 = np.int64(0), np.int64(0)
    if n >= 8 * _SAMPLE:
        stride, r = n // _SAMPLE, (k_hi * _SAMPLE) // n
        for j in range(_SAMPLE):
            s1[j] = keys[j * stride]
        p1 = np.int64(_select(s1, s2, _SAMPLE, max(r - 6, 0))[0])
        for j in range(_SAMPLE):
            s1[j] = keys[j * stride]
        p2 = np.int64(_select(s1, s2, _SAMPLE, min(r + 6, _SAMPLE - 1))[0])
    while n_hi - n_lo > _BRACKET and hi - lo > 1:
        t = lo
        if n_proposed == 0 and n >= 8 * _SAMPLE:
            t, n_proposed = p1, 1
            if not lo < t < hi:
                t, n_proposed = p2, 2
        elif n_proposed == 1:
            t, n_proposed = p2, 2
        if not lo < t < hi:  # halve the bracket in value (in key order if that does not split it)
            cast[0] = _key32(np.int32(max(lo, mn)))
            v_lo = np.float64(vals[0])
            cast[0] = _key32(np.int32(hi))
            vals[0] = np.float32(0.5 * v_lo + 0.5 * np.float64(vals[0]))
            t = np.int64(_key32(cast[0]))
            if not lo < t < hi:
                t = (lo + hi) >> 1
        t32 = np.int32(t)
        c = 0
        for i in range(n):
            c += keys[i] <= t32
        if c > k_hi:
            hi, n_hi = t, c
        elif c <= k_lo:
            lo, n_lo = t, c
        else:  # c = k_hi = k_lo + 1: the largest key ≤ t and the smallest above
            a, b = np.int32(-0x7FFFFFFF - 1), np.int32(0x7FFFFFFF)
            for i in range(n):
                kk = keys[i]
                a = max(a, kk if kk <= t32 else np.int32(-0x7FFFFFFF - 1))
                b = min(b, kk if kk > t32 else np.int32(0x7FFFFFFF))
            cast[0] = _key32(a)
            va = vals[0]
            cast[0] = _key32(b)
            return va, vals[0]
    if hi - lo <= 1:  # every value in the bracket is the key hi
        cast[0] = _key32(np.int32(hi))
        return vals[0], vals[0]
    lo1, width, m = lo + 1, np.uint32(hi - lo), 0
    for i in range(n):  # gather the bracket, lo < key ≤ hi (branch-free, one unsigned comparison)
        kk = keys[i]
        s1[m] = kk
        m += np.uint32(kk - lo1) < width
    b, a = _select(s1, s2, m, k_hi - n_lo)
    if k_lo == k_hi:
        a = b
    cast[0] = _key32(a)
    va = vals[0]
    cast[0] = _key32(b)
    return va, vals[0]


@kernel
def _median32(x, keys, s1, s2, cast):
    """The median of the float32 row x as NumPy computes it: the middle element, or the mean of the two middle
    ones rounded to float32 (NaN if x holds a NaN)."""
    n = x.shape[0]
    k = n // 2
    below, mid = _order_stats32(x, k - 1 + n % 2, k, keys, s1, s2, cast)
    if n % 2:
        return mid
    return np.float32(mid + below) * np.float32(0.5)


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
#: ... and, when their MAD is 0, the counting quiet-90 % rms, where every deviation, square and partial sum is
#: exact in float64 (so that any summation order is NumPy's pairwise sum bit for bit): |values| < 2²², rows
#: shorter than 2¹⁹ bins.
_EXACT_VALUE, _EXACT_BINS = float(1 << 22), 1 << 19


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
def _deviation_ranks(counts, lo, span, base, k1, k2):
    """The k1-th and k2-th smallest (0-based, k1 ≤ k2; k1 may be −1: then 0) of the deviations
    |lo + i − base| (float32) of the values lo + i repeated counts[i] times: walked outward from the median in
    increasing order."""
    i_dn = int(math.floor(base - lo))
    i_up = i_dn + 1
    taken = 0
    d1, d2 = np.float32(0.0), np.float32(0.0)
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
        if taken <= k1 < taken + c:
            d1 = d
        if k2 < taken + c:
            d2 = d
            return d1, d2
        taken += c


@kernel
def _counting_median_mad(y, lo, span, counts):
    """(median, MAD) as float32 of a row of integer values in [lo, lo + span): the same order statistics as
    sorting, in O(n + span); ``counts`` (≥ 4 span) is left holding the histogram in counts[:span]."""
    n = y.shape[0]
    counts[:4 * span] = 0
    n4 = n - n % 4
    for i in range(0, n4, 4):  # four partial histograms: consecutive equal values do not wait on each other
        counts[int(y[i] - lo)] += 1
        counts[span + int(y[i + 1] - lo)] += 1
        counts[2 * span + int(y[i + 2] - lo)] += 1
        counts[3 * span + int(y[i + 3] - lo)] += 1
    for i in range(n4, n):
        counts[int(y[i] - lo)] += 1
    for i in range(span):
        counts[i] += counts[span + i] + counts[2 * span + i] + counts[3 * span + i]
    k = n // 2
    vk = np.float32(lo + _kth_from_counts(counts, span, k))
    if n % 2:
        base = vk
    else:
        base = np.float32(np.float32(lo + _kth_from_counts(counts, span, k - 1)) + vk) * np.float32(0.5)
    d_km1, d_k = _deviation_ranks(counts, lo, span, base, k - 1, k)
    if n % 2:
        return base, d_k
    return base, np.float32(d_km1 + d_k) * np.float32(0.5)


@kernel
def _quiet_quantile(n):
    """NumPy's linear quantile 0.9 of n values: the ranks (prev, nxt) of the two order statistics around it and
    the weight γ (then :func:`_lerp_quantile`)."""
    virtual = n * 0.9 + (1.0 + 0.9 * (1.0 - 1.0 - 1.0)) - 1.0
    prev = int(math.floor(virtual))
    gamma = virtual - prev
    prev = min(max(prev, 0), n - 1)
    return prev, min(prev + 1, n - 1), gamma


@kernel
def _lerp_quantile(a, b, gamma):
    """NumPy's linear quantile between the order statistics a ≤ b with weight γ."""
    diff = b - a
    return b - diff * (1.0 - gamma) if gamma >= 0.5 else a + diff * gamma


@kernel
def baseline_noise_row(y, keys, s1, s2, cast, dev, d1, d2, counts):
    """(median, σ) of one float32 row: σ = 1.4826 × MAD, or where the MAD is 0 the rms deviation of the quietest
    90 % of the samples (NumPy's linear quantile, its pairwise sum).  keys, s1, s2, cast (int32), dev (float32),
    d1, d2 (float64) and counts are scratch (:func:`row_scratch`)."""
    n = y.shape[0]
    lo, hi, counted = y[0], y[0], True
    for i in (0, n // 2, n - 1):  # most float rows show at once
        counted = counted and y[i] == np.floor(y[i])
    if counted:  # fractional values (NaN counts) and the extremes by their order keys: one vectorised pass
        bits = y.view(np.int32)
        n_frac, k_min, k_max = 0, np.int32(0x7FFFFFFF), np.int32(-0x7FFFFFFF - 1)
        for i in range(n):
            n_frac += y[i] != np.floor(y[i])
            kk = _key32(bits[i])
            k_min, k_max = min(k_min, kk), max(k_max, kk)
        cast[0], cast[1] = _key32(k_min), _key32(k_max)
        lo, hi = cast.view(np.float32)[0], cast.view(np.float32)[1]
        counted = n_frac == 0 and hi - lo < _COUNTING_RANGE
    span = 0
    if counted:  # A/D counts: the median and MAD by counting
        span = int(hi - lo) + 1
        base, mad = _counting_median_mad(y, lo, span, counts)
    else:
        base = _median32(y, keys, s1, s2, cast)
        for i in range(n):
            dev[i] = abs(y[i] - base)
        mad = _median32(dev, keys, s1, s2, cast)
    sigma = np.float64(mad) * MAD_TO_SIGMA
    if sigma != 0:
        return base, sigma
    # A/D-quantized noise below one count: the rms deviation of the quietest 90 % of the samples
    # (np.quantile(d, 0.9), method "linear"; the squares below it summed as np.sum does)
    prev, nxt, gamma = _quiet_quantile(n)
    if counted and n < _EXACT_BINS and max(-lo, hi) < _EXACT_VALUE:
        # from the histogram: deviations are exact half-integers, squares and sums exact in any order
        da, db = _deviation_ranks(counts, lo, span, base, prev, nxt)
        q = _lerp_quantile(np.float64(da if prev != nxt else db), np.float64(db), gamma)
        count, total = 0, 0.0
        for i in range(span):
            c = counts[i]
            d = np.float64(abs(np.float32(lo + i) - base))
            if c and d <= q:
                count += c
                total += c * (d * d)
        return base, math.sqrt(total / max(count, 1))
    if counted:
        for i in range(n):
            dev[i] = abs(y[i] - base)
    for i in range(n):
        d1[i] = dev[i]
    b, a = _select(d1, d2, n, nxt)
    if prev == nxt:
        a = b
    q = _lerp_quantile(a, b, gamma)
    count = 0
    for i in range(n):
        d = np.float64(dev[i])
        if d <= q:
            count += 1
            d1[i] = d * d * 1.0
        else:
            d1[i] = d * d * 0.0
    return base, math.sqrt(pairwise_sum(d1, 0, n) / max(count, 1))


@kernel
def row_scratch(n):
    """Scratch of :func:`baseline_noise_row` for rows of n values (one set per thread, reused row after row)."""
    return (np.empty(n, np.int32), np.empty(n, np.int32), np.empty(n, np.int32), np.empty(2, np.int32),
            np.empty(n, np.float32), np.empty(n), np.empty(n), np.empty(4 * _COUNTING_RANGE, np.int64))


@kernel
def _baseline_noise_rows(y, base, sigma):
    keys, s1, s2, cast, dev, d1, d2, counts = row_scratch(y.shape[1])
    for r in range(y.shape[0]):
        base[r], sigma[r] = baseline_noise_row(y[r], keys, s1, s2, cast, dev, d1, d2, counts)


def robust_baseline_noise(waveforms):
    """Per-pixel baseline (median) and noise σ = 1.4826 × median(|y − median|) along the last axis (float32
    arithmetic, as NumPy on float32 rows).  Robust to the echoes themselves as long as they occupy well under half
    of the bins.  Where the MAD is 0 (noise below one A/D count), σ is the rms deviation of the quietest 90 % of
    the samples.  A row holding a NaN gets NaN for both (as np.median)."""
    y = np.ascontiguousarray(waveforms, dtype=np.float32)
    rows = y.reshape(-1, y.shape[-1])
    base, sigma = np.empty(len(rows), np.float32), np.empty(len(rows))
    _baseline_noise_rows(rows, base, sigma)
    return base.astype(np.float64).reshape(y.shape[:-1]), sigma.reshape(y.shape[:-1])


#: Outputs of the matched filter summed together, tap by tap (their float64 sums stay in L1 / registers).
FILTER_BLOCK = 256


@kernel
def correlate_row(y, b32, w, ypad, acc, out):
    """out = SciPy's correlate1d of y − b32 (float32) with a symmetric odd kernel ``w`` (float64), 'nearest'
    edges: each output summed in float64 in SciPy's order (centre tap, then the folded pairs from the outermost
    in) and rounded to float32.  The tap loop runs outside a block of outputs, which keeps every output's
    order and lets the compiler vectorise across outputs.  ypad (n + len(w) − 1) and acc (FILTER_BLOCK) are
    float64 scratch."""
    n, h = y.shape[0], w.shape[0] // 2
    for i in range(h):  # the row with its edges clamped ('nearest'), in float64
        ypad[i] = np.float64(y[0] - b32)
        ypad[n + h + i] = np.float64(y[n - 1] - b32)
    body = ypad[h:h + n]
    for i in range(n):
        body[i] = np.float64(y[i] - b32)
    wc = w[h]
    for s in range(0, n, FILTER_BLOCK):  # (slices, indexed from 0: the compiler vectorises these loops)
        m = min(FILTER_BLOCK, n - s)
        c = s + h
        centre, dst = ypad[c:c + m], out[s:s + m]
        for i in range(m):
            acc[i] = centre[i] * wc
        jj = -h
        while jj + 4 <= 0:  # four taps per pass over the block, each added in turn
            w1, w2, w3, w4 = w[h + jj], w[h + jj + 1], w[h + jj + 2], w[h + jj + 3]
            l1, r1 = ypad[c + jj:c + jj + m], ypad[c - jj:c - jj + m]
            l2, r2 = ypad[c + jj + 1:c + jj + 1 + m], ypad[c - jj - 1:c - jj - 1 + m]
            l3, r3 = ypad[c + jj + 2:c + jj + 2 + m], ypad[c - jj - 2:c - jj - 2 + m]
            l4, r4 = ypad[c + jj + 3:c + jj + 3 + m], ypad[c - jj - 3:c - jj - 3 + m]
            for i in range(m):
                a = acc[i] + (l1[i] + r1[i]) * w1
                a += (l2[i] + r2[i]) * w2
                a += (l3[i] + r3[i]) * w3
                acc[i] = a + (l4[i] + r4[i]) * w4
            jj += 4
        while jj < 0:
            wj = w[h + jj]
            left, right = ypad[c + jj:c + jj + m], ypad[c - jj:c - jj + m]
            for i in range(m):
                acc[i] += (left[i] + right[i]) * wj
            jj += 1
        for i in range(m):
            dst[i] = acc[i]


@kernel
def _correlate_rows(y, w, out):
    ypad, acc = np.empty(y.shape[1] + w.shape[0] - 1), np.empty(FILTER_BLOCK)
    for r in range(y.shape[0]):
        correlate_row(y[r], np.float32(0.0), w, ypad, acc, out[r])


def matched_filter(waveforms, pulse):
    """Correlate each waveform (last axis) with the pulse shape, normalised by Σ pulse² so that A·pulse
    (centred on a bin) gives a filtered peak of exactly A.  White noise σ becomes σ/‖pulse‖.  The pulse must
    be symmetric (odd length, as :func:`core.physics.detection.noisy.gaussian_pulse_kernel`)."""
    k = np.asarray(pulse, dtype=np.float64)
    k = (k / np.sum(k * k)).astype(np.float32)
    if len(k) % 2 == 0 or not np.array_equal(k, k[::-1]):
        raise ValueError("matched_filter: the pulse must be symmetric with an odd number of samples")
    y = np.ascontiguousarray(waveforms, dtype=np.float32)
    out = np.empty(y.shape, np.float32)
    _correlate_rows(y.reshape(-1, y.shape[-1]), k.astype(np.float64), out.reshape(-1, y.shape[-1]))
    return out
