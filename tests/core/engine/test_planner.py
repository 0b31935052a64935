"""The planner (core/systems/flash.py plan() and simulate_frame): what runs, what is skipped and why, the reduced
model when an effect is off, no waveform cube for points-only runs, field-of-view culling, BVH reuse, and the
memory check that refuses runs that would not fit."""
import dataclasses

import numpy as np
import pytest

from core.engine import frame as frame_engine
from core.systems import flash as pipeline
from core.config.settings import BRDFSettings
from core.errors import ConfigError
from core.geometry.culling import frustum_triangles
from core.engine.memory import estimate_flash_memory
from core.run import run_simulation
from core.systems.flash import simulate_frame
from core.geometry.scene import SceneGeometry, merge_meshes
from core.geometry.trace import SceneTracer
from scenes import config_for, plate


def _same_products(a, b):
    assert np.array_equal(a.energy_image, b.energy_image)
    assert np.array_equal(a.range_echoes, b.range_echoes, equal_nan=True)
    assert np.array_equal(a.intensity_echoes, b.intensity_echoes)
    assert (a.waveforms is None and b.waveforms is None) or np.array_equal(a.waveforms, b.waveforms)
    for k in a.points:
        assert np.array_equal(a.points[k], b.points[k]), k


def _crowded_scene(n_side=40):
    """A plate 100 m ahead in the field of view, and a ground of 2·n_side² triangles all around the sensor
    (behind and beside it; a strip of it also in view below the plate)."""
    target = plate(100.0, 3.0)
    g = np.linspace(-400.0, 400.0, n_side + 1)
    gx, gz = np.meshgrid(g, g)
    verts = np.stack([gx.ravel(), np.full(gx.size, -5.0), gz.ravel()], axis=1)
    i = np.arange(n_side)
    a = (i[:, None] * (n_side + 1) + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n_side + 2], 1), np.stack([a, a + n_side + 2, a + n_side + 1], 1)])
    return merge_meshes([(target.vertices_m, target.triangles, target.material_ids, ["plate"], [BRDFSettings()]),
                         (verts, tris, np.zeros(len(tris)), ["ground"], [BRDFSettings(reflectance=0.1)])])


def test_fov_culling_traces_only_the_visible_triangles_with_the_same_products():
    """Of 3202 triangles only the plate and the ground cells in the 0.1 rad field of view (69) are in the BVH;
    the products are bit-identical to tracing the whole scene."""
    scene = _crowded_scene()
    cfg = config_for(100.0, pixels=16, subsamples=2, fov_rad=0.1, bins=400, margin_bins=100)
    culled = simulate_frame(scene, np.eye(4), cfg)
    full = simulate_frame(scene, np.eye(4), cfg, fov_culling=False)
    info = culled.stats["bvh"]
    assert info["triangles_total"] == 3202 and 2 <= info["triangles_traced"] < 100  # measured 69
    assert "fov_culling" in culled.stats["stages_run"] and "fov_culling" in full.stats["stages_skipped"]
    _same_products(culled, full)


