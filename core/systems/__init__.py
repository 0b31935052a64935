"""Sensor systems: 3D flash and range profiler (:mod:`.flash`), time-of-flight scanner (:mod:`.scanner`) and gated
viewing (:mod:`.gated`)."""
