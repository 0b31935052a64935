"""The run folder: every product of a run written atomically next to a metadata record.

A run is assembled in a hidden sibling folder and renamed into place only when every file is complete, so a
failed or cancelled run leaves nothing behind, and an existing run is never replaced unless asked (and then only a
previous run of this tool): the run folder rules are fileio.staging's.
"""
from __future__ import annotations

import errno
import json
import math
import os
import platform
import sys
import threading
import time
import weakref
from pathlib import Path

import numpy as np

from ..constants import SPEED_OF_LIGHT_M_S
from .staging import claim_run_dir, naming
from ..version import __version__
from .las import las_run_facts, write_las

EXR_COMPRESSION = "ZIP"  # Blender reads ZIP/PIZ/RLE/NONE, not ZSTD


def write_exr(path, channels: dict, attributes: dict | None = None):
    """Write float32 channels {name: (H, W)} as one scanline EXR (ZIP compression) with header ``attributes``
    (str, float, int, (3,) or (4, 4) float arrays; :func:`exr_attributes`)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    data = {name: np.ascontiguousarray(arr, dtype=np.float32) for name, arr in channels.items()}
    shapes = {name: arr.shape for name, arr in data.items()}  # (the binding turns data's values into Channels)
    try:
        OpenEXR.File(header, data).write(str(path))
    except RuntimeError as exc:  # the binding reports every I/O failure so: an OSError like every other writer's
        raise exr_os_error(exc, path) from None
    # and some not at all: on a full disk it can leave an empty file and return (measured: a 16 × 16 image with
    # 0 bytes free); the file is read back whole, or the write failed
    try:
        with OpenEXR.File(str(path)) as f:
            whole = all(np.asarray(f.channels()[name].pixels).shape == shape for name, shape in shapes.items())
    except (RuntimeError, KeyError, OSError):
        whole = False
    if not whole:
        try:
            full = os.statvfs(Path(path).parent).f_bavail == 0
        except (OSError, AttributeError):
            full = False
        code = errno.ENOSPC if full else errno.EIO
        raise OSError(code, f"{os.strerror(code)} (the EXR file was not written whole)", str(path))


#: The C library's messages of the errors a writer meets, as OpenEXR quotes them at the end of its message.
_ERRNO_TEXTS = tuple((code, os.strerror(code)) for code in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM,
                                                             errno.ENOENT, errno.EROFS, errno.EIO, errno.EFBIG))


def exr_os_error(exc: RuntimeError, path) -> OSError:
    """An OpenEXR RuntimeError as OSError(errno, strerror, path): "Failed to write pixel data to image file
    "…/range.exr". No space left on device." → ENOSPC; a message naming no such error → EIO with OpenEXR's text."""
    text = str(exc)
    for code, strerror in _ERRNO_TEXTS:
        if strerror in text:
            return OSError(code, strerror, str(path))
    return OSError(errno.EIO, f"the EXR writer failed ({text.splitlines()[0][:200] if text else 'no reason'})",
                   str(path))


def exr_attributes(metadata: dict, product: str, unit: str, **more) -> dict:
    """EXR header attributes of a run's image: what it shows and its unit (``product``, ``units``), the run's
    system and frame, and the sensor pose — the standard ``worldToCamera`` (M44f, Imath's row-vector convention:
    p_camera = p_world · M, i.e. the transpose of the camera-from-world matrix; camera +X right, +Y up, looking
    along −Z) and ``ladarWorldFromSensor`` (M44d, column vectors, the matrix of metadata.json's ``sensor_pose``)
    with ``ladarSensorPosition_m`` (V3d).  ``more``: further attributes (the gated slices' gate delay)."""
    attrs = {"product": product, "units": unit, "ladarSystem": str(metadata.get("system_type", "")),
             "ladarFrame": int(metadata.get("frame", 0) or 0)}
    pose = metadata.get("sensor_pose")
    if pose:
        m = np.asarray(pose["world_from_sensor"], dtype=np.float64)
        # contiguous copies: the OpenEXR binding reads an array's buffer in C order whatever its strides
        attrs["worldToCamera"] = np.ascontiguousarray(np.linalg.inv(m).T, dtype=np.float32)
        attrs["ladarWorldFromSensor"] = m
        attrs["ladarSensorPosition_m"] = np.asarray(pose["position_m"], dtype=np.float64)
    attrs.update(more)
    return attrs


