"""The command line never destroys a user's files (issue 15): ``--overwrite`` replaces only a previous run,
``export-config`` does not replace a file unless asked, two runs never write one folder, a reader that goes away
(``| head``) does not cost the run."""
import json

import pytest

from blender_scenes import add_camera, add_plate


@pytest.fixture
def plate_scene(scene):
    cam = add_camera(scene, width_px=8, height_px=8, fov_rad=0.004)
    cam.ladar.receiver.subsamples = 1
    add_plate(scene, size=2.0, location=(0, 0, -100))
    return scene


def _run(lad, capsys, *argv):
    code = lad.cli.cli_handler(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _names(folder):
    return sorted(p.name for p in folder.iterdir())


def test_overwrite_refuses_a_folder_that_is_not_a_run(lad, plate_scene, tmp_path, capsys):
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "thesis.txt").write_text("data")
    code, _, err = _run(lad, capsys, "simulate", "--out", str(folder), "--overwrite", "--no-import")
    assert code == 1 and str(folder) in err and "previous run" in err and len(err.strip().splitlines()) == 1
    assert _names(folder) == ["thesis.txt"] and _names(tmp_path) == ["d"]
    # the scripting API ("If Exists: Replace") refuses the same way, before any work
    with pytest.raises(lad.config.ConfigError, match="previous run"):
        lad.simulate.simulate_scene(plate_scene, out_dir=str(folder), overwrite=True, import_results=False)
    assert _names(folder) == ["thesis.txt"]
    # a real previous run is replaced (--no-previews here and below: previews are files of a run like the others,
    # and 0.2-0.5 s of CPU each; the reader test keeps them, as their progress lines come after the reader left)
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--seed", "1", "--no-import",
                        "--no-previews")
    assert code == 0, err
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--seed", "2", "--overwrite",
                        "--no-import", "--no-previews")
    assert code == 0, err
    assert json.loads((tmp_path / "r" / "metadata.json").read_text())["seed"] == 2
    assert _names(tmp_path) == ["d", "r"]


def test_out_dot_overwrite_never_empties_the_current_folder(lad, plate_scene, tmp_path, capsys, monkeypatch):
    (tmp_path / "notes.txt").write_text("data")
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(lad, capsys, "simulate", "--out", ".", "--overwrite", "--no-import")
    assert code == 1 and "not the current folder" in err
    assert _names(tmp_path) == ["notes.txt"]


def test_a_name_another_run_is_writing_is_refused_or_skipped(lad, plate_scene, tmp_path, capsys):
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--no-import", "--no-previews")
    assert code == 0, err
    with lad.staging.claim_run_dir(tmp_path / "r", if_exists="replace"):  # another run holds the name
        code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--overwrite", "--no-import",
                            "--no-previews")
        assert code == 1 and "another run is writing this one" in err
        code, out, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--if-exists", "new",
                              "--no-import", "--no-previews")
        assert code == 0 and f"run      {tmp_path / 'r_2'}" in out, err
        with lad.staging.claim_run_dir(tmp_path / "r_3"):  # claimed but not written yet
            code, out, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "r"), "--if-exists", "new",
                                  "--no-import", "--no-previews")
            assert code == 0 and f"run      {tmp_path / 'r_4'}" in out, err
    assert _names(tmp_path) == ["r", "r_2", "r_4"]


def test_export_config_does_not_replace_a_file_unless_asked(lad, plate_scene, tmp_path, capsys):
    path = tmp_path / "settings.toml"
    path.write_text("# my hand-written config\n")
    code, _, err = _run(lad, capsys, "export-config", "--out", str(path))
    assert code == 1 and str(path) in err and "--overwrite" in err
    assert path.read_text() == "# my hand-written config\n" and _names(tmp_path) == ["settings.toml"]
    code, _, err = _run(lad, capsys, "export-config", "--out", str(path), "--overwrite")
    assert code == 0, err
    assert "[laser]" in path.read_text() and _names(tmp_path) == ["settings.toml"]
    (tmp_path / "folder.json").mkdir()
    code, _, err = _run(lad, capsys, "export-config", "--out", str(tmp_path / "folder.json"), "--overwrite")
    assert code == 1 and "folder" in err


class _GoneReader:
    """stdout whose reader has gone (``ladar … | head -5`` after five lines)."""

    def __init__(self, lines_before_closing=5):
        self.left = lines_before_closing

    def write(self, text):
        if self.left <= 0:
            raise BrokenPipeError(32, "Broken pipe")
        self.left -= text.count("\n")
        return len(text)

    def flush(self):
        if self.left <= 0:
            raise BrokenPipeError(32, "Broken pipe")


def test_a_reader_that_goes_away_does_not_cost_the_run(lad, plate_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("sys.stdout", _GoneReader(2))
    code = lad.cli.cli_handler(["simulate", "--out", str(tmp_path / "r"), "--no-import"])
    assert code == 0
    assert json.loads((tmp_path / "r" / "metadata.json").read_text())["format"] == "ladar-run"
    assert _names(tmp_path) == ["r"]
