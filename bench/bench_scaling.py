"""Scaling of the flash pipeline (issue 7): pipeline vs the bare embreex cast of the same rays, 1 vs 2 threads,
time and peak memory as the scene grows (10k → 2M triangles) and as the sensor grows (64² → 1024² pixels),
and what the planner's skips save (field-of-view culling, BVH reuse, points only, effects off) on the
benchmark terrain and on sample_blends/flash_demo.blend.

Every case runs in its own Python process, so its peak resident memory (``ru_maxrss``) is its own; the
baseline (the interpreter with NumPy, SciPy, embreex and core imported) is reported beside it.  Times are the best of ``--repeat`` runs
inside that process (BVH built once unless the case is about building it).  Writes ``scaling.json`` and
``scaling.md`` (the tables) to ``--out DIR`` (default runs/bench/); ``--update-committed`` writes
bench/results/scaling.json and the tables between the ``scaling`` markers of docs/performance.md instead.
``--quick``: one case of each kind, small (10k / 20k triangles, 64² px), one run each (well under a minute).

    .venv/bin/python bench/bench_scaling.py [--quick] [--repeat 3] [--out DIR | --update-committed]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

DOC = ROOT / "docs" / "performance.md"


# ----------------------------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------------------------
def terrain(n_triangles: int):
    """The flash benchmark's bumpy ground and box (bench_flash.bench_scene) with about ``n_triangles``
    triangles."""
    from bench_flash import bench_scene
    return bench_scene(max(2, int(round(np.sqrt(n_triangles / 2)))))


def surrounding_terrain(n_triangles: int):
    """A 2 km × 2 km bumpy ground centred on the sensor (most of it behind or beside the field of view), with
    the benchmark's box 300 m ahead."""
    from core.config.settings import BRDFSettings
    from core.geometry.scene import SceneGeometry

    n = max(2, int(round(np.sqrt(n_triangles / 2))))
    gx, gy = np.meshgrid(np.linspace(-1000, 1000, n + 1), np.linspace(-1000, 1000, n + 1))
    gz = 0.8 * np.sin(gx / 7.0) * np.cos(gy / 5.0)
    verts = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    i = np.arange(n)
    a = (i[:, None] * (n + 1) + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n + 2], 1), np.stack([a, a + n + 2, a + n + 1], 1)])
    return SceneGeometry(verts, tris, np.zeros(len(tris)), [BRDFSettings(reflectance=0.25)], ["ground"])


def config(pixels=128, subsamples=4, n_bins=1024, threads=1, save_waveforms=True):
    from bench_flash import bench_config
    cfg = bench_config()
    cfg.receiver.width_px = cfg.receiver.height_px = pixels
    cfg.receiver.subsamples = subsamples
    cfg.gate.n_bins = n_bins
    cfg.run.threads = threads
    cfg.run.save_waveforms = save_waveforms
    cfg.run.max_memory_bytes = 2 ** 40  # measure, do not refuse
    return cfg


def best_of(fn, repeat):
    """Best time of ``repeat`` calls; the previous result is dropped before each call (peak memory is one
    run's)."""
    best, out = np.inf, None
    for _ in range(repeat):
        out = None
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


# ----------------------------------------------------------------------------------------------------------------
# Cases (each runs in a child process)
# ----------------------------------------------------------------------------------------------------------------
def case_pipeline_vs_bare(repeat, threads):
    """128² px × 4×4 sub-rays, 1024 bins on the benchmark terrain: the floor (bench/floor.py: the bare cast of the
    frame's rays in the pipeline's blocks on its threads), full pipeline, points only (interleaved, best of)."""
    import floor
    from bench_flash import flash_floor_blocks, sensor_pose
    from core.systems.flash import simulate_frame
    from core.geometry.rays import Detector
    from core.geometry.trace import SceneTracer

    scene, pose, cfg = terrain(32768), sensor_pose(), config(threads=threads)
    cfg_pts = config(threads=threads, save_waveforms=False)
    tracer = SceneTracer(scene)
    det = Detector.from_settings(cfg.receiver)
    res = simulate_frame(scene, pose, cfg, tracer=tracer)  # the first call (kernels loaded) outside the timing
    blocks = flash_floor_blocks(tracer, det, pose, res.stats["pixels_per_block"])
    repeat = max(repeat, 7) if repeat > 1 else 1  # sub-second cases: more repeats (--quick: one run)
    casts, pipe, pts = [], [], []
    for _ in range(repeat):  # interleaved: the machine's load changes between repeats, not within one
        casts.append(floor.bare_cast(tracer, blocks, res.stats["threads"]))
        t0 = time.perf_counter()
        res = simulate_frame(scene, pose, cfg, tracer=tracer)
        pipe.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        res_pts = simulate_frame(scene, pose, cfg_pts, tracer=tracer)
        pts.append(time.perf_counter() - t0)
    fl = floor.best(casts)
    bare_s, pipe_s, pts_s = fl["wall_s"], min(pipe), min(pts)
    return {"threads": threads, "n_rays": fl["n_rays"], "n_triangles": scene.n_triangles,
            "floor": fl, "bare_cast_s": bare_s, "pipeline_s": pipe_s, "points_only_s": pts_s,
            "ratio_pipeline_to_bare": pipe_s / bare_s, "ratio_points_only_to_bare": pts_s / bare_s,
            "stage_times_s": res.stats["stage_times_s"], "stage_times_points_only_s": res_pts.stats["stage_times_s"],
            "stage_ratio_to_floor": floor.stage_ratios(res.stats["stage_times_s"], fl),
            "stage_ratio_to_floor_points_only": floor.stage_ratios(res_pts.stats["stage_times_s"], fl)}


