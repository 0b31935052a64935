"""False alarms of the noisy receiver (issue 4: "false alarms from noise are possible and counted"):
classification against the noise-free waveforms and the Gaussian (Rice) expectation, core/physics/detection/noisy.py.

Tolerances: closed forms to 1e-8; counts of Poisson-like events within 4 standard deviations (√E) of the
expectation — a test that fails by chance with probability < 1e-4 — plus, for the adaptive threshold, the
stated model bias of its per-pixel MAD noise estimate (measured ≤ 7 % at 1024 bins).
"""
import numpy as np
import pytest
from scipy import integrate, stats

from core.config.settings import DetectorSettings
from core.physics.detection.false_alarms import (filter_rows, eligible_bins, expected_false_alarms, false_alarm_mask,
                                                 local_max_probability)
from core.physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel
from core.physics.detection.matched_filter import matched_filter
from core.systems.flash import simulate_frame
from scenes import config_for, plate

PULSE = gaussian_pulse_kernel(5e-9, 1e-9)  # 5 ns FWHM, 1 ns bins


def test_local_max_probability_iid_closed_form():
    """Independent samples: P(Z0 > u, Z0 > Z−, Z0 > Z+) = ∫_u^∞ φ(y) Φ(y)² dy (1/3 at u = −∞)."""
    u = np.array([-8.0, 0.0, 2.0, 3.5, 5.0])
    got = local_max_probability(u, np.eye(3))
    want = [integrate.quad(lambda y: stats.norm.pdf(y) * stats.norm.cdf(y) ** 2, x, np.inf, epsabs=1e-14)[0]
            for x in u]
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-14)
    assert got[0] == pytest.approx(1 / 3, rel=1e-8)


def test_local_max_probability_of_matched_filtered_noise():
    """White noise through the matched filter: the fraction of bins that are local maxima above u, counted
    over 4e5 interior bins, within 4 standard errors of the formula at u = 0, 1σ, 2.5σ."""
    rng = np.random.default_rng(0)
    z = matched_filter(rng.standard_normal((100, 4096)).astype(np.float32), PULSE)
    rows = filter_rows(4096, PULSE, [1999, 2000, 2001])
    cov = rows @ rows.T
    sd = np.sqrt(cov[1, 1])
    c = z[:, 1:-1]
    for u in (0.0, sd, 2.5 * sd):
        m = ((c > z[:, :-2]) & (c >= z[:, 2:]) & (c > u))[:, 20:-20]
        p = local_max_probability(np.array([u]), cov)[0]
        assert abs(m.mean() - p) < 4 * np.sqrt(p / m.size)


@pytest.mark.parametrize("mode,k,tol", [("fixed", 3.0, 0.0), ("adaptive", 3.5, 0.07)])
def test_detector_false_alarms_on_pure_gaussian_noise(mode, k, tol):
    """4096 noise-only waveforms of 1024 bins (σ = 7 counts): the detector's count (matched filter, k σ
    threshold, up to 32 echoes) equals the expectation within 4√E (+ the adaptive model bias ``tol``)."""
    rng = np.random.default_rng(11)
    P, B, sigma = 4096, 1024, 7.0
    x = (sigma * rng.standard_normal((P, B)) + 100.0).astype(np.float32)
    sd_det = sigma / np.sqrt(np.sum(PULSE ** 2))
    e = detect_echoes_noisy(x, 1e-9, pulse=PULSE, threshold_mode=mode, threshold=k * sd_det, k_sigma=k,
                            max_echoes=32)
    expected = expected_false_alarms(e.threshold, sigma, np.ones((P, B), bool), PULSE).sum()
    n = int(e.detected.sum())
    assert expected > 300
    assert abs(n - expected) <= 4 * np.sqrt(expected) + tol * expected


