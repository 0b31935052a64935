"""A scanner pulse's sub-ray returns as one tabulated pulse at their energy centroid (``scanner.pulse_model =
"centroid"``), with its second-moment correction; the sub-ray sum (``"subrays"``, :class:`.waveform.PulseTable`)
is the reference.

A pulse's waveform is the sum of its m sub-ray returns, each the bin-integrated pulse F(b; u) (the energy of a
pulse centred at u, in gate bins, that falls in bin b; :class:`.waveform.PulseTable`) times its energy e_i:

    w_b = Σ_i e_i F(b; u_i).

With E = Σ e_i, the centroid ū = Σ e_i u_i / E, d_i = u_i − ū, V = Σ e_i d_i² / E and M₃ = Σ e_i |d_i|³ / E,
Taylor's theorem with the Lagrange remainder at third order, summed with Σ e_i d_i = 0, gives (docs/systems.md,
"The centroid pulse"):

    w_b = E [F(b; ū) + ½ V ∂²F/∂u²(b; ū)] − (1/6) Σ_i e_i d_i³ ∂³F/∂u³(b; ξ_i),

so the centroid pulse E [F + ½ V F''] differs from the sum in every bin by at most

    |Δw_b| ≤ (E M₃ / 6) max_s |∂³F/∂u³| = ε · E max_s F,    ε = M₃ B₃ / 6,    B₃ = max |F'''| / max F,

a bound relative to the peak bin of one pulse of energy E (the pulse's own peak is within ½ V max|F''| of it).
For a Gaussian pulse of σ bins, B₃ ≈ max|z³ − 3z| e^(−z²/2) / σ³ = 1.380/σ³ (the bin integral only lowers it).
A pulse takes the centroid route when ε ≤ :data:`CENTROID_BIN_TOLERANCE`, all its returns lie inside the gate
with the centroid pulse's whole support, and none carries an infinite energy; every other pulse (a multi-echo
pulse in a canopy or over an edge, whose returns spread over the pulse width: ε ≫ the tolerance) is summed
sub-ray by sub-ray exactly as the reference does, bit for bit.

What the bound means for the echoes (3-point interpolation around the peak bin, Gaussian or parabolic): each of
the three samples moves by at most ε of the peak, so the echo position moves by at most 3 ε σ'² bins
(σ'² = σ² + 1/12, the bin-integrated pulse's variance; the derivation is in docs/systems.md), the amplitude by
≈ 3 ε of itself (but for the detector's own flat tops: docs/systems.md), and the echo count changes only where the exact waveform lies within ε of a threshold (the
centroid pulse is unimodal for V < 2σ²/3, so a pulse on this route has one echo).

Echo detection on the centroid route reads only the bins around the peak (:data:`PEAK_HALF_WINDOW` each side of
the bin holding ū): for a unimodal row :func:`~.detection.peaks.detect_row` finds the same single maximum, the
same threshold (the row's maximum is inside) and the same interpolated echo there as on the whole row; a row
whose maximum falls on the window's edge is built and detected whole instead.
"""
from __future__ import annotations

import math

import numpy as np

from ..jit import kernel
from .detection.peaks import INTERPOLATION, Echoes, detect_row
from ..constants import SPEED_OF_LIGHT_M_S
from .laser import pulse_sigma_s
from .waveform import PulseTable, window_echoes

#: Largest bound ε (relative to the pulse's peak bin, :mod:`module docstring <core.physics.pulse_table>`) of a pulse
#: on the centroid route: 1e-4 keeps its echo position within 3 ε σ'² bins (0.014 bins = 0.5 mm for HELIOS++'s
#: 4 ns pulse in 0.25 ns bins, 1/1100 of the pulse's range resolution c·FWHM/2 = 0.6 m) and its amplitude within
#: ≈ 1e-4 of itself.
CENTROID_BIN_TOLERANCE = 1e-4

#: Bins each side of the centroid's bin over which a centroid-route pulse is built and detected.
PEAK_HALF_WINDOW = 4

#: The pulse models of ``scanner.pulse_model``.
PULSE_MODELS = ("subrays", "centroid")


def _gauss_derivatives(s, sigma):
    """g(s), g'(s), g''(s), g'''(s) of the Gaussian pdf of σ bins at s bins."""
    z = s / sigma
    g = np.exp(-0.5 * z * z) / (math.sqrt(2.0 * math.pi) * sigma)
    return g, -z / sigma * g, (z * z - 1.0) / sigma ** 2 * g, -(z ** 3 - 3.0 * z) / sigma ** 3 * g


