"""Bins without signal: the exact A/D code distribution, tabulated once per run (docs/theory.md §8)."""
from __future__ import annotations

import math
import threading

import numpy as np

from ...jit import kernel

#: Probabilities of the tabulated code sampler are multiples of 2**-32 (one 32-bit uniform per sample).
P_BITS = 32
#: The table route needs a Gaussian part σ ≥ this × Δ (otherwise the characteristic function decays too
#: slowly for the alias sum and the distribution is close to a lattice): the exact per-bin route is used.
TABLE_MIN_SIGMA_STEPS = 2e-3
#: Bins that caught up to this many signal photo-electrons take tabulated codes too (CaughtCodeTables).
CAUGHT_TABLES = 16
#: Largest FFT size (A/D indices spanned by the noise distribution) for the table route.
_TABLE_MAX_CODES = 1 << 20


def noise_code_pmf(step_e, *, n_mult=0.0, gain=1.0, excess_noise=1.0, shot=True, surface_dark_e=0.0,
                   surface_dark_poisson=False, gauss_mean_e=0.0, gauss_var_e2=0.0, fixed_primaries=None,
                   tail=1e-15):
    """Exact probabilities of the A/D index k = rint(X/Δ) of a bin without signal (docs/theory.md §8).

    X = Σ_{i ≤ n} g_i + D + Z (electrons):
      n ~ Poisson(``n_mult``) multiplied primaries (background + bulk dark; exactly ``n_mult`` — a continuous
        amount — when ``shot`` is off), each with the single-electron gain g ~ Gamma(1/(F − 1), G(F − 1)) of
        :func:`gamma_gain` (g = G exactly when F = 1);
      D ~ Poisson(``surface_dark_e``) unmultiplied electrons when ``surface_dark_poisson``;
      Z ~ N(``gauss_mean_e``, ``gauss_var_e2``): read-out noise (and the surface dark where it is folded in).
    Its characteristic function is φ_X(t) = exp[n(φ_g(t) − 1)] · exp[d(e^{it} − 1)] · exp(iμt − σ²t²/2),
    φ_g(t) = (1 − iθt)^(−a).  Since p_k = ∫_{(k−½)Δ}^{(k+½)Δ} f_X(x) dx samples f_X ⊛ box_Δ at kΔ, the Poisson
    summation formula gives its discrete-time Fourier transform exactly:

        Σ_k p_k e^{iωk} = Σ_j φ_X((ω + 2πj)/Δ) · sinc((ω + 2πj)/2π),

    evaluated at the M frequencies of an FFT window holding all of the mass (tails beyond it < ``tail``) and
    inverted by one FFT.  Errors: float64 round-off (~1e-16 × √M) and the alias sum truncated where
    |φ_Z| < 1e-18.  Needs a Gaussian part σ > 0.  Returns ``(k0, p)``: p[i] = P(k = k0 + i), float64, Σ = 1.

    ``fixed_primaries`` (1-D integers m_1, m_2, …): the laws given m_j *additional* multiplied primaries (a bin
    that caught m_j signal photo-electrons), factor φ_g(t)^m_j; returns ``(k0, P)`` with P[j, i] = P(k = k0 + i
    | m_j) on one common window.
    """
    step = float(step_e)
    sigma = math.sqrt(gauss_var_e2)
    if not sigma > 0 or not step > 0:
        raise ValueError("noise_code_pmf needs a Gaussian part (σ > 0) and an A/D step Δ > 0")
    G, F, b, d = float(gain), float(excess_noise), float(n_mult), float(surface_dark_e)
    gamma_gain_on = F > 1.0 + 1e-12
    theta = G * (F - 1.0) if gamma_gain_on else 0.0
    a = 1.0 / (F - 1.0) if gamma_gain_on else 0.0
    if shot:
        mean = G * b
        var = G * G * (F if gamma_gain_on else 1.0) * b
    else:
        mean, var = G * b, G * theta * b
    d_p = d if surface_dark_poisson else 0.0
    mean += d_p + gauss_mean_e
    var += d_p + gauss_var_e2
    # tail scale of the multiplied part (exponential-like, scale θ; Poisson lattice step G) and of D
    scale = max(theta, G if (shot and b > 0) else 0.0, 1.0 if d_p > 0 else 0.0)
    fixed = None if fixed_primaries is None else np.asarray(fixed_primaries, dtype=np.float64).reshape(-1, 1)
    mean_hi = mean
    if fixed is not None:  # m extra primaries: + G m mean, + G²(F − 1) m variance
        mean_lo, mean_hi = mean + G * fixed.min(), mean + G * fixed.max()
        mean = mean_lo
        var += G * theta * fixed.max()
        scale = max(scale, G)

    def cf(t):
        lc = (1j * gauss_mean_e) * t - (0.5 * gauss_var_e2) * t * t
        if fixed is not None:
            lc = lc + fixed * (-a * np.log1p((-1j * theta) * t) if gamma_gain_on else (1j * G) * t)
        if b > 0:
            if gamma_gain_on:
                lg = -a * np.log1p((-1j * theta) * t)
                lc = lc + (b * np.expm1(lg) if shot else b * lg)
            else:
                lc = lc + (b * np.expm1((1j * G) * t) if shot else (1j * G * b) * t)
        if d_p > 0:
            lc = lc + d_p * np.expm1(1j * t)
        return np.exp(lc)

    n_alias = int(math.ceil(1.5 * step / sigma)) + 1  # |φ_Z((π + 2πJ)/Δ)| < 1e-18
    half = 40.0 * math.sqrt(var) + 80.0 * scale + 4.0 * step
    for _ in range(8):
        k0 = int(math.floor((mean - half) / step)) - 2
        k1 = int(math.ceil((mean_hi + half) / step)) + 2
        M = 1 << max(4, int(k1 - k0).bit_length())
        if M > _TABLE_MAX_CODES:
            raise ValueError(f"noise distribution spans {M} A/D codes (> {_TABLE_MAX_CODES})")
        omega = 2.0 * np.pi * np.fft.fftfreq(M)
        acc = 0.0
        for j in range(-n_alias, n_alias + 1):
            w = omega + 2.0 * np.pi * j
            acc = acc + cf(w / step) * np.sinc(w / (2.0 * np.pi))
        p = np.fft.fft(np.atleast_2d(acc) * np.exp(-1j * omega * k0), axis=-1).real / M
        edge = max(1, M // 16)
        if np.all(p[:, :edge].sum(axis=1) + p[:, -edge:].sum(axis=1) < tail):
            break
        half *= 2.0
    else:  # pragma: no cover - the window doubles 8 times
        raise ValueError("noise distribution tails did not converge")
    np.maximum(p, 0.0, out=p)  # round-off negatives (~1e-17)
    p /= p.sum(axis=1, keepdims=True)
    return k0, (p[0] if fixed is None else p)


class CodeTable:
    """Inverse-CDF sampler of A/D codes from one uniform 32-bit integer per sample (exact up to probabilities
    rounded to multiples of 2**-32).

    Entries: [clipped below code 0], the A/D codes in order, [clipped above full scale]; T_i = round(2³² C_i)
    their cumulative probabilities; a sample r ∈ [0, 2³²) takes the entry i with T_{i−1} ≤ r < T_i.
    Level 1: the top 16 bits of r index a 65536-cell table holding the code when one entry covers the whole
    cell; the few cells that straddle an entry boundary hold a sentinel, and those samples are resolved by a
    binary search on T (at most one cell per entry boundary, i.e. ≤ (entries − 1)/65536 of the samples).
    """

    def __init__(self, k0, pmf, offset, top, dtype, cell_bits=16):
        self.CELL_BITS = int(cell_bits)
        pmf = np.asarray(pmf, dtype=np.float64)
        raw = k0 + np.arange(pmf.size, dtype=np.int64) + int(offset)
        low, high = raw < 0, raw > top
        mid = ~(low | high)
        p = np.concatenate([[pmf[low].sum()], pmf[mid], [pmf[high].sum()]])
        code = np.concatenate([[0], raw[mid], [top]]).astype(dtype)
        cum = np.cumsum(p)
        cum /= cum[-1]
        T = np.floor(cum * 2.0 ** P_BITS + 0.5).astype(np.uint64)
        T[-1] = np.uint64(1 << P_BITS)
        self.T, self.code = T, code
        self.T_int = T.astype(np.int64)  # (≤ 2³²: the compiled sampler compares in int64)
        self.t_low = int(T[0])        # r < t_low: clipped at code 0
        self.t_high = int(T[-2])      # r ≥ t_high: clipped at full scale
        p_q = np.diff(np.concatenate([[0], T.astype(np.int64)]))
        drawable = code[p_q > 0]
        self.n_entries = int(np.count_nonzero(p_q))
        self.max_prob_error = float(np.max(np.abs(p_q / 2.0 ** P_BITS - p)))
        # cell h holds r ∈ [h·2^s, (h+1)·2^s), s = 32 − CELL_BITS.  Its first r falls in entry #{i: T_i ≤ h·2^s}
        # = #{i: ⌈T_i/2^s⌉ ≤ h}; the cell is ambiguous when a boundary T_i lies strictly inside it.
        n_cells, sh = 1 << self.CELL_BITS, P_BITS - self.CELL_BITS
        Ti = T[:-1].astype(np.int64)
        first = np.cumsum(np.bincount(-((-Ti) >> sh), minlength=n_cells + 1))[:n_cells]
        amb = np.zeros(n_cells, dtype=bool)
        amb[(Ti >> sh)[(Ti & ((1 << sh) - 1)) != 0]] = True
        self.n_ambiguous_cells = int(np.count_nonzero(amb))
        table = code[first]
        c_lo, c_hi = int(drawable.min()), int(drawable.max())  # any value outside [c_lo, c_hi] is never drawn
        self.sentinel = c_hi + 1 if c_hi < np.iinfo(dtype).max else (c_lo - 1 if c_lo > 0 else None)
        self.amb_cells = None
        if self.sentinel is not None:
            table[amb] = self.sentinel
        else:  # pragma: no cover - every code value up to the dtype's top is drawable
            self.amb_cells = amb
        self.table = table

    def _args(self):
        amb = self.amb_cells if self.amb_cells is not None else np.zeros(1, dtype=bool)
        return (self.table, P_BITS - self.CELL_BITS, -1 if self.sentinel is None else self.sentinel, amb,
                self.T_int, self.code, self.t_low, self.t_high)

    def sample(self, r, out):
        """Codes for the given uniform uint32 ``r`` into ``out`` (1-D, table dtype).  Returns (n_low, n_high):
        how many were clipped at code 0 and at full scale."""
        return _lookup_codes(r, *self._args(), out, np.empty(r.size, dtype=np.int64))

    def sample_stream(self, key, out):
        """Codes for the uniforms 0 … len(out) − 1 of the counter-based stream ``key`` (:func:`uniform_uint32`)
        into ``out``: the uniforms are computed inside the compiled pass, chunk by chunk, never stored.
        Returns (n_low, n_high) like :meth:`sample`."""
        return _sample_stream(np.uint64(key), *self._args(), out)

    def clipped(self, r):
        n_low = int(np.count_nonzero(r < np.uint32(self.t_low))) if self.t_low > 0 else 0
        n_high = int(np.count_nonzero(r >= np.uint32(self.t_high))) if self.t_high < (1 << P_BITS) else 0
        return n_low, n_high


@kernel
def _lookup_codes(r, table, shift, sentinel, amb_cells, T, code, t_low, t_high, out, pos):
    """out[k] = the code of the entry holding r[k]: the level-1 cell's code, or for an ambiguous cell (the
    ``sentinel``; ``amb_cells`` when there is none, sentinel < 0) the binary search of r[k] on the cumulative
    T (first T_j > r[k]).  Returns the number of r below ``t_low`` and at or above ``t_high`` (clipped).

    One look-up pass that notes the (rare: ≤ one cell per entry boundary) ambiguous samples in ``pos``
    (int64 scratch, ≥ r.size), their fix-up, then the clip counts (branch-free, only if a tail is clipped)."""
    n = r.size
    n_amb = 0
    if sentinel >= 0:
        for k in range(n):
            c = table[r[k] >> shift]
            out[k] = c
            if c == sentinel:
                pos[n_amb] = k
                n_amb += 1
    else:
        for k in range(n):
            cell = r[k] >> shift
            out[k] = table[cell]
            if amb_cells[cell]:
                pos[n_amb] = k
                n_amb += 1
    n_t = T.size
    for q in range(n_amb):
        k = pos[q]
        ri = np.int64(r[k])
        lo, hi = 0, n_t
        while lo < hi:  # first j with T[j] > ri (searchsorted, side="right")
            mid = (lo + hi) >> 1
            if T[mid] > ri:
                hi = mid
            else:
                lo = mid + 1
        out[k] = code[lo]
    n_low = 0
    n_high = 0
    if t_low > 0:
        for k in range(n):
            n_low += r[k] < t_low
    if t_high < (1 << P_BITS):
        for k in range(n):
            n_high += r[k] >= t_high
    return n_low, n_high


# ---------------------------------------------------------------------------- the counter-based uniform stream
#: SplitMix64 (Steele, Lea & Flood, "Fast splittable pseudorandom number generators", OOPSLA 2014; the output
#: function is Stafford's "Mix13" variant of the MurmurHash3 finalizer): word w of the stream with key κ is
#: mix(κ + (w + 1)·γ) mod 2⁶⁴, γ the odd "golden gamma" ⌊2⁶⁴/φ⌋.
SPLITMIX_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_MIX_M1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX_M2 = np.uint64(0x94D049BB133111EB)
#: Uniforms computed per chunk of the compiled sampler (even: a chunk starts on a 64-bit word).
_STREAM_CHUNK = 1024


@kernel
def splitmix64_mix(z):
    """The SplitMix64 output function of a uint64 (a bijection of 2⁶⁴)."""
    z = (z ^ (z >> np.uint64(30))) * _MIX_M1
    z = (z ^ (z >> np.uint64(27))) * _MIX_M2
    return z ^ (z >> np.uint64(31))


@kernel
def _stream_fill(key, w0, buf):
    """buf[2j], buf[2j + 1] = low and high 32 bits of word w0 + j of the stream ``key`` (buf: uint32, even size)."""
    base = key + np.uint64(w0 + 1) * SPLITMIX_GAMMA
    for j in range(buf.size // 2):
        z = splitmix64_mix(base + np.uint64(j) * SPLITMIX_GAMMA)
        buf[2 * j] = np.uint32(z & np.uint64(0xFFFFFFFF))
        buf[2 * j + 1] = np.uint32(z >> np.uint64(32))


@kernel
def _sample_stream(key, table, shift, sentinel, amb_cells, T, code, t_low, t_high, out):
    """:func:`_lookup_codes` on the uniforms 0 … out.size − 1 of the stream ``key``, chunk by chunk."""
    buf = np.empty(_STREAM_CHUNK, np.uint32)
    pos = np.empty(_STREAM_CHUNK, np.int64)
    n = out.size
    n_low = 0
    n_high = 0
    for i0 in range(0, n, _STREAM_CHUNK):
        m = min(_STREAM_CHUNK, n - i0)
        _stream_fill(key, i0 // 2, buf)
        lo, hi = _lookup_codes(buf[:m], table, shift, sentinel, amb_cells, T, code, t_low, t_high, out[i0:i0 + m],
                               pos)
        n_low += lo
        n_high += hi
    return n_low, n_high


@kernel
def _stream_uniform(key, i):
    """Uniform number i of the stream ``key``: the 64-bit word i // 2, its low half when i is even."""
    z = splitmix64_mix(key + np.uint64((i >> 1) + 1) * SPLITMIX_GAMMA)
    return np.uint32((z >> np.uint64(32 * (i & 1))) & np.uint64(0xFFFFFFFF))


@kernel
def _stream_at(key, idx, out):
    """out[k] = uniform number idx[k] of the stream ``key``."""
    for k in range(idx.size):
        out[k] = _stream_uniform(key, idx[k])


class CaughtCodeTables:
    """Code laws of bins that caught m = 1 … ``m_max`` signal photo-electrons (plus everything a signal-free bin
    has), from :func:`noise_code_pmf` with ``fixed_primaries``; built on first use (thread-safe), sampled with
    one 32-bit uniform each like :class:`CodeTable` (4096-cell level-1 tables stacked into one array)."""

    def __init__(self, m_max, step_e, pmf_kwargs, offset, top, dtype, cell_bits=12):
        self.m_max, self.cell_bits = int(m_max), int(cell_bits)
        self._args = (step_e, pmf_kwargs, offset, top, dtype)
        self._lock = threading.Lock()
        self.tables = None

    def _build(self):
        with self._lock:
            if self.tables is not None:
                return
            step_e, kw, offset, top, dtype = self._args
            k0, P = noise_code_pmf(step_e, fixed_primaries=np.arange(1, self.m_max + 1), **kw)
            tabs = [CodeTable(k0, P[j], offset, top, dtype, self.cell_bits) for j in range(self.m_max)]
            # (int32 when every code fits: half the cache footprint of int64, the look-ups are random)
            stack = np.empty((self.m_max, 1 << self.cell_bits), dtype=np.int32 if top < 2 ** 31 else np.int64)
            for j, t in enumerate(tabs):
                stack[j] = t.table
                if t.n_ambiguous_cells:
                    amb = t.amb_cells if t.amb_cells is not None else t.table == t.sentinel
                    stack[j, amb] = -1
            self.stack = stack.reshape(-1)
            self.t_low = np.array([t.t_low for t in tabs], dtype=np.int64)
            self.t_high = np.array([t.t_high for t in tabs], dtype=np.int64)
            self.T_stack = np.stack([t.T_int for t in tabs])  # (one window: the same entries and codes)
            self.max_prob_error = max(t.max_prob_error for t in tabs)
            self.tables = tabs

    def sample(self, m, r):
        """Codes for caught counts ``m`` (1 … m_max) and uniforms ``r`` (uint32).  Returns (codes int64, n_low,
        n_high).  One compiled pass (:func:`_caught_lookup`)."""
        if self.tables is None:
            self._build()
        codes = np.empty(len(m), dtype=np.int64)
        n_low, n_high = _caught_lookup(np.ascontiguousarray(m, dtype=np.int64), r, self.stack, self.cell_bits,
                                       self.T_stack, self.tables[0].code, self.t_low, self.t_high, codes)
        return codes, n_low, n_high


    def apply(self, sig, cnt, key, table, out, rest):
        """The bins ``sig`` of a block caught ``cnt`` (float64 ≥ 1) signal photo-electrons: their signal-free
        codes (``table``, uniform number sig[q] of the stream ``key``) are replaced, for cnt ≤ m_max, by the
        code of the caught-count table for the same uniform, written into ``out``; the positions q of larger
        counts go to ``rest``.  Returns (change of n_low, change of n_high, bins coded, len(rest) used).
        One compiled pass (:func:`_caught_codes`)."""
        if self.tables is None:
            self._build()
        return _caught_codes(sig, cnt, np.uint64(key), table.t_low, table.t_high, self.stack, self.cell_bits,
                             self.T_stack, self.tables[0].code, self.t_low, self.t_high, self.m_max, out, rest)


@kernel
def _caught_code(mi, ri, stack, cell_bits, T_stack, code):
    """The code of caught-count table mi (0-based) for the uniform ri: the stacked level-1 cell, or (cell −1:
    ambiguous) the binary search of ri on that table's cumulative T (first T_j > ri)."""
    c = stack[(mi << cell_bits) | (ri >> (P_BITS - cell_bits))]
    if c < 0:
        lo, hi = 0, T_stack.shape[1]
        while lo < hi:  # searchsorted, side="right"
            mid = (lo + hi) >> 1
            if T_stack[mi, mid] > ri:
                hi = mid
            else:
                lo = mid + 1
        c = code[lo]
    return c


@kernel
def _caught_lookup(m, r, stack, cell_bits, T_stack, code, t_low, t_high, out):
    """out[q] = the code of table m[q] for the uniform r[q] (:func:`_caught_code`).  Returns the clipped counts."""
    n_low = 0
    n_high = 0
    for q in range(m.size):
        mi = m[q] - 1
        ri = np.int64(r[q])
        out[q] = _caught_code(mi, ri, stack, cell_bits, T_stack, code)
        n_low += ri < t_low[mi]
        n_high += ri >= t_high[mi]
    return n_low, n_high


@kernel
def _caught_codes(sig, cnt, key, t_low0, t_high0, stack, cell_bits, T_stack, code, t_low, t_high, m_max, out,
                  rest):
    """:meth:`CaughtCodeTables.apply`: per bin j = sig[q], its uniform (:func:`_stream_uniform`), the signal-free
    clip counts taken back, the caught-count code written (cnt ≤ m_max) or q listed in ``rest``."""
    d_low = 0
    d_high = 0
    n_tab = 0
    n_rest = 0
    for q in range(sig.size):
        j = sig[q]
        ri = np.int64(_stream_uniform(key, j))
        d_low -= ri < t_low0
        d_high -= ri >= t_high0
        if cnt[q] <= m_max:
            mi = np.int64(cnt[q]) - 1
            out[j] = _caught_code(mi, ri, stack, cell_bits, T_stack, code)
            d_low += ri < t_low[mi]
            d_high += ri >= t_high[mi]
            n_tab += 1
        else:
            rest[n_rest] = q
            n_rest += 1
    return d_low, d_high, n_tab, n_rest


def uniform_uint32(key, n):
    """Uniform 32-bit integers of the counter-based stream ``key`` (SplitMix64: word w = mix(key + (w + 1)·γ),
    two uniforms per word, low half first).  ``n``: how many from the start of the stream (int), or the
    indices of the uniforms wanted (1-D integers ≥ 0): any uniform is computed from its index alone.
    ``key``: an integer < 2⁶⁴, or a ``np.random.Generator`` (one 64-bit key drawn from it)."""
    if isinstance(key, np.random.Generator):
        key = key.integers(0, 2 ** 64, dtype=np.uint64)
    key = np.uint64(key)
    if np.ndim(n) == 0:
        out = np.empty(int(n) + (int(n) & 1), dtype=np.uint32)
        _stream_fill(key, 0, out)
        return out[:int(n)]
    idx = np.ascontiguousarray(n, dtype=np.int64).reshape(-1)
    out = np.empty(idx.size, dtype=np.uint32)
    _stream_at(key, idx, out)
    return out
