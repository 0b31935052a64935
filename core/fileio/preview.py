"""Every picture the simulator draws (the one home of plotting; physics modules never write files): false-colour
PNGs of a run's range/intensity/energy images and of every gated slice, the scanner's point cloud seen from the
sensor, waveform plots with their detected echoes, BRDF plots, and a sweep's summary figures against its axes
(``core/sweep``).  Never imports bpy.

Matplotlib draws them all (Agg, object API without pyplot: safe in a worker thread and leaves the user's
backend alone); the extension bundles it with its dependencies (scripts/build_extension.py), so every preview
has a title, axes with units and a colour bar (or a legend) wherever it is made.  Images show the receiver's
field of view on angle axes (mrad from the boresight, +x right, +y up; row 0 at the top).

A gated sweep's slices share one figure: the first is drawn in full, its drawing recorded, and the others
replay it with their own pixels and title (:class:`FigureReplay`: only where those are drawn, the image by an
index map), the same PNG bytes new figures give, at ≈ 6 % of a full draw's cost (docs/performance.md).  The
previews' renderer lays out each distinct text once per process (:class:`_MemoFont`), and the PNGs are encoded
by :func:`encode_png` (savefig's chunks, its pixels deflated more cheaply): matplotlib's own ``savefig`` gives
the same decoded pixels and text chunks (tests/core/fileio/test_preview_encoding.py).

Every PNG is written atomically (``staging.write_file_atomically``: a hidden temporary file, then
``os.replace``) and an existing file is never replaced unless ``overwrite`` is asked.  The PNG's text chunks
repeat what is drawn (``Title``, ``Description``: the axes and colour-bar labels), for tools (and tests) that
read them.
"""
from __future__ import annotations

import copy
import functools
import io
import json
import re
import struct
import threading
from pathlib import Path

import numpy as np

from ..config.settings import BRDFSettings
from ..constants import SPEED_OF_LIGHT_M_S
from ..physics.brdf import evaluate_brdf
from .staging import write_file_atomically
from .run_folder import DISPLAY_PREFIXES, display_prefix, format_energy_j, read_exr

#: What each image product shows: (title, colour map, logarithmic colour scale).  Units come from the run's
#: ``metadata.json`` (``units``, written from ``FrameResult.units``: core.engine.result.product_units).
#: Intensity and energy span several decades across a frame (inverse-square law, reflectance, incidence): on a
#: linear scale the weak half of the echoes would share the lowest colour with the pixels without one.
PRODUCTS = {"range": ("Range", "viridis", False), "intensity": ("Intensity", "inferno", True),
            "energy": ("Received energy", "inferno", True), "slices": ("Gated slice", "inferno", True)}
NO_DATA_RGB = (0.35, 0.35, 0.35)  # pixels without a value (NaN range, no echo, no return): grey
#: The intensity and energy previews' logarithmic colour scale spans at most this many decades below the
#: image's maximum (weaker echoes show in the scale's lowest colour, still not the no-echo grey).
IMAGE_DECADES = 6.0
#: Gated slices share one logarithmic colour scale over this many decades below the sweep's maximum, so the
#: faint first and last slices (the gate's edges on the return) still show their data.
SLICE_DECADES = 4.0
#: The scanner's preview draws at most this many points (evenly chosen; the title gives the total).
MAX_SCATTER_POINTS = 200_000


