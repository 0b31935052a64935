"""Hostile input at the core's boundary (issue 15): config files that cannot be read, values that cannot be
represented, scene arrays of the wrong shape, type or range, objects that are not configs.  Each must give a
ConfigError — one line, naming the field, echoing the value cut to a sane length, saying what is allowed —
and write nothing."""
import numpy as np
import pytest

from core.config import SimulationConfig, config_from_dict, load_config
from core.errors import MAX_ECHO_CHARS, ConfigError
from core.run import run_simulation, simulate
from core.geometry.scene import SceneGeometry

V = np.array([[-1, -1, -10], [1, -1, -10], [1, 1, -10], [-1, 1, -10]], float)
T = [[0, 1, 2], [0, 2, 3]]


def _one_line(exc, *fragments):
    msg = str(exc.value)
    assert "\n" not in msg and len(msg) < 4 * MAX_ECHO_CHARS + 400, msg[:300]
    for f in fragments:
        assert f in msg, msg
    return msg


@pytest.mark.parametrize("name,data,fragments", [
    ("big.toml", b"[laser]\npulse_energy_j = " + b"9" * 400 + b"\n", ["laser.pulse_energy_j", "(0, 100] J"]),
    ("big.json", b'{"laser": {"pulse_energy_j": ' + b"9" * 400 + b"}}", ["laser.pulse_energy_j", "(0, 100] J"]),
    ("huge.json", b'{"laser": {"pulse_energy_j": ' + b"9" * 5000 + b"}}", ["config file", "valid JSON"]),
    ("table.toml", b"[materials.m]\nmodel = \"table\"\ntable_angle_deg = [0, " + b"9" * 400 + b"]\n"
                   b"table_brdf_per_sr = [1, 1]\n", ["materials.m.table_angle_deg[1]", "a finite number"]),
    ("latin1.toml", b"[laser]\npulse_shape = \"gau\xdfian\"\n", ["config file", "UTF-8", "byte 26"]),
    ("latin1.json", b'{"laser": {"pulse_shape": "\xff"}}', ["config file", "UTF-8"]),
    ("deep.json", b"[" * 100_000 + b"]" * 100_000, ["config file", "nested at most"]),
    ("deep.toml", b"x = " + b"[" * 100_000 + b"]" * 100_000, ["config file"]),
    ("deep2.json", b'{"laser": {"pulse_shape": ' + b"[" * 500 + b"]" * 500 + b"}}", ["nested at most"]),
    ("schema.toml", b"schema_version = true\n", ["schema_version = True", "1 (this version"]),
    ("schema2.toml", b"schema_version = 1.0\n", ["schema_version = 1.0"]),
    ("angle.toml", b"[materials.m]\ntable_angle_deg = 0\n", ["materials.m.table_angle_deg = 0", "a list"]),
    ("brdf.toml", b"[materials.m]\ntable_brdf_per_sr = false\n", ["materials.m.table_brdf_per_sr = False"]),
])
def test_unreadable_config_files_give_one_clean_line(tmp_path, name, data, fragments):
    (tmp_path / name).write_bytes(data)
    with pytest.raises(ConfigError) as exc:
        load_config(tmp_path / name)
    _one_line(exc, *fragments)


@pytest.mark.parametrize("data", [b'[laser]\npulse_shape = "' + b"x" * 10_000_000 + b'"\n',
                                  b'[laser]\n"' + b"k" * 10_000_000 + b'" = 1\n',
                                  b'[laser]\npulse_shape = [' + b"1, " * 1_000_000 + b"1]\n"])
def test_a_huge_bad_value_is_echoed_cut(tmp_path, data):
    """A 10 MB value (or key) is echoed in ≤ ~150 characters, with its length."""
    (tmp_path / "c.toml").write_bytes(data)
    with pytest.raises(ConfigError) as exc:
        load_config(tmp_path / "c.toml")
    msg = _one_line(exc, "laser.")
    assert len(msg) < 700


def test_huge_integer_value_is_echoed_by_its_size():
    with pytest.raises(ConfigError) as exc:
        config_from_dict({"gate": {"n_bins": 10 ** 20000}})
    _one_line(exc, "gate.n_bins = <an integer of about 20001 digits>", "[1, 1e+06]")


