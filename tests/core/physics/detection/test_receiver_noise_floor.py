"""The noise estimate of echo detection must not collapse when the receiver's noise is below one A/D count
(issue 15: ``detector.read_noise_e = 0`` gave every point SNR = inf, a zero threshold and far more false alarms
than expected).  The floor is the receiver's signal-free σ with every term (core.receiver.noise_sigma_floor).

Tolerances: false-alarm counts as in test_receiver_false_alarms.py (within 4√E of the Gaussian expectation in
the run metadata; here one-sided: quantised noise far below one count is bounded, the Gaussian tail of the
floor σ is an upper bound); σ formulas to 1e-12."""
import math

import numpy as np
import pytest

from core.config.settings import DetectorSettings
from core.physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel
from core.physics.receiver.conversions import adc_step_e, current_to_electrons, noise_sigma_floor
from core.systems.flash import simulate_frame
from scenes import config_for, plate

R = 500.0


def test_noise_floor_formula():
    """PIN, no read noise: σ² = N_ds + N_db + Δ²/12 (counts: /Δ); every term off and no A/D: one primary
    (G√F electrons); Geiger: √(λ + 1/12), λ the expected noise detections per bin."""
    det = DetectorSettings(mode="noisy", detector_type="pin", read_noise_e=0.0, adc_bits=16,
                           adc_full_scale_e=32.0 * 65536, background_rate_photons_per_s=0.0)
    n_d = current_to_electrons(det.dark_current_surface_a + det.dark_current_bulk_a, 1e-9)
    assert noise_sigma_floor(det, 1e-9) == pytest.approx(math.sqrt(n_d + 32.0 ** 2 / 12) / 32.0, rel=1e-12)
    quiet = DetectorSettings(mode="noisy", detector_type="apd", apd_gain=50.0, enable_adc=False,
                             enable_read_noise=False, enable_dark_current=False, enable_background=False,
                             enable_excess_noise=False)
    assert noise_sigma_floor(quiet, 1e-9) == pytest.approx(50.0, rel=1e-12)
    g = DetectorSettings(mode="noisy", detector_type="geiger", geiger_pulses=1000, enable_dark_current=False,
                         background_rate_photons_per_s=1e6, quantum_efficiency=0.5)
    lam = 1000 * -math.expm1(-1e6 * 1e-9 * 0.5)
    assert noise_sigma_floor(g, 1e-9) == pytest.approx(math.sqrt(lam + 1 / 12), rel=1e-12)
    assert adc_step_e(16, 32.0 * 65536) == 32.0


def test_a_one_count_flip_is_not_an_echo_with_the_floor():
    """A constant waveform with one bin one count higher: MAD and the quiet-90 % rms are both 0.  Without a
    floor the threshold is 0 and the flip is an echo of infinite SNR; with the floor (1/√12 count) it is not."""
    x = np.full((4, 512), 100.0, np.float32)
    x[:, 300] += 1.0
    pulse = gaussian_pulse_kernel(5e-9, 1e-9)
    bare = detect_echoes_noisy(x, 1e-9, pulse=pulse)
    assert bare.detected.any() and np.isinf(bare.snr[bare.detected]).all()  # the collapse, without a floor
    e = detect_echoes_noisy(x, 1e-9, pulse=pulse, min_noise_sigma=1 / math.sqrt(12))
    assert not e.detected.any()
    assert np.all(e.noise_sigma == pytest.approx(1 / math.sqrt(12)))
    assert np.all(e.threshold == pytest.approx(5.0 / math.sqrt(12) / np.sqrt(np.sum(pulse ** 2))))


@pytest.mark.parametrize("k_sigma", [3.0, 5.0])
def test_read_noise_zero_gives_finite_snr_and_no_excess_false_alarms(k_sigma):
    """PIN, read_noise_e = 0, A/D step 32 e⁻ (dark-current noise 2.5 e⁻: far below one count), adaptive
    threshold: every SNR finite (= amplitude / floor σ), the false alarms do not exceed the Gaussian expectation
    in the metadata by more than 4√E (before the floor: 267 against 0), and every plate pixel finds its echo."""
    cfg = config_for(R, pixels=32, subsamples=2, fov_rad=5e-3, bins=1024, bin_s=1e-9, margin_bins=200)
    cfg.detector = DetectorSettings(mode="noisy", detector_type="pin", read_noise_e=0.0, adc_bits=16,
                                    adc_full_scale_e=32.0 * 65536, adc_offset_counts=2000)
    cfg.detection.max_echoes = 32
    cfg.detection.k_sigma = k_sigma
    res = simulate_frame(plate(R, 0.7, offset=(0.7, 0.0, 0.0)), np.eye(4), cfg)
    rx = res.stats["receiver"]
    floor = rx["noise_sigma_floor"]
    assert floor == pytest.approx(noise_sigma_floor(cfg.detector, 1e-9), rel=1e-12)
    snr = res.points["snr"].astype(np.float64)
    assert len(snr) and np.all(np.isfinite(snr))
    np.testing.assert_allclose(snr, res.points["intensity"] / floor, rtol=1e-5)
    fa = rx["false_alarms"]
    e = fa["expected_false_alarms_gaussian"]
    assert fa["n_false_alarms"] <= e + 4 * np.sqrt(e) + 1e-9
    plate_pixels = fa["n_pixels"] - fa["n_empty_pixels"]
    assert res.stats["n_points"] - fa["n_false_alarms"] == plate_pixels
