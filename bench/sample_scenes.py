"""The sample .blend scenes as plain core inputs (SceneGeometry, sensor pose, SimulationConfig) for benchmarks.

Exporting needs the ``bpy`` module (a few seconds); the result is cached in ``bench/results/cache/`` keyed by
the .blend's modification time, so benchmarks after the first run start at once.

    from sample_scenes import flash_demo
    scene, pose, cfg = flash_demo()
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.config.settings import BRDFSettings  # noqa: E402
from core.config.files import config_from_dict
from core.geometry.scene import SceneGeometry  # noqa: E402

CACHE = ROOT / "bench" / "results" / "cache"

_EXPORT = r"""
import json, sys
from pathlib import Path
sys.path.insert(0, str(Path({root!r}) / "scripts"))
import blender_env
blender_env.isolate_user_resources()
import bpy
import numpy as np
addon = blender_env.install_extension()
lad = addon.ladar_addon
bpy.ops.wm.open_mainfile(filepath={blend!r}, load_ui=False)
scene = bpy.context.scene
sensor = lad.run_inputs.active_sensor(scene)
cfg, _ = lad.run_inputs.build_config(scene, sensor)
scale = lad.blend_config.unit_scale(scene)
geo = lad.export.scene_geometry_from_depsgraph(bpy.context.evaluated_depsgraph_get(), unit_scale=scale,
                                               exclude={{sensor.name}})
pose = np.array(sensor.matrix_world, dtype=np.float64)
pose[:3, 3] *= scale
cfg.materials = {{}}
np.savez({out!r}, vertices_m=geo.vertices_m, triangles=geo.triangles, material_ids=geo.material_ids, pose=pose,
         material_names=np.array(geo.material_names),
         materials=json.dumps([b.__dict__ for b in geo.materials]),
         config=json.dumps(addon.core.config.config_to_dict(cfg)))
"""


def load_blend(name: str):
    """(SceneGeometry, world_from_sensor (4, 4), SimulationConfig) of ``sample_blends/<name>.blend``."""
    blend = ROOT / "sample_blends" / f"{name}.blend"
    CACHE.mkdir(parents=True, exist_ok=True)
    out = CACHE / f"{name}_{int(blend.stat().st_mtime)}.npz"
    if not out.exists():
        code = _EXPORT.format(root=str(ROOT), blend=str(blend), out=str(out))
        subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    data = np.load(out)
    mats = [BRDFSettings(**m) for m in json.loads(str(data["materials"]))]
    scene = SceneGeometry(data["vertices_m"], data["triangles"], data["material_ids"], mats,
                          [str(n) for n in data["material_names"]])
    return scene, data["pose"], config_from_dict(json.loads(str(data["config"])))


def flash_demo():
    return load_blend("flash_demo")