@pytest.mark.parametrize("config", [None, {"laser": {}}, "flash", SimulationConfig])
def test_core_api_refuses_what_is_not_a_config(tmp_path, config):
    scene = SceneGeometry(V, T, [0, 0])
    for call in (lambda: simulate(scene, np.eye(4), config),
                 lambda: run_simulation(scene, np.eye(4), config, tmp_path / "run")):
        with pytest.raises(ConfigError) as exc:
            call()
        _one_line(exc, "config = ", "a SimulationConfig")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kwargs,fragments", [
    (dict(triangles=np.array([[0, 1, 2], [0, 2, 2 ** 32 + 3]])), ["scene.triangles", "index 4294967299", "int64"]),
    (dict(triangles=[[0, 1, 2], [0, 2, -1]]), ["scene.triangles", "index -1"]),
    (dict(material_ids=np.array([0, 2 ** 32])), ["scene.material_ids", "index 4294967296"]),
    (dict(material_ids=np.array([0, -2 ** 40])), ["scene.material_ids", "index -1099511627776"]),
    (dict(vertices_m=np.zeros((6, 2))), ["scene.vertices_m", "shape (6, 2)", "(N, 3)"]),
    (dict(vertices_m=np.zeros(12)), ["scene.vertices_m", "shape (12,)"]),
    (dict(triangles=np.zeros((3, 4), int)), ["scene.triangles", "shape (3, 4)", "(M, 3)"]),
    (dict(triangles=np.zeros(6, int)), ["scene.triangles", "shape (6,)"]),
    (dict(material_ids=[[0], [0]]), ["scene.material_ids", "shape (2, 1)"]),
    (dict(triangles=[[0, 1, 2.7], [0, 2, 3]]), ["scene.triangles", "2.7", "float64", "no fractions"]),
    (dict(material_ids=[0.5, 0]), ["scene.material_ids", "0.5"]),
    (dict(triangles=[[0, 1, np.nan], [0, 2, 3]]), ["scene.triangles", "nan"]),
    (dict(vertices_m=V.astype(complex)), ["scene.vertices_m", "complex128"]),
    (dict(vertices_m=[[1, 2, 3], [4]]), ["scene.vertices_m", "not a rectangular array"]),
    (dict(vertices_m="abc"), ["scene.vertices_m", "dtype <U3"]),
    (dict(triangles=None), ["scene.triangles", "dtype object"]),
    (dict(material_ids=[True, False]), ["scene.material_ids", "dtype bool"]),
])
def test_scene_arrays_are_checked_not_reshaped_truncated_or_wrapped(kwargs, fragments):
    args = dict(vertices_m=V, triangles=T, material_ids=[0, 0])
    args.update(kwargs)
    with pytest.raises(ConfigError) as exc:
        SceneGeometry(**args)
    _one_line(exc, *fragments)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_vertices_are_refused_before_tracing(tmp_path, bad):
    v = V.copy()
    v[2, 1] = bad
    cfg = SimulationConfig()
    cfg.receiver.width_px = cfg.receiver.height_px = 4
    with pytest.raises(ConfigError) as exc:
        run_simulation(SceneGeometry(v, T, [0, 0]), np.eye(4), cfg, tmp_path / "run")
    _one_line(exc, "scene.vertices_m", "finite")
    assert list(tmp_path.iterdir()) == []


def test_whole_number_float_indices_are_accepted():
    """Index arrays built with np.zeros(n) (float64 of whole numbers) keep working."""
    s = SceneGeometry(V, np.array(T, float), np.zeros(2))
    assert s.triangles.dtype == np.int32 and s.material_ids.dtype == np.int32
    assert s.triangles.tolist() == T


