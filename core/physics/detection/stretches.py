"""Noisy echo detection without simulating the signal-free stretches bin by bin (detection.signal_free_bins =
"statistical", docs/receiver.md "Detector models").

The reference (``per_bin``) runs the receiver chain on every bin of the cube and detects on every row.  Here, per
pixel, only the stretch that holds signal is simulated per bin: C = [first − g, last + g] around the pixel's signal
bins (expected signal above ``SIGNAL_LEVEL_SIGMA`` of the noise σ), g = h + 1 for a filter of half-width h, and
the window S = C widened by another h + 1 bins, so that the detection waveform and its neighbours at every bin of C
are those of the whole row; detections are taken in C only.  Outside C no bin's detection triple sees signal, so
the filtered noise there is stationary (white raw noise through the filter, 'nearest' edges at the gate's ends):
its false alarms are drawn from the exact Gaussian statistics —

* count per pixel ~ Poisson(Σ_{j ∉ C} p_j), p_j = P(bin j is a local maximum of the detection waveform above the
  threshold) (:func:`core.physics.detection.false_alarms.local_max_probability`, the filter's covariance at
  position j; edges position by position).  The mean is exact; the Poisson law is the clumping limit (maxima
  above a high threshold rare and nearly independent);
* positions from p_j (inverse CDF over the pixel's bins outside C);
* the three samples (Z−, Z0, Z+) around each from the Gaussian conditional on a local maximum above u: Z0 from
  the normal truncated at u, (Z−, Z+) | Z0 bivariate normal, rejected unless Z− < Z0 ≥ Z+ (exact).

Then, per pixel, the candidates of C and of the draw are chosen as the reference kernel chooses (greedy by
amplitude with the minimum separation, at most max_echoes, in time order) and interpolated the same way.

Valid when the raw noise is white and the *filtered* noise Gaussian at the threshold: :func:`validity` uses the
Edgeworth expansion of the tail with the filtered skewness γ₁ Σw³/(Σw²)^{3/2} and excess kurtosis γ₂ Σw⁴/(Σw²)²
and accepts a relative tail error ≤ ``GAUSSIAN_TAIL_TOLERANCE``.  Multiplied background (APD with excess noise)
and Geiger histograms are skewed: they stay on the per-bin route.
"""
from __future__ import annotations

import hashlib
import math
import os
import tempfile

import numpy as np

from ...jit import CACHE_DIR, cpu_key, kernel
from .false_alarms import filter_rows, local_max_probability, row_extents
from .matched_filter import FILTER_BLOCK, correlate_row
from .noisy import NoisyEchoes, echoes_from_slots, run_row_chunks

#: Signal bins: expected signal above this fraction of the raw noise σ.
SIGNAL_LEVEL_SIGMA = 1e-3
#: Largest relative error of the Gaussian tail at the threshold (Edgeworth estimate) for the statistical route.
GAUSSIAN_TAIL_TOLERANCE = 0.02
#: Shortest window: windows are powers of two from this many bins (rows of equal length go through the chain
#: together: a few chain calls a frame).
WINDOW_QUANTUM = 32


def filter_taps(pulse):
    """The detection filter's taps w = pulse/Σpulse² as the noisy kernel uses them (float32 values)."""
    k = np.asarray(pulse, dtype=np.float64)
    return (k / np.sum(k * k)).astype(np.float32).astype(np.float64)


def filtered_noise_shape(cumulants, pulse):
    """(σ of the detection waveform, its skewness, its excess kurtosis) for white raw noise with per-bin cumulants
    [κ1, κ2, κ3, κ4] through the taps w: σ² = κ2 Σw², γ₁ = κ3 Σw³/(κ2 Σw²)^{3/2}, γ₂ = κ4 Σw⁴/(κ2 Σw²)²."""
    _, k2, k3, k4 = (float(c) for c in cumulants)
    w = np.ones(1) if pulse is None else filter_taps(pulse)
    s2 = k2 * np.sum(w ** 2)
    return math.sqrt(s2), k3 * np.sum(w ** 3) / s2 ** 1.5, k4 * np.sum(w ** 4) / s2 ** 2


