"""Config files: a SimulationConfig to and from plain dicts, JSON and TOML (``schema_version`` 1).

A file overrides any subset of the settings (keys present override the base config, default settings if none);
every value is validated on the way in (:func:`~.settings.validate`), naming the setting, the value and the
allowed range.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import tomllib
from pathlib import Path

from ..errors import ConfigError, cut
from .preset_files import resolve_preset
from .settings import BRDF_TABLE_FIELDS, GROUPS, SCHEMA_VERSION, BRDFSettings, SimulationConfig
from .validate import finite_number, validate


def _from_mapping(cls, data: dict, prefix: str):
    if not isinstance(data, dict):
        raise ConfigError(prefix.rstrip(".") or "config", data, "a table of settings")
    names = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in names:
            raise ConfigError(f"{prefix}{key}", value, "a known setting: " + ", ".join(sorted(names)))
        f = names[key]
        if dataclasses.is_dataclass(f.default_factory() if f.default_factory is not dataclasses.MISSING
                                    else None):
            kwargs[key] = _from_mapping(type(f.default_factory()), value, f"{prefix}{key}.")
        elif key == "materials":
            if not isinstance(value, dict):
                raise ConfigError(f"{prefix}{key}", value, "a table of material name -> BRDF settings")
            kwargs[key] = {name: _brdf_from_mapping(sub, f"{prefix}{key}.{name}.")
                           for name, sub in value.items()}
        else:
            if isinstance(f.default, float) and isinstance(value, int) and not isinstance(value, bool) \
                    and finite_number(value):  # (an integer too large for a float is refused by validate)
                value = float(value)
            kwargs[key] = value
    return cls(**kwargs)


def _plain(value):
    """``dataclasses.asdict`` of the settings' own types (dataclasses, dicts, lists/tuples, immutable scalars),
    5× faster: a sweep of 1000 points converted 2000 configs with asdict, 5 s of its planning on a loaded 2-core
    machine.  Other leaves are deep-copied, as asdict does."""
    if isinstance(value, (bool, int, float, str, type(None))):
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return type(value)((_plain(k), _plain(v)) for k, v in value.items())
    if isinstance(value, (list, tuple)) and type(value) in (list, tuple):
        return type(value)(_plain(v) for v in value)
    return copy.deepcopy(value)


def config_to_dict(cfg: SimulationConfig) -> dict:
    """Plain nested dict (JSON/TOML-ready) with the schema version."""
    data = {"schema_version": SCHEMA_VERSION}
    data.update(_plain(cfg))
    return data


_DEFAULT = SimulationConfig()


def config_from_dict(data: dict, base: SimulationConfig | None = None) -> SimulationConfig:
    """Build and validate a config from a dict.  Keys present override ``base`` (default settings if None)."""
    if not isinstance(data, dict):
        raise ConfigError("config", type(data).__name__, "a table of settings")
    data = dict(resolve_preset(data))  # a top-level ``preset = "name"``: its settings first, the file's over them
    version = data.pop("schema_version", SCHEMA_VERSION)
    if type(version) is not int or version != SCHEMA_VERSION:
        raise ConfigError("schema_version", version, f"{SCHEMA_VERSION} (this version of the simulator)")
    merged = config_to_dict(base if base is not None else _DEFAULT)
    merged.pop("schema_version")
    for key, value in data.items():
        if key in GROUPS and isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        elif key == "materials" and isinstance(value, dict):
            merged[key] = {**merged.get(key, {}), **value}
        else:
            merged[key] = value
    cfg = _from_mapping(SimulationConfig, merged, "")
    validate(cfg)
    return cfg


def load_config(path, base: SimulationConfig | None = None) -> SimulationConfig:
    """Read a JSON (``.json``) or TOML (``.toml``) config file; its keys override ``base``."""
    return config_from_dict(read_config_file(path), base)


def read_config_file(path, what: str = "config file"):
    """The table a JSON or TOML file holds, not yet checked as settings (:func:`config_from_dict` does that; the
    sweep reader uses it for sweep files, ``what``).  A file that cannot be read as one — missing, another
    suffix, not UTF-8, not valid JSON/TOML, nested deeper than ``MAX_CONFIG_DEPTH`` — is a one-line ConfigError
    naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(what, str(path), "an existing .json or .toml file")
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise ConfigError(what, str(path), "a file ending in .json or .toml")
    kind = suffix[1:].upper()
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(what, str(path), f"UTF-8 text (byte {exc.start} is {raw[exc.start]:#04x}, "
                                           f"not UTF-8)") from None
    try:
        data = tomllib.loads(text) if suffix == ".toml" else json.loads(text)
    except RecursionError:
        raise ConfigError(what, str(path), f"{kind} nested at most {MAX_CONFIG_DEPTH} levels deep "
                                           f"(settings tables hold numbers, strings and lists)") from None
    except ValueError as exc:  # JSONDecodeError, TOMLDecodeError, integers too long to read
        raise ConfigError(what, str(path), f"valid {kind} ({cut(str(exc), 200)})") from None
    if _depth(data) > MAX_CONFIG_DEPTH:
        raise ConfigError(what, str(path), f"{kind} nested at most {MAX_CONFIG_DEPTH} levels deep")
    return data


#: Deepest nesting a config file may have (materials.<name>.table_angle_deg[i] is 4).
MAX_CONFIG_DEPTH = 8


def _depth(value, level: int = 0) -> int:
    if level > MAX_CONFIG_DEPTH:
        return level
    if isinstance(value, dict):
        return max((_depth(v, level + 1) for v in value.values()), default=level + 1)
    if isinstance(value, list):
        return max((_depth(v, level + 1) for v in value), default=level + 1)
    return level


def dump_config_json(cfg: SimulationConfig) -> str:
    return json.dumps(config_to_dict(cfg), indent=2, sort_keys=False)


def toml_string(text: str) -> str:
    """A TOML basic string: characters as they are (UTF-8), except the quote, the backslash and the control
    characters TOML forbids, which are escaped (JSON's escapes would turn an emoji into a surrogate pair
    \\ud83d\\ude00, which TOML does not accept)."""
    out = []
    for ch in text:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def dump_config_toml(cfg: SimulationConfig) -> str:
    """Minimal TOML writer for the config's flat groups (numbers, strings, booleans)."""
    data = config_to_dict(cfg)

    def fmt(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return toml_string(v)
        if isinstance(v, float):
            return repr(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        return str(v)

    lines = [f"schema_version = {SCHEMA_VERSION}", f"system_type = {fmt(data['system_type'])}", ""]
    for group in GROUPS:
        lines.append(f"[{group}]")
        lines += [f"{k} = {fmt(v)}" for k, v in data[group].items()]
        lines.append("")
    for name, brdf in data["materials"].items():
        lines.append(f"[materials.{toml_string(name)}]")
        lines += [f"{k} = [{', '.join(fmt(x) for x in v)}]" if isinstance(v, (list, tuple)) else f"{k} = {fmt(v)}"
                  for k, v in brdf.items()]
        lines.append("")
    return "\n".join(lines)


def _brdf_from_mapping(data, prefix: str) -> "BRDFSettings":
    """BRDFSettings from a config table; table lists of whole numbers become floats."""
    brdf = _from_mapping(BRDFSettings, data, prefix)
    for name in BRDF_TABLE_FIELDS:
        values = getattr(brdf, name)
        if isinstance(values, (list, tuple)) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                     and finite_number(v) for v in values):
            setattr(brdf, name, [float(v) for v in values])
    return brdf
