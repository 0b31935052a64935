"""The waveform of one pixel (or scanner pulse) of a run, plotted as a PNG and shown in Blender's image editor."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import LadarError

from .results import load_image, load_points, read_run_info


# ------------------------------------------------------------------------------------------------------------
# Waveform view
# ------------------------------------------------------------------------------------------------------------
def frame_run_folder(run_path, frame: int | None = None) -> Path:
    """The run folder of one frame: ``run_path`` itself, or for a sequence its ``frame_NNNN`` (``frame``, else
    the first frame)."""
    run_path = Path(run_path)
    info = read_run_info(run_path)
    if info.get("format") != "ladar-sequence":
        return run_path
    frames = [int(f) for f in info["frames"]]
    if frame is None or frame not in frames:
        frame = frames[0]
    return run_path / f"frame_{frame:04d}"


def waveform_plot(run_path, *, pixel_x: int | None = None, pixel_y: int | None = None, pulse: int | None = None,
                  frame: int | None = None) -> tuple[Path, dict]:
    """Plot one waveform of a run as a PNG in ``<run>/previews/`` (a new file; an existing plot of the same
    waveform is reused, never replaced).  Returns (png path, what was plotted).

    Image runs (flash, profiler): the waveform of pixel (``pixel_x``, ``pixel_y``), default (0, 0) — the range
    profiler's one waveform.  Scanner runs: pulse ``pulse``, default the pulse that received the most energy.
    The echoes detected on it are marked.  Raises LadarError when the run saved no waveforms."""
    from ..core.errors import ConfigError
    from ..core.fileio.preview import bin_centres_range_m, waveform_png

    folder = frame_run_folder(run_path, frame)
    info = read_run_info(folder)
    wf_file = folder / "waveforms.npy"
    if not wf_file.is_file():
        raise LadarError(f"the run {folder} has no waveforms.npy: enable Run > Save Waveforms and simulate again")
    cube = np.load(wf_file, mmap_mode="r")
    points = load_points(folder / "points.npz") if (folder / "points.npz").is_file() else {}
    if cube.ndim == 3:
        h, w, n_bins = cube.shape
        x = 0 if pixel_x is None else int(pixel_x)
        y = 0 if pixel_y is None else int(pixel_y)
        if not 0 <= x < w:
            raise ConfigError("pixel_x", x, f"a column of the {w}×{h} receiver: 0 … {w - 1}")
        if not 0 <= y < h:
            raise ConfigError("pixel_y", y, f"a row of the {w}×{h} receiver: 0 … {h - 1}")
        values = np.asarray(cube[y, x], dtype=np.float64)
        mine = ((points.get("pixel_x", np.zeros(0)) == x) & (points.get("pixel_y", np.zeros(0)) == y)) \
            if points else np.zeros(0, bool)
        what = {"pixel_x": x, "pixel_y": y}
        name = f"waveform_x{x:04d}_y{y:04d}.png"
        title = "Range profile" if (h, w) == (1, 1) else f"Waveform of pixel ({x}, {y})"
    elif cube.ndim == 2:
        n_pulses, n_bins = cube.shape
        p = int(np.argmax(np.asarray(cube).sum(axis=1))) if pulse is None else int(pulse)
        if not 0 <= p < n_pulses:
            raise ConfigError("pulse", p, f"a pulse of the scan: 0 … {n_pulses - 1}")
        values = np.asarray(cube[p], dtype=np.float64)
        mine = (points.get("pulse_index", np.zeros(0)) == p) if points else np.zeros(0, bool)
        what = {"pulse": p}
        name = f"waveform_pulse{p:08d}.png"
        title = f"Waveform of pulse {p}"
    else:
        raise LadarError(f"{wf_file} has an unexpected shape {cube.shape}")
    gate = info["settings"]["gate"]
    range_m = bin_centres_range_m(gate["gate_start_s"], gate["bin_width_s"], n_bins)
    echoes_m = np.asarray(points["range_m"])[mine] if points and mine.any() else np.zeros(0)
    what.update({"frame": info.get("frame"), "n_bins": int(n_bins), "peak_j": float(values.max()),
                 "energy_j": float(values.sum()), "echo_ranges_m": [float(r) for r in echoes_m]})
    out = folder / "previews" / name
    if not out.exists():
        waveform_png(out, range_m, values, title=title, markers_m=echoes_m)
    return out, what


def show_waveform(run_path, run_name: str | None = None, **kwargs):
    """:func:`waveform_plot`, loaded as the image ``<run>.waveform`` (replacing that view).  Returns
    (image, what was plotted)."""
    path, what = waveform_plot(run_path, **kwargs)
    name = f"{run_name or Path(run_path).name}.waveform"
    img = load_image(path, name, replace=True, data=False)
    img.reload()
    return img, what
