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

import math

import numpy as np
from scipy.special import erf, ndtr

from ..config.settings import LaserSettings
from ..geometry.rays import Detector
from ..jit import intrinsic, kernel, nbtypes

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



# ----------------------------------------------------------------------------------------------------------------
# Pulse convolved with boxes: the return of a sub-ray cell whose surface spans a range interval
# ----------------------------------------------------------------------------------------------------------------
def _trapezoid_cdf(x, a, b):
    """CDF of U(a) ⊛ U(b) (a ≥ b ≥ 0 full widths) at x measured from the left end of its support [0, a + b].

    Piecewise exact: x²/(2ab), (x − b/2)/a, 1 − (a + b − x)²/(2ab) on [0, b], [b, a], [a, a + b]."""
    x, a, b = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x, a, b)))
    out = np.zeros(x.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = (x > 0) & (x <= b)
        out[rise] = x[rise] ** 2 / (2 * a[rise] * b[rise])
        mid = (x > b) & (x <= a)
        out[mid] = (x[mid] - 0.5 * b[mid]) / a[mid]
        fall = (x > a) & (x < a + b)
        out[fall] = 1.0 - (a[fall] + b[fall] - x[fall]) ** 2 / (2 * a[fall] * b[fall])
    out[x >= a + b] = 1.0
    return out


def _trapezoid_cdf_integral(x, a, b):
    """∫₀ˣ of :func:`_trapezoid_cdf` (a ≥ b ≥ 0): x³/(6ab); b²/(6a) + ((x − b/2)² − b²/4)/(2a);
    I(a) + (x − a) − (b³ − (a + b − x)³)/(6ab); (a + b)/2 + (x − a − b) on the same pieces and beyond."""
    x, a, b = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (x, a, b)))
    out = np.zeros(x.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = (x > 0) & (x <= b)
        out[rise] = x[rise] ** 3 / (6 * a[rise] * b[rise])
        mid = (x > b) & (x <= a)
        xm, am, bm = x[mid], a[mid], b[mid]
        out[mid] = bm * bm / (6 * am) + ((xm - 0.5 * bm) ** 2 - 0.25 * bm * bm) / (2 * am)
        fall = (x > a) & (x < a + b)
        xf, af, bf = x[fall], a[fall], b[fall]
        out[fall] = (bf * bf / (6 * af) + 0.5 * (af - bf) + (xf - af)
                     - (bf ** 3 - (af + bf - xf) ** 3) / (6 * af * bf))
    beyond = x >= a + b
    out[beyond] = 0.5 * (a[beyond] + b[beyond]) + (x[beyond] - a[beyond] - b[beyond])
    return out


def boxes_cdf(t_s, widths_s):
    """CDF at t of the sum of up to three independent uniform variables centred on 0 with full widths
    ``widths_s`` (..., 3) sorted in decreasing order, zeros for absent boxes, the first > 0.

    One box: clip(t/w₁ + ½); two: the trapezoid; three: the trapezoid averaged over the third box,
    [I(x + w₃/2) − I(x − w₃/2)]/w₃ with I its integral — or, where the third box lies inside the trapezoid's
    linear part, the trapezoid's value at x (the same number, without the difference).  Exact piecewise
    polynomials, no differences of large numbers beyond relative size w₁/w₃ (callers drop boxes narrower than
    1e-6 of the widest), and none at all on the flat top."""
    t = np.asarray(t_s, dtype=np.float64)
    w = np.asarray(widths_s, dtype=np.float64)
    w1, w2, w3 = w[..., 0], w[..., 1], w[..., 2]
    # the distribution is symmetric: evaluate on the left half only, F(t) = 1 − F(−t) on the right, so the
    # far tail is exactly 0 or 1 and small values keep their relative accuracy
    tl = -np.abs(t)
    x = tl + 0.5 * (w1 + w2)  # from the left end of the trapezoid of the two widest boxes
    with np.errstate(divide="ignore", invalid="ignore"):
        three = (_trapezoid_cdf_integral(x + 0.5 * w3, w1, w2) - _trapezoid_cdf_integral(x - 0.5 * w3, w1, w2)) / w3
        # the third box inside the trapezoid's linear part: its average is the value at its centre, exactly
        # (the difference above loses w₁/w₃ ulps there: 2e-12 at the centre of a 1e5-pulse-wide cell)
        flat = (x - 0.5 * w3 >= w2) & (x + 0.5 * w3 <= w1)
        three = np.where(flat, (x - 0.5 * w2) / w1, three)
    left = np.clip(np.where(w3 > 0, three, _trapezoid_cdf(x, w1, w2)), 0.0, 0.5)
    return np.where(t > 0, 1.0 - left, left)


_INV_SQRT_2PI = 0.3989422804014327


def _tail_table(h, m_max):
    """Cubic Hermite coefficients of Φ(−m), g₁(m) = φ(m) − mΦ(−m) (e₁ = σg₁) and g(m) (e₂ below 0 = σ²g) on
    [0, m_max] at spacing h: (3 functions, intervals, 4) with f(k·h + s·h) = Σ cᵢ sⁱ.  Values and first
    derivatives are exact and chained: Φ(−m)' = −φ, g₁' = −Φ(−m), g' = −g₁."""
    m = np.arange(int(round(m_max / h)) + 1) * h
    phi = np.exp(-0.5 * m * m) * _INV_SQRT_2PI
    tail = ndtr(-m)
    g1 = phi - m * tail
    g = 0.5 * (m * m + 1.0) * tail - 0.5 * m * phi
    out = np.empty((3, len(m) - 1, 4))
    for i, (f, d) in enumerate(((tail, -phi), (g1, -tail), (g, -g1))):
        df, d0, d1 = f[1:] - f[:-1], d[:-1] * h, d[1:] * h
        out[i] = np.stack([f[:-1], d0, 3 * df - 2 * d0 - d1, -2 * df + d0 + d1], axis=1)
    return out


#: Spacing (in σ) and range of the tabulated Gaussian tail functions: cubic Hermite interpolation with exact
#: derivatives, absolute error < 1e-11 (5.3e-12, 3.9e-12, 2.3e-12 measured against SciPy; the quintic table at
#: σ/32 it replaced was < 1e-13 and 20 % slower to bin with); beyond 10σ all three are < 1e-22 and taken as 0.
_TAIL_H = 1.0 / 128.0
_TAIL_MAX = 10.0
#: (3 functions, intervals + 1, 4): one function's coefficients contiguous, and a last row of zeros that every
#: m beyond the table lands on (no branch in the binning loops)
_TAIL = np.ascontiguousarray(np.concatenate([_tail_table(_TAIL_H, _TAIL_MAX), np.zeros((3, 1, 4))], axis=1))
_TAIL_LAST = _TAIL.shape[1] - 1
_TAIL_INV_H = 1.0 / _TAIL_H


@kernel
def _tail_interp(m, fn):
    """Function ``fn`` (0: Φ(−m), 1: g₁, 2: g) of the tail table at m ≥ 0; 0 beyond the table."""
    x = m * _TAIL_INV_H
    k = min(int(x), _TAIL_LAST)
    s = x - k
    return _TAIL[fn, k, 0] + s * (_TAIL[fn, k, 1] + s * (_TAIL[fn, k, 2] + s * _TAIL[fn, k, 3]))


@kernel
def gaussian_tail(m):
    """Φ(−m), the standard normal CDF at −m (m ≥ 0), from the tail table (absolute error < 1e-11)."""
    return _tail_interp(m, 0)


@kernel
def gauss_e1(u, sigma, inv_sigma):
    """P₁(u) − max(u, 0) for the Gaussian pulse (σ, 1/σ), P₁ = ∫P: σ[φ(z) − |z|Φ(−|z|)], even and decaying."""
    return sigma * _tail_interp(abs(u) * inv_sigma, 1)


@kernel
def gauss_e2(u, sigma, inv_sigma):
    """P₂(u) − max(u, 0)²/2 for the Gaussian pulse (σ, 1/σ), P₂ = ∫∫P = σ²[(z² + 1)Φ(z)/2 + zφ(z)/2]:
    σ² g(|z|) below 0 and σ²(½ − g(z)) above, g(m) = (m² + 1)Φ(−m)/2 − mφ(m)/2 ≥ 0 (bounded, no cancellation
    against the growing polynomial)."""
    g = _tail_interp(abs(u) * inv_sigma, 2)
    return sigma * sigma * (0.5 - g if u > 0 else g)


@kernel
def trapezoid_cdf_at(x, a, b):
    """CDF of U(a) ⊛ U(b) (a ≥ b > 0 full widths) at x measured from the left end of its support [0, a + b]
    (the scalar form of :func:`_trapezoid_cdf`; every piece evaluated and selected, no branch)."""
    out = x * x / (2 * a * b)
    out = (x - 0.5 * b) / a if x > b else out
    out = 1.0 - (a + b - x) ** 2 / (2 * a * b) if x > a else out
    out = 1.0 if x >= a + b else out
    return 0.0 if x <= 0.0 else out


@kernel
def gaussian_cdf_left(t, inv_sigma):
    """Kind 0 of :func:`gaussian_box_cdf_at` at t ≤ 0: Φ(t/σ)."""
    return gaussian_tail(-t * inv_sigma)


@kernel
def gaussian_box1_cdf_left(t, sigma, inv_sigma, a, inv_a):
    """Kind 1 of :func:`gaussian_box_cdf_at` at t ≤ 0: the Gaussian ⊛ U(a)."""
    box = min(max(t * inv_a + 0.5, 0.0), 1.0)
    return box + (gauss_e1(t + 0.5 * a, sigma, inv_sigma) - gauss_e1(t - 0.5 * a, sigma, inv_sigma)) * inv_a


@kernel
def gaussian_box2_cdf_left(t, sigma, inv_sigma, a, b, inv_ab):
    """Kind 2 of :func:`gaussian_box_cdf_at` at t ≤ 0: the Gaussian ⊛ U(a) ⊛ U(b)."""
    ha, hb = 0.5 * a, 0.5 * b
    box = trapezoid_cdf_at(t + ha + hb, a, b)
    return box + (gauss_e2(t + ha + hb, sigma, inv_sigma) - gauss_e2(t + ha - hb, sigma, inv_sigma)
                  - gauss_e2(t - ha + hb, sigma, inv_sigma) + gauss_e2(t - ha - hb, sigma, inv_sigma)) * inv_ab


@kernel
def symmetric_cdf(left, t_signed):
    """The CDF at t from ``left`` = its value at −|t| (a distribution symmetric about 0): clipped to [0, ½],
    1 − left on the right, so the far tails are exactly 0 and 1."""
    out = min(max(left, 0.0), 0.5)
    return 1.0 - out if t_signed > 0 else out


@kernel
def gaussian_box_cdf_at(t_signed, sigma, inv_sigma, a, inv_a, b, inv_ab, kind):
    """CDF at t of a Gaussian pulse (σ) ⊛ U(a) ⊛ U(b) for one return of ``kind`` (0: no box, 1: a only, 2: both,
    a ≥ b), with the reciprocals 1/σ, 1/a, 1/(ab) — the compiled kernel of :func:`gaussian_box_cdf`.

    P = Φ(t/σ) = H + (P − H): the box part is exact (trapezoid) and the smooth rest enters through its bounded
    integrals e₁, e₂ (one box: Δ_a e₁/a; two: Δ_a Δ_b e₂/(ab)).  Symmetric: evaluated on the left half,
    F(t) = 1 − F(−t) on the right, so the tails are exact (:func:`symmetric_cdf`).  The binning loops call the
    kinds' functions directly (one loop per kind, no branch inside)."""
    t = -abs(t_signed)
    if kind == 0:
        out = gaussian_cdf_left(t, inv_sigma)
    elif kind == 1:
        out = gaussian_box1_cdf_left(t, sigma, inv_sigma, a, inv_a)
    else:
        out = gaussian_box2_cdf_left(t, sigma, inv_sigma, a, b, inv_ab)
    return symmetric_cdf(out, t_signed)


@kernel
def _gaussian_box_cdf_array(t, sigma, a, b, kind, out):
    for i in range(t.shape[0]):
        for j in range(t.shape[1]):
            out[i, j] = gaussian_box_cdf_at(t[i, j], sigma[i], 1.0 / sigma[i], a[i], 1.0 / a[i] if a[i] > 0 else 0.0,
                                            b[i], 1.0 / (a[i] * b[i]) if b[i] > 0 else 0.0, kind[i])


class _Lanes:
    """LLVM IR on four float64 lanes for the 4-lane CDF kernels below: each operation is the IEEE operation of the
    scalar kernel it mirrors (no fused or reassociated arithmetic), so every lane is bit for bit the scalar
    result.  The table look-ups are four row loads (a row: the 4 cubic coefficients of one interval, 32 bytes)
    transposed into coefficient vectors: the scalar kernels' look-ups keep a loop from vectorising (no gathers
    on AVX2 CPUs), these do not need to."""

    def __init__(self, context, builder):
        from llvmlite import ir

        self.ir, self.context, self.b = ir, context, builder
        self.d = ir.DoubleType()
        self.v4 = ir.VectorType(self.d, 4)
        self.i32, self.i64 = ir.IntType(32), ir.IntType(64)
        self.vi = ir.VectorType(self.i32, 4)
        self._fabs = builder.module.declare_intrinsic("llvm.fabs.v4f64", fnty=ir.FunctionType(self.v4, [self.v4]))

    def splat(self, x):
        ir, b = self.ir, self.b
        v = b.insert_element(ir.Constant(self.v4, ir.Undefined), x, ir.Constant(self.i32, 0))
        return b.shuffle_vector(v, ir.Constant(self.v4, ir.Undefined), ir.Constant(self.vi, [0, 0, 0, 0]))

    def const(self, *x):
        return self.ir.Constant(self.v4, [float(v) for v in (x * 4 if len(x) == 1 else x)])

    def abs(self, x):
        return self.b.call(self._fabs, [x])

    def min(self, x, y):  # x if x < y else y (NaN: y), as the scalar kernels' min
        return self.b.select(self.b.fcmp_ordered("<", x, y), x, y)

    def max(self, x, y):  # x if x > y else y
        return self.b.select(self.b.fcmp_ordered(">", x, y), x, y)

    def where(self, cond, x, y):
        return self.b.select(cond, x, y)

    def gt(self, x, y):
        return self.b.fcmp_ordered(">", x, y)

    def ge(self, x, y):
        return self.b.fcmp_ordered(">=", x, y)

    def le(self, x, y):
        return self.b.fcmp_ordered("<=", x, y)

    def table(self, fn):
        """(first row's address, index of the last row as a float) of tail function ``fn``'s table."""
        table = np.ascontiguousarray(_TAIL[fn])
        ty = self.context.typing_context.resolve_value_type(table)
        ary = self.context.make_array(ty)(self.context, self.b, self.context.make_constant_array(self.b, ty, table))
        last = self.splat(self.ir.Constant(self.d, float(table.shape[0] - 1)))
        return self.b.bitcast(ary.data, self.ir.PointerType(self.d)), last

    def tail(self, m, table):
        """:func:`_tail_interp` of the four m ≥ 0 (the table of :meth:`table`); NaN lands on the last row."""
        ir, b = self.ir, self.b
        rows, last = table
        x = b.fmul(m, self.const(_TAIL_INV_H))
        k = b.fptosi(self.min(x, last), self.vi)  # = min(int(x), last) for x ≥ 0
        s = b.fsub(x, b.sitofp(k, self.v4))
        r = []
        for q in range(4):
            kq = b.sext(b.extract_element(k, ir.Constant(self.i32, q)), self.i64)
            ptr = b.gep(rows, [b.mul(kq, ir.Constant(self.i64, 4))])
            r.append(b.load(b.bitcast(ptr, ir.PointerType(self.v4)), align=8))
        lo = b.shuffle_vector(r[0], r[1], ir.Constant(self.vi, [0, 4, 2, 6]))
        hi = b.shuffle_vector(r[2], r[3], ir.Constant(self.vi, [0, 4, 2, 6]))
        lo2 = b.shuffle_vector(r[0], r[1], ir.Constant(self.vi, [1, 5, 3, 7]))
        hi2 = b.shuffle_vector(r[2], r[3], ir.Constant(self.vi, [1, 5, 3, 7]))
        c0 = b.shuffle_vector(lo, hi, ir.Constant(self.vi, [0, 1, 4, 5]))
        c2 = b.shuffle_vector(lo, hi, ir.Constant(self.vi, [2, 3, 6, 7]))
        c1 = b.shuffle_vector(lo2, hi2, ir.Constant(self.vi, [0, 1, 4, 5]))
        c3 = b.shuffle_vector(lo2, hi2, ir.Constant(self.vi, [2, 3, 6, 7]))
        h = b.fadd(c2, b.fmul(s, c3))
        h = b.fadd(c1, b.fmul(s, h))
        return b.fadd(c0, b.fmul(s, h))

    def edges(self, f, c, dt):
        """t = (f + q − c)·dt for q = 0 … 3 (f a whole number: f + q exact) and −|t|."""
        b = self.b
        t = b.fmul(b.fsub(b.fadd(self.splat(f), self.const(0.0, 1.0, 2.0, 3.0)), self.splat(c)), self.splat(dt))
        return t, b.fneg(self.abs(t))

    def symmetric_store(self, left, t, out, out_ty, j):
        """out[j:j + 4] = :func:`symmetric_cdf` (left, t)."""
        ir, b = self.ir, self.b
        clipped = self.min(self.max(left, self.const(0.0)), self.const(0.5))
        res = b.select(self.gt(t, self.const(0.0)), b.fsub(self.const(1.0), clipped), clipped)
        ary = self.context.make_array(out_ty)(self.context, b, out)
        ptr = b.gep(b.bitcast(ary.data, ir.PointerType(self.d)), [j])
        b.store(res, b.bitcast(ptr, ir.PointerType(self.v4)), align=8)


def _lanes_signature(out, j, scalars):
    f64 = nbtypes.float64
    ok = (isinstance(out, nbtypes.Array) and out.dtype == f64 and out.ndim == 1 and out.layout == "C"
          and isinstance(j, nbtypes.Integer) and all(x == f64 for x in scalars))
    return nbtypes.void(out, j, *scalars) if ok else None


@intrinsic
def gaussian_cdf4(typingctx, out, j, f, c, dt, inv_sigma):
    """out[j:j + 4] = symmetric_cdf(gaussian_cdf_left(−|t|, 1/σ), t) at t = (f + q − c)·dt, q = 0 … 3 (f a whole
    number), bit for bit, on four lanes (:class:`_Lanes`): kind 0, no box.  ``out`` must hold j + 4 values."""
    sig = _lanes_signature(out, j, (f, c, dt, inv_sigma))

    def codegen(context, builder, signature, args):
        v = _Lanes(context, builder)
        out_v, j_v, f_v, c_v, dt_v, inv_s_v = args
        j64 = context.cast(builder, j_v, signature.args[1], nbtypes.int64)
        t, tl = v.edges(f_v, c_v, dt_v)
        left = v.tail(builder.fmul(builder.fneg(tl), v.splat(inv_s_v)), v.table(0))
        v.symmetric_store(left, t, out_v, signature.args[0], j64)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def gaussian_box1_cdf4(typingctx, out, j, f, c, dt, sigma, inv_sigma, a, inv_a):
    """out[j:j + 4] = symmetric_cdf(gaussian_box1_cdf_left(−|t|, σ, 1/σ, a, 1/a), t) at t = (f + q − c)·dt,
    q = 0 … 3 (f a whole number), bit for bit, on four lanes (:class:`_Lanes`).  ``out`` must hold j + 4 values."""
    sig = _lanes_signature(out, j, (f, c, dt, sigma, inv_sigma, a, inv_a))

    def codegen(context, builder, signature, args):
        v = _Lanes(context, builder)
        b = builder
        out_v, j_v, f_v, c_v, dt_v, s_v, inv_s_v, a_v, inv_a_v = args
        j64 = context.cast(builder, j_v, signature.args[1], nbtypes.int64)
        t, tl = v.edges(f_v, c_v, dt_v)
        sigma_, inv_s, inv_a = v.splat(s_v), v.splat(inv_s_v), v.splat(inv_a_v)
        ha = v.splat(b.fmul(v.ir.Constant(v.d, 0.5), a_v))
        box = v.min(v.max(b.fadd(b.fmul(tl, inv_a), v.const(0.5)), v.const(0.0)), v.const(1.0))
        g1 = v.table(1)

        def e1(u):  # gauss_e1
            return b.fmul(sigma_, v.tail(b.fmul(v.abs(u), inv_s), g1))

        left = b.fadd(box, b.fmul(b.fsub(e1(b.fadd(tl, ha)), e1(b.fsub(tl, ha))), inv_a))
        v.symmetric_store(left, t, out_v, signature.args[0], j64)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def gaussian_box2_cdf4(typingctx, out, j, f, c, dt, sigma, inv_sigma, a, b, inv_ab):
    """out[j:j + 4] = symmetric_cdf(gaussian_box2_cdf_left(−|t|, σ, 1/σ, a, b, 1/(ab)), t) at t = (f + q − c)·dt,
    q = 0 … 3, bit for bit, on four lanes (:class:`_Lanes`).  ``out`` must hold j + 4 values."""
    sig = _lanes_signature(out, j, (f, c, dt, sigma, inv_sigma, a, b, inv_ab))

    def codegen(context, builder, signature, args):
        v = _Lanes(context, builder)
        bd = builder
        out_v, j_v, f_v, c_v, dt_v, s_v, inv_s_v, a_s, b_s, inv_ab_v = args
        j64 = context.cast(builder, j_v, signature.args[1], nbtypes.int64)
        half = v.ir.Constant(v.d, 0.5)
        t, tl = v.edges(f_v, c_v, dt_v)
        inv_s, inv_ab = v.splat(inv_s_v), v.splat(inv_ab_v)
        s2 = v.splat(bd.fmul(s_v, s_v))
        a, bb = v.splat(a_s), v.splat(b_s)
        ha, hb = v.splat(bd.fmul(half, a_s)), v.splat(bd.fmul(half, b_s))
        ab2 = v.splat(bd.fmul(bd.fmul(v.ir.Constant(v.d, 2.0), a_s), b_s))
        apb = v.splat(bd.fadd(a_s, b_s))
        g = v.table(2)

        def e2(u):  # gauss_e2
            gv = v.tail(bd.fmul(v.abs(u), inv_s), g)
            return bd.fmul(s2, v.where(v.gt(u, v.const(0.0)), bd.fsub(v.const(0.5), gv), gv))

        def trapezoid(x):  # trapezoid_cdf_at(x, a, b)
            out = bd.fdiv(bd.fmul(x, x), ab2)
            out = v.where(v.gt(x, bb), bd.fdiv(bd.fsub(x, bd.fmul(v.const(0.5), bb)), a), out)
            r = bd.fsub(apb, x)
            out = v.where(v.gt(x, a), bd.fsub(v.const(1.0), bd.fdiv(bd.fmul(r, r), ab2)), out)
            out = v.where(v.ge(x, apb), v.const(1.0), out)
            return v.where(v.le(x, v.const(0.0)), v.const(0.0), out)

        up, dn = bd.fadd(tl, ha), bd.fsub(tl, ha)
        a1, a2, a3, a4 = bd.fadd(up, hb), bd.fsub(up, hb), bd.fadd(dn, hb), bd.fsub(dn, hb)
        diff = bd.fadd(bd.fsub(bd.fsub(e2(a1), e2(a2)), e2(a3)), e2(a4))
        left = bd.fadd(trapezoid(a1), bd.fmul(diff, inv_ab))
        v.symmetric_store(left, t, out_v, signature.args[0], j64)
        return context.get_dummy_value()

    return sig, codegen


#: A box narrower than this fraction of the Gaussian pulse's σ is dropped: the shape changes by
#: ≈ w²/(24σ²) < 5e-6 of the peak (second order).
GAUSS_BOX_DROP = 1e-2
#: A box narrower than this fraction of the Gaussian pulse's σ is folded into the pulse (:func:`gaussian_box_terms`).
GAUSS_BOX_FOLD = 0.3
#: A box narrower than this fraction of the widest box is dropped (rectangular pulse: first-order edge change).
RECT_BOX_DROP = 1e-6


@kernel
def sorted_spread_pair(s0, s1, drop):
    """One cell's two time spreads as (a, b): |s0|, |s1| sorted widest first, each set to 0 below ``drop``
    (:func:`sorted_spreads`)."""
    a, b = abs(s0), abs(s1)
    if b > a:
        a, b = b, a
    return (0.0 if a < drop else a), (0.0 if b < drop else b)


@kernel
def gaussian_box_params(a, b, sigma, fold):
    """(σ_eff, a, b, kind) of one return of a Gaussian pulse (σ) with sorted spreads a ≥ b: boxes narrower than
    ``fold`` folded into the pulse, σ_eff² = σ² + (a² + b²)/12 over the folded ones (:func:`gaussian_box_terms`)."""
    fa, fb = a < fold, b < fold
    var = sigma * sigma + ((a * a if fa else 0.0) + (b * b if fb else 0.0)) / 12.0
    a_left, b_left = (0.0 if fa else a), (0.0 if fb else b)
    return math.sqrt(var), a_left, b_left, (1 if a_left > 0 else 0) + (1 if b_left > 0 else 0)


@kernel
def _sorted_spreads_array(spread, drop, out):
    for i in range(spread.shape[0]):
        out[i, 0], out[i, 1] = sorted_spread_pair(spread[i, 0], spread[i, 1], drop)


@kernel
def _gaussian_box_terms_array(spread, sigma, fold, sigma_eff, a, b, kind):
    for i in range(spread.shape[0]):
        sigma_eff[i], a[i], b[i], kind[i] = gaussian_box_params(spread[i, 0], spread[i, 1], sigma, fold)


def spread_drop_s(laser: LaserSettings) -> float:
    """Cell spreads narrower than this are dropped (``GAUSS_BOX_DROP``·σ for the Gaussian pulse,
    ``RECT_BOX_DROP``·width for the rectangular one)."""
    if laser.pulse_shape == "gaussian":
        return GAUSS_BOX_DROP * pulse_sigma_s(laser)
    return RECT_BOX_DROP * max(laser.pulse_fwhm_s, 1e-300)


def sorted_spreads(laser: LaserSettings, spread_s):
    """Time spreads (n, 2) of sub-ray cells, sorted widest first, with boxes too narrow to matter set to 0
    (:func:`spread_drop_s`)."""
    s = np.ascontiguousarray(np.asarray(spread_s, dtype=np.float64).reshape(-1, 2))
    out = np.empty(s.shape)
    _sorted_spreads_array(s, spread_drop_s(laser), out)
    return out


def gaussian_box_terms(laser: LaserSettings, spread_s):
    """Per ray (σ_eff, a, b, kind) for a Gaussian pulse and sorted cell spreads (n, 2) (:func:`sorted_spreads`).

    A box narrower than ``GAUSS_BOX_FOLD``·σ is folded into the pulse as a wider Gaussian,
    σ_eff² = σ² + w²/12 (same energy, centroid and variance; the shape differs by the box's fourth cumulant,
    w⁴/(960σ⁴) per box, below 2e-5 of the peak).  kind = number of boxes left (0, 1 or 2)."""
    s = np.ascontiguousarray(np.asarray(spread_s, dtype=np.float64).reshape(-1, 2))
    sigma = pulse_sigma_s(laser)
    n = len(s)
    out = np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.int64)
    _gaussian_box_terms_array(s, sigma, GAUSS_BOX_FOLD * sigma, *out)
    return out


