"""LAS 1.4 point clouds (ASPRS LAS Specification 1.4-R15), NumPy only: :func:`write_las` and :func:`read_las`.

What a ladar point cloud becomes (point data record format 6, 30 bytes, plus extra bytes):

==========================  ===================================================================================
LAS field                   from the simulator's point arrays (``FrameResult.points``)
==========================  ===================================================================================
X, Y, Z (int32, scaled)     ``position_world`` (m; or ``position_sensor``), X = round((x − offset)/scale)
Intensity (uint16)          ``intensity`` on a fixed scale (the same in every run, so files compare), chosen by
                            the intensity's unit (``intensity_unit``): energies (``J``, ``J per bin``):
                            round(65535 · log10(I / 1e-21 J) / 18), i.e. 1e-21 J → 0 … 1e-3 J → 65535
                            (3641 steps per decade, 0.063 % apart), I ≤ 1e-21 J → 0; receiver outputs
                            (``counts``, ``electrons``, ``detections``): round(I), clipped to [0, 65535].
                            The scale is stored in the LadarSimulator VLR, the unscaled value in the extra
                            dimension ``intensity_raw``
Return Number (4 bits)      ``echo_index`` (1 = first echo in time); values above 15 are clipped to 15
Number of Returns (4 bits)  ``n_echoes``, clipped to [return number, 15]
GPS Time (double)           ``gps_time_s`` (scanner: the pulse's emission time); points without it (flash,
                            gated and profiler frames) all get ``frame_time_s`` (default 0)
Point Source ID (uint16)    ``frame`` (clipped to 0…65535), else 0
Scan Angle (int16)          the pulse's scan angle in 0.006° steps (``scan_angle_rad``: the scanner's across-scan
                            angle, or azimuth for the rotating head and palmer), else the horizontal angle of the
                            point's line of sight in the sensor frame, atan2(x, −z) of ``position_sensor``
                            (a flash pixel's column angle); positive towards the sensor's +X (right)
Classification              ground truth from the scene (``material_id``, core/geometry/groundtruth.py): material k of
                            the scene → class 64 + k (user-definable classes; the names are in the
                            LadarSimulator VLR ``classes``), no scene surface near the point → 1 (unclassified),
                            a receiver false alarm (``false_alarm``) → 7 (noise), a return of the atmosphere
                            itself (``atmosphere``: fog, rain, snow; core/engine/weather_stage.py) → 18 (high
                            noise); 0 (never classified) for points without ``material_id``
Classification flags        synthetic (bit 0) on every point (the points are simulated); withheld (bit 2) on
                            false alarms and atmosphere returns
extra bytes                 ``intensity_raw`` (float32, the simulator's intensity in ``intensity_unit``),
                            ``range_m`` (float64) and ``snr`` (float32) where the points have them
==========================  ===================================================================================

Scale and offset: the offset is the centre of the bounding box rounded to whole metres; the scale (the same on
all axes) is 0.1 mm when every coordinate lies within ±200 km of the offset, else 1 mm (up to ±2000 km; beyond:
ConfigError).  The rounding error per axis is ≤ scale/2, so a point moves by at most √3·scale/2 = 0.087 mm
(0.87 mm) and its range by no more than that: the range precision is ≤ 1 mm.

The header follows the spec's byte layout (:data:`HEADER_FIELDS`): version 1.4, header size 375, legacy point
counts 0 (required for formats 6–10), 64-bit point count and points by return (15), bounds of the stored
(quantized) coordinates.  Global encoding sets bit 4 (WKT; required for formats 6–10) and leaves bit 0 clear
(GPS week time: the simulator's times are seconds from the run's time origin, not adjusted standard GPS time).
VLRs: an OGC WKT1 coordinate system (LASF_Projection 2112: the Blender world as a local engineering frame in
metres, :data:`LOCAL_WKT`), the extra-bytes descriptors (LASF_Spec 4) and a JSON record (LadarSimulator 1) with
the intensity scale, the class names and the run's facts.  The WKT names two axes (X east, Y north; Z is the
height in the same unit, as with a horizontal CRS): PROJ before 9.4, which PDAL and GDAL use, rejects a
LOCAL_CS with three axes ("buildCS: unexpected AXIS count for LOCAL_CS"), so the file would not translate.  The file is written to a temporary sibling and renamed into place (never half a file); an existing
file is replaced only with ``overwrite=True``.
"""
from __future__ import annotations

