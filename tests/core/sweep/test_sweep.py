"""Sweeps (core/sweep): the sweep file, validation of every point, and real runs on a dask.distributed
LocalCluster of worker processes — a 2-axis sweep, a worker killed mid-sweep, a resume, and the table's figures
against the same points run one by one with ``run_simulation``."""
import json
import math
import os
import shutil
import signal
import sys

import numpy as np
import pytest

from core.engine.memory import estimate_memory
from core.errors import ConfigError
from core.run import run_simulation
from core.sweep.runner import figure_statistics, open_client, plan_sweep, read_table, replot, run_sweep
from core.sweep.shipping import can_import, ship_core, stage_core
from core.sweep.scene import SweepScene, boresight_point, pose_at_range
from core.sweep.spec import load_sweep, point_configs, points, sweep_from_dict, task_seed
from core.sweep.task import FIGURES, match_window_m, summarize, task_config, truth_echo_ranges
from scenes import config_for, plate

distributed = pytest.importorskip("distributed")

RANGE_M = 200.0


def base_config(noisy=False):
    cfg = config_for(RANGE_M, pixels=8, bins=96, margin_bins=48)
    cfg.run.save_waveforms = False
    if noisy:
        cfg.detector.mode = "noisy"
        cfg.detector.read_noise_e = 50.0
    return cfg


def scene():
    return SweepScene.single(plate(RANGE_M, 4.0), np.eye(4))


def spec_dict(**over):
    d = {"sweep_version": 1, "seed": 11, "seeds": 2,
         "axes": {"laser.pulse_energy_j": [1e-4, 1e-3], "sensor.range_m": [195.0, 205.0]}}
    d.update(over)
    return d


@pytest.fixture(scope="module")
def client():
    stage_core()  # the workers inherit the staged core on sys.path (a remote cluster gets it uploaded)
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=40)
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


