"""Weather returns as waveforms: the volume backscatter of core/atmosphere/weather.py (W1) convolved with the pulse
and binned (flash, scanner, profiler), or gated by the slice response (gated viewing); docs/theory.md §14.

The range is cut into slabs of min(bin width, pulse FWHM)/4 (gated: min(FWHM, gate width, delay step)/4) in
round-trip time; each slab's energy is W1 integrated by 8-point Gauss–Legendre (:func:`~core.atmosphere.weather.
slab_integrals`) and placed at its energy centroid, then binned with the pulse exactly as a surface return.
"""
from __future__ import annotations

import math

import numpy as np

import functools

from ..atmosphere.extinction import two_way_transmission
from ..atmosphere.weather import GL_W, GL_X, Overlap, overlap_tilt, pixel_overlap, slab_integrals
from ..constants import SPEED_OF_LIGHT_M_S
from .laser import pulse_half_support_s
from .waveform import accumulate_waveforms, round_trip_time_s


def _with_breaks(edges, breaks_m):
    """The slab edges with the profile's break points (where β(R) jumps) inside them added."""
    if breaks_m is None or len(edges) < 2:
        return edges
    b = np.asarray(breaks_m, np.float64)
    b = b[(b > edges[0]) & (b < edges[-1])]
    return np.union1d(edges, b) if len(b) else edges


def _beta(beta_per_m_sr, profile):
    """w(R) = β + profile(R) for :func:`slab_integrals`: None for a constant β (multiplied afterwards)."""
    if profile is None:
        return None
    return lambda r: beta_per_m_sr + profile(r)


def slab_edges_m(laser, gate, min_range_m, slabs_per_width: int = 4):
    """Range edges of the slabs that can reach the gate (pulse support included), from ``min_range_m``."""
    c2 = 0.5 * SPEED_OF_LIGHT_M_S
    half = pulse_half_support_s(laser)
    t_lo = max(min_range_m / c2, gate.gate_start_s - half)
    t_hi = gate.gate_start_s + gate.n_bins * gate.bin_width_s + half
    if t_hi <= t_lo:
        return np.zeros(0)
    width = min(gate.bin_width_s, laser.pulse_fwhm_s) / slabs_per_width
    n = max(1, int(math.ceil((t_hi - t_lo) / width)))
    return c2 * np.linspace(t_lo, t_hi, n + 1)


def backscatter_template(laser, gate, energy_scale_jm2, beta_per_m_sr, alpha_per_m, overlap: Overlap,
                         min_range_m, slabs_per_width: int = 4, profile=None, breaks_m=None):
    """The volume-backscatter waveform (n_bins,) in J per bin for a beam of energy fraction F = 1 (W1),
    ``energy_scale_jm2`` = E_T η_sys π r_a² (core.physics.radiometry.energy_scale).  ``profile(R)``: backscatter
    (1/(m sr)) added to β at each range (the undrawn rain drops: core.atmosphere.weather.DropCut), with its jumps
    at ``breaks_m`` (slab edges are put there)."""
    edges = slab_edges_m(laser, gate, min_range_m, slabs_per_width)
    if len(edges) < 2 or (beta_per_m_sr <= 0.0 and profile is None):
        return np.zeros(gate.n_bins)
    edges = _with_breaks(edges, breaks_m)
    w = _beta(beta_per_m_sr, profile)
    integral, centroid = slab_integrals(edges, alpha_per_m, overlap, w)
    e = energy_scale_jm2 * (beta_per_m_sr if w is None else 1.0) * integral
    keep = e > 0
    return accumulate_waveforms(np.zeros(int(keep.sum()), np.int64), round_trip_time_s(centroid[keep]), e[keep], 1,
                                laser, gate)[0]


