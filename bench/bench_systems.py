"""Scanner and gated-viewing benchmarks (issue 5, Speed).

Scanner: an airborne oscillating scanner over a terrain of ≥ 1M triangles, 1M pulses × 7 sub-rays (one ring).
Measured in one run: the pipeline (`simulate_scan` with the BVH built beforehand), the bare embreex ray cast of
the very same 7M rays (the floor, bench/floor.py: one embreex call per pipeline block, on the pipeline's threads),
pulses/s, rays/s and their ratio, and the stage times with their ratios to the floor.

Gated viewing: a 30-slice sweep over the same scene from a camera, against a 1-slice run (the slices must reuse
the one ray trace: the number of traced rays is counted and the extra time per slice reported).

Writes ``systems.json`` to ``--out DIR`` (default runs/bench/; ``--update-committed``: bench/results/systems.json).
Absolute times on a shared 2-core machine are noisy; the ratios measured in the same run are the figures to track.
``--quick``: 20 000 pulses over 20 000 triangles, a 64×64 px × 2×2 gated camera (seconds).

    .venv/bin/python bench/bench_systems.py [--pulses 1000000] [--grid 708] [--out DIR | --update-committed] [--quick]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.config.settings import BRDFSettings, SimulationConfig  # noqa: E402
from core.systems.gated import simulate_gated  # noqa: E402
from core.geometry.motion import Trajectory  # noqa: E402
from core.fileio.run_folder import software_versions  # noqa: E402
from core.config.derived import n_scan_pulses  # noqa: E402
from core.systems.scan_patterns import scan_rays  # noqa: E402
from core.systems.scanner import simulate_scan  # noqa: E402
from core.geometry.scene import SceneGeometry  # noqa: E402
from core.geometry.trace import SceneTracer  # noqa: E402
from benchio import add_output_arguments, output_path, write_json  # noqa: E402
import floor  # noqa: E402  (bench/floor.py)

C = 299_792_458.0


def terrain(n_grid: int) -> SceneGeometry:
    """A 2 km × 2 km rolling terrain of 2·n_grid² triangles (n_grid = 708 → 1.0M triangles)."""
    x = np.linspace(-1000.0, 1000.0, n_grid + 1)
    gx, gy = np.meshgrid(x, x)
    gz = 6.0 * np.sin(gx / 90.0) * np.cos(gy / 70.0) + 1.5 * np.sin(gx / 9.0 + gy / 13.0)
    verts = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    i = np.arange(n_grid)
    a = (i[:, None] * (n_grid + 1) + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n_grid + 2], 1), np.stack([a, a + n_grid + 2, a + n_grid + 1], 1)])
    return SceneGeometry(verts, tris, np.zeros(len(tris), int), [BRDFSettings(reflectance=0.25)], ["ground"])


def scanner_case(n_pulses: int):
    cfg = SimulationConfig(system_type="scanner")
    s = cfg.scanner
    s.pattern, s.pulse_rate_hz, s.scan_rate_hz = "oscillating", 1e6, 100.0
    s.scan_width_rad, s.duration_s, s.beam_subray_rings = np.deg2rad(40.0), n_pulses / 1e6, 1
    cfg.laser.beam_divergence_rad, cfg.laser.pulse_fwhm_s = 0.5e-3, 3e-9
    cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2 * 470.0 / C, 0.5e-9, 1024  # 470–547 m
    cfg.run.save_waveforms = False
    # 500 m above the terrain, flying +Y at 60 m/s
    times = np.array([0.0, s.duration_s])
    mats = np.repeat(np.eye(4)[None], 2, axis=0)
    mats[:, 2, 3] = 500.0
    mats[1, 1, 3] = 60.0 * s.duration_s
    return cfg, Trajectory(times, mats)


def bench_scanner(n_pulses: int, n_grid: int) -> dict:
    scene = terrain(n_grid)
    t0 = time.perf_counter()
    tracer = SceneTracer(scene)
    build_s = time.perf_counter() - t0
    cfg, traj = scanner_case(n_pulses)
    n = n_scan_pulses(cfg)
    t0 = time.perf_counter()
    res = simulate_scan(scene, np.eye(4), cfg, tracer=tracer, trajectory=traj)
    pipeline_s = time.perf_counter() - t0
    # the floor (bench/floor.py): the bare cast of the same rays, in the pipeline's blocks, on its threads (rays
    # generated outside the timing)
    per_block = res.stats["pulses_per_block"]
    blocks = []
    for a in range(0, n, per_block):
        *_, o_world, d_world = scan_rays(cfg, traj, a, min(a + per_block, n))
        blocks += floor.float32_blocks(tracer, o_world, d_world, [(0, len(d_world))])
    threads = res.stats["threads"]
    fl = floor.best([floor.bare_cast(tracer, blocks, threads)])
    bare_s, n_rays = fl["wall_s"], fl["n_rays"]
    return {"n_triangles": scene.n_triangles, "n_pulses": n, "subrays_per_pulse": res.stats["subrays_per_pulse"],
            "n_rays": n_rays, "n_hits_bare": fl["n_hits"], "n_hits_pipeline": res.stats["n_hits"],
            "n_points": res.stats["n_points"], "threads": threads, "bvh_build_s": build_s,
            "pipeline_s": pipeline_s, "floor_definition": floor.DEFINITION, "floor": fl, "bare_cast_s": bare_s,
            "pulses_per_s": n / pipeline_s, "rays_per_s": n_rays / pipeline_s,
            "bare_rays_per_s": n_rays / bare_s,
            "ratio_pipeline_to_bare_cast": pipeline_s / bare_s,
            "stage_times_s": res.stats["stage_times_s"],
            "stage_ratio_to_floor": floor.stage_ratios(res.stats["stage_times_s"], fl)}


def bench_gated(n_grid: int, pixels: int = 256, subsamples: int = 4) -> dict:
    scene = terrain(n_grid)
    tracer = SceneTracer(scene)
    calls = []
    original = tracer.intersect

    def counting(origin, directions, **kwargs):
        calls.append(len(directions))
        return original(origin, directions, **kwargs)

    tracer.intersect = counting
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px = cfg.receiver.height_px = pixels
    cfg.receiver.subsamples = subsamples
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.05
    cfg.laser.pulse_fwhm_s = 10e-9
    g = cfg.gated
    g.gate_width_s, g.delay_step_s = 20e-9, 2 * 1.0 / C
    eye = np.array([0.0, -900.0, 60.0])
    target = np.array([0.0, -300.0, 0.0])
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(right, fwd), -fwd], axis=1)
    pose[:3, 3] = eye
    r_mid = float(np.linalg.norm(target - eye))
    out = {}
    for n_slices in (1, 30):
        g.n_slices = n_slices
        g.first_delay_s = 2 * (r_mid - 0.5 * n_slices) / C - 0.5 * g.gate_width_s
        calls.clear()
        t0 = time.perf_counter()
        res = simulate_gated(scene, pose, cfg, tracer=tracer)
        out[f"{n_slices}_slices"] = {"wall_s": time.perf_counter() - t0, "rays_traced": int(sum(calls)),
                                     "stage_times_s": res.stats["stage_times_s"]}
    n_rays = pixels * pixels * subsamples ** 2
    one, many = out["1_slices"], out["30_slices"]
    out.update(n_rays=n_rays, traced_once=bool(many["rays_traced"] == n_rays),
               extra_s_per_slice=(many["wall_s"] - one["wall_s"]) / 29,
               ratio_30_to_1_slices=many["wall_s"] / one["wall_s"],
               trace_s=many["stage_times_s"]["trace"])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pulses", type=int, default=1_000_000)
    ap.add_argument("--grid", type=int, default=708, help="terrain grid side (2·grid² triangles)")
    add_output_arguments(ap)
    args = ap.parse_args(argv)
    out = output_path(ap, args, "systems.json")
    if args.quick:
        args.pulses, args.grid = 20_000, 100
    gated = bench_gated(args.grid, 64, 2) if args.quick else bench_gated(args.grid)
    result = {"benchmark": "systems", "quick": args.quick, "software": software_versions(),
              "scanner": bench_scanner(args.pulses, args.grid), "gated": gated}
    write_json(out, result)
    sc, gv = result["scanner"], result["gated"]
    print(f"scanner: {sc['n_pulses']} pulses × {sc['subrays_per_pulse']} sub-rays on {sc['n_triangles']} "
          f"triangles: {sc['pipeline_s']:.2f} s → {sc['pulses_per_s']:.3g} pulses/s, {sc['rays_per_s']:.3g} rays/s "
          f"({sc['threads']} threads); bare embreex (same threads) {sc['bare_rays_per_s']:.3g} rays/s; "
          f"ratio {sc['ratio_pipeline_to_bare_cast']:.2f}")
    print(f"gated: 30 slices traced {gv['30_slices']['rays_traced']} rays (= {gv['n_rays']}: "
          f"{'once' if gv['traced_once'] else 'MORE THAN ONCE'}); {gv['30_slices']['wall_s']:.2f} s vs "
          f"{gv['1_slices']['wall_s']:.2f} s for one slice ({gv['extra_s_per_slice'] * 1e3:.1f} ms per extra slice)")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
