"""The receiver chain (paper Figure 4, right half) wired into the flash pipeline."""
import numpy as np
import pytest

from core.config.settings import DetectorSettings
from core.run import run_simulation
from core.systems.flash import simulate_frame
from core.physics.detection.noisy import photon_limited_range_std
from core.physics.receiver.conversions import mcintyre_excess_noise, photons_per_joule
from scenes import config_for, plate

R = 500.0


def noisy_config(pixels=16, **det):
    cfg = config_for(R, pixels=pixels, subsamples=2, fov_rad=5e-3, bins=128, bin_s=1e-9, margin_bins=50)
    cfg.detector = DetectorSettings(mode="noisy", **det)
    cfg.run.save_counts = True  # counts kept: the per-bin reference route (run.save_counts)
    return cfg


def test_ideal_receiver_skips_every_noise_stage_exactly():
    """detector.mode = ideal: whatever the detector settings, the products are the noise-free ones, bit for bit,
    and the metadata says the receiver chain was skipped."""
    ref = simulate_frame(plate(R, 20.0), np.eye(4), config_for(R, pixels=8))
    cfg = config_for(R, pixels=8)
    cfg.detector = DetectorSettings(mode="ideal", apd_gain=500.0, read_noise_e=1e4, speckle_dof=2.0)
    res = simulate_frame(plate(R, 20.0), np.eye(4), cfg)
    assert np.array_equal(res.waveforms, ref.waveforms)
    assert np.array_equal(res.range_image, ref.range_image, equal_nan=True)
    assert "receiver_chain" in res.stats["stages_skipped"] and res.digital_waveforms is None
    assert "snr" not in res.points


def test_noisy_receiver_ranges_a_plate_with_high_snr():
    """A bright plate through the §8 APD chain (η 0.4, G 100, k 0.02, 300 e⁻ read noise, 12-bit A/D): every
    pixel detects its echo; the range error is unbiased (|mean| < 5 mm) and its rms follows the photon-limited
    precision with APD excess noise, σ_R = (c/2) σ_p √(F/N) (docs/theory.md §8, §9), within a factor 2; the mean
    digital signal above the pedestal is η N G / Δ within 5 %."""
    cfg = noisy_config()
    res = simulate_frame(plate(R, 20.0), np.eye(4), cfg)
    ideal = simulate_frame(plate(R, 20.0), np.eye(4), config_for(R, pixels=16, subsamples=2, fov_rad=5e-3,
                                                                 bins=128, bin_s=1e-9, margin_bins=50))
    assert "receiver_chain" in res.stats["stages_run"] and "receiver" in res.stats
    assert np.array_equal(res.waveforms, ideal.waveforms)  # the chain leaves the noise-free cube untouched
    pts = res.points
    first = pts["echo_index"] == 1
    assert first.sum() == 16 * 16
    assert np.array_equal(pts["pixel_x"][first], np.tile(np.arange(16), 16))
    assert np.all(pts["snr"][first] > 10) and np.all(np.isfinite(pts["snr"]))
    err = (res.range_image - ideal.range_image).ravel().astype(np.float64)
    d = cfg.detector
    primaries = ideal.waveforms.sum(axis=2).mean() * photons_per_joule(cfg.laser.wavelength_m) * d.quantum_efficiency
    excess = mcintyre_excess_noise(d.apd_gain, d.apd_k_eff)
    sigma_expected = photon_limited_range_std(cfg.laser.pulse_fwhm_s / 2.3548200450309493, primaries) * np.sqrt(excess)
    assert abs(err.mean()) < 5e-3
    assert 0.5 < np.sqrt(np.mean(err ** 2)) / sigma_expected < 2.0
    step = d.adc_full_scale_e / 2 ** d.adc_bits
    electrons = ideal.waveforms.sum(axis=2) * photons_per_joule(cfg.laser.wavelength_m) * d.quantum_efficiency * d.apd_gain
    counts = res.digital_waveforms.astype(np.float64) - d.adc_offset_counts
    assert counts.sum(axis=2).mean() * step == pytest.approx(electrons.mean(), rel=0.05)


def test_noise_is_seeded_and_independent_of_threads(tmp_path):
    """Same seed: identical counts with 1 or 2 threads and any chunking; another seed: different counts."""
    a = noisy_config()
    a.run.threads, a.run.chunk_rays = 1, 100_000_000
    b = noisy_config()
    b.run.threads, b.run.chunk_rays = 2, 1024
    ra, rb = simulate_frame(plate(R, 20.0), np.eye(4), a), simulate_frame(plate(R, 20.0), np.eye(4), b)
    assert np.array_equal(ra.digital_waveforms, rb.digital_waveforms)
    b.run.seed = 1
    assert not np.array_equal(simulate_frame(plate(R, 20.0), np.eye(4), b).digital_waveforms, ra.digital_waveforms)
    assert not np.array_equal(simulate_frame(plate(R, 20.0), np.eye(4), a, frame=1).digital_waveforms,
                              ra.digital_waveforms)
    path, _ = run_simulation(plate(R, 20.0), np.eye(4), a, tmp_path / "run")
    assert np.array_equal(np.load(path / "counts.npy"), ra.digital_waveforms)


def test_weak_returns_give_misses_and_false_alarms_are_counted():
    """Far too little light: most pixels detect nothing (no NaN in the products), and what the adaptive 5σ
    threshold reports is scattered noise, not the plate."""
    cfg = noisy_config(background_rate_photons_per_s=1e9)
    cfg.laser.pulse_energy_j = 1e-15
    res = simulate_frame(plate(R, 20.0), np.eye(4), cfg)
    n_first = int(np.sum(res.points["echo_index"] == 1))
    assert n_first < 0.2 * 16 * 16
    assert np.all(np.isfinite(res.points["range_m"]))
