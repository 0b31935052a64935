"""Sub-resolution sampling of the receiver pixels: where each sub-ray goes and what it stands for.

Patterns (``receiver.subray_pattern``, :class:`SubraySampler`): the paper's regular S×S grid, jittered
(stratified), Sobol nets and adaptive refinement of the pixels whose rays disagree; each ray carries a share of
the beam energy such that a pixel's rays carry exactly the erf integral of the beam over the pixel.

A sub-ray stands for a cell of its pixel in the tan plane (core/geometry/rays.py).  Besides its direction and its share
of the beam energy the cell has an extent: the surface it hits spans a range interval across the cell.  This
module computes that interval to first order (the time spread that core/physics/waveform.py convolves with the pulse).

Range over a plane, tan-plane direction p = (x, y, −1), unit normal n (sensor frame), R₀ at p₀:

    R(p) = D |p| / (n·p)        ⇒   ∂R/∂x = R [x/|p|² − n_x/(n·p)],   ∂R/∂y = R [y/|p|² − n_y/(n·p)]

so a cell of tan-plane size δx × δy spans round-trip times uniform over U(a) ⊛ U(b) with
a = (2/c)|∂R/∂x| δx, b = (2/c)|∂R/∂y| δy (exact for a cell small enough that R is linear across it).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, fields

import math

import numpy as np

from ..constants import SPEED_OF_LIGHT_M_S
from ..jit import kernel
from .laser import beam_half_angle_tan



@kernel
def range_gradient_at(x, y, r, n0, n1, n2):
    """(∂R/∂x, ∂R/∂y) of one sub-ray (module docstring): the scalar form of :func:`range_gradient_tan`."""
    p2 = x * x + y * y + 1.0
    n_dot_p = n0 * x + n1 * y - n2
    inv = 1.0 / n_dot_p if n_dot_p != 0.0 else np.inf
    return r * (x / p2 - n0 * inv), r * (y / p2 - n1 * inv)


#: 2/c: round-trip seconds per metre of range.
_ROUND_TRIP_S_PER_M = 2.0 / SPEED_OF_LIGHT_M_S
_HALF_C = 0.5 * SPEED_OF_LIGHT_M_S


@kernel
def cell_box_at(x, y, r, n0, n1, n2, cell_x, cell_y, off_x, off_y, max_spread_s):
    """(a, b, shift) of one sub-ray cell: the scalar form of :func:`cell_time_box_s`."""
    gx, gy = range_gradient_at(x, y, r, n0, n1, n2)
    a = _ROUND_TRIP_S_PER_M * abs(gx) * cell_x
    b = _ROUND_TRIP_S_PER_M * abs(gy) * cell_y
    bad = not (np.isfinite(a) and np.isfinite(b))
    if bad:
        a, b = max_spread_s, max_spread_s
    a, b = min(a, max_spread_s), min(b, max_spread_s)
    shift = _ROUND_TRIP_S_PER_M * (gx * off_x + gy * off_y)
    if bad or not np.isfinite(shift):
        shift = 0.0
    half = 0.5 * (a + b)
    return a, b, min(max(shift, -half), half)


@kernel
def _range_gradient_array(x, y, r, n, gx, gy):
    for i in range(x.shape[0]):
        gx[i], gy[i] = range_gradient_at(x[i], y[i], r[i], n[i, 0], n[i, 1], n[i, 2])


@kernel
def _cell_box_array(x, y, r, n, cell_x, cell_y, off_x, off_y, max_spread_s, out, shift):
    for i in range(x.shape[0]):
        out[i, 0], out[i, 1], shift[i] = cell_box_at(x[i], y[i], r[i], n[i, 0], n[i, 1], n[i, 2], cell_x[i],
                                                      cell_y[i], off_x[i], off_y[i], max_spread_s)


def _float_columns(n_rows, *values):
    return [np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=np.float64), (n_rows,))) for v in values]


def range_gradient_tan(x_tan, y_tan, range_m, normal_sensor):
    """(∂R/∂x, ∂R/∂y) in metres per tan-plane unit at sub-rays hitting planes of unit normal ``normal_sensor``
    (n, 3) (sensor frame, either orientation)."""
    n = np.ascontiguousarray(np.asarray(normal_sensor, dtype=np.float64).reshape(-1, 3))
    x, y, r = _float_columns(len(n), x_tan, y_tan, range_m)
    gx, gy = np.empty(len(n)), np.empty(len(n))
    _range_gradient_array(x, y, r, n, gx, gy)
    return gx, gy


def cell_time_spread_s(x_tan, y_tan, range_m, normal_sensor, cell_x_tan, cell_y_tan, max_spread_s=np.inf):
    """Full widths (n, 2) in seconds of the two boxes of round-trip times a sub-ray cell spans (module doc).

    Widths are capped at ``max_spread_s`` (the pipeline passes 1000 gate lengths: a cell that spans more than
    that is spread over far more than the gate either way) and are finite."""
    return cell_time_box_s(x_tan, y_tan, range_m, normal_sensor, cell_x_tan, cell_y_tan, 0.0, 0.0, max_spread_s)[0]


def cell_time_box_s(x_tan, y_tan, range_m, normal_sensor, cell_x_tan, cell_y_tan, offset_x_tan, offset_y_tan,
                    max_spread_s=np.inf):
    """The cell's box of round-trip times for sub-rays that sample their cell off its centre (jittered
    patterns): (widths (n, 2) as :func:`cell_time_spread_s`, shift (n,) s of the box centre from the sample's
    round-trip time), the centre being the cell centre's range on the sample's plane,
    (2/c)(∂R/∂x·δx + ∂R/∂y·δy) with (δx, δy) = cell centre − sample.  Centred boxes of the cells of a pixel tile
    its range extent whatever the sample positions."""
    n = np.ascontiguousarray(np.asarray(normal_sensor, dtype=np.float64).reshape(-1, 3))
    cols = _float_columns(len(n), x_tan, y_tan, range_m)
    cells = _float_columns(len(n), cell_x_tan, cell_y_tan, offset_x_tan, offset_y_tan)
    out, shift = np.empty((len(n), 2)), np.empty(len(n))
    _cell_box_array(*cols, n, *cells, float(max_spread_s), out, shift)
    return out, shift


# ----------------------------------------------------------------------------------------------------------------
# Sub-ray patterns
# ----------------------------------------------------------------------------------------------------------------
#: ``receiver.subray_pattern`` choices.
SUBRAY_PATTERNS = ("grid", "stratified", "sobol", "adaptive")
#: Patterns of the adaptive pattern's first pass and of its refined pixels.
ADAPTIVE_BASE, ADAPTIVE_FINE = "sobol", "sobol"


@kernel
def _grid_samples(pixels, s, width, height, half_w, half_h, fx, fy, x_tan, y_tan, pixel, cx, cy, weight):
    """The grid pattern's rays of ``pixels`` (pixel-major, each pixel's S×S cells row by row): the cell centres in
    the arithmetic of :func:`core.geometry.rays.block_subray_tan` and the cells' exact erf energies fy·fx — the
    values NumPy gave element by element, bit for bit."""
    n = s * s
    kx = 2 * half_w / (width * s)
    ky = 2 * half_h / (height * s)
    for p in range(pixels.shape[0]):
        q = pixels[p]
        ix, iy = q % width, q // width
        for k in range(n):
            i = p * n + k
            gx, gy = k % s, k // s
            x, y = ix * s + gx, iy * s + gy
            pixel[i], cx[i], cy[i] = q, x, y
            x_tan[i] = -half_w + (x + 0.5) * kx
            y_tan[i] = half_h - (y + 0.5) * ky
            weight[i] = fy[y] * fx[x]


@dataclass
class Samples:
    """Sub-rays of a run of whole pixels, pixel-major (rays of a pixel are contiguous, pixels increasing).

    x_tan, y_tan      tan-plane direction of each ray
    pixel             global pixel index (row-major)
    sub_x, sub_y      the base S×S cell holding the ray (global cell column/row: scintillation look-up)
    weight            the share of the pulse energy the ray carries; a pixel's weights sum to the exact (erf)
                      beam energy inside the pixel
    cell_x_tan/_y_tan the tan-plane size of the cell the ray stands for (cell range spread)
    offset_x/y_tan    the cell's centre minus the ray (0 on the grid)
    """

    x_tan: np.ndarray
    y_tan: np.ndarray
    pixel: np.ndarray
    sub_x: np.ndarray
    sub_y: np.ndarray
    weight: np.ndarray
    cell_x_tan: np.ndarray
    cell_y_tan: np.ndarray
    offset_x_tan: np.ndarray
    offset_y_tan: np.ndarray

    def __len__(self):
        return len(self.x_tan)

    def take(self, index) -> "Samples":
        return Samples(*(getattr(self, f.name)[index] for f in fields(self)))

    @staticmethod
    def concat(parts) -> "Samples":
        return Samples(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Samples)))


_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


def hash_uniform(counter, key: int):
    """Uniform numbers in [0, 1) that depend only on (counter, key): the SplitMix64 finaliser (Steele, Lea &
    Flood 2014) of counter·φ + key, top 53 bits.  Counter-based, so a ray's jitter does not depend on which
    block, thread or chunk draws it."""
    with np.errstate(over="ignore"):
        z = np.asarray(counter, dtype=np.uint64) * _GOLDEN + np.uint64(key & 0xFFFFFFFFFFFFFFFF)
        z = (z ^ (z >> np.uint64(30))) * _MIX1
        z = (z ^ (z >> np.uint64(27))) * _MIX2
        z ^= z >> np.uint64(31)
    return (z >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


class SubraySampler:
    """Where the sub-rays of each pixel go and what they carry, for one frame (fixed for all frames of a run:
    a static scene keeps stable noise-free intensities frame to frame).

    ``grid``        S×S cell centres (the paper's quadratic grid); weight = the exact erf energy of the cell.
    ``stratified``  one uniformly jittered point per cell (counter-based random numbers from the run seed);
                    weight = the exact erf energy of its cell.
    ``sobol``       a scrambled 2-D Sobol net of S² points (seeded from the run seed), digitally shifted per
                    pixel: for S a power of two it is a (0, 2m, 2)-net with exactly one point in each of the S×S
                    cells (stratified, and jointly well spread) and each ray carries its cell's exact erf
                    energy; otherwise weights ∝ the beam intensity at each point, normalised to the pixel's
                    exact erf energy.
    ``adaptive``    a first pass with the ``sobol`` pattern; pixels whose samples disagree (:meth:`disagreeing`)
                    are traced again with (refine·S)² Sobol rays that replace the first pass.

    Jittered rays stand for their whole cell: with the cell range spread, a ray's box of round-trip times is
    centred on its cell's centre (:func:`cell_time_box_s`), so the cells of a pixel tile its range extent.
    """

    def __init__(self, det, pattern: str, fractions, seed: int = 0, *, laser=None, beam_offset_tan=(0.0, 0.0),
                 beam_width_scale: float = 1.0, refine: int = 4, fine_fractions=None):
        if pattern not in SUBRAY_PATTERNS:
            raise ValueError(f"unknown sub-ray pattern {pattern!r}")
        self.det = det
        self.pattern = pattern
        self.fx, self.fy = fractions
        self.refine = int(refine)
        self.fine_fractions = fine_fractions
        self.key = int(np.random.SeedSequence([int(seed), 0x5AB]).generate_state(2, np.uint64)[0])
        self.seed = int(seed)
        self._beam = None
        self._nets = {}
        if laser is not None and laser.beam_profile == "gaussian":
            self._beam = (float(beam_offset_tan[0]), float(beam_offset_tan[1]),
                          beam_half_angle_tan(laser, det) * beam_width_scale)
        s = det.subsamples
        self.pixel_fraction_x = self.fx.reshape(det.width_px, s).sum(axis=1)
        self.pixel_fraction_y = self.fy.reshape(det.height_px, s).sum(axis=1)

    @property
    def adaptive(self) -> bool:
        return self.pattern == "adaptive"

    # -- patterns -------------------------------------------------------------------------------------------
    def block(self, pixel_start: int, pixel_stop: int) -> Samples:
        """First-pass samples of the pixels [pixel_start, pixel_stop)."""
        pixels = np.arange(pixel_start, pixel_stop)
        base = {"adaptive": ADAPTIVE_BASE}.get(self.pattern, self.pattern)
        return self._samples(pixels, self.det.subsamples, base, self.fx, self.fy, level=0)

    def refined(self, pixels) -> Samples:
        """Second-pass samples of the given pixels: (refine·S)² stratified rays each."""
        fx, fy = self.fine_fractions
        return self._samples(np.asarray(pixels, dtype=np.int64), self.det.subsamples * self.refine, ADAPTIVE_FINE,
                             fx, fy, level=1)

    def _samples(self, pixels, s, pattern, fx, fy, level) -> Samples:
        det = self.det
        n = s * s
        if pattern == "grid":  # (the default: one compiled pass, no NumPy temporaries)
            m = len(pixels) * n
            x_tan, y_tan, pixel = np.empty(m), np.empty(m), np.empty(m, np.int64)
            cx, cy, weight = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m)
            _grid_samples(np.ascontiguousarray(pixels, dtype=np.int64), s, det.width_px, det.height_px,
                          det.half_width_tan, det.half_height_tan, fx, fy, x_tan, y_tan, pixel, cx, cy, weight)
            ratio = s // det.subsamples
            zeros = np.zeros(m)
            return Samples(x_tan, y_tan, pixel, cx // ratio if ratio > 1 else cx, cy // ratio if ratio > 1 else cy,
                           weight, np.full(m, det.pixel_pitch_tan[0] / s), np.full(m, det.pixel_pitch_tan[1] / s),
                           zeros, zeros)
        ix, iy = pixels % det.width_px, pixels // det.width_px
        pitch_x, pitch_y = det.pixel_pitch_tan
        cell_x, cell_y = pitch_x / s, pitch_y / s
        pixel = np.repeat(pixels, n)
        if pattern == "sobol":
            u, v = self._sobol(pixels, n, level)
            gx = np.minimum((u * s).astype(np.int64), s - 1)  # the cell holding each point
            gy = np.minimum((v * s).astype(np.int64), s - 1)
        else:
            sx, sy = np.meshgrid(np.arange(s), np.arange(s), indexing="xy")
            gx = np.tile(sx.reshape(-1), len(pixels))
            gy = np.tile(sy.reshape(-1), len(pixels))
            if pattern == "stratified":
                # one jittered point per cell, counters unique per (level, pixel, cell, axis)
                counter = ((np.uint64(level) << np.uint64(56)) + pixel.astype(np.uint64) * np.uint64(n)
                           + (gy * s + gx).astype(np.uint64)) * np.uint64(2)
                u = (gx + hash_uniform(counter, self.key)) / s
                v = (gy + hash_uniform(counter + np.uint64(1), self.key)) / s
        cx = np.repeat(ix, n) * s + gx  # global cell index at this level
        cy = np.repeat(iy, n) * s + gy
        if pattern == "grid":  # cell centres, in the same arithmetic as core.geometry.rays.block_subray_tan
            x_tan = -det.half_width_tan + (cx + 0.5) * (2 * det.half_width_tan / (det.width_px * s))
            y_tan = det.half_height_tan - (cy + 0.5) * (2 * det.half_height_tan / (det.height_px * s))
        else:  # u runs left → right inside the pixel, v top → bottom (the row order of the detector)
            x_tan = -det.half_width_tan + (np.repeat(ix, n) + u) * pitch_x
            y_tan = det.half_height_tan - (np.repeat(iy, n) + v) * pitch_y
        if pattern == "sobol" and s & (s - 1):
            # S not a power of two: a cell may hold 0 or 2 points; weights ∝ the beam at each point instead
            weight = self._intensity_weights(x_tan, y_tan, np.repeat(ix, n), np.repeat(iy, n), n)
        else:  # one ray per cell (a (0, m, 2)-net has one point in each of the S×S cells): its exact erf energy
            weight = fy[cy] * fx[cx]
        ratio = s // det.subsamples  # cell indices on the base S×S grid
        if pattern == "grid" or (pattern == "sobol" and s & (s - 1)):  # at the centre / not one ray per cell
            off_x = off_y = np.zeros(len(pixel))
        else:
            off_x = -det.half_width_tan + (cx + 0.5) * cell_x - x_tan
            off_y = det.half_height_tan - (cy + 0.5) * cell_y - y_tan
        return Samples(x_tan, y_tan, pixel, cx // ratio, cy // ratio, weight, np.full(len(pixel), cell_x),
                       np.full(len(pixel), cell_y), off_x, off_y)

    def _sobol(self, pixels, n, level):
        """A scrambled 2-D Sobol net of n points (seeded from the run seed), digitally shifted per pixel: the
        30-bit coordinates XOR a per-pixel random 30-bit word (counter-based: independent of blocks).  A digital
        shift keeps the net's stratification (each pixel still holds a (t, m, 2)-net when n is a power of two)
        while the pixels see independent point sets."""
        net = self._nets.get((n, level))
        if net is None:
            from scipy.stats import qmc

            rng = np.random.default_rng([self.seed, 0x50B01, level])
            try:
                engine = qmc.Sobol(2, scramble=True, bits=30, rng=rng)
            except TypeError:  # scipy < 1.15
                engine = qmc.Sobol(2, scramble=True, bits=30, seed=rng)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # balance warning when n is not a power of two
                net = np.round(engine.random(n) * 2.0 ** 30).astype(np.uint64)
            self._nets[(n, level)] = net
        counter = (np.uint64(level) << np.uint64(56)) + np.asarray(pixels, dtype=np.uint64) * np.uint64(2)
        mask = np.uint64(2 ** 30 - 1)
        shift_x = (hash_uniform(counter, self.key ^ 0x50B) * 2.0 ** 30).astype(np.uint64) & mask
        shift_y = (hash_uniform(counter + np.uint64(1), self.key ^ 0x50B) * 2.0 ** 30).astype(np.uint64) & mask
        u = (net[None, :, 0] ^ shift_x[:, None]).reshape(-1).astype(np.float64) * 2.0 ** -30
        v = (net[None, :, 1] ^ shift_y[:, None]).reshape(-1).astype(np.float64) * 2.0 ** -30
        return u, v

    def _intensity_weights(self, x_tan, y_tan, ix, iy, n):
        """Weights ∝ the beam intensity at each point, summing to the pixel's exact erf energy."""
        total = self.pixel_fraction_y[iy] * self.pixel_fraction_x[ix]
        if self._beam is None:
            return total / n
        x0, y0, w = self._beam
        log_p = (-2.0 * ((x_tan - x0) ** 2 + (y_tan - y0) ** 2) / (w * w)).reshape(-1, n)
        p = np.exp(log_p - log_p.max(axis=1, keepdims=True))
        return (p / p.sum(axis=1, keepdims=True)).reshape(-1) * total

    def weights_of(self, smp: Samples) -> np.ndarray:
        """The weights this sampler's cell fractions (and beam) give the first-pass rays ``smp`` of its pattern,
        drawn by any sampler of the same detector, pattern and seed: the gated system draws its rays once and
        weighs them per slice, each slice with its own beam (wander, broadening)."""
        s = self.det.subsamples
        if self.pattern == "sobol" and s & (s - 1):
            return self._intensity_weights(smp.x_tan, smp.y_tan, smp.pixel % self.det.width_px,
                                           smp.pixel // self.det.width_px, s * s)
        return self.fy[smp.sub_y] * self.fx[smp.sub_x]

    # -- adaptive refinement --------------------------------------------------------------------------------
    def disagreeing(self, smp: Samples, prim, range_m, normal_sensor, material_ids, tolerance_m: float):
        """Pixels (global indices) whose sub-rays disagree: some hit and some miss (a silhouette), they hit
        different materials, or their ranges leave the plane through the pixel's first hit by more than
        ``tolerance_m`` (a range step: several surfaces, or a fold)."""
        n = self.det.subsamples ** 2
        hit = (prim >= 0).reshape(-1, n)
        mixed = hit.any(axis=1) & ~hit.all(axis=1)
        mat = np.where(prim >= 0, material_ids[np.maximum(prim, 0)], -1).reshape(-1, n)
        several = (mat != np.max(mat, axis=1, keepdims=True)).any(axis=1) & hit.all(axis=1)
        # plane prediction from the first hit of each pixel (first in ray order)
        first = np.argmax(hit, axis=1)
        rows = np.arange(hit.shape[0])
        ref = rows * n + first
        ok = hit[rows, first]
        r = np.where(prim >= 0, range_m, np.nan).reshape(-1, n)
        x, y = smp.x_tan.reshape(-1, n), smp.y_tan.reshape(-1, n)
        step = np.zeros(hit.shape[0], bool)
        if ok.any():
            gx, gy = range_gradient_tan(smp.x_tan[ref[ok]], smp.y_tan[ref[ok]], range_m[ref[ok]],
                                        normal_sensor[ref[ok]])
            pred = (range_m[ref[ok], None] + gx[:, None] * (x[ok] - smp.x_tan[ref[ok], None])
                    + gy[:, None] * (y[ok] - smp.y_tan[ref[ok], None]))
            with np.errstate(invalid="ignore"):
                dev = np.abs(r[ok] - pred)
            step[ok] = np.nanmax(np.where(np.isfinite(dev), dev, 0.0), axis=1) > tolerance_m
        bad = mixed | several | step
        return smp.pixel.reshape(-1, n)[bad, 0]

    def refine_pass(self, smp: Samples, hits, trace, normals, material_ids, tolerance_m: float):
        """Adaptive second pass: find the disagreeing pixels of a first pass (``hits`` = (prim, range_m,
        cos_theta) of ``smp``), trace their refined rays with ``trace(x_tan, y_tan)`` and put them in place of the
        first-pass rays of those pixels (pixel-major order kept).  ``normals(prim)`` gives sensor-frame unit
        normals.  Returns (samples, hits, refined pixel indices)."""
        prim, range_m, cos_theta = hits
        bad = self.disagreeing(smp, prim, range_m, normals(prim), material_ids, tolerance_m)
        if len(bad) == 0:
            return smp, hits, bad
        fine = self.refined(bad)
        fine_hits = trace(fine.x_tan, fine.y_tan)
        keep = ~np.isin(smp.pixel, bad)
        merged = Samples.concat([smp.take(keep), fine])
        order = np.argsort(merged.pixel, kind="stable")
        hits = tuple(np.concatenate([h[keep], f])[order] for h, f in zip(hits, fine_hits))
        return merged.take(order), hits, bad


def adaptive_tolerance_m(laser, gate) -> float:
    """Range step that makes a pixel's rays disagree: a quarter of the range resolution, (c/2)·max(τ, Δ)/4."""
    return 0.25 * 0.5 * SPEED_OF_LIGHT_M_S * max(laser.pulse_fwhm_s, gate.bin_width_s)


def cell_returns(smp: Samples, index, range_m, cos_theta, prim, unit_normal, rot, max_spread_s=np.inf):
    """The cell model of the hits ``smp[index]`` for the radiometry and the waveform: (spread (n, 2) s, range_m
    and cos θ at the cell centre on the hit plane) of the n hits; ``range_m``, ``cos_theta``, ``prim`` (hit
    triangle) are the block's (all of ``smp``), ``unit_normal`` (triangles, 3) the world-frame unit normals of the
    triangles and ``rot`` the sensor-to-world rotation: a hit's sensor-frame normal is unit_normal[prim] @ rot.

    A ray off its cell's centre (jittered patterns) stands for the whole cell: the cell's return is evaluated
    where the cell centre's ray meets the plane the ray hit, R_c = R + ∂R/∂x·δx + ∂R/∂y·δy and
    cos θ_c = |n·p_c|/|p_c|; its round-trip times span the centred box (:func:`cell_time_box_s`).  Rays at their
    cell centre (the grid) keep their own range and cos θ bit for bit.  One compiled pass over the hits (the
    normals looked up and turned into the sensor frame on the way)."""
    index = np.ascontiguousarray(index, dtype=np.int64)
    k = len(index)
    spread, range_c, cos_c = np.empty((k, 2)), np.empty(k), np.empty(k)
    _cell_returns(index, smp.x_tan, smp.y_tan, np.asarray(range_m, np.float64), np.asarray(cos_theta, np.float64),
                  np.asarray(prim), np.asarray(unit_normal, np.float64), np.ascontiguousarray(rot, np.float64),
                  smp.cell_x_tan, smp.cell_y_tan, smp.offset_x_tan, smp.offset_y_tan, float(max_spread_s), spread,
                  range_c, cos_c)
    return spread, range_c, cos_c


@kernel
def _cell_returns(index, x, y, range_m, cos_theta, prim, unit_normal, rot, cell_x, cell_y, off_x, off_y,
                  max_spread_s, spread, range_c, cos_c):
    for k in range(index.shape[0]):
        i = index[k]
        p = prim[i]
        w0, w1, w2 = unit_normal[p, 0], unit_normal[p, 1], unit_normal[p, 2]
        n0 = w0 * rot[0, 0] + w1 * rot[1, 0] + w2 * rot[2, 0]
        n1 = w0 * rot[0, 1] + w1 * rot[1, 1] + w2 * rot[2, 1]
        n2 = w0 * rot[0, 2] + w1 * rot[1, 2] + w2 * rot[2, 2]
        r = range_m[i]
        spread[k, 0], spread[k, 1], shift = cell_box_at(x[i], y[i], r, n0, n1, n2, cell_x[i], cell_y[i], off_x[i],
                                                        off_y[i], max_spread_s)
        if off_x[i] != 0 or off_y[i] != 0:
            range_c[k] = r + _HALF_C * shift
            xc, yc = x[i] + off_x[i], y[i] + off_y[i]
            cos_c[k] = min(abs(n0 * xc + n1 * yc - n2) / math.sqrt(xc * xc + yc * yc + 1.0), 1.0)
        else:
            range_c[k], cos_c[k] = r, cos_theta[i]
