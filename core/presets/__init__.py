"""Real-sensor presets: one TOML file per instrument in ``core/presets/sensors/<name>.toml`` (issue 29).

A preset file holds

* config-file sections — ``system_type`` and the settings groups ``export-config`` writes (``[laser]``,
  ``[receiver]``, ``[gate]``, ``[scanner]``, ``[gated]``, ``[detection]``, ``[detector]``, ...): the settings the
  preset sets, validated like every other setting (:func:`core.config.files.config_from_dict`);
* a ``[published]`` table: the maker's figures the preset is checked against (tests/core/test_sensor_presets.py,
  docs/sensors.md).  It is metadata, never a setting.  Keys (:data:`PUBLISHED_KEYS`): omit those that do not
  apply.  ``[published.conditions.atmosphere]`` holds the scene the figures are stated under (e.g. "at 100 klx":
  the sun): the checks apply it (:func:`preset_config`), applying the preset never does.

A preset describes a sensor: the scene's groups (:data:`ENVIRONMENT_GROUPS`, the atmosphere) are refused in its
settings, naming the file (the Blender add-on keeps them on the scene, not on the sensor camera).

A config file selects a preset with a top-level ``preset = "velodyne_vlp16"`` (a name of :func:`list_presets`, or
the path of the user's own preset file ending in ``.toml``): the preset's settings are applied first, then the
file's other keys (``resolve_preset``).  No ``bpy`` here: the add-on's preset menu and the CLI call this module.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from ..config.files import config_from_dict
from ..config.preset_files import (ENVIRONMENT_GROUPS, SENSORS_DIR, list_presets, preset_path, read_preset,
                                   resolve_preset)
from ..errors import ConfigError

#: Keys of a preset's ``[published]`` table: key → (types, meaning).  Angles in degrees, ranges in metres,
#: reflectivities as fractions (0.8 = 80 %).
PUBLISHED_KEYS = {
    "maker": (str, "manufacturer (or the laboratory of a research instrument)"),
    "model": (str, "instrument name"),
    "sources": (list, 'documents the figures come from: "maker, document, revision" each'),
    "fov_h_deg": ((int, float), "horizontal field of view, degrees"),
    "fov_v_deg": ((int, float), "vertical field of view, degrees"),
    "channels": (int, "channels (lasers) of a scanner"),
    "channel_elevations_deg": (list, "elevation of every channel, degrees (any order)"),
    "width_px": (int, "detector columns of a camera"),
    "height_px": (int, "detector rows of a camera"),
    "points_per_s": ((int, float), "points (measurements) per second, single return"),
    "rotation_hz": ((int, float), "rotation rate (or scan-line rate) at which points_per_s is stated"),
    "max_range_m": ((int, float), "maximum range at max_range_reflectivity (the figure the pulse energy is "
                                  "derived from)"),
    "max_range_reflectivity": ((int, float), "Lambertian reflectivity of max_range_m (fraction)"),
    "second_range_m": ((int, float), "maximum range at second_reflectivity: the figure the simulator is "
                                     "checked against"),
    "second_reflectivity": ((int, float), "Lambertian reflectivity of second_range_m (fraction)"),
    "second_range_channel": (int, "the channel (channel-table row, from 1) second_range_m is stated for: the "
                                  "probe fires at that channel's relative_pulse_energy"),
    "second_range_derives": (str, "what is derived from second_range_m (the range equation, not the "
                                  "simulator): then checked for consistency, P within 3 binomial standard "
                                  "errors of the maker's definition at R and below it at 1.2 R"),
    "detected_range_m": ((int, float), "a range at which the source reports the target detected (checked: "
                                       "detection probability ≥ 0.5 there; no maximum implied)"),
    "detected_reflectivity": ((int, float), "Lambertian reflectivity of detected_range_m (fraction)"),
    "precision_m": ((int, float), "range precision (1 σ) the maker states"),
    "precision_range_m": ((int, float), "range at which precision_m is checked"),
    "precision_reflectivity": ((int, float), "Lambertian reflectivity of the precision check (fraction)"),
    "precision_at_snr": (list, "range precision (1σ, m) at stated peak SNRs: rows [snr, sigma_m] (checked where the "
                               "simulated echoes' median SNR is snr)"),
    "range_detection_probability": ((int, float), "detection probability at which the maker defines its maximum "
                                                  "ranges (fraction; 0.5 where the maker states none)"),
    "false_alarm_rate": ((int, float), "false alarms per pulse over the range window 0 … max_range_m the maker "
                                       "states (the figure the detection threshold is derived from)"),
    "not_reproduced": (dict, "figures this model does not reproduce: key = the reason (that figure's check is "
                             "expected to fail, and the test asserts it does)"),
    "conditions": (dict, "the scene the figures are stated under, as settings groups of the environment "
                         "([published.conditions.atmosphere], e.g. the sun of a figure stated at 100 klx): applied "
                         "by the checks, never when the preset is applied"),
}


#: Keys of ``[published]`` whose check can be declared not reproduced.
CHECKED_KEYS = ("fov_h_deg", "fov_v_deg", "channels", "channel_elevations_deg", "points_per_s", "width_px",
                "height_px", "second_range_m", "detected_range_m", "precision_m", "precision_at_snr")



@dataclasses.dataclass(frozen=True)
class Preset:
    """A sensor preset: ``settings`` (``system_type`` and settings groups, SI units, as in a config file) and
    ``published`` (the maker's figures, :data:`PUBLISHED_KEYS`)."""

    name: str
    path: Path
    settings: dict
    published: dict

    @property
    def title(self) -> str:
        p = self.published
        return f"{p.get('maker', '')} {p.get('model', self.name)}".strip()


def _check_published(published, where: str) -> dict:
    if not isinstance(published, dict):
        raise ConfigError(f"{where}published", published, "a table of the maker's figures")
    for key, value in published.items():
        if key not in PUBLISHED_KEYS:
            raise ConfigError(f"{where}published.{key}", value, "a known key: " + ", ".join(PUBLISHED_KEYS))
        types, meaning = PUBLISHED_KEYS[key]
        if isinstance(value, bool) or not isinstance(value, types):
            raise ConfigError(f"{where}published.{key}", value, meaning)
        if key == "sources":
            if not value or not all(isinstance(s, str) and s.strip() for s in value):
                raise ConfigError(f"{where}published.sources", value, "a non-empty list of document names")
        elif key == "channel_elevations_deg":
            for i, v in enumerate(value):
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > 90:
                    raise ConfigError(f"{where}published.channel_elevations_deg[{i}]", v,
                                      "an elevation in degrees within [-90, 90]")
        elif key == "precision_at_snr":
            for i, pair in enumerate(value):
                if (not isinstance(pair, list) or len(pair) != 2
                        or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                               or v <= 0 for v in pair)):
                    raise ConfigError(f"{where}published.precision_at_snr[{i}]", pair,
                                      "a row [snr, sigma_m] of two finite numbers > 0")
        elif key == "conditions":
            for group, values in value.items():
                if group not in ENVIRONMENT_GROUPS or not isinstance(values, dict):
                    raise ConfigError(f"{where}published.conditions.{group}", values,
                                      "a table of settings of the scene's groups: " + ", ".join(ENVIRONMENT_GROUPS))
        elif key == "not_reproduced":
            for k, why in value.items():
                if k not in CHECKED_KEYS or k not in published:
                    raise ConfigError(f"{where}published.not_reproduced.{k}", why,
                                      "a checked figure given in [published]: " + ", ".join(CHECKED_KEYS))
                if not isinstance(why, str) or not why.strip():
                    raise ConfigError(f"{where}published.not_reproduced.{k}", why, "the reason, as text")
        elif not isinstance(value, str):
            if not math.isfinite(value) or value <= 0:
                raise ConfigError(f"{where}published.{key}", value, f"a finite number > 0 ({meaning})")
            if (key.endswith("reflectivity") or key in ("range_detection_probability", "false_alarm_rate")) \
                    and value > 1.0:
                raise ConfigError(f"{where}published.{key}", value, "a reflectivity fraction in (0, 1]")
    for a, b in (("max_range_m", "max_range_reflectivity"), ("second_range_m", "second_reflectivity"),
                 ("precision_range_m", "precision_m"),
                 ("detected_range_m", "detected_reflectivity")):
        if (a in published) != (b in published):
            missing = b if a in published else a
            raise ConfigError(f"{where}published.{missing}", None, f"given together with {a if missing == b else b}")
    for key in ("second_range_channel", "second_range_derives"):
        if key in published and "second_range_m" not in published:
            raise ConfigError(f"{where}published.second_range_m", None, f"given with {key}")
    if "false_alarm_rate" in published and "max_range_m" not in published:
        raise ConfigError(f"{where}published.max_range_m", None, "given with false_alarm_rate (its range window)")
    return dict(published)


