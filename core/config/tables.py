"""The settings' tables: the rotating head's per-channel table (inline or from a CSV file), the Risley prisms and
the range-layered aerosol (``atmosphere.aerosol_layers``).

Each is checked row by row and column by column; a bad entry is a one-line :class:`ConfigError` naming the
setting (or file), the row and the column, the value and what is allowed.  Rows and columns are counted from 1
as a person reads a CSV file.

Channel table, one row per channel: ``[elevation_deg, azimuth_offset_deg, fire_offset_s]`` or, with a fourth
column in every row, ``[..., relative_pulse_energy]``:

* elevation_deg          the channel's elevation β above the sensor's horizontal plane, in [−90, 90] deg;
* azimuth_offset_deg     added to the head's azimuth α at the channel's firing (to +X), in [−360, 360] deg;
* fire_offset_s          the channel fires this long after the firing time k/PRF of its group, in [−1, 1] s;
* relative_pulse_energy  (optional) the channel's pulse energy over ``laser.pulse_energy_j``, in [0.001, 1000]:
                         everything its pulse returns (surfaces, drops, volume backscatter) scales with it, the
                         background (sunlight) and the detector's own noise do not.  Without the column: 1.

Aerosol layers, one row per layer: ``[start_m, end_m, extinction_per_m]`` or ``[..., backscatter_per_m_sr]``
(ranges from the sensor in [0, 1e6] m, end beyond start, rows in increasing range and not overlapping; α in
[0, 1] 1/m and β in [0, 1] 1/(m sr), added to the homogeneous ones inside the layer; without the fourth column
β = α/S).
"""
from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError

CHANNEL_COLUMNS = ("elevation_deg", "azimuth_offset_deg", "fire_offset_s", "relative_pulse_energy")
CHANNEL_LIMITS = ((-90.0, 90.0, "deg"), (-360.0, 360.0, "deg"), (-1.0, 1.0, "s"), (1e-3, 1e3, ""))
MAX_CHANNELS = 1024
#: The range-layered aerosol (atmosphere.aerosol_layers): one row per layer, the backscatter column optional (α/S).
LAYER_COLUMNS = ("start_m", "end_m", "extinction_per_m", "backscatter_per_m_sr")
LAYER_LIMITS = ((0.0, 1e6, "m"), (0.0, 1e6, "m"), (0.0, 1.0, "1/m"), (0.0, 1.0, "1/(m sr)"))
MAX_LAYERS = 256


