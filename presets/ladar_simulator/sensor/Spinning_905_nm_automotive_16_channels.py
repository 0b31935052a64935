# Ladar Simulator sensor preset: spinning automotive time-of-flight scanner, 16 channels, 905 nm.
# Modelled on the published characteristics of 16-channel spinning lidars such as the Velodyne VLP-16 (user
# manual: 16 lasers over a 30° vertical field, 360° horizontal, 5–20 Hz rotation, ~300 000 points/s, i.e. a
# 55.3 µs firing cycle; ~903 nm; ~3 mrad beam divergence; up to 100 m; strongest and last return).
# Pulse energy, aperture and detector figures are representative of the class, not the data sheet of a product.
# Values are in SI units (wavelengths in m); the add-on converts them to the stored units and validates them.
# Sets the camera shown in the Properties editor (else the scene's ladar sensor or camera): the head spins about
# the camera's +Y axis.  Run settings (seed, threads, memory) are left alone.
import math
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_sensor_preset({
    "system_type": "scanner",
    "laser": {"wavelength_m": 9.05e-7, "pulse_energy_j": 0.2e-6, "pulse_shape": "gaussian", "pulse_fwhm_s": 6e-9,
              "beam_profile": "gaussian", "beam_divergence_rad": 3e-3, "divergence_fills_fov": False},
    "receiver": {"aperture_diameter_m": 0.025, "system_efficiency": 0.5},
    "scanner": {"pattern": "rotating", "pulse_rate_hz": 18_080.0, "scan_rate_hz": 10.0,
                "scan_width_rad": 2.0 * math.pi, "scan_height_rad": math.radians(30.0), "n_channels": 16,
                "duration_s": 0.0, "beam_subray_rings": 1},
    # 1 ns bins over 0–210 m.
    "gate": {"gate_start_s": 0.0, "bin_width_s": 1e-9, "n_bins": 1400},
    "detection": {"max_echoes": 2},
    "detector": {"mode": "noisy", "detector_type": "apd", "quantum_efficiency": 0.8, "apd_gain": 100.0,
                 "apd_k_eff": 0.02, "dark_current_bulk_a": 1e-11, "dark_current_surface_a": 5e-9,
                 "read_noise_e": 300.0, "adc_bits": 12},
})
