"""Sunlight reflected by the scene: a background photon rate per pixel (core/physics/solar.py, docs/theory.md §8)."""
import math

import numpy as np
import pytest

from core.config.settings import BRDFSettings, DetectorSettings
from core.config.validate import validate_config
from core.errors import ConfigError
from core.geometry.scene import SceneGeometry
from core.physics.receiver.chain import ChainSettings, apply_receiver_chain
from core.physics.receiver.conversions import bin_moments
from core.physics.solar import radiance_to_rate, subray_solar_rates, sun_direction
from core.systems.flash import simulate_frame
from scenes import config_for, plate

H_PLANCK, C_LIGHT = 6.62607015e-34, 299_792_458.0


def sunny_config(range_m, elevation_deg, irradiance=1.0, bandwidth_nm=10.0):
    cfg = config_for(range_m)
    cfg.detector.mode = "noisy"
    cfg.detector.background_rate_photons_per_s = 0.0
    cfg.atmosphere.solar_irradiance_w_m2_nm = irradiance
    cfg.atmosphere.sun_elevation_rad = math.radians(elevation_deg)
    cfg.receiver.filter_bandwidth_m = bandwidth_nm * 1e-9
    return cfg


def closed_form_rate(cfg, rho, cos_sun):
    """ρ/π · E_λ Δλ · cos θ_s · A_r · Ω_pixel · τ / (hν), Ω_pixel = (fov/pixels)² on the axis."""
    rx, atm = cfg.receiver, cfg.atmosphere
    area = math.pi * (rx.aperture_diameter_m / 2) ** 2
    omega = (rx.fov_x_rad / rx.width_px) * (rx.fov_y_rad / rx.height_px)
    h_nu = H_PLANCK * C_LIGHT / cfg.laser.wavelength_m
    return (rho / math.pi * atm.solar_irradiance_w_m2_nm * rx.filter_bandwidth_m * 1e9 * cos_sun * area * omega
            * rx.system_efficiency / h_nu)


def two_plates(target_m, occluder=None):
    """The Lambertian target plate (ρ 0.3, facing the sensor at ``target_m``) and, optionally, a second plate
    ``occluder`` = (distance, half size, (x, y, z) offset) of its own, parallel to it."""
    parts = [plate(target_m, 5.0)] + ([plate(occluder[0], occluder[1], offset=occluder[2])] if occluder else [])
    v = np.concatenate([p.vertices_m for p in parts])
    t = np.concatenate([p.triangles + 4 * k for k, p in enumerate(parts)])
    return SceneGeometry(v, t, np.zeros(len(t), np.int64), [BRDFSettings(reflectance=0.3)], ["plate"])


def test_sun_direction_follows_elevation_and_azimuth():
    cfg = sunny_config(100.0, 30.0)
    cfg.atmosphere.sun_azimuth_rad = math.radians(90.0)
    np.testing.assert_allclose(sun_direction(cfg.atmosphere), [0.0, math.cos(math.radians(30)), 0.5], atol=1e-15)


@pytest.mark.parametrize("elevation_deg", [30.0, 75.0])
def test_lit_lambertian_plate_gives_the_closed_form_rate(elevation_deg):
    """A plate filling the 0.01 rad field of view, normal towards the sensor (+Z) and the sun at elevation e
    (cos θ_s = sin e): every pixel gets ρ/π E Δλ sin e A_r Ω τ/(hν) (9.81e8 photons/s at 30°).  The closed form
    takes Ω on the axis; a pixel's sub-rays each carry (p²/N)/(1 + x² + y²)^(3/2), which differs from it by at
    most 1.5 × (0.005² + 0.005²) = 7.5e-5 at the corners, and its tan-space cell (2 tan(0.005)/16)² is larger
    than (0.01/16)² by 1.7e-5: tolerance 1e-4 relative (the Lambertian BRDF and sin e enter exactly)."""
    cfg = sunny_config(100.0, elevation_deg)
    res = simulate_frame(plate(100.0, 5.0, brdf=BRDFSettings(reflectance=0.3)), np.eye(4), cfg)
    bg = res.stats["receiver"]["pixel_background"]
    want = closed_form_rate(cfg, 0.3, math.sin(math.radians(elevation_deg)))
    assert bg["pixels_with_background"] == 256
    assert abs(bg["max_rate_photons_per_s"] / want - 1) < 1e-4, (bg, want)
    assert abs(bg["mean_rate_photons_per_s"] / want - 1) < 1e-4, (bg, want)
    assert res.stats["receiver"]["detector_model"]["signal_free_bins"] == "per_bin"
    assert "fov_culling" in res.stats["stages_skipped"]  # shadow rays see the whole scene