def _number(value) -> float | None:
    """A finite real number from a table cell (int, float or a numeric string), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, str):
        try:
            value = float(value.strip())
        except ValueError:
            return None
    if not isinstance(value, (int, float)):
        return None
    try:
        value = float(value)
    except OverflowError:
        return None
    return value if np.isfinite(value) else None


def check_table_rows(rows, where: str, columns, limits, row_name: str, max_rows: int,
                     text_cells: bool = False) -> np.ndarray:
    """(n, k) float64 array from rows of k cells, k = len(columns) − 1 or len(columns) (the last column optional;
    every row as many as the first), each cell a finite number within its (lo, hi, unit) of ``limits``;
    ConfigError naming ``where``, the row and the column of the first bad cell (rows and columns from 1)."""
    first_cols = ", ".join(columns[:-1])
    if not isinstance(rows, (list, tuple)):
        raise ConfigError(where, rows, f"a list of rows [{first_cols}]")
    if not rows:
        raise ConfigError(where, "no rows", f"at least one {row_name} row [{first_cols}]")
    if len(rows) > max_rows:
        raise ConfigError(where, f"{len(rows)} rows", f"at most {max_rows} {row_name}s")
    first = rows[0]
    short = len(columns) - 1
    ncol = len(first) if isinstance(first, (list, tuple)) and len(first) in (short, short + 1) else short
    out = np.empty((len(rows), ncol))
    for r, row in enumerate(rows, start=1):
        if not isinstance(row, (list, tuple)) or len(row) != ncol:
            allowed = (f"{ncol} columns like row 1: " + ", ".join(columns[:ncol]) if r > 1 else
                       f"{short} columns: {first_cols} (or {short + 1}: and {columns[-1]})")
            raise ConfigError(f"{where} row {r}", row, allowed)
        for c, (cell, name, (lo, hi, unit)) in enumerate(zip(row, columns, limits), start=1):
            v = _number(cell) if text_cells or not isinstance(cell, str) else None
            if v is None or not lo <= v <= hi:
                raise ConfigError(f"{where} row {r} column {c} ({name})", cell,
                                  f"a finite number in [{lo:g}, {hi:g}]" + (f" {unit}" if unit else ""))
            out[r - 1, c - 1] = v
    return out


def check_channel_rows(rows, where: str, text_cells: bool = False) -> np.ndarray:
    """(n, 3) float64 array [elevation_deg, azimuth_offset_deg, fire_offset_s] from rows of 3 cells, or (n, 4)
    with relative_pulse_energy from rows of 4 (every row as many as the first); ConfigError naming ``where``, the
    row and the column of the first bad cell."""
    return check_table_rows(rows, where, CHANNEL_COLUMNS, CHANNEL_LIMITS, "channel", MAX_CHANNELS, text_cells)


def read_channel_csv(path) -> np.ndarray:
    """The channel table a CSV file holds: three columns (elevation_deg, azimuth_offset_deg, fire_offset_s) or
    four (and relative_pulse_energy), an optional header row naming them, blank lines and lines starting with
    '#' skipped."""
    p = Path(path)
    where = f"scanner.channel_table_file {p.name[:60]!r}"
    if not p.is_file():
        raise ConfigError("scanner.channel_table_file", str(path), "an existing CSV file")
    try:
        text = p.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError("scanner.channel_table_file", str(path), f"UTF-8 text (byte {exc.start} is not "
                                                                   f"UTF-8)") from None
    rows, line_rows = [], []
    for line_no, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        cells = next(csv.reader(io.StringIO(line)))
        if not rows and not line_rows and all(_number(c) is None for c in cells):
            names = tuple(c.strip() for c in cells)
            if names not in (CHANNEL_COLUMNS[:3], CHANNEL_COLUMNS):
                raise ConfigError(f"{where} row {line_no}", line.strip(),
                                  "a header naming the columns " + ", ".join(CHANNEL_COLUMNS[:3]) + " (and "
                                  + CHANNEL_COLUMNS[3] + ") or numbers")
            continue
        rows.append(cells)
        line_rows.append(line_no)
    if not rows:
        raise ConfigError("scanner.channel_table_file", str(path), "a CSV file with at least one channel row")
    try:
        return check_channel_rows(rows, where, text_cells=True)
    except ConfigError as exc:  # name the file's line, not the data row's number
        if " row " in exc.field:
            head, _, tail = exc.field.partition(" row ")
            num, _, rest = tail.partition(" ")
            raise ConfigError(f"{head} row {line_rows[int(num) - 1]}" + (f" {rest}" if rest else ""),
                              exc.value, exc.allowed) from None
        raise


_CSV_CACHE: dict = {}


def channel_table_deg(scanner) -> np.ndarray | None:
    """The rotating head's channel table (n, 3) [elevation_deg, azimuth_offset_deg, fire_offset_s] (or (n, 4) with
    relative_pulse_energy), or None for the evenly spaced channels.  A CSV file is read once per (path, modification time, size)."""
    if scanner.channel_table:
        return check_channel_rows(scanner.channel_table, "scanner.channel_table")
    if scanner.channel_table_file:
        path = os.fspath(scanner.channel_table_file)
        try:
            st = os.stat(path)
            key = (os.path.abspath(path), st.st_mtime_ns, st.st_size)
        except (OSError, ValueError):  # missing, unreadable, or not a path (a NUL character)
            key = None
        if key is not None and key in _CSV_CACHE:
            return _CSV_CACHE[key]
        table = read_channel_csv(path)
        if key is not None:
            _CSV_CACHE.clear()
            _CSV_CACHE[key] = table
        return table
    return None


def channel_energy_scale(scanner) -> np.ndarray | None:
    """Each channel's pulse energy over laser.pulse_energy_j (n_channels,) for a rotating head whose channel table
    has the relative_pulse_energy column with a value other than 1, else None (every pulse at the laser's
    energy: the products are those of a table without the column, bit for bit)."""
    if scanner.pattern != "rotating":
        return None
    table = channel_table_deg(scanner)
    if table is None or table.shape[1] < 4 or np.all(table[:, 3] == 1.0):
        return None
    return np.ascontiguousarray(table[: scanner.n_channels, 3])


def check_channel_table(scanner) -> None:
    """The channel table's settings: not both inline and from a file; one row per channel (n_channels)."""
    if not isinstance(scanner.channel_table, (list, tuple)):
        raise ConfigError("scanner.channel_table", scanner.channel_table,
                          "a list of rows [elevation_deg, azimuth_offset_deg, fire_offset_s]")
    if not isinstance(scanner.channel_table_file, (str, os.PathLike)):
        raise ConfigError("scanner.channel_table_file", scanner.channel_table_file, "a file path (a string)")
    if scanner.channel_table and scanner.channel_table_file:
        raise ConfigError("scanner.channel_table_file", str(scanner.channel_table_file),
                          "empty when scanner.channel_table is given (one table: inline or from a file)")
    table = channel_table_deg(scanner)
    if table is not None and len(table) != scanner.n_channels:
        src = "scanner.channel_table" if scanner.channel_table else "scanner.channel_table_file"
        raise ConfigError("scanner.n_channels", scanner.n_channels,
                          f"{len(table)}, the number of rows of {src} (one row per channel)")


