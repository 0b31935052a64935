# Ladar Simulator sensor preset: burst-illumination / gated-viewing system at 532 nm, gates swept around 1 km.
# Modelled on the published FOI range-gated imaging experiments (Andersson, Opt. Eng. 45, 034301, 2006;
# docs/theory.md §9): a frequency-doubled Nd:YAG laser at 532 nm flood-lighting the scene, a gated intensified
# camera, a sweep of gate delays in ns steps.  The intensifier is represented by the APD model with a high gain
# and k_eff = 0 (excess noise F ≈ 2, as a microchannel plate) and a photocathode-like quantum efficiency.
# Pulse energy, aperture, pixel count and noise figures are representative of the class, not the data sheet of
# a specific product.
# Values are in SI units (wavelengths in m); the add-on converts them to the stored units and validates them.
# Sets the camera shown in the Properties editor (else the scene's ladar sensor or camera); the camera's lens is
# set so that the receiver sees the field of view.  Run settings (seed, threads, memory) are left alone.
import math
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_sensor_preset({
    "system_type": "gated",
    "laser": {"wavelength_m": 5.32e-7, "pulse_energy_j": 10e-3, "pulse_shape": "gaussian", "pulse_fwhm_s": 5e-9,
              "beam_profile": "gaussian", "divergence_fills_fov": True},
    "receiver": {"width_px": 256, "height_px": 256, "fov_x_rad": math.radians(1.0),
                 "aperture_diameter_m": 0.1, "system_efficiency": 0.4},
    # First gate opens at 2·990 m/c = 6.604 µs; 30 gates 2 ns (0.30 m) apart cover 990–999 m and beyond.
    "gated": {"first_delay_s": 6.604e-6, "delay_step_s": 2e-9, "n_slices": 30, "gate_width_s": 20e-9,
              "shutter_edge_s": 1e-9, "range_method": "centroid"},
    "detector": {"mode": "noisy", "detector_type": "apd", "quantum_efficiency": 0.2, "apd_gain": 1000.0,
                 "apd_k_eff": 0.0, "dark_current_bulk_a": 1e-15, "dark_current_surface_a": 1e-12,
                 "read_noise_e": 20.0, "adc_bits": 12},
})
