"""Coverage of the range gate (core/engine/coverage.py): the fractions of the hit sub-rays and of their energy
before, inside and after the gate, checked against the geometry of plates inside, outside and straddling it,
and the warning that names the gate, the hits and the settings that cover them."""
import numpy as np
import pytest

from core.config.settings import SimulationConfig
from core.engine.coverage import (COVERAGE_WARN_FRACTION, OrderedTally, add_tallies, coverage_record, gate_tally,
                                  gate_window_s)
from core.geometry.scene import SceneGeometry
from core.run import simulate
from tests.core.scenes import C, config_for, plate


def _two_plates(d_left_m, d_right_m, half_fov_rad):
    """Plate L fills the left half of the field of view at ``d_left_m``, plate R the right half at ``d_right_m``
    (the sub-ray grid is mirror-symmetric about x = 0: half the sub-rays hit each)."""
    a = plate(d_left_m, 2 * d_left_m * half_fov_rad, offset=(-2 * d_left_m * half_fov_rad, 0.0, 0.0))
    b = plate(d_right_m, 2 * d_right_m * half_fov_rad, offset=(2 * d_right_m * half_fov_rad, 0.0, 0.0))
    return SceneGeometry(np.vstack([a.vertices_m, b.vertices_m]), np.vstack([a.triangles, b.triangles + 4]),
                         [0, 0, 0, 0], a.materials, ["plate"])


def test_tally_counts_each_hit_by_its_round_trip_time_with_half_open_edges():
    start, end = 2 * 100.0 / C, 2 * 200.0 / C  # the gate 100–200 m
    r = np.array([50.0, 99.999, 100.0, 150.0, 199.999, 200.0, 300.0])
    e = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
    t = gate_tally(r, e, (start, end))
    assert t[:3].tolist() == [2, 3, 2]          # before: 50, 99.999; inside: 100, 150, 199.999; after: 200, 300
    assert t[3:6].tolist() == [3.0, 28.0, 96.0]
    assert (t[6], t[7]) == (50.0, 300.0)


def test_ordered_tally_is_the_tally_of_all_hits_at_once_however_they_are_cut():
    """Folded block by block in block order, the tally is bit for bit the tally of every hit at once (the
    gated system's coverage record does not depend on the blocks or threads); summing blocks' tallies is not
    (this data: it differs in the last bits, which is why the gated system folds)."""
    rng = np.random.default_rng(7)
    r = rng.uniform(80.0, 260.0, 50_000)
    e = rng.random(50_000) ** 6 * 1e-12
    window = (2 * 100.0 / C, 2 * 200.0 / C)
    whole = gate_tally(r, e, window)
    for cuts in ([0, 50_000], [0, 1, 777, 20_000, 50_000], list(range(0, 50_001, 911)) + [50_000]):
        fold = OrderedTally(window)
        for a, b in zip(cuts, cuts[1:]):
            fold.add(r[a:b], e[a:b])
        assert np.array_equal(fold.tally, whole), cuts
    cuts = list(range(0, 50_001, 911)) + [50_000]
    summed = add_tallies(gate_tally(r[a:b], e[a:b], window) for a, b in zip(cuts, cuts[1:]))
    assert not np.array_equal(summed, whole)
    empty = OrderedTally(window)
    empty.add(np.zeros(0), np.zeros(0))
    assert np.array_equal(empty.tally[:6], np.zeros(6)) and empty.tally[6] == np.inf


def test_tally_kernel_is_the_element_wise_definition_bit_for_bit():
    """The compiled tally equals its definition in NumPy (each hit classed by t = 2r/c against [start, end), the
    energies summed in element order: ``np.bincount``), bit for bit, for one energy per hit and one for all; a
    NaN range is counted inside and makes the range extremes NaN (as ``ndarray.min``)."""
    rng = np.random.default_rng(3)
    r = rng.uniform(60.0, 240.0, 100_000)
    e = rng.random(100_000) ** 4 * 1e-12
    window = (2 * 100.0 / C, 2 * 200.0 / C)

    def definition(r, e):
        t = 2.0 * r / C
        where = np.where(t < window[0], 0, np.where(t >= window[1], 2, 1))
        e = np.broadcast_to(e, r.shape)
        return np.concatenate([np.bincount(where, minlength=3), np.bincount(where, weights=e, minlength=3),
                               [r.min(), r.max()]])

    for energy in (e, 2.5e-13):
        assert np.array_equal(gate_tally(r, energy, window), definition(r, energy))
    r[17] = np.nan
    t = gate_tally(r, e, window)
    assert np.array_equal(t, definition(r, e), equal_nan=True) and np.isnan(t[6]) and np.isnan(t[7])


