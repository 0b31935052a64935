"""LAS files other tools read (issue 14): a CRS that PROJ < 9.4 (PDAL's and GDAL's parser) accepts, LAZ through
laspy + lazrs (what ``pdal translate`` to LAZ does), scan angles, the synthetic flag, ground-truth classes from
the scene's materials, false alarms as withheld noise, a fixed intensity scale, a merged LAS for frame ranges,
and the sensor pose / trajectory in metadata.json."""
import json
import re
import shutil
import subprocess

import laspy
import numpy as np
import pytest

from core import sequence
from core.config import BRDFSettings, SimulationConfig
from core.fileio.las import LOCAL_WKT, las_intensity, read_las, write_las
from core.geometry.groundtruth import surface_material_ids
from core.geometry.motion import Trajectory
from core.geometry.scene import SceneGeometry
from core.geometry.trace import SceneTracer
from core.run import run_simulation, simulate
from scenes import C, config_for, plate


def scene_of(*parts):
    """Merge (SceneGeometry, material name) parts, one material per part."""
    v, t, m, off = [], [], [], 0
    for k, (s, _) in enumerate(parts):
        v.append(s.vertices_m)
        t.append(s.triangles + off)
        m.append(np.full(len(s.triangles), k))
        off += len(s.vertices_m)
    return SceneGeometry(np.vstack(v), np.vstack(t), np.concatenate(m), [BRDFSettings() for _ in parts],
                         [name for _, name in parts])


def scanner_config(**scan):
    cfg = SimulationConfig(system_type="scanner")
    for k, v in scan.items():
        setattr(cfg.scanner, k, v)
    cfg.laser.beam_divergence_rad = 1e-3
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.gate.gate_start_s = 0.0
    cfg.gate.bin_width_s = 0.25e-9
    cfg.gate.n_bins = 2048  # 0 … 76.8 m
    cfg.run.save_waveforms = False
    cfg.run.threads = 1
    return cfg


def wkt_of(path):
    return next(p for u, r, _, p in read_las(path)["vlrs"] if (u, r) == ("LASF_Projection", 2112)).rstrip(b"\0")


# --------------------------------------------------------------------------------------------------------------
# CRS and LAZ
# --------------------------------------------------------------------------------------------------------------
def test_the_crs_parses_with_proj_before_9_4_as_pdal_uses_it(tmp_path):
    """projinfo (Debian's PROJ 9.1.1, installed by scripts/setup.sh) parses the file's WKT as PDAL does through
    GDAL: before, the three-axis LOCAL_CS failed with 'buildCS: unexpected AXIS count for LOCAL_CS'."""
    projinfo = shutil.which("projinfo")
    assert projinfo, "projinfo (Debian package proj-bin) is missing: run scripts/setup.sh"
    ran = subprocess.run([projinfo], capture_output=True, text=True)
    version = ran.stdout + ran.stderr
    path = write_las(tmp_path / "a.las", {"position_world": np.zeros((2, 3)), "intensity": np.ones(2)})
    wkt = wkt_of(path).decode("ascii")
    assert wkt == LOCAL_WKT
    out = subprocess.run([projinfo, "-o", "WKT1_GDAL", "-q", wkt], capture_output=True, text=True)
    assert out.returncode == 0 and "error" not in (out.stdout + out.stderr).lower(), out.stdout + out.stderr
    assert 'UNIT["metre",1]' in out.stdout and 'AXIS["X",EAST]' in out.stdout and 'AXIS["Y",NORTH]' in out.stdout
    major, minor = map(int, re.search(r"Rel\. (\d+)\.(\d+)", version).groups())
    if (major, minor) < (9, 4):  # the checker reproduces the reported failure of the former WKT
        old = wkt.replace("]]", '],AXIS["Z",UP]]')
        bad = subprocess.run([projinfo, "-o", "WKT1_GDAL", "-q", old], capture_output=True, text=True)
        assert "unexpected AXIS count for LOCAL_CS" in bad.stdout + bad.stderr


