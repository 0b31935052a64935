"""ladar_addon.derived: the receiver's derived panel figures follow the chain's switches (core.physics.receiver.bin_moments)
and reproduce docs/theory.md §8 (photons per fJ, McIntyre F, SNR table, Geiger P_d)."""
import importlib
import math

import pytest

REL4 = 5e-4  # 4 significant digits
PHOTONS_PER_J = 1.064e-6 / (6.62607015e-34 * 299_792_458.0)  # λ/(hc): 5356 per fJ

SEC8 = dict(mode="noisy", quantum_efficiency=0.4, apd_gain=100.0, apd_k_eff=0.02, dark_current_bulk_a=1e-12,
            dark_current_surface_a=1e-9, background_rate_photons_per_s=2 / (0.4 * 10e-9), read_noise_e=300.0,
            adc_bits=12, adc_full_scale_e=500.0 * 4096, adc_offset_counts=16)


@pytest.fixture
def derived(lad):
    return importlib.import_module(f"{lad.package.__name__}.ladar_addon.derived")


def sec8_config(lad, **over):
    cfg = lad.config.SimulationConfig()
    cfg.laser.wavelength_m = 1.064e-6
    cfg.gate.bin_width_s = 10e-9  # τ = 10 ns (docs/theory.md §8)
    cfg.detector = lad.config.DetectorSettings(**{**SEC8, **over})
    return cfg


def test_snr_table_of_section8(lad, derived):
    cfg = sec8_config(lad)
    for e, want in ((1e-17, 2.102), (1e-16, 7.282), (1e-15, 23.26)):
        fig = derived.detector_snr(cfg, e)
        assert fig["snr"] == pytest.approx(want, rel=REL4)
    assert derived.detector_snr(cfg, 1e-17)["peak_signal_electrons"] == pytest.approx(21.43, rel=REL4)


def sec8_snr_by_hand(n_s, gain=100.0, F=3.9502, n_b=2.0, n_db=1e-12 * 10e-9 / 1.602176634e-19,
                     n_ds=1e-9 * 10e-9 / 1.602176634e-19, read=300.0, step=500.0, shot=True, M=0.0):
    var = (gain ** 2 * F * (n_s + n_b + n_db) + n_ds) if shot else gain ** 2 * (F - 1) * (n_s + n_b + n_db)
    var += (gain ** 2 * n_s ** 2 / M if M else 0.0) + read ** 2 + step ** 2 / 12
    return gain * n_s / math.sqrt(var)


@pytest.mark.parametrize("over,kw", [
    (dict(enable_excess_noise=False), dict(F=1.0)),  # the bug: F was used with excess noise off
    (dict(enable_read_noise=False), dict(read=0.0)),
    (dict(enable_background=False), dict(n_b=0.0)),
    (dict(enable_dark_current=False), dict(n_db=0.0, n_ds=0.0)),
    (dict(enable_adc=False), dict(step=0.0)),
    (dict(enable_shot_noise=False), dict(shot=False)),
    (dict(speckle_dof=4.0), dict(M=4.0)),
    (dict(detector_type="pin"), dict(gain=1.0, F=1.0)),
])
def test_snr_follows_each_switch(lad, derived, over, kw):
    cfg = sec8_config(lad, **over)
    n_s = 1e-16 * PHOTONS_PER_J * 0.4  # 214.3 photo-electrons
    got = derived.detector_snr(cfg, 1e-16)
    assert got["snr"] == pytest.approx(sec8_snr_by_hand(n_s, **kw), rel=1e-3)


