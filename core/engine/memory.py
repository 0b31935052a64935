"""Memory of a flash run, estimated before anything is allocated (the planner refuses what cannot fit).

A run's peak memory is the whole-frame arrays it keeps plus what every worker thread holds for its block:

* waveform cube (float32, pixels × bins) when saved or needed by a whole-cube stage (turbulence blur, the
  noisy receiver chain); the noisy chain adds its digital cube and float32/float64 working copies (≈ 4 cubes);
* per block and thread: the block's rays (≈ ``BYTES_PER_RAY`` each for directions, hits, weights, cell
  geometry and their hit-filtered copies; the adaptive pattern's refinement at worst re-traces every pixel of
  the block with refine² × the rays), the waveform rows (``BLOCK_WAVEFORM_BYTES``, float64) and echo
  detection's temporaries on them (≈ 3 ×), and the waveform binning's (ray, bin) terms (``waveform.MAX_TERMS``
  × ≈ 56 B) where it forms them in NumPy (the splat method, the rectangular pulse's cell boxes; the exact
  Gaussian binning is one compiled pass without them);
* products: energy/range/intensity images, per-echo images and the point cloud (≤ max_echoes points per
  pixel, ≈ 120 B each).

The other systems (:func:`estimate_memory` dispatches on ``system_type``):

* scanner: the per-pulse record (≈ ``BYTES_PER_PULSE``), the point cloud (≤ max_echoes points per pulse, twice
  while the blocks' echoes are merged), the saved float32 waveforms (pulses × bins), and per block and thread
  the pulses' sub-rays, their float64 waveforms (full gate when saved or noisy; ≤ the gate in windows
  otherwise) with binning and detection temporaries, and the noisy chain on one tile of pulses;
* gated viewing: the float64 slice stack and its (H, W, slices) copy, the float32 stacks of the range
  estimate (and the noisy chain's), the float64 profile and the centroid window; one energy image and one
  atmosphere realisation (scintillation pattern) per slice when turbulence is drawn per slice; per block and
  thread the rays, the per-slice energies and the (ray, slice) gate terms (≤ ``GATE_MAX_TERMS``).

Noisy receivers add, per (pixel, bin): ``NOISY_BYTES_PER_SAMPLE`` (linear mode: the uint16 digital cube and
the detector's per-thread rows) or ``GEIGER_BYTES_PER_SAMPLE`` (float64 rates and pile-up probabilities, the
int64 histogram, then the detection).

Every system also estimates its work — elementary samples: rays traced, (pixel, bin) samples through the
waveform, receiver chain and detection, Geiger per-pulse arrival searches, gated (ray, slice) terms — and a
run whose work would take longer than ``run.max_work_s`` on this machine (rays at :data:`RAYS_PER_S`, samples at
:data:`SAMPLES_PER_S`, per thread, over the run's threads) is refused, naming the setting that drives it, the
estimated time, and ``run.max_work_s``.

The limit is ``run.max_memory_bytes`` and the memory the system has available (Linux: MemAvailable).
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import ConfigError
from ..config.settings import SimulationConfig
from ..config.derived import n_scan_pulses
from ..physics.laser import pulse_half_support_s
from .atmosphere_stage import turbulence_switches
from ..physics.waveform import MAX_TERMS, binning_method

#: Waveform memory of one block (float64 while accumulating): bounds the memory of a run.
BLOCK_WAVEFORM_BYTES = 64 * 2**20
#: Scanner: pulses per random-number tile of the noisy receiver (streams are per tile, so results do not depend
#: on blocks); blocks hold whole tiles.
SCAN_NOISE_TILE_PULSES = 4096
#: Gated viewing: largest number of (ray, slice) gate evaluations at once (bounds memory, ~32 MB of float64
#: each).
GATE_MAX_TERMS = 4_000_000
BYTES_PER_RAY = 400
BYTES_PER_TERM = 56
BYTES_PER_POINT = 120
#: Scanner: per pulse (time, pose, axis, channel, angle, energy, echo count and the output record's copies).
BYTES_PER_PULSE = 110
#: Noisy linear receiver and its echo detection, per (pixel, bin) beyond the float32 cube: the uint16 codes, the
#: detector's per-thread rows and the echoes (measured 7.6 B in all, cube included, from the resident peak of
#: a 256² px × 1024-bin frame, points only or cube saved; 36 B before the compiled chain and detection).
NOISY_BYTES_PER_SAMPLE = 8
#: Geiger mode and its echo detection, per (pixel, bin) beyond the float32 cube (measured 52 B in all).
GEIGER_BYTES_PER_SAMPLE = 48
#: Gated viewing: bytes per (ray, slice) gate term alive at once (indices, responses, weights and their
#: hit-filtered copies).
BYTES_PER_GATE_TERM = 80
#: Elementary samples (waveform, receiver chain, detection, gate terms) computed per second by one thread
#: (measured 1–5e7 on one core: noisy flash 2.5e7, scanner 0.8e7, Geiger per-pulse 1.2–2.2e7).
SAMPLES_PER_S = 2.5e7
#: Rays (sub-rays) traced per second by one thread, with their radiometry and waveform splatting (measured on
#: the flash demo, 64² px × 4² sub-rays: trace + rays + radiometry + waveform stages 0.38 s summed over threads
#: for 65 536 rays: 1.7e5 rays/s).
RAYS_PER_S = 1.7e5
#: Work parts counted in rays (the others in samples).
RAY_PARTS = ("rays",)


def available_memory_bytes() -> int | None:
    """Memory the system can give this process now (Linux /proc/meminfo MemAvailable; None if unknown)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _chain_bytes_per_sample(config: SimulationConfig) -> int:
    det = config.detector
    if det.mode != "noisy":
        return 0
    return GEIGER_BYTES_PER_SAMPLE if det.detector_type == "geiger" else NOISY_BYTES_PER_SAMPLE


