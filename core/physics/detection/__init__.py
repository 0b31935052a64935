"""Echo detection: noise-free peaks (:mod:`.peaks`) and detection in noisy digital waveforms (:mod:`.noisy`)."""
