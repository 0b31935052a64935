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

``gated_board.blend`` — burst illumination / gated viewing of a reference board at 1 km (paper §4, §5.1):

* sensor "Gated camera": 96×64 pixels, 8 × 5.3 mrad, 532 nm, 10 ns pulse of 20 mJ flooding the field of view,
  a 20 ns gate swept in 30 slices of 3.34 ns (0.5 m) from 992 m to 1007 m, range by the slice centroid;
* the board: three 1 m × 2 m panels (10 %, 50 %, glossy paint) at 1000 m, a staircase of four blocks at
  996–1004 m beside it, ground;
* atmosphere: visibility 15 km, Cn² = 5·10⁻¹⁵ m^-2/3 (scintillation per slice, wander, long-exposure blur).

``forest_scan.blend`` — an airborne time-of-flight scanner over a vehicle in a forest (paper §2.1):

* sensor "Scanner" 120 m above the ground, flying north (+Y) at 24 m/s (animated, frames 1–25 = 1 s), an
  oscillating mirror ±25° across track at 50 Hz, 100 kHz pulses of 3 ns at 1064 nm, 1 mrad beam sampled by 19
  sub-rays, range gate 95–145 m with 0.5 ns bins;
* a 160 m × 160 m rolling ground, 60 trees (trunks and crowns of loose leaves, so pulses give several echoes),
  a car-sized vehicle in a clearing;
* every pulse's waveform saved (``waveforms.npy``, 100,000 pulses × 668 bins, 255 MB a run): the waveform view
  shows by default the pulse with the most echoes, one through a tree crown.

``aircraft_profile.blend`` — a range profiler on an aircraft-like target at 2 km (paper §5.3, Fig. 13):

* sensor "Profiler": one detector with a 12 mrad field of view, 256 × 256 sub-rays, uniform flood beam,
  1 ns pulse, 0.2 ns bins from 1985 m to 2015 m;
* an aircraft (fuselage with a nose cone, wings, tailplane and fin), seen 35° off its nose.

``fog_vehicle.blend`` — a vehicle 60 m away seen through fog of 200 m visibility (issue 30, docs/atmosphere.md):

* the vehicle: a box 4.5 m × 1.8 m × 1.5 m side-on at 60 m (Lambertian 35 %), a ground plane;
* atmosphere: ``weather = fog``, visibility 200 m (Kim; α = 0.0196 /m at 1064 nm, β = α/18 sr), the default
  geometric overlap (5 cm transmitter–receiver offset);
* sensor "Flash" (active): 48×32 pixels, 8° × 5.3°, 3×3 sub-rays, 5 ns pulse, gate 0–90 m in 1 ns bins, 3 echoes above 0.2 % of
  the pixel's strongest (the vehicle's echo is ~2 % of the near-range clutter's);
* sensor "Scanner": a raster of 30 lines × 40 pulses over 0.15 rad × 0.08 rad, 1 mrad beam, 3 ns pulse, gate
  0–90 m in 0.5 ns bins (``--sensor Scanner``).

Options: ``--out DIR`` (default: ``sample_blends/``), ``--only NAME`` (flash_demo, gated_board, forest_scan,
aircraft_profile, fog_vehicle).

The committed .blend files were built before the panels stored times in ns (issue 27): they hold these
settings in the old SI properties, which the add-on reads bit for bit (docs/blender.md, "Units and labels in the
panels"), so the README's runs of them are unchanged.  The settings those properties held are set here at single
precision (``_set_single``), so a rebuild gives the same values bit for bit (tests/addon/test_sample_blend.py).
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
    scene = _new_scene(bpy, "Flash demo", (64, 64))
    root = scene.collection
    mats = _materials(bpy, MATERIALS)

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
    ladar.laser.pulse_shape = "gaussian"
    _set_single(scene, cam, {"laser.pulse_fwhm_s": 5e-9})
    _set_single(scene, cam, {"gate.gate_start_s": 2 * GATE_NEAR_M / SPEED_OF_LIGHT_M_S})
    _set_single(scene, cam, {"gate.bin_width_s": BIN_S})
    ladar.gate.n_bins = int(math.ceil(2 * (GATE_FAR_M - GATE_NEAR_M) / SPEED_OF_LIGHT_M_S / BIN_S))
    scene.ladar.sensor = cam
    scene.ladar.output_dir = "//../runs/"
    scene.ladar.seed = 1
    scene.ladar.point_radius = 0.04
    _set_si(scene, cam, {"laser.wavelength_m": 1.064e-6})

    path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True)