def test_laz_round_trip_through_laspy_and_lazrs(tmp_path):
    """What 'pdal translate a.las a.laz' does: read with laspy, compress with lazrs, read back — every
    dimension (coordinates, intensity, classes, flags, scan angle, GPS time, extra bytes) survives."""
    rng = np.random.default_rng(3)
    n = 500
    pos = rng.uniform(-20, 20, (n, 3)) + [0.0, 0.0, -50.0]
    pts = {"position_world": pos, "position_sensor": pos, "intensity": rng.uniform(1e-15, 1e-12, n),
           "range_m": np.linalg.norm(pos, axis=1), "material_id": rng.integers(-1, 3, n).astype(np.int16),
           "false_alarm": (rng.random(n) < 0.1).astype(np.uint8), "gps_time_s": np.arange(n) * 1e-4}
    src = write_las(tmp_path / "a.las", pts, class_names=["asphalt", "brick", "glass"])
    las = laspy.read(str(src))
    las.write(str(tmp_path / "a.laz"), do_compress=True, laz_backend=laspy.LazBackend.Lazrs)
    laz = laspy.read(str(tmp_path / "a.laz"))
    assert laz.header.are_points_compressed and laz.header.point_count == n
    for dim in ("X", "Y", "Z", "intensity", "classification", "synthetic", "withheld", "scan_angle", "gps_time",
                "return_number", "range_m", "intensity_raw"):
        np.testing.assert_array_equal(np.asarray(laz[dim]), np.asarray(las[dim]), err_msg=dim)
    assert laz.header.vlrs[0].record_id == 2112 or any(v.record_id == 2112 for v in laz.header.vlrs)


# --------------------------------------------------------------------------------------------------------------
# Point fields
# --------------------------------------------------------------------------------------------------------------
def test_scanner_scan_angles_span_the_scan_and_points_are_synthetic(tmp_path):
    """A raster scan ±25° wide: the LAS scan angle is each pulse's across-scan angle (0.006° steps), spanning
    −25° … +25°; every point carries the synthetic flag (before: scan angle 0, no flag)."""
    cfg = scanner_config(pattern="raster", n_lines=3, scan_rate_hz=100.0, pulse_rate_hz=8000.0,
                         scan_width_rad=np.deg2rad(50.0), scan_height_rad=0.05)
    res = simulate(plate(20.0, 40.0), np.eye(4), cfg)
    las = laspy.read(str(write_las(tmp_path / "s.las", res.points)))
    deg = np.asarray(las.scan_angle) * 0.006
    np.testing.assert_allclose(deg, np.degrees(res.points["scan_angle_rad"]), atol=0.003 + 1e-6)
    step = 50.0 / 80  # 80 pulses per line
    assert deg.min() == pytest.approx(-25.0, abs=0.01) and deg.max() == pytest.approx(25.0 - step, abs=0.01)
    assert np.all(np.asarray(las.synthetic)) and not np.any(np.asarray(las.withheld))


def test_flash_scan_angle_is_the_pixel_column_angle(tmp_path):
    cfg = config_for(100.0, pixels=8, subsamples=2, fov_rad=0.2)
    res = simulate(plate(100.0, 50.0), np.eye(4), cfg)
    las = read_las(write_las(tmp_path / "f.las", res.points))
    ps = res.points["position_sensor"]
    want = np.degrees(np.arctan2(ps[:, 0], -ps[:, 2]))
    np.testing.assert_allclose(las["points"]["scan_angle"] * 0.006, want, atol=0.003 + 1e-6)
    # 8 columns over a 0.2 rad field of view: the outer column centres at ±atan(7/8 · tan 0.1)
    edge = np.degrees(np.arctan(7 / 8 * np.tan(0.1)))
    assert las["points"]["scan_angle"].max() * 0.006 == pytest.approx(edge, abs=0.003)


def test_classes_are_the_scene_materials_of_each_echo(tmp_path):
    """A scanner beam half on a front plate ('hedge', 30 m), half on a wall behind ('brick', 31.5 m): echo 1 is
    class 64 + 0, echo 2 class 64 + 1; the class names are in the LadarSimulator VLR."""
    front = plate(30.0, 1.0, offset=(-1.0 - 1e-4, 0.0, 0.0))
    back = plate(31.5, 5.0)
    cfg = scanner_config(pattern="raster", n_lines=1, scan_rate_hz=1000.0, pulse_rate_hz=1000.0,
                         scan_width_rad=0.0, scan_height_rad=0.0, beam_subray_rings=4)
    cfg.laser.beam_divergence_rad = 4e-3
    path, res = run_simulation(scene_of((front, "hedge"), (back, "brick")), np.eye(4), cfg, tmp_path / "run")
    assert list(res.points["material_id"]) == [0, 1]
    las = read_las(path / "points.las")
    assert list(las["points"]["classification"]) == [64, 65]
    info = json.loads(las["vlrs"][-1][3])
    assert info["classes"]["64"] == "material hedge" and info["classes"]["65"] == "material brick"
    meta = json.loads((path / "metadata.json").read_text())
    assert meta["material_names"] == ["hedge", "brick"]


