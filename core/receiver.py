"""Receiver chain: photons, detector noise, gain, read-out and A/D conversion (paper §3.1 Figure 4).

Physics references are to ``/work/shared/reference/physics.md``:
§5 (optics MTF, used through :mod:`core.speckle`), §7 (speckle), §8 (photons and detector noise).

Chain order (paper Figure 4, right of the ``Quant`` step)::

    energy J/bin --(Quant: E λ/hc)--> mean photons --(MTF_opt ⊛)--> --(η ⊗)--> --(speckle ⊗)-->
    --(+ background, + bulk dark)--> Poisson primaries --(G, excess noise F)--> --(+ surface dark)-->
    --(+ read-out noise)--> --(A/D: step Δ, offset, clip)--> digital counts

All random steps are applied to *means* first and sampled once at the end of each linear stage, which is
exactly equivalent in distribution to the photon-by-photon picture: blurring a Poisson photon field photon by
photon gives a Poisson field with the blurred mean; binomial thinning (η) of Poisson(N) is Poisson(ηN); a
gamma-distributed speckle factor on the mean gives the negative-binomial counts of §7.

Speed: a cube is processed in fixed-size pixel blocks, each with its own generator spawned from one
``SeedSequence`` (spawn key = block index), so the output depends only on the seed and the cube shape, never
on the number of threads.  Poisson primaries are sampled exactly and sparsely (a Poisson total per block or
per pixel, then placement by inverse-CDF search or uniform index), with a per-bin ``rng.poisson`` only for
bins whose mean exceeds ``_DENSE_MEAN``; the APD gain with excess noise is the exact sum of n gamma-distributed
single-electron gains, i.e. one Gamma(n/(F-1), G(F-1)) draw per *non-zero* bin.  See docs/receiver.md.
"""
from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .config import DetectorSettings, setting, validate  # noqa: F401  (DetectorSettings re-exported)

# CODATA 2018 exact constants
H_PLANCK_J_S = 6.62607015e-34
C_LIGHT_M_S = 299_792_458.0
Q_ELECTRON_C = 1.602176634e-19

#: Bins whose Poisson mean is at least this are drawn with ``rng.poisson`` per bin (exact); below it the
#: events are placed sparsely (exact).  Pure speed trade-off, no approximation.
_DENSE_MEAN = 8.0
#: Table route: signal bins with a mean below this are drawn by sparse placement (one Poisson total first).
_SPARSE_MEAN = 1e-3
#: Poisson means above this are drawn as a normal with the exact mean and variance (relative skewness error
#: 1/sqrt(mean) < 3e-4); far beyond any ADC full scale in practice.
_NORMAL_MEAN = 1e7
#: Largest mean number of primaries per bin carried (float32 safe); larger means are clipped and reported.
_MEAN_CAP = 1e30
#: Samples (pixels × bins) per random block.  Fixed: the result depends on the seed and shape only.
_BLOCK_SAMPLES = 1 << 18

STEPS = ("photon_conversion", "optics_mtf", "quantum_efficiency", "speckle", "background", "dark_current",
         "shot_noise", "gain", "excess_noise", "read_noise", "adc")


# ----------------------------------------------------------------------------------------------------------
# §8 elementary conversions (pure, vectorized)
# ----------------------------------------------------------------------------------------------------------
def photons_per_joule(wavelength_m):
    """Photons per joule, λ/(hc) (physics.md §8).  1 fJ = 2678 / 5356 / 7803 photons at 532/1064/1550 nm."""
    return np.asarray(wavelength_m, dtype=np.float64) / (H_PLANCK_J_S * C_LIGHT_M_S)


def energy_to_photons(energy_j, wavelength_m, quantum_efficiency=1.0):
    """Mean photo-electrons N = η E λ/(hc) (physics.md §8)."""
    return np.asarray(energy_j, dtype=np.float64) * photons_per_joule(wavelength_m) * quantum_efficiency


def current_to_electrons(current_a, time_s):
    """Mean electrons I τ / q delivered by a current during τ (dark current, physics.md §8)."""
    return np.asarray(current_a, dtype=np.float64) * np.asarray(time_s, dtype=np.float64) / Q_ELECTRON_C


def background_photons(rate_photons_per_s, bin_width_s):
    """Mean background (solar) photons per bin: constant rate × bin width (physics.md §8)."""
    return np.asarray(rate_photons_per_s, dtype=np.float64) * bin_width_s


def mcintyre_excess_noise(gain, k_eff):
    """McIntyre excess noise factor F = k G + (1 − k)(2 − 1/G) (physics.md §8).  G = 100, k = 0.02 → 3.950."""
    g = np.asarray(gain, dtype=np.float64)
    return k_eff * g + (1.0 - k_eff) * (2.0 - 1.0 / g)


def adc_step_e(bits, full_scale_e):
    """A/D quantization step Δ in electrons: full scale / 2**bits (physics.md §8)."""
    return float(full_scale_e) / float(2 ** int(bits))


def linear_detector_moments(n_signal_e, n_background_e=0.0, gain=1.0, excess_noise=1.0,
                            bulk_dark_e=0.0, surface_dark_e=0.0, read_noise_e=0.0, adc_step=0.0):
    """Mean and variance (electrons²) of one bin at the A/D output, in electrons (physics.md §8).

    mean = G (N_s + N_b + N_db) + N_ds;  var = G² F (N_s + N_b + N_db) + N_ds + σ_read² + Δ²/12.
    ``n_*`` are primary photo-electrons (after η); the A/D offset is not included.
    """
    n_mult = np.asarray(n_signal_e, dtype=np.float64) + n_background_e + bulk_dark_e
    mean = gain * n_mult + surface_dark_e
    var = gain ** 2 * excess_noise * n_mult + surface_dark_e + read_noise_e ** 2 + adc_step ** 2 / 12.0
    return mean, var


def snr_linear(energy_j, wavelength_m, quantum_efficiency, gain, k_eff, dark_current_bulk_a,
               dark_current_surface_a, integration_time_s, n_background_e, read_noise_e, adc_step=0.0):
    """Linear-mode (PIN: G = 1, k = 0 → F = 1; APD) SNR of physics.md §8:

    SNR = G N_s / √[G² F (N_s + N_b + I_db τ/q) + I_ds τ/q + σ_read² + Δ²/12].
    Test: η 0.4, G 100, k 0.02, 1 pA, 1 nA, 10 ns, N_b 2, 300 e⁻, Δ 500 e⁻ → 2.102 / 7.282 / 23.26 at
    1e-17 / 1e-16 / 1e-15 J (1064 nm).
    """
    n_s = energy_to_photons(energy_j, wavelength_m, quantum_efficiency)
    f = mcintyre_excess_noise(gain, k_eff)
    _, var = linear_detector_moments(n_s, n_background_e, gain, f,
                                     current_to_electrons(dark_current_bulk_a, integration_time_s),
                                     current_to_electrons(dark_current_surface_a, integration_time_s),
                                     read_noise_e, adc_step)
    return gain * n_s / np.sqrt(var)


