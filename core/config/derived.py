"""Values derived from the settings alone (no physics, no geometry): the scan pattern's duration and pulse counts.

They live here, below every other layer, so that validation (which bounds the waveform memory of a scan by its
pulse count) needs nothing above the settings."""
from __future__ import annotations

import numpy as np

from .tables import scan_channels


def scan_duration_s(config) -> float:
    """Duration of the scan: ``scanner.duration_s`` or one full pattern."""
    s = config.scanner
    if s.duration_s > 0:
        return s.duration_s
    if s.pattern == "raster":
        return s.n_lines / s.scan_rate_hz
    if s.pattern == "rotating":
        return max(s.scan_width_rad, 1e-12) / (2 * np.pi * s.scan_rate_hz)
    return 1.0 / s.scan_rate_hz  # oscillating: one mirror period; palmer: one revolution; risley: 1/scan_rate


def n_pulse_times(config) -> int:
    """Firing times in the scan (each fires n_channels pulses for the rotating head)."""
    return max(1, int(np.floor(scan_duration_s(config) * config.scanner.pulse_rate_hz + 1e-9)))


def n_scan_pulses(config) -> int:
    return n_pulse_times(config) * scan_channels(config.scanner)
