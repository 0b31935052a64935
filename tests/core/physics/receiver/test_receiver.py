"""Receiver chain (paper Figure 4; docs/theory.md §8): photons, detector noise, gain, A/D, Geiger mode.

Tolerances: reference values at 4 significant digits (rel 5e-4); sampled means/variances within 2 % over
≥ 2.6e5 samples (statistical error of a variance ≈ √((κ4 + 2)/n) < 0.7 % here).
"""
import dataclasses

import numpy as np
import pytest

from core.physics.receiver.chain import ChainSettings, apply_receiver_chain
from core.config.settings import DetectorSettings
from core.physics.receiver.adc import adc_convert
from core.physics.receiver.conversions import (adc_step_e, current_to_electrons, energy_to_photons,
                                               linear_detector_moments, mcintyre_excess_noise, photons_per_joule,
                                               snr_linear)
from core.physics.receiver.geiger import (coates_correction, geiger_detection_probability, geiger_histogram,
                                          pileup_probabilities)
from core.physics.receiver.samplers import gamma_gain, poisson_sparse_counts, poisson_uniform_rows

REL4 = 5e-4  # "4 significant digits"

# docs/theory.md §8 test detector: η 0.4, G 100, k 0.02, 1 pA / 1 nA, τ 10 ns, N_b 2, 300 e⁻, Δ 500 e⁻ (12 bit)
SEC8 = dict(quantum_efficiency=0.4, apd_gain=100.0, apd_k_eff=0.02, dark_current_bulk_a=1e-12,
            dark_current_surface_a=1e-9, background_rate_photons_per_s=2 / (0.4 * 10e-9), read_noise_e=300.0,
            adc_bits=12, adc_full_scale_e=500.0 * 4096, adc_offset_counts=16)


def chain(cube, rng=0, wavelength_m=1.064e-6, bin_width_s=10e-9, **det):
    return apply_receiver_chain(cube, ChainSettings(DetectorSettings(**{"mode": "noisy", **det}), wavelength_m=wavelength_m,
                                                    bin_width_s=bin_width_s), rng)


# ------------------------------------------------------------------------------------------------ §8 values
def test_photons_per_femtojoule():
    got = photons_per_joule(np.array([532e-9, 1064e-9, 1550e-9])) * 1e-15
    np.testing.assert_allclose(got, [2678, 5356, 7803], rtol=REL4)


def test_excess_noise_and_signal_electrons():
    assert mcintyre_excess_noise(100, 0.02) == pytest.approx(3.950, rel=REL4)
    assert mcintyre_excess_noise(1, 0.4) == pytest.approx(1.0)
    assert energy_to_photons(1e-17, 1.064e-6, 0.4) == pytest.approx(21.43, rel=REL4)


def test_snr_table():
    snr = snr_linear(np.array([1e-17, 1e-16, 1e-15]), 1.064e-6, 0.4, 100.0, 0.02, 1e-12, 1e-9, 10e-9, 2.0,
                     300.0, 500.0)
    np.testing.assert_allclose(snr, [2.102, 7.282, 23.26], rtol=REL4)


def test_adc_reports_clipping():
    codes, lo, hi = adc_convert(np.array([-1e4, 0.0, 499.0, 1e12]), bits=12, full_scale_e=4096 * 500.0)
    assert codes.dtype == np.uint16
    assert codes.tolist() == [0, 0, 1, 4095] and lo == 1 and hi == 1


# ------------------------------------------------------------------------------------- exact samplers
def test_sparse_poisson_moments():
    rng = np.random.default_rng(1)
    reps = 400_000
    mu = np.array([0.0, 1e-3, 0.05, 0.7, 3.0])
    n = poisson_sparse_counts(np.tile(mu.astype(np.float32), reps), rng).reshape(-1, 5)
    np.testing.assert_allclose(n.mean(axis=0)[2:], mu[2:], rtol=0.02)
    np.testing.assert_allclose(n.var(axis=0)[2:], mu[2:], rtol=0.02)
    assert abs(n[:, 1].mean() - 1e-3) < 4 * np.sqrt(1e-3 / reps)  # 4 standard errors
    assert n[:, 0].sum() == 0  # a zero-mean bin never receives an event


def test_uniform_rows_and_gamma_gain_moments():
    rng = np.random.default_rng(2)
    n = poisson_uniform_rows(np.array([0.02, 2.0, 30.0]).repeat(200), 600, 1000, rng).reshape(3, -1)
    np.testing.assert_allclose(n.mean(axis=1), [0.02, 2.0, 30.0], rtol=0.02)
    np.testing.assert_allclose(n.var(axis=1), [0.02, 2.0, 30.0], rtol=0.02)
    F = 3.9502
    y = gamma_gain(np.full(400_000, 3.0, np.float32), 100.0, F, rng)
    assert y.mean() == pytest.approx(300.0, rel=0.01)
    assert y.var() == pytest.approx(100.0 ** 2 * (F - 1) * 3, rel=0.02)


