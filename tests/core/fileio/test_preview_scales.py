"""The previews show weak returns: intensity and energy images on a logarithmic colour scale whose colour bar says
so, pixels without an echo in the no-data grey and no echo pixel in it (however weak), and sweep plots with a
log y axis when a figure spans more than two decades.  Checked on the drawn colours and on the PNG's pixels."""
import io

import numpy as np
import pytest

from core.fileio import preview
from core.fileio.run_folder import read_exr
from core.run import run_simulation
from tests.core.scenes import config_for, plate

GREY = np.round(np.array(preview.NO_DATA_RGB) * 255).astype(int)


def _flash_like(n=64, decades=4.0, empty_fraction=0.45, seed=3):
    """An intensity image like the flash demo's: echoes log-uniform over ``decades`` decades, the rest 0."""
    rng = np.random.default_rng(seed)
    img = 1e-14 * 10.0 ** (-decades * rng.random((n, n)))
    img[rng.random((n, n)) < empty_fraction] = 0.0
    return img


def _drawn_rgba(fig):
    im = fig.axes[0].images[0]
    return im.to_rgba(im.get_array())  # (H, W, 4) floats: the colour of every pixel as drawn


def _png_pixels(fig):
    """The PNG as saved (RGB uint8) and the pixel box of the image axes in it."""
    import matplotlib.image

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    rgb = np.round(matplotlib.image.imread(io.BytesIO(buf.getvalue()), format="png")[..., :3] * 255).astype(int)
    box = fig.axes[0].get_window_extent()
    h = rgb.shape[0]
    return rgb[int(h - box.y1) + 2:int(h - box.y0) - 2, int(box.x0) + 2:int(box.x1) - 2]


def test_no_echo_pixel_is_grey_and_no_echo_pixel_is_drawn_grey():
    img = _flash_like()
    echo = img > 0
    fig = preview.false_colour_figure(img, title="Intensity", unit="J per bin", cmap="inferno", log=True,
                                      no_data="no echo")
    rgba = _drawn_rgba(fig)
    grey = np.all(np.abs(rgba[..., :3] - np.array(preview.NO_DATA_RGB)) < 1e-6, axis=-1)
    assert grey[~echo].all()
    assert grey[echo].sum() == 0                      # the fraction of echo pixels drawn as "no echo": 0
    lowest = np.all(np.abs(rgba - np.array(fig.axes[0].images[0].cmap(0.0))) < 1e-6, axis=-1)
    # log-uniform echoes over the whole scale: the lowest of the map's 256 levels holds ≈ 1/256 of them
    assert lowest[echo].mean() < 0.01
    assert fig.axes[1].get_ylabel() == "J per bin, logarithmic scale (grey: no echo)"
    # the same image on the former linear scale from 0: most echoes within a few % of the lowest colour
    lin = preview.false_colour_figure(img, title="Intensity", unit="J per bin", cmap="inferno", zero_based=True)
    lin_rgba = _drawn_rgba(lin)
    near_black = np.all(np.abs(lin_rgba[..., :3] - np.array(lin.axes[0].images[0].cmap(0.0))[:3]) < 0.05,
                        axis=-1)
    assert near_black[echo].mean() > 0.5


def test_png_pixels_grey_only_where_there_is_no_echo():
    full = _flash_like(empty_fraction=0.0)
    fig = preview.false_colour_figure(full, title="Intensity", unit="J per bin", cmap="inferno", log=True)
    area = _png_pixels(fig)
    assert np.all(area == GREY, axis=-1).mean() == 0.0  # every pixel an echo: no grey in the PNG's image
    half = full.copy()
    half[:, :32] = 0.0  # the left half without echoes
    area = _png_pixels(preview.false_colour_figure(half, title="Intensity", unit="J per bin", cmap="inferno",
                                                   log=True))
    frac = np.all(area == GREY, axis=-1).mean()
    assert frac == pytest.approx(0.5, abs=0.03)


def test_log_scale_spans_the_data_at_most_six_decades():
    img = np.array([[0.0, 1e-20, 1e-12], [np.nan, 1e-13, 1e-14]])
    assert preview.log_scale(img) == (pytest.approx(1e-18), 1e-12)
    assert preview.log_scale(np.array([[0.0, 1e-15, 1e-14]])) == (1e-15, 1e-14)
    assert preview.log_scale(np.array([[2.0, 2.0]])) == (pytest.approx(0.2), 2.0)
    assert preview.log_scale(np.zeros((2, 2))) == (0.1, 1.0)


def test_run_previews_of_a_run_with_weak_and_strong_echoes(tmp_path):
    """A run on two plates whose echoes differ 1000-fold (reflectance 0.9 and 0.0009) beside empty sky: the
    intensity and energy previews draw every echo pixel in a colour other than the grey, every pixel without an
    echo in the grey, and their colour bars say logarithmic; the range preview keeps its linear scale."""
    from core.config.settings import BRDFSettings
    from core.geometry.scene import SceneGeometry

    a = plate(100.0, 0.25, brdf=BRDFSettings(reflectance=0.9), offset=(-0.25, 0.0, 0.0))
    b = plate(100.0, 0.25, brdf=BRDFSettings(reflectance=0.0009), offset=(0.25, 0.0, 0.0))
    scene = SceneGeometry(np.vstack([a.vertices_m, b.vertices_m]), np.vstack([a.triangles, b.triangles + 4]),
                          [0, 0, 1, 1], [a.materials[0], b.materials[0]], ["bright", "dark"])
    cfg = config_for(100.0, pixels=16, fov_rad=0.01)  # the plates fill the middle 10×5 … of 16×16 pixels
    path, res = run_simulation(scene, np.eye(4), cfg, tmp_path / "run")
    preview.write_run_previews(path)
    inten = read_exr(path / "intensity.exr")["Y"]
    echo = inten > 0
    assert 0 < echo.sum() < echo.size
    ratio = inten[echo].max() / inten[echo].min()
    assert ratio > 500.0
    for product, no_data in (("intensity", "no echo"), ("energy", "no return")):
        img = read_exr(path / f"{product}.exr")["Y"]
        fig = preview.false_colour_figure(img, title=product, unit="J", cmap="inferno", log=True, no_data=no_data)
        grey = np.all(np.abs(_drawn_rgba(fig)[..., :3] - np.array(preview.NO_DATA_RGB)) < 1e-6, axis=-1)
        assert np.array_equal(grey, ~(img > 0)), product
        from PIL import Image  # matplotlib's own dependency

        desc = Image.open(path / f"{product}.png").info["Description"]
        assert f"logarithmic scale (grey: {no_data})" in desc
    assert "logarithmic" not in Image.open(path / "range.png").info["Description"]