def bin_moments(det: DetectorSettings, n_signal_e, bin_width_s):
    """Mean and variance [electrons] of one bin at the A/D output for ``n_signal_e`` mean signal photo-electrons
    (after η) with the switches exactly as :func:`apply_receiver_chain` uses them (PIN/APD, linear mode):

        shot noise on : mean = G(N_s + N_b + N_db) + N_ds,  var = G²F(N_s + N_b + N_db) + N_ds + G²N_s²/M + σ² + Δ²/12
        shot noise off: mean the same,                       var = G²(F − 1)(N_s + N_b + N_db) + G²N_s²/M + σ² + Δ²/12

    G = 1 for PIN; F = McIntyre F for an APD with excess noise on, else 1; N_b = η · background rate · Δt and
    N_db, N_ds = I Δt/q only when switched on; M the speckle degrees of freedom (term absent when 0); σ the read
    noise when on; Δ the A/D step when the A/D is on (physics.md §7, §8).  The A/D offset is not included.
    Returns ``(mean, var, parts)`` with ``parts`` the terms used (gain, F, N_b, N_db, N_ds, σ, Δ, M)."""
    if det.detector_type == "geiger":
        raise ValueError("bin_moments: Geiger mode counts detections, not electrons")
    gain = det.apd_gain if det.detector_type == "apd" else 1.0
    F = float(mcintyre_excess_noise(gain, det.apd_k_eff)) if (det.detector_type == "apd"
                                                               and det.enable_excess_noise) else 1.0
    n_b = (float(background_photons(det.background_rate_photons_per_s, bin_width_s)) * det.quantum_efficiency
           if det.enable_background else 0.0)
    n_db = float(current_to_electrons(det.dark_current_bulk_a, bin_width_s)) if det.enable_dark_current else 0.0
    n_ds = float(current_to_electrons(det.dark_current_surface_a, bin_width_s)) if det.enable_dark_current else 0.0
    sigma_r = det.read_noise_e if det.enable_read_noise else 0.0
    step = adc_step_e(det.adc_bits, det.adc_full_scale_e) if det.enable_adc else 0.0
    M = det.speckle_dof
    n_s = np.asarray(n_signal_e, dtype=np.float64)
    n_mult = n_s + n_b + n_db
    mean = gain * n_mult + n_ds
    var = (gain * gain * F * n_mult + n_ds) if det.enable_shot_noise else gain * gain * (F - 1.0) * n_mult
    if M > 0:
        var = var + gain * gain * n_s * n_s / M
    var = var + sigma_r ** 2 + step ** 2 / 12.0
    parts = {"gain": gain, "excess_noise": F, "n_background_e": n_b, "n_dark_bulk_e": n_db, "n_dark_surface_e": n_ds,
             "read_noise_e": sigma_r, "adc_step_e": step, "speckle_dof": M}
    return mean, var, parts


# ----------------------------------------------------------------------------------------------------------
# A/D conversion
# ----------------------------------------------------------------------------------------------------------
def adc_dtype(bits: int):
    return np.uint16 if bits <= 16 else (np.uint32 if bits <= 32 else np.uint64)


def adc_convert(electrons, bits, full_scale_e, offset_counts=0, out=None, overwrite_input=False):
    """A/D conversion (physics.md §8): code = clip(rint(e/Δ) + offset, 0, 2**bits − 1), Δ = full scale/2**bits.

    Returns ``(codes, n_low, n_high)``: the number of samples clipped at code 0 and at full scale
    (saturation) — clipping is always reported, never silent.  Quantization adds variance Δ²/12.
    ``overwrite_input`` lets a float32/float64 input be used as scratch space (no copy).
    """
    e = np.asarray(electrons)
    step = adc_step_e(bits, full_scale_e)
    top = float(2 ** int(bits) - 1)
    wdt = np.float64 if bits > 23 else np.float32
    work = e if (overwrite_input and e.dtype == wdt) else e.astype(wdt, copy=True)
    work *= work.dtype.type(1.0 / step)
    np.rint(work, out=work)
    if offset_counts:
        work += work.dtype.type(offset_counts)
    n_low = int(np.count_nonzero(work < 0))
    n_high = int(np.count_nonzero(work > top))
    if n_low or n_high:
        np.clip(work, 0, top, out=work)
    if out is None:
        return work.astype(adc_dtype(bits)), n_low, n_high
    np.copyto(out, work, casting="unsafe")
    return out, n_low, n_high


# ----------------------------------------------------------------------------------------------------------
# Exact fast samplers
# ----------------------------------------------------------------------------------------------------------
def poisson_sparse_counts(mean, rng):
    """Exact Poisson counts for a 1-D array of (mostly small) means: K ~ Poisson(Σ mean), then each of the K
    events falls in element i with probability mean_i/Σ mean (inverse-CDF search on the float64 cumulative
    sum).  Exact (superposition of independent Poisson processes); cost O(size + K log size).
    Returns int64 counts of the same length."""
    m = np.asarray(mean).reshape(-1)
    total = float(np.sum(m, dtype=np.float64)) if m.size else 0.0
    if not total > 0.0:
        return np.zeros(m.size, dtype=np.int64)
    k = int(rng.poisson(total))
    if k == 0:  # the common case for very faint bins: one pass over the means
        return np.zeros(m.size, dtype=np.int64)
    c = m.astype(np.float64)
    np.cumsum(c, out=c)  # in place: much faster than a casting cumsum
    total = float(c[-1])
    u = rng.random(k)
    u *= total
    idx = np.searchsorted(c, u, side="right")
    np.minimum(idx, m.size - 1, out=idx)  # u < total always; guards round-off at the very top
    return np.bincount(idx, minlength=m.size)


def _poisson_dense(lam, rng):
    """Exact Poisson per element (float64 means); normal with exact moments above _NORMAL_MEAN.
    Returns (float64 counts, number of normal-approximated elements)."""
    lam = np.asarray(lam, dtype=np.float64)
    big = lam >= _NORMAL_MEAN
    nb = int(np.count_nonzero(big))
    if not nb:
        return rng.poisson(lam).astype(np.float64), 0
    res = np.empty_like(lam)
    res[~big] = rng.poisson(lam[~big])
    lb = lam[big]
    res[big] = np.maximum(np.rint(lb + np.sqrt(lb) * rng.standard_normal(lb.size)), 0.0)
    return res, nb


def poisson_uniform_rows(mean_per_bin, n_rows, n_bins, rng, out=None):
    """Exact Poisson counts with the same mean in every bin of a row (background, bulk dark): the total per row
    is Poisson(B·mean) and the events fall uniformly on the row's bins (multinomial with equal cells = uniform
    indices).  ``mean_per_bin`` scalar or (n_rows,).  Accumulates into / returns float32 (n_rows, n_bins)."""
    if out is None:
        out = np.zeros((n_rows, n_bins), dtype=np.float32)
    m = np.broadcast_to(np.asarray(mean_per_bin, dtype=np.float64), (n_rows,))
    dense = m >= _DENSE_MEAN
    if dense.any():
        rows = np.flatnonzero(dense)
        lam = np.repeat(m[rows], n_bins).reshape(len(rows), n_bins)
        out[rows] += _poisson_dense(lam, rng)[0].astype(np.float32)
    sparse = ~dense & (m > 0)
    if sparse.any():
        rows = np.flatnonzero(sparse)
        k = rng.poisson(m[rows] * n_bins)
        tot = int(k.sum())
        if tot:
            pos = rng.integers(0, n_bins, size=tot, dtype=np.int64)
            pos += np.repeat(rows.astype(np.int64) * n_bins, k)
            oflat = out.reshape(-1)
            if tot * 50 < oflat.size:
                np.add.at(oflat, pos, 1.0)
            else:
                np.add(oflat, np.bincount(pos, minlength=oflat.size), out=oflat, casting="unsafe")
    return out