# --------------------------------------------------------------------- the chain: sampled statistics
CASES = {
    # name: (energy per bin J, detector overrides)
    "sec8_1e-17J": (1e-17, {}),
    "sec8_1e-16J": (1e-16, {}),  # N_s = 214 ≥ 8: per-bin Poisson path
    "pin_exact_surface_dark": (2e-18, dict(detector_type="pin", read_noise_e=0.0, dark_current_surface_a=3e-11,
                                           adc_full_scale_e=4096.0 * 0.25, adc_offset_counts=0)),
    "apd_no_adc": (5e-18, dict(enable_adc=False, background_rate_photons_per_s=1e6)),
}


@pytest.mark.parametrize("name", list(CASES))
def test_chain_mean_and_variance_match_formula(name):
    energy, over = CASES[name]
    det = dict(SEC8, **over)
    cube = np.full((64, 64, 64), energy, dtype=np.float32)  # 262144 samples
    out = chain(cube, rng=11, **det)
    d = DetectorSettings(**{"mode": "noisy", **det})
    tau = 10e-9
    gain, F = (1.0, 1.0) if d.detector_type == "pin" else (d.apd_gain, mcintyre_excess_noise(d.apd_gain,
                                                                                          d.apd_k_eff))
    step = adc_step_e(d.adc_bits, d.adc_full_scale_e) if d.enable_adc else 0.0
    mean_e, var_e = linear_detector_moments(
        energy_to_photons(energy, 1.064e-6, d.quantum_efficiency),
        d.background_rate_photons_per_s * tau * d.quantum_efficiency, gain, F,
        current_to_electrons(d.dark_current_bulk_a, tau), current_to_electrons(d.dark_current_surface_a, tau),
        d.read_noise_e, step)
    x = out.data.astype(np.float64)
    if d.enable_adc:
        assert out.report["units"] == "counts" and out.report["n_adc_high"] == 0
        x = (x - d.adc_offset_counts) * step
        # nothing may have been clipped at code 0 for the variance to be meaningful
        assert out.report["n_adc_low"] == 0
    assert x.mean() == pytest.approx(mean_e, rel=0.02)
    assert x.var() == pytest.approx(var_e, rel=0.02)


def test_chain_speckle_negative_binomial():
    """PIN, no read noise, no A/D: counts are negative binomial, variance N̄ + N̄²/M (§7)."""
    n_bar, M = 20.0, 4.0
    e = n_bar / photons_per_joule(1.064e-6)
    cube = np.full((512, 512, 1), e, dtype=np.float32)  # one bin per pixel: speckle is per pixel per pulse
    out = chain(cube, rng=3, detector_type="pin", quantum_efficiency=1.0, read_noise_e=0.0,
                enable_dark_current=False, enable_background=False, enable_adc=False, speckle_dof=M)
    x = out.data.astype(np.float64).ravel()
    assert "speckle" in out.report["steps_run"]
    assert x.mean() == pytest.approx(n_bar, rel=0.02)
    assert x.var() == pytest.approx(n_bar + n_bar ** 2 / M, rel=0.02)


def test_shot_noise_off_is_deterministic_mean():
    cube = np.full((4, 4, 8), 1e-17, dtype=np.float32)
    out = chain(cube, detector_type="pin", enable_shot_noise=False, enable_read_noise=False,
                enable_dark_current=False, enable_adc=False)
    np.testing.assert_allclose(out.data, energy_to_photons(1e-17, 1.064e-6, 0.4), rtol=1e-6)


# ------------------------------------------------------------------------- modes, seeds, robustness
def test_ideal_mode_returns_input_exactly():
    cube = np.random.default_rng(0).random((5, 6, 7)).astype(np.float32) * 1e-15
    ref = cube.copy()
    out = chain(cube, mode="ideal")
    assert out.data is cube
    assert np.array_equal(out.data.view(np.uint32), ref.view(np.uint32))
    assert out.report["steps_run"] == [] and "adc" in out.report["steps_skipped"]


def test_seed_reproducibility_and_thread_independence():
    cube = np.random.default_rng(0).random((40, 40, 300)).astype(np.float32) * 3e-17
    a = chain(cube, rng=7, **SEC8).data
    b = chain(cube, rng=7, threads=1, **SEC8).data
    c = chain(cube, rng=8, **SEC8).data
    g = chain(cube, rng=np.random.default_rng(7), **SEC8).data
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.array_equal(g, chain(cube, rng=np.random.default_rng(7), **SEC8).data)


def test_the_chain_runs_on_the_runs_threads_unless_the_detector_says_otherwise(monkeypatch):
    """detector.threads = 0 follows run.threads (a run on one thread ran its chain on every core: session 28's
    one-thread benchmarks); an explicit detector.threads wins; both 0: one per CPU."""
    import os

    import core.physics.receiver.chain as chain_module
    from core.config.settings import SimulationConfig

    seen = []
    real = chain_module.map_list
    monkeypatch.setattr(chain_module, "map_list", lambda fn, items, threads: seen.append(threads) or
                        real(fn, items, threads))
    cube = np.zeros((4, 4, 16), np.float32)
    for run_threads, det_threads, want in ((1, 0, 1), (3, 0, 3), (1, 2, 2), (0, 0, os.cpu_count() or 1)):
        cfg = SimulationConfig()
        cfg.run.threads = run_threads
        det = DetectorSettings(**{**SEC8, "mode": "noisy", "threads": det_threads})
        seen.clear()
        apply_receiver_chain(cube, ChainSettings.from_config(cfg, det), 5)
        assert seen and set(seen) == {want}, (run_threads, det_threads, seen)