def gaussian_tail_error(z, skewness, excess_kurtosis):
    """Relative error of the Gaussian tail Q(z) at z σ by the Edgeworth expansion (first two orders):
    φ(z)[γ₁ He₂(z)/6 + γ₂ He₃(z)/24 + γ₁² He₅(z)/72]/Q(z)."""
    from scipy.special import ndtr
    z = float(z)
    he2, he3, he5 = z * z - 1, z ** 3 - 3 * z, z ** 5 - 10 * z ** 3 + 15 * z
    phi = math.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    corr = skewness * he2 / 6 + excess_kurtosis * he3 / 24 + skewness ** 2 * he5 / 72
    return phi * corr / float(ndtr(-z))


def validity(report: dict, det, pulse, k_sigma: float, threshold_mode: str, saves_counts: bool, has_law=False):
    """(route that runs: "statistical" or "per_bin", reason, Edgeworth tail error or None).  ``has_law``: the
    chain's exact code law of a signal-free bin is known (table route): any white noise law is then handled exactly
    (:class:`LatticeRates`); without it (A/D off) the Gaussian model must hold within GAUSSIAN_TAIL_TOLERANCE."""
    if saves_counts:
        return "per_bin", "run.save_counts: the counts of every bin are kept (counts.npy)", None
    if det.detector_type == "geiger":
        return "per_bin", ("Geiger histograms: counts of detections with dead time, no linear noise model (the "
                           "calibrated threshold falls back to adaptive)"), None
    if threshold_mode != "calibrated":
        return "per_bin", f"threshold mode {threshold_mode!r} (the statistical route needs the calibrated one)", None
    if det.enable_optics_mtf or (det.speckle_dof > 0 and det.speckle_correlated):
        return "per_bin", "optics MTF / correlated speckle couple the pixels", None
    if has_law:
        return "statistical", ("signal stretches per bin, signal-free false alarms from the exact code law "
                               "(importance sampling)"), None
    cum = report.get("noise_cumulants")
    if cum is None or not cum[1] > 0:
        return "per_bin", "no noise model", None
    _, g1, g2 = filtered_noise_shape(cum, pulse)
    err = gaussian_tail_error(k_sigma, g1, g2)
    if abs(err) > GAUSSIAN_TAIL_TOLERANCE:
        return "per_bin", (f"filtered noise not Gaussian at {k_sigma:g} σ: Edgeworth tail error {err:+.3f} "
                           f"(skewness {g1:.3g}, excess kurtosis {g2:.3g}; tolerance {GAUSSIAN_TAIL_TOLERANCE})"), err
    return "statistical", "signal stretches per bin, signal-free stretches from the Gaussian statistics", err


def signal_windows(truth, level, h, n_bins, threads=1, extents=None):
    """Per pixel: (C lo, C hi) half-open, clamped to [1, B − 1] (lo = hi: no signal), the window's start and
    length (0: nothing to simulate; lengths are powers of two from WINDOW_QUANTUM, or B), of the signal bins
    truth > level (see the module docstring).  ``extents``: :func:`row_extents` of these rows at this level."""
    first, last = (row_extents(truth, level, threads) if extents is None else extents)[:2]
    has = first >= 0
    g = h + 1
    c_lo = np.where(has, np.clip(first - g, 1, n_bins - 1), 1)
    c_hi = np.where(has, np.clip(last + g + 1, 1, n_bins - 1), 1)
    c_hi = np.maximum(c_hi, c_lo)
    s_lo = np.maximum(c_lo - (h + 1), 0)
    s_hi = np.minimum(c_hi + (h + 1), n_bins)
    need = np.maximum(s_hi - s_lo, WINDOW_QUANTUM)
    pow2 = (1 << np.ceil(np.log2(need)).astype(np.int64))
    length = np.where(has, np.minimum(pow2, n_bins), 0)
    start = np.where(has, np.minimum(s_lo, n_bins - length), 0)
    return c_lo, c_hi, start, length