def read_exr_header(path) -> dict:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return dict(f.header())


def read_exr(path) -> dict:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return {name: np.array(ch.pixels) for name, ch in f.channels().items()}


#: PLY property types every common client reads (Open3D 0.20 skips short, ushort, char and uint properties;
#: CloudCompare, plyfile, trimesh and Blender read all of these): doubles, floats, 32-bit ints and uchar.
_PLY_TYPES = {np.dtype(np.float64): "double", np.dtype(np.float32): "float", np.dtype(np.int32): "int",
              np.dtype(np.uint8): "uchar"}
_PLY_INVERSE = {"double": "<f8", "float": "<f4", "int": "<i4", "short": "<i2", "uchar": "u1", "char": "i1",
                "ushort": "<u2", "uint": "<u4"}
#: SI prefixes in ASCII (a PLY header is ASCII): "u" for micro.
_SI_PREFIXES = {0: "", -3: "m", -6: "u", -9: "n", -12: "p", -15: "f", -18: "a", -21: "z", -24: "y", -27: "r",
                -30: "q"}


def _ply_column(arr: np.ndarray) -> np.ndarray:
    """A 1-D attribute in a type of :data:`_PLY_TYPES`: other integers (int16 …) as int32, bool as uchar,
    half floats as float."""
    if arr.dtype in _PLY_TYPES:
        return arr
    if arr.dtype == np.bool_:
        return arr.astype(np.uint8)
    if arr.dtype.kind in "iu":
        return arr.astype(np.int32)
    return arr.astype(np.float32)


def ply_intensity_scale(intensity, unit: str | None = None) -> tuple[float, str]:
    """The power of ten (10^(3k), k ≤ 0) the PLY's ``intensity`` is stored in, so that its smallest positive
    value is at least 1 (clients printing 6 decimals show no zeros), and the stored unit (``unit`` with its SI
    prefix, e.g. "aJ per bin" for 1e-18 of "J per bin").  1 when the smallest positive value is already ≥ 1."""
    v = np.abs(np.asarray(intensity, dtype=np.float64))
    v = v[np.isfinite(v) & (v > 0)]
    k = 0 if v.size == 0 or v.min() >= 1.0 else max(-30, 3 * math.floor(math.log10(v.min()) / 3))
    scale = float(f"1e{k}")
    unit = unit or ""
    if unit.startswith("J") and k in _SI_PREFIXES:
        stored = _SI_PREFIXES[k] + unit
    else:
        stored = (f"{scale:g} " if k else "") + unit
    return scale, stored.strip()


def write_ply(path, points: dict, intensity_unit: str | None = None) -> dict:
    """Binary little-endian PLY: x, y, z (world, double) and every 1-D per-point attribute, in types every common
    client reads (:data:`_PLY_TYPES`); ``intensity`` stored divided by :func:`ply_intensity_scale` (stated in the
    header's comments ``intensity_scale`` and ``intensity_unit``).  Returns {"intensity_scale", "intensity_unit"}."""
    pos = points["position_world"]
    fields = [("x", pos[:, 0]), ("y", pos[:, 1]), ("z", pos[:, 2])]
    scale, stored_unit = 1.0, intensity_unit or ""
    if "intensity" in points:
        scale, stored_unit = ply_intensity_scale(points["intensity"], intensity_unit)
    for name, arr in points.items():
        if arr.ndim == 1:
            col = _ply_column(arr)
            if name == "intensity" and scale != 1.0:
                col = (col / scale).astype(col.dtype)
            fields.append((name, col))
    dtype = np.dtype([(n, a.dtype.newbyteorder("<")) for n, a in fields])
    table = np.empty(len(pos), dtype=dtype)
    for n, a in fields:
        table[n] = a
    header = ["ply", "format binary_little_endian 1.0", "comment ladar simulator point cloud",
              f"comment intensity_scale {scale:g}",
              f"comment intensity_unit {stored_unit or 'none'} (intensity x {scale:g} = the run's intensity"
              + (f" in {intensity_unit})" if intensity_unit else ")"),
              f"element vertex {len(pos)}"]
    header += [f"property {_PLY_TYPES[np.dtype(a.dtype)]} {n}" for n, a in fields]
    header.append("end_header")
    with naming(path), open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii", errors="replace"))
        f.write(table.tobytes())
    return {"intensity_scale": scale, "intensity_unit": stored_unit}


