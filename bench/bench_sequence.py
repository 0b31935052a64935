#!/usr/bin/env python3
"""Frame ranges and the modal run in Blender (through the bpy module): what reusing the geometry saves, how
long the interface is blocked, how fast a cancel stops.

    .venv/bin/python bench/bench_sequence.py [--triangles 1000000] [--frames 6] [--out DIR | --update-committed]
        [--quick]

Scene: a quad grid of ~N triangles 100 m below a 64×64-pixel flash sensor (2×2 sub-rays).  Cases, each a
sequence run (``ladar_addon.job.SimulationJob``, previews and import off):

* static grid: exported once, one BVH for every frame;
* moving grid (1 mm per frame): exported and its BVH rebuilt every frame.

A one-frame warm-up run first takes the kernels' compilation (or loading) out of the timings.  Then both as the
modal operator runs them (worker thread, ``step()`` every 20 ms from the main thread): the
set-up on the main thread (the first frame's export), the longest main-thread step (a moving scene's per-frame
export), and for the static case the time from ``cancel()`` (at ~40 %) to the job having stopped and cleaned
up.  Writes ``sequence.json`` to ``--out DIR`` (default runs/bench/; ``--update-committed``:
bench/results/sequence.json).  ``--quick``: 20 000 triangles, 4 frames (seconds).
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import blender_env  # noqa: E402
from benchio import add_output_arguments, output_path, write_json  # noqa: E402  (bench/, the script's folder)


def _fcurves(obj):
    action = obj.animation_data.action
    if hasattr(action, "fcurves"):
        return action.fcurves
    from bpy_extras import anim_utils
    return anim_utils.action_get_channelbag_for_slot(action, obj.animation_data.action_slot).fcurves


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--triangles", type=int, default=1_000_000)
    parser.add_argument("--frames", type=int, default=6)
    add_output_arguments(parser)
    args = parser.parse_args(argv)
    results = output_path(parser, args, "sequence.json")
    if args.quick:
        args.triangles, args.frames = 20_000, 4
    blender_env.isolate_user_resources()
    import bpy

    addon = blender_env.install_extension()
    # SimulationJob (ladar_addon.simulate holds the blocking wrappers only); imported when used, as the operators do:
    # enabling the add-on no longer imports the simulator
    sim = importlib.import_module(f"{addon.ladar_addon.__name__}.job")
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    side = int(math.ceil(math.sqrt(args.triangles / 2)))
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=side + 1, y_subdivisions=side + 1, size=40.0,
                                    location=(0, 0, -100))
    grid = bpy.context.object
    cam = bpy.data.objects.new("Ladar", bpy.data.cameras.new("Ladar"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.data.lens = 0.5 * cam.data.sensor_width / math.tan(0.5 * 0.1)  # 0.1 rad: 10 m at 100 m
    rx = cam.ladar.receiver
    rx.width_px = rx.height_px = 64
    rx.subsamples = 2
    cam.ladar.run.save_waveforms = False
    frames = list(range(1, args.frames + 1))
    tmp = Path(tempfile.mkdtemp(prefix="bench_sequence_"))
    out = {"blender": bpy.app.version_string, "quick": args.quick, "frames": len(frames),
           "receiver": "64×64 px × 2×2 sub-rays"}
    try:
        def run(label, **kwargs):
            t0 = time.perf_counter()
            job = sim.SimulationJob(scene, frames=frames, out_dir=tmp / label, import_results=False,
                                    previews=False, **kwargs).run()
            wall = time.perf_counter() - t0
            meta = json.loads((job.run_path / "metadata.json").read_text())
            return job, wall, meta

        # warm-up: one frame, so that compiling (or loading) the kernels is in none of the timings below
        t0 = time.perf_counter()
        sim.SimulationJob(scene, frames=frames[:1], out_dir=tmp / "warm_up", import_results=False,
                          previews=False).run()
        out["warm_up_s"] = time.perf_counter() - t0
        job, wall, meta = run("static")
        n_tri = job.source.geometry.n_triangles
        out["triangles"] = n_tri
        out["static"] = {"wall_s": wall, "per_frame_s": wall / len(frames), "exports": job.source.exports,
                         "bvh_builds": meta["bvh_builds"], "main_thread_s": job.source.main_thread_s}
        print(f"Blender {bpy.app.version_string}: {n_tri:,} triangles, {len(frames)} frames")
        print(f"static grid : {wall:6.2f} s ({wall / len(frames):.3f} s/frame), {job.source.exports} export(s), "
              f"{meta['bvh_builds']} BVH build(s)")

        grid.keyframe_insert("location", frame=frames[0])
        grid.location.z -= 1e-3 * (frames[-1] - frames[0])
        grid.keyframe_insert("location", frame=frames[-1])
        for fc in _fcurves(grid):
            for key in fc.keyframe_points:
                key.interpolation = "LINEAR"
        job, wall, meta = run("moving")
        out["moving"] = {"wall_s": wall, "per_frame_s": wall / len(frames), "exports": job.source.exports,
                         "bvh_builds": meta["bvh_builds"], "main_thread_s": job.source.main_thread_s}
        print(f"moving grid : {wall:6.2f} s ({wall / len(frames):.3f} s/frame), {job.source.exports} export(s), "
              f"{meta['bvh_builds']} BVH build(s)")
        out["moving_over_static"] = out["moving"]["wall_s"] / out["static"]["wall_s"]
        print(f"re-export + rebuild every frame costs {out['moving_over_static']:.2f}× the reused run")
        # the modal operator's view of the moving case: each frame's export blocks the interface for one step
        t0 = time.perf_counter()
        job = sim.SimulationJob(scene, frames=frames, out_dir=tmp / "modal_moving", import_results=False,
                                previews=False)
        construct_s = time.perf_counter() - t0
        job.start(threaded=True)
        while not job.step():
            time.sleep(0.02)
        out["modal_moving"] = {"state": job.state, "constructor_s": construct_s,
                               "max_main_thread_step_s": job.max_step_s,
                               "main_thread_total_s": job.source.main_thread_s}
        print(f"modal moving: constructor (first export) {construct_s * 1e3:.0f} ms, longest main-thread step "
              f"{job.max_step_s * 1e3:.0f} ms (one frame's export)")
        grid.animation_data_clear()

        t0 = time.perf_counter()
        job = sim.SimulationJob(scene, frames=frames, out_dir=tmp / "modal", import_results=False, previews=False)
        construct_s = time.perf_counter() - t0
        job.start(threaded=True)
        t_cancel = None
        while not job.step():
            if t_cancel is None and job.fraction >= 0.4:
                job.cancel()
                t_cancel = time.perf_counter()
            time.sleep(0.02)
        stop_s = time.perf_counter() - t_cancel if t_cancel is not None else None
        out["modal"] = {"state": job.state, "cancel_to_stopped_s": stop_s, "constructor_s": construct_s,
                        "max_main_thread_step_s": job.max_step_s,
                        "main_thread_total_s": job.source.main_thread_s,
                        "left_behind": sorted(p.name for p in tmp.iterdir()
                                              if p.name == "modal" or p.name.startswith(".modal."))}
        print(f"modal run   : cancelled at 40 % → stopped in {stop_s:.3f} s; longest main-thread step "
              f"{job.max_step_s * 1e3:.1f} ms; nothing left: {out['modal']['left_behind'] == []}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {write_json(results, out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