@kernel
def _gather_windows(truth, rows, start, out):
    """out[i] = truth[rows[i], start[i]:start[i] + L] as float32 (L = out.shape[1])."""
    L = out.shape[1]
    for i in range(rows.shape[0]):
        r, s = rows[i], start[i]
        for j in range(L):
            out[i, j] = np.float32(truth[r, s + j])


@kernel
def _window_candidates(y, start, c_lo, c_hi, b32, w, thr, cand_bin, cand_s, n_cand):
    """Local maxima above ``thr`` of each window's detection waveform inside its C (absolute bins), with their
    three samples; at most cand_bin.shape[1] per row (n_cand counts all)."""
    n_rows, L = y.shape
    ypad, acc = np.empty(L + w.shape[0] - 1, np.float32), np.empty(FILTER_BLOCK)
    yr, yd = np.empty(L, np.float32), np.empty(L, np.float32)
    t32 = np.float32(thr)
    m = cand_bin.shape[1]
    for r in range(n_rows):
        for i in range(L):
            yr[i] = np.float32(y[r, i])
        if w.shape[0] > 1:
            correlate_row(yr, b32, w, ypad, acc, yd, False)
        else:
            for i in range(L):
                yd[i] = yr[i] - b32
        a = max(c_lo[r] - start[r], 1)
        b = min(c_hi[r] - start[r], L - 1)
        nc = 0
        for j in range(a, b):
            c = yd[j]
            if c > t32 and c > yd[j - 1] and c >= yd[j + 1]:
                if nc < m:
                    cand_bin[r, nc] = start[r] + j
                    cand_s[r, nc, 0], cand_s[r, nc, 1], cand_s[r, nc, 2] = yd[j - 1], c, yd[j + 1]
                nc += 1
        n_cand[r] = nc


@kernel
def _choose(ptr, cbin, cs, min_sep, pos, samples):
    """Per pixel (candidates cbin[ptr[p]:ptr[p+1]], any order): the reference kernel's choice — the strongest
    (ties: the earliest bin), then the next outside ``min_sep`` bins of those taken, …, at most pos.shape[1],
    in time order."""
    P, K = pos.shape
    for p in range(P):
        a, b = ptr[p], ptr[p + 1]
        if a == b:
            continue
        alive = np.ones(b - a, np.bool_)
        n_found = 0
        for k in range(K):
            best = -1
            for q in range(a, b):
                if alive[q - a]:
                    if best < 0 or cs[q, 1] > cs[best, 1] or (cs[q, 1] == cs[best, 1] and cbin[q] < cbin[best]):
                        best = q
            if best < 0:
                break
            pos[p, k] = cbin[best]
            samples[p, k, 0], samples[p, k, 1], samples[p, k, 2] = cs[best, 0], cs[best, 1], cs[best, 2]
            n_found += 1
            for q in range(a, b):
                if alive[q - a] and abs(cbin[q] - cbin[best]) < min_sep:
                    alive[q - a] = False
        for k in range(1, n_found):  # time order (the samples move with their bin)
            v, s0, s1, s2 = pos[p, k], samples[p, k, 0], samples[p, k, 1], samples[p, k, 2]
            q = k - 1
            while q >= 0 and pos[p, q] > v:
                pos[p, q + 1] = pos[p, q]
                samples[p, q + 1, 0], samples[p, q + 1, 1], samples[p, q + 1, 2] = \
                    samples[p, q, 0], samples[p, q, 1], samples[p, q, 2]
                q -= 1
            pos[p, q + 1] = v
            samples[p, q + 1, 0], samples[p, q + 1, 1], samples[p, q + 1, 2] = s0, s1, s2


def position_classes(n_bins, pulse):
    """(class of each bin position (B,) int, a representative position per class): the matched filter's
    'nearest' edges make positions 1 … h and B − 2 − h … B − 2 each a class of their own; the interior is class 0."""
    h = 0 if pulse is None else len(pulse) // 2
    cls = np.zeros(n_bins, np.int64)
    reps = [min(h + 1, n_bins - 2)]
    for j in range(1, n_bins - 1):
        if j <= h or j >= n_bins - 1 - h:
            cls[j] = len(reps)
            reps.append(j)
    return cls, reps


