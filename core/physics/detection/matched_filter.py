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
