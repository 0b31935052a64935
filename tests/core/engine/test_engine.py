"""The frame engine (core/engine/): opening a frame, the stage log, blocks on a thread pool, the random streams,
and that every sensor system of core.run.SYSTEMS goes through it with the one common signature."""
import inspect
import threading

import numpy as np
import pytest

from core.config.settings import BRDFSettings, SimulationConfig
from core.engine import frame as frame_engine
from core.engine.blocks import (BLOCKS_PER_THREAD, MATMUL_ROWS, balanced_block_size, item_blocks, rows_matmul,
                                run_blocks, worker_threads)
from core.engine.frame import StageLog, open_frame
from core.engine.rng import RNG_STAGE, stage_rng, stage_seed
from core.errors import Cancelled, ConfigError
from core.geometry.trace import SceneTracer
from core.run import SYSTEMS, simulate
from scenes import C, config_for, plate


# --------------------------------------------------------------------------------------------------------------
# Blocks
# --------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("n, per", [(0, 4), (1, 4), (10, 3), (12, 4), (7, 100)])
def test_item_blocks_cover_the_items_once_in_order(n, per):
    blocks = item_blocks(n, per)
    assert [i for a, b in blocks for i in range(a, b)] == list(range(n))
    assert all(0 < b - a <= per for a, b in blocks)


def test_balanced_block_size_gives_each_thread_eight_blocks_when_it_can():
    assert BLOCKS_PER_THREAD == 8
    assert balanced_block_size(1000, 4000, 1, 10) == 1000          # one thread: as asked
    assert balanced_block_size(1000, 4000, 2, 10) == 250           # ceil(4000 / 16)
    assert balanced_block_size(1000, 4001, 2, 10) == 251           # ceil(4001 / 16)
    assert balanced_block_size(1000, 4000, 2, 800) == 800          # never below the minimum block
    assert balanced_block_size(100, 4000, 2, 10) == 100            # never above the asked size
    assert worker_threads(3) == 3 and worker_threads(0) >= 1


@pytest.mark.parametrize("n", [1, 2, 1000, MATMUL_ROWS + 1, 2 * MATMUL_ROWS, 2 * MATMUL_ROWS + 1, 3 * MATMUL_ROWS + 7])
def test_rows_matmul_is_the_one_product_bit_for_bit(n):
    """Unit directions rotated in row chunks (no one-row chunk, which NumPy computes without BLAS): every bit of
    the single product a @ b, for a rotation and its transpose."""
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=1)[:, None]
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for b in (rot, rot.T):
        assert np.array_equal(rows_matmul(a, b), a @ b)


@pytest.mark.parametrize("threads", [1, 3])
def test_run_blocks_returns_results_in_block_order_and_reports_progress(threads):
    seen = []
    blocks = item_blocks(10, 3)
    out = run_blocks(lambda blk: sum(range(*blk)), blocks, threads, lambda f, text: seen.append((f, text)),
                     label="pixel block")
    assert out == [3, 12, 21, 9]
    # a line at 0 before the first block (which loads or compiles the kernels: issue 27), then one per block
    assert [f for f, _ in seen] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert seen[0][1].startswith("first block: kernels") and seen[-1][1] == "pixel block 4/4"


def test_run_blocks_cancel_raises_and_starts_no_further_block():
    started = []
    lock = threading.Lock()

    def process(blk):
        with lock:
            started.append(blk)
        return blk

    calls = iter([False, False, True] + [True] * 10)
    with pytest.raises(Cancelled):
        run_blocks(process, item_blocks(10, 1), 1, cancel=lambda: next(calls))
    assert started == [(0, 1), (1, 2)]


# --------------------------------------------------------------------------------------------------------------
# Random streams
# --------------------------------------------------------------------------------------------------------------
def test_stage_streams_are_reproducible_and_distinct():
    draw = lambda *key: stage_rng(*key).random(4).tolist()  # noqa: E731
    assert draw(7, 3, "receiver") == draw(7, 3, "receiver")
    others = [draw(8, 3, "receiver"), draw(7, 4, "receiver"), draw(7, 3, "scintillation"),
              draw(7, 3, "receiver", 0), draw(7, 3, "receiver", 1)]
    firsts = [draw(7, 3, "receiver")] + others
    assert len({tuple(x) for x in firsts}) == len(firsts)
    assert stage_seed(7, 3, "beam_wander", 5).entropy == [7, 3, RNG_STAGE["beam_wander"], 6]