def test_ground_truth_walks_through_several_surfaces_and_rejects_empty_air():
    scene = scene_of((plate(10.0, 5.0), "a"), (plate(20.0, 5.0), "b"), (plate(30.0, 5.0), "c"))
    tracer = SceneTracer(scene)
    pos = np.array([[0, 0, -10.01], [0, 0, -19.98], [0.5, 0, -30.0], [0, 0, -25.0], [0, 0, -45.0]])
    ids = surface_material_ids(tracer, scene.material_ids, np.zeros(3), pos, tolerance_m=0.5)
    assert list(ids) == [0, 1, 2, -1, -1]  # 25 m and 45 m: 5 m and 15 m from the nearest surface


def test_false_alarms_are_withheld_noise(tmp_path):
    """Noisy scanner: the echoes flagged false alarms are class 7 and withheld in the LAS file, the others carry
    the wall's material class (before: class 0 and no flag for all)."""
    cfg = scanner_config(pattern="raster", n_lines=4, scan_rate_hz=100.0, pulse_rate_hz=4000.0,
                         scan_width_rad=0.1, scan_height_rad=0.05)
    cfg.detector.mode = "noisy"
    cfg.detection.k_sigma = 2.5  # a low threshold: false alarms on the noise
    cfg.gate.n_bins = 512
    cfg.gate.gate_start_s = 2 * 30.0 / C
    res = simulate(plate(40.0, 10.0), np.eye(4), cfg)
    fa = res.points["false_alarm"].astype(bool)
    assert 0 < fa.sum() < len(fa)
    las = laspy.read(str(write_las(tmp_path / "n.las", res.points, intensity_unit="counts",
                                   class_names=["plate"])))
    cls = np.asarray(las.classification)
    np.testing.assert_array_equal(np.asarray(las.withheld), fa)
    assert np.all(cls[fa] == 7) and np.all(cls[~fa] == 64)
    assert np.all(np.asarray(las.synthetic))


def test_intensity_scale_is_the_same_in_every_file(tmp_path):
    """The same echo gets the same LAS intensity whatever else the file holds (before: scaled to each file's
    maximum, so one bright point changed every other value)."""
    a = {"position_world": np.zeros((2, 3)), "intensity": np.array([1e-13, 1e-12])}
    b = {"position_world": np.zeros((2, 3)), "intensity": np.array([1e-13, 1e-9])}
    ia = read_las(write_las(tmp_path / "a.las", a))["points"]["intensity"]
    ib = read_las(write_las(tmp_path / "b.las", b))["points"]["intensity"]
    assert ia[0] == ib[0] == round(65535 * 8 / 18)  # 1e-13 J is 8 decades above 1e-21 J
    assert list(las_intensity(np.array([0.0, 1e-21, 1e-3, 1.0]), "J")) == [0, 0, 65535, 65535]
    assert list(las_intensity(np.array([-3.0, 12.4, 70000.0]), "counts")) == [0, 12, 65535]


def test_run_las_intensity_unit_follows_the_receiver(tmp_path):
    cfg = config_for(100.0, pixels=4, subsamples=2, fov_rad=0.01)
    cfg.detector.mode = "noisy"
    path, res = run_simulation(plate(100.0, 10.0), np.eye(4), cfg, tmp_path / "run")
    info = json.loads(read_las(path / "points.las")["vlrs"][-1][3])
    assert info["intensity_unit"] == res.stats["receiver"]["units"] == "counts"


# --------------------------------------------------------------------------------------------------------------
# Frame ranges, pose and trajectory
# --------------------------------------------------------------------------------------------------------------
def pose(x_m):
    m = np.eye(4)
    m[0, 3] = x_m
    return m


def test_sequence_writes_a_merged_las_beside_the_merged_ply(tmp_path):
    wall = plate(50.0, 30.0)
    cfg = config_for(50.0, pixels=8, fov_rad=0.1, bins=512, margin_bins=128)
    cfg.run.save_waveforms = False
    path, stats = sequence.run_sequence([1, 2, 3], lambda f: wall, lambda f: pose(2.0 * f), cfg, tmp_path / "seq")
    f = laspy.read(str(path / "points_merged.las"))
    assert f.header.point_count == sum(s["n_points"] for s in stats) == 3 * 64
    assert sorted(set(np.asarray(f.point_source_id).tolist())) == [1, 2, 3]
    np.testing.assert_allclose(np.asarray(f.z), -50.0, atol=2e-3)
    assert np.all(np.asarray(f.classification) == 64)
    meta = json.loads((path / "metadata.json").read_text())
    assert "points_merged.las" in meta["files"]
    assert [meta["sensor_poses"][str(f)][0][3] for f in (1, 2, 3)] == [2.0, 4.0, 6.0]  # each frame's pose