def read_ply(path, *, raw: bool = False) -> dict:
    """Read a PLY written by :func:`write_ply` (binary little-endian vertices only).  ``intensity`` is returned in
    the run's unit (the stored values times the header's ``intensity_scale``) unless ``raw``."""
    with open(path, "rb") as f:
        names, types, n, scale = [], [], 0, 1.0
        while True:
            line = f.readline().decode("utf-8").strip()
            if line.startswith("element vertex"):
                n = int(line.split()[-1])
            elif line.startswith("comment intensity_scale"):
                scale = float(line.split()[-1])
            elif line.startswith("property"):
                _, t, name = line.split()
                names.append(name)
                types.append(_PLY_INVERSE[t])
            elif line == "end_header":
                break
        table = np.frombuffer(f.read(), dtype=np.dtype(list(zip(names, types))), count=n)
    out = {name: table[name] for name in names}
    if "intensity" in out and scale != 1.0 and not raw:
        out["intensity"] = out["intensity"] * out["intensity"].dtype.type(scale)
    return out


def software_versions() -> dict:
    versions = {"python": platform.python_version(), "numpy": np.__version__, "platform": platform.platform()}
    for mod in ("scipy", "embreex", "OpenEXR"):
        try:
            versions[mod] = getattr(__import__(mod), "__version__", "unknown")
        except ImportError:  # pragma: no cover - all are requirements
            versions[mod] = "missing"
    versions["ladar_core"] = __version__
    if "bpy" in sys.modules:
        versions["blender"] = sys.modules["bpy"].app.version_string
    return versions


class ProductFiles:
    """The large arrays of a run filled in place in their ``.npy`` files of the run folder being built (a claim's
    work folder), instead of in memory and then copied out by ``np.save``.

    :meth:`zeros` gives a zero-filled array mapped onto ``<folder>/<name>`` (``np.lib.format.open_memmap``: the
    same header and bytes ``np.save`` writes), its blocks reserved on the disk first (``posix_fallocate``: a full
    disk is an OSError naming the file before the run fills it, never a SIGBUS while filling); without a folder,
    or where ``posix_fallocate`` or shared mappings of a folder being renamed are not available (not POSIX), an
    array in memory as before.  :func:`write_run_files` then writes nothing more for such an array.

    Why: the airborne-scanner example's saved waveforms are 267 MB; built in memory and saved they cost that much
    fresh memory twice over (the array's, then the file's page cache) and a copy: ``write_run_files`` took
    1.9 s wall / 0.48 s CPU of that command before, 0.27 s / 0.06 s now (docs/performance.md, "Writing the
    scanner's products")."""

    def __init__(self, folder=None):
        self.folder = None if folder is None else Path(folder)

    @property
    def maps_files(self) -> bool:
        return self.folder is not None and os.name == "posix" and hasattr(os, "posix_fallocate")

    def zeros(self, name: str, shape, dtype) -> np.ndarray:
        """A zero-filled C-ordered array of ``shape`` and ``dtype``: mapped onto ``<folder>/<name>`` (created, with
        the folder) when :attr:`maps_files`, else in memory."""
        if not self.maps_files:
            return np.zeros(shape, dtype)
        self.folder.mkdir(exist_ok=True)
        path = self.folder / name
        try:
            with naming(path):
                arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.dtype(dtype), shape=tuple(shape))
                fd = os.open(path, os.O_RDWR)
                try:
                    os.posix_fallocate(fd, 0, arr.offset + arr.nbytes)
                finally:
                    os.close(fd)
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        with _MAPPED_LOCK:
            _MAPPED[os.path.abspath(path)] = arr
        return arr


def _mapped_onto(arr, path: Path) -> bool:
    """Is ``arr`` the very array :meth:`ProductFiles.zeros` mapped onto ``path`` (the file already holds it)?"""
    with _MAPPED_LOCK:
        return arr is not None and _MAPPED.get(os.path.abspath(path)) is arr


def _maps_into(folder: Path) -> bool:
    """Has :meth:`ProductFiles.zeros` mapped a living array onto a file in ``folder``?"""
    folder = os.path.abspath(folder)
    with _MAPPED_LOCK:
        return any(os.path.dirname(k) == folder for k in list(_MAPPED.keys()))


#: path → the array ProductFiles.zeros mapped onto it, while it lives (runs on several threads: under the lock).
_MAPPED: "weakref.WeakValueDictionary[str, np.ndarray]" = weakref.WeakValueDictionary()
_MAPPED_LOCK = threading.Lock()


