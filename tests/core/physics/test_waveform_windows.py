"""Waveforms stored as one window of bins per pixel (core/physics/waveform.py WaveformWindows) and echo detection on
the windows (core/physics/detection/peaks.py detect_echoes_windows): the same numbers as the full (pixels × bins) arrays."""
import numpy as np
import pytest

from core.config.settings import DetectionSettings, LaserSettings, RangeGateSettings
from core.physics.detection.peaks import detect_echoes, detect_echoes_windows
from core.physics.laser import pulse_cdf
from core.physics.waveform import accumulate_waveform_windows


def _rays(rng, n_pixels=40, n=300, t_lo=-30e-9, t_hi=330e-9):
    """Returns clustered per pixel (a surface, sometimes two), some clusters across the gate's ends."""
    pix = np.sort(rng.integers(0, n_pixels, n))
    centre = rng.uniform(t_lo, t_hi, (n_pixels, 2))
    second = rng.random(n) < 0.3
    t = centre[pix, second.astype(int)] + rng.uniform(-6e-9, 6e-9, n)
    return pix, t, rng.uniform(0.1, 1.0, n)


@pytest.mark.parametrize("shape,fwhm_s", [("gaussian", 5e-9), ("rectangular", 7e-9), ("gaussian", 0.3e-9),
                                          ("gaussian", 40e-9)])
def test_windows_hold_the_whole_waveform(shape, fwhm_s):
    """Against a direct sum over every bin of the gate, w_j = Σ E_i [P(t_{j+1} − t_i) − P(t_j − t_i)]: equal
    within 1e-8 of the peak (the pipeline stops at ±6.1σ, 1e-9 of a pulse; splat for the 40 ns pulse: 2e-3),
    rays straddling both gate ends included; bins outside the windows are exactly 0."""
    rng = np.random.default_rng(4)
    laser = LaserSettings(pulse_shape=shape, pulse_fwhm_s=fwhm_s)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=300)
    pix, t, e = _rays(rng)
    win = accumulate_waveform_windows(pix, t, e, 40, laser, gate)
    dense = win.dense()
    edges = np.arange(gate.n_bins + 1) * gate.bin_width_s
    ref = np.zeros((40, gate.n_bins))
    for p, ti, ei in zip(pix, t, e):
        ref[p] += ei * np.diff(pulse_cdf(laser, edges - ti))
    tol = 2e-3 if fwhm_s > 20e-9 else 1e-8
    assert np.abs(dense - ref).max() < tol * ref.max()
    row, col = win.bins()
    mask = np.zeros(dense.shape, bool)
    mask[row, col] = True
    assert np.all(dense[~mask] == 0)
    if fwhm_s < 20e-9:  # (the 40 ns pulse spans ±100 bins: its windows are most of this gate)
        assert win.length.sum() < 0.5 * dense.size
    cube = np.full((50, gate.n_bins), np.nan, np.float32)  # whole rows written: zeros outside the windows
    win.write_rows(cube, np.arange(40) + 10)
    assert np.array_equal(cube[10:], dense.astype(np.float32)) and np.isnan(cube[:10]).all()


@pytest.mark.parametrize("settings", [DetectionSettings(), DetectionSettings(interpolation="parabolic", max_echoes=1),
                                      DetectionSettings(min_dip=0.0, relative_threshold=0.0),
                                      DetectionSettings(interpolation="none", threshold_j=0.05)])
def test_echoes_on_windows_are_the_echoes_on_the_full_waveforms(settings):
    """Bit-identical echoes (pixel, position, amplitude, order, count) for Gaussian and flat-topped returns,
    several per pixel, touching the gate's first and last bins."""
    rng = np.random.default_rng(9)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=256)
    for laser in (LaserSettings(pulse_fwhm_s=4e-9), LaserSettings(pulse_shape="rectangular", pulse_fwhm_s=10e-9)):
        pix, t, e = _rays(rng, n_pixels=60, n=240, t_lo=-8e-9, t_hi=264e-9)
        spread = np.stack([rng.uniform(0, 30e-9, 240), rng.uniform(0, 3e-9, 240)], axis=1) * (rng.random((240, 1)) < 0.5)
        win = accumulate_waveform_windows(pix, t, e, 60, laser, gate, spread_s=spread)
        a, b = detect_echoes_windows(win, settings), detect_echoes(win.dense(), settings)
        assert len(a.pixel) > 20
        for name in ("pixel", "position_bins", "amplitude", "echo_index", "n_echoes"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
