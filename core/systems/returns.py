"""What a scanner reports of its echoes (``scanner.return_mode``, ``range_quantum_m``, ``intensity_encoding``).

Return modes, per pulse, of the echoes detected (``detection.max_echoes`` at most, in time order):

* ``all``        every echo (the default; as before);
* ``strongest``  the echo of largest amplitude (the first of equals);
* ``last``       the last (farthest) echo;
* ``dual``       the strongest and the last; when they are the same echo, the last and the second strongest (the
                 Velodyne dual-return rule), so a pulse with two or more echoes gives two points;
* ``first_n``    the first ``n_returns`` echoes.

A reported point keeps its echo number and the pulse's number of detected echoes.

Range quantum q > 0: the range is rounded to the nearest multiple of q (error ≤ q/2), and the point placed at that
range along the beam axis; the echo time is 2·range/c.

Intensity encodings (ideal detector): the echo amplitude A is compared with A_ref(R), the amplitude a Lambertian
target of reflectance 1 filling the beam at normal incidence would give at the echo's range R (same laser,
receiver and extinction; the pulse's peak per bin of one echo centred in a bin):  ρ = A / A_ref(R).

* ``amplitude``     A (J per bin), as before;
* ``reflectivity``  calibrated reflectivity as Velodyne defines its scale: 0–100 for diffuse targets of
                    reflectance 0–100 % (round(100 ρ)), 101–255 for retro-reflectors (ρ > 1), here
                    101 + round(154 · min(1, log10(ρ)/3)): a gain of 1000 over a white Lambertian target or more is
                    255;
* ``intensity8``    an 8-bit range-compensated intensity: round(255 · min(ρ, 1)).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..config.settings import BRDFSettings
from ..constants import SPEED_OF_LIGHT_M_S
from ..physics.detection.peaks import detect_echoes
from ..physics.radiometry import received_energy
from ..physics.waveform import accumulate_waveforms, binning_method


def select_returns(pixel, amplitude, echo_index, n_echoes, mode: str, n_returns: int = 1) -> np.ndarray:
    """Boolean mask of the echoes reported in ``mode`` (echoes ordered by pixel, then time)."""
    k = len(pixel)
    if mode == "all" or k == 0:
        return np.ones(k, dtype=bool)
    echo_index, n_echoes = np.asarray(echo_index), np.asarray(n_echoes)
    if mode == "first_n":
        return echo_index < n_returns
    last = echo_index == n_echoes - 1
    if mode == "last":
        return last
    # rank of each echo by amplitude within its pixel: 0 = strongest (first of equals)
    order = np.lexsort((np.arange(k), -np.asarray(amplitude, dtype=np.float64), np.asarray(pixel)))
    starts = np.flatnonzero(np.r_[True, np.diff(np.asarray(pixel)[order]) != 0])
    group = np.repeat(starts, np.diff(np.r_[starts, k]))
    rank = np.empty(k, dtype=np.int64)
    rank[order] = np.arange(k) - group
    strongest = rank == 0
    if mode == "strongest":
        return strongest
    # dual: strongest + last; a pixel whose strongest is its last reports its second strongest instead
    strongest_is_last = np.zeros(k, dtype=bool)
    pix_of = np.asarray(pixel)
    both = pix_of[strongest & last]
    strongest_is_last = np.isin(pix_of, both)
    return last | (strongest & ~strongest_is_last) | ((rank == 1) & strongest_is_last)


def quantize_range(range_m, quantum_m: float):
    """Ranges rounded to the nearest multiple of ``quantum_m`` (unchanged for 0)."""
    if not quantum_m:
        return range_m
    return np.round(np.asarray(range_m) / quantum_m) * quantum_m


def peak_per_joule(config) -> float:
    """The detected peak amplitude (J per bin) of a single echo of 1 J centred in a bin, as the detector finds it
    with the run's pulse, binning and interpolation."""
    laser, gate = config.laser, config.gate
    half = 8 * laser.pulse_fwhm_s / gate.bin_width_s
    n_bins = int(min(max(16, 2 * np.ceil(half) + 2), 1_000_000))
    g = dataclasses.replace(gate, gate_start_s=0.0, n_bins=n_bins)
    t = (n_bins // 2 + 0.5) * gate.bin_width_s
    wf = accumulate_waveforms(np.zeros(1, np.int64), np.array([t]), np.array([1.0]), 1, laser, g,
                              binning_method(laser, g))
    det = dataclasses.replace(config.detection, threshold_j=0.0, relative_threshold=0.0)
    ech = detect_echoes(wf, det)
    return float(ech.amplitude.max()) if len(ech.amplitude) else float(wf.max())


def reference_amplitude(config, range_m, extinction_per_m: float, peak: float | None = None):
    """A_ref(R): the echo amplitude (J per bin) of a Lambertian reflectance-1 target filling the beam, normal to
    it, at ``range_m``."""
    r = np.asarray(range_m, dtype=np.float64).reshape(-1)
    e = received_energy(config.laser, config.receiver, extinction_per_m, [BRDFSettings(reflectance=1.0)],
                        np.zeros(len(r), np.int64), np.ones(len(r)), np.maximum(r, 1e-6), 1.0)
    return e * (peak_per_joule(config) if peak is None else peak)


def encode_intensity(amplitude, range_m, config, extinction_per_m: float, peak: float | None = None):
    """The points' intensity in ``scanner.intensity_encoding`` (float32; whole numbers 0–255 when encoded)."""
    mode = config.scanner.intensity_encoding
    amplitude = np.asarray(amplitude, dtype=np.float64)
    if mode == "amplitude":
        return amplitude.astype(np.float32)
    rho = amplitude / reference_amplitude(config, range_m, extinction_per_m, peak)
    if mode == "intensity8":
        return np.round(255.0 * np.clip(rho, 0.0, 1.0)).astype(np.float32)
    diffuse = np.round(100.0 * np.clip(rho, 0.0, 1.0))
    retro = 101.0 + np.round(154.0 * np.clip(np.log10(np.maximum(rho, 1.0)) / 3.0, 0.0, 1.0))
    return np.where(rho > 1.0, retro, diffuse).astype(np.float32)


def intensity_unit(config, default: str) -> str:
    """The unit of the points' intensity in the run's encoding."""
    return {"reflectivity": "calibrated reflectivity 0-255 (0-100 diffuse %, 101-255 retro)",
            "intensity8": "8-bit intensity 0-255"}.get(config.scanner.intensity_encoding, default)
