"""The tabulated code distribution of signal-free bins (core/physics/receiver/: noise_code_pmf, CodeTable), the fast
route of the receiver chain (docs/theory.md §8).

Tolerances: the pmf against closed forms to 1e-12 (float64 FFT round-off); quantization moments within 1e-4
(the rounding bias of rint(X/Δ) is periodic with amplitude ~exp(−2π²σ²/Δ²) < 1e-5 here); sampled
histograms by a χ² test at the 0.1 % level; sampled means/variances within 2 % over ≥ 2.6e5 samples.
"""
import numpy as np
import pytest
from scipy import special, stats

from core.physics.receiver.code_tables import CaughtCodeTables, CodeTable, noise_code_pmf, uniform_uint32
from core.config.settings import DetectorSettings
from core.physics.receiver.conversions import (current_to_electrons, energy_to_photons, linear_detector_moments,
                                               mcintyre_excess_noise)
from scenes import SEC8, sec8_chain as chain

F_SEC8 = float(mcintyre_excess_noise(100.0, 0.02))  # 3.950
DS_SEC8 = float(current_to_electrons(1e-9, 1e-9))   # surface dark 6.242 e⁻ per 1 ns bin


def test_pmf_matches_closed_form_for_a_lattice_signal():
    """PIN (G = 1, F = 1): X = Poisson(b + d) + N(0, σ²), so P(k) = Σ_m Pois(m) [Φ((k+½)Δ − m) − Φ((k−½)Δ − m)]/σ."""
    b, d, sigma, step = 2.0, 6.242, 30.0, 20.0
    k0, p = noise_code_pmf(step, n_mult=b, surface_dark_e=d, surface_dark_poisson=True, gauss_var_e2=sigma ** 2)
    k = k0 + np.arange(p.size)
    m = np.arange(200)
    w = stats.poisson.pmf(m, b + d)
    hi = special.ndtr(((k[:, None] + 0.5) * step - m[None, :]) / sigma)
    lo = special.ndtr(((k[:, None] - 0.5) * step - m[None, :]) / sigma)
    expected = (hi - lo) @ w
    assert np.max(np.abs(p - expected)) < 1e-12
    assert p.sum() == pytest.approx(1.0, abs=1e-14)


@pytest.mark.parametrize("b,G,F,sigma,step", [(2.0, 100.0, F_SEC8, 300.0, 100.0),   # docs/theory.md §8 detector
                                              (0.02, 100.0, F_SEC8, 300.0, 100.0),  # faint background
                                              (30.0, 50.0, 2.0, 80.0, 40.0)])       # bright, fine A/D
def test_pmf_moments_match_the_compound_poisson_gamma_formula(b, G, F, sigma, step):
    """Mean and variance of the A/D index: E[kΔ] = G b + d, Var[kΔ] = G²F b + d + σ² + Δ²/12 (docs/theory.md §8).
    With σ ≥ 2Δ Sheppard's correction is exact to exp(−2π²σ²/Δ²) < 1e-30 relative, so 1e-6 tests the pmf."""
    k0, p = noise_code_pmf(step, n_mult=b, gain=G, excess_noise=F, surface_dark_e=DS_SEC8,
                           surface_dark_poisson=True, gauss_var_e2=sigma ** 2)
    x = (k0 + np.arange(p.size)) * step
    mean = np.dot(p, x)
    var = np.dot(p, (x - mean) ** 2)
    mean_e, var_e = linear_detector_moments(0.0, b, G, F, 0.0, DS_SEC8, sigma, step)
    assert mean == pytest.approx(mean_e, rel=1e-6)
    assert var == pytest.approx(var_e, rel=1e-6)