def _materials(bpy, table):
    mats = {}
    for name, (colour, brdf) in table.items():
        mat = bpy.data.materials.new(name)
        mat.diffuse_color = colour
        mat.ladar_brdf.enabled = True
        for key, value in brdf.items():
            setattr(mat.ladar_brdf, key, value)
        mats[name] = mat
    return mats


def _camera(bpy, name, fov_x_rad, fov_y_rad, location, rotation):
    cam_data = bpy.data.cameras.new(name)
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.lens = 0.5 * cam_data.sensor_width / math.tan(0.5 * fov_x_rad)
    cam_data.clip_start, cam_data.clip_end = 1.0, 5000.0
    cam = bpy.data.objects.new(name, cam_data)
    cam.location = location
    cam.rotation_euler = rotation
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    return cam


def _new_scene(bpy, name, resolution):
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.name = name
    scene.unit_settings.system = "METRIC"
    scene.frame_start = scene.frame_end = scene.frame_current = 1
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    return scene


def _set_si(scene, cam, values: dict) -> None:
    """Settings in SI units through the add-on's Python API (``ladar_addon.blend_config.set_settings``): several
    properties store scaled values (nm, ×1e-14 m^-2/3, Blender units), never write SI values into them."""
    import importlib

    importlib.import_module(f"{blender_env.ADDON_MODULE}.ladar_addon.blend_config").set_settings(scene, cam, values)


def _set_single(scene, cam, values: dict) -> None:
    """Settings in SI units at single precision (the shortest decimal of their float32): what the samples held
    when these settings were stored in SI single-precision properties, so a rebuild gives the same values."""
    import numpy as np

    _set_si(scene, cam, {path: float(str(np.float32(value))) for path, value in values.items()})


def _save(bpy, scene, sensor, path: Path):
    scene.ladar.sensor = sensor
    scene.ladar.output_dir = "//../runs/"
    scene.ladar.seed = 1
    path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True)


def build_gated_board(bpy, path: Path) -> None:
    scene = _new_scene(bpy, "Gated viewing at 1 km", (96, 64))
    root = scene.collection
    mats = _materials(bpy, {k: MATERIALS[k] for k in ("Lambertian 10%", "Lambertian 50%", "Steinvall paint",
                                                      "Ground", "Box")})
    ground_z = -1.5
    _mesh_object(bpy, "Ground", [(-30, 900, 0), (30, 900, 0), (30, 1100, 0), (-30, 1100, 0)], [(0, 1, 2, 3)],
                 root, (0.0, 0.0, ground_z), (mats["Ground"],))
    xs = [-2.5, -1.5, -0.5, 0.5]
    verts = [(x, 0.0, z) for z in (0.0, 2.0) for x in xs]
    faces = [(i, i + 1, i + 5, i + 4) for i in range(3)]
    _mesh_object(bpy, "Board panels", verts, faces, root, (0.0, 1000.0, ground_z + 0.3),
                 (mats["Lambertian 10%"], mats["Lambertian 50%"], mats["Steinvall paint"]), [0, 1, 2])
    for i, y in enumerate((996.0, 998.5, 1001.5, 1004.0)):  # a staircase: 0.6 m wide blocks, 2.5–3 m apart
        _box(bpy, f"Step {i + 1}", (0.6, 0.6, 2.2), root, (1.3 + 0.7 * i, y, ground_z), mats["Box"])
    fov_x, fov_y = 8e-3, 8e-3 * 64 / 96
    cam = _camera(bpy, "Gated camera", fov_x, fov_y, (0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0))
    ladar = cam.ladar
    ladar.system_type = "gated"
    ladar.receiver.width_px, ladar.receiver.height_px = 96, 64
    ladar.receiver.subsamples = 3
    _set_single(scene, cam, {"laser.pulse_energy_j": 0.02})
    _set_single(scene, cam, {"laser.pulse_fwhm_s": 10e-9})
    _set_single(scene, cam, {"gated.gate_width_s": 20e-9})
    _set_single(scene, cam, {"gated.delay_step_s": 2 * 0.5 / SPEED_OF_LIGHT_M_S})
    ladar.gated.n_slices = 30
    _set_single(scene, cam, {"gated.first_delay_s": 2 * 992.5 / SPEED_OF_LIGHT_M_S - 0.5 * 20e-9})
    ladar.gated.range_method = "centroid"
    _set_si(scene, cam, {"receiver.aperture_diameter_m": 0.1, "laser.wavelength_m": 532e-9,
                         "atmosphere.visibility_m": 15000.0, "atmosphere.cn2_m_23": 5e-15})
    _save(bpy, scene, cam, path)