def test_extinction_takes_its_one_way_share():
    """α = 2e-3 /m over 100 m: the rate × e^(−αR) = e^(−0.2) (within the 1e-4 of the solid-angle sampling)."""
    cfg = sunny_config(100.0, 30.0)
    cfg.atmosphere.extinction_per_m = 2e-3
    res = simulate_frame(plate(100.0, 5.0, brdf=BRDFSettings(reflectance=0.3)), np.eye(4), cfg)
    want = closed_form_rate(cfg, 0.3, 0.5) * math.exp(-0.2)
    assert abs(res.stats["receiver"]["pixel_background"]["mean_rate_photons_per_s"] / want - 1) < 1e-4


def test_aerosol_layers_take_their_one_way_share():
    """A layer of 0.01 /m from 40 to 60 m (atmosphere.aerosol_layers) before the plate at 100 m, on top of
    α = 1e-3 /m: the rate × exp(−τ) = exp(−(0.1 + 0.2)) (within the 1e-4 of the solid-angle sampling); a layer
    behind the plate changes nothing."""
    cfg = sunny_config(100.0, 30.0)
    cfg.atmosphere.extinction_per_m = 1e-3
    cfg.atmosphere.aerosol_layers = [[40.0, 60.0, 0.01]]
    res = simulate_frame(plate(100.0, 5.0, brdf=BRDFSettings(reflectance=0.3)), np.eye(4), cfg)
    want = closed_form_rate(cfg, 0.3, 0.5) * math.exp(-0.3)
    assert abs(res.stats["receiver"]["pixel_background"]["mean_rate_photons_per_s"] / want - 1) < 1e-4
    cfg.atmosphere.aerosol_layers = [[150.0, 200.0, 0.01]]
    res = simulate_frame(plate(100.0, 5.0, brdf=BRDFSettings(reflectance=0.3)), np.eye(4), cfg)
    want = closed_form_rate(cfg, 0.3, 0.5) * math.exp(-0.1)
    assert abs(res.stats["receiver"]["pixel_background"]["mean_rate_photons_per_s"] / want - 1) < 1e-4


def test_shadowed_plate_and_sun_below_horizon_give_zero():
    """Sun at 30° towards +X; a 30 m plate 20 m above the target (towards the sensor) and 34.6 m = 20/tan 30° off
    towards +X (outside the 0.01 rad field of view) shades the whole target: zero rate.  Without it: the
    closed form; with the sun below the horizon (−10°, and straight below: the plate's back face): zero."""
    occluder = (80.0, 15.0, (20.0 / math.tan(math.radians(30.0)), 0.0, 0.0))
    cfg = sunny_config(100.0, 30.0)
    lit = simulate_frame(two_plates(100.0), np.eye(4), cfg).stats["receiver"]["pixel_background"]
    assert abs(lit["mean_rate_photons_per_s"] / closed_form_rate(cfg, 0.3, 0.5) - 1) < 1e-4
    shaded = simulate_frame(two_plates(100.0, occluder), np.eye(4), cfg).stats["receiver"]["pixel_background"]
    assert shaded["max_rate_photons_per_s"] == 0.0 and shaded["pixels_with_background"] == 0
    for el in (-10.0, -90.0):
        cfg_low = sunny_config(100.0, el)
        bg = simulate_frame(two_plates(100.0), np.eye(4), cfg_low).stats["receiver"]["pixel_background"]
        assert bg["max_rate_photons_per_s"] == 0.0


def test_only_the_face_the_sensor_sees_counts():
    """The side of the triangle the sensor sees decides: a normal given either way round gives the same rate
    (ρ/π · sin 30° · the common factors, unit solid angle share); the sensor looking at the face turned away
    from the sun gets nothing."""
    cfg = sunny_config(100.0, 30.0)
    args = dict(materials=[BRDFSettings(reflectance=0.3)], material_ids=np.zeros(1, np.int64), range_m=[100.0],
                lit=[True], omega=1.0)
    want = radiance_to_rate(cfg) * 0.3 / math.pi * 0.5
    for n in ([[0.0, 0.0, 1.0]], [[0.0, 0.0, -1.0]]):
        got = subray_solar_rates(cfg, 0.0, normal=n, to_surface=[[0.0, 0.0, -1.0]], **args)
        assert got[0] == pytest.approx(want, rel=1e-14)
        assert subray_solar_rates(cfg, 0.0, normal=n, to_surface=[[0.0, 0.0, 1.0]], **args)[0] == 0.0


