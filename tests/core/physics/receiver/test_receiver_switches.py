"""core.physics.receiver.bin_moments follows every switch of the chain (the panel's derived figures use it): sampled
mean and variance of the chain output within 2 % of it over 262144 samples (docs/theory.md §7, §8)."""
import numpy as np
import pytest

from core.physics.receiver.chain import ChainSettings, apply_receiver_chain
from core.config.settings import DetectorSettings
from core.physics.receiver.conversions import bin_moments, energy_to_photons, snr_linear

SEC8 = dict(quantum_efficiency=0.4, apd_gain=100.0, apd_k_eff=0.02, dark_current_bulk_a=1e-12,
            dark_current_surface_a=1e-9, background_rate_photons_per_s=2 / (0.4 * 10e-9), read_noise_e=300.0,
            adc_bits=12, adc_full_scale_e=500.0 * 4096, adc_offset_counts=16)
SWITCHES = {
    "all on": {},
    "excess noise off": dict(enable_excess_noise=False),
    "read noise off": dict(enable_read_noise=False, adc_full_scale_e=50.0 * 4096),
    "background off": dict(enable_background=False),
    "dark current off": dict(enable_dark_current=False),
    "shot noise off": dict(enable_shot_noise=False),
    "A/D off": dict(enable_adc=False),
    "speckle M=4": dict(speckle_dof=4.0),
    "PIN": dict(detector_type="pin", read_noise_e=30.0, adc_full_scale_e=5.0 * 4096),
}


@pytest.mark.parametrize("name", list(SWITCHES))
def test_bin_moments_follow_the_chain_switches(name):
    det = DetectorSettings(**{"mode": "noisy", **SEC8, **SWITCHES[name]})
    energy = 5e-17  # 107 signal photo-electrons per bin at 1064 nm, η 0.4
    cube = np.full((256, 256, 4), energy, np.float32)  # 65536 pixels: the speckle factor is per pixel
    out = apply_receiver_chain(cube, ChainSettings(det, wavelength_m=1.064e-6, bin_width_s=10e-9), 21)
    n_s = float(energy_to_photons(energy, 1.064e-6, det.quantum_efficiency))
    mean, var, parts = bin_moments(det, n_s, 10e-9)
    x = out.data.astype(np.float64)
    if det.enable_adc:
        assert out.report["n_adc_low"] == 0 and out.report["n_adc_high"] == 0
        x = (x - det.adc_offset_counts) * parts["adc_step_e"]
    assert x.mean() == pytest.approx(mean, rel=0.02)
    assert x.var() == pytest.approx(var, rel=0.02)


def test_bin_moments_reproduce_the_section8_snr_table():
    det = DetectorSettings(**{"mode": "noisy", **SEC8})
    e = np.array([1e-17, 1e-16, 1e-15])
    n_s = energy_to_photons(e, 1.064e-6, 0.4)
    _, var, parts = bin_moments(det, n_s, 10e-9)
    snr = parts["gain"] * n_s / np.sqrt(var)
    np.testing.assert_allclose(snr, [2.102, 7.282, 23.26], rtol=5e-4)
    np.testing.assert_allclose(snr, snr_linear(e, 1.064e-6, 0.4, 100.0, 0.02, 1e-12, 1e-9, 10e-9, 2.0, 300.0, 500.0))
