"""Several frames with a moving sensor, registered in one world frame (issue 5, paper §2.3 / Fig. 12)."""
import json

import numpy as np
import pytest

from core import sequence
from core.config.settings import BRDFSettings
from core.errors import ConfigError
from core.errors import Cancelled
from core.fileio.run_folder import read_ply
from core.geometry.trace import SceneTracer
from scenes import config_for, plate


def pose(x_m, yaw_rad):
    """Sensor at (x, 0, 0) turned by yaw about +Y (camera frame: looks along its −Z)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[0, 3] = x_m
    return m


def test_frames_register_on_the_wall_and_share_one_bvh(tmp_path, monkeypatch):
    builds = []
    original = SceneTracer.__init__

    def counting(self, scene):
        builds.append(1)
        original(self, scene)

    monkeypatch.setattr(SceneTracer, "__init__", counting)
    wall = plate(50.0, 30.0)
    cfg = config_for(50.0, pixels=16, fov_rad=0.1, bins=512, margin_bins=128)
    cfg.run.save_waveforms = False
    cfg.materials = {"plate": BRDFSettings(reflectance=0.5)}  # an override shares the geometry: same BVH
    poses = {1: pose(0.0, 0.0), 2: pose(3.0, 0.05), 3: pose(6.0, -0.05)}
    path, stats = sequence.run_sequence([1, 2, 3], lambda f: wall, poses.__getitem__, cfg, tmp_path / "seq")
    assert len(builds) == 1  # static geometry: one BVH for the three frames
    meta = json.loads((path / "metadata.json").read_text())
    assert meta["bvh_builds"] == 1 and meta["frames"] == [1, 2, 3]
    merged = read_ply(path / "points_merged.ply")
    z = merged["z"]
    np.testing.assert_allclose(z, -50.0, atol=2e-3)  # every frame's points on the wall in world coordinates
    assert sorted(set(merged["frame"].tolist())) == [1, 2, 3]
    # the frames see different parts of the wall (the sensor moved and turned): centred where the optical
    # axis meets the wall, x0 − 50 tan(yaw)
    centres = [merged["x"][merged["frame"] == f].mean() for f in (1, 2, 3)]
    np.testing.assert_allclose(centres, [0.0, 3.0 - 50 * np.tan(0.05), 6.0 + 50 * np.tan(0.05)], atol=0.1)
    for f in (1, 2, 3):
        assert (path / f"frame_{f:04d}" / "metadata.json").exists()
    assert sum(s["n_points"] for s in stats) == len(z)


def test_animated_geometry_is_rebuilt_and_a_cancelled_sequence_leaves_nothing(tmp_path):
    cfg = config_for(50.0, pixels=8, fov_rad=0.1, bins=512, margin_bins=128)
    scenes = {1: plate(50.0, 30.0), 2: plate(50.5, 30.0)}  # the wall moves: a new geometry per frame
    path, stats = sequence.run_sequence([1, 2], scenes.__getitem__, lambda f: np.eye(4), cfg, tmp_path / "moving")
    assert json.loads((path / "metadata.json").read_text())["bvh_builds"] == 2
    ranges = [np.load(path / f"frame_{f:04d}" / "points.npz")["range_m"] for f in (1, 2)]
    assert np.median(ranges[1]) - np.median(ranges[0]) == pytest.approx(0.5, abs=5e-3)
    calls = []
    with pytest.raises(Cancelled):
        sequence.run_sequence([1, 2], scenes.__getitem__, lambda f: np.eye(4), cfg, tmp_path / "cancelled",
                              cancel=lambda: len(calls) > 0, progress=lambda x, t: calls.append(t))
    assert not (tmp_path / "cancelled").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    with pytest.raises(ConfigError, match="out"):
        sequence.run_sequence([1], scenes.__getitem__, lambda f: np.eye(4), cfg, path)
    with pytest.raises(ConfigError, match="frames"):
        sequence.run_sequence([], scenes.__getitem__, lambda f: np.eye(4), cfg, tmp_path / "none")