def test_chain_takes_each_pixels_background():
    """Four pixels with 0, 1e9, 3e9 and 1e10 photons/s of reflected sunlight on top of the detector's 5e8: each
    pixel's signal-free mean is that of a detector whose fixed rate is the sum (bin_moments), within 5 standard
    errors σ/√B of its 40 000 bins; the chain reports the per-pixel mean and σ that bin_moments gives."""
    det = DetectorSettings(mode="noisy", background_rate_photons_per_s=5e8, read_noise_e=300.0)
    rates = np.array([[0.0, 1e9], [3e9, 1e10]])
    cs = ChainSettings(det, wavelength_m=1.064e-6, bin_width_s=1e-9, pixel_background_rate=rates)
    out = apply_receiver_chain(np.zeros((2, 2, 40_000), np.float32), cs, 7)
    assert out.report["noise_sampling"] == "per-bin"
    step = det.adc_full_scale_e / 2 ** det.adc_bits
    for (i, j), r in np.ndenumerate(rates):
        m, var, _ = bin_moments(DetectorSettings(mode="noisy", background_rate_photons_per_s=5e8 + r,
                                                 read_noise_e=300.0), 0.0, 1e-9)
        mean_counts, sigma_counts = m / step + det.adc_offset_counts, math.sqrt(var) / step
        assert out.pixel_noise["noise_mean"][i, j] == pytest.approx(mean_counts, rel=1e-12)
        assert out.pixel_noise["noise_sigma"][i, j] == pytest.approx(sigma_counts, rel=1e-12)
        got = float(out.data[i, j].astype(np.float64).mean())
        assert abs(got - mean_counts) < 5 * sigma_counts / math.sqrt(40_000), (i, j, got, mean_counts)
    with pytest.raises(ValueError, match="pixel_background_rate"):
        apply_receiver_chain(np.zeros((2, 2, 4), np.float32),
                             ChainSettings(det, pixel_background_rate=np.zeros((2, 3))), 0)


def test_geiger_false_alarms_rise_with_the_reflected_sunlight():
    """Geiger mode, the plate beyond the gate (its echo outside), no dark current, no fixed background: every
    detection is reflected sunlight.  With one detection per pulse (dead time ≥ the gate), a pixel-pulse detects
    with probability 1 − exp(−η Φ T), Φ the closed-form rate and T the 256 ns gate: 15.4 % of 100 pulses × 256
    pixels, within 4 binomial standard errors (0.23 %); with the sun off, none."""
    cfg = sunny_config(100.0, 30.0, irradiance=0.01, bandwidth_nm=1.0)
    cfg.gate.gate_start_s = 0.0  # 0–38 m: the plate's echo at 100 m is outside
    d = cfg.detector
    d.detector_type, d.dark_current_bulk_a, d.dark_current_surface_a = "geiger", 0.0, 0.0
    d.geiger_pulses = 100
    cfg.run.save_waveforms = True
    scene = plate(100.0, 5.0, brdf=BRDFSettings(reflectance=0.3))
    res = simulate_frame(scene, np.eye(4), cfg)
    trials = d.geiger_pulses * 256
    p = float(np.sum(res.digital_waveforms)) / trials
    want = -math.expm1(-d.quantum_efficiency * closed_form_rate(cfg, 0.3, 0.5) * cfg.gate.n_bins * 1e-9)
    assert abs(p - want) <= 4 * math.sqrt(want * (1 - want) / trials), (p, want)
    cfg.atmosphere.solar_irradiance_w_m2_nm = 0.0
    assert float(np.sum(simulate_frame(scene, np.eye(4), cfg).digital_waveforms)) == 0.0


def test_bad_solar_settings_name_the_field():
    cfg = sunny_config(100.0, 30.0)
    cfg.receiver.filter_bandwidth_m = 0.0
    with pytest.raises(ConfigError, match="filter_bandwidth_m"):
        validate_config(cfg)
    cfg = sunny_config(100.0, 30.0, irradiance=-1.0)
    with pytest.raises(ConfigError, match="solar_irradiance_w_m2_nm"):
        validate_config(cfg)


