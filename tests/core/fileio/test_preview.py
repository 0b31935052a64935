"""core/fileio/preview.py: every system's preview carries a title, axes with units and a colour bar or legend (issue 14):
false-colour images on angle axes, gated slices labelled with their gate and on a shared log scale, the
scanner's points, the profiler's waveform with its echoes; atomic, write-once files."""
import json

import matplotlib
import matplotlib.image
import numpy as np
import pytest
from PIL import Image

from core.config import SimulationConfig
from core.constants import SPEED_OF_LIGHT_M_S
from core.fileio import preview
from core.fileio.run_folder import write_exr
from core.run import run_simulation
from scenes import C, config_for, plate


def png_text(path) -> dict:
    with Image.open(path) as im:
        return dict(im.text)


def colour_present(px, rgb, tol=6) -> bool:
    """Some pixel of a PNG (floats 0…1) has the colour ``rgb`` (floats 0…1) within ``tol`` of 255."""
    flat = (px[:, :, :3] * 255).reshape(-1, 3)
    return bool(np.min(np.abs(flat - np.asarray(rgb[:3]) * 255).max(axis=1)) < tol)


def test_false_colour_figure_has_title_angle_axes_and_colour_bar(tmp_path):
    settings = {"receiver": {"fov_x_rad": 0.02, "fov_y_rad": 0.01}}
    fig = preview.false_colour_figure(np.linspace(100, 120, 12).reshape(3, 4), title="Range", unit="m",
                                      settings=settings)
    image_ax, bar_ax = fig.axes
    assert image_ax.get_title() == "Range"
    assert image_ax.get_xlabel() == "horizontal angle (mrad)" and image_ax.get_ylabel() == "vertical angle (mrad)"
    assert bar_ax.get_ylabel() == "m"
    assert image_ax.images[0].get_extent() == [-10.0, 10.0, -5.0, 5.0]  # ± half the field of view, mrad
    path = preview.false_colour_png(tmp_path / "r.png", np.linspace(100, 120, 12).reshape(3, 4), title="Range",
                                    unit="m", settings=settings)
    px = matplotlib.image.imread(path)
    assert px.shape[1] == 640
    viridis = matplotlib.colormaps["viridis"]
    assert colour_present(px, viridis(0.0)) and colour_present(px, viridis(1.0))  # the scale's two ends
    text = png_text(path)
    assert text["Title"] == "Range" and "x: horizontal angle (mrad)" in text["Description"]
    assert "y: m" in text["Description"]  # the colour bar's label
    with pytest.raises(FileExistsError):
        preview.false_colour_png(path, np.ones((2, 2)))
    assert [p.name for p in tmp_path.iterdir()] == ["r.png"]  # no temporary files left behind


def test_value_range():
    assert preview.value_range(np.array([3.0, 5.0]), zero_based=True) == (0.0, 5.0)
    assert preview.value_range(np.array([4.0, 4.0])) == (4.0, pytest.approx(4.0 + 4e-6))
    assert preview.value_range(np.full(3, np.nan)) == (0.0, 1.0)


def test_waveform_plot_marks_the_detected_echoes(tmp_path):
    rng_m = preview.bin_centres_range_m(1e-6, 1e-9, 200)
    assert rng_m[0] == pytest.approx(0.5 * SPEED_OF_LIGHT_M_S * (1e-6 + 0.5e-9), rel=1e-12)
    assert rng_m[1] - rng_m[0] == pytest.approx(0.5 * SPEED_OF_LIGHT_M_S * 1e-9, rel=1e-9)
    values = np.exp(-0.5 * ((np.arange(200) - 80) / 3.0) ** 2)
    fig = preview.waveform_figure(rng_m, values, title="Range profile", markers_m=[rng_m[80], rng_m[150]])
    ax = fig.axes[0]
    assert ax.get_xlabel() == "range (m)" and ax.get_ylabel() == "energy per bin (J)"
    dashed = [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]
    assert [ln.get_xdata()[0] for ln in dashed] == [rng_m[80], rng_m[150]]
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend[1] == f"detected echoes: {rng_m[80]:.2f}, {rng_m[150]:.2f} m"
    px = matplotlib.image.imread(preview.waveform_png(tmp_path / "m.png", rng_m, values, markers_m=[rng_m[80]]))
    assert px.shape[:2] == (360, 640)
    with pytest.raises(ValueError):
        preview.waveform_png(tmp_path / "x.png", rng_m[:3], values)


