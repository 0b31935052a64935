"""Random turbulence realisations: scintillation patterns, beam wander, turbulence blur (paper §3.4 B, D, E).

docs/theory.md §11 (exact FFT scintillation generator), §3 (pdfs), §4 (wander), §5 (MTFs).

Patterns are defined in metres on the target plane, on a periodic grid whose pitch is a fraction of the
correlation radius, independent of the receiver resolution; :meth:`ScintillationPattern.sample` evaluates
them at arbitrary target-plane points.  All randomness comes from a ``numpy.random.Generator`` argument.

Gaussian random fields
    A zero-mean field g with a prescribed isotropic correlation ρ_g(r) is made by filtering white Gaussian
    noise w on an N_y × N_x periodic grid:  g = IDFT( √P · DFT(w) ),  P = DFT(ρ_g sampled at the
    minimum-image distances).  Then Cov(g_i, g_j) = ρ_g(r_ij) exactly (circulant covariance), and var(g) = 1
    exactly in expectation because P is normalised so that IDFT(P)[0] = 1.  Where P has (tiny) negative
    values they are set to 0 before the normalisation (the correlation is then the nearest valid one).

Marginal transforms
    Each intensity field is a pointwise transform of such a g, so its one-point pdf is exact; the
    correlation ρ_g is chosen so that the *intensity* correlation has the wanted shape (see below).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial.hermite_e import hermegauss
from scipy.special import gammainccinv, gammaincinv, ndtr, ndtri

from . import turbulence as tb
from . import wave_optics as wo
from .derived import derived_turbulence
from ..lazy import lazy_module

sfft = lazy_module("scipy.fft")  # SciPy's FFT, imported at its first use (core/lazy.py)

PATTERN_MODELS = ("auto", "lognormal", "gamma_gamma", "gamma_lognormal")


# ----------------------------------------------------------------------------------------------------------
# Gaussian random field with a prescribed correlation
# ----------------------------------------------------------------------------------------------------------
def periodic_distances(shape, pitch_m):
    """Minimum-image distances [m] from node (0, 0) on a periodic grid of ``shape`` (ny, nx)."""
    ny, nx = shape
    y = np.fft.fftfreq(ny, 1.0 / ny) * float(pitch_m)
    x = np.fft.fftfreq(nx, 1.0 / nx) * float(pitch_m)
    return np.hypot(y[:, None], x[None, :])


def field_spectrum(shape, pitch_m, correlation):
    """Half-plane (rfft2) filter power P for :func:`gaussian_random_field` (see module docstring).

    ``correlation(r_m)`` must return ρ_g(r) with ρ_g(0) = 1.  Returns (P, clipped_fraction) where
    clipped_fraction is the fraction of spectral power that was negative and set to zero.
    """
    ny, nx = shape
    # the correlation is evaluated on one quadrant of minimum-image distances and mirrored (4× fewer calls)
    qy, qx = ny // 2 + 1, nx // 2 + 1
    quad = correlation(np.hypot(np.arange(qy)[:, None] * float(pitch_m), np.arange(qx)[None, :] * float(pitch_m)))
    iy = np.minimum(np.arange(ny), ny - np.arange(ny))
    ix = np.minimum(np.arange(nx), nx - np.arange(nx))
    rho = quad[iy[:, None], ix[None, :]]
    p = sfft.rfft2(rho).real
    neg = -p[p < 0.0].sum()
    tot = np.abs(p).sum()
    p = np.maximum(p, 0.0)
    # IDFT(P)[0] without a transform: the half-plane columns other than 0 (and nx/2) stand for two
    weight = np.full(p.shape[1], 2.0)
    weight[0] = 1.0
    if nx % 2 == 0:
        weight[-1] = 1.0
    var = float(p.sum(axis=0) @ weight) / (ny * nx)
    if not var > 0.0:
        raise ValueError("correlation has no positive spectral power on this grid")
    return p / var, (neg / tot if tot > 0 else 0.0)


def gaussian_random_field(shape, pitch_m, correlation, rng, spectrum=None):
    """Zero-mean, unit-variance Gaussian field on a periodic grid with correlation ρ_g(r) (docs/theory.md §11).

    Exact: Cov = ρ_g at the grid nodes (periodic minimum-image distance), var = 1 in expectation.  The grid
    should span ≥ ~8 correlation radii so that the periodic wrap does not alter ρ_g.  ``spectrum`` may be a
    precomputed :func:`field_spectrum` result (reuse for many realisations).
    """
    if spectrum is None:
        spectrum, _ = field_spectrum(shape, pitch_m, correlation)
    w = rng.standard_normal(shape)
    return sfft.irfft2(np.sqrt(spectrum) * sfft.rfft2(w), s=shape)


def gaussian_random_field_pair(shape, pitch_m, correlation_a, correlation_b, rng):
    """Two independent zero-mean, unit-variance Gaussian fields with correlations ρ_a and ρ_b (the same
    statistics as two :func:`gaussian_random_field` calls at about half the cost).

    Each field's white noise is drawn directly in the frequency domain: complex normal values W on the rfft2
    half plane with E|W|² = N (N = ny·nx, the spectrum of real white noise), g = irfft2(√P · W).  irfft2 uses
    the Hermitian part of the columns k_x = 0 (and n_x/2), which halves their power; those columns are drawn
    √2 larger, so that every mode has its power P exactly (one inverse transform per field, no forward one).
    """
    ny, nx = shape
    out = []
    for correlation in (correlation_a, correlation_b):
        p = field_spectrum(shape, pitch_m, correlation)[0]
        w = rng.standard_normal((2,) + p.shape)
        z = np.sqrt(p * (0.5 * ny * nx)) * (w[0] + 1j * w[1])
        z[:, 0] *= math.sqrt(2.0)
        if nx % 2 == 0:
            z[:, -1] *= math.sqrt(2.0)
        out.append(sfft.irfft2(z, s=shape))
    return out[0], out[1]


# ----------------------------------------------------------------------------------------------------------
# Log-normal pattern (weak turbulence, seed eq. 3-5)
# ----------------------------------------------------------------------------------------------------------
def gaussian_g_width(cell_radius_m, sigma2_lnI):
    """Closed-form width a of a Gaussian ρ_g = exp(−r²/a²) giving an intensity 1/e radius ρ_l (docs/theory.md §11).

    a = ρ_l / √(−ln(ln(1 + σ_I² e⁻¹)/σ²)), σ_I² = e^(σ²) − 1; a → ρ_l as σ² → 0.
    """
    s2 = np.asarray(sigma2_lnI, dtype=np.float64)
    return np.asarray(cell_radius_m, dtype=np.float64) / np.sqrt(-np.log(np.log1p(np.expm1(s2) / math.e) / s2))


def lognormal_g_correlation(sigma2_lnI, cell_radius_m, correlation="exact"):
    """ρ_g(r) for the log-normal generator (docs/theory.md §11).

    ``"exact"``: ρ_g = ln(1 + σ_I² b_I)/σ² with b_I(r) = exp(−r²/ρ_l²): the intensity covariance is then
    exactly σ_I² · Gaussian of 1/e radius ρ_l.  ``"gaussian"``: ρ_g = exp(−r²/a²) with the closed-form a of
    :func:`gaussian_g_width`: the intensity correlation (e^(σ²ρ_g) − 1)/σ_I² has its 1/e point exactly at ρ_l
    but is only approximately Gaussian (exact as σ² → 0).
    """
    s2 = float(sigma2_lnI)
    rl = float(cell_radius_m)
    if correlation == "exact":
        si = math.expm1(s2)
        return lambda r: np.log1p(si * np.exp(-(r / rl) ** 2)) / s2
    if correlation == "gaussian":
        a = float(gaussian_g_width(rl, s2))
        return lambda r: np.exp(-(r / a) ** 2)
    raise ValueError("correlation must be 'exact' or 'gaussian'")


def lognormal_pattern(shape, pitch_m, sigma2_lnI, cell_radius_m, rng, *, mean=1.0, correlation="exact",
                      spectrum=None):
    """Log-normal scintillation pattern S = S_av exp(σ g − σ²/2) on a periodic grid (docs/theory.md §11, eq. 3-5).

    ``shape`` (ny, nx) nodes of ``pitch_m`` metres; ``sigma2_lnI`` = σ² the log-intensity variance (use the
    all-regime :func:`~core.atmosphere.turbulence.log_intensity_variance`); ``cell_radius_m`` = ρ_l, the 1/e
    radius of the intensity correlation (eq. 3-6).  Exact: pdf of every node (eq. 3-5), mean S_av in
    expectation, SI = e^(σ²) − 1; with ``correlation="exact"`` also the Gaussian intensity covariance.
    σ² = 0 returns exactly S_av everywhere.  Use pitch ≤ ρ_l/4 and a grid ≥ 8 ρ_l wide.
    """
    s2 = float(sigma2_lnI)
    if s2 <= 0.0 or cell_radius_m <= 0.0:
        return np.full(shape, float(mean))
    g = gaussian_random_field(shape, pitch_m, lognormal_g_correlation(s2, cell_radius_m, correlation), rng,
                              spectrum)
    return mean * np.exp(math.sqrt(s2) * g - 0.5 * s2)


# ----------------------------------------------------------------------------------------------------------
# Gamma-gamma pattern (moderate / strong turbulence)
# ----------------------------------------------------------------------------------------------------------
def unit_gamma_from_gaussian(g, shape_param):
    """Translate a standard normal field into a unit-mean gamma(shape α, scale 1/α) field, exact marginal.

    X = F_Γ⁻¹(Φ(g))/α, evaluated with the upper-tail inverse for g > 0 (no loss of precision in the tail).
    α = +inf gives X ≡ 1.
    """
    a = float(shape_param)
    g = np.asarray(g, dtype=np.float64)
    if not math.isfinite(a):
        return np.ones_like(g)
    out = np.empty_like(g)
    pos = g > 0.0
    out[pos] = gammainccinv(a, ndtr(-g[pos]))
    out[~pos] = gammaincinv(a, ndtr(g[~pos]))
    return out / a


#: Nodes of the tabulated translation ln X(g) (:func:`unit_gamma_transform`): uniform on [−8.5, 8.5].
_TRANSFORM_NODES = np.linspace(-8.5, 8.5, 4097)
_TRANSFORM_STEP = 17.0 / 4096


@functools.lru_cache(maxsize=64)
def _log_unit_gamma_table(shape_param):
    return np.log(unit_gamma_from_gaussian(_TRANSFORM_NODES, shape_param))


def unit_gamma_transform(g, shape_param):
    """Fast :func:`unit_gamma_from_gaussian`: ln X tabulated on 4097 nodes of g ∈ [−8.5, 8.5] (exact
    inverse there) and interpolated linearly, then exponentiated.  ln X is smooth in g (≈ −g²/(2α) in the
    lower tail), so the relative error is < 1e-5 for α ≥ 0.5 (test); |g| > 8.5 (probability 2e-17) is
    clamped.  Used by the pattern generators; α = inf gives 1."""
    a = float(shape_param)
    g = np.asarray(g, dtype=np.float64)
    if not math.isfinite(a):
        return np.ones_like(g)
    tab = _log_unit_gamma_table(a)
    u = np.clip((g - _TRANSFORM_NODES[0]) * (1.0 / _TRANSFORM_STEP), 0.0, len(tab) - 1.000001)
    i = u.astype(np.intp)
    f = u - i
    return np.exp(tab[i] * (1.0 - f) + tab[i + 1] * f)


@functools.lru_cache(maxsize=64)
def _gamma_translation_correlation(shape_param, n_terms=40, n_nodes=160):
    """Tabulated map ρ_g → corr(X1, X2) for X = unit_gamma_from_gaussian(g, α) (Hermite expansion).

    corr = Σ_{n≥1} d_n² ρ^n / Σ d_n², d_n = E[h(Z) ψ_n(Z)] with ψ_n the orthonormal Hermite polynomials,
    by Gauss–Hermite quadrature.  Returns (rho_g_table, corr_table) on ρ_g ∈ [−1, 1] (the nodes on [0, 1]
    are those of a 4001-point grid), corr made non-decreasing (a negative target beyond the reachable minimum
    maps to ρ_g = −1).
    """
    z, w = hermegauss(n_nodes)
    w = w / math.sqrt(2.0 * math.pi)
    h = unit_gamma_from_gaussian(z, shape_param)
    psi_prev = np.ones_like(z)
    psi = z.copy()
    d = []
    for n in range(1, n_terms + 1):
        d.append(np.sum(w * h * psi))
        psi_prev, psi = psi, (z * psi - math.sqrt(n) * psi_prev) / math.sqrt(n + 1)
    d2 = np.asarray(d) ** 2
    rho = np.linspace(-1.0, 1.0, 8001)
    corr = (rho[:, None] ** np.arange(1, n_terms + 1)[None, :]) @ d2 / d2.sum()
    return rho, np.maximum.accumulate(corr)


def gamma_factor_g_correlation(shape_param, radius_m=None, target=None):
    """ρ_g(r) such that X = unit_gamma_from_gaussian(g, α) has correlation exactly exp(−r²/radius²), or
    ``target(r)`` when given (a correlation function with target(0) = 1, in [−1, 1]).

    Inverse of the Hermite-expansion map (translation fields lose correlation, so |ρ_g| ≥ |target|).
    """
    rho_tab, corr_tab = _gamma_translation_correlation(float(shape_param))
    if target is None:
        rad = float(radius_m)
        target = lambda r: np.exp(-(r / rad) ** 2)  # noqa: E731
    return lambda r: np.interp(target(r), corr_tab, rho_tab)


def gamma_gamma_covariance(r_m, alpha, beta, large_scale_radius_m, small_scale_radius_m):
    """Normalised intensity covariance B_I(r)/SI of :func:`gamma_gamma_pattern` (exact for that model).

    Cov(I1, I2) = (1 + b_X/α)(1 + b_Y/β) − 1 with b_X, b_Y Gaussian of 1/e radii ρ_X, ρ_Y; divided by SI.
    """
    r = np.asarray(r_m, dtype=np.float64)
    ia = 0.0 if not np.isfinite(alpha) else 1.0 / alpha
    ib = 0.0 if not np.isfinite(beta) else 1.0 / beta
    bx = np.exp(-(r / large_scale_radius_m) ** 2)
    by = np.exp(-(r / small_scale_radius_m) ** 2)
    si = (1 + ia) * (1 + ib) - 1
    return ((1 + ia * bx) * (1 + ib * by) - 1) / si


def gamma_gamma_pattern(shape, pitch_m, alpha, beta, large_scale_radius_m, small_scale_radius_m, rng, *,
                        mean=1.0, targets=(None, None)):
    """Gamma-gamma scintillation pattern I = S_av · X · Y on a periodic grid (docs/theory.md §3, §11).

    X (shape α, large-scale eddies) and Y (shape β, small-scale eddies) are independent unit-mean gamma
    fields, each a translated Gaussian field (:func:`unit_gamma_from_gaussian`) whose Gaussian correlation
    is solved so that the gamma field itself has a Gaussian correlation of 1/e radius ρ_X resp. ρ_Y.

    Exact: the one-point pdf (product of independent unit-mean gammas = gamma-gamma), the mean, the
    SI = (1 + 1/α)(1 + 1/β) − 1, and the covariance of each factor (up to the Hermite truncation, < 1e-3,
    and the clipping of negative spectral power).  Modelling choice (approximate physics): the two-scale
    Gaussian correlations with ρ_Y = eq. 3-6 cell radius and ρ_X = (L/k)/ρ_Y (see
    :func:`~core.atmosphere.turbulence.large_scale_radius`); the total intensity covariance is then
    :func:`gamma_gamma_covariance`.  The joint (multi-point) statistics are those of a translation field,
    not of a propagated optical field.  ``targets`` = (b_X, b_Y) correlation functions, when given, replace the
    Gaussian ones (the wave-optics statistics give both factors the correlation solved from the tabulated
    covariance, :func:`~core.atmosphere.wave_optics.shared_factor_correlation`).  The two Gaussian fields are drawn in the
    frequency domain, one inverse transform each (:func:`gaussian_random_field_pair`); the gamma translation is tabulated
    (:func:`unit_gamma_transform`, relative error < 1e-5).
    """
    ga, gb = gaussian_random_field_pair(shape, pitch_m,
                                        gamma_factor_g_correlation(alpha, large_scale_radius_m, targets[0]),
                                        gamma_factor_g_correlation(beta, small_scale_radius_m, targets[1]), rng)
    return mean * unit_gamma_transform(ga, alpha) * unit_gamma_transform(gb, beta)


def gamma_lognormal_pattern(shape, pitch_m, alpha, sigma2, correlation_x, correlation_y, rng, *, mean=1.0):
    """Gamma × log-normal pattern I = S_av · X · Y on a periodic grid (the wave-optics statistics' default).

    X: unit-mean gamma of shape α, a translation field whose own correlation is ``correlation_x(r)`` (ρ_g
    solved by the Hermite map); Y = exp(σ g − σ²/2) with g of correlation ``correlation_y(r)`` (ρ_g itself; for
    Y to share X's normalised covariance b, ρ_g = ln(1 + (e^(σ²) − 1) b)/σ²).  Exact: the one-point law (product
    of independent unit-mean gamma and log-normal), the mean, SI = (1 + 1/α) e^(σ²) − 1 and
    var(ln I) = ψ₁(α) + σ²; the covariance up to the Hermite truncation and clipped negative spectral power.
    """
    gx = gamma_factor_g_correlation(alpha, None, correlation_x)
    if sigma2 > 0.0:
        ga, gb = gaussian_random_field_pair(shape, pitch_m, gx, correlation_y, rng)
        y = np.exp(math.sqrt(sigma2) * gb - 0.5 * sigma2)
    else:
        ga, y = gaussian_random_field(shape, pitch_m, gx, rng), 1.0
    return mean * unit_gamma_transform(ga, alpha) * y


def _gamma_factor(shape, pitch_m, shape_param, radius_m, rng, target=None):
    if not math.isfinite(float(shape_param)):
        return np.ones(shape)
    g = gaussian_random_field(shape, pitch_m, gamma_factor_g_correlation(shape_param, radius_m, target), rng)
    return unit_gamma_transform(g, shape_param)


# ----------------------------------------------------------------------------------------------------------
# The seed paper's speckle method made exact (docs/theory.md §11, first two bullets) — for comparison only
# ----------------------------------------------------------------------------------------------------------
def speckle_correlation_radius_px(n, window_radius_px):
    """1/e radius N/(π w) [output pixels] of the intensity correlation of the seed FFT speckle (§11)."""
    return n / (np.pi * np.asarray(window_radius_px, dtype=np.float64))


def seed_speckle_lognormal_pattern(n, window_radius_px, sigma2_lnI, rng, *, mean=1.0):
    """Seed §3.4.1 generator (Harris/Letalick) with the exact normal-score transform (docs/theory.md §11).

    Uniform random phase × TEM00 window exp(−r²/w²) on an n × n grid, FFT → fully developed speckle I
    (exponential pdf, intensity 1/e correlation radius N/(πw) px); g = −Φ⁻¹(exp(−I/Ī)) is standard normal;
    S = S_av exp(σ g − σ²/2) is exactly log-normal.  The correlation of g (hence of S) is narrower than the
    speckle's (about 0.924 × the intensity radius for its 1/e point) and not Gaussian — prefer
    :func:`lognormal_pattern`.
    """
    s2 = float(sigma2_lnI)
    if s2 <= 0.0:
        return np.full((n, n), float(mean))
    c = np.fft.fftfreq(n, 1.0 / n)
    win = np.exp(-(c[:, None] ** 2 + c[None, :] ** 2) / float(window_radius_px) ** 2)
    field_ = np.fft.fft2(win * np.exp(2j * np.pi * rng.random((n, n))))
    i_mean = np.sum(win**2)                       # E|U|² for unit random phasors
    u = np.exp(-(field_.real**2 + field_.imag**2) / i_mean)
    u = np.clip(u, np.finfo(float).tiny, 1.0 - np.finfo(float).epsneg)   # guard I = 0 (u = 1)
    g = -ndtri(u)
    return mean * np.exp(math.sqrt(s2) * g - 0.5 * s2)


# ----------------------------------------------------------------------------------------------------------
# A pattern in target-plane metres, sampled at arbitrary points
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ScintillationPattern:
    """A periodic intensity pattern on the target plane (unit mean when ``mean`` = 1).

    ``values[j, i]`` is the pattern at x = origin_m[0] + i·pitch_m, y = origin_m[1] + j·pitch_m.  The grid is
    periodic with period (nx·pitch, ny·pitch); :meth:`sample` wraps around, so any point is defined.
    """

    values: np.ndarray
    pitch_m: float
    origin_m: tuple = (0.0, 0.0)
    model: str = "none"
    params: dict = field(default_factory=dict)

    def sample(self, x_m, y_m, method="linear"):
        """Pattern at target-plane points (arrays of any shape, broadcast); see :func:`sample_pattern`."""
        return sample_pattern(self, x_m, y_m, method)


def sample_pattern(pattern, x_m, y_m, method="linear"):
    """Evaluate a :class:`ScintillationPattern` at target-plane points [m], periodic wrap (vectorised).

    ``"linear"``: bilinear interpolation — smooth, but it averages neighbouring nodes: the SI of points
    sampled uniformly is ≈ 4 % low at pitch ρ/4 and ≈ 1 % low at pitch ρ/8 (the default of
    :func:`make_scintillation_pattern`); the pdf is exact only at the nodes.  ``"nearest"``: nearest node,
    exact pdf everywhere, blocky at the pitch scale.
    """
    v = pattern.values
    ny, nx = v.shape
    u = (np.asarray(x_m, dtype=np.float64) - pattern.origin_m[0]) / pattern.pitch_m
    w = (np.asarray(y_m, dtype=np.float64) - pattern.origin_m[1]) / pattern.pitch_m
    if method == "nearest":
        return v[np.mod(np.rint(w).astype(np.int64), ny), np.mod(np.rint(u).astype(np.int64), nx)]
    if method != "linear":
        raise ValueError("method must be 'linear' or 'nearest'")
    u0 = np.floor(u)
    w0 = np.floor(w)
    fu = u - u0
    fw = w - w0
    i0 = np.mod(u0.astype(np.int64), nx)
    j0 = np.mod(w0.astype(np.int64), ny)
    i1 = np.mod(i0 + 1, nx)
    j1 = np.mod(j0 + 1, ny)
    return ((1 - fw) * ((1 - fu) * v[j0, i0] + fu * v[j0, i1])
            + fw * ((1 - fu) * v[j1, i0] + fu * v[j1, i1]))


def make_scintillation_pattern(extent_m, cn2_m_23, wavelength_m, range_m, rng, *, wave="spherical",
                               model="auto", lognormal_max_rytov=tb.WEAK_LIMIT, samples_per_cell=8,
                               max_grid_px=4096, correlation="exact", statistics="wave_optics",
                               inner_scale_m=0.0):
    """Scintillation pattern covering a target-plane footprint (paper §3.4 B).

    ``extent_m`` = (x_min, x_max, y_min, y_max) of the footprint [m]; ``wave`` chooses the plane/spherical
    statistics (spherical suits a diverging ladar beam).  ``statistics`` picks where the statistics come from:

    * ``"wave_optics"`` (default): SI, σ²_lnI and the covariance shape C(r) of our split-step wave-optics
      table (:mod:`core.atmosphere.wave_optics`, inner scale ``inner_scale_m``).  ``model="auto"`` is
      ``"gamma_lognormal"``: I = X·Y, X gamma (shape α) and Y log-normal (σ²) fitted to SI and σ²_lnI
      (:func:`~core.atmosphere.wave_optics.gamma_lognormal_fit`; gamma-gamma cannot reach the wave-optics σ²_lnI
      in strong turbulence); X and Y share the normalised covariance b(r) solved from
      (1 + b v_X)(1 + b v_Y) − 1 = SI·C(r), so the intensity covariance is the tabulated one (a Gaussian
      large-scale X would add spectral power at zero frequency that the wave-optics covariance, whose integral
      is ≈ 0 by energy conservation, does not have).  ``"gamma_gamma"``: α, β from
      :func:`~core.atmosphere.wave_optics.gamma_gamma_fit`, same shared covariance.  ``"lognormal"``: σ² = ln(1 + SI),
      ρ_g = ln(1 + SI·C)/σ² (exact SI and covariance; σ²_lnI then differs from wave optics).
    * ``"paper"``: the paper's formulas (:func:`~core.atmosphere.derived.derived_turbulence`): ``auto`` is
      log-normal (eq. 3-5, Gaussian covariance of radius ρ_l, eq. 3-6) when σ_R² < ``lognormal_max_rytov``,
      else gamma-gamma (Gaussian scales ρ_l and (L/k)/ρ_l).

    Pitch = smallest correlation radius / ``samples_per_cell``; the grid is ≥ 8 of the largest correlation
    radius and covers the footprint unless that needs more than ``max_grid_px`` per side, in which case the
    periodic tile (still ≥ hundreds of cells) repeats over the footprint.  When the gamma-gamma scales are too
    far apart for one grid (8 ρ_X > max_grid_px · pitch) a :class:`ProductPattern` of the X and Y factors on
    their own grids is returned instead (same ``sample`` interface, no ``values``).  Cn² = 0 returns the
    constant pattern 1.
    """
    if model not in PATTERN_MODELS:
        raise ValueError(f"model must be one of {PATTERN_MODELS}")
    if model == "gamma_lognormal" and statistics != "wave_optics":
        raise ValueError("model 'gamma_lognormal' needs statistics='wave_optics' (it is fitted to its σ²_lnI)")
    x0, x1, y0, y1 = (float(e) for e in extent_m)
    d = derived_turbulence(cn2_m_23, wavelength_m, range_m, wave=wave, lognormal_max_rytov=lognormal_max_rytov,
                              statistics=statistics, inner_scale_m=inner_scale_m)
    if d["pdf_model"] == "none" or d["sigma2_lnI"] <= 0.0:
        return ScintillationPattern(np.ones((1, 1)), max(x1 - x0, y1 - y0, 1.0), (x0, y0), "none", d)
    chosen = d["pdf_model"] if model == "auto" else model
    a = d["gamma_alpha"] if d["gamma_alpha"] is not None else np.inf
    b = d["gamma_beta"] if d["gamma_beta"] is not None else np.inf
    r_small = d["cell_radius_m"]
    target_x = target_y = g_corr = None
    r_large = r_small if chosen == "lognormal" else d["large_scale_radius_m"]
    if statistics == "wave_optics":
        st = wo.statistics(cn2_m_23, wavelength_m, range_m, wave, inner_scale_m)
        cov = wo.covariance_function(st)
        si = st["scintillation_index"]
        lags, c = st["lags_m"], st["covariance"]
        # grid ≥ 8 r_large ≥ 3 × the lag beyond which |C| < 0.02 (the covariance's tail fits in the period)
        r_large = max(r_small, 3.0 * float(lags[np.nonzero(np.abs(c) >= 0.02)[0][-1]]) / 8.0)
        if chosen == "lognormal":
            s2 = math.log1p(si)
            g_corr = lambda r: np.log1p(si * cov(r)) / s2  # noqa: E731
        elif chosen == "gamma_gamma":
            a, b, _ = wo.gamma_gamma_fit(si, st["sigma2_lnI"])
            d = dict(d, pattern_gamma_alpha=a, pattern_gamma_beta=b)
            target_x = target_y = wo.shared_factor_correlation(cov, si, 1.0 / a, 1.0 / b)
        else:
            s2 = d["lognormal_sigma2"]
            target_x = wo.shared_factor_correlation(cov, si, 1.0 / a, math.expm1(s2))
            if s2 > 0.0:
                target_y = lambda r: np.log1p(math.expm1(s2) * target_x(r)) / s2  # noqa: E731
    pitch = r_small / float(samples_per_cell)
    if chosen == "gamma_gamma" and target_x is None and 8.0 * r_large / pitch > max_grid_px - 2:
        # scales too far apart for one grid: X and Y on their own grids (each at its radius/samples_per_cell)
        px = r_large / float(samples_per_cell)
        fx = _grid_for(extent_m, px, r_large, max_grid_px)
        fy = _grid_for(extent_m, pitch, r_small, max_grid_px)
        xf = ScintillationPattern(_gamma_factor(fx[0], px, a, r_large, rng), px, (x0, y0), "gamma_X")
        yf = ScintillationPattern(_gamma_factor(fy[0], pitch, b, r_small, rng, target_y), pitch, (x0, y0),
                                  "gamma_Y")
        params = dict(d, pattern_model=chosen, pitch_m=[px, pitch], grid_shape=[list(fx[0]), list(fy[0])],
                      periodic_tile_m=[[fx[0][1] * px, fx[0][0] * px], [fy[0][1] * pitch, fy[0][0] * pitch]],
                      tiled=bool(fx[1] or fy[1]))
        return ProductPattern((xf, yf), chosen, params)
    shape, tiled = _grid_for(extent_m, pitch, r_large, max_grid_px)
    if chosen == "lognormal" and g_corr is not None:
        s2 = math.log1p(d["scintillation_index"])
        g = gaussian_random_field(shape, pitch, g_corr, rng)
        vals = np.exp(math.sqrt(s2) * g - 0.5 * s2)
    elif chosen == "lognormal":
        vals = lognormal_pattern(shape, pitch, d["sigma2_lnI"], r_small, rng, correlation=correlation)
    elif chosen == "gamma_lognormal":
        vals = gamma_lognormal_pattern(shape, pitch, a, d["lognormal_sigma2"], target_x, target_y, rng)
    else:
        vals = gamma_gamma_pattern(shape, pitch, a, b, r_large, r_small, rng, targets=(target_x, target_y))
    params = dict(d, pattern_model=chosen, pitch_m=pitch, grid_shape=list(shape),
                  periodic_tile_m=[shape[1] * pitch, shape[0] * pitch], tiled=tiled)
    return ScintillationPattern(vals, pitch, (x0, y0), chosen, params)


def _grid_for(extent_m, pitch, r_large, max_grid_px):
    """(ny, nx) covering the extent and ≥ 8 r_large, FFT-friendly, capped at max_grid_px; and 'tiled'."""
    x0, x1, y0, y1 = (float(e) for e in extent_m)
    n = []
    for span in (y1 - y0, x1 - x0):
        n.append(min(sfft.next_fast_len(int(math.ceil(max(8.0 * r_large, span) / pitch)) + 2, real=True),
                     max_grid_px))
    tiled = max(x1 - x0, y1 - y0) / pitch + 2 > max_grid_px
    return (n[0], n[1]), bool(tiled)


@dataclass(frozen=True)
class ProductPattern:
    """Product of independent patterns on their own grids (gamma-gamma with widely separated scales:
    X on a coarse grid at ρ_X/8, Y on a fine grid at ρ_Y/8).  Same ``sample`` interface."""

    factors: tuple
    model: str = "gamma_gamma"
    params: dict = field(default_factory=dict)

    def sample(self, x_m, y_m, method="linear"):
        out = self.factors[0].sample(x_m, y_m, method)
        for f in self.factors[1:]:
            out = out * f.sample(x_m, y_m, method)
        return out


# ----------------------------------------------------------------------------------------------------------
# Beam wander (paper §3.4 D)
# ----------------------------------------------------------------------------------------------------------
def beam_wander_offsets(r_c2_m2, rng, size=None):
    """Random beam-centroid displacements [m], shape (*size, 2) (x, y), per-axis variance ⟨r_c²⟩/2 (§4).

    Zero-mean Gaussian, independent axes and pulses (pulses further apart than the wander correlation time
    L/(wind speed)).  ⟨r_c²⟩ from :func:`~core.atmosphere.turbulence.beam_wander_variance`; 0 gives 0.
    """
    sd = math.sqrt(max(float(r_c2_m2), 0.0) / 2.0)
    shp = (2,) if size is None else (tuple(np.atleast_1d(size)) + (2,))
    return sd * rng.standard_normal(shp)


# ----------------------------------------------------------------------------------------------------------
# Turbulence blur (paper §3.4 E)
# ----------------------------------------------------------------------------------------------------------
def turbulence_mtf_grid(shape, pixel_pitch_rad, wavelength_m, r0_m, *, exposure="long",
                        aperture_diameter_m=None, alpha=1.0):
    """Turbulence MTF on the rfft2 frequency grid of an image ``shape`` (ny, nx) (docs/theory.md §5).

    ``pixel_pitch_rad``: angular pixel pitch (scalar or (py, px)); frequencies in cycles/rad.
    """
    py, px = (pixel_pitch_rad, pixel_pitch_rad) if np.ndim(pixel_pitch_rad) == 0 else pixel_pitch_rad
    fy = np.fft.fftfreq(shape[0], d=float(py))
    fx = np.fft.rfftfreq(shape[1], d=float(px))
    nu = np.hypot(fy[:, None], fx[None, :])
    if exposure == "long":
        return tb.turbulence_mtf_long(nu, wavelength_m, r0_m)
    if exposure == "short":
        if aperture_diameter_m is None:
            raise ValueError("short exposure needs aperture_diameter_m")
        return tb.turbulence_mtf_short(nu, wavelength_m, r0_m, aperture_diameter_m, alpha)
    raise ValueError("exposure must be 'long' or 'short'")


def turbulence_blur(image, pixel_pitch_rad, wavelength_m, r0_m, *, exposure="long", aperture_diameter_m=None,
                    alpha=1.0, pad_px=None, pad_mode="constant"):
    """Blur an image (last two axes) with the turbulence MTF by FFT convolution (paper §3.4 E; docs/theory.md §5).

    ``pixel_pitch_rad``: angular pixel pitch of the image; ``r0_m``: Fried parameter (spherical for a
    target at range).  MTF(0) = 1, so the energy of the padded image is conserved (light spread beyond the
    border is lost from the returned crop, as in a real camera).  The image is padded by ``pad_px``
    (default 32 λ/r0 in pixels, ≥ 2, ≤ the image size: the Kolmogorov PSF halo decays only as θ^(−11/3), a
    3 λ/r0 pad lets ~1e-4 of a border spot's energy wrap to the opposite border, 32 λ/r0 < 1e-6) with ``pad_mode`` ("constant" = zeros, or any
    ``numpy.pad`` mode such as "reflect") to avoid wrap-around.  r0 = +inf (no turbulence) returns a copy.
    """
    img = np.asarray(image, dtype=np.float64)
    if not np.isfinite(r0_m) or r0_m <= 0.0:
        if np.isfinite(r0_m):
            raise ValueError("r0_m must be > 0")
        return img.copy()
    py, px = (pixel_pitch_rad, pixel_pitch_rad) if np.ndim(pixel_pitch_rad) == 0 else pixel_pitch_rad
    ny, nx = img.shape[-2:]
    if pad_px is None:
        spread = 32.0 * wavelength_m / r0_m
        pad = (int(min(max(math.ceil(spread / py), 2), ny)), int(min(max(math.ceil(spread / px), 2), nx)))
    else:
        pad = (int(pad_px), int(pad_px))
    fy_len = sfft.next_fast_len(ny + 2 * pad[0], real=True)
    fx_len = sfft.next_fast_len(nx + 2 * pad[1], real=True)
    extra_y, extra_x = fy_len - ny - 2 * pad[0], fx_len - nx - 2 * pad[1]
    widths = [(0, 0)] * (img.ndim - 2) + [(pad[0], pad[0] + extra_y), (pad[1], pad[1] + extra_x)]
    padded = np.pad(img, widths, mode=pad_mode)
    mtf = turbulence_mtf_grid((fy_len, fx_len), (py, px), wavelength_m, r0_m, exposure=exposure,
                              aperture_diameter_m=aperture_diameter_m, alpha=alpha)
    out = sfft.irfft2(sfft.rfft2(padded, axes=(-2, -1)) * mtf, s=(fy_len, fx_len), axes=(-2, -1))
    return out[..., pad[0]:pad[0] + ny, pad[1]:pad[1] + nx]
