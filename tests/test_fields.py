"""The core setting ↔ Blender property mapping (ladar_addon/fields.py) without Blender: every setting of the
core has its field map, and the stored value converts back to the SI value exactly (nm, powers of ten,
Blender units, MiB), as the panels and config files rely on."""
import importlib
import math
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "ladar_simulator_without_blender"


@pytest.fixture(scope="module")
def fields():
    """``ladar_addon.fields`` imported as part of the repository package, with no bpy anywhere."""
    root = types.ModuleType(PACKAGE)
    root.__path__ = [str(REPO)]  # the extension root as a package, without running its register() __init__
    sys.modules[PACKAGE] = root
    try:
        mod = importlib.import_module(f"{PACKAGE}.ladar_addon.fields")
        yield mod
    finally:
        for name in [n for n in sys.modules if n == PACKAGE or n.startswith(PACKAGE + ".")]:
            del sys.modules[name]


def test_fields_import_no_blender(fields):
    """Only the package __init__ and fields itself are loaded (tests/test_architecture.py checks that fields
    imports no bpy, module-level or deferred)."""
    assert "bpy" not in vars(fields)
    assert not [n for n in sys.modules if n.startswith(f"{PACKAGE}.ladar_addon.") and n.split(".")[-1]
                not in ("fields", "__init__")]


def test_every_core_setting_has_one_field_map(fields):
    config = importlib.import_module(f"{PACKAGE}.core.config.settings")
    core_paths = {"system_type"} | {f"{g}.{n}" for g in config.GROUPS
                                    for n, _, _ in config.field_specs(type(getattr(config.SimulationConfig(), g)))}
    assert fields.all_core_paths() == core_paths
    maps = [f for fs in fields.SENSOR_FIELDS.values() for f in fs] + fields.ATMOSPHERE_FIELDS + fields.TOP_FIELDS
    assert len({f.path for f in maps}) == len(maps)  # one home each


def _field(fields, path):
    maps = [f for fs in fields.SENSOR_FIELDS.values() for f in fs] + fields.ATMOSPHERE_FIELDS
    return next(f for f in maps if f.path == path)


@pytest.mark.parametrize("path, si, stored, conversion", [
    ("laser.wavelength_m", 1.064e-6, 1064.0, "pow10"),           # nanometres
    ("atmosphere.cn2_m_23", 5e-15, 0.5, "pow10"),                # units of 1e-14 (label ×1e-14 m^-2/3)
    ("detector.dark_current_bulk_a", 1e-12, 1.0, "pow10"),       # pA
    ("laser.pulse_fwhm_s", 5e-9, 5.0, "pow10"),                  # ns
    ("gate.gate_start_s", 6.67e-7, 667.0, "pow10"),              # ns
    ("laser.pulse_energy_j", 2e-7, 0.2, "pow10"),                # µJ
    ("detection.threshold_j", 2.5e-15, 2.5, "pow10"),            # fJ
    ("laser.beam_divergence_rad", 2.2e-4, 0.22, "pow10"),        # mrad
    ("atmosphere.extinction_per_m", 1.2e-4, 0.12, "pow10"),      # 1/km
    ("scanner.pulse_rate_hz", 100_000.0, 100.0, "pow10"),        # kHz
    ("run.max_memory_bytes", 4 * 2**30, 4096, "mib"),            # beyond int32: MiB
])
def test_scaled_settings_convert_both_ways(fields, path, si, stored, conversion):
    f = _field(fields, path)
    assert f.conversion == conversion
    assert f.to_blender(si) == pytest.approx(stored, rel=1e-12)
    assert f.to_core(f.to_blender(si)) == si


def test_distances_follow_the_unit_scale(fields):
    f = next(f for f in _all(fields) if f.conversion == "distance")
    assert f.to_blender(250.0, unit_scale=0.5) == 500.0       # 0.5 m per Blender unit
    assert f.to_core(500.0, unit_scale=0.5) == 250.0


def _all(fields):
    return [f for fs in fields.SENSOR_FIELDS.values() for f in fs] + fields.ATMOSPHERE_FIELDS


def test_float32_storage_reads_back_as_the_shortest_decimal(fields):
    f = _field(fields, "receiver.system_efficiency")
    import numpy as np
    assert f.to_core(np.float32(1e-3)) == 1e-3                 # not 0.0010000000474974513
    assert fields.shortest_float32(0.1) == "0.1"


def test_an_int_beyond_a_blend_names_the_setting(fields):
    f = _field(fields, "run.seed") if any(x.path == "run.seed" for x in _all(fields)) else fields.SEED_FIELD
    with pytest.raises(Exception, match="run.seed"):
        f.to_blender(2**31)
    assert math.isfinite(f.to_core(7))
