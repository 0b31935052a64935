"""The HELIOS++ airborne survey (issue 16): this simulator against HELIOS++ on HELIOS++'s own benchmark survey.

Scene and survey, as HELIOS++ v2.0.1 (C++, Release build) ran them on this kind of machine:

* terrain: 1000 × 1000 vertices, z = sin(x)·cos(y) over x, y ∈ [−50, 50] m (1,996,002 triangles);
* scanner: an oscillating mirror, 500 kHz, ±20° (40° full width) at 100 Hz, 0.5 mrad divergence, 4 ns pulse,
  1064 nm, 19 sub-rays per pulse (two rings); full waveform computed at 0.25 ns bins, not written;
* platform: 100.7 m up, flying +X at 30 m/s from x = −45 to +45 m (3 s, 1.5M pulses), sweeping across track.

Measured in one run (one process): the scene load (terrain built and its BVH), the whole survey
(``simulate_scan``, BVH built beforehand) at 1 and 2 threads, pulses/s, the thread scaling, the peak resident
memory of the process up to the end of the survey runs (scene, BVH, kernels and the surveys) with the resident
memory at the stage boundaries, the bare embreex cast of as many rays along the same scan lines (the very same
sub-rays, generated outside the timing, cast in the pipeline's blocks on 1 and 2 threads of the shared pool: the
floor of bench/floor.py) and the ratio of the pipeline, and of each stage, to it; the survey's thread scaling 1 → 2
against the floor's and each side's process CPU (all threads); the load average at the start and the end.  The first call's latency
(JIT compilation, or loading the compiled kernels from the per-user cache) is measured separately, in fresh
processes, on a 4096-pulse scan: with an empty kernel cache and with the cache filled.  HELIOS++'s figures are the stated reference: 37.4k pulses/s on 2 threads, 20.1k on 1,
4.4 GB peak memory, 18 s scene load.  Writes ``helios_survey.json`` to ``--out DIR`` (default runs/bench/;
``--update-committed``: bench/results/helios_survey.json).  ``--quick``: a 0.02 s survey (10 000 pulses) over a
101 × 101-vertex terrain, no first-call latency runs (seconds; the comparison with HELIOS++ is meaningless there).
The survey again in fog (visibility 200 m) and in rain (25 mm/h) on 2 threads (issue 30; ``--no-weather`` skips):
its time over the bare cast's and over the clear survey's, and the weather stage's thread-seconds over the floor's.
``--pulse-model`` sets ``scanner.pulse_model`` of the surveys (the JSON's ``survey.pulse_model`` records which ran:
the weather surveys build full-gate waveforms from the sub-rays whatever it says).

    .venv/bin/python bench/bench_helios_survey.py [--duration 3.0] [--grid 1000] [--repeat 1] [--no-first-call]
        [--no-weather] [--pulse-model centroid|subrays] [--out DIR | --update-committed] [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

C = 299_792_458.0
HELIOS = {"version": "HELIOS++ v2.0.1 (C++, Release build)", "pulses_per_s_2_threads": 37_400.0,
          "pulses_per_s_1_thread": 20_100.0, "peak_memory_bytes": 4.4e9, "scene_load_s": 18.0}


def terrain(n_vertices: int = 1000):
    """z = sin(x)·cos(y) on an n × n vertex grid over [−50, 50]² m: 2(n − 1)² triangles."""
    from core.config.settings import BRDFSettings
    from core.geometry.scene import SceneGeometry

    x = np.linspace(-50.0, 50.0, n_vertices)
    gx, gy = np.meshgrid(x, x)
    verts = np.stack([gx.ravel(), gy.ravel(), (np.sin(gx) * np.cos(gy)).ravel()], axis=1)
    n = n_vertices - 1
    i = np.arange(n)
    a = (i[:, None] * n_vertices + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n_vertices + 1], 1),
                           np.stack([a, a + n_vertices + 1, a + n_vertices], 1)])
    return SceneGeometry(verts, tris, np.zeros(len(tris), int), [BRDFSettings(reflectance=0.3)], ["terrain"])


def survey(duration_s: float = 3.0, threads: int = 1):
    """(config, trajectory): the oscillating scanner flying +X at 30 m/s, 100.7 m up, centred on x = 0."""
    from core.config.settings import SimulationConfig
    from core.geometry.motion import Trajectory

    cfg = SimulationConfig(system_type="scanner")
    s = cfg.scanner
    s.pattern, s.pulse_rate_hz, s.scan_rate_hz = "oscillating", 500e3, 100.0
    s.scan_width_rad, s.duration_s, s.beam_subray_rings = np.deg2rad(40.0), duration_s, 2  # 19 sub-rays
    cfg.laser.beam_divergence_rad, cfg.laser.pulse_fwhm_s, cfg.laser.wavelength_m = 0.5e-3, 4e-9, 1.064e-6
    cfg.laser.divergence_fills_fov = False
    # ranges 99.7 m (nadir, a crest) to 108 m (20° off nadir, a trough): a gate 95–119 m at 0.25 ns
    cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2 * 95.0 / C, 0.25e-9, 640
    cfg.run.save_waveforms = False  # computed, not written
    cfg.run.threads = threads
    # sensor −Z down, sensor +X across track (world +Y): the mirror sweeps across the flight line
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    x0 = -0.5 * 30.0 * duration_s
    mats = np.repeat(np.eye(4)[None], 2, axis=0)
    mats[:, :3, :3] = rot
    mats[:, :3, 3] = [[x0, 0.0, 100.7], [-x0, 0.0, 100.7]]
    return cfg, Trajectory(np.array([0.0, duration_s]), mats)


def peak_rss_bytes() -> int:
    """Peak resident memory of this process so far (ru_maxrss)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)


