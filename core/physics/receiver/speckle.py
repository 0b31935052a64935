"""Target speckle (docs/theory.md §7) and the optics / speckle MTFs (docs/theory.md §5).

Angular spatial frequency ν_a is in cycles/rad (image-plane ν = ν_a/f).  Pure, vectorized functions.
"""
from __future__ import annotations

import numpy as np
from scipy import special

from ...lazy import lazy_module

sfft = lazy_module("scipy.fft")  # SciPy's FFT, imported at its first use (core/lazy.py)


# ----------------------------------------------------------------------------------------------------------
# §5 MTFs
# ----------------------------------------------------------------------------------------------------------
def mtf_diffraction(nu_a, aperture_diameter_m, wavelength_m):
    """Diffraction-limited circular aperture (docs/theory.md §5): (2/π)[acos u − u√(1 − u²)], u = λν_a/D, 0 for
    u ≥ 1.  λ = 1.064 µm, D = 0.1 m: 0.6850 at u = 0.25, 0.3910 at u = 0.5."""
    u = np.abs(np.asarray(nu_a, dtype=np.float64)) * wavelength_m / aperture_diameter_m
    uc = np.minimum(u, 1.0)
    return np.where(u < 1.0, (2.0 / np.pi) * (np.arccos(uc) - uc * np.sqrt(1.0 - uc * uc)), 0.0)


def mtf_pixel(nu, pixel_size):
    """Pixel aperture |sinc(a ν)| (docs/theory.md §5), sinc(x) = sin(πx)/(πx).  a and ν in reciprocal units
    (m and cycles/m, or rad and cycles/rad).  a = 20 µm at 25 cycles/mm: 0.6366."""
    return np.abs(np.sinc(np.asarray(nu, dtype=np.float64) * pixel_size))


def mtf_speckle(nu_a, aperture_diameter_m, wavelength_m):
    """MTF_speckle (docs/theory.md §7): the speckle intensity power spectrum has the shape of the incoherent pupil
    MTF, i.e. the autocorrelation of the circular pupil (same function as :func:`mtf_diffraction`)."""
    return mtf_diffraction(nu_a, aperture_diameter_m, wavelength_m)


def mtf_optics(nu_a, aperture_diameter_m, wavelength_m, ifov_rad=None):
    """Total optics MTF = diffraction × pixel (docs/theory.md §5); the pixel term uses the angular pixel size
    (IFOV = pitch/f) so that ν_a stays in cycles/rad.  ``ifov_rad=None`` omits the pixel term."""
    m = mtf_diffraction(nu_a, aperture_diameter_m, wavelength_m)
    if ifov_rad is not None:
        m = m * mtf_pixel(nu_a, ifov_rad)
    return m


def optics_mtf_2d(shape, wavelength_m, aperture_diameter_m, ifov_x_rad, ifov_y_rad=None, pixel=True,
                  pad=(0, 0), alias=True, max_alias_orders=32):
    """Discrete optics transfer function on the ``rfft2`` grid of an (H + pad_y, W + pad_x) image whose
    pixel spacing is the IFOV (docs/theory.md §5): radial diffraction MTF × separable pixel sinc (cycles/pixel).

    ``alias=True`` (default) sums the continuous OTF over all aliases, Σ_k OTF(f + k), using the signed pixel
    sinc: its inverse DFT is exactly the (pixel-integrated, if ``pixel``) PSF sampled at the pixel centres,
    hence non-negative.  Without the pixel term the sum is normalised to 1 at f = 0 (energy conserved).
    For a diffraction cut-off below Nyquist this is identical to the plain product MTF.
    """
    ifov_y_rad = ifov_x_rad if ifov_y_rad is None else ifov_y_rad
    H, W = shape[0] + pad[0], shape[1] + pad[1]
    fy = sfft.fftfreq(H)[:, None]  # cycles/pixel
    fx = sfft.rfftfreq(W)[None, :]
    if not alias:
        m = mtf_diffraction(np.hypot(fx / ifov_x_rad, fy / ifov_y_rad), aperture_diameter_m, wavelength_m)
        if pixel:
            m = m * np.abs(np.sinc(fx)) * np.abs(np.sinc(fy))
        return m
    fcx = aperture_diameter_m / wavelength_m * ifov_x_rad  # diffraction cut-off, cycles/pixel
    fcy = aperture_diameter_m / wavelength_m * ifov_y_rad
    kx_max = min(int(np.ceil(fcx)) + 1, max_alias_orders)
    ky_max = min(int(np.ceil(fcy)) + 1, max_alias_orders)
    total = np.zeros((H, fx.shape[1]))
    norm = 0.0
    for ky in range(-ky_max, ky_max + 1):
        gy = fy + ky
        py = np.sinc(gy) if pixel else 1.0
        for kx in range(-kx_max, kx_max + 1):
            gx = fx + kx
            d = mtf_diffraction(np.hypot(gx / ifov_x_rad, gy / ifov_y_rad), aperture_diameter_m, wavelength_m)
            if not d.any():
                continue
            total += d * (py * np.sinc(gx) if pixel else 1.0)
            norm += float(mtf_diffraction(np.hypot(kx / ifov_x_rad, ky / ifov_y_rad), aperture_diameter_m,
                                          wavelength_m)) * (np.sinc(kx) * np.sinc(ky) if pixel else 1.0)
    return total / norm