@pytest.mark.parametrize("divergence_y_rad", [0.0, 3e-3])
def test_scanner_pulse_gets_the_closed_form_rate_over_its_beam_cone(divergence_y_rad):
    """Scanner: the receiver sees the beam's 1/e² cone, Ω = π θ_x θ_y/4 (θ_x 1 mrad; circular, and elliptical
    with θ_y 3 mrad), shared equally by the pulse's sub-rays.  A Lambertian wall filling it, sun at 30°: every
    pulse gets ρ/π E Δλ sin 30° A_r Ω τ/(hν), the Lambertian radiance being the same on every sub-ray — to
    rounding (1e-12 relative)."""
    from core.config.settings import SimulationConfig
    from core.run import simulate

    cfg = SimulationConfig(system_type="scanner")
    cfg.scanner.pattern, cfg.scanner.n_lines, cfg.scanner.pulse_rate_hz = "raster", 2, 4000.0
    cfg.scanner.scan_width_rad = cfg.scanner.scan_height_rad = 0.05
    cfg.laser.beam_divergence_rad, cfg.laser.beam_divergence_y_rad = 1e-3, divergence_y_rad
    cfg.gate.n_bins, cfg.gate.gate_start_s, cfg.run.threads = 512, 2 * 30.0 / 299_792_458.0, 1
    cfg.detector.mode, cfg.detector.background_rate_photons_per_s = "noisy", 0.0
    cfg.atmosphere.solar_irradiance_w_m2_nm, cfg.atmosphere.sun_elevation_rad = 1.0, math.radians(30.0)
    res = simulate(plate(40.0, 10.0, brdf=BRDFSettings(reflectance=0.3)), np.eye(4), cfg)
    bg = res.stats["receiver"]["pixel_background"]
    rx = cfg.receiver
    omega = math.pi * 1e-3 * (divergence_y_rad or 1e-3) / 4
    want = (0.3 / math.pi * 1.0 * rx.filter_bandwidth_m * 1e9 * 0.5 * math.pi * (rx.aperture_diameter_m / 2) ** 2
            * omega * rx.system_efficiency * cfg.laser.wavelength_m / (H_PLANCK * C_LIGHT))
    assert bg["max_rate_photons_per_s"] == pytest.approx(want, rel=1e-12)
    assert bg["mean_rate_photons_per_s"] == pytest.approx(want, rel=1e-12)
    per_pulse = res.pulses["solar_background_photons_per_s"]
    assert len(per_pulse) == res.stats["n_pulses"] == bg["pixels_with_background"]
    np.testing.assert_allclose(per_pulse, want, rtol=1e-12)


def test_gated_viewing_sees_the_sunlit_plate_per_pixel():
    """Gated viewing: the same per-pixel rate as the flash (a 32 × 8 camera, 8 × 2 mrad, a Lambertian plate at
    1 km filling it, the sun at 30°: the closed form within the 1e-4 of the solid-angle sampling, the off-axis
    factor being ≤ 1.5 × (0.004² + 0.001²) = 2.6e-5 here); the slices' noise is per pixel (σ and threshold per
    pixel, recorded as their range), and a shadowed half of the plate gets none."""
    from core.config.settings import SimulationConfig
    from core.systems.gated import simulate_gated

    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px, cfg.receiver.height_px = 32, 8
    cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = 8e-3, 2e-3
    cfg.laser.beam_profile = "uniform"
    g = cfg.gated
    g.gate_width_s, g.delay_step_s, g.n_slices = 20e-9, 5e-9, 40
    g.first_delay_s = 2 * 1000.0 / C_LIGHT - 20 * 5e-9
    cfg.run.threads = 1
    cfg.detector.mode, cfg.detector.background_rate_photons_per_s = "noisy", 0.0
    cfg.atmosphere.solar_irradiance_w_m2_nm, cfg.atmosphere.sun_elevation_rad = 1.0, math.radians(30.0)
    scene = plate(1000.0, 20.0, brdf=BRDFSettings(reflectance=0.3))
    res = simulate_gated(scene, np.eye(4), cfg)
    bg = res.stats["receiver"]["pixel_background"]
    rx = cfg.receiver
    omega = (8e-3 / 32) * (2e-3 / 8)
    want = (0.3 / math.pi * rx.filter_bandwidth_m * 1e9 * 0.5 * math.pi * (rx.aperture_diameter_m / 2) ** 2 * omega
            * rx.system_efficiency * cfg.laser.wavelength_m / (H_PLANCK * C_LIGHT))
    assert bg["pixels_with_background"] == 256
    assert abs(bg["max_rate_photons_per_s"] / want - 1) < 1e-4 and abs(bg["mean_rate_photons_per_s"] / want - 1) < 1e-4
    sig = res.stats["detection"]["noise_sigma"]
    assert sig["max"] == pytest.approx(sig["min"], rel=1e-3) and sig["min"] > 0
    # an occluder 20 m above the target, towards the sun, over the half x > 0 of the view: half the pixels dark
    occ = 20.0 / math.tan(math.radians(30.0))
    v = np.concatenate([scene.vertices_m, np.array([[occ, -30, -980.0], [occ + 60, -30, -980.0],
                                                    [occ + 60, 30, -980.0], [occ, 30, -980.0]])])
    two = SceneGeometry(v, np.concatenate([scene.triangles, scene.triangles + 4]), np.zeros(4, np.int64),
                        [BRDFSettings(reflectance=0.3)], ["plate"])
    bg2 = simulate_gated(two, np.eye(4), cfg).stats["receiver"]["pixel_background"]
    assert bg2["pixels_with_background"] == 128 and bg2["max_rate_photons_per_s"] == pytest.approx(want, rel=1e-4)