def gaussian_box_cdf(t_s, sigma_s, a_s, b_s, kind):
    """CDF at t (n, k) of a Gaussian pulse (σ) ⊛ U(a) ⊛ U(b) for n returns with per-return σ, a, b and kind
    (n,) (:func:`gaussian_box_terms`): :func:`gaussian_box_cdf_at` at every element."""
    t = np.ascontiguousarray(t_s, dtype=np.float64)
    n = t.shape[0]
    par = [np.ascontiguousarray(np.broadcast_to(np.asarray(v).reshape(-1), (n,)), dtype=dt)
           for v, dt in ((sigma_s, np.float64), (a_s, np.float64), (b_s, np.float64), (kind, np.int64))]
    out = np.empty(t.shape)
    _gaussian_box_cdf_array(t.reshape(n, -1), *par, out.reshape(n, -1))
    return out


def pulse_box_cdf(laser: LaserSettings, t_s, spread_s):
    """Fraction of the energy of a return spread uniformly over a box (or a trapezoid, two boxes) of round-trip
    times that arrives before t: the pulse CDF convolved with U(a) ⊛ U(b).

    ``t_s`` (n, k): times relative to each box centre; ``spread_s`` (n, 2): full widths (a, b) sorted a ≥ b,
    zeros for absent boxes (:func:`sorted_spreads`).  Gaussian pulse: :func:`gaussian_box_terms` and
    :func:`gaussian_box_cdf`; rectangular pulse of width τ: the CDF of three boxes (τ, a, b), exact."""
    t = np.asarray(t_s, dtype=np.float64)
    s = np.asarray(spread_s, dtype=np.float64)
    if laser.pulse_shape != "gaussian":
        w = np.concatenate([np.full((len(s), 1), laser.pulse_fwhm_s), s], axis=1)
        w = np.sort(w, axis=1)[:, ::-1]
        return boxes_cdf(t, w[:, None, :])
    sigma, a, b, kind = gaussian_box_terms(laser, s)
    return gaussian_box_cdf(t, sigma, a, b, kind)
