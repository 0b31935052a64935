"""Weather-stage benchmark (issue 30): the cost of the returns of the atmosphere on the flash benchmark frame.

The frame of bench/bench_flash.py (128×128 px × 4×4 sub-rays, 1024 bins of 1 ns from 200 m; ``--quick``: 32×32 px
× 2×2, 256 bins) in clear air, in fog (visibility 200 m: volume backscatter) and in heavy rain (25 mm/h: volume
backscatter of the drops below 4 mm plus the drops ≥ 4 mm above the detectability cut (0.01 photo-electrons, the
default) drawn as returns of their own; ``rain_25mm_h_brute_force``: every drop ≥ 4 mm drawn (cut 0, as before
the cut); ``rain_25mm_h_1mm``: D_min = 1 mm with the cut (brute force the 12° field of view holds 2.4e8 drops
between 200 and 350 m, which the stage refuses)), each against the floor
(bench/floor.py: the bare embreex cast of the frame's own rays on the pipeline's threads): the frame's wall time
over the floor's, and the ``weather`` stage's thread-seconds over the floor's thread-seconds.  The clear frame
keeps its cube too (``run.save_waveforms``), as a weather frame does, so the difference is the weather's.

Error of the cut: the rain frame's mean waveform with the cut against brute force (``rain_cut_accuracy``).
Run time against error: the volume template (core/atmosphere/weather.py) with 1, 2, 4 (the default) and 8 range
slabs per min(bin, pulse FWHM), each timed and compared (relative L2) with 32 slabs.

Writes ``weather.json`` to ``--out DIR`` (default runs/bench/; ``--update-committed``: bench/results/weather.json).

    .venv/bin/python bench/bench_weather.py [--repeat 3] [--out DIR | --update-committed] [--quick]
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from core.atmosphere.weather import Overlap  # noqa: E402
from core.physics.weather_waveform import backscatter_template  # noqa: E402
from core.config.settings import LaserSettings, RangeGateSettings  # noqa: E402
from core.geometry.rays import Detector  # noqa: E402
from core.geometry.trace import SceneTracer  # noqa: E402
from core.systems.flash import simulate_frame  # noqa: E402
from benchio import add_output_arguments, output_path, write_json  # noqa: E402
from bench_flash import bench_config, bench_scene, flash_floor_blocks, sensor_pose  # noqa: E402
import floor  # noqa: E402

CASES = {"clear": {}, "fog_200m": {"weather": "fog", "visibility_m": 200.0},
         "rain_25mm_h": {"weather": "rain", "rain_rate_mm_h": 25.0, "drop_min_diameter_mm": 4.0},
         "rain_25mm_h_brute_force": {"weather": "rain", "rain_rate_mm_h": 25.0, "drop_min_diameter_mm": 4.0,
                                     "drop_cut_photoelectrons": 0.0},
         "rain_25mm_h_1mm": {"weather": "rain", "rain_rate_mm_h": 25.0, "drop_min_diameter_mm": 1.0}}


def template_accuracy(repeat: int) -> list:
    """Volume template: time and relative L2 error against 32 slabs, for 1, 2, 4 and 8 slabs per width."""
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    gate = RangeGateSettings(gate_start_s=2 * 10.0 / 299_792_458.0, bin_width_s=1e-9, n_bins=1024)
    args = (laser, gate, 1.0, 0.0196 / 18, 0.0196, Overlap("geometric", 0.05, 0.01, 0.1, 0.025, 1e-3), 3.0)
    ref = backscatter_template(*args, slabs_per_width=32)
    rows = []
    for k in (1, 2, 4, 8):
        best = np.inf
        for _ in range(repeat):
            t = time.perf_counter()
            wf = backscatter_template(*args, slabs_per_width=k)
            best = min(best, time.perf_counter() - t)
        rows.append({"slabs_per_width": k, "time_s": best,
                     "l2_error_vs_32": float(np.linalg.norm(wf - ref) / np.linalg.norm(ref))})
    return rows


def cut_accuracy(scene, pose, tracer, configs, quick: bool) -> dict:
    """Error of the detectability cut: the frame's mean waveform (all pixels) with the cut against brute force, over
    a few seeds each.  Pixel by pixel (same pixel, same seed index) the scene's part cancels and the difference is
    the draws' (independent: the two schemes use the stream differently): relative L2 of the mean difference and
    its statistical floor (the L2 of its standard error), and the total energy's relative difference with its
    standard error."""
    seeds = range(2 if quick else 4)

    def rows(cfg):
        out = []
        for seed in seeds:
            c = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, seed=seed))
            out.append(simulate_frame(scene, pose, c, tracer=tracer).waveforms.reshape(-1, c.gate.n_bins))
        return np.concatenate(out).astype(np.float64)

    w_c, w_b = rows(configs["rain_25mm_h"]), rows(configs["rain_25mm_h_brute_force"])
    d = w_c - w_b
    norm = np.linalg.norm(w_b.mean(0))
    se = d.std(0, ddof=1) / np.sqrt(len(d))
    t = d.sum(1)
    return {"frames_each": len(seeds), "l2_mean_waveform_cut_vs_brute": float(np.linalg.norm(d.mean(0)) / norm),
            "l2_statistical_floor": float(np.linalg.norm(se) / norm),
            "total_energy_relative_difference": float(t.mean() / w_b.sum(1).mean()),
            "total_energy_relative_standard_error": float(t.std(ddof=1) / np.sqrt(len(t)) / w_b.sum(1).mean())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    add_output_arguments(ap)
    args = ap.parse_args(argv)
    out = output_path(ap, args, "weather.json")
    if args.quick:
        args.repeat = 1
    scene, pose = bench_scene(32 if args.quick else 128), sensor_pose()
    tracer = SceneTracer(scene)
    configs = {}
    for name, atm in CASES.items():
        cfg = bench_config(args.quick)
        cfg.run.save_waveforms = True
        cfg.atmosphere = dataclasses.replace(cfg.atmosphere, **atm)
        configs[name] = cfg
    first = {}
    for name, cfg in configs.items():  # first calls (compiling or loading kernels), apart
        t = time.perf_counter()
        res = simulate_frame(scene, pose, cfg, tracer=tracer)
        first[name] = time.perf_counter() - t
    det = Detector.from_settings(configs["clear"].receiver)
    threads = res.stats["threads"]
    blocks = flash_floor_blocks(tracer, det, pose, res.stats["pixels_per_block"])
    casts, times, last = [], {k: [] for k in CASES}, {}
    for _ in range(args.repeat):
        casts.append(floor.bare_cast(tracer, blocks, threads))
        for name, cfg in configs.items():
            t = time.perf_counter()
            last[name] = simulate_frame(scene, pose, cfg, tracer=tracer)
            times[name].append(time.perf_counter() - t)
    fl = floor.best(casts)
    cases = {}
    for name in CASES:
        st = last[name].stats
        frame_s = min(times[name])
        weather_s = st["stage_times_s"].get("weather", 0.0)
        cases[name] = {"frame_s": frame_s, "ratio_frame_to_bare_cast": frame_s / fl["wall_s"],
                       "weather_stage_thread_s": weather_s,
                       "ratio_weather_stage_to_floor": weather_s / fl["thread_s"],
                       "n_points": st["n_points"],
                       "atmosphere_echoes": st.get("weather", {}).get("n_atmosphere_echoes", 0),
                       "drops_drawn": st.get("weather", {}).get("drops", {}).get("drawn", 0),
                       "drops_expected": st.get("weather", {}).get("drops", {}).get("expected", 0),
                       "stage_times_s": st["stage_times_s"], "first_call_s": first[name]}
    report = {"benchmark": ("quick: " if args.quick else "") + "flash frame of bench_flash.py, clear / fog / rain",
              "quick": args.quick, "repeat": args.repeat, "threads": threads,
              "floor_definition": floor.DEFINITION, "floor": fl, "bare_embreex_cast_s": fl["wall_s"],
              "cases": cases,
              "ratio_fog_frame_to_clear_frame": cases["fog_200m"]["frame_s"] / cases["clear"]["frame_s"],
              "ratio_rain_frame_to_clear_frame": cases["rain_25mm_h"]["frame_s"] / cases["clear"]["frame_s"],
              "ratio_rain_brute_force_frame_to_clear_frame": (cases["rain_25mm_h_brute_force"]["frame_s"]
                                                              / cases["clear"]["frame_s"]),
              "rain_cut_accuracy": cut_accuracy(scene, pose, tracer, configs, args.quick),
              "template_time_vs_error": template_accuracy(1 if args.quick else 5)}
    write_json(out, report)
    for name, c in cases.items():
        print(f"{name:12s} frame {c['frame_s']:.3f} s = {c['ratio_frame_to_bare_cast']:.1f} × bare cast; weather "
              f"stage {c['weather_stage_thread_s']:.3f} thread-s = {c['ratio_weather_stage_to_floor']:.2f} × floor; "
              f"{c['drops_drawn']} drops drawn; {c['atmosphere_echoes']} atmosphere echoes of {c['n_points']}")
    acc = report["rain_cut_accuracy"]
    print(f"rain cut vs brute force: mean waveform L2 {acc['l2_mean_waveform_cut_vs_brute']:.2e} (statistical floor "
          f"{acc['l2_statistical_floor']:.2e}); total energy {acc['total_energy_relative_difference']:+.2e} "
          f"± {acc['total_energy_relative_standard_error']:.1e}")
    for r in report["template_time_vs_error"]:
        print(f"template {r['slabs_per_width']} slabs/width: {r['time_s'] * 1e3:.1f} ms, L2 error {r['l2_error_vs_32']:.1e}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