def test_pmf_matches_sampled_compound_poisson_gamma():
    """χ² goodness of fit of 2e6 directly simulated bins (Poisson primaries × gamma single-electron gains +
    Poisson surface dark + Gaussian read noise, rounded) against the tabulated pmf; fails with probability 1e-3."""
    rng = np.random.default_rng(42)
    b, G, F, sigma, step = 2.0, 100.0, F_SEC8, 300.0, 500.0
    k0, p = noise_code_pmf(step, n_mult=b, gain=G, excess_noise=F, surface_dark_e=DS_SEC8,
                           surface_dark_poisson=True, gauss_var_e2=sigma ** 2)
    n = 2_000_000
    prim = rng.poisson(b, n).astype(np.float64)
    x = rng.standard_gamma(prim / (F - 1.0)) * G * (F - 1.0) + rng.poisson(DS_SEC8, n) + sigma * rng.standard_normal(n)
    idx = np.rint(x / step).astype(np.int64) - k0
    assert idx.min() >= 0 and idx.max() < p.size
    h = np.bincount(idx, minlength=p.size)
    e = p * n
    big = e > 5
    chi2 = np.sum((h[big] - e[big]) ** 2 / e[big]) + (h[~big].sum() - e[~big].sum()) ** 2 / max(e[~big].sum(), 1e-9)
    assert stats.chi2.sf(chi2, np.count_nonzero(big)) > 1e-3


def test_pmf_without_shot_noise_is_a_gamma_plus_gauss():
    """Shot noise off: X = G(F−1)·Gamma(b/(F−1)) + N(μ, σ²); its mean and variance (no Poisson term)."""
    b, G, F, sigma, step, mu = 3.0, 100.0, F_SEC8, 200.0, 100.0, 6.0
    k0, p = noise_code_pmf(step, n_mult=b, gain=G, excess_noise=F, shot=False, gauss_mean_e=mu,
                           gauss_var_e2=sigma ** 2)
    x = (k0 + np.arange(p.size)) * step
    mean = np.dot(p, x)
    assert mean == pytest.approx(G * b + mu, rel=1e-4)
    assert np.dot(p, (x - mean) ** 2) == pytest.approx(G * G * (F - 1) * b + sigma ** 2 + step ** 2 / 12, rel=1e-4)


def test_pmf_given_caught_signal_primaries():
    """m caught primaries on top of the noise: mean G(m + b) + d, variance G²(F−1)m + G²F b + d + σ² + Δ²/12."""
    b, G, F, sigma, step = 2.0, 100.0, F_SEC8, 300.0, 100.0
    m = np.array([1, 2, 7, 16])
    k0, P = noise_code_pmf(step, n_mult=b, gain=G, excess_noise=F, surface_dark_e=DS_SEC8,
                           surface_dark_poisson=True, gauss_var_e2=sigma ** 2, fixed_primaries=m)
    assert P.shape[0] == 4 and np.allclose(P.sum(axis=1), 1.0, atol=1e-14)
    x = (k0 + np.arange(P.shape[1])) * step
    mean = P @ x
    var = np.sum(P * (x[None, :] - mean[:, None]) ** 2, axis=1)
    np.testing.assert_allclose(mean, G * (m + b) + DS_SEC8, rtol=1e-6)
    np.testing.assert_allclose(var, G * G * (F - 1) * m + G * G * F * b + DS_SEC8 + sigma ** 2 + step ** 2 / 12,
                               rtol=1e-6)


def test_caught_tables_equal_inverse_cdf_search():
    """Stacked 4096-cell tables: the code of (m, r) is exactly the inverse-CDF entry of table m."""
    kw = dict(n_mult=2.0, gain=100.0, excess_noise=F_SEC8, surface_dark_e=DS_SEC8, surface_dark_poisson=True,
              gauss_var_e2=300.0 ** 2)
    tabs = CaughtCodeTables(16, 500.0, kw, 0, 4095, np.uint16)
    rng = np.random.default_rng(4)
    m = rng.integers(1, 17, 500_000)
    r = uniform_uint32(rng, m.size)
    codes, lo, hi = tabs.sample(m, r)
    exp_lo = 0
    for j in range(16):
        sel = m == j + 1
        t = tabs.tables[j]
        entry = np.searchsorted(t.T, r[sel].astype(np.uint64), side="right")
        assert np.array_equal(codes[sel], t.code[entry])
        exp_lo += np.count_nonzero(entry == 0)
    assert lo == exp_lo and lo > 0 and hi == 0  # offset 0: the low tail is clipped and counted


