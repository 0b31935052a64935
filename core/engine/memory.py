"""Memory of a flash run, estimated before anything is allocated (the planner refuses what cannot fit).

A run's peak memory is the whole-frame arrays it keeps plus what every worker thread holds for its block:

* waveform cube (float32, pixels × bins) when saved or needed by a whole-cube stage (turbulence blur, the
  noisy receiver chain); the noisy chain adds its digital cube and float32/float64 working copies (≈ 4 cubes);
* per block and thread: the block's rays (≈ ``BYTES_PER_RAY`` each for directions, hits, weights, cell
  geometry and their hit-filtered copies; the adaptive pattern's refinement at worst re-traces every pixel of
  the block with refine² × the rays), the waveform rows (``BLOCK_WAVEFORM_BYTES``, float64) and echo
  detection's temporaries on them (≈ 3 ×), and the waveform binning's (ray, bin) terms (``waveform.MAX_TERMS``
  × ≈ 56 B);
* products: energy/range/intensity images, per-echo images and the point cloud (≤ max_echoes points per
  pixel, ≈ 120 B each).

The limit is ``run.max_memory_bytes`` and the memory the system has available (Linux: MemAvailable).
"""
from __future__ import annotations

import os

from ..errors import ConfigError
from ..config.settings import SimulationConfig
from ..physics.waveform import MAX_TERMS

#: Waveform memory of one block (float64 while accumulating): bounds the memory of a run.
BLOCK_WAVEFORM_BYTES = 64 * 2**20
BYTES_PER_RAY = 400
BYTES_PER_TERM = 56
BYTES_PER_POINT = 120


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
    parts = {
        "waveform_cube": (cube if keep_cube else 0, "gate.n_bins"),
        "receiver_chain": (4 * cube if noisy else 0, "gate.n_bins"),
        "block_rays": (threads * rays * BYTES_PER_RAY,
                       "receiver.subray_refine" if rx.subray_pattern == "adaptive" else "run.chunk_rays"),
        "block_waveforms": (threads * (4 * wf_rows + MAX_TERMS * BYTES_PER_TERM), "run.threads"),
        "products": (pixels * (8 + 8 * config.detection.max_echoes)
                     + pixels * config.detection.max_echoes * BYTES_PER_POINT, "receiver.width_px"),
    }
    return {"parts": {k: int(v[0]) for k, v in parts.items()}, "fields": {k: v[1] for k, v in parts.items()},
            "total": int(sum(v[0] for v in parts.values())), "threads": threads, "pixels_per_block": per_block_px}


def _value(config, field):
    group, name = field.split(".")
    return getattr(getattr(config, group), name)


def check_flash_memory(config: SimulationConfig, available: int | None = -1) -> dict:
    """Raise ConfigError, naming the setting that drives the largest part, if the run's estimated memory
    exceeds ``run.max_memory_bytes`` or the available memory (``available``: bytes, None = unknown, −1 = ask
    the system).  Returns the estimate."""
    est = estimate_flash_memory(config)
    limit, where = config.run.max_memory_bytes, "run.max_memory_bytes"
    if available == -1:
        available = available_memory_bytes()
    if available is not None and available < limit:
        limit, where = available, "the memory available now"
    if est["total"] <= limit:
        return est
    parts = est["parts"]
    big = max(parts, key=parts.get)
    field = est["fields"][big]
    advice = {
        "waveform_cube": "fewer bins or pixels, or run.save_waveforms = false (points only; not possible with "
                         "turbulence blur or the noisy receiver, which need the whole cube)",
        "receiver_chain": "fewer bins or pixels, or detector.mode = ideal",
        "block_rays": "a smaller run.chunk_rays (fewer rays per block)" if field == "run.chunk_rays" else
                      "a smaller receiver.subray_refine or receiver.subsamples",
        "block_waveforms": "fewer run.threads (each thread holds one block)",
        "products": "fewer pixels or detection.max_echoes",
    }[big]
    gib = 2.0 ** 30
    detail = ", ".join(f"{k} {v / gib:.2f}" for k, v in parts.items() if v)
    raise ConfigError(field, _value(config, field),
                      f"a run that fits in {where} = {limit / gib:.2f} GiB: this one needs ≈ {est['total'] / gib:.2f} "
                      f"GiB ({detail} GiB); use {advice}, or raise run.max_memory_bytes")
