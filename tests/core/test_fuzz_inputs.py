"""Fuzz suite of the core's input boundary (issue 15, "make it stay fixed"): every config field mutated
(non-finite, huge, wrong type, nested), config files with random bytes (non-UTF-8, truncated, bit flips),
malformed scene arrays and objects that are not configs.  Each attempt must either be accepted as valid or give
a ConfigError — one line, of bounded length, naming the field — and write nothing.  Any other exception
(a traceback at the boundary) fails the test.

Bounded for CI: a fixed number of derandomized examples per property (a few seconds each), no example
database written."""
import dataclasses
import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.config.files import config_from_dict, config_to_dict, dump_config_json, dump_config_toml, load_config
from core.config.settings import GROUPS, BRDFSettings, SimulationConfig
from core.errors import MAX_ECHO_CHARS, ConfigError
from core.geometry.scene import SceneGeometry
from core.run import run_simulation, simulate

FUZZ = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

#: every plain setting: (group, name)
FIELDS = [(g, f.name) for g in GROUPS for f in dataclasses.fields(getattr(SimulationConfig(), g))]
BRDF_FIELDS = [f.name for f in dataclasses.fields(BRDFSettings)]


def _clean(exc: ConfigError, field_hint=None):
    msg = str(exc)
    assert "\n" not in msg
    assert len(msg) <= 5 * MAX_ECHO_CHARS + 600, len(msg)
    assert " is not allowed: " in msg
    if field_hint is not None:
        assert exc.field.startswith(field_hint) or exc.field in ("config", "config file"), (exc.field, field_hint)


huge_ints = st.one_of(st.integers(), st.integers(min_value=2 ** 62, max_value=10 ** 400).map(lambda v: v),
                      st.integers(min_value=-10 ** 400, max_value=-2 ** 62))
leaves = st.one_of(st.none(), st.booleans(), huge_ints,
                   st.floats(allow_nan=True, allow_infinity=True),
                   st.text(max_size=40), st.integers(1000, 100_000).map(lambda n: "x" * n),
                   st.binary(max_size=20).map(lambda b: b.decode("latin-1")),
                   st.sampled_from(["gaussian", "noisy", "table", "raster", "inf", "nan", "1e400", "", "\x00"]))
values = st.recursive(leaves, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                      st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=12)


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(FIELDS), values), min_size=1, max_size=3))
def test_mutated_config_fields_are_accepted_or_refused_cleanly(mutations):
    data = {}
    for (group, name), value in mutations:
        data.setdefault(group, {})[name] = value
    try:
        cfg = config_from_dict(data)
    except ConfigError as exc:
        _clean(exc)
        return
    assert isinstance(cfg, SimulationConfig)  # what is accepted is a valid config that round-trips
    assert config_from_dict(config_to_dict(cfg)) == cfg


@FUZZ
@given(st.dictionaries(st.text(max_size=30), st.dictionaries(st.sampled_from(BRDF_FIELDS + ["bogus"]), values,
                                                              max_size=3), max_size=2),
       st.one_of(st.just(1), values))
def test_mutated_materials_and_schema_version(materials, version):
    data = {"materials": materials, "schema_version": version}
    try:
        cfg = config_from_dict(data)
    except ConfigError as exc:
        _clean(exc)
        return
    assert type(version) is int and version == 1
    assert tomllib_round_trip(cfg) == cfg


def tomllib_round_trip(cfg):
    import tomllib
    return config_from_dict(tomllib.loads(dump_config_toml(cfg)))


VALID = SimulationConfig()
VALID.materials = {"plate ünï 😀": BRDFSettings(reflectance=0.2)}
VALID_FILES = {".toml": dump_config_toml(VALID).encode("utf-8"), ".json": dump_config_json(VALID).encode("utf-8")}


@FUZZ
@given(st.sampled_from(sorted(VALID_FILES)), st.data())
def test_corrupt_config_files_are_refused_cleanly(tmp_path_factory, suffix, data):
    raw = bytearray(VALID_FILES[suffix])
    kind = data.draw(st.sampled_from(["truncate", "flip", "insert", "random", "deep", "bigint"]))
    if kind == "truncate":
        raw = raw[:data.draw(st.integers(0, len(raw)))]
    elif kind == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(raw) - 1))
            raw[i] ^= 1 << data.draw(st.integers(0, 7))
    elif kind == "insert":
        i = data.draw(st.integers(0, len(raw)))
        raw[i:i] = data.draw(st.binary(min_size=1, max_size=8))
    elif kind == "random":
        raw = bytearray(data.draw(st.binary(max_size=200)))
    elif kind == "deep":
        n = data.draw(st.integers(10, 50_000))
        raw = bytearray((b"x = " if suffix == ".toml" else b"") + b"[" * n + b"]" * n)
    else:
        digits = data.draw(st.integers(300, 6000))
        key = b"pulse_energy_j" if data.draw(st.booleans()) else b"n_bins"
        raw = bytearray(b"[laser]\n" + key + b" = " + b"7" * digits + b"\n" if suffix == ".toml"
                        else b'{"laser": {"' + key + b'": ' + b"7" * digits + b"}}")
    path = tmp_path_factory.mktemp("cfg") / ("c" + suffix)
    path.write_bytes(bytes(raw))
    before = sorted(p.name for p in path.parent.iterdir())
    try:
        load_config(path)
    except ConfigError as exc:
        _clean(exc)
    assert sorted(p.name for p in path.parent.iterdir()) == before  # nothing written


