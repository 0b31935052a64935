"""Laser source: spatial beam profile and temporal pulse shape (paper §3.1, "laser source" settings).

Spatial: the fraction of the pulse energy that leaves the (monostatic) transmitter inside each sub-ray cell
of the receiver's tan-plane grid.  For the Gaussian TEM00 beam the far-field intensity in tan-plane
coordinates is p(x, y) = 2/(π w²) exp(−2(x² + y²)/w²), w = tan(θ_div/2) (1/e² half-angle), normalised over the
whole plane; the energy of a rectangular cell is exact and separable:

    F = ¼ [erf(√2 x₁/w) − erf(√2 x₀/w)] · [erf(√2 y₁/w) − erf(√2 y₀/w)].

The uniform profile spreads the energy evenly over the receiver field of view.

Temporal: the pulse shape's cumulative distribution; integrating it over each time bin is how the waveform
avoids point-sampling a pulse narrower than a bin.
"""
from __future__ import annotations

import numpy as np
from scipy.special import erf, ndtr

from .config import LaserSettings
from .rays import Detector

FWHM_TO_SIGMA = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def beam_half_angle_tan(laser: LaserSettings, det: Detector) -> float:
    """1/e² beam radius w in tan-plane units (fills the FOV diagonal if asked)."""
    if laser.divergence_fills_fov:
        return float(np.hypot(det.half_width_tan, det.half_height_tan))
    return float(np.tan(laser.beam_divergence_rad / 2))


def cell_energy_fractions(laser: LaserSettings, det: Detector, center_offset_tan=(0.0, 0.0), width_scale=1.0):
    """Per-axis factors (fx (W·S,), fy (H·S,)) whose outer product is the fraction of the pulse energy in each
    sub-ray cell: fraction[sub_y, sub_x] = fy[sub_y]·fx[sub_x].

    ``center_offset_tan`` displaces the beam centre (beam wander / pointing) in tan-plane units;
    ``width_scale`` widens the Gaussian beam (turbulent broadening), keeping its total energy.
    """
    x_edges, y_edges = det.sub_cell_edges()
    if laser.beam_profile == "uniform":
        nx, ny = len(x_edges) - 1, len(y_edges) - 1
        return np.full(nx, 1.0 / nx), np.full(ny, 1.0 / ny)
    w = beam_half_angle_tan(laser, det) * width_scale
    k = np.sqrt(2.0) / w
    ex = erf(k * (x_edges - center_offset_tan[0]))
    ey = erf(k * (y_edges - center_offset_tan[1]))
    fx = 0.5 * np.abs(np.diff(ex))
    fy = 0.5 * np.abs(np.diff(ey))
    return fx, fy


def pulse_sigma_s(laser: LaserSettings) -> float:
    """Standard deviation of the Gaussian pulse (s)."""
    return laser.pulse_fwhm_s * FWHM_TO_SIGMA


def pulse_half_support_s(laser: LaserSettings) -> float:
    """Half-width beyond which the pulse carries < 1e-9 of its energy (Gaussian: 6.1σ)."""
    if laser.pulse_shape == "gaussian":
        return 6.1 * pulse_sigma_s(laser)
    return 0.5 * laser.pulse_fwhm_s


def pulse_cdf(laser: LaserSettings, t_s):
    """Fraction of the pulse energy emitted before time t (the pulse is centred on t = 0)."""
    t_s = np.asarray(t_s, dtype=np.float64)
    if laser.pulse_shape == "gaussian":
        return ndtr(t_s / pulse_sigma_s(laser))
    return np.clip(t_s / laser.pulse_fwhm_s + 0.5, 0.0, 1.0)

