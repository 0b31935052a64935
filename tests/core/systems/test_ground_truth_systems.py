"""Ground truth for every system (issue 27): each echo's ``material_id`` is the material of the object it came from.

Two plates of different materials ("left", "right"), apart across the line of sight and 6 m apart in range, seen
noise-free (every echo is a true return).  For the flash, gated and scanner systems a point lies on its own line
of sight, so the object it came from is the plate on its side (x < 0: left, x > 0: right).  The profiler's one
element sees both plates in one waveform and places its echoes on the boresight, which crosses neither plate (nor
do the 8 lines at the rim of its field of view: the sample aircraft's case, whose echoes were labelled −1); the
object an echo came from is then the plate whose range is nearest to the echo's (the echoes are 6 m apart, the
pulse 0.3 m long).
"""
import numpy as np
import pytest

from core.config.settings import BRDFSettings, SimulationConfig
from core.engine.products import ground_truth_tolerance
from core.geometry.groundtruth import surface_material_ids
from core.geometry.scene import merge_meshes
from core.geometry.trace import SceneTracer
from core.run import simulate
from scenes import C, plate

NEAR_M, GAP_M = 100.0, 6.0


def two_plates(range_m, half_m=0.4, lateral_m=0.8):
    """"left" at ``range_m`` (x < 0) and "right" ``GAP_M`` farther (x > 0), both facing the sensor (−Z)."""
    left = plate(range_m, half_m, offset=(-lateral_m, 0.3, 0.0))
    right = plate(range_m + GAP_M, half_m, offset=(lateral_m, -0.3, 0.0))
    return merge_meshes([(left.vertices_m, left.triangles, left.material_ids, ["left"], [BRDFSettings()]),
                         (right.vertices_m, right.triangles, right.material_ids, ["right"],
                          [BRDFSettings(reflectance=0.3)])])


def config(system, range_m):
    cfg = SimulationConfig(system_type=system)
    cfg.run.threads = 1
    cfg.run.save_waveforms = False
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.laser.beam_profile = "uniform"
    half_fov = 2.0 * 1.3 / range_m  # both plates inside, with a margin
    if system == "scanner":
        s = cfg.scanner
        s.pattern, s.n_lines, s.scan_rate_hz, s.pulse_rate_hz = "raster", 24, 100.0, 4800.0
        s.scan_width_rad, s.scan_height_rad = 2 * half_fov, half_fov
        cfg.laser.beam_divergence_rad = 1e-3
    else:
        cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = 2 * half_fov, half_fov
        cfg.receiver.width_px, cfg.receiver.height_px = (1, 1) if system == "profiler" else (32, 16)
        cfg.receiver.subsamples = 200 if system == "profiler" else 3
    if system == "gated":
        g = cfg.gated
        g.gate_width_s, g.delay_step_s, g.n_slices = 20e-9, 3e-9, 30
        g.first_delay_s = 2 * (range_m - 8.0) / C
    else:
        cfg.gate.bin_width_s, cfg.gate.n_bins = 0.25e-9, 400  # 15 m
        cfg.gate.gate_start_s = 2 * (range_m - 4.0) / C
    cfg.detection.max_echoes = 4
    return cfg


@pytest.mark.parametrize("system", ["flash", "gated", "scanner", "profiler"])
def test_every_echo_carries_the_material_of_the_object_it_came_from(system):
    scene = two_plates(NEAR_M)
    cfg = config(system, NEAR_M)
    result = simulate(scene, np.eye(4), cfg)
    pts = result.points
    labels = np.asarray(pts["material_id"])
    names = result.stats["material_names"]
    assert sorted(names) == ["left", "right"]
    assert not np.any(np.asarray(pts.get("false_alarm", np.zeros(len(labels)))))  # noise-free: true returns only
    if system == "profiler":
        rng = np.asarray(pts["range_m"])
        expected = np.where(np.abs(rng - NEAR_M) < np.abs(rng - NEAR_M - GAP_M), "left", "right")
    else:
        expected = np.where(np.asarray(pts["position_world"])[:, 0] < 0, "left", "right")
    got = np.array([names[i] if i >= 0 else "none" for i in labels])
    # both objects seen: the profiler's two echoes, and a field of points on each plate for the imaging systems
    least = 1 if system == "profiler" else 20
    assert np.sum(expected == "left") >= least and np.sum(expected == "right") >= least, system
    np.testing.assert_array_equal(got, expected)


def test_profiler_footprint_fill_finds_an_object_off_the_centre_and_rim():
    """The labelling itself: a point at the range of a plate that sits between the boresight and the rim of a
    6 mrad footprint is unlabelled by the centre line and the 8 rim lines, labelled by the filled footprint, and
    a point 2 m before the plate (beyond the tolerance) stays unlabelled."""
    scene = two_plates(2000.0, half_m=1.0, lateral_m=4.0)  # plates 2 mrad off the axis, 0.5 mrad wide
    tracer = SceneTracer(scene)
    points = np.array([[0.0, 0.0, -2000.0], [0.0, 0.0, -2000.0 - GAP_M], [0.0, 0.0, -1998.0]])
    cfg = SimulationConfig(system_type="profiler")
    cfg.laser.pulse_fwhm_s, cfg.gate.bin_width_s = 1e-9, 0.2e-9
    tol_m, _ = ground_truth_tolerance(cfg)
    assert tol_m == pytest.approx(0.5 * C * (2e-9 + 0.8e-9))  # 0.42 m
    rim = surface_material_ids(tracer, scene.material_ids, np.zeros(3), points, tol_m, 6e-3)
    assert rim.tolist() == [-1, -1, -1]
    filled = surface_material_ids(tracer, scene.material_ids, np.zeros(3), points, tol_m, 6e-3, fill_rings=32)
    assert [scene.material_names[i] if i >= 0 else None for i in filled] == ["left", "right", None]