class CentroidPulseTable:
    """:class:`.waveform.PulseTable` (the reference's rows, shared) with the second derivative of its rows in the
    position, tabulated the same way: ∂²F/∂u²(j + m; j + f) = g'(m + 1 − f) − g'(m − f), g the pulse's pdf in bins;
    and B₃ = max |∂³F/∂u³| / max F (sampled on a grid of min(1, σ)/64 bin: the sampling misses the maximum of a
    smooth curve by a relative O(1/64)², 2.4e-4)."""

    def __init__(self, laser, bin_width_s, tolerance: float = CENTROID_BIN_TOLERANCE):
        if laser.pulse_shape != "gaussian":
            raise ValueError("the centroid pulse model needs a Gaussian pulse")
        self.base = PulseTable(laser, bin_width_s)
        self.sigma_bins = pulse_sigma_s(laser) / bin_width_s
        self.tolerance = float(tolerance)
        k, n_tab = self.base.k, self.base.N
        m = np.arange(-k, k + 1)
        f = np.arange(n_tab + 1) / n_tab
        s0 = m[None, :] - f[:, None]
        self.d2rows = (_gauss_derivatives(s0 + 1.0, self.sigma_bins)[1]
                       - _gauss_derivatives(s0, self.sigma_bins)[1])
        step = min(1.0, self.sigma_bins) / 64.0
        reach = int((8 * self.sigma_bins + 2) / step)
        s = np.arange(-reach, reach + 1) * step
        third = _gauss_derivatives(s + 1.0, self.sigma_bins)[2] - _gauss_derivatives(s, self.sigma_bins)[2]
        self.b3 = float(np.abs(third).max() / self.base.rows.max())

    def echoes(self, pulse_local, u, energy_j, n_pulses, n_bins, detection):
        """(Echoes, the number of pulses on the centroid route, the largest ε among them): the echoes of each
        pulse's waveform over the gate's ``n_bins`` bins, as :meth:`.waveform.PulseTable.echoes` (same inputs)."""
        return self._echoes(pulse_local, np.asarray(u, np.float64), 0.0, 1.0, energy_j, n_pulses, n_bins,
                            detection)

    def echoes_from_ranges(self, pulse_local, range_m, gate, energy_j, n_pulses, detection):
        """:meth:`echoes` of returns at ranges ``range_m``: u = (2R/c − t_gate)/Δ, evaluated in the kernel in the
        order of ``(round_trip_time_s(range_m) − gate_start_s) / bin_width_s`` (the same u to the bit, without
        the two whole-block arrays)."""
        return self._echoes(pulse_local, np.asarray(range_m, np.float64), float(gate.gate_start_s),
                            float(gate.bin_width_s), energy_j, n_pulses, gate.n_bins, detection, from_range=True)

    def _echoes(self, pulse_local, x, t0, dt, energy_j, n_pulses, n_bins, detection, from_range=False):
        u = x if not from_range else None
        cap = min(len(x), n_pulses) * detection.max_echoes
        pix, pos, amp = np.empty(cap, np.int64), np.empty(cap), np.empty(cap)
        idx, cnt = np.empty(cap, np.int16), np.empty(cap, np.int16)
        stats = np.zeros(2)
        t = self.base
        if u is None:
            u = np.empty(len(x))
            _positions(x, t0, dt, SPEED_OF_LIGHT_M_S, u)
        k = _centroid_echoes(np.asarray(pulse_local, np.int64), u,
                             np.asarray(energy_j, np.float64), t.rows, t.wide, self.d2rows, t.k, t.half, n_bins,
                             self.b3 / 6.0, self.tolerance, PEAK_HALF_WINDOW,
                             float(detection.threshold_j), float(detection.relative_threshold),
                             float(detection.min_dip), int(detection.max_echoes),
                             INTERPOLATION[detection.interpolation], pix, pos, amp, idx, cnt, stats)
        ech = Echoes(pixel=pix[:k].copy(), position_bins=pos[:k].copy(), amplitude=amp[:k].copy(),
                     echo_index=idx[:k].copy(), n_echoes=cnt[:k].copy())
        return ech, int(stats[0]), float(stats[1])