import datetime as _dt
import json
import struct
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .staging import write_file_atomically
from ..version import __version__

LAS_VERSION = (1, 4)
HEADER_SIZE = 375
POINT_FORMAT = 6
POINT_FORMAT_6_LENGTH = 30
VLR_HEADER_SIZE = 54
EXTRA_BYTES_DESCRIPTOR_SIZE = 192
INTENSITY_MAX = 65535
GLOBAL_ENCODING_WKT = 1 << 4

#: (name, struct format, byte offset) of the LAS 1.4 public header block (spec Table 3), little-endian.
HEADER_FIELDS = (
    ("file_signature", "4s", 0), ("file_source_id", "H", 4), ("global_encoding", "H", 6),
    ("project_id", "16s", 8), ("version_major", "B", 24), ("version_minor", "B", 25),
    ("system_identifier", "32s", 26), ("generating_software", "32s", 58), ("creation_day_of_year", "H", 90),
    ("creation_year", "H", 92), ("header_size", "H", 94), ("offset_to_point_data", "I", 96),
    ("number_of_vlrs", "I", 100), ("point_data_format", "B", 104), ("point_data_record_length", "H", 105),
    ("legacy_point_count", "I", 107), ("legacy_points_by_return", "5I", 111),
    ("x_scale", "d", 131), ("y_scale", "d", 139), ("z_scale", "d", 147),
    ("x_offset", "d", 155), ("y_offset", "d", 163), ("z_offset", "d", 171),
    ("max_x", "d", 179), ("min_x", "d", 187), ("max_y", "d", 195), ("min_y", "d", 203),
    ("max_z", "d", 211), ("min_z", "d", 219), ("start_of_waveform_data", "Q", 227), ("start_of_first_evlr", "Q", 235),
    ("number_of_evlrs", "I", 243), ("point_count", "Q", 247), ("points_by_return", "15Q", 255),
)
HEADER_STRUCT = struct.Struct("<" + "".join(fmt for _, fmt, _ in HEADER_FIELDS))
assert HEADER_STRUCT.size == HEADER_SIZE

#: Point data record format 6 (spec Table 14) as a NumPy dtype (30 bytes, packed, little-endian).
POINT_FORMAT_6_DTYPE = np.dtype([
    ("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2"), ("return_byte", "u1"), ("flags_byte", "u1"),
    ("classification", "u1"), ("user_data", "u1"), ("scan_angle", "<i2"), ("point_source_id", "<u2"),
    ("gps_time", "<f8")])
assert POINT_FORMAT_6_DTYPE.itemsize == POINT_FORMAT_6_LENGTH

#: Extra-bytes data types (spec Table 24): code → dtype.
_EXTRA_TYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8", 9: "<f4", 10: "<f8"}
_EXTRA_CODES = {np.dtype(v): k for k, v in _EXTRA_TYPES.items()}
#: Extra dimensions written when the points have them: point key → (LAS name, dtype, description).
EXTRA_DIMENSIONS = {
    "intensity": ("intensity_raw", np.float32, "simulated intensity (J/bin|counts)"),
    "range_m": ("range_m", np.float64, "range from the sensor (m)"),
    "snr": ("snr", np.float32, "detection SNR"),
}

#: The Blender world as a WKT1 local (engineering) coordinate system in metres: two axes (module docstring).
LOCAL_WKT = ('LOCAL_CS["Ladar Simulator world (Blender world coordinates, metres)",'
             'LOCAL_DATUM["Blender scene",0],UNIT["metre",1],AXIS["X",EAST],AXIS["Y",NORTH]]')

