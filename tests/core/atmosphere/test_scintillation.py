"""Statistics of the random turbulence realisations (docs/theory.md §3, §4, §5, §11): log-normal and gamma-gamma
scintillation patterns, beam wander, turbulence blur.  Every statistical test uses a fixed seed; tolerances
are stated in each docstring and are ≥ 3 standard errors of the estimate unless noted."""
import math

import numpy as np
import pytest
from scipy import stats

from core import atmosphere as atm


def one_over_e_radius(ac, pitch):
    """1/e crossing [m] of the axis profiles of an autocorrelation (mean of x and y), linear interpolation."""
    prof = 0.5 * (ac[0, : ac.shape[1] // 2] + ac[: ac.shape[0] // 2, 0])
    j = np.nonzero(prof < math.exp(-1))[0][0]
    p0, p1 = prof[j - 1], prof[j]
    return (j - 1 + (p0 - math.exp(-1)) / (p0 - p1)) * pitch


# ---------------------------------------------------------------------------------------------------- log-normal
S2, S_AV, RHO_L, PITCH, N, REAL = 0.3, 2.0, 0.016, 0.002, 512, 16


@pytest.fixture(scope="module")
def lognormal_fields():
    rng = np.random.default_rng(2024)
    corr = atm.lognormal_g_correlation(S2, RHO_L, "exact")
    spec, _ = atm.field_spectrum((N, N), PITCH, corr)
    return [atm.lognormal_pattern((N, N), PITCH, S2, RHO_L, rng, mean=S_AV, spectrum=spec) for _ in range(REAL)]


def test_lognormal_pdf_ks(lognormal_fields):
    """KS of ln S (nodes decimated by 20 px = 2.5 ρ_l, intensity correlation there e^(−6.25) < 0.002;
    16 × 26² = 10 816 samples) vs N(ln S_av − σ²/2, σ²): p-value > 0.01 and D < 0.015."""
    x = np.concatenate([np.log(f[::20, ::20]).ravel() for f in lognormal_fields])
    res = stats.kstest(x, stats.norm(loc=math.log(S_AV) - S2 / 2, scale=math.sqrt(S2)).cdf)
    assert res.pvalue > 0.01 and res.statistic < 0.015, res


def test_lognormal_moments(lognormal_fields):
    """σ_lnI² = var(ln S) within 5 % of 0.3 (std. error ≈ 1 %); mean within 1 % of S_av (≈ 0.3 %);
    SI within 5 % of e^(σ²) − 1."""
    allv = np.concatenate([f.ravel() for f in lognormal_fields])
    assert abs(np.var(np.log(allv)) / S2 - 1) < 0.05
    assert abs(allv.mean() / S_AV - 1) < 0.01
    assert abs(allv.var() / allv.mean() ** 2 / math.expm1(S2) - 1) < 0.05


def test_lognormal_correlation_radius_and_shape(lognormal_fields):
    """1/e radius of the intensity autocorrelation within 10 % of ρ_l (measured ≈ 1–3 %); shape Gaussian:
    |B(r) − exp(−r²/ρ_l²)| < 0.03 at r = ρ_l/2, ρ_l, 2ρ_l."""
    ac = atm.periodic_autocorrelation(lognormal_fields)
    assert abs(one_over_e_radius(ac, PITCH) / RHO_L - 1) < 0.10
    for k in (4, 8, 16):
        b = 0.5 * (ac[0, k] + ac[k, 0])
        assert abs(b - math.exp(-((k * PITCH / RHO_L) ** 2))) < 0.03, (k, b)


def test_lognormal_gaussian_g_mode_radius():
    """correlation='gaussian' (closed-form width a of §11): 1/e radius within 10 % of ρ_l, σ² = 1.0,
    8 realisations of 512²."""
    rng = np.random.default_rng(7)
    f = [atm.lognormal_pattern((N, N), PITCH, 1.0, RHO_L, rng, correlation="gaussian") for _ in range(8)]
    assert abs(one_over_e_radius(atm.periodic_autocorrelation(f), PITCH) / RHO_L - 1) < 0.10


def test_unit_variance_field_normalisation():
    """The filter spectrum is normalised so that var(g) = 1 exactly in expectation: IDFT(P)[0] = 1 to
    1e-12, and the pooled sample variance of 8 fields of 256² (ρ = 8 px) is within 3 % of 1."""
    corr = atm.lognormal_g_correlation(1.0, 8.0)
    spec, clipped = atm.field_spectrum((256, 256), 1.0, corr)
    assert abs(np.fft.irfft2(spec, s=(256, 256))[0, 0] - 1) < 1e-12
    assert clipped < 0.05
    rng = np.random.default_rng(5)
    g = np.stack([atm.gaussian_random_field((256, 256), 1.0, corr, rng, spec) for _ in range(8)])
    assert abs(g.var() - 1) < 0.03 and abs(g.mean()) < 0.03


def test_seed_speckle_method():
    """§11 seed generator (N = 1024, w = 40, intensity radius N/(πw) = 8.149 px): ln S exactly normal
    (KS on nodes decimated by 20 px, p > 0.01) and the 1/e radius of ln S = 0.926 × 8.149 px within 3 %
    (docs/theory.md §11 value; 4 realisations)."""
    rng = np.random.default_rng(11)
    f = [np.log(atm.seed_speckle_lognormal_pattern(1024, 40, 0.3, rng)) for _ in range(4)]
    x = np.concatenate([a[::20, ::20].ravel() for a in f])
    assert stats.kstest(x, stats.norm(loc=-0.15, scale=math.sqrt(0.3)).cdf).pvalue > 0.01
    r = one_over_e_radius(atm.periodic_autocorrelation(f), 1.0)
    assert abs(r / (0.926 * 8.149) - 1) < 0.03, r


# ---------------------------------------------------------------------------------------------------- gamma-gamma
@pytest.fixture(scope="module")
def gamma_case():
    """Case A, plane wave (σ_R² = 1.100): α = 4.282, β = 2.402, ρ_Y = 0.01193 m, ρ_X = 0.02838 m."""
    c, lam, L = 1e-14, 1064e-9, 2e3
    a, b = atm.gamma_gamma_parameters(atm.rytov_variance(c, lam, L, "plane"), "plane")
    rho0 = atm.coherence_radius(c, lam, L, "plane")
    ry = float(atm.cell_radius(lam, L, rho0))
    rx = float(atm.large_scale_radius(lam, L, rho0))
    pitch = ry / 4
    rng = np.random.default_rng(99)
    fields = [atm.gamma_gamma_pattern((512, 512), pitch, a, b, rx, ry, rng) for _ in range(24)]
    return dict(a=float(a), b=float(b), rx=rx, ry=ry, pitch=pitch, fields=fields)


def test_gamma_gamma_moments(gamma_case):
    """Mean 1 within 2 % (std. error ≈ 0.3 %); SI within 5 % of (1+1/α)(1+1/β) − 1 = 0.7471 (≈ 1.5 %)."""
    allv = np.concatenate([f.ravel() for f in gamma_case["fields"]])
    si = (1 + 1 / gamma_case["a"]) * (1 + 1 / gamma_case["b"]) - 1
    assert abs(si - 0.7471) < 5e-4
    assert abs(allv.mean() - 1) < 0.02
    assert abs(allv.var() / si - 1) < 0.05


def test_gamma_gamma_ks(gamma_case):
    """KS of nodes decimated by 24 px (≥ 2 ρ_X; 24 × 22² = 11 616 samples) vs the gamma-gamma CDF
    (numerical integration of the kve pdf): p-value > 0.01 and D < 0.015."""
    x = np.concatenate([f[::24, ::24].ravel() for f in gamma_case["fields"]])
    res = stats.kstest(x, lambda t: atm.gamma_gamma_cdf(t, gamma_case["a"], gamma_case["b"]))
    assert res.pvalue > 0.01 and res.statistic < 0.015, res


def test_gamma_gamma_covariance(gamma_case):
    """Normalised intensity autocovariance at lags ρ_Y, ρ_X, 2ρ_X within 0.04 (absolute) of the model
    (1 + b_X/α)(1 + b_Y/β) − 1 over SI; each factor's own correlation is exactly Gaussian by construction."""
    g = gamma_case
    ac = atm.periodic_autocorrelation(g["fields"])
    for lag in (g["ry"], g["rx"], 2 * g["rx"]):
        k = int(round(lag / g["pitch"]))
        meas = 0.5 * (ac[0, k] + ac[k, 0])
        model = atm.gamma_gamma_covariance(k * g["pitch"], g["a"], g["b"], g["rx"], g["ry"])
        assert abs(meas - model) < 0.04, (lag, meas, model)


def test_unit_gamma_translation_exact_marginal():
    """unit_gamma_from_gaussian maps N(0,1) quantiles to gamma(α, 1/α) quantiles to 1e-9 (incl. tails
    |z| ≤ 8), and α = inf gives exactly 1."""
    z = np.linspace(-8, 8, 161)
    for a in (0.7, 2.4, 30.0):
        x = atm.unit_gamma_from_gaussian(z, a)
        ref = stats.gamma(a, scale=1 / a).ppf(stats.norm.cdf(z))
        up = z > 0
        ref[up] = stats.gamma(a, scale=1 / a).isf(stats.norm.sf(z[up]))
        np.testing.assert_allclose(x, ref, rtol=1e-9)
    assert np.all(atm.unit_gamma_from_gaussian(z, np.inf) == 1.0)


# ---------------------------------------------------------------------------------------------------- patterns in metres
def test_make_pattern_regime_choice_and_grid():
    """Weak (case B, σ_R² = 0.38) → log-normal; case A (σ_R² = 1.10) → gamma-gamma; pitch ≤ ρ_l/8; the grid
    covers the 1 m footprint; every node finite and > 0."""
    rng = np.random.default_rng(1)
    pb = atm.make_scintillation_pattern((-0.5, 0.5, -0.5, 0.5), 1e-15, 1550e-9, 5e3, rng, statistics="paper")
    pa = atm.make_scintillation_pattern((-0.5, 0.5, -0.5, 0.5), 1e-14, 1064e-9, 2e3, rng, statistics="paper")
    assert pb.model == "lognormal" and pa.model == "gamma_gamma"
    for p in (pa, pb):
        assert p.pitch_m <= p.params["cell_radius_m"] / 8 * (1 + 1e-12)
        assert p.values.shape[0] * p.pitch_m >= 1.0 and p.values.shape[1] * p.pitch_m >= 1.0
        assert np.all(np.isfinite(p.values)) and np.all(p.values > 0)
    assert pa.params["tiled"] is False


def test_make_pattern_large_footprint_is_tiled_not_huge():
    """A 20 m footprint with a 4 mm cell: grid capped at max_grid_px per side (periodic tile), finite."""
    p = atm.make_scintillation_pattern((0, 20, 0, 20), 1e-15, 532e-9, 1e3, np.random.default_rng(0),
                                       max_grid_px=1024, statistics="paper")
    assert max(p.values.shape) <= 1024 and p.params["tiled"] is True
    v = p.sample(np.linspace(0, 20, 1000), np.linspace(0, 20, 1000))
    assert np.all(np.isfinite(v))


def test_make_pattern_separated_scales_product():
    """Case C plane (σ_R² = 6.9, ρ_X/ρ_Y = 13.6) with max_grid_px = 256 forces X and Y onto separate grids
    (ProductPattern): each factor resolved at its radius/8; over 8 seeds, 400 000 random points per seed
    inside the 0.6 m footprint: mean within 3 % of 1, SI within 10 % of (1+1/α)(1+1/β) − 1 (few large
    cells per footprint, so looser than the single-grid tests); strong case (Cn² = 1e-12, 20 km) finite."""
    c, lam, L = 1e-13, 532e-9, 1e3
    m, v = [], []
    for seed in range(8):
        p = atm.make_scintillation_pattern((-0.3, 0.3, -0.3, 0.3), c, lam, L, np.random.default_rng(seed),
                                           wave="plane", max_grid_px=256, statistics="paper")
        assert isinstance(p, atm.ProductPattern)
        xs, ys = np.random.default_rng(100 + seed).uniform(-0.3, 0.3, (2, 400_000))
        s = p.sample(xs, ys)
        m.append(s.mean())
        v.append(s.var())
    si = (1 + 1 / p.params["gamma_alpha"]) * (1 + 1 / p.params["gamma_beta"]) - 1
    assert abs(np.mean(m) - 1) < 0.03
    assert abs(np.mean(v) / si - 1) < 0.10, (np.mean(v), si)
    ps = atm.make_scintillation_pattern((-1, 1, -1, 1), 1e-12, 532e-9, 2e4, np.random.default_rng(0),
                                        max_grid_px=1024, statistics="paper")
    assert np.all(np.isfinite(ps.sample(np.linspace(-1, 1, 999), np.zeros(999))))


def test_sampling_nodes_periodicity_and_resolution_independence():
    """Bilinear sampling returns the node values exactly at nodes (1e-12), is periodic with the grid
    period, and two receivers of different resolution see identical values at the same target points."""
    rng = np.random.default_rng(3)
    p = atm.make_scintillation_pattern((-0.2, 0.2, -0.2, 0.2), 1e-15, 1550e-9, 5e3, rng, statistics="paper")
    ny, nx = p.values.shape
    j, i = np.meshgrid(np.arange(0, ny, 7), np.arange(0, nx, 5), indexing="ij")
    x = p.origin_m[0] + i * p.pitch_m
    y = p.origin_m[1] + j * p.pitch_m
    np.testing.assert_allclose(p.sample(x, y), p.values[j, i], rtol=0, atol=1e-12)
    np.testing.assert_allclose(p.sample(x, y, "nearest"), p.values[j, i], rtol=0, atol=0)
    xs = np.random.default_rng(4).uniform(-0.2, 0.2, 1000)
    ys = np.random.default_rng(5).uniform(-0.2, 0.2, 1000)
    np.testing.assert_allclose(p.sample(xs + nx * p.pitch_m, ys - ny * p.pitch_m), p.sample(xs, ys), atol=1e-9)
    coarse = np.linspace(-0.2, 0.2, 33)
    fine = np.linspace(-0.2, 0.2, 129)                # every 4th fine point is a coarse point
    cx, cy = np.meshgrid(coarse, coarse)
    fx, fy = np.meshgrid(fine, fine)
    np.testing.assert_array_equal(p.sample(cx, cy), p.sample(fx, fy)[::4, ::4])


def test_bilinear_variance_loss_small():
    """Bilinear sampling on a 4 × 4 sub-grid of every cell (log-normal σ² = 0.3, 512² nodes): SI loss
    < 6 % at pitch ρ_l/4 (measured 4.2 %) and < 1.5 % at ρ_l/8 (1.1 %, the make_scintillation_pattern
    default); mean preserved to 1e-9 (bilinear weights sum to 1 over a periodic grid)."""
    rng = np.random.default_rng(8)
    o = (np.arange(4) + 0.5) / 4
    for spc, tol in ((4, 0.06), (8, 0.015)):
        vals = atm.lognormal_pattern((512, 512), 1.0 / spc, 0.3, 1.0, rng)
        p = atm.ScintillationPattern(vals, 1.0 / spc)
        x = (np.arange(512)[None, :, None, None] + o[None, None, None, :]) / spc
        y = (np.arange(512)[:, None, None, None] + o[None, None, :, None]) / spc
        v = p.sample(*np.broadcast_arrays(x, y))
        assert 0 < 1 - v.var() / vals.var() < tol
        assert abs(v.mean() / vals.mean() - 1) < 1e-9


def test_no_turbulence_pattern_is_one():
    """Cn² = 0: pattern identically 1 (exact), any sample exactly 1.0; σ² = 0 generators return S_av."""
    p = atm.make_scintillation_pattern((-1, 1, -1, 1), 0.0, 1064e-9, 2e3, np.random.default_rng(0), statistics="paper")
    assert p.model == "none" and np.all(p.values == 1.0)
    assert np.all(p.sample(np.linspace(-5, 5, 11), np.zeros(11)) == 1.0)
    assert np.all(atm.lognormal_pattern((8, 8), 1.0, 0.0, 3.0, np.random.default_rng(0), mean=2.0) == 2.0)
    assert np.all(atm.gamma_gamma_pattern((8, 8), 1.0, np.inf, np.inf, 3.0, 2.0, np.random.default_rng(0)) == 1.0)


def test_seeds():
    """Same seed → identical patterns and wander (exact); different seeds → different (max diff > 0.1)."""
    def make(seed, model):
        return atm.make_scintillation_pattern((-0.3, 0.3, -0.3, 0.3), 1e-14, 1064e-9, 2e3,
                                              np.random.default_rng(seed), model=model, statistics="paper").values
    for model in ("lognormal", "gamma_gamma"):
        assert np.array_equal(make(1, model), make(1, model))
        assert np.max(np.abs(make(1, model) - make(2, model))) > 0.1
    w1 = atm.beam_wander_offsets(1e-4, np.random.default_rng(1), 10)
    assert np.array_equal(w1, atm.beam_wander_offsets(1e-4, np.random.default_rng(1), 10))
    assert not np.array_equal(w1, atm.beam_wander_offsets(1e-4, np.random.default_rng(2), 10))


# ---------------------------------------------------------------------------------------------------- beam wander
def test_beam_wander_variance():
    """B1 ⟨r_c²⟩ = 7.132e-4 m²: 200 000 pulses, per-axis variance within 2 % of ⟨r_c²⟩/2 (std. error 0.3 %),
    two-axis mean square within 2 % of ⟨r_c²⟩, axes uncorrelated (|ρ| < 0.01); ⟨r_c²⟩ = 0 gives exactly 0."""
    rc2 = float(atm.beam_wander_variance(1e-14, 2e3, 0.02))
    d = atm.beam_wander_offsets(rc2, np.random.default_rng(6), 200_000)
    assert d.shape == (200_000, 2)
    assert np.all(np.abs(d.var(axis=0) / (rc2 / 2) - 1) < 0.02)
    assert abs(np.mean(np.sum(d**2, axis=1)) / rc2 - 1) < 0.02
    assert abs(np.corrcoef(d.T)[0, 1]) < 0.01
    assert np.all(atm.beam_wander_offsets(0.0, np.random.default_rng(6), 5) == 0.0)
    assert atm.beam_wander_offsets(rc2, np.random.default_rng(6)).shape == (2,)


# ---------------------------------------------------------------------------------------------------- blur
LAM, D, R0 = 1.064e-6, 0.1, 0.05
NU_C = D / LAM


def measured_mtf(blurred, n, pitch, frac):
    """|DFT| of a blurred centred delta at ν = frac·ν_c along x and y (mean), normalised by the input 1."""
    f = np.abs(np.fft.fft2(blurred))
    k = int(round(frac * NU_C * n * pitch))
    return 0.5 * (f[0, k] + f[k, 0])


@pytest.mark.parametrize("exposure,alpha,expected", [
    ("long", 1.0, (0.3384, 0.03206)), ("short", 1.0, (0.6697, 0.4918)), ("short", 0.5, (0.4760, 0.1256))])
def test_blur_reproduces_mtf(exposure, alpha, expected):
    """Blur of a centred delta (512², pitch chosen so 0.25 ν_c and 0.5 ν_c are DFT bins 32 and 64):
    measured MTF within 5 % (relative) of the §5 values at 0.25 and 0.5 of the cut-off."""
    n = 512
    pitch = 128 / (n * NU_C)                       # ν_c ↔ bin 128
    img = np.zeros((n, n))
    img[n // 2, n // 2] = 1.0
    out = atm.turbulence_blur(img, pitch, LAM, R0, exposure=exposure, aperture_diameter_m=D, alpha=alpha)
    for frac, mtf in zip((0.25, 0.5), expected):
        assert abs(measured_mtf(out, n, pitch, frac) / mtf - 1) < 0.05, (frac, measured_mtf(out, n, pitch, frac))


def test_blur_energy_padding_and_identity():
    """Energy: a blob in the middle keeps its sum to 1e-3 (MTF(0) = 1, padding); no wrap-around: a spot on
    the left border gives < 1e-6 of its energy on the right border columns; r0 = inf returns the image
    unchanged (exact); a (2, H, W) stack blurs each slice like the single image (1e-12)."""
    n = 256
    pitch = 128 / (n * NU_C)
    img = np.zeros((n, n))
    img[100:156, 100:156] = 1.0
    out = atm.turbulence_blur(img, pitch, LAM, R0)
    assert abs(out.sum() / img.sum() - 1) < 1e-3 and out.min() > -1e-9
    edge = np.zeros((n, n))
    edge[128, 0] = 1.0
    oe = atm.turbulence_blur(edge, pitch, LAM, R0)
    assert oe[:, -3:].sum() < 1e-6
    assert np.array_equal(atm.turbulence_blur(img, pitch, LAM, np.inf), img)
    stack = atm.turbulence_blur(np.stack([img, edge]), pitch, LAM, R0)
    np.testing.assert_allclose(stack[0], out, atol=1e-12)
