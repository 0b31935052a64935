"""Receiver chain: photons, detector noise, gain, read-out and A/D conversion (paper §3.1 Figure 4).

Physics references are to ``docs/theory.md``:
§5 (optics MTF, used through :mod:`core.physics.receiver.speckle`), §7 (speckle), §8 (photons and detector noise).

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
on the number of threads; on the table route the signal-free bins' uniforms and the signal bins' Poisson
counts (means below 8) come from counter-based streams per block (SplitMix64 on the block's key and the bin's
index, evaluated inside the compiled kernels).  On the per-bin
route Poisson primaries are sampled exactly and sparsely (a Poisson total per block or per pixel, then
placement by inverse-CDF search or uniform index), with a per-bin ``rng.poisson`` only for bins whose mean
exceeds ``DENSE_MEAN``; the APD gain with excess noise is the exact sum of n gamma-distributed
single-electron gains, i.e. one Gamma(n/(F-1), G(F-1)) draw per *non-zero* bin.  See docs/receiver.md.
"""
from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass, field

import numpy as np

from ...config.settings import DetectorSettings
from ...config.validate import validate
from ...threads import map_list
from .adc import adc_convert, adc_dtype
from .code_tables import P_BITS, TABLE_MIN_SIGMA_STEPS
from .conversions import (adc_step_e, background_photons, bin_moments, current_to_electrons, mcintyre_excess_noise,
                          noise_sigma_floor, photons_per_joule)
from .geiger import geiger_histogram
from .samplers import (DENSE_MEAN, NORMAL_MEAN, POISSON_SAMPLER, gamma_gain, poisson_dense, poisson_sparse_counts,
                       poisson_uniform_rows)
from .speckle import apply_mtf, optics_mtf_2d, speckle_gain_field
from .table_route import (MEAN_CAP, TABLE_BLOCK_SAMPLES, noise_tables, per_bin_tail, process_block_table,
                          scratch)

#: Samples (pixels × bins) per random block.  Fixed: the result depends on the seed and shape only.
_BLOCK_SAMPLES = 1 << 18

STEPS = ("photon_conversion", "optics_mtf", "quantum_efficiency", "speckle", "background", "dark_current",
         "shot_noise", "gain", "excess_noise", "read_noise", "adc")


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
    #: the run's threads (``run.threads``), used when ``detector.threads`` is 0; 0 here too: one per CPU
    run_threads: int = 0
    #: (H, W) photons/s before η added to ``detector.background_rate_photons_per_s`` pixel by pixel (the sunlight
    #: the scene reflects into each pixel, core/physics/solar.py); None: the detector's rate alone, as before.
    pixel_background_rate: np.ndarray | None = None

    @classmethod
    def from_config(cls, cfg, detector: DetectorSettings | None = None) -> "ChainSettings":
        """Context from a :class:`core.config.SimulationConfig`; detector from ``detector`` or ``cfg.detector``."""
        det = detector if detector is not None else getattr(cfg, "detector", DetectorSettings())
        r = cfg.receiver
        return cls(det, cfg.laser.wavelength_m, cfg.gate.bin_width_s, r.aperture_diameter_m,
                   r.fov_x_rad / r.width_px, r.fov_y_rad / r.height_px, cfg.run.threads)


@dataclass
class ChainOutput:
    """Result of :func:`apply_receiver_chain`.

    ``data``: digital counts (uint16/uint32) after the A/D, float32 electrons if the A/D is off, int32
    detections for Geiger mode, or the input array itself in ideal mode.  ``report``: steps run/skipped,
    units, clipping counts, approximations used."""

    data: np.ndarray
    report: dict
    #: (codes, probabilities) of a signal-free bin on the table route (the sampled law; None otherwise): the
    #: statistical detector model's noise law (core/physics/detection/stretches.py).  Not part of the report.
    noise_pmf: tuple | None = None
    #: With ``ChainSettings.pixel_background_rate``: the per-pixel noise model, (H, W) arrays under the report's
    #: names ``noise_mean``, ``noise_sigma`` (linear mode) and ``noise_sigma_floor``; None otherwise.
    pixel_noise: dict | None = None