def rss_bytes() -> int | None:
    """Resident memory now (Linux /proc; None elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return None


#: The survey in weather (issue 30): fog of 200 m visibility (volume backscatter), heavy rain (drops ≥ 1 mm above
#: the default detectability cut, the smaller ones as volume).
WEATHER = {"fog_200m": {"weather": "fog", "visibility_m": 200.0},
           "rain_25mm_h": {"weather": "rain", "rain_rate_mm_h": 25.0}}


#: scanner.pulse_model of the surveys (``--pulse-model``; None: the setting's default)
PULSE_MODEL = None


def run_survey(scene, tracer, duration_s, threads, weather=None):
    import dataclasses

    from core.systems.scanner import simulate_scan

    cfg, traj = survey(duration_s, threads)
    if PULSE_MODEL is not None:
        cfg.scanner.pulse_model = PULSE_MODEL
    if weather:
        cfg.atmosphere = dataclasses.replace(cfg.atmosphere, **weather)
    t0, c0 = time.perf_counter(), time.process_time()
    res = simulate_scan(scene, np.eye(4), cfg, tracer=tracer, trajectory=traj)
    res.stats["process_cpu_s"] = time.process_time() - c0  # all threads
    return time.perf_counter() - t0, res


def bare_cast(tracer, duration_s, per_block, threads_list):
    """The floor (bench/floor.py): the bare embreex cast of the survey's sub-rays (generated first, outside the
    timing) in the pipeline's blocks, on each thread count of the shared pool: {threads: floor.bare_cast report}."""
    import floor
    from core.config.derived import n_scan_pulses
    from core.systems.scan_patterns import scan_rays

    cfg, traj = survey(duration_s)
    n = n_scan_pulses(cfg)
    blocks = []
    for a in range(0, n, per_block):
        *_, o_world, d_world = scan_rays(cfg, traj, a, min(a + per_block, n))
        blocks += floor.float32_blocks(tracer, o_world, d_world, [(0, len(d_world))])
    out = {}
    for threads in threads_list:
        c0 = time.process_time()
        out[threads] = floor.best([floor.bare_cast(tracer, blocks, threads)])
        out[threads]["cpu_s"] = time.process_time() - c0  # process CPU, all threads
    return out


_FIRST_CALL = r"""
import json, sys, time
sys.path.insert(0, {root!r}); sys.path.insert(0, {bench!r})
t0 = time.perf_counter()
import numpy as np
import bench_helios_survey as b
import core.systems.scanner  # noqa: F401  (imports the compiled-kernel module)
t_import = time.perf_counter() - t0
from core.geometry.scene import SceneGeometry
from core.config.settings import BRDFSettings
from core.geometry.trace import SceneTracer
scene = b.terrain(101)
tracer = SceneTracer(scene)
times = []
for _ in range(2):
    t0 = time.perf_counter()
    b.run_survey(scene, tracer, 4096 / 500e3, 1)
    times.append(time.perf_counter() - t0)
print("RESULT " + json.dumps({{"import_s": t_import, "first_call_s": times[0], "second_call_s": times[1]}}))
"""