def _series(*means):
    return [("", [1.0, 2.0, 3.0], list(m), [0.0] * len(m), [4] * len(m)) for m in means]


def test_sweep_plots_choose_a_log_axis_beyond_two_decades():
    far = preview.sweep_figure(_series([1e-9, 1e-11, 1e-13]), xlabel="sensor.range_m", ylabel="received_energy_j")
    assert far.axes[0].get_yscale() == "log" and far.axes[0].get_ylabel() == "received_energy_j (log scale)"
    near = preview.sweep_figure(_series([1.0, 5.0, 90.0]), xlabel="x", ylabel="points")   # < 2 decades
    assert near.axes[0].get_yscale() == "linear" and near.axes[0].get_ylabel() == "points"
    edge = preview.sweep_figure(_series([1.0, 50.0, 100.0]), xlabel="x", ylabel="points")  # exactly 2 decades
    assert edge.axes[0].get_yscale() == "linear"
    zeros = preview.sweep_figure(_series([4096.0, 12.0, 0.0]), xlabel="x", ylabel="points")
    assert zeros.axes[0].get_yscale() == "log"
    assert zeros.axes[0].get_ylabel() == "points (log scale; zeros not drawn)"
    signed = preview.sweep_figure(_series([-0.5, 0.001, 2.0]), xlabel="x", ylabel="range_error_mean_m")
    assert signed.axes[0].get_yscale() == "linear"  # negative values: never log
    # the far points are drawn where their values are, not on zero: the y limits reach below the smallest
    assert far.axes[0].get_ylim()[0] < 1e-13


@pytest.mark.parametrize("lo, hi, expect", [(1e-16, 3e-12, ["100 aJ", "1 fJ", "10 fJ", "100 fJ", "1 pJ"]),
                                            (1e-9, 1e-3, ["1 nJ", "100 nJ", "1 µJ", "100 µJ", "1 mJ"])])
def test_log_colour_bar_in_joules_ticks_in_si_prefixed_units(lo, hi, expect):
    """A log colour bar of an energy image labels its decades "10 fJ", "1 µJ" (core.fileio.run_folder's SI
    prefixes), not "10^-14"; a bar in counts keeps matplotlib's powers of ten."""
    img = np.geomspace(lo, hi, 64).reshape(8, 8)
    fig = preview.false_colour_figure(img, title="t", unit="J per bin", log=True)
    fig.canvas.draw()
    labels = [t.get_text() for t in fig.axes[1].yaxis.get_majorticklabels()]
    assert set(expect) <= set(labels)
    assert all(t == "" or t.endswith("J") and "^" not in t for t in labels)
    counts = preview.false_colour_figure(img * 1e15, title="t", unit="counts", log=True)
    counts.canvas.draw()
    assert any("10^{" in t.get_text() for t in counts.axes[1].yaxis.get_majorticklabels())


@pytest.mark.parametrize("lo, hi, unit", [(1.0, 2.0, "counts"),              # within one decade
                                          (1e-3, 1.0, "counts"),             # view ends on decades
                                          (3.7e-15, 2.2e-12, "J per bin"),   # SI-prefixed labels, 2.8 decades
                                          (1e-13 * 10 ** -5.999, 1e-13, "J"),  # the image scale's 6 decades
                                          (2.5e-7, 4e-1, "W")])
def test_log_colour_bar_drawn_from_the_ticks_in_view_gives_the_same_png(lo, hi, unit, monkeypatch):
    """ticks_in_view_only (a log axis is given only the tick locations near its view: fewer Tick objects made)
    changes no pixel and no byte of the PNG: the same figure drawn with matplotlib's own locators is compared."""
    img = np.geomspace(lo, hi, 96).reshape(8, 12)
    img[0, :3] = 0.0  # no-echo pixels
    fig = preview.false_colour_figure(img, title="t", unit=unit, log=True)
    bar = fig.axes[1].yaxis
    assert type(bar.get_major_locator()).__name__ == "InViewLocator"
    fast = preview.figure_png(fig)
    monkeypatch.setattr(preview, "ticks_in_view_only", lambda axis: None)
    plain = preview.false_colour_figure(img, title="t", unit=unit, log=True)
    assert type(plain.axes[1].yaxis.get_major_locator()).__name__ == "LogLocator"
    assert fast == preview.figure_png(plain)
    # fewer Tick objects were made (matplotlib's locators give ticks a decade beyond the view), not fewer drawn
    made = len(bar.majorTicks) + len(bar.minorTicks)
    plain_made = len(plain.axes[1].yaxis.majorTicks) + len(plain.axes[1].yaxis.minorTicks)
    assert made < plain_made
