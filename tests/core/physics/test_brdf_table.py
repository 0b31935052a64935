"""Measured BRDF tables (paper §3.3), the Principled BSDF mapping and the BRDF plot (core/physics/brdf.py)."""
import json
import math
import tomllib

import numpy as np
import pytest

from core.fileio.preview import plot_brdf
from core.physics.brdf import (brdf_from_principled, directional_hemispherical_reflectance, evaluate_brdf,
                               evaluate_materials, lambertian_equivalent_reflectance, load_brdf_table,
                               parse_brdf_table, table_brdf)
from core.config.settings import BRDFSettings, SimulationConfig
from core.config.validate import validate
from core.config.files import config_from_dict, dump_config_json, dump_config_toml, load_config
from core.errors import ConfigError
from core.physics.radiometry import received_energy
from core.config.settings import LaserSettings, ReceiverSettings

ANGLES = [0.0, 10.0, 30.0, 60.0]
VALUES = [1.0, 0.5, 0.2, 0.1]


def _cos(deg):
    return np.cos(np.radians(np.asarray(deg, dtype=np.float64)))


@pytest.mark.parametrize("deg, expected", [
    (0.0, 1.0), (10.0, 0.5), (30.0, 0.2), (60.0, 0.1),          # the rows themselves
    (5.0, 0.75), (20.0, 0.35), (45.0, 0.15), (15.0, 0.425),      # linear in θ between rows
    (70.0, 0.1), (89.0, 0.1), (90.0, 0.1),                       # beyond the last angle: the last value
])
def test_table_interpolation_known_values(deg, expected):
    """f_r = f_i + (f_{i+1} − f_i)(θ − θ_i)/(θ_{i+1} − θ_i); e.g. θ = 20°: 0.5 + (0.2 − 0.5)·10/20 = 0.35."""
    assert float(table_brdf(_cos(deg), ANGLES, VALUES)) == pytest.approx(expected, rel=1e-9)


def test_table_below_first_angle_and_grazing_cosines():
    """A table starting at 20° gives its first value below 20°; cos θ outside [0, 1] (float32 round-off) is
    clipped, never NaN."""
    v = table_brdf(np.array([1.0, _cos(10.0), 1.0 + 1e-7, -1e-7, 0.0]), [20.0, 40.0], [0.3, 0.1])
    assert np.allclose(v, [0.3, 0.3, 0.3, 0.1, 0.1], rtol=1e-12)
    b = BRDFSettings(model="table", table_angle_deg=[0.0, 90.0], table_brdf_per_sr=[0.2, 0.0])
    # Linear from 0.2 at 0° to 0 at 90°: 0.2·(1 − θ/90); θ = 60° → 0.0667.
    assert float(evaluate_brdf(b, _cos(60.0))) == pytest.approx(0.2 / 3, rel=1e-9)


def test_materials_mix_table_and_models():
    """evaluate_materials picks each ray's material; a constant table ρ/π returns exactly the Lambertian energy
    (eq. 3-1 is linear in f_r)."""
    lam = BRDFSettings(model="lambertian", reflectance=0.4)
    tab = BRDFSettings(model="table", table_angle_deg=[0.0, 90.0], table_brdf_per_sr=[0.4 / math.pi] * 2)
    ste = BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0)
    cos = _cos([0.0, 30.0, 60.0, 0.0, 10.0])
    ids = np.array([0, 1, 1, 2, 2])
    f = evaluate_materials([lam, tab, ste], ids, cos)
    assert np.allclose(f[:3], 0.4 / math.pi, rtol=1e-12)
    assert f[3] == pytest.approx(0.1300, rel=5e-4) and f[4] == pytest.approx(0.1040, rel=5e-4)  # docs/theory.md §10
    laser, rx = LaserSettings(), ReceiverSettings()
    rng = np.array([100.0, 250.0, 400.0])
    e_lam = received_energy(laser, rx, 0.0, [lam], np.zeros(3, int), cos[:3], rng, 1.0)
    e_tab = received_energy(laser, rx, 0.0, [tab], np.zeros(3, int), cos[:3], rng, 1.0)
    assert np.allclose(e_tab, e_lam, rtol=1e-12, atol=0.0)  # (energies of 1e-11 J: no absolute slack)
    assert lambertian_equivalent_reflectance(tab, [0.0, 45.0]) == pytest.approx([0.4, 0.4], rel=1e-12)
    with pytest.raises(ValueError, match="bistatic"):
        directional_hemispherical_reflectance(tab)


