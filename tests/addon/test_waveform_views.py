"""Every view for every system (issue 27): the waveform view of each sample scene's run, opened with its defaults.

flash: the waveform of the strongest pixel; gated: the pixel's slice profile (there is no waveform cube); scanner:
the sample saves its waveforms and the view opens on a multi-echo pulse through a tree crown; profiler: the range
profile with both aircraft echoes.  Each plot is checked by its numbers (the plotted energy is that of the saved
cube or slice stack, the marked echoes those of the points) and by its pixels (the waveform's line is drawn)."""
from pathlib import Path

import bpy
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
C = 299_792_458.0
LINE_RGB = np.array([0x1F, 0x5F, 0xA8])  # core/fileio/preview.py waveform_figure's line colour


def _run(lad, name, tmp_path):
    bpy.ops.wm.open_mainfile(filepath=str(REPO / "sample_blends" / f"{name}.blend"), load_ui=False)
    run, result = lad.simulate.simulate_scene(bpy.context.scene, out_dir=tmp_path / name, previews=False,
                                              import_results=False)
    return run, result


def _line_pixels(path):
    """Pixels of the PNG drawn in the waveform's line colour (±40 per channel)."""
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = img.size
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    rgb = np.round(px.reshape(-1, 4)[:, :3] * 255.0)
    return int(np.sum(np.all(np.abs(rgb - LINE_RGB) <= 40, axis=1)))


def test_flash_sample_view_opens_on_the_strongest_pixel(lad, addon, tmp_path):
    run, result = _run(lad, "flash_demo", tmp_path)
    path, what = lad.waveform_view.waveform_plot(run)
    energy = result.waveforms.astype(np.float64).sum(axis=2)
    y, x = np.unravel_index(np.argmax(energy), energy.shape)
    assert (what["pixel_x"], what["pixel_y"], what["view"]) == (x, y, "waveform")
    assert what["energy_j"] == pytest.approx(energy[y, x], rel=1e-6)
    mine = (result.points["pixel_x"] == x) & (result.points["pixel_y"] == y)
    assert mine.sum() >= 1 and what["echo_ranges_m"] == pytest.approx(result.points["range_m"][mine].tolist())
    assert _line_pixels(path) > 300


def test_gated_sample_view_is_the_pixels_slice_profile(lad, addon, tmp_path):
    run, result = _run(lad, "gated_board", tmp_path)
    assert not (run / "waveforms.npy").exists()  # gated viewing has slices, not waveforms
    path, what = lad.waveform_view.waveform_plot(run)
    assert path.name.startswith("slices_") and what["view"] == "slice profile"
    slices = np.load(run / "slices.npy").astype(np.float64)
    x, y = what["pixel_x"], what["pixel_y"]
    energy = slices.sum(axis=0)
    assert energy[y, x] == energy.max() > 0  # the strongest pixel
    assert what["energy_j"] == pytest.approx(energy[y, x], rel=1e-9)
    assert what["n_slices"] == slices.shape[0] == 30
    # the x axis: the gates' centres c/2 (delay + width/2), 0.5 m apart (a 3.34 ns step) from 992 m + 3 m
    g = lad.waveform_view.read_run_info(run)["settings"]["gated"]
    first = 0.5 * C * (g["first_delay_s"] + 0.5 * g["gate_width_s"])
    assert what["range_m"] == pytest.approx([first, first + 29 * 0.5 * C * g["delay_step_s"]], rel=1e-12)
    assert what["range_m"][1] - what["range_m"][0] == pytest.approx(29 * 0.5, rel=1e-6)
    # the pixel's echo is marked, inside the profile's range span, at the board (≈ 1 km)
    mine = (result.points["pixel_x"] == x) & (result.points["pixel_y"] == y)
    assert mine.sum() == 1 and what["echo_ranges_m"] == pytest.approx(result.points["range_m"][mine].tolist())
    assert 996.0 < what["echo_ranges_m"][0] < 1004.5
    assert _line_pixels(path) > 300


def test_scanner_sample_saves_waveforms_and_the_view_opens_on_a_canopy_pulse(lad, addon, tmp_path):
    run, result = _run(lad, "forest_scan", tmp_path)
    cube = np.load(run / "waveforms.npy", mmap_mode="r")
    assert cube.shape == (100_000, 668)  # 50 m of 0.5 ns bins
    path, what = lad.waveform_view.waveform_plot(run)
    p = what["pulse"]
    pts = result.points
    echoes_per_pulse = np.bincount(pts["pulse_index"], minlength=cube.shape[0])
    assert echoes_per_pulse[p] == echoes_per_pulse.max() >= 4  # the multi-echo pulse
    mine = pts["pulse_index"] == p
    assert what["echo_ranges_m"] == pytest.approx(pts["range_m"][mine].tolist())
    names = result.stats["material_names"]
    assert "Leaves" in {names[i] for i in pts["material_id"][mine] if i >= 0}  # through a crown
    assert what["energy_j"] == pytest.approx(float(np.asarray(cube[p], np.float64).sum()), rel=1e-6)
    assert _line_pixels(path) > 300
    # a named pulse is still shown as asked
    assert lad.waveform_view.waveform_plot(run, pulse=7)[1]["pulse"] == 7


def test_profiler_sample_view_is_the_range_profile_with_both_echoes(lad, addon, tmp_path):
    run, result = _run(lad, "aircraft_profile", tmp_path)
    path, what = lad.waveform_view.waveform_plot(run)
    assert (what["pixel_x"], what["pixel_y"], what["view"]) == (0, 0, "range profile")
    assert what["energy_j"] == pytest.approx(float(result.waveforms.astype(np.float64).sum()), rel=1e-6)
    assert len(what["echo_ranges_m"]) == len(result.points["range_m"]) >= 2
    assert _line_pixels(path) > 300
    # its echoes carry the aircraft's material (the ground truth of issue 27)
    names = result.stats["material_names"]
    assert [names[i] for i in result.points["material_id"]] == ["Aircraft paint"] * len(result.points["range_m"])


def test_operator_reports_the_view(lad, addon, tmp_path):
    run, _ = _run(lad, "gated_board", tmp_path)
    bpy.context.scene.ladar.last_run = str(run)
    assert bpy.ops.ladar.waveform_view() == {"FINISHED"}
    img = bpy.data.images[f"{run.name}.waveform"]
    assert Path(img.filepath).name.startswith("slices_x")
    assert tuple(img.size) == (640, 360)
