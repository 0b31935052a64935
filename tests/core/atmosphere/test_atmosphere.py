"""Deterministic atmosphere physics: the worked test vectors of docs/theory.md §1–6, §11, §13 and the split-step
reference of §12.  Sheet values have 4 significant digits; unless stated, rtol = 5e-4 (half a unit of the
4th digit, relative)."""
import math

import numpy as np
import pytest
from scipy.integrate import quad

from core import atmosphere as atm

RTOL = 5e-4
CASES = {  # docs/theory.md §1: Cn², λ, L
    "A": (1e-14, 1064e-9, 2e3),
    "B": (1e-15, 1550e-9, 5e3),
    "C": (1e-13, 532e-9, 1e3),
}


def close(actual, expected, rtol=RTOL):
    np.testing.assert_allclose(actual, expected, rtol=rtol)


# ---------------------------------------------------------------------------------------------------- §1, §2
@pytest.mark.parametrize("case,s_pl,s_sp", [("A", 1.100, 0.4473), ("B", 0.3806, 0.1547), ("C", 6.932, 2.818)])
def test_rytov_variance_table(case, s_pl, s_sp):
    """§1 table: σ_R² and β0² to 4 digits (rtol 5e-4)."""
    c, lam, L = CASES[case]
    close(atm.rytov_variance(c, lam, L, "plane"), s_pl)
    close(atm.rytov_variance(c, lam, L, "spherical"), s_sp)


def test_rytov_vectorised_and_regimes():
    """Broadcasting over arrays; regime labels at the §1 limits (exact)."""
    c = np.array([0.0, 1e-16, 1e-14, 1e-13])
    s = atm.rytov_variance(c, 1064e-9, 2e3)
    assert s.shape == (4,)
    assert list(atm.turbulence_regime(np.array([0.0, 0.5, 1.0, 5.0, 10.0, 50.0]))) == [
        "none", "weak", "moderate", "moderate", "strong", "strong"]
    assert atm.turbulence_regime(0.2) == "weak"


@pytest.mark.parametrize("case,rpl,rsp,r0pl,r0sp", [
    ("A", 0.01568, 0.02832, 0.03297, 0.05938),
    ("B", 0.05657, 0.1022, 0.1190, 0.2143),
    ("C", 2.598e-3, 4.693e-3, 5.464e-3, 9.841e-3)])
def test_coherence_radius_and_fried(case, rpl, rsp, r0pl, r0sp):
    """§2 table: ρ0 and r0, plane and spherical, rtol 5e-4.  r0/ρ0 = 2.099 holds for the exact coefficients;
    with the rounded 1.46 and 0.423 of docs/theory.md §2 it is (1.46/0.423)^(3/5) = 2.103, so rtol 2e-3 there."""
    c, lam, L = CASES[case]
    close(atm.coherence_radius(c, lam, L, "plane"), rpl)
    close(atm.coherence_radius(c, lam, L, "spherical"), rsp)
    close(atm.fried_parameter(c, lam, L, "plane"), r0pl)
    close(atm.fried_parameter(c, lam, L, "spherical"), r0sp)
    close(atm.fried_parameter(c, lam, L, "plane") / atm.coherence_radius(c, lam, L, "plane"), 2.099, 2e-3)


@pytest.mark.parametrize("case,cpl,csp", [("A", 0.01193, 0.01543), ("B", 0.02984, 0.03321),
                                          ("C", 2.500e-3, 4.181e-3)])
def test_cell_radius_eq_3_6(case, cpl, csp):
    """§2: seed eq. 3-6 cell radius with ρ0,pl and ρ0,sp, rtol 5e-4."""
    c, lam, L = CASES[case]
    close(atm.cell_radius(lam, L, atm.coherence_radius(c, lam, L, "plane")), cpl)
    close(atm.cell_radius(lam, L, atm.coherence_radius(c, lam, L, "spherical")), csp)


