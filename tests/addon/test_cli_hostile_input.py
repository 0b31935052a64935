"""Hostile input at the command line (issue 15): ``validate-config`` refuses what ``simulate`` would refuse
(unknown material names, ``schema_version = true``, a scalar BRDF table, a run that cannot fit), ``export-config``
writes TOML the tool reads back whatever the material names, frames Blender would clamp are refused, and
corrupt .blend files give one clean error line (scripts/ladar_run.py).  Nothing is written on an error."""
import json
import random
import subprocess
import sys
from pathlib import Path

import bpy
import pytest

from blender_scenes import add_camera, add_plate, brdf_material

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def plate_scene(scene):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=2.0, location=(0, 0, -100), materials=[brdf_material("Paint 😀 \"red\"", reflectance=0.4)])
    return scene


def _run(lad, capsys, *argv):
    code = lad.cli.cli_handler(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _one_error_line(err, *fragments):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ladar: error: "), err
    for f in fragments:
        assert f in lines[0], lines[0]


def test_validate_config_refuses_an_unknown_material_as_simulate_does(lad, plate_scene, tmp_path, capsys):
    cfg = tmp_path / "m.toml"
    cfg.write_text('[materials."Paint 😀 \\"red\\""]\nreflectance = 0.1\n', encoding="utf-8")
    code, _, err = _run(lad, capsys, "validate-config", str(cfg))
    assert code == 0, err  # a material of the scene: accepted
    cfg.write_text('[materials.Pianit]\nreflectance = 0.1\n', encoding="utf-8")
    code, _, err = _run(lad, capsys, "validate-config", str(cfg))
    assert code == 1
    _one_error_line(err, "materials = 'Pianit'", "the name of a material in the scene", "Paint 😀")
    code, _, err2 = _run(lad, capsys, "simulate", "--config", str(cfg), "--out", str(tmp_path / "run"))
    assert code == 1 and err2 == err  # the same refusal, word for word
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.toml"]


@pytest.mark.parametrize("text,fragments", [
    ("schema_version = true\n", ["schema_version = True"]),
    ("schema_version = 1.0\n", ["schema_version = 1.0"]),
    ('[materials."Paint 😀 \\"red\\""]\ntable_angle_deg = 0\n', ["table_angle_deg = 0", "a list of numbers"]),
    ("[laser]\npulse_energy_j = " + "9" * 400 + "\n", ["laser.pulse_energy_j = 999", "(0, 100] J"]),
    ('system_type = "gated"\n[gated]\nn_slices = 3000\n[receiver]\nwidth_px = 256\nheight_px = 256\n',
     ["gated.n_slices = 3000", "slice_stack", "GiB"]),
])
def test_validate_config_refuses_what_simulate_refuses(lad, plate_scene, tmp_path, capsys, text, fragments):
    cfg = tmp_path / "c.toml"
    cfg.write_text(text, encoding="utf-8")
    code, _, err = _run(lad, capsys, "validate-config", str(cfg))
    assert code == 1
    _one_error_line(err, *fragments)


def test_export_config_with_non_ascii_material_names_reads_back(lad, plate_scene, tmp_path, capsys):
    brdf_material("Ünïcødé \\ tab\tbell\x07 🦀", reflectance=0.7)
    path = tmp_path / "settings.toml"
    code, _, err = _run(lad, capsys, "export-config", "--out", str(path))
    assert code == 0, err
    loaded = lad.config.load_config(path)
    assert {"Paint 😀 \"red\"", "Ünïcødé \\ tab\tbell\x07 🦀"} <= set(loaded.materials)
    assert loaded.materials["Ünïcødé \\ tab\tbell\x07 🦀"].reflectance == pytest.approx(0.7)
    code, _, err = _run(lad, capsys, "validate-config", str(path))
    assert code == 0, err


@pytest.mark.parametrize("argv,field", [(["--frame", "99999999"], "frame = 99999999"),
                                        (["--frame", "-2000000"], "frame = -2000000"),
                                        (["--frames", "1,99999999"], "frames = 99999999")])
def test_frames_blender_would_clamp_are_refused(lad, plate_scene, tmp_path, capsys, argv, field):
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "run"), *argv)
    assert code == 1
    _one_error_line(err, field, "Blender's frame range")
    assert list(tmp_path.iterdir()) == []


CORRUPT = {
    "truncated": lambda b, r: b[:len(b) // 3],
    "header only": lambda b, r: b[:12],
    "empty": lambda b, r: b"",
    "random bytes": lambda b, r: bytes(r.getrandbits(8) for _ in range(4096)),
    "text": lambda b, r: b"this is not a blend file\n" * 10,
    "bit flips": lambda b, r: bytes(x ^ (1 << r.randrange(8)) if r.random() < 1e-3 else x for x in b),
    "gzip magic": lambda b, r: b"\x1f\x8b\x08" + b[3:200],
    "zstd magic": lambda b, r: b"\x28\xb5\x2f\xfd" + b[4:200],
}


def test_corrupt_blend_files_give_one_clean_line(lad, plate_scene, tmp_path):
    """Every corrupt variant of a valid .blend is opened through ladar_run.open_blend in one fresh process:
    a BlendFileError (one line) or a successful open, never another exception or a crash; then the script
    itself on two of them: exit 1, one stderr line, no traceback, nothing written."""
    blend = tmp_path / "plate.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    raw, rng = blend.read_bytes(), random.Random(15)
    files = []
    for i, (name, make) in enumerate(CORRUPT.items()):
        path = tmp_path / f"corrupt_{i}.blend"
        path.write_bytes(make(raw, rng))
        files.append(path)
    driver = f"""
import sys, json
sys.path.insert(0, {str(REPO / 'scripts')!r})
import blender_env, ladar_run
from pathlib import Path
blender_env.isolate_user_resources()
import bpy
for p in {[str(f) for f in files]!r}:
    try:
        ladar_run.open_blend(bpy, Path(p))
        print(json.dumps([p, "opened"]), file=sys.stderr)
    except ladar_run.BlendFileError as exc:
        print(json.dumps([p, "clean", str(exc)]), file=sys.stderr)
"""
    done = subprocess.run([sys.executable, "-c", driver], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    outcomes = [json.loads(line) for line in done.stderr.splitlines() if line.startswith("[")]
    assert [o[0] for o in outcomes] == [str(f) for f in files]
    for path, kind, *msg in outcomes:
        if kind == "clean":
            assert "\n" not in msg[0] and "is not a readable .blend file" in msg[0] and len(msg[0]) < 400
    assert sum(o[1] == "clean" for o in outcomes) >= len(CORRUPT) - 1  # the bit flips may still open
    for path in files[:2] + files[3:4]:
        out = subprocess.run([sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(path), "simulate",
                              "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=300,
                             cwd=tmp_path)
        assert out.returncode == 1
        _one_error_line(out.stderr, str(path), "is not a readable .blend file")
        assert "Traceback" not in out.stdout + out.stderr
    assert not (tmp_path / "run").exists()
