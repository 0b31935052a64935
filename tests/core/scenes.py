"""Small analytic scenes for the core tests (plates in the sensor frame: the sensor looks along −Z)."""
import numpy as np

from core.config.settings import BRDFSettings, DetectorSettings, SimulationConfig
from core.geometry.scene import SceneGeometry
from core.physics.receiver.chain import ChainSettings, apply_receiver_chain

C = 299_792_458.0


def plate(distance_m, half_size_m, brdf=None, tilt_rad=0.0, offset=(0.0, 0.0, 0.0)):
    """A square plate facing the sensor at ``distance_m`` along −Z, tilted about the x axis by ``tilt_rad``."""
    u = np.array([1.0, 0.0, 0.0])
    v = np.array([0.0, np.cos(tilt_rad), -np.sin(tilt_rad)])
    c = np.array([0.0, 0.0, -distance_m]) + np.asarray(offset)
    h = half_size_m
    verts = np.array([c - h * u - h * v, c + h * u - h * v, c + h * u + h * v, c - h * u + h * v])
    return SceneGeometry(verts, [[0, 1, 2], [0, 2, 3]], [0, 0], [brdf or BRDFSettings()], ["plate"])


def config_for(range_m, pixels=16, subsamples=4, fov_rad=0.01, bins=256, bin_s=1e-9, margin_bins=64):
    """A flash config whose gate opens ``margin_bins`` before the echo of a surface at ``range_m``."""
    cfg = SimulationConfig()
    cfg.receiver.width_px = cfg.receiver.height_px = pixels
    cfg.receiver.subsamples = subsamples
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = fov_rad
    cfg.gate.n_bins = bins
    cfg.gate.bin_width_s = bin_s
    cfg.gate.gate_start_s = max(0.0, 2 * range_m / C - margin_bins * bin_s)
    cfg.run.threads = 1
    return cfg


#: The §8 APD with a 12-bit A/D (docs/receiver.md) and a 5e9 photons/s background: the receiver tests' detector.
SEC8 = dict(quantum_efficiency=0.4, apd_gain=100.0, apd_k_eff=0.02, dark_current_bulk_a=1e-12,
            dark_current_surface_a=1e-9, read_noise_e=300.0, adc_bits=12, adc_full_scale_e=500.0 * 4096,
            adc_offset_counts=16, background_rate_photons_per_s=5e9)


def sec8_chain(cube, rng, noise_table=True, **det):
    """The noisy receiver chain with the SEC8 detector (``det`` overrides), 1064 nm, 1 ns bins."""
    return apply_receiver_chain(cube, ChainSettings(DetectorSettings(**{"mode": "noisy", **SEC8, **det}),
                                                    wavelength_m=1.064e-6, bin_width_s=1e-9), rng,
                                noise_table=noise_table)


def gated_fog_pixel(**atmosphere):
    """Gated viewing of a pixel that sees only the atmosphere (8×8 px over 0.01 rad, a 10 ns pulse, 30 slices of
    20 ns every 10 ns from 0, O = 1, nothing returned below 2 m; a 5 cm plate at 40 m off that pixel), with the
    fog ``atmosphere`` settings on top.  Returns (the run's result, the config, the slices' delays (s), the energy
    scale F_p E η π r_a² of the corner pixel (the beam's share F_p of it times energy_scale), the homogeneous
    extinction α₀ (1/m))."""
    import dataclasses

    from core.geometry.rays import Detector
    from core.physics.laser import cell_energy_fractions
    from core.physics.propagation import aerosol_extinction_per_m
    from core.physics.radiometry import energy_scale
    from core.systems.gated import simulate_gated

    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px = cfg.receiver.height_px = 8
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.01
    cfg.laser.pulse_fwhm_s = 10e-9
    g = cfg.gated
    g.gate_width_s, g.delay_step_s, g.n_slices, g.first_delay_s = 20e-9, 10e-9, 30, 0.0
    cfg.atmosphere = dataclasses.replace(cfg.atmosphere, weather="fog", overlap_model="none",
                                         backscatter_min_range_m=2.0, **atmosphere)
    cfg.run.threads = 1
    r = simulate_gated(plate(40.0, 0.05), np.eye(4), cfg)
    det = Detector.from_settings(cfg.receiver)
    fx, fy = cell_energy_fractions(cfg.laser, det)
    s = det.subsamples
    scale = fx[:s].sum() * fy[:s].sum() * energy_scale(cfg.laser, cfg.receiver)
    delays = g.first_delay_s + g.delay_step_s * np.arange(g.n_slices)
    return r, cfg, delays, scale, aerosol_extinction_per_m(cfg)