def write_run(out_dir, result, metadata: dict, *, overwrite: bool = False) -> Path:
    """Write a FrameResult's products and ``metadata.json`` atomically into run folder ``out_dir``.

    ``overwrite`` replaces a previous run of this tool in ``out_dir`` (nothing else: fileio.staging)."""
    with claim_run_dir(out_dir, if_exists="replace" if overwrite else "stop") as claim:
        write_run_files(claim.work, result, metadata)
        return claim.commit()


def write_run_files(folder, result, metadata: dict) -> Path:
    """Write a FrameResult's products and ``metadata.json`` into the new folder ``folder`` (a claim's work
    folder: nothing else sees it until it is committed)."""
    tmp = Path(folder)
    # new, unless ProductFiles made it for the arrays mapped onto its files
    tmp.mkdir(exist_ok=_maps_into(tmp))
    t0 = time.perf_counter()
    units = result.units
    files = {}
    if result.range_image is not None:
        gated = getattr(result, "slices", None) is not None
        what = {"range": "range from the slice stack" if gated else "first-echo range",
                "intensity": "strongest slice" if gated else "first-echo peak amplitude",
                "energy": "energy received per pixel before time binning"}
        for product, image in (("range", result.range_image), ("intensity", result.intensity_image),
                               ("energy", result.energy_image)):
            write_exr(tmp / f"{product}.exr", {"Y": image},
                      exr_attributes(metadata, what[product], units[product]))
        files.update({"range.exr": f"{what['range']} ({units['range']}), NaN where none; row 0 = top",
                      "intensity.exr": f"{what['intensity']} ({units['intensity']})",
                      "energy.exr": f"{what['energy']} ({units['energy']})"})
    ply = write_ply(tmp / "points.ply", result.points, units.get("intensity"))
    with naming(tmp / "points.npz"):
        np.savez(tmp / "points.npz", **result.points)
    files["points.ply"] = (f"point cloud, world coordinates + per-point attributes (intensity in "
                           f"{ply['intensity_unit']}: × {ply['intensity_scale']:g})")
    files["points.npz"] = "the same point cloud as NumPy arrays"
    if len(result.points.get("range_m", ())):
        write_las(tmp / "points.las", result.points, **las_run_facts(dict(metadata, units=units)))
        files["points.las"] = ("the point cloud as LAS 1.4 (point format 6, world coordinates, GPS time, "
                               "scan angle, classes from the scene's materials, synthetic flag)")
    if result.range_echoes is not None:
        with naming(tmp / "echoes.npz"):
            np.savez(tmp / "echoes.npz", range_m=result.range_echoes, intensity=result.intensity_echoes)
        files["echoes.npz"] = "range_m and intensity (H, W, max_echoes), echoes in time order, NaN/0 if none"
    if getattr(result, "digital_waveforms", None) is not None:
        with naming(tmp / "counts.npy"):
            np.save(tmp / "counts.npy", result.digital_waveforms)
        files["counts.npy"] = f"receiver output per pixel and bin ({units['counts']})"
    if result.waveforms is not None:
        if not _mapped_onto(result.waveforms, tmp / "waveforms.npy"):  # (else filled in place: ProductFiles)
            with naming(tmp / "waveforms.npy"):
                np.save(tmp / "waveforms.npy", result.waveforms)
        files["waveforms.npy"] = ("waveforms (n_pulses, n_bins)" if result.waveforms.ndim == 2
                                  else "waveform cube (H, W, n_bins)") + f" float32, {units['waveforms']}"
    if getattr(result, "pulses", None) is not None:
        with naming(tmp / "pulses.npz"):
            np.savez(tmp / "pulses.npz", **result.pulses)
        files["pulses.npz"] = "every pulse fired (also those without an echo): time, pose, direction, energy"
    if getattr(result, "slices", None) is not None:
        (tmp / "slices").mkdir()
        gate_s = float(metadata["settings"]["gated"]["gate_width_s"]) if "settings" in metadata else None
        for k, img in enumerate(result.slices):
            delay = float(result.slice_delays_s[k])
            more = {"ladarSlice": k + 1, "ladarGateDelay_s": delay,
                    "ladarGateRange_m": 0.5 * SPEED_OF_LIGHT_M_S * delay}
            if gate_s is not None:
                more["ladarGateWidth_s"] = gate_s
            write_exr(tmp / "slices" / f"slice_{k + 1:04d}.exr", {"Y": img},
                      exr_attributes(metadata, f"gated slice {k + 1} of {len(result.slices)}",
                                     f"{units['slices']} per pixel", **more))
        with naming(tmp / "slices.npy"):
            np.save(tmp / "slices.npy", result.slices)
        files["slices/slice_NNNN.exr"] = f"gated slices as an image sequence ({units['slices']} per pixel), 1-based"
        files["slices.npy"] = f"gated slices (n_slices, H, W) float32, {units['slices']} per pixel"
    if metadata.get("system_type") == "profiler" and result.waveforms is not None:
        _write_profile_csv(tmp / "profile.csv", result.waveforms.reshape(-1), metadata)
        files["profile.csv"] = "the range profile: time_s, range_m, energy_j per bin"
    meta = dict(metadata)
    meta["units"] = dict(units)
    meta["files"] = files
    meta["ply"] = ply
    meta.setdefault("stage_times_s", {})["write"] = time.perf_counter() - t0
    with naming(tmp / "metadata.json"), open(tmp / "metadata.json", "w", encoding="utf-8") as f:
        json.dump(meta, f, indent=2, default=json_default)
    return tmp