def position_covariances(n_bins, pulse, sigma):
    """(classes (B,), covariance of (Z_{j−1}, Z_j, Z_{j+1}) per class (n, 3, 3)) of the detection waveform of white
    noise σ through the filter with 'nearest' edges (:func:`position_classes`)."""
    cls, reps = position_classes(n_bins, pulse)
    covs = []
    for j in reps:
        A = filter_rows(n_bins, pulse, [j - 1, j, j + 1])
        covs.append(sigma ** 2 * A @ A.T)
    return cls, np.array(covs)


def _conditional_triples(u, cov, n, rng):
    """n samples of (Z−, Z0, Z+) ~ N(0, cov) conditional on Z0 > u, Z0 > Z−, Z0 ≥ Z+ (rejection; exact)."""
    from scipy.special import ndtr, ndtri
    v0 = cov[1, 1]
    s0 = math.sqrt(v0)
    q = float(ndtr(-u / s0))
    c = np.array([cov[0, 1], cov[2, 1]]) / v0
    S = cov[np.ix_([0, 2], [0, 2])] - np.outer([cov[0, 1], cov[2, 1]], [cov[0, 1], cov[2, 1]]) / v0
    L = np.linalg.cholesky(S + 1e-300 * np.eye(2))
    out = np.empty((0, 3))
    while len(out) < n:
        m = 2 * (n - len(out)) + 16
        z0 = -s0 * ndtri(q * (1.0 - rng.random(m)))  # truncated normal above u: U in (0, 1]
        side = c[None, :] * z0[:, None] + rng.standard_normal((m, 2)) @ L.T
        ok = (side[:, 0] < z0) & (side[:, 1] <= z0)
        out = np.concatenate([out, np.stack([side[ok, 0], z0[ok], side[ok, 1]], axis=1)])
    return out[:n]


#: Importance samples per position class (interior, each edge position) for the exact noise law's rates.
IS_SAMPLES_INTERIOR = 200_000
IS_SAMPLES_EDGE = 20_000


def _dominant_point(A, u, lo, hi):
    """The smallest-norm raw vector x with Y = A x a local maximum at the threshold (Y0 = u, Y0 ≥ Y−, Y0 ≥ Y+):
    the Gaussian dominating point, where the tilted laws are centred (each constraint active or not: the feasible
    candidate of least norm), kept strictly inside the law's support [lo, hi]."""
    a0, a1, a2 = A
    best = None
    for rows in ([a1], [a1, a1 - a0], [a1, a1 - a2], [a1, a1 - a0, a1 - a2]):
        M = np.array(rows)
        rhs = np.zeros(len(rows))
        rhs[0] = u
        try:
            x = M.T @ np.linalg.solve(M @ M.T, rhs)
        except np.linalg.LinAlgError:
            continue
        y = A @ x
        if y[1] >= y[0] - 1e-9 * abs(u) and y[1] >= y[2] - 1e-9 * abs(u) and (best is None or x @ x < best @ best):
            best = x
    span = hi - lo
    return np.clip(best, lo + 1e-3 * span, hi - 1e-3 * span)


