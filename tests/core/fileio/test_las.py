"""LAS 1.4 export (core/fileio/las.py): header bytes at the spec's offsets, our reader, laspy as an independent reader,
range precision, intensity scaling, atomic writes."""
import datetime
import json
import math
import struct

import laspy
import numpy as np
import pytest

from core.errors import ConfigError
from core.fileio.las import read_las, write_las
from core.systems.flash import simulate_frame
from scenes import config_for, plate


def _points(n=2000, seed=0, centre=(1234.5, -567.8, 42.0), spread=60.0):
    rng = np.random.default_rng(seed)
    origin = np.array(centre) + [0.0, 0.0, 300.0]
    pos = np.array(centre) + rng.uniform(-spread, spread, (n, 3))
    n_echoes = rng.integers(1, 4, n)
    echo = np.minimum(rng.integers(1, 4, n), n_echoes)
    return origin, {
        "position_world": pos, "position_sensor": pos - origin,
        "intensity": rng.uniform(0.0, 3e-13, n).astype(np.float32),
        "echo_index": echo.astype(np.int16), "n_echoes": n_echoes.astype(np.int16),
        "range_m": np.linalg.norm(pos - origin, axis=1), "time_s": rng.uniform(0, 1e-6, n),
        "gps_time_s": 86400.0 * 3 + np.arange(n) * 1e-5, "frame": np.full(n, 7, np.int32),
        "pixel_x": np.zeros(n, np.int32)}


def test_header_fields_at_the_spec_byte_offsets(tmp_path):
    """LAS 1.4-R15 Table 3: every public-header field read with struct at its documented offset."""
    _, pts = _points()
    path = write_las(tmp_path / "a.las", pts, creation_date=datetime.date(2026, 3, 1))
    data = path.read_bytes()

    def at(offset, fmt):
        return struct.unpack_from("<" + fmt, data, offset)

    assert data[0:4] == b"LASF"
    assert at(24, "BB") == (1, 4)                                          # version 1.4
    assert data[26:58].rstrip(b"\0") == b"Ladar Simulator (simulated)"     # system identifier
    assert data[58:90].rstrip(b"\0").startswith(b"ladar_simulator ")       # generating software
    assert at(90, "HH") == (60, 2026)                                      # day of year, year
    assert at(94, "H") == (375,)                                           # header size
    offset_to_points, n_vlrs = at(96, "I")[0], at(100, "I")[0]
    assert at(104, "B") == (6,)                                            # point data record format 6
    record_length = at(105, "H")[0]
    assert record_length == 30 + 4 + 8                                     # + intensity_raw f4, range_m f8
    assert at(107, "I") == (0,) and at(111, "5I") == (0,) * 5              # legacy counts: 0 for format 6
    assert at(6, "H")[0] & 0x10 and not at(6, "H")[0] & 0x01               # WKT bit set, GPS week time
    scale = at(131, "ddd")
    offset = at(155, "ddd")
    assert scale == (1e-4,) * 3                                            # 0.1 mm: within ±200 km
    pw = pts["position_world"]
    centre = np.round(0.5 * (pw.min(axis=0) + pw.max(axis=0)))
    assert offset == tuple(centre) and offset[2] == 42.0                   # bounding-box centre, whole metres
    max_x, min_x, max_y, min_y, max_z, min_z = at(179, "6d")
    assert at(227, "Q") == (0,) and at(235, "Q") == (0,) and at(243, "I") == (0,)  # no waveforms, no EVLRs
    assert at(247, "Q") == (2000,)                                         # 64-bit point count
    by_return = at(255, "15Q")
    assert sum(by_return) == 2000 and by_return[3:] == (0,) * 12
    assert list(by_return[:3]) == [int(np.sum(pts["echo_index"] == k)) for k in (1, 2, 3)]
    # VLRs fill the bytes between the header and the points exactly.
    pos = 375
    users = []
    for _ in range(n_vlrs):
        user, rid, length = data[pos + 2: pos + 18].rstrip(b"\0"), at(pos + 18, "H")[0], at(pos + 20, "H")[0]
        users.append((user, rid))
        pos += 54 + length
    assert pos == offset_to_points
    assert users == [(b"LASF_Projection", 2112), (b"LASF_Spec", 4), (b"LadarSimulator", 1)]
    assert len(data) == offset_to_points + 2000 * record_length
    # The first point record: X, Y, Z scaled integers at the start of the point data.
    x0, y0, z0 = at(offset_to_points, "3i")
    p0 = pts["position_world"][0]
    assert abs(x0 * scale[0] + offset[0] - p0[0]) <= 0.5e-4 + 1e-9
    assert abs(z0 * scale[2] + offset[2] - p0[2]) <= 0.5e-4 + 1e-9
    gps0 = at(offset_to_points + 22, "d")[0]
    assert gps0 == pts["gps_time_s"][0]
    # Bounds are those of the stored coordinates.
    xs = pts["position_world"][:, 0]
    assert min_x <= xs.min() + 0.5e-4 and max_x >= xs.max() - 0.5e-4 and max_x - min_x < 120.0 + 1e-3
    assert min_y < max_y and min_z < max_z


