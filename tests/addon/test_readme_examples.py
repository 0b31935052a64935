"""The README's per-system examples, in quick form, through the same ``ladar`` command handler that
``blender -b SCENE -c ladar …`` and ``scripts/ladar_run.py SCENE …`` run (docs/commands.toml maps the documented
commands here; tests/test_documented_commands.py checks the mapping, tests/addon/test_sweep_example.py runs the sweep
example).  Outputs go to a temporary folder; each sample scene is the committed .blend, with a config file cutting
only its size where the full run is long (the forest scan: 1000 pulses instead of 100 000)."""
import json
from pathlib import Path

import bpy
import pytest

REPO = Path(__file__).resolve().parents[2]

#: README example → (sample scene, quick config overrides or None, a file the run folder must hold)
EXAMPLES = {
    "flash": ("flash_demo", None, "range.exr"),
    "gated": ("gated_board", None, "slices.npy"),
    "scan": ("forest_scan", "schema_version = 1\n[scanner]\nduration_s = 0.01\n", "pulses.npz"),
    "profile": ("aircraft_profile", None, "profile.csv"),
}


def _open(name):
    bpy.ops.wm.open_mainfile(filepath=str(REPO / "sample_blends" / f"{name}.blend"), load_ui=False)
    return bpy.context.scene


def _run(lad, capsys, *argv):
    code = lad.cli.cli_handler(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("example", sorted(EXAMPLES))
def test_readme_system_example_runs(lad, addon, tmp_path, capsys, example):
    """``scripts/ladar_run.py sample_blends/<scene>.blend simulate --out runs/<example>`` (quick where long)."""
    blend, config, product = EXAMPLES[example]
    _open(blend)
    argv = ["simulate", "--out", str(tmp_path / example)]
    if config is not None:
        (tmp_path / "quick.toml").write_text(config, encoding="utf-8")
        argv += ["--config", str(tmp_path / "quick.toml")]
    code, out, err = _run(lad, capsys, *argv)
    assert code == 0, err
    assert (tmp_path / example / product).is_file()
    meta = json.loads((tmp_path / example / "metadata.json").read_text(encoding="utf-8"))
    assert meta["system_type"] == lad.config.config_to_dict(lad.blend_config.config_from_blender(
        bpy.context.scene, bpy.context.scene.ladar.sensor))["system_type"]
    assert meta.get("n_hits", 1) > 0


@pytest.mark.parametrize("sensor", ["flash", "scanner"])
def test_readme_fog_example_runs(lad, addon, tmp_path, capsys, sensor):
    """``scripts/ladar_run.py sample_blends/fog_vehicle.blend simulate [--sensor Scanner] --out runs/fog_…``: the
    fog's near-range returns are marked as the atmosphere's (LAS class 18) and the vehicle at 60 m is still
    seen behind them (flash: first echoes under 2 m, second echoes at the vehicle's 59–60 m)."""
    import numpy as np
    _open("fog_vehicle")
    argv = ["simulate", "--out", str(tmp_path / sensor)] + (["--sensor", "Scanner"] if sensor == "scanner" else [])
    code, out, err = _run(lad, capsys, *argv)
    assert code == 0, err
    assert "returns of the atmosphere" in out
    pts = np.load(tmp_path / sensor / "points.npz")
    atm = pts["atmosphere"].astype(bool)
    assert atm.any() and not atm.all()
    vehicle = (~atm) & (np.abs(pts["range_m"] - 59.5) < 1.0)
    assert vehicle.sum() > (100 if sensor == "flash" else 50)
    if sensor == "flash":
        assert np.all(pts["range_m"][pts["echo_index"] == 1] < 2.0)  # every first echo: the fog next to the sensor
        assert (tmp_path / sensor / "range.png").is_file()
    else:
        assert (tmp_path / sensor / "points.png").is_file()
    meta = json.loads((tmp_path / sensor / "metadata.json").read_text(encoding="utf-8"))
    assert meta["system_type"] == sensor
