"""Issue 27: every ladar property is shown in a unit a person reads, under a label written for people, and the
panel value converts to the SI value of the core and back exactly (``ladar_addon.fields``: the one place).

The displayed string is Blender's own: ``bpy.utils.units.to_string`` with the property's RNA unit and precision
(for a unit-less property Blender prints the bare number and the unit is the one in the label).  It must not show
``0`` for a value that is not zero, nor more than 4 leading zeros, and its unit must be the one docs/settings.md
gives in its "in the panels" column."""
import math
import re
from decimal import Decimal
from pathlib import Path

import bpy
import numpy as np
import pytest

from blender_scenes import add_camera

DOCS = Path(__file__).resolve().parents[2] / "docs" / "settings.md"
#: Metric length units Blender's formatter may choose for a DISTANCE ("m, the scene's length unit").
LENGTH_UNITS = {"km", "m", "cm", "mm", "µm"}
#: Representative SI values beside the default and the allowed range's ends (what sample scenes and presets use).
TYPICAL = {
    "laser.pulse_energy_j": [2e-7, 50e-6, 0.02, 0.1], "laser.pulse_fwhm_s": [1e-9, 3e-9, 10e-9],
    "laser.beam_divergence_rad": [1e-4, 2.2e-4, 1e-3], "laser.wavelength_m": [532e-9, 905e-9, 1.55e-6],
    "gate.gate_start_s": [6.67e-7, 6.337718e-7, 1.3243e-5], "gate.bin_width_s": [0.2e-9, 0.5e-9, 1e-9],
    "gated.first_delay_s": [6.611248e-06, 9.7e-7], "gated.delay_step_s": [3.335641e-09, 1e-9],
    "gated.gate_width_s": [20e-9, 40e-9], "gated.shutter_edge_s": [1e-9, 2e-9], "gated.min_signal_j": [1e-16],
    "detection.threshold_j": [1e-16, 2.5e-15], "atmosphere.extinction_per_m": [1e-4, 3e-4, 2e-3],
    "atmosphere.cn2_m_23": [1e-16, 5e-15, 1e-13], "scanner.pulse_rate_hz": [20_000.0, 100_000.0, 1e6],
    "detector.dark_current_bulk_a": [1e-11], "detector.dark_current_surface_a": [5e-9],
    "laser.beam_waist_radius_m": [0.005, 0.02], "receiver.aperture_diameter_m": [0.08, 0.2],
    "atmosphere.inner_scale_m": [0.005], "atmosphere.outer_scale_m": [50.0], "atmosphere.visibility_m": [5000.0],
}


def _maps(lad):
    f = lad.fields
    return ([x for fs in f.SENSOR_FIELDS.values() for x in fs] + f.ATMOSPHERE_FIELDS + f.BRDF_FIELDS
            + f.TOP_FIELDS + [f.SEED_FIELD])


def _owner(scene, cam, f):
    if f.group == "atmosphere":
        return scene.ladar_atmosphere
    if f.group == "brdf":
        mat = bpy.data.materials.get("M") or bpy.data.materials.new("M")
        return mat.ladar_brdf
    if f.group is None:
        return cam.ladar
    if f.path == "run.seed":
        return scene.ladar
    return getattr(cam.ladar, f.group)


def _values(f):
    """Default, allowed ends and representative values of a numeric setting (SI)."""
    lo, hi = f.meta.get("lo"), f.meta.get("hi")
    vals = [f.default] + TYPICAL.get(f.path, [])
    if lo is not None and not f.meta.get("lo_open"):
        vals.append(lo)
    if hi is not None and not f.meta.get("hi_open"):
        vals.append(hi)
    if f.kind == "int":
        vals = [v for v in vals if v <= 2**31 - 1]
        if f.conversion == "mib":
            vals = [v for v in vals if v % 2**20 == 0]
    return sorted(set(vals))


def _significant_digits(x: float) -> int:
    return len(Decimal(repr(x)).normalize().as_tuple().digits)


