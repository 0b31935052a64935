"""Bad input gives a clear error naming the setting and writes nothing; runs are written atomically."""
import json
import math

import numpy as np
import pytest

from core.systems import flash as pipeline
from core.errors import ConfigError
from core.config.settings import SimulationConfig
from core.config.validate import validate
from core.config.files import config_from_dict, config_to_dict, dump_config_json, dump_config_toml, load_config
from core.errors import Cancelled
from core.run import run_simulation
from core.systems.flash import simulate_frame
from core.fileio.run_folder import read_exr, read_ply
from core.geometry.scene import SceneGeometry
from scenes import config_for, plate


@pytest.mark.parametrize("group,name,value,fragment", [
    ("laser", "pulse_energy_j", -1.0, "(0, 100] J"),
    ("laser", "pulse_energy_j", math.nan, "(0, 100] J"),
    ("laser", "wavelength_m", math.inf, "[2e-07, 1.2e-05] m"),
    ("receiver", "width_px", 0, "[1, 8192] px"),
    ("receiver", "aperture_diameter_m", 0.0, "(0, 10] m"),
    ("gate", "bin_width_s", -1e-9, "[1e-12, 1e-06] s"),
    ("atmosphere", "extinction_per_m", -0.1, "[0, 1] 1/m"),
    ("laser", "pulse_shape", "square", "'gaussian', 'rectangular'"),
    ("receiver", "subsamples", 2.0, "whole number"),
])
def test_bad_setting_names_field_value_and_range(group, name, value, fragment):
    cfg = SimulationConfig()
    setattr(getattr(cfg, group), name, value)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    msg = str(info.value)
    assert info.value.field == f"{group}.{name}"
    assert f"{group}.{name}" in msg and fragment in msg and repr(value) in msg


def test_range_gate_too_large_for_memory():
    cfg = SimulationConfig()
    cfg.receiver.width_px = cfg.receiver.height_px = 4096
    cfg.gate.n_bins = 100_000
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    assert info.value.field == "gate.n_bins"
    assert "at most 64 bins" in str(info.value) and "GiB" in str(info.value)
    cfg.run.save_waveforms = False  # points only: no cube, so no limit on the gate
    validate(cfg)


def test_config_round_trip_json_and_toml(tmp_path):
    cfg = SimulationConfig()
    cfg.laser.pulse_energy_j = 2.5e-3
    cfg.gate.n_bins = 333
    (tmp_path / "c.json").write_text(dump_config_json(cfg))
    (tmp_path / "c.toml").write_text(dump_config_toml(cfg))
    assert load_config(tmp_path / "c.json") == cfg
    assert load_config(tmp_path / "c.toml") == cfg
    partial = config_from_dict({"schema_version": 1, "laser": {"pulse_energy_j": 1}})
    assert partial.laser.pulse_energy_j == 1.0 and partial.gate.n_bins == SimulationConfig().gate.n_bins
    with pytest.raises(ConfigError, match="laser.bogus"):
        config_from_dict({"laser": {"bogus": 1}})
    with pytest.raises(ConfigError, match="schema_version"):
        config_from_dict({"schema_version": 99})
    assert config_to_dict(cfg)["schema_version"] == 1