def aerosol_layer_table(atm, where: str = "atmosphere.aerosol_layers") -> np.ndarray | None:
    """The range-layered aerosol (``atm.aerosol_layers``): (n, 4) [start_m, end_m, extinction_per_m,
    backscatter_per_m_sr], the backscatter of a 3-column row α/S (S = ``atm.lidar_ratio_sr``), or None without
    layers.  Each row's end beyond its start, each row's start at or beyond the previous row's end (increasing,
    not overlapping); ConfigError naming the row and the column otherwise."""
    rows = atm.aerosol_layers
    if isinstance(rows, (list, tuple)) and not rows:
        return None
    t = check_table_rows(rows, where, LAYER_COLUMNS, LAYER_LIMITS, "layer", MAX_LAYERS)
    for r in range(len(t)):
        if not t[r, 1] > t[r, 0]:
            raise ConfigError(f"{where} row {r + 1} column 2 (end_m)", rows[r][1],
                              f"a range beyond the row's start_m {t[r, 0]:g} m")
        if r and t[r, 0] < t[r - 1, 1]:
            raise ConfigError(f"{where} row {r + 1} column 1 (start_m)", rows[r][0],
                              f"at least the previous row's end_m {t[r - 1, 1]:g} m (rows in increasing range, "
                              f"not overlapping)")
    if t.shape[1] == 3:
        t = np.column_stack([t, t[:, 2] / atm.lidar_ratio_sr])
    return t


RISLEY_LISTS = (("risley_prism_hz", -1e5, 1e5, "Hz"), ("risley_wedge_deg", -60.0, 60.0, "deg"),
                ("risley_index", 1.0, 5.0, ""), ("risley_phase_deg", -360.0, 360.0, "deg"))
MAX_PRISMS, MAX_EMITTERS = 8, 256


def risley_prisms(scanner) -> np.ndarray:
    """(n_prisms, 4) [frequency Hz, wedge deg, index, phase deg] of the Risley prisms, checked."""
    values = {}
    for name, lo, hi, unit in RISLEY_LISTS:
        seq = getattr(scanner, name)
        path = f"scanner.{name}"
        if not isinstance(seq, (list, tuple)):
            raise ConfigError(path, seq, "a list of numbers, one per prism")
        out = []
        for i, v in enumerate(seq):
            x = _number(v) if not isinstance(v, str) else None
            if x is None or not lo <= x <= hi:
                raise ConfigError(f"{path}[{i}]", v, f"a finite number in [{lo:g}, {hi:g}]" +
                                  (f" {unit}" if unit else ""))
            out.append(x)
        values[name] = out
    n = len(values["risley_wedge_deg"])
    if not 1 <= n <= MAX_PRISMS:
        raise ConfigError("scanner.risley_wedge_deg", values["risley_wedge_deg"],
                          f"1 to {MAX_PRISMS} prisms for pattern risley")
    if not values["risley_phase_deg"]:
        values["risley_phase_deg"] = [0.0] * n
    for name, _, _, _ in RISLEY_LISTS:
        if len(values[name]) != n:
            raise ConfigError(f"scanner.{name}", f"{len(values[name])} values",
                              f"one per prism ({n} in scanner.risley_wedge_deg)")
    for i, w in enumerate(values["risley_wedge_deg"]):
        if w == 0.0:
            raise ConfigError(f"scanner.risley_wedge_deg[{i}]", w, "a non-zero wedge angle in [-60, 60] deg")
    return np.array([values[name] for name, _, _, _ in RISLEY_LISTS]).T


def risley_emitters_deg(scanner) -> np.ndarray:
    """(n_emitters, 2) [alpha_deg, beta_deg] of the beams entering the prisms (one along −Z if none given)."""
    rows = scanner.risley_emitters_deg
    if not isinstance(rows, (list, tuple)):
        raise ConfigError("scanner.risley_emitters_deg", rows, "a list of rows [alpha_deg, beta_deg]")
    if not rows:
        return np.zeros((1, 2))
    if len(rows) > MAX_EMITTERS:
        raise ConfigError("scanner.risley_emitters_deg", f"{len(rows)} rows", f"at most {MAX_EMITTERS} emitters")
    out = np.empty((len(rows), 2))
    for r, row in enumerate(rows, start=1):
        if not isinstance(row, (list, tuple)) or len(row) != 2:
            raise ConfigError(f"scanner.risley_emitters_deg row {r}", row, "2 columns: alpha_deg, beta_deg")
        for c, cell in enumerate(row, start=1):
            x = _number(cell) if not isinstance(cell, str) else None
            if x is None or not -30.0 <= x <= 30.0:
                raise ConfigError(f"scanner.risley_emitters_deg row {r} column {c}", cell,
                                  "a finite number in [-30, 30] deg")
            out[r - 1, c - 1] = x
    return out


