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


# ----------------------------------------------------------------------------------------------------------------
# Generated command lines (issue 31's hostile-input suite): the real entry point, scripts/ladar_run.py's main(argv),
# in this process (a few hundred) and as separate processes (a few).  Each attempt: exit 0 with its output, 1 with
# one `ladar: error:` line, or 2 with argparse's usage error; never a traceback; nothing left in the output folder
# by a refused attempt.
# ----------------------------------------------------------------------------------------------------------------
HOSTILE_TEXT = ["", " ", "-", "--", "x", "0", "-1", "1e3", "nan", "inf", "9" * 30, "-" + "9" * 30, "1,2,,3",
                "1-", "-5--1", "5-1", "1-3", "1-10:0", "1-10:-1", "1-4:2", "1-100000000", "2", "1", "a\x01b",
                "😀", "x" * 5000, "%s%n", "$(echo hi)", "'\"", "\\"]


def _fs_listing(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def _hostile_files(base):
    """Config files, sweep files and other things a user could pass by mistake (made once)."""
    base.mkdir()
    files = {}

    def put(name, data):
        p = base / name
        p.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
        files[name] = p

    put("ok.toml", "[laser]\npulse_energy_j = 0.002\n")
    put("bad_value.toml", "[laser]\npulse_energy_j = -1\n")
    put("empty_table.toml", "[gate]\nn_bins = {}\n")
    put("huge.json", '{"laser": {"pulse_energy_j": 1' + "0" * 5000 + "}}")
    put("deep.json", "[" * 20000 + "]" * 20000)
    put("not_utf8.toml", b"\xff\xfe[laser]\n")
    put("binary.toml", bytes(range(256)))
    put("wrong.suffix", "[laser]\n")
    put("sweep_ok.toml", 'sweep_version = 1\nseeds = 1\n[axes]\n"laser.pulse_energy_j" = [0.001]\n')
    put("sweep_frames.toml", 'sweep_version = 1\nframes = 99999\n[axes]\n"laser.pulse_energy_j" = [0.001]\n')
    put("sweep_big.toml", 'sweep_version = 1\nseeds = 100000\n[axes]\n"laser.pulse_energy_j" = [0.001, 0.002]\n')
    put("sweep_bad_point.toml", 'sweep_version = 1\n[axes]\n"atmosphere.visibility_m" = [2000, 10]\n')
    put("sweep_unknown_material.toml", 'sweep_version = 1\n[axes]\n"materials.Steel.reflectance" = [0.5]\n')
    put("sweep_huge_range.toml", 'sweep_version = 1\n[axes]\n"laser.pulse_energy_j" = { start = 1, stop = 1'
        + "0" * 400 + ", num = 2 }\n")
    put("sweep_long_base.toml", 'sweep_version = 1\nbase = "' + "b" * 5000 + '"\n[axes]\n"run.threads" = [1]\n')
    (base / "a_folder.toml").mkdir()
    files["a_folder.toml"] = base / "a_folder.toml"
    files["missing.toml"] = base / "missing.toml"
    return files


def _generate_argv(rng, files, outs):
    """One hostile command line (after the .blend argument)."""
    def out_path():
        r = rng.random()
        if r < 0.4:
            return str(outs / f"o{rng.randrange(10 ** 6)}")
        return rng.choice([str(outs / "a_file"), str(outs / "a_file" / "below"), str(outs / "dangling"),
                           str(outs / ("n" * 300)), "", str(outs / "x\x01y"), str(outs / "deep" / "er" / "run"),
                           str(outs / "occupied"), "/proc/ladar_cannot_write_here"])

    def a_file():
        return str(rng.choice(list(files.values())))

    cmd = rng.choice(["simulate"] * 5 + ["sweep"] * 3 + ["export-config", "validate-config"] * 2
                     + ["bogus", "", "--help-me"])
    argv = [cmd] if cmd else []
    if cmd == "simulate":
        opts = {"--out": out_path, "--frame": lambda: rng.choice(HOSTILE_TEXT),
                "--frames": lambda: rng.choice(HOSTILE_TEXT), "--seed": lambda: rng.choice(HOSTILE_TEXT),
                "--config": a_file, "--if-exists": lambda: rng.choice(["stop", "replace", "new", "REPLACE", ""]),
                "--sensor": lambda: rng.choice(["", "Nope", "Plate", "Ladar", "😀"]),
                "--clouds": lambda: rng.choice(["run", "frame", "all"]), "--overwrite": None, "--no-import": None,
                "--no-previews": None, "--bogus": None}
        # a run that is valid may happen (then it must write its folder); most carry something hostile
        chosen = rng.sample(sorted(opts), rng.randint(1, 4))
        if "--out" not in chosen and rng.random() < 0.9:
            chosen.append("--out")
        if not ({"--config", "--frame", "--frames", "--seed", "--sensor", "--bogus"} & set(chosen)) \
                and rng.random() < 0.85:
            chosen.append(rng.choice(["--config", "--frame", "--frames", "--seed", "--sensor"]))
    elif cmd == "sweep":
        # always something that is refused before a cluster starts (a valid sweep would start one: seconds)
        argv.append(rng.choice([a_file(), "", str(files["sweep_ok.toml"])]))
        opts = {"--out": out_path, "--scheduler": lambda: rng.choice(
                    ["nonsense", "tcp://", "tcp://127.0.0.1", "tcp://127.0.0.1:0", "tcp://127.0.0.1:99999",
                     "udp://127.0.0.1:8786", "tcp://[::1", "tcp://127.0.0.1:1", "ws://:", "x" * 3000]),
                "--workers": lambda: rng.choice(["0", "-1", "100000", "x", "1e2", "9" * 30]),
                "--restart": None, "--sensor": lambda: rng.choice(["Nope", "Plate", ""]), "--bogus": None}
        chosen = rng.sample(sorted(opts), rng.randint(1, 3))
        if "--out" not in chosen and rng.random() < 0.8:
            chosen.append("--out")
        if not ({"--scheduler", "--workers", "--sensor", "--bogus"} & set(chosen)):
            chosen.append(rng.choice(["--scheduler", "--workers"]))
    elif cmd == "export-config":
        opts = {"--out": lambda: rng.choice([str(outs / f"c{rng.randrange(10 ** 6)}.toml"),
                                             str(outs / f"c{rng.randrange(10 ** 6)}.json"), out_path(),
                                             str(outs / "c.yaml"), a_file()]),
                "--sensor": lambda: rng.choice(["Nope", "Plate", "", "Ladar"]), "--overwrite": None, "--bogus": None}
        chosen = rng.sample(sorted(opts), rng.randint(1, 3))
    elif cmd == "validate-config":
        argv.append(rng.choice([a_file(), a_file(), "", str(outs / "nothing.toml")]))
        opts = {"--sensor": lambda: rng.choice(["Nope", "Plate", "", "Ladar"]), "--bogus": None}
        chosen = rng.sample(sorted(opts), rng.randint(0, 1))
    else:
        opts, chosen = {}, []
    for name in chosen:
        make = opts[name]
        argv.append(name)
        if make is not None:
            argv.append(make())
    return argv


def _check_outcome(code, out, err, argv):
    text = out + err
    assert "Traceback" not in text, (argv, text[-3000:])
    assert code in (0, 1, 2), (argv, code, text[-2000:])
    if code == 1:
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("ladar: error: "), (argv, err[-2000:])
        assert len(lines[0]) < 2000, (argv, len(lines[0]))
    elif code == 2:
        assert "error:" in err or "usage:" in err, (argv, err[-2000:])


@pytest.fixture
def cli_world(lad, plate_scene, tmp_path):
    """The plate scene saved as a .blend, the hostile files, an output folder with its traps."""
    blend = tmp_path / "plate.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    files = _hostile_files(tmp_path / "files")
    outs = tmp_path / "outs"
    outs.mkdir()
    (outs / "a_file").write_text("not a folder")
    (outs / "dangling").symlink_to(tmp_path / "nowhere")
    (outs / "occupied").mkdir()
    (outs / "occupied" / "mine.txt").write_text("a user's file")
    return blend, files, outs


def test_generated_command_lines_in_process(hostile_attempts, lad, cli_world, capfd):
    """200 generated command lines through scripts/ladar_run.py's main(argv) in this process (the .blend opened,
    the command parsed and run as `blender -c ladar` would): simulate, sweep, export-config, validate-config and
    nonsense, with hostile frames, seeds, config and sweep files, output paths (a file, below a file, a dangling
    link, 300 characters, a control character, an occupied folder, an unwritable place), scheduler addresses and
    worker counts.  A refused attempt leaves the output folder as it was; an accepted one writes what it says."""
    import random
    import time

    import ladar_run

    blend, files, outs = cli_world
    rng = random.Random(3106)
    n_ok, times = 0, []
    for attempt in range(200):
        hostile_attempts()
        argv = _generate_argv(rng, files, outs)
        before = _fs_listing(outs)
        files_before = _fs_listing(files["ok.toml"].parent)
        t0 = time.perf_counter()
        code = ladar_run.main([str(blend), *argv])
        times.append((time.perf_counter() - t0, code, argv))
        out, err = capfd.readouterr()
        _check_outcome(code, out, err, argv)
        assert _fs_listing(files["ok.toml"].parent) == files_before, argv  # inputs never touched
        after = _fs_listing(outs)
        if code != 0:
            assert after == before, (attempt, argv, sorted(set(after) ^ set(before))[:10])
            continue
        n_ok += 1
        new = sorted(set(after) - set(before))
        if argv[:1] == ["simulate"]:
            out_dir = Path(argv[argv.index("--out") + 1]) if "--out" in argv else None
            if out_dir is not None and out_dir.parent == outs:
                assert (out_dir / "metadata.json").is_file() or list(out_dir.glob("*/metadata.json")), argv
                assert not [n for n in new if Path(n).name.startswith(".")], new  # no staging left
                import shutil
                shutil.rmtree(out_dir)
        elif argv[:1] == ["export-config"]:
            path = Path(argv[argv.index("--out") + 1])
            lad.config.load_config(path)  # what it wrote reads back
            if path.parent == outs:
                path.unlink()
        assert _fs_listing(outs) == before or argv[:1] == ["simulate"], argv
    times.sort(key=lambda t: -t[0])
    print(f"\n{n_ok} of 200 generated command lines accepted; {sum(t[0] for t in times):.1f} s in main(), the "
          f"slowest: " + "; ".join(f"{t:.2f} s exit {c} {' '.join(a)[:150]}" for t, c, a in times[:5]))


def test_generated_command_lines_as_subprocesses(hostile_attempts, cli_world):
    """Three generated command lines through scripts/ladar_run.py as separate processes (the interpreter's own
    exit path: exit code, one stderr line, no traceback, nothing written)."""
    import random

    blend, files, outs = cli_world
    rng = random.Random(3107)
    cases = [["sweep", str(files["sweep_ok.toml"]), "--out", str(outs / "s"), "--workers", "100000"],
             ["simulate", "--out", str(outs / "r"), "--config", str(files["empty_table.toml"])],
             _generate_argv(rng, files, outs)]
    for argv in cases:
        hostile_attempts()
        before = _fs_listing(outs)
        done = subprocess.run([sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(blend), *argv],
                              capture_output=True, text=True, timeout=300, cwd=outs.parent)
        _check_outcome(done.returncode, done.stdout, done.stderr, argv)
        if argv is not cases[-1]:
            assert done.returncode == 1, (argv, done.stderr)
        if done.returncode != 0:
            assert _fs_listing(outs) == before, argv


@pytest.mark.parametrize("frames,fragment", [("1-100000000", "frames = 100000000"),
                                             ("-100000000-1", "frames = -100000000"),
                                             ("1-1000000,1-1000000,1-1000000", "each frame once")])
def test_a_huge_frame_range_is_refused_before_it_is_expanded(lad, plate_scene, tmp_path, capsys, frames, fragment):
    """Found by test_generated_command_lines_in_process: `--frames 1-100000000` built a list of 10⁸ frame numbers
    (171 s on a loaded machine, gigabytes) before Blender's frame range refused them."""
    import time

    t0 = time.perf_counter()
    code, _, err = _run(lad, capsys, "simulate", f"--frames={frames}", "--out", str(tmp_path / "run"))
    assert code == 1
    _one_error_line(err, fragment)
    assert time.perf_counter() - t0 < 10.0  # (3 lists of 10⁶ at most: well under a second)
    assert list(tmp_path.iterdir()) == []
