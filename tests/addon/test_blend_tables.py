"""Settings without a Blender property (the list-valued ``table_fields`` of every group: the scanner's channel
table, its file and the Risley prisms; the atmosphere's aerosol layers) survive config -> Blender -> config: kept as
JSON in a custom property ``ladar_<group>_tables`` of the sensor camera (sensor groups) or the scene (atmosphere),
ladar_addon/blend_config.py.  Before issue 30's follow-up the aerosol layers were dropped on the way."""
import importlib
import json

import bpy
import numpy as np
import pytest

from test_cli import _run, plate_scene  # noqa: F401 - the fixture: an 8 x 8 px flash camera, a plate at 100 m
from test_panels import _context, _draw

LAYERS_4 = [[40.0, 60.0, 0.02, 1e-3], [70.0, 80.0, 0.005, 2e-4]]
LAYERS_3 = [[40.0, 60.0, 0.02]]


def _settings(lad):
    return importlib.import_module(f"{lad.package.__name__}.core.config.settings")


def _tables_configs(tmp_path):
    """Two configs that between them set every table field of every group (other settings: the .blend's)."""
    csv = tmp_path / "channels.csv"
    csv.write_text("1.0,0,0\n-1.0,0.5,1e-6\n-2.0,0,2e-6\n", encoding="utf-8")
    rotating = {"system_type": "scanner", "atmosphere": {"aerosol_layers": LAYERS_4},
                "scanner": {"pattern": "rotating", "n_channels": 2, "channel_table": [[1.5, 0.25, 0.0],
                                                                                       [-1.5, -0.25, 1e-6]]}}
    risley = {"system_type": "flash", "atmosphere": {"aerosol_layers": LAYERS_3},
              "scanner": {"n_channels": 3, "channel_table": [], "channel_table_file": str(csv), "risley_prism_hz": [100.0, -75.0],
                          "risley_wedge_deg": [10.0, 10.0], "risley_index": [1.5, 1.5],
                          "risley_phase_deg": [0.0, 90.0], "risley_emitters_deg": [[0.0, 0.0], [1.0, -1.0]]}}
    return [rotating, risley]


def test_every_table_field_round_trips_config_blender_config(lad, plate_scene, tmp_path, capsys):
    """A config file with aerosol layers (and every scanner table) loaded into Blender (``ladar.load_config``)
    and exported back (``ladar export-config``) is the original config, setting for setting; saving and
    reopening the .blend keeps them."""
    settings = _settings(lad)
    covered = set()
    for i, tables in enumerate(_tables_configs(tmp_path)):
        base = tmp_path / f"base{i}.toml"
        code, _, err = _run(lad, capsys, "export-config", "--out", str(base), "--overwrite")
        assert code == 0, err
        data = lad.config.config_to_dict(lad.config.load_config(base))
        for key, value in tables.items():
            data[key] = {**data[key], **value} if isinstance(value, dict) else value
        original = lad.config.config_from_dict(data)
        path = tmp_path / f"tables{i}.toml"
        path.write_text(lad.config.dump_config_toml(original), encoding="utf-8")
        assert bpy.ops.ladar.load_config(filepath=str(path)) == {"FINISHED"}
        out = tmp_path / f"exported{i}.toml"
        code, _, err = _run(lad, capsys, "export-config", "--out", str(out))
        assert code == 0, err
        exported = lad.config.config_to_dict(lad.config.load_config(out))
        assert exported["atmosphere"]["aerosol_layers"] == tables["atmosphere"]["aerosol_layers"]
        assert exported == lad.config.config_to_dict(original)
        for group in settings.GROUPS:
            default = getattr(settings.SimulationConfig(), group)
            covered |= {(group, f) for f in settings.table_fields(type(default))
                        if getattr(getattr(original, group), f) != getattr(default, f)}
    every = {(g, f) for g in settings.GROUPS
             for f in settings.table_fields(type(getattr(settings.SimulationConfig(), g)))}
    assert ("atmosphere", "aerosol_layers") in every and covered == every
    # the layers live on the scene (as the other atmosphere settings), the scanner's tables on the camera
    assert json.loads(plate_scene["ladar_atmosphere_tables"]) == {"aerosol_layers": LAYERS_3}
    assert "ladar_scanner_tables" in bpy.data.objects["Ladar"]
    blend = tmp_path / "layers.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.read_homefile(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    cfg = lad.blend_config.config_from_blender(bpy.context.scene, bpy.data.objects["Ladar"])
    assert cfg.atmosphere.aerosol_layers == LAYERS_3 and cfg.scanner.risley_prism_hz == [100.0, -75.0]