def _tilts(logp, c, target):
    """Per raw variable m, the exponentially tilted law q_m ∝ p e^{θ_m c} whose mean is target[m]: (q (m, n),
    log M(θ_m) (m,), θ (m,))."""
    from scipy.optimize import brentq

    def law(theta):
        lw = logp + theta * c
        mx = lw.max()
        e = np.exp(lw - mx)
        z = e.sum()
        return e / z, np.log(z) + mx

    def gap(theta, t):
        return float(law(theta)[0] @ c) - t

    q, logm, th = [], [], []
    for t in target:
        g0 = gap(0.0, t)
        if g0 == 0.0:
            theta = 0.0
        else:
            step = 1.0 / max(float(np.sqrt(np.exp(logp) @ (c * c))), 1e-30)
            lo, hi = (0.0, step) if g0 < 0 else (-step, 0.0)
            while (gap(hi, t) < 0) if g0 < 0 else (gap(lo, t) > 0):
                if g0 < 0:
                    lo, hi = hi, 2 * hi
                else:
                    lo, hi = 2 * lo, lo
            theta = brentq(gap, lo, hi, args=(t,), xtol=1e-14 * max(abs(lo), abs(hi)))
        qq, lm = law(theta)
        q.append(qq), logm.append(lm), th.append(theta)
    return np.array(q), np.array(logm), np.array(th)


class GaussianRates:
    """Local-maximum rates and conditional triples for white Gaussian raw noise of σ (exact quadrature)."""

    model = "gaussian"

    def __init__(self, n_bins, pulse, sigma, u):
        self.cls, self.covs = position_covariances(n_bins, pulse, sigma)
        self.u = u
        self.rates = np.array([local_max_probability(u, cv)[0] for cv in self.covs])
        self.rel_se = np.zeros(len(self.rates))

    def triples(self, c, n, rng):
        return _conditional_triples(self.u, self.covs[c], n, rng)


class LatticeRates:
    """Local-maximum rates and conditional triples for white raw noise of any discrete law (the chain's exact code
    distribution): importance sampling with exponential tilting.  For a position, the detection triple is
    Y = A x over the 2h + 3 raw bins of its support; each x_m is drawn from p(c) e^{θ_m c}/M(θ_m), θ_m such that
    its tilted mean is the m-th component of the dominating point (the least-norm x with a local maximum of Y at
    the threshold u: :func:`_dominant_point`), weight Π M(θ_m) e^{−θ_m x_m}:
    rate = E_q[1{Y0 > u, Y0 > Y−, Y0 ≥ Y+} · weight] (unbiased; its relative standard error is reported), and the
    triples are drawn from the weighted local maxima (sampling–importance–resampling).  Computed once per detector,
    pulse, threshold and row length (fixed seed: the rates are a function of these only)."""

    model = "exact code law (importance sampling)"

    def __init__(self, n_bins, pulse, codes, probs, base, u):
        keep = probs > 0
        c = np.asarray(codes, float)[keep] - base
        p = np.asarray(probs, float)[keep]
        p = p / p.sum()
        logp = np.log(p)
        self.cls, reps = position_classes(n_bins, pulse)
        self.u = u
        rates, rel, pools = [], [], []
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([n_bins, len(reps), 28])))
        for k, j in enumerate(reps):
            A = filter_rows(n_bins, pulse, [j - 1, j, j + 1])
            cols = np.flatnonzero(np.any(A != 0, axis=0))
            A = A[:, cols]
            a = A[1]
            if float(np.sum(np.where(a > 0, a * c.max(), a * c.min()))) <= u:
                rates.append(0.0), rel.append(0.0), pools.append((np.zeros((1, 3)), np.ones(1)))
                continue
            target = _dominant_point(A, u, c.min(), c.max())
            q, logm, theta = _tilts(logp, c, target)
            n = IS_SAMPLES_INTERIOR if k == 0 else IS_SAMPLES_EDGE
            cq = np.cumsum(q, axis=1)
            cq[:, -1] = 1.0
            x = np.empty((n, len(cols)))
            for m in range(len(cols)):
                x[:, m] = c[np.minimum(np.searchsorted(cq[m], rng.random(n), side="right"), len(c) - 1)]
            logw = np.sum(logm) - x @ theta
            y = x @ A.T
            hit = (y[:, 1] > u) & (y[:, 1] > y[:, 0]) & (y[:, 1] >= y[:, 2])
            w = np.where(hit, np.exp(logw), 0.0)
            rate = float(w.mean())
            rates.append(rate)
            rel.append(float(w.std(ddof=1) / np.sqrt(n) / rate) if rate > 0 else 0.0)
            pools.append((y[hit], w[hit] / w[hit].sum() if hit.any() else np.ones(0)))
        self.rates, self.rel_se, self.pools = np.array(rates), np.array(rel), pools

    def triples(self, c, n, rng):
        y, w = self.pools[c]
        return y[rng.choice(len(w), size=n, p=w)]


