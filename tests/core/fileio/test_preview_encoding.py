"""core/fileio/preview.py's cheaper routes to the same pictures (issue 25, session 32): the PNG encoder
(``encode_png``), the nearest-neighbour image by index map (``_NearestImage``), the dirty-region replay of a
gated sweep's figure (``FigureReplay._pixels``) and the text memo of the previews' renderer (``_MemoFont``).

Each is compared with *the old route*: a new figure on matplotlib's own Agg canvas (no memo) saved with
``savefig(format="png")`` (Pillow's encoder), decoded pixel for pixel, with the same text chunks and resolution."""
import io
import struct
import zlib

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.image import imsave
from PIL import Image

from core.fileio import preview

GATE_TITLE = "Gated slice 2/30, gate delay 6614.6 ns: 991.5 – 994.5 m"  # an en dash: an iTXt chunk


def chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """A PNG's chunks: (type, whole chunk bytes)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    out, pos = [], 8
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        out.append((data[pos + 4:pos + 8], data[pos:pos + 12 + n]))
        pos += 12 + n
    return out


def decoded(data: bytes):
    """(mode, pixels, text chunks, dpi) of PNG bytes."""
    with Image.open(io.BytesIO(data)) as im:
        return im.mode, np.asarray(im).copy(), dict(im.text), im.info.get("dpi")


def old_route_png(fig) -> bytes:
    """What preview.figure_png gave before session 32: savefig's PNG, on a plain Agg canvas (no text memo)."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata=preview.png_metadata(fig))
    return buf.getvalue()


def assert_same_picture(new: bytes, old: bytes, what: str = ""):
    mode_n, px_n, text_n, dpi_n = decoded(new)
    mode_o, px_o, text_o, dpi_o = decoded(old)
    assert (mode_n, px_n.shape, text_n, dpi_n) == (mode_o, px_o.shape, text_o, dpi_o), what
    bad = np.argwhere(np.any(px_n != px_o, axis=-1))
    assert len(bad) == 0, f"{what}: {len(bad)} pixels differ, first at row/column {bad[0]}"


@pytest.mark.parametrize("title", [GATE_TITLE, "Range"], ids=["iTXt", "tEXt"])
def test_encode_png_is_savefigs_png_but_for_the_compression(title):
    """Every chunk but the pixel data is byte for byte the one matplotlib's imsave (Pillow) writes, in the same
    order; the pixel data is unfiltered rows (filter type 0) deflated by zlib, decoding to the same pixels."""
    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, (37, 53, 4), dtype=np.uint8)
    rgba[:, :20] = (255, 255, 255, 255)
    meta = {"Title": title, "Description": "x: horizontal angle (mrad); y: J, logarithmic scale (grey: no signal)"}
    ours = preview.encode_png(rgba, dpi=100, metadata=meta)
    buf = io.BytesIO()
    imsave(buf, rgba, format="png", origin="upper", dpi=100, metadata=meta)
    theirs = buf.getvalue()
    ours_c, theirs_c = chunks(ours), chunks(theirs)
    assert [k for k, _ in ours_c] == [k for k, _ in theirs_c]
    assert [c for k, c in ours_c if k != b"IDAT"] == [c for k, c in theirs_c if k != b"IDAT"]
    assert (b"iTXt" in dict(ours_c)) == (title == GATE_TITLE)
    idat = b"".join(c[8:-4] for k, c in ours_c if k == b"IDAT")
    rows = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(37, 1 + 53 * 4)
    assert np.all(rows[:, 0] == 0) and np.array_equal(rows[:, 1:].reshape(rgba.shape), rgba)
    assert_same_picture(ours, theirs)
    with pytest.raises(ValueError, match="RGBA"):
        preview.encode_png(rgba[:, :, :3], dpi=100, metadata=meta)


def _stack() -> np.ndarray:
    """Five 12 × 20 slices whose masks and ranges differ from the first's: NaN, zeros, negatives, infinities,
    values below the scale (drawn in its lowest colour) and at its top."""
    rng = np.random.default_rng(7)
    stack = np.empty((5, 12, 20))
    stack[0] = rng.uniform(1e-3, 1.0, (12, 20))
    stack[1] = rng.uniform(1e-7, 1e-4, (12, 20))
    stack[1, 3:5] = -1.0
    stack[2] = 0.0
    stack[2, ::3] = np.nan
    stack[3] = 1e-9
    stack[3, 0, :4] = (np.inf, -np.inf, np.nan, 2.0)
    stack[4] = rng.uniform(0.1, 0.5, (12, 20))
    stack[4, 0, 0] = 2.0
    return stack


@pytest.mark.parametrize("log", [True, False], ids=["log scale", "linear scale"])
@pytest.mark.parametrize("settings", [{"receiver": {"fov_x_rad": 8e-3, "fov_y_rad": 4e-3}}, None],
                         ids=["angle axes", "pixel axes"])