#: Fixed intensity scales (module docstring): energies on a log scale, receiver outputs as they are.
ENERGY_UNITS = ("J", "J per bin")
COUNT_UNITS = ("counts", "electrons", "detections")
LOG_INTENSITY_FLOOR_J = 1e-21
LOG_INTENSITY_DECADES = 18.0
SCAN_ANGLE_STEP_DEG = 0.006
#: Classes written (LAS 1.4 Table 17 and the user-definable range 64–255).
CLASS_UNCLASSIFIED = 1
CLASS_NOISE = 7
#: LAS 1.4 class 18 "high noise": a return of the atmosphere itself (fog, rain, snow; ``points["atmosphere"]``)
CLASS_ATMOSPHERE = 18
CLASS_FIRST_MATERIAL = 64
FLAG_SYNTHETIC = 1 << 0
FLAG_WITHHELD = 1 << 2


def las_intensity(intensity: np.ndarray, unit: str) -> np.ndarray:
    """The LAS intensity (uint16) of simulator intensities in ``unit`` on the fixed scale of the module
    docstring."""
    i = np.asarray(intensity, dtype=np.float64)
    if unit in ENERGY_UNITS:
        with np.errstate(divide="ignore", invalid="ignore"):
            decades = np.log10(np.maximum(i, LOG_INTENSITY_FLOOR_J) / LOG_INTENSITY_FLOOR_J)
        scaled = INTENSITY_MAX * decades / LOG_INTENSITY_DECADES
    elif unit in COUNT_UNITS:
        scaled = i
    else:
        raise ConfigError("intensity_unit", unit, "one of " + ", ".join(ENERGY_UNITS + COUNT_UNITS))
    return np.clip(np.round(scaled), 0, INTENSITY_MAX).astype(np.uint16)


def intensity_scale_description(unit: str) -> str:
    if unit in ENERGY_UNITS:
        return (f"LAS intensity = round(65535 * log10(I / {LOG_INTENSITY_FLOOR_J:g} J) / {LOG_INTENSITY_DECADES:g}),"
                f" clipped to [0, 65535] (I in {unit}; {LOG_INTENSITY_FLOOR_J:g} J -> 0, 1e-3 J -> 65535)")
    return f"LAS intensity = round(I), clipped to [0, 65535] (I in {unit})"


def las_scan_angle(points: dict, n: int) -> np.ndarray:
    """Scan angle (int16, 0.006° steps) of each point (module docstring)."""
    if "scan_angle_rad" in points and np.asarray(points["scan_angle_rad"]).shape == (n,):
        angle = np.asarray(points["scan_angle_rad"], dtype=np.float64)
    elif "position_sensor" in points and np.asarray(points["position_sensor"]).shape == (n, 3):
        ps = np.asarray(points["position_sensor"], dtype=np.float64)
        angle = np.arctan2(ps[:, 0], -ps[:, 2])
    else:
        return np.zeros(n, np.int16)
    if not np.all(np.isfinite(angle)):
        raise ConfigError("points.scan_angle_rad", "non-finite values", "finite angles (rad)")
    angle = (angle + np.pi) % (2 * np.pi) - np.pi  # (−180°, 180°]
    return np.clip(np.round(np.degrees(angle) / SCAN_ANGLE_STEP_DEG), -30000, 30000).astype(np.int16)


def las_classes(points: dict, n: int, class_names=()) -> tuple[np.ndarray, np.ndarray, dict]:
    """(classification uint8, flags uint8, {class: meaning}) of the points (module docstring)."""
    classification = np.zeros(n, np.uint8)
    flags = np.full(n, FLAG_SYNTHETIC, np.uint8)
    meanings = {}
    if "material_id" in points:
        mid = np.asarray(points["material_id"]).astype(np.int64)
        if mid.shape != (n,):
            raise ConfigError("points.material_id", mid.shape, f"one value per point ({n},)")
        known = (mid >= 0) & (mid < 256 - CLASS_FIRST_MATERIAL)
        classification[:] = np.where(known, CLASS_FIRST_MATERIAL + mid, CLASS_UNCLASSIFIED)
        meanings[str(CLASS_UNCLASSIFIED)] = "unclassified: no scene surface near the point"
        for k, name in enumerate(list(class_names)[: 256 - CLASS_FIRST_MATERIAL]):
            meanings[str(CLASS_FIRST_MATERIAL + k)] = f"material {name}"
    if "false_alarm" in points:
        fa = np.asarray(points["false_alarm"]).astype(bool)
        if fa.shape != (n,):
            raise ConfigError("points.false_alarm", fa.shape, f"one value per point ({n},)")
        classification[fa] = CLASS_NOISE
        flags[fa] |= FLAG_WITHHELD
        meanings[str(CLASS_NOISE)] = "noise: a receiver false alarm (no true return near the echo), withheld"
    if "atmosphere" in points:
        atm = np.asarray(points["atmosphere"]).astype(bool)
        if atm.shape != (n,):
            raise ConfigError("points.atmosphere", atm.shape, f"one value per point ({n},)")
        classification[atm] = CLASS_ATMOSPHERE
        flags[atm] |= FLAG_WITHHELD
        if atm.any():
            meanings[str(CLASS_ATMOSPHERE)] = ("high noise: a return of the atmosphere itself (fog, rain, snow; no "
                                               "surface near the echo), withheld")
    return classification, flags, meanings