# ----------------------------------------------------------------------------------------------------------
# The chain
# ----------------------------------------------------------------------------------------------------------
def _seed_sequence(rng) -> np.random.SeedSequence:
    if isinstance(rng, np.random.SeedSequence):
        return rng
    if isinstance(rng, np.random.Generator):
        return np.random.SeedSequence(rng.integers(0, 2**63, size=4).tolist())
    return np.random.SeedSequence(rng)


def _child_ss(ss, *key) -> np.random.SeedSequence:
    return np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + tuple(key))


def _child(ss, *key) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(_child_ss(ss, *key)))


def apply_receiver_chain(waveforms_j, settings: ChainSettings, rng, *, noise_table=True) -> ChainOutput:
    """Apply the receiver chain of the paper's Figure 4 (docs/theory.md §5, §7, §8) to a waveform cube.

    waveforms_j : (H, W, B) float32 signal energy per pixel per time bin [J] (no background: that is added here).
    settings    : :class:`ChainSettings` (``settings.detector`` switches the steps).
    rng         : ``np.random.Generator``, ``SeedSequence`` or int seed.  Same seed → identical output,
                  independent of the thread count.

    noise_table : draw the bins without signal photo-electrons from the exact tabulated code distribution
                  (:class:`CodeTable`; A/D on, read noise ≥ 0.002 Δ).  False forces the per-bin route (tests).

    Ideal mode returns ``waveforms_j`` itself (bit for bit) and reports every step skipped.
    """
    plan = _chain_plan(waveforms_j, settings, rng, noise_table)
    return plan if isinstance(plan, ChainOutput) else run_chain_plans([plan])[0]


def apply_receiver_chains(cubes, settings: ChainSettings, rngs, *, noise_table=True) -> list:
    """:func:`apply_receiver_chain` of each cube with its own ``rng`` (the same detector), the blocks of all the
    cubes drawn in one parallel pass and then their per-bin tails in one: the outputs of the separate calls, bit
    for bit (each cube's blocks, streams and tail parts are the same; only the threads' order of work changes),
    without a thread waiting at the end of each small cube (the statistical route's windows: one cube per window
    length, most of them a block or two)."""
    validate(settings.detector)  # (once: the same detector for every cube)
    plans = [_chain_plan(c, settings, r, noise_table, checked=True) for c, r in zip(cubes, rngs)]
    todo = [k for k, pl in enumerate(plans) if not isinstance(pl, ChainOutput)]
    outs = list(plans)
    for k, o in zip(todo, run_chain_plans([plans[k] for k in todo])):
        outs[k] = o
    return outs


class _ChainPlan:
    """A chain call prepared up to its blocks (:func:`_chain_plan`): ``blocks`` for ``work``, then ``tail_parts``
    (callables, after all blocks), then ``finish`` (the report and the output)."""

    def __init__(self, blocks, work, tail_parts, finish, threads):
        self.blocks, self.work, self.tail_parts, self.finish, self.threads = blocks, work, tail_parts, finish, threads


def run_chain_plans(plans) -> list:
    """Run prepared chain calls: every plan's blocks in one :func:`map_list`, then every plan's tail parts in one,
    then each plan's finish, in the plans' order.  Returns their ChainOutputs."""
    if not plans:
        return []
    threads = max(pl.threads for pl in plans)
    items = [(k, blk) for k, pl in enumerate(plans) for blk in pl.blocks]
    done = map_list(lambda it: plans[it[0]].work(it[1]), items, threads)
    stats = [[] for _ in plans]
    for (k, _), st in zip(items, done):
        stats[k].append(st)
    parts = [(k, f) for k, pl in enumerate(plans) for f in pl.tail_parts(stats[k])]
    for (k, _), st in zip(parts, map_list(lambda it: it[1](), parts, threads)):
        stats[k].append(st)
    return [pl.finish(st) for pl, st in zip(plans, stats)]


