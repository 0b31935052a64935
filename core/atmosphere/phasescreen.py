"""Split-step phase-screen propagation: the accurate, slow reference model (docs/theory.md §12).

Used only to validate the fast engineering model of :mod:`core.atmosphere.scintillation` (the seed paper
rejects phase screens for run time, §3.4).  Plane wave, constant Cn², paraxial angular-spectrum
propagation on a periodic N × N grid (Schmidt, *Numerical Simulation of Optical Wave Propagation*, 2010).
"""
from __future__ import annotations

import math

import numpy as np

from . import turbulence as tb
from ..lazy import lazy_module

sfft = lazy_module("scipy.fft")  # SciPy's FFT, imported at its first use (core/lazy.py)


def von_karman_phase_psd(f_cyc_per_m, r0_m, outer_scale_m=np.inf, inner_scale_m=0.0):
    """Phase PSD Φ_φ(f) = 0.023 r0^(−5/3) (f² + 1/L0²)^(−11/6) exp(−(f/f_m)²) [rad² m²] (docs/theory.md §12).

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
    """``count`` independent von Kármán phase screens [rad], shape (count, n, n) (docs/theory.md §12).

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


def default_screen_count(cn2_m_23, wavelength_m, range_m):
    """Screens of the split-step reference: each slab has a plane-wave Rytov variance ≤ 0.1,
    n ≥ (10 σ_R²)^(6/11), and at least 5 (docs/theory.md §12)."""
    s_r = float(tb.rytov_variance(cn2_m_23, wavelength_m, range_m, "plane"))
    return max(5, int(math.ceil((10 * s_r) ** (6.0 / 11.0))))


def split_step_screens(wavelength_m, range_m, cn2_m_23, rng, *, wave="plane", n=512, dx_m=2e-3, n_screens=None,
                       outer_scale_m=np.inf, inner_scale_m=0.0, subharmonics=True):
    """The phase screens [rad] :func:`split_step_intensity` would draw, shape (n_screens, n, n) (for a paired
    comparison, e.g. the same turbulence on a coarser grid by spectral truncation)."""
    k = 2 * math.pi / wavelength_m
    if n_screens is None:
        n_screens = default_screen_count(cn2_m_23, wavelength_m, range_m)
    dz = range_m / n_screens
    m = np.ones(n_screens) if wave == "plane" else (np.arange(n_screens) + 0.5) * dz / range_m
    r0_i = (0.423 * k**2 * cn2_m_23 * dz) ** (-0.6)
    return np.stack([phase_screens(1, n, dx_m, r0_i / m[i], rng, outer_scale_m=outer_scale_m / m[i],
                                   inner_scale_m=inner_scale_m / m[i], subharmonics=subharmonics)[0]
                     for i in range(n_screens)])


