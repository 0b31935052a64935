"""The compiled noisy-detection kernels (core/physics/detection/noisy.py) against their NumPy/SciPy formulation,
bit for bit: the robust baseline and noise (np.median, the MAD, the quiet-90 % rms where the MAD is 0), the
matched filter (scipy.ndimage.correlate1d) and the whole detection (threshold, greedy maxima, interpolation)
written out in NumPy.  Rows of every kind the kernels treat differently: A/D counts (counting median, MAD 0 or
not), float rows (order statistics by bracketing), short rows, duplicates, NaN and inf, both parities of the
row length.  Tolerance: none (np.array_equal; −0.0 equals +0.0).
"""
import numpy as np
import pytest
from scipy import ndimage

from core.physics.detection.noisy import (detect_echoes_noisy, gaussian_peak, gaussian_pulse_kernel, parabolic_offset,
                                          parabolic_peak, gaussian_offset)
from core.physics.detection.row_statistics import MAD_TO_SIGMA, matched_filter, robust_baseline_noise


def numpy_baseline_noise(y):
    """Median and σ of each float32 row as NumPy computes them (the documented estimator)."""
    base = np.median(y, axis=-1)
    dev = np.abs(y - base[:, None])
    sig = np.median(dev, axis=-1).astype(np.float64) * MAD_TO_SIGMA
    for r in np.nonzero(sig == 0)[0]:  # MAD 0: rms deviation of the quietest 90 %
        d = dev[r].astype(np.float64)
        quiet = d <= np.quantile(d, 0.9)
        sig[r] = np.sqrt(np.sum(np.where(quiet, d * d, 0.0)) / max(np.count_nonzero(quiet), 1))
    return base.astype(np.float64), sig


def row_families(rng, n, p=40):
    """Rows of every kind, float32, (k × p, n)."""
    echoes = np.zeros((p, n), np.float32)
    for r in range(p):
        for _ in range(rng.integers(0, 4)):
            j = rng.integers(0, n)
            echoes[r, max(0, j - 3):j + 3] += rng.uniform(5, 300)
    fam = [
        rng.standard_normal((p, n)) * rng.uniform(0.1, 40, (p, 1)) + rng.uniform(-50, 100, (p, 1)) + echoes,
        np.round(rng.standard_normal((p, n)) * rng.uniform(0.05, 3, (p, 1)) + 16) + np.round(echoes),  # A/D
        rng.poisson(rng.uniform(0.01, 4, (p, 1)), (p, n)) + 13.0,  # A/D, mostly MAD 0
        np.round(rng.standard_normal((p, n)) * 0.3) + 16 + echoes,  # MAD 0, float (echoes not whole)
        np.where(rng.random((p, n)) < 0.1, rng.standard_normal((p, n)), 0.25),  # float duplicates, MAD 0
        rng.integers(-3, 3, (p, n)) * 0.5,  # half counts
        rng.integers(0, 70000, (p, n)),  # integers spanning more than the counting range
        rng.integers(0, 3, (p, n)) + 5e6,  # large counts
        np.full((p, n), 7.0),
    ]
    return np.concatenate(fam).astype(np.float32)


@pytest.mark.parametrize("n", [1, 2, 3, 8, 63, 64, 65, 255, 256, 257, 1000, 1024, 1025, 1668])
def test_robust_baseline_noise_is_numpys_median_and_mad(n):
    rng = np.random.default_rng(n)
    y = row_families(rng, n)
    base, sig = robust_baseline_noise(y)
    want_base, want_sig = numpy_baseline_noise(y)
    assert np.array_equal(base, want_base)
    assert np.array_equal(sig, want_sig)
    if n >= 8:  # both estimators exercised: MAD and the quiet-90 % rms
        mad = np.median(np.abs(y - np.median(y, axis=-1)[:, None]), axis=-1)
        assert np.any(mad == 0) and np.any(mad > 0)


