"""The sample scene's grazing ground gives one echo per pixel (issue 7: it used to give 1359 multi-echo pixels
of 2537, one spurious echo per sub-ray row, before the cell range spread)."""
from pathlib import Path

import bpy
import numpy as np

SAMPLE = Path(__file__).resolve().parents[2] / "sample_blends" / "flash_demo.blend"


def _simulate(lad, spread):
    bpy.ops.wm.open_mainfile(filepath=str(SAMPLE), load_ui=False)
    scene = bpy.context.scene
    sensor = lad.simulate.active_sensor(scene)
    cfg, _ = lad.simulate.build_config(scene, sensor)
    cfg.receiver.cell_range_spread = spread
    cfg.materials = {}
    geometry = lad.export.scene_geometry_from_depsgraph(bpy.context.evaluated_depsgraph_get(), exclude={sensor.name})
    return lad.pipeline.simulate_frame(geometry, np.array(sensor.matrix_world), cfg)


def test_flash_demo_multi_echoes_are_real_surfaces(lad, addon):
    """With the spread, under 1 % of the pixels report several echoes, and each of those has echoes at least
    5 m apart (an object edge in front of a farther surface), not the ≈ 1 m steps of sub-ray rows on the
    ground; without it, over a third of the pixels do."""
    res = _simulate(lad, True)
    pts = res.points
    first = pts["echo_index"] == 1
    multi = first & (pts["n_echoes"] > 1)
    assert first.sum() > 2000
    assert multi.sum() < 0.01 * first.sum()
    for x, y in zip(pts["pixel_x"][multi], pts["pixel_y"][multi]):
        r = pts["range_m"][(pts["pixel_x"] == x) & (pts["pixel_y"] == y)]
        assert np.diff(r).min() > 5.0
    old = _simulate(lad, False).points
    assert np.sum((old["echo_index"] == 1) & (old["n_echoes"] > 1)) > 0.33 * first.sum()
