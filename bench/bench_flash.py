"""Flash-ladar benchmark: 128×128 pixels × 4×4 sub-rays, 1024 time bins (issues 2, 16).

Measures in one run, on the same rays: the floor (bench/floor.py: the bare embreex cast of the frame's rays in the
pipeline's blocks on the pipeline's threads), the full pipeline (`simulate_frame`, all cores) with the cube saved,
points only, and with full physics (Cn² 1e-14 with every turbulence effect, visibility 10 km, the noisy APD receiver with A/D, cube
saved), their ratios to the floor, and the time of every stage and its ratio to the floor's thread-seconds; and on sample_blends/flash_demo.blend the
noisy receiver against the ideal one (``--no-flash-demo`` to skip: its export needs the ``bpy`` module once); and
the detector models (full physics, points only: adaptive / calibrated threshold, per-bin / statistical signal-free
bins, docs/receiver.md) with each one's ratio to the floor; ``--terrain``: issue 28's second flash case on the HELIOS++
terrain (1,996,002 triangles and a 4 m box, 128² px × 4×4 sub-rays, 1024 bins of 0.5 ns, FOV 0.6 rad).
The thread scaling 1 → 2 (issue 28: each frame's ≥ 0.9 × the cast's): the project's three frames and every terrain
frame also run on one thread, against the floor cast on one thread in the one-thread frame's blocks
(``thread_scaling_1_to_2``: wall speed-ups, their ratio, and each side's process CPU on 1 and 2 threads).
The first call of each case (compiling or loading the compiled kernels) is timed separately from the best of
``--repeat`` runs, the floor and the frames interleaved (one of each per repeat; the medians are reported too);
each frame's and the floor's process CPU time (all threads) too, and the load average at the start and the end.  Absolute times on a shared 2-core machine are noisy; the ratios are the figures to track.
Writes ``flash.json`` to ``--out DIR`` (default runs/bench/); ``--update-committed`` regenerates
bench/results/flash.json; ``--quick``: 32×32 px × 2×2 sub-rays, 256 bins, one run each (seconds).

    .venv/bin/python bench/bench_flash.py [--repeat 3] [--no-flash-demo] [--terrain [--terrain-bins 8192]] [--out DIR | --update-committed] [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.config.settings import BRDFSettings, SimulationConfig  # noqa: E402
from core.systems.flash import simulate_frame  # noqa: E402
from core.geometry.rays import Detector, block_subray_tan, tan_to_unit_direction  # noqa: E402
from core.fileio.run_folder import software_versions  # noqa: E402
from core.geometry.scene import SceneGeometry  # noqa: E402
from core.geometry.trace import SceneTracer  # noqa: E402
from machine import machine_info  # noqa: E402  (bench/machine.py)
from benchio import add_output_arguments, output_path, write_json  # noqa: E402
import floor  # noqa: E402  (bench/floor.py)


def bench_scene(n_grid: int = 128) -> SceneGeometry:
    """A bumpy ground grid (2·n_grid² triangles, 300 m × 600 m) and a glossy box standing on it 300 m ahead."""
    gx, gy = np.meshgrid(np.linspace(-150, 150, n_grid + 1), np.linspace(100, 700, n_grid + 1))
    gz = 0.8 * np.sin(gx / 7.0) * np.cos(gy / 5.0)
    verts = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    i = np.arange(n_grid)
    a = (i[:, None] * (n_grid + 1) + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n_grid + 2], 1), np.stack([a, a + n_grid + 2, a + n_grid + 1], 1)])
    box = np.array([[-4, 296, 0], [4, 296, 0], [4, 304, 0], [-4, 304, 0],
                    [-4, 296, 5], [4, 296, 5], [4, 304, 5], [-4, 304, 5]], float)
    box_tris = np.array([[0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
                         [4, 5, 6], [4, 6, 7]]) + len(verts)
    return SceneGeometry(np.concatenate([verts, box]), np.concatenate([tris, box_tris]),
                         np.concatenate([np.zeros(len(tris)), np.ones(len(box_tris))]),
                         [BRDFSettings(reflectance=0.25),
                          BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08)],
                         ["ground", "paint"])


def sensor_pose() -> np.ndarray:
    """Camera 40 m up, looking at the ground 300 m ahead (+Y), tilted down."""
    target = np.array([0.0, 300.0, 2.0])
    eye = np.array([0.0, 0.0, 40.0])
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, up, -fwd], axis=1)
    pose[:3, 3] = eye
    return pose


def bench_config(quick: bool = False) -> SimulationConfig:
    """128×128 px × 4×4 sub-rays, 1024 bins of 1 ns from 200 m (``quick``: 32×32 px × 2×2, 256 bins)."""
    cfg = SimulationConfig()
    cfg.receiver.width_px = cfg.receiver.height_px = 32 if quick else 128
    cfg.receiver.subsamples = 2 if quick else 4
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = np.radians(12.0)
    cfg.gate.n_bins = 256 if quick else 1024
    cfg.gate.bin_width_s = 1e-9
    cfg.gate.gate_start_s = 2 * 200.0 / 299_792_458.0
    return cfg


def full_physics_config(quick: bool = False) -> SimulationConfig:
    """The benchmark frame with every effect on: turbulence (Cn² 1e-14: broadening, scintillation both ways,
    wander, long-exposure blur), visibility 10 km, the noisy APD receiver with A/D; cube saved."""
    cfg = bench_config(quick)
    cfg.atmosphere.cn2_m_23 = 1e-14
    cfg.atmosphere.visibility_m = 10e3
    cfg.detector.mode, cfg.detector.detector_type = "noisy", "apd"
    return cfg


#: The detector models compared in the "run time against error" table (docs/performance.md): full physics, points
#: only (no per-bin product: the statistical route may run), (threshold mode, signal-free bins).
DETECTOR_MODELS = (("adaptive", "per_bin"), ("calibrated", "per_bin"), ("calibrated", "statistical"))


def detector_model_config(threshold_mode: str, signal_free_bins: str, quick: bool = False) -> SimulationConfig:
    """Full physics, points only, with this threshold mode and signal-free route."""
    cfg = full_physics_config(quick)
    cfg.run.save_waveforms = False
    cfg.detection.noisy_threshold_mode = threshold_mode
    cfg.detection.signal_free_bins = signal_free_bins
    return cfg


def best_of(fn, repeat=3):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def timed(fn):
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


CPU_S: dict = {}  # name → the process CPU times (all threads) of its timed runs: less sensitive to the load than wall


def timed_cpu(name, fn):
    """:func:`timed`, also recording the run's process CPU time (all threads) under ``name`` in CPU_S."""
    c = time.process_time()
    s, out = timed(fn)
    CPU_S.setdefault(name, []).append(time.process_time() - c)
    return s, out


