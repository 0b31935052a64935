"""Several frames in one run (paper §2.3, §5.2, Fig. 12): the sensor moves between frames and every frame's
points are registered in one world coordinate system.

The run folder holds one ordinary run folder per frame (``frame_0001/`` …), the merged point cloud of all frames
(``points_merged.ply`` / ``.npz``, world coordinates, with a ``frame`` attribute) and a ``metadata.json`` listing
the frames.  It is assembled in a hidden sibling folder and renamed into place at the end, so a failed or cancelled
sequence leaves nothing behind; the folder's name is claimed when the sequence starts (fileio.staging).  When consecutive frames hand over the same SceneGeometry object (static
geometry) the ray-tracing acceleration structure is built once and reused.
"""
from __future__ import annotations

import json
import operator
import time

import numpy as np

from .errors import ConfigError
from .config.settings import SimulationConfig
from .config.validate import validate_config
from .engine.memory import check_memory
from .config.files import config_to_dict
from .errors import Cancelled
from .run import run_metadata, simulate
from .fileio.run_folder import (ProductFiles, json_default, naming, run_figures, run_warnings, software_versions,
                                write_ply, write_run_files)
from .fileio.staging import claim_run_dir
from .heap import release_freed_blocks
from .geometry.trace import SceneTracer
from .fileio.las import las_run_facts, write_las


def merge_points(point_sets: list[dict]) -> dict:
    """Concatenate per-frame point dicts (the attributes every frame has)."""
    point_sets = [p for p in point_sets if p]
    if not point_sets:
        return {}
    keys = [k for k in point_sets[0] if all(k in p for p in point_sets)]
    return {k: np.concatenate([p[k] for p in point_sets]) for k in keys}


def unify_material_ids(point_sets: list[dict], names_per_frame: list[list]) -> list:
    """Renumber each frame's ``material_id`` into one list of material names (frames whose scenes list their
    materials differently share one numbering); returns that list."""
    names = []
    for pts, frame_names in zip(point_sets, names_per_frame):
        index = []
        for name in frame_names:
            if name not in names:
                names.append(name)
            index.append(names.index(name))
        if "material_id" in pts and len(frame_names):
            mid = pts["material_id"]
            pts["material_id"] = np.where(mid >= 0, np.asarray(index)[np.maximum(mid, 0)], mid).astype(mid.dtype)
    return names


