"""Every view for every system (issue 27): the waveform view and the Cycles preview of each sample scene's run.

Waveform view, opened with its defaults:

flash: the waveform of the strongest pixel; gated: the pixel's slice profile (there is no waveform cube); scanner:
the sample saves its waveforms and the view opens on a multi-echo pulse through a tree crown; profiler: the range
profile with both aircraft echoes.  Each plot is checked by its numbers (the plotted energy is that of the saved
cube or slice stack, the marked echoes those of the points) and by its pixels (the waveform's line is drawn).

Cycles preview (ladar_addon/render.py): the lit pixels of the raw render of each sample's cloud are counted (the
profiler's two echoes were two specks: 12 of 19,200 pixels at 160 × 120, 0.06 %; now 2.5 %).

Each sample is simulated once for the module (no previews, not imported)."""
from pathlib import Path

import math

import bpy
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
C = 299_792_458.0
LINE_RGB = np.array([0x1F, 0x5F, 0xA8])  # core/fileio/preview.py waveform_figure's line colour


_RUNS = {}


@pytest.fixture(scope="module")
def runs_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("sample_runs")


def _open(name):
    bpy.ops.wm.open_mainfile(filepath=str(REPO / "sample_blends" / f"{name}.blend"), load_ui=False)


def _run(lad, name, runs_dir):
    """(run folder, FrameResult) of the sample ``name``, simulated once for the module."""
    if name not in _RUNS:
        _open(name)
        _RUNS[name] = lad.simulate.simulate_scene(bpy.context.scene, out_dir=runs_dir / name, previews=False,
                                                  import_results=False)
    return _RUNS[name]


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


def test_flash_sample_view_opens_on_the_strongest_pixel(lad, addon, runs_dir):
    run, result = _run(lad, "flash_demo", runs_dir)
    path, what = lad.waveform_view.waveform_plot(run)
    energy = result.waveforms.astype(np.float64).sum(axis=2)
    y, x = np.unravel_index(np.argmax(energy), energy.shape)
    assert (what["pixel_x"], what["pixel_y"], what["view"]) == (x, y, "waveform")
    assert what["energy_j"] == pytest.approx(energy[y, x], rel=1e-6)
    mine = (result.points["pixel_x"] == x) & (result.points["pixel_y"] == y)
    assert mine.sum() >= 1 and what["echo_ranges_m"] == pytest.approx(result.points["range_m"][mine].tolist())
    assert _line_pixels(path) > 300


def test_gated_sample_view_is_the_pixels_slice_profile(lad, addon, runs_dir):
    run, result = _run(lad, "gated_board", runs_dir)
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


def test_scanner_sample_saves_waveforms_and_the_view_opens_on_a_canopy_pulse(lad, addon, runs_dir):
    run, result = _run(lad, "forest_scan", runs_dir)
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


def test_profiler_sample_view_is_the_range_profile_with_both_echoes(lad, addon, runs_dir):
    run, result = _run(lad, "aircraft_profile", runs_dir)
    path, what = lad.waveform_view.waveform_plot(run)
    assert (what["pixel_x"], what["pixel_y"], what["view"]) == (0, 0, "range profile")
    assert what["energy_j"] == pytest.approx(float(result.waveforms.astype(np.float64).sum()), rel=1e-6)
    assert len(what["echo_ranges_m"]) == len(result.points["range_m"]) >= 2
    assert _line_pixels(path) > 300
    # its echoes carry the aircraft's material (the ground truth of issue 27)
    names = result.stats["material_names"]
    assert [names[i] for i in result.points["material_id"]] == ["Aircraft paint"] * len(result.points["range_m"])


def test_operator_reports_the_view(lad, addon, runs_dir):
    run, _ = _run(lad, "gated_board", runs_dir)
    bpy.context.scene.ladar.last_run = str(run)
    assert bpy.ops.ladar.waveform_view() == {"FINISHED"}
    img = bpy.data.images[f"{run.name}.waveform"]
    assert Path(img.filepath).name.startswith("slices_x")
    assert tuple(img.size) == (640, 360)


@pytest.mark.parametrize("name, least", [("flash_demo", None), ("gated_board", None), ("forest_scan", 0.10),
                                         ("aircraft_profile", 0.015)])
def test_cycles_preview_of_each_sample_shows_its_points(lad, addon, runs_dir, monkeypatch, name, least):
    """The raw render's lit pixels (alpha > 0.5) at 160 wide: the flash and gated clouds seen from the sensor
    light at least 95 % of the fraction of receiver pixels that hold a point (``least`` None), the scanner's
    100,000 points framed light more than 10 % (a swath seen obliquely: 14.7 % measured), the profiler's 2 echoes now cover
    2 % (π r² n = 0.02 × 160 × 120: r = 7.8 px, 2.5 % measured; before, 1.2 px: 12 pixels, 0.06 %)."""
    import shutil
    render = lad.package.ladar_addon.render
    run, result = _run(lad, name, runs_dir)
    _open(name)
    bpy.context.scene.ladar.if_exists = "REPLACE"
    assert bpy.ops.ladar.import_run(directory=str(run)) == {"FINISHED"}
    obj = bpy.data.objects[run.name]
    assert len(obj.data.vertices) == len(result.points["range_m"])
    raws = []
    original = render.compose

    def keep(raw, out, **kw):
        raws.append(shutil.copy(raw, runs_dir / f"raw_{name}.png"))
        return original(raw, out, **kw)
    monkeypatch.setattr(render, "compose", keep)
    out = render.render_preview([obj], runs_dir / f"{name}_render.png", resolution=(160, 120), samples=2,
                                overwrite=True)
    assert out.is_file()
    img = bpy.data.images.load(str(raws[0]), check_existing=False)
    try:
        w, h = img.size
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    lit = float((px.reshape(-1, 4)[:, 3] > 0.5).mean())
    print(f"{name}: {lit:.4f} of {w}×{h} lit")
    if least is None:  # the sensor view: as many pixels lit as the range image has echoes
        cfg = lad.waveform_view.read_run_info(run)["settings"]["receiver"]
        pixels = len(set(zip(result.points["pixel_x"].tolist(), result.points["pixel_y"].tolist())))
        least = 0.95 * pixels / (cfg["width_px"] * cfg["height_px"])
    assert lit > least, (name, lit, least)
    if name == "aircraft_profile":
        assert render.framed_point_px(2, 160, 120) == pytest.approx(math.sqrt(0.02 * 160 * 120 / (2 * math.pi)))
        assert render.framed_point_px(100_000, 160, 120) == render.FRAMED_POINT_PX  # large clouds unchanged
