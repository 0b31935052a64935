"""The table route's per-bin tail in two compiled passes (session 32, issue 28) gives the codes of the NumPy
sequence it replaced, bit for bit: the same generator calls in the same order, the same float32/float64
roundings, the same A/D conversion and clip counts."""
import numpy as np
import pytest

from core.physics.receiver.table_route import _numpy_tail, per_bin_tail


def _reference_tail(idx, n, p, rng, of):
    """per_bin_tail as NumPy passes (the code before session 32, kept as the route of the cases the fused
    passes do not take)."""
    key = rng.integers(0, 2 ** 64, dtype=np.uint64) if p["shot"] and (p["b_mult"] > 0 or p["ds"] > 0) else None
    return _numpy_tail(idx, n, p, rng, key, of)


BASE = dict(shot=True, b_mult=0.004, ds=0.3, gain=50.0, F=2.6, sigma_r=120.0, bits=14, fs=2.0e6, offset=16)


@pytest.mark.parametrize("change", [
    {},  # the terrain benchmark's kind of detector
    {"offset": 0},
    {"sigma_r": 0.0},
    {"ds": 0.0},
    {"b_mult": 0.0, "ds": 0.0},  # (no Poisson stream: no key drawn)
    {"b_mult": 25.0, "ds": 3.0e3},
    {"fs": 2.0e4, "offset": 200},  # full scale reached: high clips counted
    {"offset": -40, "sigma_r": 400.0, "gain": 2.0},  # code 0 reached: low clips counted
    {"bits": 8, "fs": 5.0e4},
    {"bits": 20, "fs": 1.0e8, "offset": 3},
])
def test_fused_tail_equals_the_numpy_passes(change):
    p = dict(BASE, **change)
    rng0 = np.random.default_rng(11)
    size = 40_000
    idx = np.sort(rng0.choice(3 * size, size, replace=False)).astype(np.int64)
    n = rng0.integers(17, 1200, size).astype(np.float64)
    dtype = np.uint16 if p["bits"] <= 16 else np.uint32
    got, want = np.zeros(3 * size, dtype), np.zeros(3 * size, dtype)
    lo, hi = per_bin_tail(idx, n, p, np.random.default_rng(5), got)
    lo_r, hi_r = _reference_tail(idx, n, p, np.random.default_rng(5), want)
    assert np.array_equal(got, want)
    assert (lo, hi) == (lo_r, hi_r)
    if "fs" in change and change["fs"] == 2.0e4:
        assert hi > 0  # (the case does reach full scale)
    if change.get("offset") == -40:
        assert lo > 0  # (and this one code 0)


def test_fused_tail_leaves_the_other_bins_alone():
    p = dict(BASE)
    of = np.full(100, 7, np.uint16)
    idx = np.array([3, 50, 99], np.int64)
    per_bin_tail(idx, np.array([20.0, 300.0, 40.0]), p, np.random.default_rng(1), of)
    rest = np.setdiff1d(np.arange(100), idx)
    assert np.all(of[rest] == 7)
