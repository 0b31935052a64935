"""Split-step phase-screen propagation: the accurate, slow reference model (physics.md §12).

Used only to validate the fast engineering model of :mod:`core.atmosphere.scintillation` (the seed paper
rejects phase screens for run time, §3.4).  Plane wave, constant Cn², paraxial angular-spectrum
propagation on a periodic N × N grid (Schmidt, *Numerical Simulation of Optical Wave Propagation*, 2010).
"""
from __future__ import annotations

import math

import numpy as np

from . import turbulence as tb


def von_karman_phase_psd(f_cyc_per_m, r0_m, outer_scale_m=np.inf, inner_scale_m=0.0):
    """Phase PSD Φ_φ(f) = 0.023 r0^(−5/3) (f² + 1/L0²)^(−11/6) exp(−(f/f_m)²) [rad² m²] (physics.md §12).

    f in cycles/m, f_m = 5.92/(2π l0) (no cut-off for l0 = 0), L0 = inf: Kolmogorov.  f = 0 with L0 = inf
    returns 0 (the piston term is irrelevant).
    """
    f2 = np.asarray(f_cyc_per_m, dtype=np.float64) ** 2
    f0 = 0.0 if not math.isfinite(outer_scale_m) else 1.0 / outer_scale_m**2
    base = f2 + f0
    with np.errstate(divide="ignore"):
        psd = np.where(base > 0, 0.023 * r0_m ** (-5.0 / 3.0) * np.where(base > 0, base, 1.0) ** (-11.0 / 6.0),
                       0.0)
    if inner_scale_m > 0:
        fm = 5.92 / (2 * math.pi * inner_scale_m)
        psd = psd * np.exp(-f2 / fm**2)
    return psd


def phase_screens(count, n, dx_m, r0_m, rng, *, outer_scale_m=np.inf, inner_scale_m=0.0, subharmonics=True):
    """``count`` independent von Kármán phase screens [rad], shape (count, n, n) (physics.md §12).

    FFT method: c_f = (a + i b) √Φ_φ(f) Δf summed over the n × n frequency grid (Δf = 1/(n dx)); the real
    and imaginary parts of the sum are two independent screens.  Lane (1992) subharmonics, 3 levels of
    3 × 3 frequencies at Δf/3^p (p = 1..3), restore the low-order (tilt) content missing from the FFT grid;
    the subharmonic part is not periodic over the grid.
    """
    pairs = (count + 1) // 2
    df = 1.0 / (n * dx_m)
    f = np.fft.fftfreq(n, dx_m)
    fr = np.hypot(f[:, None], f[None, :])
    amp = np.sqrt(von_karman_phase_psd(fr, r0_m, outer_scale_m, inner_scale_m)) * df
    amp[0, 0] = 0.0
    c = (rng.standard_normal((pairs, n, n)) + 1j * rng.standard_normal((pairs, n, n))) * amp
    scr = np.fft.ifft2(c) * (n * n)
    if subharmonics:
        x = (np.arange(n) - n / 2) * dx_m
        for p in range(1, 4):
            dfp = df / 3**p
            fs = np.array([-1.0, 0.0, 1.0]) * dfp
            fsr = np.hypot(fs[:, None], fs[None, :])
            a = np.sqrt(von_karman_phase_psd(fsr, r0_m, outer_scale_m, inner_scale_m)) * dfp
            a[1, 1] = 0.0
            cp = (rng.standard_normal((pairs, 3, 3)) + 1j * rng.standard_normal((pairs, 3, 3))) * a
            e = np.exp(2j * np.pi * fs[:, None] * x[None, :])          # (3, n)
            # SH[y, x] = Σ_{b,a} c[b, a] e[b, y] e[a, x]
            scr = scr + np.einsum("by,kba,ax->kyx", e, cp, e, optimize=True)
        scr = scr - scr.mean(axis=(1, 2), keepdims=True)
    out = np.concatenate([scr.real, scr.imag], axis=0)[:count]
    return out


