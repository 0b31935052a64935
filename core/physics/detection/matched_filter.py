"""The matched filter of noisy echo detection (docs/theory.md §9): SciPy ``correlate1d``'s summation order,
compiled and vectorised across outputs (core/physics/detection/noisy.py runs it row by row)."""
from __future__ import annotations

import numpy as np

from ...jit import fma, kernel


#: Outputs of the matched filter summed together, tap by tap (their float64 sums stay in L1 / registers).
FILTER_BLOCK = 256


#: correlate_row's exact_pairs: rows of halves (whole numbers minus a whole or half baseline) below this
#: magnitude, whose pair sums times a float32 tap are exact in float64.
EXACT_PAIR_VALUE = float(1 << 21)


@kernel
def correlate_row(y, b32, w, ypad, acc, out, exact_pairs):
    """out = SciPy's correlate1d of y − b32 (float32) with a symmetric odd kernel ``w`` (float64), 'nearest'
    edges: each output summed in float64 in SciPy's order (centre tap, then the folded pairs from the outermost
    in) and rounded to float32.  The tap loop runs outside a block of outputs, which keeps every output's
    order and lets the compiler vectorise across outputs.  ``exact_pairs``: the caller knows every y − b32 is
    a multiple of ½ below EXACT_PAIR_VALUE in magnitude, so that each pair sum (≤ 24 significant bits) times a
    tap (a float32: 24 bits) is exact in float64 — then each product and its addition are one fused
    multiply-add (:func:`core.jit.fma`), the same float64 value in fewer instructions.  ``w``'s taps must be
    float32 values (as :func:`matched_filter` and the noisy detection make them).  ypad (float32, n + len(w) − 1: the row with
    its edges, widened to float64 where it is read) and acc (float64, FILTER_BLOCK) are scratch."""
    n, h = y.shape[0], w.shape[0] // 2
    for i in range(h):  # the row with its edges clamped ('nearest')
        ypad[i] = y[0] - b32
        ypad[n + h + i] = y[n - 1] - b32
    body = ypad[h:h + n]
    for i in range(n):
        body[i] = y[i] - b32
    wc = w[h]
    for s in range(0, n, FILTER_BLOCK):  # (slices, indexed from 0: the compiler vectorises these loops)
        m = min(FILTER_BLOCK, n - s)
        c = s + h
        centre, dst = ypad[c:c + m], out[s:s + m]
        for i in range(m):
            acc[i] = np.float64(centre[i]) * wc
        jj = -h
        while jj + 4 <= 0:  # four taps per pass over the block, each added in turn
            w1, w2, w3, w4 = w[h + jj], w[h + jj + 1], w[h + jj + 2], w[h + jj + 3]
            l1, r1 = ypad[c + jj:c + jj + m], ypad[c - jj:c - jj + m]
            l2, r2 = ypad[c + jj + 1:c + jj + 1 + m], ypad[c - jj - 1:c - jj - 1 + m]
            l3, r3 = ypad[c + jj + 2:c + jj + 2 + m], ypad[c - jj - 2:c - jj - 2 + m]
            l4, r4 = ypad[c + jj + 3:c + jj + 3 + m], ypad[c - jj - 3:c - jj - 3 + m]
            if exact_pairs:  # (exact pair sums and products: a fused multiply-add is the same number)
                for i in range(m):
                    a = fma(np.float64(l1[i]) + np.float64(r1[i]), w1, acc[i])
                    a = fma(np.float64(l2[i]) + np.float64(r2[i]), w2, a)
                    a = fma(np.float64(l3[i]) + np.float64(r3[i]), w3, a)
                    acc[i] = fma(np.float64(l4[i]) + np.float64(r4[i]), w4, a)
            else:
                for i in range(m):
                    a = acc[i] + (np.float64(l1[i]) + np.float64(r1[i])) * w1
                    a += (np.float64(l2[i]) + np.float64(r2[i])) * w2
                    a += (np.float64(l3[i]) + np.float64(r3[i])) * w3
                    acc[i] = a + (np.float64(l4[i]) + np.float64(r4[i])) * w4
            jj += 4
        while jj < 0:
            wj = w[h + jj]
            left, right = ypad[c + jj:c + jj + m], ypad[c - jj:c - jj + m]
            for i in range(m):
                acc[i] += (np.float64(left[i]) + np.float64(right[i])) * wj
            jj += 1
        for i in range(m):
            dst[i] = acc[i]


