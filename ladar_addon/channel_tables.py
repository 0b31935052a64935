"""The rotating head's channel table in Blender: a CSV file chosen in the Scanner panel, validated when it is
chosen and again whenever the panel draws (core/config/tables.py reads it; a bad file's error names the row and
column).  The table settings have no Blender property: they live in the sensor camera's JSON custom property
(:func:`ladar_addon.blend_config.read_tables`, key ``ladar_scanner_tables``), as config files hold them."""
from __future__ import annotations

import os

from ..core.config.settings import ScannerSettings
from ..core.config.tables import CHANNEL_COLUMNS, channel_table_deg, read_channel_csv
from ..core.errors import ConfigError
from .blend_config import read_tables, remove_tables, store_tables

#: Rows of a table the panel lists (the first ones; the summary line covers all).
PREVIEW_ROWS = 4


def set_channel_table_file(sensor_obj, path: str) -> int:
    """Validate the CSV file ``path`` and make it the sensor's channel table (its number of channels set to the
    rows; an inline table replaced).  Returns the number of channels.  A bad file raises the ConfigError naming
    the row and column, and changes nothing."""
    path = os.path.abspath(os.fspath(path))
    table = read_channel_csv(path)  # ConfigError before anything is written
    tables = read_tables(sensor_obj, "scanner")
    tables.pop("channel_table", None)
    tables["channel_table_file"] = path
    store_tables(sensor_obj, "scanner", tables)
    sensor_obj.ladar.scanner.n_channels = len(table)
    return len(table)


def clear_channel_table(sensor_obj) -> None:
    """Back to evenly spaced channels: the inline table and the file removed (the other tables kept)."""
    remove_tables(sensor_obj, "scanner", ("channel_table", "channel_table_file"))


def channel_table_lines(sensor_obj) -> list[str]:
    """What the Scanner panel shows of the channel table: its source, a summary and the first rows, or the
    validation error (a missing or changed file, a bad cell, a row count that is not n_channels)."""
    tables = read_tables(sensor_obj, "scanner")
    if not tables.get("channel_table") and not tables.get("channel_table_file"):
        return ["Evenly spaced channels (no channel table)"]
    scanner = ScannerSettings(channel_table=tables.get("channel_table", []),
                              channel_table_file=tables.get("channel_table_file", ""),
                              n_channels=sensor_obj.ladar.scanner.n_channels)
    src = (f"File {os.path.basename(scanner.channel_table_file)}" if scanner.channel_table_file
           else "Inline table (from a preset or config file)")
    try:
        table = channel_table_deg(scanner)
    except ConfigError as exc:
        return [src, f"Error: {exc}"]
    lines = [src, f"{len(table)} channels, elevation {table[:, 0].min():+.3f}° … {table[:, 0].max():+.3f}°, "
                  f"azimuth offset {table[:, 1].min():+.3f}° … {table[:, 1].max():+.3f}°, "
                  f"fire offset ≤ {table[:, 2].max() * 1e6:.3g} µs"
                  + (f", relative pulse energy {table[:, 3].min():.3g} … {table[:, 3].max():.3g}"
                     if table.shape[1] > 3 else "")]
    if len(table) != scanner.n_channels:
        lines.append(f"Error: scanner.n_channels = {scanner.n_channels}, the table has {len(table)} rows")
    lines.append("  " + ", ".join(CHANNEL_COLUMNS[:table.shape[1]]))
    lines += [f"  {row[0]:+.4f}, {row[1]:+.4f}, {row[2]:.4g}" + "".join(f", {x:.4g}" for x in row[3:])
              for row in table[:PREVIEW_ROWS]]
    if len(table) > PREVIEW_ROWS:
        lines.append(f"  … {len(table) - PREVIEW_ROWS} more")
    return lines