def test_replayed_slices_are_the_old_routes_pictures(tmp_path, settings, log):
    """A sweep drawn through one reused figure (its image by index map, its later slices by dirty-region replay,
    encoded by encode_png) gives, slice by slice, the pixels and text chunks of a new figure saved by
    matplotlib's savefig, and the cheap routes were the ones taken."""
    stack = _stack()
    vmin, vmax = preview.slice_scale(stack) if log else (-1.0, 2.0)
    titles = [GATE_TITLE, "Gated slice 2/5", "Gated slice 3/5 (g, y, j)", "W" * 40, ""]
    kw = dict(unit="J", cmap="inferno" if log else "viridis", vmin=vmin, vmax=vmax, log=log, settings=settings,
              no_data="no signal")
    reuse = {}
    for k, title in enumerate(titles):
        new = preview.false_colour_png(tmp_path / f"s{k}.png", stack[k], title=title, reuse=reuse, **kw)
        old = old_route_png(preview.false_colour_figure(stack[k], title=title, **kw))
        assert_same_picture(new.read_bytes(), old, f"slice {k + 1}")
    replay = reuse["replay"]
    assert replay.active and replay._fast and replay._static is not None
    assert len({(tmp_path / f"s{k}.png").read_bytes() for k in range(5)}) == 5


def test_product_figures_and_plots_are_the_old_routes_pictures():
    """Full draws (range, intensity, energy with SI ticks, a waveform, a sweep plot) through the previews'
    canvas (text memo) and encode_png: the pixels and text chunks of matplotlib's own savefig, memo cold and
    warm."""
    rng = np.random.default_rng(2)
    image = rng.uniform(200.0, 260.0, (16, 24))
    image[2, 3] = np.nan
    energy = 10.0 ** rng.uniform(-15, -11, (16, 24))
    energy[5] = 0.0
    settings = {"receiver": {"fov_x_rad": 6e-3, "fov_y_rad": 4e-3}}
    makers = [
        lambda: preview.false_colour_figure(image, title="Range", unit="m", settings=settings, no_data="no echo"),
        lambda: preview.false_colour_figure(energy * 1e3, title="Intensity", unit="J per bin", cmap="inferno",
                                            log=True, settings=settings, no_data="no echo"),
        lambda: preview.false_colour_figure(energy, title="Received energy", unit="J", cmap="inferno", log=True,
                                            no_data="no return"),
        lambda: preview.waveform_figure(np.linspace(990, 1010, 200), np.exp(-np.linspace(-4, 4, 200) ** 2) * 1e-14,
                                        title="Range profile", markers_m=[1000.0]),
        lambda: preview.sweep_figure([("a", [1, 2, 3], [1e-15, 1e-13, 1e-11], [0, 0, 0], [3, 3, 3])],
                                     xlabel="range (m)", ylabel="energy (J)"),
    ]
    preview._TEXT_MEMO.clear()
    for rnd in ("cold", "warm"):
        for k, make in enumerate(makers):
            assert_same_picture(preview.figure_png(make()), old_route_png(make()), f"figure {k}, memo {rnd}")
    assert preview._TEXT_MEMO


def test_a_text_memo_that_answered_wrongly_would_be_caught():
    """The comparison above can fail: a memo entry with another glyph bitmap for a tick label shows."""
    make = lambda: preview.false_colour_figure(np.arange(12.0).reshape(3, 4), title="Range", unit="m")  # noqa: E731
    preview._TEXT_MEMO.clear()
    preview.figure_png(make())
    for key, entry in preview._TEXT_MEMO.items():
        if key[5] == "Range":
            for what in list(entry):
                if what[0] == "image":
                    entry[what] = np.roll(entry[what], 1, axis=1)
    with pytest.raises(AssertionError, match="pixels differ"):
        assert_same_picture(preview.figure_png(make()), old_route_png(make()))
    preview._TEXT_MEMO.clear()


def test_dirty_region_replay_checks_itself_and_falls_back(tmp_path, monkeypatch):
    """The dirty-region replay is used only if, for the recorded slice, it gives the full draw's pixels: footprints
    that miss what a call draws (here: every call said to draw nothing) fail that check, and every later
    slice is then replayed in full: still the old route's pictures."""
    stack = _stack()
    vmin, vmax = preview.slice_scale(stack)
    kw = dict(unit="J", cmap="inferno", vmin=vmin, vmax=vmax, log=True, no_data="no signal")
    monkeypatch.setattr(preview, "_footprint", lambda *args: (0, 0, 0, 0))
    reuse = {}
    for k in range(3):
        new = preview.false_colour_png(tmp_path / f"s{k}.png", stack[k], title=f"slice {k + 1}", reuse=reuse, **kw)
        assert_same_picture(new.read_bytes(), old_route_png(preview.false_colour_figure(
            stack[k], title=f"slice {k + 1}", **kw)), f"slice {k + 1}")
    assert reuse["replay"].active and reuse["replay"]._static is None


def test_nearest_image_is_not_used_where_it_does_not_apply():
    """An image that is smoothed (not nearest-neighbour) draws itself: no index map."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4, 3), dpi=100)
    FigureCanvasAgg(fig)
    im = fig.add_subplot().imshow(np.random.default_rng(0).uniform(0, 1, (8, 8)), interpolation="bilinear")
    replay = preview.FigureReplay(fig, (im,))
    replay.png({"Title": ""})
    assert replay.active and not replay._fast
