"""The table route's Poisson sampler (core/physics/receiver/samplers.py, docs/receiver.md "Table route"): bright
signal bins (means 8 … 1024) by a tabulated Poisson(2j) plus the inversion of the rest, the per-bin tail's background
and surface dark by inversion of one tabulated law, all on counter-based streams.  Exact in law, so every test
compares with the Poisson law itself or with the per-bin reference route (NumPy's ``rng.poisson``).

Tolerances: sampled means and variances within 3 standard errors (mean: √(λ/n); variance: √((2λ² + λ)/n), the
Poisson fourth central moment λ + 3λ²), χ² of the histogram at the 0.1 % level, ≥ 2¹⁸ samples per mean and fixed
keys; each statistic is shown to fail (> 3 standard errors) for the law of a mean 0.5 % off.  The tabulated laws
against SciPy's to 1e-14 (float64 cumulative sums of ≤ 700 terms of relative error ≤ 700 × 2⁻⁵³ each: ≤ 1.6e-13
at worst; measured ≤ 8e-16).
"""
import numpy as np
import pytest
from scipy import stats

from core.physics.receiver.conversions import energy_to_photons
from core.physics.receiver.samplers import (POISSON_GRID_MAX, POISSON_GRID_STEP, POISSON_SAMPLER, poisson_grid,
                                            poisson_grid_tables, poisson_law_table, poisson_stream, stream_uniform53)
from core.jit import kernel
from scenes import sec8_chain as chain

N = 1 << 18


@kernel
def _grid_draws(lam, key, out, cdf, off, kmin, guide, goff, step):
    for t in range(out.size):
        out[t] = poisson_grid(lam, stream_uniform53(key, 2 * t), stream_uniform53(key, 2 * t + 1), cdf, off, kmin,
                              guide, goff, step)


def _z_mean_var(x, lam):
    n = x.size
    return (x.mean() - lam) / np.sqrt(lam / n), (x.var() - lam) / np.sqrt((2 * lam * lam + lam) / n)


def _chi2_p(x, lam):
    """χ² p-value of the counts x against Poisson(lam), cells pooled to ≥ 5 expected (both tails included)."""
    n = x.size
    k = np.arange(int(x.max()) + 1)
    obs = np.bincount(x.astype(np.int64), minlength=k.size).astype(float)
    exp = stats.poisson.pmf(k, lam) * n
    exp[0] += stats.poisson.cdf(-1, lam) * n
    exp[-1] += stats.poisson.sf(k[-1], lam) * n
    o2, e2, co, ce = [], [], 0.0, 0.0
    for a, b in zip(obs, exp):
        co, ce = co + a, ce + b
        if ce >= 5:
            o2.append(co)
            e2.append(ce)
            co = ce = 0.0
    o2[-1] += co
    e2[-1] += ce
    return stats.chisquare(o2, e2).pvalue


@pytest.mark.parametrize("lam", [1.5, 40.0, 100.25, 1023.75])
def test_law_tables_equal_scipy(lam):
    """F[i] = P(N ≤ k_lo + i) to 1e-14; the trimmed tails below 2⁻⁶⁴; the guide starts each search at or
    before the answer (F[guide[g] − 1] ≤ g/L)."""
    c, k_lo, guide = poisson_law_table(lam)
    k = k_lo + np.arange(c.size)
    assert np.max(np.abs(c - stats.poisson.cdf(k, lam))) < 1e-14
    assert stats.poisson.cdf(k_lo - 1, lam) < 2.0 ** -64 and stats.poisson.sf(k[-1], lam) < 2.0 ** -63
    assert stats.poisson.sf(k[-2], lam) >= 2.0 ** -64  # (trimmed: nothing kept beyond the first such k)
    g = np.arange(c.size) / c.size
    assert np.all(c[guide] > g) and np.all(c[np.maximum(guide - 1, 0)][guide > 0] <= g[guide > 0])


def test_grid_covers_every_mean_up_to_the_top():
    """One table per grid mean 2, 4, …, POISSON_GRID_MAX − 2 (the rest below POISSON_GRID_STEP)."""
    cdf, off, kmin, guide, goff, step = poisson_grid_tables()
    assert step == POISSON_GRID_STEP and len(off) - 1 == int(POISSON_GRID_MAX / step)
    for j in (1, 7, int(POISSON_GRID_MAX / step) - 1):
        c, k_lo, _ = poisson_law_table(step * j)
        assert kmin[j] == k_lo and np.array_equal(cdf[off[j]:off[j + 1]], c)