def test_default_config_sees_a_plate_at_200_m():
    """SimulationConfig() covers 0–307 m (2048 bins of 1 ns): a plate at 200 m gives points, all its energy
    inside the gate (it gave 0 points with the former 1024 bins, 0–153.5 m)."""
    cfg = SimulationConfig()
    assert gate_window_s(cfg)[1] * C / 2 == pytest.approx(307.0, abs=0.1)
    cfg.receiver.width_px = cfg.receiver.height_px = 8
    cfg.run.threads = 1
    res = simulate(plate(200.0, 5.0), np.eye(4), cfg)
    cov = res.stats["gate_coverage"]
    assert len(res.points["range_m"]) == 64
    assert np.allclose(res.points["range_m"], 200.0, atol=0.05)
    assert cov["energy_fraction"] == {"before": 0.0, "inside": 1.0, "after": 0.0}
    assert cov["subray_fraction"]["inside"] == 1.0 and cov["hit_subrays"] == res.stats["n_hits"] == 8 * 8 * 16
    assert cov["hit_energy_j"] == pytest.approx(res.stats["received_energy_j"], rel=1e-12)
    assert cov["warning"] is None


def test_plate_after_the_gate_warns_and_the_suggested_settings_cover_it():
    cfg = config_for(100.0, pixels=8)       # gate 64 bins before 100 m, 256 bins: 90.4–128.8 m
    res = simulate(plate(400.0, 20.0), np.eye(4), cfg)
    cov = res.stats["gate_coverage"]
    assert len(res.points["range_m"]) == 0
    assert cov["energy_fraction"]["after"] == 1.0 and cov["subray_fraction"]["after"] == 1.0
    w = cov["warning"]
    assert "0.0 % of the hit energy" in w and "90.4–128.8 m" in w and "400.0–400." in w
    fix = cov["suggested_settings"]
    assert "gate.gate_start_s" in w and "gate.n_bins" in w
    cfg.gate.gate_start_s, cfg.gate.n_bins = fix["gate.gate_start_s"], fix["gate.n_bins"]
    start, end = gate_window_s(cfg)
    assert start * C / 2 < 400.0 < cov["hit_range_m"][1] < end * C / 2
    res2 = simulate(plate(400.0, 20.0), np.eye(4), cfg)
    assert res2.stats["gate_coverage"]["energy_fraction"]["inside"] == 1.0
    assert res2.stats["gate_coverage"]["warning"] is None
    assert len(res2.points["range_m"]) == 64 and np.allclose(res2.points["range_m"], 400.0, atol=0.1)


def test_plate_before_the_gate_is_counted_before():
    cfg = config_for(300.0, pixels=8)
    cov = simulate(plate(100.0, 5.0), np.eye(4), cfg).stats["gate_coverage"]
    assert cov["energy_fraction"]["before"] == 1.0 and cov["subray_fraction"]["before"] == 1.0
    assert cov["suggested_settings"]["gate.gate_start_s"] < 2 * 100.0 / C


def _inside_fraction(cfg, near_m, far_m):
    """Energy fraction of the near plate when half the sub-rays see each (eq. 3-1 with the projected solid angle
    πa²/(R² + a²) of the aperture of radius a)."""
    a2 = (0.5 * cfg.receiver.aperture_diameter_m) ** 2
    return (far_m ** 2 + a2) / (near_m ** 2 + far_m ** 2 + 2.0 * a2)


