"""Config files: a SimulationConfig to and from plain dicts, JSON and TOML (``schema_version`` 1).

A file overrides any subset of the settings (keys present override the base config, default settings if none);
every value is validated on the way in (:func:`~.settings.validate`), naming the setting, the value and the
allowed range.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ..errors import ConfigError
from .settings import BRDF_TABLE_FIELDS, GROUPS, SCHEMA_VERSION, BRDFSettings, SimulationConfig
from .validate import validate


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
            if isinstance(f.default, float) and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            kwargs[key] = value
    return cls(**kwargs)


def config_to_dict(cfg: SimulationConfig) -> dict:
    """Plain nested dict (JSON/TOML-ready) with the schema version."""
    data = {"schema_version": SCHEMA_VERSION}
    data.update(dataclasses.asdict(cfg))
    return data


def config_from_dict(data: dict, base: SimulationConfig | None = None) -> SimulationConfig:
    """Build and validate a config from a dict.  Keys present override ``base`` (default settings if None)."""
    if not isinstance(data, dict):
        raise ConfigError("config", type(data).__name__, "a table of settings")
    data = dict(data)
    version = data.pop("schema_version", SCHEMA_VERSION)
    if version != SCHEMA_VERSION:
        raise ConfigError("schema_version", version, f"{SCHEMA_VERSION} (this version of the simulator)")
    merged = config_to_dict(base) if base is not None else config_to_dict(SimulationConfig())
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
    path = Path(path)
    if not path.is_file():
        raise ConfigError("config file", str(path), "an existing .json or .toml file")
    text = path.read_text(encoding="utf-8")
    try:
        if path.suffix.lower() == ".toml":
            import tomllib
            data = tomllib.loads(text)
        elif path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            raise ConfigError("config file", str(path), "a file ending in .json or .toml")
    except (json.JSONDecodeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError("config file", str(path), f"valid {path.suffix[1:].upper()} ({exc})") from exc
    return config_from_dict(data, base)


def dump_config_json(cfg: SimulationConfig) -> str:
    return json.dumps(config_to_dict(cfg), indent=2, sort_keys=False)


def dump_config_toml(cfg: SimulationConfig) -> str:
    """Minimal TOML writer for the config's flat groups (numbers, strings, booleans)."""
    data = config_to_dict(cfg)

    def fmt(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, float):
            return repr(v)
        return str(v)

    lines = [f"schema_version = {SCHEMA_VERSION}", f"system_type = {fmt(data['system_type'])}", ""]
    for group in GROUPS:
        lines.append(f"[{group}]")
        lines += [f"{k} = {fmt(v)}" for k, v in data[group].items()]
        lines.append("")
    for name, brdf in data["materials"].items():
        lines.append(f"[materials.{json.dumps(name)}]")
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
                                                     for v in values):
            setattr(brdf, name, [float(v) for v in values])
    return brdf