def test_no_geometry_and_sensor_that_sees_nothing_write_nothing(tmp_path):
    cfg = config_for(100.0, pixels=4)
    empty = SceneGeometry(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(ConfigError) as info:
        run_simulation(empty, np.eye(4), cfg, tmp_path / "run")
    assert info.value.field == "scene.triangles"
    behind = plate(-100.0, 10.0)  # behind the sensor
    with pytest.raises(ConfigError) as info:
        run_simulation(behind, np.eye(4), cfg, tmp_path / "run")
    assert info.value.field == "sensor" and "rays missed" in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_bad_pose_is_rejected():
    cfg = config_for(100.0, pixels=4)
    with pytest.raises(ConfigError, match="sensor.matrix_world"):
        simulate_frame(plate(100.0, 10.0), np.full((4, 4), np.nan), cfg)


def test_run_folder_contents_and_metadata(tmp_path):
    cfg = config_for(100.0, pixels=8)
    path, res = run_simulation(plate(100.0, 10.0), np.eye(4), cfg, tmp_path / "run", frame=7)
    names = sorted(p.name for p in path.iterdir())
    assert names == ["echoes.npz", "energy.exr", "intensity.exr", "metadata.json", "points.las", "points.npz",
                     "points.ply", "range.exr", "waveforms.npy"]
    meta = json.loads((path / "metadata.json").read_text())
    assert meta["frame"] == 7 and meta["seed"] == 0
    assert meta["settings"]["gate"]["n_bins"] == cfg.gate.n_bins
    assert set(meta["stage_times_s"]) >= {"build_bvh", "trace", "radiometry", "waveform", "echoes", "write"}
    assert "extinction" in meta["stages_skipped"]
    assert {"numpy", "scipy", "embreex", "OpenEXR", "python"} <= set(meta["software"])
    exr = read_exr(path / "range.exr")
    assert np.array_equal(exr["Y"], res.range_image)
    from core.fileio.las import read_las
    las = read_las(path / "points.las")["points"]
    assert len(las["x"]) == len(res.points["range_m"])
    np.testing.assert_allclose(las["z"], res.points["position_world"][:, 2], atol=1e-3)
    ply = read_ply(path / "points.ply")
    assert np.allclose(ply["z"], -100.0, atol=1e-3) and len(ply["x"]) == 64
    assert np.array_equal(ply["pixel_x"], res.points["pixel_x"])
    assert np.load(path / "waveforms.npy").shape == (8, 8, cfg.gate.n_bins)


def test_existing_run_is_not_overwritten_unless_asked(tmp_path):
    cfg = config_for(100.0, pixels=4)
    path, _ = run_simulation(plate(100.0, 10.0), np.eye(4), cfg, tmp_path / "run")
    before = (path / "metadata.json").read_bytes()
    with pytest.raises(ConfigError) as info:
        run_simulation(plate(100.0, 10.0), np.eye(4), cfg, tmp_path / "run")
    assert info.value.field == "out"
    assert (path / "metadata.json").read_bytes() == before
    cfg.run.seed = 5
    run_simulation(plate(100.0, 10.0), np.eye(4), cfg, tmp_path / "run", overwrite=True)
    assert json.loads((path / "metadata.json").read_text())["seed"] == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no temporary folders left


def test_failure_while_writing_leaves_nothing(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise OSError("disk full")
    monkeypatch.setattr("core.fileio.run_folder.write_ply", broken)
    with pytest.raises(OSError):
        run_simulation(plate(100.0, 10.0), np.eye(4), config_for(100.0, pixels=4), tmp_path / "run")
    assert list(tmp_path.iterdir()) == []


def test_cancel_writes_nothing(tmp_path):
    with pytest.raises(Cancelled):
        run_simulation(plate(100.0, 10.0), np.eye(4), config_for(100.0, pixels=4), tmp_path / "run",
                       cancel=lambda: True)
    assert list(tmp_path.iterdir()) == []


def test_products_do_not_depend_on_threads_or_chunking():
    """Bit-identical products for 1 or 2 threads and any block size."""
    scene = plate(150.0, 3.0, tilt_rad=0.7)
    ref = None
    for threads, chunk in ((1, 100_000_000), (2, 1024), (2, 4096)):
        cfg = config_for(150.0, pixels=32, subsamples=4, fov_rad=0.05)
        cfg.run.threads, cfg.run.chunk_rays = threads, chunk
        res = simulate_frame(scene, np.eye(4), cfg)
        if ref is None:
            ref = res
            assert res.stats["n_blocks"] == 1
            continue
        assert res.stats["n_blocks"] > 1
        assert np.array_equal(res.waveforms, ref.waveforms)
        assert np.array_equal(res.range_image, ref.range_image, equal_nan=True)
        assert np.array_equal(res.energy_image, ref.energy_image)


def test_points_only_run_allocates_no_cube(monkeypatch):
    cfg = config_for(100.0, pixels=8)
    cfg.run.save_waveforms = False
    res = simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    assert res.waveforms is None and "waveform_cube" in res.stats["stages_skipped"]
    assert len(res.points["range_m"]) == 64


def test_pose_moves_points_into_world():
    """A translated and rotated sensor: points land on the plate in world coordinates, sensor coordinates
    are camera-local (−Z forward)."""
    angle = np.radians(30)
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = [1000.0, -20.0, 5.0]
    local = plate(200.0, 10.0)
    scene = SceneGeometry(local.vertices_m @ rot.T + pose[:3, 3], local.triangles, local.material_ids)
    res = simulate_frame(scene, pose, config_for(200.0, pixels=8))
    back = (res.points["position_world"] - pose[:3, 3]) @ rot
    assert np.allclose(back, res.points["position_sensor"], atol=1e-9)
    assert np.abs(res.points["position_sensor"][:, 2] + 200.0).max() < 1e-3