def gamma_gain(primaries, gain, excess_noise, rng, out=None):
    """Multiplied electrons for ``primaries`` photo-electrons per bin (physics.md §8, linear-mode APD).

    Each primary is multiplied by an independent gain of mean G and variance G²(F − 1) (gamma-distributed
    single-electron gain); the sum of n of them is exactly Gamma(n/(F−1), scale G(F−1)): mean G n, variance
    G²(F−1) n, so with Poisson n the total has variance G² F N̄ (the §8 formula).  F = 1 → G n exactly.
    Only non-zero bins are drawn.  Works for integer counts and for continuous means (shot noise off).
    ``out`` may be ``primaries`` itself (in place).
    """
    p = np.asarray(primaries, dtype=np.float32)
    if out is None:
        out = np.empty(p.shape, dtype=np.float32)
    if excess_noise <= 1.0 + 1e-12:
        np.multiply(p, np.float32(gain), out=out)
        return out
    theta = gain * (excess_noise - 1.0)
    a = 1.0 / (excess_noise - 1.0)
    pf, of = p.reshape(-1), out.reshape(-1)
    mask = pf != 0  # boolean masks: nonzero/count on a bool array is ~10x faster than on floats
    if np.count_nonzero(mask) * 2 > pf.size:  # dense: draw every bin (Gamma(0) = 0 exactly), no index gather
        shape = pf.astype(np.float64)
        shape *= a
        g = rng.standard_gamma(shape)
        g *= theta
        of[...] = g
        return out
    nz = np.flatnonzero(mask)
    shape = pf[nz].astype(np.float64)  # gather before ``out`` (possibly the same memory) is written
    if of is not pf and not np.shares_memory(of, pf):
        of[...] = 0.0
    if nz.size:
        shape *= a
        of[nz] = rng.standard_gamma(shape) * theta
    return out


# ----------------------------------------------------------------------------------------------------------
# Bins without signal: the exact A/D code distribution, tabulated once per run (physics.md §8)
# ----------------------------------------------------------------------------------------------------------
#: Probabilities of the tabulated code sampler are multiples of 2**-32 (one 32-bit uniform per sample).
_P_BITS = 32
#: The table route needs a Gaussian part σ ≥ this × Δ (otherwise the characteristic function decays too
#: slowly for the alias sum and the distribution is close to a lattice): the exact per-bin route is used.
_TABLE_MIN_SIGMA_STEPS = 2e-3
#: Bins that caught up to this many signal photo-electrons take tabulated codes too (CaughtCodeTables).
_CAUGHT_TABLES = 16
#: Largest FFT size (A/D indices spanned by the noise distribution) for the table route.
_TABLE_MAX_CODES = 1 << 20