def _chain_work(config: SimulationConfig, pixels: int, n_bins: int) -> tuple[float, str]:
    """Samples the receiver chain and detection process for ``pixels`` waveforms of ``n_bins`` bins, and the
    setting that drives them."""
    det = config.detector
    if det.mode != "noisy":
        return 0.0, "gate.n_bins"
    work = 10.0 * pixels * n_bins  # chain, matched filter, robust noise, detection (≈ 10 passes)
    if det.detector_type == "geiger" and (det.speckle_dof > 0 or det.geiger_dead_time_bins < n_bins):
        # per-pulse simulation: a bisection for every arrival of every pulse
        arrivals = 1 if det.geiger_dead_time_bins >= n_bins else max(1, n_bins // (det.geiger_dead_time_bins + 1))
        work += float(det.geiger_pulses) * pixels * arrivals * (2 + max(1, int(n_bins).bit_length()))
        return work, "detector.geiger_pulses"
    return work, "gate.n_bins"


def estimate_flash_memory(config: SimulationConfig) -> dict:
    """Estimated peak bytes of a flash (or profiler) frame, by part, and the setting that drives each part."""

    rx, gate, run = config.receiver, config.gate, config.run
    pixels = 1 if config.system_type == "profiler" else rx.width_px * rx.height_px
    s2 = rx.subsamples ** 2
    threads = max(1, run.threads or os.cpu_count() or 1)
    blur = config.atmosphere.cn2_m_23 > 0 and config.atmosphere.turbulence_blur != "none"
    noisy = config.detector.mode == "noisy"
    cube = pixels * gate.n_bins * 4
    keep_cube = run.save_waveforms or blur or noisy
    per_block_px = max(1, min(run.chunk_rays // s2, BLOCK_WAVEFORM_BYTES // (8 * gate.n_bins)))
    per_block_px = min(per_block_px, pixels)
    rays = per_block_px * s2
    if rx.subray_pattern == "adaptive":
        rays += per_block_px * s2 * rx.subray_refine ** 2  # worst case: every pixel of the block refined
    wf_rows = per_block_px * gate.n_bins * 8
    numpy_terms = (binning_method(config.laser, gate) == "splat"
                   or (config.laser.pulse_shape != "gaussian" and rx.cell_range_spread))
    terms = MAX_TERMS * BYTES_PER_TERM if numpy_terms else 0
    parts = {
        "waveform_cube": (cube if keep_cube else 0, "gate.n_bins"),
        "receiver_chain": (pixels * gate.n_bins * _chain_bytes_per_sample(config), "gate.n_bins"),
        "block_rays": (threads * rays * BYTES_PER_RAY,
                       "receiver.subray_refine" if rx.subray_pattern == "adaptive" else "run.chunk_rays"),
        "block_waveforms": (threads * (4 * wf_rows + terms), "run.threads"),
        "products": (pixels * (8 + 8 * config.detection.max_echoes)
                     + pixels * config.detection.max_echoes * BYTES_PER_POINT, "receiver.width_px"),
    }
    rays_total = pixels * s2 * (1 + (rx.subray_refine ** 2 if rx.subray_pattern == "adaptive" else 0))
    chain_work, chain_field = _chain_work(config, pixels, gate.n_bins)
    work = {"rays": (float(rays_total), "receiver.subsamples"),
            "waveforms": (2.0 * pixels * gate.n_bins if keep_cube else 0.0, "gate.n_bins"),
            "receiver_chain": (chain_work, chain_field)}
    advice = {
        "waveform_cube": "fewer bins or pixels, or run.save_waveforms = false (points only; not possible with "
                         "turbulence blur or the noisy receiver, which need the whole cube)",
        "receiver_chain": "fewer bins or pixels, or detector.mode = ideal",
        "block_rays": "a smaller run.chunk_rays (fewer rays per block)" if parts["block_rays"][1] == "run.chunk_rays"
                      else "a smaller receiver.subray_refine or receiver.subsamples",
        "block_waveforms": "fewer run.threads (each thread holds one block)",
        "products": "fewer pixels or detection.max_echoes",
        "rays": "fewer pixels or sub-rays (receiver.subsamples, receiver.subray_refine)",
        "waveforms": "fewer bins or pixels",
    }
    return _estimate(parts, work, advice, threads=threads, pixels_per_block=per_block_px)


def _estimate(parts: dict, work: dict, advice: dict, **extra) -> dict:
    """The estimate record: bytes and work by part, the setting driving each part, advice for the largest."""
    out = {"parts": {k: int(v[0]) for k, v in parts.items()}, "fields": {k: v[1] for k, v in parts.items()},
           "total": int(sum(v[0] for v in parts.values())),
           "work_parts": {k: float(v[0]) for k, v in work.items()},
           "work_fields": {k: v[1] for k, v in work.items()},
           "work": float(sum(v[0] for v in work.values())), "advice": advice}
    out.update(extra)
    threads = int(extra.get("threads", 1))
    out["work_threads"] = threads
    out["seconds_parts"] = work_seconds(out["work_parts"], threads)
    out["seconds"] = float(sum(out["seconds_parts"].values()))
    return out


def estimate_scan_memory(config: SimulationConfig) -> dict:
    """Estimated peak bytes and work of a scanner frame (module docstring), by part."""
    run, gate, det = config.run, config.gate, config.detector
    n_pulses = n_scan_pulses(config)
    rings = config.scanner.beam_subray_rings
    m = 1 + 3 * rings * (rings + 1)  # sub-rays of a pulse (scanner.beam_subrays)
    threads = max(1, run.threads or os.cpu_count() or 1)
    noisy, save = det.mode == "noisy", run.save_waveforms
    tile = SCAN_NOISE_TILE_PULSES
    per_block = max(tile, (max(1, run.chunk_rays // m) // tile) * tile)
    if save or noisy:
        per_block = max(tile, min(per_block, (64 * 2 ** 20 // (8 * gate.n_bins)) // tile * tile))
    per_block = min(per_block, n_pulses)
    active = min(threads, -(-n_pulses // per_block))
    e_max = config.detection.max_echoes
    # float64 waveform rows per block: the full gate (+ binning and detection temporaries ≈ 4.5 ×) when saved
    # or noisy; windows of at most the gate otherwise
    wf_block = per_block * gate.n_bins * 8 * (4.5 if (save or noisy) else 1.0)
    chain_block = min(tile, per_block) * gate.n_bins * _chain_bytes_per_sample(config) if noisy else 0
    pulses_field = "scanner.n_channels" if config.scanner.pattern == "rotating" else "scanner.duration_s"
    parts = {
        "pulses": (n_pulses * BYTES_PER_PULSE, pulses_field),
        "points": (n_pulses * e_max * (BYTES_PER_POINT + 40), pulses_field),
        "waveform_cube": (n_pulses * gate.n_bins * 4 if save else 0, "run.save_waveforms"),
        "block_rays": (active * per_block * m * BYTES_PER_RAY, "scanner.beam_subray_rings"),
        "block_waveforms": (active * (wf_block + chain_block + min(per_block * m, 4_000_000) * BYTES_PER_TERM),
                            "gate.n_bins" if (save or noisy) else "run.threads"),
    }
    chain_work, chain_field = _chain_work(config, n_pulses, gate.n_bins)
    work = {"rays": (float(n_pulses) * m, pulses_field),
            "waveforms": (2.0 * n_pulses * (gate.n_bins if (save or noisy) else min(gate.n_bins, 64)),
                          "gate.n_bins"),
            "receiver_chain": (chain_work, chain_field)}
    scan = ("fewer pulses (a shorter scanner.duration_s, a lower scanner.pulse_rate_hz"
            + (", fewer scanner.n_channels" if config.scanner.pattern == "rotating" else "") + ")")
    advice = {
        "pulses": scan, "rays": scan + " or fewer scanner.beam_subray_rings",
        "points": scan + " or fewer detection.max_echoes",
        "waveform_cube": "run.save_waveforms = false (points only), fewer bins or " + scan,
        "block_rays": "fewer scanner.beam_subray_rings or a smaller run.chunk_rays",
        "block_waveforms": "fewer bins (gate.n_bins) or fewer run.threads (each thread holds one block)",
        "receiver_chain": "fewer bins, detector.mode = ideal, or " + scan,
        "waveforms": "fewer bins or " + scan,
    }
    return _estimate(parts, work, advice, threads=threads, pulses_per_block=per_block, n_pulses=n_pulses)


def estimate_gated_memory(config: SimulationConfig, pattern_bytes: int = 0) -> dict:
    """Estimated peak bytes and work of a gated-viewing sweep (module docstring), by part.  ``pattern_bytes``:
    the memory of one atmosphere realisation (known once the first slice's is drawn; 0 before)."""
    rx, g, run = config.receiver, config.gated, config.run
    pixels, s2, n_sl = rx.width_px * rx.height_px, rx.subsamples ** 2, g.n_slices
    threads = max(1, run.threads or os.cpu_count() or 1)
    skipped = turbulence_switches(config)
    per_slice = n_sl if any(s not in skipped for s in ("scintillation", "beam_wander")) else 1
    block_px = min(max(1, run.chunk_rays // s2), pixels)
    rays = block_px * s2
    active = min(threads, -(-pixels // block_px))
    support = pulse_half_support_s(config.laser) + 0.5 * g.shutter_edge_s
    span = min(n_sl, int((g.gate_width_s + 2 * support) / g.delay_step_s) + 2)
    reach = int((0.5 * g.gate_width_s + pulse_half_support_s(config.laser) + g.shutter_edge_s)
                / g.delay_step_s) + 2
    window = min(2 * reach + 1, n_sl) if g.range_method == "centroid" else 3
    noisy = config.detector.mode == "noisy"
    stack = pixels * n_sl
    parts = {
        # float64 slices and their (H, W, slices) copy, float32 stack/profile/maximum/result, float64 profile
        "slice_stack": (stack * (8 + 8 + 4 * 4 + 8) + (stack * 8 if noisy else 0), "gated.n_slices"),
        "range_estimate": (pixels * window * 8 * 6, "gated.n_slices"),
        "slice_atmosphere": (per_slice * (pixels * 8 + pattern_bytes), "gated.n_slices"),
        "block_rays": (active * rays * BYTES_PER_RAY, "run.chunk_rays"),
        "block_slice_energies": (active * rays * 16 * per_slice if per_slice > 1 else 0, "gated.n_slices"),
        "block_gating": (active * (min(rays * span, GATE_MAX_TERMS) * BYTES_PER_GATE_TERM + 16 * n_sl * block_px),
                         "run.threads"),
    }
    work = {"rays": (float(pixels) * s2, "receiver.subsamples"),
            "gating": (float(pixels) * s2 * span * 4, "gated.n_slices"),
            "slices": (10.0 * stack * (per_slice > 1 or noisy) + float(stack), "gated.n_slices")}
    advice = {
        "slice_stack": "fewer slices or pixels",
        "range_estimate": "fewer pixels, or range_method peak",
        "slice_atmosphere": "fewer slices, or no per-slice turbulence (atmosphere.scintillation/beam_wander = "
                            "false)",
        "block_rays": "a smaller run.chunk_rays or fewer receiver.subsamples",
        "block_slice_energies": "fewer slices or a smaller run.chunk_rays, or no per-slice turbulence",
        "block_gating": "fewer run.threads (each thread holds one block) or a smaller run.chunk_rays",
        "rays": "fewer pixels or receiver.subsamples",
        "gating": "fewer slices or a shorter gate",
        "slices": "fewer slices or pixels",
    }
    return _estimate(parts, work, advice, threads=threads, pixels_per_block=block_px,
                     slices_per_atmosphere=per_slice)


def held_bytes(obj, depth: int = 2) -> int:
    """Bytes of the NumPy arrays an object holds (itself, or its attributes ``depth`` levels down): e.g. one
    atmosphere realisation, measured before the others are drawn."""
    if isinstance(obj, np.ndarray):
        return int(obj.nbytes)
    if depth == 0 or not hasattr(obj, "__dict__"):
        return 0
    return sum(held_bytes(v, depth - 1) for v in vars(obj).values())


def estimate_memory(config: SimulationConfig, **kwargs) -> dict:
    """Estimated peak bytes and work of one frame of ``config.system_type`` (flash, profiler, scanner, gated)."""
    if config.system_type == "scanner":
        return estimate_scan_memory(config)
    if config.system_type == "gated":
        return estimate_gated_memory(config, **kwargs)
    return estimate_flash_memory(config)


def _value(config, field):
    group, name = field.split(".")
    return getattr(getattr(config, group), name)


def check_memory(config: SimulationConfig, available: int | None = -1, estimate: dict | None = None,
                 frames: int = 1) -> dict:
    """Raise ConfigError, naming the setting that drives the largest part, if the run's estimated memory
    exceeds ``run.max_memory_bytes`` or the available memory (``available``: bytes, None = unknown, −1 = ask
    the system), or its work exceeds ``MAX_WORK_SAMPLES``.  Returns the estimate (``estimate``: one already
    made, e.g. with the first atmosphere realisation's size).  ``frames``: the work of that many frames (a
    sequence, checked before its first frame) is compared with ``run.max_work_s``."""
    est = estimate if estimate is not None else estimate_memory(config)
    limit, where = config.run.max_memory_bytes, "run.max_memory_bytes"
    if available == -1:
        available = available_memory_bytes()
    if available is not None and available < limit:
        limit, where = available, "the memory available now"
    if est["total"] > limit:
        parts = est["parts"]
        big = max(parts, key=parts.get)
        field = est["fields"][big]
        gib = 2.0 ** 30
        detail = ", ".join(f"{k} {v / gib:.2f}" for k, v in parts.items() if v)
        raise ConfigError(field, _value(config, field),
                          f"a run that fits in {where} = {limit / gib:.2f} GiB: this one needs ≈ "
                          f"{est['total'] / gib:.2f} GiB ({detail} GiB); use {est['advice'][big]}, or raise "
                          f"run.max_memory_bytes")
    limit_s = config.run.max_work_s
    frames = max(1, int(frames))
    if est["seconds"] * frames > limit_s:
        secs = est["seconds_parts"]
        big = max(secs, key=secs.get)
        field = est["work_fields"][big]
        detail = ", ".join(f"{est['work_parts'][k]:.2g} {'rays' if k in RAY_PARTS else k + ' samples'}"
                           for k, v in secs.items() if v)
        raise ConfigError(field, _value(config, field),
                          f"a run estimated to take at most run.max_work_s = {limit_s:.0f} s: this one would take "
                          f"≈ {_duration(est['seconds'] * frames)} on {est['work_threads']} thread(s) of this "
                          f"machine ({detail}{f' per frame, {frames} frames' if frames > 1 else ''}); use {est['advice'][big]}, or raise run.max_work_s")
    return est


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


def work_seconds(work_parts: dict, threads: int) -> dict:
    """Estimated seconds of each work part on ``threads`` threads (:data:`RAYS_PER_S`, :data:`SAMPLES_PER_S`)."""
    return {k: float(v) / ((RAYS_PER_S if k in RAY_PARTS else SAMPLES_PER_S) * max(1, threads))
            for k, v in work_parts.items()}
