"""Exact fast samplers for the receiver chain: sparse and dense Poisson counts, APD gain with excess noise."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ...jit import kernel
from .code_tables import SPLITMIX_GAMMA, splitmix64_mix

#: Bins whose Poisson mean is at least this are drawn with ``rng.poisson`` per bin (exact); below it the
#: events are placed sparsely (exact).  Pure speed trade-off, no approximation.
DENSE_MEAN = 8.0
#: Poisson means above this are drawn as a normal with the exact mean and variance (relative skewness error
#: 1/sqrt(mean) < 3e-4); far beyond any ADC full scale in practice.
NORMAL_MEAN = 1e7
#: Poisson means below this are drawn by :func:`poisson_inversion` (compiled, one uniform each); larger ones by
#: ``rng.poisson``.  Pure speed trade-off (the inversion walks ≈ mean + 1 terms), no approximation.
POISSON_INVERSION_MAX = 8.0
#: Poisson means from POISSON_INVERSION_MAX up to (not including) this are drawn by :func:`poisson_grid` (compiled,
#: two uniforms each: one from the tabulated law of the grid mean Λ = POISSON_GRID_STEP·j at or below the mean, one by
#: inversion of the rest);
#: larger ones by ``rng.poisson``.  Pure speed trade-off, no approximation (exact to float64 round-off).
POISSON_GRID_MAX = 1024.0
#: Spacing of the grid means of :func:`poisson_grid_tables` (a power of two; the rest λ − Λ_j below it costs
#: ≈ rest + 1 inversion steps, the tables' size grows as 1/step).
POISSON_GRID_STEP = 2.0
#: The table route's Poisson sampler (the chain report's ``poisson_sampler``, docs/receiver.md): exact in law, its
#: realisation differs from NumPy's ``rng.poisson`` (session 30 of issue 28; before it, means ≥ 8 and the per-bin
#: tail's background and surface dark came from ``rng.poisson``).
POISSON_SAMPLER = (f"counter-based streams: inversion below a mean of {POISSON_INVERSION_MAX:g}, table of "
                   f"Poisson({POISSON_GRID_STEP:g}j) + inversion of the rest below {POISSON_GRID_MAX:g}, "
                   f"rng.poisson above")
#: :func:`poisson_inversion` stops at this count: P(N ≥ 64) < 1e-34 for means below POISSON_INVERSION_MAX.
_INVERSION_KMAX = 64


def poisson_sparse_counts(mean, rng):
    """Exact Poisson counts for a 1-D array of (mostly small) means: K ~ Poisson(Σ mean), then each of the K
    events falls in element i with probability mean_i/Σ mean (inverse-CDF search on the float64 cumulative
    sum).  Exact (superposition of independent Poisson processes); cost O(size + K log size).
    Returns int64 counts of the same length."""
    m = np.asarray(mean).reshape(-1)
    total = float(np.sum(m, dtype=np.float64)) if m.size else 0.0
    if not total > 0.0:
        return np.zeros(m.size, dtype=np.int64)
    k = int(rng.poisson(total))
    if k == 0:  # the common case for very faint bins: one pass over the means
        return np.zeros(m.size, dtype=np.int64)
    c = m.astype(np.float64)
    np.cumsum(c, out=c)  # in place: much faster than a casting cumsum
    total = float(c[-1])
    u = rng.random(k)
    u *= total
    idx = np.searchsorted(c, u, side="right")
    np.minimum(idx, m.size - 1, out=idx)  # u < total always; guards round-off at the very top
    return np.bincount(idx, minlength=m.size)


@kernel
def poisson_inversion(lam, p0, u):
    """Poisson(``lam``) from one uniform ``u`` ∈ [0, 1) by inversion: the smallest k with u < F_k = P(N ≤ k),
    F_0 = p0 = e^(−λ) (given: computed for a whole array at once), F_k = F_{k−1} + p_k, p_k = p_{k−1} λ/k.
    Exact up to float64 round-off (~1e-16, as fine as the 53-bit uniform).  For means below
    :data:`POISSON_INVERSION_MAX` (≈ λ + 1 steps); stops at 64 (probability < 1e-34)."""
    if u < p0:
        return 0
    p = p0
    f = p0
    k = 0
    while k < _INVERSION_KMAX:
        k += 1
        p *= lam / k
        f += p
        if u < f:
            break
    return k


def poisson_law_table(lam):
    """The cumulative law of Poisson(``lam``) as :func:`poisson_grid_tables` keeps it: ``(F, k_lo, guide)``,
    F[i] = P(N ≤ k_lo + i) (float64 cumulative sum from k = 0 of p_k ∝ λ^k/k!, by the recurrences from the mode,
    normalised), from the first k with F(k) ≥ 2⁻⁶⁴ to the first with P(N > k) < 2⁻⁶⁴ (the law outside, < 2⁻⁶⁴ on
    each side, lies below the 2⁻⁵³ grain of the uniforms), and the guide (Chen & Asau's indexed search): guide[g] =
    the first i with F[i] > g/L, L = len(F), so that the inverse of u starts at guide[⌊uL⌋] (≈ 1–2 comparisons)."""
    return _law_arrays(float(lam))


@kernel
def _law_arrays(lam):
    """:func:`poisson_law_table`, compiled (the grid's 511 tables in a few ms)."""
    k_top = np.int64(math.ceil(lam + 30.0 * math.sqrt(lam) + 60.0))
    m = np.int64(lam)  # the mode: p_k by the recurrences p_{k+1} = p_k λ/(k + 1) up and p_{k−1} = p_k k/λ down
    # from it (relative error ≈ steps × 2⁻⁵³; exp(k ln λ − λ − ln k!) term by term has ≈ 1e-12 at λ ≈ 1000),
    # then divided by their sum (the mass left out above k_top is < 1e-80)
    p = np.empty(k_top + 1)
    p[m] = 1.0
    for k in range(m + 1, k_top + 1):
        p[k] = p[k - 1] * (lam / k)
    for k in range(m - 1, -1, -1):
        p[k] = p[k + 1] * ((k + 1) / lam)
    total = 0.0
    for k in range(k_top + 1):
        total += p[k]
    cdf = np.empty(k_top + 1)
    acc = 0.0
    k_lo = -1
    for k in range(k_top + 1):
        p[k] /= total
        acc += p[k]
        cdf[k] = acc
        if k_lo < 0 and acc >= 2.0 ** -64:  # first F ≥ 2⁻⁶⁴
            k_lo = k
    above = 0.0  # P(N > k), summed from the top (no cancellation against 1)
    k_hi = k_top
    for k in range(k_top, -1, -1):
        if above < 2.0 ** -64:
            k_hi = k  # the first (lowest) k with P(N > k) < 2⁻⁶⁴
        else:
            break
        above += p[k]
    c = cdf[k_lo:k_hi + 1].copy()
    n = c.size
    guide = np.empty(n, np.int32)
    i = 0
    for g in range(n):
        while i < n - 1 and not c[i] > g / n:
            i += 1
        guide[g] = i
    return c, k_lo, guide


@kernel
def table_inverse(u, cdf, c0, n, guide, g0):
    """The index i (0 … n − 1) of the first entry cdf[c0 + i] > u, from the guide guide[g0 + ⌊u n⌋]
    (:func:`poisson_law_table`); n − 1 when u is at or above the last entry."""
    i = np.int64(guide[g0 + np.int64(u * n)])
    while i < n - 1 and u >= cdf[c0 + i]:
        i += 1
    return i


@lru_cache(maxsize=4)
def poisson_grid_tables(step=POISSON_GRID_STEP, top=POISSON_GRID_MAX):
    """The cumulative laws of Poisson(Λ_j), Λ_j = j·``step`` (j = 1 … top/step − 1), for :func:`poisson_grid`:
    ``(cdf, off, kmin, guide, goff, step)``.  Table j holds F(k) = P(N ≤ k) for k = kmin[j] … kmin[j] + L − 1 in
    cdf[off[j]:off[j + 1]] (L entries), and its guide in guide[goff[j]:goff[j + 1]]: :func:`poisson_law_table`.
    ``step``: a power of two (the rest λ − Λ_j is then exact).  Built once per process (step 2: ≈ 0.2 M entries,
    2.4 MB, 9 ms of CPU)."""
    n_tab = int(top / step)
    return _grid_arrays(float(step), n_tab) + (float(step),)


@kernel
def _grid_arrays(step, n_tab):
    """:func:`poisson_grid_tables`' arrays in one compiled call (a call per table cost ≈ 60 µs)."""
    laws = [_law_arrays(step * j) for j in range(1, n_tab)]
    off = np.zeros(n_tab + 1, np.int64)
    kmin = np.zeros(n_tab, np.int64)
    for j in range(1, n_tab):
        off[j + 1] = off[j] + laws[j - 1][0].size
        kmin[j] = laws[j - 1][1]
    cdf = np.empty(off[n_tab])
    guide = np.empty(off[n_tab], np.int32)
    for j in range(1, n_tab):
        cdf[off[j]:off[j + 1]] = laws[j - 1][0]
        guide[off[j]:off[j + 1]] = laws[j - 1][2]
    return cdf, off, kmin, guide, off.copy()


#: 1/m for the rest's inversion in :func:`poisson_grid` (a multiply instead of a divide per step).
_RECIPROCALS = 1.0 / np.maximum(np.arange(_INVERSION_KMAX + 1, dtype=np.float64), 1.0)
#: A rest r has N₂ = 0 without its exp when u2 < (1 − r) − this (e^(−r) ≥ 1 − r; the roundings are < 2⁻⁵⁰).
_ZERO_MARGIN = 2.0 ** -40


@kernel
def poisson_grid(lam, u1, u2, cdf, off, kmin, guide, goff, step):
    """Poisson(``lam``), ``step`` ≤ lam < POISSON_GRID_MAX, from two independent uniforms in [0, 1): N = N₁ + N₂
    with N₁ ~ Poisson(Λ), Λ = step·⌊lam/step⌋, by inversion of ``u1`` on the table of Λ
    (:func:`poisson_grid_tables`), and N₂ ~ Poisson(r), r = lam − Λ < step (exact in float64 by Sterbenz's
    lemma), by inversion of ``u2`` (the recurrence of :func:`poisson_inversion` with e^(−r)).  Exact in
    distribution (a sum of independent Poisson numbers is Poisson of the summed mean) up to the float64
    round-off of the cumulative laws and the 2⁻⁵³ grain of the uniforms; ≈ 2 table reads and ≈ r + 1 steps."""
    j = np.int64(lam / step)
    k = kmin[j] + table_inverse(u1, cdf, off[j], off[j + 1] - off[j], guide, goff[j])
    r = lam - step * j
    if r > 0.0 and not u2 < (1.0 - r) - _ZERO_MARGIN:  # (else N₂ = 0: u2 < 1 − r ≤ e^(−r), no exp needed)
        p = math.exp(-r)
        if u2 >= p:
            f = p
            m = 0
            while m < _INVERSION_KMAX:
                m += 1
                p *= r * _RECIPROCALS[m]
                f += p
                if u2 < f:
                    break
            k += m
    return k


@kernel
def stream_uniform53(key, word):
    """The 53-bit uniform (w ≫ 11)·2⁻⁵³ ∈ [0, 1) of word ``word`` of the SplitMix64 stream ``key``
    (w = mix(key + (word + 1)·γ), :mod:`.code_tables`; docs/receiver.md)."""
    w = splitmix64_mix(key + np.uint64(word + 1) * SPLITMIX_GAMMA)
    return np.float64(w >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@lru_cache(maxsize=16)
def scalar_poisson_table(lam):
    """:func:`poisson_law_table` of one mean (the chain's background and surface dark per bin), kept for the next
    frames of a run."""
    return poisson_law_table(lam)


#: :func:`poisson_stream` tabulates means up to this (the table spans ≈ 2·9.5·√λ + 10 entries).
SCALAR_TABLE_MAX = 1e6


@kernel
def _poisson_table_stream(key, word0, out, cdf, k_lo, guide):
    """out[t] = k_lo + the inverse of the 53-bit uniform of word word0 + t of the stream ``key`` on ``cdf``."""
    n = cdf.size
    for t in range(out.size):
        out[t] = k_lo + table_inverse(stream_uniform53(key, word0 + t), cdf, 0, n, guide, 0)


def poisson_stream(lam, n, key, word0, rng):
    """n Poisson(``lam``) numbers (float64; one scalar mean) by inversion of the uniforms of words word0 …
    word0 + n − 1 of the counter-based stream ``key`` on the tabulated law (:func:`scalar_poisson_table`): exact
    to float64 round-off, ≈ 3 ns a number against NumPy's 10–90 ns; means above SCALAR_TABLE_MAX by
    ``rng.poisson``."""
    out = np.empty(n)
    if not lam > 0:
        out[:] = 0.0
    elif lam <= SCALAR_TABLE_MAX:
        cdf, k_lo, guide = scalar_poisson_table(float(lam))
        _poisson_table_stream(np.uint64(key), word0, out, cdf, k_lo, guide)
    else:
        out[:] = rng.poisson(lam, n)
    return out


def poisson_dense(lam, rng):
    """Exact Poisson per element (float64 means); normal with exact moments above NORMAL_MEAN.
    Returns (float64 counts, number of normal-approximated elements)."""
    lam = np.asarray(lam, dtype=np.float64)
    big = lam >= NORMAL_MEAN
    nb = int(np.count_nonzero(big))
    if not nb:
        return rng.poisson(lam).astype(np.float64), 0
    res = np.empty_like(lam)
    res[~big] = rng.poisson(lam[~big])
    lb = lam[big]
    res[big] = np.maximum(np.rint(lb + np.sqrt(lb) * rng.standard_normal(lb.size)), 0.0)
    return res, nb


def poisson_uniform_rows(mean_per_bin, n_rows, n_bins, rng, out=None):
    """Exact Poisson counts with the same mean in every bin of a row (background, bulk dark): the total per row
    is Poisson(B·mean) and the events fall uniformly on the row's bins (multinomial with equal cells = uniform
    indices).  ``mean_per_bin`` scalar or (n_rows,).  Accumulates into / returns float32 (n_rows, n_bins)."""
    if out is None:
        out = np.zeros((n_rows, n_bins), dtype=np.float32)
    m = np.broadcast_to(np.asarray(mean_per_bin, dtype=np.float64), (n_rows,))
    dense = m >= DENSE_MEAN
    if dense.any():
        rows = np.flatnonzero(dense)
        lam = np.repeat(m[rows], n_bins).reshape(len(rows), n_bins)
        out[rows] += poisson_dense(lam, rng)[0].astype(np.float32)
    sparse = ~dense & (m > 0)
    if sparse.any():
        rows = np.flatnonzero(sparse)
        k = rng.poisson(m[rows] * n_bins)
        tot = int(k.sum())
        if tot:
            pos = rng.integers(0, n_bins, size=tot, dtype=np.int64)
            pos += np.repeat(rows.astype(np.int64) * n_bins, k)
            oflat = out.reshape(-1)
            if tot * 50 < oflat.size:
                np.add.at(oflat, pos, 1.0)
            else:
                np.add(oflat, np.bincount(pos, minlength=oflat.size), out=oflat, casting="unsafe")
    return out


def gamma_gain(primaries, gain, excess_noise, rng, out=None):
    """Multiplied electrons for ``primaries`` photo-electrons per bin (docs/theory.md §8, linear-mode APD).

    Each primary is multiplied by an independent gain of mean G and variance G²(F − 1) (gamma-distributed
    single-electron gain); the sum of n of them is exactly Gamma(n/(F−1), scale G(F−1)): mean G n, variance
    G²(F−1) n, so with Poisson n the total has variance G² F N̄ (the §8 formula).  F = 1 → G n exactly.
    Only non-zero bins are drawn.  Works for integer counts and for continuous means (shot noise off).
    ``out`` may be ``primaries`` itself (in place).
    """
    p = np.asarray(primaries, dtype=np.float32)
    if out is None:
        out = np.empty(p.shape, dtype=np.float32)
    if excess_noise <= 1.0 + 1e-12:
        np.multiply(p, np.float32(gain), out=out)
        return out
    theta = gain * (excess_noise - 1.0)
    a = 1.0 / (excess_noise - 1.0)
    pf, of = p.reshape(-1), out.reshape(-1)
    mask = pf != 0  # boolean masks: nonzero/count on a bool array is ~10x faster than on floats
    if np.count_nonzero(mask) * 2 > pf.size:  # dense: draw every bin (Gamma(0) = 0 exactly), no index gather
        shape = pf.astype(np.float64)
        shape *= a
        g = rng.standard_gamma(shape)
        g *= theta
        of[...] = g
        return out
    nz = np.flatnonzero(mask)
    shape = pf[nz].astype(np.float64)  # gather before ``out`` (possibly the same memory) is written
    if of is not pf and not np.shares_memory(of, pf):
        of[...] = 0.0
    if nz.size:
        shape *= a
        of[nz] = rng.standard_gamma(shape) * theta
    return out

