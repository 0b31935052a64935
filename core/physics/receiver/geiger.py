"""Geiger mode (photon counting), docs/theory.md §8: detection probability, pile-up, Coates correction, histograms."""
from __future__ import annotations

import numpy as np


def geiger_detection_probability(n_mean, speckle_dof=None):
    """P_d = 1 − exp(−N); with speckle of M degrees of freedom 1 − (1 + N/M)^(−M) (docs/theory.md §8).
    N = 1: 0.6321; M = 1: 0.5; M = 4: 0.5904."""
    n = np.asarray(n_mean, dtype=np.float64)
    if speckle_dof is None:
        return -np.expm1(-n)
    m = np.asarray(speckle_dof, dtype=np.float64)
    return -np.expm1(-m * np.log1p(n / m))


def pileup_probabilities(rates):
    """First-detection probability per bin p_i = exp(−Σ_{j<i} r_j)(1 − e^(−r_i)) (docs/theory.md §8), along the
    last axis.  Rates [0.1, 0.5, 1.0] → [0.09516, 0.3560, 0.3469]."""
    r = np.asarray(rates, dtype=np.float64)
    before = np.cumsum(r, axis=-1) - r
    return np.exp(-before) * -np.expm1(-r)


def coates_correction(histogram, n_pulses):
    """Coates pile-up correction r_i = −ln[1 − h_i/(N − Σ_{j<i} h_j)] (docs/theory.md §8), along the last axis.
    Bins where every remaining pulse fired (h_i = N − Σ_{j<i} h_j) have an unbounded estimate: returned as inf."""
    h = np.asarray(histogram, dtype=np.float64)
    remaining = n_pulses - (np.cumsum(h, axis=-1) - h)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(remaining > 0, h / np.where(remaining > 0, remaining, 1.0), 0.0)
        return -np.log1p(-frac)


def geiger_histogram(rate_per_bin, n_pulses, rng, noise_per_bin=0.0, dead_time_bins=None, speckle_dof=None,
                     max_pulse_chunk=None, force_per_pulse=False):
    """Histogram of Geiger-mode detections over ``n_pulses`` pulses (docs/theory.md §8: pile-up, dead time).

    rate_per_bin   : (..., B) mean *detectable* signal primaries per bin per pulse (η already applied).
    noise_per_bin  : background + dark primaries per bin per pulse (scalar or (...,) per pixel).
    dead_time_bins : after a detection in bin i the detector re-arms at bin i + 1 + dead_time_bins.
                     None or ≥ B: at most one (the first) detection per pulse.
    speckle_dof    : M; the signal of each pixel is multiplied by an independent Gamma(M, 1/M) factor per pulse.

    Without speckle and with one detection per pulse the histogram is exactly multinomial(N, p_i) with the
    pile-up p_i (one vectorized call).  Otherwise each pulse is simulated: the first event after re-arming is
    where the cumulative rate crosses an Exp(1) variate (exact inhomogeneous Poisson first arrival),
    found by a vectorized bisection (``force_per_pulse`` selects it always).  Returns (int64 histogram,
    info dict).
    """
    r = np.asarray(rate_per_bin, dtype=np.float64)
    shape = r.shape
    B = shape[-1]
    r = r.reshape(-1, B)
    P = r.shape[0]
    noise = np.broadcast_to(np.asarray(noise_per_bin, dtype=np.float64), shape[:-1]).reshape(P, 1)
    single = dead_time_bins is None or dead_time_bins >= B
    info = {"pulses": int(n_pulses), "path": "", "dead_time_bins": dead_time_bins}
    if single and not speckle_dof and not force_per_pulse:
        tot = r + noise
        p = pileup_probabilities(tot)
        pv = np.empty((P, B + 1))
        pv[:, :B] = p
        pv[:, B] = np.exp(-tot.sum(axis=1))  # no detection in this pulse
        pv /= pv.sum(axis=1, keepdims=True)
        h = rng.multinomial(int(n_pulses), pv)
        info["path"] = "multinomial"
        return h[:, :B].astype(np.int64).reshape(shape), info
    info["path"] = "per-pulse"
    cs = np.zeros((P, B + 1))
    np.cumsum(r, axis=1, out=cs[:, 1:])
    cn = noise * np.arange(B + 1)  # (P, B+1) cumulative noise rate
    dead = B if single else int(dead_time_bins)
    hist = np.zeros(P * B, dtype=np.int64)
    chunk = max_pulse_chunk or max(1, (1 << 22) // max(P, 1))
    done = 0
    rows = np.arange(P)[:, None]
    while done < n_pulses:
        nb = min(chunk, n_pulses - done)
        done += nb
        if speckle_dof:
            s = rng.standard_gamma(float(speckle_dof), size=(P, nb)) / float(speckle_dof)
        else:
            s = np.ones((P, nb))
        arm = np.zeros((P, nb), dtype=np.int64)  # bin index at which the detector is armed
        active = np.ones((P, nb), dtype=bool)
        while active.any():
            c_arm = s * cs[rows, arm] + cn[rows, arm]
            target = c_arm + rng.standard_exponential(size=(P, nb))
            c_end = s * cs[:, B:B + 1] + cn[:, B:B + 1]
            hit = active & (target < c_end)
            # bisection: smallest j in (arm, B] with C(j) > target; detection bin = j - 1
            lo = arm.copy()
            hi = np.full((P, nb), B, dtype=np.int64)
            while True:
                open_ = hit & (hi - lo > 1)
                if not open_.any():
                    break
                mid = (lo + hi) // 2
                cm = s * np.take_along_axis(cs, mid, axis=1) + np.take_along_axis(cn, mid, axis=1)
                up = cm > target
                hi = np.where(open_ & up, mid, hi)
                lo = np.where(open_ & ~up, mid, lo)
            det_bin = hi - 1
            pix = np.broadcast_to(rows, (P, nb))
            hist += np.bincount((pix[hit] * B + det_bin[hit]), minlength=P * B)
            arm = np.where(hit, det_bin + 1 + dead, B)
            active = hit & (arm < B)
            arm = np.minimum(arm, B)
    return hist.reshape(shape), info