# ----------------------------------------------------------------------------------------------------------
# Atomic writes
# ----------------------------------------------------------------------------------------------------------
def write_bytes_atomically(path, data: bytes, *, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` through a hidden temporary file in the same folder (never half a file).

    Raises FileExistsError if ``path`` exists and ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (previews never replace a file unless asked)")
    return write_file_atomically(path, lambda f: f.write(data))


def save_figure(fig, path, overwrite: bool = False, replay: "FigureReplay | None" = None) -> Path:
    """The figure as a PNG at ``path`` (atomic), its title and axis/colour-bar labels in the text chunks.

    ``replay``: the figure's :class:`FigureReplay` (a figure drawn again with other pixels and title: the
    same PNG bytes as a full draw, at a fraction of the cost)."""
    data = replay.png(png_metadata(fig)) if replay is not None else figure_png(fig)
    return write_bytes_atomically(path, data, overwrite=overwrite)


def png_metadata(fig) -> dict:
    """The PNG text chunks of a figure: ``Title`` and ``Description`` (its axes' and colour bar's labels)."""
    labels = []
    for ax in fig.axes:
        for what, text in (("x", ax.get_xlabel()), ("y", ax.get_ylabel())):
            if text:
                labels.append(f"{what}: {text}")
    return {"Title": figure_title(fig), "Description": "; ".join(labels)}


def figure_png(fig) -> bytes:
    """The PNG bytes of a full draw of ``fig`` (matplotlib's ``savefig``, its pixels encoded by
    :func:`encode_png`)."""
    return encode_png(figure_rgba(fig), dpi=fig.dpi, metadata=png_metadata(fig))


def figure_rgba(fig) -> np.ndarray:
    """A full draw of ``fig``: the (H, W, 4) uint8 pixels ``savefig`` would encode as a PNG (its ``rgba`` format:
    the same draw of the canvas as its ``png``, then the canvas' buffer as it is)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="rgba")
    width, height = (int(v) for v in fig.canvas.get_width_height(physical=True))
    return np.frombuffer(buf.getvalue(), dtype=np.uint8).reshape(height, width, 4)


#: zlib level of the PNG previews' pixel data (:func:`encode_png`).
PNG_ZLIB_LEVEL = 3


def encode_png(rgba, *, dpi: float, metadata: dict) -> bytes:
    """An 8-bit RGBA PNG of ``rgba`` ((H, W, 4) uint8, row 0 at the top), as matplotlib's ``savefig`` writes it
    but for how the pixels are compressed: the same chunks in the same order and bytes (``IHDR``; the text chunks
    ``Software`` = matplotlib's version, then ``metadata`` in its order; ``pHYs`` from ``dpi``), taken from
    Pillow's own encoding of a 1×1 image with that information, and one ``IDAT`` whose rows are unfiltered
    (filter type 0) and deflated by zlib at level :data:`PNG_ZLIB_LEVEL`, where Pillow tries every PNG filter on
    every row and deflates at level 6.  The decoded pixels are the same; encoding a 640×426 preview takes
    ≈ 4 ms instead of ≈ 18 ms, and the file is ≈ 10–15 % larger (docs/performance.md, session 32)."""
    import zlib

    rgba = np.ascontiguousarray(rgba, dtype=np.uint8)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or not rgba.shape[0] or not rgba.shape[1]:
        raise ValueError(f"expected an (H, W, 4) RGBA image, got shape {rgba.shape}")
    height, width = rgba.shape[:2]
    rows = np.empty((height, 1 + 4 * width), dtype=np.uint8)
    rows[:, 0] = 0
    rows[:, 1:] = rgba.reshape(height, 4 * width)
    head, tail = _png_info_chunks(float(dpi), tuple(metadata.items()))
    ihdr = _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0))
    idat = _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), PNG_ZLIB_LEVEL))
    return b"".join((b"\x89PNG\r\n\x1a\n", ihdr, head, idat, tail))


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    import zlib

    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(body, zlib.crc32(kind)))


@functools.lru_cache(maxsize=64)
def _png_info_chunks(dpi: float, items: tuple) -> tuple[bytes, bytes]:
    """(the chunks between ``IHDR`` and the pixel data, those after it) of the PNG ``savefig`` writes with this
    ``dpi`` and text ``metadata`` items: read from Pillow's PNG of a 1×1 image saved as ``matplotlib.image.imsave``
    saves a figure (so a text that is not Latin-1 is an ``iTXt`` chunk, as Pillow decides)."""
    from matplotlib.image import imsave

    buf = io.BytesIO()
    imsave(buf, np.zeros((1, 1, 4), dtype=np.uint8), format="png", origin="upper", dpi=dpi, metadata=dict(items))
    data = buf.getvalue()
    chunks, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        chunks.append((data[pos + 4:pos + 8], data[pos:pos + 12 + length]))
        pos += 12 + length
    kinds = [kind for kind, _ in chunks]
    if kinds[0] != b"IHDR" or kinds.count(b"IDAT") != 1 or kinds[-1] != b"IEND":
        raise RuntimeError(f"unexpected PNG from Pillow: chunks {kinds}")
    at = kinds.index(b"IDAT")
    return (b"".join(c for _, c in chunks[1:at]), b"".join(c for _, c in chunks[at + 1:]))


class FigureReplay:
    """A figure drawn once in full, then again and again with only some of its artists changed (a gated sweep's
    slices: the image's pixels and the title), byte for byte the PNG a full draw gives, at a fraction of its cost.

    A full draw of a false-colour figure spends ≈ 80 % of its time in matplotlib's Python layer laying out
    what never changes from slice to slice: the axes' and colour bar's ticks (locators, formatters, one Tick
    object per tick), their labels' text layout, the title's position.  The rasterizer (Agg) only sees the
    result, a sequence of calls (``draw_path``, ``draw_markers``, ``draw_text_image`` with a glyph bitmap,
    ``draw_quad_mesh``, ``draw_image``) with their arguments.  The first draw records that sequence, its
    arguments frozen (copies of the graphics contexts, paths, transforms, glyph bitmaps); a later draw clears
    the canvas and replays it, calling the *dynamic* artists' own ``draw`` at their place in the order (so their
    pixels are blended over exactly what lay under them), then encodes the canvas (:func:`encode_png`, as a full
    draw's PNG is).  A nearest-neighbour ``AxesImage`` among the dynamic artists is drawn from an index map
    (:class:`_NearestImage`), and later draws replay only the calls that can touch the dynamic artists' pixels
    (``_pixels``: the dirty-region replay).  Right after recording, the replay of the first draw is compared
    pixel for pixel with the full draw; if it differs (a matplotlib whose Agg renderer works otherwise), every
    later draw is a full draw (``active`` is false).  Only valid while nothing but the dynamic artists' data
    changes (same figure size, colour scale, labels).
    """

    def __init__(self, fig, dynamic):
        self.fig = fig
        self.dynamic = tuple(dynamic)
        self.calls = None
        self.active = False
        self._renderer = None
        self._fast = {}  # id(dynamic artist): its _NearestImage
        self._static = None  # the canvas with only the static calls drawn (the dirty-region replay's base)
        self._boxes = None  # each recorded call's pixel footprint (_footprint), None for a mark

    def png(self, metadata: dict) -> bytes:
        """The figure's PNG (the first call draws and records it in full)."""
        if self.calls is None:
            return self._record(metadata)
        if not self.active or self.fig.canvas.get_renderer() is not self._renderer:
            return self._savefig(metadata)  # replay unusable, or the figure's size changed: a full draw
        # what FigureCanvasAgg.print_png encodes after its draw
        return encode_png(self._pixels(), dpi=self.fig.dpi, metadata=metadata)

    def _savefig(self, metadata):
        return encode_png(figure_rgba(self.fig), dpi=self.fig.dpi, metadata=metadata)

    def _record(self, metadata) -> bytes:
        self.calls = []
        fig, canvas = self.fig, self.fig.canvas
        recorder = _RecordingAgg(self.calls)
        used = []

        def draw_recorded(renderer):  # the figure's draw inside savefig, through the recorder
            real = getattr(renderer, "_renderer", None)
            if real is None or not hasattr(renderer, "_update_methods"):
                return type(fig).draw(fig, renderer)  # not the Agg renderer this class knows: full draws
            used.append(renderer)
            recorder.real = real
            renderer._renderer = recorder
            renderer._update_methods()
            try:
                return type(fig).draw(fig, renderer)
            finally:
                renderer._renderer = real
                renderer._update_methods()

        fig.draw = draw_recorded
        for artist in self.dynamic:
            artist.draw = _marked_draw(artist, recorder)
        try:
            data = self._savefig(metadata)
        finally:
            del fig.draw
            for artist in self.dynamic:
                del artist.draw
        marks = [args for name, args in self.calls if name is None]
        self.active = (len(used) == 1 and canvas.get_renderer() is used[0] and len(marks) == len(self.dynamic)
                       and all(any(m is a for m in marks) for a in self.dynamic))
        if self.active:
            self._renderer = used[0]
            for artist in self.dynamic:
                fast = _NearestImage.build(artist, used[0], recorder.dynamic_calls.get(id(artist), ()))
                if fast is not None:
                    self._fast[id(artist)] = fast
            drawn = np.array(canvas.buffer_rgba(), copy=True)
            try:
                self._replay()
                self.active = bool(np.array_equal(np.asarray(canvas.buffer_rgba()), drawn))
            except Exception:  # noqa: BLE001 - any trouble replaying: full draws, as before
                self.active = False
            if self.active:
                self._prepare_dirty(drawn)  # checked against the full draw too; if it fails, full replays
        return data

    def _replay(self) -> None:
        """Clear the canvas and replay every recorded call, the dynamic artists drawing at their marks."""
        renderer = self.fig.canvas.get_renderer()
        renderer.clear()
        agg = renderer._renderer
        for name, args in self.calls:
            if name is None:
                if id(args) in self._fast:
                    self._fast[id(args)].draw(agg)
                else:
                    args.draw(renderer)
            else:
                getattr(agg, name)(*args)

    # -- the dirty-region replay ------------------------------------------------------------------------------
    # The pixels a replay gives differ from those of the static calls alone only where a dynamic artist draws
    # (the image's rectangle, the title's glyph bitmap).  A pixel's value is the blend, in order, of the calls
    # that touch it, so inside those regions it suffices to replay the calls whose footprint (a conservative
    # pixel rectangle, :func:`_footprint`; a call without one is always replayed) meets them, and outside them
    # the static calls' canvas, drawn once, is the answer.  Checked on the recorded draw: if the result is not
    # the full draw's pixels exactly, every later slice replays every call (as before).
    def _prepare_dirty(self, drawn) -> None:
        renderer = self.fig.canvas.get_renderer()
        height, width = drawn.shape[:2]
        try:
            boxes = [None if name is None else _footprint(name, args, height, width, self.fig.dpi)
                     for name, args in self.calls]
            renderer.clear()
            agg = renderer._renderer
            for name, args in self.calls:
                if name is not None:
                    getattr(agg, name)(*args)
            self._static, self._boxes = np.array(renderer.buffer_rgba(), copy=True), boxes
            if not np.array_equal(self._pixels(), drawn):
                self._static = self._boxes = None
        except Exception:  # noqa: BLE001 - any trouble: every call replayed, as before
            self._static = self._boxes = None

    def _dynamic_calls(self, renderer) -> list:
        """Each dynamic artist's renderer calls for its current data, caught (frozen), not drawn."""
        out = []
        for artist in self.dynamic:
            fast = self._fast.get(id(artist))
            if fast is not None:
                out.append([("draw_image", (fast.gc, fast.x, fast.y, fast.rgba()))])
                continue
            calls = []
            catcher = _RecordingAgg(calls, forward=False)
            real = catcher.real = renderer._renderer
            renderer._renderer = catcher
            renderer._update_methods()
            try:
                type(artist).draw(artist, renderer)
            finally:
                renderer._renderer = real
                renderer._update_methods()
            out.append(calls)
        return out

    def _pixels(self) -> np.ndarray:
        """The canvas' (H, W, 4) pixels after a replay with the dynamic artists' current data."""
        canvas = self.fig.canvas
        if self._static is None:
            self._replay()
            return np.asarray(canvas.buffer_rgba())
        renderer = canvas.get_renderer()
        height, width = self._static.shape[:2]
        dynamic = self._dynamic_calls(renderer)
        rects = [_footprint(name, args, height, width, self.fig.dpi) for calls in dynamic for name, args in calls]
        if any(r is None for r in rects):
            rects = [(0, height, 0, width)]
        rects = [r for r in rects if r[0] < r[1] and r[2] < r[3]]
        renderer.clear()
        agg = renderer._renderer
        marks = iter(dynamic)
        for (name, args), box in zip(self.calls, self._boxes):
            if name is None:
                for dname, dargs in next(marks):
                    getattr(agg, dname)(*dargs)
            elif box is None or any(box[0] < r[1] and r[0] < box[1] and box[2] < r[3] and r[2] < box[3]
                                    for r in rects):
                getattr(agg, name)(*args)
        out = self._static.copy()
        buf = np.asarray(renderer.buffer_rgba())
        for r0, r1, c0, c1 in rects:
            out[r0:r1, c0:c1] = buf[r0:r1, c0:c1]
        return out


def _footprint(name, args, height, width, dpi):
    """A conservative pixel rectangle (row0, row1, col0, col1; rows from the top, ends excluded, within the
    canvas) that a recorded Agg call changes at most, or None when this function cannot bound it (such calls
    are always replayed).  Paths and markers: their extents through their transforms, widened by twice the line
    width (miter joins, caps, snapping) and 2 pixels of antialiasing; glyph bitmaps: their rectangle (rotated:
    the disc the rotation sweeps); images: their rectangle; the clip rectangle bounds each."""
    if name in ("draw_path", "draw_markers", "draw_quad_mesh") or (name == "draw_image" and len(args) == 4):
        gc = args[0]
    elif name == "draw_text_image" and len(args) == 5:
        gc = args[4]
    else:
        return None
    if gc.get_sketch_params() is not None:
        return None
    lw = float(gc.get_linewidth()) * dpi / 72.0
    margin = 2.0 * lw + 2.0
    if name == "draw_path":
        _, path, transform = args[:3]
        ext = path.get_extents(transform)
        x0, y0, x1, y1 = ext.x0 - margin, ext.y0 - margin, ext.x1 + margin, ext.y1 + margin
        rows = (height - y1, height - y0)
        cols = (x0, x1)
    elif name == "draw_markers":
        _, marker_path, marker_trans, path, trans = args[:5]
        verts = trans.transform(np.asarray(path.vertices, dtype=np.float64).reshape(-1, 2))
        verts = verts[np.isfinite(verts).all(axis=1)]
        if not len(verts):
            return (0, 0, 0, 0)
        m = marker_path.get_extents(marker_trans)
        x0, x1 = verts[:, 0].min() + m.x0 - margin, verts[:, 0].max() + m.x1 + margin
        y0, y1 = verts[:, 1].min() + m.y0 - margin, verts[:, 1].max() + m.y1 + margin
        rows, cols = (height - y1, height - y0), (x0, x1)
    elif name == "draw_quad_mesh":
        _, master, _, _, coords, offsets, *_ = args
        if np.size(offsets) and np.any(np.asarray(offsets) != 0):
            return None
        pts = master.transform(np.asarray(coords, dtype=np.float64).reshape(-1, 2))
        x0, x1 = pts[:, 0].min() - margin, pts[:, 0].max() + margin
        y0, y1 = pts[:, 1].min() - margin, pts[:, 1].max() + margin
        rows, cols = (height - y1, height - y0), (x0, x1)
    elif name == "draw_text_image":
        image, x, y, angle = args[:4]
        h, w = np.shape(image)[:2]
        if angle == 0:
            rows, cols = (y - h - 1, y + 1), (x - 1, x + w + 1)
        else:
            r = float(np.hypot(h, w)) + 4.0
            rows, cols = (y - r, y + r), (x - r, x + r)
    elif name == "draw_image" and len(args) == 4:
        _, x, y, image = args
        h, w = np.shape(image)[:2]
        c0, r0 = int(x), int(height - (y + h))
        rows, cols = (r0 - 1, r0 + h + 1), (c0 - 1, c0 + w + 1)
    else:
        return None
    clip = gc.get_clip_rectangle()
    if clip is not None:
        cx0, cy0, cx1, cy1 = clip.extents
        rows = (max(rows[0], height - cy1 - 2), min(rows[1], height - cy0 + 2))
        cols = (max(cols[0], cx0 - 2), min(cols[1], cx1 + 2))
    box = (rows[0], rows[1], cols[0], cols[1])
    if not all(np.isfinite(box)):
        return None
    r0, r1 = max(0, int(np.floor(rows[0]))), min(height, int(np.ceil(rows[1])) + 1)
    c0, c1 = max(0, int(np.floor(cols[0]))), min(width, int(np.ceil(cols[1])) + 1)
    return (r0, max(r0, r1), c0, max(c0, c1))


class _RecordingAgg:
    """Stands in for a RendererAgg's C++ renderer while a figure draws: forwards every call, and records the
    ``draw_*`` ones (arguments frozen) unless a dynamic artist is drawing."""

    def __init__(self, calls, forward: bool = True):
        self.real = None
        self._calls = calls
        self.forward = forward  # false: record only (a dynamic artist's calls caught for the dirty-region replay)
        self.paused = None  # the dynamic artist drawing, if one is
        self.dynamic_calls = {}  # id(dynamic artist): its own calls (frozen), in order

    def __getattr__(self, name):
        attr = getattr(self.real, name)
        if not name.startswith("draw_"):
            return attr

        def record(*args):
            frozen = (name, tuple(_frozen(a) for a in args))
            if self.paused is None:
                self._calls.append(frozen)
            else:
                self.dynamic_calls.setdefault(id(self.paused), []).append(frozen)
            return attr(*args) if self.forward else None

        return record


def _marked_draw(artist, recorder):
    """``artist.draw`` while recording: a mark in the call sequence where it draws, its own calls not recorded."""
    cls_draw = type(artist).draw

    def draw(renderer):
        recorder._calls.append((None, artist))
        recorder.paused = artist
        try:
            return cls_draw(artist, renderer)
        finally:
            recorder.paused = None

    return draw


_RESAMPLE_LOCK = threading.Lock()


class _NearestImage:
    """A cheaper way to the pixels a dynamic ``AxesImage`` with ``interpolation="nearest"`` gives the renderer
    (its one ``draw_image`` call), for :class:`FigureReplay`.

    matplotlib draws such an image by resampling its data to the output pixels (``_image.resample``, nearest
    neighbour: each output pixel is a copy of one input pixel, or 0 outside the image), the mask likewise
    (its alpha: 1, NaN where masked, 0 outside), then normalises and colour-maps the ≈ 10⁵ output pixels and
    multiplies their alpha by the resampled one; every step after the resampling is element by element (the
    norm with its fixed ``vmin``/``vmax``, the colour map's look-up table, the alpha product).  So the output
    is the input's pixels normalised and colour-mapped *once* (a gated slice: 64 × 96 of them, not 397 × 265),
    then gathered through the index map that the same resampling gives for an image of pixel numbers (one
    extra entry, value 0 with alpha factor 0, stands for "outside").  ``build`` finds the map with matplotlib's
    own resampler (the transform and output shape its drawing used, caught once), and returns ``None`` (the
    artist draws itself, as before) unless the image resamples at the data stage with nearest neighbours, the
    map is the same for the mask's resampling, and the pixels the map gives equal matplotlib's own for the
    recorded draw exactly.  Valid while the data's shape and the norm's scale stay as recorded (a gated
    sweep's reused figure: same shape, scale and colour map)."""

    def __init__(self, image, gc, x, y, index, dtype):
        self.image, self.gc, self.x, self.y, self.index, self.dtype = image, gc, x, y, index, dtype

    @classmethod
    def build(cls, image, renderer, calls):
        from matplotlib import colors as mcolors
        from matplotlib import image as mimage

        try:
            if (not isinstance(image, mimage.AxesImage) or image.get_interpolation() != "nearest"
                    or len(calls) != 1 or calls[0][0] != "draw_image" or len(calls[0][1]) != 4
                    or isinstance(image.norm, mcolors.NoNorm) or not hasattr(mimage, "_resample")):
                return None
            data = image.get_array()
            if data is None or data.ndim != 2 or np.asarray(data).dtype.kind != "f":
                return None
            gc, x, y, drawn = calls[0][1]
            caught = []
            real = mimage._resample

            def catching(image_obj, arr, out_shape, transform, **kwargs):
                if image_obj is image:
                    caught.append((np.ndim(arr), out_shape, transform.frozen(), kwargs))
                return real(image_obj, arr, out_shape, transform, **kwargs)

            with _RESAMPLE_LOCK:  # one catch at a time (other images pass through it untouched)
                mimage._resample = catching
                try:
                    im, l, b, _ = image.make_image(renderer, renderer.get_image_magnification())
                finally:
                    mimage._resample = real
            # the data stage: the data, then its mask (resample=True), both 2-D, on the same grid
            if (im is None or (l, b) != (x, y) or not np.array_equal(im, drawn) or len(caught) != 2
                    or caught[0][0] != 2 or caught[1][0] != 2 or caught[1][3].get("resample") is not True
                    or caught[0][1] != caught[1][1]):
                return None
            h, w = data.shape
            numbers = np.arange(1, h * w + 1, dtype=np.float64).reshape(h, w)
            at = real(image, numbers, caught[0][1], caught[0][2], **caught[0][3])
            at_mask = real(image, numbers, caught[1][1], caught[1][2], **caught[1][3])
            if not (np.array_equal(at, at_mask) and np.array_equal(at, np.round(at))
                    and at.min() >= 0 and at.max() <= h * w):
                return None
            index = at.astype(np.intp) - 1
            index[index < 0] = h * w  # outside the image: the extra entry
            dtype = np.dtype("f8" if np.asarray(data).dtype.itemsize > 4 else "f4")
            fast = cls(image, gc, x, y, index, dtype)
            return fast if np.array_equal(fast.rgba(), drawn) else None
        except Exception:  # noqa: BLE001 - anything unexpected: the artist draws itself, as before
            return None

    def rgba(self) -> np.ndarray:
        """The (H, W, 4) uint8 pixels matplotlib's ``make_image`` gives for the image's current data."""
        image = self.image
        data = image.get_array()
        values = np.asarray(np.ma.getdata(data)).astype(self.dtype)
        mask = np.ma.getmask(data)
        mask = (np.asarray(mask, dtype=bool) if np.shape(mask) == data.shape
                else np.zeros(data.shape, dtype=bool))
        values = np.append(values.ravel(), values.dtype.type(0))
        mask = np.append(mask.ravel(), False)
        colours = image.to_rgba(image.norm(np.ma.masked_array(values, mask)), bytes=True, norm=False)
        factor = np.ones(len(values), dtype=np.float32)  # the resampled mask's alpha: 1 inside, 0 outside
        factor[-1] = 0
        colours[:, 3] = colours[:, 3].astype(np.float32) * factor * image._get_scalar_alpha()
        colours = np.ascontiguousarray(colours, dtype=np.uint8).view(np.uint32)  # one gather per pixel
        return colours[:, 0][self.index].view(np.uint8).reshape(self.index.shape + (4,))

    def draw(self, agg) -> None:
        agg.draw_image(self.gc, self.x, self.y, self.rgba())


def _frozen(arg):
    """A copy of a renderer call's argument that later changes to the figure's objects cannot alter: graphics
    contexts (shallow: their attributes are replaced, never mutated), paths, transforms (their matrix now),
    arrays, and anything exposing a buffer (a glyph bitmap: matplotlib's font object is reused for the next
    text; the previews' :class:`_MemoFont` gives its bitmap as an array)."""
    from matplotlib.backend_bases import GraphicsContextBase
    from matplotlib.path import Path as MplPath
    from matplotlib.transforms import Transform

    if arg is None or isinstance(arg, (bool, int, float, str)):
        return arg
    if isinstance(arg, np.ndarray):
        return arg.copy()
    if isinstance(arg, GraphicsContextBase):
        return copy.copy(arg)
    if isinstance(arg, MplPath):
        if arg.readonly:  # its arrays cannot change
            return arg
        frozen = copy.copy(arg)  # what copy.deepcopy gives (its other attributes are numbers), cheaper
        frozen._vertices = np.array(arg.vertices, copy=True)
        frozen._codes = None if arg.codes is None else np.array(arg.codes, copy=True)
        return frozen
    if isinstance(arg, Transform):
        return arg.frozen()
    if isinstance(arg, (list, tuple)):
        return type(arg)(_frozen(a) for a in arg)
    if isinstance(arg, _MemoFont):  # its glyph bitmap now, whatever the memo and the font's properties do later
        return np.array(arg, dtype=np.uint8, copy=True)
    try:
        return np.array(memoryview(arg), copy=True)
    except TypeError:
        return arg


def figure_title(fig) -> str:
    return next((ax.get_title() for ax in fig.axes if ax.get_title()), "")


def new_figure(width_in: float, height_in: float):
    """A matplotlib Figure on an Agg canvas (no pyplot), 100 dpi, whose renderer lays out and rasterizes each
    distinct text once per process (:func:`_text_memo_classes`)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100)
    _text_memo_classes()[0](fig)
    return fig


#: (font files, hinting factor, kerning factor, size, dpi, text, angle, hinting flags) → what FreeType gave
_TEXT_MEMO: dict = {}
_TEXT_MEMO_MAX = 4096


@functools.cache
def _text_memo_classes():
    """(the previews' canvas class, its renderer class): FigureCanvasAgg and RendererAgg, except that the
    renderer's fonts are :class:`_MemoFont` stand-ins.

    matplotlib's Agg renderer lays out every text twice (once to measure it, once to draw it), each time on a
    font it has just cleared, so FreeType loads and hints every glyph again: a preview's tick labels, axis
    labels and title took ≈ 0.9 ms each, ≈ 0.19 s of the gated example's 33 PNGs, for 61 distinct strings in
    220 calls.  The font's answers after ``set_text`` (size, descent, glyph bitmap and its offset) depend only
    on the font files, the hinting and kerning settings, the size, the dpi, the text, the angle and the hinting
    flags; the stand-in keeps them, keyed by exactly those, and asks FreeType only for a key it has not seen
    (in the order matplotlib does), so every drawn pixel is what a new font would give."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg, RendererAgg

    class PreviewRendererAgg(RendererAgg):
        def _prepare_font(self, font_prop):
            return _MemoFont(self, font_prop)

    class PreviewCanvasAgg(FigureCanvasAgg):
        def get_renderer(self):
            renderer = super().get_renderer()
            if type(renderer) is RendererAgg:
                renderer.__class__ = PreviewRendererAgg
            return renderer

    return PreviewCanvasAgg, PreviewRendererAgg


class _MemoFont:
    """Stands in for the FT2Font a RendererAgg prepares for one text (:func:`_text_memo_classes`): ``set_text``,
    then ``get_width_height``, ``get_descent``, ``draw_glyphs_to_bitmap``, ``get_bitmap_offset`` and the glyph
    bitmap (``__array__``, what ``draw_text_image`` reads), answered from :data:`_TEXT_MEMO`."""

    def __init__(self, renderer, prop):
        import matplotlib
        from matplotlib.font_manager import fontManager

        self._renderer, self._prop = renderer, prop
        paths = fontManager._find_fonts_by_props(prop)
        self._base = (tuple(str(p) for p in paths), matplotlib.rcParams.get("text.hinting_factor"),
                      matplotlib.rcParams.get("text.kerning_factor"), float(prop.get_size_in_points()),
                      float(renderer.dpi))
        self._key = None
        self._antialiased = None

    def set_text(self, s, angle=0.0, flags=None):
        self._key = self._base + (s, float(angle), flags)
        self._antialiased = None

    def _value(self, what):
        entry = _TEXT_MEMO.get(self._key)
        if entry is None or what not in entry:
            from matplotlib.backends.backend_agg import RendererAgg

            s, angle, flags = self._key[-3:]
            font = RendererAgg._prepare_font(self._renderer, self._prop)  # cleared, sized
            if flags is None:
                font.set_text(s, angle)
            else:
                font.set_text(s, angle, flags=flags)
            entry = dict(entry or {}, wh=font.get_width_height(), descent=font.get_descent())
            # the bitmap, drawn as matplotlib draws it, then its offset: the one asked for, or (a text being
            # measured, to be drawn next) the antialiased one, saving FreeType's second layout of it
            antialiased = what[1] if isinstance(what, tuple) else True
            if ("image", antialiased) not in entry:
                font.draw_glyphs_to_bitmap(antialiased=antialiased)
                entry[("offset", antialiased)] = font.get_bitmap_offset()
                entry[("image", antialiased)] = np.array(font, dtype=np.uint8, copy=True)
            if len(_TEXT_MEMO) >= _TEXT_MEMO_MAX:
                _TEXT_MEMO.clear()
            _TEXT_MEMO[self._key] = entry
        return entry[what]

    def get_width_height(self):
        return self._value("wh")

    def get_descent(self):
        return self._value("descent")

    def draw_glyphs_to_bitmap(self, antialiased=True):
        self._antialiased = bool(antialiased)
        self._value(("image", self._antialiased))

    def get_bitmap_offset(self):
        return self._value(("offset", self._antialiased))

    def __array__(self, dtype=None, copy=None):
        image = self._value(("image", self._antialiased))
        return image if dtype is None else image.astype(dtype)


def _cmap(name):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad=NO_DATA_RGB)


# ----------------------------------------------------------------------------------------------------------
# False-colour images
# ----------------------------------------------------------------------------------------------------------
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


def angle_extent(settings: dict | None, shape) -> tuple[list | None, str, str]:
    """(imshow extent, x label, y label): the field of view in mrad when the run's settings give it (a run's
    ``metadata["settings"]``), else pixel indices."""
    rx = (settings or {}).get("receiver") or {}
    if "fov_x_rad" in rx and "fov_y_rad" in rx:
        hx, hy = 500.0 * rx["fov_x_rad"], 500.0 * rx["fov_y_rad"]
        return [-hx, hx, -hy, hy], "horizontal angle (mrad)", "vertical angle (mrad)"
    h, w = shape
    return [-0.5, w - 0.5, h - 0.5, -0.5], "pixel column", "pixel row"


def log_scale(image, decades: float = IMAGE_DECADES) -> tuple[float, float]:
    """(vmin, vmax) of a logarithmic colour scale over an image's positive values: its maximum and its smallest
    positive value, at most ``decades`` decades below the maximum (a flat image: one decade below)."""
    img = np.asarray(image, dtype=np.float64)
    positive = img[np.isfinite(img) & (img > 0)]
    if positive.size == 0:
        return 0.1, 1.0
    vmax = float(positive.max())
    vmin = max(float(positive.min()), vmax * 10.0 ** -decades)
    return (vmin if vmin < vmax else 0.1 * vmax), vmax


def false_colour_figure(image, *, title: str, unit: str, cmap: str = "viridis", vmin=None, vmax=None,
                        zero_based: bool = False, log: bool = False, settings: dict | None = None,
                        no_data: str | None = None):
    """A matplotlib Figure of a 2-D image (row 0 at the top): title, angle axes (:func:`angle_extent`) and a
    colour bar labelled with ``unit``.  ``log``: a logarithmic colour scale from ``vmin`` (> 0) to ``vmax``
    (default :func:`log_scale`), the colour bar's label says so; values at or below zero show in the no-data grey
    with NaN, values between 0 and ``vmin`` in the map's lowest colour.  ``no_data``: what the grey means
    ("no echo"), added to the colour bar's label."""
    from matplotlib.colors import LogNorm, Normalize

    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2:
        raise ValueError(f"expected a 2-D image, got shape {image.shape}")
    if log and (vmin is None or vmax is None):
        lo, hi = log_scale(image)
        vmin, vmax = (lo if vmin is None else vmin), (hi if vmax is None else vmax)
    extent, xlabel, ylabel = angle_extent(settings, image.shape)
    h, w = image.shape
    (x0, x1, y0, y1) = extent
    aspect_img = abs(y1 - y0) / max(abs(x1 - x0), 1e-300)
    fig = new_figure(6.4, max(2.6, min(8.0, 4.6 * aspect_img + 1.2)))
    ax = fig.add_subplot()
    if log:
        norm = LogNorm(vmin=vmin, vmax=vmax, clip=True)
        shown = _log_shown(image)
    else:
        lo, hi = value_range(image, vmin, vmax, zero_based)
        norm = Normalize(vmin=lo, vmax=hi)
        shown = image
    im = ax.imshow(np.ma.masked_invalid(shown), cmap=_cmap(cmap), norm=norm, interpolation="nearest",
                   origin="upper", extent=extent, aspect="auto" if max(h, w) / max(1, min(h, w)) > 8 else "equal")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    bar = fig.colorbar(im, ax=ax)
    label = unit + (", logarithmic scale" if log else "") if unit else ("logarithmic scale" if log else "")
    if no_data:
        label += f" (grey: {no_data})"
    bar.set_label(label)
    if not log:
        bar.formatter.set_useOffset(False)  # 299.98 m, not "+2.9998e2" above the bar
    elif re.match(r"J\b", unit or ""):
        si_energy_ticks(bar)
    if log:
        ticks_in_view_only(bar.ax.yaxis if bar.orientation == "vertical" else bar.ax.xaxis)
    return fig


def ticks_in_view_only(axis) -> None:
    """Give a logarithmic axis only the tick locations near its view: the same picture, cheaper to draw.

    matplotlib's LogLocator returns ticks a decade beyond each end of the view, and the axis makes a Tick
    object (five artists, their properties deep-copied) for every location before it draws only those inside
    the view: a log colour bar over six decades made 98 Ticks to draw about 60, a quarter of the figure's
    drawing time.  Wrapping both locators to drop locations more than 10⁻³ of the view's span outside it
    (matplotlib's own test, ``_interval_contains_close``, still decides what is drawn, and the minor ticks it
    removes as duplicates of major ones are found within 10⁻⁵ of the span) leaves every drawn tick and its label
    as they were: a log axis' formatters (``LogFormatter``, ``NullFormatter``) label from the view, never from
    the list of locations (``LogFormatter.set_locs`` ignores it).  Any other axis is left alone.  The PNG bytes
    are the same (tests/core/fileio/test_preview_scales.py)."""
    from matplotlib.ticker import LogFormatter, NullFormatter

    if axis.get_scale() != "log" or not all(isinstance(f, (LogFormatter, NullFormatter))
                                            for f in (axis.get_major_formatter(), axis.get_minor_formatter())):
        return
    cls = _in_view_locator_class()
    for get, set_ in ((axis.get_major_locator, axis.set_major_locator),
                      (axis.get_minor_locator, axis.set_minor_locator)):
        if not isinstance(get(), cls):
            set_(cls(get()))


@functools.cache
def _in_view_locator_class():
    from matplotlib.ticker import Locator

    class InViewLocator(Locator):
        """Another locator's ticks, only those within 10⁻³ of the view's span of the view (:func:`ticks_in_view_only`)."""

        def __init__(self, inner):
            self.inner = inner

        def set_axis(self, axis):
            super().set_axis(axis)
            self.inner.set_axis(axis)

        def __call__(self):
            locs = np.asarray(self.inner(), dtype=np.float64)
            transform = self.axis.get_transform()
            lo, hi = sorted(transform.transform(np.asarray(self.axis.get_view_interval(), dtype=np.float64)))
            margin = 1e-3 * (hi - lo)
            with np.errstate(all="ignore"):
                t = transform.transform(locs)
            return locs[(t >= lo - margin) & (t <= hi + margin)]

        def tick_values(self, vmin, vmax):
            return self.inner.tick_values(vmin, vmax)

        def nonsingular(self, v0, v1):
            return self.inner.nonsingular(v0, v1)

        def view_limits(self, vmin, vmax):
            return self.inner.view_limits(vmin, vmax)

    return InViewLocator


def si_energy_ticks(bar) -> None:
    """Label a logarithmic colour bar in joules with SI prefixes ("10 fJ", "1 pJ", "3 nJ"), not powers of ten of
    J (issue 27): matplotlib's log formatter still chooses which ticks get a label, only their text changes."""
    from matplotlib.ticker import LogFormatterSciNotation

    class SIEnergyFormatter(LogFormatterSciNotation):
        def __call__(self, x, pos=None):
            return format_energy_j(x) if super().__call__(x, pos) else ""

    axis = bar.ax.yaxis if bar.orientation == "vertical" else bar.ax.xaxis
    axis.set_major_formatter(SIEnergyFormatter())
    axis.set_minor_formatter(SIEnergyFormatter(labelOnlyBase=False))


def _log_shown(image: np.ndarray):
    """The pixels a log scale draws: values ≤ 0 (no echo, no return) masked like NaN (the no-data grey)."""
    return np.ma.masked_where(~(image > 0), image)


def false_colour_png(path, image, *, title: str = "", unit: str = "", cmap: str = "viridis", vmin=None,
                     vmax=None, zero_based: bool = False, log: bool = False, settings: dict | None = None,
                     overwrite: bool = False, reuse: dict | None = None, no_data: str | None = None) -> Path:
    """Write :func:`false_colour_figure` as a PNG; returns the path.

    ``reuse``: a dict kept by the caller across images (a gated sweep's slices): the first call lays the figure
    out, draws it in full and keeps it there; a later call with the same shape, unit, colour map and colour
    scale (the given ``vmin``/``vmax``, else the one its own data give) only swaps the pixels and the title and
    replays what it changes (:class:`FigureReplay`: the same PNG bytes as a new figure's; a gated example's
    slice ≈ 10 ms with its encoding against ≈ 0.17 s for a new figure, docs/performance.md); any other call lays
    out a new figure."""
    if reuse is None:
        return save_figure(false_colour_figure(image, title=title, unit=unit, cmap=cmap, vmin=vmin, vmax=vmax,
                                               zero_based=zero_based, log=log, settings=settings,
                                               no_data=no_data), path, overwrite)
    image = np.asarray(image, dtype=np.float64)
    if log:
        lo, hi = log_scale(image) if vmin is None or vmax is None else (None, None)
        scale = (lo if vmin is None else vmin, hi if vmax is None else vmax)
    else:
        scale = value_range(image, vmin, vmax, zero_based)
    key = (image.shape, unit, cmap, log, zero_based, tuple(float(v) for v in scale), no_data,
           json.dumps(settings, sort_keys=True, default=str))
    if reuse.get("key") != key:
        fig = false_colour_figure(image, title=title, unit=unit, cmap=cmap, vmin=scale[0], vmax=scale[1],
                                  zero_based=zero_based, log=log, settings=settings, no_data=no_data)
        ax = fig.axes[0]
        reuse.update(key=key, figure=fig, replay=FigureReplay(fig, (ax.images[0], ax.title)))
    else:
        fig = reuse["figure"]
        fig.axes[0].images[0].set_data(np.ma.masked_invalid(_log_shown(image) if log else image))
        fig.axes[0].set_title(title, fontsize=10)
    return save_figure(fig, path, overwrite, replay=reuse["replay"])


def slice_scale(stack: np.ndarray) -> tuple[float, float]:
    """(vmin, vmax) of the gated slices' shared log colour scale: the sweep's maximum and
    :data:`SLICE_DECADES` decades below it (or the smallest positive value, if higher)."""
    positive = stack[np.isfinite(stack) & (stack > 0)]
    if positive.size == 0:
        return 1e-30, 1.0
    vmax = float(positive.max())
    vmin = max(float(positive.min()), vmax * 10.0 ** -SLICE_DECADES)
    return (vmin if vmin < vmax else 0.1 * vmax), vmax


def gate_label(delay_s: float, width_s: float | None) -> str:
    """'gate 6600.0 ns: 989.3 – 992.3 m': the gate's opening delay and the ranges it spans (c·t/2)."""
    r0 = 0.5 * SPEED_OF_LIGHT_M_S * delay_s
    if width_s is None:
        return f"gate delay {delay_s * 1e9:.1f} ns ({r0:.1f} m)"
    r1 = 0.5 * SPEED_OF_LIGHT_M_S * (delay_s + width_s)
    return f"gate delay {delay_s * 1e9:.1f} ns: {r0:.1f} – {r1:.1f} m"


# ----------------------------------------------------------------------------------------------------------
# Waveform plot
# ----------------------------------------------------------------------------------------------------------
def bin_centres_range_m(gate_start_s: float, bin_width_s: float, n_bins: int) -> np.ndarray:
    """Range (m) of each waveform bin's centre: c·t/2 with t = gate_start + (k + ½)·bin_width (docs/theory.md §9)."""
    t = gate_start_s + (np.arange(n_bins) + 0.5) * bin_width_s
    return 0.5 * SPEED_OF_LIGHT_M_S * t


def prefixed_energy(values, label: str):
    """``values`` in joules and their axis ``label`` ("energy per bin (J)", "energy (J per bin)") on the SI prefix
    that puts the largest magnitude in [1, 1000): (values / 10^k, "energy per bin (fJ)").  A label without a
    unit in J, or values without a finite non-zero one, come back as they are (a linear axis of 2e-15 J showed
    "1e-15" over ticks 0.25 … 2.00, issue 27)."""
    values = np.asarray(values, dtype=np.float64)
    m = re.search(r"\(J\b", label)
    finite = np.abs(values[np.isfinite(values)])
    if m is None or not finite.size or finite.max() == 0.0:
        return values, label
    k = display_prefix(finite.max())
    if k == 0:
        return values, label
    return values / float(f"1e{k}"), label[:m.start()] + f"({DISPLAY_PREFIXES[k]}J" + label[m.end():]


def waveform_figure(range_m, values, *, title: str = "", ylabel: str = "energy per bin (J)", markers_m=()):
    """A line plot of one waveform against range, the detected echoes (``markers_m``) as dashed lines with
    their ranges in the legend.  Energies in J are drawn on the SI prefix that suits them
    (:func:`prefixed_energy`)."""
    range_m = np.asarray(range_m, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if range_m.shape != values.shape or values.ndim != 1 or len(values) == 0:
        raise ValueError(f"range_m {range_m.shape} and values {values.shape} must be equal 1-D shapes")
    values, ylabel = prefixed_energy(values, ylabel)
    fig = new_figure(6.4, 3.6)
    ax = fig.add_subplot()
    ax.plot(range_m, values, lw=1.0, color="#1f5fa8", label="waveform")
    markers = np.atleast_1d(np.asarray(markers_m, dtype=np.float64))
    for k, r in enumerate(markers):
        ax.axvline(r, color="#c0392b", lw=0.8, ls="--",
                   label=(f"detected echo{'es' if len(markers) > 1 else ''}: "
                          + ", ".join(f"{m:.2f}" for m in markers[:6]) + (" …" if len(markers) > 6 else "")
                          + " m") if k == 0 else None)
    ax.legend(loc="upper right", fontsize="small")
    ax.set_xlabel("range (m)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig


def waveform_png(path, range_m, values, *, title: str = "", ylabel: str = "energy per bin (J)", markers_m=(),
                 overwrite: bool = False) -> Path:
    """Write :func:`waveform_figure` as a PNG; returns the path."""
    return save_figure(waveform_figure(range_m, values, title=title, ylabel=ylabel, markers_m=markers_m), path,
                       overwrite)


# ----------------------------------------------------------------------------------------------------------
# Scanner point cloud
# ----------------------------------------------------------------------------------------------------------
def scan_figure(points: dict, world_from_sensor, *, title: str = "Scanner points"):
    """The scanner's points seen from the sensor: x and y in the sensor frame of the scan's start pose (m; for
    a sensor looking down this is a plan view), coloured by range, first echoes over later ones."""
    pos = np.asarray(points["position_world"], dtype=np.float64).reshape(-1, 3)
    rng = np.asarray(points.get("range_m", np.linalg.norm(pos, axis=1)), dtype=np.float64)
    m = np.asarray(world_from_sensor, dtype=np.float64)
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    local = (pos - m[:3, 3]) @ rot
    n = len(pos)
    keep = np.arange(n) if n <= MAX_SCATTER_POINTS else np.linspace(0, n - 1, MAX_SCATTER_POINTS).astype(int)
    if "echo_index" in points:
        keep = keep[np.argsort(-np.asarray(points["echo_index"])[keep], kind="stable")]  # first echoes on top
    fig = new_figure(6.4, 5.2)
    ax = fig.add_subplot()
    sc = ax.scatter(local[keep, 0], local[keep, 1], c=rng[keep], s=max(0.2, min(6.0, 4e4 / max(len(keep), 1))),
                    cmap=_cmap("viridis"), linewidths=0, rasterized=True)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("sensor x, right (m)")
    ax.set_ylabel("sensor y, up (m)")
    shown = "" if len(keep) == n else f", {len(keep)} drawn"
    ax.set_title(f"{title}: {n} points{shown}", fontsize=10)
    ax.grid(alpha=0.3)
    bar = fig.colorbar(sc, ax=ax)
    bar.set_label("range (m)")
    return fig


# ----------------------------------------------------------------------------------------------------------
# Sweep plots
# ----------------------------------------------------------------------------------------------------------
#: A sweep figure gets a logarithmic y axis when its drawn means span more than this many decades.
SWEEP_LOG_Y_DECADES = 2.0


def sweep_log_y(series) -> bool:
    """True when the means of the drawn ``series`` are all ≥ 0 and their positive values span more than
    :data:`SWEEP_LOG_Y_DECADES` decades (received energy against range: a linear axis puts the far points on
    zero).  Zero means (no points at all) are then not drawn: the title says so."""
    means = np.concatenate([np.asarray(s[2], dtype=np.float64).ravel() for s in series[:12]])
    means = means[np.isfinite(means)]
    positive = means[means > 0]
    return bool(positive.size >= 2 and means.min() >= 0
                and positive.max() > positive.min() * 10.0 ** SWEEP_LOG_Y_DECADES)


def sweep_figure(series, *, xlabel: str, ylabel: str, log_x: bool = False, log_y: bool | None = None):
    """A summary figure of a sweep against one swept axis: ``series`` = [(label, x values, mean, std, n)], one per
    combination of the other axes (at most 12 drawn); the mean across seeds as a line with markers and mean ± one
    standard deviation as a band.  ``log_y``: a logarithmic y axis (None: :func:`sweep_log_y` decides; the
    axis label says "log scale")."""
    if not series:
        raise ValueError("no series to plot")
    if log_y is None:
        log_y = sweep_log_y(series)
    fig = new_figure(7.2, 4.4)
    ax = fig.add_subplot()
    zeros = False
    for label, x, mean, std, _ in series[:12]:
        x, mean, std = (np.asarray(a, dtype=np.float64) for a in (x, mean, std))
        if log_y:
            zeros |= bool(np.any(mean <= 0))
            mean = np.where(mean > 0, mean, np.nan)  # not drawn on a log axis
            low = np.where(mean - std > 0, mean - std, mean * 0.1)  # the band's lower edge, kept on the axis
        else:
            low = mean - std
        line, = ax.plot(x, mean, marker="o", ms=4, lw=1.2, label=label or None)
        ax.fill_between(x, low, mean + std, color=line.get_color(), alpha=0.2, lw=0)
    if log_x:
        ax.set_xscale("log")
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel + (" (log scale" + ("; zeros not drawn)" if zeros else ")") if log_y else ""))
    counts = sorted({int(k) for s in series for k in s[4]})
    ax.set_title(f"{ylabel} vs {xlabel}: mean ± std over "
                 + (f"{counts[0]}" if len(counts) == 1 else f"{counts[0]}–{counts[-1]}") + " seeds", fontsize=10)
    if any(s[0] for s in series):
        ax.legend(fontsize="x-small", loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def sweep_plot_png(path, series, *, xlabel: str, ylabel: str, log_x: bool = False, log_y: bool | None = None,
                   overwrite: bool = False) -> Path:
    """Write :func:`sweep_figure` as a PNG; returns the path."""
    return save_figure(sweep_figure(series, xlabel=xlabel, ylabel=ylabel, log_x=log_x, log_y=log_y), path,
                       overwrite)


# ----------------------------------------------------------------------------------------------------------
# A run folder's previews
# ----------------------------------------------------------------------------------------------------------
def preview_count(run_dir) -> int:
    """How many previews :func:`write_run_previews` may draw in ``run_dir`` (its progress total)."""
    run_dir = Path(run_dir)
    slices = run_dir / "slices"
    return (sum((run_dir / f"{p}.exr").is_file() for p in ("range", "intensity", "energy"))
            + (len(list(slices.glob("slice_*.exr"))) if slices.is_dir() else 0)
            + (run_dir / "pulses.npz").is_file() + (run_dir / "waveforms.npy").is_file())


def write_run_previews(run_dir, *, cancel=None, progress=None, share=None) -> list[Path]:
    """The previews of a run folder, beside its products (files that exist are left alone):

    * ``range.png``, ``intensity.png``, ``energy.png`` beside the EXRs of an image of more than one pixel;
    * ``slices/slice_NNNN.png`` for gated viewing: each titled with its gate delay and range interval, all on
      one logarithmic colour scale (:func:`slice_scale`; the colour bar's ticks show it);
    * ``points.png`` for the scanner (:func:`scan_figure`);
    * ``waveform.png`` for the range profiler: its one waveform with the detected echoes marked.

    Call it on a run folder that is still being assembled.  ``cancel()`` true stops between files;
    ``progress(done, total)`` is called before the first file and after each (the previews that may be drawn:
    a gated run's 30 slices take seconds).  ``share=(k, n)``: only every ``n``-th preview from the ``k``-th, in
    the order above (the ``n`` calls of ``k = 0 … n-1`` together draw every preview, each the same PNG as one
    call without ``share``: core.fileio.preview_worker draws them on several cores); ``total`` is then the
    share's.  Returns the written paths."""

    run_dir = Path(run_dir)
    k, n = (0, 1) if share is None else (int(share[0]), int(share[1]))
    if not 0 <= k < n:
        raise ValueError(f"share {share!r}: (k, n) with 0 <= k < n")
    written = []
    meta = run_metadata(run_dir)
    units = dict(meta.get("units", {}))
    settings = meta.get("settings")
    slices = sorted((run_dir / "slices").glob("slice_*.exr")) if (run_dir / "slices").is_dir() else []
    total_all = preview_count(run_dir)
    total = len(range(k, total_all, n))
    done = [0]
    index = [0]

    def mine():
        """The next preview in the order above is this share's."""
        i = index[0]
        index[0] += 1
        return i % n == k

    def step():
        done[0] = min(total, done[0] + 1)
        if progress is not None:
            progress(done[0], total)

    if progress is not None:
        progress(0, total)

    def stop():
        return cancel is not None and cancel()

    for product in ("range", "intensity", "energy"):
        exr = run_dir / f"{product}.exr"
        png = exr.with_suffix(".png")
        if not exr.is_file() or not mine():
            continue
        if png.exists() or stop():
            step()
            continue
        image = _first_channel(read_exr(exr))
        if image.size <= 1:  # the profiler's one pixel: its waveform plot is the preview
            step()
            continue
        title, cmap, log = PRODUCTS[product]
        no_data = "no return" if product == "energy" else "no echo"
        written.append(false_colour_png(png, image, title=title, unit=units.get(product, ""), cmap=cmap,
                                        log=log, settings=settings, no_data=no_data))
        step()
    chosen = [exr for exr in slices if mine()]
    if chosen and not stop():
        written += _slice_previews(run_dir, slices, meta, units.get("slices", ""), stop, step,
                                   chosen=set(chosen))
    if (run_dir / "pulses.npz").is_file() and mine():
        png = run_dir / "points.png"
        if (run_dir / "points.npz").is_file() and not stop() and not png.exists():
            with np.load(run_dir / "points.npz") as npz:
                points = {key: npz[key] for key in ("position_world", "range_m", "echo_index") if key in npz.files}
            if len(points.get("position_world", ())):
                pose = (meta.get("sensor_pose") or {}).get("world_from_sensor", np.eye(4))
                written.append(save_figure(scan_figure(points, pose), png))
        step()
    wf_path = run_dir / "waveforms.npy"
    png = run_dir / "waveform.png"
    if wf_path.is_file() and mine():
        if not png.exists() and not stop():
            cube = np.load(wf_path, mmap_mode="r")
            if cube.ndim == 3 and cube.shape[:2] == (1, 1):
                gate = settings["gate"]
                rng = bin_centres_range_m(gate["gate_start_s"], gate["bin_width_s"], cube.shape[2])
                echoes = ()
                if (run_dir / "points.npz").is_file():
                    with np.load(run_dir / "points.npz") as npz:
                        echoes = np.sort(npz["range_m"]) if "range_m" in npz.files else ()
                written.append(waveform_png(png, rng, np.asarray(cube[0, 0]), title="Range profile",
                                            ylabel=f"energy ({units.get('waveforms', 'J per bin')})",
                                            markers_m=echoes))
        step()
    return written


def preload() -> None:
    """Import what drawing a run's previews needs (a preview worker does it while the command starts)."""
    import matplotlib
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.colorbar  # noqa: F401
    import matplotlib.colors  # noqa: F401
    import matplotlib.figure  # noqa: F401
    import matplotlib.font_manager
    import matplotlib.image  # noqa: F401
    import matplotlib.ticker  # noqa: F401

    matplotlib.font_manager.fontManager  # noqa: B018  (loads the font list)
    _text_memo_classes()


def _slice_previews(run_dir, slice_files, meta, unit, stop, step=lambda: None, chosen=None) -> list[Path]:
    """One figure for the sweep: laid out and drawn in full for the first slice, replayed for the others with
    their pixels and titles (:class:`FigureReplay`).  ``chosen``: only these slices (all on the sweep's scale)."""
    stack = _slice_stack(run_dir, slice_files)
    vmin, vmax = slice_scale(stack)
    gated = (meta.get("settings") or {}).get("gated") or {}
    delays = meta.get("slice_delays_s")
    if delays is None and gated:
        delays = [gated["first_delay_s"] + k * gated["delay_step_s"] for k in range(len(slice_files))]
    width = gated.get("gate_width_s")
    title, cmap, _ = PRODUCTS["slices"]
    reuse = {}
    written = []
    for k, exr in enumerate(slice_files):
        if chosen is not None and exr not in chosen:
            continue
        png = exr.with_suffix(".png")
        if png.exists() or stop():
            step()
            continue
        name = f"{title} {k + 1}/{len(slice_files)}"
        if delays is not None and k < len(delays):
            name += ", " + gate_label(float(delays[k]), width)
        written.append(false_colour_png(png, stack[k], title=name, unit=unit, cmap=cmap, vmin=vmin, vmax=vmax,
                                        log=True, settings=meta.get("settings"), reuse=reuse,
                                        no_data="no signal"))
        step()
    return written


def _first_channel(channels: dict) -> np.ndarray:
    return channels["Y"] if "Y" in channels else next(iter(channels.values()))


def _slice_stack(run_dir, slice_files) -> np.ndarray:
    npy = run_dir / "slices.npy"
    if npy.is_file():
        stack = np.load(npy, mmap_mode="r")
        if len(stack) == len(slice_files):
            return np.asarray(stack, dtype=np.float64)
    return np.stack([_first_channel(read_exr(p)) for p in slice_files]).astype(np.float64)


def run_metadata(run_dir) -> dict:
    """A run folder's ``metadata.json`` (empty if it has none yet)."""
    path = Path(run_dir) / "metadata.json"
    if not path.is_file():
        return {}
    return json.loads(path.read_text(encoding="utf-8"))


def run_units(run_dir) -> dict:
    """The units of a run folder's products (``metadata.json`` → ``units``); empty for a folder without them
    (a run written before units were recorded: its previews carry no unit rather than a wrong one)."""
    return dict(run_metadata(run_dir).get("units", {}))


# --------------------------------------------------------------------------------------------------------------
# BRDF plot (paper §3.3): f_r(θ) of a material's ladar BRDF
# --------------------------------------------------------------------------------------------------------------
def plot_brdf(brdf: BRDFSettings, path, *, title: str = "", laser_wavelength_m: float | None = None,
              dpi: int = 100) -> Path:
    """Write a 500×340 px PNG plot of f_r(θ) for θ = 0…90° (written atomically, replacing ``path``).

    Matplotlib (Agg canvas, no pyplot; bundled with the extension): axes, labels, a log f_r axis when all
    values are positive and span more than a factor 20 (a specular peak and a diffuse floor both show), a
    table's measured rows as markers.
    """
    theta = np.linspace(0.0, 90.0, 361)
    f_r = evaluate_brdf(brdf, np.cos(np.radians(theta)))
    positive = np.all(f_r > 0) and (brdf.model != "table" or min(brdf.table_brdf_per_sr) > 0)
    log_axis = bool(positive and f_r.max() / f_r.min() > 20.0)
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # no pyplot: leaves the user's backend alone
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.0, 3.4), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    label = {"lambertian": f"Lambertian, ρ = {brdf.reflectance:.3g}",
             "steinvall": f"Steinvall A={brdf.specular_a:.3g}, s={brdf.slope_s:.3g}, B={brdf.diffuse_b:.3g}, "
                          f"m={brdf.diffuse_m:.3g}",
             "table": f"table at {brdf.table_wavelength_m * 1e9:.0f} nm (linear in θ)"}[brdf.model]
    ax.plot(theta, f_r, color="#1f5fa8", label=label)
    if brdf.model == "table":
        ax.plot(brdf.table_angle_deg, brdf.table_brdf_per_sr, "o", color="#c2410c", markersize=4,
                label="measured")
    if log_axis:
        ax.set_yscale("log")
    else:
        ax.set_ylim(bottom=0.0)
    ax.set_xlim(0.0, 90.0)
    ax.set_xlabel("incidence angle θ (deg)")
    ax.set_ylabel("monostatic BRDF f_r (1/sr)")
    text = title or "Ladar BRDF"
    if laser_wavelength_m:
        text += f" — laser {laser_wavelength_m * 1e9:.0f} nm"
    ax.set_title(text, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    return save_figure(fig, path, overwrite=True)
