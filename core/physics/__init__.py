"""Physics layer: laser, BRDF, radiometry, propagation through the atmosphere, waveforms, sub-ray sampling,
echo detection (:mod:`.detection`) and the receiver chain (:mod:`.receiver`).  Formulas beside the code; no file
output; imports only the settings, geometry and atmosphere layers below it."""