def _write_profile_csv(path, waveform, metadata):
    gate = metadata["settings"]["gate"]
    t = gate["gate_start_s"] + (np.arange(len(waveform)) + 0.5) * gate["bin_width_s"]
    table = np.column_stack([t, 0.5 * SPEED_OF_LIGHT_M_S * t, waveform])
    with naming(path):
        np.savetxt(path, table, delimiter=",", header="time_s,range_m,energy_j", comments="", fmt="%.10g")


def json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


#: SI prefixes of energies and times as people read them (µ for micro; the PLY header's ASCII ones:
#: :data:`_SI_PREFIXES`).
DISPLAY_PREFIXES = {0: "", -3: "m", -6: "\u00b5", -9: "n", -12: "p", -15: "f", -18: "a", -21: "z", -24: "y"}


def display_prefix(magnitude: float) -> int:
    """The power of ten (a multiple of 3 in [-24, 0]) that puts ``magnitude`` (> 0) in [1, 1000)."""
    return min(0, max(min(DISPLAY_PREFIXES), 3 * math.floor(math.log10(magnitude) / 3)))


def format_si(value: float, unit: str) -> str:
    """A value of an SI ``unit`` ("J", "s") on the prefix that puts it in [1, 1000), 4 significant digits:
    "667.7 fJ", "13.24 µs", "100 mJ", "0 J" (at most the unit itself: "1500 s")."""
    v = float(value)
    if v == 0.0 or not math.isfinite(v):
        return f"{v:g} {unit}"
    k = display_prefix(abs(v))
    if k < 0 and abs(float(f"{v / float(f'1e{k}'):.4g}")) >= 1000.0:  # 999.96 fJ rounds to 1 pJ, not "1000 fJ"
        k += 3
    return f"{v / float(f'1e{k}'):.4g} {DISPLAY_PREFIXES[k]}{unit}"


def format_energy_j(joules: float) -> str:
    """An energy on the SI prefix that puts it in [1, 1000): "667.7 fJ", "1.094 pJ", "49.19 nJ", "0 J" (issue 27:
    "6.677e-13 J" is not a unit a person reads)."""
    return format_si(joules, "J")


def _range(values) -> list | None:
    return [float(np.min(values)), float(np.max(values))] if len(values) else None


