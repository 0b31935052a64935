"""Robust statistics of one waveform row: the compiled baseline and noise of noisy echo detection
(core/physics/detection/noisy.py), docs/theory.md §9; the matched filter is in :mod:`.matched_filter`.

Baseline and noise of a row: median and 1.4826 × median absolute deviation — exact order statistics (float
rows: selection on integer keys that sort like the floats; integer A/D rows: counting histograms), equal to
NumPy's ``np.median`` to the bit; the quiet-90 % rms where the MAD of integer codes is 0.
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
_KEY_MIN, _KEY_MAX = -0x7FFFFFFF - 1, 0x7FFFFFFF
#: Order statistics of float32 rows without a model of the values: a strided sample of this many values
#: proposes the first probes.
_SAMPLE = 32
#: Probes made when the wanted ranks are at most this many values from the near end also find the neighbours
#: of the probe (the end they set then knows its next value).
_AROUND = 8


@kernel
def _key32(b):
    """The order key of float32 bits b (int32), and back (the map is its own inverse)."""
    return b ^ ((b >> 31) & 0x7FFFFFFF)


@kernel
def _key_value(k, cast, castf):
    """The float32 value of the order key k (cast: int32 scratch, ≥ 1; castf: its float32 view)."""
    cast[0] = _key32(np.int32(k))
    return castf[0]


@kernel
def _value_key(v, cast, castf):
    """The order key of the float32 value v."""
    castf[0] = np.float32(v)
    return np.int64(_key32(cast[0]))


@kernel
def _float_keys(x, keys):
    """keys[:n] = the order keys of the float32 row x; returns their (min, max) (two vectorised passes: with the
    extremes in the same loop the compiler did not vectorise it)."""
    bits = x.view(np.int32)
    n = x.shape[0]
    for i in range(n):
        keys[i] = _key32(bits[i])
    mn, mx = keys[0], keys[0]
    for i in range(n):
        kk = keys[i]
        mn = kk if kk < mn else mn
        mx = kk if kk > mx else mx
    return np.int64(mn), np.int64(mx)


@kernel
def _count_le(keys, n, t):
    """#(keys[:n] ≤ t): one vectorised pass (the comparison as the sign of an int64 difference, which the
    compiler vectorises into fewer instructions than an int32 comparison widened to the count)."""
    c = 0
    for i in range(n):
        c += (t - np.int64(keys[i])) >= 0
    return c


@kernel
def _around(keys, n, t):
    """(#(keys ≤ t), the largest key ≤ t or _KEY_MIN, the smallest above t or _KEY_MAX): two vectorised passes
    (the count and the neighbours in one loop vectorised worse)."""
    t32 = np.int32(t)
    prv, nxt = np.int32(_KEY_MIN), np.int32(_KEY_MAX)
    for i in range(n):
        kk = keys[i]
        prv = max(prv, kk if kk <= t32 else np.int32(_KEY_MIN))
        nxt = min(nxt, kk if kk > t32 else np.int32(_KEY_MAX))
    return _count_le(keys, n, t), np.int64(prv), np.int64(nxt)


@kernel
def _step_up(keys, n, t):
    """(#(keys ≤ t), the smallest key above t or _KEY_MAX): two vectorised passes."""
    t32 = np.int32(t)
    nxt = np.int32(_KEY_MAX)
    for i in range(n):
        kk = keys[i]
        nxt = min(nxt, kk if kk > t32 else np.int32(_KEY_MAX))
    return _count_le(keys, n, t), np.int64(nxt)


@kernel
def _step_down(keys, n, t):
    """(#(keys < t), the largest key below t or _KEY_MIN): two vectorised passes."""
    t32 = np.int32(t)
    prv = np.int32(_KEY_MIN)
    for i in range(n):
        kk = keys[i]
        prv = max(prv, kk if kk < t32 else np.int32(_KEY_MIN))
    return _count_le(keys, n, t - 1), np.int64(prv)


@kernel
def _order_stats32(keys, n, mn, mx, k_lo, k_hi, s1, s2, cast, guess, density):
    """(x₍k_lo₎, x₍k_hi₎): order statistics (0-based ranks, k_lo ≤ k_hi ≤ k_lo + 1) of the float32 values
    whose order keys are keys[:n] (extremes mn, mx), exact; NaN if they hold a NaN (as np.median).  Vectorised
    counting passes only (no gather, no sort): a bracket lo < wanted ≤ hi whose ends' counts are known is
    narrowed by probes until a wanted rank is the next value past one end; passes then step from that end
    value by value.  The first probe is ``guess`` when ``density`` (values per unit value near the wanted rank,
    from a model; 0: none) is given, else two ranks of a strided sample.  Each next probe aims just past the
    wanted ranks on the near end's side: a Newton step from that end with the slope measured by the last two
    probes (``density`` before there are two), or, when that end is not a probe yet, interpolation in value
    between the ends.  A probe that does not halve the near end's distance makes the next one aim past the
    far side; after three such, the bracket is halved in value (in key order if that does not split it).
    ``guess`` and ``density`` only choose the probes: the result is exact whatever they are.  Equal values
    −0.0 and +0.0 are ordered −0.0 first.  s1, s2 (int32, ≥ _SAMPLE) and cast (int32, ≥ 1) are scratch."""
    if mx > _KEY_POS_INF or mn < _KEY_NEG_INF:
        return np.float32(np.nan), np.float32(np.nan)
    castf = cast.view(np.float32)
    # invariant: #(keys ≤ lo) = n_lo ≤ k_lo and #(keys ≤ hi) = n_hi > k_hi
    lo, hi, n_lo, n_hi = mn - 1, mx, 0, n
    p1, p2, n_prop, i_prop = np.int64(0), np.int64(0), 0, 0
    modelled = density > 0 and math.isfinite(guess) and abs(guess) < 3e38
    if modelled:
        p1, n_prop = _value_key(guess, cast, castf), 1
    elif n >= 8 * _SAMPLE:
        stride, r = n // _SAMPLE, (k_hi * _SAMPLE) // n
        for j in range(_SAMPLE):
            s1[j] = keys[j * stride]
        p1 = np.int64(_select(s1, s2, _SAMPLE, max(r - 6, 0))[0])
        for j in range(_SAMPLE):
            s1[j] = keys[j * stride]
        p2 = np.int64(_select(s1, s2, _SAMPLE, min(r + 6, _SAMPLE - 1))[0])
        n_prop = 2
    above_lo, below_hi = np.int64(_KEY_MAX), np.int64(_KEY_MIN)  # the next value past each end, if known
    fails = 0  # probes in a row that did not halve the near end's distance
    # value per count: measured by the last two probes (0: not yet), the model's; the last probe
    per_count, per_count_model, pv, pc = 0.0, 1.0 / density if modelled else 0.0, np.nan, -1
    while hi - lo > 1:
        d_lo, d_hi = k_lo - n_lo, n_hi - 1 - k_hi  # ranks between each end and the wanted ones
        near = min(d_lo, d_hi)
        if near == 0:
            break
        t = lo
        if i_prop < n_prop:
            t = p1 if i_prop == 0 else p2
            i_prop += 1
            if i_prop == 1 and n_prop == 2 and not lo < t < hi:
                t, i_prop = p2, 2
        elif fails < 3:
            up = (d_hi <= d_lo) != (fails > 0)  # aim past the wanted ranks on the near end's side (far: stuck)
            if near <= _AROUND:  # the probe finds its neighbours: aim between the wanted ranks
                target = 0.5 * (k_lo + k_hi + 1)
            else:
                margin = math.floor(0.5 * math.sqrt(near))
                target = k_hi + 1 + margin if up else k_lo - margin
            from_lo = d_lo <= d_hi
            step = per_count if per_count > 0 else per_count_model
            v = np.nan
            if step > 0 and (lo >= mn if from_lo else hi < mx):  # Newton step from the near end
                end, n_end = (lo, n_lo) if from_lo else (hi, n_hi)
                v = np.float64(_key_value(end, cast, castf)) + (target - n_end) * step
            else:  # interpolation between the ends
                v_lo = np.float64(_key_value(max(lo, mn), cast, castf))
                v = v_lo + (target - n_lo) / (n_hi - n_lo) * (np.float64(_key_value(hi, cast, castf)) - v_lo)
            if math.isfinite(v) and abs(v) < 3e38:
                t = _value_key(v, cast, castf)
        if not lo < t < hi:  # halve the bracket in value (in key order if that does not split it)
            v = 0.5 * np.float64(_key_value(max(lo, mn), cast, castf))
            v += 0.5 * np.float64(_key_value(hi, cast, castf))
            t = _value_key(v, cast, castf) if math.isfinite(v) else lo
            if not lo < t < hi:
                t = (lo + hi) >> 1
        if near <= _AROUND:  # also the neighbours of t: an end set here knows its next value
            c, below_t, above_t = _around(keys, n, t)
        else:
            c, below_t, above_t = _count_le(keys, n, t), np.int64(_KEY_MIN), np.int64(_KEY_MAX)
        if c > k_hi:
            hi, n_hi, below_hi = t, c, below_t
        elif c <= k_lo:
            lo, n_lo, above_lo = t, c, above_t
        else:  # c = k_hi = k_lo + 1: the largest key ≤ t and the smallest above
            if near > _AROUND:
                c, below_t, above_t = _around(keys, n, t)  # (not found by the pass above)
            return _key_value(below_t, cast, castf), _key_value(above_t, cast, castf)
        tv = np.float64(_key_value(t, cast, castf))
        if pc >= 0 and c != pc and tv != pv:
            per_count = (tv - pv) / (c - pc)
        pv, pc = tv, c
        if i_prop >= n_prop:
            fails = 0 if 2 * min(k_lo - n_lo, n_hi - 1 - k_hi) <= near else fails + 1
    a, b = hi, hi  # (hi − lo ≤ 1: every value of the bracket is the key hi)
    if hi - lo > 1 and k_lo == n_lo:  # step up from lo: v, the smallest key above, holds rank n_lo = k_lo
        v = above_lo
        if v == _KEY_MAX:  # (not found by a probe)
            v = _step_up(keys, n, lo)[1]
        a = b = v
        if k_lo < k_hi:
            f_v, nxt = _step_up(keys, n, v)
            b = v if k_hi < f_v else nxt
    elif hi - lo > 1:  # step down from hi: v, the largest key ≤ hi, holds rank n_hi − 1 = k_hi
        v = below_hi
        if v == _KEY_MIN:  # (not found by a probe)
            v = _step_down(keys, n, hi + 1)[1]
        a = b = v
        if k_lo < k_hi:
            c, prv = _step_down(keys, n, v)
            a = v if c <= k_lo else prv
    return _key_value(a, cast, castf), _key_value(b, cast, castf)


@kernel
def _median32(keys, n, mn, mx, s1, s2, cast, guess, density):
    """The median of n float32 values given by their order keys (extremes mn, mx) as NumPy computes it: the
    middle element, or the mean of the two middle ones rounded to float32 (NaN if they hold a NaN).
    ``guess`` and ``density``: :func:`_order_stats32`."""
    k = n // 2
    below, mid = _order_stats32(keys, n, mn, mx, k - 1 + n % 2, k, s1, s2, cast, guess, density)
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


#: Rows of integers spanning at most this many values are counted value by value (when every integer of the
#: span is a float32: magnitudes below 2²⁴), wider ones into histograms.
_VALUE_PASSES, _WHOLE_FLOAT32 = 8, float(1 << 24)


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
    if span <= _VALUE_PASSES and max(-lo, lo + span) < _WHOLE_FLOAT32:
        # value by value: one vectorised counting pass each, no scattered writes; the last value (the row's
        # maximum) counts the rest
        rest = n
        for j in range(span - 1):
            v, c = lo + np.float32(j), 0
            for i in range(n):
                c += y[i] == v
            counts[j] = c
            rest -= c
        counts[span - 1] = rest
    else:
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


#: The median of normal values lies at the density n φ(0)/σ, their MAD (0.6745 σ) at the density of |values|
#: n 2φ(0.6745)/σ: the model of :func:`baseline_noise_row`'s first probes.
_MEDIAN_DENSITY, _MAD_OF_SIGMA, _MAD_DENSITY = 0.3989422804014327, 0.6744897501960817, 0.6355857189727987


@kernel
def baseline_noise_row(y, integral, lo, hi, centre, spread, keys, s1, s2, cast, dev, d1, d2, counts):
    """(median, σ) of one float32 row: σ = 1.4826 × MAD, or where the MAD is 0 the rms deviation of the quietest
    90 % of the samples (NumPy's linear quantile, its pairwise sum).  ``integral``: the row is known to hold
    whole numbers (converted from an integer type) whose extremes are ``lo`` and ``hi``; else both are found
    here.  ``centre`` and ``spread`` (> 0; else none): the expected median and σ of the row, which only choose
    where the exact selection of a float row starts counting (:func:`_order_stats32`).  keys, s1, s2, cast
    (int32), dev (float32), d1, d2 (float64) and counts are scratch (:func:`row_scratch`)."""
    n = y.shape[0]
    counted = True
    if not integral:
        lo, hi = y[0], y[0]
        for i in (0, n // 2, n - 1):  # most float rows show at once
            counted = counted and y[i] == np.floor(y[i])
    if counted and not integral:  # fractional values (NaN counts) and the extremes by their order keys
        bits = y.view(np.int32)
        n_frac, k_min, k_max = 0, np.int32(0x7FFFFFFF), np.int32(-0x7FFFFFFF - 1)
        for i in range(n):
            n_frac += y[i] != np.floor(y[i])
            kk = _key32(bits[i])
            k_min, k_max = min(k_min, kk), max(k_max, kk)
        cast[0], cast[1] = _key32(k_min), _key32(k_max)
        lo, hi = cast.view(np.float32)[0], cast.view(np.float32)[1]
        counted = n_frac == 0
    counted = counted and hi - lo < _COUNTING_RANGE
    span = 0
    if counted:  # A/D counts: the median and MAD by counting
        span = int(hi - lo) + 1
        base, mad = _counting_median_mad(y, lo, span, counts)
    else:
        modelled = spread > 0 and math.isfinite(spread)
        mn, mx = _float_keys(y, keys)
        base = _median32(keys, n, mn, mx, s1, s2, cast, centre, n * _MEDIAN_DENSITY / spread if modelled else 0.0)
        for i in range(n):
            dev[i] = abs(y[i] - base)
        # |y − median| ≥ +0 (or NaN): its bits are its order keys, at least 0, at most those of the deviation
        # of an extreme (rounding keeps the order of |y − median|)
        castf = cast.view(np.float32)
        d_mx = max(_value_key(abs(_key_value(mx, cast, castf) - base), cast, castf),
                   _value_key(abs(_key_value(mn, cast, castf) - base), cast, castf))
        mad = _median32(dev.view(np.int32), n, np.int64(0), d_mx, s1, s2, cast, _MAD_OF_SIGMA * spread,
                        n * _MAD_DENSITY / spread if modelled else 0.0)
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
        base[r], sigma[r] = baseline_noise_row(y[r], False, np.float32(0.0), np.float32(0.0), 0.0, 0.0, keys, s1, s2,
                                               cast, dev, d1, d2, counts)


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