def test_unknown_stage_has_no_stream():
    with pytest.raises(KeyError):
        stage_seed(0, 0, "no_such_stage")


# --------------------------------------------------------------------------------------------------------------
# Stage log
# --------------------------------------------------------------------------------------------------------------
def test_stage_log_records_times_runs_and_skips():
    log = StageLog.of(("rays", "trace"), ran=("rays", "trace", "extinction"))
    assert log.times == {"rays": 0.0, "trace": 0.0}
    log.add_times({"rays": 0.25, "echoes": 1.0})
    log.add_times({"rays": 0.5})
    assert log.times == {"rays": 0.75, "trace": 0.0, "echoes": 1.0}
    log.skip("extinction", "no extinction")
    log.skip("extinction", "another reason", keep_earlier=True)
    assert log.ran == ["rays", "trace"] and log.skipped == {"extinction": "no extinction"}
    with log.timed("write"):
        pass
    assert 0.0 <= log.times["write"] < 1.0
    assert log.record() == {"stage_times_s": log.times, "stages_run": ["rays", "trace"],
                            "stages_skipped": {"extinction": "no extinction"}}


# --------------------------------------------------------------------------------------------------------------
# Opening a frame
# --------------------------------------------------------------------------------------------------------------
def test_open_frame_validates_before_anything_is_built(monkeypatch):
    def no_build(*a, **k):
        raise AssertionError("a BVH was built for bad settings")

    monkeypatch.setattr(frame_engine, "SceneTracer", no_build)
    cfg = config_for(100.0, pixels=4)
    cfg.laser.pulse_energy_j = -1.0
    with pytest.raises(ConfigError, match="laser.pulse_energy_j"):
        open_frame(plate(100.0, 10.0), np.eye(4), cfg, StageLog())
    cfg = config_for(100.0, pixels=4)
    cfg.materials = {"no_such_material": BRDFSettings()}
    with pytest.raises(ConfigError, match="no_such_material"):
        open_frame(plate(100.0, 10.0), np.eye(4), cfg, StageLog())


def test_open_frame_applies_material_overrides_and_reuses_a_serving_bvh():
    scene = plate(100.0, 10.0)
    cfg = config_for(100.0, pixels=4)
    cfg.materials = {"plate": BRDFSettings(reflectance=0.123)}
    log = StageLog.of(("build_bvh",), ran=("build_bvh", "rays"))
    fr = open_frame(scene, np.eye(4), cfg, log)
    assert fr.built and fr.bvh == {"bvh": "built"} and log.ran == ["build_bvh", "rays", "scene_check"]
    assert fr.scene.materials[0].reflectance == 0.123 and scene.materials[0].reflectance != 0.123
    np.testing.assert_array_equal(fr.origin, [0.0, 0.0, 0.0])

    log2 = StageLog.of(("build_bvh",), ran=("build_bvh", "rays"))
    fr2 = open_frame(scene, np.eye(4), cfg, log2, tracer=fr.tracer)  # an override shares the geometry arrays
    assert fr2.tracer is fr.tracer and not fr2.built and fr2.bvh == {"bvh": "reused"}
    assert log2.ran == ["rays"] and "build_bvh" in log2.skipped
    assert "scene_check" in log2.skipped  # the same arrays: checked once, at the first frame


