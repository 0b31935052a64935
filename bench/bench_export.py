#!/usr/bin/env python3
"""Time the Blender → simulator scene export (``ladar_addon.export.scene_geometry_from_depsgraph``).

    .venv/bin/python bench/bench_export.py [--triangles 1000000] [--out DIR | --update-committed] [--quick]

Cases: one quad grid of ~N triangles (fan path), the same grid triangulated (all-triangle path), an n-gon mesh
(Blender's loop_triangles fallback) and 1000 collection instances of a ~N/1000-triangle mesh.  Prints the best
of three exports per case and writes them to ``export.json`` in ``--out DIR`` (default runs/bench/;
``--update-committed``: bench/results/export.json).  Target: a 1M-triangle mesh well under a second.
``--quick``: 20 000 triangles per case (seconds).
"""
from __future__ import annotations

import argparse
import math
import time
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import blender_env  # noqa: E402
from bench_flash import best_of  # noqa: E402  (bench/ is the script folder, first on sys.path)
from benchio import add_output_arguments, output_path, write_json  # noqa: E402
from machine import machine_info  # noqa: E402


def _isolate(bpy, keep):
    for obj in list(bpy.context.scene.objects):
        obj.hide_viewport = obj.name not in keep


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--triangles", type=int, default=1_000_000)
    add_output_arguments(parser)
    args = parser.parse_args(argv)
    results = output_path(parser, args, "export.json")
    if args.quick:
        args.triangles = 20_000
    blender_env.isolate_user_resources()
    import bpy

    addon = blender_env.install_extension()
    export = addon.ladar_addon.export
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    side = int(math.ceil(math.sqrt(args.triangles / 2)))

    bpy.ops.mesh.primitive_grid_add(x_subdivisions=side + 1, y_subdivisions=side + 1, size=100)
    grid = bpy.context.object
    grid.name = "QuadGrid"
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=side + 1, y_subdivisions=side + 1, size=100)
    tri = bpy.context.object
    tri.name = "TriGrid"
    tri.modifiers.new("Triangulate", "TRIANGULATE")
    bpy.ops.mesh.primitive_circle_add(vertices=64, fill_type="NGON", radius=5)
    ngon = bpy.context.object
    ngon.name = "Ngon"
    ngon.modifiers.new("Array", "ARRAY").count = max(1, args.triangles // 62)

    proto = bpy.data.collections.new("Proto")
    small = int(math.ceil(math.sqrt(args.triangles / 1000 / 2)))
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=small + 1, y_subdivisions=small + 1, size=1)
    proto_obj = bpy.context.object
    for c in proto_obj.users_collection:
        c.objects.unlink(proto_obj)
    proto.objects.link(proto_obj)
    holders = []
    for i in range(1000):
        inst = bpy.data.objects.new(f"Inst{i:04d}", None)
        inst.instance_type = "COLLECTION"
        inst.instance_collection = proto
        inst.location = (i % 40 * 2.0, i // 40 * 2.0, 10.0)
        scene.collection.objects.link(inst)
        holders.append(inst.name)

    cases = [("quad grid (fan triangulation)", {"QuadGrid"}),
             ("triangulated grid (all-triangle path)", {"TriGrid"}),
             ("64-gons (loop_triangles fallback)", {"Ngon"}),
             ("1000 collection instances", set(holders))]
    print(f"Blender {bpy.app.version_string}, target ~{args.triangles:,} triangles per case")
    report = {"benchmark": "Blender scene export (scene_geometry_from_depsgraph), best of 3", "quick": args.quick,
              "blender": bpy.app.version_string, "target_triangles": args.triangles, "cases": {},
              "created": time.strftime("%Y-%m-%d"), "machine": machine_info()}
    for label, keep in cases:
        _isolate(bpy, keep)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        seconds, geometry = best_of(lambda: export.scene_geometry_from_depsgraph(depsgraph))
        print(f"{label:40s} {geometry.n_triangles:>10,d} triangles  {seconds * 1e3:8.1f} ms  "
              f"({geometry.n_triangles / seconds / 1e6:5.1f} M triangles/s)")
        report["cases"][label] = {"n_triangles": int(geometry.n_triangles), "export_s": seconds,
                                  "triangles_per_s": geometry.n_triangles / seconds}
    print(f"wrote {write_json(results, report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