@pytest.mark.parametrize("peak, label, want_label, want_peak", [
    (2e-15, "energy (J per bin)", "energy (fJ per bin)", 2.0),       # the aircraft profile's 2 fJ echo
    (3.4e-13, "energy per bin (J)", "energy per bin (fJ)", 340.0),
    (1e-6, "signal per slice (J)", "signal per slice (\u00b5J)", 1.0),
    (0.5, "energy per bin (J)", "energy per bin (mJ)", 500.0),
    (2.0, "energy per bin (J)", "energy per bin (J)", 2.0),           # ≥ 1 J: as it is
    (2e-15, "counts per bin", "counts per bin", 2e-15)])              # not an energy: as it is
def test_waveform_energy_axis_reads_on_an_si_prefix(peak, label, want_label, want_peak):
    """The plot's energy axis in fJ/pJ/nJ/µJ/mJ, the largest value in [1, 1000): before, a 2 fJ profile was drawn
    in J with matplotlib's '1e-15' above ticks 0.25 … 2.00."""
    rng_m = preview.bin_centres_range_m(1e-6, 1e-9, 100)
    values = peak * np.exp(-0.5 * ((np.arange(100) - 40) / 3.0) ** 2)
    fig = preview.waveform_figure(rng_m, values, ylabel=label)
    ax = fig.axes[0]
    line = ax.get_lines()[0]
    assert ax.get_ylabel() == want_label
    assert max(line.get_ydata()) == pytest.approx(want_peak, rel=1e-12)
    fig.canvas.draw()
    assert ax.yaxis.get_offset_text().get_text() == ("" if want_label != "counts per bin" else "1e\u221215")


def _gated_run(tmp_path):
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px, cfg.receiver.height_px = 16, 8
    cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = 8e-3, 4e-3
    cfg.laser.pulse_fwhm_s = 3e-9
    g = cfg.gated
    g.n_slices, g.delay_step_s, g.gate_width_s, g.shutter_edge_s = 5, 4e-9, 10e-9, 2e-9
    g.first_delay_s = 2 * 300.0 / C - 14e-9  # slice maxima 0.002, 0.50, 1, 0.93, 0.077 of the peak
    cfg.run.threads = 1
    path, res = run_simulation(plate(300.0, 20.0), np.eye(4), cfg, tmp_path / "gated")
    return path, res, cfg


def test_gated_slices_are_labelled_and_their_faint_edges_show(tmp_path):
    """Each slice's title names its gate delay and range interval; one log colour scale over the sweep, so the
    first and last slices, holding 0.002 and 0.077 of the peak, are drawn in visible colours — before, a linear scale
    shared with the peak slice drew them black."""
    path, res, cfg = _gated_run(tmp_path)
    steps = []
    written = preview.write_run_previews(path, progress=lambda done, total: steps.append((done, total)))
    names = sorted(p.relative_to(path).as_posix() for p in written)
    assert names == ["energy.png", "intensity.png", "range.png"] + [f"slices/slice_{k:04d}.png" for k in range(1, 6)]
    assert steps == [(k, 8) for k in range(9)]  # before the first file and after each (the run's ETA comes from it)
    peak = res.slices.max()
    vmin, vmax = preview.slice_scale(res.slices.astype(np.float64))
    positive = res.slices[res.slices > 0]
    assert vmax == pytest.approx(peak, rel=1e-6, abs=0)
    assert vmin == pytest.approx(max(positive.min(), peak * 1e-4), rel=1e-6, abs=0)  # here 3.5e-4 × the peak
    inferno = matplotlib.colormaps["inferno"]
    for k in (1, 5):
        d = cfg.gated.first_delay_s + (k - 1) * cfg.gated.delay_step_s
        text = png_text(path / "slices" / f"slice_{k:04d}.png")
        r0, r1 = 0.5 * C * d, 0.5 * C * (d + cfg.gated.gate_width_s)
        assert text["Title"] == f"Gated slice {k}/5, gate delay {d * 1e9:.1f} ns: {r0:.1f} – {r1:.1f} m"
        brightest = float(res.slices[k - 1].max())
        assert 0 < brightest < 0.1 * peak  # a faint edge slice that holds data
        level = np.log10(brightest / vmin) / np.log10(vmax / vmin)
        assert level > 0.2 and level > 3 * brightest / peak  # the former linear scale: 0.002 and 0.077
        px = matplotlib.image.imread(path / "slices" / f"slice_{k:04d}.png")
        assert colour_present(px, inferno(level), tol=8)
    assert preview.write_run_previews(path) == []  # nothing twice
    assert not [p for p in path.rglob(".*")]  # no temporary files


