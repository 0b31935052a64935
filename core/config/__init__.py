"""Settings layer (bottom of ``core``): the settings dataclasses with their ranges and units, validation,
config files (TOML/JSON) and the values derived from the settings alone.

``core.config`` is the documented public entry point (``from core.config import SimulationConfig``); code inside
``core`` imports from the defining modules, :mod:`.settings`, :mod:`.files` and :mod:`.derived`.
"""
from ..errors import ConfigError
from .derived import n_pulse_times, n_scan_pulses, scan_duration_s
from .settings import (BRDF_TABLE_FIELDS, DEFAULT_BRDF, GROUPS, SCHEMA_VERSION, SYSTEM_TYPES, AtmosphereSettings,
                       BRDFSettings, DetectionSettings, DetectorSettings, GatedSettings, LaserSettings,
                       RangeGateSettings, ReceiverSettings, RunSettings, ScannerSettings, SimulationConfig,
                       field_specs, setting)
from .validate import check_brdf_table, validate, validate_config
from .files import (config_from_dict, config_to_dict, dump_config_json, dump_config_toml, load_config,
                    read_config_file)

__all__ = ["ConfigError", "n_pulse_times", "n_scan_pulses", "scan_duration_s", "BRDF_TABLE_FIELDS", "DEFAULT_BRDF",
           "GROUPS", "SCHEMA_VERSION", "SYSTEM_TYPES", "AtmosphereSettings", "BRDFSettings", "DetectionSettings",
           "DetectorSettings", "GatedSettings", "LaserSettings", "RangeGateSettings", "ReceiverSettings",
           "RunSettings", "ScannerSettings", "SimulationConfig", "check_brdf_table", "config_from_dict",
           "config_to_dict", "dump_config_json", "dump_config_toml", "field_specs", "load_config", "read_config_file",
           "setting", "validate", "validate_config"]