def test_fresnel_scale():
    """§2: √(L/k) for case A = 0.01840 m (rtol 5e-4); ρ_X ρ_l = L/k (rtol 1e-12)."""
    c, lam, L = CASES["A"]
    close(atm.fresnel_scale(lam, L), 0.01840)
    rho0 = atm.coherence_radius(c, lam, L, "plane")
    close(atm.large_scale_radius(lam, L, rho0) * atm.cell_radius(lam, L, rho0), L / atm.wavenumber(lam), 1e-12)


# ---------------------------------------------------------------------------------------------------- §3
@pytest.mark.parametrize("case,ln_pl,ln_sp", [("A", 0.5580, 0.3628), ("B", 0.2965, 0.1452),
                                              ("C", 0.8032, 0.9115)])
def test_all_regime_log_intensity_variance(case, ln_pl, ln_sp):
    """§3: all-regime σ_lnI², plane (σ_R²) and spherical (β0²), rtol 5e-4."""
    c, lam, L = CASES[case]
    close(atm.log_intensity_variance(atm.rytov_variance(c, lam, L, "plane"), "plane"), ln_pl)
    close(atm.log_intensity_variance(atm.rytov_variance(c, lam, L, "spherical"), "spherical"), ln_sp)


def test_scintillation_index_case_a():
    """§3 case A: SI plane 0.7471, spherical 0.4373; naive exp(σ_R²) − 1 = 2.006 (rtol 5e-4)."""
    c, lam, L = CASES["A"]
    s = atm.rytov_variance(c, lam, L, "plane")
    close(atm.scintillation_index(atm.log_intensity_variance(s, "plane")), 0.7471)
    b = atm.rytov_variance(c, lam, L, "spherical")
    close(atm.scintillation_index(atm.log_intensity_variance(b, "spherical")), 0.4373)
    close(atm.scintillation_index(s), 2.006)


def test_gamma_gamma_case_a():
    """§3 case A plane: α = 4.282, β = 2.402, p(1) = 0.4617 (rtol 5e-4); pdf integrates to 1 (1e-6)."""
    s = atm.rytov_variance(*CASES["A"], "plane")
    a, b = atm.gamma_gamma_parameters(s, "plane")
    close(a, 4.282)
    close(b, 2.402)
    close(atm.gamma_gamma_pdf(1.0, a, b), 0.4617)
    total, _ = quad(lambda x: atm.gamma_gamma_pdf(x, a, b), 0, np.inf, limit=200)
    assert abs(total - 1) < 1e-6


def test_gamma_gamma_cdf_matches_quadrature():
    """gamma_gamma_cdf (trapezoid on a log grid) vs adaptive quad, abs error < 2e-6, incl. min(α,β) < 1."""
    for a, b in [(4.282, 2.402), (5.03, 1.159), (3.0, 0.8)]:
        for x in (0.1, 0.5, 1.0, 3.0):
            ref, _ = quad(lambda t: atm.gamma_gamma_pdf(t, a, b), 0, x, limit=200)
            assert abs(atm.gamma_gamma_cdf(x, a, b) - ref) < 2e-6


def test_gamma_gamma_pdf_large_parameters_finite():
    """kve/gammaln evaluation: α, β up to 1e4 finite and the pdf still integrates to 1 (1e-4)."""
    x = np.linspace(0.5, 1.5, 20001)
    p = atm.gamma_gamma_pdf(x, 1e4, 2e3)
    assert np.all(np.isfinite(p))
    assert abs(np.trapz(p, x) - 1) < 1e-4


def test_lognormal_pdf_eq_3_5():
    """§3: σ² = 0.3, S_av = 1: p(0.5) = 0.8909, p(1) = 0.7016, p(2) = 0.1114 (rtol 5e-4); p(0) = 0."""
    close(atm.lognormal_pdf(np.array([0.5, 1.0, 2.0]), 0.3), [0.8909, 0.7016, 0.1114])
    assert atm.lognormal_pdf(0.0, 0.3) == 0.0


