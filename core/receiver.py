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
    c = m.astype(np.float64)
    np.cumsum(c, out=c)  # in place: much faster than a casting cumsum
    total = float(c[-1]) if c.size else 0.0
    if not total > 0.0:
        return np.zeros(m.size, dtype=np.int64)
    k = int(rng.poisson(total))
    if k == 0:
        return np.zeros(m.size, dtype=np.int64)
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


def apply_receiver_chain(waveforms_j, settings: ChainSettings, rng) -> ChainOutput:
    """Apply the receiver chain of the paper's Figure 4 (physics.md §5, §7, §8) to a waveform cube.

    waveforms_j : (H, W, B) float32 signal energy per pixel per time bin [J] (no background: that is added here).
    settings    : :class:`ChainSettings` (``settings.detector`` switches the steps).
    rng         : ``np.random.Generator``, ``SeedSequence`` or int seed.  Same seed → identical output,
                  independent of the thread count.

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

    # surface dark (not multiplied): Gaussian folded into the read noise when its skewness contribution
    # lambda/sigma_tot^3 is negligible (< 1e-3); otherwise exact Poisson.
    ds_gauss = False
    if ds > 0 and shot:
        step = adc_step_e(det.adc_bits, det.adc_full_scale_e) if det.enable_adc else 0.0
        sig_tot2 = sigma_r ** 2 + ds + step ** 2 / 12.0
        skew = ds / sig_tot2 ** 1.5
        if skew < 1e-3:
            ds_gauss = True
            report["approximations"].append(
                f"surface dark Poisson({ds:.4g}) as Gaussian with exact mean/variance "
                f"(skewness contribution {skew:.2e})")

    use_adc = det.enable_adc
    (run if use_adc else skip).append("adc")
    out = np.empty((H * W, B), dtype=adc_dtype(det.adc_bits) if use_adc else np.float32)
    report["units"] = "counts" if use_adc else "electrons"

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
        return _process_block(src2[r0:r1], out[r0:r1], _child(ss, 0, i),
                              None if spk is None else spk[r0:r1], params, local.ws)

    threads = det.threads or (os.cpu_count() or 1)
    if threads > 1 and len(blocks) > 1:
        with ThreadPoolExecutor(max_workers=threads) as ex:
            stats = list(ex.map(work, blocks))
    else:
        stats = [work(b) for b in blocks]
    for key in ("n_mean_clipped", "n_adc_low", "n_adc_high"):
        report[key] = int(sum(s[key] for s in stats))
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


def _process_block(E, out, rng, spk, p, ws) -> dict:
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