def cpu_ratios(names, floor_name):
    """Each name's least CPU time over the floor's least CPU time (both: process CPU, all threads)."""
    f = min(CPU_S[floor_name])
    return {"floor_cpu_s": f, **{k: {"cpu_s": min(CPU_S[k]), "cpu_ratio_to_floor": min(CPU_S[k]) / f} for k in names}}


def flash_demo_noisy_vs_ideal(repeat, min_repeat=9):
    """sample_blends/flash_demo.blend (as saved: ideal receiver) against the same frame with the noisy
    receiver chain, all cores."""
    import dataclasses

    sys.path.insert(0, str(ROOT / "bench"))
    from sample_scenes import flash_demo

    scene, pose, cfg = flash_demo()
    tracer = SceneTracer(scene)
    noisy = dataclasses.replace(cfg, detector=dataclasses.replace(cfg.detector, mode="noisy"))
    first_ideal, _ = timed(lambda: simulate_frame(scene, pose, cfg, tracer=tracer))
    first_noisy, _ = timed(lambda: simulate_frame(scene, pose, noisy, tracer=tracer))
    repeat = max(repeat, min_repeat)  # 0.1 s frames: more repeats against the shared machine's noise
    ideal_s, _ = best_of(lambda: simulate_frame(scene, pose, cfg, tracer=tracer), repeat)
    noisy_s, res = best_of(lambda: simulate_frame(scene, pose, noisy, tracer=tracer), repeat)
    return {"ideal_s": ideal_s, "noisy_s": noisy_s, "ratio_noisy_to_ideal": noisy_s / ideal_s,
            "first_call_ideal_s": first_ideal, "first_call_noisy_s": first_noisy,
            "stage_times_s noisy (summed over threads, last run)": res.stats["stage_times_s"]}


