"""The statistical route's one pass for each row's signal extent (core.physics.detection.stretches.row_extents) and
the false-alarm classification restricted to those stretches (classify_false_alarms ``extents``): both exact,
checked against brute force and against the whole-row classification on rows built to hit every branch (signal in
the first and last 64-bin blocks, a row length that is not a multiple of 64, no signal, weak signal below the
false-alarm level, NaN, negative values)."""
from __future__ import annotations

import numpy as np
import pytest

from core.physics.detection.false_alarms import classify_false_alarms
from core.physics.detection.noisy import NoisyEchoes, gaussian_pulse_kernel
from core.physics.detection.stretches import row_extents, signal_windows


def _rows(n_bins, dtype, seed=5):
    rng = np.random.default_rng(seed)
    P = 400
    t = np.zeros((P, n_bins), dtype)
    for p in range(P):
        kind = p % 8
        if kind == 0:
            continue  # no signal at all
        if kind == 1:  # tiny values everywhere, below the signal level
            t[p] = rng.uniform(0, 0.5e-3, n_bins)
            continue
        n_pk = rng.integers(1, 4)
        for _ in range(n_pk):
            c = {2: rng.integers(0, 3), 3: n_bins - 1 - rng.integers(0, 3)}.get(kind, rng.integers(0, n_bins))
            amp = rng.uniform(2e-3, 1e-2) if kind == 4 else rng.uniform(0.5, 50.0)  # kind 4: weak signal
            j = np.arange(n_bins)
            t[p] += (amp * np.exp(-0.5 * ((j - c) / rng.uniform(0.5, 4.0)) ** 2)).astype(dtype)
        if kind == 5:
            t[p, rng.integers(0, n_bins)] = -rng.uniform(0, 1)  # a negative value
        if kind == 6:
            t[p] += rng.uniform(0, 0.5e-3, n_bins).astype(dtype)  # a floor below the level
    return t


def _brute(t, level):
    lv = t.dtype.type(level)
    first, last, peak, bad = [], [], [], []
    for row in t:
        idx = np.flatnonzero(row > lv)
        first.append(idx[0] if len(idx) else -1)
        last.append(idx[-1] if len(idx) else -1)
        peak.append(np.nanmax(row) if len(idx) else -np.inf)
        bad.append(bool(np.isnan(row).any()))
    return np.array(first), np.array(last), np.array(peak, t.dtype), np.array(bad)


@pytest.mark.parametrize("n_bins", [64, 100, 1024, 1091])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_row_extents_match_brute_force(n_bins, dtype):
    t = _rows(n_bins, dtype)
    t[7, n_bins // 3] = np.nan  # a NaN in a signal-free row (kind 7) and one inside a signal row's stretch
    t[10, :] = 0.0
    t[10, 5], t[10, n_bins - 7], t[10, n_bins // 2] = 1.0, 2.0, np.nan
    level = 1e-3
    got = row_extents(t, level, threads=3)
    want = _brute(t, level)
    for g, w, name in zip(got, want, ("first", "last", "peak", "has_nan")):
        assert np.array_equal(g, w), name
    assert got[3].sum() == 2
    # the windows from the extents are those of the rows themselves
    a = signal_windows(t, level, 3, n_bins, threads=2)
    b = signal_windows(t, level, 3, n_bins, extents=got)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize("n_bins", [100, 1024])
@pytest.mark.parametrize("abs_level", [0.0, 5e-4, 2e-3])
def test_classification_in_the_stretches_is_the_whole_rows(n_bins, abs_level):
    """Every row kind, with the false-alarm level (max(1e-3 × peak, abs_level)) below and above the stretches'
    level: flags, eligible counts and the expectation identical to the whole-row pass (the weak rows and, when
    abs_level is below the level, the signal-free ones take the whole-row branch)."""
    t = _rows(n_bins, np.float32, seed=11)
    P, K = len(t), 3
    rng = np.random.default_rng(3)
    det = rng.random((P, K)) < 0.6
    pos = np.where(det, rng.uniform(0, n_bins, (P, K)), np.nan)
    found = NoisyEchoes(time_s=pos, range_m=pos, position_bins=pos, amplitude=pos, snr=pos, detected=det,
                        n_echoes=det.sum(1), baseline=np.zeros(P), noise_sigma=np.ones(P),
                        threshold=np.full(P, 3.0), n_interp_fallback=0)
    pulse = gaussian_pulse_kernel(4e-9, 1e-9)
    level = 1e-3
    first, last, peak, bad = row_extents(t, level)
    ext = {"first": first, "last": last, "peak": peak, "has_nan": bad, "level": np.float32(level)}
    kw = dict(noise_sigma=1.0, pulse=pulse, abs_level=abs_level, threads=2)
    fa0, s0 = classify_false_alarms(found, t, 4.0, **kw)
    fa1, s1 = classify_false_alarms(found, t, 4.0, extents=ext, **kw)
    assert np.array_equal(fa0, fa1)
    assert s0 == s1  # counts, eligible bins, the Gaussian expectation (finite numbers, strings)
    assert 0 < fa0.sum() < det.sum()  # both kinds of detection present: the test can fail
