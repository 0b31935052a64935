"""Noisy detection with a threshold known before the row is filtered (calibrated: the noise model's σ and
baseline given) screens each row of A/D codes: the row filtered in float32, the exact outputs (SciPy's float64 sum
rounded to float32) only near the threshold (core/physics/detection/noisy.py, matched_filter.py).  The echoes must
be those of the whole row filtered exactly: checked here bit for bit against SciPy's correlate1d and a Python
selection, on rows whose maxima sit at the threshold to within float32 rounding, on rows long enough in signal
to be filtered in full, and on codes up to 2¹⁶ − 1."""
import numpy as np
import pytest
from scipy import ndimage

from core.physics.detection.noisy import SCREEN_FRACTION, detect_echoes_noisy, gaussian_pulse_kernel


def reference(y, base, sigma, pulse, k_sigma, max_echoes, min_sep):
    """Positions and (yd[j − 1], yd[j], yd[j + 1]) of the chosen maxima, in NumPy/SciPy and Python loops."""
    k = np.asarray(pulse, dtype=np.float64)
    w = (k / np.sum(k * k)).astype(np.float32)
    norm = float(np.sqrt(np.sum(k * k)))
    yd = ndimage.correlate1d(y.astype(np.float32) - np.float32(base), w, axis=-1, mode="nearest",
                             output=np.float32)
    t = np.float32(k_sigma * (sigma / norm))
    P, B = y.shape
    pos = np.full((P, max_echoes), -1)
    for r in range(P):
        c = yd[r]
        cand = [j for j in range(1, B - 1) if c[j] > c[j - 1] and c[j] >= c[j + 1] and c[j] > t]
        taken = []
        while cand and len(taken) < max_echoes:
            j = max(cand, key=lambda q: (c[q], -q))
            taken.append(j)
            cand = [q for q in cand if abs(q - j) >= min_sep]
        pos[r, :len(taken)] = sorted(taken)
    return pos, yd, t


def code_rows(rng, n_rows, n_bins, pulse, t, offset, dtype, scale):
    """Rows of codes: noise around ``offset``, one to three pulses each with filtered peaks spread over 0.7–1.3 × the
    threshold ``t`` (many maxima within float32 rounding of it: the same pulse at a few nearby amplitudes), every
    8th row a long bright stretch (filtered in full), every 16th a pulse near full scale."""
    x = np.arange(n_bins)
    y = offset + rng.normal(0.0, 0.7, (n_rows, n_bins))
    h = len(pulse) // 2
    for r in range(n_rows):
        for _ in range(rng.integers(1, 4)):
            c = rng.integers(h + 2, n_bins - h - 2)
            a = t * rng.choice([0.7, 0.95, 0.999, 1.0, 1.001, 1.05, 1.3])
            y[r] += a * np.exp(-0.5 * ((x - c) / (len(pulse) / 8.0)) ** 2)
        if r % 8 == 0:
            y[r, n_bins // 4:3 * n_bins // 4] += 6.0 * t
        if r % 16 == 0:
            y[r, n_bins // 2] = scale
    return np.clip(np.rint(y), 0, np.iinfo(dtype).max).astype(dtype)


@pytest.mark.parametrize("dtype, offset, scale", [(np.uint16, 16.0, 4000.0), (np.uint16, 16.5, 65000.0),
                                                  (np.uint32, 100.25, 1e6)])
@pytest.mark.parametrize("threads", [1, 3])
def test_screened_calibrated_detection_is_the_exact_filter_bit_for_bit(dtype, offset, scale, threads):
    rng = np.random.default_rng(int(offset * 4) + threads)
    pulse = gaussian_pulse_kernel(5e-9, 5e-10)  # 35 taps, as the benchmark terrain's
    n_bins, sigma, k_sigma = 600, 0.7, 3.0
    norm = float(np.sqrt(np.sum(pulse * pulse)))
    y = code_rows(rng, 800, n_bins, pulse, k_sigma * sigma / norm, offset, dtype, scale)
    min_sep = max(3, len(pulse) // 2)
    got = detect_echoes_noisy(y, 5e-10, threshold_mode="calibrated", pulse=pulse, k_sigma=k_sigma, max_echoes=3,
                              noise_sigma=sigma, baseline=offset, threads=threads)
    pos, yd, t = reference(y, offset, sigma, pulse, k_sigma, 3, min_sep)
    det = pos >= 0
    assert np.array_equal(got.detected, det)
    assert det.sum() > 500 and (det.sum(axis=1) >= 2).sum() > 100
    # the chosen positions (position_bins = j + 0.5 + an interpolation offset within ±0.5)
    assert np.all(np.abs(got.position_bins[det] - (pos[det] + 0.5)) <= 0.5)
    ref = detect_echoes_noisy(y.astype(np.float64), 5e-10, threshold_mode="fixed", pulse=pulse,
                              threshold=float(k_sigma * (sigma / norm)), max_echoes=3, baseline=offset,
                              threads=threads)
    # the fixed threshold of the same value estimates σ from the row, so its rows are filtered in full
    for f in ("position_bins", "amplitude", "detected"):
        assert np.array_equal(getattr(got, f), getattr(ref, f), equal_nan=True), f
    # near-threshold maxima were there to be decided: many within 2 % of the threshold on either side
    peaks = yd[:, 1:-1][(yd[:, 1:-1] > yd[:, :-2]) & (yd[:, 1:-1] >= yd[:, 2:])]
    assert np.count_nonzero((peaks > t) & (peaks < 1.02 * t)) > 20
    assert np.count_nonzero((peaks <= t) & (peaks > 0.98 * t)) > 20
    assert SCREEN_FRACTION > 1