def _tree(rng, x, y, z, height):
    """A trunk (8-sided prism) and a crown of loose leaf triangles: (verts, faces, is_leaf per face)."""
    verts, faces, leaf = [], [], []
    r, trunk_h = 0.15 + 0.02 * height / 10, 0.45 * height
    ring = [(x + r * math.cos(a), y + r * math.sin(a)) for a in (2 * math.pi * k / 8 for k in range(8))]
    verts += [(px, py, z) for px, py in ring] + [(px, py, z + trunk_h) for px, py in ring]
    faces += [(k, (k + 1) % 8, 8 + (k + 1) % 8, 8 + k) for k in range(8)]
    leaf += [False] * 8
    centre = (x, y, z + 0.65 * height)
    radii = (0.22 * height, 0.22 * height, 0.32 * height)
    n_leaves = 220
    pos = rng.normal(size=(n_leaves, 3))
    pos /= (abs(pos) ** 2).sum(axis=1, keepdims=True) ** 0.5
    pos *= rng.uniform(0, 1, (n_leaves, 1)) ** (1 / 3)
    for p in pos:
        c = [centre[i] + p[i] * radii[i] for i in range(3)]
        e1, e2 = rng.normal(size=3), rng.normal(size=3)
        e1 = 0.35 * e1 / (e1 @ e1) ** 0.5
        e2 = 0.35 * e2 / (e2 @ e2) ** 0.5
        base = len(verts)
        verts += [tuple(c), tuple(c + e1), tuple(c + e2)]
        faces.append((base, base + 1, base + 2))
        leaf.append(True)
    return verts, faces, leaf


def _ground_height(x, y):
    return 1.5 * math.sin(x / 23.0) * math.cos(y / 31.0)


def build_forest_scan(bpy, path: Path) -> None:
    import numpy as np

    scene = _new_scene(bpy, "Vehicle in a forest", (64, 64))
    scene.frame_end = 25
    scene.render.fps = 24
    root = scene.collection
    mats = _materials(bpy, {
        "Ground": MATERIALS["Ground"],
        "Bark": ((0.3, 0.2, 0.1, 1.0), {"model": "lambertian", "reflectance": 0.25}),
        "Leaves": ((0.1, 0.5, 0.1, 1.0), {"model": "lambertian", "reflectance": 0.45}),  # NIR-bright foliage
        "Car paint": MATERIALS["Steinvall paint"],
        "Glass": ((0.1, 0.1, 0.2, 1.0), {"model": "steinvall", "specular_a": 0.5, "slope_s": 0.05,
                                         "diffuse_b": 0.005, "diffuse_m": 1.0}),
    })
    n = 48
    grid = [(-80 + 160 * i / n, -80 + 160 * j / n) for j in range(n + 1) for i in range(n + 1)]
    verts = [(x, y, _ground_height(x, y)) for x, y in grid]
    faces = [(j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i + 1, (j + 1) * (n + 1) + i)
             for j in range(n) for i in range(n)]
    _mesh_object(bpy, "Ground", verts, faces, root, materials=(mats["Ground"],))
    rng = np.random.default_rng(7)
    tv, tf, tl = [], [], []
    placed = 0
    while placed < 60:
        x, y = rng.uniform(-70, 70, 2)
        if abs(x) < 9 and abs(y) < 9:  # the clearing around the vehicle
            continue
        v, f, leaf = _tree(rng, x, y, _ground_height(x, y), rng.uniform(9, 16))
        tf += [tuple(k + len(tv) for k in face) for face in f]
        tv += v
        tl += leaf
        placed += 1
    _mesh_object(bpy, "Trees", tv, tf, root, materials=(mats["Bark"], mats["Leaves"]),
                 face_materials=[1 if is_leaf else 0 for is_leaf in tl])
    z0 = _ground_height(0.0, 0.0)
    car = bpy.data.collections.new("Vehicle")
    root.children.link(car)
    _box(bpy, "Vehicle body", (1.8, 4.5, 0.9), car, (0.0, 0.0, z0 + 0.3), mats["Car paint"])
    _box(bpy, "Vehicle cabin", (1.6, 2.2, 0.6), car, (0.0, -0.3, z0 + 1.2), mats["Glass"])
    cam = _camera(bpy, "Scanner", math.radians(50.0), math.radians(50.0), (0.0, -12.0, 120.0), (0.0, 0.0, 0.0))
    # fly north at 24 m/s: frames 1 → 25 (1 s); linear keys so the speed is constant
    bpy.context.preferences.edit.keyframe_new_interpolation_type = "LINEAR"
    cam.location = (0.0, -12.0, 120.0)
    cam.keyframe_insert("location", frame=1)
    cam.location = (0.0, 12.0, 120.0)
    cam.keyframe_insert("location", frame=25)
    cam.location = (0.0, -12.0, 120.0)
    ladar = cam.ladar
    ladar.system_type = "scanner"
    _set_single(scene, cam, {"laser.pulse_fwhm_s": 3e-9})
    _set_single(scene, cam, {"laser.pulse_energy_j": 50e-6})
    _set_single(scene, cam, {"laser.beam_divergence_rad": 1e-3})
    ladar.laser.divergence_fills_fov = False
    sc = ladar.scanner
    sc.pattern = "oscillating"
    _set_single(scene, cam, {"scanner.pulse_rate_hz": 100_000.0})
    sc.scan_rate_hz = 50.0
    sc.scan_width_rad = math.radians(50.0)
    sc.duration_s = 1.0
    sc.beam_subray_rings = 2
    sc.motion_samples_per_s = 200.0
    _set_single(scene, cam, {"gate.gate_start_s": 2 * 95.0 / SPEED_OF_LIGHT_M_S})
    _set_single(scene, cam, {"gate.bin_width_s": 0.5e-9})
    ladar.gate.n_bins = int(math.ceil(2 * 50.0 / SPEED_OF_LIGHT_M_S / 0.5e-9))
    ladar.detection.max_echoes = 5
    ladar.run.save_waveforms = True  # every pulse's waveform (255 MB a run), for the waveform view (issue 27)
    _set_si(scene, cam, {"laser.wavelength_m": 1.064e-6, "receiver.aperture_diameter_m": 0.08})
    _save(bpy, scene, cam, path)