@pytest.mark.parametrize("energy", [0.0, 1e-30, 1.0, 3e38])
def test_no_nan_or_inf_for_zero_or_huge_energy(energy):
    cube = np.full((8, 8, 32), energy, dtype=np.float32)
    for det in (dict(SEC8), dict(SEC8, enable_adc=False), dict(SEC8, detector_type="pin", speckle_dof=2.0)):
        out = chain(cube, **det)
        assert np.all(np.isfinite(out.data.astype(np.float64)))
        if energy >= 1.0 and det.get("enable_adc", True):
            assert out.report["n_adc_high"] == cube.size  # saturation is reported
        if energy == 3e38:
            assert out.report["n_mean_clipped"] == cube.size and out.report["approximations"]


def test_rejects_nan_and_negative_input():
    with pytest.raises(ValueError):
        chain(np.full((2, 2, 2), np.nan, np.float32))
    with pytest.raises(ValueError):
        chain(np.full((2, 2, 2), -1.0, np.float32))


def test_optics_mtf_step_conserves_energy():
    cube = np.zeros((32, 32, 4), np.float32)
    cube[16, 16, 1] = 1e-15
    out = chain(cube, detector_type="pin", quantum_efficiency=1.0, enable_shot_noise=False,
                enable_read_noise=False, enable_dark_current=False, enable_adc=False, enable_optics_mtf=True)
    assert "optics_mtf" in out.report["steps_run"]
    assert out.data.sum() == pytest.approx(1e-15 * photons_per_joule(1.064e-6), rel=1e-4)
    assert out.data[16, 16, 1] < 1e-15 * photons_per_joule(1.064e-6)  # it blurred


# ------------------------------------------------------------------------------------- Geiger mode
def test_geiger_detection_probability_values():
    assert geiger_detection_probability(1.0) == pytest.approx(0.6321, rel=REL4)
    assert geiger_detection_probability(1.0, 1.0) == pytest.approx(0.5, rel=REL4)
    assert geiger_detection_probability(1.0, 4.0) == pytest.approx(0.5904, rel=REL4)


def test_pileup_values_and_coates():
    p = pileup_probabilities([0.1, 0.5, 1.0])
    np.testing.assert_allclose(p, [0.09516, 0.3560, 0.3469], rtol=REL4)
    np.testing.assert_allclose(coates_correction(p * 1e6, 1e6), [0.1, 0.5, 1.0], rtol=1e-12)


@pytest.mark.parametrize("per_pulse", [False, True])
def test_geiger_sampled_pileup_histogram_and_coates(per_pulse):
    n = 400_000 if not per_pulse else 200_000
    rates = np.array([[0.1, 0.5, 1.0]])
    h, info = geiger_histogram(rates, n, np.random.default_rng(5), force_per_pulse=per_pulse)
    assert info["path"] == ("per-pulse" if per_pulse else "multinomial")
    np.testing.assert_allclose(h[0] / n, [0.09516, 0.3560, 0.3469], rtol=0.02)
    np.testing.assert_allclose(coates_correction(h[0], n), [0.1, 0.5, 1.0], rtol=0.02)


def test_geiger_dead_time_and_speckle():
    rng = np.random.default_rng(9)
    rates = np.array([[0.1, 0.5, 1.0]])
    # zero dead time: the detector re-arms at the next bin, so every bin fires independently with 1 − e^(−r)
    h, _ = geiger_histogram(rates, 200_000, rng, dead_time_bins=0)
    np.testing.assert_allclose(h[0] / 200_000, 1 - np.exp(-rates[0]), rtol=0.02)
    # speckle per pulse, one bin of mean 1: P_d = 1 − (1 + N/M)^(−M) = 0.5904 for M = 4
    h, _ = geiger_histogram(np.array([[1.0]]), 200_000, rng, speckle_dof=4.0)
    assert h[0, 0] / 200_000 == pytest.approx(0.5904, rel=0.02)


def test_chain_geiger_mode():
    cube = np.zeros((6, 5, 40), np.float32)
    cube[..., 20] = 1.0 / (0.4 * photons_per_joule(1.064e-6))  # one detectable photon on average
    out = chain(cube, rng=1, detector_type="geiger", geiger_pulses=2000, enable_dark_current=False,
                enable_background=False)
    assert out.data.shape == cube.shape and out.report["units"] == "detections"
    frac = out.data[..., 20].sum() / (30 * 2000)
    assert frac == pytest.approx(0.6321, rel=0.03)
    assert out.data.sum() == out.data[..., 20].sum()


def test_settings_validate():
    from core.errors import ConfigError
    from core.config.validate import validate
    validate(DetectorSettings())
    with pytest.raises(ConfigError):
        validate(dataclasses.replace(DetectorSettings(), quantum_efficiency=1.5))
