"""The sample scene's grazing ground gives one echo per pixel (issue 7: it used to give 1359 multi-echo pixels
of 2537, one spurious echo per sub-ray row, before the cell range spread)."""
import dataclasses
from pathlib import Path

import bpy
import numpy as np
import pytest

SAMPLE = Path(__file__).resolve().parents[2] / "sample_blends" / "flash_demo.blend"


@pytest.fixture(scope="module")
def demo(lad, addon):
    bpy.ops.wm.open_mainfile(filepath=str(SAMPLE), load_ui=False)
    scene = bpy.context.scene
    sensor = lad.run_inputs.active_sensor(scene)
    cfg, _ = lad.run_inputs.build_config(scene, sensor)
    cfg.materials = {}
    geometry = lad.export.scene_geometry_from_depsgraph(bpy.context.evaluated_depsgraph_get(), exclude={sensor.name})
    return geometry, np.array(sensor.matrix_world), cfg


def _run(lad, demo, **receiver):
    geometry, pose, cfg = demo
    cfg = dataclasses.replace(cfg, receiver=dataclasses.replace(cfg.receiver, **receiver))
    return lad.flash.simulate_frame(geometry, pose, cfg).points


@pytest.mark.parametrize("pattern", ["grid", "sobol", "adaptive"])
def test_flash_demo_multi_echoes_are_real_surfaces(lad, demo, pattern):
    """With the cell range spread, under 1 % of the pixels report several echoes, and each of those has echoes
    at least 5 m apart (an object edge in front of a farther surface), not the ≈ 1 m steps of sub-ray rows on
    the ground."""
    pts = _run(lad, demo, subray_pattern=pattern)
    first = pts["echo_index"] == 1
    multi = first & (pts["n_echoes"] > 1)
    assert first.sum() > 2000
    assert multi.sum() < 0.01 * first.sum()
    for x, y in zip(pts["pixel_x"][multi], pts["pixel_y"][multi]):
        r = pts["range_m"][(pts["pixel_x"] == x) & (pts["pixel_y"] == y)]
        assert np.diff(r).min() > 5.0


def test_flash_demo_point_sub_rays_give_spurious_echoes(lad, demo):
    """The reduced model (cell_range_spread off, the paper's point sub-rays): over a third of the pixels
    report several echoes."""
    pts = _run(lad, demo, subray_pattern="grid", cell_range_spread=False)
    first = pts["echo_index"] == 1
    assert np.sum(first & (pts["n_echoes"] > 1)) > 0.33 * first.sum()
