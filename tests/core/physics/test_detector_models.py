"""Statistical validation of the detector models (issue 28; docs/receiver.md "Detector models").

The reference: the receiver chain on every bin, then detection with the calibrated threshold
(``detect_echoes_noisy(threshold_mode="calibrated")``).  The fast model: core.physics.detection.stretches
(signal stretches per bin, the false alarms of the signal-free bins drawn from the Gaussian statistics).  Per
detector (PIN, APD with excess noise, background on and off) and per point (no target; a target at three SNRs),
10⁵ pixels of 64 bins each, fixed seeds, every statistic within 3 standard errors of the difference: false alarms per
pixel, detection probability, range error mean and σ, the echo-count histogram.  Where the filtered noise is not
Gaussian (multiplied background, Geiger counts) the fast model refuses (validity) — and, forced, disagrees.
"""
from __future__ import annotations

import numpy as np
import pytest

from core.config.settings import DetectorSettings
from core.physics.detection.false_alarms import filter_rows, expected_false_alarms
from core.physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel
from core.physics.detection.stretches import detect_statistical, filtered_noise_shape, validity
from core.physics.receiver.chain import ChainSettings, apply_receiver_chain
from core.physics.receiver.conversions import adc_step_e, photons_per_joule

N_PIX = 100_000       # pixel trials per point
N_BINS = 64
BIN_S = 1e-9
FWHM_S = 4e-9
T0 = 30.3             # true echo position, bins from the gate opening
K_SIGMA = 3.5
MAX_ECHOES = 3
MATCH_BINS = 3.0      # a detection within this many bins of T0 is the target
PULSE = gaussian_pulse_kernel(FWHM_S, BIN_S)
NORM = float(np.sqrt(np.sum(PULSE ** 2)))
# peak signal per bin in units of the threshold on the raw scale (k σ/‖pulse‖): below, near and above it
SNR_POINTS = (0.8, 1.0, 1.4)

DETECTORS = {
    "pin_background_off": dict(detector_type="pin", read_noise_e=30.0, adc_bits=16, adc_full_scale_e=2.0 ** 17,
                               background_rate_photons_per_s=0.0),
    "pin_background_on": dict(detector_type="pin", read_noise_e=30.0, adc_bits=16, adc_full_scale_e=2.0 ** 17,
                              background_rate_photons_per_s=2e10),
    "apd_excess_background_off": dict(detector_type="apd", apd_gain=100.0, apd_k_eff=0.02, enable_excess_noise=True,
                                      read_noise_e=300.0, adc_bits=16, adc_full_scale_e=20.0 * 2 ** 16,
                                      background_rate_photons_per_s=0.0),
    # multiplied background: 10 primaries a ns, each with an APD gain of F ≈ 4 (skewed filtered noise)
    "apd_excess_background_on": dict(detector_type="apd", apd_gain=100.0, apd_k_eff=0.02, enable_excess_noise=True,
                                     read_noise_e=300.0, adc_bits=16, adc_full_scale_e=20.0 * 2 ** 16,
                                     background_rate_photons_per_s=2.5e10),
    # the defaults (§8): dark currents, 12-bit A/D of 500 e⁻ (σ = 0.67 counts: a coarse lattice)
    "apd_defaults_section8": dict(adc_offset_counts=16, dark_current_bulk_a=1e-12, dark_current_surface_a=1e-9),
}
APD_BACKGROUND_ON = DETECTORS["apd_excess_background_on"]


def _detector(**kw):
    base = dict(mode="noisy", dark_current_bulk_a=0.0, dark_current_surface_a=0.0, speckle_dof=0.0,
                adc_offset_counts=400, threads=2)
    base.update(kw)
    return DetectorSettings(**base)


def _codes_per_joule(det):
    gain = 1.0 if det.detector_type == "pin" else det.apd_gain
    return float(photons_per_joule(1.064e-6)) * det.quantum_efficiency * gain / adc_step_e(det.adc_bits,
                                                                                            det.adc_full_scale_e)