def test_round_trip_with_our_reader_and_range_precision(tmp_path):
    origin, pts = _points()
    las = read_las(write_las(tmp_path / "a.las", pts))
    p = las["points"]
    xyz = np.stack([p["x"], p["y"], p["z"]], axis=1)
    assert np.abs(xyz - pts["position_world"]).max() <= 0.5e-4 * (1 + 1e-9)   # ≤ scale/2 per axis
    range_err = np.abs(np.linalg.norm(xyz - origin, axis=1) - pts["range_m"])
    assert range_err.max() <= math.sqrt(3) * 0.5e-4 < 1e-3                    # range precision ≤ 1 mm
    # Intensity (J per bin): the fixed log scale round(65535 · log10(I / 1e-21 J) / 18), 0 at or below 1e-21 J.
    i = pts["intensity"].astype(np.float64)
    want = np.round(65535 * np.log10(np.maximum(i, 1e-21) / 1e-21) / 18)
    np.testing.assert_array_equal(p["intensity"], want)
    np.testing.assert_array_equal(p["return_number"], pts["echo_index"])
    np.testing.assert_array_equal(p["number_of_returns"], pts["n_echoes"])
    np.testing.assert_array_equal(p["gps_time"], pts["gps_time_s"])
    np.testing.assert_array_equal(p["point_source_id"], 7)
    np.testing.assert_array_equal(p["intensity_raw"], pts["intensity"])
    np.testing.assert_array_equal(p["range_m"], pts["range_m"])
    info = json.loads(las["vlrs"][-1][3])
    assert info["intensity_unit"] == "J per bin" and "log10(I / 1e-21 J) / 18" in info["intensity_scaling"]
    assert info["scale_m"] == 1e-4


def test_laspy_reads_the_same_file(tmp_path):
    """An independent reader (laspy 2.7.0, test-only dependency) sees the same header and points."""
    origin, pts = _points(seed=1)
    path = write_las(tmp_path / "a.las", pts)
    f = laspy.read(str(path))
    assert str(f.header.version) == "1.4" and f.header.point_format.id == 6
    assert f.header.point_count == 2000 and f.header.global_encoding.wkt
    assert list(f.point_format.extra_dimension_names) == ["intensity_raw", "range_m"]
    np.testing.assert_allclose(np.asarray(f.x), pts["position_world"][:, 0], atol=0.5e-4 * (1 + 1e-9), rtol=0)
    np.testing.assert_allclose(np.asarray(f.z), pts["position_world"][:, 2], atol=0.5e-4 * (1 + 1e-9), rtol=0)
    np.testing.assert_array_equal(np.asarray(f.return_number), pts["echo_index"])
    np.testing.assert_array_equal(np.asarray(f.number_of_returns), pts["n_echoes"])
    np.testing.assert_array_equal(np.asarray(f.gps_time), pts["gps_time_s"])
    np.testing.assert_array_equal(np.asarray(f.range_m), pts["range_m"])
    ours = read_las(path)["points"]
    np.testing.assert_array_equal(np.asarray(f.intensity), ours["intensity"])
    assert f.header.mins[0] == pytest.approx(np.asarray(f.x).min(), abs=1e-9)
    assert f.header.maxs[2] == pytest.approx(np.asarray(f.z).max(), abs=1e-9)
    assert list(f.header.number_of_points_by_return[:3]) == [int(np.sum(pts["echo_index"] == k))
                                                             for k in (1, 2, 3)]


