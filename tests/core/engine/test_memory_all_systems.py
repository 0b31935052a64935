"""Every system estimates its peak memory and its work before starting, and refuses — a ConfigError naming
the setting to change, before anything is traced, allocated or written — what would not fit or would not end
(issue 15: gated sweeps, scanners without saved waveforms, the rotating head with many channels and noisy
Geiger runs ended in MemoryError tracebacks or ran for hours).

The estimate is checked against the measured peak (tracemalloc: NumPy's allocations) of small runs of each
system: it must bound the peak, and by no more than 8× (the fixed per-block terms dominate small runs; at
scale the measured ratios are 1.2–2.2, docs/performance.md)."""
import time
import tracemalloc

import numpy as np
import pytest

from core.engine.memory import (RAYS_PER_S, SAMPLES_PER_S, NOISY_BYTES_PER_SAMPLE, check_memory, estimate_gated_memory,
                                estimate_memory, held_bytes)
from core.errors import ConfigError
from core.geometry.rays import Detector
from core.run import run_simulation, simulate
from scenes import config_for, plate

R = 200.0


def _cfg(system="flash", pixels=32, bins=256, sub=2):
    c = config_for(R, pixels=pixels, subsamples=sub, bins=bins, fov_rad=0.01)
    c.system_type = system
    c.run.threads = 1
    if system == "scanner":
        c.scanner.n_lines, c.scanner.scan_width_rad, c.scanner.scan_height_rad = 20, 0.01, 0.01
    if system == "gated":
        c.gated.n_slices, c.gated.first_delay_s = 60, 2 * R / 299_792_458.0 - 60e-9
    return c