FINE_SCALE_M = 1e-4
COARSE_SCALE_M = 1e-3
_INT32_MAX = 2**31 - 1


def choose_scale_offset(xyz: np.ndarray) -> tuple[float, np.ndarray]:
    """(scale, offset[3]) for coordinates ``xyz`` (N, 3) in metres (module docstring)."""
    if len(xyz) == 0:
        return FINE_SCALE_M, np.zeros(3)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    offset = np.round(0.5 * (lo + hi))
    reach = float(np.max(np.maximum(np.abs(hi - offset), np.abs(lo - offset))))
    for scale in (FINE_SCALE_M, COARSE_SCALE_M):
        if reach / scale < 0.99 * _INT32_MAX:
            return scale, offset
    raise ConfigError("points.position", f"{reach:.6g} m from the centre",
                      f"coordinates within ±{0.99 * _INT32_MAX * COARSE_SCALE_M:.0f} m of the point cloud's "
                      f"centre (LAS stores 32-bit integers at 1 mm)")


def _text(value: str, size: int) -> bytes:
    data = value.encode("ascii", "replace")[: size - 1]
    return data + b"\0" * (size - len(data))


def _vlr(user_id: str, record_id: int, payload: bytes, description: str) -> bytes:
    if len(payload) > 65535:
        raise ConfigError(f"LAS VLR {user_id}/{record_id}", f"{len(payload)} bytes", "at most 65535 bytes")
    return struct.pack("<H16sHH32s", 0, _text(user_id, 16), record_id, len(payload),
                       _text(description, 32)) + payload


def _extra_bytes_descriptor(name: str, dtype, description: str) -> bytes:
    """One 192-byte extra-bytes descriptor (spec Table 23): type, name and description only (options 0)."""
    out = struct.pack("<2sBB32s4s", b"\0\0", _EXTRA_CODES[np.dtype(dtype).newbyteorder("<")], 0,
                      _text(name, 32), b"\0" * 4)
    out += b"\0" * (8 + 16 + 8 + 16 + 8 + 16 + 8 + 16 + 8 + 16)  # no_data, min, max, scale, offset (unused)
    out += _text(description, 32)
    assert len(out) == EXTRA_BYTES_DESCRIPTOR_SIZE
    return out