def _docs_panel_units() -> dict:
    """Setting (as named in the table: ``laser.pulse_fwhm_s``, ``reflectance``) → unit of its panel field."""
    out = {}
    for line in DOCS.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^\| `([^`]+)` \| [^|]* \| [^|]* \| ([^|]*) \|", line)
        if m:
            unit = re.search(r"\(([^()]*)\)\s*$", m.group(2).strip())
            out[m.group(1)] = unit.group(1) if unit else ""
    return out


def _doc_key(f):
    return f.name if f.group in (None, "brdf") else f.path


# ---------------------------------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------------------------------
def test_every_property_has_a_label_written_for_people(lad):
    for f in _maps(lad):
        label = f.meta.get("label")
        assert label, f"{f.path}: no label in the settings schema"
        cls = bpy.types.Scene if f.path == "run.seed" else None
        rna_props = (lad.properties.LadarSceneSettings if cls else
                     lad.properties.LadarSensorSettings if f.group is None else
                     lad.properties.property_group_class(f.group)).bl_rna.properties
        name = rna_props[f.attr].name
        assert name.startswith(label), (f.path, name)
        assert "_" not in name, (f.path, name)
        # the words a title made from the name has ("N Bins", "Pulse Fwhm", "Adc Bits", "Max Memory Mib")
        assert not re.search(r"\b(N|Px|Fwhm|Per|Rad|Apd|Adc|Mib|Max|Min|Dof|Eff|Cn2|J|S)\b", label), \
            (f.path, label)
        if f.kind == "enum":
            items = rna_props[f.attr].enum_items
            for item in items:
                assert item.name == f.meta["choice_labels"][item.identifier], (f.path, item.identifier)
                assert "_" not in item.name and "/" not in item.name, (f.path, item.name)
    detector = lad.properties.property_group_class("detector").bl_rna.properties
    assert [i.name for i in detector["detector_type"].enum_items] == ["PIN photodiode", "APD", "Geiger-mode APD"]
    assert lad.properties.property_group_class("gate").bl_rna.properties["n_bins"].name == "Number of Bins"


# ---------------------------------------------------------------------------------------------------------------
# The conversion, both ways
# ---------------------------------------------------------------------------------------------------------------
def test_conversion_round_trips_for_every_property_and_value(lad, scene):
    """value → panel → config → the same SI value, bit for bit, for every numeric setting at its default, the
    ends of its range and representative values (all of at most 7 significant digits: what a person types; a
    value of more digits is kept to float32 precision, as Blender stores it).  And the other way: a panel value
    → SI → the same panel value."""
    cam = add_camera(scene)
    checked = 0
    for f in _maps(lad):
        if f.kind not in ("float", "int"):
            continue
        props = _owner(scene, cam, f)
        for si in _values(f):
            assert f.conversion != "pow10" or _significant_digits(si) <= 7, (f.path, si)
            lad.fields.write_value(props, f, si)
            stored = getattr(props, f.attr)
            back = lad.fields.read_value(props, f)
            assert back == si and type(back) is type(si), (f.path, si, stored, back)
            # panel → SI → panel: the stored (float32) value comes back unchanged
            assert np.float32(f.to_blender(back)) == np.float32(stored), (f.path, si)
            checked += 1
    assert checked > 150


def test_every_setting_through_the_blend_and_a_config(lad, scene):
    """Every setting at a non-default representative value through apply_config_to_blender and back."""
    cam = add_camera(scene)
    cfg = lad.blend_config.config_from_blender(scene, cam)
    changed = 0
    for f in _maps(lad):
        if f.group in (None, "brdf") or f.path == "run.seed" or f.path not in TYPICAL:
            continue
        setattr(getattr(cfg, f.group), f.name, TYPICAL[f.path][-1])
        changed += 1
    cfg.scanner.pulse_rate_hz = 100_000.0
    lad.config.validate(cfg)
    lad.blend_config.apply_config_to_blender(cfg, scene, cam)
    back = lad.blend_config.config_from_blender(scene, cam)
    want, got = lad.config.config_to_dict(cfg), lad.config.config_to_dict(back)
    for key in ("fov_x_rad", "fov_y_rad"):
        assert got["receiver"].pop(key) == pytest.approx(want["receiver"].pop(key), rel=1e-6)
    assert got == want and changed >= 20
    assert cam.ladar.laser.pulse_fwhm_ns == 10.0 and cam.ladar.gate.gate_start_ns == 13243.0
    assert cam.ladar.laser.pulse_energy_uj == 1e5 and cam.ladar.detection.threshold_fj == 2.5


# ---------------------------------------------------------------------------------------------------------------
# What the panel shows
# ---------------------------------------------------------------------------------------------------------------
def _shown(scene, props, f):
    """The string Blender's unit formatter makes of the property (value and unit) and the unit part."""
    rna = props.bl_rna.properties[f.attr]
    value = getattr(props, f.attr)
    us = scene.unit_settings
    if rna.unit == "LENGTH" and us.system != "NONE":
        value *= us.scale_length  # the UI shows distances in metres (Blender units × unit scale)
    precision = rna.precision if f.kind == "float" else 0
    text = bpy.utils.units.to_string(us.system, rna.unit, float(value), precision=precision).strip()
    if rna.unit == "NONE":
        unit = re.search(r"\(([^()]*)\)\s*$", rna.name)
        return text, unit.group(1) if unit else ""
    m = re.match(r"^-?[\d.]+\s*(.*)$", text)
    return text, m.group(1)


def _leading_zeros(text: str) -> int:
    m = re.match(r"^-?(0[.0]*)", text)
    return m.group(1).count("0") if m else 0


@pytest.mark.parametrize("system", ["METRIC", "NONE"])
def test_every_property_reads_in_a_unit_a_person_reads(lad, scene, system):
    scene.unit_settings.system = system
    cam = add_camera(scene)
    docs = _docs_panel_units()
    bad, shown = [], 0
    for f in _maps(lad):
        if f.kind not in ("float", "int"):
            continue
        props = _owner(scene, cam, f)
        for si in _values(f):
            lad.fields.write_value(props, f, si)
            text, unit = _shown(scene, props, f)
            number = re.match(r"^-?[\d.]+", text).group(0)
            shown += 1
            if si != 0 and float(number) == 0:
                bad.append(f"{f.path} = {si:g}: shows {text!r}")
            if _leading_zeros(number) > 4:
                bad.append(f"{f.path} = {si:g}: shows {text!r} (more than 4 leading zeros)")
            want = docs[_doc_key(f)]
            if want.startswith("m, the scene's length unit"):
                ok = unit in LENGTH_UNITS if system == "METRIC" else unit == ""
            else:
                ok = unit == want
            if not ok:
                bad.append(f"{f.path}: shows {text!r} in {unit!r}, docs/settings.md says {want!r}")
        lad.fields.write_value(props, f, f.default)
    assert not bad, "\n".join(bad)
    assert shown > 150


def test_the_nanosecond_settings_of_issue_27_read_in_ns(lad, scene):
    cam = add_camera(scene)
    lad.blend_config.set_settings(scene, cam, {"laser.pulse_fwhm_s": 5e-9, "gate.gate_start_s": 6.67e-7,
                                               "laser.pulse_energy_j": 2e-7, "gate.bin_width_s": 1e-9})
    g = cam.ladar.gate
    assert _shown(scene, g, next(f for f in lad.fields.SENSOR_FIELDS["gate"] if f.name == "gate_start_s")) == \
        ("667", "ns")
    laser = {f.name: f for f in lad.fields.SENSOR_FIELDS["laser"]}
    assert _shown(scene, cam.ladar.laser, laser["pulse_fwhm_s"]) == ("5", "ns")
    assert _shown(scene, cam.ladar.laser, laser["pulse_energy_j"]) == ("0.2", "µJ")


_PREFIX = {"": 1.0, "m": 1e-3, "µ": 1e-6, "n": 1e-9, "p": 1e-12, "f": 1e-15, "a": 1e-18}


def test_energies_and_times_the_field_unit_does_not_suit_get_a_readable_companion(lad, scene):
    """A FloatProperty has one static unit: 0.1 J in the µJ field shows "100000" through Blender's formatter.
    For every energy and time field, at every representative value: either the number Blender shows is in
    [1, 1000) and the panel adds nothing, or the panel adds ``FieldMap.readable`` — a number in [1, 1000) on an
    SI prefix of the same unit that gives the SI value back to its 4 significant digits."""
    cam = add_camera(scene)
    checked = 0
    for f in _maps(lad):
        if f.kind != "float" or f.meta.get("unit") not in ("J", "s") or f.conversion != "pow10":
            continue
        props = _owner(scene, cam, f)
        for si in _values(f):
            lad.fields.write_value(props, f, si)
            text, unit = _shown(scene, props, f)
            readable = f.readable(lad.fields.read_value(props, f))
            number = float(re.match(r"^-?[\d.]+", text).group(0))
            if si == 0 or 1.0 <= number < 1000.0:
                assert readable == "", (f.path, si, text, readable)
                continue
            m = re.match(r"^(-?[\d.]+) (\S?)" + f.meta["unit"] + "$", readable)
            assert m and 1.0 <= float(m.group(1)) < 1000.0, (f.path, si, text, readable)
            assert float(m.group(1)) * _PREFIX[m.group(2)] == pytest.approx(si, rel=5e-4), (f.path, si, readable)
            checked += 1
        lad.fields.write_value(props, f, f.default)
    assert checked >= 5
    laser = {f.name: f for f in lad.fields.SENSOR_FIELDS["laser"]}
    lad.fields.write_value(cam.ladar.laser, laser["pulse_energy_j"], 0.1)
    assert _shown(scene, cam.ladar.laser, laser["pulse_energy_j"]) == ("100000", "µJ")
    assert laser["pulse_energy_j"].readable(0.1) == "100 mJ"
    assert laser["pulse_energy_j"].readable(2e-7) == "200 nJ" and laser["pulse_energy_j"].readable(5e-5) == ""
    gate = {f.name: f for f in lad.fields.SENSOR_FIELDS["gate"]}
    assert gate["gate_start_s"].readable(1.3243e-5) == "13.24 µs"


# ---------------------------------------------------------------------------------------------------------------
# Files saved before the change
# ---------------------------------------------------------------------------------------------------------------
def test_a_file_saved_with_si_properties_loads_with_the_same_si_values(lad, scene, tmp_path):
    """A .blend of the add-on before issue 27 held ``pulse_fwhm_s`` etc. in SI (float32).  Written here as those
    ID properties, saved and loaded: the config has the SI values the old add-on read (shortest decimal of the
    float32), bit for bit, and the panel properties show them in ns, µJ, ... ."""
    cam = add_camera(scene)
    legacy = [f for f in _maps(lad) if f.legacy_attr]
    assert {f.path for f in legacy} >= {"laser.pulse_fwhm_s", "gate.gate_start_s", "gated.gate_width_s",
                                        "laser.pulse_energy_j", "detection.threshold_j"}
    old_values = {}
    for f in legacy:
        props = _owner(scene, cam, f)
        si = (TYPICAL.get(f.path) or [f.meta["hi"] / 7.0])[-1] * (1 + 1e-7 * math.pi)  # 9+ digits: float32 decides
        props[f.legacy_attr] = float(np.float32(si))  # what Blender stored in the old property
        old_values[f.path] = float(lad.fields.shortest_float32(np.float32(si)))
    cam_name = cam.name
    path = tmp_path / "old.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    cam = bpy.data.objects[cam_name]
    cfg = lad.blend_config.config_from_blender(scene, cam)
    for f in legacy:
        group = cfg.atmosphere if f.group == "atmosphere" else getattr(cfg, f.group)
        assert getattr(group, f.name) == old_values[f.path], f.path
        props = _owner(scene, cam, f)
        # migrated on load: the panel property holds the value in its panel unit
        assert getattr(props, f.attr) == pytest.approx(old_values[f.path] / 10.0 ** f.exponent, rel=1e-6), f.path
    # a value typed in the panel afterwards wins over the old one
    cam.ladar.laser.pulse_fwhm_ns = 7.0
    assert lad.blend_config.config_from_blender(scene, cam).laser.pulse_fwhm_s == 7e-9
    # writing through the API keeps the exact (double-precision) SI value there
    lad.blend_config.set_settings(scene, cam, {"gate.gate_start_s": 1e-6})
    assert cam.ladar.gate.get("gate_start_s") == 1e-6 and cam.ladar.gate.gate_start_ns == 1000.0


def test_si_values_of_any_digits_set_through_the_api_come_back_bit_for_bit(lad, scene, tmp_path):
    """A computed SI value (2 × 95 m / c: 16 digits) set through set_settings or a config file, saved and loaded,
    is read back bit for bit (kept as a double beside the float32 panel value); the panel shows it in ns."""
    cam = add_camera(scene)
    c = 299_792_458.0
    values = {"gate.gate_start_s": 2 * 95.0 / c, "gated.first_delay_s": 2 * 992.5 / c - 10e-9,
              "gated.delay_step_s": 1.0 / c, "laser.pulse_energy_j": 1.0 / 3.0 * 1e-3}
    lad.blend_config.set_settings(scene, cam, values)
    cam_name = cam.name
    path = tmp_path / "exact.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    cam = bpy.data.objects[cam_name]
    cfg = lad.blend_config.config_from_blender(scene, cam)
    for p, want in values.items():
        group, name = p.split(".")
        assert getattr(getattr(cfg, group), name) == want, p
    assert cam.ladar.gate.gate_start_ns == pytest.approx(2e9 * 95.0 / c, rel=1e-7)
    cam.ladar.gate.gate_start_ns = 700.0  # typed in the panel: the panel value wins
    assert lad.blend_config.config_from_blender(scene, cam).gate.gate_start_s == 7e-7


@pytest.mark.parametrize("sample, values", [
    ("gated_board", {"gated.first_delay_s": 6.6112475e-06, "gated.delay_step_s": 3.3356409e-09,
                     "gated.gate_width_s": 2e-08, "laser.pulse_energy_j": 0.02, "laser.pulse_fwhm_s": 1e-08}),
    ("forest_scan", {"gate.gate_start_s": 6.337718e-07, "gate.bin_width_s": 5e-10, "laser.pulse_energy_j": 5e-05,
                     "laser.beam_divergence_rad": 0.001, "scanner.pulse_rate_hz": 100000.0}),
])
def test_the_sample_scenes_saved_before_the_change_keep_their_values(lad, addon, sample, values):
    """The committed sample .blend files hold the SI properties: they load with the values the old add-on read
    (the numbers its runs wrote to metadata.json)."""
    bpy.ops.wm.open_mainfile(filepath=str(Path(__file__).resolve().parents[2] / "sample_blends" / f"{sample}.blend"))
    scene = bpy.context.scene
    cfg = lad.blend_config.config_from_blender(scene, scene.ladar.sensor or scene.camera)
    for path, want in values.items():
        group, name = path.split(".")
        assert getattr(getattr(cfg, group), name) == want, path