def test_scanner_run_gets_a_points_preview(tmp_path):
    cfg = SimulationConfig(system_type="scanner")
    cfg.scanner.pattern, cfg.scanner.n_lines = "raster", 10
    cfg.scanner.scan_rate_hz, cfg.scanner.pulse_rate_hz = 100.0, 4000.0
    cfg.scanner.scan_width_rad, cfg.scanner.scan_height_rad = 0.4, 0.2
    cfg.laser.beam_divergence_rad = 1e-3
    cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 0.0, 0.25e-9, 2048
    cfg.run.threads = 1
    path, res = run_simulation(plate(40.0, 30.0), np.eye(4), cfg, tmp_path / "scan")
    assert preview.write_run_previews(path) == [path / "points.png"]
    text = png_text(path / "points.png")
    n = len(res.points["range_m"])
    assert text["Title"] == f"Scanner points: {n} points"
    assert "x: sensor x, right (m)" in text["Description"] and "y: range (m)" in text["Description"]
    fig = preview.scan_figure(res.points, np.eye(4))
    offsets = fig.axes[0].collections[0].get_offsets()
    np.testing.assert_allclose(np.sort(offsets[:, 0]), np.sort(res.points["position_world"][:, 0]))


def test_profiler_preview_is_its_waveform_with_the_echoes_not_a_1x1_image(tmp_path):
    cfg = config_for(100.0, pixels=1, fov_rad=0.01)
    cfg.system_type = "profiler"
    cfg.run.save_waveforms = True
    front = plate(100.0, 0.5, offset=(-0.5, 0.0, 0.0))
    path, res = run_simulation(front, np.eye(4), cfg, tmp_path / "prof")
    written = preview.write_run_previews(path)
    assert written == [path / "waveform.png"]  # before: range/intensity/energy PNGs of 1×1 pixel
    text = png_text(path / "waveform.png")
    assert text["Title"] == "Range profile" and "x: range (m)" in text["Description"]
    assert len(res.points["range_m"]) >= 1