V = np.array([[-1, -1, -10], [1, -1, -10], [1, 1, -10], [-1, 1, -10]], float)
DTYPES = [np.float64, np.float32, np.int64, np.int32, np.uint64, np.int8, np.bool_, np.complex128, object, "U3"]


def _array(data, rows, cols, values):
    shape = data.draw(st.one_of(st.just((rows, cols) if cols else (rows,)),
                                st.tuples(st.integers(0, 6), st.integers(0, 5)),
                                st.tuples(st.integers(0, 12)),
                                st.tuples(st.integers(0, 3), st.integers(0, 3), st.integers(1, 3))))
    dtype = data.draw(st.sampled_from(DTYPES))
    flat = data.draw(st.lists(values, min_size=int(np.prod(shape)), max_size=int(np.prod(shape))))
    try:
        return np.array(flat, dtype=dtype).reshape(shape)
    except (ValueError, TypeError, OverflowError):
        return np.array(flat, dtype=object).reshape(shape)


index_values = st.one_of(st.integers(-3, 5), st.sampled_from([2 ** 31, 2 ** 32 + 1, -2 ** 40, 2 ** 63 - 1]),
                         st.floats(-2, 6), st.just(math.nan), st.none())
coord_values = st.one_of(st.floats(-20, 20), st.sampled_from([math.nan, math.inf, -math.inf, 1e300]), st.none())


@FUZZ
@given(st.data())
def test_malformed_scene_arrays_are_refused_cleanly(tmp_path_factory, data):
    which = data.draw(st.sampled_from(["vertices_m", "triangles", "material_ids"]))
    args = dict(vertices_m=V, triangles=[[0, 1, 2], [0, 2, 3]], material_ids=[0, 0])
    if which == "vertices_m":
        args[which] = _array(data, 4, 3, coord_values)
    elif which == "triangles":
        args[which] = _array(data, 2, 3, index_values)
    else:
        args[which] = _array(data, 2, 0, index_values)
    out = tmp_path_factory.mktemp("run")
    try:
        scene = SceneGeometry(**args)
        scene.check()
    except ConfigError as exc:
        _clean(exc, "scene.")
        # a run with these arrays is refused the same way and writes nothing
        with pytest.raises(ConfigError):
            run_simulation(SceneGeometry(**args), np.eye(4), SimulationConfig(), out / "r")
        assert list(out.iterdir()) == []
        return
    # accepted: exactly the shapes, ranges and values the tracer needs
    assert scene.vertices_m.dtype == np.float64 and scene.vertices_m.shape[1:] == (3,)
    assert np.isfinite(scene.vertices_m).all()
    assert scene.triangles.dtype == np.int32 and scene.triangles.shape[1:] == (3,)
    assert 0 <= scene.triangles.min() and scene.triangles.max() < len(scene.vertices_m)
    assert scene.material_ids.shape == (scene.n_triangles,) and 0 <= scene.material_ids.min()
    source = np.asarray(args[which])
    if which != "vertices_m":  # never truncated or wrapped
        np.testing.assert_array_equal(getattr(scene, which), source.astype(np.float64))


@FUZZ
@given(st.one_of(values, st.builds(object), st.just(SimulationConfig), st.just(BRDFSettings())))
def test_what_is_not_a_config_is_refused_cleanly(tmp_path_factory, config):
    out = tmp_path_factory.mktemp("run")
    scene = SceneGeometry(V, [[0, 1, 2], [0, 2, 3]], [0, 0])
    for call in (lambda: simulate(scene, np.eye(4), config),
                 lambda: run_simulation(scene, np.eye(4), config, out / "r")):
        with pytest.raises(ConfigError) as exc:
            call()
        _clean(exc.value, "config")
    assert list(out.iterdir()) == []


@FUZZ
@given(values)
def test_config_from_dict_of_anything(data):
    try:
        config_from_dict(data)
    except ConfigError as exc:
        _clean(exc)


def test_json_special_numbers_in_files(tmp_path):
    """NaN/Infinity tokens (Python's json accepts them) in a JSON file: refused by range, not a traceback."""
    for token in ("NaN", "Infinity", "-Infinity", "1e400"):
        p = tmp_path / "c.json"
        p.write_text(json.dumps({"laser": {"pulse_energy_j": 0}}).replace("0}", token + "}"))
        with pytest.raises(ConfigError) as exc:
            load_config(p)
        _clean(exc.value, "laser.pulse_energy_j")


@FUZZ
@given(st.data())
def test_malformed_poses_and_trajectories_are_refused_cleanly(data):
    """Sensor poses (4×4) and scanner trajectories ((n,) times, (n, 4, 4) poses) of random shape, dtype and
    values: accepted exactly as given or refused with one clean line, never reshaped or a traceback."""
    from core.geometry.motion import Trajectory, split_pose
    pose = _array(data, 4, 4, coord_values)
    try:
        origin, rot = split_pose(pose)
    except ConfigError as exc:
        _clean(exc, "sensor.")
    else:
        assert pose.shape == (4, 4) and pose.dtype.kind in "iuf"
        assert np.isfinite(origin).all() and np.isfinite(rot).all()
    n = data.draw(st.integers(0, 3))
    times = np.arange(n, dtype=float) if data.draw(st.booleans()) else _array(data, n, 0, coord_values)
    matrices = (np.stack([np.eye(4)] * n) if n else np.zeros((0, 4, 4))) if data.draw(st.booleans()) \
        else _array(data, n, 4, coord_values)
    try:
        traj = Trajectory(times, matrices)
    except ConfigError as exc:
        _clean(exc, "trajectory")
        return
    assert traj.matrices.shape == (len(traj.times_s), 4, 4) and np.asarray(times).shape == (len(traj.times_s),)
