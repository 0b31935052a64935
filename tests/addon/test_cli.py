"""The ``ladar`` command (``blender -c ladar``): exit codes, messages, nothing written on errors; and
``scripts/ladar_run.py``, which runs it through the bpy module in a fresh process."""
import json
import subprocess
import sys
from pathlib import Path

import bpy
import pytest

from blender_scenes import add_camera, add_plate
from tests.silence import timed_run

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def plate_scene(scene):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=2.0, location=(0, 0, -100))
    return scene


def test_warm_up_compiles_what_the_sample_scenes_need(tmp_path):
    """``ladar_run.py warm-up`` (no .blend) compiles or loads every system's kernels with a line of progress per
    case; afterwards the flash and the airborne-scanner samples (ideal receiver, waveforms kept / discarded,
    moving platform, sub-ray rings) compile no kernel.  Uses the user's kernel cache, as a user's warm-up does.
    Each of the three commands is never silent for more than 2 s from its process's start to its exit (issue 27:
    a warm-up that compiles, 10-40 s a case, was silent for the whole case).

    First in this file: with a cold cache (the suite's ``build/kernel-cache/``) the warm-up compiles, once and
    early, the kernels that the later ``scripts/ladar_run.py`` runs of the session (this file's, the fault-injection,
    heartbeat and README-example tests') then load (the order of the tests changes nothing they check)."""
    run = [sys.executable, str(REPO / "scripts" / "ladar_run.py")]
    warm = timed_run([*run, "warm-up"], timeout=900, cwd=tmp_path)
    assert warm.returncode == 0, warm.stderr
    assert not warm.silences(), warm.silences()
    steps = [line for line in warm.stdout.splitlines() if line.startswith("warm-up  [")]
    assert len(steps) >= 20 and steps[-1].startswith(f"warm-up  [{len(steps)}/{len(steps)}]")
    assert "kernels ready:" in warm.stdout
    for sample in ("flash_demo", "forest_scan"):
        done = timed_run([*run, str(REPO / "sample_blends" / f"{sample}.blend"), "simulate", "--out",
                          str(tmp_path / sample), "--no-previews"], timeout=600, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        assert not done.silences(), (sample, done.silences())
        kernels = json.loads((tmp_path / sample / "metadata.json").read_text())["kernels"]
        assert kernels["compiled"] == 0 and kernels["loaded"] > 0, (sample, kernels)


def _run(lad, capsys, *argv):
    code = lad.cli.cli_handler(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_success(lad, plate_scene, tmp_path, capsys):
    code, out, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r1"), "--seed", "5", "--frame", "3")
    assert code == 0, err
    assert "run      " in out and "echoes   64 points, 64 pixels with an echo" in out
    assert "range 100.000 – 100.000 m" in out
    meta = json.loads((tmp_path / "r1" / "metadata.json").read_text())
    assert meta["seed"] == 5 and meta["frame"] == 3
    # again without --overwrite: a user error, the run is kept
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r1"))
    assert code == 1 and "--overwrite" in err
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r1"), "--overwrite")
    assert code == 0, err


def test_bad_config_value_names_the_field_and_writes_nothing(lad, plate_scene, tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text("schema_version = 1\n[laser]\npulse_energy_j = -1.0\n")
    out_dir = tmp_path / "out" / "run"
    code, _, err = _run(lad, capsys, "simulate", "--out", str(out_dir), "--config", str(config))
    assert code == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ladar: error: laser.pulse_energy_j = -1.0")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["simulate", "--out"], ["simulate", "--out", "x", "--frame", "abc"], ["bogus"],
                                  [], ["export-config"], ["validate-config"],
                                  ["simulate", "--frame", "1", "--frames", "1-3"],
                                  ["simulate", "--overwrite", "--if-exists", "new"],
                                  ["simulate", "--if-exists", "maybe"], ["simulate", "--clouds", "pixel"]])
def test_usage_errors_return_2_without_exiting(lad, plate_scene, tmp_path, capsys, argv):
    code, _, err = _run(lad, capsys, *argv)
    assert code == 2
    assert "usage:" in err
    assert list(tmp_path.iterdir()) == []


def test_help_returns_0(lad, plate_scene, capsys):
    code, out, _ = _run(lad, capsys, "simulate", "--help")
    assert code == 0 and "--overwrite" in out


def test_user_errors(lad, scene, tmp_path, capsys):
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"))
    assert code == 1 and "no ladar sensor" in err
    add_camera(scene)
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"))
    assert code == 1 and "no geometry" in err
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--sensor", "Nope")
    assert code == 1 and "Nope" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".json", ".toml"])
def test_export_config_round_trips(lad, plate_scene, tmp_path, capsys, suffix):
    cam = bpy.data.objects["Ladar"]
    cam.ladar.laser.pulse_energy_uj = 3000.0
    path = tmp_path / f"settings{suffix}"
    code, _, err = _run(lad, capsys, "export-config", "--out", str(path))
    assert code == 0, err
    loaded = lad.config.load_config(path)
    assert lad.config.config_to_dict(loaded) == \
        lad.config.config_to_dict(lad.blend_config.config_from_blender(plate_scene, cam))
    assert loaded.laser.pulse_energy_j == 0.003
    code, _, err = _run(lad, capsys, "validate-config", str(path))
    assert code == 0, err


def test_export_and_validate_config_errors(lad, plate_scene, tmp_path, capsys):
    code, _, err = _run(lad, capsys, "export-config", "--out", str(tmp_path / "settings.yaml"))
    assert code == 1 and ".json or .toml" in err
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"schema_version": 1, "receiver": {"width_px": 0}}))
    code, _, err = _run(lad, capsys, "validate-config", str(bad))
    assert code == 1 and "receiver.width_px" in err
    bad.write_text(json.dumps({"laser": {"bogus": 1}}))
    code, _, err = _run(lad, capsys, "validate-config", str(bad))
    assert code == 1 and "laser.bogus" in err
    code, _, err = _run(lad, capsys, "validate-config", str(tmp_path / "missing.toml"))
    assert code == 1 and "missing.toml" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json"]


def test_ladar_run_script_in_a_fresh_process(lad, plate_scene, tmp_path):
    """scripts/ladar_run.py installs the extension in its own isolated Blender and runs the same handler.  (A
    single run and its products, and a second run in a new temporary Blender user folder that loads every kernel
    and compiles none: tests/addon/test_fault_injection.py's
    test_signals_while_kernels_compile_or_load_leave_nothing_and_the_cache_works, on the flash demo.)"""
    blend = tmp_path / "plate.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)

    def run(*args):
        return subprocess.run([sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(blend), *args],
                              capture_output=True, text=True, timeout=300, cwd=tmp_path)

    usage = run("simulate", "--frames")
    assert usage.returncode == 2 and "--frames: expected one argument" in usage.stderr
    helped = run("simulate", "--help")
    assert helped.returncode == 0 and "--frames RANGE" in helped.stdout and "exit codes:" in helped.stdout
    seq = run("simulate", "--frames", "2-3", "--out", str(tmp_path / "seq"), "--no-previews")
    assert seq.returncode == 0, seq.stderr
    assert "frames   2 (2 … 3), 128 points, 1 BVH build(s)" in seq.stdout
    assert json.loads((tmp_path / "seq" / "metadata.json").read_text())["frames"] == [2, 3]
    assert not (tmp_path / "seq" / "frame_0002" / "range.png").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text("[gate]\nbin_width_s = 0.0\n")
    user = run("simulate", "--out", str(tmp_path / "r2"), "--config", str(bad))
    assert user.returncode == 1
    assert "gate.bin_width_s" in user.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "r2").exists()
