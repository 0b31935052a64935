"""Files the add-on writes respect the user's umask (issue 14): the run folder (staged, previews included), an
exported config and the preview render."""
import os
import stat

import bpy
import pytest

from blender_scenes import add_camera, add_plate


@pytest.fixture(params=[0o022, 0o077])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def test_run_export_and_render_follow_the_umask(lad, scene, tmp_path, umask):
    cam = add_camera(scene, width_px=4, height_px=4, fov_rad=0.004)
    cam.ladar.gate.gate_start_ns = 2e9 * 90 / 299_792_458.0
    cam.ladar.gate.n_bins = 128
    add_plate(scene, size=4.0)
    run, _ = lad.simulate.simulate_scene(scene, out_dir=tmp_path / "run", previews=True)
    assert (run / "range.png").is_file() and (run / "points.las").is_file()
    for dirpath, dirs, files in os.walk(run):
        assert _mode(dirpath) == 0o777 & ~umask, dirpath
        for name in files:
            assert _mode(os.path.join(dirpath, name)) == 0o666 & ~umask, name
    config = lad.cli.export_config(scene, tmp_path / "settings.toml", sensor=cam)
    assert _mode(config) == 0o666 & ~umask
    assert bpy.ops.ladar.render_preview(resolution_x=16, resolution_y=12, samples=1) == {"FINISHED"}
    assert _mode(run / "previews" / "render.png") == 0o666 & ~umask


@pytest.mark.parametrize("dangling", [True, False])
def test_a_run_folder_given_as_a_symbolic_link_is_refused_and_nothing_is_made(lad, scene, tmp_path, dangling, capfd):
    """Issue 31: ``--out`` a dangling link made the link's target without a word.  A symbolic link as the run
    folder is refused (dangling or not: docs/blender.md), naming where it points; the target is not created."""
    cam = add_camera(scene, width_px=4, height_px=4, fov_rad=0.004)
    add_plate(scene, size=4.0)
    target = tmp_path / "elsewhere" / "target"
    if not dangling:
        target.mkdir(parents=True)
    link = tmp_path / "out"
    link.symlink_to(target)
    code = lad.cli.cli_handler(["simulate", "--out", str(link), "--no-import", "--sensor", cam.name])
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 1 and err[-1].startswith("ladar: error: out = ") and "symbolic link" in err[-1], err
    assert str(target) in err[-1]
    assert target.exists() is not dangling and link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == (["out"] if dangling else ["elsewhere", "out"])
    if not dangling:
        assert list(target.iterdir()) == []