def split_step_plane_wave(wavelength_m, range_m, cn2_m_23, rng, *, n=512, dx_m=2e-3, n_screens=None,
                          outer_scale_m=np.inf, inner_scale_m=0.0, subharmonics=True):
    """Receiver-plane intensity (unit incident irradiance) of a plane wave after split-step propagation.

    The path is cut into ``n_screens`` equal slabs (default: enough that each has Rytov ≤ 0.1,
    n ≥ (10 σ_R²)^(6/11), and at least 5), each slab's turbulence lumped into one screen at its centre with
    r0,i = (0.423 k² Cn² Δz)^(−3/5); vacuum steps use the paraxial transfer function
    exp(−iπλΔz(fx² + fy²)).  Returns the (n, n) intensity.
    """
    k = 2 * math.pi / wavelength_m
    s_r = float(tb.rytov_variance(cn2_m_23, wavelength_m, range_m, "plane"))
    if n_screens is None:
        n_screens = max(5, int(math.ceil((10 * s_r) ** (6.0 / 11.0))))
    dz = range_m / n_screens
    f = np.fft.fftfreq(n, dx_m)
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    h_full = np.exp(-1j * math.pi * wavelength_m * dz * f2)
    h_half = np.exp(-1j * math.pi * wavelength_m * 0.5 * dz * f2)
    u = np.ones((n, n), dtype=np.complex128)
    if cn2_m_23 > 0:
        r0_i = (0.423 * k**2 * cn2_m_23 * dz) ** (-0.6)
        screens = phase_screens(n_screens, n, dx_m, r0_i, rng, outer_scale_m=outer_scale_m,
                                inner_scale_m=inner_scale_m, subharmonics=subharmonics)
    else:
        screens = np.zeros((n_screens, n, n))
    for i in range(n_screens):                       # loop over screens (not pixels)
        u = np.fft.ifft2(np.fft.fft2(u) * (h_half if i == 0 else h_full))
        u = u * np.exp(1j * screens[i])
    u = np.fft.ifft2(np.fft.fft2(u) * h_half)
    return u.real**2 + u.imag**2


def one_over_e_radius(profile, dx_m):
    """First crossing of 1/e in a decreasing correlation profile (linear interpolation) [m]."""
    below = np.nonzero(profile < math.exp(-1.0))[0]
    if below.size == 0:
        return float("nan")
    j = below[0]
    p0, p1 = profile[j - 1], profile[j]
    return float((j - 1 + (p0 - math.exp(-1.0)) / (p0 - p1)) * dx_m)


def split_step_reference(wavelength_m, range_m, cn2_m_23, rng, *, n=512, dx_m=2e-3, n_screens=None,
                         realizations=10, crop=0.5, outer_scale_m=np.inf, inner_scale_m=0.0,
                         subharmonics=True):
    """Split-step reference statistics of a plane wave (physics.md §12).

    Runs ``realizations`` independent propagations, keeps the central ``crop`` fraction of each side (the
    subharmonics are not periodic, the border is polluted by wrap-around), and returns a dict:
    ``scintillation_index`` = ⟨I²⟩/⟨I⟩² − 1 pooled, ``si_std_err`` (spread over realizations / √n),
    ``correlation_radius_m`` (1/e radius of the mean normalised intensity autocovariance, averaged over x
    and y), ``n_screens``, ``rytov_variance``.
    """
    c0 = int(n * (1 - crop) / 2)
    c1 = n - c0
    m = c1 - c0
    sis, m1, m2 = [], 0.0, 0.0
    acov = np.zeros((m, m))
    s_r = float(tb.rytov_variance(cn2_m_23, wavelength_m, range_m, "plane"))
    ns = n_screens if n_screens is not None else max(5, int(math.ceil((10 * s_r) ** (6.0 / 11.0))))
    # overlap count for the non-periodic autocovariance of the crop (zero-padded FFT)
    ones = np.zeros((2 * m, 2 * m))
    ones[:m, :m] = 1.0
    cnt = np.fft.irfft2(np.abs(np.fft.rfft2(ones)) ** 2, s=(2 * m, 2 * m))
    for _ in range(realizations):
        i = split_step_plane_wave(wavelength_m, range_m, cn2_m_23, rng, n=n, dx_m=dx_m, n_screens=ns,
                                  outer_scale_m=outer_scale_m, inner_scale_m=inner_scale_m,
                                  subharmonics=subharmonics)[c0:c1, c0:c1]
        sis.append(i.var() / i.mean() ** 2)
        m1 += i.mean()
        m2 += np.mean(i**2)
        d = np.zeros((2 * m, 2 * m))
        d[:m, :m] = i - i.mean()
        ac = np.fft.irfft2(np.abs(np.fft.rfft2(d)) ** 2, s=(2 * m, 2 * m)) / np.maximum(cnt, 1.0)
        acov += ac[:m, :m]
    m1 /= realizations
    m2 /= realizations
    acov /= acov[0, 0]
    half = m // 2
    rad = 0.5 * (one_over_e_radius(acov[0, :half], dx_m) + one_over_e_radius(acov[:half, 0], dx_m))
    return {"scintillation_index": float(m2 / m1**2 - 1.0),
            "si_std_err": float(np.std(sis, ddof=1) / math.sqrt(realizations)) if realizations > 1 else None,
            "correlation_radius_m": rad, "n_screens": ns, "rytov_variance": s_r, "n": n, "dx_m": dx_m,
            "realizations": realizations}


def periodic_autocorrelation(fields):
    """Mean normalised periodic autocovariance (value 1 at zero lag) of a list of equally shaped 2-D fields."""
    ac = 0.0
    for f in fields:
        d = f - f.mean()
        ac = ac + np.fft.irfft2(np.abs(np.fft.rfft2(d)) ** 2, s=f.shape)
    return ac / ac[0, 0]
