"""bench_flash's terrain case in its quick sizes (``terrain_case(quick=True)``): the bins option
(``--terrain-bins``: issue 28's 8192-bin target) reaches every frame's gate, the full-physics target follows it,
and the figures the docs quote are there."""
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

import bench_flash  # noqa: E402


def test_terrain_bins_option_sets_every_frame_and_the_target():
    cfgs = bench_flash.terrain_configs(quick=True, n_bins=8192)
    assert {c.gate.n_bins for c in cfgs.values()} == {8192}
    assert {c.gate.n_bins for c in bench_flash.terrain_configs(quick=True).values()} == {256}
    assert {c.gate.n_bins for c in bench_flash.terrain_configs().values()} == {1024}


def test_terrain_case_quick_with_bins():
    rep = bench_flash.terrain_case(1, quick=True, n_bins=512)
    assert rep["n_bins"] == 512
    full = rep["frames"]["full_physics"]
    assert full["target"] == 3.0 and full["n_points"] > 0
    for k in ("time_s", "ratio_to_floor"):
        assert math.isfinite(full[k]) and full[k] > 0
    assert rep["thread_scaling_1_to_2"]["full_physics"]["relative_to_floor"] > 0