@pytest.mark.parametrize("lam", [8.0, 9.999, 13.7, 100.25, 425.3, 1023.9])
def test_grid_sampler_has_the_poisson_law(lam):
    """Mean, variance within 3 SE and χ² (p > 1e-3) over 2¹⁸ draws; the same statistics reject Poisson(1.005 λ)."""
    x = np.empty(N)
    _grid_draws(lam, np.uint64(0x5EED + int(lam * 1000)), x, *poisson_grid_tables())
    zm, zv = _z_mean_var(x, lam)
    assert abs(zm) < 3 and abs(zv) < 3
    assert _chi2_p(x, lam) > 1e-3
    zm_off, _ = _z_mean_var(x, 1.005 * lam)  # the test's power: a 0.5 % error in the mean is seen
    assert abs(zm_off) > 3 or _chi2_p(x, 1.005 * lam) < 1e-3


@pytest.mark.parametrize("lam", [0.0031, 3.12, 50.5, 5000.0])
def test_scalar_stream_has_the_poisson_law(lam):
    """poisson_stream (the per-bin tail's background and surface dark): the same checks."""
    x = poisson_stream(lam, N, 0xABCDEF + int(lam * 10), 0, np.random.default_rng(0))
    zm, zv = _z_mean_var(x, lam)
    assert abs(zm) < 3 and abs(zv) < 3
    assert _chi2_p(x, lam) > 1e-3


def test_scalar_stream_is_a_function_of_key_and_words():
    """Number t is word word0 + t of the stream: a slice of a longer draw, another key another draw."""
    a = poisson_stream(7.5, 1000, 99, 0, None)
    assert np.array_equal(poisson_stream(7.5, 600, 99, 400, None), a[400:])
    assert not np.array_equal(poisson_stream(7.5, 1000, 98, 0, None), a)


@pytest.mark.parametrize("n_s", [20.0, 100.0, 300.0])
def test_bright_bins_match_the_per_bin_reference(n_s):
    """A constant signal of n_s primaries per bin (2¹⁸ bins): the table route (bright bins from the grid, those
    that caught more than 16 from the per-bin tail with the stream's background and surface dark) against the
    per-bin reference route (NumPy's Poisson and gamma draws): code mean and variance within 3 standard errors
    of their difference."""
    e = n_s / float(energy_to_photons(1.0, 1.064e-6, 0.4))
    cube = np.full((64, 64, 64), e, np.float32)
    fast, ref = chain(cube, 11), chain(cube, 12, noise_table=False)
    assert fast.report["poisson_sampler"] == POISSON_SAMPLER and "poisson_sampler" not in ref.report
    a, b = fast.data.astype(np.float64).ravel(), ref.data.astype(np.float64).ravel()
    n = a.size
    z_mean = (a.mean() - b.mean()) / np.sqrt((a.var() + b.var()) / n)

    def var_se(x):
        return np.sqrt((np.mean((x - x.mean()) ** 4) - x.var() ** 2) / n)
    z_var = (a.var() - b.var()) / np.hypot(var_se(a), var_se(b))
    assert abs(z_mean) < 3 and abs(z_var) < 3


@pytest.mark.parametrize("peak", [60.0, 250.0])
def test_range_of_bright_returns_matches_the_per_bin_reference(peak):
    """A Gaussian return (FWHM 4 bins at 30.3 bins, peak bin ``peak`` signal primaries: every bin near the peak
    drawn by the grid sampler, most of them by the per-bin tail) in 2¹⁷ pixels, matched filter and calibrated
    threshold at 5 σ: the first echo's range error, mean and standard deviation, agree with the per-bin reference
    route within 3 standard errors of their difference (σ/√n and σ/√(2n)); all pixels detected on both routes."""
    from scipy.special import ndtr

    from core.physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel

    n_bins, t0, sd = 64, 30.3, 4.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    edges = np.arange(n_bins + 1, dtype=float)
    shape = ndtr((edges[1:] - t0) / sd) - ndtr((edges[:-1] - t0) / sd)
    e = (shape / shape.max() * peak / float(energy_to_photons(1.0, 1.064e-6, 0.4))).astype(np.float32)
    cube = np.broadcast_to(e, (256, 512, n_bins)).copy()
    stats_ = {}
    for route, seed in (("table", 21), ("per-bin", 22)):
        out = chain(cube, seed, noise_table=route == "table")
        ech = detect_echoes_noisy(out.data.reshape(-1, n_bins), 1e-9, threshold_mode="calibrated", k_sigma=5.0,
                                  pulse=gaussian_pulse_kernel(4e-9, 1e-9), max_echoes=1,
                                  noise_sigma=out.report["noise_sigma"], baseline=out.report["noise_mean"])
        assert ech.detected[:, 0].all()
        err = ech.position_bins[:, 0] - t0
        stats_[route] = (err.mean(), err.std(), err.size)
    (m1, s1, n1), (m2, s2, n2) = stats_["table"], stats_["per-bin"]
    assert abs(m1 - m2) < 3 * np.hypot(s1 / np.sqrt(n1), s2 / np.sqrt(n2))
    assert abs(s1 - s2) < 3 * np.hypot(s1 / np.sqrt(2 * n1), s2 / np.sqrt(2 * n2))