def test_straddling_plates_fractions_follow_the_inverse_square_law():
    """Half the field of view on a plate at 100 m (inside the gate), half on one at 200 m (after it).  Half the
    hit sub-rays are inside; the energy of a Lambertian plate filling its sub-rays goes as cos³α / D² (eq. 3-1
    with R = D / cos α, θ = α), the same α on both halves; with the aperture's projected solid angle
    πa²/(R² + a²) (a = 25 mm) the inside fraction is (200² + a²)/(100² + 200² + 2a²) = 0.8 − 7.5e-9 (tolerance
    1e-9: the residue of cos α ≤ 1 in the a² terms is a²α²/D² ≈ 3e-12)."""
    cfg = config_for(100.0, pixels=16)  # gate 90.4–138.8 m
    res = simulate(_two_plates(100.0, 200.0, 0.5 * cfg.receiver.fov_x_rad), np.eye(4), cfg)
    cov = res.stats["gate_coverage"]
    assert res.stats["n_hits"] == 16 * 16 * 16
    assert cov["subray_fraction"] == {"before": 0.0, "inside": 0.5, "after": 0.5}
    inside = _inside_fraction(cfg, 100.0, 200.0)
    assert cov["energy_fraction"]["inside"] == pytest.approx(inside, abs=1e-9)
    assert cov["energy_fraction"]["after"] == pytest.approx(1.0 - inside, abs=1e-9)
    assert cov["energy_fraction"]["inside"] < COVERAGE_WARN_FRACTION
    assert "80.0 % of the hit energy (50.0 % of the 4096 hit sub-rays)" in cov["warning"]
    lo, hi = cov["hit_range_m"]
    assert 100.0 <= lo < 100.01 and 200.0 < hi < 200.01  # the corner rays: D / cos α, α ≤ 0.0071 rad
    cfg.gate.gate_start_s, cfg.gate.n_bins = (cov["suggested_settings"][k] for k in ("gate.gate_start_s",
                                                                                     "gate.n_bins"))
    res2 = simulate(_two_plates(100.0, 200.0, 0.5 * cfg.receiver.fov_x_rad), np.eye(4), cfg)
    assert res2.stats["gate_coverage"]["energy_fraction"]["inside"] == 1.0
    assert sorted(set(np.round(res2.points["range_m"]).tolist())) == [100.0, 200.0]


def test_gated_sweep_coverage_uses_the_slice_delays():
    cfg = SimulationConfig()
    cfg.system_type = "gated"
    cfg.receiver.width_px = cfg.receiver.height_px = 8
    cfg.run.threads = 1
    g = cfg.gated
    g.first_delay_s, g.delay_step_s, g.n_slices, g.gate_width_s = 2 * 490.0 / C, 2e-9, 10, 20e-9
    start, end = gate_window_s(cfg)
    assert end - start == pytest.approx(9 * 2e-9 + 20e-9, rel=1e-12)
    inside = simulate(plate(493.0, 10.0), np.eye(4), cfg).stats["gate_coverage"]
    assert inside["energy_fraction"]["inside"] == 1.0 and inside["warning"] is None
    out = simulate(plate(800.0, 10.0), np.eye(4), cfg).stats["gate_coverage"]
    assert out["energy_fraction"]["after"] == 1.0
    assert "the slice sweep" in out["warning"] and "gated.first_delay_s" in out["warning"]
    g.first_delay_s, g.n_slices = out["suggested_settings"]["gated.first_delay_s"], \
        out["suggested_settings"]["gated.n_slices"]
    assert simulate(plate(800.0, 10.0), np.eye(4), cfg).stats["gate_coverage"]["energy_fraction"]["inside"] == 1.0


def test_record_without_hits_has_no_fractions_to_warn_about():
    rec = coverage_record(SimulationConfig(), gate_tally([], [], (0.0, 1e-6)))
    assert rec["hit_subrays"] == 0 and rec["hit_range_m"] is None and rec["warning"] is None