def test_noise_floor_and_excess_noise_readout(lad, derived):
    cfg = sec8_config(lad)
    fig = derived.detector_snr(cfg, 0.0)
    floor_e = math.sqrt(100.0 ** 2 * 3.9502 * (2.0 + 1e-12 * 10e-9 / 1.602176634e-19)
                        + 1e-9 * 10e-9 / 1.602176634e-19 + 300.0 ** 2 + 500.0 ** 2 / 12)
    assert fig["noise_floor_e"] == pytest.approx(floor_e, rel=1e-4)
    assert fig["noise_floor_counts"] == pytest.approx(floor_e / 500.0, rel=1e-4)
    figs = derived.detector_figures(cfg, 1000.0)
    assert figs["photons_per_fj"] == pytest.approx(5356, rel=REL4)
    assert figs["excess_noise_factor"] == pytest.approx(3.950, rel=REL4)
    off = derived.detector_figures(sec8_config(lad, enable_excess_noise=False), 1000.0)
    assert off["excess_noise_factor"] == 1.0
    lines = derived.detector_lines(sec8_config(lad, enable_excess_noise=False), 1000.0)
    assert any("F 1 (excess noise off)" in line for line in lines), lines
    assert any(line.startswith("Noise floor") for line in derived.detector_lines(cfg, 1000.0))


def test_peak_bin_share_of_the_pulse(lad, derived):
    """Gaussian 5 ns FWHM pulse centred in a 1 ns bin: erf(0.5/(σ√2)) with σ = 5/2.3548 ns → 0.1856."""
    cfg = sec8_config(lad)
    cfg.gate.bin_width_s = 1e-9
    assert derived.peak_bin_fraction(cfg.laser, 1e-9) == pytest.approx(math.erf(0.5 / (5 / 2.3548200450309493 *
                                                                                      math.sqrt(2))), rel=1e-9)
    fig = derived.detector_figures(cfg, 500.0)
    assert fig["peak_signal_electrons"] == pytest.approx(fig["signal_electrons"] * fig["peak_bin_fraction"])


def test_saturation_and_ideal_mode(lad, derived):
    cfg = sec8_config(lad)
    sat = derived.detector_snr(cfg, 1e-12)  # 2.1e6 e⁻ × G 100 ≫ full scale
    top_e = (4095 - 16) * 500.0
    mean0 = 100.0 * (2.0 + 1e-12 * 10e-9 / 1.602176634e-19) + 1e-9 * 10e-9 / 1.602176634e-19
    assert sat["adc_saturated"] and sat["snr"] == pytest.approx((top_e - mean0) / math.sqrt(
        100.0 ** 2 * 3.9502 * (1e-12 * PHOTONS_PER_J * 0.4 + mean0 / 100.0 - 0.6242) + 62.42 + 300.0 ** 2
        + 500.0 ** 2 / 12), rel=1e-3)
    ideal = derived.detector_snr(sec8_config(lad, mode="ideal"), 1e-17)
    assert ideal["ideal"] and ideal["snr"] == math.inf and ideal["noise_floor_e"] == 0.0
    assert any("noise-free" in line for line in derived.detector_lines(sec8_config(lad, mode="ideal"), 1000.0))


def test_geiger_detection_probability_with_speckle(lad, derived):
    """One detectable photo-electron per pulse: P_d = 0.6321; with speckle M = 4: 0.5904 (docs/theory.md §8)."""
    cfg = sec8_config(lad, detector_type="geiger", enable_background=False, enable_dark_current=False)
    cfg.gate.bin_width_s = 1e-9
    r = 1000.0
    e1 = 1.0 / (PHOTONS_PER_J * 0.4)  # energy of one photo-electron
    scale = e1 / derived.received_pixel_energy_j(cfg, r)
    cfg.laser.pulse_energy_j *= scale
    assert derived.detector_figures(cfg, r)["detection_probability"] == pytest.approx(0.6321, rel=REL4)
    cfg.detector.speckle_dof = 4.0
    assert derived.detector_figures(cfg, r)["detection_probability"] == pytest.approx(0.5904, rel=REL4)
    cfg.detector.enable_background = True
    fig = derived.detector_figures(cfg, r)
    assert fig["noise_primaries_per_bin"] == pytest.approx(2 / (0.4 * 10e-9) * 1e-9 * 0.4)
