# Ladar Simulator detector preset: Geiger-mode APD (single-photon) focal-plane array.
# Published-typical values for this detector class, not the data sheet of a specific product.
# Sets the detector of the camera shown in the Properties editor (else the scene's ladar sensor or camera)
# and switches the receiver chain to "noisy".
import bpy

obj = bpy.context.object if getattr(bpy.context, "object", None) is not None and bpy.context.object.type == "CAMERA" else (bpy.context.scene.ladar.sensor or bpy.context.scene.camera)
detector = obj.ladar.detector

detector.mode = "noisy"
detector.detector_type = "geiger"
detector.quantum_efficiency = 0.25  # photon detection efficiency (PDE)
detector.geiger_pulses = 100
# Dead time in range bins: 100 bins = 100 ns at the default 1 ns bin width.
detector.geiger_dead_time_bins = 100
# Dark counts come from the bulk dark current, stored in units of 1e-12 A (pA): 1 fA = about 6 kHz of primary
# dark electrons, a typical dark count rate of one Geiger-mode pixel.
detector.dark_current_bulk_a = 0.001  # 1 fA
detector.dark_current_surface_a = 0.0