def apply_mtf(image, mtf2d, axes=(0, 1), clamp_negative=False, workers=-1):
    """Blur ``image`` along two ``axes`` by a real, even 2-D MTF given on the rfft2 grid of those axes (docs/theory.md
    §5, paper §3.5: MTFs applied by convolution).  The FFT is periodic: pad the image first if wrap-around
    matters.  ``clamp_negative`` sets round-off negatives (ringing of a truncated MTF) to 0 and returns their
    count: ``(blurred, n_clamped)``; otherwise returns ``(blurred, 0)``.  Preserves float32."""
    a = np.asarray(image)
    dtype = np.float32 if a.dtype == np.float32 else np.float64
    ax = tuple(ax % a.ndim for ax in axes)
    shape = [a.shape[ax[0]], a.shape[ax[1]]]
    spec = sfft.rfftn(a, axes=ax, workers=workers)
    m = np.asarray(mtf2d)
    expand = [1] * a.ndim
    expand[ax[0]], expand[ax[1]] = m.shape
    spec *= m.reshape(expand).astype(spec.real.dtype)
    out = sfft.irfftn(spec, s=shape, axes=ax, workers=workers).astype(dtype, copy=False)
    n = 0
    if clamp_negative:
        neg = out < 0
        n = int(np.count_nonzero(neg))
        if n:
            out[neg] = 0
    return out, n


# ----------------------------------------------------------------------------------------------------------
# §7 speckle statistics
# ----------------------------------------------------------------------------------------------------------
def coherence_area_m2(wavelength_m, range_m, spot_diameter_m):
    """Speckle coherence area at the receiver A_c = (λR)²/(π d²/4) for a uniformly lit spot of diameter d
    (docs/theory.md §7)."""
    return (wavelength_m * range_m) ** 2 / (np.pi * spot_diameter_m ** 2 / 4.0)


def speckle_dof_approx(aperture_diameter_m, spot_diameter_m, wavelength_m, range_m):
    """M ≈ 1 + A_R/A_c (docs/theory.md §7).  S1: 341.5, S2: 2.027."""
    a_r = np.pi * aperture_diameter_m ** 2 / 4.0
    return 1.0 + a_r / coherence_area_m2(wavelength_m, range_m, spot_diameter_m)


def speckle_dof_exact(aperture_diameter_m, spot_diameter_m, wavelength_m, range_m):
    """Exact speckle degrees of freedom (docs/theory.md §7, Goodman):
    M⁻¹ = (1/A_R) ∫₀^D (2/π)[acos u − u√(1−u²)] [2J₁(x)/x]² 2πΔ dΔ, u = Δ/D_R, x = πdΔ/(λR).
    S1 (0.1 m, 0.5 m, 1064 nm, 2 km): 363.1; S2 (0.05 m, 0.2 m, 1550 nm, 5 km): 2.263.  Scalar inputs."""
    D, d, lam, R = float(aperture_diameter_m), float(spot_diameter_m), float(wavelength_m), float(range_m)
    a_r = np.pi * D ** 2 / 4.0
    k = np.pi * d / (lam * R)

    def f(delta):
        u = delta / D
        kr = (2.0 / np.pi) * (np.arccos(u) - u * np.sqrt(max(1.0 - u * u, 0.0)))
        x = k * delta
        mu2 = 1.0 if x < 1e-8 else (2.0 * special.j1(x) / x) ** 2
        return kr * mu2 * 2.0 * np.pi * delta

    from scipy import integrate  # imported where used: with scipy.optimize, 0.2 s of every run's start-up

    # split at the zeros of J1 so quad sees smooth pieces
    zeros = special.jn_zeros(1, 2000) / k
    pts = np.concatenate([[0.0], zeros[zeros < D], [D]])
    total = sum(integrate.quad(f, a, b, limit=200, epsabs=0, epsrel=1e-11)[0] for a, b in zip(pts[:-1], pts[1:]))
    return a_r / total