def test_false_alarm_mask_and_eligible_bins():
    """Signal at bins 100–104 of pixel 0 (guard 10 bins): detections at 95 and 113.9 are true, 115 and 300 are
    false alarms; every detection in pixel 1 (no signal) is a false alarm, and so are detections near signal
    below the levels."""
    B = 400
    truth = np.zeros((3, B))
    truth[0, 100:105] = [1, 5, 10, 5, 1]
    truth[2, 200] = 1e-9  # below the absolute level: no signal at all
    pix = np.array([0, 0, 0, 0, 1, 2])
    pos = np.array([95.2, 113.9, 115.0, 300.5, 102.0, 200.5])
    fa = false_alarm_mask(pix, pos, truth, guard_bins=10, rel_level=1e-3, abs_level=1e-6)
    assert fa.tolist() == [False, False, True, True, True, True]
    el = eligible_bins(truth, 10, 1e-3, 1e-6)
    assert el[0, 89] and not el[0, 90] and not el[0, 114] and el[0, 115]
    assert el[1].all() and el[2].all()
    assert np.count_nonzero(~el[0]) == 25
    assert np.array_equal(fa, el[pix, np.floor(pos).astype(int)])  # the two routes agree


R = 500.0


def test_pipeline_counts_false_alarms_in_a_pure_noise_region():
    """A plate fills half of the field of view; the other half sees nothing (pure noise). PIN detector, 30 e⁻
    read noise, fine A/D (Δ = 2 e⁻, σ = 15 counts), matched filter, fixed threshold at 2.5 σ of the detection
    waveform, up to 32 echoes: the false alarms in the empty pixels and in the whole frame equal the Gaussian
    expectation in the run metadata within 4√E; no echo on the plate's return is counted as a false alarm."""
    cfg = config_for(R, pixels=32, subsamples=2, fov_rad=5e-3, bins=1024, bin_s=1e-9, margin_bins=200)
    cfg.detector = DetectorSettings(mode="noisy", detector_type="pin", read_noise_e=30.0, background_rate_photons_per_s=0.0,
                                    enable_dark_current=False, adc_bits=16, adc_full_scale_e=2.0 * 65536,
                                    adc_offset_counts=2000)
    sigma_counts = np.sqrt((30.0 / 2.0) ** 2 + 1 / 12)
    cfg.detection.noisy_threshold_mode = "fixed"
    cfg.detection.threshold_counts = 2.5 * sigma_counts / np.sqrt(np.sum(PULSE ** 2))
    cfg.detection.max_echoes = 32
    cfg.laser.pulse_energy_j = 1e-3
    res = simulate_frame(plate(R, 0.7, offset=(0.7, 0.0, 0.0)), np.eye(4), cfg)
    fa = res.stats["receiver"]["false_alarms"]
    assert res.stats["receiver"]["noise_sigma"] == pytest.approx(sigma_counts, rel=1e-3)
    assert 0.3 * 32 ** 2 < fa["n_empty_pixels"] < 0.9 * 32 ** 2
    e_empty = fa["expected_false_alarms_in_empty_pixels_gaussian"]
    assert e_empty > 500
    assert abs(fa["n_false_alarms_in_empty_pixels"] - e_empty) <= 4 * np.sqrt(e_empty)
    e_all = fa["expected_false_alarms_gaussian"]
    assert abs(fa["n_false_alarms"] - e_all) <= 4 * np.sqrt(e_all)
    assert fa["false_alarms_per_pixel"] == pytest.approx(fa["n_false_alarms"] / 32 ** 2)
    # every plate pixel detects its return and that echo is not a false alarm (a few noise peaks inside the
    # ±2-pulse-width guard around a return count as true: ≤ 20 % extra at this threshold)
    plate_pixels = fa["n_pixels"] - fa["n_empty_pixels"]
    n_true = res.stats["n_points"] - fa["n_false_alarms"]
    assert plate_pixels <= n_true <= 1.2 * plate_pixels