def split_step_intensity(wavelength_m, range_m, cn2_m_23, rng, *, wave="plane", n=512, dx_m=2e-3,
                         n_screens=None, outer_scale_m=np.inf, inner_scale_m=0.0, subharmonics=True,
                         dtype=np.complex128, screens=None):
    """Receiver-plane intensity (n, n) after split-step propagation of a plane or spherical wave.

    The path is cut into ``n_screens`` equal slabs (default :func:`default_screen_count`), each slab's
    turbulence lumped into one screen at its centre z_i with r0,i = (0.423 k² Cn² Δz)^(−3/5); vacuum steps
    use the paraxial transfer function exp(−iπλΔζ(fx² + fy²)).

    ``wave="plane"``: unit plane wave, Δζ = Δz.  ``wave="spherical"``: a point source at z = 0, computed
    exactly (paraxially) on the receiver grid by the lens (Talanov) transformation: with m(z) = z/L the field
    u(x, z) = v(x/m, ζ) exp(ikx²/(2z))/m, dζ = dz/m², where v obeys the same paraxial equation and starts as a
    uniform plane wave.  So the spherical wave is a plane wave in the scaled coordinates ξ = x L/z that passes
    screens φ_i(m_i ξ) — von Kármán screens with r0, l0 and L0 all divided by m_i — separated by
    Δζ = L²(1/z_i − 1/z_(i+1)) (and L(L/z_last − 1) to the receiver, where m = 1 and ξ = x).  The receiver
    intensity of a unit-amplitude-at-receiver point source is |v|².  ``screens`` (n_screens, n, n): use these
    phase screens (:func:`split_step_screens`) instead of drawing them.  ``dtype=np.complex64`` (single-precision field)
    halves the cost of the long tabulation runs.
    """
    if wave not in tb.WAVE_TYPES:
        raise ValueError(f"wave must be one of {tb.WAVE_TYPES}, got {wave!r}")
    k = 2 * math.pi / wavelength_m
    if n_screens is None:
        n_screens = default_screen_count(cn2_m_23, wavelength_m, range_m)
    dz = range_m / n_screens
    z = (np.arange(n_screens) + 0.5) * dz
    if wave == "plane":
        m = np.ones(n_screens)
        steps = np.concatenate([[0.5 * dz], np.full(n_screens - 1, dz), [0.5 * dz]])
    else:
        m = z / range_m
        zz = np.concatenate([z, [range_m]])
        steps = np.concatenate([[0.0], range_m**2 * (1.0 / zz[:-1] - 1.0 / zz[1:])])
    f = np.fft.fftfreq(n, dx_m)
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    transfer = {}
    u = np.ones((n, n), dtype=dtype)
    r0_i = (0.423 * k**2 * cn2_m_23 * dz) ** (-0.6) if cn2_m_23 > 0 else np.inf
    pair = None
    for i in range(n_screens + 1):                   # loop over screens (not pixels)
        if steps[i] > 0:
            h = transfer.get(steps[i])
            if h is None:
                h = transfer[steps[i]] = np.exp(-1j * math.pi * wavelength_m * steps[i] * f2).astype(dtype)
            u = sfft.ifft2(sfft.fft2(u) * h)
        if i == n_screens or cn2_m_23 <= 0:
            continue
        if screens is not None:
            scr = screens[i]
        elif wave == "plane":                          # identical screens: made two at a time (one FFT)
            if i % 2 == 0:
                pair = phase_screens(2, n, dx_m, r0_i, rng, outer_scale_m=outer_scale_m,
                                     inner_scale_m=inner_scale_m, subharmonics=subharmonics)
            scr = pair[i % 2]
        else:
            scr = phase_screens(1, n, dx_m, r0_i / m[i], rng, outer_scale_m=outer_scale_m / m[i],
                                inner_scale_m=inner_scale_m / m[i], subharmonics=subharmonics)[0]
        u = u * np.exp(1j * scr).astype(dtype, copy=False)
    return (u.real**2 + u.imag**2).astype(np.float64)