# ----------------------------------------------------------------------------------------------------------------
# The sweep file
# ----------------------------------------------------------------------------------------------------------------
def test_axes_lists_ranges_log_ranges_grid_and_zip(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('sweep_version = 1\nseeds = 3\ncombine = "grid"\n[axes]\n'
                 '"laser.pulse_energy_j" = { start = 1e-5, stop = 1e-3, num = 3, spacing = "log" }\n'
                 'receiver.width_px = { start = 16, stop = 64, step = 16 }\n'
                 '"atmosphere.visibility_m" = { start = 1000, stop = 2000, num = 3 }\n', encoding="utf-8")
    spec = load_sweep(f)
    assert spec.axis_names == ["laser.pulse_energy_j", "receiver.width_px", "atmosphere.visibility_m"]
    assert spec.axes[0].values == pytest.approx([1e-5, 1e-4, 1e-3], rel=1e-12)
    assert spec.axes[1].values == [16, 32, 48, 64] and all(isinstance(v, int) for v in spec.axes[1].values)
    assert spec.axes[2].values == [1000.0, 1500.0, 2000.0]
    pts = points(spec)
    assert len(pts) == 3 * 4 * 3
    assert pts[0] == {"laser.pulse_energy_j": spec.axes[0].values[0], "receiver.width_px": 16,
                      "atmosphere.visibility_m": 1000.0}
    assert pts[1]["atmosphere.visibility_m"] == 1500.0  # the last axis varies fastest
    z = sweep_from_dict({"sweep_version": 1, "combine": "zip",
                         "axes": {"atmosphere": {"visibility_m": [1000, 2000]}, "laser.pulse_energy_j": [1e-3, 2e-3]}})
    assert points(z) == [{"atmosphere.visibility_m": 1000, "laser.pulse_energy_j": 1e-3},
                         {"atmosphere.visibility_m": 2000, "laser.pulse_energy_j": 2e-3}]


@pytest.mark.parametrize("data, field, words", [
    ({"sweep_version": 2, "axes": {"laser.pulse_energy_j": [1e-3]}}, "sweep_version", "1"),
    ({"sweep_version": 1, "axes": {}}, "axes", "at least one axis"),
    ({"sweep_version": 1, "axes": {"run.seed": [1, 2]}}, "axes.run.seed", "seeds"),
    ({"sweep_version": 1, "combine": "zip", "axes": {"a.b": [1, 2], "c.d": [1]}}, "axes.c.d", "2 values"),
    ({"sweep_version": 1, "axes": {"laser.pulse_energy_j": {"start": 0, "stop": 1, "num": 3, "spacing": "log"}}},
     "axes.laser.pulse_energy_j.start", "> 0"),
    ({"sweep_version": 1, "axes": {"laser.pulse_energy_j": {"start": 1, "stop": 2}}}, "axes.laser.pulse_energy_j",
     "num"),
    ({"sweep_version": 1, "seeds": 0, "axes": {"laser.pulse_energy_j": [1e-3]}}, "seeds", "[1, 100000]"),
    ({"sweep_version": 1, "axis": {}}, "axis", "a sweep entry"),
])
def test_bad_sweep_files_are_refused_naming_the_entry(data, field, words):
    with pytest.raises(ConfigError) as err:
        sweep_from_dict(data)
    assert err.value.field == field
    assert words in str(err.value)


@pytest.mark.parametrize("axes, field, value, words", [
    ({"atmosphere.visibility_m": [1000.0, 20.0]}, "atmosphere.visibility_m", 20.0, "[50, 1e+06] m"),
    ({"laser.pulse_energy_j": [1e-3, -1.0]}, "laser.pulse_energy_j", -1.0, "(0, 100] J"),
    ({"receiver.width_px": {"start": 8, "stop": 9, "num": 3}}, "receiver.width_px", 8.5, "whole number"),
    ({"laser.pulse_shape": ["gaussian", "square"]}, "laser.pulse_shape", "square", "'rectangular'"),
    ({"laser.no_such": [1.0]}, "axes.laser.no_such", 1.0, "a known setting"),
    ({"materials.Steel.reflectance": [0.5]}, "axes.materials.Steel.reflectance", "Steel", "plate"),
    ({"sensor.range_m": [100.0, -5.0]}, "sensor.range_m", -5.0, "(0, 1e+07] m"),
])
def test_every_point_is_validated_before_anything_runs(tmp_path, axes, field, value, words):
    spec = sweep_from_dict({"sweep_version": 1, "axes": axes})
    out = tmp_path / "sweep"
    with pytest.raises(ConfigError) as err:
        run_sweep(spec, scene(), out, base=base_config(), client=object())  # never reaches the client
    assert err.value.field == field and err.value.value == value
    assert words in str(err.value) and "sweep point" in str(err.value)
    assert not out.exists()  # nothing written


def test_task_seeds_derive_from_the_sweep_seed_and_indices_only():
    seeds = {task_seed(11, p, s) for p in range(20) for s in range(20)}
    assert len(seeds) == 400 and all(0 <= s < 2**63 for s in seeds)
    assert task_seed(11, 3, 4) == task_seed(11, 3, 4) != task_seed(12, 3, 4)
    ref = np.random.SeedSequence([11, 3, 4]).generate_state(2, np.uint64)[0] >> np.uint64(1)
    assert task_seed(11, 3, 4) == int(ref)


def test_range_axis_moves_the_sensor_along_its_boresight():
    sc = SweepScene.single(plate(RANGE_M, 4.0), np.eye(4))
    target = boresight_point(sc, 0)
    assert target == pytest.approx([0.0, 0.0, -RANGE_M], abs=1e-9)
    pose = pose_at_range(np.eye(4), target, 150.0)
    assert pose[:3, 3] == pytest.approx([0.0, 0.0, -50.0], abs=1e-9)


def test_material_axis_starts_from_the_scene_brdf():
    spec = sweep_from_dict({"sweep_version": 1, "axes": {"materials.plate.reflectance": [0.1, 0.9]}})
    sc = scene()
    cfgs = point_configs(spec, base_config(), sc.material_brdfs())
    assert [c.materials["plate"].reflectance for _, c, _ in cfgs] == [0.1, 0.9]
    assert cfgs[0][1].materials["plate"].model == "lambertian"


def test_frames_make_one_task_each_with_the_point_seed(tmp_path):
    pose2 = np.eye(4)
    pose2[2, 3] = 10.0  # frame 2: the sensor 10 m further back
    sc = SweepScene([plate(RANGE_M, 4.0)], [1, 2], [0, 0], [np.eye(4), pose2])
    spec = sweep_from_dict({"sweep_version": 1, "seeds": 2, "frames": [1, 2],
                            "axes": {"laser.pulse_energy_j": [1e-4, 1e-3]}})
    plan = plan_sweep(spec, sc, base_config(), tmp_path / "sw")
    assert [t["name"] for t in plan.tasks[:4]] == ["p0000-s00-f0001", "p0000-s00-f0002", "p0000-s01-f0001",
                                                    "p0000-s01-f0002"]
    assert plan.tasks[0]["seed"] == plan.tasks[1]["seed"] != plan.tasks[2]["seed"]
    with pytest.raises(ConfigError) as err:
        plan_sweep(sweep_from_dict({**spec.normalized(), "frames": [3], "axes": {"laser.pulse_energy_j": [1e-3]}}),
                   sc, base_config())
    assert err.value.field == "frames" and "1, 2" in str(err.value)


def test_summary_figures_against_a_known_truth():
    """Pixel 0 has noise-free echoes at 100 and 110 m and reports 100.1, 104 (a true return the noise-free
    detection left out: no match within c·5 ns/2 = 0.75 m) and 109.8 m; pixel 1 (truth 50 m) reports only a false
    alarm; pixel 2 (no truth) a false alarm."""
    from types import SimpleNamespace
    cfg = base_config()
    cfg.laser.pulse_fwhm_s = 5e-9
    assert match_window_m(cfg) == pytest.approx(0.749481145)
    truth = np.full((1, 3, 2), np.nan)
    truth[0, 0] = (100.0, 110.0)
    truth[0, 1, 0] = 50.0
    pts = {"range_m": np.array([100.1, 104.0, 109.8, 70.0, 30.0]), "pixel_x": np.array([0, 0, 0, 1, 2]),
           "pixel_y": np.zeros(5, int), "echo_index": np.array([1, 2, 3, 1, 1]),
           "false_alarm": np.array([0, 0, 0, 1, 1])}
    row = summarize(SimpleNamespace(points=pts, stats={"received_energy_j": 2.5e-12}), cfg, truth)
    assert (row["points"], row["pixels_with_echo"], row["false_alarms"]) == (5, 3, 2)
    assert row["received_energy_j"] == 2.5e-12
    assert row["detection_probability"] == 0.5
    assert row["range_error_mean_m"] == pytest.approx(-0.05, abs=1e-12)
    assert row["range_error_rms_m"] == pytest.approx(math.sqrt(0.025), abs=1e-12)
    assert row["range_error_p95_abs_m"] == pytest.approx(0.195, abs=1e-12)
    ideal = summarize(SimpleNamespace(points={k: v for k, v in pts.items() if k != "false_alarm"}, stats={}), None)
    assert math.isnan(ideal["detection_probability"]) and math.isnan(ideal["false_alarms"])


def test_scene_round_trips_through_its_files(tmp_path):
    sc = scene()
    sc.save(tmp_path / "scene")
    back = SweepScene.load(tmp_path / "scene")
    assert back.digest() == sc.digest()
    assert np.array_equal(back.geometries[0].vertices_m, sc.geometries[0].vertices_m)


# ----------------------------------------------------------------------------------------------------------------
# On a real LocalCluster of worker processes
# ----------------------------------------------------------------------------------------------------------------
def serial_row(task, noisy):
    """The same task run by itself in this process through run_simulation (no Dask)."""
    cfg = task_config(task)
    cfg.run.save_waveforms = noisy  # keep the noise-free cube for the truth (products otherwise identical)
    pose = np.eye(4)
    if task["range_m"] is not None:
        pose = pose_at_range(pose, task["target_m"], task["range_m"])
    tmp = f"{task['out']}-serial"
    _, result = run_simulation(plate(RANGE_M, 4.0), pose, cfg, tmp)
    shutil.rmtree(tmp)
    truth = truth_echo_ranges(result.waveforms, cfg) if noisy else None
    return summarize(result, cfg, truth)


def as_number(text):
    return math.nan if text == "" else float(text)


def test_two_axis_sweep_table_equals_the_points_run_one_by_one(client, tmp_path):
    spec = sweep_from_dict(spec_dict())
    base = base_config(noisy=True)
    out = run_sweep(spec, scene(), tmp_path / "sw", base=base, client=client)
    assert (out.n_tasks, out.n_done, out.n_failed, out.n_run) == (8, 8, 0, 8)
    rows = read_table(tmp_path / "sw" / "results.csv")
    assert len(rows) == 8 and [r["task"] for r in rows] == [f"p{p:04d}-s{s:02d}" for p in range(4) for s in range(2)]
    plan = plan_sweep(spec, scene(), base, tmp_path / "sw")
    for task, row in zip(plan.tasks, rows):
        assert row["status"] == "done" and row["error"] == ""
        assert float(row["laser.pulse_energy_j"]) == task["values"]["laser.pulse_energy_j"]
        assert float(row["sensor.range_m"]) == task["values"]["sensor.range_m"]
        assert int(row["seed"]) == task_seed(11, task["point"], task["seed_index"])
        ref = serial_row(task, noisy=True)
        for fig in FIGURES:
            got, want = as_number(row[fig]), float(ref[fig])
            assert (math.isnan(got) and math.isnan(want)) or got == want, (task["name"], fig, got, want)
        meta = json.loads((tmp_path / "sw" / row["run"] / "metadata.json").read_text())
        assert meta["seed"] == int(row["seed"]) and meta["sweep"]["task"] == task["name"]
    # the figures mean something: more pulse energy, more pixels with an echo and a smaller range error
    weak = [r for r in rows if float(r["laser.pulse_energy_j"]) == 1e-4]
    strong = [r for r in rows if float(r["laser.pulse_energy_j"]) == 1e-3]
    assert np.mean([as_number(r["received_energy_j"]) for r in strong]) == pytest.approx(
        10 * np.mean([as_number(r["received_energy_j"]) for r in weak]), rel=1e-9)
    assert all(as_number(r["detection_probability"]) == 1.0 for r in strong)
    assert all(abs(as_number(r["range_error_mean_m"])) < 0.15 for r in strong)
    assert len(out.plots) == 2 * sum(1 for r in FIGURES)  # every figure is defined for a noisy flash sweep
    assert all(p.stat().st_size > 1000 for p in out.plots)
    assert sorted(p.name for p in replot(tmp_path / "sw")) == sorted(p.name for p in out.plots)  # from the table


def test_results_do_not_depend_on_the_number_of_workers(client, tmp_path, monkeypatch):
    """The same noisy sweep on the 2-worker cluster and on a 1-worker LocalCluster that run_sweep starts itself
    (which inherits the staged core: no upload); the same table but for run times; progress counts the tasks
    with an ETA."""
    import re

    import distributed.diagnostics.plugin as plugin

    def no_upload(*args, **kwargs):
        raise AssertionError("the workers of the sweep's own local cluster should not need the core uploaded")

    spec = sweep_from_dict(spec_dict(seeds=3))  # 12 tasks
    two = run_sweep(spec, scene(), tmp_path / "two", base=base_config(noisy=True), client=client, plots=False)
    monkeypatch.setattr(plugin, "UploadDirectory", no_upload)
    _, outer = stage_core()
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(outer)])  # as in a fresh process
    seen = []
    one = run_sweep(spec, scene(), tmp_path / "one", base=base_config(noisy=True), n_workers=1, plots=False,
                    progress=lambda fraction, text: seen.append((fraction, text)))
    assert (two.n_workers, one.n_workers) == (2, 1) and one.n_done == two.n_done == 12
    keep = ("task", "point", "seed_index", "laser.pulse_energy_j", "sensor.range_m", "seed", "status", "run",
            *FIGURES)
    rows_one = read_table(tmp_path / "one" / "results.csv")
    assert [{k: r[k] for k in keep} for r in rows_one] == [{k: r[k] for k in keep}
                                                            for r in read_table(tmp_path / "two" / "results.csv")]
    assert len({r["seed"] for r in rows_one}) == 12 and all(as_number(r["false_alarms"]) >= 0 for r in rows_one)
    assert [f for f, _ in seen] == sorted(f for f, _ in seen) and seen[-1][0] == 1.0 and len(seen) >= 2
    assert all(re.fullmatch(r"\d+/12 tasks, ETA \d+ s", text) for _, text in seen), seen
    assert seen[-1][1] == "12/12 tasks, ETA 0 s"


def test_plot_statistics_are_the_mean_and_spread_over_seeds():
    rows = [{"status": "done", "a": a, "b": b, "points": v} for a, b, v in
            [(1, 10, 2.0), (1, 10, 4.0), (2, 10, 6.0), (2, 10, 6.0), (1, 20, 1.0), (1, 20, 3.0), (2, 20, 5.0)]]
    rows.append({"status": "failed", "a": 2, "b": 20, "points": math.nan})
    series = figure_statistics(rows, "a", "points", ["b"])
    assert series == [("b = 10", [1, 2], [3.0, 6.0], [1.0, 0.0], [2, 2]),
                      ("b = 20", [1, 2], [2.0, 5.0], [1.0, 0.0], [2, 1])]


def test_resume_runs_only_what_is_missing_and_a_changed_sweep_is_refused(client, tmp_path):
    spec = sweep_from_dict(spec_dict(seeds=1))
    out_dir = tmp_path / "sw"
    first = run_sweep(spec, scene(), out_dir, base=base_config(), client=client, plots=False)
    assert (first.n_done, first.n_run) == (4, 4)
    table = (out_dir / "results.csv").read_text()
    again = run_sweep(spec, scene(), out_dir, base=base_config(), client=client, plots=False)
    assert (again.n_done, again.n_run, again.n_resumed) == (4, 0, 4)
    assert (out_dir / "results.csv").read_text() == table
    shutil.rmtree(out_dir / "runs" / "p0002-s00")
    third = run_sweep(spec, scene(), out_dir, base=base_config(), client=client, plots=False)
    assert (third.n_done, third.n_run) == (4, 1)
    rows, old = read_table(out_dir / "results.csv"), [dict(zip(table.splitlines()[0].split(","), ln.split(",")))
                                                      for ln in table.splitlines()[1:]]
    for r, o in zip(rows, old):
        assert {k: r[k] for k in FIGURES} == {k: o[k] for k in FIGURES}  # the re-run point gives the same figures
    changed = sweep_from_dict(spec_dict(seeds=1, seed=12))
    with pytest.raises(ConfigError) as err:
        run_sweep(changed, scene(), out_dir, base=base_config(), client=client, plots=False)
    assert "sweep file changed" in str(err.value) and "--restart" in str(err.value)
    restarted = run_sweep(changed, scene(), out_dir, base=base_config(), client=client, plots=False, restart=True)
    assert (restarted.n_done, restarted.n_run) == (4, 4)


