"""Points-only flash frames bin each pixel's waveform only where the echo detection reads it
(core/physics/waveform.py ``detection_windows``): the echoes must be those of the whole windows bit for bit, the
values on the cut the whole windows' values bit for bit, the cut must fall back to the whole window where its
check fails, and the two facts the check rests on (the table's error below its slack; each return's bins falling
away from its centre) must hold."""
import dataclasses

import numpy as np
import pytest

from core.config.settings import DetectionSettings, LaserSettings, RangeGateSettings
from core.physics import waveform as W
from core.physics.detection.peaks import detect_echoes_windows
from core.physics.laser import GAUSS_BOX_FOLD, pulse_sigma_s


def pixels(sigma_bins, n_pixels=400, seed=3):
    """16 returns a pixel in a 600-bin gate: a sloped surface (returns spread over a few σ, cells spanning boxes
    below and above the fold), a second surface behind it in a third of the pixels (weak or strong), some returns
    near the gate's ends and a few of zero energy: (laser, gate, pixel, times, energies, spreads)."""
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    sig = pulse_sigma_s(laser)
    dt = sig / sigma_bins
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=dt, n_bins=600)
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(n_pixels), 16)
    centre = rng.uniform(-10, 610, n_pixels)[pix]  # (some pixels' returns partly outside the gate)
    slope = rng.uniform(0, 3, n_pixels)[pix] * sig
    t = centre * dt + slope * rng.uniform(-1, 1, len(pix))
    second = (rng.random(n_pixels) < 0.35)[pix] & (rng.random(len(pix)) < 0.5)
    t = np.where(second, t + rng.uniform(2, 12, n_pixels)[pix] * sig, t)
    e = rng.uniform(0.2, 1.0, len(pix)) * np.where(second, rng.choice([0.03, 0.3, 3.0], n_pixels)[pix], 1.0) * 1e-15
    e[rng.random(len(pix)) < 0.02] = 0.0
    a = rng.uniform(0, 2.5, len(pix)) * sig * (rng.random(len(pix)) < 0.8)
    b = rng.uniform(0, 1, len(pix)) * a * (rng.random(len(pix)) < 0.7)
    return laser, gate, pix, t, e, np.stack([a, b], axis=1)


SETTINGS = {"default": DetectionSettings(), "absolute": DetectionSettings(threshold_j=2e-17),
            "relative 0.3": DetectionSettings(relative_threshold=0.3), "one echo": DetectionSettings(max_echoes=1),
            "no dip": DetectionSettings(min_dip=0.0), "parabolic": DetectionSettings(interpolation="parabolic"),
            "low 0.002": DetectionSettings(relative_threshold=0.002)}


def same(x, y):
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@pytest.mark.parametrize("sigma_bins", [4.25, 1.0])
@pytest.mark.parametrize("name", list(SETTINGS))
def test_echoes_of_the_cut_windows_are_the_whole_windows_echoes_bit_for_bit(sigma_bins, name):
    laser, gate, pix, t, e, sp = pixels(sigma_bins)
    det = SETTINGS[name]
    n = pix[-1] + 1
    whole = W.accumulate_waveform_windows(pix, t, e, n, laser, gate, "table", spread_s=sp)
    cut, n_whole = W.detection_windows(pix, t, e, n, laser, gate, "table", det, spread_s=sp)
    ref, got = detect_echoes_windows(whole, det), detect_echoes_windows(cut, det)
    assert len(ref.pixel) > 300
    for f in ("pixel", "position_bins", "amplitude", "echo_index", "n_echoes"):
        assert same(getattr(ref, f), getattr(got, f)), f
    # every value of the cut windows is the whole window's value of that bin, bit for bit
    dense = whole.dense()
    row, col = cut.bins()
    assert same(cut.values, dense[row, col])
    assert np.all(cut.start >= whole.start) and np.all(cut.start + cut.length <= whole.start + whole.length)
    # the cut binned fewer bins, and its check fell back to whole windows somewhere (a weak second surface at a
    # low threshold) without ever falling back everywhere
    assert len(cut.values) < 0.8 * len(whole.values)
    if name == "low 0.002":
        assert 0 < n_whole < n


def test_the_cut_falls_back_where_its_check_fails():
    """A relative threshold of 1e-6 lies below the pulse's value K σ away: no cut stands, every pixel with returns
    is binned whole, and the echoes (and values) are the whole windows'."""
    laser, gate, pix, t, e, sp = pixels(4.25)
    det = DetectionSettings(relative_threshold=1e-6)
    n = pix[-1] + 1
    whole = W.accumulate_waveform_windows(pix, t, e, n, laser, gate, "table", spread_s=sp)
    cut, n_whole = W.detection_windows(pix, t, e, n, laser, gate, "table", det, spread_s=sp)
    clipped = np.count_nonzero(whole.length > 0)
    assert n_whole >= 0.95 * clipped
    assert same(detect_echoes_windows(cut, det).position_bins, detect_echoes_windows(whole, det).position_bins)