def load_preset(name_or_path) -> Preset:
    """Read and validate a preset (a shipped name or a user's ``.toml`` file).  Its settings are checked as a
    config (every setting's range, on top of the default settings); a bad key or value is a one-line
    ConfigError naming the file, the key and the value."""
    path, data, published = read_preset(name_or_path)
    where = f"preset {path.stem}: "
    published = _check_published(published, where)
    try:
        config_from_dict(_with_conditions(data, published))
    except ConfigError as exc:
        raise ConfigError(f"{where}{exc.field}", exc.value, exc.allowed) from None
    return Preset(path.stem, path, data, published)


def _with_conditions(settings: dict, published: dict) -> dict:
    """The preset's settings with the groups of ``[published.conditions]`` added."""
    return {**settings, **{g: dict(v) for g, v in (published.get("conditions") or {}).items()}}


def preset_settings(name_or_path) -> dict:
    """The settings a preset sets (a config-file table: ``system_type`` and groups), without ``[published]``."""
    return load_preset(name_or_path).settings


def preset_config(name_or_path, base=None):
    """The SimulationConfig a preset's figures are checked under, validated: ``base`` (default settings if None)
    with the preset's settings and its ``[published.conditions]`` (the scene of the figures) applied.  Applying the
    preset itself (:func:`preset_settings`, a config file's ``preset`` key, the Blender menu) sets no conditions."""
    preset = load_preset(name_or_path)
    return config_from_dict(_with_conditions(preset.settings, preset.published), base)


__all__ = ["CHECKED_KEYS", "ENVIRONMENT_GROUPS", "PUBLISHED_KEYS", "Preset", "SENSORS_DIR", "list_presets",
           "load_preset", "preset_config", "preset_path", "preset_settings", "resolve_preset"]