def case_scene(repeat, n_triangles):
    """Scene growth: BVH build (whole scene and culled) and a 128² × 2×2 frame with the BVH reused."""
    from bench_flash import sensor_pose
    from core.geometry.culling import frustum_triangles
    from core.systems.flash import simulate_frame
    from core.geometry.rays import Detector
    from core.geometry.trace import SceneTracer

    scene, pose, cfg = terrain(n_triangles), sensor_pose(), config(subsamples=2)
    build_s, tracer = best_of(lambda: SceneTracer(scene), repeat)
    det = Detector.from_settings(cfg.receiver)
    keep = frustum_triangles(scene.vertices_m, scene.triangles, pose[:3, 3], pose[:3, :3], det.half_width_tan,
                             det.half_height_tan)
    culled_s, _ = best_of(lambda: SceneTracer(scene, keep=frustum_triangles(
        scene.vertices_m, scene.triangles, pose[:3, 3], pose[:3, :3], det.half_width_tan, det.half_height_tan)),
        repeat)
    frame_s, _ = best_of(lambda: simulate_frame(scene, pose, cfg, tracer=tracer), repeat)
    return {"n_triangles": scene.n_triangles, "bvh_build_s": build_s, "bvh_build_culled_s": culled_s,
            "triangles_in_view": int(keep.sum()), "frame_s": frame_s}


def case_sensor(repeat, pixels, save_waveforms):
    """Sensor growth: pixels² × 1 sub-ray on the benchmark terrain, 1024 bins."""
    from bench_flash import sensor_pose
    from core.systems.flash import simulate_frame
    from core.geometry.trace import SceneTracer

    scene, pose = terrain(32768), sensor_pose()
    cfg = config(pixels=pixels, subsamples=1, threads=1, save_waveforms=save_waveforms)
    tracer = SceneTracer(scene)
    frame_s, res = best_of(lambda: simulate_frame(scene, pose, cfg, tracer=tracer), repeat)
    return {"pixels": pixels, "save_waveforms": save_waveforms, "frame_s": frame_s,
            "n_points": res.stats["n_points"], "memory_estimate_bytes": res.stats.get("memory_estimate_bytes"),
            "stage_times_s": res.stats["stage_times_s"]}


def case_culling(repeat, n_triangles):
    """A single frame (BVH built for it) of a sensor inside a 2 km terrain: whole scene vs culled."""
    from bench_flash import sensor_pose
    from core.systems.flash import simulate_frame

    scene, pose, cfg = surrounding_terrain(n_triangles), sensor_pose(), config(subsamples=2)
    full_s, full = best_of(lambda: simulate_frame(scene, pose, cfg, fov_culling=False), repeat)
    culled_s, culled = best_of(lambda: simulate_frame(scene, pose, cfg), repeat)
    same = bool(np.array_equal(full.energy_image, culled.energy_image)
                and np.array_equal(full.waveforms, culled.waveforms))
    return {"n_triangles": scene.n_triangles, "triangles_in_view": culled.stats["bvh"]["triangles_traced"],
            "frame_full_s": full_s, "frame_culled_s": culled_s, "saved_s": full_s - culled_s,
            "build_full_s": full.stats["stage_times_s"]["build_bvh"],
            "build_culled_s": culled.stats["stage_times_s"]["build_bvh"], "identical_products": same}


