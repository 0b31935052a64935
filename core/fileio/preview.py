"""Preview images of a run: false-colour PNGs of the range/intensity/energy images and gated slices, and
waveform plots.  Never imports bpy.

Matplotlib (Agg, object API: thread-safe enough for a worker thread) draws the PNGs with a colour bar, title and
units when it is installed; otherwise a small NumPy renderer writes the same false-colour image (nearest-neighbour
upscaled, colour bar strip on the right, no text) through the stdlib PNG encoder below, so the extension works
in a Blender that lacks matplotlib.

Every PNG is written atomically (a hidden temporary file in the same folder, then ``os.replace``) and an existing
file is never replaced unless ``overwrite`` is asked.
"""
from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..constants import SPEED_OF_LIGHT_M_S

#: Colour maps as a few linear-RGB-ish stops (sRGB values of matplotlib's viridis and inferno at 0, ¼, ½, ¾, 1).
COLORMAP_STOPS = {
    "viridis": ((0.267, 0.005, 0.329), (0.229, 0.322, 0.546), (0.128, 0.567, 0.551), (0.369, 0.789, 0.383),
                (0.993, 0.906, 0.144)),
    "inferno": ((0.001, 0.000, 0.014), (0.341, 0.062, 0.429), (0.735, 0.216, 0.330), (0.978, 0.557, 0.035),
                (0.988, 0.998, 0.645)),
}
#: What each image product shows: (title, colour map, scale starts at zero).  Units come from the run's
#: ``metadata.json`` (``units``, written from ``FrameResult.units``: core.systems.flash.product_units).
PRODUCTS = {"range": ("Range", "viridis", False), "intensity": ("Intensity", "inferno", True),
            "energy": ("Received energy", "inferno", True), "slices": ("Gated slice", "inferno", True)}
NO_DATA_RGB = (0.35, 0.35, 0.35)  # pixels without a value (NaN range): grey
MIN_PREVIEW_PX = 256              # the NumPy renderer upscales small images to at least this size


def have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:  # pragma: no cover - matplotlib is in requirements.txt
        return False
    return True


# ----------------------------------------------------------------------------------------------------------
# PNG encoding and atomic writes
# ----------------------------------------------------------------------------------------------------------
def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) or (H, W, 4) uint8 image (8-bit RGB/RGBA, no filtering, zlib level 6)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] not in (3, 4):
        raise ValueError(f"expected an (H, W, 3|4) uint8 image, got shape {rgb.shape}")
    h, w, c = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, w * c)], axis=1).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 2 if c == 3 else 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