def test_run_folder_and_summary_carry_the_warning_false_alarms_and_snr(tmp_path):
    """A noisy run on two plates, the far one after the gate: metadata.json's ``warnings`` and the terminal
    summary name the coverage (80.0 %), the summary counts the false alarms (as the points' flags do, and per
    pixel) and gives the SNR range of the true returns."""
    import json

    from core.fileio.run_folder import run_summary
    from core.run import run_simulation

    cfg = config_for(100.0, pixels=16)
    cfg.detector.mode = "noisy"
    cfg.detector.background_rate_photons_per_s = 5e9
    cfg.detection.k_sigma = 3.0  # a low threshold: false alarms in 256 pixels × 256 bins
    path, res = run_simulation(_two_plates(100.0, 200.0, 0.5 * cfg.receiver.fov_x_rad), np.eye(4), cfg,
                               tmp_path / "run")
    meta = json.loads((path / "metadata.json").read_text())
    assert len(meta["warnings"]) == 1 and "80.0 % of the hit energy" in meta["warnings"][0]
    assert meta["gate_coverage"]["energy_fraction"]["inside"] == pytest.approx(_inside_fraction(cfg, 100.0, 200.0),
                                                                               abs=1e-9)
    text = run_summary(path, res)
    fa = res.points["false_alarm"]
    n_fa = int(fa.sum())
    assert 0 < n_fa < len(fa)
    assert f"false    {n_fa} false alarms of {len(fa)} points ({n_fa / 256:.3g} per pixel" in text
    snr = res.points["snr"][fa == 0]
    assert f"snr      true returns {snr.min():.3g} – {snr.max():.3g}" in text
    assert "WARNING  range gate: only 80.0 % of the hit energy" in text
    assert "holds 80.0 % of the hit energy (0.0 % before, 20.0 % after) and 50.0 % of the hit sub-rays" in text


def _sensor_preset(name):
    """The settings a shipped sensor preset applies (presets/ladar_simulator/sensor/<name>.py), as a config."""
    import runpy
    import sys
    import types
    from pathlib import Path

    from core.config.files import config_from_dict

    got = {}
    mod = types.ModuleType("stand_in.ladar_simulator.ladar_addon.presets")
    mod.apply_sensor_preset = got.update
    # the preset takes the first module named *ladar_simulator.ladar_addon.presets: the stand-in only
    real = {n: sys.modules.pop(n) for n in list(sys.modules) if n.endswith("ladar_simulator.ladar_addon.presets")}
    sys.modules[mod.__name__] = mod
    try:
        runpy.run_path(str(Path(__file__).resolve().parents[3] / "presets" / "ladar_simulator" / "sensor"
                           / f"{name}.py"))
    finally:
        del sys.modules[mod.__name__]
        sys.modules.update(real)
    return config_from_dict({"schema_version": 1, **got})


@pytest.mark.parametrize("name,design_m", [
    ("Airborne_1064_nm_full_waveform", (1000.0, 1000.0 / np.cos(np.radians(20.0)))),  # 1 km AGL, ±20° off nadir
    ("Gated_viewing_532_nm_at_1_km", (990.0, 999.0)),
    ("InGaAs_3D_flash_128x128_1570_nm", (1.0, 300.0)),
    ("Spinning_905_nm_automotive_16_channels", (1.0, 200.0)),  # VLP-16 class: 100 m specified, 200 m margin
])
def test_sensor_presets_gates_cover_their_design_ranges(name, design_m):
    start, end = gate_window_s(_sensor_preset(name))
    assert start * C / 2 <= design_m[0] and design_m[1] <= end * C / 2