def case_sample(repeat):
    """The planner's skips on sample_blends/flash_demo.blend (64² px × 4×4, 1668 bins)."""
    import dataclasses

    from core.systems.flash import simulate_frame
    from core.geometry.trace import SceneTracer
    from sample_scenes import flash_demo

    scene, pose, cfg = flash_demo()
    cfg.run.threads = 1
    tracer = SceneTracer(scene)
    repeat = max(repeat, 9) if repeat > 1 else 1  # 0.1 s frames: more repeats (--quick: one run)
    out = {"n_triangles": scene.n_triangles}
    base_s, _ = best_of(lambda: simulate_frame(scene, pose, cfg, tracer=tracer), repeat)
    rebuild_s, _ = best_of(lambda: simulate_frame(scene, pose, cfg), repeat)
    pts = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, save_waveforms=False))
    pts_s, _ = best_of(lambda: simulate_frame(scene, pose, pts, tracer=tracer), repeat)
    turb = dataclasses.replace(cfg, atmosphere=dataclasses.replace(cfg.atmosphere, cn2_m_23=1e-14))
    turb_s, _ = best_of(lambda: simulate_frame(scene, pose, turb, tracer=tracer), repeat)
    noisy = dataclasses.replace(cfg, detector=dataclasses.replace(cfg.detector, mode="noisy"))
    noisy_s, _ = best_of(lambda: simulate_frame(scene, pose, noisy, tracer=tracer), repeat)
    point = dataclasses.replace(cfg, receiver=dataclasses.replace(cfg.receiver, cell_range_spread=False))
    point_s, _ = best_of(lambda: simulate_frame(scene, pose, point, tracer=tracer), repeat)
    out.update({"frame_s": base_s, "frame_with_bvh_build_s": rebuild_s, "points_only_s": pts_s,
                "with_turbulence_s": turb_s, "noisy_receiver_s": noisy_s, "point_sub_rays_s": point_s})
    return out


CASES = {"pipeline_vs_bare": case_pipeline_vs_bare, "scene": case_scene, "sensor": case_sensor,
         "culling": case_culling, "sample": case_sample}


def preload():
    """Import what every case uses, so the baseline resident set is measured after it."""
    import embreex.rtcore_scene  # noqa: F401
    import scipy.special  # noqa: F401
    import scipy.stats  # noqa: F401

    import core.systems.flash  # noqa: F401


