"""The independent transient renderer comparison (scripts/validation/transient.py, Mitsuba 3 + mitransient).

The exporter and the pulse integration are tested everywhere; the comparison itself runs where the optional
environment .venv-validation works (``bash scripts/setup_validation.sh``) and is skipped with the exact reason
elsewhere (CI does not set it up).
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

from validation import Skipped, transient  # noqa: E402

from core.config.settings import BRDFSettings, SimulationConfig  # noqa: E402
from core.geometry.scene import SceneGeometry  # noqa: E402
from core.physics.brdf import evaluate_brdf  # noqa: E402

C = 299_792_458.0


def _profiler_cfg():
    cfg = SimulationConfig(system_type="profiler")
    cfg.receiver.width_px = cfg.receiver.height_px = 1
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.01
    cfg.laser.beam_profile = "uniform"
    cfg.laser.pulse_fwhm_s = 1e-9
    cfg.gate.bin_width_s = 0.2e-9
    cfg.gate.n_bins = 200
    cfg.gate.gate_start_s = 2 * 95.0 / C
    return cfg


def _two_material_scene():
    v = np.array([[-1, -1, -100], [1, -1, -100], [1, 1, -100], [-1, 1, -101], [5, 5, -102], [6, 5, -102]], float)
    stv = BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0)
    return SceneGeometry(v, [[0, 1, 2], [0, 2, 3], [3, 4, 5]], [0, 0, 1],
                         [BRDFSettings(model="lambertian", reflectance=0.4), stv], ["lam", "stv"])


def _read_ply(path: Path):
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode("ascii").splitlines()
    nv = int(next(s for s in lines if s.startswith("element vertex")).split()[-1])
    nf = int(next(s for s in lines if s.startswith("element face")).split()[-1])
    verts = np.frombuffer(body[:12 * nv], "<f4").reshape(nv, 3)
    faces = np.frombuffer(body[12 * nv:], dtype=[("n", "u1"), ("v", "<i4", 3)])
    assert len(faces) == nf and (faces["n"] == 3).all()
    return verts, faces["v"]


def test_exported_scene_holds_the_geometry_pose_window_and_brdfs(tmp_path):
    scene, cfg = _two_material_scene(), _profiler_cfg()
    pose = np.eye(4)
    pose[:3, 3] = [0.5, -0.25, 2.0]
    desc = transient.export_mitsuba_scene(scene, pose, cfg, tmp_path, pixels=16, spp=8, batches=2, seed=3)
    assert json.loads((tmp_path / "scene.json").read_text()) == json.loads(json.dumps(desc))
    assert desc["world_from_sensor"] == pose.tolist()
    assert desc["fov_x_deg"] == pytest.approx(math.degrees(0.01), rel=1e-12)
    assert desc["start_opl_m"] == pytest.approx(C * cfg.gate.gate_start_s, rel=1e-15)
    assert desc["bin_opl_m"] == pytest.approx(C * 0.2e-9 / transient.FINE, rel=1e-15)
    assert desc["bins"] == 200 * transient.FINE
    lam, stv = desc["materials"]
    assert lam == {"kind": "lambert", "reflectance": 0.4, "mesh": "mesh_0.ply"}
    assert stv["kind"] == "table" and stv["step_deg"] == transient.TABLE_STEP_DEG
    theta = np.arange(len(stv["values"])) * stv["step_deg"]
    assert theta[-1] == pytest.approx(90.0)
    np.testing.assert_allclose(stv["values"], evaluate_brdf(scene.materials[1], np.cos(np.radians(theta))),
                               rtol=1e-15)
    # linear interpolation of the table: error ≤ h²/8·max|f''| — below 1e-5 of f_r up to 80° for this material
    fine = np.linspace(0, 80, 8001)
    interp = np.interp(fine, theta, stv["values"])
    exact = evaluate_brdf(scene.materials[1], np.cos(np.radians(fine)))
    assert np.max(np.abs(interp / exact - 1)) < 1e-5
    for k, (n_tri, mesh) in enumerate(((2, "mesh_0.ply"), (1, "mesh_1.ply"))):
        verts, faces = _read_ply(tmp_path / mesh)
        assert len(faces) == n_tri
        tri = np.asarray(scene.triangles)[np.asarray(scene.material_ids) == k]
        np.testing.assert_allclose(verts[faces], scene.vertices_m[tri].astype(np.float32), rtol=0, atol=0)


def test_pulse_integration_keeps_the_energy_and_the_delay():
    """A path-length histogram with one fine bin: its energy lands in the simulator's bins, centred on the bin's
    time (the Gaussian pulse integrated over each bin)."""
    cfg = _profiler_cfg()
    hist = np.zeros(cfg.gate.n_bins * transient.FINE)
    k = 1003
    hist[k] = 2.5e-12
    wf = transient.pulse_waveform(hist, cfg)
    assert wf.sum() == pytest.approx(2.5e-12, rel=1e-9)
    t = cfg.gate.gate_start_s + (np.arange(cfg.gate.n_bins) + 0.5) * cfg.gate.bin_width_s
    t_k = cfg.gate.gate_start_s + (k + 0.5) * cfg.gate.bin_width_s / transient.FINE
    assert np.sum(wf * t) / wf.sum() == pytest.approx(t_k, abs=1e-15)


def test_the_exporter_refuses_what_it_cannot_represent(tmp_path):
    cfg = _profiler_cfg()
    cfg.laser.beam_profile = "gaussian"
    with pytest.raises(ValueError, match="beam_profile = 'uniform'"):
        transient.export_mitsuba_scene(_two_material_scene(), np.eye(4), cfg, tmp_path, pixels=4, spp=1,
                                       batches=1, seed=0)
    assert not (tmp_path / "scene.json").exists()


def test_missing_environment_skips_with_its_reason(monkeypatch, tmp_path):
    monkeypatch.setattr(transient, "VENV_PYTHON", tmp_path / "no-venv" / "bin" / "python")
    monkeypatch.setattr(transient, "ROOT", tmp_path)
    reason = transient.environment_reason()
    assert reason == ("the optional Mitsuba environment no-venv/bin/python is missing (set it up with "
                      "`bash scripts/setup_validation.sh`)")
    with pytest.raises(Skipped, match="no-venv/bin/python is missing"):
        transient.run(tmp_path, quick=True)


@pytest.mark.slow
def test_profiler_agrees_with_mitsuba(tmp_path):
    """The page's quick run: every check passes (the tolerances are the sample counts' 4σ; the stratified shape
    the stated bound) and the plot is written."""
    reason = transient.environment_reason()
    if reason is not None:
        pytest.skip(reason)
    checks = transient.run(tmp_path, quick=True)
    assert len(checks) == 12
    failed = [c for c in checks if not c["passed"]]
    assert not failed, failed
    assert (tmp_path / "profiler_vs_mitsuba.png").stat().st_size > 10_000


def test_the_validation_environment_is_pinned():
    """requirements-validation.txt pins every package; Mitsuba within the range mitransient 1.3.1 supports
    (≥ 3.6.0, < 3.10.0: its version.py) and Dr.Jit at the version that Mitsuba pins."""
    pins = {}
    for line in (REPO / "requirements-validation.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"{line!r} is not pinned"
            pins[name] = tuple(int(x) for x in version.split("."))
    assert set(pins) == {"mitsuba", "drjit", "mitransient", "numpy"}
    assert (3, 6, 0) <= pins["mitsuba"] < (3, 10, 0) and pins["mitransient"] == (1, 3, 1)
    assert pins["mitsuba"] == (3, 9, 1) and pins["drjit"] == (1, 5, 0)  # Mitsuba 3.9.1 requires drjit==1.5.0