def test_robust_baseline_noise_nan_and_inf_rows_as_numpy():
    rng = np.random.default_rng(3)
    y = rng.standard_normal((6, 1024)).astype(np.float32)
    y[0, 10] = np.nan
    y[1, :3] = np.inf
    y[2, :700] = -np.inf  # the median itself is −inf
    y[3, 5] = -np.inf
    y[4, :] = np.nan
    with np.errstate(invalid="ignore"):
        want_base, want_sig = numpy_baseline_noise(y)
    base, sig = robust_baseline_noise(y)
    assert np.isnan(base[0]) and np.isnan(base[4])
    assert np.array_equal(base, want_base, equal_nan=True)
    assert np.array_equal(sig, want_sig, equal_nan=True)


@pytest.mark.parametrize("n_bins", [1, 2, 3, 255, 256, 257, 511, 513, 1024, 1668])
@pytest.mark.parametrize("fwhm_bins", [0.8, 1.2, 2.0, 5.0, 9.0, 20.0])
def test_matched_filter_is_scipys_correlation_bit_for_bit_at_any_length_and_tap_count(n_bins, fwhm_bins):
    """Block edges of the compiled filter (256 outputs), taps in fours and the rest, rows shorter than the pulse.
    Some rows mix values of ±1e12 among O(1) ones: large terms cancel, so that another summation order shows."""
    pulse = gaussian_pulse_kernel(fwhm_bins * 1e-9, 1e-9)
    rng = np.random.default_rng(n_bins)
    y = (rng.standard_normal((6, n_bins)) * 30 + rng.integers(0, 5, (6, 1))).astype(np.float32)
    y[3:] += np.where(rng.random((3, n_bins)) < 0.3, rng.choice([-1e12, 1e12], (3, n_bins)), 0).astype(np.float32)
    k = np.asarray(pulse, dtype=np.float64)
    w = (k / np.sum(k * k)).astype(np.float32)
    expect = ndimage.correlate1d(y, w, axis=-1, mode="nearest", output=np.float32)
    assert np.array_equal(matched_filter(y, pulse), expect)


def numpy_detection(y, pulse, k_sigma, floor, max_echoes, min_sep):
    """The detection of detect_echoes_noisy (adaptive threshold, matched filter, Gaussian interpolation) written
    out in NumPy/SciPy and Python loops: (positions in bins, amplitudes, baseline, σ, threshold)."""
    base, sig = numpy_baseline_noise(y)
    sig = np.maximum(sig, floor)
    k = np.asarray(pulse, dtype=np.float64)
    w = (k / np.sum(k * k)).astype(np.float32)
    norm = float(np.sqrt(np.sum(k * k)))
    yd = ndimage.correlate1d(y - base.astype(np.float32)[:, None], w, axis=-1, mode="nearest", output=np.float32)
    thr = k_sigma * np.maximum(numpy_baseline_noise(yd)[1], floor / norm)
    P, B = y.shape
    pos = np.full((P, max_echoes), -1)
    for r in range(P):
        c = yd[r]
        t = np.float32(thr[r])
        cand = [j for j in range(1, B - 1) if c[j] > c[j - 1] and c[j] >= c[j + 1] and c[j] > t]
        taken = []
        while cand and len(taken) < max_echoes:
            j = max(cand, key=lambda q: (c[q], -q))  # strongest, the earliest of equals
            taken.append(j)
            cand = [q for q in cand if abs(q - j) >= min_sep]
        pos[r, :len(taken)] = sorted(taken)
    det = pos >= 0
    jj = np.where(det, pos, 1)
    rows = np.arange(P)[:, None]
    ym, y0, yp = (yd[rows, jj + s].astype(np.float64) for s in (-1, 0, 1))
    with np.errstate(all="ignore"):
        d_par = parabolic_offset(ym, y0, yp)
        d_par = np.where(np.isfinite(d_par), d_par, 0.0)
        d_g = gaussian_offset(ym, y0, yp)
        okg = np.isfinite(d_g)
        a_g = gaussian_peak(np.where(okg, ym, 1.0), np.where(okg, y0, 1.0), np.where(okg, yp, 1.0),
                            np.where(okg, d_g, 0.0))
    delta = np.where(okg, d_g, d_par)
    amp = np.where(okg, a_g, parabolic_peak(ym, y0, yp, d_par))
    return (np.where(det, jj + 0.5 + delta, np.nan), np.where(det, amp, np.nan), base, sig, thr)