def test_pmf_needs_a_gaussian_part():
    with pytest.raises(ValueError):
        noise_code_pmf(500.0, n_mult=1.0, gauss_var_e2=0.0)


@pytest.mark.parametrize("offset,top,dtype", [(16, 4095, np.uint16), (0, 4095, np.uint16),
                                              (3, 65535, np.uint16), (100, 2 ** 20 - 1, np.uint32)])
def test_code_table_equals_inverse_cdf_search(offset, top, dtype):
    """The two-level sampler returns exactly the entry found by a binary search of r on the quantized CDF, and
    counts exactly the samples that fell into the clipped entries."""
    k0, p = noise_code_pmf(500.0 if top == 4095 else 7.0, n_mult=2.0, gain=100.0, excess_noise=F_SEC8,
                           surface_dark_e=DS_SEC8, surface_dark_poisson=True, gauss_var_e2=300.0 ** 2)
    table = CodeTable(k0, p, offset, top, dtype)
    r = uniform_uint32(np.random.default_rng(3), 1_000_000)
    # force samples into every ambiguous cell and onto the boundaries themselves
    bounds = table.T[:-1][table.T[:-1] < 2 ** 32].astype(np.uint32)
    r[: 3 * bounds.size] = np.concatenate([bounds, bounds - np.uint32(1), bounds + np.uint32(1)])
    out = np.empty(r.size, dtype=dtype)
    lo, hi = table.sample(r, out)
    entry = np.searchsorted(table.T, r.astype(np.uint64), side="right")
    assert np.array_equal(out, table.code[entry])
    assert lo == np.count_nonzero(entry == 0) and hi == np.count_nonzero(entry == table.T.size - 1)
    if offset == 0:  # X < −Δ/2 (11 % of the noise) falls below code 0: clipped and counted
        p_low = p[k0 + np.arange(p.size) < 0].sum()
        assert p_low > 0.1 and abs(lo - r.size * p_low) < 5 * np.sqrt(r.size * p_low)
    # each probability is a difference of two CDF values rounded to 2^-32: changed by at most 2^-32
    assert table.max_prob_error <= 2.0 ** -32


# ------------------------------------------------------------------------------- the chain on the table route
def sparse_returns_cube():
    """64×64×128: a return of 1e-17 J/bin (21.4 primaries) in bins 60–63 of every pixel, zero elsewhere."""
    cube = np.zeros((64, 64, 128), np.float32)
    cube[..., 60:64] = 1e-17
    return cube


@pytest.mark.parametrize("noise_table", [True, False])
def test_table_and_per_bin_routes_match_the_formula(noise_table):
    """Both routes: signal-free bins and signal bins have the §8 mean and variance within 2 % (5e5 and 1.6e4
    samples: signal bins within 4 %, 5 standard errors of the variance)."""
    out = chain(sparse_returns_cube(), 5, noise_table=noise_table)
    assert out.report["noise_sampling"] == ("table" if noise_table else "per-bin")
    d = DetectorSettings(**{"mode": "noisy", **SEC8})
    step = d.adc_full_scale_e / 2 ** d.adc_bits
    b = 5e9 * 1e-9 * 0.4 + current_to_electrons(1e-12, 1e-9)
    x = (out.data.astype(np.float64) - d.adc_offset_counts) * step
    F = F_SEC8
    for sl, n_s, tol in ((np.s_[..., :60], 0.0, 0.02), (np.s_[..., 60:64], 21.43, 0.04)):
        mean_e, var_e = linear_detector_moments(n_s, b, 100.0, F, 0.0, DS_SEC8, 300.0, step)
        assert x[sl].mean() == pytest.approx(mean_e, rel=tol)
        assert x[sl].var() == pytest.approx(var_e, rel=tol)