@pytest.mark.parametrize("n_bins", [5, 40, 1668])
def test_matched_filter_is_scipys_correlation_bit_for_bit(n_bins):
    """The compiled matched filter (interior summed tap by tap over all bins, edges clamped) is SciPy's
    ndimage.correlate1d ('nearest' edges, float32 output) bit for bit, also for rows shorter than the pulse."""
    from scipy import ndimage

    rng = np.random.default_rng(n_bins)
    y = (rng.standard_normal((7, n_bins)) * 30 + rng.integers(0, 5, (7, 1))).astype(np.float32)
    k = np.asarray(PULSE, dtype=np.float64)
    w = (k / np.sum(k * k)).astype(np.float32)
    expect = ndimage.correlate1d(y, w, axis=-1, mode="nearest", output=np.float32)
    assert np.array_equal(matched_filter(y, PULSE), expect)


def _eligible_by_definition(truth, guard, rel, lvl):
    """The definition of eligible_bins, bin by bin (slow): no bin within ±guard with t > max(rel·peak, lvl), t > 0."""
    t = np.asarray(truth, dtype=np.float64)
    el = np.ones(t.shape, bool)
    for p in range(t.shape[0]):
        if np.isnan(t[p]).any():
            continue
        level = max(rel * t[p].max(), lvl)
        for j in np.flatnonzero((t[p] > level) & (t[p] > 0)):
            el[p, max(0, j - guard):j + guard + 1] = False
    return el


