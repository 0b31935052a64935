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


#: Speed of light (m/s), for the gated slices' gate-centre ranges.
_C_M_S = 299_792_458.0


def _strongest(energy: np.ndarray) -> tuple[int, int]:
    """(x, y) of the pixel with the most energy in ``energy`` (H, W); (0, 0) when every pixel is empty."""
    e = np.nan_to_num(np.asarray(energy, dtype=np.float64), nan=0.0)
    y, x = np.unravel_index(int(np.argmax(e)), e.shape)
    return int(x), int(y)


def _pixel(pixel_x, pixel_y, w: int, h: int, energy) -> tuple[int, int]:
    from ..core.errors import ConfigError

    if pixel_x is None or pixel_y is None or int(pixel_x) < 0 or int(pixel_y) < 0:
        sx, sy = _strongest(energy())
        x = sx if pixel_x is None or int(pixel_x) < 0 else int(pixel_x)
        y = sy if pixel_y is None or int(pixel_y) < 0 else int(pixel_y)
    else:
        x, y = int(pixel_x), int(pixel_y)
    if not 0 <= x < w:
        raise ConfigError("pixel_x", x, f"a column of the {w}×{h} receiver: 0 … {w - 1}")
    if not 0 <= y < h:
        raise ConfigError("pixel_y", y, f"a row of the {w}×{h} receiver: 0 … {h - 1}")
    return x, y


def default_pulse(cube, points: dict) -> int:
    """The scanner pulse shown by default: the one with the most echoes (a multi-echo pulse through a canopy
    when there is one), of those the one that received the most energy."""
    energy = np.asarray(cube, dtype=np.float64).sum(axis=1)
    n = len(energy)
    if points and "pulse_index" in points and len(points["pulse_index"]):
        echoes = np.bincount(np.asarray(points["pulse_index"], dtype=np.int64), minlength=n)[:n]
        most = np.flatnonzero(echoes == echoes.max())
        return int(most[np.argmax(energy[most])])
    return int(np.argmax(energy)) if n else 0


def _unit_label(info: dict, key: str, fallback: str) -> str:
    """The y axis label in the run's units (metadata.json ``units``): energy per bin or slice in J, else the unit."""
    unit = (info.get("units") or {}).get(key)
    if not unit:
        return fallback
    per = "bin" if key == "waveforms" else "slice"
    if unit in ("J", "J per bin"):
        return f"energy per {per} (J)"
    return f"signal per {per} ({unit.removesuffix(' per bin')})"