def test_open_frame_culls_to_the_field_of_view_when_asked():
    near, far = plate(100.0, 1.0), plate(100.0, 1.0, offset=(500.0, 0.0, 0.0))  # the second is far off-axis
    scene = near.__class__(np.vstack([near.vertices_m, far.vertices_m]),
                           np.vstack([near.triangles, far.triangles + 4]), [0, 0, 0, 0], near.materials,
                           near.material_names)
    log = StageLog()
    fr = open_frame(scene, np.eye(4), config_for(100.0, pixels=4), log, frustum_tan=(0.01, 0.01), fov_culling=True)
    assert fr.bvh["triangles_traced"] == 2 and fr.bvh["triangles_total"] == 4
    assert "fov_culling" in log.ran
    log = StageLog()
    open_frame(scene, np.eye(4), config_for(100.0, pixels=4), log, frustum_tan=(0.01, 0.01), fov_culling=False)
    assert "fov_culling" in log.skipped


# --------------------------------------------------------------------------------------------------------------
# Every system goes through the engine
# --------------------------------------------------------------------------------------------------------------
COMMON = ["scene", "world_from_sensor", "config", "frame", "tracer", "trajectory", "start_time_s", "progress",
          "cancel"]


def _small_config(system):
    """A small frame of each system looking at a plate 100 m away along −Z."""
    cfg = config_for(100.0, pixels=4) if system in ("flash", "profiler") else SimulationConfig(system_type=system)
    cfg.system_type = system
    cfg.run.threads = 2
    if system == "scanner":
        cfg.scanner.n_lines, cfg.scanner.scan_rate_hz, cfg.scanner.pulse_rate_hz = 4, 200.0, 1600.0
        cfg.scanner.scan_width_rad = cfg.scanner.scan_height_rad = 0.01
        cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2 * 90.0 / C, 0.5e-9, 256
        cfg.run.save_waveforms = False
    if system == "gated":
        cfg.receiver.width_px, cfg.receiver.height_px = 8, 4
        cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = 8e-3, 4e-3
        g = cfg.gated
        g.gate_width_s, g.delay_step_s, g.n_slices = 20e-9, 5e-9, 12
        g.first_delay_s = 2 * 100.0 / C - 30e-9
    return cfg


def test_the_dispatcher_is_a_table_of_the_settings_system_types():
    from core.config.settings import SYSTEM_TYPES

    assert set(SYSTEMS) == set(SYSTEM_TYPES)


@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_every_system_has_the_common_signature(system):
    params = inspect.signature(SYSTEMS[system]).parameters
    assert list(params)[:len(COMMON)] == COMMON
    assert all(params[p].kind is inspect.Parameter.KEYWORD_ONLY for p in COMMON[3:])
    assert [params[p].default for p in COMMON[3:]] == [0, None, None, 0.0, None, None]


@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_every_system_records_its_stages_and_reuses_a_given_bvh(system):
    scene = plate(100.0, 10.0)
    cfg = _small_config(system)
    fractions = []
    first = simulate(scene, np.eye(4), cfg, progress=lambda f, text: fractions.append(f))
    assert fractions and fractions[-1] == 1.0
    stats = first.stats
    assert "build_bvh" in stats["stages_run"] and "build_bvh" in stats["stage_times_s"]
    assert set(stats["stages_run"]).isdisjoint(stats["stages_skipped"])
    assert first.points["range_m"].size > 0
    assert np.allclose(np.nanmin(first.points["range_m"]), 100.0, atol=0.5)

    again = simulate(scene, np.eye(4), cfg, tracer=SceneTracer(scene))
    assert "build_bvh" not in again.stats["stages_run"] and "build_bvh" in again.stats["stages_skipped"]
    for key in first.points:
        np.testing.assert_array_equal(first.points[key], again.points[key], err_msg=key)


@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_every_system_can_be_cancelled(system):
    with pytest.raises(Cancelled):
        simulate(plate(100.0, 10.0), np.eye(4), _small_config(system), cancel=lambda: True)


@pytest.mark.parametrize("system", sorted(SYSTEMS))
def test_every_system_refuses_bad_settings_before_tracing(system, monkeypatch):
    def no_build(*a, **k):
        raise AssertionError("a BVH was built for bad settings")

    monkeypatch.setattr(frame_engine, "SceneTracer", no_build)
    cfg = _small_config(system)
    cfg.laser.wavelength_m = -1.0
    with pytest.raises(ConfigError, match="laser.wavelength_m"):
        simulate(plate(100.0, 10.0), np.eye(4), cfg)
