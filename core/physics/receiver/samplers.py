"""Exact fast samplers for the receiver chain: sparse and dense Poisson counts, APD gain with excess noise."""
from __future__ import annotations

import numpy as np

from ...jit import kernel

#: Bins whose Poisson mean is at least this are drawn with ``rng.poisson`` per bin (exact); below it the
#: events are placed sparsely (exact).  Pure speed trade-off, no approximation.
DENSE_MEAN = 8.0
#: Poisson means above this are drawn as a normal with the exact mean and variance (relative skewness error
#: 1/sqrt(mean) < 3e-4); far beyond any ADC full scale in practice.
NORMAL_MEAN = 1e7
#: Poisson means below this are drawn by :func:`poisson_inversion` (compiled, one uniform each); larger ones by
#: ``rng.poisson``.  Pure speed trade-off (the inversion walks ≈ mean + 1 terms), no approximation.
POISSON_INVERSION_MAX = 8.0
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

