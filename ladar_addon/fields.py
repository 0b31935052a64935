"""The mapping between core settings and Blender properties, without Blender (testable in plain Python).

One :class:`FieldMap` per core setting that has a home in a .blend: which group and property it is stored in,
its kind, default, range, label and unit, and the conversion between the SI value of the core and the value
Blender stores: the setting's *panel unit* (``core.config.settings.PANEL_UNITS``: ns, mJ, fJ, mrad, nm, 1/km,
kHz, pA, ...; a decimal power of ten, converted exactly), Blender units for distances, MiB for large byte
counts; ``ladar_addon.properties`` documents where every setting lives.  This module is the one place where
a panel value becomes an SI value and back (:meth:`FieldMap.to_blender`, :meth:`FieldMap.to_core`).

Properties whose stored unit changed (issue 27: times were stored in seconds, energies in joules, ...) got a new
name (``pulse_fwhm_s`` → ``pulse_fwhm_ns``); :attr:`FieldMap.legacy_attr` names the old property, which a
.blend saved before the change still holds (read as before: :func:`legacy_si`; the panel properties are set from
it on load: :func:`ladar_addon.blend_config.migrate_legacy_units`) and which :func:`write_value` uses to keep the
exact double-precision SI value.  ``properties.py`` builds the PropertyGroups from these maps;
``blend_config.py`` reads and writes a SimulationConfig through them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal

import numpy as np

from ..core.config.settings import PANEL_UNITS, BRDFSettings, GROUPS, RunSettings, SimulationConfig, field_specs
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
    """A title made from a setting's name (only for settings the schema gives no ``label``)."""
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
    conversion: str = ""   # "", "pow10", "distance" or "mib"
    exponent: int = 0      # "pow10": Blender stores the value in units of 10^exponent (the panel unit)
    legacy_attr: str = ""  # the property that held this setting before its stored unit changed ("" if none)
    legacy_exponent: int = 0  # ... in units of 10^legacy_exponent (0: SI)

    @property
    def path(self) -> str:
        return self.name if self.group in (None, "brdf") else f"{self.group}.{self.name}"

    @property
    def subtype(self) -> str:
        """The Blender subtype: "NONE" for a setting with a panel unit (Blender's units cannot show ns, fJ, ...:
        the unit is in the label), else the one the core asks for ("NONE" if none); properties.py falls back to
        "NONE" where this Blender lacks it."""
        if self.meta.get("panel_unit"):
            return "NONE"
        return self.meta.get("subtype") or "NONE"

    @property
    def label(self) -> str:
        """The name a person reads in the panels (the schema's ``label``), without the unit."""
        return self.meta.get("label") or label(self.name, self.meta.get("unit") or "")

    def choice_label(self, choice: str) -> str:
        return (self.meta.get("choice_labels") or {}).get(choice) or choice.replace("_", " ").capitalize()

    def unit_text(self) -> str:
        """The unit of the stored (and shown) value."""
        if self.meta.get("panel_unit"):
            return self.meta["panel_unit"]
        if self.conversion == "distance":
            return "Blender units = m / unit scale"
        return self.meta.get("unit") or ""

    # -- conversions ------------------------------------------------------------------------------------------
    def to_blender(self, value, unit_scale: float = 1.0):
        if self.kind == "float":
            value = float(value)
            if self.conversion == "pow10":
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
            if self.conversion == "pow10":
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

    def readable(self, si) -> str:
        """What the panel adds beside a field whose panel unit does not suit the value (issue 27): a Blender
        property has one static unit, so 0.1 J in a µJ field reads "100000"; for energies and times (J, s) whose
        panel number is outside [1, 1000) this is the value on the SI prefix that puts it there ("100 mJ",
        "13.24 µs", core.fileio.run_folder.format_si), else "" (the field reads well by itself)."""
        from ..core.fileio.run_folder import format_si

        unit = self.meta.get("unit") or ""
        if self.conversion != "pow10" or unit not in ("J", "s") or not si:
            return ""
        shown = abs(self.to_blender(si))  # the panel number, in decimal arithmetic (1e-6 s is 1000 ns, not 999.99…)
        return "" if 1.0 <= shown < 1000.0 else format_si(si, unit)

    def legacy_to_core(self, value) -> float:
        """The SI value held in the legacy property (``legacy_attr``): a single-precision float of a file saved
        before the change, read as the add-on read it then (shortest decimal of the float32, scaled by
        10^legacy_exponent), or the double-precision SI value :func:`write_value` keeps there since."""
        value = float(value)
        if float(np.float32(value)) != value:  # a double: the exact SI value written by write_value
            return value
        return float(Decimal(shortest_float32(value)).scaleb(self.legacy_exponent))

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
    conversion, attr, exponent, legacy_attr, legacy_exponent = "", name, 0, "", 0
    panel_unit = meta.get("panel_unit") or ""
    power = PANEL_UNITS[panel_unit][1] if panel_unit else 0
    if kind == "float" and power:
        # Stored and shown in the panel unit (ns, mJ, ...): SI value = stored value × 10^power, exactly.
        conversion, exponent = "pow10", power
        old = _stored_exponent_before_issue_27(meta, default)
        if old != exponent:  # a new name, so that a .blend holding the old value is not misread
            attr = _renamed(name, meta.get("unit") or "", panel_unit)
            legacy_attr, legacy_exponent = name, old
    elif kind == "float" and meta.get("subtype") == "DISTANCE" and not panel_unit:
        conversion = "distance"
    elif kind == "int" and meta.get("unit") == "B" and (meta.get("hi") or 0) > INT32_MAX:
        conversion, attr = "mib", name.removesuffix("_bytes") + "_mib"
    return FieldMap(group, name, attr, kind, default, meta, conversion, exponent, legacy_attr, legacy_exponent)


