# Ladar Simulator detector preset: InGaAs/InP linear-mode APD at 1550 nm (eye-safe).
# Published-typical values for this detector class, not the data sheet of a specific product.
# Sets the detector of the camera shown in the Properties editor (else the scene's ladar sensor or camera)
# and switches the receiver chain to "noisy".
import bpy

obj = bpy.context.object if getattr(bpy.context, "object", None) is not None and bpy.context.object.type == "CAMERA" else (bpy.context.scene.ladar.sensor or bpy.context.scene.camera)
detector = obj.ladar.detector

detector.mode = "noisy"
detector.detector_type = "apd"
detector.quantum_efficiency = 0.8
detector.apd_gain = 15.0
detector.apd_k_eff = 0.4
# Dark currents are stored scaled: bulk in units of 1e-12 A (pA), surface in units of 1e-9 A (nA).
detector.dark_current_bulk_a = 1000.0  # 1 nA bulk (multiplied: 15 nA at G = 15)
detector.dark_current_surface_a = 10.0  # 10 nA surface
detector.read_noise_e = 300.0
