"""The radiometry stage of the flash benchmark frame (bench_flash.py: 128×128 px × 4×4 sub-rays, points only),
and optionally the same against another checkout in the same process (issue 16).

For 1 and 2 threads: the "radiometry" stage time (summed over the threads) and the whole frame's wall time,
best and median of ``--repeat`` runs.  With ``--base DIR`` (a checkout or an exported tree of another commit) its
``core`` is imported as the package ``core_base`` and the two versions run interleaved, frame by frame, so the
shared machine's load falls on both alike; the ratios new/base are the figures to read, and the two energy
images are compared.  Writes ``radiometry.json`` to ``--out DIR`` (default runs/bench/; ``--update-committed``:
bench/results/radiometry.json).  ``--quick``: the 32×32 px × 2×2 frame of ``bench_flash.py --quick``, 2 runs.

    .venv/bin/python bench/bench_radiometry.py [--repeat 15] [--base /path/to/other/checkout]
        [--out DIR | --update-committed] [--quick]
"""
from __future__ import annotations

import argparse
import importlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_flash import bench_config, bench_scene, sensor_pose  # noqa: E402
from benchio import add_output_arguments, output_path, write_json  # noqa: E402


def load_version(package: str, quick: bool = False):
    """(simulate_frame, config, scene, tracer) of the benchmark frame built with ``package``'s own classes."""
    flash = importlib.import_module(package + ".systems.flash")
    settings = importlib.import_module(package + ".config.settings")
    scene_mod = importlib.import_module(package + ".geometry.scene")
    trace_mod = importlib.import_module(package + ".geometry.trace")
    src = bench_scene(32 if quick else 128)
    materials = [settings.BRDFSettings(reflectance=0.25),
                 settings.BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08)]
    scene = scene_mod.SceneGeometry(src.vertices_m, src.triangles, src.material_ids, materials, src.material_names)

    def config(threads):
        cfg = settings.SimulationConfig()
        ref = bench_config(quick)
        cfg.receiver.width_px, cfg.receiver.height_px = ref.receiver.width_px, ref.receiver.height_px
        cfg.receiver.subsamples = ref.receiver.subsamples
        cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad = ref.receiver.fov_x_rad, ref.receiver.fov_y_rad
        cfg.gate.n_bins, cfg.gate.bin_width_s, cfg.gate.gate_start_s = (ref.gate.n_bins, ref.gate.bin_width_s,
                                                                       ref.gate.gate_start_s)
        cfg.run.threads, cfg.run.save_waveforms = threads, False
        return cfg

    return flash.simulate_frame, config, scene, trace_mod.SceneTracer(scene)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--base", type=Path, help="another checkout whose core/ runs interleaved with this one")
    add_output_arguments(ap)
    args = ap.parse_args(argv)
    out = output_path(ap, args, "radiometry.json")
    if args.quick:
        args.repeat = 2
    versions = {"core": load_version("core", args.quick)}
    if args.base is not None:
        link_dir = Path(tempfile.mkdtemp())
        (link_dir / "core_base").symlink_to(args.base.resolve() / "core", target_is_directory=True)
        sys.path.insert(0, str(link_dir))
        versions["core_base"] = load_version("core_base", args.quick)
    pose = sensor_pose()
    size = "32x32 px x 2x2" if args.quick else "128x128 px x 4x4"
    report = {"benchmark": f"flash {size} sub-rays, points only: radiometry stage", "quick": args.quick,
              "repeat": args.repeat, "base": str(args.base)}
    for threads in (1, 2):
        times = {name: {"radiometry": [], "frame": []} for name in versions}
        last = {}
        for name, (simulate, config, scene, tracer) in versions.items():
            simulate(scene, pose, config(threads), tracer=tracer)  # compile or load the kernels
        for _ in range(args.repeat):
            for name, (simulate, config, scene, tracer) in versions.items():
                t = time.perf_counter()
                last[name] = simulate(scene, pose, config(threads), tracer=tracer)
                times[name]["frame"].append(time.perf_counter() - t)
                times[name]["radiometry"].append(last[name].stats["stage_times_s"]["radiometry"])
        entry = {name: {f"{k}_{f.__name__}_s": float(f(v)) for k, v in d.items() for f in (np.min, np.median)}
                 for name, d in times.items()}
        if "core_base" in versions:
            new, base = times["core"], times["core_base"]
            entry["ratio_new_to_base"] = {f"{k}_{f.__name__}": float(f(new[k]) / f(base[k]))
                                          for k in new for f in (np.min, np.median)}
            e_new, e_base = last["core"].energy_image, last["core_base"].energy_image
            lit = e_base > 0
            rel = np.abs(e_new[lit] - e_base[lit]) / e_base[lit]
            entry["energy_image_max_relative_difference"] = float(np.max(rel))
            entry["energy_image_zeros_equal"] = bool(np.array_equal(e_new[~lit], e_base[~lit]))
        report[f"threads_{threads}"] = entry
    print(json.dumps(report, indent=2))
    print(f"wrote {write_json(out, report)}")


if __name__ == "__main__":
    main()