def _truth(det, sigma, level):
    """(N_PIX, N_BINS) J: a Gaussian pulse at T0 whose peak bin holds ``level`` × the raw-scale threshold."""
    x = np.arange(N_BINS) + 0.5
    s = FWHM_S / BIN_S / 2.3548200450309493
    shape = np.exp(-0.5 * ((x - T0) / s) ** 2)
    peak_codes = level * K_SIGMA * sigma / NORM
    row = (peak_codes / shape.max() / _codes_per_joule(det) * shape).astype(np.float32)
    return np.broadcast_to(row, (N_PIX, N_BINS)).copy()


def _routes(det, level, seed, law=True, correlate=False):
    """(reference echoes, fast echoes, chain report) for one detector and one point.  ``law`` False: the fast
    route's false-alarm rates from the Gaussian model instead of the exact code law; ``correlate``: the raw noise
    made correlated in time (each output bin the sum of two neighbouring chain outputs) in both routes."""
    cs = ChainSettings(det, bin_width_s=BIN_S)
    probe = apply_receiver_chain(np.zeros((1, 1, 1), np.float32), cs, 0)
    report = probe.report
    truth = _truth(det, report["noise_sigma"], level) if level else np.zeros((N_PIX, N_BINS), np.float32)
    def correlated(codes):
        x = codes.astype(np.float64)
        return x + np.concatenate([x[..., 1:], x[..., -1:]], axis=-1) - report["noise_mean"]

    ref = apply_receiver_chain(truth[None], cs, np.random.SeedSequence([seed, 1]))
    data = correlated(ref.data[0]) if correlate else ref.data[0]
    e_ref = detect_echoes_noisy(data, BIN_S, threshold_mode="calibrated", k_sigma=K_SIGMA, pulse=PULSE,
                                max_echoes=MAX_ECHOES, noise_sigma=report["noise_sigma"],
                                baseline=report["noise_mean"], threads=2)

    def chain(cube, ss):
        out = apply_receiver_chain(cube, cs, ss)
        return (correlated(out.data) if correlate else out.data), out.report

    e_fast, _ = detect_statistical(truth, chain, report, pulse=PULSE, k_sigma=K_SIGMA, max_echoes=MAX_ECHOES,
                                   bin_width_s=BIN_S, codes_per_joule=_codes_per_joule(det),
                                   seed=np.random.SeedSequence([seed, 2]), noise_law=probe.noise_pmf if law else None)
    return e_ref, e_fast, report


def _statistics(e, target):
    """Per pixel: false alarms, target found, range errors of the target detections, echo counts."""
    pb = e.position_bins
    near = e.detected & (np.abs(pb - T0) < MATCH_BINS) if target else np.zeros_like(e.detected)
    fa = (e.detected & ~near).sum(axis=1)
    err = (pb - T0)[near]
    return {"fa": fa, "found": near.any(axis=1), "err": err, "n": e.n_echoes}