@kernel
def _centroid_echoes(pulse, u, energy, rows, wide, d2rows, k, half, n_bins, b3_6, tolerance, hw, threshold_j,
                     relative_threshold, min_dip, max_echoes, mode, out_pix, out_pos, out_amp, out_idx, out_n, stats):
    """Each pulse's echoes: on the centroid route (module docstring) from E [F + ½ V F''] at ū over the bins
    ū's bin ± ``hw``, else from the sub-ray sum exactly as :func:`.waveform._table_echoes` builds it (the same
    terms in the same order).  ``stats``: [pulses on the centroid route, the largest ε among them]."""
    n_tab = rows.shape[0] - 1
    wcol = wide.shape[1]
    hw = min(hw, k)  # (a pulse narrower than the window: its whole row)
    buf = np.zeros(n_bins + wcol)
    cand = np.empty(max(n_bins, 2 * hw + 1), np.int64)
    win = np.empty(2 * hw + 1)
    n_out = 0
    a = 0
    n = u.shape[0]
    while a < n:
        b = a
        while b < n and pulse[b] == pulse[a]:
            b += 1
        e_sum, eu_sum, finite, n_valid = 0.0, 0.0, True, 0
        u0 = u[a]  # (a reference near the returns: the sums of small differences)
        for r in range(a, b):
            if energy[r] > 0 and u[r] + half >= 0 and u[r] - half < n_bins:
                n_valid += 1
                e_sum += energy[r]
                eu_sum += energy[r] * (u[r] - u0)
                if not energy[r] < math.inf:
                    finite = False
        if n_valid == 0:
            a = b
            continue
        done = False
        if finite and e_sum < math.inf:
            ubar = u0 + eu_sum / e_sum
            jb = math.floor(ubar)
            if jb - k >= 0 and jb + k < n_bins:
                v2, m3 = 0.0, 0.0
                for r in range(a, b):
                    if energy[r] > 0 and u[r] + half >= 0 and u[r] - half < n_bins:
                        d = u[r] - ubar
                        v2 += energy[r] * d * d
                        ad = abs(d)
                        m3 += energy[r] * ad * ad * ad
                v2 /= e_sum
                eps = m3 / e_sum * b3_6
                if eps <= tolerance:
                    x = (ubar - jb) * n_tab  # (the table's interpolation in the position inside the bin)
                    i = min(int(x), n_tab - 1)
                    w = x - i
                    c0, c1 = e_sum * (1.0 - w), e_sum * w
                    h0, h1 = 0.5 * v2 * c0, 0.5 * v2 * c1
                    for q in range(2 * hw + 1):
                        col = k - hw + q
                        win[q] = rows[i, col] * c0 + rows[i + 1, col] * c1 + d2rows[i, col] * h0 \
                            + d2rows[i + 1, col] * h1
                    top = 0
                    for q in range(1, 2 * hw + 1):
                        if win[q] > win[top]:
                            top = q
                    if 0 < top < 2 * hw:
                        n_out = detect_row(win, 0, 2 * hw + 1, int(jb) - hw, threshold_j, relative_threshold,
                                           min_dip, max_echoes, mode, cand, out_pix, pulse[a], out_pos, out_amp,
                                           out_idx, out_n, n_out)
                    else:  # (the maximum on the window's edge: the whole row)
                        length = 2 * k + 1
                        for q in range(length):
                            buf[q] = rows[i, q] * c0 + rows[i + 1, q] * c1 + d2rows[i, q] * h0 + d2rows[i + 1, q] * h1
                        n_out = detect_row(buf, 0, length, int(jb) - k, threshold_j, relative_threshold, min_dip,
                                           max_echoes, mode, cand, out_pix, pulse[a], out_pos, out_amp, out_idx,
                                           out_n, n_out)
                    stats[0] += 1
                    stats[1] = max(stats[1], eps)
                    done = True
        if not done:  # the reference: every sub-ray's return added (waveform._table_echoes' sums)
            n_out = window_echoes(buf, cand, a, b, pulse, u, energy, rows, wide, k, half, n_bins, threshold_j,
                                  relative_threshold, min_dip, max_echoes, mode, out_pix, out_pos, out_amp, out_idx,
                                  out_n, n_out)
        a = b
    return n_out


@kernel
def _positions(range_m, gate_start_s, bin_width_s, c, out):
    """Each return's position in gate bins, ``(2 R / c − gate_start_s) / bin_width_s``, rounded as NumPy rounds
    ``(round_trip_time_s(R) − gate_start_s) / bin_width_s`` (the same operations in the same order, no fused
    multiply-add: the kernels are compiled without fastmath)."""
    for i in range(range_m.shape[0]):
        out[i] = (2.0 * range_m[i] / c - gate_start_s) / bin_width_s