def noise_code_pmf(step_e, *, n_mult=0.0, gain=1.0, excess_noise=1.0, shot=True, surface_dark_e=0.0,
                   surface_dark_poisson=False, gauss_mean_e=0.0, gauss_var_e2=0.0, fixed_primaries=None,
                   tail=1e-15):
    """Exact probabilities of the A/D index k = rint(X/Δ) of a bin without signal (physics.md §8).

    X = Σ_{i ≤ n} g_i + D + Z (electrons):
      n ~ Poisson(``n_mult``) multiplied primaries (background + bulk dark; exactly ``n_mult`` — a continuous
        amount — when ``shot`` is off), each with the single-electron gain g ~ Gamma(1/(F − 1), G(F − 1)) of
        :func:`gamma_gain` (g = G exactly when F = 1);
      D ~ Poisson(``surface_dark_e``) unmultiplied electrons when ``surface_dark_poisson``;
      Z ~ N(``gauss_mean_e``, ``gauss_var_e2``): read-out noise (and the surface dark where it is folded in).
    Its characteristic function is φ_X(t) = exp[n(φ_g(t) − 1)] · exp[d(e^{it} − 1)] · exp(iμt − σ²t²/2),
    φ_g(t) = (1 − iθt)^(−a).  Since p_k = ∫_{(k−½)Δ}^{(k+½)Δ} f_X(x) dx samples f_X ⊛ box_Δ at kΔ, the Poisson
    summation formula gives its discrete-time Fourier transform exactly:

        Σ_k p_k e^{iωk} = Σ_j φ_X((ω + 2πj)/Δ) · sinc((ω + 2πj)/2π),

    evaluated at the M frequencies of an FFT window holding all of the mass (tails beyond it < ``tail``) and
    inverted by one FFT.  Errors: float64 round-off (~1e-16 × √M) and the alias sum truncated where
    |φ_Z| < 1e-18.  Needs a Gaussian part σ > 0.  Returns ``(k0, p)``: p[i] = P(k = k0 + i), float64, Σ = 1.

    ``fixed_primaries`` (1-D integers m_1, m_2, …): the laws given m_j *additional* multiplied primaries (a bin
    that caught m_j signal photo-electrons), factor φ_g(t)^m_j; returns ``(k0, P)`` with P[j, i] = P(k = k0 + i
    | m_j) on one common window.
    """
    step = float(step_e)
    sigma = math.sqrt(gauss_var_e2)
    if not sigma > 0 or not step > 0:
        raise ValueError("noise_code_pmf needs a Gaussian part (σ > 0) and an A/D step Δ > 0")
    G, F, b, d = float(gain), float(excess_noise), float(n_mult), float(surface_dark_e)
    gamma_gain_on = F > 1.0 + 1e-12
    theta = G * (F - 1.0) if gamma_gain_on else 0.0
    a = 1.0 / (F - 1.0) if gamma_gain_on else 0.0
    if shot:
        mean = G * b
        var = G * G * (F if gamma_gain_on else 1.0) * b
    else:
        mean, var = G * b, G * theta * b
    d_p = d if surface_dark_poisson else 0.0
    mean += d_p + gauss_mean_e
    var += d_p + gauss_var_e2
    # tail scale of the multiplied part (exponential-like, scale θ; Poisson lattice step G) and of D
    scale = max(theta, G if (shot and b > 0) else 0.0, 1.0 if d_p > 0 else 0.0)
    fixed = None if fixed_primaries is None else np.asarray(fixed_primaries, dtype=np.float64).reshape(-1, 1)
    mean_hi = mean
    if fixed is not None:  # m extra primaries: + G m mean, + G²(F − 1) m variance
        mean_lo, mean_hi = mean + G * fixed.min(), mean + G * fixed.max()
        mean = mean_lo
        var += G * theta * fixed.max()
        scale = max(scale, G)

    def cf(t):
        lc = (1j * gauss_mean_e) * t - (0.5 * gauss_var_e2) * t * t
        if fixed is not None:
            lc = lc + fixed * (-a * np.log1p((-1j * theta) * t) if gamma_gain_on else (1j * G) * t)
        if b > 0:
            if gamma_gain_on:
                lg = -a * np.log1p((-1j * theta) * t)
                lc = lc + (b * np.expm1(lg) if shot else b * lg)
            else:
                lc = lc + (b * np.expm1((1j * G) * t) if shot else (1j * G * b) * t)
        if d_p > 0:
            lc = lc + d_p * np.expm1(1j * t)
        return np.exp(lc)

    n_alias = int(math.ceil(1.5 * step / sigma)) + 1  # |φ_Z((π + 2πJ)/Δ)| < 1e-18
    half = 40.0 * math.sqrt(var) + 80.0 * scale + 4.0 * step
    for _ in range(8):
        k0 = int(math.floor((mean - half) / step)) - 2
        k1 = int(math.ceil((mean_hi + half) / step)) + 2
        M = 1 << max(4, int(k1 - k0).bit_length())
        if M > _TABLE_MAX_CODES:
            raise ValueError(f"noise distribution spans {M} A/D codes (> {_TABLE_MAX_CODES})")
        omega = 2.0 * np.pi * np.fft.fftfreq(M)
        acc = 0.0
        for j in range(-n_alias, n_alias + 1):
            w = omega + 2.0 * np.pi * j
            acc = acc + cf(w / step) * np.sinc(w / (2.0 * np.pi))
        p = np.fft.fft(np.atleast_2d(acc) * np.exp(-1j * omega * k0), axis=-1).real / M
        edge = max(1, M // 16)
        if np.all(p[:, :edge].sum(axis=1) + p[:, -edge:].sum(axis=1) < tail):
            break
        half *= 2.0
    else:  # pragma: no cover - the window doubles 8 times
        raise ValueError("noise distribution tails did not converge")
    np.maximum(p, 0.0, out=p)  # round-off negatives (~1e-17)
    p /= p.sum(axis=1, keepdims=True)
    return k0, (p[0] if fixed is None else p)


class CodeTable:
    """Inverse-CDF sampler of A/D codes from one uniform 32-bit integer per sample (exact up to probabilities
    rounded to multiples of 2**-32).

    Entries: [clipped below code 0], the A/D codes in order, [clipped above full scale]; T_i = round(2³² C_i)
    their cumulative probabilities; a sample r ∈ [0, 2³²) takes the entry i with T_{i−1} ≤ r < T_i.
    Level 1: the top 16 bits of r index a 65536-cell table holding the code when one entry covers the whole
    cell; the few cells that straddle an entry boundary hold a sentinel, and those samples are resolved by a
    binary search on T (at most one cell per entry boundary, i.e. ≤ (entries − 1)/65536 of the samples).
    """

    def __init__(self, k0, pmf, offset, top, dtype, cell_bits=16):
        self.CELL_BITS = int(cell_bits)
        pmf = np.asarray(pmf, dtype=np.float64)
        raw = k0 + np.arange(pmf.size, dtype=np.int64) + int(offset)
        low, high = raw < 0, raw > top
        mid = ~(low | high)
        p = np.concatenate([[pmf[low].sum()], pmf[mid], [pmf[high].sum()]])
        code = np.concatenate([[0], raw[mid], [top]]).astype(dtype)
        cum = np.cumsum(p)
        cum /= cum[-1]
        T = np.floor(cum * 2.0 ** _P_BITS + 0.5).astype(np.uint64)
        T[-1] = np.uint64(1 << _P_BITS)
        self.T, self.code = T, code
        self.t_low = int(T[0])        # r < t_low: clipped at code 0
        self.t_high = int(T[-2])      # r ≥ t_high: clipped at full scale
        p_q = np.diff(np.concatenate([[0], T.astype(np.int64)]))
        drawable = code[p_q > 0]
        self.n_entries = int(np.count_nonzero(p_q))
        self.max_prob_error = float(np.max(np.abs(p_q / 2.0 ** _P_BITS - p)))
        # cell h holds r ∈ [h·2^s, (h+1)·2^s), s = 32 − CELL_BITS.  Its first r falls in entry #{i: T_i ≤ h·2^s}
        # = #{i: ⌈T_i/2^s⌉ ≤ h}; the cell is ambiguous when a boundary T_i lies strictly inside it.
        n_cells, sh = 1 << self.CELL_BITS, _P_BITS - self.CELL_BITS
        Ti = T[:-1].astype(np.int64)
        first = np.cumsum(np.bincount(-((-Ti) >> sh), minlength=n_cells + 1))[:n_cells]
        amb = np.zeros(n_cells, dtype=bool)
        amb[(Ti >> sh)[(Ti & ((1 << sh) - 1)) != 0]] = True
        self.n_ambiguous_cells = int(np.count_nonzero(amb))
        table = code[first]
        c_lo, c_hi = int(drawable.min()), int(drawable.max())  # any value outside [c_lo, c_hi] is never drawn
        self.sentinel = c_hi + 1 if c_hi < np.iinfo(dtype).max else (c_lo - 1 if c_lo > 0 else None)
        self.amb_cells = None
        if self.sentinel is not None:
            table[amb] = self.sentinel
        else:  # pragma: no cover - every code value up to the dtype's top is drawable
            self.amb_cells = amb
        self.table = table

    def sample(self, r, out, scratch=None):
        """Codes for the uniform uint32 ``r`` into ``out`` (1-D, table dtype).  Returns (n_low, n_high):
        how many were clipped at code 0 and at full scale."""
        shift = np.uint32(_P_BITS - self.CELL_BITS)
        cell = np.right_shift(r, shift, out=scratch)
        np.take(self.table, cell, out=out)
        if self.n_ambiguous_cells:
            amb = np.flatnonzero(self.amb_cells[cell] if self.amb_cells is not None else out == self.sentinel)
            if amb.size:
                out[amb] = self.code[np.searchsorted(self.T, r[amb].astype(np.uint64), side="right")]
        return self.clipped(r)

    def clipped(self, r):
        n_low = int(np.count_nonzero(r < np.uint32(self.t_low))) if self.t_low > 0 else 0
        n_high = int(np.count_nonzero(r >= np.uint32(self.t_high))) if self.t_high < (1 << _P_BITS) else 0
        return n_low, n_high


class CaughtCodeTables:
    """Code laws of bins that caught m = 1 … ``m_max`` signal photo-electrons (plus everything a signal-free bin
    has), from :func:`noise_code_pmf` with ``fixed_primaries``; built on first use (thread-safe), sampled with
    one 32-bit uniform each like :class:`CodeTable` (4096-cell level-1 tables stacked into one array)."""

    def __init__(self, m_max, step_e, pmf_kwargs, offset, top, dtype, cell_bits=12):
        self.m_max, self.cell_bits = int(m_max), int(cell_bits)
        self._args = (step_e, pmf_kwargs, offset, top, dtype)
        self._lock = threading.Lock()
        self.tables = None

    def _build(self):
        with self._lock:
            if self.tables is not None:
                return
            step_e, kw, offset, top, dtype = self._args
            k0, P = noise_code_pmf(step_e, fixed_primaries=np.arange(1, self.m_max + 1), **kw)
            tabs = [CodeTable(k0, P[j], offset, top, dtype, self.cell_bits) for j in range(self.m_max)]
            stack = np.empty((self.m_max, 1 << self.cell_bits), dtype=np.int64)
            for j, t in enumerate(tabs):
                stack[j] = t.table
                if t.n_ambiguous_cells:
                    amb = t.amb_cells if t.amb_cells is not None else t.table == t.sentinel
                    stack[j, amb] = -1
            self.stack = stack.reshape(-1)
            self.t_low = np.array([t.t_low for t in tabs], dtype=np.int64)
            self.t_high = np.array([t.t_high for t in tabs], dtype=np.int64)
            self.clip_low = bool(np.any(self.t_low > 0))
            self.clip_high = bool(np.any(self.t_high < (1 << _P_BITS)))
            self.max_prob_error = max(t.max_prob_error for t in tabs)
            self.tables = tabs

    def sample(self, m, r):
        """Codes for caught counts ``m`` (1 … m_max) and uniforms ``r`` (uint32).  Returns (codes int64, n_low,
        n_high)."""
        if self.tables is None:
            self._build()
        mi = m.astype(np.int32) - 1
        flat = (r >> np.uint32(_P_BITS - self.cell_bits)).astype(np.int32)
        flat |= mi << self.cell_bits
        codes = self.stack[flat]
        amb = np.flatnonzero(codes < 0)
        if amb.size:
            for j in np.unique(mi[amb]):
                sel = amb[mi[amb] == j]
                t = self.tables[j]
                codes[sel] = t.code[np.searchsorted(t.T, r[sel].astype(np.uint64), side="right")]
        n_low = n_high = 0
        if self.clip_low:
            n_low = int(np.count_nonzero(r.astype(np.int64) < self.t_low[mi]))
        if self.clip_high:
            n_high = int(np.count_nonzero(r.astype(np.int64) >= self.t_high[mi]))
        return codes, n_low, n_high


def uniform_uint32(rng, n):
    """``n`` independent uniform 32-bit integers from the generator's raw 64-bit stream."""
    return rng.bit_generator.random_raw((n + 1) // 2).view(np.uint32)[:n]


# ----------------------------------------------------------------------------------------------------------
# Settings
# ----------------------------------------------------------------------------------------------------------
@dataclass
class ChainSettings:
    """Everything :func:`apply_receiver_chain` needs: the detector plus the physical context."""

    detector: DetectorSettings = field(default_factory=DetectorSettings)
    wavelength_m: float = 1.064e-6
    bin_width_s: float = 1e-9
    aperture_diameter_m: float = 0.05
    ifov_x_rad: float = 0.02 / 64
    ifov_y_rad: float = 0.02 / 64

    @classmethod
    def from_config(cls, cfg, detector: DetectorSettings | None = None) -> "ChainSettings":
        """Context from a :class:`core.config.SimulationConfig`; detector from ``detector`` or ``cfg.detector``."""
        det = detector if detector is not None else getattr(cfg, "detector", DetectorSettings())
        r = cfg.receiver
        return cls(det, cfg.laser.wavelength_m, cfg.gate.bin_width_s, r.aperture_diameter_m,
                   r.fov_x_rad / r.width_px, r.fov_y_rad / r.height_px)


@dataclass
class ChainOutput:
    """Result of :func:`apply_receiver_chain`.

    ``data``: digital counts (uint16/uint32) after the A/D, float32 electrons if the A/D is off, int32
    detections for Geiger mode, or the input array itself in ideal mode.  ``report``: steps run/skipped,
    units, clipping counts, approximations used."""

    data: np.ndarray
    report: dict


# ----------------------------------------------------------------------------------------------------------
# The chain
# ----------------------------------------------------------------------------------------------------------
def _seed_sequence(rng) -> np.random.SeedSequence:
    if isinstance(rng, np.random.SeedSequence):
        return rng
    if isinstance(rng, np.random.Generator):
        return np.random.SeedSequence(rng.integers(0, 2**63, size=4).tolist())
    return np.random.SeedSequence(rng)


def _child(ss, *key) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(
        np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + tuple(key))))


