"""Preset files of the settings layer: where the real-sensor presets are, and a config table's ``preset`` key
expanded into the preset's settings (config files, ``config_from_dict``).  Reading and checking a preset as a
whole (its ``[published]`` figures too) is :mod:`core.presets`, which builds on this module.

A preset is a TOML file: ``system_type`` and settings groups as in a config file, plus a ``[published]`` table
of the maker's figures (metadata, never settings).  ``preset = "NAME"`` names a shipped one
(``core/presets/sensors/NAME.toml``); a value ending in ``.toml`` is the path of the user's own file.
"""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

from ..errors import ConfigError, cut

#: Settings groups that describe the scene, not the sensor: refused in a preset's settings (the conditions its
#: figures are stated under go in ``[published.conditions.<group>]``, core.presets).
ENVIRONMENT_GROUPS = ("atmosphere",)
#: Folder of the shipped presets.
SENSORS_DIR = Path(__file__).resolve().parents[1] / "presets" / "sensors"
_NAME = re.compile(r"^[a-z0-9][a-z0-9_]*$")


def list_presets() -> list[str]:
    """Names of the shipped presets (file names without ``.toml``), sorted."""
    return sorted(p.stem for p in SENSORS_DIR.glob("*.toml"))


def _allowed() -> str:
    return "a shipped preset name (" + ", ".join(list_presets()) + ") or an existing preset file ending in .toml"


def preset_path(name_or_path) -> Path:
    """The file of a shipped preset's name, or a user's preset file (a path ending in ``.toml``)."""
    if isinstance(name_or_path, Path) or (isinstance(name_or_path, str) and name_or_path.lower().endswith(".toml")):
        path = Path(name_or_path).expanduser()
        if not path.is_file():
            raise ConfigError("preset", str(name_or_path), _allowed())
        return path
    if not isinstance(name_or_path, str) or not _NAME.match(name_or_path) \
            or not (SENSORS_DIR / f"{name_or_path}.toml").is_file():
        raise ConfigError("preset", name_or_path, _allowed())
    return SENSORS_DIR / f"{name_or_path}.toml"


def read_preset(name_or_path) -> tuple[Path, dict, dict]:
    """(path, settings table, ``[published]`` table) of a preset, read but not yet checked as settings.  A file
    that is not UTF-8 TOML, or that names a preset itself, is a one-line ConfigError naming the file."""
    path = preset_path(name_or_path)
    raw = path.read_bytes()
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError("preset file", str(path), f"UTF-8 text (byte {exc.start} is not UTF-8)") from None
    except ValueError as exc:  # TOMLDecodeError
        raise ConfigError("preset file", str(path), f"valid TOML ({cut(str(exc), 200)})") from None
    if "preset" in data:
        raise ConfigError(f"preset {path.stem}: preset", data["preset"], "no preset key inside a preset file")
    for group in ENVIRONMENT_GROUPS:
        if group in data:
            raise ConfigError(f"preset {path.stem}: {group}", data[group],
                              f"no [{group}] in a sensor preset (it describes the scene: set it in the config or on "
                              f"the scene; the conditions of the published figures go in "
                              f"[published.conditions.{group}])")
    published = data.pop("published", {})
    return path, data, published


def resolve_preset(data: dict) -> dict:
    """A config table with its ``preset`` key (if any) expanded: the preset's settings, then the table's own
    keys over them (settings groups merged key by key).  Tables without ``preset`` come back unchanged; the
    result is checked as settings by the caller (``config_from_dict``)."""
    if not isinstance(data, dict) or "preset" not in data:
        return data
    data = dict(data)
    name = data.pop("preset")
    if not isinstance(name, str):
        raise ConfigError("preset", name, _allowed())
    _, settings, _ = read_preset(name)
    merged = {k: (dict(v) if isinstance(v, dict) else v) for k, v in settings.items()}
    for key, value in data.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict) and key != "materials":
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged
