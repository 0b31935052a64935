"""The receiver chain's table route (A/D on, docs/receiver.md): a block of the cube drawn from the exact code
distribution of signal-free bins, the bins with signal redrawn given their caught photo-electrons.

Random numbers: counter-based streams (SplitMix64, :mod:`.code_tables`) keyed per block, evaluated inside the
compiled kernels; the few per-bin draws from NumPy generators.  Used by :func:`.chain.apply_receiver_chain`.
"""
from __future__ import annotations

import threading
from functools import lru_cache

import numpy as np

from ...jit import kernel
from .adc import adc_convert
from .code_tables import (CAUGHT_TABLES, SPLITMIX_GAMMA, CaughtCodeTables, CodeTable, noise_code_pmf, splitmix64_mix,
                          uniform_uint32)
from .conversions import adc_step_e
from .samplers import (POISSON_GRID_MAX, POISSON_INVERSION_MAX, SCALAR_TABLE_MAX, gamma_gain, poisson_dense,
                       poisson_grid, poisson_grid_tables, poisson_inversion, poisson_stream, scalar_poisson_table,
                       stream_uniform53, table_inverse)

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


def process_block_table(E, out, new_rng, key, pkey, spk, p, ws, table) -> dict:
    """One block of pixels (P, B), A/D on, with the tabulated code distribution of signal-free bins.

    Exact decomposition: the primaries of a bin are n = n_s + n_b (independent Poisson, signal and
    background/bulk dark).  Every bin first gets a code from ``table`` (the law of a bin with n_s = 0); then
    the signal primaries n_s are drawn exactly for the bins with a non-zero mean and the bins with n_s > 0 are
    redrawn from the law given n_s: by the tables of ``table.caught`` for n_s ≤ 16 (re-using the bin's uniform,
    which is independent of n_s), else per bin (listed in ``stats["tail"]``, drawn by :func:`per_bin_tail` for
    all blocks at once): n_b ~ Poisson, gain Gamma((n_s + n_b)/(F − 1), G(F − 1)), surface dark Poisson, read
    noise, A/D.

    Random numbers: the uniform of bin i is number i of the counter-based stream ``key`` (:func:`uniform_uint32`):
    made inside the compiled sampler and recomputed from i for the bins with signal; n_s of bin i, for means
    below ``POISSON_INVERSION_MAX``, is the Poisson inversion of the 53-bit uniform of word i of the stream
    ``pkey`` (compiled, :func:`_signal_draws` and :func:`_signal_counts`; e^(−λ) only for the bins whose uniform
    is not below 1 − λ); larger means from the generator ``new_rng()``, made only when needed.  A float32 block
    is also checked for NaN/Inf and negative energies by the scan (counts in the stats; the block stops there if
    any).
    Cost: one table look-up per bin (its uniform ~0.2 ns), plus a few ns per bin with signal."""
    P, B = E.shape
    N = P * B
    stats = {"n_mean_clipped": 0, "n_adc_low": 0, "n_adc_high": 0, "normal_bins": 0}
    of = out.reshape(-1)
    stats["n_adc_low"], stats["n_adc_high"] = table.sample_stream(key, of)
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
        stats["n_mean_clipped"], n_todo, n_inv = _signal_draws(ev, nz, p["k_sig"], spk_b, B, MEAN_CAP, pkey, lam, u,
                                                               todo, p0)
        todo = todo[:n_todo]
        p0 = p0[:n_inv]
        np.exp(p0, out=p0)  # e^(−λ) of the undecided bins drawn by inversion (only): NumPy's vectorised exp
        n_sig, n_big = _signal_counts(nz, todo, lam, p0, u, sig, cnt, big, pkey, *poisson_grid_tables())
        sig, cnt = sig[:n_sig], cnt[:n_sig]
        if n_big:  # means ≥ POISSON_GRID_MAX: one exact rng.poisson each
            rng = new_rng()
            nb, stats["normal_bins"] = poisson_dense(lam[big[:n_big]], rng)
            hit = nb > 0
            sig = np.concatenate([sig, nz[big[:n_big][hit]]])
            cnt = np.concatenate([cnt, nb[hit]])
        if not sig.size:
            return stats
        # codes given the caught count, from the tables (the bin's uniform again: independent of n), in place of
        # the signal-free codes; the bins that caught more than m_max go on to the per-bin draws below
        rest = scratch(ws, "rest", sig.size, np.int64)
        d_low, d_high, n_tab, n_rest = table.caught.apply(sig, cnt, key, table, of, rest)
        stats["n_adc_low"] += d_low
        stats["n_adc_high"] += d_high
        if n_tab:
            stats["caught_table"] = n_tab
        if not n_rest:
            return stats
        sig, n = sig[rest[:n_rest]], cnt[rest[:n_rest]]
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
    stats["tail"] = (sig, n)  # drawn by per_bin_tail once all blocks are done
    return stats


def per_bin_tail(idx, n, p, rng, of):
    """Table route: the bins ``idx`` (in the cube) whose code is drawn per bin, for all blocks at once (a few
    calls instead of a few per block).  With shot noise ``n`` holds the signal primaries (> 16): n_b ~ Poisson
    is added; without, the continuous mean of all primaries.  Then gain Gamma(n/(F − 1), G(F − 1)), surface dark
    (Poisson with shot noise), read noise, A/D; codes written into ``of``.  Returns (n_low, n_high)."""
    # the Poisson numbers (background + bulk dark primaries, surface dark electrons) from a counter-based stream
    # keyed by the part's generator (:func:`.samplers.poisson_stream`), the gains, read noise from the generator
    key = rng.integers(0, 2 ** 64, dtype=np.uint64) if p["shot"] and (p["b_mult"] > 0 or p["ds"] > 0) else None
    if (p["shot"] and p["F"] > 1.0 + 1e-12 and p["bits"] <= 23 and p["b_mult"] <= SCALAR_TABLE_MAX
            and p["ds"] <= SCALAR_TABLE_MAX and n.size):
        return _fused_tail(idx, n, p, rng, key, of)
    return _numpy_tail(idx, n, p, rng, key, of)


def _numpy_tail(idx, n, p, rng, key, of):
    """:func:`per_bin_tail` as NumPy passes: the cases :func:`_fused_tail` does not take, and the reference it
    is tested against (tests/core/physics/receiver/test_fused_tail.py)."""
    if p["shot"] and p["b_mult"] > 0:
        n = n + poisson_stream(p["b_mult"], n.size, key, 0, rng)
    y = gamma_gain(n.astype(np.float32), p["gain"], p["F"], rng).astype(np.float64)
    if p["ds"] > 0:
        y += poisson_stream(p["ds"], n.size, key, n.size, rng) if p["shot"] else p["ds"]
    if p["sigma_r"] > 0:
        y += p["sigma_r"] * rng.standard_normal(n.size)
    codes, lo, hi = adc_convert(y, p["bits"], p["fs"], p["offset"])
    of[idx] = codes
    return lo, hi


def _fused_tail(idx, n, p, rng, key, of):
    """:func:`per_bin_tail` with shot noise, excess noise (F > 1) and an A/D of ≤ 23 bits (float32 work, as
    :func:`.adc.adc_convert`): the same numbers in two compiled passes around NumPy's ``standard_gamma`` and
    ``standard_normal`` (the generator's calls and their order unchanged): no temporaries, no NumPy passes.
    Codes written into ``of``; returns (n_low, n_high)."""
    a, theta = 1.0 / (p["F"] - 1.0), p["gain"] * (p["F"] - 1.0)
    tb = _stream_table(p["b_mult"]) if p["b_mult"] > 0 else None
    td = _stream_table(p["ds"]) if p["ds"] > 0 else None
    k = np.uint64(0 if key is None else key)
    ws = _tail_scratch()
    shape = scratch(ws, "shape", n.size, np.float64)
    _tail_shapes(n, a, k, *(tb if tb is not None else _NO_TABLE), tb is not None, shape)
    g = rng.standard_gamma(shape, out=shape)  # (in place: the same numbers as a new array)
    z = shape[:0]
    if p["sigma_r"] > 0:
        z = rng.standard_normal(out=scratch(ws, "z", n.size, np.float64))
    step = adc_step_e(p["bits"], p["fs"])
    lo, hi = _tail_codes(idx, g, theta, k, *(td if td is not None else _NO_TABLE), td is not None, n.size,
                         float(p["sigma_r"]), z, np.float32(1.0 / step), np.float32(p["offset"]),
                         p["offset"] != 0, float(2 ** int(p["bits"]) - 1), of)
    return int(lo), int(hi)


_TAIL_SCRATCH = threading.local()


def _tail_scratch() -> dict:
    """This thread's scratch arrays of :func:`_fused_tail` (kept: fresh 2 MB arrays cost their page faults)."""
    ws = getattr(_TAIL_SCRATCH, "ws", None)
    if ws is None:
        ws = _TAIL_SCRATCH.ws = {}
    return ws


#: (cdf, k_lo, guide) standing in for an absent Poisson table (never read).
_NO_TABLE = (np.ones(1), 0, np.zeros(1, np.int32))


def _stream_table(lam):
    return scalar_poisson_table(float(lam))


@kernel
def _tail_shapes(n, a, key, cdf, k_lo, guide, add, shape):
    """shape[t] = float64(float32(n[t] + N_b)) · a, N_b the Poisson number of word t of the stream ``key`` on the
    tabulated law (``add``; :func:`.samplers.poisson_stream`): per_bin_tail's gamma shapes, the same roundings."""
    m = cdf.size
    for t in range(n.size):
        x = n[t]
        if add:
            x = x + np.float64(k_lo + table_inverse(stream_uniform53(key, t), cdf, 0, m, guide, 0))
        shape[t] = np.float64(np.float32(x)) * a


@kernel
def _tail_codes(idx, g, theta, key, cdf, k_lo, guide, add, word0, sigma, z, inv_step, offset, has_offset, top, of):
    """of[idx[t]] = the A/D code of float64(float32(g[t]·θ)) (+ the Poisson number of word word0 + t of the stream
    ``key`` when ``add``) (+ σ·z[t] when z is not empty), converted as :func:`.adc.adc_convert` does in float32.
    Returns (n_low, n_high)."""
    m = cdf.size
    n_low = 0
    n_high = 0
    for t in range(g.size):
        y = np.float64(np.float32(g[t] * theta))
        if add:
            y = y + np.float64(k_lo + table_inverse(stream_uniform53(key, word0 + t), cdf, 0, m, guide, 0))
        if z.size:
            y = y + sigma * z[t]
        w = np.rint(np.float32(y) * inv_step)
        if has_offset:
            w = w + offset
        if w < 0:
            n_low += 1
            w = np.float32(0.0)
        elif w > top:
            n_high += 1
            w = np.float32(top)
        of[idx[t]] = w
    return n_low, n_high


#: Word offset of the second uniform of a signal bin whose mean is drawn by :func:`.samplers.poisson_grid`: word
#: i + 2⁴⁰ of the stream of the signal counts (word i: the first; i < 2⁴⁰ is a bin's index in its block).
SECOND_WORD = 1 << 40

#: The count of a signal bin is 0 without computing e^(−λ) when its uniform u < (1 − λ) − this: e^(−λ) ≥ 1 − λ
#: for every λ, and the float64 roundings of 1 − λ and of NumPy's exp (a few ulp of numbers ≤ 1: < 2⁻⁵⁰) are
#: far below the margin, so u < e^(−λ) as computed; the decision is the same as with the exp.
_ZERO_MARGIN = 2.0 ** -40


@kernel
def _signal_draws(ev, idx, k_sig, spk, n_bins, cap, pkey, lam, u, todo, neg_lam):
    """The signal bins idx of a block, energies ``ev``: lam[q] = their mean signal primaries (ev·k_sig in
    float64, × the pixel's speckle factor when ``spk`` is not empty, clipped to ``cap``); u[q] = the 53-bit
    uniform (w ≫ 11)·2⁻⁵³ of word idx[q] of the counter-based stream ``pkey``; ``todo`` = the positions q whose
    Poisson count is not already known to be 0 by u < (1 − λ) − :data:`_ZERO_MARGIN`; ``neg_lam`` = −λ of
    those of them below POISSON_INVERSION_MAX, in todo's order (e^(−λ) is computed for these only: the
    larger means are drawn without it, :func:`_signal_counts`).
    Returns (number of means clipped, number of positions in todo, number in neg_lam)."""
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
    n_inv = 0
    for q in range(idx.size):
        if not u[q] < (1.0 - lam[q]) - _ZERO_MARGIN:
            todo[n_todo] = q
            n_todo += 1
            if lam[q] < POISSON_INVERSION_MAX:
                neg_lam[n_inv] = -lam[q]
                n_inv += 1
    return n_clip, n_todo, n_inv


@kernel
def _signal_counts(idx, todo, lam, p0, u, sig, cnt, big, pkey, cdf, off, kmin, guide, goff, step):
    """Poisson counts of the signal bins at the positions ``todo`` (in order; the others have count 0), with
    means lam[q], uniforms u[q] and p0 = e^(−λ) of the positions in todo with a mean below POISSON_INVERSION_MAX,
    in order (:func:`_signal_draws`): below POISSON_INVERSION_MAX by
    :func:`poisson_inversion`, below POISSON_GRID_MAX by :func:`poisson_grid` (u[q] and the 53-bit uniform of word
    idx[q] + SECOND_WORD of the stream ``pkey``; the grid tables: :func:`poisson_grid_tables`); the bins with a
    count > 0 listed in ``sig`` (bin index idx[q]) and ``cnt`` (float64 count); larger means listed in ``big``
    (position q) for ``rng.poisson``.  Returns (n_sig, n_big)."""
    n_sig = 0
    n_big = 0
    i = 0  # position in p0 of the next bin drawn by inversion
    for t in range(todo.size):
        q = todo[t]
        s = lam[q]
        if s >= POISSON_GRID_MAX:
            big[n_big] = q
            n_big += 1
        elif s >= POISSON_INVERSION_MAX:
            k = poisson_grid(s, u[q], stream_uniform53(pkey, idx[q] + SECOND_WORD), cdf, off, kmin, guide, goff,
                             step)
            if k > 0:
                sig[n_sig] = idx[q]
                cnt[n_sig] = k
                n_sig += 1
        else:
            if u[q] >= p0[i]:  # (count 0 otherwise: decided without a call)
                sig[n_sig] = idx[q]
                cnt[n_sig] = poisson_inversion(s, p0[i], u[q])
                n_sig += 1
            i += 1
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