def run_figures(result) -> dict:
    """What one run (or one frame of a sequence) saw, as the terminal summary and Blender's report print it:
    points, cells with an echo, false alarms, returns of the atmosphere, the SNR ranges, the energy received and
    the range gate's coverage in absolute sub-rays and joules (so frames add up: :func:`combine_figures`)."""
    st, pts = result.stats, result.points
    pulsed = "n_pulses" in st
    image = getattr(result, "range_image", None)
    fig = {"frames": 1, "unit": "pulses" if pulsed else "pixels",
           "cells": int(st["n_pulses"]) if pulsed else (int(image.size) if image is not None else 1),
           "points": int(len(pts["range_m"])), "points_per_frame": [int(len(pts["range_m"]))] * 2,
           "range_m": _range(pts["range_m"]), "received_energy_j": float(st["received_energy_j"])}
    if fig["points"]:
        first = pts["echo_index"] == 1
        fig["with_echo"] = int(first.sum())
        fig["with_several"] = int((pts["n_echoes"][first] > 1).sum())
    else:
        fig["with_echo"] = fig["with_several"] = 0
    fa, snr, atm = pts.get("false_alarm"), pts.get("snr"), pts.get("atmosphere")
    fig["false_alarms"] = None if fa is None else int(np.count_nonzero(fa))
    fig["false_alarms_per_frame"] = None if fa is None else [fig["false_alarms"]] * 2
    fig["ideal"] = fa is None and snr is None
    if atm is not None:
        fig["atmosphere"] = int(np.count_nonzero(atm))
        fig["weather"] = st["weather"]["model"]["condition"] if "weather" in st else None
    if snr is not None:
        fig["snr_true"] = _range(snr[fa == 0] if fa is not None else snr)
        fig["snr_false"] = _range(snr[fa != 0]) if fa is not None else None
    cov = st.get("gate_coverage")
    if cov and cov.get("hit_subrays"):
        n, e = cov["hit_subrays"], cov["hit_energy_j"]
        fig["coverage"] = {"gate_range_m": list(cov["gate_range_m"]), "hit_range_m": list(cov["hit_range_m"]),
                           "subrays": {k: v * n for k, v in cov["subray_fraction"].items()},
                           "energy_j": {k: v * e for k, v in cov["energy_fraction"].items()}}
    return fig


def _merge_range(a, b):
    return b if a is None else a if b is None else [min(a[0], b[0]), max(a[1], b[1])]


def combine_figures(figures: list[dict]) -> dict:
    """The figures of a sequence from its frames' (:func:`run_figures`): counts, cells and energies summed, value
    ranges (range, SNR, the hits' range) from the smallest to the largest, points and false alarms per frame from
    the fewest to the most, the gate's coverage from the summed sub-rays and joules."""
    out = None
    for f in figures:
        if out is None:
            out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in f.items()}
            if "coverage" in f:
                out["coverage"] = {k: (dict(v) if isinstance(v, dict) else list(v)) for k, v in f["coverage"].items()}
            continue
        for k in ("frames", "cells", "points", "with_echo", "with_several", "received_energy_j", "atmosphere"):
            if k in f:
                out[k] = out.get(k, 0) + f[k]
        for k in ("false_alarms",):
            if f.get(k) is not None:
                out[k] = (out.get(k) or 0) + f[k]
        for k in ("points_per_frame", "false_alarms_per_frame", "range_m", "snr_true", "snr_false"):
            if k in out or k in f:  # (an ideal receiver's frames have no SNR at all)
                out[k] = _merge_range(out.get(k), f.get(k))
        out["ideal"] = out.get("ideal", True) and f["ideal"]
        if "coverage" in f:
            c = out.setdefault("coverage", {"gate_range_m": list(f["coverage"]["gate_range_m"]), "hit_range_m": None,
                                            "subrays": dict.fromkeys(f["coverage"]["subrays"], 0.0),
                                            "energy_j": dict.fromkeys(f["coverage"]["energy_j"], 0.0)})
            c["hit_range_m"] = _merge_range(c["hit_range_m"], f["coverage"]["hit_range_m"])
            for part in ("subrays", "energy_j"):
                for k, v in f["coverage"][part].items():
                    c[part][k] += v
    return out or {}