def test_metadata_records_the_sensor_pose_and_the_scan_trajectory(tmp_path):
    m = pose(3.0)
    c, s = np.cos(0.3), np.sin(0.3)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]  # yaw 0.3 rad about +Y
    cfg = config_for(50.0, pixels=4, fov_rad=0.01, bins=512, margin_bins=128)
    path, _ = run_simulation(plate(50.0, 40.0, offset=(3.0 - 50 * np.tan(0.3), 0.0, 0.0)), m, cfg, tmp_path / "a")
    meta = json.loads((path / "metadata.json").read_text())
    np.testing.assert_allclose(meta["sensor_pose"]["world_from_sensor"], m, atol=1e-15)
    assert meta["sensor_pose"]["position_m"] == [3.0, 0.0, 0.0]
    np.testing.assert_allclose(meta["sensor_pose"]["quaternion_wxyz"], [np.cos(0.15), 0, np.sin(0.15), 0],
                               atol=1e-12)
    # a moving scanner: the sampled trajectory it flew
    cfg = scanner_config(pattern="oscillating", scan_width_rad=0.2, scan_rate_hz=20.0, pulse_rate_hz=2000.0,
                         duration_s=0.1, beam_subray_rings=1)
    times = np.linspace(0.0, 0.1, 5)
    mats = np.repeat(np.eye(4)[None], len(times), axis=0)
    mats[:, 0, 3] = 50.0 * times
    path, _ = run_simulation(plate(20.0, 40.0), mats[0], cfg, tmp_path / "b", trajectory=Trajectory(times, mats))
    traj = json.loads((path / "metadata.json").read_text())["trajectory"]
    assert traj["times_s"] == pytest.approx(times.tolist())
    np.testing.assert_allclose(np.array(traj["position_m"])[:, 0], 50.0 * times)
    np.testing.assert_allclose(traj["quaternion_wxyz"], [[1, 0, 0, 0]] * 5)


def test_exr_headers_carry_unit_pose_and_gate_delay(tmp_path):
    """OpenEXR's reader sees each image's product and unit, the sensor pose (standard worldToCamera, Imath
    row-vector convention, and the exact matrix) and, on every gated slice, its gate delay, width and range
    (before: compression and type only)."""
    import OpenEXR

    from core.systems.gated import slice_delays_s
    from core.fileio.run_folder import read_exr_header
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px, cfg.receiver.height_px = 8, 4
    cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = 8e-3, 4e-3
    cfg.gated.n_slices, cfg.gated.delay_step_s, cfg.gated.gate_width_s = 6, 5e-9, 20e-9
    cfg.gated.first_delay_s = 2 * 300.0 / C - 15e-9
    cfg.run.threads = 1
    m = pose(2.0)
    path, res = run_simulation(plate(300.0, 20.0, offset=(2.0, 0.0, 0.0)), m, cfg, tmp_path / "g")
    h = read_exr_header(path / "range.exr")
    assert h["product"] == "range from the slice stack" and h["units"] == "m"
    assert h["ladarSystem"] == "gated" and h["ladarFrame"] == 0
    np.testing.assert_array_equal(h["ladarWorldFromSensor"], m)
    np.testing.assert_array_equal(h["ladarSensorPosition_m"], [2.0, 0.0, 0.0])
    p_world = np.array([5.0, 1.0, -300.0, 1.0])
    np.testing.assert_allclose(p_world @ h["worldToCamera"], [3.0, 1.0, -300.0, 1.0], atol=1e-4)
    assert read_exr_header(path / "intensity.exr")["units"] == res.units["intensity"] == "J"
    delays = slice_delays_s(cfg)
    for k in range(6):
        hs = read_exr_header(path / "slices" / f"slice_{k + 1:04d}.exr")
        assert hs["ladarSlice"] == k + 1 and hs["units"] == "J per pixel"
        assert hs["ladarGateDelay_s"] == pytest.approx(delays[k], rel=1e-7)  # float32 attribute
        assert hs["ladarGateRange_m"] == pytest.approx(0.5 * C * delays[k], rel=1e-7)
        assert hs["ladarGateWidth_s"] == pytest.approx(20e-9, rel=1e-7)
    with OpenEXR.File(str(path / "slices" / "slice_0001.exr")) as f:  # the pixels are unchanged
        np.testing.assert_array_equal(f.channels()["Y"].pixels, res.slices[0])
