#!/usr/bin/env python3
"""Install a built extension zip into a clean ``bpy`` environment, enable it and simulate one frame.

    <clean venv>/bin/python scripts/smoke_extension.py dist/ladar_simulator-0.1.0-linux_x64.zip [--json out.json]

Run it with the Python of an environment that has ``bpy`` (and the numpy bpy needs) but none of the bundled
packages (scipy, embreex, OpenEXR, numba, llvmlite): the script checks that first.  It then

1. points Blender's user resources at a temporary folder (before ``import bpy``);
2. installs the zip the way a user does (``bpy.ops.extensions.package_install_files`` into the
   ``user_default`` repository, enabled on install) — Blender unpacks the zip's wheels for this platform;
3. checks that scipy, embreex, OpenEXR, numba and llvmlite now import from the extension's bundled wheels (not from the
   environment);
4. builds a scene (a camera 100 m from a 10 m plate, 16×16 pixels) and runs ``bpy.ops.ladar.simulate()``;
5. checks the run folder: every pixel has its echo at 100 m ± 1 cm, the EXR range image (written by the
   bundled OpenEXR) reads back, the range preview was drawn by the bundled matplotlib with a title, angle axes
   and a colour bar in metres, and the point cloud is in the .blend;
6. runs a two-point sweep with ``bpy.ops.ladar.sweep`` on a local Dask cluster of one worker process (the
   bundled dask.distributed; the worker imports the bundled packages and the shipped core) and checks its
   results table.

This proves the bundled wheels work with the Blender (and numpy) of that environment: CI runs it on bpy 4.2 LTS
with numpy 1.24.3 (``scripts/smoke_bpy.sh``).  Exit status 0 on success; a one-line reason otherwise.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

#: Import names of the bundled packages (scripts/build_extension.py BUNDLED; Dask's dependencies come with it).
BUNDLED = ("scipy", "embreex", "OpenEXR", "matplotlib", "contourpy", "cycler", "fontTools", "kiwisolver", "PIL",
           "pyparsing", "dateutil", "tzdata", "packaging", "numba", "llvmlite", "dask", "distributed")
EXTENSION_ID = "ladar_simulator"
REPO_MODULE = "user_default"


def fail(message: str) -> None:
    print(f"smoke: FAILED: {message}", flush=True)
    sys.exit(1)


def check_preview(png: Path) -> dict:
    """The run's range preview was drawn by the bundled matplotlib with a title, axes with units and a colour
    bar: its PNG text chunks (core.fileio.preview.save_figure) name them, and it has the figure's size."""
    from PIL import Image

    if not png.is_file():
        fail(f"no preview {png.name} in the run folder")
    with Image.open(png) as im:
        text, size = dict(im.text), im.size
    if text.get("Title") != "Range" or "Matplotlib" not in text.get("Software", ""):
        fail(f"{png.name} was not drawn by matplotlib with a title: {text}")
    for label in ("x: horizontal angle (mrad)", "y: vertical angle (mrad)", "y: m"):  # axes, colour bar
        if label not in text.get("Description", ""):
            fail(f"{png.name} lacks the label {label!r}: {text.get('Description')!r}")
    if size[0] != 640:
        fail(f"{png.name} is {size[0]}×{size[1]} px, not the 640 px wide figure")
    return {"png": png.name, "size": list(size), "title": text["Title"], "labels": text["Description"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("zip", type=Path, help="the extension zip for this platform")
    ap.add_argument("--json", type=Path, help="write a summary JSON here")
    args = ap.parse_args(argv)
    if not args.zip.is_file():
        fail(f"{args.zip} is not a file")

    present = [m for m in BUNDLED if importlib.util.find_spec(m) is not None]
    if present:
        fail(f"the environment is not clean: {', '.join(present)} importable before installing the extension")

    resources = Path(tempfile.mkdtemp(prefix="ladar_smoke_"))
    os.environ["BLENDER_USER_RESOURCES"] = str(resources)
    # the compiled kernels' cache must land in the per-user cache folder, never in the installed extension
    os.environ.pop("NUMBA_CACHE_DIR", None)
    os.environ.pop("LADAR_KERNEL_CACHE", None)
    os.environ["XDG_CACHE_HOME"] = str(resources / "user_cache")
    os.environ["LOCALAPPDATA"] = str(resources / "user_cache")
    t0 = time.perf_counter()
    try:
        import bpy  # noqa: I001 - bpy first: it puts Blender's modules (addon_utils) on the path
        import addon_utils
        import numpy as np

        print(f"smoke: Blender {bpy.app.version_string}, Python {sys.version.split()[0]}, numpy {np.__version__}",
              flush=True)
        bpy.ops.wm.read_homefile(use_empty=True)
        result = bpy.ops.extensions.package_install_files(filepath=str(args.zip.resolve()), repo=REPO_MODULE,
                                                          enable_on_install=True)
        if result != {"FINISHED"}:
            fail(f"package_install_files returned {result}")
        module = f"bl_ext.{REPO_MODULE}.{EXTENSION_ID}"
        loaded, enabled = addon_utils.check(module)
        if not (loaded and enabled):
            fail(f"{module} is not enabled after the install (loaded={loaded}, enabled={enabled})")
        install_s = time.perf_counter() - t0

        origins = {}
        for name in BUNDLED:
            mod = __import__(name)
            origins[name] = {"version": getattr(mod, "__version__", "?"), "file": str(Path(mod.__file__))}
            if str(resources) not in origins[name]["file"]:
                fail(f"{name} imported from {mod.__file__}, not from the extension's bundled wheels")

        scene = bpy.context.scene
        cam_data = bpy.data.cameras.new("Ladar")
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.lens = 0.5 * cam_data.sensor_width / math.tan(0.5 * 0.004)
        cam = bpy.data.objects.new("Ladar", cam_data)
        scene.collection.objects.link(cam)
        scene.camera = cam
        cam.ladar.receiver.width_px = 16
        cam.ladar.receiver.height_px = 16
        cam.ladar.receiver.subsamples = 2
        mesh = bpy.data.meshes.new("Plate")
        mesh.from_pydata([(-5, -5, 0), (5, -5, 0), (5, 5, 0), (-5, 5, 0)], [], [(0, 1, 2, 3)])
        plate = bpy.data.objects.new("Plate", mesh)
        plate.location = (0.0, 0.0, -100.0)
        scene.collection.objects.link(plate)
        out = resources / "runs"
        scene.ladar.output_dir = str(out)
        t1 = time.perf_counter()
        if bpy.ops.ladar.simulate() != {"FINISHED"}:
            fail("bpy.ops.ladar.simulate() did not finish")
        simulate_s = time.perf_counter() - t1
        # core/jit.py's entries are .nbc files (numba's own cache writes .nbi indexes beside them)
        kernel_cache = [p for p in (resources / "user_cache").rglob("*") if p.suffix in (".nbi", ".nbc")]
        in_extension = [str(p) for p in (resources / "extensions").rglob("*") if p.suffix in (".nbi", ".nbc")]
        if not kernel_cache or in_extension:
            fail(f"compiled kernels cached in the extension ({in_extension[:3]}) or not in the per-user folder "
                 f"({resources / 'user_cache'}: {len(kernel_cache)} files)")
        runs = [p for p in out.iterdir() if p.is_dir()]
        if len(runs) != 1:
            fail(f"expected one run folder in {out}, found {[p.name for p in runs]}")
        run = runs[0]
        with np.load(run / "points.npz") as pts:
            range_m = pts["range_m"]
        if len(range_m) != 256 or np.abs(range_m - 100.0).max() > 0.01:
            fail(f"{len(range_m)} points, range {range_m.min() if len(range_m) else 'n/a'} … "
                 f"{range_m.max() if len(range_m) else 'n/a'} m (want 256 at 100 m ± 1 cm)")
        import OpenEXR
        with OpenEXR.File(str(run / "range.exr")) as f:
            image = next(iter(f.channels().values())).pixels
        if image.shape != (16, 16) or np.abs(image - 100.0).max() > 0.01:
            fail(f"range.exr {image.shape}, not 16×16 at 100 m")
        preview = check_preview(run / "range.png")
        clouds = [o for o in bpy.data.objects if o.type == "MESH" and o.name.startswith(run.name)]
        if not clouds or len(clouds[0].data.vertices) != 256:
            fail(f"the point cloud object of {run.name} is missing or incomplete")
        sweep_file = resources / "sweep.toml"
        sweep_file.write_text('sweep_version = 1\n[axes]\n"laser.pulse_energy_j" = [1e-4, 1e-3]\n')
        t1 = time.perf_counter()
        if bpy.ops.ladar.sweep(filepath=str(sweep_file), out_dir=str(resources / "sweep"), workers=1) != {"FINISHED"}:
            fail("bpy.ops.ladar.sweep() did not finish")
        sweep_s = time.perf_counter() - t1
        import csv
        with open(resources / "sweep" / "results.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        if [(r["status"], r["pixels_with_echo"]) for r in rows] != [("done", "256")] * 2:
            fail(f"sweep results {[(r['status'], r['pixels_with_echo'], r['error']) for r in rows]}")
        summary = {"ok": True, "blender": bpy.app.version_string, "python": sys.version.split()[0],
                   "numpy": np.__version__, "zip": args.zip.name, "bundled": origins, "points": int(len(range_m)),
                   "range_m_mean": float(range_m.mean()), "preview": preview, "install_s": round(install_s, 2),
                   "simulate_s (first run: compiles the kernels)": round(simulate_s, 2),
                   "kernel_cache_files": len(kernel_cache), "sweep_s": round(sweep_s, 2)}
        print("smoke: OK " + json.dumps(summary), flush=True)
        if args.json:
            args.json.write_text(json.dumps(summary, indent=2))
    finally:
        shutil.rmtree(resources, ignore_errors=True)
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    # bpy's exit handlers may touch the removed user folder: leave without them.
    os._exit(code)