def _sunlit_pin_frame(sun, mode, threshold_counts=0.0):
    """A PIN camera (3 e⁻ read noise, Δ = 4 e⁻, no dark current) whose 512 × 1 ns gate ends at 77 m, before the
    plate's echo at 100 m: every detection is a false alarm.  Aperture 0.5 m and 0.1 rad over 16 pixels: the
    sunlit plate (ρ 0.3, 1 W m⁻² nm⁻¹, 10 nm, 30°) sends each pixel about 9.8e12 photons/s, η·rate·1 ns ≈ 3920
    primaries a bin, σ ≈ √3920 / 4 = 15.65 counts (0.80 without the sun: read noise and A/D step).
    Returns (config, the receiver report)."""
    cfg = config_for(100.0, pixels=16, fov_rad=0.1, bins=512, bin_s=1e-9)
    cfg.gate.gate_start_s = 0.0
    cfg.receiver.aperture_diameter_m = 0.5
    d = cfg.detector
    d.mode, d.detector_type, d.read_noise_e, d.adc_full_scale_e = "noisy", "pin", 3.0, 4.0 * 4096
    d.background_rate_photons_per_s = d.dark_current_bulk_a = d.dark_current_surface_a = 0.0
    det = cfg.detection
    det.noisy_threshold_mode, det.k_sigma, det.threshold_counts, det.max_echoes = mode, 3.0, threshold_counts, 32
    cfg.atmosphere.solar_irradiance_w_m2_nm = 1.0 if sun else 0.0
    cfg.atmosphere.sun_elevation_rad = math.radians(30.0)
    return cfg, simulate_frame(plate(100.0, 20.0, brdf=BRDFSettings(reflectance=0.3)), np.eye(4),
                               cfg).stats["receiver"]


def test_false_alarms_follow_each_pixels_sunlit_noise():
    """The detection sees each pixel's background.  Calibrated threshold (3 σ of the filtered noise, σ per
    pixel): the false alarms of 256 pixels × 512 bins match the Gaussian expectation for each pixel's σ.
    Fixed threshold (30 counts): none without the sun (expectation ~1e-295), with it the number the larger σ
    gives.  Tolerance: 4 Poisson standard deviations √μ, plus 5 % for the Gaussian form of the expectation (the
    Poisson(3920) primaries have skewness 0.016 per bin, less after the matched filter; at 3 σ the tail moves by
    about skewness × (t³ − 3t)/6 ≈ 5e-3 relative)."""
    cfg, r = _sunlit_pin_frame(True, "calibrated")
    # each pixel's σ: the on-axis rate (Ω of the tan-space cell, (2 tan 0.05 / 16)²) times the off-axis factor
    # (1 + x² + y²)^(−3/2) ≥ 1 − 1.5 × 2 × 0.05² = 0.9925 at the corners (σ: half that)
    phi = closed_form_rate(cfg, 0.3, 0.5) * (2 * math.tan(0.05) / 0.1) ** 2
    sigma_axis = math.sqrt(0.4 * phi * 1e-9 + 9.0 + 16.0 / 12.0) / 4.0
    sig = r["false_alarms"]["noise_sigma"]
    assert sigma_axis * (1 - 3.75e-3) <= sig["min"] < sig["max"] <= sigma_axis * (1 + 1e-12), (sig, sigma_axis)
    for rec in (r, _sunlit_pin_frame(True, "fixed", 30.0)[1]):
        n, mu = rec["false_alarms"]["n_false_alarms"], rec["false_alarms"]["expected_false_alarms_gaussian"]
        assert mu > 1.0 and abs(n - mu) <= 4 * math.sqrt(mu) + 0.05 * mu, (n, mu)
    dark = _sunlit_pin_frame(False, "fixed", 30.0)[1]["false_alarms"]
    assert dark["n_false_alarms"] == 0 and dark["expected_false_alarms_gaussian"] < 1e-6