def _chain_plan(waveforms_j, settings: ChainSettings, rng, noise_table=True, checked=False):
    """:func:`apply_receiver_chain` up to its blocks: a ChainOutput when nothing is left to draw in blocks (ideal
    mode, Geiger), else a :class:`_ChainPlan`.  ``checked``: the caller has validated ``settings.detector``."""
    det = settings.detector
    if not checked:
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

    # input check (NaN or Inf first, then negative energies; nothing is returned for a bad cube).  A float32
    # cube that reaches the blocks unchanged (no optics MTF) is checked on the table route by the compiled
    # scan that finds each block's signal bins, in parallel and without a pass of its own; otherwise here.
    deferred = cube.dtype == np.float32 and not det.enable_optics_mtf and det.detector_type != "geiger"
    if not deferred:
        _check_energies(cube)
    H, W, B = cube.shape
    ss = _seed_sequence(rng)
    run, skip = report["steps_run"], report["steps_skipped"]
    geiger = det.detector_type == "geiger"

    # Quant: J -> mean photons (deterministic factor, fused into the block kernel); optics MTF acts on means
    k_sig = float(photons_per_joule(settings.wavelength_m))
    run.append("photon_conversion")
    src = cube
    if det.enable_optics_mtf:
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
        spk = speckle_gain_field((H, W), det.speckle_dof, _child(ss, 1), correlated=det.speckle_correlated,
                                 wavelength_m=settings.wavelength_m,
                                 aperture_diameter_m=settings.aperture_diameter_m,
                                 ifov_rad=settings.ifov_x_rad).astype(np.float32).reshape(-1)
        run.append("speckle")
    else:
        skip.append("speckle")

    tau = settings.bin_width_s
    b_mult = 0.0
    pix_rate = _pixel_rate(settings, H, W)
    b_rows = None  # per-pixel background primaries per bin, added to b_mult
    if pix_rate is not None:
        if det.enable_background:
            b_rows = background_photons(pix_rate.reshape(-1), tau) * det.quantum_efficiency
        report["pixel_background"] = background_summary(pix_rate)
    if det.enable_background and (det.background_rate_photons_per_s > 0 or b_rows is not None):
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
        hist = _geiger_chain(src, k_sig, spk, b_mult + ds if b_rows is None else b_mult + ds + b_rows, det, ss,
                             report)
        report["units"] = "detections"
        report["noise_sigma_floor"] = noise_sigma_floor(det, tau)
        pixel_noise = None if pix_rate is None else \
            {"noise_sigma_floor": noise_sigma_floor(det, tau, pix_rate)}
        return ChainOutput(hist, report, pixel_noise=pixel_noise)

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
    if b_rows is not None:  # one code distribution per background level: the per-bin route
        report["noise_table_refused"] = "per-pixel background (sunlight reflected by the scene)"
    elif noise_table and use_adc and sigma_r >= TABLE_MIN_SIGMA_STEPS * step:
        table, refused = noise_tables(step, b_mult, gain, F, shot, ds, sigma_r, det.adc_offset_counts,
                                       int(det.adc_bits), np.dtype(out_dtype).str)
        if refused:  # too many codes: per-bin route
            report["noise_table_refused"] = refused
    report["noise_sampling"] = "table" if table is not None else "per-bin"
    if table is not None and shot:  # which exact Poisson sampler drew the signal bins' and the per-bin tail's counts
        report["poisson_sampler"] = POISSON_SAMPLER
    if deferred and table is None:
        _check_energies(cube)
    if table is not None:
        report["noise_table"] = {"codes": table.n_entries, "ambiguous_cells": table.n_ambiguous_cells,
                                 "probability_step": 2.0 ** -P_BITS, "max_probability_error": table.max_prob_error}
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
        pq = np.diff(np.concatenate([[0], table.T.astype(np.int64)])) / 2.0 ** P_BITS
        c = table.code.astype(np.float64)
        m0 = float(np.dot(pq, c))
        report["noise_mean"], report["noise_sigma"] = m0, float(np.sqrt(np.dot(pq, (c - m0) ** 2)))
        m2, m3, m4 = (float(np.dot(pq, (c - m0) ** r)) for r in (2, 3, 4))
        report["noise_cumulants"] = [m0, m2, m3, m4 - 3.0 * m2 * m2]  # exact, from the code distribution
    else:
        m0, var0, _ = bin_moments(det, 0.0, tau)  # the same switches (Sheppard's Δ²/12 for the A/D)
        m0, var0 = float(m0), float(var0)
        if use_adc:
            report["noise_mean"] = m0 / step + det.adc_offset_counts
            report["noise_sigma"] = math.sqrt(var0) / step
        else:
            report["noise_mean"], report["noise_sigma"] = m0, math.sqrt(var0)
        report["noise_cumulants"] = _noise_cumulants(report["noise_mean"], b_mult, ds, shot, gain, F, sigma_r,
                                                     step if use_adc else 0.0)
    report["noise_sigma_floor"] = noise_sigma_floor(det, tau)
    pixel_noise = None
    if pix_rate is not None:  # the same moments pixel by pixel
        m_p, var_p, _ = bin_moments(det, 0.0, tau, pix_rate)
        m_p, sd_p = np.broadcast_to(m_p, (H, W)), np.broadcast_to(np.sqrt(var_p), (H, W))
        if use_adc:
            m_p, sd_p = m_p / step + det.adc_offset_counts, sd_p / step
        pixel_noise = {"noise_mean": np.array(m_p, dtype=np.float64), "noise_sigma": np.array(sd_p, np.float64),
                       "noise_sigma_floor": np.broadcast_to(noise_sigma_floor(det, tau, pix_rate), (H, W)).copy()}

    src2 = np.ascontiguousarray(src, dtype=np.float32).reshape(H * W, B)
    rows = max(1, (_BLOCK_SAMPLES if table is None else TABLE_BLOCK_SAMPLES) // max(B, 1))
    blocks = [(i, r0, min(r0 + rows, H * W)) for i, r0 in enumerate(range(0, H * W, rows))]
    params = dict(k_sig=k_sig, b_mult=b_mult, ds=ds, ds_gauss=ds_gauss, shot=shot, gain=gain, F=F,
                  sigma_r=sigma_r, adc=use_adc, bits=det.adc_bits, fs=det.adc_full_scale_e,
                  offset=det.adc_offset_counts)

    # table route: counter-based streams, one 64-bit key per block for the signal-free bins' uniforms (all keys
    # drawn from the child (3,) of the seed: one ``generate_state`` for the frame) and one for the uniforms of
    # the signal bins' Poisson counts (child (4,))
    keys = None if table is None else _child_ss(ss, 3).generate_state(len(blocks), np.uint64)
    pkeys = None if table is None else _child_ss(ss, 4).generate_state(len(blocks), np.uint64)

    def work(blk):
        i, r0, r1 = blk
        ws = _scratch_of_thread()
        if table is None:
            return _process_block(src2[r0:r1], out[r0:r1], _child(ss, 0, i), None if spk is None else spk[r0:r1],
                                  params, ws, None if b_rows is None else b_rows[r0:r1])
        st = process_block_table(src2[r0:r1], out[r0:r1], lambda: _child(ss, 0, i), keys[i], pkeys[i],
                                  None if spk is None else spk[r0:r1], params, ws, table)
        if "tail" in st:  # (bin indices in the block → in the cube)
            st["tail"] = (st["tail"][0] + r0 * B, st["tail"][1])
        return st

    threads = det.threads or settings.run_threads or (os.cpu_count() or 1)  # 0: as the run (run.threads = 1 is 1)

    def finish(stats):
        if deferred and table is not None:
            _energy_error(any(s.get("n_nonfinite", 0) for s in stats), any(s.get("n_negative", 0) for s in stats))
        for key in ("n_mean_clipped", "n_adc_low", "n_adc_high"):
            report[key] = int(sum(s[key] for s in stats))
        if table is not None:
            report["noise_table"]["caught_bins_from_tables"] = int(sum(s.get("caught_table", 0) for s in stats))
            report["noise_table"]["caught_bins_per_bin"] = int(sum(s.get("caught_per_bin", 0) for s in stats))
        if report["n_mean_clipped"]:
            report["approximations"].append(f"{report['n_mean_clipped']} bins had a mean above {MEAN_CAP:g} "
                                            f"primaries and were clipped to it")
        if any(s["normal_bins"] for s in stats):
            report["approximations"].append(f"{sum(s['normal_bins'] for s in stats)} bins with Poisson mean ≥ "
                                            f"{NORMAL_MEAN:g} drawn as normal (exact mean and variance)")
        pmf = None
        if table is not None:
            pmf = (table.code.astype(np.float64), np.diff(np.concatenate([[0], table.T.astype(np.int64)])) / 2.0 ** P_BITS)
        return ChainOutput(out.reshape(H, W, B), report, pmf, pixel_noise)

    # (the blocks and then the tail parts on the caller and the shared pool, core/threads.py: run_chain_plans)
    return _ChainPlan(blocks, work, lambda stats: _tail_parts(stats, deferred, params, ss, out), finish, threads)


def background_summary(rate) -> dict:
    """The report's record of a per-pixel (per-pulse) background: mean, largest, pixels with any."""
    rate = np.asarray(rate, dtype=np.float64)
    return {"mean_rate_photons_per_s": float(rate.mean()) if rate.size else 0.0,
            "max_rate_photons_per_s": float(rate.max()) if rate.size else 0.0,
            "pixels_with_background": int(np.count_nonzero(rate))}


def _pixel_rate(settings: ChainSettings, H, W):
    """``settings.pixel_background_rate`` checked ((H, W), finite, ≥ 0) as float64, or None."""
    rate = settings.pixel_background_rate
    if rate is None:
        return None
    rate = np.asarray(rate, dtype=np.float64)
    if rate.shape != (H, W):
        raise ValueError(f"pixel_background_rate must be (H, W) = ({H}, {W}), got shape {rate.shape}")
    if not np.all(np.isfinite(rate)) or (rate.size and rate.min() < 0):
        raise ValueError("pixel_background_rate must be finite and ≥ 0 photons/s")
    return rate


def _noise_cumulants(mean, b_mult, ds, shot, gain, F, sigma_r, step):
    """[κ1, κ2, κ3, κ4] of a signal-free bin in output units (per-bin route): compound Poisson(b_mult) of
    single-electron gains Gamma(1/(F − 1), G(F − 1)) (G exactly when F = 1), E g^r = θ^r a(a+1)…(a+r−1), plus
    Poisson(ds) surface dark, Gaussian read noise and (A/D on) Sheppard's Δ²/12 and −Δ⁴/120 for the rounding.
    Without shot noise the primaries add no cumulant above the first."""
    k = [0.0, sigma_r ** 2, 0.0, 0.0]
    if shot:
        if F > 1.0:
            a, th = 1.0 / (F - 1.0), gain * (F - 1.0)
            moments = [th ** r * math.prod(a + i for i in range(r)) for r in (2, 3, 4)]
        else:
            moments = [gain ** r for r in (2, 3, 4)]
        for i, m in enumerate(moments):
            k[i + 1] += b_mult * m + ds
    if step > 0:
        k[1] += step ** 2 / 12.0
        k[3] -= step ** 4 / 120.0
        k = [k[r] / step ** (r + 1) for r in range(4)]
    k[0] = float(mean)
    return k


_THREAD_SCRATCH = threading.local()


def _scratch_of_thread() -> dict:
    """This thread's scratch buffers (:func:`.table_route.scratch`), kept between calls: a block's buffers are
    sized by the block (table route: 6 MB, plus 64 B per signal bin of the busiest block, ≤ 40 MB), and fresh
    ones cost their first-touch page faults every frame."""
    ws = getattr(_THREAD_SCRATCH, "ws", None)
    if ws is None:
        ws = _THREAD_SCRATCH.ws = {}
    return ws


def _energy_error(nonfinite, negative):
    if nonfinite:
        raise ValueError("waveforms_j contains NaN or Inf")
    if negative:
        raise ValueError("waveforms_j contains negative energies")


def _check_energies(cube):
    """The input check as one pass of NumPy reductions (cubes that do not go through the table route's scan)."""
    lo, hi = (cube.min(), cube.max()) if cube.size else (0.0, 0.0)  # (two SIMD passes over the cube)
    _energy_error(not (np.isfinite(lo) and np.isfinite(hi)), lo < 0)


#: The table route's per-bin draws (bins that caught more than 16 photo-electrons) are split into this many
#: fixed parts by position, each with its own generator (spawn key (5, k)), drawn in parallel.
_TAIL_PARTS = 2


def _tail_parts(stats, deferred, p, ss, out):
    """Table route, after the blocks: the bins they left for per-bin draws (``"tail"`` of their stats), all
    blocks together in block order, in :data:`_TAIL_PARTS` fixed parts, as callables (run on the caller's threads
    after every block: :func:`run_chain_plans`), each returning its stats (A/D clip counts); none when a block
    found bad input (raised later)."""
    tails = [s["tail"] for s in stats if "tail" in s]
    if not tails or (deferred and any(s.get("n_nonfinite", 0) or s.get("n_negative", 0) for s in stats)):
        return []
    idx, n = np.concatenate([t[0] for t in tails]), np.concatenate([t[1] for t in tails])
    cuts = [len(idx) * k // _TAIL_PARTS for k in range(_TAIL_PARTS + 1)]
    of = out.reshape(-1)

    def part(k):
        lo, hi = per_bin_tail(idx[cuts[k]:cuts[k + 1]], n[cuts[k]:cuts[k + 1]], p, _child(ss, 5, k), of)
        return {"n_mean_clipped": 0, "n_adc_low": lo, "n_adc_high": hi, "normal_bins": 0}

    return [lambda k=k: part(k) for k in range(_TAIL_PARTS)]


def _process_block(E, out, rng, spk, p, ws, b_rows=None) -> dict:
    """One block of pixels (P, B): exact sampling of the §8 statistics, written into ``out``.
    ``ws``: per-thread scratch buffers (reused across blocks: fresh large allocations are slow).
    ``b_rows``: (P,) background primaries per bin of each pixel, added to ``p["b_mult"]`` (None: none)."""
    P, B = E.shape
    N = P * B
    stats = {"n_mean_clipped": 0, "n_adc_low": 0, "n_adc_high": 0, "normal_bins": 0}
    s = scratch(ws, "s", N, np.float32).reshape(P, B)
    with np.errstate(over="ignore"):  # overflow -> inf -> clipped to MEAN_CAP and reported below
        np.multiply(E, np.float32(p["k_sig"]), out=s)  # mean signal primaries (after eta)
    if spk is not None:
        with np.errstate(over="ignore"):
            s *= spk[:, None]
    sf = s.reshape(-1)
    smax = float(sf.max()) if N else 0.0
    if not math.isfinite(smax) or smax > MEAN_CAP:
        bad = ~(sf <= MEAN_CAP)
        stats["n_mean_clipped"] = int(np.count_nonzero(bad))
        sf[bad] = MEAN_CAP
        smax = MEAN_CAP
    if p["shot"]:
        n = scratch(ws, "n", N, np.float32).reshape(P, B)
        nf = n.reshape(-1)
        nf.fill(0.0)
        if smax > 0:
            if smax >= DENSE_MEAN:  # bright bins: one exact Poisson draw each
                hi = np.flatnonzero(sf >= DENSE_MEAN)
                cnt, nb = poisson_dense(sf[hi], rng)
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
        if b_rows is not None:
            poisson_uniform_rows(p["b_mult"] + b_rows, P, B, rng, out=n)
        elif p["b_mult"] > 0:
            poisson_uniform_rows(p["b_mult"], P, B, rng, out=n)
    else:
        n = s
        if b_rows is not None:
            n += (p["b_mult"] + b_rows).astype(np.float32)[:, None]
        elif p["b_mult"] > 0:
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
        z = scratch(ws, "z", N, np.float32).reshape(P, B)
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
