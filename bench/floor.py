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