def test_gaussian_beam_on_axis_si():
    """§3: σ_R² = 0.1, Θ = 0.2586, Λ = 0.4378 → σ_I²(0) = 0.02499 (rtol 5e-4)."""
    close(atm.gaussian_beam_scintillation_weak(0.1, 0.2586, 0.4378), 0.02499)


def test_aperture_averaging_case_a():
    """§3 case A, D = 5 cm: A_pl = 0.2820, A_sp = 0.5741 (rtol 5e-4)."""
    _, lam, L = CASES["A"]
    close(atm.aperture_averaging_factor(lam, L, 0.05, "plane"), 0.2820)
    close(atm.aperture_averaging_factor(lam, L, 0.05, "spherical"), 0.5741)


def test_two_way_si():
    """§3: SI_tot = (1 + SI_up)(1 + SI_down) − 1 (exact)."""
    assert atm.two_way_scintillation_index(0.2, 0.3) == pytest.approx(0.56, rel=1e-12)


# ---------------------------------------------------------------------------------------------------- §4
@pytest.mark.parametrize("lam,w0,L,f0,cn2,W,theta,lam_,wlt,rc2,wst", [
    (1064e-9, 0.02, 2e3, np.inf, 1e-14, 0.03933, 0.2586, 0.4378, 0.05181, 7.132e-4, 0.04439),
    (1550e-9, 0.05, 5e3, np.inf, 1e-15, 0.07024, 0.5067, 0.5000, 0.07960, 8.211e-4, 0.07425),
    (1064e-9, 0.05, 2e3, 2e3, 1e-14, 0.01355, None, 3.691, 0.03132, 5.912e-4, None)])
def test_gaussian_beam_table(lam, w0, L, f0, cn2, W, theta, lam_, wlt, rc2, wst):
    """§4 table B1–B3: W, Θ, Λ, W_LT, ⟨r_c²⟩ (2.42 form), W_ST, rtol 5e-4.

    W_ST of B1 computes to 0.044402 (docs/theory.md §4 lists 0.04440;
    the 0.04439 expected here is 2.7e-4 away, within rtol)."""
    p = atm.gaussian_beam_parameters(lam, w0, L, f0)
    close(p["w_m"], W)
    if theta is not None:
        close(p["theta"], theta)
    close(p["lam"], lam_)
    s = atm.rytov_variance(cn2, lam, L, "plane")
    w_lt = atm.long_term_beam_radius(p["w_m"], s, p["lam"])
    close(w_lt, wlt)
    r = atm.beam_wander_variance(cn2, L, w0, f0)
    close(r, rc2)
    if wst is not None:
        close(atm.short_term_beam_radius(w_lt, r, p["w_m"]), wst)


def test_long_term_radius_strong_form_no_turbulence():
    """Strong-turbulence W_LT form reduces to W for ρ0 = inf (exact)."""
    assert atm.long_term_beam_radius(0.04, 0.0, 0.4, rho0_spherical_m=np.inf, wavelength_m=1e-6,
                                     range_m=1e3, method="strong") == 0.04


# ---------------------------------------------------------------------------------------------------- §5
LAM, D, R0 = 1.064e-6, 0.1, 0.05
NU_C = D / LAM


def test_cutoff():
    """§5: ν_c = D/λ = 9.398e4 cycles/rad (rtol 5e-4)."""
    close(NU_C, 9.398e4)


@pytest.mark.parametrize("frac,dif,le,se1,se05", [(0.25, 0.6850, 0.3384, 0.6697, 0.4760),
                                                  (0.5, 0.3910, 0.03206, 0.4918, 0.1256)])
def test_mtf_vectors(frac, dif, le, se1, se05):
    """§5: diffraction, LE, SE(α=1), SE(α=0.5) at 0.25 and 0.5 ν_c, rtol 5e-4."""
    nu = frac * NU_C
    close(atm.diffraction_mtf(nu, LAM, D), dif)
    close(atm.turbulence_mtf_long(nu, LAM, R0), le)
    close(atm.turbulence_mtf_short(nu, LAM, R0, D, 1.0), se1)
    close(atm.turbulence_mtf_short(nu, LAM, R0, D, 0.5), se05)