_RATE_CACHE: dict = {}
#: The importance-sampled rates (:class:`LatticeRates`, ≈ 1.5 s of one thread on the terrain frame) are also kept on
#: disk, in this source's kernel cache folder (core/jit.py ``CACHE_DIR``, removed with it), one file per key: a new
#: process (every run from Blender) loads them instead of sampling again.  The same numbers bit for bit: the file
#: holds the arrays the sampling made, keyed by every input, the CPU and these constants.
RATE_FILE_FORMAT = 1


def _rate_file(key):
    h = hashlib.sha256(repr((key, cpu_key(), IS_SAMPLES_INTERIOR, IS_SAMPLES_EDGE, RATE_FILE_FORMAT)).encode())
    return CACHE_DIR / "false_alarm_rates" / f"{h.hexdigest()[:32]}.npz", h.hexdigest()


def _load_lattice_rates(key, n_bins, pulse, u):
    """The :class:`LatticeRates` of ``key`` from its file, or None (no file, unreadable, another key)."""
    path, tag = _rate_file(key)
    try:
        with np.load(path, allow_pickle=False) as f:
            if str(f["tag"]) != tag:
                return None
            n = len(f["rates"])
            pools = [(f[f"y{k}"], f[f"w{k}"]) for k in range(n)]
            rates, rel_se = f["rates"], f["rel_se"]
    except Exception:  # no file, cut short, not a zip archive, a member missing: sampled again
        return None
    model = LatticeRates.__new__(LatticeRates)
    model.cls, _ = position_classes(n_bins, pulse)
    model.u = u
    model.rates, model.rel_se, model.pools = rates, rel_se, pools
    return model


def _save_lattice_rates(key, model):
    """Write the model's arrays to its file (a temporary file renamed into place; errors ignored: a cache)."""
    path, tag = _rate_file(key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"tag": np.array(tag), "rates": model.rates, "rel_se": model.rel_se}
        for k, (y, w) in enumerate(model.pools):
            arrays[f"y{k}"], arrays[f"w{k}"] = y, w
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
    except OSError:
        pass


def rate_model(n_bins, pulse, sigma, u, law=None, base=0.0):
    """The kept :class:`LatticeRates` (``law`` = (codes, probabilities); kept in memory and on disk) or
    :class:`GaussianRates` (law None; in memory)."""
    key = (n_bins, None if pulse is None else np.asarray(pulse, float).tobytes(), float(sigma), float(u),
           None if law is None else (np.asarray(law[0]).tobytes(), np.asarray(law[1]).tobytes()), float(base))
    model = _RATE_CACHE.get(key)
    if model is None:
        if law is None:
            model = GaussianRates(n_bins, pulse, sigma, u)
        else:
            model = _load_lattice_rates(key, n_bins, pulse, u)
            if model is None:
                model = LatticeRates(n_bins, pulse, law[0], law[1], base, u)
                _save_lattice_rates(key, model)
        if len(_RATE_CACHE) > 8:
            _RATE_CACHE.clear()
        _RATE_CACHE[key] = model
    return model


