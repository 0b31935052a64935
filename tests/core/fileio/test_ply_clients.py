"""points.ply read back by the clients people open it with: every property in a type Open3D 0.20, CloudCompare,
plyfile, trimesh and Blender read (double, float, int, uchar: Open3D skips short/ushort/char/uint), and the
intensity stored on an SI-prefixed scale so that clients printing 6 decimals show no zeros.

The clients are not part of the project's install: each client test runs where the client is found and is
skipped otherwise — Open3D, plyfile and trimesh in this Python or in the Python named by ``LADAR_CLIENT_PYTHON``
(scripts/setup.sh makes ``.venv-clients`` from requirements-clients.txt, and scripts/test.sh names it there),
CloudCompare's command-line mode when ``CloudCompare`` and ``xvfb-run`` are on PATH (Debian: ``apt-get install
cloudcompare xvfb``), Blender through the ``bpy`` module of the project's venv.
"""
import importlib.util
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from core.fileio.run_folder import _PLY_TYPES, ply_intensity_scale, read_ply, write_ply
from core.run import run_simulation
from tests.core.scenes import config_for, plate

CLIENT_TIMEOUT_S = 180


@pytest.fixture(scope="module")
def noisy_run(tmp_path_factory):
    """A noisy flash run on a plate: points with float64, float32, int32, int16 and uint8 attributes."""
    cfg = config_for(100.0, pixels=8)
    cfg.detector.mode = "noisy"
    cfg.detection.k_sigma = 3.0
    path, res = run_simulation(plate(100.0, 5.0), np.eye(4), cfg, tmp_path_factory.mktemp("ply") / "run")
    return path, res


def _header(path):
    with open(path, "rb") as f:
        head = f.read(4096).split(b"end_header")[0].decode("utf-8")
    return head.splitlines()


def test_every_property_is_in_a_type_all_clients_read(noisy_run):
    path, res = noisy_run
    props = [ln.split() for ln in _header(path / "points.ply") if ln.startswith("property")]
    assert {t for _, t, _ in props} <= set(_PLY_TYPES.values()) == {"double", "float", "int", "uchar"}
    types = {n: t for _, t, n in props}
    assert types["echo_index"] == types["n_echoes"] == types["material_id"] == "int"  # int16 in the NumPy file
    assert types["false_alarm"] == "uchar" and types["snr"] == "float" and types["range_m"] == "double"
    ply = read_ply(path / "points.ply")
    for name, arr in res.points.items():
        if arr.ndim == 1 and name != "intensity":
            assert np.array_equal(ply[name], arr), name  # the same values in the wider type


def test_intensity_is_stored_on_a_prefixed_scale_stated_in_header_and_metadata(noisy_run):
    path, res = noisy_run
    meta = json.loads((path / "metadata.json").read_text())
    unit = meta["units"]["intensity"]
    scale, stored = ply_intensity_scale(res.points["intensity"], unit)
    assert meta["ply"] == {"intensity_scale": scale, "intensity_unit": stored}
    head = _header(path / "points.ply")
    assert f"comment intensity_scale {scale:g}" in head
    raw = read_ply(path / "points.ply", raw=True)["intensity"]
    positive = raw[raw > 0]
    assert positive.min() >= 1.0 and positive.min() < 1000.0  # the smallest shown as 1 … 999 in its unit
    assert all(float(f"{v:.6f}") != 0.0 for v in positive)
    np.testing.assert_allclose(read_ply(path / "points.ply")["intensity"], res.points["intensity"], rtol=1e-6)


@pytest.mark.parametrize("values,unit,scale,stored", [
    ([4.2e-17, 8e-15], "J per bin", 1e-18, "aJ per bin"),   # smallest 42 aJ
    ([1e-18, 1.0], "J per bin", 1e-18, "aJ per bin"),       # exactly 1 aJ
    ([9.99e-13], "J", 1e-15, "fJ"),                         # 999 fJ
    ([2e-6, 1e-3], "J", 1e-6, "uJ"),                         # micro in ASCII: the PLY header is ASCII
    ([0.5, 300.0], "counts", 1e-3, "0.001 counts"),
    ([3.0, 4000.0], "counts", 1.0, "counts"),                 # already ≥ 1: unscaled
    ([0.0, -1.0], "J per bin", 1.0, "J per bin"),           # nothing positive: unscaled
])
def test_intensity_scale_rule(values, unit, scale, stored):
    assert ply_intensity_scale(np.array(values), unit) == (scale, stored)


def test_ply_without_points_is_still_valid(tmp_path):
    pts = {"position_world": np.zeros((0, 3)), "intensity": np.zeros(0, np.float32),
           "echo_index": np.zeros(0, np.int16)}
    assert write_ply(tmp_path / "e.ply", pts, "J per bin") == {"intensity_scale": 1.0, "intensity_unit": "J per bin"}
    assert len(read_ply(tmp_path / "e.ply")["x"]) == 0