@pytest.mark.parametrize("angles, values, field, allowed", [
    ([0.0, 20.0, 10.0], [1, 1, 1], "table_angle_deg[2]", "strictly increasing"),
    ([0.0, 10.0, 10.0], [1, 1, 1], "table_angle_deg[2]", "strictly increasing"),
    ([0.0, 95.0], [1, 1], "table_angle_deg[1]", "[0, 90] degrees"),
    ([-1.0, 10.0], [1, 1], "table_angle_deg[0]", "[0, 90] degrees"),
    ([0.0, 10.0], [1.0, -0.01], "table_brdf_per_sr[1]", "≥ 0"),
    ([0.0, 10.0], [float("nan"), 1.0], "table_brdf_per_sr[0]", "finite"),
    ([0.0, 10.0], [1.0, float("inf")], "table_brdf_per_sr[1]", "finite"),
    ([0.0], [1.0], "table_angle_deg", "at least 2 rows"),
    ([], [], "table_angle_deg", "at least 2 rows"),
    ([0.0, 10.0, 20.0], [1.0, 1.0], "table_brdf_per_sr", "one BRDF value per angle"),
    ([0.0, "10"], [1.0, 1.0], "table_angle_deg[1]", "a finite number"),
    ("0, 10", [1.0, 1.0], "table_angle_deg", "a list of numbers"),
])
def test_table_validation_names_field_value_and_range(angles, values, field, allowed):
    b = BRDFSettings(model="table", table_angle_deg=angles, table_brdf_per_sr=values)
    with pytest.raises(ConfigError) as err:
        validate(b, "materials.Paint.")
    assert err.value.field == f"materials.Paint.{field}"
    assert allowed in err.value.allowed


def test_valid_tables_and_unused_tables():
    validate(BRDFSettings(model="table", table_angle_deg=[0.0, 90.0], table_brdf_per_sr=[0.0, 0.0]))
    validate(BRDFSettings(model="steinvall"))  # no table: fine
    # A table kept beside another model is still checked (it came from the user).
    with pytest.raises(ConfigError, match="table_angle_deg"):
        validate(BRDFSettings(model="lambertian", table_angle_deg=[0.0], table_brdf_per_sr=[1.0]))


def test_config_round_trip_json_and_toml(tmp_path):
    table = BRDFSettings(model="table", table_wavelength_m=1.55e-6, table_angle_deg=[0.0, 12.5, 45.0, 80.0],
                         table_brdf_per_sr=[3.2, 0.71, 0.0123, 1e-5])
    cfg = SimulationConfig(materials={"Paint": table, "Grass \"wet\"": BRDFSettings(reflectance=0.5)})
    validate(cfg)
    from_json = config_from_dict(json.loads(dump_config_json(cfg)))
    assert from_json == cfg
    toml_text = dump_config_toml(cfg)
    assert "table_angle_deg = [0.0, 12.5, 45.0, 80.0]" in toml_text
    from_toml = config_from_dict(tomllib.loads(toml_text))
    assert from_toml == cfg
    assert from_toml.materials["Paint"].table_brdf_per_sr == [3.2, 0.71, 0.0123, 1e-5]
    (tmp_path / "c.toml").write_text(toml_text)
    (tmp_path / "c.json").write_text(dump_config_json(cfg))
    assert load_config(tmp_path / "c.toml") == cfg == load_config(tmp_path / "c.json")
    # Whole numbers in a hand-written config become floats.
    cfg2 = config_from_dict({"materials": {"Board": {"model": "table", "table_angle_deg": [0, 90],
                                                     "table_brdf_per_sr": [1, 0]}}})
    assert cfg2.materials["Board"].table_angle_deg == [0.0, 90.0]
    assert all(isinstance(v, float) for v in cfg2.materials["Board"].table_brdf_per_sr)