@kernel
def pad_row(y, b32, h, ypad):
    """ypad = y − b32 (float32) with h samples of 'nearest' edge on either side, as :func:`correlate_row` makes
    it."""
    n = y.shape[0]
    for i in range(h):
        ypad[i] = y[0] - b32
        ypad[n + h + i] = y[n - 1] - b32
    body = ypad[h:h + n]
    for i in range(n):
        body[i] = y[i] - b32


@kernel
def exact_output(ypad, w, i):
    """Output i of :func:`correlate_row` on the padded row ``ypad`` (made by :func:`pad_row`): the float64 sum in
    SciPy's order (centre tap, then the folded pairs from the outermost in), rounded to float32 — the same number
    as correlate_row's (its fused multiply-adds, used only when every pair product is exact, give the same
    values as these separate ones)."""
    h = w.shape[0] // 2
    c = i + h
    acc = np.float64(ypad[c]) * w[h]
    for jj in range(-h, 0):
        acc += (np.float64(ypad[c + jj]) + np.float64(ypad[c - jj])) * w[h + jj]
    return np.float32(acc)


@kernel
def approx_row(ypad, w32, n, acc, out):
    """out[:n] ≈ correlate_row's outputs, summed in float32 (eight lanes where correlate_row has four): for
    screening only; :func:`screen_margin` bounds the difference."""
    h = w32.shape[0] // 2
    wc = w32[h]
    for s in range(0, n, FILTER_BLOCK):
        m = min(FILTER_BLOCK, n - s)
        c = s + h
        centre, dst = ypad[c:c + m], out[s:s + m]
        for i in range(m):
            acc[i] = centre[i] * wc
        jj = -h
        while jj + 4 <= 0:
            w1, w2, w3, w4 = w32[h + jj], w32[h + jj + 1], w32[h + jj + 2], w32[h + jj + 3]
            l1, r1 = ypad[c + jj:c + jj + m], ypad[c - jj:c - jj + m]
            l2, r2 = ypad[c + jj + 1:c + jj + 1 + m], ypad[c - jj - 1:c - jj - 1 + m]
            l3, r3 = ypad[c + jj + 2:c + jj + 2 + m], ypad[c - jj - 2:c - jj - 2 + m]
            l4, r4 = ypad[c + jj + 3:c + jj + 3 + m], ypad[c - jj - 3:c - jj - 3 + m]
            for i in range(m):
                acc[i] = acc[i] + (l1[i] + r1[i]) * w1 + (l2[i] + r2[i]) * w2 + (l3[i] + r3[i]) * w3 + \
                    (l4[i] + r4[i]) * w4
            jj += 4
        while jj < 0:
            wj = w32[h + jj]
            left, right = ypad[c + jj:c + jj + m], ypad[c - jj:c - jj + m]
            for i in range(m):
                acc[i] += (left[i] + right[i]) * wj
            jj += 1
        for i in range(m):
            dst[i] = acc[i]


@kernel
def screen_margin(w, max_abs):
    """A bound on |approx_row − correlate_row| at any output of a row whose |ypad| ≤ ``max_abs``: every output is
    a sum of at most h + 1 terms (the centre tap and h pair sums times their taps) of total magnitude at most
    A = (|w_c| + 2 Σ|w_pairs|)·max_abs.  In float32 (unit roundoff u = 2⁻²⁴) each pair sum, each product and each
    of the h + 1 additions rounds once: |approx − exact sum| ≤ (h + 3)·u·A/(1 − (h + 3)u); correlate_row's float64
    sum is within 2⁻⁵²·(h + 3)·A of the exact sum and its float32 rounding within u·A.  The margin returned,
    (h + 8)·2⁻²³·A, is more than twice their total."""
    h = w.shape[0] // 2
    a = abs(w[h])
    for k in range(h):
        a += 2.0 * abs(w[k])
    return (h + 8) * 2.0 ** -23 * a * max_abs


@kernel
def _correlate_rows(y, w, out):
    ypad, acc = np.empty(y.shape[1] + w.shape[0] - 1, np.float32), np.empty(FILTER_BLOCK)
    for r in range(y.shape[0]):
        correlate_row(y[r], np.float32(0.0), w, ypad, acc, out[r], False)


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