def test_other_methods_and_no_threshold_bin_the_whole_windows():
    laser, gate, pix, t, e, sp = pixels(4.25, n_pixels=50)
    n = pix[-1] + 1
    for method, det in (("exact", DetectionSettings()),
                        ("table", DetectionSettings(threshold_j=0.0, relative_threshold=0.0))):
        whole = W.accumulate_waveform_windows(pix, t, e, n, laser, gate, method, spread_s=sp)
        cut, n_whole = W.detection_windows(pix, t, e, n, laser, gate, method, det, spread_s=sp)
        assert n_whole == 0 and same(cut.values, whole.values) and same(cut.start, whole.start)


@pytest.mark.parametrize("sigma_bins", [1.0, 2.12, 4.25, 8.0])
def test_table_error_is_far_below_the_slack(sigma_bins):
    """The check adds twice ``DETECTION_TABLE_SLACK`` per unit energy for the table's error: the error bound of
    the table (BoxTable.error_bound, per term; a box's value is two terms over a, a trapezoid's four over ab, a and
    b ≥ the fold 0.3σ; δ up to both boxes folded) is at least 10 times below it."""
    delta_max = 2 * (GAUSS_BOX_FOLD * sigma_bins) ** 2 / 12
    eb = W.box_table(sigma_bins).error_bound(delta_max)
    a_min = GAUSS_BOX_FOLD * sigma_bins
    worst = max(eb["impulse"], 2 * eb["box"] / a_min, 4 * eb["trapezoid"] / a_min ** 2)
    assert worst <= W.DETECTION_TABLE_SLACK / 10, worst


@pytest.mark.parametrize("spread", [(0.0, 0.0), (0.2, 0.1), (2.0, 0.0), (3.0, 1.5), (6.0, 5.0)])
def test_each_return_falls_away_from_its_centre(spread):
    """The check's premise: a return's bin values (table binning) do not grow from bin j to j − 1 for j ≤ c − ½
    nor from j to j + 1 for j ≥ c − ½ (up to the slack), at 200 positions within a bin, for every kind."""
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    sig = pulse_sigma_s(laser)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=sig / 4.25, n_bins=200)
    c = 100.0 + np.arange(200) / 200.0
    n = len(c)
    sp = np.tile(np.asarray(spread) * sig, (n, 1))
    win = W.accumulate_waveform_windows(np.arange(n), c * gate.bin_width_s, np.ones(n), n, laser, gate, "table",
                                        spread_s=sp)
    d = win.dense()
    j = np.arange(gate.n_bins)[None, :]
    left = j[:, 1:] <= c[:, None] - 0.5  # pairs (j − 1, j) with j ≤ c − ½: d[j − 1] ≤ d[j]
    right = j[:, :-1] >= c[:, None] - 0.5  # pairs (j, j + 1) with j ≥ c − ½: d[j + 1] ≤ d[j]
    tol = 2 * W.DETECTION_TABLE_SLACK
    assert np.all((d[:, :-1] - d[:, 1:])[left] <= tol)
    assert np.all((d[:, 1:] - d[:, :-1])[right] <= tol)
    # (the premise is not empty: the values do fall, by far more than the slack)
    assert (d[:, 1:] - d[:, :-1])[left].max() > 100 * tol


def test_flash_points_only_frame_has_the_cube_frames_points():
    """End to end on the flash benchmark's scene (bench/bench_flash.py, its quick size: 32² px × 2×2 sub-rays, 256
    bins of 1 ns, a σ of 2.1 bins: table binning): the points-only frame (cut windows) and the frame that saves
    the cube (whole windows) give the same points and images, bit for bit; only the first records the route."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
    from bench_flash import bench_config, bench_scene, sensor_pose
    from core.systems.flash import simulate_frame

    scene, pose, cfg = bench_scene(32), sensor_pose(), bench_config(quick=True)
    cube = simulate_frame(scene, pose, cfg)
    points_only = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, save_waveforms=False))
    pts = simulate_frame(scene, pose, points_only)
    assert pts.stats["waveform_binning"] == "table" and "waveform_windows" in pts.stats
    assert "waveform_windows" not in cube.stats and cube.waveforms is not None and pts.waveforms is None
    assert len(pts.points["range_m"]) > 200
    assert sorted(pts.points) == sorted(cube.points)
    for k in cube.points:
        assert same(np.asarray(cube.points[k]), np.asarray(pts.points[k])), k
    for k in ("range_image", "intensity_image", "energy_image", "range_echoes", "intensity_echoes"):
        assert same(getattr(cube, k), getattr(pts, k)), k