def speckle_gamma_pdf(w, dof, mean=1.0):
    """Integrated speckle pdf (docs/theory.md §7): gamma with M degrees of freedom,
    p(W) = (M/W̄)^M W^(M−1) exp(−M W/W̄)/Γ(M).  M = 4, W̄ = 1: p(0.5) 0.7218, p(1) 0.7815, p(2) 0.1145."""
    w = np.asarray(w, dtype=np.float64)
    m = float(dof)
    with np.errstate(divide="ignore"):
        logp = m * np.log(m / mean) + special.xlogy(m - 1.0, w) - m * w / mean - special.gammaln(m)
    return np.where(w >= 0, np.exp(logp), 0.0)


def speckle_contrast(dof):
    """Speckle contrast σ_W/W̄ = 1/√M (docs/theory.md §7)."""
    return 1.0 / np.sqrt(np.asarray(dof, dtype=np.float64))


def sample_speckle_gain(shape, dof, rng, dtype=np.float64):
    """Independent multiplicative speckle factors with unit mean: Gamma(M, 1/M) (docs/theory.md §7), contrast 1/√M."""
    return (rng.standard_gamma(float(dof), size=shape) / float(dof)).astype(dtype, copy=False)


def speckle_gain_field(shape, dof, rng, correlated=False, wavelength_m=None, aperture_diameter_m=None,
                       ifov_rad=None):
    """Per-pixel, per-pulse multiplicative speckle factor (mean 1, gamma marginal with M degrees of freedom,
    docs/theory.md §7).

    ``correlated=False``: independent pixels (speckle grain ≤ pixel).  ``correlated=True``: a circular complex
    Gaussian field is low-passed by the pupil (coherent cut-off D/(2λ) cycles/rad), so the intensity power
    spectrum has the MTF_speckle shape; the exponential intensity is then mapped pointwise to the Gamma(M)
    marginal (W = P⁻¹(M, 1 − e^(−I))/M).  The marginal is exact; the correlation is that of the pupil
    spectrum up to the monotone mapping.  If the grain is smaller than a pixel (cut-off ≥ Nyquist) the pixels
    are independent.
    """
    if not correlated:
        return sample_speckle_gain(shape, dof, rng)
    fc = aperture_diameter_m * ifov_rad / (2.0 * wavelength_m)  # coherent cut-off, cycles/pixel
    if fc >= 0.5:
        return sample_speckle_gain(shape, dof, rng)
    H, W = shape
    field = rng.standard_normal((H, W)) + 1j * rng.standard_normal((H, W))
    fy = sfft.fftfreq(H)[:, None]
    fx = sfft.fftfreq(W)[None, :]
    pupil = (np.hypot(fx, fy) <= fc).astype(np.float64)
    f = sfft.ifft2(sfft.fft2(field) * pupil)
    inten = np.abs(f) ** 2
    inten /= inten.mean()
    u = -np.expm1(-inten)  # exponential CDF -> uniform
    u = np.clip(u, 0.0, 1.0 - 1e-16)
    return special.gammaincinv(float(dof), u) / float(dof)


def negative_binomial_counts(mean_counts, dof, rng):
    """Photon counts with speckle (docs/theory.md §7): Poisson with a Gamma(M, N̄/M) mean, i.e. negative binomial
    with mean N̄ and variance N̄ + N̄²/M (exact mixture)."""
    mean = np.asarray(mean_counts, dtype=np.float64)
    return rng.poisson(mean * sample_speckle_gain(mean.shape, dof, rng))