def test_config_rejects_a_bad_table():
    with pytest.raises(ConfigError) as err:
        config_from_dict({"materials": {"Board": {"model": "table", "table_angle_deg": [0.0, 50.0, 40.0],
                                                  "table_brdf_per_sr": [1.0, 0.5, 0.2]}}})
    assert err.value.field == "materials.Board.table_angle_deg[2]" and err.value.value == 40.0
    with pytest.raises(ConfigError) as err:
        config_from_dict({"materials": {"Board": {"model": "table"}}})
    assert err.value.field == "materials.Board.table_angle_deg"


CSV = """# Measured monostatic BRDF, green paint
# wavelength = 1064 nm
angle_deg, brdf_per_sr
0, 0.80
10; 0.30
# a comment between rows
20\t0.12

45   0.050
80,0.010
"""


def test_parse_csv_with_header_comments_and_separators(tmp_path):
    angles, values, wavelength = parse_brdf_table(CSV)
    assert angles == [0.0, 10.0, 20.0, 45.0, 80.0]
    assert values == [0.80, 0.30, 0.12, 0.050, 0.010]
    assert wavelength == pytest.approx(1.064e-6, rel=1e-12)
    assert parse_brdf_table("wavelength: 1.55 um\n0 1\n90 0\n")[2] == pytest.approx(1.55e-6)
    assert parse_brdf_table("0 1\n90 0\n")[2] is None
    path = tmp_path / "paint.csv"
    path.write_text(CSV, encoding="utf-8")
    assert load_brdf_table(path)[:2] == (angles, values)


@pytest.mark.parametrize("text, field, allowed", [
    ("0 1\n10 x\n", "t.csv line 2", "exactly two numbers"),
    ("0 1\n10 1 3\n", "t.csv line 2", "exactly two numbers"),
    ("0 1\nangle brdf\n20 1\n", "t.csv line 2", "two numbers per row"),
    ("# c\n0 1\n10 0.5\n5 0.2\n", "t.csv: table_angle_deg[2] (line 4)", "strictly increasing"),
    ("0 1\n100 0.5\n", "t.csv: table_angle_deg[1] (line 2)", "[0, 90] degrees"),
    ("0 1\n10 -0.5\n", "t.csv: table_brdf_per_sr[1] (line 2)", "≥ 0"),
    ("0 nan\n10 0.5\n", "t.csv: table_brdf_per_sr[0] (line 1)", "finite"),
    ("header only\n", "t.csv: table_angle_deg", "at least 2 rows"),
    ("0 1\n", "t.csv: table_angle_deg", "at least 2 rows"),
    ("# wavelength = 50 m\n0 1\n10 1\n", "t.csv: wavelength", "[2e-07, 1.2e-05] m"),
])
def test_parse_errors_name_the_line(text, field, allowed):
    with pytest.raises(ConfigError) as err:
        parse_brdf_table(text, "t.csv")
    assert err.value.field == field
    assert allowed in err.value.allowed


