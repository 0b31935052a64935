"""Receiver: photon statistics, APD gain and excess noise, read noise, A/D, dark and background; detection and
false-alarm probabilities (ROC); Geiger-mode detection and pile-up."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy import stats

from validation import check, save
from validation._common import ROOT  # noqa: F401  (puts the repository on sys.path)

from core.config.settings import DetectorSettings
from core.physics.detection.false_alarms import expected_false_alarms
from core.physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel
from core.physics.receiver.chain import ChainSettings, apply_receiver_chain
from core.physics.receiver.geiger import coates_correction, geiger_histogram

TITLE = "Receiver: photon statistics, APD, noise, A/D, detection, Geiger mode"
ORDER = 30
INTRO = """Every simulated number is a statistic of the receiver chain's output (`apply_receiver_chain`, the
noisy mode of a run) over identical bins of a synthetic energy cube; the references are the textbook formulas,
written out here independently of core/ (docs/theory.md §8, §9):

* photon statistics: Poisson, mean = variance = N̄ = η E λ/(h c), and its pmf;
* APD: mean G N̄, variance G² F N̄ with McIntyre's F = k G + (1 − k)(2 − 1/G);
* dark current and background: N = I τ/q and η × rate × τ add to the mean and (as Poisson) to the variance;
  surface dark current is not multiplied;