def draw_false_alarms(c_lo, c_hi, n_bins, rates, rng):
    """Noise maxima above the threshold in each pixel's bins outside [c_lo, c_hi) (module docstring), from a rate
    model (:func:`rate_model`).  Returns (pixel, bin, samples (n, 3) float32, expected count per pixel)."""
    P = len(c_lo)
    cls = rates.cls
    p = np.zeros(n_bins)
    p[1:n_bins - 1] = rates.rates[cls[1:n_bins - 1]]
    cs = np.concatenate([[0.0], np.cumsum(p)])  # cs[j] = Σ_{i<j} p_i
    lam = cs[n_bins] - (cs[c_hi] - cs[c_lo])
    n = rng.poisson(lam)
    pix = np.repeat(np.arange(P), n)
    # inverse CDF over the bins outside C: a uniform share of the pixel's λ, skipping C's mass
    t = rng.random(len(pix)) * lam[pix]
    lo_mass = cs[c_lo[pix]]
    t = np.where(t < lo_mass, t, t + (cs[c_hi[pix]] - cs[c_lo[pix]]))
    j = np.clip(np.searchsorted(cs, t, side="right") - 1, 1, n_bins - 2)
    samples = np.empty((len(pix), 3))
    kind = cls[j]
    for c in np.unique(kind):
        sel = np.flatnonzero(kind == c)
        samples[sel] = rates.triples(c, len(sel), rng)
    return pix, j.astype(np.int64), samples.astype(np.float32), lam