def flash_floor_blocks(tracer, det, pose, pixels_per_block):
    """The frame's rays (every pixel's sub-rays, row-major) in the pipeline's blocks of ``pixels_per_block``
    pixels, as Embree casts them (bench/floor.py)."""
    from core.engine.blocks import item_blocks

    x_tan, y_tan, *_ = block_subray_tan(det, 0, det.n_pixels)
    dirs = tan_to_unit_direction(x_tan, y_tan) @ pose[:3, :3].T
    s2 = det.rays_per_pixel
    bounds = [(a * s2, b * s2) for a, b in item_blocks(det.n_pixels, pixels_per_block)]
    return floor.float32_blocks(tracer, pose[:3, 3], dirs, bounds)


def terrain_scene(n_vertices: int = 1000) -> SceneGeometry:
    """The HELIOS++ terrain (bench/bench_helios_survey.py: z = sin x · cos y over ±50 m, 2(n − 1)² triangles;
    1,996,002 at n = 1000) with a 4 m box standing on it at the origin."""
    from bench_helios_survey import terrain

    t = terrain(n_vertices)
    box = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0], [-2, -2, 4], [2, -2, 4], [2, 2, 4], [-2, 2, 4]],
                   float)
    box_tris = np.array([[0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
                         [4, 5, 6], [4, 6, 7]]) + len(t.vertices_m)
    return SceneGeometry(np.concatenate([t.vertices_m, box]), np.concatenate([t.triangles, box_tris]),
                         np.concatenate([t.material_ids, np.ones(len(box_tris), int)]),
                         list(t.materials) + [BRDFSettings(reflectance=0.4)], list(t.material_names) + ["box"])


def terrain_pose() -> np.ndarray:
    """Sensor 60 m from the box (−Y) and 30 m up, looking at the box's centre."""
    target, eye = np.array([0.0, 0.0, 2.0]), np.array([0.0, -60.0, 30.0])
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(right, fwd), -fwd], axis=1)
    pose[:3, 3] = eye
    return pose


def terrain_configs(quick: bool = False, n_bins: int | None = None) -> dict:
    """Issue 28's second flash case: 128² px × 4×4 sub-rays, 1024 bins of 0.5 ns from 40 m, FOV 0.6 rad (quick:
    32² px × 2×2, 256 bins; ``n_bins``: that many bins of 0.5 ns instead, e.g. issue 28's 8192): ideal points only,
    ideal with the cube, full physics (cube saved: the default detector model may skip the signal-free bins), full
    physics points only, and full physics with the counts saved (``run.save_counts``: the per-bin reference
    route)."""
    def base():
        cfg = SimulationConfig()
        cfg.receiver.width_px = cfg.receiver.height_px = 32 if quick else 128
        cfg.receiver.subsamples = 2 if quick else 4
        cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.6
        cfg.gate.n_bins, cfg.gate.bin_width_s = n_bins or (256 if quick else 1024), 0.5e-9
        cfg.gate.gate_start_s = 2 * 40.0 / 299_792_458.0
        return cfg
    ideal, cube, full, full_points, full_counts = base(), base(), base(), base(), base()
    ideal.run.save_waveforms = False
    for c in (full, full_points, full_counts):
        c.atmosphere.cn2_m_23, c.atmosphere.visibility_m = 1e-14, 10e3
        c.detector.mode, c.detector.detector_type = "noisy", "apd"
    full_points.run.save_waveforms = False
    full_counts.run.save_counts = True  # counts.npy kept: the per-bin reference route
    return {"ideal_points_only": ideal, "ideal_cube": cube, "full_physics": full,
            "full_physics_points_only": full_points, "full_physics_counts_saved": full_counts}


class _Stats:
    """A frame result reduced to its ``stats`` (what the reports read): the arrays released."""

    def __init__(self, stats):
        self.stats = stats