def write_las(path, points: dict, *, coordinates: str = "world", intensity_unit: str = "J per bin",
              class_names=(), frame_time_s: float = 0.0, overwrite: bool = False,
              creation_date: _dt.date | None = None, system_identifier: str = "Ladar Simulator (simulated)",
              software: str | None = None, metadata: dict | None = None) -> Path:
    """Write ``points`` (the simulator's point arrays) as a LAS 1.4 file, point format 6 (module docstring).

    ``coordinates``: "world" (``position_world``) or "sensor" (``position_sensor``).  ``intensity_unit``: the
    unit of ``points["intensity"]`` (picks the fixed LAS intensity scale).  ``class_names``: the scene's
    material names, index = ``material_id``.  ``metadata``: extra JSON stored in the LadarSimulator VLR.
    Returns the path.  Raises ConfigError (writing nothing) on bad input or when the file exists and
    ``overwrite`` is false.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise ConfigError("las file", str(path), "a file that does not exist yet (or overwrite it)")
    if path.exists() and path.is_dir():
        raise ConfigError("las file", str(path), "a file path (a folder of that name exists)")
    key = {"world": "position_world", "sensor": "position_sensor"}.get(coordinates)
    if key is None:
        raise ConfigError("coordinates", coordinates, "'world' or 'sensor'")
    if key not in points:
        raise ConfigError(f"points.{key}", "missing", "an (N, 3) array of positions in metres")
    xyz = np.asarray(points[key], dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ConfigError(f"points.{key}", xyz.shape, "an (N, 3) array of positions in metres")
    n = len(xyz)
    if not np.all(np.isfinite(xyz)):
        raise ConfigError(f"points.{key}", "non-finite coordinates", "finite positions")

    def column(name, default, dtype=np.float64):
        if name not in points:
            return np.full(n, default, dtype=dtype)
        arr = np.asarray(points[name])
        if arr.shape != (n,):
            raise ConfigError(f"points.{name}", arr.shape, f"one value per point ({n},)")
        return arr.astype(dtype)

    intensity = column("intensity", 0.0)
    if not np.all(np.isfinite(intensity)):
        raise ConfigError("points.intensity", "non-finite values", "finite intensities")
    las_i = las_intensity(intensity, intensity_unit)
    scan_angle = las_scan_angle(points, n)
    classification, flags, classes = las_classes(points, n, class_names)
    return_number = np.clip(column("echo_index", 1, np.int64), 1, 15)
    n_returns = np.clip(column("n_echoes", 1, np.int64), return_number, 15)
    gps_time = column("gps_time_s", frame_time_s)
    if not np.all(np.isfinite(gps_time)):
        raise ConfigError("points.gps_time_s", "non-finite values", "finite times (s)")

    scale, offset = choose_scale_offset(xyz)
    ints = np.round((xyz - offset) / scale).astype(np.int64)
    extras = [(las_name, dtype, desc, np.asarray(points[k]).astype(dtype))
              for k, (las_name, dtype, desc) in EXTRA_DIMENSIONS.items()
              if k in points and np.asarray(points[k]).shape == (n,)]
    record_dtype = np.dtype(POINT_FORMAT_6_DTYPE.descr + [(name, np.dtype(dt).newbyteorder("<").str)
                                                          for name, dt, _, _ in extras])
    table = np.zeros(n, dtype=record_dtype)
    table["X"], table["Y"], table["Z"] = ints[:, 0], ints[:, 1], ints[:, 2]
    table["intensity"] = las_i
    table["return_byte"] = (return_number | (n_returns << 4)).astype(np.uint8)
    table["flags_byte"] = flags
    table["classification"] = classification
    table["scan_angle"] = scan_angle
    table["point_source_id"] = np.clip(column("frame", 0, np.int64), 0, 65535)
    table["gps_time"] = gps_time
    for name, _, _, values in extras:
        table[name] = values

    info = {"intensity_unit": intensity_unit, "intensity_scaling": intensity_scale_description(intensity_unit),
            "classes": classes, "scan_angle": "0.006 degree steps, positive towards the sensor's +X",
            "coordinate_frame": "Blender world, metres, Z up" if coordinates == "world"
            else "sensor frame (x right, y up, z backwards), metres",
            "gps_time": "gps_time_s of each point (scanner pulse emission time), else frame_time_s",
            "frame_time_s": frame_time_s, "coordinates": coordinates, "scale_m": scale,
            "offset_m": offset.tolist(), "point_source_id": "frame number"}
    info.update(metadata or {})
    vlrs = [_vlr("LASF_Projection", 2112, LOCAL_WKT.encode("ascii") + b"\0", "OGC coordinate system WKT")]
    if extras:
        vlrs.append(_vlr("LASF_Spec", 4, b"".join(_extra_bytes_descriptor(nm, dt, desc)
                                                  for nm, dt, desc, _ in extras), "Extra bytes"))
    vlrs.append(_vlr("LadarSimulator", 1, json.dumps(info, default=float).encode("utf-8"),
                     "intensity scaling, frame (JSON)"))
    offset_to_points = HEADER_SIZE + sum(len(v) for v in vlrs)

    if n:
        stored = ints * scale + offset
        mins, maxs = stored.min(axis=0), stored.max(axis=0)
    else:
        mins = maxs = np.zeros(3)
    by_return = np.bincount(return_number, minlength=16)[1:16] if n else np.zeros(15, np.int64)
    date = creation_date or _dt.datetime.now(_dt.timezone.utc).date()
    if software is None:
        software = f"ladar_simulator {__version__}"
    values = {
        "file_signature": b"LASF", "file_source_id": 0, "global_encoding": GLOBAL_ENCODING_WKT,
        "project_id": b"\0" * 16, "version_major": LAS_VERSION[0], "version_minor": LAS_VERSION[1],
        "system_identifier": _text(system_identifier, 32), "generating_software": _text(software, 32),
        "creation_day_of_year": date.timetuple().tm_yday, "creation_year": date.year, "header_size": HEADER_SIZE,
        "offset_to_point_data": offset_to_points, "number_of_vlrs": len(vlrs), "point_data_format": POINT_FORMAT,
        "point_data_record_length": record_dtype.itemsize, "legacy_point_count": 0,
        "legacy_points_by_return": (0,) * 5, "x_scale": scale, "y_scale": scale, "z_scale": scale,
        "x_offset": offset[0], "y_offset": offset[1], "z_offset": offset[2],
        "max_x": maxs[0], "min_x": mins[0], "max_y": maxs[1], "min_y": mins[1], "max_z": maxs[2], "min_z": mins[2],
        "start_of_waveform_data": 0, "start_of_first_evlr": 0, "number_of_evlrs": 0, "point_count": n,
        "points_by_return": tuple(int(c) for c in by_return),
    }
    flat = []
    for name, fmt, _ in HEADER_FIELDS:
        v = values[name]
        flat.extend(v if isinstance(v, tuple) else (v,))
    header = HEADER_STRUCT.pack(*flat)

    def write(f):
        f.write(header)
        for v in vlrs:
            f.write(v)
        f.write(table.tobytes())

    return write_file_atomically(path, write, suffix=".partial")


def read_header(data: bytes) -> dict:
    """The public header block of LAS 1.4 bytes as a dict (names of :data:`HEADER_FIELDS`)."""
    if len(data) < HEADER_SIZE or data[:4] != b"LASF":
        raise ConfigError("las file", "not a LAS file", "a file starting with 'LASF' and a 375-byte header")
    flat = list(HEADER_STRUCT.unpack_from(data, 0))
    out = {}
    for name, fmt, _ in HEADER_FIELDS:
        count = int(fmt[:-1]) if fmt[:-1].isdigit() and fmt[-1] != "s" else 1
        out[name] = tuple(flat[:count]) if count > 1 else flat[0]
        del flat[:count]
    return out


def read_las(path) -> dict:
    """Read a LAS 1.4 point format 6 file (as :func:`write_las` writes it).

    Returns ``{"header": dict, "vlrs": [(user_id, record_id, description, payload)], "points": dict}`` with
    points ``x, y, z`` (float64, m), ``intensity``, ``return_number``, ``number_of_returns``, ``classification``,
    ``scan_angle``, ``point_source_id``, ``gps_time`` and every extra-bytes dimension by name.
    """
    data = Path(path).read_bytes()
    header = read_header(data)
    if (header["version_major"], header["version_minor"]) != LAS_VERSION or header["point_data_format"] != 6:
        raise ConfigError("las file", f"version {header['version_major']}.{header['version_minor']}, format "
                                      f"{header['point_data_format']}", "LAS 1.4, point data record format 6")
    pos, vlrs = header["header_size"], []
    for _ in range(header["number_of_vlrs"]):
        _, user, rid, length, desc = struct.unpack_from("<H16sHH32s", data, pos)
        payload = data[pos + VLR_HEADER_SIZE: pos + VLR_HEADER_SIZE + length]
        vlrs.append((user.rstrip(b"\0").decode("ascii"), rid, desc.rstrip(b"\0").decode("ascii"), payload))
        pos += VLR_HEADER_SIZE + length
    extras = []
    for user, rid, _, payload in vlrs:
        if user == "LASF_Spec" and rid == 4:
            for i in range(0, len(payload), EXTRA_BYTES_DESCRIPTOR_SIZE):
                code = payload[i + 2]
                name = payload[i + 4: i + 36].rstrip(b"\0").decode("ascii")
                extras.append((name, _EXTRA_TYPES[code]))
    dtype = np.dtype(POINT_FORMAT_6_DTYPE.descr + extras)
    if dtype.itemsize != header["point_data_record_length"]:
        raise ConfigError("las file", f"record length {header['point_data_record_length']}",
                          f"{dtype.itemsize} bytes (format 6 + described extra bytes)")
    n = header["point_count"]
    table = np.frombuffer(data, dtype=dtype, count=n, offset=header["offset_to_point_data"])
    points = {axis: table[axis.upper()] * header[f"{axis}_scale"] + header[f"{axis}_offset"] for axis in "xyz"}
    points.update(intensity=table["intensity"].copy(), return_number=table["return_byte"] & 0x0F,
                  number_of_returns=table["return_byte"] >> 4, classification=table["classification"].copy(),
                  synthetic=(table["flags_byte"] & FLAG_SYNTHETIC) > 0,
                  withheld=(table["flags_byte"] & FLAG_WITHHELD) > 0,
                  scan_angle=table["scan_angle"].copy(), point_source_id=table["point_source_id"].copy(),
                  gps_time=table["gps_time"].copy())
    for name, _ in extras:
        points[name] = table[name].copy()
    return {"header": header, "vlrs": vlrs, "points": points}


def run_points(run_dir) -> tuple[dict, dict]:
    """(points, metadata) of a run folder: its ``points.npz``, or the ``frame_*/points.npz`` of a frame sequence
    concatenated in frame order (each point keeps its ``frame``)."""
    run = Path(run_dir)
    meta_path = run / "metadata.json"
    metadata = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
    files = [run / "points.npz"] if (run / "points.npz").is_file() else sorted(run.glob("frame_*/points.npz"))
    if not files:
        raise ConfigError("run folder", str(run), "a ladar run folder holding points.npz (or frame_*/points.npz)")
    parts = []
    for f in files:
        with np.load(f) as npz:
            parts.append({k: npz[k] for k in npz.files})
    keys = set.intersection(*(set(p) for p in parts))
    points = {k: np.concatenate([p[k] for p in parts]) for k in sorted(keys)}
    return points, metadata


def intensity_unit_of(metadata: dict) -> str:
    """The unit of a run's point intensities: its metadata's ``units["intensity"]`` (core.engine.result.product_units),
    J per bin for run folders written before units were recorded."""
    return (metadata.get("units") or {}).get("intensity") or "J per bin"


def las_run_facts(metadata: dict, **more) -> dict:
    """The keyword arguments of :func:`write_las` that a run's metadata decides: intensity unit, class names and
    the run's facts for the LadarSimulator VLR."""
    info = {k: metadata[k] for k in ("system_type", "frame", "frames", "seed", "simulator_version",
                                     "sensor_pose") if k in metadata}
    info.update(more)
    return {"intensity_unit": intensity_unit_of(metadata), "class_names": metadata.get("material_names", ()),
            "metadata": info}


def write_run_las(run_dir, path, *, coordinates: str = "world", overwrite: bool = False, **kwargs) -> Path:
    """Write a run folder's point cloud as LAS 1.4 (:func:`write_las`); points without a ``gps_time_s`` get the
    run's ``start_time_s`` (metadata; 0 if absent).  The run's frame, system type and seed go into the
    LadarSimulator VLR."""
    points, meta = run_points(run_dir)
    facts = las_run_facts(meta, run=Path(run_dir).name)
    facts.update(kwargs)
    facts.setdefault("frame_time_s", float(meta.get("start_time_s", 0.0) or 0.0))
    return write_las(path, points, coordinates=coordinates, overwrite=overwrite, **facts)