def _client_python(module: str) -> str:
    """A Python that imports ``module``: this one, else $LADAR_CLIENT_PYTHON; skip the test otherwise."""
    if importlib.util.find_spec(module) is not None:
        return sys.executable
    other = os.environ.get("LADAR_CLIENT_PYTHON")
    if other and subprocess.run([other, "-c", f"import {module}"], capture_output=True,
                                timeout=CLIENT_TIMEOUT_S).returncode == 0:
        return other
    pytest.skip(f"{module} is not installed here (nor in $LADAR_CLIENT_PYTHON)")


_READERS = {
    "open3d": ("import open3d as o3d\n"
               "pc = o3d.t.io.read_point_cloud(path)\n"
               "out = {k: pc.point[k].numpy().reshape(len(pc.point[k]), -1)[:, 0].tolist() for k in pc.point}\n"
               "p = pc.point['positions'].numpy()\n"
               "out.update(x=p[:, 0].tolist(), y=p[:, 1].tolist(), z=p[:, 2].tolist()); out.pop('positions')\n"),
    "plyfile": ("import plyfile\n"
                "v = plyfile.PlyData.read(path)['vertex']\n"
                "out = {p.name: v[p.name].tolist() for p in v.properties}\n"),
    "trimesh": ("import trimesh\n"
                "m = trimesh.load(path)\n"
                "d = m.metadata['_ply_raw']['vertex']['data']\n"
                "out = {k: d[k].tolist() for k in d.dtype.names}\n"),
}


@pytest.mark.parametrize("client", sorted(_READERS))
def test_python_clients_read_every_property(noisy_run, client):
    path, _ = noisy_run
    python = _client_python(client)
    code = f"import json, sys\npath = sys.argv[1]\n{_READERS[client]}print(json.dumps(out))\n"
    run = subprocess.run([python, "-c", code, str(path / "points.ply")], capture_output=True, text=True,
                         timeout=CLIENT_TIMEOUT_S)
    assert run.returncode == 0, run.stderr[-2000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    ours = read_ply(path / "points.ply", raw=True)
    assert set(got) == set(ours), f"{client} lost {set(ours) - set(got)}"
    for name, arr in ours.items():
        np.testing.assert_array_equal(np.asarray(got[name], dtype=arr.dtype), arr, err_msg=f"{client}: {name}")


def test_blender_imports_every_property_as_an_attribute(noisy_run):
    bpy = pytest.importorskip("bpy")
    path, _ = noisy_run
    # an empty file; not read_factory_settings, which also resets the preferences and so disables the add-on that
    # the tests/addon files of the same pytest worker installed (their later tests failed: 'Object' object has
    # no attribute 'ladar', seen when this file ran between two of them)
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.ops.wm.ply_import(filepath=str(path / "points.ply")) == {"FINISHED"}
    mesh = bpy.context.scene.objects[0].data
    ours = read_ply(path / "points.ply", raw=True)
    assert len(mesh.vertices) == len(ours["x"])
    for name, arr in ours.items():
        if name in "xyz":
            continue
        att = mesh.attributes[name]  # Blender keeps every property as a float attribute
        vals = np.empty(len(arr), np.float32)
        att.data.foreach_get("value", vals)
        np.testing.assert_allclose(vals, arr.astype(np.float32), rtol=1e-7, err_msg=name)


@pytest.mark.skipif(shutil.which("CloudCompare") is None or shutil.which("xvfb-run") is None,
                    reason="CloudCompare (command-line mode) or xvfb-run is not installed here")
def test_cloudcompare_command_line_reads_the_points_and_prints_nonzero_intensities(noisy_run, tmp_path):
    """CloudCompare 2.11's command-line mode loads x, y, z and ``intensity`` of a PLY (further properties it
    loads only when named ``scalar_*``, or in the GUI's PLY dialog); its ASCII export prints 12 decimals."""
    path, _ = noisy_run
    shutil.copy(path / "points.ply", tmp_path / "p.ply")
    run = subprocess.run(["xvfb-run", "-a", "CloudCompare", "-SILENT", "-O", "p.ply", "-C_EXPORT_FMT", "ASC",
                          "-ADD_HEADER", "-SAVE_CLOUDS"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=CLIENT_TIMEOUT_S)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    asc = sorted(tmp_path.glob("p_*.asc"))
    assert len(asc) == 1, run.stdout[-2000:]
    lines = asc[0].read_text().splitlines()
    assert lines[0].lstrip("/").split() == ["X", "Y", "Z", "intensity"]
    table = np.array([ln.split() for ln in lines[1:]], dtype=np.float64)
    ours = read_ply(path / "points.ply", raw=True)
    assert len(table) == len(ours["x"])
    np.testing.assert_allclose(table[:, 2], ours["z"], atol=1e-5)
    np.testing.assert_allclose(table[:, 3], ours["intensity"], rtol=1e-6)
    assert np.all(table[:, 3][ours["intensity"] > 0] >= 1.0)  # as printed: no 0.000000