def one_thread(cfg: SimulationConfig) -> SimulationConfig:
    """``cfg`` on one thread: ``run.threads`` = 1 and ``detector.threads`` = 1 (the receiver chain's own)."""
    import dataclasses

    return dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, threads=1),
                               detector=dataclasses.replace(cfg.detector, threads=1))


def scaling_report(names, times, times1, floor2, floor1, cpu_prefix="") -> dict:
    """Each frame's thread scaling 1 → 2 against the floor's (bench/floor.py ``thread_scaling``): ``times`` and
    ``times1`` name → wall times on 2 and 1 threads; the floors' best wall times; process CPU from CPU_S."""
    f_cpu = {1: min(CPU_S[f"{cpu_prefix}floor 1 thread"]), 2: min(CPU_S[f"{cpu_prefix}floor"])}
    return {k: floor.thread_scaling({1: min(times1[k]), 2: min(times[k])}, {1: floor1["wall_s"], 2: floor2["wall_s"]},
                                    {1: min(CPU_S[f"{cpu_prefix}{k} 1 thread"]), 2: min(CPU_S[f"{cpu_prefix}{k}"])},
                                    f_cpu) for k in names}


def terrain_case(repeat: int, quick: bool = False, n_bins: int | None = None) -> dict:
    """Each terrain frame's wall time over the floor (the bare cast of its rays on the same threads), interleaved,
    with its stages' ratios; issue 28's targets: ideal points only ≤ 1.8×, cube ≤ 2.2×, full physics ≤ 3× (at
    8192 bins, ``n_bins``, full physics ≤ 4×); and each frame on one thread against the floor on one thread (its
    blocks): the thread scaling 1 → 2.  Each timed frame runs after the previous result of the same frame is
    released, as a run does after writing it (core/sequence.py): a kept 512 MB cube (8192 bins) would make the
    next frame's cube fresh pages (0.5 s of system time a frame, measured in session 31)."""
    t0 = time.perf_counter()
    scene, pose = terrain_scene(100 if quick else 1000), terrain_pose()
    tracer = SceneTracer(scene)
    build_s = time.perf_counter() - t0
    cfgs = terrain_configs(quick, n_bins)
    cfgs1 = {k: one_thread(c) for k, c in cfgs.items()}
    first, times, times1, last, last1 = {}, {k: [] for k in cfgs}, {k: [] for k in cfgs}, {}, {}
    for k, c in cfgs.items():
        first[k], last[k] = timed(lambda: simulate_frame(scene, pose, c, tracer=tracer))
        last1[k] = simulate_frame(scene, pose, cfgs1[k], tracer=tracer)
    det = Detector.from_settings(cfgs["ideal_cube"].receiver)
    blocks = flash_floor_blocks(tracer, det, pose, last["ideal_cube"].stats["pixels_per_block"])
    blocks1 = flash_floor_blocks(tracer, det, pose, last1["ideal_cube"].stats["pixels_per_block"])
    threads = last["ideal_cube"].stats["threads"]
    casts, casts1 = [], []
    for _ in range(repeat):
        casts.append(timed_cpu("terrain floor", lambda: floor.bare_cast(tracer, blocks, threads))[1])
        casts1.append(timed_cpu("terrain floor 1 thread", lambda: floor.bare_cast(tracer, blocks1, 1))[1])
        for k, c in cfgs.items():
            last[k] = last1[k] = None  # released before the next frame, as a run does (docstring)
            s, last[k] = timed_cpu(f"terrain {k}", lambda: simulate_frame(scene, pose, c, tracer=tracer))
            times[k].append(s)
            stats = last[k].stats
            last[k] = _Stats(stats)  # (only its stats are reported)
            s, last1[k] = timed_cpu(f"terrain {k} 1 thread", lambda: simulate_frame(scene, pose, cfgs1[k], tracer=tracer))
            times1[k].append(s)
            last1[k] = _Stats(last1[k].stats)
    fl, fl1 = floor.best(casts), floor.best(casts1)
    targets = {"ideal_points_only": 1.8, "ideal_cube": 2.2, "full_physics": 3.0 if cfgs["full_physics"].gate.n_bins < 8192
               else 4.0}
    return {"n_triangles": scene.n_triangles, "n_bins": cfgs["full_physics"].gate.n_bins, "scene_and_bvh_s": build_s, "floor": fl, "floor_one_thread": fl1,
            "threads": threads,
            "cpu_time (process, all threads; best of the repeats)": cpu_ratios([f"terrain {k}" for k in cfgs],
                                                                              "terrain floor"),
            "cpu_time one thread (process; best of the repeats)": cpu_ratios([f"terrain {k} 1 thread" for k in cfgs],
                                                                            "terrain floor 1 thread"),
            "thread_scaling_1_to_2": scaling_report(list(cfgs), times, times1, fl, fl1, "terrain "),
            "frames": {k: {"time_s": min(v), "median_s": float(np.median(v)), "ratio_to_floor": min(v) / fl["wall_s"],
                           "target": targets.get(k), "first_call_s": first[k], "n_points": last[k].stats["n_points"],
                           "stage_ratio_to_floor": floor.stage_ratios(last[k].stats["stage_times_s"], fl),
                           "one_thread": {"time_s": min(times1[k]), "ratio_to_floor": min(times1[k]) / fl1["wall_s"],
                                          "stage_ratio_to_floor": floor.stage_ratios(last1[k].stats["stage_times_s"],
                                                                                     fl1)},
                           "detector_model": last[k].stats.get("receiver", {}).get("detector_model"),
                           "waveform_binning": last[k].stats["waveform_binning"]}
                       for k, v in times.items()}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-flash-demo", action="store_true", help="skip the flash_demo.blend noisy/ideal case")
    ap.add_argument("--terrain", action="store_true", help="also the HELIOS++ terrain flash case (2M triangles)")
    ap.add_argument("--terrain-bins", type=int, default=None, metavar="N",
                    help="the terrain case with N bins of 0.5 ns (default 1024; issue 28's second target: 8192)")
    add_output_arguments(ap)
    args = ap.parse_args(argv)
    out = output_path(ap, args, "flash.json")
    if args.quick:
        args.repeat = 1

    scene, pose, cfg = bench_scene(32 if args.quick else 128), sensor_pose(), bench_config(args.quick)
    tracer = SceneTracer(scene)  # the BVH, built before every clock
    det = Detector.from_settings(cfg.receiver)
    cfg_points = bench_config(args.quick)
    cfg_points.run.save_waveforms = False
    cfg_full = full_physics_config(args.quick)
    # first calls (compiling or loading the kernels), timed apart
    first_s, res = timed(lambda: simulate_frame(scene, pose, cfg, tracer=tracer))
    first_points_s, _ = timed(lambda: simulate_frame(scene, pose, cfg_points, tracer=tracer))
    first_full_s, _ = timed(lambda: simulate_frame(scene, pose, cfg_full, tracer=tracer))
    cfg_models = {f"{m}/{r}": detector_model_config(m, r, args.quick) for m, r in DETECTOR_MODELS}
    first_models = {k: timed(lambda: simulate_frame(scene, pose, c, tracer=tracer))[0] for k, c in cfg_models.items()}
    threads = res.stats["threads"]
    blocks = flash_floor_blocks(tracer, det, pose, res.stats["pixels_per_block"])
    # the thread scaling 1 → 2: the three frames on one thread, the floor on one thread in their blocks
    cfg_one = {"pipeline": one_thread(cfg), "points_only": one_thread(cfg_points), "full_physics": one_thread(cfg_full)}
    res1 = simulate_frame(scene, pose, cfg_one["pipeline"], tracer=tracer)
    blocks1 = flash_floor_blocks(tracer, det, pose, res1.stats["pixels_per_block"])
    # interleaved: each repeat casts the floor, then runs the three frames (the load of a shared machine
    # changes between runs, not between the floor and the frames of one repeat)
    casts, casts1, times = [], [], {"pipeline": [], "points_only": [], "full_physics": [], **{k: [] for k in cfg_models}}
    times1 = {k: [] for k in cfg_one}
    last = {}
    load_start = os.getloadavg()
    for _ in range(args.repeat):
        casts.append(timed_cpu("floor", lambda: floor.bare_cast(tracer, blocks, threads))[1])
        casts1.append(timed_cpu("floor 1 thread", lambda: floor.bare_cast(tracer, blocks1, 1))[1])
        for name, c in (("pipeline", cfg), ("points_only", cfg_points), ("full_physics", cfg_full),
                        *cfg_models.items()):
            s, last[name] = timed_cpu(name, lambda: simulate_frame(scene, pose, c, tracer=tracer))
            times[name].append(s)
        for name, c in cfg_one.items():
            times1[name].append(timed_cpu(f"{name} 1 thread",
                                          lambda: simulate_frame(scene, pose, c, tracer=tracer))[0])
    fl, fl1 = floor.best(casts), floor.best(casts1)
    bare_s = fl["wall_s"]
    pipe_s, points_s, full_s = (min(times[k]) for k in ("pipeline", "points_only", "full_physics"))
    res, res_points, res_full = last["pipeline"], last["points_only"], last["full_physics"]
    demo = None if args.no_flash_demo else flash_demo_noisy_vs_ideal(args.repeat, 1 if args.quick else 9)
    report = {
        "benchmark": ("quick: flash 32x32 px x 2x2 sub-rays, 256 bins" if args.quick
                      else "flash 128x128 px x 4x4 sub-rays, 1024 bins"),
        "quick": args.quick, "repeat": args.repeat,
        "n_rays": fl["n_rays"], "n_triangles": scene.n_triangles,
        "hit_fraction": fl["n_hits"] / fl["n_rays"],
        "threads": threads,
        "floor_definition": floor.DEFINITION,
        "floor": fl,
        "floor_one_thread": fl1,
        "floor_thread_scaling": fl1["wall_s"] / bare_s,
        "thread_scaling_1_to_2": scaling_report(list(cfg_one), times, times1, fl, fl1),
        "bare_embreex_cast_s": bare_s,
        "pipeline_s": pipe_s,
        "pipeline_points_only_s": points_s,
        "ratio_pipeline_to_bare_cast": pipe_s / bare_s,
        "ratio_points_only_to_bare_cast": points_s / bare_s,
        "pipeline_full_physics_s": full_s,
        "ratio_full_physics_to_bare_cast": full_s / bare_s,
        "median_s": {k: float(np.median(v)) for k, v in times.items()},
        "cpu_time (process, all threads; best of the repeats)": cpu_ratios(list(times), "floor"),
        "first_call_s": {"pipeline": first_s, "points_only": first_points_s, "full_physics": first_full_s},
        "stage_times_s (summed over threads, last run)": res.stats["stage_times_s"],
        "stage_times_s points only (summed over threads, last run)": res_points.stats["stage_times_s"],
        "stage_times_s full physics (summed over threads, last run)": res_full.stats["stage_times_s"],
        "stage_ratio_to_floor": {"pipeline": floor.stage_ratios(res.stats["stage_times_s"], fl),
                                 "points_only": floor.stage_ratios(res_points.stats["stage_times_s"], fl),
                                 "full_physics": floor.stage_ratios(res_full.stats["stage_times_s"], fl)},
        "detector_models (full physics, points only)": {
            k: {"time_s": min(times[k]), "median_s": float(np.median(times[k])), "ratio_to_floor": min(times[k]) / bare_s,
                "first_call_s": first_models[k],
                "stage_ratio_to_floor": floor.stage_ratios(last[k].stats["stage_times_s"], fl),
                "detector_model": last[k].stats["receiver"].get("detector_model"),
                "n_points": last[k].stats["n_points"],
                "false_alarms_per_pixel": last[k].stats["receiver"]["false_alarms"].get("false_alarms_per_pixel"),
                "expected_false_alarms_per_pixel_gaussian":
                    last[k].stats["receiver"]["false_alarms"].get("expected_false_alarms_per_pixel_gaussian")}
            for k in cfg_models},
        "flash_demo_noisy_vs_ideal": demo,
        "terrain_flash": terrain_case(args.repeat, args.quick, args.terrain_bins) if args.terrain else None,
        "waveform_binning": res.stats["waveform_binning"],
        "n_points": res.stats["n_points"],
        "load_average_1_5_15_min": {"start": list(load_start), "end": list(os.getloadavg())},
        "machine": machine_info(),
        "software": software_versions(),
    }
    print(json.dumps(report, indent=2))
    print(f"wrote {write_json(out, report)}")


if __name__ == "__main__":
    main()