def test_far_coordinates_use_millimetres_and_beyond_is_an_error(tmp_path):
    _, pts = _points(centre=(0.0, 0.0, 0.0), spread=1.0)
    pts["position_world"][0] = (5.0e5, 0.0, 0.0)  # 250 km from the bounding-box centre → 1 mm scale
    las = read_las(write_las(tmp_path / "far.las", pts))
    assert las["header"]["x_scale"] == 1e-3
    xyz = np.stack([las["points"][a] for a in "xyz"], axis=1)
    assert np.abs(xyz - pts["position_world"]).max() <= 0.5e-3 * (1 + 1e-9)
    pts["position_world"][0] = (5.0e6, 0.0, 0.0)
    with pytest.raises(ConfigError, match="points.position"):
        write_las(tmp_path / "too_far.las", pts)
    assert not (tmp_path / "too_far.las").exists()


def test_clipping_defaults_and_sensor_coordinates(tmp_path):
    n = 4
    pts = {"position_world": np.zeros((n, 3)) + [0.0, 0.0, -100.0], "position_sensor": np.zeros((n, 3)),
           "intensity": np.array([1.0, 2.0, 4.0, -1.0]), "echo_index": np.array([1, 2, 20, 16]),
           "n_echoes": np.array([1, 1, 20, 17])}
    las = read_las(write_las(tmp_path / "c.las", pts, intensity_unit="counts", frame_time_s=12.5))
    p = las["points"]
    assert list(p["intensity"]) == [1, 2, 4, 0]                        # counts as they are, clipped at 0
    assert list(p["return_number"]) == [1, 2, 15, 15]                  # at most 15 returns in LAS
    assert list(p["number_of_returns"]) == [1, 2, 15, 15]              # never fewer than the return number
    assert list(p["gps_time"]) == [12.5] * 4                           # no gps_time_s: the frame's time
    assert list(p["point_source_id"]) == [0] * 4 and list(p["z"]) == [-100.0] * 4
    las = read_las(write_las(tmp_path / "s.las", pts, coordinates="sensor"))
    assert list(las["points"]["z"]) == [0.0] * 4
    # An empty cloud is a valid file.
    empty = {"position_world": np.zeros((0, 3)), "intensity": np.zeros(0)}
    f = laspy.read(str(write_las(tmp_path / "e.las", empty)))
    assert f.header.point_count == 0


@pytest.mark.parametrize("change, field", [
    (lambda p: p.update(position_world=np.full((3, 3), np.nan)), "points.position_world"),
    (lambda p: p.update(position_world=np.zeros((3, 2))), "points.position_world"),
    (lambda p: p.pop("position_world"), "points.position_world"),
    (lambda p: p.update(intensity=np.array([1.0, np.inf, 0.0])), "points.intensity"),
    (lambda p: p.update(echo_index=np.ones(5)), "points.echo_index"),
    (lambda p: p.update(gps_time_s=np.array([0.0, np.nan, 1.0])), "points.gps_time_s"),
])
def test_bad_points_write_nothing(tmp_path, change, field):
    pts = {"position_world": np.zeros((3, 3)), "intensity": np.ones(3)}
    change(pts)
    with pytest.raises(ConfigError) as err:
        write_las(tmp_path / "bad.las", pts)
    assert err.value.field == field
    assert list(tmp_path.iterdir()) == []


