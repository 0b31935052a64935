"""The README's per-system examples, in quick form, through the same ``ladar`` command handler that
``blender -b SCENE -c ladar …`` and ``scripts/ladar_run.py SCENE …`` run (docs/commands.toml maps the documented
commands here; tests/test_documented_commands.py checks the mapping and runs the sweep example).  Outputs go to a temporary
folder; each sample scene is the committed .blend, with a config file cutting only its size where the full run is
long (the forest scan: 1000 pulses instead of 100 000)."""
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