def test_a_config_without_layers_clears_them(lad, plate_scene, tmp_path):
    """``apply_config_to_blender`` stores exactly the config's layers: none removes the old ones (and the custom
    property), and a .blend saved before the atmosphere had tables (no property) reads none.  A config file loaded
    with ``ladar.load_config`` sets what it names (docs/atmosphere.md): ``aerosol_layers = []`` removes the layers,
    a file without the setting leaves them."""
    scene, cam = plate_scene, bpy.data.objects["Ladar"]
    bc = lad.blend_config
    assert "ladar_atmosphere_tables" not in scene
    assert bc.config_from_blender(scene, cam).atmosphere.aerosol_layers == []
    layers, other, empty = (tmp_path / f"{n}.toml" for n in ("layers", "other", "empty"))
    layers.write_text("schema_version = 1\n[atmosphere]\naerosol_layers = [[40.0, 60.0, 0.02]]\n", encoding="utf-8")
    other.write_text("schema_version = 1\n[atmosphere]\nlidar_ratio_sr = 20.0\n", encoding="utf-8")
    empty.write_text("schema_version = 1\n[atmosphere]\naerosol_layers = []\n", encoding="utf-8")
    for path, expected in [(layers, LAYERS_3), (other, LAYERS_3), (empty, [])]:
        assert bpy.ops.ladar.load_config(filepath=str(path)) == {"FINISHED"}
        assert bc.config_from_blender(scene, cam).atmosphere.aerosol_layers == expected, path.name
    assert "ladar_atmosphere_tables" not in scene
    cfg = bc.config_from_blender(scene, cam)
    cfg.atmosphere.aerosol_layers = LAYERS_3
    bc.apply_config_to_blender(cfg, scene, cam)
    assert bc.config_from_blender(scene, cam).atmosphere.aerosol_layers == LAYERS_3
    cfg.atmosphere.aerosol_layers = []
    bc.apply_config_to_blender(cfg, scene, cam)
    assert "ladar_atmosphere_tables" not in scene
    bad = bc.config_from_blender(scene, cam)
    bad.atmosphere.aerosol_layers = [[60.0, 40.0, 0.02]]  # invalid: nothing changes
    with pytest.raises(lad.config.ConfigError, match=r"aerosol_layers row 1 column 2"):
        bc.apply_config_to_blender(bad, scene, cam)
    assert "ladar_atmosphere_tables" not in scene


@pytest.mark.parametrize("text, match", [("not json", r"ladar_atmosphere_tables.*a JSON object of aerosol_layers"),
                                         ('{"layers": []}', r"ladar_atmosphere_tables'\]\.layers")])
def test_a_hand_edited_property_is_a_clear_error(lad, plate_scene, text, match):
    scene, cam = plate_scene, bpy.data.objects["Ladar"]
    scene["ladar_atmosphere_tables"] = text
    with pytest.raises(lad.config.ConfigError, match=match):
        lad.blend_config.config_from_blender(scene, cam)
    log = _draw(lad.package.panels.scene.LADAR_PT_atmosphere, _context(scene, cam))  # draws, with the error
    assert any(kind == "label" and text.startswith("Aerosol layers unavailable") for kind, text in log)


