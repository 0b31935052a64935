#!/usr/bin/env python3
"""Sweep throughput on Dask: points/s with 1, 2 and 4 worker processes against the same points run serially in
one process, and the scheduler's overhead per point.

    .venv/bin/python bench/bench_sweep.py [--points 16] [--workers 1,2,4] [--out DIR | --update-committed] [--quick]

Scene: the bundled flash demo (bench/sample_scenes.py: 80 triangles; its sensor cut to 32×32 pixels).  The sweep: a
``sensor.range_m`` × ``atmosphere.visibility_m`` grid with seeds, noisy receiver, save_waveforms off — the
worked example of docs/sweeps.md, cut to ``--points`` tasks.

* serial: every task through ``core.sweep.task.run_task`` in this process, one after the other (the same work a
  worker does: the scene read once, one BVH, simulate, summarise, write the run folder);
* Dask: ``run_sweep`` on the local cluster a sweep starts by default (``runner.open_client``: N single-threaded
  worker processes), started beforehand (its start-up is reported apart), into a fresh folder each time;
* overhead per point: (1-worker sweep − serial) / points, and the round trip of a no-op task through the same
  scheduler (submit → result, one at a time and 200 at once);
* CPU seconds per point (serial: this process; Dask: the workers, and apart this process — client and
  scheduler): unlike wall times, nearly independent of what else the machine runs.

The serial pass runs before and after the Dask runs (the machine's load drifts; both are reported, the ratios use
their mean).

Writes ``sweep.json`` to ``--out DIR`` (default runs/bench/; ``--update-committed``: bench/results/sweep.json).  On
a machine with fewer cores than workers the extra processes share cores: compare the ratios with ``cpu_count``.
``--quick``: 4 tasks, one 1-worker cluster, 10 and 20 no-op round trips (seconds; a smoke run).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))



def sweep_spec(n_points: int):
    from core.sweep.spec import sweep_from_dict

    seeds = 2
    ranges = max(1, n_points // (2 * seeds))
    return sweep_from_dict({"sweep_version": 1, "seed": 2026, "seeds": seeds,
                            "settings": {"detector": {"mode": "noisy"}, "run": {"save_waveforms": False},
                                         "receiver": {"width_px": 32, "height_px": 32}},
                            "axes": {"sensor.range_m": {"start": 150, "stop": 300, "num": ranges},
                                     "atmosphere.visibility_m": [2000, 10000]}})


def cpu_seconds() -> float:
    """This process's CPU time (all its threads), s: run on each worker."""
    return time.process_time()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=16, help="tasks (points × seeds) per run")
    ap.add_argument("--workers", default="1,2,4")
    from benchio import add_output_arguments, output_path, write_json

    add_output_arguments(ap)
    args = ap.parse_args(argv)
    results = output_path(ap, args, "sweep.json")
    if args.quick:
        args.points, args.workers = 4, "1"
    n_trips, n_batch = (10, 20) if args.quick else (50, 200)
    from core.sweep.runner import open_client, plan_sweep, run_sweep
    from core.sweep.scene import SweepScene
    from core.sweep.shipping import stage_core
    from core.sweep.task import run_task
    from sample_scenes import flash_demo

    geometry, pose, cfg = flash_demo()
    scene = SweepScene.single(geometry, pose, frame=1)
    spec = sweep_spec(args.points)
    work = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    stage_core()
    out = {"scene": "sample_blends/flash_demo.blend", "load_average_start": os.getloadavg(),
           "receiver": f"32×32 px × {cfg.receiver.subsamples}×{cfg.receiver.subsamples} sub-rays, "
                       f"{cfg.gate.n_bins} bins, noisy",
           "cpu_count": os.cpu_count(), "quick": args.quick, "sweep": spec.normalized()}
    try:
        def serial(tag):  # every task in this process, one after the other (the scene read once, one BVH)
            plan = plan_sweep(spec, scene, cfg, work / tag)
            plan.scene.save(work / tag / "scene")
            t0, c0 = time.perf_counter(), time.process_time()
            rows = [run_task(str(work / tag / "scene"), plan.manifest["scene_digest"], t) for t in plan.tasks]
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            assert all(r["status"] == "done" for r in rows), [r["error"] for r in rows if r["status"] != "done"]
            n = len(plan.tasks)
            print(f"serial    {n} tasks in {wall:.2f} s: {n / wall:.2f} points/s", flush=True)
            return n, {"wall_s": wall, "points_per_s": n / wall, "cpu_s_per_point": cpu / n,
                       "task_s_mean": sum(r["run_time_s"] for r in rows) / n}

        n, first = serial("serial")
        out["tasks"] = n
        out["serial"] = first
        serial_s = first["wall_s"]
        out["dask"] = {}
        for w in [int(x) for x in args.workers.split(",")]:
            t0 = time.perf_counter()
            client, cluster = open_client(n_workers=w)  # the local cluster a sweep starts by default
            startup = time.perf_counter() - t0
            try:
                w0 = client.run(cpu_seconds)
                t0, c0 = time.perf_counter(), time.process_time()
                res = run_sweep(spec, scene, work / f"dask{w}", base=cfg, client=client, plots=False)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                w1 = client.run(cpu_seconds)
                assert res.n_done == n and w0.keys() == w1.keys(), res.summary()
                entry = {"cluster_startup_s": startup, "wall_s": wall, "points_per_s": n / wall,
                         "task_s_mean": sum(r["run_time_s"] for r in res.rows) / n,
                         "worker_cpu_s_per_point": sum(w1[k] - w0[k] for k in w0) / n,
                         "client_and_scheduler_cpu_s_per_point": cpu / n}
                if w == 1:
                    t0 = time.perf_counter()
                    for i in range(n_trips):
                        client.submit(abs, -i, pure=False).result()
                    entry["noop_round_trip_s"] = (time.perf_counter() - t0) / n_trips
                    t0 = time.perf_counter()
                    client.gather(client.map(abs, range(-n_batch, 0), pure=False))
                    entry["noop_batch_per_task_s"] = (time.perf_counter() - t0) / n_batch
                out["dask"][str(w)] = entry
                print(f"dask {w}w   {n} tasks in {wall:.2f} s: {n / wall:.2f} points/s (cluster start-up "
                      f"{startup:.1f} s)", flush=True)
            finally:
                client.close()
                cluster.close()
        _, last = serial("serial-after")
        out["serial_after"] = last
        serial_s = 0.5 * (first["wall_s"] + last["wall_s"])
        out["serial_mean_wall_s"] = serial_s
        for w, entry in out["dask"].items():
            entry["speedup_vs_serial"] = serial_s / entry["wall_s"]
            if w == "1":
                entry["overhead_per_point_s"] = (entry["wall_s"] - serial_s) / n
            print(f"dask {w}w   {entry['points_per_s']:.2f} points/s = {entry['speedup_vs_serial']:.2f}× serial "
                  f"(mean of the two serial passes, {n / serial_s:.2f} points/s); CPU s per point: workers "
                  f"{entry['worker_cpu_s_per_point']:.2f}, client + scheduler "
                  f"{entry['client_and_scheduler_cpu_s_per_point']:.3f} (serial {first['cpu_s_per_point']:.2f}, "
                  f"{last['cpu_s_per_point']:.2f})", flush=True)
        one = out["dask"].get("1")
        if one:
            print(f"overhead  {one['overhead_per_point_s'] * 1e3:.0f} ms per point (1 worker vs serial); no-op task "
                  f"round trip {one['noop_round_trip_s'] * 1e3:.1f} ms, {one['noop_batch_per_task_s'] * 1e3:.2f} ms "
                  f"per task in a batch of {n_batch}", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out["load_average_end"] = os.getloadavg()
    print(f"wrote {write_json(results, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