@pytest.mark.parametrize("n_s", [0.5, 40.0])
@pytest.mark.parametrize("noise_table", [True, False])
def test_signal_in_every_bin_matches_the_formula(n_s, noise_table):
    """A constant signal of n_s primaries in every bin (262144 samples): Poisson n_s — caught bins from the
    tables (n ≤ 16) and per bin (n > 16) — gives the §8 mean and variance within 2 %."""
    e = n_s / float(energy_to_photons(1.0, 1.064e-6, 0.4))
    out = chain(np.full((64, 64, 64), e, np.float32), 9, noise_table=noise_table)
    if noise_table:
        nt = out.report["noise_table"]
        assert nt["caught_bins_from_tables"] > 0 and (nt["caught_bins_per_bin"] > 0) == (n_s > 16)
    step = 500.0
    b = 5e9 * 1e-9 * 0.4 + current_to_electrons(1e-12, 1e-9)
    x = (out.data.astype(np.float64) - 16) * step
    mean_e, var_e = linear_detector_moments(n_s, b, 100.0, F_SEC8, 0.0, DS_SEC8, 300.0, step)
    assert x.mean() == pytest.approx(mean_e, rel=0.02)
    assert x.var() == pytest.approx(var_e, rel=0.02)


def test_table_route_is_seeded_and_thread_independent():
    cube = sparse_returns_cube()
    a = chain(cube, 7).data
    assert np.array_equal(a, chain(cube, 7, threads=1).data)
    assert not np.array_equal(a, chain(cube, 8).data)


def test_table_route_reports_clipping_like_the_per_bin_route():
    """Offset 0: half of the signal-free bins fall below code 0; the table route counts them (expected 5e5 × P,
    P from the pmf, within 5 standard errors), and saturated signal bins are counted at full scale."""
    cube = sparse_returns_cube()
    cube[:8, :8, 100] = 1.0  # saturates
    out = chain(cube, 2, adc_offset_counts=0, background_rate_photons_per_s=0.0, dark_current_bulk_a=0.0,
                dark_current_surface_a=0.0)
    k0, p = noise_code_pmf(500.0, gauss_var_e2=300.0 ** 2)
    p_low = p[(k0 + np.arange(p.size)) < 0].sum()
    n_free = 64 * 64 * 124 - 64
    assert abs(out.report["n_adc_low"] - n_free * p_low) < 5 * np.sqrt(n_free * p_low)
    assert out.report["n_adc_high"] == 64


def test_per_bin_route_where_the_table_does_not_apply():
    """A/D off (continuous electrons) or no read noise (a lattice): the exact per-bin route, said so."""
    cube = sparse_returns_cube()[:8, :8]
    assert chain(cube, 1, enable_adc=False).report["noise_sampling"] == "per-bin"
    assert chain(cube, 1, enable_read_noise=False).report["noise_sampling"] == "per-bin"


def test_tables_kept_for_the_next_frames_give_the_same_codes():
    """The code tables are kept between frames of a run (bounded cache): a frame drawn with kept tables (their
    caught-count tables already built) is bit for bit the frame drawn with tables built afresh."""
    from core.physics.receiver.table_route import noise_tables as _noise_tables

    cube = sparse_returns_cube()
    _noise_tables.cache_clear()
    fresh = chain(cube, 4)
    assert _noise_tables.cache_info().currsize == 1
    again = chain(cube, 4)
    assert _noise_tables.cache_info().hits >= 1
    assert np.array_equal(fresh.data, again.data) and fresh.report == again.report
    _noise_tables.cache_clear()
    assert np.array_equal(chain(cube, 4).data, fresh.data)


@pytest.mark.parametrize("n", [0, 1, 63, 64, 65, 1000])
def test_nonzero_index_equals_flatnonzero(n):
    """The compiled compaction of the chain (64-element SIMD tests, then the element loop): np.flatnonzero on
    sparse, dense, signed-zero and NaN data."""
    from core.physics.receiver.table_route import nonzero_index as _nonzero_index

    rng = np.random.default_rng(n)
    for frac in (0.0, 0.01, 0.5, 1.0):
        x = np.where(rng.random(n) < frac, rng.standard_normal(n), 0.0).astype(np.float32)
        if n > 10:
            x[3], x[7] = -0.0, np.nan
        idx = np.empty(n, np.int64)
        m = _nonzero_index(x, idx)
        assert np.array_equal(idx[:m], np.flatnonzero(x))