@pytest.mark.parametrize("n_bins", [1, 5, 63, 64, 65, 200])
def test_eligible_bins_compiled_pass_equals_the_definition(n_bins):
    """Random sparse signal (runs, isolated bins, block edges of the compiled 64-bin test, both row ends), rows
    with a NaN, all-zero and negative rows, guard 0 … 12, float32, float64 and integer waveforms, 1 and 3
    threads: the compiled pass gives the definition's bins exactly."""
    rng = np.random.default_rng(n_bins)
    P = 700
    t = np.where(rng.random((P, n_bins)) < 0.03, rng.exponential(1.0, (P, n_bins)), 0.0)
    t[::7, -1] = 5.0
    t[::11, 0] = 5.0
    t[3] = np.nan
    t[4] = 0.0
    t[5] = -1.0
    t[6, n_bins // 2] = 1e-9
    for guard in (0, 1, 12):
        for dtype in (np.float32, np.float64, np.int64):
            x = (t * 10 if dtype is np.int64 else t)
            x = np.nan_to_num(x).astype(dtype) if dtype is np.int64 else x.astype(dtype)
            want = _eligible_by_definition(x, guard, 0.05, 1e-6)
            for threads in (1, 3):
                assert np.array_equal(eligible_bins(x, guard, 0.05, 1e-6, threads=threads), want), (guard, dtype)


def test_local_max_probability_of_a_stack_equals_single_calls_bit_for_bit():
    """A stack of covariances (the matched filter's edge positions and the interior) in one call: each row is
    the single call's result bit for bit."""
    B = 300
    covs = np.array([(r := filter_rows(B, PULSE, [j - 1, j, j + 1])) @ r.T * 2.5 for j in (1, 2, 5, 150, 298)])
    u = np.linspace(0.3, 4.0, 17)
    stack = local_max_probability(u, covs)
    for c, row in zip(covs, stack):
        assert np.array_equal(local_max_probability(u, c), row)


def test_expected_false_alarms_independent_of_threads():
    rng = np.random.default_rng(5)
    el = rng.random((900, 500)) < 0.9
    thr = rng.uniform(1.0, 3.0, 900)
    thr[::50] = np.inf
    one = expected_false_alarms(thr, 1.3, el, PULSE, threads=1)
    assert np.array_equal(one, expected_false_alarms(thr, 1.3, el, PULSE, threads=3))
    assert np.all(one[::50] == 0) and np.all(one[1::50] > 0)




def _expected_by_quadrature(thr, sigma, el, pulse):
    """The definition of expected_false_alarms, pixel by pixel: Σ over eligible bins j of the local-maximum rate
    of position j at the pixel's own threshold (no lattice, no interpolation)."""
    from core.physics.detection.false_alarms import _positions

    P, B = el.shape
    edges, interior = _positions(B, pulse)
    out = np.zeros(P)
    ok = np.isfinite(thr) & (thr > 0)
    for j in edges + ([interior[0]] if interior else []):
        rows = filter_rows(B, pulse, [j - 1, j, j + 1])
        rate = np.zeros(P)
        rate[ok] = local_max_probability(thr[ok], sigma ** 2 * rows @ rows.T)
        n = el[:, j] if j in edges else np.count_nonzero(el[:, interior[0]:interior[1]], axis=1)
        out += rate * n
    return out


@pytest.mark.parametrize("n_bins,pulse", [(1024, PULSE), (30, PULSE), (12, PULSE), (500, None)])
def test_expected_false_alarms_equals_the_quadrature_at_each_threshold(n_bins, pulse):
    """The lattice of rates (1/32 σ, cubic interpolation of log-rate + t²/2v₀) against the quadrature at each
    pixel's own threshold, from 0.02 σ to 18 σ (rates from 0.3 to below 1e-250), within 1e-7 relative, pixel
    by pixel; where the quadrature underflows to 0 (60 σ), below 1e-280; inf, NaN, 0 and negative thresholds: 0."""
    rng = np.random.default_rng(n_bins)
    sigma = 1.7
    thr = sigma * np.concatenate([rng.uniform(0.02, 8.0, 150), rng.uniform(8.0, 18.0, 30), [25.0, 30.0, 60.0],
                                  [np.inf, np.nan, 0.0, -1.0, 1.0 / 32, 2.0]])
    el = rng.random((thr.size, n_bins)) < 0.8
    got = expected_false_alarms(thr, sigma, el, pulse)
    want = _expected_by_quadrature(thr, sigma, el, pulse)
    assert np.all(got[-6:-2] == 0)
    ok = want > 0
    assert np.all(ok[:180])
    assert np.max(np.abs(got[ok] / want[ok] - 1)) <= 1e-7
    assert np.all(got[~ok] < 1e-280)


def test_expected_false_alarms_independent_of_what_was_computed_before():
    """Rates are kept between calls (a run's frames share them): a pixel's expectation is the same bit for bit
    whether the lattice was empty, filled by other thresholds first, or filled in the same call."""
    from core.physics.detection.false_alarms import _rate_lattice

    rng = np.random.default_rng(9)
    el = rng.random((300, 400)) < 0.9
    a, b = rng.uniform(1.0, 4.0, 300), rng.uniform(3.0, 9.0, 300)
    _rate_lattice.cache_clear()
    first = expected_false_alarms(a, 1.1, el, PULSE)
    _rate_lattice.cache_clear()
    expected_false_alarms(b, 1.1, el, PULSE)
    assert np.array_equal(expected_false_alarms(a, 1.1, el, PULSE), first)
    _rate_lattice.cache_clear()
    both = expected_false_alarms(np.concatenate([b, a]), 1.1, np.concatenate([el, el]), PULSE, threads=3)
    assert np.array_equal(both[300:], first)


def test_row_level_is_numpys_maximum_of_the_scaled_peak_and_the_floor():
    """The compiled level of a row (classification's signal level): np.maximum(rel × row max, abs) to the bit,
    in the row's float type (float32 rows: float32 arithmetic, as NumPy does), NaN for a row holding a NaN."""
    from core.physics.detection.false_alarms import _row_level

    rng = np.random.default_rng(3)
    for dt in (np.float32, np.float64):
        t = (rng.standard_normal((400, 37)) ** 3).astype(dt)
        t[5, 3], t[7, 0], t[9] = np.nan, np.nan, -1.0
        for rel, floor in ((1e-3, 0.0), (1e-3, 0.05), (0.3, 1e-9)):
            want = np.maximum(rel * t.max(axis=1), floor)
            got = np.array([_row_level(row, t.dtype.type(rel), t.dtype.type(floor)) for row in t]).astype(dt)
            assert np.array_equal(got, want, equal_nan=True), (dt, rel, floor)
            assert np.isnan(got[[5, 7]]).all() and not np.isnan(np.delete(got, [5, 7])).any()