def waveform_plot(run_path, *, pixel_x: int | None = None, pixel_y: int | None = None, pulse: int | None = None,
                  frame: int | None = None) -> tuple[Path, dict]:
    """Plot one waveform of a run as a PNG in ``<run>/previews/`` (a new file; an existing plot of the same
    waveform is reused, never replaced).  Returns (png path, what was plotted).

    Image runs (flash, profiler): the waveform of pixel (``pixel_x``, ``pixel_y``); a coordinate that is None
    or negative is the strongest pixel's (most energy in its waveform) — the range profiler's one waveform.
    Gated runs (no waveforms, a stack of range slices): the pixel's slice profile, each slice's signal against
    the range of its gate's centre c/2 (delay + width/2), the pixel chosen the same way (most energy over the
    slices).  Scanner runs: pulse ``pulse``, default the pulse with the most echoes (of those the one that
    received the most energy).  The echoes detected on it are marked.  Raises LadarError when the run saved no
    waveforms (and is not gated)."""
    from ..core.errors import ConfigError
    from ..core.fileio.preview import bin_centres_range_m, waveform_png

    folder = frame_run_folder(run_path, frame)
    info = read_run_info(folder)
    wf_file = folder / "waveforms.npy"
    slices_file = folder / "slices.npy"
    points = load_points(folder / "points.npz") if (folder / "points.npz").is_file() else {}
    gated = not wf_file.is_file() and slices_file.is_file()
    if not wf_file.is_file() and not gated:
        raise LadarError(f"the run {folder} has no waveforms.npy: enable Run > Save Waveforms and simulate again")
    if gated:
        stack = np.load(slices_file, mmap_mode="r")
        if stack.ndim != 3:
            raise LadarError(f"{slices_file} has an unexpected shape {stack.shape}")
        n_bins, h, w = stack.shape
        x, y = _pixel(pixel_x, pixel_y, w, h, lambda: np.asarray(stack, dtype=np.float64).sum(axis=0))
        values = np.asarray(stack[:, y, x], dtype=np.float64)
        g = info["settings"]["gated"]
        delays = g["first_delay_s"] + g["delay_step_s"] * np.arange(n_bins)
        range_m = 0.5 * _C_M_S * (delays + 0.5 * g["gate_width_s"])
        mine = ((points.get("pixel_x", np.zeros(0)) == x) & (points.get("pixel_y", np.zeros(0)) == y)) \
            if points else np.zeros(0, bool)
        what = {"pixel_x": x, "pixel_y": y, "view": "slice profile"}
        name = f"slices_x{x:04d}_y{y:04d}.png"
        title = f"Slice profile of pixel ({x}, {y}): {n_bins} gates of {g['gate_width_s'] * 1e9:.3g} ns"
        ylabel = _unit_label(info, "slices", "signal per slice")
        xname = "n_slices"
    else:
        cube = np.load(wf_file, mmap_mode="r")
        ylabel = _unit_label(info, "waveforms", "energy per bin (J)")
        xname = "n_bins"
        if cube.ndim == 3:
            h, w, n_bins = cube.shape
            x, y = _pixel(pixel_x, pixel_y, w, h, lambda: np.asarray(cube, dtype=np.float64).sum(axis=2))
            values = np.asarray(cube[y, x], dtype=np.float64)
            mine = ((points.get("pixel_x", np.zeros(0)) == x) & (points.get("pixel_y", np.zeros(0)) == y)) \
                if points else np.zeros(0, bool)
            what = {"pixel_x": x, "pixel_y": y, "view": "range profile" if (h, w) == (1, 1) else "waveform"}
            name = f"waveform_x{x:04d}_y{y:04d}.png"
            title = "Range profile" if (h, w) == (1, 1) else f"Waveform of pixel ({x}, {y})"
        elif cube.ndim == 2:
            n_pulses, n_bins = cube.shape
            p = default_pulse(cube, points) if pulse is None or int(pulse) < 0 else int(pulse)
            if not 0 <= p < n_pulses:
                raise ConfigError("pulse", p, f"a pulse of the scan: 0 … {n_pulses - 1}")
            values = np.asarray(cube[p], dtype=np.float64)
            mine = (points.get("pulse_index", np.zeros(0)) == p) if points else np.zeros(0, bool)
            what = {"pulse": p, "view": "pulse waveform"}
            name = f"waveform_pulse{p:08d}.png"
            title = f"Waveform of pulse {p}"
        else:
            raise LadarError(f"{wf_file} has an unexpected shape {cube.shape}")
        gate = info["settings"]["gate"]
        range_m = bin_centres_range_m(gate["gate_start_s"], gate["bin_width_s"], n_bins)
    echoes_m = np.asarray(points["range_m"])[mine] if points and mine.any() else np.zeros(0)
    what.update({"frame": info.get("frame"), xname: int(n_bins), "peak_j": float(values.max()),
                 "energy_j": float(values.sum()), "echo_ranges_m": [float(r) for r in echoes_m],
                 "range_m": [float(range_m[0]), float(range_m[-1])]})
    if gated:
        what["n_bins"] = int(n_bins)  # the profile's samples, as the waveforms' bins
    out = folder / "previews" / name
    if not out.exists():
        waveform_png(out, range_m, values, title=title, ylabel=ylabel, markers_m=echoes_m)
    return out, what


def show_waveform(run_path, run_name: str | None = None, **kwargs):
    """:func:`waveform_plot`, loaded as the image ``<run>.waveform`` (replacing that view).  Returns
    (image, what was plotted)."""
    path, what = waveform_plot(run_path, **kwargs)
    name = f"{run_name or Path(run_path).name}.waveform"
    img = load_image(path, name, replace=True, data=False)
    img.reload()
    return img, what