def test_atmosphere_panel_lists_the_layers_and_clears_them(lad, plate_scene):
    scene, cam = plate_scene, bpy.data.objects["Ladar"]
    panel = lad.package.panels.scene.LADAR_PT_atmosphere

    def labels():
        return [t for kind, t in _draw(panel, _context(scene, cam)) if kind == "label"]

    assert "No aerosol layers (homogeneous atmosphere)" in labels()
    assert ("operator", "ladar.aerosol_layers_clear") in _draw(panel, _context(scene, cam))
    lad.blend_config.set_settings(scene, cam, {"atmosphere.aerosol_layers": LAYERS_4 + [[90.0, 95.0, 0.1, 1e-2]],
                                               "atmosphere.lidar_ratio_sr": 20.0})
    text = labels()
    assert "3 aerosol layers (from a config file or preset)" in text
    assert "  40–60 m: α 20 /km, β 0.001 /(m sr)" in text
    assert "  70–80 m: α 5 /km, β 0.0002 /(m sr)" in text
    lad.blend_config.set_settings(scene, cam, {"atmosphere.aerosol_layers": LAYERS_3})
    text = labels()
    assert "  40–60 m: α 20 /km, β = α/S = 0.001 /(m sr)" in text  # 0.02 / 20 sr
    # the derived figures' transmission at the reference range crosses the layer: exp(-2 * 0.02 /m * 20 m)
    assert scene.ladar.reference_range_m == 1000.0 and scene.ladar_atmosphere.extinction_per_km == 0.0
    assert f"Two-way transmission {np.exp(-0.8):.4g} at 1000 m (aerosol layers included)" in text, text
    rows = [[10.0 * i, 10.0 * i + 5.0, 0.01] for i in range(6)]
    lad.blend_config.set_settings(scene, cam, {"atmosphere.aerosol_layers": rows})
    text = labels()
    assert "6 aerosol layers (from a config file or preset)" in text and "  … 2 more" in text
    assert bpy.ops.ladar.aerosol_layers_clear() == {"FINISHED"}
    assert "ladar_atmosphere_tables" not in scene
    assert "No aerosol layers (homogeneous atmosphere)" in labels()


def test_the_blend_run_equals_the_config_run(lad, plate_scene, tmp_path, capsys):
    """Simulating the .blend with the layers loaded from a config gives the products of simulating the same
    config file over a .blend without layers; the layers attenuate the plate's echo (8 x 8 px flash at 100 m) by
    the two-way transmission of the 20 m layer, exp(-2 * 0.02 /m * 20 m) = exp(-0.8), to float precision."""
    base = tmp_path / "base.toml"
    code, _, err = _run(lad, capsys, "export-config", "--out", str(base))
    assert code == 0, err
    data = lad.config.config_to_dict(lad.config.load_config(base))
    data["atmosphere"]["aerosol_layers"] = LAYERS_3
    path = tmp_path / "layers.toml"
    path.write_text(lad.config.dump_config_toml(lad.config.config_from_dict(data)), encoding="utf-8")
    runs = {}
    for name, argv in [("clear", []), ("config", ["--config", str(path)])]:
        code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / name), "--seed", "3", "--no-previews",
                            "--no-import", *argv)
        assert code == 0, err
        runs[name] = tmp_path / name
    assert bpy.ops.ladar.load_config(filepath=str(path)) == {"FINISHED"}
    code, _, err = _run(lad, capsys, "simulate", "--out", str(tmp_path / "blend"), "--seed", "3", "--no-previews",
                        "--no-import")
    assert code == 0, err
    runs["blend"] = tmp_path / "blend"
    for name in ("waveforms.npy", "echoes.npz", "points.npz"):
        blend, config = (np.load(runs[k] / name) for k in ("blend", "config"))
        for key in (config.files if name.endswith(".npz") else [None]):
            np.testing.assert_array_equal(blend[key] if key else blend, config[key] if key else config,
                                          err_msg=f"{name} {key}")
    # the ideal receiver's waveform energy per pixel: the layer's two-way transmission (float32 sums of 2048 bins:
    # relative rounding well below 1e-5)
    clear, layers = (np.load(runs[k] / "waveforms.npy").astype(np.float64).sum(axis=-1) for k in ("clear", "config"))
    assert (clear > 0).all() and clear.size == 64
    np.testing.assert_allclose(layers / clear, np.exp(-2.0 * 0.02 * 20.0), rtol=1e-5)