def figure_lines(fig: dict) -> list[str]:
    """The summary's lines of what was seen (``run_figures`` of a run, ``combine_figures`` of a sequence's frames:
    a sequence's counts are totals over its frames, with the fewest and most per frame)."""
    lines, unit, frames = [], fig["unit"], fig["frames"]
    per = unit[:-1] + (" and frame" if frames > 1 else "")
    if fig["points"]:
        lo, hi = fig["points_per_frame"]
        each = f" ({lo} – {hi} per frame)" if frames > 1 else ""
        lines.append(f"echoes   {fig['points']} points{each}, {fig['with_echo']} {unit} with an echo, "
                     f"{fig['with_several']} with several; range "
                     f"{fig['range_m'][0]:.3f} – {fig['range_m'][1]:.3f} m")
    else:
        lines.append("echoes   none detected")
    n_fa = fig.get("false_alarms")
    if n_fa is not None:
        lo, hi = fig["false_alarms_per_frame"]
        each = f", {lo} – {hi} per frame" if frames > 1 else ""
        lines.append(f"false    {n_fa} false alarms of {fig['points']} points ({n_fa / max(fig['cells'], 1):.3g} "
                     f"per {per}{each}; {fig['points'] - n_fa} true returns)")
    if "atmosphere" in fig:
        n_atm = fig["atmosphere"]
        lines.append(f"weather  {n_atm} returns of the atmosphere of {fig['points']} points ({fig['weather']}"
                     f"; LAS class 18, withheld)" if fig.get("weather") else
                     f"weather  {n_atm} returns of the atmosphere")
    if fig["ideal"]:
        lines.append("false    none possible: ideal receiver (detector.mode = ideal: no noise, so no SNR either)")
    if "snr_true" in fig and fig["points"]:
        t, f = fig["snr_true"], fig.get("snr_false")
        part = [f"true returns {t[0]:.3g} – {t[1]:.3g}" if t else "no true return"]
        if f:
            part.append(f"false alarms {f[0]:.3g} – {f[1]:.3g}")
        lines.append("snr      " + "; ".join(part))
    lines.append(f"energy   {format_energy_j(fig['received_energy_j'])} at the aperture from every hit sub-ray "
                 "(before the range gate and time binning)" + (f", summed over {frames} frames" if frames > 1 else ""))
    cov = fig.get("coverage")
    if cov:
        n, e = sum(cov["subrays"].values()), sum(cov["energy_j"].values())
        ef = {k: (v / e if e > 0 else 0.0) for k, v in cov["energy_j"].items()}
        sf = {k: (v / n if n > 0 else 0.0) for k, v in cov["subrays"].items()}
        g0, g1 = cov["gate_range_m"]
        h0, h1 = cov["hit_range_m"]
        lines.append(f"gate     {g0:.1f} – {g1:.1f} m holds {100 * ef['inside']:.1f} % of the hit energy "
                     f"({100 * ef['before']:.1f} % before, {100 * ef['after']:.1f} % after) and "
                     f"{100 * sf['inside']:.1f} % of the hit sub-rays; hits at {h0:.1f} – {h1:.1f} m"
                     + (f" (all {frames} frames)" if frames > 1 else ""))
    return lines


def run_summary(run_path, result) -> str:
    """A few lines a person reads after a run: what was seen (points, false alarms, SNR), how much of what the
    rays hit the range gate covers (with a warning below 90 %), what ran, what was skipped, where it went."""
    st = result.stats
    lines = [f"run      {run_path}"]
    if "n_pulses" in st:
        lines.append(f"pulses   {st['n_pulses']} fired ({st['subrays_per_pulse']} sub-rays each) over "
                     f"{st['scan_duration_s']:.3g} s, {st['pulses_without_echo']} without an echo")
    lines.append(f"rays     {st['n_rays']} traced, {st['n_hits']} hits on {st['n_triangles']} triangles "
                 f"({st['threads']} threads, {st['wall_time_s']:.2f} s)")
    if getattr(result, "slices", None) is not None:
        d = np.asarray(st["slice_delays_s"])
        lines.append(f"slices   {len(d)} gates, delays {d[0] * 1e9:.1f} – {d[-1] * 1e9:.1f} ns; range by "
                     f"{st['range_method']}")
    lines += figure_lines(run_figures(result))
    times = ", ".join(f"{k} {v:.3f}" for k, v in st["stage_times_s"].items() if v >= 5e-4)
    lines.append(f"stages   {times} (s, summed over threads; without loading or compiling kernels)")
    k = st.get("kernels")
    if k and (k["loaded"] or k["compiled"]):
        lines.append(f"kernels  {k['loaded']} loaded from the cache, {k['compiled']} compiled: "
                     f"{k['load_and_compile_s']:.2f} s (not in the stage times"
                     + ("; compiled once per install and CPU)" if k["compiled"] else ")"))
    if st.get("stages_skipped"):
        lines.append("skipped  " + "; ".join(f"{k} ({v})" for k, v in st["stages_skipped"].items()))
    for w in run_warnings(st):
        lines.append("WARNING  " + w)
    return "\n".join(lines)


def run_warnings(stats: dict) -> list[str]:
    """The warnings a person must see after a run (one line each): today the range gate's coverage."""
    cov = stats.get("gate_coverage") or {}
    return [f"range gate: {cov['warning']}"] if cov.get("warning") else []