* read noise σ_r and the A/D step Δ add σ_r² + Δ²/12 to the variance (the A/D output is (code − offset)·Δ);
* ROC: a bin's value against a threshold T: for counting (PIN, no read noise) P = P(Poisson(N) ≥ T) exactly;
  read-noise-limited P = Q((T − μ)/σ); the detector's false alarms on white Gaussian noise (matched filter,
  local maxima above a fixed threshold) against the expected count of `expected_false_alarms` (Rice-type
  quadrature over the filtered noise's covariance; a closed form in tests);
* Geiger mode: P_d = 1 − e^(−N); pile-up: the first detection in bin i has probability
  exp(−Σ_{j<i} r_j)(1 − e^(−r_i)), and the Coates estimate −ln[1 − h_i/(P − Σ_{j<i} h_j)] recovers r_i.

Tolerances are statistical: about 4 standard errors of the estimate for the number of samples drawn (a variance
over n samples: ≈ √(2/n) relative for Gaussian-like data), stated per check."""

H_PLANCK, C_LIGHT, Q_E = 6.62607015e-34, 299_792_458.0, 1.602176634e-19
LAM = 1.064e-6
TAU = 10e-9


def photons_per_j(lam=LAM):
    return lam / (H_PLANCK * C_LIGHT)


def chain(cube, seed, **det):
    s = ChainSettings(DetectorSettings(**{"mode": "noisy", **det}), wavelength_m=LAM, bin_width_s=TAU)
    return apply_receiver_chain(cube, s, seed)


QUIET = dict(enable_dark_current=False, enable_background=False, enable_read_noise=False, enable_adc=False)


def mcintyre(g, k):
    return k * g + (1 - k) * (2 - 1 / g)


def run(out_dir: Path, quick: bool) -> list[dict]:
    checks = []
    side = 256 if quick else 512
    n = side * side
    se_var = 4 * math.sqrt(2 / n)  # 4 standard errors of a Gaussian variance

    # ---- photon statistics (PIN, quantum efficiency 0.5)
    nbar = 5.0
    e = nbar / (0.5 * photons_per_j())
    x = chain(np.full((side, side, 1), e, np.float32), 1, detector_type="pin", quantum_efficiency=0.5,
              **QUIET).data.astype(np.float64).ravel()
    checks.append(check("PIN photo-electrons: mean (N̄ = η E λ/hc = 5)", x.mean(), nbar, 4 * math.sqrt(nbar / n) / nbar,
                        unit="e⁻"))
    checks.append(check("PIN photo-electrons: variance (Poisson: N̄)", x.var(), nbar,
                        4 * math.sqrt((2 * nbar ** 2 + nbar) / n) / nbar, unit="e⁻²"))
    k = np.arange(0, 18)
    emp = np.bincount(x.astype(int), minlength=40)[:18] / n
    checks.append(check("PIN photo-electrons: max |pmf − Poisson pmf|", float(np.max(np.abs(emp - stats.poisson.pmf(k, nbar)))),
                        0.0, 4 * math.sqrt(0.18 / n), kind="max"))
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ax[0].bar(k, emp, color="C0", alpha=0.6, label=f"chain output ({n} bins)")
    ax[0].plot(k, stats.poisson.pmf(k, nbar), "ko", ms=4, label="Poisson pmf, N̄ = 5")
    ax[0].set(title="photon statistics (PIN, no noise sources)", xlabel="photo-electrons per bin [e⁻]",
              ylabel="probability")
    ax[0].legend(fontsize=7)

    # ---- APD gain and excess noise
    gains = [10.0, 100.0] if quick else [5.0, 10.0, 30.0, 100.0, 300.0]
    fs = []
    for g in gains:
        for kk in ((0.02,) if quick else (0.02, 0.2)):
            y = chain(np.full((side, side, 1), e, np.float32), 2, detector_type="apd", quantum_efficiency=0.5,
                      apd_gain=g, apd_k_eff=kk, **QUIET).data.astype(np.float64).ravel()
            F = mcintyre(g, kk)
            checks.append(check(f"APD mean, G = {g:g}, k = {kk:g} (G N̄)", y.mean(), g * nbar,
                                4 * math.sqrt(F / (nbar * n)), unit="e⁻"))
            var_rel = 4 * math.sqrt((2 + (F ** 2 * 3 + 6 * F) / (F * nbar)) / n)  # 4 s.e. incl. kurtosis
            checks.append(check(f"APD variance, G = {g:g}, k = {kk:g} (G² F N̄)", y.var(), g * g * F * nbar,
                                var_rel, unit="e⁻²"))
            fs.append((g, kk, y.var() / (g * g * nbar)))
    gg = np.geomspace(1, 400, 100)
    for j, kk in enumerate((0.02,) if quick else (0.02, 0.2)):
        ax[1].semilogx(gg, mcintyre(gg, kk), f"C{j}", label=f"McIntyre F, k = {kk}")
        pts = [(g, f) for g, kk2, f in fs if kk2 == kk]
        ax[1].semilogx([p[0] for p in pts], [p[1] for p in pts], f"C{j}o", ms=5,
                       label=f"chain var/(G² N̄), k = {kk}")
    ax[1].set(title="APD excess noise factor", xlabel="mean gain G", ylabel="excess noise factor F")
    ax[1].legend(fontsize=7)
    save(fig, out_dir / "photon_statistics_and_apd.png")

    # ---- dark, background, read noise, A/D (the §8 detector, all terms on)
    det = dict(detector_type="apd", quantum_efficiency=0.4, apd_gain=100.0, apd_k_eff=0.02,
               dark_current_bulk_a=1e-12, dark_current_surface_a=1e-9, background_rate_photons_per_s=5e8,
               read_noise_e=300.0, adc_bits=12, adc_full_scale_e=500.0 * 4096, adc_offset_counts=16)
    step = 500.0
    for label, energy in (("no signal", 0.0), ("1e-17 J", 1e-17), ("1e-16 J", 1e-16)):
        out = chain(np.full((side, side, 1), energy, np.float32), 3, **det)
        z = (out.data.astype(np.float64).ravel() - 16) * step
        n_s = 0.4 * energy * photons_per_j()
        n_b = 0.4 * 5e8 * TAU
        n_db, n_ds = 1e-12 * TAU / Q_E, 1e-9 * TAU / Q_E
        F = mcintyre(100.0, 0.02)
        mean = 100 * (n_s + n_b + n_db) + n_ds
        var = 100 ** 2 * F * (n_s + n_b + n_db) + n_ds + 300.0 ** 2 + step ** 2 / 12
        checks.append(check(f"§8 APD + dark + background + read noise + 12-bit A/D, {label}: mean",
                            z.mean(), mean, 4 * math.sqrt(var / n), kind="abs", unit="e⁻"))
        checks.append(check(f"§8 APD + dark + background + read noise + 12-bit A/D, {label}: variance",
                            z.var(), var, 3 * se_var, unit="e⁻²"))
    # read noise alone and the A/D step alone
    r = chain(np.zeros((side, side, 1), np.float32), 4, detector_type="pin",
              **dict(QUIET, enable_read_noise=True), read_noise_e=50.0).data.astype(np.float64).ravel()
    checks.append(check("read noise alone: variance (σ_r² = 2500)", r.var(), 2500.0, se_var, unit="e⁻²"))
    a = chain(np.full((side, side, 1), 2000 / photons_per_j(), np.float32), 5, detector_type="pin",
              quantum_efficiency=1.0, enable_dark_current=False, enable_background=False, read_noise_e=0.0,
              adc_bits=16, adc_full_scale_e=65536 * 40.0, adc_offset_counts=100).data.astype(np.float64).ravel()
    a = (a - 100) * 40.0
    checks.append(check("PIN + A/D step 40 e⁻: variance (N̄ + Δ²/12)", a.var(), 2000 + 40 ** 2 / 12,
                        se_var * 1.5, unit="e⁻²"))

    # ---- ROC, counting (exact Poisson) and read-noise-limited (Gaussian)
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    n_b, n_sig = 2.0, 5.0
    cube = np.zeros((side, side, 2), np.float32)
    cube[..., 0] = n_sig / photons_per_j()
    c = chain(cube, 6, detector_type="pin", quantum_efficiency=1.0, enable_dark_current=False,
              enable_read_noise=False, enable_adc=False, background_rate_photons_per_s=n_b / TAU).data
    sig_bins, noise_bins = c[..., 0].ravel(), c[..., 1].ravel()
    thr = np.arange(1, 15)
    pd = np.array([(sig_bins >= t).mean() for t in thr])
    pfa = np.array([(noise_bins >= t).mean() for t in thr])
    pd_th, pfa_th = stats.poisson.sf(thr - 1, n_b + n_sig), stats.poisson.sf(thr - 1, n_b)
    for t in ((5, 8) if quick else (3, 5, 8, 10)):
        i = t - 1
        checks.append(check(f"counting ROC (N_b = 2, N_s = 5): P_d at T = {t}", pd[i], pd_th[i],
                            4 * math.sqrt(max(pd_th[i] * (1 - pd_th[i]), 1e-6) / n), kind="abs"))
        checks.append(check(f"counting ROC (N_b = 2, N_s = 5): P_fa at T = {t}", pfa[i], pfa_th[i],
                            4 * math.sqrt(max(pfa_th[i] * (1 - pfa_th[i]), 1e-6) / n), kind="abs"))
    ax[0].loglog(pfa_th, pd_th, "k-", label="Poisson theory")
    ax[0].loglog(pfa, pd, "C0o", ms=4, label="chain, T = 1 … 14 e⁻")
    # read-noise limited
    sig_r, n_s2 = 300.0, 600.0
    cube = np.zeros((side, side, 2), np.float32)
    cube[..., 0] = n_s2 / photons_per_j()
    c = chain(cube, 7, detector_type="pin", quantum_efficiency=1.0, enable_dark_current=False,
              enable_background=False, enable_adc=False, read_noise_e=sig_r).data.astype(np.float64)
    s_b, n_bb = c[..., 0].ravel(), c[..., 1].ravel()
    thr2 = np.linspace(-300, 1500, 37)
    pd2 = np.array([(s_b >= t).mean() for t in thr2])
    pfa2 = np.array([(n_bb >= t).mean() for t in thr2])
    pd2_th = stats.norm.sf((thr2 - n_s2) / math.sqrt(sig_r ** 2 + n_s2))
    pfa2_th = stats.norm.sf(thr2 / sig_r)
    for t in (600.0, 900.0):
        i = int(np.argmin(np.abs(thr2 - t)))
        checks.append(check(f"read-noise ROC (σ_r = 300 e⁻, N_s = 600): P_d at T = {t:g} e⁻", pd2[i], pd2_th[i],
                            4 * math.sqrt(pd2_th[i] * (1 - pd2_th[i]) / n) + 2e-3, kind="abs",
                            note="+0.002 for the Poisson skew of N_s"))
        checks.append(check(f"read-noise ROC (σ_r = 300 e⁻, N_s = 600): P_fa at T = {t:g} e⁻", pfa2[i],
                            pfa2_th[i], 4 * math.sqrt(max(pfa2_th[i] * (1 - pfa2_th[i]), 1e-6) / n), kind="abs"))
    ax[0].loglog(pfa2_th, pd2_th, "k--", label="Gaussian theory (read noise)")
    ax[0].loglog(pfa2, pd2, "C1s", ms=3, label="chain, read-noise limited")
    ax[0].set(title="ROC of one bin", xlabel="false-alarm probability P_fa", ylabel="detection probability P_d",
              xlim=(1e-5, 1.1), ylim=(1e-2, 1.1))
    ax[0].legend(fontsize=7)

    # ---- the detector's false alarms on white Gaussian noise vs the expectation
    rng = np.random.default_rng(11)
    P, B, sigma = (1024 if quick else 4096), 1024, 7.0
    xw = (sigma * rng.standard_normal((P, B)) + 100.0).astype(np.float32)
    pulse = gaussian_pulse_kernel(5e-9, 1e-9)
    sd_det = sigma / math.sqrt(float(np.sum(pulse ** 2)))
    ks = [3.0, 3.5, 4.0]
    got, want = [], []
    for kk in ks:
        ech = detect_echoes_noisy(xw, 1e-9, pulse=pulse, threshold_mode="fixed", threshold=kk * sd_det,
                                  max_echoes=32)
        exp_ = float(expected_false_alarms(ech.threshold, sigma, np.ones((P, B), bool), pulse).sum())
        got.append(int(ech.detected.sum()))
        want.append(exp_)
        checks.append(check(f"detector false alarms, matched filter, fixed {kk:g} σ threshold", got[-1], exp_,
                            4 * math.sqrt(exp_), kind="abs", unit="count", note=f"{P} × {B} noise bins"))
    ax[1].semilogy(ks, np.array(want) / (P * B), "k-o", mfc="none", label="expectation (local maxima above T)")
    ax[1].semilogy(ks, np.array(got) / (P * B), "C3x", ms=8, label="detect_echoes_noisy on noise")
    ax[1].set(title="false-alarm rate of the detector", xlabel="threshold / σ of the filtered noise",
              ylabel="false alarms per bin")
    ax[1].legend(fontsize=7)
    save(fig, out_dir / "roc_and_false_alarms.png")

    # ---- Geiger mode
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    pulses = 2000 if quick else 5000
    ns = np.array([0.1, 0.5, 1.0, 2.0, 4.0])
    cube = np.zeros((8, 8, len(ns) * 4), np.float32)
    for i, nn in enumerate(ns):
        cube[..., 4 * i + 1] = nn / (0.4 * photons_per_j())
    g = chain(cube, 8, detector_type="geiger", geiger_pulses=pulses, enable_dark_current=False,
              enable_background=False, geiger_dead_time_bins=1).data.astype(np.float64)
    pd_g = np.array([g[..., 4 * i + 1].sum() / (64 * pulses) for i in range(len(ns))])
    for nn, p in zip(ns, pd_g):
        th = 1 - math.exp(-nn)
        checks.append(check(f"Geiger P_d at N = {nn:g} (1 − e^(−N))", p, th,
                            4 * math.sqrt(th * (1 - th) / (64 * pulses)), kind="abs"))
    nn = np.linspace(0, 5, 100)
    ax[0].plot(nn, 1 - np.exp(-nn), "k", label="1 − exp(−N)")
    ax[0].plot(ns, pd_g, "C0o", label=f"chain, 64 pixels × {pulses} pulses")
    ax[0].set(title="Geiger-mode detection probability", xlabel="mean detectable photons N per pulse",
              ylabel="detection probability P_d")
    ax[0].legend(fontsize=7)
    # pile-up on a long return, first detection only
    rates = np.array([[0.05, 0.2, 0.5, 0.8, 0.5, 0.2, 0.05]])
    n_p = 100_000 if quick else 400_000
    h, _ = geiger_histogram(rates, n_p, np.random.default_rng(5))
    before = np.concatenate([[0.0], np.cumsum(rates[0])[:-1]])
    p_th = np.exp(-before) * (1 - np.exp(-rates[0]))
    coates = coates_correction(h[0], n_p)
    for i in (1, 3, 5):
        checks.append(check(f"pile-up: first-detection fraction in bin {i} (rate {rates[0, i]:g})", h[0, i] / n_p,
                            p_th[i], 4 * math.sqrt(p_th[i] * (1 - p_th[i]) / n_p), kind="abs"))
        checks.append(check(f"Coates-corrected rate in bin {i}", coates[i], rates[0, i],
                            4 / math.sqrt(n_p * p_th[i]), note="4/√(expected detections)"))
    b = np.arange(rates.shape[1])
    ax[1].bar(b - 0.2, rates[0], 0.4, color="0.7", label="true rate r_i")
    ax[1].bar(b + 0.2, h[0] / n_p, 0.4, color="C0", label="detections per pulse (piled up)")
    ax[1].plot(b + 0.2, p_th, "k_", ms=14, mew=2, label="theory exp(−Σr_j)(1 − e^(−r_i))")
    ax[1].plot(b - 0.2, coates, "C3x", ms=8, label="Coates-corrected")
    ax[1].set(title="Geiger pile-up and the Coates correction", xlabel="time bin", ylabel="per pulse")
    ax[1].legend(fontsize=7)
    save(fig, out_dir / "geiger.png")
    return checks
