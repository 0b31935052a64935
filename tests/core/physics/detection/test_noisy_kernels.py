"""The compiled noisy-detection kernels (core/physics/detection/noisy.py) against their NumPy/SciPy formulation,
bit for bit: the robust baseline and noise (np.median, the MAD, the quiet-90 % rms where the MAD is 0), the
matched filter (scipy.ndimage.correlate1d) and the whole detection (threshold, greedy maxima, interpolation)
written out in NumPy.  Rows of every kind the kernels treat differently: A/D counts (counting median, MAD 0 or
not), float rows (order statistics by bracketing), short rows, duplicates, NaN and inf, both parities of the
row length.  Tolerance: none (np.array_equal; −0.0 equals +0.0).
"""
import inspect
import sys

import numpy as np
import pytest
from scipy import ndimage

from core.physics.detection.noisy import (detect_echoes_noisy, gaussian_peak, gaussian_pulse_kernel, parabolic_offset,
                                          parabolic_peak, gaussian_offset)
from core.physics.detection.matched_filter import matched_filter
from core.physics.detection.row_statistics import MAD_TO_SIGMA, robust_baseline_noise


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


# ----------------------------------------------------------------------------------------------------------
# Exact selection whatever the model that chooses its probes (row_statistics._order_stats32)
# ----------------------------------------------------------------------------------------------------------
def adversarial_rows(rng, n):
    """Float32 rows the probes' model (median near a centre, normal spread) does not describe, (k, n)."""
    rows = [
        rng.standard_exponential(n) * 3.0,  # skewed, all positive
        rng.lognormal(0.0, 2.0, n),  # strongly skewed
        np.clip(rng.standard_cauchy(n) * 5.0, -3e38, 3e38),  # heavy tails
        np.where(rng.random(n) < 0.7, rng.uniform(200, 900, n), rng.standard_normal(n)),  # mostly echoes
        np.full(n, -2.5),  # constant
        np.where(np.arange(n) % 2 == 0, 1.0, 3.0),  # two values, half each
        np.where(rng.random(n) < 0.9, 4.25, rng.standard_normal(n)),  # 90 % one value
        np.round(rng.standard_normal(n) * 3) * 0.5 + 0.25,  # few values, many duplicates
        np.where(rng.random(n) < 0.5, -0.0, 0.0) * np.where(rng.random(n) < 0.9, 1.0, rng.standard_normal(n)),
        rng.standard_normal(n) * 1e-42,  # subnormal
        np.where(rng.random(n) < 0.3, rng.choice([-3e38, 3e38], n), rng.standard_normal(n)),  # huge values
        np.where(rng.random(n) < 0.2, rng.choice([-np.inf, np.inf], n), rng.standard_normal(n)),  # infinities
        np.where(np.arange(n) < 0.7 * n, -np.inf, rng.standard_normal(n)),  # the median is −inf
        np.where(np.arange(n) == n // 3, np.nan, rng.standard_normal(n)),  # one NaN
        rng.standard_normal(n) * 0.01 + 1e6,  # far from the model's centre
        rng.integers(0, 3, n) * 2.0 + 2.0 ** 25,  # whole numbers of few values where float32 skips odd ones
    ]
    return np.array(rows, dtype=np.float32)


#: (centre, spread) of the model handed to the selection: from exact to absurd; spread ≤ 0 or not finite
#: means none.
MODELS = [(0.0, 1.0), (0.0, 0.3), (0.0, 30.0), (50.0, 1.0), (-1e30, 1e-30), (0.0, 1e-300), (1e38, 1e38),
          (np.nan, 1.0), (np.inf, 1.0), (0.0, np.nan), (0.0, np.inf), (0.0, 0.0), (0.0, -1.0)]


def sorted_order_stats(x, k_lo, k_hi):
    """The order statistics of x by sorting the order keys (−0 before +0), NaN if x holds a NaN."""
    if np.isnan(x).any():
        return np.float32(np.nan), np.float32(np.nan)
    bits = x.view(np.int32)
    keys = np.sort(bits ^ ((bits >> 31) & 0x7FFFFFFF))
    vals = (keys ^ ((keys >> 31) & 0x7FFFFFFF)).astype(np.int32).view(np.float32)
    return vals[k_lo], vals[k_hi]


@pytest.mark.parametrize("n", [7, 64, 255, 1024, 1025, 1668])
def test_baseline_noise_row_is_numpys_whatever_the_model(n):
    """The median and σ of rows of every kind, each with every model (centre, spread) of the probes: NumPy's."""
    from core.physics.detection.row_statistics import baseline_noise_row, row_scratch
    rng = np.random.default_rng(100 + n)
    y = np.concatenate([adversarial_rows(rng, n), row_families(rng, n, p=4)])
    with np.errstate(invalid="ignore"):
        want_base, want_sig = numpy_baseline_noise(y)
    scratch = row_scratch(n)
    for r in range(len(y)):
        for centre, spread in MODELS + [(float(want_base[r]), float(want_sig[r]))]:
            base, sig = baseline_noise_row(y[r], False, np.float32(0), np.float32(0), centre, spread, *scratch)
            assert np.array_equal(base, want_base[r], equal_nan=True), (r, centre, spread)
            assert np.array_equal(sig, want_sig[r], equal_nan=True), (r, centre, spread)


def traced(func, *args):
    """func(*args) run as Python (its compiled callees compiled), and the set of its own lines executed."""
    code, hit = func.__code__, set()

    def tracer(frame, event, arg):
        if frame.f_code is not code:
            return None
        if event == "line":
            hit.add(frame.f_lineno)
        return tracer
    sys.settrace(tracer)
    try:
        return func(*args), hit
    finally:
        sys.settrace(None)


def test_every_branch_of_the_selection_runs_and_is_exact():
    """The selection's Python source run on the adversarial rows with every model, traced line by line: each
    rank pair (odd and even rows) equals the sorted keys' and every branch — model or sample first probes, the
    second sample probe alone, Newton steps, interpolation, the bisections (in value and in key), probes that
    find their neighbours or not, the exit between two ranks, stepping up and stepping down with the next
    value known or not, NaN — runs at least once."""
    from core.physics.detection import row_statistics as rs
    func = rs._order_stats32.py_func
    lines, first = inspect.getsourcelines(func)
    markers = {"model probe": "p1, n_prop = _value_key(guess", "sample probes": "p2 = np.int64(_select(",
               "second sample probe alone": "t, i_prop = p2, 2", "Newton": "# Newton step from the near end",
               "interpolation": "v_lo = np.float64(", "value bisection": "t = _value_key(v, cast, castf) if",
               "key bisection": "t = (lo + hi) >> 1",
               "between two ranks": "return _key_value(below_t, cast, castf), _key_value(above_t",
               "neighbours with the probe": "c, below_t, above_t = _around(keys, n, t)\n",
               "neighbours after the probe": "(not found by the pass above)",
               "step up, next unknown": "v = _step_up(keys, n, lo)[1]",
               "step down, next unknown": "v = _step_down(keys, n, hi + 1)[1]",
               "step up": "b = v if k_hi < f_v else nxt", "step down": "a = v if c <= k_lo else prv",
               "NaN": "return np.float32(np.nan), np.float32(np.nan)"}
    where = {name: [first + i for i, text in enumerate(lines) if m in text] for name, m in markers.items()}
    assert all(len(v) == 1 for v in where.values()), where
    up_ab, down_ab = [first + i for i, text in enumerate(lines) if "a = b = v" in text]  # step up, step down
    derived = {"step up, next known": (up_ab, where["step up, next unknown"][0]),
               "step down, next known": (down_ab, where["step down, next unknown"][0])}
    seen = set()
    rng = np.random.default_rng(7)
    for n in (255, 256, 1024, 1025):
        y = np.concatenate([adversarial_rows(rng, n), row_families(rng, n, p=2)])
        keys, s1, s2, cast = (np.empty(n, np.int32) for _ in range(4))
        for r in range(len(y)):
            mn, mx = rs._float_keys(y[r], keys)
            for k_lo, k_hi in ((n // 2 - 1 + n % 2, n // 2), (n // 3, n // 3), (n - 2, n - 1), (0, 1)):
                want = sorted_order_stats(y[r], k_lo, k_hi)
                for centre, spread in MODELS:
                    density = n * 0.4 / spread if spread > 0 and np.isfinite(spread) else 0.0
                    with np.errstate(all="ignore"):  # (inf − inf in Python, as in the compiled kernel)
                        got, hit = traced(func, keys, n, mn, mx, k_lo, k_hi, s1, s2, cast, centre, density)
                    compiled = rs._order_stats32(keys, n, mn, mx, k_lo, k_hi, s1, s2, cast, centre, density)
                    for g in (got, compiled):
                        assert np.array_equal(np.array(g, np.float32).view(np.int32),
                                              np.array(want, np.float32).view(np.int32)) or \
                            (np.isnan(want[0]) and np.isnan(g).all()), (n, r, k_lo, centre, spread)
                    seen |= {name for name, ln in where.items() if ln[0] in hit}
                    seen |= {name for name, (ran, not_ran) in derived.items() if ran in hit and not_ran not in hit}
    assert seen == set(markers) | set(derived), set(markers) | set(derived) - seen


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("dtype", [np.uint16, np.int8, np.int64, np.float64, np.float32])
def test_detection_of_adversarial_rows_of_any_type_is_its_numpy_formulation(dtype, threads):
    """Rows full of echoes, constant, two-valued, skewed, all-zero, negative (int8), beyond the counting range
    (int64), with the matched filter and the adaptive threshold: bit for bit the NumPy formulation on the
    float32 copy, on 1 and 3 threads."""
    rng = np.random.default_rng(11)
    n = 1024
    rows = [rng.poisson(2.0, n) + 13, np.full(n, 16), np.where(np.arange(n) % 2 == 0, 15, 17),
            np.where(rng.random(n) < 0.7, rng.integers(60, 120, n), 16),  # mostly echo
            rng.geometric(0.3, n) + 10, np.zeros(n, np.int64)]
    for _ in range(300):  # noise rows with an echo or two
        row = rng.poisson(rng.uniform(0.2, 3.0), n) + 14
        for _ in range(rng.integers(0, 3)):
            j = rng.integers(20, n - 20)
            row[j - 3:j + 4] += rng.integers(5, 100)
        rows.append(row)
    y = np.array(rows)
    if dtype == np.int8:
        y = np.clip(y - 40, -128, 127)
    if dtype == np.int64:
        y[::7] = y[::7] * 3 + rng.integers(0, 1 << 40, (1, n))  # beyond the counting range
    if dtype in (np.float64, np.float32):
        y = y + rng.standard_normal(y.shape) * 0.3
    y = y.astype(dtype)
    pulse = gaussian_pulse_kernel(5e-9, 1e-9)
    with np.errstate(all="ignore"):
        got = detect_echoes_noisy(y, 1e-9, pulse=pulse, k_sigma=4.0, max_echoes=3, min_noise_sigma=0.5,
                                  threads=threads)
        pos, amp, base, sig, thr = numpy_detection(y.astype(np.float32), pulse, 4.0, 0.5, 3,
                                                   max(3, len(pulse) // 2))
    assert np.count_nonzero(got.detected) > 100
    assert np.array_equal(got.position_bins, pos, equal_nan=True)
    assert np.array_equal(got.amplitude, amp, equal_nan=True)
    assert np.array_equal(got.baseline, base)
    assert np.array_equal(got.noise_sigma, sig)
    assert np.array_equal(got.threshold, thr)


@pytest.mark.parametrize("fwhm_bins", [1.2, 5.0, 20.0])
def test_matched_filter_of_halves_summed_in_float32_pairs_is_scipys(fwhm_bins):
    """Rows of whole numbers minus a whole or half baseline up to the bound of the float32 pair sums
    (EXACT_PAIR_VALUE): the filter with exact_pairs is SciPy's correlate1d bit for bit; the detection takes
    that route for integer rows only when the bound holds (int64 rows beyond it: the adversarial test above)."""
    from core.physics.detection.matched_filter import EXACT_PAIR_VALUE, FILTER_BLOCK, correlate_row
    pulse = gaussian_pulse_kernel(fwhm_bins * 1e-9, 1e-9)
    k = np.asarray(pulse, dtype=np.float64)
    w = (k / np.sum(k * k)).astype(np.float32)
    rng = np.random.default_rng(int(fwhm_bins * 10))
    big = EXACT_PAIR_VALUE - 1
    for b32 in (np.float32(0.0), np.float32(16.5), np.float32(-3.0), np.float32(-0.5)):
        for scale in (3.0, 1e3, big / 2):
            lo, hi = np.ceil(b32 - big), np.floor(b32 + big)  # the extreme whole numbers within the bound
            y = np.clip(np.round(rng.standard_normal(1030) * scale + b32), lo, hi)
            y[::97], y[5::89] = hi, lo
            y = y.astype(np.float32)
            assert np.all(np.abs(y - b32) < EXACT_PAIR_VALUE) and np.all(y == np.round(y))
            out = np.empty_like(y)
            correlate_row(y, b32, w.astype(np.float64), np.empty(len(y) + len(w) - 1, np.float32),
                          np.empty(FILTER_BLOCK), out, True)
            want = ndimage.correlate1d(y - b32, w, mode="nearest", output=np.float32)
            assert np.array_equal(out.view(np.int32), want.view(np.int32)), (b32, scale)