def split_step_plane_wave(wavelength_m, range_m, cn2_m_23, rng, *, n=512, dx_m=2e-3, n_screens=None,
                          outer_scale_m=np.inf, inner_scale_m=0.0, subharmonics=True):
    """Receiver-plane intensity (unit incident irradiance) of a plane wave after split-step propagation:
    :func:`split_step_intensity` with ``wave="plane"``."""
    return split_step_intensity(wavelength_m, range_m, cn2_m_23, rng, wave="plane", n=n, dx_m=dx_m,
                                n_screens=n_screens, outer_scale_m=outer_scale_m, inner_scale_m=inner_scale_m,
                                subharmonics=subharmonics)


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
    """Split-step reference statistics of a plane wave (docs/theory.md §12).

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


class IntensityStatistics:
    """Accumulates wave-optics intensity statistics over periodic n × n realisations of pitch dx.

    Pooled SI = ⟨I²⟩/⟨I⟩² − 1 and its standard error from the per-realisation spread; σ²_lnI = pooled
    variance of ln I; the normalised periodic intensity autocovariance averaged over realisations and
    azimuth (radial profile at the requested lags, by interpolation of the azimuthal means in bins of dx/2);
    and, per aperture diameter D, the SI of the intensity averaged over a disk of diameter D (periodic
    convolution), i.e. the aperture-averaged SI.
    """

    def __init__(self, n, dx_m, lags_m, aperture_diameters_m=()):
        self.n, self.dx = n, float(dx_m)
        self.lags = np.asarray(lags_m, dtype=np.float64)
        c = np.fft.fftfreq(n, 1.0 / n) * self.dx
        r = np.hypot(c[:, None], c[None, :])
        self._r = r
        keep = r <= min(self.lags.max() + 2 * self.dx, 0.5 * n * self.dx)
        self._bins = np.floor(r[keep] / (0.5 * self.dx)).astype(np.int64)
        self._keep = keep
        cnt = np.bincount(self._bins)
        self._cnt = np.where(cnt > 0, cnt, 1)
        self._rmean = np.bincount(self._bins, weights=r[keep]) / self._cnt
        self._valid = cnt > 0
        self.diameters = [float(d) for d in aperture_diameters_m]
        self._disks = []
        for d in self.diameters:
            disk = (r <= 0.5 * d).astype(np.float64)
            self._disks.append(sfft.rfft2(disk / disk.sum()))
        self.si, self.m1, self.m2, self.lnv, self.lnm = [], [], [], [], []
        self._ac = 0.0
        self.ap = [[] for _ in self.diameters]

    def add(self, intensity):
        i = np.asarray(intensity, dtype=np.float64)
        mu = i.mean()
        self.m1.append(mu)
        self.m2.append(np.mean(i * i))
        self.si.append(i.var() / mu**2)
        li = np.log(np.maximum(i, np.finfo(float).tiny))
        self.lnm.append(li.mean())
        self.lnv.append(np.mean(li * li))
        spec = sfft.rfft2(i - mu)
        self._ac = self._ac + sfft.irfft2(np.abs(spec) ** 2, s=i.shape)
        for j, dk in enumerate(self._disks):
            a = sfft.irfft2(sfft.rfft2(i) * dk, s=i.shape)
            self.ap[j].append((np.mean(a * a), a.mean()))

    @property
    def count(self):
        return len(self.si)

    def result(self):
        n_r = self.count
        m1, m2 = float(np.mean(self.m1)), float(np.mean(self.m2))
        si = m2 / m1**2 - 1.0
        ac = self._ac / self._ac[0, 0]
        prof = np.bincount(self._bins, weights=ac[self._keep]) / self._cnt
        rr, pp = self._rmean[self._valid], prof[self._valid]
        cov = np.interp(self.lags, rr, pp)
        cov[self.lags == 0.0] = 1.0
        out = {"scintillation_index": si,
               "si_std_err": float(np.std(self.si, ddof=1) / math.sqrt(n_r)) if n_r > 1 else None,
               "sigma2_lnI": float(np.mean(self.lnv) - np.mean(self.lnm) ** 2),
               "covariance": cov, "correlation_radius_m": one_over_e_radius_profile(self.lags, cov),
               "realizations": n_r}
        if self.diameters:
            out["aperture_si"] = [float(np.mean([a[0] for a in ap]) / np.mean([a[1] for a in ap]) ** 2 - 1.0)
                                  for ap in self.ap]
        return out


def one_over_e_radius_profile(lags, profile):
    """First crossing of 1/e of a correlation profile sampled at (increasing) ``lags``, linear interpolation."""
    lags = np.asarray(lags, dtype=np.float64)
    profile = np.asarray(profile, dtype=np.float64)
    below = np.nonzero(profile < math.exp(-1.0))[0]
    if below.size == 0 or below[0] == 0:
        return float("nan")
    j = below[0]
    p0, p1 = profile[j - 1], profile[j]
    return float(lags[j - 1] + (p0 - math.exp(-1.0)) / (p0 - p1) * (lags[j] - lags[j - 1]))


def wave_optics_statistics(wavelength_m, range_m, cn2_m_23, rng, *, wave="spherical", n=512, dx_m=2e-3,
                           n_screens=None, realizations=8, lags_m=None, aperture_diameters_m=(),
                           outer_scale_m=np.inf, inner_scale_m=0.0, dtype=np.complex64):
    """Split-step wave-optics statistics of a plane or spherical wave (:class:`IntensityStatistics`).

    Screens without subharmonics, so the whole periodic field is used (intensity statistics depend on the
    scales ≲ the box; the box must span many large-scale radii L/(kρ0)).  ``lags_m`` default: 0 to n·dx/4.
    """
    if lags_m is None:
        lags_m = np.arange(0, n // 4 + 1) * dx_m
    acc = IntensityStatistics(n, dx_m, lags_m, aperture_diameters_m)
    for _ in range(realizations):
        acc.add(split_step_intensity(wavelength_m, range_m, cn2_m_23, rng, wave=wave, n=n, dx_m=dx_m,
                                     n_screens=n_screens, outer_scale_m=outer_scale_m,
                                     inner_scale_m=inner_scale_m, subharmonics=False, dtype=dtype))
    out = acc.result()
    out.update(n=n, dx_m=dx_m, n_screens=n_screens or default_screen_count(cn2_m_23, wavelength_m, range_m),
               wave=wave)
    return out