def test_run_previews_leave_existing_files_and_stop_when_cancelled(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    write_exr(run / "range.exr", {"Y": np.array([[100.0, np.nan], [101.0, 102.0]], np.float32)})
    write_exr(run / "intensity.exr", {"Y": np.ones((2, 2), np.float32)})
    (run / "metadata.json").write_text(json.dumps({"units": {"range": "m", "intensity": "J per bin"}}))
    (run / "intensity.png").write_bytes(b"mine")
    assert preview.write_run_previews(run, cancel=lambda: True) == []
    assert preview.write_run_previews(run) == [run / "range.png"]
    assert (run / "intensity.png").read_bytes() == b"mine"
    assert png_text(run / "range.png")["Title"] == "Range"


def _slice_stack_with_varied_ranges():
    """Five 12×20 slices whose values span very different ranges under one shared log scale: a bright slice, a
    faint one four decades down, one of zeros and NaNs only (all grey), one below the scale's floor, and one
    reaching the sweep's maximum in a corner — so slice k's pixels, title or clipped colours left over in slice
    k + 1 would change its bytes."""
    rng = np.random.default_rng(7)
    stack = np.empty((5, 12, 20))
    stack[0] = rng.uniform(1e-3, 1.0, (12, 20))
    stack[1] = rng.uniform(1e-7, 1e-4, (12, 20))
    stack[2] = 0.0
    stack[2, ::3] = np.nan
    stack[3] = 1e-9
    stack[4] = rng.uniform(0.1, 0.5, (12, 20))
    stack[4, 0, 0] = 2.0
    return stack


@pytest.mark.parametrize("settings", [{"receiver": {"fov_x_rad": 8e-3, "fov_y_rad": 4e-3}}, None],
                         ids=["angle axes", "pixel axes"])
def test_reused_slice_figure_gives_the_bytes_of_a_new_figure(tmp_path, settings):
    """The slices share one figure, laid out and drawn in full once and replayed for the others (issue 25): every
    later slice's PNG is byte for byte the PNG of a new figure drawn for it alone (titles of different lengths,
    data over different ranges, empty slices), and the replay was used, not a full draw of the kept figure."""
    stack = _slice_stack_with_varied_ranges()
    vmin, vmax = preview.slice_scale(stack)
    titles = ["Gated slice 1/5, gate delay 1990.1 ns: 298.3 – 299.8 m", "Gated slice 2/5",
              "Gated slice 3/5, gate delay 1998.1 ns: 299.5 – 301.0 m (g, y, j)", "W" * 40, ""]
    kw = dict(unit="J", cmap="inferno", vmin=vmin, vmax=vmax, log=True, settings=settings, no_data="no signal")
    reuse = {}
    for k, title in enumerate(titles):
        preview.false_colour_png(tmp_path / f"reused_{k}.png", stack[k], title=title, reuse=reuse, **kw)
        preview.false_colour_png(tmp_path / f"new_{k}.png", stack[k], title=title, **kw)
    assert reuse["replay"].active and reuse["replay"].calls  # the later slices were replayed
    data = [(tmp_path / f"reused_{k}.png").read_bytes() for k in range(5)]
    for k in range(1, 5):
        assert data[k] == (tmp_path / f"new_{k}.png").read_bytes(), f"slice {k + 1}"
    assert len(set(data)) == 5  # the five slices are five different pictures
    assert png_text(tmp_path / "reused_2.png")["Title"] == titles[2]


def test_replay_that_kept_the_title_would_be_caught(tmp_path):
    """The comparison above can fail: a replay that does not redraw the title (the first slice's title left in
    every later PNG) gives other bytes than a new figure."""
    stack = _slice_stack_with_varied_ranges()
    vmin, vmax = preview.slice_scale(stack)
    kw = dict(unit="J", cmap="inferno", vmin=vmin, vmax=vmax, log=True)
    fig = preview.false_colour_figure(stack[0], title="slice 1", **kw)
    replay = preview.FigureReplay(fig, (fig.axes[0].images[0],))  # the title not redrawn
    replay.png(preview.png_metadata(fig))
    assert replay.active
    fig.axes[0].images[0].set_data(np.ma.masked_invalid(np.ma.masked_where(~(stack[1] > 0), stack[1])))
    fig.axes[0].set_title("slice 2", fontsize=10)
    fresh = preview.figure_png(preview.false_colour_figure(stack[1], title="slice 2", **kw))
    assert replay.png(preview.png_metadata(fig)) != fresh


def test_reuse_lays_out_a_new_figure_for_another_scale_or_shape(tmp_path):
    """A reuse dict never carries one image's colour scale, unit or shape over to the next: a call whose scale
    (given, or from its own data) or shape differs gets a new figure, so each PNG is the one drawn alone."""
    rng = np.random.default_rng(3)
    images = [rng.uniform(100.0, 110.0, (6, 8)), rng.uniform(200.0, 260.0, (6, 8)), rng.uniform(1.0, 2.0, (8, 6))]
    reuse = {}
    for k, image in enumerate(images):
        preview.false_colour_png(tmp_path / f"reused_{k}.png", image, title=f"Range {k}", unit="m", reuse=reuse)
        preview.false_colour_png(tmp_path / f"new_{k}.png", image, title=f"Range {k}", unit="m")
        assert (tmp_path / f"reused_{k}.png").read_bytes() == (tmp_path / f"new_{k}.png").read_bytes(), k
    first = reuse["figure"]
    preview.false_colour_png(tmp_path / "log.png", images[2], title="Range", unit="m", log=True, reuse=reuse)
    preview.false_colour_png(tmp_path / "log_fixed.png", images[2], title="Range", unit="m", log=True,
                             vmin=1.0, vmax=1e3, reuse=reuse)
    assert reuse["figure"] is not first
    assert (tmp_path / "log_fixed.png").read_bytes() == preview.figure_png(preview.false_colour_figure(
        images[2], title="Range", unit="m", log=True, vmin=1.0, vmax=1e3))


def test_run_previews_slices_are_the_pngs_of_new_figures(tmp_path):
    """write_run_previews on a gated run: every slice PNG after the first, drawn by replay, is the PNG a new
    figure for that slice alone gives (its title with the gate, the sweep's shared log scale)."""
    path, res, cfg = _gated_run(tmp_path)
    preview.write_run_previews(path)
    meta = preview.run_metadata(path)
    stack = res.slices.astype(np.float64)
    vmin, vmax = preview.slice_scale(stack)
    for k in range(2, 6):
        png = path / "slices" / f"slice_{k:04d}.png"
        fig = preview.false_colour_figure(stack[k - 1], title=png_text(png)["Title"], unit=meta["units"]["slices"],
                                          cmap="inferno", vmin=vmin, vmax=vmax, log=True,
                                          settings=meta["settings"], no_data="no signal")
        assert png.read_bytes() == preview.figure_png(fig), png.name


def test_a_replay_that_fails_its_check_falls_back_to_full_draws(tmp_path, monkeypatch):
    """Right after recording, the replay of the first slice is compared pixel for pixel with its full draw; a
    replay that differs (here: one that draws nothing) is never used: later slices are full draws, the same
    bytes as new figures."""
    stack = _slice_stack_with_varied_ranges()
    vmin, vmax = preview.slice_scale(stack)
    kw = dict(unit="J", cmap="inferno", vmin=vmin, vmax=vmax, log=True, no_data="no signal")
    monkeypatch.setattr(preview.FigureReplay, "_replay", lambda self: self.fig.canvas.get_renderer().clear())
    reuse = {}
    for k in range(3):
        preview.false_colour_png(tmp_path / f"reused_{k}.png", stack[k], title=f"slice {k + 1}", reuse=reuse, **kw)
    assert reuse["replay"].calls and not reuse["replay"].active
    for k in range(3):
        fresh = preview.figure_png(preview.false_colour_figure(stack[k], title=f"slice {k + 1}", **kw))
        assert (tmp_path / f"reused_{k}.png").read_bytes() == fresh
