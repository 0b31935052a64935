"""The reference range of the turbulence (core.engine.products.reference_range_m) kept per tracer, pixel grid
and pose (session 31): a kept value is the traced one (exact equality), another pose or pixel grid traces again,
and a kept value never crosses to another tracer's geometry."""
import numpy as np

from core.engine import products
from core.engine.products import _trace_reference_range, reference_range_m
from core.geometry.rays import Detector
from core.geometry.trace import SceneTracer
from scenes import plate


def _pose(z):
    pose = np.eye(4)
    pose[2, 3] = z
    return pose


def test_kept_value_is_the_traced_one_and_keyed_by_pose_grid_and_tracer():
    near, far = SceneTracer(plate(100.0, 30.0)), SceneTracer(plate(250.0, 30.0))
    det = Detector(16, 12, 2, 0.05, 0.04)
    origin, rot = np.zeros(3), np.eye(3)
    first = reference_range_m(near, det, origin, rot, 2)
    assert first == _trace_reference_range(near, det, origin, rot, 1)
    assert abs(first - 100.0) < 0.5  # the plate 100 m ahead, pixel-centre rays within 3° of the axis
    calls = []
    orig = products._trace_reference_range
    products._trace_reference_range = lambda *a: calls.append(a) or orig(*a)
    try:
        assert reference_range_m(near, det, origin, rot, 1) == first and not calls  # kept
        moved = reference_range_m(near, det, np.array([0.0, 0.0, 10.0]), rot, 1)  # 10 m further back
        assert len(calls) == 1 and abs(moved - first * 1.1) < 1e-9 * moved  # every range × 110/100
        other_grid = reference_range_m(near, Detector(8, 8, 1, 0.05, 0.04), origin, rot, 1)
        assert len(calls) == 2 and other_grid == _trace_reference_range(near, Detector(8, 8, 1, 0.05, 0.04),
                                                                        origin, rot, 1)
        other = reference_range_m(far, det, origin, rot, 1)  # the same pose on another geometry
        assert len(calls) == 3 and abs(other - 250.0) < 1.0
    finally:
        products._trace_reference_range = orig


def test_kept_values_bounded_per_tracer():
    tracer = SceneTracer(plate(100.0, 30.0))
    det = Detector(4, 4, 1, 0.05, 0.05)
    for k in range(3 * products._REFERENCE_KEEP):
        reference_range_m(tracer, det, np.array([0.0, 0.0, 0.01 * k]), np.eye(3), 1)
    assert len(products._REFERENCE_RANGES[tracer]) <= products._REFERENCE_KEEP