def test_pixel_and_total_mtf():
    """§5: pixel a = 20 µm at 25 cyc/mm = 0.6366; total (diffraction × LE × pixel, f = 0.5 m) = 0.3624."""
    close(atm.pixel_mtf(25e3, 20e-6), 0.6366)
    nu_a = 25e3 * 0.5
    total = atm.diffraction_mtf(nu_a, LAM, D) * atm.turbulence_mtf_long(nu_a, LAM, R0) * atm.pixel_mtf(25e3, 20e-6)
    close(total, 0.3624)


def test_mtf_limits():
    """MTF(0) = 1 exactly; r0 = inf gives MTF ≡ 1 exactly; SE clamped beyond cut-off is finite."""
    nu = np.linspace(0, 3 * NU_C, 101)
    assert atm.turbulence_mtf_long(0.0, LAM, R0) == 1.0
    assert np.all(atm.turbulence_mtf_long(nu, LAM, np.inf) == 1.0)
    assert np.all(atm.turbulence_mtf_short(nu, LAM, np.inf, D) == 1.0)
    assert np.all(np.isfinite(atm.turbulence_mtf_short(nu, LAM, R0, D, 0.5)))
    assert atm.diffraction_mtf(2 * NU_C, LAM, D) == 0.0


# ---------------------------------------------------------------------------------------------------- §6, §13
@pytest.mark.parametrize("v_km,kruse,kim", [
    (23, (0.1776, 0.07213, 0.04423), (0.1776, 0.07213, 0.04423)),
    (5, (0.8089, 0.4043, 0.2775), (0.8126, 0.3687, 0.2401)),
    (1, (3.989, 2.659, 2.134), (3.978, 2.813, 2.330))])
def test_extinction_table(v_km, kruse, kim):
    """§6 table: β [1/km] for 532/1064/1550 nm, Kruse and Kim, rtol 5e-4 (function returns 1/m)."""
    lam = np.array([532e-9, 1064e-9, 1550e-9])
    close(atm.extinction_from_visibility(v_km * 1e3, lam, "kruse") * 1e3, kruse)
    close(atm.extinction_from_visibility(v_km * 1e3, lam, "kim") * 1e3, kim)


def test_two_way_transmission_vectors():
    """§6: Kim, R = 2 km, 1064 nm: T² = 0.7494 (V = 23 km), 1.300e-5 (V = 1 km), rtol 5e-4."""
    b = atm.extinction_from_visibility(np.array([23e3, 1e3]), 1064e-9, "kim")
    close(atm.two_way_transmission(b, 2e3), [0.7494, 1.300e-5])


def test_log_transmission_thick_fog_50km():
    """§13: V = 200 m, 1550 nm, R = 50 km: ln T² finite and exactly −2σR (float64 equality); T² underflows."""
    s = atm.extinction_from_visibility(200.0, 1550e-9, "kim")
    r = np.float64(50e3)
    lt = atm.log_two_way_transmission(s, r)
    assert np.isfinite(lt) and lt == -2.0 * s * r and lt < -1900
    assert atm.two_way_transmission(s, r) == 0.0


def test_extinction_continuity_and_sane_ranges():
    """q(V) continuous at the Kim breakpoints 0.5, 1, 6 km (abs 1e-12 at 1 and 0.5 km, 0.3 jump at 6 km is
    the model's own); all V in 0.2–50 km and λ in 0.5–2 µm finite and positive."""
    q = atm.visibility_size_exponent
    assert abs(q(1000.0) - q(1000.0 + 1e-9)) < 1e-9
    assert abs(q(500.0) - q(500.0 + 1e-9)) < 1e-9
    v, lam = np.meshgrid(np.geomspace(200, 50e3, 50), np.linspace(0.5e-6, 2e-6, 7))
    for model in atm.EXTINCTION_MODELS:
        b = atm.extinction_from_visibility(v, lam, model)
        assert np.all(np.isfinite(b)) and np.all(b > 0)
    with pytest.raises(ValueError):
        atm.extinction_from_visibility(0.0, 1e-6)