def test_frustum_test_keeps_every_triangle_a_ray_hits():
    """Random triangles around a random pose: every triangle hit by 40 000 rays spread over the field of view
    (traced against the whole scene) is kept; triangles entirely behind the sensor are dropped."""
    rng = np.random.default_rng(11)
    centres = rng.uniform(-200, 200, (3000, 3))
    verts = (centres[:, None, :] + rng.normal(scale=3.0, size=(3000, 3, 3))).reshape(-1, 3)
    scene = SceneGeometry(verts, np.arange(9000).reshape(-1, 3), np.zeros(3000))
    angle = 0.7
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    origin = np.array([3.0, -2.0, 1.0])
    tx, ty = np.tan(0.2), np.tan(0.15)
    keep = frustum_triangles(scene.vertices_m, scene.triangles, origin, rot, tx, ty)
    x, y = rng.uniform(-tx, tx, 40_000), rng.uniform(-ty, ty, 40_000)
    d = np.stack([x, y, -np.ones_like(x)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    prim, _, _ = SceneTracer(scene).intersect(origin, d @ rot.T)
    hit = np.unique(prim[prim >= 0])
    assert len(hit) > 20 and keep[hit].all()
    assert 0.005 < keep.mean() < 0.1  # a 0.4 × 0.3 rad view of a cloud around the sensor (measured 1.5 %)
    behind = ((scene.vertices_m - origin) @ rot)[:, 2].reshape(-1, 3).min(axis=1) > 0
    assert not keep[behind].any()
    # the culled tracer reports the same hits, with the scene's triangle numbers
    prim_culled, _, _ = SceneTracer(scene, keep=keep).intersect(origin, d @ rot.T)
    assert np.array_equal(prim_culled, prim)


def test_static_geometry_is_not_rebuilt(monkeypatch):
    """A second frame given the first frame's tracer (same SceneGeometry, or a copy with material overrides,
    which shares the arrays) builds no BVH, and says so."""
    scene = plate(100.0, 10.0)
    cfg = config_for(100.0, pixels=4)
    tracer = SceneTracer(scene)
    built = []
    real = frame_engine.SceneTracer

    def counting(*args, **kwargs):
        built.append(args)
        return real(*args, **kwargs)
    monkeypatch.setattr(frame_engine, "SceneTracer", counting)  # the frame engine builds every BVH
    first = simulate_frame(scene, np.eye(4), cfg, tracer=tracer, frame=1)
    cfg.materials = {"plate": BRDFSettings(reflectance=0.6)}
    second = simulate_frame(scene, np.eye(4), cfg, tracer=tracer, frame=2)
    assert built == []
    assert first.stats["bvh"]["bvh"] == "reused" and "build_bvh" in first.stats["stages_skipped"]
    assert second.energy_image.sum() == pytest.approx(2 * first.energy_image.sum())
    simulate_frame(scene, np.eye(4), cfg)  # no tracer: one is built
    assert len(built) == 1


class _AllocationSpy:
    """Stands in for numpy inside core.systems.flash and records the shapes of the arrays it allocates."""

    def __init__(self):
        self.shapes = []

    def __getattr__(self, name):
        return getattr(np, name)

    def zeros(self, shape, *args, **kwargs):
        self.shapes.append(tuple(np.atleast_1d(shape)))
        return np.zeros(shape, *args, **kwargs)

    def empty(self, shape, *args, **kwargs):
        self.shapes.append(tuple(np.atleast_1d(shape)))
        return np.empty(shape, *args, **kwargs)


def test_points_only_run_never_builds_a_waveform_cube(monkeypatch):
    """save_waveforms = false: no (pixels, bins) array is ever allocated by the pipeline (the spy sees the
    cube when waveforms are saved), and the points are those of the full run."""
    cfg = config_for(100.0, pixels=8, bins=300)
    spy = _AllocationSpy()
    monkeypatch.setattr(pipeline, "np", spy)
    full = simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    assert (64, 300) in spy.shapes
    spy.shapes.clear()
    cfg.run.save_waveforms = False
    points = simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    assert not any(len(s) >= 2 and s[-1] == 300 and int(np.prod(s[:-1])) == 64 for s in spy.shapes)
    assert points.waveforms is None and "waveform_cube" in points.stats["stages_skipped"]
    for k in full.points:
        assert np.array_equal(full.points[k], points.points[k]), k


@pytest.mark.parametrize("case", ["turbulence_off", "adaptive_without_disagreement", "spread_at_normal_incidence",
                                  "no_extinction"])
def test_an_effect_turned_off_gives_exactly_the_reduced_model(case):
    """Bit-identical products: Cn² > 0 with every turbulence effect switched off ≡ Cn² = 0; the adaptive
    pattern when no pixel disagrees ≡ Sobol; the cell range spread where every cell's box is below 1 % of the
    pulse σ ≡ point sub-rays; visibility 0 and extinction 0 ≡ the default (no extinction stage)."""
    scene = plate(300.0, 40.0)
    cfg = config_for(300.0, pixels=8, subsamples=4, fov_rad=0.002)
    reduced = dataclasses.replace(cfg)
    if case == "turbulence_off":
        cfg.atmosphere = dataclasses.replace(cfg.atmosphere, cn2_m_23=1e-13, beam_broadening=False,
                                             scintillation=False, beam_wander=False, turbulence_blur="none")
    elif case == "adaptive_without_disagreement":
        cfg.receiver = dataclasses.replace(cfg.receiver, subray_pattern="adaptive")
        reduced.receiver = dataclasses.replace(cfg.receiver, subray_pattern="sobol")
    elif case == "spread_at_normal_incidence":
        reduced.receiver = dataclasses.replace(cfg.receiver, cell_range_spread=False)
    else:
        cfg.atmosphere = dataclasses.replace(cfg.atmosphere, visibility_m=0.0, extinction_per_m=0.0)
    a, b = simulate_frame(scene, np.eye(4), cfg), simulate_frame(scene, np.eye(4), reduced)
    _same_products(a, b)
    if case == "turbulence_off":
        assert {"beam_broadening", "scintillation", "beam_wander", "turbulence_blur"} <= set(a.stats["stages_skipped"])
    if case == "adaptive_without_disagreement":
        assert a.stats["adaptive"]["refined_pixels"] == 0


def test_stage_times_and_reasons_are_recorded():
    res = simulate_frame(_crowded_scene(10), np.eye(4), config_for(100.0, pixels=8, fov_rad=0.1, margin_bins=100))
    times = res.stats["stage_times_s"]
    assert {"build_bvh", "rays", "trace", "radiometry", "waveform", "echoes", "products"} <= set(times)
    assert all(t >= 0 for t in times.values()) and times["trace"] > 0
    assert res.stats["stages_skipped"]["extinction"].startswith("no extinction")
    assert "atmosphere.cn2_m_23 = 0" in res.stats["stages_skipped"]["scintillation"]
    assert res.stats["bvh"]["time_s"] >= 0 and res.stats["memory_estimate_bytes"] > 0


def test_a_run_that_would_not_fit_is_refused_naming_the_setting_and_writes_nothing(tmp_path):
    """2048² pixels × 4×4 sub-rays × 1000 bins, points only (no cube), with adaptive refinement ×32: the
    worst-case refinement alone is ≈ 1000 GiB: refused before anything is traced or written, naming
    receiver.subray_refine; a cube-dominated run names gate.n_bins; threads name run.threads."""
    cfg = config_for(100.0, pixels=2048, subsamples=4, bins=1000)
    cfg.run.save_waveforms = False
    cfg.receiver.subray_pattern = "adaptive"
    cfg.receiver.subray_refine = 32
    with pytest.raises(ConfigError) as info:
        run_simulation(plate(100.0, 10.0), np.eye(4), cfg, tmp_path / "run")
    assert info.value.field == "receiver.subray_refine" and "GiB" in str(info.value)
    assert "run.max_memory_bytes" in str(info.value)
    assert list(tmp_path.iterdir()) == []
    cfg.receiver.subray_refine = 2
    cfg.receiver.subray_pattern = "grid"
    cfg.detector.mode = "noisy"  # the noisy chain needs the cube: ≈ 5 cubes of 16 GiB
    cfg.run.max_memory_bytes = 2 ** 40
    with pytest.raises(ConfigError) as info:
        simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    assert info.value.field == "gate.n_bins"


def test_the_available_memory_limits_a_run(monkeypatch):
    """With 100 MiB available (less than run.max_memory_bytes) a default 64×64 run (≈ 0.12 GiB estimated) is
    refused, and the message says the limit is the available memory."""
    monkeypatch.setattr("core.engine.memory.available_memory_bytes", lambda: 100 * 2 ** 20)
    cfg = config_for(100.0, pixels=64)
    cfg.run.threads = 2
    with pytest.raises(ConfigError) as info:
        simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    assert "the memory available now" in str(info.value)
    assert estimate_flash_memory(cfg)["total"] > 100 * 2 ** 20


def test_the_scene_is_checked_once_not_every_frame(monkeypatch):
    """open_frame checks a scene's arrays at its first frame only (also through a material-override copy, which
    shares them); a replaced array is checked again at the next frame, the materials at every frame; a change made
    in place is not seen (the documented limit) until ``check()`` is called, which always validates."""
    from core.run import simulate

    scene = plate(100.0, 10.0)
    cfg = config_for(100.0, pixels=4)
    calls = []
    real = SceneGeometry.check

    def counting(self):
        calls.append(self)
        return real(self)
    monkeypatch.setattr(SceneGeometry, "check", counting)
    tracer = SceneTracer(scene)
    first = simulate(scene, np.eye(4), cfg, tracer=tracer)
    assert len(calls) == 1 and "scene_check" in first.stats["stages_run"]
    cfg.materials = {"plate": BRDFSettings(reflectance=0.6)}
    second = simulate(scene, np.eye(4), cfg, tracer=tracer)
    third = simulate(scene, np.eye(4), cfg, tracer=tracer)
    assert len(calls) == 1
    for res in (second, third):
        assert "scene_check" in res.stats["stages_skipped"] and "scene_check" not in res.stats["stages_run"]
    # a replaced array: checked again, and refused
    bad = scene.vertices_m.copy()
    bad[1, 2] = np.nan
    scene.vertices_m = bad
    with pytest.raises(ConfigError, match="scene.vertices_m"):
        simulate(scene, np.eye(4), cfg, tracer=tracer)
    # the materials are checked at every frame
    scene = plate(100.0, 10.0)
    simulate(scene, np.eye(4), config_for(100.0, pixels=4))
    scene.materials[0] = "not a BRDF"
    with pytest.raises(ConfigError, match="materials.plate"):
        simulate(scene, np.eye(4), config_for(100.0, pixels=4))
    # in place: not seen by the per-frame check (documented), seen by check()
    scene = plate(100.0, 10.0)
    assert scene.ensure_checked() is True and scene.ensure_checked() is False
    scene.triangles[0, 0] = 99
    assert scene.ensure_checked() is False
    with pytest.raises(ConfigError, match="scene.triangles"):
        scene.check()
    with pytest.raises(ConfigError, match="scene.triangles"):  # and stays refused until the arrays pass again
        scene.ensure_checked()


def test_ground_truth_is_the_same_on_any_thread_count_and_skipped_when_not_needed(monkeypatch):
    """surface_material_ids labels each point on its own: 1, 2 and 3 threads give the same labels, on points on
    both materials, at object edges (the lines around the centre line) and in empty air (−1); and lines that end
    at their first crossing past the point and cast no farther than a crossing can win (PRUNE_LINES) give the
    labels of tracing on to the tolerance (with fewer casts).  simulate(..., ground_truth=False) skips it and says so; by default the stage plan lists
    it as run."""
    from core.geometry import groundtruth
    from core.run import simulate

    scene = _crowded_scene()
    tracer = SceneTracer(scene)
    rng = np.random.default_rng(7)
    n = 5 * groundtruth.MIN_PART
    # points on the plate (z = −100, |x|, |y| ≤ 3 + a margin: edges), on the ground (y = −5) and in the air
    on_plate = np.column_stack([rng.uniform(-3.5, 3.5, n // 2), rng.uniform(-3.5, 3.5, n // 2),
                                np.full(n // 2, -100.0) + rng.normal(0, 0.05, n // 2)])
    on_ground = np.column_stack([rng.uniform(-60, 60, n // 4), np.full(n // 4, -5.0), rng.uniform(-300, -20, n // 4)])
    in_air = rng.uniform([-50, 10, -300], [50, 50, -20], (n - n // 2 - n // 4, 3))
    pos = np.concatenate([on_plate, on_ground, in_air])
    one = groundtruth.surface_material_ids(tracer, scene.material_ids, np.zeros(3), pos, 0.3, 0.01, threads=1)
    assert set(np.unique(one)) == {-1, 0, 1}
    for threads in (2, 3):
        assert np.array_equal(groundtruth.surface_material_ids(tracer, scene.material_ids, np.zeros(3), pos, 0.3,
                                                               0.01, threads=threads), one)
    casts = []
    real = tracer.intersect

    def counting(origin, directions, **kwargs):
        casts.append(len(directions))
        return real(origin, directions, **kwargs)
    monkeypatch.setattr(tracer, "intersect", counting)
    for stop in (True, False):
        monkeypatch.setattr(groundtruth, "PRUNE_LINES", stop)
        casts.clear()
        # a tolerance of 3 m: the plate's points see the ground behind it within reach when traced on
        labels = groundtruth.surface_material_ids(tracer, scene.material_ids, np.zeros(3), pos, 3.0, 0.01)
        if stop:
            stopped, n_stopped = labels, sum(casts)
    assert np.array_equal(stopped, labels) and n_stopped < 0.95 * sum(casts)  # 46 224 against 51 695 rays
    monkeypatch.undo()
    cfg = config_for(100.0, pixels=8)
    labelled = simulate(scene, np.eye(4), cfg, tracer=tracer)
    assert "ground_truth" in labelled.stats["stages_run"] and "material_id" in labelled.points
    skipped = simulate(scene, np.eye(4), cfg, tracer=tracer, ground_truth=False)
    assert "ground_truth" in skipped.stats["stages_skipped"] and "material_id" not in skipped.points