def test_no_silent_overwrite_and_atomic_write(tmp_path, monkeypatch):
    _, pts = _points(n=10)
    path = write_las(tmp_path / "a.las", pts)
    before = path.read_bytes()
    with pytest.raises(ConfigError, match="does not exist yet"):
        write_las(path, pts)
    assert path.read_bytes() == before
    pts["intensity"] = pts["intensity"] * 0.5
    write_las(path, pts, overwrite=True)
    assert path.read_bytes() != before
    # A failure while writing leaves the old file and no temporary file.
    import core.fileio.staging as staging  # the one atomic single-file write

    def fail(*args, **kwargs):
        raise OSError("disk full")
    monkeypatch.setattr(staging.os, "replace", fail)
    current = path.read_bytes()
    with pytest.raises(OSError, match="disk full"):
        write_las(path, pts, overwrite=True)
    assert path.read_bytes() == current
    assert [p.name for p in tmp_path.iterdir()] == ["a.las"]


def test_simulated_frame_to_las(tmp_path):
    """A flash frame of a plate at 100 m: every pixel's echo in the LAS file at 100 m ± 1 mm."""
    cfg = config_for(100.0, pixels=8, subsamples=2, fov_rad=0.01)
    res = simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    path = write_las(tmp_path / "frame.las", res.points)
    f = laspy.read(str(path))
    assert f.header.point_count == 64
    z = np.asarray(f.z)
    np.testing.assert_allclose(z, res.points["position_world"][:, 2], atol=0.5e-4 * (1 + 1e-9), rtol=0)
    assert np.all(np.abs(np.asarray(f.range_m) - 100.0) < 1e-3 * 100)  # slant ranges within the 0.01 rad FOV
    i = res.points["intensity"].astype(np.float64)
    np.testing.assert_array_equal(np.asarray(f.intensity), np.round(65535 * np.log10(i / 1e-21) / 18))


def test_run_folder_to_las(tmp_path):
    """write_run_las: a run's points.npz, or a sequence's frame_*/points.npz in frame order; the run's
    start time for points without gps_time_s; run facts in the LadarSimulator VLR."""
    from core.fileio.las import write_run_las
    run = tmp_path / "run"
    run.mkdir()
    pts = {"position_world": np.array([[0.0, 0.0, -10.0], [1.0, 0.0, -10.0]]), "intensity": np.array([1.0, 0.5]),
           "frame": np.array([3, 3])}
    np.savez(run / "points.npz", **pts)
    (run / "metadata.json").write_text(json.dumps({"system_type": "flash", "frame": 3, "seed": 9,
                                                   "start_time_s": 0.125}))
    las = read_las(write_run_las(run, tmp_path / "a.las"))
    assert list(las["points"]["gps_time"]) == [0.125, 0.125] and list(las["points"]["point_source_id"]) == [3, 3]
    info = json.loads(las["vlrs"][-1][3])
    assert info["system_type"] == "flash" and info["seed"] == 9 and info["run"] == "run"
    seq = tmp_path / "seq"
    for frame in (2, 1):
        (seq / f"frame_{frame:04d}").mkdir(parents=True)
        np.savez(seq / f"frame_{frame:04d}" / "points.npz",
                 position_world=np.full((frame, 3), float(frame)), intensity=np.ones(frame),
                 frame=np.full(frame, frame))
    las = read_las(write_run_las(seq, tmp_path / "seq.las"))
    assert list(las["points"]["point_source_id"]) == [1, 2, 2] and list(las["points"]["x"]) == [1.0, 2.0, 2.0]
    with pytest.raises(ConfigError, match="run folder"):
        write_run_las(tmp_path / "nothing", tmp_path / "n.las")
