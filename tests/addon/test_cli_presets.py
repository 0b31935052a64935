"""Real-sensor presets through the ``ladar`` command: ``export-config --preset``, config files with
``preset = "NAME"`` (validate-config, and the settings simulate builds from them), bad names."""
import importlib
import bpy
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


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_export_config_with_a_preset(lad, plate_scene, tmp_path, capsys, suffix):
    path = tmp_path / f"vlp16{suffix}"
    code, out, err = _run(lad, capsys, "export-config", "--preset", "velodyne_vlp16", "--out", str(path))
    assert code == 0, err
    text = path.read_text(encoding="utf-8")
    assert "published" not in text and "preset" not in text  # the expanded settings, no figures
    cfg = lad.config.load_config(path)
    assert cfg.system_type == "scanner" and cfg.scanner.n_channels == 16
    want = importlib.import_module(f"{lad.package.__name__}.core.presets").preset_config("velodyne_vlp16").laser
    assert cfg.laser.pulse_energy_j == want.pulse_energy_j == 1.962e-9 and cfg.laser.wavelength_m == 9.03e-7
    # the sensor's other settings (not in the preset) are the scene's
    cam = bpy.data.objects["Ladar"]
    assert cfg.run == lad.blend_config.config_from_blender(plate_scene, cam).run


def test_export_config_bad_preset_writes_nothing(lad, plate_scene, tmp_path, capsys):
    code, _, err = _run(lad, capsys, "export-config", "--preset", "velodyne_vlp99", "--out",
                        str(tmp_path / "x.toml"))
    assert code == 1
    assert "preset = 'velodyne_vlp99' is not allowed" in err and "velodyne_vlp16" in err
    assert len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []
    # the user's own preset file with a bad channel-table cell: the row and column named, nothing written
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    out.mkdir()
    mine = src / "mine.toml"
    mine.write_text('system_type = "scanner"\n[scanner]\npattern = "rotating"\nn_channels = 2\n'
                    'channel_table = [[1.0, 0.0, 0.0], [2.0, 0.0, 5.0]]\n', encoding="utf-8")
    code, _, err = _run(lad, capsys, "export-config", "--preset", str(mine), "--out", str(out / "x.toml"))
    assert code == 1
    assert "scanner.channel_table row 2 column 3 (fire_offset_s) = 5.0 is not allowed" in err, err
    assert len(err.strip().splitlines()) == 1
    assert list(out.iterdir()) == []


def test_config_file_preset_for_validate_and_simulate(lad, plate_scene, tmp_path, capsys):
    f = tmp_path / "run.toml"
    f.write_text('preset = "pli_geiger_32"\n[gate]\ngate_start_s = 6.0e-7\n', encoding="utf-8")
    code, out, err = _run(lad, capsys, "validate-config", str(f))
    assert code == 0, err
    cam = bpy.data.objects["Ladar"]
    cfg, _ = lad.run_inputs.build_config(plate_scene, cam, config_path=f)  # what simulate runs
    assert cfg.detector.detector_type == "geiger" and cfg.receiver.width_px == 32
    assert cfg.receiver.fov_x_rad == 0.0032  # the preset's field of view, not the camera's lens
    assert cfg.gate.gate_start_s == 6.0e-7 and cfg.gate.bin_width_s == 0.25e-9  # the file's key over the preset
    bad = tmp_path / "bad.toml"
    bad.write_text('preset = "pli_geiger_32"\n[gate]\nbin_width_s = -1.0\n', encoding="utf-8")
    code, _, err = _run(lad, capsys, "validate-config", str(bad))
    assert code == 1 and "gate.bin_width_s = -1.0" in err