# ---------------------------------------------------------------------------------------------------- §11 (closed forms)
def test_section11_closed_forms():
    """§11: Gaussian g width a = 8.398 px for ρ_l = 8 px, σ² = 0.3; speckle radius N/(πw) = 8.149 px
    (N = 1024, w = 40); rtol 5e-4.  a → ρ_l as σ² → 0 (rtol 1e-6)."""
    close(atm.gaussian_g_width(8.0, 0.3), 8.398)
    close(atm.speckle_correlation_radius_px(1024, 40), 8.149)
    close(atm.gaussian_g_width(8.0, 1e-9), 8.0, 1e-6)


# ---------------------------------------------------------------------------------------------------- no turbulence, sane ranges
def test_no_turbulence_is_exact():
    """Cn² = 0: σ_R² = 0, σ_lnI² = 0, SI = 0, ρ0 = r0 = inf, cell = Fresnel scale, α = β = inf,
    wander 0, regime 'none', metadata JSON-safe (None for inf).  All exact."""
    lam, L = 1064e-9, 2e3
    assert atm.rytov_variance(0.0, lam, L) == 0.0
    assert atm.log_intensity_variance(0.0) == 0.0
    assert atm.coherence_radius(0.0, lam, L) == np.inf
    assert atm.fried_parameter(0.0, lam, L) == np.inf
    assert atm.cell_radius(lam, L, np.inf) == atm.fresnel_scale(lam, L)
    a, b = atm.gamma_gamma_parameters(0.0)
    assert a == np.inf and b == np.inf
    assert atm.beam_wander_variance(0.0, L, 0.02) == 0.0
    d = atm.derived_turbulence(0.0, lam, L, aperture_diameter_m=0.05)
    assert d["regime"] == "none" and d["pdf_model"] == "none" and d["scintillation_index"] == 0.0
    assert d["rho0_spherical_m"] is None and d["gamma_alpha"] is None
    import json
    json.dumps(d, allow_nan=False)


def test_sane_ranges_finite():
    """§13 ranges and beyond (Cn² 0 and 1e-17…1e-11, λ 0.532–2 µm, L 0 m…50 km): every derived quantity
    finite (or None for an infinite radius), none NaN."""
    cn2 = np.concatenate([[0.0], np.geomspace(1e-17, 1e-11, 7)])
    lam = np.array([0.532e-6, 0.85e-6, 1.064e-6, 1.55e-6, 2.0e-6])
    rng_m = np.array([0.0, 1.0, 10.0, 1e3, 2e4, 5e4])
    C, LAMG, R = np.meshgrid(cn2, lam, rng_m, indexing="ij")
    s = atm.rytov_variance(C, LAMG, R)
    for wave in atm.WAVE_TYPES:
        v = atm.log_intensity_variance(atm.rytov_variance(C, LAMG, R, wave), wave)
        assert np.all(np.isfinite(v)) and np.all(v >= 0)
        rho0 = atm.coherence_radius(C, LAMG, R, wave)
        assert not np.any(np.isnan(rho0))
        assert np.all(np.isfinite(atm.cell_radius(LAMG, R, rho0)))
    assert np.all(np.isfinite(s))
    for c in cn2:
        for l_ in lam:
            for r in rng_m:
                d = atm.derived_turbulence(c, l_, r, aperture_diameter_m=0.1)
                assert all(not (isinstance(x, float) and not math.isfinite(x)) for x in d.values())


