"""core/fileio/preview.py: PNG encoding, false colour, waveform plots, run-folder previews (pixel values checked)."""
import json
import struct
import zlib

import numpy as np
import pytest

from core.fileio import preview
from core.fileio.run_folder import write_exr
from core.constants import SPEED_OF_LIGHT_M_S


def decode_png(data: bytes) -> np.ndarray:
    """Minimal decoder for the encoder's output (8-bit RGB/RGBA, filter 0 on every row)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, w = 8, b"", None
    while pos < len(data):
        n = struct.unpack(">I", data[pos:pos + 4])[0]
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        crc = struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])[0]
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF
        if kind == b"IHDR":
            w, h, depth, ctype = struct.unpack(">IIBB", body[:10])
            c = {2: 3, 6: 4}[ctype]
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + w * c)
    assert np.all(raw[:, 0] == 0)
    return raw[:, 1:].reshape(h, w, c)


def test_png_round_trip():
    rng = np.random.default_rng(1)
    for c in (3, 4):
        img = rng.integers(0, 256, (5, 7, c), dtype=np.uint8)
        np.testing.assert_array_equal(decode_png(preview.encode_png(img)), img)
    with pytest.raises(ValueError):
        preview.encode_png(np.zeros((4, 4), np.uint8))


def test_false_colour_values():
    stops = np.round(np.asarray(preview.COLORMAP_STOPS["viridis"]) * 255)
    img = np.array([[10.0, 30.0], [20.0, np.nan]])
    rgb = preview.false_colour_rgb(img)  # range 10 … 30: 10 → first stop, 20 → middle, 30 → last
    np.testing.assert_array_equal(rgb[0, 0], stops[0])
    np.testing.assert_array_equal(rgb[1, 0], stops[2])
    np.testing.assert_array_equal(rgb[0, 1], stops[4])
    np.testing.assert_array_equal(rgb[1, 1], np.round(np.array(preview.NO_DATA_RGB) * 255))
    # a quarter of the way between stops 0 and 1 (value 12.5 on 10…30 is 1/8 of the scale)
    q = preview.false_colour_rgb(np.array([[12.5, 10.0, 30.0]]))[0, 0]
    np.testing.assert_allclose(q, 0.5 * (stops[0] + stops[1]), atol=0.51)
    assert preview.value_range(np.array([3.0, 5.0]), zero_based=True) == (0.0, 5.0)
    assert preview.value_range(np.array([4.0, 4.0])) == (4.0, pytest.approx(4.0 + 4e-6))
    assert preview.value_range(np.full(3, np.nan)) == (0.0, 1.0)


def test_numpy_false_colour_png(tmp_path):
    img = np.array([[0.0, 1.0], [0.5, 0.25]])
    path = preview.false_colour_png(tmp_path / "a.png", img, cmap="inferno", use_matplotlib=False)
    px = decode_png(path.read_bytes())
    assert px.shape[0] == 256 and px.shape[1] > 256  # upscaled ×128, then a gap and the colour bar
    stops = np.round(np.asarray(preview.COLORMAP_STOPS["inferno"]) * 255)
    np.testing.assert_array_equal(px[0, 0], stops[0])        # pixel (0, 0) = 0 → bottom of the map
    np.testing.assert_array_equal(px[0, 255], stops[4])      # pixel (0, 1) = 1 → top
    np.testing.assert_array_equal(px[200, 50], stops[2])     # pixel (1, 0) = 0.5
    np.testing.assert_array_equal(px[0, -1], stops[4])       # colour bar: maximum at the top
    np.testing.assert_array_equal(px[-1, -1], stops[0])
    with pytest.raises(FileExistsError):
        preview.false_colour_png(tmp_path / "a.png", img, use_matplotlib=False)
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary files left behind


def test_matplotlib_false_colour_png(tmp_path):
    import matplotlib.image

    path = preview.false_colour_png(tmp_path / "r.png", np.linspace(100, 120, 12).reshape(3, 4), title="Range",
                                    unit="m", use_matplotlib=True)
    px = matplotlib.image.imread(path)
    assert px.shape[1] == 560 and px.shape[0] >= 200  # 5.6 in × 100 dpi
    # the image holds the map's two ends (the darkest viridis purple and the yellow)
    rgb = (px[:, :, :3] * 255).reshape(-1, 3)
    for stop in (preview.COLORMAP_STOPS["viridis"][0], preview.COLORMAP_STOPS["viridis"][4]):
        assert np.min(np.abs(rgb - np.array(stop) * 255).max(axis=1)) < 4


def test_waveform_plots(tmp_path):
    rng_m = preview.bin_centres_range_m(1e-6, 1e-9, 200)
    assert rng_m[0] == pytest.approx(0.5 * SPEED_OF_LIGHT_M_S * (1e-6 + 0.5e-9), rel=1e-12)
    assert rng_m[1] - rng_m[0] == pytest.approx(0.5 * SPEED_OF_LIGHT_M_S * 1e-9, rel=1e-9)
    values = np.zeros(200)
    values[100:] = 2.0  # a step: the right half of the plot is filled to the top
    values[:100] = 1.0  # the left half to half height
    px = decode_png(preview.waveform_png(tmp_path / "w.png", rng_m, values, use_matplotlib=False,
                                         size_px=(200, 101)).read_bytes())
    filled = np.all(px == (31, 95, 168), axis=2)
    heights = filled.sum(axis=0)
    assert np.all(heights[:100] == 50) and np.all(heights[100:] == 100)  # zero line is row 100 (black)
    assert np.all(px[100] == 0)
    import matplotlib.image
    mpl = matplotlib.image.imread(preview.waveform_png(tmp_path / "m.png", rng_m, values, use_matplotlib=True))
    assert mpl.shape[:2] == (360, 640)
    with pytest.raises(ValueError):
        preview.waveform_png(tmp_path / "x.png", rng_m[:3], values, use_matplotlib=False)


@pytest.mark.parametrize("use_mpl", [False, True])
def test_run_previews(tmp_path, use_mpl):
    run = tmp_path / "run"
    (run / "slices").mkdir(parents=True)
    write_exr(run / "range.exr", {"Y": np.array([[100.0, np.nan], [101.0, 102.0]], np.float32)})
    write_exr(run / "intensity.exr", {"Y": np.ones((2, 2), np.float32)})
    slices = np.array([np.full((2, 2), 4.0), np.full((2, 2), 2.0), np.zeros((2, 2))], np.float32)
    for k, s in enumerate(slices):
        write_exr(run / "slices" / f"slice_{k + 1:04d}.exr", {"Y": s})
    np.save(run / "slices.npy", slices)
    np.save(run / "waveforms.npy", np.arange(50, dtype=np.float32).reshape(1, 1, 50))
    (run / "metadata.json").write_text(json.dumps({"settings": {"gate": {"gate_start_s": 0.0,
                                                                          "bin_width_s": 1e-9}}}))
    (run / "intensity.png").write_bytes(b"mine")  # an existing file is left alone
    written = preview.write_run_previews(run, use_matplotlib=use_mpl)
    assert sorted(p.relative_to(run).as_posix() for p in written) == [
        "range.png", "slices/slice_0001.png", "slices/slice_0002.png", "slices/slice_0003.png", "waveform.png"]
    assert (run / "intensity.png").read_bytes() == b"mine"
    # slices: the NumPy renderer, one colour scale for all: 4 J → top, 2 J → middle, 0 J → bottom
    stops = np.round(np.asarray(preview.COLORMAP_STOPS["inferno"]) * 255)
    for k, stop in ((1, stops[4]), (2, stops[2]), (3, stops[0])):
        px = decode_png((run / "slices" / f"slice_{k:04d}.png").read_bytes())
        np.testing.assert_array_equal(px[0, 0], stop)
    assert preview.write_run_previews(run, use_matplotlib=use_mpl) == []  # nothing twice
    assert not [p for p in run.rglob(".*")]  # no temporary files


def test_run_previews_stop_when_cancelled(tmp_path):
    write_exr(tmp_path / "range.exr", {"Y": np.ones((2, 2), np.float32)})
    assert preview.write_run_previews(tmp_path, use_matplotlib=False, cancel=lambda: True) == []
    assert not (tmp_path / "range.png").exists()