#: Name suffix of a property stored in a panel unit, replacing the SI suffix of the setting's name.
_PANEL_SUFFIXES = {"ns": "_ns", "µJ": "_uj", "fJ": "_fj", "mrad": "_mrad", "1/km": "_per_km", "kHz": "_khz",
                   "pA": "_pa", "nA": "_na", "nm": "_nm"}


def _renamed(name: str, unit: str, panel_unit: str) -> str:
    suffix = _UNIT_SUFFIXES.get(unit) or ("_hz" if unit == "Hz" else "")
    base = name[: -len(suffix)] if suffix and name.endswith(suffix) else name
    return base + _PANEL_SUFFIXES[panel_unit]


def _stored_exponent_before_issue_27(meta: dict, default) -> int:
    """The power of ten a float setting was stored in before the panel units (what old .blend files hold):
    nanometres for wavelengths, a power of ten for tiny unit-less values, else SI.  Frozen: only migration uses
    it."""
    subtype, hi = meta.get("subtype") or "NONE", meta.get("hi")
    if subtype == "WAVELENGTH":
        return -9
    if subtype == "NONE" and hi is not None and 0 < hi < 1e-3:
        return int(math.floor(math.log10(hi))) - 3
    if subtype == "NONE" and isinstance(default, float) and 0 < abs(default) < 1e-4:
        return int(math.floor(math.log10(abs(default))))
    return 0


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




# ------------------------------------------------------------------------------------------------------------
# Reading and writing a property group (duck-typed: a Blender PropertyGroup, or anything with getattr/get)
# ------------------------------------------------------------------------------------------------------------
def _stored(props, key):
    """The raw value stored under ``key`` in a property group's ID properties (None when it holds none)."""
    try:
        return props.get(key)
    except (AttributeError, TypeError):
        return None


def legacy_si(props, f: FieldMap):
    """The SI value held in ``f.legacy_attr`` (the property's name before its stored unit changed), while it
    stands: the panel property is not stored yet, or holds exactly the float32 of that value in the panel unit (a
    value typed in the panel since then wins).  A .blend saved before the change holds the old single-precision
    SI value there, read as the add-on read it then, so an old file gives the same SI values bit for bit;
    :func:`write_value` keeps the exact double-precision SI value there, so an SI value set through the API or a
    config file comes back bit for bit whatever its digits (None when there is none)."""
    if not f.legacy_attr:
        return None
    old = _stored(props, f.legacy_attr)
    if old is None:
        return None
    si = f.legacy_to_core(old)
    new = _stored(props, f.attr)
    if new is None or np.float32(new) == np.float32(f.to_blender(si)):
        return si
    return None


def read_value(props, f: FieldMap, unit_scale: float = 1.0):
    """The SI value of setting ``f`` held by ``props`` (the one place a stored value becomes an SI value)."""
    si = legacy_si(props, f)
    return si if si is not None else f.to_core(getattr(props, f.attr), unit_scale)


def write_value(props, f: FieldMap, value, unit_scale: float = 1.0) -> None:
    """Store the SI ``value`` of setting ``f`` in ``props``: in its stored (panel) unit, and where the setting
    has a legacy property, the exact SI value in it too (:func:`legacy_si`)."""
    setattr(props, f.attr, f.to_blender(value, unit_scale))
    if f.legacy_attr:
        if float(np.float32(value)) != float(value):
            props[f.legacy_attr] = float(value)  # an ID property of double precision
        elif _stored(props, f.legacy_attr) is not None:
            del props[f.legacy_attr]  # single precision: the panel value holds it exactly


def migrate_group(props, fields) -> int:
    """Give the properties of ``props`` whose stored unit changed the value their legacy property holds (a .blend
    saved before the change), so the panels show it; the legacy value is kept (it is the exact SI value,
    :func:`legacy_si`).  Returns how many properties were set."""
    n = 0
    for f in fields:
        if f.legacy_attr and _stored(props, f.attr) is None:
            si = legacy_si(props, f)
            if si is not None:
                setattr(props, f.attr, f.to_blender(si))
                n += 1
    return n