def test_a_failing_point_is_recorded_and_the_others_go_on(client, tmp_path):
    spec = sweep_from_dict({"sweep_version": 1, "axes": {"run.max_memory_bytes": [2**20, 2**32]}})
    base = base_config()
    base.gate.n_bins = 1024  # a frame estimated above the smallest limit allowed (1 MiB): ≈ 2.4 MiB
    assert estimate_memory(base)["total"] > 2**20
    out = run_sweep(spec, scene(), tmp_path / "sw", base=base, client=client, plots=False)
    assert (out.n_done, out.n_failed) == (1, 1)
    rows = read_table(tmp_path / "sw" / "results.csv")
    assert rows[0]["status"] == "failed" and "run.max_memory_bytes" in rows[0]["error"] and rows[0]["run"] == ""
    assert rows[1]["status"] == "done"
    record = json.loads((tmp_path / "sw" / "failed" / "p0000-s00.json").read_text())
    assert "ConfigError" in record["error"]


def test_killing_a_worker_mid_sweep_loses_no_finished_point(client, tmp_path):
    spec = sweep_from_dict(spec_dict(seeds=4))  # 16 tasks
    pids = client.run(os.getpid)
    killed = []

    def progress(fraction, text):
        if not killed and fraction > 0.1:
            victim = sorted(pids.values())[0]
            os.kill(victim, signal.SIGKILL)
            killed.append(victim)

    out = run_sweep(spec, scene(), tmp_path / "sw", base=base_config(), client=client, progress=progress,
                    plots=False)
    assert killed
    assert (out.n_tasks, out.n_done, out.n_failed) == (16, 16, 0), [
        (r["task"], r["error"]) for r in read_table(tmp_path / "sw" / "results.csv") if r["status"] != "done"]
    runs = sorted(p.name for p in (tmp_path / "sw" / "runs").iterdir())
    assert len(runs) == 16 and not [r for r in runs if r.startswith(".")]  # no partial folder left
    client.wait_for_workers(2, timeout=60)  # the nanny restarted it
    # and the figures equal a sweep that was not disturbed
    ref = run_sweep(spec, scene(), tmp_path / "ref", base=base_config(), client=client, plots=False)
    strip = [{k: r[k] for k in ("task", "seed", *FIGURES)} for r in read_table(tmp_path / "ref" / "results.csv")]
    assert [{k: r[k] for k in ("task", "seed", *FIGURES)} for r in read_table(tmp_path / "sw" / "results.csv")] == strip
    assert ref.n_done == 16


def test_the_core_is_shipped_to_workers_that_cannot_import_it(tmp_path, monkeypatch):
    """The remote-cluster path: workers started without the staged core on their path get it uploaded, and a
    sweep given the scheduler's address runs on them."""
    name, outer = stage_core()
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(outer)])
    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=40)
    try:
        with distributed.Client(cluster) as c:
            assert not any(c.run(can_import, name).values())
            assert ship_core(c) == name
            assert all(c.run(can_import, name).values())
        spec = sweep_from_dict({"sweep_version": 1, "axes": {"laser.pulse_energy_j": [1e-4, 1e-3]}})
        out = run_sweep(spec, scene(), tmp_path / "sw", base=base_config(), scheduler=cluster.scheduler_address,
                        plots=False)
        assert (out.n_workers, out.n_done, out.n_run) == (1, 2, 2)
        assert [r["status"] for r in read_table(tmp_path / "sw" / "results.csv")] == ["done", "done"]
    finally:
        cluster.close()