def build_aircraft_profile(bpy, path: Path) -> None:
    scene = _new_scene(bpy, "Aircraft range profile", (64, 64))
    root = scene.collection
    mats = _materials(bpy, {"Aircraft paint": ((0.7, 0.7, 0.75, 1.0),
                                               {"model": "steinvall", "specular_a": 0.05, "slope_s": 0.2,
                                                "diffuse_b": 0.08, "diffuse_m": 1.0})})
    verts, faces = [], []
    # fuselage along +X: a 16-sided tube 14 m long, radius 1 m, with a 3 m nose cone at +X
    sides, r = 16, 1.0
    for x in (-7.0, 7.0):
        verts += [(x, r * math.cos(2 * math.pi * k / sides), r * math.sin(2 * math.pi * k / sides))
                  for k in range(sides)]
    faces += [(k, (k + 1) % sides, sides + (k + 1) % sides, sides + k) for k in range(sides)]
    tip = len(verts)
    verts.append((10.0, 0.0, 0.0))
    faces += [(sides + k, sides + (k + 1) % sides, tip) for k in range(sides)]
    faces.append(tuple(range(sides - 1, -1, -1)))  # flat tail cap

    def plate(points):
        base = len(verts)
        verts.extend(points)
        faces.append(tuple(range(base, base + len(points))))

    plate([(1.5, -8.0, 0.0), (3.5, -8.0, 0.0), (4.0, 8.0, 0.0), (2.0, 8.0, 0.0)])          # wings (swept)
    plate([(-7.0, -3.0, 0.3), (-5.8, -3.0, 0.3), (-5.5, 3.0, 0.3), (-6.7, 3.0, 0.3)])      # tailplane
    plate([(-7.0, 0.0, 0.8), (-5.5, 0.0, 0.8), (-6.2, 0.0, 3.5), (-7.0, 0.0, 3.5)])        # fin
    obj = _mesh_object(bpy, "Aircraft", verts, faces, root, (0.0, 2000.0, 0.0), (mats["Aircraft paint"],))
    obj.rotation_euler = (0.0, 0.0, math.radians(-90.0 - 35.0))  # nose towards the sensor, 35° off
    cam = _camera(bpy, "Profiler", 12e-3, 12e-3, (0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0))
    ladar = cam.ladar
    ladar.system_type = "profiler"
    ladar.receiver.width_px = ladar.receiver.height_px = 1
    ladar.receiver.fov_x_rad = ladar.receiver.fov_y_rad = 12e-3
    ladar.receiver.subsamples = 256
    ladar.laser.beam_profile = "uniform"
    _set_single(scene, cam, {"laser.pulse_fwhm_s": 1e-9})
    _set_single(scene, cam, {"laser.pulse_energy_j": 0.1})
    _set_single(scene, cam, {"gate.gate_start_s": 2 * 1985.0 / SPEED_OF_LIGHT_M_S})
    _set_single(scene, cam, {"gate.bin_width_s": 0.2e-9})
    ladar.gate.n_bins = int(math.ceil(2 * 30.0 / SPEED_OF_LIGHT_M_S / 0.2e-9))
    ladar.detection.max_echoes = 8
    _set_si(scene, cam, {"laser.wavelength_m": 1.064e-6, "receiver.aperture_diameter_m": 0.2})
    _save(bpy, scene, cam, path)