@pytest.mark.parametrize("system", ["flash", "profiler", "scanner", "gated"])
@pytest.mark.parametrize("pose", [None, np.eye(3), np.full((4, 4), np.nan), "pose"])
def test_a_pose_that_is_not_a_4x4_matrix_is_refused_by_every_system(tmp_path, system, pose):
    """Every system opens its frame through the engine: a missing or malformed sensor pose is one ConfigError
    (before the Engine refactor's None-means-trajectory rule, None reached the culling as a ValueError)."""
    cfg = SimulationConfig()
    cfg.system_type = system
    cfg.receiver.width_px = cfg.receiver.height_px = 4
    cfg.scanner.n_lines = 4
    for call in (lambda: simulate(SceneGeometry(V, T, [0, 0]), pose, cfg),
                 lambda: run_simulation(SceneGeometry(V, T, [0, 0]), pose, cfg, tmp_path / "run")):
        with pytest.raises(ConfigError) as exc:
            call()
        _one_line(exc, "sensor.matrix_world", "a finite 4×4 matrix")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("times,matrices,fragments", [
    ([0.0, 1.0], np.zeros((2, 3, 4)), ["trajectory.matrices", "shape (2, 3, 4)", "(n, 4, 4)"]),
    ([0.0, 1.0], np.tile(np.eye(4), (2, 1)).reshape(8, 4), ["trajectory.matrices", "shape (8, 4)"]),
    (np.array([[0.0, 1.0]]), np.stack([np.eye(4)] * 2), ["trajectory.times_s", "shape (1, 2)", "(n,)"]),
    (["a", "b"], np.stack([np.eye(4)] * 2), ["trajectory.times_s", "dtype <U1"]),
    ([0.0, 1.0], [np.eye(4), np.eye(3)], ["trajectory.matrices", "not a rectangular array"]),
    ([0.0, 1.0], np.stack([np.eye(4)] * 2).astype(complex), ["trajectory.matrices", "complex128"]),
])
def test_trajectory_arrays_are_checked_not_reshaped(times, matrices, fragments):
    """A scanner's trajectory is a core-API array too: (n,) times and (n, 4, 4) poses, never reshaped (an (8, 4)
    stack of two poses was read as two 4×4 matrices by reshape, a (2, 3, 4) array gave a ValueError)."""
    from core.geometry.motion import Trajectory
    with pytest.raises(ConfigError) as exc:
        Trajectory(times, matrices)
    _one_line(exc, *fragments)


@pytest.mark.parametrize("frames,config,fragments", [
    ([1, 2], None, ["config = 'a NoneType'", "a SimulationConfig"]),
    ([1, 2], {"laser": {}}, ["config = 'a dict'"]),
    ([1.5, 2], "ok", ["frames = [1.5, 2]", "whole frame numbers"]),
    (None, "ok", ["frames = None"]),
    (["a"], "ok", ["frames = ['a']"]),
])
def test_a_sequence_refuses_what_is_not_a_config_or_a_frame_number(tmp_path, frames, config, fragments):
    """core.sequence.run_sequence is a core API too: None or a dict as config was an AttributeError, and
    ``int()`` truncated frame 1.5 to frame 1 silently."""
    from core.sequence import run_sequence
    cfg = SimulationConfig()
    cfg.receiver.width_px = cfg.receiver.height_px = 4
    with pytest.raises(ConfigError) as exc:
        run_sequence(frames, lambda f: SceneGeometry(V, T, [0, 0]), lambda f: np.eye(4),
                     cfg if config == "ok" else config, tmp_path / "seq")
    _one_line(exc, *fragments)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name,data,fragments", [
    ("latin1.toml", b"sweep_version = 1\n[axes]\n\"laser.pulse_shape\" = [\"gau\xdfian\"]\n", ["UTF-8", "byte 52"]),
    ("deep.json", b"[" * 100_000 + b"]" * 100_000, ["nested at most"]),
    ("deep.toml", b"x = " + b"[" * 100_000 + b"]" * 100_000, ["nested at most"]),
    ("huge.json", b'{"sweep_version": ' + b"9" * 5000 + b"}", ["valid JSON"]),
])
def test_unreadable_sweep_files_give_one_clean_line(tmp_path, name, data, fragments):
    """Sweep files are read like config files (config.files.read_config_file): before, the sweep reader's own
    copy of the old config reader gave UnicodeDecodeError and RecursionError tracebacks."""
    from core.sweep.spec import load_sweep
    (tmp_path / name).write_bytes(data)
    with pytest.raises(ConfigError) as exc:
        load_sweep(tmp_path / name)
    _one_line(exc, "sweep file", *fragments)