def run_sequence(frames, scene_for_frame, pose_for_frame, config: SimulationConfig, out_dir, *,
                 overwrite: bool = False, trajectory_for_frame=None, start_time_for_frame=None,
                 extra_metadata: dict | None = None, progress=None, cancel=None):
    """Simulate ``frames`` (an iterable of frame numbers) and write one sequence run folder.

    scene_for_frame(frame) -> SceneGeometry (return the same object for static geometry: its BVH is reused),
    pose_for_frame(frame) -> 4×4 sensor→world matrix, trajectory_for_frame(frame) -> Trajectory or None
    (scanner motion within a frame), start_time_for_frame(frame) -> seconds (the scanner's GPS-style time).
    Returns (run_path, list of per-frame stats), each frame's with its summary ``figures``
    (core.fileio.run_folder.run_figures: the terminal summary and Blender's report add them up over the frames).
    """
    try:  # whole numbers only: int() would truncate 1.5 to frame 1
        frames = [operator.index(f) for f in frames]
    except TypeError:
        raise ConfigError("frames", frames, "an iterable of whole frame numbers") from None
    if not frames:
        raise ConfigError("frames", frames, "at least one frame")
    if len(set(frames)) != len(frames):
        raise ConfigError("frames", frames, "distinct frame numbers")
    validate_config(config)  # a SimulationConfig (not None or a dict), before the folder is claimed
    check_memory(config, frames=len(frames))  # every frame's work within run.max_work_s, before the first one
    try:
        with claim_run_dir(out_dir, if_exists="replace" if overwrite else "stop") as claim:
            tmp = claim.work
            tmp.mkdir()
            t_wall = time.perf_counter()
            tracer, bvh_builds, all_stats, point_sets, units = None, 0, [], [], {}
            for i, frame in enumerate(frames):
                if cancel is not None and cancel():
                    raise Cancelled()
                scene = scene_for_frame(frame).with_overrides(config.materials)
                if tracer is None or not tracer.serves(scene):  # static geometry keeps the previous frame's BVH
                    scene.check()
                    tracer = SceneTracer(scene)
                    bvh_builds += 1
                frame_progress = None
                if progress is not None:
                    def frame_progress(fraction, text, _i=i, _f=frame):
                        progress((_i + fraction) / len(frames), f"frame {_f} ({_i + 1}/{len(frames)}): {text}")
                traj = trajectory_for_frame(frame) if trajectory_for_frame is not None else None
                start = start_time_for_frame(frame) if start_time_for_frame is not None else 0.0
                result = simulate(scene, pose_for_frame(frame), config, frame=frame, tracer=tracer, trajectory=traj,
                                  start_time_s=start, progress=frame_progress, cancel=cancel,
                                  products=ProductFiles(tmp / f"frame_{frame:04d}"))
                meta = run_metadata(config, result, frame, extra_metadata)
                write_run_files(tmp / f"frame_{frame:04d}", result, meta)
                all_stats.append({**result.stats, "figures": run_figures(result)})  # (the summary's: not in metadata)
                point_sets.append(result.points)
                units = result.units  # the same settings every frame: the same units
                del result
            names = unify_material_ids(point_sets, [st.get("material_names", []) for st in all_stats])
            merged = merge_points(point_sets)
            files = {f"frame_{f:04d}/": "the run folder of one frame" for f in frames}
            if merged:
                ply = write_ply(tmp / "points_merged.ply", merged, units.get("intensity"))
                with naming(tmp / "points_merged.npz"):
                    np.savez(tmp / "points_merged.npz", **merged)
                files["points_merged.ply"] = "all frames' points in world coordinates (attribute frame)"
                files["points_merged.npz"] = "the same as NumPy arrays"
                if len(merged.get("range_m", ())):
                    write_las(tmp / "points_merged.las", merged, **las_run_facts(
                        {"system_type": config.system_type, "frames": frames, "seed": config.run.seed,
                         "units": units, "material_names": names}))
                    files["points_merged.las"] = "all frames' points as LAS 1.4 (point source ID = frame)"
            meta = {"format": "ladar-sequence", "format_version": 1, "system_type": config.system_type,
                    "frames": frames, "seed": config.run.seed, "settings": config_to_dict(config),
                    "software": software_versions(), "created_unix_s": time.time(),
                    "bvh_builds": bvh_builds,
                    "n_points": int(sum(len(p.get("range_m", ())) for p in point_sets)),
                    "frame_wall_time_s": [s["wall_time_s"] for s in all_stats],
                    "sensor_poses": {str(f): st["sensor_pose"]["world_from_sensor"]
                                     for f, st in zip(frames, all_stats) if "sensor_pose" in st},
                    "wall_time_s": time.perf_counter() - t_wall, "units": dict(units), "files": files}
            warnings = [f"frame {f}: {w}" for f, st in zip(frames, all_stats) for w in run_warnings(st)]
            if warnings:
                meta["warnings"] = warnings
            if merged:
                meta["ply"] = ply
            if bvh_builds < len(frames):
                meta["stages_skipped"] = {"build_bvh": f"static geometry: one BVH for {len(frames)} frames "
                                                       f"({bvh_builds} built)"}
            if extra_metadata:
                meta.update(extra_metadata)
            with naming(tmp / "metadata.json"), open(tmp / "metadata.json", "w", encoding="utf-8") as f:
                json.dump(meta, f, indent=2, default=json_default)
            if cancel is not None and cancel():
                raise Cancelled()
            out = claim.commit()
    finally:
        release_freed_blocks()  # the memory the run freed goes back to the system (core/heap.py)
    return out, all_stats