def test_principled_mapping_worked_values():
    """Grey dielectric: base 0.8, roughness 0.5, IOR 1.5, level 0.5 → Y = 0.8, F0 = 0.04, s = 0.25,
    A = 0.04/(4π·0.0625) = 0.050930, B = 0.96·0.8/π = 0.244462, m = 0."""
    b = brdf_from_principled((0.8, 0.8, 0.8, 1.0), roughness=0.5)
    assert b.model == "steinvall" and b.diffuse_m == 0.0
    assert b.slope_s == pytest.approx(0.25)
    assert b.specular_a == pytest.approx(0.050930, rel=1e-4)
    assert b.diffuse_b == pytest.approx(0.244462, rel=1e-5)
    # f_r(0) = A + B = 0.29539 (1/sr).
    assert float(evaluate_brdf(b, 1.0)) == pytest.approx(0.29539, rel=1e-4)
    # Energy: ρ_DH(0) = ρ_F(1 − e^(−1/s²)) + ρ_d = 0.04(1 − e^−16) + 0.768 = 0.808 ≤ 1.
    assert directional_hemispherical_reflectance(b) == pytest.approx(0.808, rel=1e-6)
    validate(b)


def test_principled_mapping_metal_ior_level_and_clamps():
    """Metal (gold-like base (1, 0.766, 0.336), metallic 1, roughness 0.2): Y = 0.78468 all specular,
    s = 0.04, A = 0.78468/(4π·0.04²) = 39.026, B = 0.  IOR 1.5 at level 1.0 doubles F0 to 0.08.
    Roughness 0 clamps the slope to 0.01."""
    metal = brdf_from_principled((1.0, 0.766, 0.336), roughness=0.2, metallic=1.0)
    assert metal.diffuse_b == 0.0
    assert metal.slope_s == pytest.approx(0.04)
    assert metal.specular_a == pytest.approx(39.026, rel=1e-4)
    level = brdf_from_principled((0.0, 0.0, 0.0), roughness=1.0, specular_ior_level=1.0)
    assert level.specular_a == pytest.approx(0.08 / (4 * math.pi), rel=1e-9) and level.diffuse_b == 0.0
    mirror = brdf_from_principled((0.5, 0.5, 0.5), roughness=0.0)
    assert mirror.slope_s == pytest.approx(0.01)
    assert mirror.specular_a == pytest.approx(0.04 / (4 * math.pi * 1e-4), rel=1e-9)
    # Colours beyond [0, 1] (emission-like values) are clipped: white 1.0 at most.
    bright = brdf_from_principled((5.0, 5.0, 5.0), roughness=1.0)
    assert bright.diffuse_b == pytest.approx(0.96 / math.pi, rel=1e-12)
    for b in (metal, level, mirror, bright):
        validate(b)
        assert directional_hemispherical_reflectance(b) <= 1.0


@pytest.mark.parametrize("brdf", [
    BRDFSettings(model="table", table_angle_deg=[0.0, 10.0, 90.0], table_brdf_per_sr=[2.0, 0.1, 0.0]),
    BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0),
    BRDFSettings(model="lambertian", reflectance=0.3),
])
def test_plot_writes_a_png_and_nothing_else(tmp_path, brdf):
    """A 500×340 PNG, replacing an older plot, no temporary file."""
    out = tmp_path / "plots" / "brdf.png"
    out.parent.mkdir()
    out.write_bytes(b"old")
    assert plot_brdf(brdf, out, title="Paint", laser_wavelength_m=1.064e-6) == out
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert (width, height) == (500, 340)  # 5.0 × 3.4 in at 100 dpi
    assert [p.name for p in out.parent.iterdir()] == ["brdf.png"]  # no temporary file left


def test_plot_has_a_title_and_labelled_axes(tmp_path):
    """The plot (matplotlib, bundled with the extension) names what it shows; its PNG text chunks repeat it."""
    from PIL import Image
    brdf = BRDFSettings(model="table", table_angle_deg=[0.0, 90.0], table_brdf_per_sr=[1.0, 0.5])
    with Image.open(plot_brdf(brdf, tmp_path / "b.png", title="Paint", laser_wavelength_m=1.064e-6)) as im:
        text = dict(im.text)
    assert text["Title"] == "Paint — laser 1064 nm"
    assert text["Description"] == "x: incidence angle θ (deg); y: monostatic BRDF f_r (1/sr)"