def run_child(name, repeat, *args):
    """Run one case in a fresh process: its result with peak memory."""
    code = ("import json, resource, sys; sys.path.insert(0, {b!r}); import bench_scaling as b; b.preload(); "
            "base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024; r = b.CASES[{n!r}]({rep}, *{a!r}); "
            "r['baseline_rss_bytes'] = base; "
            "r['peak_rss_bytes'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024; "
            "print('RESULT ' + json.dumps(r))").format(b=str(ROOT / "bench"), n=name, rep=repeat, a=list(args))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT))
    if proc.returncode != 0:
        raise RuntimeError(f"case {name}{args} failed:\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    result = json.loads(line[len("RESULT "):])
    print(f"{name} {args}: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                           for k, v in result.items() if not isinstance(v, dict)), flush=True)
    return result


def mib(x):
    return f"{x / 2 ** 20:.0f}"


def markdown(rep):
    out = [f"Generated by `bench/bench_scaling.py`{' --quick' if rep['quick'] else ''} ({rep['created']}, "
           f"{rep['cpu_count']} cores shared, best of {rep['repeat']}; memory: peak resident set of the case's "
           "own process, and above the baseline of the interpreter with the libraries imported).", "",
           "**Pipeline vs the floor: the bare embreex cast of the same rays in the pipeline's blocks on the same "
           "threads** (128² px × 4×4 = 262 144 rays, 32 778-triangle terrain, 1024 bins):", "",
           "| threads | floor (s) | pipeline (s) | ratio | points only (s) | ratio | trace | waveform | echoes |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rep["pipeline_vs_bare"]:
        st = r["stage_times_s"]
        out.append(f"| {r['threads']} | {r['bare_cast_s']:.4f} | {r['pipeline_s']:.3f} | "
                   f"{r['ratio_pipeline_to_bare']:.1f} | {r['points_only_s']:.3f} | {r['ratio_points_only_to_bare']:.1f} "
                   f"| {st['trace']:.3f} | {st['waveform']:.3f} | {st['echoes']:.3f} |")
    if len(rep["pipeline_vs_bare"]) == 2:
        a, b = rep["pipeline_vs_bare"]
        out += ["", f"Two threads: bare cast {a['bare_cast_s'] / b['bare_cast_s']:.2f}× faster, pipeline "
                    f"{a['pipeline_s'] / b['pipeline_s']:.2f}× (stage times are summed over threads)."]
    out += ["", "**Scene growth** (benchmark terrain, 128² px × 2×2, one thread):", "",
            "| triangles | BVH build (s) | culled build (s) | in view | frame, BVH reused (s) | peak RSS (MiB) | "
            "above baseline (MiB) |", "|---|---|---|---|---|---|---|"]
    for r in rep["scene"]:
        out.append(f"| {r['n_triangles']:,} | {r['bvh_build_s']:.3f} | {r['bvh_build_culled_s']:.3f} | "
                   f"{r['triangles_in_view']:,} | {r['frame_s']:.3f} | {mib(r['peak_rss_bytes'])} | "
                   f"{mib(r['peak_rss_bytes'] - r['baseline_rss_bytes'])} |")
    out += ["", "**Sensor growth** (1 sub-ray per pixel, 1024 bins, one thread):", "",
            "| pixels | waveform cube | frame (s) | µs per pixel | points | peak RSS (MiB) | above baseline (MiB) | "
            "planner's estimate (MiB) |", "|---|---|---|---|---|---|---|---|"]
    for r in rep["sensor"]:
        n = r["pixels"] ** 2
        out.append(f"| {r['pixels']}² | {'saved' if r['save_waveforms'] else 'none (points)'} | {r['frame_s']:.3f} | "
                   f"{1e6 * r['frame_s'] / n:.2f} | {r['n_points']:,} | {mib(r['peak_rss_bytes'])} | "
                   f"{mib(r['peak_rss_bytes'] - r['baseline_rss_bytes'])} | {mib(r['memory_estimate_bytes'])} |")
    c = rep["culling"]
    out += ["", f"**Field-of-view culling** (one frame, BVH built for it, sensor inside a 2 km × 2 km terrain of "
                f"{c['n_triangles']:,} triangles, {c['triangles_in_view']:,} in view): "
                f"{c['frame_full_s']:.2f} s whole scene → {c['frame_culled_s']:.2f} s culled "
                f"(BVH {c['build_full_s']:.2f} s → {c['build_culled_s']:.3f} s); products identical: "
                f"{c['identical_products']}."]
    s = rep["sample"]
    out += ["", f"**flash_demo.blend** ({s['n_triangles']} triangles, 64² px × 4×4, 1668 bins, one thread): "
                "time of one frame with each stage the planner can skip put back:", "",
            "| run | time (s) | vs planned |", "|---|---|---|",
            f"| as planned (BVH reused, ideal receiver, no turbulence, waveforms saved) | {s['frame_s']:.3f} | 1.00 |",
            f"| BVH rebuilt for the frame | {s['frame_with_bvh_build_s']:.3f} | "
            f"{s['frame_with_bvh_build_s'] / s['frame_s']:.2f} |",
            f"| points only (no cube) | {s['points_only_s']:.3f} | {s['points_only_s'] / s['frame_s']:.2f} |",
            f"| turbulence on (Cn² = 1e-14) | {s['with_turbulence_s']:.3f} | "
            f"{s['with_turbulence_s'] / s['frame_s']:.2f} |",
            f"| noisy receiver chain | {s['noisy_receiver_s']:.3f} | {s['noisy_receiver_s'] / s['frame_s']:.2f} |",
            f"| point sub-rays (cell range spread off) | {s['point_sub_rays_s']:.3f} | "
            f"{s['point_sub_rays_s'] / s['frame_s']:.2f} |"]
    return "\n".join(out)


def write_doc_block(text, marker="scaling"):
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    doc = DOC.read_text(encoding="utf-8")
    if begin not in doc:
        raise SystemExit(f"{DOC} has no {begin} … {end} block")
    head, rest = doc.split(begin, 1)
    _, tail = rest.split(end, 1)
    DOC.write_text(f"{head}{begin}\n{text}\n{end}{tail}", encoding="utf-8")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    from benchio import add_output_arguments, output_folder, write_json

    add_output_arguments(ap)
    args = ap.parse_args(argv)
    folder = output_folder(ap, args)
    from core.fileio.run_folder import software_versions

    if args.quick:
        args.repeat = 1
    threads = (1,) if args.quick else (1, 2)
    scenes = (10_000,) if args.quick else (10_000, 100_000, 500_000, 2_000_000)
    sensors = ((64, True),) if args.quick else \
        ((64, True), (128, True), (256, True), (512, True), (64, False), (128, False), (256, False), (512, False),
         (1024, False))
    rep = {"benchmark": "flash scaling (issue 7)", "quick": args.quick, "repeat": args.repeat,
           "created": time.strftime("%Y-%m-%d"), "cpu_count": os.cpu_count(), "software": software_versions()}
    rep["pipeline_vs_bare"] = [run_child("pipeline_vs_bare", args.repeat, t) for t in threads]
    rep["scene"] = [run_child("scene", args.repeat, n) for n in scenes]
    rep["sensor"] = [run_child("sensor", args.repeat, p, w) for p, w in sensors]
    rep["culling"] = run_child("culling", args.repeat, 20_000 if args.quick else 2_000_000)
    rep["sample"] = run_child("sample", args.repeat)
    text = markdown(rep)
    write_json(folder / "scaling.json", rep, indent=1)
    if args.update_committed:
        write_doc_block(text)
    else:
        (folder / "scaling.md").write_text(text + "\n", encoding="utf-8")
    print(text)
    print(f"wrote {folder / 'scaling.json'}")


if __name__ == "__main__":
    main()
