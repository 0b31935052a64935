"""The statistical detector model searches each pixel's signal only inside the binning's window of that pixel
(core/physics/detection/false_alarms.py ``row_extents(..., spans)``; the flash frame passes its waveform windows
when no whole-cube stage adds to the rows): the same extents, echoes and false-alarm flags as the whole-row
search, on rows built for every branch and on a full-physics frame."""
import numpy as np
import pytest

from core.physics.detection.false_alarms import row_extents


def rows_with_spans(rng, n_rows, n):
    """Float32 rows exactly 0 outside a random span each: empty spans, spans at either edge, whole rows, signal at
    the span's ends, sub-level values, a NaN inside some spans, all-zero rows with a span."""
    lo = rng.integers(0, n, n_rows)
    hi = np.minimum(lo + rng.integers(0, 300, n_rows), n)
    lo[::17], hi[::17] = 0, n  # whole rows
    lo[1::17], hi[1::17] = 0, rng.integers(0, 70, n_rows)[1::17]  # at the front
    lo[2::17], hi[2::17] = n - rng.integers(0, 70, n_rows)[2::17], n  # at the back
    hi[3::17] = lo[3::17]  # empty
    lo = np.clip(lo, 0, n)
    hi = np.clip(hi, lo, n)
    t = np.zeros((n_rows, n), np.float32)
    for r in range(n_rows):
        k = hi[r] - lo[r]
        if k == 0 or r % 11 == 4:  # (r % 11 == 4: a span of zeros)
            continue
        v = np.where(rng.random(k) < 0.3, rng.uniform(0.0, 2.0, k), 0.0).astype(np.float32)  # level 1: some below
        if r % 5 == 0:  # signal on the span's very ends
            v[0] = v[-1] = 3.0
        if r % 13 == 6:
            v[rng.integers(0, k)] = np.nan
        t[r, lo[r]:hi[r]] = v
    return t, lo, hi


@pytest.mark.parametrize("n", [64, 200, 1030])
@pytest.mark.parametrize("threads", [1, 3])
def test_extents_in_spans_are_the_whole_rows(n, threads):
    rng = np.random.default_rng(n + threads)
    t, lo, hi = rows_with_spans(rng, 900, n)
    full = row_extents(t, 1.0, threads)
    spanned = row_extents(t, 1.0, threads, (lo, hi))
    for a, b in zip(full, spanned):
        assert np.array_equal(a, b, equal_nan=True)
    assert (full[0] >= 0).sum() > 300 and full[3].sum() > 10 and (full[0] < 0).sum() > 50
    # the spans are what is read: a signal bin put outside a row's span is not found with the spans
    r = int(np.flatnonzero((full[0] > 5) & ~full[3])[0])
    t[r, 0] = 5.0
    assert row_extents(t, 1.0, threads)[0][r] == 0 and row_extents(t, 1.0, threads, (lo, hi))[0][r] == full[0][r]
    # a level not above 0 would count the zeros outside the spans: the spans are then ignored
    z = row_extents(t, -1.0, threads, (lo, hi))
    assert np.array_equal(z[0], row_extents(t, -1.0, threads)[0]) and np.all(z[0][~np.isnan(t[:, 0])] == 0)


def test_flash_frame_with_windows_is_the_whole_row_search():
    """A full-physics frame (noisy APD with A/D, turbulence, visibility; the statistical route): its points and
    false-alarm flags are those of the statistical route searching whole rows of the frame's own cube."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "bench"))
    from bench_flash import bench_scene, full_physics_config, sensor_pose
    from core.constants import SPEED_OF_LIGHT_M_S
    from core.engine.products import statistical_noisy_echoes
    from core.engine.rng import stage_seed
    from core.systems.flash import simulate_frame

    cfg = full_physics_config(quick=True)
    res = simulate_frame(bench_scene(32), sensor_pose(), cfg)
    assert res.stats["receiver"]["detector_model"]["signal_free_bins"] == "statistical"
    assert "turbulence_blur" not in res.stats["stages_run"]  # (no whole-cube stage: the windows are passed)
    e, _ = statistical_noisy_echoes(res.waveforms, cfg, stage_seed(cfg.run.seed, 0, "receiver"))
    g = cfg.gate
    assert len(e.pixel) > 50
    assert np.array_equal(res.points["range_m"], 0.5 * SPEED_OF_LIGHT_M_S * (g.gate_start_s + e.position_bins *
                                                                            g.bin_width_s))
    assert np.array_equal(res.points["false_alarm"], e.false_alarm.astype(np.uint8))
    assert np.array_equal(res.points["snr"], e.snr.astype(np.float32))
