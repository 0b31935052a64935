"""Every product carries its true unit everywhere it is shown (issue 14): ``FrameResult.units`` is the one source
the run folder's ``metadata.json`` (``units`` and the file descriptions), the previews and the LAS record read."""
import json

import numpy as np
import pytest

from core.config.settings import SimulationConfig
from core.fileio import preview
from core.fileio.las import read_las
from core.engine.result import product_units
from core.run import run_simulation
from scenes import C, config_for, plate


def _flash(mode="ideal", adc=True):
    cfg = config_for(200.0, pixels=6, subsamples=2, bins=128)
    cfg.detector.mode = mode
    cfg.detector.enable_adc = adc
    cfg.run.save_counts = True  # counts kept: the per-bin reference route (run.save_counts)
    cfg.laser.pulse_energy_j = 1e-3
    return cfg


def _gated(mode="ideal"):
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px = cfg.receiver.height_px = 6
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 2e-3
    cfg.receiver.subsamples = 2
    g = cfg.gated
    g.n_slices, g.delay_step_s, g.gate_width_s = 8, 5e-9, 20e-9
    g.first_delay_s = 2 * 300.0 / C - 4 * 5e-9 - 10e-9
    cfg.detector.mode = mode
    cfg.laser.pulse_energy_j = 0.05
    cfg.run.threads = 1
    return cfg


def _meta(path):
    return json.loads((path / "metadata.json").read_text())


@pytest.mark.parametrize("case, expected", [
    ("flash ideal", {"intensity": "J per bin"}),
    ("flash noisy", {"intensity": "counts", "counts": "counts"}),
    ("flash noisy no adc", {"intensity": "electrons", "counts": "electrons"}),
    ("gated ideal", {"intensity": "J", "slices": "J"}),
    ("gated noisy", {"intensity": "counts", "slices": "counts"}),
])
def test_run_folder_states_each_product_in_its_true_unit(tmp_path, case, expected):
    system, mode = case.split()[:2]
    if system == "flash":
        cfg, scene = _flash(mode, adc="no adc" not in case), plate(200.0, 5.0)
    else:
        cfg, scene = _gated(mode), plate(300.0, 5.0)
    path, res = run_simulation(scene, np.eye(4), cfg, tmp_path / "run")
    meta = _meta(path)
    assert meta["units"] == res.units
    for key, unit in expected.items():
        assert meta["units"][key] == unit
    assert meta["units"]["range"] == "m" and meta["units"]["energy"] == "J"
    files = meta["files"]
    assert files["intensity.exr"].endswith(f"({expected['intensity']})")
    if mode == "noisy":
        assert "J per bin" not in files["intensity.exr"]
    if "counts" in expected:
        assert f"({expected['counts']})" in files["counts.npy"]
    if system == "gated":
        assert f"{expected['slices']} per pixel" in files["slices.npy"]
    # the LAS record names the unit of its intensity_raw
    record = next(json.loads(payload) for user, rid, _, payload in read_las(path / "points.las")["vlrs"]
                  if user == "LadarSimulator")
    assert record["intensity_unit"] == expected["intensity"]


def test_scanner_noisy_intensity_is_in_counts(tmp_path):
    cfg = SimulationConfig(system_type="scanner")
    sc = cfg.scanner
    sc.pattern, sc.pulse_rate_hz, sc.scan_rate_hz, sc.duration_s = "oscillating", 2000.0, 50.0, 0.01
    sc.scan_width_rad = 0.01
    cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2 * 190.0 / C, 1e-9, 128
    cfg.detector.mode = "noisy"
    cfg.run.threads = 1
    path, res = run_simulation(plate(200.0, 20.0), np.eye(4), cfg, tmp_path / "scan")
    assert res.units["intensity"] == "counts" and _meta(path)["units"]["intensity"] == "counts"


def test_previews_take_their_units_from_the_run(tmp_path, monkeypatch):
    cfg = _gated("noisy")
    path, _ = run_simulation(plate(300.0, 5.0), np.eye(4), cfg, tmp_path / "run")
    drawn = {}

    def spy(png, image, *, title="", unit="", **kw):
        drawn[png.name] = unit
        return png

    monkeypatch.setattr(preview, "false_colour_png", spy)
    preview.write_run_previews(path)
    assert drawn["intensity.png"] == "counts"
    assert drawn["range.png"] == "m" and drawn["energy.png"] == "J"
    assert drawn["slice_0001.png"] == "counts"


def test_product_units_table():
    assert product_units("flash") == {"range": "m", "energy": "J", "waveforms": "J per bin",
                                      "intensity": "J per bin"}
    assert product_units("profiler", "detections")["intensity"] == "detections"
    assert product_units("gated", "J") == {"range": "m", "energy": "J", "waveforms": "J per bin", "slices": "J",
                                           "intensity": "J"}