@pytest.mark.parametrize("n_bins", [300, 1024, 1025])
@pytest.mark.parametrize("threads", [1, 3])
def test_detection_is_its_numpy_formulation_bit_for_bit(n_bins, threads):
    rng = np.random.default_rng(n_bins + threads)
    y = row_families(rng, n_bins, p=12)
    pulse = gaussian_pulse_kernel(5e-9, 1e-9)
    floor = 0.4
    with np.errstate(all="ignore"):
        got = detect_echoes_noisy(y, 1e-9, pulse=pulse, k_sigma=4.0, max_echoes=4, min_noise_sigma=floor,
                                  threads=threads)
    pos, amp, base, sig, thr = numpy_detection(y, pulse, 4.0, floor, 4, max(3, len(pulse) // 2))
    assert np.count_nonzero(got.detected) > 20
    assert np.array_equal(got.position_bins, pos, equal_nan=True)
    assert np.array_equal(got.amplitude, amp, equal_nan=True)
    assert np.array_equal(got.baseline, base)
    assert np.array_equal(got.noise_sigma, sig)
    assert np.array_equal(got.threshold, thr)


@pytest.mark.parametrize("d_outer, d_inner", [(9, 8), (7, 1), (5, 4), (4, 1), (8, 5), (3, 2)])
def test_matched_filter_sums_in_scipys_order(d_outer, d_inner):
    """A 19-tap pulse (as the receiver's 5 ns pulse at 1 ns bins) with power-of-two weights (centre 1/4, two pairs
    of 1/8) and bins 4, 2⁵⁶, −2⁵⁶ around an output: SciPy's order (centre, then the pairs from the outermost in)
    gives (1 + 2⁵³) − 2⁵³ = 0; the pairs the other way round, or the centre last, would give 1.  Pairs in one
    group of four taps, in two, in a group and the last tap; outputs on block edges."""
    p = np.zeros(19)
    p[9] = 2.0
    p[[9 - d_outer, 9 + d_outer, 9 - d_inner, 9 + d_inner]] = 1.0
    centre = np.arange(16, 1000, 40)  # 256 among them
    y = np.zeros((2, 1024), np.float32)
    y[:, centre] = 4.0
    y[:, centre - d_outer] = 2.0 ** 56
    y[:, centre - d_inner] = -(2.0 ** 56)
    got = matched_filter(y, p)
    w = (p / np.sum(p * p)).astype(np.float32)
    assert np.array_equal(got, ndimage.correlate1d(y, w, axis=-1, mode="nearest", output=np.float32))
    assert np.all(got[:, centre] == 0.0)
    assert (1.0 + -(2.0 ** 53)) + 2.0 ** 53 == 1.0  # the other order


def test_detection_of_a_code_cube_is_that_of_its_float32_copy():
    """A/D codes (uint16) are converted a few rows at a time: the same echoes as on the float32 copy."""
    rng = np.random.default_rng(5)
    codes = (rng.poisson(2.0, (700, 512)) + 13).astype(np.uint16)
    codes[:, 200:206] += rng.integers(0, 40, (700, 1)).astype(np.uint16)
    pulse = gaussian_pulse_kernel(5e-9, 1e-9)
    for threads in (1, 3):
        a = detect_echoes_noisy(codes, 1e-9, pulse=pulse, threads=threads)
        b = detect_echoes_noisy(codes.astype(np.float32), 1e-9, pulse=pulse, threads=threads)
        assert np.count_nonzero(a.detected) > 300
        for f in ("time_s", "amplitude", "snr", "detected", "baseline", "noise_sigma", "threshold"):
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f
