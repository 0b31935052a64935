"""The receiver chain's table route (A/D on, docs/receiver.md): a block of the cube drawn from the exact code
distribution of signal-free bins, the bins with signal redrawn given their caught photo-electrons.

Random numbers: counter-based streams (SplitMix64, :mod:`.code_tables`) keyed per block, evaluated inside the
compiled kernels; the few per-bin draws from NumPy generators.  Used by :func:`.chain.apply_receiver_chain`.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ...jit import kernel
from .adc import adc_convert
from .code_tables import (CAUGHT_TABLES, SPLITMIX_GAMMA, CaughtCodeTables, CodeTable, noise_code_pmf, splitmix64_mix,
                          uniform_uint32)
from .samplers import POISSON_INVERSION_MAX, gamma_gain, poisson_dense, poisson_inversion

#: Largest mean number of primaries per bin carried (float32 safe); larger means are clipped and reported.
MEAN_CAP = 1e30
#: Samples (pixels × bins) per block of the table route (larger than the per-bin route's: its per-block work
#: outside the compiled kernels is a fixed ~50 µs).
TABLE_BLOCK_SAMPLES = 1 << 19


@lru_cache(maxsize=4)
def noise_tables(step, b_mult, gain, F, shot, ds, sigma_r, offset, bits, dtype):
    """The code tables of signal-free bins (and of bins that caught 1 … 16 signal photo-electrons, built on
    first use) for these detector numbers: ``(CodeTable, None)``, or ``(None, reason)`` when the distribution
    spans too many codes.  Kept for the next frames of a run (a few detectors at most: bounded cache); the
    tables depend on nothing else, so a kept table gives the same codes as a new one."""
    top = 2 ** bits - 1
    try:
        k0, pmf = noise_code_pmf(step, n_mult=b_mult, gain=gain, excess_noise=F, shot=shot,
                                 surface_dark_e=ds, surface_dark_poisson=shot and ds > 0,
                                 gauss_mean_e=0.0 if shot else ds, gauss_var_e2=sigma_r ** 2)
    except ValueError as exc:
        return None, str(exc)
    table = CodeTable(k0, pmf, offset, top, np.dtype(dtype))
    table.caught = None
    if shot:  # bins that caught 1 … 16 signal photo-electrons: their own tables, built on first use
        table.caught = CaughtCodeTables(
            CAUGHT_TABLES, step, dict(n_mult=b_mult, gain=gain, excess_noise=F, surface_dark_e=ds,
                                       surface_dark_poisson=ds > 0, gauss_var_e2=sigma_r ** 2),
            offset, top, np.dtype(dtype))
    return table, None


def scratch(ws, name, n, dtype):
    """A scratch array of n ``dtype`` from the per-thread dict ``ws`` (kept and reused: fresh large allocations
    are slow)."""
    a = ws.get(name)
    if a is None or a.size < n or a.dtype != dtype:
        a = np.empty(n, dtype=dtype)
        ws[name] = a
    return a[:n]


def block_signal_table(E, new_rng, key, pkey, spk, p, ws, table) -> dict:
    """A block of pixels (P, B), A/D on, table route, first pass: its bins with signal and what they caught; nothing
    is written to the output (:func:`block_codes_table` does that once every block's signal is known).

    Exact decomposition: the primaries of a bin are n = n_s + n_b (independent Poisson, signal and
    background/bulk dark).  Every bin gets a code from ``table`` (the law of a bin with n_s = 0); the signal
    primaries n_s are drawn exactly here for the bins with a non-zero mean, and the bins with n_s > 0 are
    redrawn from the law given n_s: by the tables of ``table.caught`` for n_s ≤ 16 (re-using the bin's uniform,
    which is independent of n_s; listed in ``stats["hits"]`` = (bin indices, counts), all the bins with
    n_s > 0), else per bin (listed in ``stats["tail"]``, drawn by :func:`per_bin_tail` for all blocks at once):
    n_b ~ Poisson, gain Gamma((n_s + n_b)/(F − 1), G(F − 1)), surface dark Poisson, read noise, A/D.  Without
    shot noise every signal bin goes to the tail, and the clip counts of its signal-free code (uniform i of the
    block's stream ``key``) are taken back here.

    Random numbers: n_s of bin i, for means below ``POISSON_INVERSION_MAX``, is the Poisson inversion of the
    53-bit uniform of word i of the counter-based stream ``pkey`` (compiled, :func:`_signal_draws` and
    :func:`_signal_counts`; e^(−λ) only for the bins whose uniform is not below 1 − λ); larger means from the
    generator ``new_rng()``, made only when needed.  A float32 block is also checked for NaN/Inf and negative
    energies by the scan (counts in the stats; the block stops there if any).
    Cost: the scan (≈ 0.35 ns a bin), plus a few ns per bin with signal."""
    P, B = E.shape
    N = P * B
    stats = {"n_mean_clipped": 0, "n_adc_low": 0, "n_adc_high": 0, "normal_bins": 0}
    Ef = E.reshape(-1)
    nz = scratch(ws, "nz", N, np.int64)
    ev = scratch(ws, "ev", N, np.float32)
    invalid = np.zeros(2, np.int64)
    # the bins with signal (compiled: signal-free stretches skipped by SIMD tests) and their energies, and the
    # input check
    nnz = nonzero_index(Ef, nz, invalid, ev)
    if invalid.any():
        stats["n_nonfinite"], stats["n_negative"] = int(invalid[0]), int(invalid[1])
        return stats
    if not nnz:
        return stats
    nz, ev = nz[:nnz], ev[:nnz]
    spk_b = np.empty(0, np.float32) if spk is None else spk
    if p["shot"]:
        lam, p0, u, todo, sig, cnt, big = (scratch(ws, k, nnz, t) for k, t in (
            ("lam", np.float64), ("p0", np.float64), ("u", np.float64), ("todo", np.int64), ("sig", np.int64),
            ("cnt", np.float64), ("big", np.int64)))
        stats["n_mean_clipped"], n_todo = _signal_draws(ev, nz, p["k_sig"], spk_b, B, MEAN_CAP, pkey, lam, u, todo)
        todo = todo[:n_todo]
        p0 = p0[:n_todo]
        np.negative(lam[todo], out=p0)
        np.exp(p0, out=p0)  # e^(−λ) of the undecided signal bins: NumPy's vectorised exp
        n_sig, n_big = _signal_counts(nz, todo, lam, p0, u, sig, cnt, big)
        sig, cnt = sig[:n_sig].copy(), cnt[:n_sig].copy()  # (out of the scratch: kept for the second pass)
        if n_big:  # bright bins: one exact rng.poisson each
            rng = new_rng()
            nb, stats["normal_bins"] = poisson_dense(lam[big[:n_big]], rng)
            hit = nb > 0
            sig = np.concatenate([sig, nz[big[:n_big][hit]]])
            cnt = np.concatenate([cnt, nb[hit]])
        if not sig.size:
            return stats
        stats["hits"] = (sig, cnt)
        over = cnt > table.caught.m_max  # (the bins CaughtCodeTables.apply leaves to the per-bin draws)
        if not over.any():
            return stats
        sig, n = sig[over], cnt[over]
        stats["caught_per_bin"] = int(sig.size)
    else:
        with np.errstate(over="ignore"):
            s = Ef[nz].astype(np.float64)
            s *= p["k_sig"]
            if spk is not None:
                s *= spk[nz // B]
        bad = ~(s <= MEAN_CAP)
        if bad.any():
            stats["n_mean_clipped"] = int(np.count_nonzero(bad))
            s[bad] = MEAN_CAP
        sig = nz.copy()
        n = s + p["b_mult"]
        lo_t, hi_t = table.clipped(uniform_uint32(key, sig))
        stats["n_adc_low"] -= lo_t
        stats["n_adc_high"] -= hi_t
    stats["tail"] = (sig, n)  # drawn by per_bin_tail for all blocks at once
    return stats


def block_codes_table(out, key, table, hits, ws):
    """A block of pixels, table route, second pass: the codes of its signal-free bins from the uniforms of the
    counter-based stream ``key`` (uniform i for bin i: :meth:`CodeTable.sample_stream`, made inside the compiled
    sampler), then, for the bins in ``hits`` (bin indices, caught counts ≥ 1; None: none), the codes given the
    caught count from ``table.caught`` with the bin's same uniform (independent of the count), in place of the
    signal-free ones; bins with more than m_max are left to :func:`per_bin_tail` (their signal-free clip
    counts taken back).  Returns (n_low, n_high, bins coded from the caught-count tables).
    Cost: one table look-up per bin (its uniform ≈ 0.3 ns), a few ns per bin in ``hits``."""
    of = out.reshape(-1)
    n_low, n_high = table.sample_stream(key, of)
    if hits is None:
        return n_low, n_high, 0
    sig, cnt = hits
    rest = scratch(ws, "rest", sig.size, np.int64)
    d_low, d_high, n_tab, _ = table.caught.apply(sig, cnt, key, table, of, rest)
    return n_low + d_low, n_high + d_high, n_tab


def per_bin_tail(n, p, rng):
    """Table route: the codes of the bins drawn per bin, for all blocks at once (a few calls instead of a few per
    block; the caller writes them into the output).  With shot noise ``n`` holds the signal primaries (> 16): n_b ~ Poisson
    is added; without, the continuous mean of all primaries.  Then gain Gamma(n/(F − 1), G(F − 1)), surface dark
    (Poisson with shot noise), read noise, A/D.  Returns (codes, n_low, n_high)."""
    if p["shot"] and p["b_mult"] > 0:
        n = n + rng.poisson(p["b_mult"], n.size)
    y = gamma_gain(n.astype(np.float32), p["gain"], p["F"], rng).astype(np.float64)
    if p["ds"] > 0:
        y += rng.poisson(p["ds"], n.size) if p["shot"] else p["ds"]
    if p["sigma_r"] > 0:
        y += p["sigma_r"] * rng.standard_normal(n.size)
    return adc_convert(y, p["bits"], p["fs"], p["offset"])


#: The count of a signal bin is 0 without computing e^(−λ) when its uniform u < (1 − λ) − this: e^(−λ) ≥ 1 − λ
#: for every λ, and the float64 roundings of 1 − λ and of NumPy's exp (a few ulp of numbers ≤ 1: < 2⁻⁵⁰) are
#: far below the margin, so u < e^(−λ) as computed; the decision is the same as with the exp.
_ZERO_MARGIN = 2.0 ** -40


@kernel
def _signal_draws(ev, idx, k_sig, spk, n_bins, cap, pkey, lam, u, todo):
    """The signal bins idx of a block, energies ``ev``: lam[q] = their mean signal primaries (ev·k_sig in
    float64, × the pixel's speckle factor when ``spk`` is not empty, clipped to ``cap``); u[q] = the 53-bit
    uniform (w ≫ 11)·2⁻⁵³ of word idx[q] of the counter-based stream ``pkey``; ``todo`` = the positions q whose
    Poisson count is not already known to be 0 by u < (1 − λ) − :data:`_ZERO_MARGIN` (so e^(−λ) is computed
    for those only).
    Returns (number of means clipped, number of positions in todo)."""
    n_clip = 0
    for q in range(idx.size):
        s = np.float64(ev[q]) * k_sig
        if spk.size:
            s *= spk[idx[q] // n_bins]
        if not s <= cap:
            s = cap
            n_clip += 1
        lam[q] = s
    for q in range(idx.size):  # (a loop of its own: vectorised)
        w = splitmix64_mix(pkey + np.uint64(idx[q] + 1) * SPLITMIX_GAMMA)
        u[q] = np.float64(w >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    n_todo = 0
    for q in range(idx.size):
        if not u[q] < (1.0 - lam[q]) - _ZERO_MARGIN:
            todo[n_todo] = q
            n_todo += 1
    return n_clip, n_todo


@kernel
def _signal_counts(idx, todo, lam, p0, u, sig, cnt, big):
    """Poisson counts of the signal bins at the positions ``todo`` (in order; the others have count 0), with
    means lam[q], uniforms u[q] and p0[t] = e^(−lam[todo[t]]): below POISSON_INVERSION_MAX by
    :func:`poisson_inversion`; the bins with a count > 0 listed in ``sig`` (bin index idx[q]) and ``cnt`` (float64
    count); larger means listed in ``big`` (position q) for ``rng.poisson``.  Returns (n_sig, n_big)."""
    n_sig = 0
    n_big = 0
    for t in range(todo.size):
        q = todo[t]
        s = lam[q]
        if s >= POISSON_INVERSION_MAX:
            big[n_big] = q
            n_big += 1
        elif u[q] >= p0[t]:  # (count 0 otherwise: decided without a call)
            sig[n_sig] = idx[q]
            cnt[n_sig] = poisson_inversion(s, p0[t], u[q])
            n_sig += 1
    return n_sig, n_big


@kernel
def nonzero_index(x, idx, invalid=None, values=None):
    """The indices of the non-zero elements of the 1-D ``x`` into ``idx`` (as np.flatnonzero); returns how
    many.  Blocks of 64 elements are tested with one vectorised count first: zero blocks cost no branch.
    ``invalid`` (int64 (2,), optional): adds the number of NaN/±Inf elements to invalid[0] and of negative
    finite ones to invalid[1] (the chain's input check, in the same pass: a stretch of zeros holds neither).
    ``values`` (optional, like ``idx``): the non-zero elements themselves, values[k] = x[idx[k]]."""
    n = x.size
    m = 0
    for q in range(n // 64 + 1):
        j0 = q * 64
        if j0 + 64 <= n:
            c = 0
            for k in range(64):  # fixed trip count: compiled to SIMD compares
                c += x[j0 + k] != 0  # (NaN, ±Inf and negatives are non-zero: checked below)
            if c == 0:
                continue
        for j in range(j0, min(j0 + 64, n)):
            xj = x[j]
            if xj != 0:
                idx[m] = j
                if values is not None:
                    values[m] = xj
                m += 1
            if invalid is not None:
                if not (xj == xj and abs(xj) < np.inf):
                    invalid[0] += 1
                elif xj < 0:
                    invalid[1] += 1
    return m