# ---------------------------------------------------------------------------------------------------- §12 split step
def test_split_step_reference_plane_wave():
    """§12: plane wave, L = 1 km, 1064 nm, Cn² = 6.477e-15 (σ_R² = 0.2): reference SI = 0.1989 ± 0.0008.

    Modest run for 2 cores: 512² grid, 2 mm spacing (Fresnel scale 13 mm ≈ 6.5 samples; unresolved
    eddies < 4 mm carry < 1 % of the log-amplitude variance), 5 screens (Rytov 0.04 each), 16 realisations,
    central 256² crop: statistical standard error ≈ 1 %; tolerance 5 % (≈ 4 standard errors plus the
    discretisation bias).  Also the intensity 1/e correlation radius must lie within 30 % of the Fresnel
    scale √(L/k) (weak-turbulence plane-wave cell size).  Runtime ≈ 2 s."""
    rng = np.random.default_rng(12)
    r = atm.split_step_reference(1064e-9, 1e3, 6.477e-15, rng, n=512, dx_m=2e-3, realizations=16)
    close(r["rytov_variance"], 0.2, 1e-3)
    assert abs(r["scintillation_index"] - 0.1989) < 0.05 * 0.1989, r
    assert abs(r["correlation_radius_m"] / float(atm.fresnel_scale(1064e-9, 1e3)) - 1) < 0.3, r


def test_split_step_no_turbulence():
    """Cn² = 0: the plane wave stays exactly uniform up to FFT round-off (|I − 1| < 1e-12)."""
    i = atm.split_step_plane_wave(1064e-9, 1e3, 0.0, np.random.default_rng(0), n=64, dx_m=2e-3)
    assert np.max(np.abs(i - 1)) < 1e-12


def _discrete_structure_function(n, dx, r0, lag, subharmonics):
    """Expected D(lag·dx) along x of the FFT(+SH) screen: Σ 2 Φ(f) Δf² (1 − cos 2π f_x r) over its frequencies."""
    df = 1.0 / (n * dx)
    f = np.fft.fftfreq(n, dx)
    fx, fy = np.meshgrid(f, f)
    p = atm.von_karman_phase_psd(np.hypot(fx, fy), r0) * df**2
    p[0, 0] = 0.0
    r = lag * dx
    d = np.sum(2 * p * (1 - np.cos(2 * np.pi * fx * r)))
    if subharmonics:
        for k in range(1, 4):
            dfp = df / 3**k
            gx, gy = np.meshgrid(np.array([-1, 0, 1]) * dfp, np.array([-1, 0, 1]) * dfp)
            q = atm.von_karman_phase_psd(np.hypot(gx, gy), r0) * dfp**2
            q[1, 1] = 0.0
            d += np.sum(2 * q * (1 - np.cos(2 * np.pi * gx * r)))
    return d


def test_phase_screen_structure_function():
    """FFT + Lane-subharmonic screens (60 screens of 256², dx = r0/8), lags r0/2 … 4 r0:
    (1) the measured phase structure function equals the expectation of the discrete spectrum actually
    synthesised within 5 % for lags ≤ 2 r0 and 10 % at 4 r0, where few low-frequency modes dominate
    (checks the normalisation; statistical error ≈ 2 % resp. 5 %);
    (2) vs Kolmogorov 6.88 (r/r0)^(5/3): within 20 % with subharmonics (point sampling of the steep PSD
    in the lowest rings is the method's known residual deficit, 11–22 % here) and clearly better than
    without (FFT only: 27–53 % short)."""
    rng = np.random.default_rng(3)
    r0, n, dx = 0.1, 256, 0.1 / 8
    s = atm.phase_screens(60, n, dx, r0, rng)
    for lag in (4, 8, 16, 32):
        d = 0.5 * (np.mean((s[:, :, lag:] - s[:, :, :-lag]) ** 2) + np.mean((s[:, lag:, :] - s[:, :-lag, :]) ** 2))
        expected = _discrete_structure_function(n, dx, r0, lag, True)
        assert abs(d / expected - 1) < (0.05 if lag <= 16 else 0.10), (lag, d, expected)
        theory = 6.88 * (lag * dx / r0) ** (5 / 3)
        assert abs(d / theory - 1) < 0.20, (lag, d, theory)
        assert _discrete_structure_function(n, dx, r0, lag, False) < 0.75 * theory
