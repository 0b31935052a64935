"""Validation of the settings: every value against the range, type and choices its ``setting()`` declares,
then the rules that tie settings together (a scan's waveform memory, the gated sweep), each error naming the
setting, the value and what is allowed (:class:`~core.errors.ConfigError`)."""
from __future__ import annotations

import dataclasses
import math

from ..errors import ConfigError
from .derived import n_scan_pulses
from .settings import BRDF_TABLE_FIELDS, AtmosphereSettings, BRDFSettings, ScannerSettings, SimulationConfig
from .tables import aerosol_layer_table, check_channel_table, check_risley

RISLEY_FIELDS = ("risley_prism_hz", "risley_wedge_deg", "risley_index", "risley_phase_deg", "risley_emitters_deg")


def _range_text(meta) -> str:
    lo, hi = meta["lo"], meta["hi"]
    left = "(" if meta["lo_open"] else "["
    right = ")" if meta["hi_open"] else "]"
    unit = f" {meta['unit']}" if meta["unit"] else ""
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    return f"a finite number in {left}{lo_s}, {hi_s}{right}{unit}"


def finite_number(value) -> bool:
    """A finite real number (an integer too large for a float is not)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _check_value(path: str, value, f: dataclasses.Field):
    meta = f.metadata
    if meta.get("choices"):
        if value not in meta["choices"]:
            raise ConfigError(path, value, "one of " + ", ".join(repr(c) for c in meta["choices"]))
        return
    if isinstance(f.default, bool):
        if not isinstance(value, bool):
            raise ConfigError(path, value, "true or false")
        return
    if isinstance(f.default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                raise ConfigError(path, value, "a whole number (not a float) " + _range_text(meta)[2:])
            raise ConfigError(path, value, "a whole number " + _range_text(meta)[2:])
    elif isinstance(f.default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(path, value, _range_text(meta))
        if not finite_number(value):
            raise ConfigError(path, value, _range_text(meta))
    else:
        return
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is not None and (value < lo or (meta["lo_open"] and value == lo)):
        raise ConfigError(path, value, _range_text(meta))
    if hi is not None and (value > hi or (meta["hi_open"] and value == hi)):
        raise ConfigError(path, value, _range_text(meta))


def check_brdf_table(angle_deg, brdf_per_sr, prefix: str = "") -> None:
    """Raise ConfigError unless (angle_deg, brdf_per_sr) is a valid measured BRDF table: equal lengths, at least
    2 rows, real numbers, angles strictly increasing within [0, 90]°, BRDF finite and ≥ 0 (1/sr)."""
    a_path, v_path = f"{prefix}table_angle_deg", f"{prefix}table_brdf_per_sr"
    for path, values in ((a_path, angle_deg), (v_path, brdf_per_sr)):
        if not isinstance(values, (list, tuple)):
            raise ConfigError(path, values, "a list of numbers")
        for i, v in enumerate(values):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not finite_number(v):
                raise ConfigError(f"{path}[{i}]", v, "a finite number")
    if len(angle_deg) != len(brdf_per_sr):
        raise ConfigError(v_path, f"{len(brdf_per_sr)} values",
                          f"one BRDF value per angle ({len(angle_deg)} angles)")
    if len(angle_deg) < 2:
        raise ConfigError(a_path, list(angle_deg), "at least 2 rows (angle, BRDF)")
    for i, a in enumerate(angle_deg):
        if not 0.0 <= a <= 90.0:
            raise ConfigError(f"{a_path}[{i}]", a, "an angle in [0, 90] degrees")
        if i and a <= angle_deg[i - 1]:
            raise ConfigError(f"{a_path}[{i}]", a, f"strictly increasing angles (greater than the previous "
                                                   f"{angle_deg[i - 1]!r} deg)")
    for i, v in enumerate(brdf_per_sr):
        if v < 0.0:
            raise ConfigError(f"{v_path}[{i}]", v, "a BRDF ≥ 0 (1/sr)")


def _check_brdf(brdf: "BRDFSettings", prefix: str) -> None:
    """The table of a BRDF: checked when the model is "table" or a table is present (another model keeps a
    table it does not use, e.g. while the user compares models)."""
    if brdf.model == "table" or any(getattr(brdf, n) != [] for n in BRDF_TABLE_FIELDS):
        check_brdf_table(brdf.table_angle_deg, brdf.table_brdf_per_sr, prefix)


def validate_config(config) -> None:
    """The whole run's settings at an API boundary: a :class:`SimulationConfig` (not None, a dict or another
    settings group) with valid settings; ConfigError otherwise."""
    if not isinstance(config, SimulationConfig):
        raise ConfigError("config", f"a {type(config).__name__}",
                          "a SimulationConfig (core.config; config_from_dict or load_config build one from a "
                          "table of settings)")
    validate(config)


def validate(obj, prefix: str = "") -> None:
    """Check every field of a settings dataclass (recursively); raise ConfigError on the first bad one."""
    if not (dataclasses.is_dataclass(obj) and not isinstance(obj, type)):
        raise ConfigError(prefix.rstrip(".") or "settings", f"a {type(obj).__name__}", "a settings dataclass")
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        path = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            validate(value, path + ".")
        elif isinstance(value, dict) and f.default_factory is dict:  # the materials table (by name)
            for key, sub in value.items():
                if not isinstance(sub, BRDFSettings):
                    raise ConfigError(f"{path}.{key}", sub, "a BRDF settings table")
                validate(sub, f"{path}.{key}.")
        else:
            _check_value(path, value, f)
    if isinstance(obj, BRDFSettings):
        _check_brdf(obj, prefix)
    if isinstance(obj, ScannerSettings):
        check_channel_table(obj)
        if obj.pattern == "risley" or any(getattr(obj, n) != [] for n in RISLEY_FIELDS):
            check_risley(obj)  # (a prism table another pattern keeps is checked too, as BRDF tables are)
    if isinstance(obj, AtmosphereSettings):
        aerosol_layer_table(obj, f"{prefix}aerosol_layers")
    if isinstance(obj, SimulationConfig):
        _check_cross_field(obj)


def _check_cross_field(cfg: SimulationConfig) -> None:
    if cfg.atmosphere.scintillation_model == "gamma_lognormal" and cfg.atmosphere.scintillation_statistics != "wave_optics":
        raise ConfigError("atmosphere.scintillation_model", "gamma_lognormal",
                          "auto, lognormal or gamma_gamma with atmosphere.scintillation_statistics = 'paper' "
                          "(gamma_lognormal is fitted to the wave-optics statistics)")
    if 0.0 < cfg.atmosphere.outer_scale_m < 1.0:
        raise ConfigError("atmosphere.outer_scale_m", cfg.atmosphere.outer_scale_m,
                          "0 (infinite outer scale) or a finite number in [1, 10000] m")
    if 0.0 < cfg.atmosphere.visibility_m < 50.0:
        raise ConfigError("atmosphere.visibility_m", cfg.atmosphere.visibility_m,
                          "0 (off) or a visibility in [50, 1e+06] m")
    _check_weather(cfg)
    if cfg.system_type == "gated":
        _check_gated(cfg)
        return
    if cfg.system_type == "scanner":
        if cfg.scanner.intensity_encoding != "amplitude" and cfg.detector.mode == "noisy":
            raise ConfigError("scanner.intensity_encoding", cfg.scanner.intensity_encoding,
                              "'amplitude' with detector.mode = 'noisy' (reflectivity and 8-bit intensity are "
                              "calibrated against the ideal detector's echo amplitude)")
        n_pulses = n_scan_pulses(cfg)
        cube = n_pulses * cfg.gate.n_bins * 4
        if cfg.run.save_waveforms and cube > cfg.run.max_memory_bytes:
            raise ConfigError("run.save_waveforms", True,
                              f"false for this scan: {n_pulses} pulses × {cfg.gate.n_bins} bins of float32 "
                              f"waveforms need {cube / 2**30:.2f} GiB, more than run.max_memory_bytes = "
                              f"{cfg.run.max_memory_bytes / 2**30:.2f} GiB (or scan fewer pulses, use fewer "
                              f"bins, or raise run.max_memory_bytes)")
        return
    pixels = 1 if cfg.system_type == "profiler" else cfg.receiver.width_px * cfg.receiver.height_px
    cube = pixels * cfg.gate.n_bins * 4
    if cfg.run.save_waveforms and cube > cfg.run.max_memory_bytes:
        max_bins = cfg.run.max_memory_bytes // (4 * cfg.receiver.width_px * cfg.receiver.height_px)
        raise ConfigError("gate.n_bins", cfg.gate.n_bins,
                          f"at most {max_bins} bins for a {cfg.receiver.width_px}×{cfg.receiver.height_px} "
                          f"receiver: the float32 waveform cube would need {cube / 2**30:.2f} GiB, more than "
                          f"run.max_memory_bytes = {cfg.run.max_memory_bytes / 2**30:.2f} GiB "
                          f"(use fewer bins or pixels, set run.save_waveforms = false, or raise "
                          f"run.max_memory_bytes)")


def _check_weather(cfg: SimulationConfig) -> None:
    """atmosphere.weather needs its own inputs (core/atmosphere/weather.py)."""
    atm = cfg.atmosphere
    if atm.weather in ("haze", "fog") and atm.visibility_m == 0.0:
        raise ConfigError("atmosphere.visibility_m", 0.0,
                          f"a visibility in [50, 1e+06] m for atmosphere.weather = {atm.weather!r} "
                          f"(β = α/S from the visibility)")
    if atm.weather in ("rain", "snow") and atm.rain_rate_mm_h == 0.0:
        raise ConfigError("atmosphere.rain_rate_mm_h", 0.0,
                          f"a rate in (0, 300] mm/h for atmosphere.weather = {atm.weather!r}")
    if atm.weather != "none" and cfg.system_type in ("flash", "profiler"):
        pixels = 1 if cfg.system_type == "profiler" else cfg.receiver.width_px * cfg.receiver.height_px
        cube = pixels * cfg.gate.n_bins * 4
        if cube > cfg.run.max_memory_bytes:
            raise ConfigError("atmosphere.weather", atm.weather,
                              f"'none' for this receiver, or fewer pixels or bins: the weather returns fill "
                              f"every pixel's whole gate, a float32 cube of {cube / 2**30:.2f} GiB, more than "
                              f"run.max_memory_bytes = {cfg.run.max_memory_bytes / 2**30:.2f} GiB")


#: range_method peak: the largest slice step per (pulse FWHM + shutter edge).
PEAK_MAX_STEP_PER_EDGE = 2.0


def _check_gated(cfg: SimulationConfig) -> None:
    g = cfg.gated
    if g.range_method == "two_gate":
        if g.n_slices < 2:
            raise ConfigError("gated.n_slices", g.n_slices, "at least 2 for the two-gate ratio method")
        if abs(g.delay_step_s - g.gate_width_s) > 1e-9 * g.gate_width_s:
            raise ConfigError("gated.delay_step_s", g.delay_step_s,
                              f"equal to gated.gate_width_s = {g.gate_width_s:g} s for the two-gate ratio method "
                              f"(adjacent gates), or choose range_method centroid or peak")
        if g.shutter_edge_s > 0:
            raise ConfigError("gated.shutter_edge_s", g.shutter_edge_s,
                              "0 (a rectangular gate) for the two-gate ratio method")
        if cfg.laser.pulse_fwhm_s > g.gate_width_s:
            raise ConfigError("laser.pulse_fwhm_s", cfg.laser.pulse_fwhm_s,
                              f"at most gated.gate_width_s = {g.gate_width_s:g} s for the two-gate ratio method "
                              f"(the pulse must fit in one gate)")
    if g.range_method == "peak":
        # the fit places the profile from the slices on its edges (pulse + shutter edge wide): a sweep stepping
        # over them, or over whole gates, cannot locate it to a fraction of the step (tests/core/systems/
        # test_gated.py: ≤ 0.09 × the step RMS over the accepted grid, ≤ 0.2 required)
        edge = cfg.laser.pulse_fwhm_s + g.shutter_edge_s
        if g.delay_step_s > PEAK_MAX_STEP_PER_EDGE * edge * (1 + 1e-9):
            raise ConfigError("gated.delay_step_s", g.delay_step_s,
                              f"at most {PEAK_MAX_STEP_PER_EDGE:g} × (laser.pulse_fwhm_s + gated.shutter_edge_s) = "
                              f"{PEAK_MAX_STEP_PER_EDGE * edge:g} s for range_method peak (smaller steps, a longer "
                              f"pulse or shutter edge, or range_method centroid)")
        if g.delay_step_s > g.gate_width_s * (1 + 1e-9):
            raise ConfigError("gated.delay_step_s", g.delay_step_s,
                              f"at most gated.gate_width_s = {g.gate_width_s:g} s for range_method peak (a step "
                              f"longer than the gate leaves ranges no slice sees)")
    stack = cfg.receiver.width_px * cfg.receiver.height_px * g.n_slices * 8
    if stack > cfg.run.max_memory_bytes:  # the first of several stacks (the run's whole estimate: engine.memory)
        raise ConfigError("gated.n_slices", g.n_slices,
                          f"fewer slices: the float64 slice stack alone would need {stack / 2**30:.2f} GiB, more "
                          f"than run.max_memory_bytes = {cfg.run.max_memory_bytes / 2**30:.2f} GiB")