def pixel_backscatter_templates(laser, gate, energy_scale_jm2, beta_per_m_sr, alpha_per_m, overlap: Overlap,
                                min_range_m, tan_x, tan_y, slabs_per_width: int = 4, profile=None, breaks_m=None):
    """:func:`backscatter_template` of flash pixels whose axes are (tan_x[k], tan_y[k]) (K,): (K, n_bins), each
    with its own overlap :func:`~core.atmosphere.weather.pixel_overlap` = O(R) × T (the same slabs and the same
    arithmetic: the pixel at t = 0, T = 1, gets the on-axis template bit for bit)."""
    tx, ty = np.atleast_1d(np.asarray(tan_x, np.float64)), np.atleast_1d(np.asarray(tan_y, np.float64))
    out = np.zeros((len(tx), gate.n_bins))
    edges = slab_edges_m(laser, gate, min_range_m, slabs_per_width)
    if len(edges) < 2 or (beta_per_m_sr <= 0.0 and profile is None):
        return out
    edges = _with_breaks(edges, breaks_m)
    w = _beta(beta_per_m_sr, profile)
    lo, hi = edges[:-1], edges[1:]  # slab_integrals, for K overlaps at once
    half, mid = 0.5 * (hi - lo), 0.5 * (hi + lo)
    r = mid[:, None] + half[:, None] * GL_X[None, :]
    o = overlap(r)
    att = two_way_transmission(alpha_per_m, r)
    rr = r * r
    wr = None if w is None else w(r)
    per = max(1, 4_000_000 // r.size)
    for k0 in range(0, len(tx), per):
        kk = slice(k0, min(len(tx), k0 + per))
        g = (o[None] * overlap_tilt(overlap, r[None], tx[kk, None, None], ty[kk, None, None])) * att / rr
        if wr is not None:
            g = g * wr
        wg = g * GL_W
        integral = half * wg.sum(axis=-1)
        s = wg.sum(axis=-1)
        centroid = np.where(s > 0, (wg * r).sum(axis=-1) / np.where(s > 0, s, 1.0), mid)
        e = energy_scale_jm2 * (beta_per_m_sr if w is None else 1.0) * integral
        keep = e > 0
        node, _ = np.nonzero(keep)
        out[kk] = accumulate_waveforms(node, round_trip_time_s(centroid[keep]), e[keep], len(g), laser, gate)
    return out


def gated_slab_table(laser, delays_s, gate_width_s, edge_s, energy_scale_jm2, beta_per_m_sr, alpha_per_m,
                     overlap: Overlap, min_range_m, response, slabs_per_width: int = 4, profile=None,
                     breaks_m=None):
    """Gated viewing: (slab round-trip times (M,), C (M + 1, n_slices)) with C[m] = Σ_{m' < m} e_m' g(t_m' − d_k),
    the volume backscatter of the slabs nearer than slab m in every slice (``response`` = g(τ), the slice
    response of core.systems.gated).  A pixel sees C[m_hit] for a sub-ray whose surface is at slab m_hit, C[M]
    for a sub-ray that hits nothing (prefix sums: the volume behind a surface is hidden)."""
    c2 = 0.5 * SPEED_OF_LIGHT_M_S
    d = np.asarray(delays_s, np.float64)
    support = pulse_half_support_s(laser) + 0.5 * edge_s
    t_lo = max(min_range_m / c2, float(d.min()) - support)
    t_hi = float(d.max()) + gate_width_s + support
    if t_hi <= t_lo or (beta_per_m_sr <= 0.0 and profile is None):
        return np.zeros(0), np.zeros((1, len(d)))
    step = float(np.min(np.diff(d))) if len(d) > 1 else gate_width_s
    width = min(laser.pulse_fwhm_s, gate_width_s, step if step > 0 else gate_width_s) / slabs_per_width
    n = max(1, int(math.ceil((t_hi - t_lo) / width)))
    edges = _with_breaks(c2 * np.linspace(t_lo, t_hi, n + 1), breaks_m)
    w = _beta(beta_per_m_sr, profile)
    integral, centroid = slab_integrals(edges, alpha_per_m, overlap, w)
    e = energy_scale_jm2 * (beta_per_m_sr if w is None else 1.0) * integral
    t = 2.0 * centroid / SPEED_OF_LIGHT_M_S
    table = np.zeros((len(e) + 1, len(d)))
    table[1:] = np.cumsum(e[:, None] * response(t[:, None] - d[None, :]), axis=0)
    return t, table


def pixel_gated_slab_tables(laser, delays_s, gate_width_s, edge_s, energy_scale_jm2, beta_per_m_sr, alpha_per_m,
                            overlap: Overlap, min_range_m, response, tan_x, tan_y, slabs_per_width: int = 4,
                            profile=None, breaks_m=None):
    """:func:`gated_slab_table` (its C only, flattened: (K, (M + 1)·n_slices)) of pixels whose axes are
    (tan_x[k], tan_y[k]), each with its own overlap :func:`~core.atmosphere.weather.pixel_overlap` (t = 0: the
    on-axis table exactly)."""
    tx, ty = np.atleast_1d(np.asarray(tan_x, np.float64)), np.atleast_1d(np.asarray(tan_y, np.float64))
    rows = []
    for k in range(len(tx)):
        ov = functools.partial(pixel_overlap, overlap, tan_x=tx[k], tan_y=ty[k])
        rows.append(gated_slab_table(laser, delays_s, gate_width_s, edge_s, energy_scale_jm2, beta_per_m_sr,
                                     alpha_per_m, ov, min_range_m, response, slabs_per_width, profile,
                                     breaks_m)[1].ravel())
    return np.stack(rows)