def write_bytes_atomically(path, data: bytes, *, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` through a hidden temporary file in the same folder (never half a file).

    Raises FileExistsError if ``path`` exists and ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (previews never replace a file unless asked)")
    path.parent.mkdir(parents=True, exist_ok=True)
    from .run_folder import new_temp_file

    fd, tmp = new_temp_file(path.parent, f".{path.name}.", ".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


# ----------------------------------------------------------------------------------------------------------
# False colour
# ----------------------------------------------------------------------------------------------------------
def colormap_rgb(values01: np.ndarray, name: str = "viridis") -> np.ndarray:
    """RGB floats (..., 3) of ``values01`` (clipped to 0…1) on the piecewise-linear colour map ``name``."""
    stops = np.asarray(COLORMAP_STOPS[name])
    pos = np.linspace(0.0, 1.0, len(stops))
    v = np.clip(np.asarray(values01, dtype=np.float64), 0.0, 1.0)
    return np.stack([np.interp(v, pos, stops[:, k]) for k in range(3)], axis=-1)


def value_range(image: np.ndarray, vmin=None, vmax=None, zero_based: bool = False) -> tuple[float, float]:
    """Display range: ``vmin``/``vmax`` where given, else the finite data's minimum (0 when ``zero_based``, for
    energies) and maximum.  A flat image gets a range of width 1e-6 × its value (1 for zero)."""
    finite = np.asarray(image, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    lo = vmin if vmin is not None else (0.0 if zero_based else float(finite.min()) if finite.size else 0.0)
    hi = vmax if vmax is not None else (float(finite.max()) if finite.size else 1.0)
    if not hi > lo:
        hi = lo + (abs(lo) * 1e-6 or 1.0)
    return lo, hi


def false_colour_rgb(image: np.ndarray, cmap: str = "viridis", vmin=None, vmax=None) -> np.ndarray:
    """(H, W, 3) uint8 false colour of a 2-D image; non-finite pixels are grey (:data:`NO_DATA_RGB`)."""
    image = np.asarray(image, dtype=np.float64)
    lo, hi = value_range(image, vmin, vmax)
    rgb = colormap_rgb((np.nan_to_num(image, nan=lo) - lo) / (hi - lo), cmap)
    rgb[~np.isfinite(image)] = NO_DATA_RGB
    return np.round(rgb * 255.0).astype(np.uint8)


def _numpy_figure(image, cmap, vmin, vmax) -> np.ndarray:
    """The false-colour image upscaled (nearest) to ≥ MIN_PREVIEW_PX on its long side, plus a colour bar."""
    rgb = false_colour_rgb(image, cmap, vmin, vmax)
    h, w = rgb.shape[:2]
    k = max(1, int(np.ceil(MIN_PREVIEW_PX / max(h, w))))
    big = np.repeat(np.repeat(rgb, k, axis=0), k, axis=1)
    bh = big.shape[0]
    bar = np.round(colormap_rgb(np.linspace(1.0, 0.0, bh), cmap) * 255).astype(np.uint8)  # top = maximum
    bar = np.repeat(bar[:, None, :], max(8, bh // 16), axis=1)
    gap = np.full((bh, max(4, bh // 32), 3), 255, np.uint8)
    return np.concatenate([big, gap, bar], axis=1)


def false_colour_png(path, image, *, title: str = "", unit: str = "", cmap: str = "viridis", vmin=None, vmax=None,
                     zero_based: bool = False, use_matplotlib: bool | None = None, overwrite: bool = False) -> Path:
    """Write a false-colour PNG of a 2-D image (row 0 at the top) with a colour bar; returns the path.

    The colour scale spans :func:`value_range` (``vmin``, ``vmax``, ``zero_based``)."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"expected a 2-D image, got shape {image.shape}")
    vmin, vmax = value_range(image, vmin, vmax, zero_based)
    if use_matplotlib is None:
        use_matplotlib = have_matplotlib()
    if not use_matplotlib:
        return write_bytes_atomically(path, encode_png(_numpy_figure(image, cmap, vmin, vmax)), overwrite=overwrite)
    from matplotlib.figure import Figure

    lo, hi = vmin, vmax
    h, w = image.shape
    aspect = h / w
    fig = Figure(figsize=(5.6, max(2.0, min(8.0, 4.4 * aspect + 0.8))), dpi=100)
    ax = fig.add_subplot()
    cm = _mpl_cmap(cmap)
    shown = ax.imshow(np.ma.masked_invalid(image.astype(np.float64)), cmap=cm, vmin=lo, vmax=hi,
                      interpolation="nearest", origin="upper")
    ax.set_xlabel("pixel x")
    ax.set_ylabel("pixel y")
    if title:
        ax.set_title(title)
    bar = fig.colorbar(shown, ax=ax)
    if unit:
        bar.set_label(unit)
    return _save_figure(fig, path, overwrite)


def _mpl_cmap(name):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=NO_DATA_RGB)


def _save_figure(fig, path, overwrite) -> Path:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return write_bytes_atomically(path, buf.getvalue(), overwrite=overwrite)


# ----------------------------------------------------------------------------------------------------------
# Waveform plot
# ----------------------------------------------------------------------------------------------------------
def bin_centres_range_m(gate_start_s: float, bin_width_s: float, n_bins: int) -> np.ndarray:
    """Range (m) of each waveform bin's centre: c·t/2 with t = gate_start + (k + ½)·bin_width (physics.md §9)."""
    t = gate_start_s + (np.arange(n_bins) + 0.5) * bin_width_s
    return 0.5 * SPEED_OF_LIGHT_M_S * t


def waveform_png(path, range_m, values, *, title: str = "", ylabel: str = "energy per bin (J)", markers_m=(),
                 use_matplotlib: bool | None = None, overwrite: bool = False, size_px=(640, 360)) -> Path:
    """A line plot of one waveform against range (``markers_m``: ranges marked by dashed lines, e.g. the
    detected echoes; matplotlib only); returns the path."""
    range_m = np.asarray(range_m, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if range_m.shape != values.shape or values.ndim != 1 or len(values) == 0:
        raise ValueError(f"range_m {range_m.shape} and values {values.shape} must be equal 1-D shapes")
    if use_matplotlib is None:
        use_matplotlib = have_matplotlib()
    if not use_matplotlib:
        return write_bytes_atomically(path, encode_png(_numpy_plot(values, *size_px)), overwrite=overwrite)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size_px[0] / 100, size_px[1] / 100), dpi=100)
    ax = fig.add_subplot()
    ax.plot(range_m, values, lw=1.0, color="#1f5fa8")
    for k, r in enumerate(np.atleast_1d(np.asarray(markers_m, dtype=np.float64))):
        ax.axvline(r, color="#c0392b", lw=0.8, ls="--", label="detected echo" if k == 0 else None)
    if len(np.atleast_1d(markers_m)):
        ax.legend(loc="upper right", fontsize="small")
    ax.set_xlabel("range (m)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save_figure(fig, path, overwrite)


def _numpy_plot(values, width, height) -> np.ndarray:
    """White canvas, the waveform as filled columns from the zero line (no axes, no text)."""
    img = np.full((height, width, 3), 255, np.uint8)
    v = np.nan_to_num(values.astype(np.float64))
    lo, hi = min(0.0, v.min()), max(0.0, v.max())
    if hi == lo:
        hi = lo + 1.0
    cols = np.clip((np.arange(width) * len(v)) // width, 0, len(v) - 1)
    y = np.round((hi - v[cols]) / (hi - lo) * (height - 1)).astype(int)
    y0 = int(round(hi / (hi - lo) * (height - 1)))
    rows = np.arange(height)[:, None]
    fill = (rows >= np.minimum(y, y0)[None, :]) & (rows <= np.maximum(y, y0)[None, :])
    img[fill] = (31, 95, 168)
    img[y0, :] = (0, 0, 0)
    return img


# ----------------------------------------------------------------------------------------------------------
# A run folder's previews
# ----------------------------------------------------------------------------------------------------------
def write_run_previews(run_dir, *, use_matplotlib: bool | None = None, cancel=None) -> list[Path]:
    """False-colour PNGs beside every image EXR of a run folder (``range.png`` beside ``range.exr``, ...;
    ``slices/slice_NNNN.png`` on one colour scale shared by all slices, 0 … the sweep's maximum, drawn by the
    fast NumPy renderer since a sweep has tens of slices) and, for a single-pixel run (range
    profiler), ``waveform.png`` of its waveform.  Call it on a run folder that is still being assembled; files
    that exist are left alone.  ``cancel()`` true stops between files.  Returns the written paths."""
    from .run_folder import read_exr

    run_dir = Path(run_dir)
    written = []
    units = run_units(run_dir)

    def stop():
        return cancel is not None and cancel()

    for product in ("range", "intensity", "energy"):
        exr = run_dir / f"{product}.exr"
        png = exr.with_suffix(".png")
        if not exr.is_file() or png.exists() or stop():
            continue
        title, cmap, zero_based = PRODUCTS[product]
        written.append(false_colour_png(png, _first_channel(read_exr(exr)), title=title, unit=units.get(product, ""),
                                        cmap=cmap,
                                        zero_based=zero_based, use_matplotlib=use_matplotlib))
    slices = sorted((run_dir / "slices").glob("slice_*.exr")) if (run_dir / "slices").is_dir() else []
    if slices:
        stack = _slice_stack(run_dir, slices)
        vmax = float(np.nanmax(stack)) if np.isfinite(stack).any() else 1.0
        title, cmap, _ = PRODUCTS["slices"]
        unit = units.get("slices", "")
        for k, exr in enumerate(slices):
            png = exr.with_suffix(".png")
            if png.exists() or stop():
                continue
            # the fast renderer (no text) for slices: a sweep has tens of them per frame
            written.append(false_colour_png(png, stack[k], title=f"{title} {k + 1}/{len(slices)}", unit=unit,
                                            cmap=cmap, vmin=0.0, vmax=max(vmax, 1e-300), use_matplotlib=False))
    wf_path = run_dir / "waveforms.npy"
    png = run_dir / "waveform.png"
    if wf_path.is_file() and not png.exists() and not stop():
        cube = np.load(wf_path, mmap_mode="r")
        if cube.ndim == 3 and cube.shape[:2] == (1, 1):
            gate = _gate_settings(run_dir)
            rng = bin_centres_range_m(gate["gate_start_s"], gate["bin_width_s"], cube.shape[2])
            written.append(waveform_png(png, rng, np.asarray(cube[0, 0]), title="Range profile",
                                        ylabel=f"energy ({units.get('waveforms', 'J per bin')})",
                                        use_matplotlib=use_matplotlib))
    return written


def _first_channel(channels: dict) -> np.ndarray:
    return channels["Y"] if "Y" in channels else next(iter(channels.values()))


def _slice_stack(run_dir, slice_files) -> np.ndarray:
    npy = run_dir / "slices.npy"
    if npy.is_file():
        stack = np.load(npy, mmap_mode="r")
        if len(stack) == len(slice_files):
            return np.asarray(stack, dtype=np.float64)
    from .run_folder import read_exr
    return np.stack([_first_channel(read_exr(p)) for p in slice_files]).astype(np.float64)


def _gate_settings(run_dir) -> dict:
    meta = json.loads((Path(run_dir) / "metadata.json").read_text(encoding="utf-8"))
    return meta["settings"]["gate"]


def run_units(run_dir) -> dict:
    """The units of a run folder's products (``metadata.json`` → ``units``); empty for a folder without them
    (a run written before units were recorded: its previews carry no unit rather than a wrong one)."""
    path = Path(run_dir) / "metadata.json"
    if not path.is_file():
        return {}
    return dict(json.loads(path.read_text(encoding="utf-8")).get("units", {}))