def build_fog_vehicle(bpy, path: Path) -> None:
    scene = _new_scene(bpy, "Vehicle in fog", (48, 32))
    root = scene.collection
    mats = _materials(bpy, {k: MATERIALS[k] for k in ("Ground", "Box")})
    ground_z = -1.5
    _mesh_object(bpy, "Ground", [(-30, 0.5, 0), (30, 0.5, 0), (30, 120, 0), (-30, 120, 0)], [(0, 1, 2, 3)], root,
                 (0.0, 0.0, ground_z), (mats["Ground"],))
    _box(bpy, "Vehicle", (4.5, 1.8, 1.5), root, (0.0, 60.0, ground_z), mats["Box"])
    gate = {"gate.gate_start_s": 0.0}
    fov_x = math.radians(8.0)
    flash = _camera(bpy, "Flash", fov_x, fov_x * 32 / 48, (0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0))
    ladar = flash.ladar
    ladar.system_type = "flash"
    ladar.receiver.width_px, ladar.receiver.height_px = 48, 32
    ladar.receiver.subsamples = 3
    ladar.detection.max_echoes = 3
    ladar.detection.relative_threshold = 0.002  # the vehicle's echo is ~2 % of the near-range clutter's
    ladar.gate.n_bins = 600
    _set_si(scene, flash, {**gate, "gate.bin_width_s": 1e-9, "laser.pulse_fwhm_s": 5e-9,
                           "laser.wavelength_m": 1.064e-6})
    scanner = _camera(bpy, "Scanner", 0.15, 0.08, (0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0))
    ladar = scanner.ladar
    ladar.system_type = "scanner"
    ladar.laser.divergence_fills_fov = False
    sc = ladar.scanner
    sc.pattern = "raster"
    sc.n_lines = 30
    sc.scan_rate_hz = 200.0
    sc.beam_subray_rings = 2
    sc.duration_s = 0.0
    ladar.detection.max_echoes = 3
    ladar.detection.relative_threshold = 0.002
    ladar.gate.n_bins = 1200
    ladar.run.save_waveforms = False
    _set_si(scene, scanner, {**gate, "gate.bin_width_s": 0.5e-9, "laser.pulse_fwhm_s": 3e-9,
                             "laser.beam_divergence_rad": 1e-3, "scanner.pulse_rate_hz": 8000.0,
                             "scanner.scan_width_rad": 0.15, "scanner.scan_height_rad": 0.08,
                             "laser.wavelength_m": 1.064e-6})
    scene.ladar_atmosphere.weather = "fog"
    _set_si(scene, flash, {"atmosphere.visibility_m": 200.0})
    _save(bpy, scene, flash, path)


BUILDERS = {"flash_demo": build_flash_demo, "gated_board": build_gated_board, "forest_scan": build_forest_scan,
            "aircraft_profile": build_aircraft_profile, "fog_vehicle": build_fog_vehicle}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=HERE, help="folder for the .blend files")
    parser.add_argument("--only", choices=sorted(BUILDERS), action="append", help="build only this scene")
    args = parser.parse_args(argv)
    blender_env.isolate_user_resources()
    import bpy

    blender_env.install_extension()
    for name in args.only or BUILDERS:
        path = (args.out / f"{name}.blend").resolve()
        BUILDERS[name](bpy, path)
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