def _z_mean(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return (a.mean() - b.mean()) / se if se > 0 else 0.0


def _z_sd(a, b):
    """Difference of standard deviations in standard errors (SE of s: √((m4 − s⁴)/n)/(2s))."""
    def sd_se(x):
        x = np.asarray(x, float)
        s2 = x.var(ddof=1)
        m4 = np.mean((x - x.mean()) ** 4)
        return np.sqrt(s2), np.sqrt(max(m4 - s2 * s2, 0.0) / len(x)) / (2 * np.sqrt(s2))
    (sa, ea), (sb, eb) = sd_se(a), sd_se(b)
    return (sa - sb) / np.hypot(ea, eb)


def _compare(e_ref, e_fast, target):
    r, f = _statistics(e_ref, target), _statistics(e_fast, target)
    z = {"false alarms per pixel": _z_mean(r["fa"], f["fa"])}
    for k in range(MAX_ECHOES + 1):
        z[f"pixels with {k} echoes"] = _z_mean(r["n"] == k, f["n"] == k)
    if target:
        z["detection probability"] = _z_mean(r["found"], f["found"])
        z["range error mean"] = _z_mean(r["err"], f["err"])
        z["range error sigma"] = _z_sd(r["err"], f["err"])
    return z, r, f


@pytest.mark.parametrize("name", sorted(DETECTORS))
def test_fast_route_agrees_with_the_per_bin_reference(name):
    det = _detector(**DETECTORS[name])
    probe = apply_receiver_chain(np.zeros((1, 1, 1), np.float32), ChainSettings(det, bin_width_s=BIN_S), 0)
    assert probe.noise_pmf is not None  # (the table route: the exact code law is known)
    assert validity(probe.report, det, PULSE, K_SIGMA, "calibrated", False, True)[0] == "statistical"
    for i, level in enumerate((0.0,) + SNR_POINTS):
        e_ref, e_fast, _ = _routes(det, level, seed=1000 + 10 * i + sorted(DETECTORS).index(name))
        z, r, f = _compare(e_ref, e_fast, level > 0)
        bad = {k: round(v, 2) for k, v in z.items() if not abs(v) <= 3.0}
        assert not bad, f"{name}, level {level}: beyond 3 standard errors: {bad}"
        if level == 0.0:  # enough false alarms to test (≈ 0.5 % of the pixels at 3.5 σ over 62 bins)
            assert r["fa"].sum() > 200 and f["fa"].sum() > 200
        else:
            assert 0.05 < r["found"].mean() < 0.999  # the three points span the detection curve


def test_calibrated_threshold_sigma_and_false_alarm_rate():
    """σ of the matched-filtered noise = √(Σ w_k²) σ_n (white raw noise) — measured on 10⁵ noise rows within 3 SE —
    and the calibrated threshold's false alarms per pixel equal the Gaussian local-maximum expectation (3 SE)."""
    det = _detector(**DETECTORS["pin_background_off"])
    cs = ChainSettings(det, bin_width_s=BIN_S)
    out = apply_receiver_chain(np.zeros((1, N_PIX, N_BINS), np.float32), cs, 7)
    rep = out.report
    sigma = rep["noise_sigma"]
    A = filter_rows(N_BINS, PULSE, [N_BINS // 2])[0]
    filtered = (out.data[0].astype(np.float64) - rep["noise_mean"]) @ A
    predicted = sigma * np.sqrt(np.sum(A ** 2))
    assert abs(predicted - sigma / NORM) < 1e-6 * predicted
    s = filtered.std(ddof=1)
    se = s * np.sqrt(0.5 / N_PIX * (1 + 0.5 * filtered_noise_shape(rep["noise_cumulants"], PULSE)[2]))
    assert abs(s - predicted) < 3 * se, (s, predicted, se)
    e = detect_echoes_noisy(out.data[0], BIN_S, threshold_mode="calibrated", k_sigma=K_SIGMA, pulse=PULSE,
                            max_echoes=MAX_ECHOES, noise_sigma=sigma, baseline=rep["noise_mean"], threads=2)
    assert np.allclose(e.threshold, K_SIGMA * sigma / NORM)
    expected = expected_false_alarms(e.threshold, sigma, np.ones((N_PIX, N_BINS), bool), pulse=PULSE).sum()
    n = e.n_echoes.sum()
    assert abs(n - expected) < 3 * np.sqrt(expected), (n, expected)


def test_gaussian_rates_refused_for_skewed_noise_and_disagree_when_forced():
    """The Gaussian model's limit: multiplied background (APD, F ≈ 4) makes the filtered noise skewed; without the
    exact code law (A/D off) validity() keeps it on the per-bin route, and the Gaussian rates, forced, give false
    alarms per pixel far more than 3 standard errors from the reference.  Geiger histograms, the adaptive
    threshold and a saved counts.npy are refused too."""
    det = _detector(**APD_BACKGROUND_ON)
    e_ref, e_fast, report = _routes(det, 0.0, seed=77, law=False)
    route, reason, err = validity(report, det, PULSE, K_SIGMA, "calibrated", False)
    assert route == "per_bin" and "not Gaussian" in reason and abs(err) > 0.02
    z, r, f = _compare(e_ref, e_fast, False)
    assert abs(z["false alarms per pixel"]) > 10, z
    assert validity(report, _detector(detector_type="geiger"), PULSE, K_SIGMA, "calibrated", False, True)[0] \
        == "per_bin"
    assert validity(report, det, PULSE, K_SIGMA, "adaptive", False, True)[0] == "per_bin"  # needs the noise model
    assert validity(report, det, PULSE, K_SIGMA, "calibrated", True, True)[0] == "per_bin"  # run.save_counts


def test_fast_route_disagrees_on_correlated_noise():
    """The fast route's limit: it assumes white raw noise (the chain's bins are independent).  Noise correlated in
    time (each bin the sum of two neighbouring outputs: a band-limited amplifier, which the chain does not model)
    breaks it: false alarms per pixel far more than 3 standard errors from the per-bin reference."""
    det = _detector(**DETECTORS["pin_background_off"])
    e_ref, e_fast, _ = _routes(det, 0.0, seed=78, correlate=True)
    z, r, f = _compare(e_ref, e_fast, False)
    assert abs(z["false alarms per pixel"]) > 10, z


def test_flash_frame_statistical_route_and_metadata():
    """The pipeline: detection.signal_free_bins = statistical with the calibrated threshold runs the fast route
    whether or not the noise-free cube is saved (no counts kept: digital_waveforms None), the metadata says which
    model ran and why; with run.save_counts the same settings run the per-bin reference and keep the counts."""
    import dataclasses
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
    from bench_flash import bench_config, bench_scene, sensor_pose
    from core.systems.flash import simulate_frame

    cfg = bench_config(quick=True)
    cfg.detector.mode = "noisy"
    cfg.detection.noisy_threshold_mode = "calibrated"
    cfg.detection.signal_free_bins = "statistical"
    cfg.run.save_waveforms = False
    scene, pose = bench_scene(32), sensor_pose()
    fast = simulate_frame(scene, pose, cfg)
    model = fast.stats["receiver"]["detector_model"]
    assert model["signal_free_bins"] == "statistical" and model["threshold"] == "calibrated"
    assert fast.digital_waveforms is None and 0 < model["fraction_simulated"] < 0.5
    assert model["false_alarm_rate_model"].startswith("exact code law")
    assert "n_false_alarms" in fast.stats["receiver"]["false_alarms"]
    # the noise-free cube saved: still the statistical route, the same echoes and false-alarm flags (the cube is
    # the same numbers; only whether it is kept differs)
    cube = simulate_frame(scene, pose, dataclasses.replace(cfg, run=dataclasses.replace(cfg.run,
                                                                                       save_waveforms=True)))
    assert cube.stats["receiver"]["detector_model"]["signal_free_bins"] == "statistical"
    assert cube.digital_waveforms is None and cube.waveforms is not None
    for key in ("range_m", "intensity", "false_alarm", "snr"):
        assert np.array_equal(cube.points[key], fast.points[key]), key
    saved = simulate_frame(scene, pose, dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, save_waveforms=True,
                                                                                        save_counts=True)))
    model = saved.stats["receiver"]["detector_model"]
    assert model["signal_free_bins"] == "per_bin" and "save_counts" in model["reason"]
    assert saved.digital_waveforms is not None and model["threshold"] == "calibrated"
    # the same echoes on both routes where the signal is strong (the target pixels): detection counts agree
    n_fast, n_ref = len(fast.points["range_m"]), len(saved.points["range_m"])
    assert abs(n_fast - n_ref) <= 5 * np.sqrt(n_ref) + 5