def first_call_latency():
    """A 4096-pulse scan in fresh processes: an empty kernel cache (compiles), then the filled cache (loads)."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("empty_cache", "filled_cache"):
            code = _FIRST_CALL.format(root=str(ROOT), bench=str(ROOT / "bench"))
            proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT)
            if proc.returncode != 0:
                raise RuntimeError(proc.stderr[-3000:])
            line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")][-1]
            r = json.loads(line[len("RESULT "):])
            r["first_call_extra_s"] = r["first_call_s"] - r["second_call_s"]
            out[label] = r
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=3.0, help="survey duration (s); 3 s = 1.5M pulses")
    ap.add_argument("--grid", type=int, default=1000, help="terrain vertices per side")
    ap.add_argument("--repeat", type=int, default=1, help="survey runs per thread count (best taken)")
    ap.add_argument("--no-first-call", action="store_true", help="skip the fresh-process first-call latency")
    ap.add_argument("--no-weather", action="store_true", help="skip the survey in fog and in rain (2 threads)")
    ap.add_argument("--pulse-model", choices=("centroid", "subrays"), default=None,
                    help="scanner.pulse_model of the clear surveys (default: the setting's default)")
    sys.path.insert(0, str(ROOT / "bench"))
    import floor
    from benchio import add_output_arguments, output_path, write_json

    add_output_arguments(ap)
    args = ap.parse_args(argv)
    out_path = output_path(ap, args, "helios_survey.json")
    global PULSE_MODEL
    PULSE_MODEL = args.pulse_model
    if args.quick:
        args.duration, args.grid, args.repeat, args.no_first_call = 0.02, 101, 1, True

    from core.fileio.run_folder import software_versions
    from core.geometry.trace import SceneTracer
    from machine import machine_info

    load_start = os.getloadavg()
    first = None if args.no_first_call else first_call_latency()
    import core.systems.scanner  # noqa: F401  (the libraries and the compiled-kernel modules)
    memory = {"after_imports": (rss_bytes(), peak_rss_bytes())}
    t0 = time.perf_counter()
    scene = terrain(args.grid)
    tracer = SceneTracer(scene)  # builds the BVH
    load_s = time.perf_counter() - t0
    memory["after_scene_and_bvh"] = (rss_bytes(), peak_rss_bytes())
    # warm-up: a short scan so compilation or kernel loading is not in the timings
    run_survey(scene, tracer, 0.01, 1)
    memory["after_warm_up (kernels loaded)"] = (rss_bytes(), peak_rss_bytes())
    runs = {}
    for threads in (1, 2):
        best, stats = np.inf, None
        for _ in range(args.repeat):
            s, res = run_survey(scene, tracer, args.duration, threads)
            if s < best:
                best, stats = s, res.stats
            del res  # one survey's products in memory at a time (the peak is one run's)
        runs[threads] = (best, stats)
        memory[f"after_surveys_on_{threads}_thread{'s' if threads > 1 else ''}"] = (rss_bytes(), peak_rss_bytes())
    peak = peak_rss_bytes()
    memory["after_surveys"] = (rss_bytes(), peak)
    weather_runs = {}
    if not args.no_weather:  # after the peak is read: the clear surveys' memory figures stay comparable
        for name, atm in WEATHER.items():
            run_survey(scene, tracer, 0.01, 2, atm)  # warm-up of the weather code paths
            best, stats = np.inf, None
            for _ in range(args.repeat):
                s, res = run_survey(scene, tracer, args.duration, 2, atm)
                if s < best:
                    best, stats = s, res.stats
                del res
            weather_runs[name] = (best, stats)
    res1 = runs[1][1]
    n_pulses = res1["n_pulses"]
    floors = bare_cast(tracer, args.duration, res1["pulses_per_block"], (1, 2))
    bare = {t: floors[t]["wall_s"] for t in (1, 2)}
    n_rays, bare_hits = floors[1]["n_rays"], floors[1]["n_hits"]
    pps = {t: n_pulses / runs[t][0] for t in (1, 2)}
    report = {
        "benchmark": "HELIOS++ airborne survey (issue 16)" + (" (quick: not comparable)" if args.quick else ""),
        "quick": args.quick, "duration_s": args.duration,
        "scene": {"vertices": int(scene.vertices_m.shape[0]), "n_triangles": scene.n_triangles,
                  "load_s (terrain built + BVH)": load_s},
        "survey": {"n_pulses": n_pulses, "subrays_per_pulse": res1["subrays_per_pulse"], "n_rays": n_rays,
                   "bin_width_s": 0.25e-9, "n_bins": 640, "pulses_per_block": res1["pulses_per_block"],
                   "n_hits": res1["n_hits"], "n_hits_bare": bare_hits, "n_points": res1["n_points"],
                   "pulses_without_echo": res1["pulses_without_echo"],
                   "pulse_model": res1.get("pulse_model")},
        "pipeline_s": {str(t): runs[t][0] for t in (1, 2)},
        "pulses_per_s": {str(t): pps[t] for t in (1, 2)},
        "thread_scaling_1_to_2": runs[1][0] / runs[2][0],
        "thread_scaling_against_floor": floor.thread_scaling(
            {t: runs[t][0] for t in (1, 2)}, bare, {t: runs[t][1]["process_cpu_s"] for t in (1, 2)},
            {t: floors[t]["cpu_s"] for t in (1, 2)}),
        "cpu_ratio_pipeline_to_floor (process CPU, all threads)": {
            str(t): runs[t][1]["process_cpu_s"] / floors[t]["cpu_s"] for t in (1, 2)},
        "bare_cast_s": {str(t): bare[t] for t in (1, 2)},
        "bare_rays_per_s_per_thread": n_rays / bare[1],
        "ratio_pipeline_to_bare_cast": {str(t): runs[t][0] / bare[t] for t in (1, 2)},
        "floor_definition": floor.DEFINITION,
        "floor": {str(t): floors[t] for t in (1, 2)},
        "stage_ratio_to_floor": {str(t): floor.stage_ratios(runs[t][1]["stage_times_s"], floors[t]) for t in (1, 2)},
        "peak_rss_bytes (scene, kernels and one survey run)": peak,
        "peak_rss_includes": "the whole process up to the end of the survey runs: interpreter and libraries, the "
                             "terrain and its BVH, the compiled kernels, the warm-up scan and the full surveys at 1 "
                             "and 2 threads (one survey's products held at a time); the bare cast runs after the "
                             "peak is read",
        "memory_bytes (rss now, peak so far) at stage boundaries": memory,
        "stage_times_s (1 thread)": runs[1][1]["stage_times_s"],
        "stage_times_s (2 threads, summed over threads)": runs[2][1]["stage_times_s"],
        "weather (2 threads)": {
            name: {"pipeline_s": w[0], "ratio_pipeline_to_bare_cast": w[0] / bare[2],
                   "ratio_to_clear_survey": w[0] / runs[2][0],
                   "weather_stage_thread_s": w[1]["stage_times_s"].get("weather", 0.0),
                   "ratio_weather_stage_to_floor": w[1]["stage_times_s"].get("weather", 0.0) / floors[2]["thread_s"],
                   "n_points": w[1]["n_points"],
                   "atmosphere_echoes": w[1].get("weather", {}).get("n_atmosphere_echoes", 0),
                   "drops_expected": w[1].get("weather", {}).get("drops", {}).get("expected", 0),
                   "stage_times_s": w[1]["stage_times_s"]} for name, w in weather_runs.items()},
        "first_call_latency": first,
        "helios_reference": HELIOS,
        "vs_helios": {"pulses_per_s_2_threads": pps[2] / HELIOS["pulses_per_s_2_threads"],
                      "pulses_per_s_1_thread": pps[1] / HELIOS["pulses_per_s_1_thread"],
                      "peak_memory": peak / HELIOS["peak_memory_bytes"],
                      "scene_load": load_s / HELIOS["scene_load_s"]},
        "load_average_1_5_15_min": {"start": list(load_start), "end": list(os.getloadavg())},
        "cpu_count": os.cpu_count(),
        "machine": machine_info(),
        "software": software_versions(),
    }
    print(json.dumps(report, indent=2))
    print(f"wrote {write_json(out_path, report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
