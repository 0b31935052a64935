"""The mapping between core settings and Blender properties, without Blender (testable in plain Python).

One :class:`FieldMap` per core setting that has a home in a .blend: which group and property it is stored in,
its kind, default, range and unit, and the conversion between the SI value of the core and the value Blender
stores (nanometres for wavelengths, powers of ten for tiny values, Blender units for distances, MiB for large
byte counts; ``ladar_addon.properties`` documents where every setting lives).  ``properties.py`` builds the
PropertyGroups from these maps; ``blend_config.py`` reads and writes a SimulationConfig through them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal

import numpy as np

from ..core.config.settings import BRDFSettings, GROUPS, RunSettings, SimulationConfig, field_specs
from ..core.errors import ConfigError

INT32_MAX = 2**31 - 1
MIB = 2**20

CORE_GROUPS = {g: type(getattr(SimulationConfig(), g)) for g in GROUPS}
#: Settings groups stored on the scene (``Scene.ladar_<group>``); every other core group is a sensor setting.
SCENE_GROUPS = {"atmosphere": CORE_GROUPS["atmosphere"]}
#: Settings groups stored on the sensor object (``Object.ladar.<group>``): laser, receiver, gate, detection, run
#: and any group the core adds later.
SENSOR_GROUPS = {g: cls for g, cls in CORE_GROUPS.items() if g not in SCENE_GROUPS}
#: Settings not stored as sensor properties (derived from the camera, or kept on the scene).
NOT_ON_SENSOR = {("receiver", "fov_x_rad"), ("receiver", "fov_y_rad"), ("run", "seed")}
#: Receiver size of a new sensor (the core default may differ).
SENSOR_DEFAULT_OVERRIDES = {("receiver", "width_px"): 64, ("receiver", "height_px"): 64}

#: Name suffixes that spell a field's unit (stripped from the label; the unit shows through the subtype or
#: in parentheses).  Keyed by the unit, so "specular_a" (no unit) keeps its "A".
_UNIT_SUFFIXES = {"m": "_m", "s": "_s", "J": "_j", "rad": "_rad", "px": "_px", "B": "_bytes", "1/m": "_per_m",
                  "1/s": "_per_s", "A": "_a", "e-": "_e", "m^-2/3": "_m_23"}
_ACRONYMS = {"Fwhm": "FWHM", "Fov": "FOV", "Brdf": "BRDF", "Cn2": "Cn²", "Apd": "APD", "Adc": "ADC",
             "Dof": "DOF"}


def label(name: str, unit: str = "") -> str:
    suffix = _UNIT_SUFFIXES.get(unit)
    if suffix and name.endswith(suffix) and len(name) > len(suffix):
        name = name[: -len(suffix)]
    words = [w.capitalize() for w in name.split("_")]
    return " ".join(_ACRONYMS.get(w, w) for w in words)


def shortest_float32(value: float) -> str:
    """The shortest decimal string that rounds to the same float32 as ``value``."""
    return str(np.float32(value))


@dataclass(frozen=True)
class FieldMap:
    """How one core setting maps onto one Blender property."""

    group: str | None      # core group ("laser", ...), None for top-level settings, "brdf" for BRDFSettings
    name: str              # core field name
    attr: str              # Blender property name
    kind: str              # "float", "int", "bool" or "enum"
    default: object        # core default (SI)
    meta: dict
    conversion: str = ""   # "", "nm", "pow10", "distance" or "mib"
    exponent: int = 0      # "nm": −9; "pow10": Blender stores the value in units of 10^exponent

    @property
    def path(self) -> str:
        return self.name if self.group in (None, "brdf") else f"{self.group}.{self.name}"

    @property
    def subtype(self) -> str:
        """The Blender subtype the core asks for ("NONE" if none); properties.py falls back to "NONE" where this
        Blender lacks it."""
        return self.meta.get("subtype") or "NONE"

    def unit_text(self) -> str:
        if self.conversion == "nm":
            return "nm"
        if self.conversion == "pow10":
            unit = self.meta.get("unit") or ""
            return f"×1e{self.exponent} {unit}".rstrip()
        if self.conversion == "mib":
            return "MiB"
        if self.conversion == "distance":
            return "Blender units = m / unit scale"
        return self.meta.get("unit") or ""

    # -- conversions ------------------------------------------------------------------------------------------
    def to_blender(self, value, unit_scale: float = 1.0):
        if self.kind == "float":
            value = float(value)
            if self.conversion in ("nm", "pow10"):
                return float(Decimal(repr(value)).scaleb(-self.exponent))
            if self.conversion == "distance":
                return value / unit_scale
            return value
        if self.kind == "int" and self.conversion == "mib":
            return max(1, int(round(value / MIB)))
        if self.kind == "int":
            hi = self.meta.get("hi")
            if value > INT32_MAX:
                raise ConfigError(self.path, value, f"at most {INT32_MAX} when stored in a .blend"
                                  + (f" (the simulator accepts up to {hi} from a config file)" if hi else ""))
            return int(value)
        return value

    def to_core(self, value, unit_scale: float = 1.0):
        if self.kind == "float":
            text = shortest_float32(value)
            if self.conversion in ("nm", "pow10"):
                return float(Decimal(text).scaleb(self.exponent))
            if self.conversion == "distance":
                return float(text) * unit_scale
            v, lo, hi = float(text), self.meta.get("lo"), self.meta.get("hi")
            # A bound float32 cannot hold (2π) is stored rounded outwards: it reads back as the bound itself.
            if hi is not None and v > hi and np.float32(hi) == np.float32(value):
                return float(hi)
            if lo is not None and v < lo and np.float32(lo) == np.float32(value):
                return float(lo)
            return v
        if self.kind == "int" and self.conversion == "mib":
            return int(value) * MIB
        if self.kind == "int":
            return int(value)
        if self.kind == "bool":
            return bool(value)
        return str(value)

    def description(self) -> str:
        doc = self.meta.get("doc", "")
        unit = self.unit_text()
        text = doc + (f" [{unit}]" if unit else "")
        path = f"materials.<name>.{self.name}" if self.group == "brdf" else self.path
        return f"{text}. Config: {path}"


def field_map(group, name, default, meta) -> FieldMap:
    if meta.get("choices"):
        kind = "enum"
    elif isinstance(default, bool):
        kind = "bool"
    elif isinstance(default, int):
        kind = "int"
    elif isinstance(default, float):
        kind = "float"
    else:  # pragma: no cover - the core declares only these
        raise TypeError(f"setting {group}.{name} has an unsupported type {type(default).__name__}")
    default = SENSOR_DEFAULT_OVERRIDES.get((group, name), default)
    conversion, attr, exponent = "", name, 0
    hi = meta.get("hi")
    if kind == "float" and meta.get("subtype") == "WAVELENGTH":
        conversion, exponent = "nm", -9
    elif kind == "float" and (meta.get("subtype") or "NONE") == "NONE" and hi is not None and 0 < hi < 1e-3:
        # Values far below what a six-decimal field shows (Cn² ~ 1e-14): store them in units of 10^exponent,
        # so the largest allowed value shows as 1000.
        conversion, exponent = "pow10", int(math.floor(math.log10(hi))) - 3
    elif kind == "float" and (meta.get("subtype") or "NONE") == "NONE" and 0 < abs(default) < 1e-4:
        # A tiny default (dark current ~ 1e-12 A): the default shows as 1 in units of 10^exponent.
        conversion, exponent = "pow10", int(math.floor(math.log10(abs(default))))
    elif kind == "float" and meta.get("subtype") == "DISTANCE":
        conversion = "distance"
    elif kind == "int" and meta.get("unit") == "B" and (meta.get("hi") or 0) > INT32_MAX:
        conversion, attr = "mib", name.removesuffix("_bytes") + "_mib"
    return FieldMap(group, name, attr, kind, default, meta, conversion, exponent)


def group_field_maps(group: str, cls, skip=()) -> list[FieldMap]:
    return [field_map(group, n, d, m) for n, d, m in field_specs(cls) if (group, n) not in skip]


#: Field maps of every Blender-stored setting, by group.
SENSOR_FIELDS = {g: group_field_maps(g, cls, NOT_ON_SENSOR) for g, cls in SENSOR_GROUPS.items()}
#: Top-level plain settings (``system_type``), stored on ``Object.ladar``.
TOP_FIELDS = group_field_maps(None, SimulationConfig)
SYSTEM_TYPE_FIELD = next(f for f in TOP_FIELDS if f.name == "system_type")
ATMOSPHERE_FIELDS = group_field_maps("atmosphere", SCENE_GROUPS["atmosphere"])
BRDF_FIELDS = group_field_maps("brdf", BRDFSettings)
SEED_FIELD = next(field_map("run", n, d, m) for n, d, m in field_specs(RunSettings) if n == "seed")


def all_core_paths() -> set:
    """Dotted paths of every core setting that has a home in Blender (for the 1:1 test)."""
    paths = {f.path for f in TOP_FIELDS} | {SEED_FIELD.path, "receiver.fov_x_rad", "receiver.fov_y_rad"}
    for fields in SENSOR_FIELDS.values():
        paths |= {f.path for f in fields}
    paths |= {f.path for f in ATMOSPHERE_FIELDS}
    return paths


