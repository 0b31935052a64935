"""Sub-resolution sampling of the receiver pixels: where each sub-ray goes, what it stands for.

A sub-ray samples a cell of its pixel in the tan plane (core/rays.py).  Besides its direction and its share of
the beam energy, the cell has an extent: the surface it hits spans a range interval across the cell.  This
module computes that interval to first order (the time spread that core/waveform.py convolves with the pulse).

Range over a plane, tan-plane direction p = (x, y, −1), unit normal n (sensor frame), R₀ at p₀:

    R(p) = D |p| / (n·p)        ⇒   ∂R/∂x = R [x/|p|² − n_x/(n·p)],   ∂R/∂y = R [y/|p|² − n_y/(n·p)]

so a cell of tan-plane size δx × δy spans round-trip times uniform over U(a) ⊛ U(b) with
a = (2/c)|∂R/∂x| δx, b = (2/c)|∂R/∂y| δy (exact for a cell small enough that R is linear across it).
"""
from __future__ import annotations

import numpy as np

SPEED_OF_LIGHT_M_S = 299_792_458.0


def range_gradient_tan(x_tan, y_tan, range_m, normal_sensor):
    """(∂R/∂x, ∂R/∂y) in metres per tan-plane unit at sub-rays hitting planes of unit normal ``normal_sensor``
    (n, 3) (sensor frame, either orientation)."""
    x = np.asarray(x_tan, dtype=np.float64)
    y = np.asarray(y_tan, dtype=np.float64)
    r = np.asarray(range_m, dtype=np.float64)
    n = np.asarray(normal_sensor, dtype=np.float64)
    p2 = x * x + y * y + 1.0
    n_dot_p = n[:, 0] * x + n[:, 1] * y - n[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(n_dot_p != 0.0, 1.0 / n_dot_p, np.inf)
        gx = r * (x / p2 - n[:, 0] * inv)
        gy = r * (y / p2 - n[:, 1] * inv)
    return gx, gy


def cell_time_spread_s(x_tan, y_tan, range_m, normal_sensor, cell_x_tan, cell_y_tan, max_spread_s=np.inf):
    """Full widths (n, 2) in seconds of the two boxes of round-trip times a sub-ray cell spans (module doc).

    Widths are capped at ``max_spread_s`` (the pipeline passes 1000 gate lengths: a cell that spans more than
    that is spread over far more than the gate either way) and are finite."""
    gx, gy = range_gradient_tan(x_tan, y_tan, range_m, normal_sensor)
    a = 2.0 / SPEED_OF_LIGHT_M_S * np.abs(gx) * np.asarray(cell_x_tan, dtype=np.float64)
    b = 2.0 / SPEED_OF_LIGHT_M_S * np.abs(gy) * np.asarray(cell_y_tan, dtype=np.float64)
    out = np.stack([a, b], axis=1)
    out[~np.isfinite(out)] = max_spread_s
    return np.minimum(out, max_spread_s)
