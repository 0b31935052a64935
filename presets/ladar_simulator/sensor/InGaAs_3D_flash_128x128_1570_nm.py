# Ladar Simulator sensor preset: 3D flash ladar camera, 128×128 InGaAs APD array, 1570 nm (eye-safe).
# Modelled on the published descriptions of 128×128 InGaAs 3D flash cameras (Advanced Scientific Concepts
# TigerEye/Portable 3D Flash LIDAR: Stettner, Proc. SPIE 7684, 768405, 2010; the FOI experiments of the seed
# paper used such a camera): 128×128 pixels, 1570 nm, ns pulses, an 8.6° lens option.  Pulse energy, aperture,
# gate and detector figures are representative of the class, not the data sheet of a specific product.
# Values are in SI units (wavelengths in m); the add-on converts them to the stored units and validates them.
# Sets the camera shown in the Properties editor (else the scene's ladar sensor or camera); the camera's lens is
# set so that the receiver sees the field of view.  Run settings (seed, threads, memory) are left alone.
import math
import sys

presets = next(m for n, m in sys.modules.items() if n.endswith("ladar_simulator.ladar_addon.presets"))
presets.apply_sensor_preset({
    "system_type": "flash",
    "laser": {"wavelength_m": 1.57e-6, "pulse_energy_j": 3e-3, "pulse_shape": "gaussian", "pulse_fwhm_s": 5e-9,
              "beam_profile": "gaussian", "divergence_fills_fov": True},
    "receiver": {"width_px": 128, "height_px": 128, "fov_x_rad": math.radians(8.6),
                 "aperture_diameter_m": 0.04, "system_efficiency": 0.5},
    # 1 ns bins over 0–307 m: move gate_start_s to the scene's range (2R/c).
    "gate": {"gate_start_s": 0.0, "bin_width_s": 1e-9, "n_bins": 2048},
    "detection": {"max_echoes": 3},
    "detector": {"mode": "noisy", "detector_type": "apd", "quantum_efficiency": 0.8, "apd_gain": 15.0,
                 "apd_k_eff": 0.4, "dark_current_bulk_a": 1e-9, "dark_current_surface_a": 1e-8,
                 "read_noise_e": 300.0, "adc_bits": 14},
})