def _refused(tmp_path, cfg, field, *fragments, max_s=5.0):
    t = time.perf_counter()
    with pytest.raises(ConfigError) as exc:
        run_simulation(plate(R, 50.0), np.eye(4), cfg, tmp_path / "run")
    assert time.perf_counter() - t < max_s  # refused up front, not after the work
    assert exc.value.field == field, str(exc.value)
    msg = str(exc.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, msg
    assert list(tmp_path.iterdir()) == []
    return msg


def test_gated_sweep_counts_float64_stacks(tmp_path):
    """512² px × 2000 slices: the old check (float32, one stack: 2 GiB < 4 GiB) let it start; the float64
    stacks alone need ≈ 20 GiB."""
    cfg = _cfg("gated", pixels=512)
    cfg.gated.n_slices = 2000
    assert 512 ** 2 * 2000 * 4 < cfg.run.max_memory_bytes
    _refused(tmp_path, cfg, "gated.n_slices", "slice_stack", "run.max_memory_bytes = 4.00 GiB")


def test_gated_per_slice_atmosphere_is_counted_before_it_is_drawn(tmp_path, monkeypatch):
    """Turbulence drawn per slice: the first slice's realisation is measured, and a sweep whose realisations
    would not fit is refused before the others are drawn."""
    import core.systems.gated as gated
    cfg = _cfg("gated", pixels=32)
    cfg.atmosphere.cn2_m_23 = 1e-14
    cfg.gated.n_slices = 3000
    calls = []
    real = gated.prepare_frame_atmosphere
    monkeypatch.setattr(gated, "prepare_frame_atmosphere", lambda *a, **k: calls.append(1) or real(*a, **k))
    one = real(cfg, Detector.from_settings(cfg.receiver), R, 0, pulse=0)
    size = held_bytes(one)
    assert size > 0
    without = estimate_gated_memory(cfg)["total"]
    with_patterns = estimate_gated_memory(cfg, pattern_bytes=size)["total"]
    assert with_patterns - without == 3000 * size
    cfg.run.max_memory_bytes = (without + with_patterns) // 2
    _refused(tmp_path, cfg, "gated.n_slices", "slice_atmosphere")
    assert len(calls) == 1


def test_scanner_is_checked_without_saved_waveforms(tmp_path):
    """A rotating head with 1024 channels turning once in 100 s at 100 kHz (1e10 pulses), points only:
    refused (≈ TiB), naming the channel count."""
    cfg = _cfg("scanner")
    cfg.run.save_waveforms = False
    s = cfg.scanner
    s.pattern, s.n_channels, s.scan_width_rad, s.scan_rate_hz = "rotating", 1024, 6.28, 0.01
    msg = _refused(tmp_path, cfg, "scanner.n_channels", "pulses", "scanner.duration_s")
    assert float(msg.split("needs ≈ ")[1].split(" GiB")[0]) > 1000


def test_noisy_scanner_with_a_long_gate_is_refused(tmp_path):
    """Noisy receiver: each thread's block holds whole-gate float64 waveforms of ≥ 4096 pulses (1e6 bins:
    ≈ 150 GiB)."""
    cfg = _cfg("scanner")
    cfg.detector.mode = "noisy"
    cfg.run.save_waveforms = False
    cfg.gate.n_bins = 1_000_000
    _refused(tmp_path, cfg, "gate.n_bins", "block_waveforms")


def test_noisy_flash_counts_the_whole_receiver_chain(tmp_path):
    """1024² px × 1024 bins, noisy, points only: the float32 cube and, per sample, the chain and its detection
    (8 B beyond the cube; measured 7.6 B per sample in all at 256² px × 1024 bins) are counted: ≈ 12 GiB,
    refused under a limit that holds the cube alone, naming the bins and the receiver chain."""
    cfg = _cfg(pixels=1024, bins=1024)
    cfg.detector.mode = "noisy"
    cfg.run.save_waveforms = False
    cfg.run.max_memory_bytes = 2 ** 40
    est = estimate_memory(cfg)
    assert est["parts"]["receiver_chain"] == NOISY_BYTES_PER_SAMPLE * 1024 ** 3
    assert est["total"] > est["parts"]["receiver_chain"] + 4 * 1024 ** 3  # the cube beside the chain
    cfg.run.max_memory_bytes = est["total"] - est["parts"]["receiver_chain"] // 2
    _refused(tmp_path, cfg, "gate.n_bins", "receiver_chain")


def test_geiger_per_pulse_work_is_refused(tmp_path):
    """Geiger mode with speckle (one bisection per pulse): 1e7 pulses × 64² px is ≈ 6e11 samples, hours of
    computing: refused naming detector.geiger_pulses; 100 pulses pass the check."""
    cfg = _cfg(pixels=64, bins=512)
    cfg.detector.mode, cfg.detector.detector_type = "noisy", "geiger"
    cfg.detector.speckle_dof, cfg.detector.geiger_pulses = 4.0, 10_000_000
    _refused(tmp_path, cfg, "detector.geiger_pulses", "run.max_work_s = 3600 s", "raise run.max_work_s")
    cfg.detector.geiger_pulses = 100
    assert check_memory(cfg, available=None)["seconds"] < cfg.run.max_work_s


def test_flash_ray_work_is_refused(tmp_path):
    """2048² px × 256² sub-rays (2.7e11 rays), points only: refused naming receiver.subsamples."""
    cfg = _cfg(pixels=2048, sub=256)
    cfg.run.save_waveforms = False
    _refused(tmp_path, cfg, "receiver.subsamples", "rays")


def test_work_beyond_max_work_s_is_refused_with_the_time_and_the_setting_and_can_be_allowed(tmp_path):
    """Issue 31: the flash demo's 64² px with receiver.subsamples = 1024 (4.3e9 rays) was validated and ran for
    minutes.  Its time, rays / RAYS_PER_S / threads (+ samples / SAMPLES_PER_S / threads), is ≈ 7 h on one thread:
    refused naming receiver.subsamples, the estimated time and run.max_work_s; within a raised run.max_work_s
    the estimate passes (memory permitting)."""
    cfg = _cfg(pixels=64, sub=1024, bins=256)
    cfg.run.save_waveforms = False
    est = estimate_memory(cfg)
    rays = 64 ** 2 * 1024 ** 2
    assert est["work_parts"]["rays"] == rays
    expected_s = rays / RAYS_PER_S + sum(v for k, v in est["work_parts"].items() if k != "rays") / SAMPLES_PER_S
    assert est["seconds"] == pytest.approx(expected_s, rel=1e-12)
    assert 6.95 * 3600 < expected_s < 7.05 * 3600  # 4.29e9 / 1.7e5 = 25 266 s
    _refused(tmp_path, cfg, "receiver.subsamples", "≈ 7.0 h on 1 thread(s) of this machine", "4.3e+09 rays",
             "raise run.max_work_s")
    cfg.run.threads = 2  # two threads: half the time
    assert estimate_memory(cfg)["seconds"] == pytest.approx(expected_s / 2, rel=1e-12)
    cfg.run.max_work_s = 1e5
    cfg.run.max_memory_bytes = 2 ** 44
    assert check_memory(cfg, available=None)["seconds"] < 1e5
    cfg.run.max_work_s = expected_s / 2 * 0.99  # just below: refused
    with pytest.raises(ConfigError, match="run.max_work_s"):
        check_memory(cfg, available=None)


@pytest.mark.parametrize("system,kw", [
    ("flash", dict(pixels=96, bins=1024, noisy="apd")),
    ("flash", dict(pixels=64, bins=1024, noisy="geiger")),
    ("gated", dict(pixels=96)),
    ("scanner", dict(bins=512)),
])
def test_estimate_bounds_the_measured_peak(system, kw):
    cfg = _cfg(system, pixels=kw.get("pixels", 32), bins=kw.get("bins", 256))
    if "noisy" in kw:
        cfg.detector.mode, cfg.detector.detector_type = "noisy", kw["noisy"]
    est = estimate_memory(cfg)["total"]
    scene = plate(R, 50.0)
    tracemalloc.start()
    try:
        res = simulate(scene, np.eye(4), cfg)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert res.stats["memory_estimate_bytes"] == est and res.stats["work_estimate_samples"] > 0
    assert peak <= est <= 8 * peak, (peak / 2 ** 20, est / 2 ** 20)


def test_profiler_is_checked_as_one_element(tmp_path):
    """The range profiler is estimated as what it runs, one detector element: 4096² px × 10⁶ noisy bins would
    be refused for a flash (≈ PiB) and passes for the profiler; its Geiger per-pulse work (10⁷ pulses × 10⁵
    arrivals, dead time 0) is refused naming detector.geiger_pulses."""
    cfg = _cfg("profiler", pixels=4096, bins=1_000_000, sub=1)
    cfg.detector.mode = "noisy"
    est = check_memory(cfg, available=None)
    assert est["total"] < 2 ** 30 and est["parts"]["receiver_chain"] == 1_000_000 * NOISY_BYTES_PER_SAMPLE
    cfg.system_type = "flash"
    with pytest.raises(ConfigError):
        check_memory(cfg, available=None)
    cfg = _cfg("profiler", bins=100_000, sub=1)
    cfg.detector.mode, cfg.detector.detector_type = "noisy", "geiger"
    cfg.detector.geiger_pulses, cfg.detector.geiger_dead_time_bins = 10_000_000, 0
    _refused(tmp_path, cfg, "detector.geiger_pulses", "samples")


def test_geiger_histogram_memory_is_counted(tmp_path):
    """Geiger mode keeps float64 rates and pile-up probabilities and an int64 histogram per (pixel, bin): 48 B
    beyond the float32 cube (measured 52 B in all).  512² px × 4096 bins needs ≈ 52 GiB: refused under a 30 GiB
    limit, naming gate.n_bins, where the linear chain's 16 B/sample of the old estimate (≈ 20 GiB) let it start."""
    cfg = _cfg(pixels=512, bins=4096, sub=1)
    cfg.detector.mode, cfg.detector.detector_type = "noisy", "geiger"
    cfg.run.save_waveforms = False
    cfg.run.max_memory_bytes = 2 ** 40
    est = estimate_memory(cfg)
    samples = 512 ** 2 * 4096
    assert est["parts"]["receiver_chain"] == 48 * samples and est["parts"]["waveform_cube"] == 4 * samples
    cfg.run.max_memory_bytes = 30 * 2 ** 30
    _refused(tmp_path, cfg, "gate.n_bins", "receiver_chain")


def test_a_sequence_is_refused_when_its_frames_together_exceed_max_work_s(tmp_path):
    """The frames' work adds up: a run of 3 frames each within run.max_work_s but together beyond it is refused
    before the first frame, saying so; 2 frames pass the check."""
    from core.sequence import run_sequence

    cfg = _cfg(pixels=64, sub=64, bins=256)
    cfg.run.save_waveforms = False
    one = estimate_memory(cfg)["seconds"]
    cfg.run.max_work_s = 2.5 * one
    with pytest.raises(ConfigError, match=r"run.max_work_s .* per frame, 3 frames") as info:
        run_sequence([1, 2, 3], lambda f: plate(R, 50.0), lambda f: np.eye(4), cfg, tmp_path / "seq")
    assert info.value.field == "receiver.subsamples"
    assert list(tmp_path.iterdir()) == []
    assert check_memory(cfg, available=None, frames=2)["seconds"] == pytest.approx(one, rel=1e-12)
