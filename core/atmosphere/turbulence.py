"""Optical-turbulence parameters of a horizontal path with constant Cn² (paper §3.4 A, B, D, E).

Formulas from Andrews & Phillips, *Laser Beam Propagation through Random Media* (2nd ed., 2005) as
collected in docs/theory.md §1–5.  Every function is vectorised (numpy broadcasting), works in float64
and returns exactly "no turbulence" for Cn² = 0 (Rytov variance 0, coherence radii +inf, MTF 1, wander 0).

Notation: k = 2π/λ, L the path length (``range_m``), Cn² in m^(-2/3) (``cn2_m_23``).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import gammaln, hyp2f1, kve

WAVE_TYPES = ("plane", "spherical")

#: Regime limits on the plane-wave Rytov variance σ_R² (docs/theory.md §1).
WEAK_LIMIT = 1.0          # σ_R² < 1: weak fluctuations (log-normal, seed eq. 3-5, acceptable)
STRICT_RYTOV_LIMIT = 0.3  # σ_R² ≲ 0.3: first-order Rytov theory strictly valid
STRONG_LIMIT = 10.0       # σ_R² ≳ 10: SI past its focusing peak (≈ 1.24), tending to saturation (SI → 1)


def _f64(x):
    return np.asarray(x, dtype=np.float64)


def check_wave(wave):
    if wave not in WAVE_TYPES:
        raise ValueError(f"wave must be one of {WAVE_TYPES}, got {wave!r}")


def wavenumber(wavelength_m):
    """k = 2π/λ [rad/m]."""
    return 2.0 * np.pi / _f64(wavelength_m)


# ----------------------------------------------------------------------------------------------------------
# §1 Rytov variance and regimes
# ----------------------------------------------------------------------------------------------------------
def rytov_variance(cn2_m_23, wavelength_m, range_m, wave="plane"):
    """Rytov variance (docs/theory.md §1).

    plane:     σ_R² = 1.23 Cn² k^(7/6) L^(11/6)
    spherical: β0²  = 0.50 Cn² k^(7/6) L^(11/6)   (= 0.406 σ_R²)

    The rounded coefficients 1.23 / 0.50 are the ones docs/theory.md §1 quotes (exact 1.2285 / 0.4967).
    These are the first-order (weak-fluctuation) scintillation indices of a point receiver; they are the
    turbulence-strength parameters used by all the other formulas, not the SI in strong turbulence.
    """
    check_wave(wave)
    c = 1.23 if wave == "plane" else 0.50
    k = wavenumber(wavelength_m)
    return c * _f64(cn2_m_23) * k ** (7.0 / 6.0) * _f64(range_m) ** (11.0 / 6.0)


def turbulence_regime(rytov_plane):
    """Regime label from the plane-wave Rytov variance σ_R² (docs/theory.md §1), vectorised.

    ``"none"`` (σ_R² = 0), ``"weak"`` (σ_R² < 1), ``"moderate"`` (1 ≤ σ_R² < 10, focusing regime where
    SI rises to its peak ≈ 1.24), ``"strong"`` (σ_R² ≥ 10, saturation towards SI = 1).  Returns a str for
    a scalar input, else an array of str.
    """
    s = _f64(rytov_plane)
    out = np.select([s <= 0.0, s < WEAK_LIMIT, s < STRONG_LIMIT], ["none", "weak", "moderate"], "strong")
    return str(out) if out.ndim == 0 else out


# ----------------------------------------------------------------------------------------------------------
# §2 Coherence radius, Fried parameter, cell size, Fresnel scale
# ----------------------------------------------------------------------------------------------------------
def coherence_radius(cn2_m_23, wavelength_m, range_m, wave="spherical"):
    """Spatial coherence radius ρ0 [m] (docs/theory.md §2).

    plane: ρ0 = (1.46 Cn² k² L)^(−3/5); spherical: ρ0 = (0.545 Cn² k² L)^(−3/5).
    Kolmogorov spectrum, zero inner scale, ρ0 ≫ l0.  +inf for Cn² = 0 or L = 0 (no turbulence).
    Use the spherical value when imaging a target at range L (docs/theory.md §2).
    """
    check_wave(wave)
    c = 1.46 if wave == "plane" else 0.545
    k = wavenumber(wavelength_m)
    x = c * _f64(cn2_m_23) * k**2 * _f64(range_m)
    with np.errstate(divide="ignore"):
        return np.where(x > 0.0, np.power(np.where(x > 0.0, x, 1.0), -0.6), np.inf)


def fried_parameter(cn2_m_23, wavelength_m, range_m, wave="spherical"):
    """Fried parameter r0 [m] (docs/theory.md §2; r0 = 2.099 ρ0 for the same wave type).

    plane: r0 = (0.423 k² Cn² L)^(−3/5); spherical: r0 = ((3/8) 0.423 k² Cn² L)^(−3/5).  +inf for Cn² = 0.
    """
    check_wave(wave)
    c = 0.423 if wave == "plane" else 0.423 * 3.0 / 8.0
    k = wavenumber(wavelength_m)
    x = c * _f64(cn2_m_23) * k**2 * _f64(range_m)
    return np.where(x > 0.0, np.power(np.where(x > 0.0, x, 1.0), -0.6), np.inf)


def fresnel_scale(wavelength_m, range_m):
    """Fresnel scale √(L/k) [m] (docs/theory.md §2): the scintillation cell size in weak turbulence."""
    return np.sqrt(_f64(range_m) / wavenumber(wavelength_m))


def cell_radius(wavelength_m, range_m, rho0_m):
    """Turbulence cell radius ρ_l [m], seed eq. (3-6) (docs/theory.md §2).

    ρ_l = √(L/k) / √(1 + L/(k ρ0²)): the Fresnel scale in weak turbulence, → ρ0 in strong turbulence.
    With ρ0 = +inf (no turbulence) it is √(L/k).  Used as the 1/e radius of the intensity correlation.
    """
    k = wavenumber(wavelength_m)
    L = _f64(range_m)
    rho0 = _f64(rho0_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(np.isfinite(rho0), L / (k * np.where(np.isfinite(rho0), rho0, 1.0) ** 2), 0.0)
    return np.sqrt(L / k) / np.sqrt(1.0 + ratio)


def large_scale_radius(wavelength_m, range_m, rho0_m):
    """Large-scale (refractive) cell radius [m] used for the X factor of the gamma-gamma pattern.

    Our interpolation (not from the literature; docs/theory.md §2):
    ρ_X = (L/k)/ρ_l = √(L/k) √(1 + L/(k ρ0²)), the partner of eq. 3-6
    so that ρ_X ρ_l = L/k.  It is √(L/k) in weak turbulence and the scattering-disk size L/(k ρ0) in strong
    turbulence, the large-eddy scale of the Andrews–Phillips filtered-spectrum model.
    """
    L = _f64(range_m)
    k = wavenumber(wavelength_m)
    rl = cell_radius(wavelength_m, range_m, rho0_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(rl > 0, (L / k) / np.where(rl > 0, rl, 1.0), 0.0)


# ----------------------------------------------------------------------------------------------------------
# §3 Log-intensity variance, SI, gamma-gamma, aperture averaging, pdfs
# ----------------------------------------------------------------------------------------------------------
def log_intensity_variance_terms(rytov, wave="plane"):
    """The large- and small-scale terms (σ_lnX², σ_lnY²) of the all-regime σ_lnI² (docs/theory.md §3).

    Andrews (1999), zero inner scale, point receiver:
    σ_lnX² = 0.49 s/(1 + a s^(6/5))^(7/6), σ_lnY² = 0.51 s/(1 + 0.69 s^(6/5))^(5/6), with s = σ_R², a = 1.11
    for a plane wave and s = β0², a = 0.56 for a spherical wave.  ``rytov`` is σ_R² or β0² accordingly.
    """
    check_wave(wave)
    a = 1.11 if wave == "plane" else 0.56
    s = _f64(rytov)
    s65 = s ** 1.2
    sx = 0.49 * s / (1.0 + a * s65) ** (7.0 / 6.0)
    sy = 0.51 * s / (1.0 + 0.69 * s65) ** (5.0 / 6.0)
    return sx, sy


def log_intensity_variance(rytov, wave="plane"):
    """All-regime log-intensity variance σ_lnI² = σ_lnX² + σ_lnY² (docs/theory.md §3).

    Valid from weak to saturated fluctuations (Kolmogorov, l0 = 0, point receiver); ≈ ``rytov`` when weak.
    Feeding σ_R² directly as the log-normal σ² instead badly overestimates strong turbulence.
    """
    sx, sy = log_intensity_variance_terms(rytov, wave)
    return sx + sy


def scintillation_index(sigma2_lnI):
    """SI = σ_I² = exp(σ_lnI²) − 1 (docs/theory.md §3)."""
    return np.expm1(_f64(sigma2_lnI))


def gamma_gamma_parameters(rytov, wave="plane"):
    """Gamma-gamma shape parameters (α, β) = (1/(e^(σ_lnX²) − 1), 1/(e^(σ_lnY²) − 1)) (docs/theory.md §3).

    Al-Habash, Andrews & Phillips (2001).  +inf for zero turbulence (each factor ≡ 1).
    """
    sx, sy = log_intensity_variance_terms(rytov, wave)
    with np.errstate(divide="ignore"):
        return 1.0 / np.expm1(sx), 1.0 / np.expm1(sy)


def lognormal_pdf(intensity, sigma2_lnI, mean=1.0):
    """Log-normal scintillation pdf, seed eq. (3-5) (docs/theory.md §3).

    p(S) = 1/(S √(2π σ²)) exp(−(ln(S/S_av) + σ²/2)² / (2σ²)), σ² = σ_lnI² > 0; 0 for S ≤ 0.
    Valid for weak turbulence (σ_R² ≲ 1).
    """
    s = _f64(intensity)
    v = _f64(sigma2_lnI)
    pos = s > 0.0
    ss = np.where(pos, s, 1.0)
    p = np.exp(-(np.log(ss / mean) + 0.5 * v) ** 2 / (2.0 * v)) / (ss * np.sqrt(2.0 * np.pi * v))
    return np.where(pos, p, 0.0)


def gamma_gamma_pdf(intensity, alpha, beta):
    """Gamma-gamma pdf of unit-mean intensity (docs/theory.md §3, Al-Habash et al. 2001).

    p(I) = 2(αβ)^((α+β)/2) I^((α+β)/2 − 1) K_(α−β)(2√(αβI)) / (Γ(α)Γ(β)), evaluated in log form with the
    exponentially scaled Bessel function ``kve`` (no overflow for large α, β).  0 for I ≤ 0.
    """
    i = _f64(intensity)
    a = _f64(alpha)
    b = _f64(beta)
    pos = i > 0.0
    ii = np.where(pos, i, 1.0)
    z = 2.0 * np.sqrt(a * b * ii)
    logp = (math.log(2.0) + 0.5 * (a + b) * np.log(a * b) + (0.5 * (a + b) - 1.0) * np.log(ii)
            + log_bessel_k(a - b, z) - gammaln(a) - gammaln(b))
    return np.where(pos, np.exp(logp), 0.0)


def log_bessel_k(nu, x):
    """ln K_ν(x) for x > 0 without overflow: ln kve(ν, x) − x, or for large orders (|ν| > 200, or where
    ``kve`` over/underflows) the uniform (Debye) asymptotic expansion of K_ν(νz) to O(ν⁻²)
    (Abramowitz & Stegun 9.7.8), relative error < 1e-8 there."""
    nu = np.abs(np.asarray(nu, dtype=np.float64))
    x = np.asarray(x, dtype=np.float64)
    nu, x = np.broadcast_arrays(nu, x)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        k = kve(nu, x)
        direct = np.log(k) - x
        nn = np.where(nu > 0, nu, 1.0)
        z = x / nn
        sq = np.sqrt(1.0 + z * z)
        t = 1.0 / sq
        eta = sq + np.log(z / (1.0 + sq))
        u1 = (3 * t - 5 * t**3) / 24.0
        u2 = (81 * t**2 - 462 * t**4 + 385 * t**6) / 1152.0
        asym = (0.5 * np.log(np.pi / (2 * nn)) - nn * eta - 0.5 * np.log(sq)
                + np.log1p(-u1 / nn + u2 / nn**2))
    use_asym = (nu > 200.0) | ~np.isfinite(direct)
    return np.where(use_asym, asym, direct)


def gamma_gamma_cdf(intensity, alpha, beta, n_nodes=20001):
    """Gamma-gamma CDF by numerical integration of :func:`gamma_gamma_pdf` (scalar α, β).

    Integrates p(I) I d(ln I) with the trapezoid rule on a log grid from 1e-12 to 200 (the pdf may be
    integrably singular at 0 when min(α, β) < 1; the mass below 1e-12 is added analytically from the
    small-I behaviour p ∝ I^(min(α,β) − 1)), then interpolates.  Accuracy ≈ 1e-6 for α, β ≥ 0.5.
    """
    a, b = float(alpha), float(beta)
    lo, hi = 1e-12, 200.0
    t = np.linspace(math.log(lo), math.log(hi), n_nodes)
    x = np.exp(t)
    f = gamma_gamma_pdf(x, a, b) * x
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(t))])
    m = min(a, b)
    cum += f[0] / m                     # ∫_0^lo c I^(m−1) dI = p(lo) lo / m
    cum /= cum[-1]
    i = _f64(intensity)
    return np.interp(i, x, cum, left=0.0, right=1.0)


def gaussian_beam_scintillation_weak(rytov_plane, theta, lam):
    """On-axis scintillation index of a Gaussian beam, weak turbulence (docs/theory.md §3).

    σ_I²(0) = 3.86 σ_R² {0.40 [(1+2Θ)² + 4Λ²]^(5/12) cos[(5/6) atan((1+2Θ)/(2Λ))] − (11/16) Λ^(5/6)}.
    Valid for σ_R² < 1 and σ_R² Λ^(5/6) < 1.
    """
    s, t, l = _f64(rytov_plane), _f64(theta), _f64(lam)
    return 3.86 * s * (0.40 * ((1 + 2 * t) ** 2 + 4 * l**2) ** (5.0 / 12.0)
                       * np.cos((5.0 / 6.0) * np.arctan2(1 + 2 * t, 2 * l)) - (11.0 / 16.0) * l ** (5.0 / 6.0))


def aperture_averaging_factor(wavelength_m, range_m, aperture_diameter_m, wave="plane"):
    """Aperture-averaging factor A = SI(D)/SI(0), weak turbulence (docs/theory.md §3).

    d² = k D²/(4L); plane A = (1 + 1.062 d²)^(−7/6), spherical A = (1 + 0.33 d²)^(−7/6).
    Applies to a receiver of diameter D looking at a point source/beam; not to the target-plane pattern.
    """
    check_wave(wave)
    c = 1.062 if wave == "plane" else 0.33
    k = wavenumber(wavelength_m)
    with np.errstate(divide="ignore"):
        d2 = k * _f64(aperture_diameter_m) ** 2 / (4.0 * _f64(range_m))   # L = 0: d² = inf, A = 0
    return (1.0 + c * d2) ** (-7.0 / 6.0)


def two_way_scintillation_index(si_up, si_down):
    """Independent up/down paths: SI_tot = (1 + SI_up)(1 + SI_down) − 1 (docs/theory.md §3)."""
    return (1.0 + _f64(si_up)) * (1.0 + _f64(si_down)) - 1.0


# ----------------------------------------------------------------------------------------------------------
# §4 Gaussian beam: spread and wander
# ----------------------------------------------------------------------------------------------------------
def gaussian_beam_parameters(wavelength_m, w0_m, range_m, focus_m=np.inf):
    """Free-space Gaussian-beam parameters at the receiver plane (docs/theory.md §4).

    Θ0 = 1 − L/F0, Λ0 = 2L/(k W0²); W = W0 √(Θ0² + Λ0²), Θ = Θ0/(Θ0² + Λ0²), Λ = Λ0/(Θ0² + Λ0²).
    ``focus_m`` = +inf is a collimated beam.  Returns a dict with keys theta0, lambda0, w_m, theta, lam.
    """
    k = wavenumber(wavelength_m)
    L = _f64(range_m)
    w0 = _f64(w0_m)
    theta0 = 1.0 - L / _f64(focus_m)
    lambda0 = 2.0 * L / (k * w0**2)
    den = theta0**2 + lambda0**2
    return {"theta0": theta0, "lambda0": lambda0, "w_m": w0 * np.sqrt(den),
            "theta": theta0 / den, "lam": lambda0 / den}


def long_term_beam_radius(w_m, rytov_plane, lam, *, rho0_spherical_m=None, wavelength_m=None, range_m=None,
                          method="weak"):
    """Long-term (turbulence-broadened) 1/e² radius W_LT [m] (docs/theory.md §4, paper §3.4 A).

    ``"weak"``:   W_LT = W √(1 + 1.33 σ_R² Λ^(5/6))  (Andrews & Phillips, σ_R² Λ^(5/6) ≲ 1).
    ``"strong"``: W_LT² = W² + 2 (2L/(k ρ0,sp))²   (needs rho0_spherical_m, wavelength_m, range_m).
    """
    w = _f64(w_m)
    if method == "weak":
        return w * np.sqrt(1.0 + 1.33 * _f64(rytov_plane) * _f64(lam) ** (5.0 / 6.0))
    if method == "strong":
        k = wavenumber(wavelength_m)
        rho0 = _f64(rho0_spherical_m)
        with np.errstate(divide="ignore"):
            spread = np.where(np.isfinite(rho0), 2.0 * _f64(range_m) / (k * rho0), 0.0)
        return np.sqrt(w**2 + 2.0 * spread**2)
    raise ValueError("method must be 'weak' or 'strong'")


def beam_wander_variance(cn2_m_23, range_m, w0_m, focus_m=np.inf):
    """Two-axis beam-wander variance ⟨r_c²⟩ [m²] (docs/theory.md §4, paper §3.4 D).

    Chosen definition (Andrews & Phillips, infinite outer scale):
        ⟨r_c²⟩ = 2.42 Cn² L³ W0^(−1/3) ₂F₁(1/3, 1; 4; 1 − |Θ0|),  Θ0 = 1 − L/F0 (₂F₁ = 1 collimated).
    Per-axis variance is ⟨r_c²⟩/2.  Note a first-order centroid calculation / split-step simulation of a
    near-field beam gives a coefficient 1.52 instead of 2.42; the 2.42 form is an upper estimate.  The
    expression is independent of the wavelength; valid for L ≫ W0 and a transmitter W0 ≫ inner scale.
    """
    L = _f64(range_m)
    theta0 = 1.0 - L / _f64(focus_m)
    z = np.clip(1.0 - np.abs(theta0), -np.inf, 1.0)
    return 2.42 * _f64(cn2_m_23) * L**3 * _f64(w0_m) ** (-1.0 / 3.0) * hyp2f1(1.0 / 3.0, 1.0, 4.0, z)


def short_term_beam_radius(w_lt_m, r_c2_m2, w_m=None):
    """Short-term radius W_ST = √(W_LT² − ⟨r_c²⟩) [m] (docs/theory.md §4).

    If the free-space radius ``w_m`` is given, W_ST is clamped to ≥ W (the wander estimate can exceed the
    broadening term in weak turbulence); otherwise clamped to ≥ 0.
    """
    w2 = _f64(w_lt_m) ** 2 - _f64(r_c2_m2)
    floor = 0.0 if w_m is None else _f64(w_m) ** 2
    return np.sqrt(np.maximum(w2, floor))


# ----------------------------------------------------------------------------------------------------------
# §5 MTFs (ν_a in cycles/rad)
# ----------------------------------------------------------------------------------------------------------
def turbulence_mtf_long(nu_cyc_per_rad, wavelength_m, r0_m):
    """Long-exposure turbulence MTF = exp[−3.44 (λ ν_a / r0)^(5/3)] (docs/theory.md §5, paper §3.4 E).

    ν_a: angular spatial frequency [cycles/rad]; r0: Fried parameter (spherical for a target at range).
    Exactly 1 at ν = 0 and for r0 = +inf.
    """
    x = _f64(wavelength_m) * np.abs(_f64(nu_cyc_per_rad)) / _f64(r0_m)
    return np.exp(-3.44 * x ** (5.0 / 3.0))


def turbulence_mtf_short(nu_cyc_per_rad, wavelength_m, r0_m, aperture_diameter_m, alpha=1.0):
    """Short-exposure (tilt-removed) turbulence MTF (docs/theory.md §5).

    MTF_SE = exp{−3.44 (λν_a/r0)^(5/3) [1 − α (λν_a/D)^(1/3)]}, α = 1 near field, 0.5 far field.
    λν_a/D is clamped to ≤ 1 (beyond the diffraction cut-off the expression has no meaning; the total MTF
    is zero there through the diffraction MTF anyway).
    """
    lam = _f64(wavelength_m)
    nu = np.abs(_f64(nu_cyc_per_rad))
    u = np.minimum(lam * nu / _f64(aperture_diameter_m), 1.0)
    x = lam * nu / _f64(r0_m)
    return np.exp(-3.44 * x ** (5.0 / 3.0) * (1.0 - alpha * u ** (1.0 / 3.0)))


def diffraction_mtf(nu_cyc_per_rad, wavelength_m, aperture_diameter_m):
    """Incoherent diffraction MTF of a circular aperture (docs/theory.md §5).

    (2/π)[acos u − u √(1 − u²)], u = λ ν_a / D, zero for u ≥ 1.
    """
    u = np.clip(_f64(wavelength_m) * np.abs(_f64(nu_cyc_per_rad)) / _f64(aperture_diameter_m), 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(u) - u * np.sqrt(1.0 - u * u))


def pixel_mtf(nu_cyc_per_m, pixel_pitch_m):
    """Pixel (square aperture of width a) MTF |sinc(a ν)| along one axis (docs/theory.md §5); ν in cycles/m."""
    return np.abs(np.sinc(_f64(pixel_pitch_m) * _f64(nu_cyc_per_m)))
