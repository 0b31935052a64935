#!/usr/bin/env python3
"""Build the sample scenes (deterministic, re-runnable):  ``.venv/bin/python sample_blends/build_samples.py``

``flash_demo.blend`` — a 3D flash ladar at the origin, 3 m above flat ground, looking north (+Y) at a small
range 170–240 m away:

* sensor "Ladar": 64×64 pixels, 2° field of view, 4×4 sub-rays per pixel, 1064 nm, 5 ns Gaussian pulse,
  range gate 100–350 m (1 ns bins);
* a reference board at 200 m with three 1 m × 2 m panels: Lambertian 10 %, Lambertian 50 % and a Steinvall
  glossy paint (A = 0.05 sr⁻¹, s = 0.2, B = 0.08 sr⁻¹, m = 1);
* two boxes at 185 m and 230 m;
* three instances of the collection "Bollard" (so the export's instancing path is exercised);
* a ground plane (Lambertian 20 %).

Options: ``--out PATH`` (default: ``sample_blends/flash_demo.blend``).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "scripts"))
import blender_env  # noqa: E402

SPEED_OF_LIGHT_M_S = 299_792_458.0
SENSOR_HEIGHT_M = 3.0  # the sensor is at the origin; the ground is 3 m below it
FOV_RAD = math.radians(2.0)
TILT_RAD = math.radians(0.5)  # look slightly down, so the ground fills the bottom rows
GATE_NEAR_M, GATE_FAR_M, BIN_S = 100.0, 350.0, 1e-9

MATERIALS = {  # name: (viewport colour, ladar BRDF settings)
    "Lambertian 10%": ((0.1, 0.1, 0.1, 1.0), {"model": "lambertian", "reflectance": 0.1}),
    "Lambertian 50%": ((0.5, 0.5, 0.5, 1.0), {"model": "lambertian", "reflectance": 0.5}),
    "Steinvall paint": ((0.6, 0.1, 0.1, 1.0), {"model": "steinvall", "specular_a": 0.05, "slope_s": 0.2,
                                                "diffuse_b": 0.08, "diffuse_m": 1.0}),
    "Ground": ((0.2, 0.25, 0.15, 1.0), {"model": "lambertian", "reflectance": 0.2}),
    "Box": ((0.35, 0.3, 0.25, 1.0), {"model": "lambertian", "reflectance": 0.35}),
    "Bollard": ((0.8, 0.7, 0.1, 1.0), {"model": "lambertian", "reflectance": 0.6}),
}


def _mesh_object(bpy, name, verts, faces, collection, location=(0.0, 0.0, 0.0), materials=(),
                 face_materials=None):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    for mat in materials:
        mesh.materials.append(mat)
    if face_materials is not None:
        mesh.polygons.foreach_set("material_index", face_materials)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    collection.objects.link(obj)
    return obj


def _box(bpy, name, size, collection, location, material):
    """An axis-aligned box standing on its base (origin at the centre of the base)."""
    sx, sy, sz = (0.5 * size[0], 0.5 * size[1], size[2])
    verts = [(-sx, -sy, 0), (sx, -sy, 0), (sx, sy, 0), (-sx, sy, 0),
             (-sx, -sy, sz), (sx, -sy, sz), (sx, sy, sz), (-sx, sy, sz)]
    faces = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    return _mesh_object(bpy, name, verts, faces, collection, location, (material,))


def build_flash_demo(bpy, path: Path) -> None:
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.name = "Flash demo"
    scene.unit_settings.system = "METRIC"
    scene.frame_start = scene.frame_end = scene.frame_current = 1
    scene.render.resolution_x = scene.render.resolution_y = 64
    scene.render.resolution_percentage = 100
    root = scene.collection

    mats = {}
    for name, (colour, brdf) in MATERIALS.items():
        mat = bpy.data.materials.new(name)
        mat.diffuse_color = colour
        mat.ladar_brdf.enabled = True
        for key, value in brdf.items():
            setattr(mat.ladar_brdf, key, value)
        mats[name] = mat

    ground_z = -SENSOR_HEIGHT_M
    _mesh_object(bpy, "Ground", [(-40, 90, 0), (40, 90, 0), (40, 380, 0), (-40, 380, 0)], [(0, 1, 2, 3)], root,
                 (0.0, 0.0, ground_z), (mats["Ground"],))

    # Reference board at 200 m: three 1 m × 2 m panels facing the sensor (normal −Y), 0.2 m above the ground.
    board = bpy.data.collections.new("Reference board")
    root.children.link(board)
    xs = [-1.5, -0.5, 0.5, 1.5]
    verts = [(x, 0.0, z) for z in (0.0, 2.0) for x in xs]
    faces = [(i, i + 1, i + 5, i + 4) for i in range(3)]  # wound so the normal points to −Y (the sensor)
    _mesh_object(bpy, "Board panels", verts, faces, board, (0.0, 200.0, ground_z + 0.2),
                 (mats["Lambertian 10%"], mats["Lambertian 50%"], mats["Steinvall paint"]), [0, 1, 2])
    _box(bpy, "Board stand", (3.2, 0.1, 0.2), board, (0.0, 200.05, ground_z), mats["Box"])

    targets = bpy.data.collections.new("Targets")
    root.children.link(targets)
    _box(bpy, "Box near", (1.5, 1.5, 1.5), targets, (-2.6, 185.0, ground_z), mats["Box"])
    _box(bpy, "Box far", (2.0, 2.0, 2.5), targets, (2.8, 230.0, ground_z), mats["Box"])

    # A collection instanced three times (its own collection is not linked to the scene).
    bollard = bpy.data.collections.new("Bollard")
    _box(bpy, "Bollard post", (0.3, 0.3, 1.2), bollard, (0.0, 0.0, 0.0), mats["Bollard"])
    for i, (x, y) in enumerate([(-3.4, 175.0), (3.3, 195.0), (-0.8, 240.0)]):
        inst = bpy.data.objects.new(f"Bollard.{i:03d}", None)
        inst.instance_type = "COLLECTION"
        inst.instance_collection = bollard
        inst.location = (x, y, ground_z)
        inst.empty_display_size = 0.5
        targets.objects.link(inst)

    cam_data = bpy.data.cameras.new("Ladar")
    cam_data.sensor_fit = "AUTO"
    cam_data.lens = 0.5 * cam_data.sensor_width / math.tan(0.5 * FOV_RAD)
    cam_data.clip_start, cam_data.clip_end = 1.0, 1000.0
    cam = bpy.data.objects.new("Ladar", cam_data)
    cam.location = (0.0, 0.0, 0.0)
    cam.rotation_euler = (math.pi / 2 - TILT_RAD, 0.0, 0.0)  # camera −Z → world +Y, tilted down
    root.objects.link(cam)
    scene.camera = cam

    ladar = cam.ladar
    ladar.system_type = "flash"
    ladar.receiver.width_px = ladar.receiver.height_px = 64
    ladar.receiver.subsamples = 4
    ladar.laser.wavelength_m = 1064.0  # stored in nm
    ladar.laser.pulse_shape = "gaussian"
    ladar.laser.pulse_fwhm_s = 5e-9
    ladar.gate.gate_start_s = 2 * GATE_NEAR_M / SPEED_OF_LIGHT_M_S
    ladar.gate.bin_width_s = BIN_S
    ladar.gate.n_bins = int(math.ceil(2 * (GATE_FAR_M - GATE_NEAR_M) / SPEED_OF_LIGHT_M_S / BIN_S))
    scene.ladar.sensor = cam
    scene.ladar.output_dir = "//../runs/"
    scene.ladar.seed = 1
    scene.ladar.point_radius = 0.04

    path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=HERE / "flash_demo.blend")
    args = parser.parse_args(argv)
    blender_env.isolate_user_resources()
    import bpy

    blender_env.install_extension()
    build_flash_demo(bpy, args.out.resolve())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