def scan_channels(scanner) -> int:
    """Pulses fired together at each firing time: n_channels (rotating), the emitters (risley), else 1."""
    if scanner.pattern == "rotating":
        return scanner.n_channels
    if scanner.pattern == "risley":
        rows = scanner.risley_emitters_deg
        return max(1, len(rows)) if isinstance(rows, (list, tuple)) else 1
    return 1


# ----------------------------------------------------------------------------------------------------------
# Risley prisms: exact vector refraction (Snell's law in 3D) through both faces of each prism
# ----------------------------------------------------------------------------------------------------------
def refract(d, normal, n1: float, n2: float):
    """Directions (n, 3) refracted at a surface of unit normal(s) ``normal`` pointing back against the beam
    (n·d < 0), from index n1 into n2: t = η d + (η cos i − cos t) n with η = n1/n2, cos i = −n·d and
    cos t = √(1 − η²(1 − cos² i)).  Returns (t, tir) with tir True where total internal reflection occurs
    (t is then NaN)."""
    eta = n1 / n2
    cos_i = -np.einsum("ij,ij->i", normal, d)
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    tir = sin2_t > 1.0
    cos_t = np.sqrt(np.where(tir, np.nan, 1.0 - sin2_t))
    t = eta * d + (eta * cos_i - cos_t)[:, None] * normal
    return t / np.linalg.norm(t, axis=1, keepdims=True), tir


def wedge_normals(wedge_deg: float, psi):
    """Normals (n, 3) of a prism's two faces, pointing back towards the laser (+Z): the flat face's is +Z, the
    inclined face's is tilted by the wedge angle w towards the azimuth ψ (first face, w > 0) or away from it
    (second face, w < 0).  Returns (first face, second face)."""
    a = np.radians(abs(wedge_deg))
    flat = np.zeros((len(psi), 3))
    flat[:, 2] = 1.0
    sign = 1.0 if wedge_deg > 0 else -1.0
    incl = np.stack([sign * np.sin(a) * np.cos(psi), sign * np.sin(a) * np.sin(psi),
                     np.full(len(psi), np.cos(a))], axis=-1)
    return (incl, flat) if wedge_deg > 0 else (flat, incl)


def risley_trace(t_s, incident, prisms):
    """Directions (n, 3) (sensor frame) leaving a stack of Risley prisms at times ``t_s`` (n,), for beams
    entering along ``incident`` (n, 3), the prisms (rows [frequency Hz, wedge deg, index, phase deg], in beam
    order, air index 1) each turned to ψ = −(2π f t + phase) about the −Z axis.  Returns (directions, tir)."""
    d = np.asarray(incident, dtype=np.float64)
    tir = np.zeros(len(d), dtype=bool)
    for f, wedge, index, phase in prisms:
        psi = -(2.0 * np.pi * f * t_s + np.radians(phase))
        first, second = wedge_normals(wedge, psi)
        d, t1 = refract(d, first, 1.0, index)
        d, t2 = refract(d, second, index, 1.0)
        tir |= t1 | t2
    return d, tir


def check_risley(scanner) -> None:
    """The Risley prisms' settings, and no total internal reflection at 20 000 times over one second (the
    prisms' relative angles sampled densely)."""
    emitters = risley_emitters_deg(scanner)  # (first: a wrong type there is named there, not as a prism count)
    prisms = risley_prisms(scanner)
    t = np.linspace(0.0, 1.0, 20_000)
    for e, (alpha, beta) in enumerate(np.radians(emitters)):
        inc = np.tile([np.cos(beta) * np.sin(alpha), np.sin(beta), -np.cos(beta) * np.cos(alpha)], (len(t), 1))
        _, tir = risley_trace(t, inc, prisms)
        if tir.any():
            raise ConfigError("scanner.risley_wedge_deg", [float(w) for w in prisms[:, 1]],
                              f"wedge angles and indices without total internal reflection (emitter {e + 1} "
                              f"is totally reflected at t = {t[np.argmax(tir)]:.4g} s)")
