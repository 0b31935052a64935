"""The table route's per-bin tail (``table_route.per_bin_tail``) with its arithmetic in one compiled pass
(session 31): bit for bit the codes, clip counts and generator state of the NumPy version it replaced, kept here
as the reference, over every branch (shot noise on/off, background, surface dark Poisson/constant, excess noise
on/off, gamma draws dense/sparse, read noise on/off, A/D ≤ 23 and > 23 bits).  Exact equality: the same draws
in the same order and the same roundings; a difference of one code anywhere fails.
"""
import itertools

import numpy as np
import pytest

from core.physics.receiver.adc import adc_convert, adc_dtype
from core.physics.receiver.samplers import gamma_gain, poisson_stream
from core.physics.receiver.table_route import per_bin_tail


def reference_tail(idx, n, p, rng, of):
    """per_bin_tail as it was before session 31 (NumPy expressions)."""
    key = rng.integers(0, 2 ** 64, dtype=np.uint64) if p["shot"] and (p["b_mult"] > 0 or p["ds"] > 0) else None
    if p["shot"] and p["b_mult"] > 0:
        n = n + poisson_stream(p["b_mult"], n.size, key, 0, rng)
    y = gamma_gain(n.astype(np.float32), p["gain"], p["F"], rng).astype(np.float64)
    if p["ds"] > 0:
        y += poisson_stream(p["ds"], n.size, key, n.size, rng) if p["shot"] else p["ds"]
    if p["sigma_r"] > 0:
        y += p["sigma_r"] * rng.standard_normal(n.size)
    codes, lo, hi = adc_convert(y, p["bits"], p["fs"], p["offset"])
    of[idx] = codes
    return lo, hi


CASES = list(itertools.product((True, False), (0.0, 0.7), (0.0, 3.1), (1.0, 3.95), (0.0, 300.0), (12, 24),
                               (False, True)))


@pytest.mark.parametrize("shot,b_mult,ds,F,sigma_r,bits,sparse", CASES)
def test_fused_tail_bit_for_bit(shot, b_mult, ds, F, sigma_r, bits, sparse):
    rng0 = np.random.default_rng([31, int(shot), int(b_mult * 10), int(ds * 10), int(F * 100), int(sigma_r), bits])
    m = 5000
    if shot:  # caught counts above 16
        n = rng0.integers(17, 400, m).astype(np.float64)
    else:  # continuous means, some zero (sparse: most zero, gamma_gain's sparse branch)
        n = rng0.exponential(60.0, m)
        n[rng0.random(m) < (0.8 if sparse else 0.1)] = 0.0
        n += b_mult
    if sparse and shot:
        n[: m // 10] = 0.0  # (not reached by the chain with shot noise; the branch still agrees)
    size = 3 * m
    idx = np.sort(rng0.choice(size, m, replace=False))
    fs = 500.0 * 2 ** bits if bits <= 23 else 50.0 * 2 ** bits
    p = dict(shot=shot, b_mult=b_mult, ds=ds, gain=100.0 if F > 1 else 1.0, F=F, sigma_r=sigma_r, bits=bits,
             fs=fs, offset=16)
    dt = adc_dtype(bits)
    out_ref, out_new = np.zeros(size, dt), np.zeros(size, dt)
    r_ref, r_new = np.random.default_rng(7), np.random.default_rng(7)
    clips_ref = reference_tail(idx, n.copy(), p, r_ref, out_ref)
    clips_new = per_bin_tail(idx, n.copy(), p, r_new, out_new)
    assert clips_new == clips_ref
    assert out_new.tobytes() == out_ref.tobytes()
    assert r_new.bit_generator.state == r_ref.bit_generator.state  # the same number of draws


def test_fused_tail_clips_counted():
    """Saturation and the low clip are counted as before (full scale small enough that some bins clip)."""
    rng0 = np.random.default_rng(5)
    n = rng0.integers(17, 3000, 4000).astype(np.float64)
    p = dict(shot=True, b_mult=0.5, ds=2.0, gain=100.0, F=3.95, sigma_r=300.0, bits=12, fs=500.0 * 2 ** 8,
             offset=0)
    idx = np.arange(4000)
    a, b = np.zeros(4000, np.uint16), np.zeros(4000, np.uint16)
    ref = reference_tail(idx, n, p, np.random.default_rng(1), a)
    new = per_bin_tail(idx, n, p, np.random.default_rng(1), b)
    assert new == ref and new[1] > 0
    assert a.tobytes() == b.tobytes()