def apply_receiver_chain(waveforms_j, settings: ChainSettings, rng, *, noise_table=True) -> ChainOutput:
    """Apply the receiver chain of the paper's Figure 4 (physics.md §5, §7, §8) to a waveform cube.

    waveforms_j : (H, W, B) float32 signal energy per pixel per time bin [J] (no background: that is added here).
    settings    : :class:`ChainSettings` (``settings.detector`` switches the steps).
    rng         : ``np.random.Generator``, ``SeedSequence`` or int seed.  Same seed → identical output,
                  independent of the thread count.

    noise_table : draw the bins without signal photo-electrons from the exact tabulated code distribution
                  (:class:`CodeTable`; A/D on, read noise ≥ 0.002 Δ).  False forces the per-bin route (tests).

    Ideal mode returns ``waveforms_j`` itself (bit for bit) and reports every step skipped.
    """
    det = settings.detector
    validate(det)
    cube = np.asarray(waveforms_j)
    if cube.ndim != 3:
        raise ValueError(f"waveforms_j must be (H, W, B), got shape {cube.shape}")
    report = {"mode": det.mode, "detector_type": det.detector_type, "steps_run": [], "steps_skipped": [],
              "approximations": [], "n_mean_clipped": 0, "n_adc_low": 0, "n_adc_high": 0,
              "n_optics_negative_clamped": 0, "units": "J"}
    if det.mode == "ideal":
        report["steps_skipped"] = list(STEPS)
        return ChainOutput(waveforms_j, report)

    if cube.size and not (np.isfinite(cube.min()) and np.isfinite(cube.max())):
        raise ValueError("waveforms_j contains NaN or Inf")
    if cube.size and cube.min() < 0:
        raise ValueError("waveforms_j contains negative energies")
    H, W, B = cube.shape
    ss = _seed_sequence(rng)
    run, skip = report["steps_run"], report["steps_skipped"]
    geiger = det.detector_type == "geiger"

    # Quant: J -> mean photons (deterministic factor, fused into the block kernel); optics MTF acts on means
    k_sig = float(photons_per_joule(settings.wavelength_m))
    run.append("photon_conversion")
    src = cube
    if det.enable_optics_mtf:
        from .speckle import apply_mtf, optics_mtf_2d
        # zero padding (light from outside the field of view is not simulated) against FFT wrap-around:
        # 8 diffraction widths λ/D, at most the image size
        ifov = min(settings.ifov_x_rad, settings.ifov_y_rad)
        pad = int(min(max(H, W), math.ceil(8.0 * settings.wavelength_m / settings.aperture_diameter_m / ifov) + 1))
        mtf = optics_mtf_2d((H, W), settings.wavelength_m, settings.aperture_diameter_m,
                            settings.ifov_x_rad, settings.ifov_y_rad, pixel=det.optics_pixel_mtf, pad=(pad, pad))
        padded = np.pad(cube.astype(np.float32, copy=False), ((0, pad), (0, pad), (0, 0)))
        blurred, n_neg = apply_mtf(padded, mtf, axes=(0, 1), clamp_negative=True)
        src = np.ascontiguousarray(blurred[:H, :W])
        report["n_optics_negative_clamped"] = n_neg
        report["optics_pad_px"] = pad
        run.append("optics_mtf")
    else:
        skip.append("optics_mtf")
    k_sig *= det.quantum_efficiency
    run.append("quantum_efficiency")

    spk = None
    if det.speckle_dof > 0 and geiger:
        run.append("speckle")  # redrawn per pulse inside the Geiger simulation
    elif det.speckle_dof > 0:
        from .speckle import speckle_gain_field
        spk = speckle_gain_field((H, W), det.speckle_dof, _child(ss, 1), correlated=det.speckle_correlated,
                                 wavelength_m=settings.wavelength_m,
                                 aperture_diameter_m=settings.aperture_diameter_m,
                                 ifov_rad=settings.ifov_x_rad).astype(np.float32).reshape(-1)
        run.append("speckle")
    else:
        skip.append("speckle")

    tau = settings.bin_width_s
    b_mult = 0.0
    if det.enable_background and det.background_rate_photons_per_s > 0:
        b_mult += float(background_photons(det.background_rate_photons_per_s, tau)) * det.quantum_efficiency
        run.append("background")
    else:
        skip.append("background")
    ds = 0.0
    if det.enable_dark_current and (det.dark_current_bulk_a > 0 or det.dark_current_surface_a > 0):
        b_mult += float(current_to_electrons(det.dark_current_bulk_a, tau))
        ds = float(current_to_electrons(det.dark_current_surface_a, tau))
        run.append("dark_current")
    else:
        skip.append("dark_current")

    shot = det.enable_shot_noise
    (run if shot else skip).append("shot_noise")

    if geiger:
        for s in ("gain", "excess_noise", "read_noise", "adc"):
            skip.append(s)
        hist = _geiger_chain(src, k_sig, spk, b_mult + ds, det, ss, report)
        report["units"] = "detections"
        return ChainOutput(hist, report)

    gain = 1.0 if det.detector_type == "pin" else det.apd_gain
    F = 1.0
    if det.detector_type == "apd":
        run.append("gain")
        if det.enable_excess_noise:
            F = float(mcintyre_excess_noise(gain, det.apd_k_eff))
            run.append("excess_noise")
        else:
            skip.append("excess_noise")
    else:
        skip += ["gain", "excess_noise"]
    sigma_r = det.read_noise_e if det.enable_read_noise else 0.0
    (run if det.enable_read_noise and sigma_r > 0 else skip).append("read_noise")

    use_adc = det.enable_adc
    step = adc_step_e(det.adc_bits, det.adc_full_scale_e) if use_adc else 0.0
    out_dtype = adc_dtype(det.adc_bits) if use_adc else np.float32
    # Bins without signal photo-electrons all have the same code distribution: tabulate it exactly once
    # (noise_code_pmf, CodeTable) and draw those bins with one 32-bit uniform each.  Needs the A/D (discrete
    # output) and a Gaussian read noise of at least 0.002 Δ; otherwise the per-bin route below.
    table = None
    if noise_table and use_adc and sigma_r >= _TABLE_MIN_SIGMA_STEPS * step:
        try:
            k0, pmf = noise_code_pmf(step, n_mult=b_mult, gain=gain, excess_noise=F, shot=shot,
                                     surface_dark_e=ds, surface_dark_poisson=shot and ds > 0,
                                     gauss_mean_e=0.0 if shot else ds, gauss_var_e2=sigma_r ** 2)
            table = CodeTable(k0, pmf, det.adc_offset_counts, 2 ** int(det.adc_bits) - 1, out_dtype)
            if shot:  # bins that caught 1 … 16 signal photo-electrons: their own tables, built on first use
                table.caught = CaughtCodeTables(
                    _CAUGHT_TABLES, step, dict(n_mult=b_mult, gain=gain, excess_noise=F, surface_dark_e=ds,
                                               surface_dark_poisson=ds > 0, gauss_var_e2=sigma_r ** 2),
                    det.adc_offset_counts, 2 ** int(det.adc_bits) - 1, out_dtype)
        except ValueError as exc:  # too many codes: per-bin route
            report["noise_table_refused"] = str(exc)
    report["noise_sampling"] = "table" if table is not None else "per-bin"
    if table is not None:
        report["noise_table"] = {"codes": table.n_entries, "ambiguous_cells": table.n_ambiguous_cells,
                                 "probability_step": 2.0 ** -_P_BITS, "max_probability_error": table.max_prob_error}
        report["approximations"].append(
            f"bins without signal photo-electrons: A/D codes from the exact code distribution with "
            f"probabilities rounded to multiples of 2^-32 (largest change {table.max_prob_error:.1e})")

    # surface dark (not multiplied): Gaussian folded into the read noise when its skewness contribution
    # lambda/sigma_tot^3 is negligible (< 1e-3); otherwise exact Poisson.  Always exact on the table route.
    ds_gauss = False
    if ds > 0 and shot and table is None:
        sig_tot2 = sigma_r ** 2 + ds + step ** 2 / 12.0
        skew = ds / sig_tot2 ** 1.5
        if skew < 1e-3:
            ds_gauss = True
            report["approximations"].append(
                f"surface dark Poisson({ds:.4g}) as Gaussian with exact mean/variance "
                f"(skewness contribution {skew:.2e})")

    (run if use_adc else skip).append("adc")
    out = np.empty((H * W, B), dtype=out_dtype)
    report["units"] = "counts" if use_adc else "electrons"
    # mean and σ of a bin without signal at the output (the noise floor; echo detection's false-alarm model)
    if table is not None:
        pq = np.diff(np.concatenate([[0], table.T.astype(np.int64)])) / 2.0 ** _P_BITS
        c = table.code.astype(np.float64)
        m0 = float(np.dot(pq, c))
        report["noise_mean"], report["noise_sigma"] = m0, float(np.sqrt(np.dot(pq, (c - m0) ** 2)))
    else:
        m0, var0, _ = bin_moments(det, 0.0, tau)  # the same switches (Sheppard's Δ²/12 for the A/D)
        m0, var0 = float(m0), float(var0)
        if use_adc:
            report["noise_mean"] = m0 / step + det.adc_offset_counts
            report["noise_sigma"] = math.sqrt(var0) / step
        else:
            report["noise_mean"], report["noise_sigma"] = m0, math.sqrt(var0)

    src2 = np.ascontiguousarray(src, dtype=np.float32).reshape(H * W, B)
    rows = max(1, _BLOCK_SAMPLES // max(B, 1))
    blocks = [(i, r0, min(r0 + rows, H * W)) for i, r0 in enumerate(range(0, H * W, rows))]
    params = dict(k_sig=k_sig, b_mult=b_mult, ds=ds, ds_gauss=ds_gauss, shot=shot, gain=gain, F=F,
                  sigma_r=sigma_r, adc=use_adc, bits=det.adc_bits, fs=det.adc_full_scale_e,
                  offset=det.adc_offset_counts)

    local = threading.local()

    def work(blk):
        i, r0, r1 = blk
        if not hasattr(local, "ws"):
            local.ws = {}
        fn = _process_block if table is None else _process_block_table
        return fn(src2[r0:r1], out[r0:r1], _child(ss, 0, i), None if spk is None else spk[r0:r1], params,
                  local.ws, table)

    threads = det.threads or (os.cpu_count() or 1)
    if threads > 1 and len(blocks) > 1:
        with ThreadPoolExecutor(max_workers=threads) as ex:
            stats = list(ex.map(work, blocks))
    else:
        stats = [work(b) for b in blocks]
    for key in ("n_mean_clipped", "n_adc_low", "n_adc_high"):
        report[key] = int(sum(s[key] for s in stats))
    if table is not None:
        report["noise_table"]["caught_bins_from_tables"] = int(sum(s.get("caught_table", 0) for s in stats))
        report["noise_table"]["caught_bins_per_bin"] = int(sum(s.get("caught_per_bin", 0) for s in stats))
    if report["n_mean_clipped"]:
        report["approximations"].append(f"{report['n_mean_clipped']} bins had a mean above {_MEAN_CAP:g} "
                                        f"primaries and were clipped to it")
    if any(s["normal_bins"] for s in stats):
        report["approximations"].append(f"{sum(s['normal_bins'] for s in stats)} bins with Poisson mean ≥ "
                                        f"{_NORMAL_MEAN:g} drawn as normal (exact mean and variance)")
    return ChainOutput(out.reshape(H, W, B), report)


def _buf(ws, name, n, dtype):
    a = ws.get(name)
    if a is None or a.size < n or a.dtype != dtype:
        a = np.empty(n, dtype=dtype)
        ws[name] = a
    return a[:n]


def _process_block_table(E, out, rng, spk, p, ws, table) -> dict:
    """One block of pixels (P, B), A/D on, with the tabulated code distribution of signal-free bins.

    Exact decomposition: the primaries of a bin are n = n_s + n_b (independent Poisson, signal and
    background/bulk dark).  Every bin first gets a code from ``table`` (the law of a bin with n_s = 0); then
    the signal primaries n_s are drawn exactly for the bins with a non-zero mean (one Poisson each; sparse
    placement below a mean of 1e-3) and the bins with n_s > 0 are redrawn from the law given n_s: by the
    tables of ``table.caught`` for n_s ≤ 16 (re-using the bin's uniform, which is independent of n_s), else
    per bin: n_b ~ Poisson, gain Gamma((n_s + n_b)/(F − 1), G(F − 1)), surface dark Poisson, read noise, A/D.
    Cost: one 32-bit uniform and one table look-up per bin, plus one Poisson draw per bin with signal."""
    P, B = E.shape
    N = P * B
    stats = {"n_mean_clipped": 0, "n_adc_low": 0, "n_adc_high": 0, "normal_bins": 0}
    of = out.reshape(-1)
    r = uniform_uint32(rng, N)
    stats["n_adc_low"], stats["n_adc_high"] = table.sample(r, of, _buf(ws, "cell", N, np.uint32))
    Ef = E.reshape(-1)
    mask = Ef != 0  # boolean mask: much faster than a float scan
    nnz = int(np.count_nonzero(mask))
    if not nnz:
        return stats
    dense = nnz * 2 > N  # most bins hold signal: work on the whole block (no index array)
    nz = None if dense else np.flatnonzero(mask)
    with np.errstate(over="ignore"):
        s = Ef.astype(np.float64) if dense else Ef[nz].astype(np.float64)
        s *= p["k_sig"]
        if spk is not None and dense:
            sv = s.reshape(P, B)
            sv *= spk[:, None]
        elif spk is not None:
            s *= spk[nz // B]
    bad = ~(s <= _MEAN_CAP)
    if bad.any():
        stats["n_mean_clipped"] = int(np.count_nonzero(bad))
        s[bad] = _MEAN_CAP
    if p["shot"]:
        # exact Poisson counts: one draw per bin (numpy: 8–10 ns below a mean of 0.1, ~30 ns at 1) except for
        # very faint bins (pulse tails, FFT round-off), placed sparsely — usually no event at all
        faint = s < _SPARSE_MEAN
        if faint.any():
            n = np.empty(s.size)
            fi = np.flatnonzero(faint)
            n[fi] = poisson_sparse_counts(s[fi], rng)
            bi = np.flatnonzero(~faint)
            n[bi], stats["normal_bins"] = _poisson_dense(s[bi], rng)
        else:
            n, stats["normal_bins"] = _poisson_dense(s, rng)
        caught = np.flatnonzero(n > 0)
        sig, n = (caught if dense else nz[caught]), n[caught]
        if not sig.size:
            return stats
        rs = r[sig]
        lo_t, hi_t = table.clipped(rs)  # those bins' signal-free codes are replaced
        stats["n_adc_low"] -= lo_t
        stats["n_adc_high"] -= hi_t
        few = n <= table.caught.m_max
        if few.any():  # codes given the caught count, from the tables (the same uniform r: independent of n)
            codes, lo, hi = table.caught.sample(n[few], rs[few])
            of[sig[few]] = codes
            stats["n_adc_low"] += lo
            stats["n_adc_high"] += hi
            stats["caught_table"] = int(np.count_nonzero(few))
            sig, n = sig[~few], n[~few]
            if not sig.size:
                return stats
        stats["caught_per_bin"] = int(sig.size)
        if p["b_mult"] > 0:
            n += rng.poisson(p["b_mult"], sig.size)
    else:
        sig = np.arange(N) if dense else nz
        n = s + p["b_mult"]
        lo_t, hi_t = table.clipped(r[sig])
        stats["n_adc_low"] -= lo_t
        stats["n_adc_high"] -= hi_t
    y = gamma_gain(n.astype(np.float32), p["gain"], p["F"], rng).astype(np.float64)
    if p["ds"] > 0:
        y += rng.poisson(p["ds"], sig.size) if p["shot"] else p["ds"]
    if p["sigma_r"] > 0:
        y += p["sigma_r"] * rng.standard_normal(sig.size)
    codes, lo, hi = adc_convert(y, p["bits"], p["fs"], p["offset"])
    stats["n_adc_low"] += lo
    stats["n_adc_high"] += hi
    of[sig] = codes
    return stats


def _process_block(E, out, rng, spk, p, ws, table=None) -> dict:
    """One block of pixels (P, B): exact sampling of the §8 statistics, written into ``out``.
    ``ws``: per-thread scratch buffers (reused across blocks: fresh large allocations are slow)."""
    P, B = E.shape
    N = P * B
    stats = {"n_mean_clipped": 0, "n_adc_low": 0, "n_adc_high": 0, "normal_bins": 0}
    s = _buf(ws, "s", N, np.float32).reshape(P, B)
    with np.errstate(over="ignore"):  # overflow -> inf -> clipped to _MEAN_CAP and reported below
        np.multiply(E, np.float32(p["k_sig"]), out=s)  # mean signal primaries (after eta)
    if spk is not None:
        with np.errstate(over="ignore"):
            s *= spk[:, None]
    sf = s.reshape(-1)
    smax = float(sf.max()) if N else 0.0
    if not math.isfinite(smax) or smax > _MEAN_CAP:
        bad = ~(sf <= _MEAN_CAP)
        stats["n_mean_clipped"] = int(np.count_nonzero(bad))
        sf[bad] = _MEAN_CAP
        smax = _MEAN_CAP
    if p["shot"]:
        n = _buf(ws, "n", N, np.float32).reshape(P, B)
        nf = n.reshape(-1)
        nf.fill(0.0)
        if smax > 0:
            if smax >= _DENSE_MEAN:  # bright bins: one exact Poisson draw each
                hi = np.flatnonzero(sf >= _DENSE_MEAN)
                cnt, nb = _poisson_dense(sf[hi], rng)
                stats["normal_bins"] += nb
                nf[hi] = cnt
                sf[hi] = 0.0
            mask = sf != 0
            nnz = int(np.count_nonzero(mask))
            if nnz * 4 < N:  # faint bins, compact: inverse-CDF placement over the non-zero bins only
                nz = np.flatnonzero(mask)
                nf[nz] += poisson_sparse_counts(sf[nz], rng)
            elif nnz:
                np.add(nf, poisson_sparse_counts(sf, rng), out=nf, casting="unsafe")
        if p["b_mult"] > 0:
            poisson_uniform_rows(p["b_mult"], P, B, rng, out=n)
    else:
        n = s
        if p["b_mult"] > 0:
            n += np.float32(p["b_mult"])
    y = gamma_gain(n, p["gain"], p["F"], rng, out=n)  # in place
    mu = 0.0
    var = p["sigma_r"] ** 2
    if p["ds"] > 0:
        if not p["shot"]:
            mu += p["ds"]
        elif p["ds_gauss"]:
            mu += p["ds"]
            var += p["ds"]
        else:
            poisson_uniform_rows(p["ds"], P, B, rng, out=y)
    if var > 0:
        z = _buf(ws, "z", N, np.float32).reshape(P, B)
        rng.standard_normal(dtype=np.float32, out=z)
        z *= np.float32(math.sqrt(var))
        y += z
    if mu:
        y += np.float32(mu)
    if p["adc"]:
        _, lo, hi = adc_convert(y, p["bits"], p["fs"], p["offset"], out=out, overwrite_input=p["bits"] <= 23)
        stats["n_adc_low"], stats["n_adc_high"] = lo, hi
    else:
        out[...] = y
    return stats


def _geiger_chain(src, k_sig, spk, noise_per_bin, det, ss, report):
    H, W, B = src.shape
    rate = np.asarray(src, dtype=np.float64).reshape(H * W, B) * k_sig
    hist, info = geiger_histogram(rate, det.geiger_pulses, _child(ss, 2), noise_per_bin=noise_per_bin,
                                  dead_time_bins=det.geiger_dead_time_bins,
                                  speckle_dof=det.speckle_dof if det.speckle_dof > 0 else None)
    report.update({f"geiger_{k}": v for k, v in info.items()})
    return hist.reshape(H, W, B)


# ----------------------------------------------------------------------------------------------------------
# Geiger mode (photon counting), physics.md §8
# ----------------------------------------------------------------------------------------------------------
def geiger_detection_probability(n_mean, speckle_dof=None):
    """P_d = 1 − exp(−N); with speckle of M degrees of freedom 1 − (1 + N/M)^(−M) (physics.md §8).
    N = 1: 0.6321; M = 1: 0.5; M = 4: 0.5904."""
    n = np.asarray(n_mean, dtype=np.float64)
    if speckle_dof is None:
        return -np.expm1(-n)
    m = np.asarray(speckle_dof, dtype=np.float64)
    return -np.expm1(-m * np.log1p(n / m))


def pileup_probabilities(rates):
    """First-detection probability per bin p_i = exp(−Σ_{j<i} r_j)(1 − e^(−r_i)) (physics.md §8), along the
    last axis.  Rates [0.1, 0.5, 1.0] → [0.09516, 0.3560, 0.3469]."""
    r = np.asarray(rates, dtype=np.float64)
    before = np.cumsum(r, axis=-1) - r
    return np.exp(-before) * -np.expm1(-r)


def coates_correction(histogram, n_pulses):
    """Coates pile-up correction r_i = −ln[1 − h_i/(N − Σ_{j<i} h_j)] (physics.md §8), along the last axis.
    Bins where every remaining pulse fired (h_i = N − Σ_{j<i} h_j) have an unbounded estimate: returned as inf."""
    h = np.asarray(histogram, dtype=np.float64)
    remaining = n_pulses - (np.cumsum(h, axis=-1) - h)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(remaining > 0, h / np.where(remaining > 0, remaining, 1.0), 0.0)
        return -np.log1p(-frac)


def geiger_histogram(rate_per_bin, n_pulses, rng, noise_per_bin=0.0, dead_time_bins=None, speckle_dof=None,
                     max_pulse_chunk=None, force_per_pulse=False):
    """Histogram of Geiger-mode detections over ``n_pulses`` pulses (physics.md §8: pile-up, dead time).

    rate_per_bin   : (..., B) mean *detectable* signal primaries per bin per pulse (η already applied).
    noise_per_bin  : background + dark primaries per bin per pulse (scalar or (...,) per pixel).
    dead_time_bins : after a detection in bin i the detector re-arms at bin i + 1 + dead_time_bins.
                     None or ≥ B: at most one (the first) detection per pulse.
    speckle_dof    : M; the signal of each pixel is multiplied by an independent Gamma(M, 1/M) factor per pulse.

    Without speckle and with one detection per pulse the histogram is exactly multinomial(N, p_i) with the
    pile-up p_i (one vectorized call).  Otherwise each pulse is simulated: the first event after re-arming is
    where the cumulative rate crosses an Exp(1) variate (exact inhomogeneous Poisson first arrival),
    found by a vectorized bisection (``force_per_pulse`` selects it always).  Returns (int64 histogram,
    info dict).
    """
    r = np.asarray(rate_per_bin, dtype=np.float64)
    shape = r.shape
    B = shape[-1]
    r = r.reshape(-1, B)
    P = r.shape[0]
    noise = np.broadcast_to(np.asarray(noise_per_bin, dtype=np.float64), shape[:-1]).reshape(P, 1)
    single = dead_time_bins is None or dead_time_bins >= B
    info = {"pulses": int(n_pulses), "path": "", "dead_time_bins": dead_time_bins}
    if single and not speckle_dof and not force_per_pulse:
        tot = r + noise
        p = pileup_probabilities(tot)
        pv = np.empty((P, B + 1))
        pv[:, :B] = p
        pv[:, B] = np.exp(-tot.sum(axis=1))  # no detection in this pulse
        pv /= pv.sum(axis=1, keepdims=True)
        h = rng.multinomial(int(n_pulses), pv)
        info["path"] = "multinomial"
        return h[:, :B].astype(np.int64).reshape(shape), info
    info["path"] = "per-pulse"
    cs = np.zeros((P, B + 1))
    np.cumsum(r, axis=1, out=cs[:, 1:])
    cn = noise * np.arange(B + 1)  # (P, B+1) cumulative noise rate
    dead = B if single else int(dead_time_bins)
    hist = np.zeros(P * B, dtype=np.int64)
    chunk = max_pulse_chunk or max(1, (1 << 22) // max(P, 1))
    done = 0
    rows = np.arange(P)[:, None]
    while done < n_pulses:
        nb = min(chunk, n_pulses - done)
        done += nb
        if speckle_dof:
            s = rng.standard_gamma(float(speckle_dof), size=(P, nb)) / float(speckle_dof)
        else:
            s = np.ones((P, nb))
        arm = np.zeros((P, nb), dtype=np.int64)  # bin index at which the detector is armed
        active = np.ones((P, nb), dtype=bool)
        while active.any():
            c_arm = s * cs[rows, arm] + cn[rows, arm]
            target = c_arm + rng.standard_exponential(size=(P, nb))
            c_end = s * cs[:, B:B + 1] + cn[:, B:B + 1]
            hit = active & (target < c_end)
            # bisection: smallest j in (arm, B] with C(j) > target; detection bin = j - 1
            lo = arm.copy()
            hi = np.full((P, nb), B, dtype=np.int64)
            while True:
                open_ = hit & (hi - lo > 1)
                if not open_.any():
                    break
                mid = (lo + hi) // 2
                cm = s * np.take_along_axis(cs, mid, axis=1) + np.take_along_axis(cn, mid, axis=1)
                up = cm > target
                hi = np.where(open_ & up, mid, hi)
                lo = np.where(open_ & ~up, mid, lo)
            det_bin = hi - 1
            pix = np.broadcast_to(rows, (P, nb))
            hist += np.bincount((pix[hit] * B + det_bin[hit]), minlength=P * B)
            arm = np.where(hit, det_bin + 1 + dead, B)
            active = hit & (arm < B)
            arm = np.minimum(arm, B)
    return hist.reshape(shape), info
