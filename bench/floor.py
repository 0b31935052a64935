"""The floor of every benchmark (issue 28): the bare embreex cast of the pipeline's own rays on the pipeline's own
number of threads.

* the same rays: the pipeline's blocks of rays, generated (and converted to float32, relative to the BVH's
  reference point) before the clock starts;
* the same threads: the blocks cast on the process's shared pool (core/threads.py ``imap``, as the pipeline's
  ``run_blocks`` runs its blocks), one ``EmbreeScene.run`` call a block;
* the BVH built before both clocks (``SceneTracer`` builds it when it is made); nothing compiles in the floor, and
  the pipeline's first call (compiling or loading its kernels) is timed apart by each benchmark.

Stage times are thread-seconds (summed over the blocks' threads), so a stage's ratio to the floor is taken to the
floor's thread-seconds (the sum of its blocks' cast times); a frame's wall time to the floor's wall time.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.threads import imap  # noqa: E402

DEFINITION = ("floor = the bare embreex cast (EmbreeScene.run, INTERSECT) of the pipeline's own rays, in the "
              "pipeline's blocks, on the pipeline's number of threads (the shared pool), BVH built before both "
              "clocks, rays generated outside the clock, compile excluded from both (the first call is reported "
              "apart). Frame ratios: wall time / the floor's wall time; stage ratios: stage thread-seconds / the "
              "floor's thread-seconds (the sum of its blocks' cast times)")


def float32_blocks(tracer, origins, directions, bounds) -> list:
    """The rays of each (start, stop) in ``bounds`` as Embree casts them: (origins, directions) float32, the
    origins relative to the BVH's reference point.  ``origins``: one (3,) or one per ray (n, 3)."""
    directions = np.asarray(directions)
    origins = np.asarray(origins, dtype=np.float64)
    out = []
    for a, b in bounds:
        d = np.ascontiguousarray(directions[a:b], dtype=np.float32)
        o = origins if origins.ndim == 1 else origins[a:b]
        o = np.ascontiguousarray(np.broadcast_to((o - tracer.reference_m).astype(np.float32), d.shape))
        out.append((o, d))
    return out


def bare_cast(tracer, blocks, threads: int) -> dict:
    """One cast of ``blocks`` (:func:`float32_blocks`) on ``threads`` threads: ``wall_s``, ``thread_s`` (the sum of
    the blocks' cast times), ``n_rays`` and ``n_hits``."""
    def cast(block):
        t0 = time.perf_counter()
        prim = tracer._embree.run(block[0], block[1], query="INTERSECT")
        dt = time.perf_counter() - t0
        return dt, int((np.asarray(prim) >= 0).sum())

    t0 = time.perf_counter()
    parts = list(imap(cast, blocks, threads))
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "thread_s": float(sum(p[0] for p in parts)),
            "n_rays": int(sum(len(b[1]) for b in blocks)), "n_hits": int(sum(p[1] for p in parts)),
            "threads": int(threads), "n_blocks": len(blocks)}


def best(runs: list) -> dict:
    """The run with the smallest wall time of several :func:`bare_cast` runs (with the median wall time)."""
    out = dict(min(runs, key=lambda r: r["wall_s"]))
    out["median_wall_s"] = float(np.median([r["wall_s"] for r in runs]))
    out["runs"] = len(runs)
    return out


def stage_ratios(stage_times_s: dict, floor: dict) -> dict:
    """Each stage's thread-seconds over the floor's thread-seconds."""
    return {k: v / floor["thread_s"] for k, v in stage_times_s.items() if isinstance(v, (int, float))}


def thread_scaling(frame_wall_s: dict, floor_wall_s: dict, frame_cpu_s: dict | None = None,
                   floor_cpu_s: dict | None = None) -> dict:
    """A frame's thread scaling 1 → 2 against its floor's (issue 28's target: the frame's ≥ 0.9 × the cast's).

    ``frame_wall_s`` / ``floor_wall_s``: {1: s, 2: s}, each the best of its repeats, the floor cast in the
    frame's own blocks on the same thread count.  ``relative_to_floor``: (frame 1 → 2 speed-up) / (floor 1 → 2
    speed-up), wall times (on a loaded machine both speed-ups fall towards 1: read it with the load average).
    ``frame_cpu_s`` / ``floor_cpu_s`` (optional, process CPU, all threads): the CPU each side spends more on 2
    threads than on 1 (``cpu_growth_1_to_2``: cpu(2) / cpu(1)), the part of the scaling the load does not set."""
    out = {"frame_1_to_2": frame_wall_s[1] / frame_wall_s[2], "floor_1_to_2": floor_wall_s[1] / floor_wall_s[2]}
    out["relative_to_floor"] = out["frame_1_to_2"] / out["floor_1_to_2"]
    out["target_relative_to_floor"] = 0.9
    if frame_cpu_s and floor_cpu_s:
        out["cpu_s"] = {"frame": {str(k): v for k, v in frame_cpu_s.items()},
                        "floor": {str(k): v for k, v in floor_cpu_s.items()}}
        out["cpu_growth_1_to_2"] = {"frame": frame_cpu_s[2] / frame_cpu_s[1], "floor": floor_cpu_s[2] / floor_cpu_s[1]}
    return out
