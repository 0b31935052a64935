# Ladar Simulator sensor preset: airborne full-waveform laser scanner at 1064 nm (oscillating mirror).
# Modelled on published specifications of airborne topographic scanners of this class (e.g. Leica ALS60,
# Optech ALTM Gemini: Nd:YAG 1064 nm, 100–200 kHz pulse rate, oscillating mirror of up to ~50–100 Hz over a
# 40–75° field, ~0.2 mrad beam divergence, waveform digitised at 1 ns).  Flying height ~1 km: the range gate
# covers 900–1130 m (slant ranges to ±20° off nadir).  Pulse energy, aperture and detector figures are
# representative of the class, not the data sheet of a specific product.  Save the waveforms with Run > Save
# Waveforms (on by default).
# Values are in SI units (wavelengths in m); the add-on converts them to the stored units and validates them.
# Sets the camera shown in the Properties editor (else the scene's ladar sensor or camera): point it down (−Z
# of the camera towards the ground) and animate it along the flight line.  Run settings are left alone.
import math
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_sensor_preset({
    "system_type": "scanner",
    "laser": {"wavelength_m": 1.064e-6, "pulse_energy_j": 0.1e-3, "pulse_shape": "gaussian", "pulse_fwhm_s": 5e-9,
              "beam_profile": "gaussian", "beam_divergence_rad": 0.22e-3, "divergence_fills_fov": False},
    "receiver": {"aperture_diameter_m": 0.08, "system_efficiency": 0.5},
    "scanner": {"pattern": "oscillating", "pulse_rate_hz": 100_000.0, "scan_rate_hz": 50.0,
                "scan_width_rad": math.radians(40.0), "duration_s": 0.0, "beam_subray_rings": 2},
    "gate": {"gate_start_s": 6.0e-6, "bin_width_s": 1e-9, "n_bins": 1536},
    "detection": {"max_echoes": 5},
    "detector": {"mode": "noisy", "detector_type": "apd", "quantum_efficiency": 0.35, "apd_gain": 100.0,
                 "apd_k_eff": 0.02, "dark_current_bulk_a": 1e-11, "dark_current_surface_a": 5e-9,
                 "read_noise_e": 300.0, "adc_bits": 12},
})