def test_airborne_preset_over_ground_120_m_below_warns_and_1_km_below_does_not():
    """The airborne preset (gate 899–1130 m) scanning flat ground: from 1 km up every hit is inside; from 120 m
    up (forest_scan.blend's flying height) none is, and the warning names the gate settings for 120 m."""
    cfg = _sensor_preset("Airborne_1064_nm_full_waveform")
    cfg.scanner.duration_s = 0.002  # 200 pulses
    cfg.run.threads = 1
    down = np.eye(4)  # the sensor looks along −Z: a ground plate "below" is a plate in front
    high = simulate(plate(1000.0, 500.0), down, cfg).stats["gate_coverage"]
    assert high["energy_fraction"]["inside"] == 1.0 and high["warning"] is None
    low = simulate(plate(120.0, 100.0), down, cfg).stats["gate_coverage"]
    assert low["energy_fraction"]["before"] == 1.0
    assert "899.4–1129.6 m" in low["warning"] and "the hits are at 120.0–12" in low["warning"]
    fix = low["suggested_settings"]
    assert fix["gate.gate_start_s"] * C / 2 < 120.0 and fix["gate.n_bins"] < 1536


def test_sequence_metadata_lists_each_frames_warning(tmp_path):
    import json

    from core import sequence

    cfg = config_for(100.0, pixels=4)  # gate 90.4–128.8 m
    path, stats = sequence.run_sequence([1, 2], lambda f: plate(100.0 if f == 1 else 300.0, 5.0),
                                        lambda f: np.eye(4), cfg, tmp_path / "seq")
    meta = json.loads((path / "metadata.json").read_text())
    assert [s["gate_coverage"]["warning"] is None for s in stats] == [True, False]
    assert len(meta["warnings"]) == 1 and meta["warnings"][0].startswith("frame 2: range gate: only 0.0 %")
    frame2 = json.loads((path / "frame_0002" / "metadata.json").read_text())
    assert frame2["warnings"] == [meta["warnings"][0].removeprefix("frame 2: ")]


def test_sequence_summary_adds_up_its_frames_false_alarms_snr_and_coverage(tmp_path):
    """A noisy two-frame sequence (frame 1: the two plates at 100 and 200 m, 80 % of the energy inside the gate;
    frame 2: one plate at 100 m, all inside): the sequence's summary lines (core.fileio.run_folder.figure_lines of
    combine_figures, as the CLI and Blender's report print them) count the false alarms of both frames' points,
    give the SNR range of the merged points and the gate's coverage weighted by each frame's hit energy."""
    import json

    from core import sequence
    from core.fileio.run_folder import combine_figures, figure_lines

    cfg = config_for(100.0, pixels=8)
    cfg.detector.mode = "noisy"
    cfg.detector.background_rate_photons_per_s = 5e9
    cfg.detection.k_sigma = 3.0
    half = 0.5 * cfg.receiver.fov_x_rad
    path, stats = sequence.run_sequence(
        [1, 2], lambda f: _two_plates(100.0, 200.0, half) if f == 1 else plate(100.0, 5.0),
        lambda f: np.eye(4), cfg, tmp_path / "seq")
    merged = np.load(path / "points_merged.npz")
    fa, snr = merged["false_alarm"], merged["snr"]
    per_frame = [int(np.load(path / f"frame_{f:04d}" / "points.npz")["false_alarm"].sum()) for f in (1, 2)]
    assert int(fa.sum()) == sum(per_frame) > 0
    text = "\n".join(figure_lines(combine_figures([s["figures"] for s in stats])))
    assert (f"false    {int(fa.sum())} false alarms of {len(fa)} points ({fa.sum() / 128:.3g} per pixel and frame, "
            f"{min(per_frame)} – {max(per_frame)} per frame; {len(fa) - int(fa.sum())} true returns)") in text
    assert f"snr      true returns {snr[fa == 0].min():.3g} – {snr[fa == 0].max():.3g}; false alarms " \
           f"{snr[fa != 0].min():.3g} – {snr[fa != 0].max():.3g}" in text
    cov = [json.loads((path / f"frame_{f:04d}" / "metadata.json").read_text())["gate_coverage"] for f in (1, 2)]
    e = [c["hit_energy_j"] for c in cov]
    inside = sum(c["energy_fraction"]["inside"] * ei for c, ei in zip(cov, e)) / sum(e)
    assert 0.8 < inside < 1.0
    assert f"holds {100 * inside:.1f} % of the hit energy" in text and "hits at 100.0 – 200.0 m (all 2 frames)" in text
    assert len(merged["range_m"]) == sum(s["n_points"] for s in stats)