def detect_statistical(truth, chain, report, *, pulse, k_sigma, max_echoes, min_separation_bins=None,
                       interpolation="gaussian", bin_width_s, gate_start_s=0.0, codes_per_joule, seed,
                       min_noise_sigma=0.0, noise_law=None, threads=1, extents_out=None, spans=None,
                       chains=None):
    """Echoes of the noisy receiver with the signal-free stretches drawn from the statistics.

    truth : (P, B) float32 noise-free energy per bin [J]; chain(cube (1, n, L) float32, SeedSequence) → (codes,
    report) runs the receiver chain (the same detector as ``report``: the chain report of the noise model, with
    ``noise_mean``, ``noise_sigma``); codes_per_joule: mean output units per J of signal (the signal level).
    Threshold: calibrated, k_sigma × σ_n/‖pulse‖ above the baseline ``noise_mean``.  ``noise_law``: the chain's
    (codes, probabilities) of a signal-free bin (ChainOutput.noise_pmf) — the false-alarm rates from that exact law
    (:class:`LatticeRates`); None: white Gaussian noise of σ (:class:`GaussianRates`).
    ``extents_out``: a dict that receives the rows' signal extents at the signal level (``first``, ``last``,
    ``peak``, ``has_nan``: :func:`row_extents`; ``level``), from which the false-alarm classification needs only
    the signal stretches (core.physics.detection.false_alarms.classify_false_alarms ``extents``).
    ``spans``: (lo, hi) per row when truth is exactly 0 outside [lo, hi) (:func:`row_extents`; the same results).
    ``chains``: optional, chains(cubes, SeedSequences) → [(codes, report)] — ``chain`` of every window length at
    once (core.physics.receiver.chain.apply_receiver_chains: the same codes, the small cubes' blocks not waiting
    for each other).
    Returns (NoisyEchoes (P rows), info dict)."""
    truth = np.asarray(truth)
    P, B = truth.shape
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    sigma = max(float(report["noise_sigma"]), float(min_noise_sigma))
    base = float(report["noise_mean"])
    h = 0 if pulse is None else len(pulse) // 2
    w = np.ones(1) if pulse is None else filter_taps(pulse)
    norm = 1.0 if pulse is None else float(np.sqrt(np.sum(np.asarray(pulse, float) ** 2)))
    u = k_sigma * sigma / norm
    if min_separation_bins is None:
        min_separation_bins = max(3, len(pulse) // 2) if pulse is not None else 3
    level = SIGNAL_LEVEL_SIGMA * sigma / codes_per_joule
    extents = row_extents(truth, level, threads, spans)
    if extents_out is not None:
        extents_out.update(first=extents[0], last=extents[1], peak=extents[2], has_nan=extents[3],
                           level=truth.dtype.type(level))
    c_lo, c_hi, start, length = signal_windows(truth, level, h, B, threads, extents)
    b32 = np.float32(base)
    cand_pix, cand_bin, cand_s = [], [], []
    n_sim = 0
    n_overflow = 0
    windows = []  # (rows, their starts, the gathered cube) per window length
    for k, L in enumerate(np.unique(length[length > 0])):
        rows = np.flatnonzero(length == L)
        cube = np.empty((len(rows), L), np.float32)
        s_rows = np.ascontiguousarray(start[rows])
        run_row_chunks(lambda a, b: _gather_windows(truth, rows[a:b], s_rows[a:b], cube[a:b]), len(rows), threads)
        windows.append((rows, s_rows, cube))
    seeds = [np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (1, k)) for k in range(len(windows))]
    if chains is not None:  # every length's chain at once (the same codes as one call each)
        all_codes = [c for c, _ in chains([w[2][None] for w in windows], seeds)]
    else:
        all_codes = [chain(w[2][None], sd)[0] for w, sd in zip(windows, seeds)]
    for (rows, s_rows, cube), codes in zip(windows, all_codes):
        L = cube.shape[1]
        codes = codes.reshape(len(rows), L)
        m = 4 * max_echoes
        cb = np.full((len(rows), m), -1, np.int64)
        cs = np.zeros((len(rows), m, 3), np.float32)
        nc = np.zeros(len(rows), np.int64)
        c_lo_r, c_hi_r = c_lo[rows], c_hi[rows]
        run_row_chunks(lambda a, b: _window_candidates(codes[a:b], s_rows[a:b], c_lo_r[a:b], c_hi_r[a:b], b32, w, u,
                                                       cb[a:b], cs[a:b], nc[a:b]), len(rows), threads)
        n_overflow += int(np.count_nonzero(nc > m))
        keep = cb >= 0
        cand_pix.append(np.repeat(rows, keep.sum(axis=1)))
        cand_bin.append(cb[keep])
        cand_s.append(cs[keep])
        n_sim += len(rows) * int(L)
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence(ss.entropy,
                                                                     spawn_key=tuple(ss.spawn_key) + (2,))))
    if B >= 3:
        rates = rate_model(B, pulse, sigma, u, noise_law, base)
        fa_pix, fa_bin, fa_s, lam = draw_false_alarms(c_lo, c_hi, B, rates, rng)
    else:  # (no bin has two neighbours: no detection anywhere, as on the per-bin route)
        rates = GaussianRates.__new__(GaussianRates)
        rates.rates, rates.rel_se = np.zeros(1), np.zeros(1)
        fa_pix, fa_bin, fa_s, lam = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float32),
                                     np.zeros(P))
    pix = np.concatenate(cand_pix + [fa_pix]).astype(np.int64)
    cbin = np.concatenate(cand_bin + [fa_bin]).astype(np.int64)
    csmp = np.concatenate(cand_s + [fa_s]).astype(np.float32).reshape(-1, 3)
    order = np.argsort(pix, kind="stable")
    pix, cbin, csmp = pix[order], cbin[order], np.ascontiguousarray(csmp[order])
    ptr = np.searchsorted(pix, np.arange(P + 1))
    K = int(max_echoes)
    pos = np.full((P, K), -1, np.int64)
    samples = np.zeros((P, K, 3), np.float32)
    _choose(ptr, cbin, csmp, int(min_separation_bins), pos, samples)
    echoes = echoes_from_slots(pos, samples, np.full(P, base), np.full(P, sigma), np.full(P, u), (P,),
                               bin_width_s, gate_start_s, interpolation)
    info = {"bins_simulated": n_sim, "bins_total": P * B, "fraction_simulated": n_sim / max(1, P * B),
            "statistical_false_alarms_drawn": int(len(fa_pix)),
            "statistical_false_alarms_expected": float(lam.sum()), "window_candidate_overflow": n_overflow,
            "signal_level_sigma": SIGNAL_LEVEL_SIGMA, "false_alarm_rate_model": rates.model,
            "rate_per_bin_interior": float(rates.rates[0]),
            "rate_relative_standard_error": float(rates.rel_se.max()) if len(rates.rel_se) else 0.0}
    return echoes, info


__all__ = ["NoisyEchoes", "detect_statistical", "validity", "filtered_noise_shape", "gaussian_tail_error",
           "draw_false_alarms", "signal_windows", "row_extents", "position_covariances"]
