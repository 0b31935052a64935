"""Frames of a run on the Blender side: frame ranges ("1-100:5"), and each frame's inputs read on the main thread
(the exported geometry, the sensor pose and, for a scanner, the trajectory it flies during the scan)."""
from __future__ import annotations

import dataclasses
import math
import re
import time

import bpy
import numpy as np

from ..core.errors import ConfigError
from ..core.geometry.motion import Trajectory
from .errors import LadarError
from .export import frame_dependent_objects, geometry_digest, scene_geometry_from_depsgraph

from .run_inputs import log

#: Most sensor poses sampled per scan (each costs a scene evaluation on the main thread).
MAX_MOTION_SAMPLES = 1000
#: Poses per Blender frame that resolve the sensor's animation curves (finer sampling adds nothing).
MOTION_SAMPLES_PER_FRAME = 16

_FRAMES_ITEM = re.compile(r"^\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*(?::\s*(\d+)\s*)?)?$")


def parse_frames(text) -> list[int]:
    """Frame numbers from "7", "1-100", "1-100:5" (every 5th) or a comma list such as "1,4,10-12".

    Raises ConfigError (field ``frames``) for anything else, an empty or reversed range, or a repeated frame.
    """
    allowed = 'frame numbers such as "7", "1-100", "1-100:5" (every 5th) or "1,4,10-12"'
    frames = []
    for item in str(text).split(","):
        m = _FRAMES_ITEM.match(item)
        if m is None:
            raise ConfigError("frames", text, allowed)
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) is not None else first
        step = int(m.group(3)) if m.group(3) is not None else 1
        if last < first or step < 1:
            raise ConfigError("frames", text, allowed + " (first ≤ last, step ≥ 1)")
        # Blender's frame range before the range is expanded: "1-100000000" was a list of 10⁸ numbers built
        # (minutes, gigabytes) before the frames were checked (issue 31's hostile suite)
        prop = bpy.types.Scene.bl_rna.properties["frame_current"]
        for f in (first, last):
            if not prop.hard_min <= f <= prop.hard_max:
                raise ConfigError("frames", f, f"a frame in [{prop.hard_min}, {prop.hard_max}] (Blender's frame "
                                               f"range)")
        frames.extend(range(first, last + 1, step))
        if len(frames) > prop.hard_max - prop.hard_min + 1:  # more than there are frames: some repeat
            raise ConfigError("frames", text, "each frame once")
    if len(set(frames)) != len(frames):
        raise ConfigError("frames", text, "each frame once")
    return frames



# ------------------------------------------------------------------------------------------------------------
# Per-frame inputs (main thread)
# ------------------------------------------------------------------------------------------------------------
def scene_time_s(scene, frame: float) -> float:
    """Scene time (s) of a (sub-)frame, as Blender's Scene Time node: frame / (fps / fps_base)."""
    return float(frame) * scene.render.fps_base / scene.render.fps


def sensor_may_move(scene, sensor) -> bool:
    """True when the sensor's world matrix may change with time (animation, drivers, constraints, parents)."""
    from .export import animated

    obj = sensor
    while obj is not None:
        if animated(obj) or len(obj.constraints) or obj.rigid_body is not None:
            return True
        obj = obj.parent
    return animated(scene)


def _world_matrix_m(obj, scale_m: float) -> np.ndarray:
    m = np.array(obj.matrix_world, dtype=np.float64)
    m[:3, 3] *= scale_m
    return m


def motion_sample_count(duration_s: float, rate_hz: float, fps: float) -> int:
    """Poses sampled over a scan: ``rate_hz`` × duration, at most :data:`MOTION_SAMPLES_PER_FRAME` per Blender
    frame and :data:`MAX_MOTION_SAMPLES` in all, at least the two ends."""
    n = min(math.ceil(duration_s * rate_hz), math.ceil(duration_s * fps * MOTION_SAMPLES_PER_FRAME),
            MAX_MOTION_SAMPLES - 1)
    return max(1, n) + 1


def sample_trajectory(scene, sensor, frame: int, duration_s: float, rate_hz: float, scale_m: float = 1.0):
    """The sensor's pose over ``[0, duration_s]`` after the start of ``frame`` (sub-frames), or None when it does
    not move.  Leaves the scene at ``frame``."""
    if duration_s <= 0.0 or not sensor_may_move(scene, sensor):
        return None
    fps = scene.render.fps / scene.render.fps_base
    times = np.linspace(0.0, duration_s, motion_sample_count(duration_s, rate_hz, fps))
    matrices = []
    try:
        for t in times:
            f = frame + t * fps
            whole = math.floor(f)
            scene.frame_set(int(whole), subframe=float(f - whole))
            matrices.append(_world_matrix_m(sensor, scale_m))
    finally:
        scene.frame_set(frame)
    traj = Trajectory(times, np.array(matrices))
    return None if traj.is_static else traj


@dataclasses.dataclass
class FrameInputs:
    frame: int
    geometry: object            # core SceneGeometry (material overrides applied)
    world_from_sensor: np.ndarray
    trajectory: object | None   # core Trajectory (scanner with a moving sensor) or None
    start_time_s: float
    export: dict                # what the export did (counts, reused or not)


class FrameSource:
    """Each frame's inputs from Blender (main thread only), reusing the exported geometry while it is unchanged."""

    def __init__(self, scene, sensor, cfg, blender_materials, scale_m: float):
        self.scene, self.sensor, self.cfg = scene, sensor, cfg
        self.blender_materials = blender_materials
        self.scale_m = scale_m
        self.geometry, self.digest = None, None
        self.exports, self.geometries = 0, 0
        self.time_dependent = None   # {object: [reasons]} once known
        self.main_thread_s = 0.0     # time spent in prepare() (blocks the interface in a modal run)

    def _depsgraph(self):
        scene = self.scene
        view_layer = bpy.context.view_layer if bpy.context.scene == scene else scene.view_layers[0]
        depsgraph = view_layer.depsgraph
        depsgraph.update()
        return depsgraph

    def prepare(self, frame: int) -> FrameInputs:
        t0 = time.perf_counter()
        scene, sensor = self.scene, self.sensor
        scene.frame_set(frame)  # also at the current frame: evaluates the animation as a render would
        depsgraph = self._depsgraph()
        if self.time_dependent is None:
            self.time_dependent = frame_dependent_objects(scene, depsgraph, exclude={sensor.name})
        info = {"geometry": "reused"}
        if self.geometry is None or self.time_dependent:
            stats = {}
            exported = scene_geometry_from_depsgraph(depsgraph, unit_scale=self.scale_m, exclude={sensor.name},
                                                     stats=stats)
            self.exports += 1
            info.update(stats)
            if exported.n_triangles == 0:
                raise LadarError(f"no geometry to simulate at frame {frame}: the scene has no visible mesh (or "
                                 f"curve/text) objects enabled for rendering")
            log(f"exported {stats['triangles']} triangles ({stats['objects']} objects, {stats['instances']} "
                 f"instances) at frame {frame}")
            overrides = {n: b for n, b in self.cfg.materials.items()
                         if n in exported.material_names or self.blender_materials.get(n) != b}
            geometry = exported.with_overrides(overrides)
            digest = geometry_digest(geometry)
            if digest != self.digest:
                self.geometry, self.digest = geometry, digest
                self.geometries += 1
                info["geometry"] = "exported"
        trajectory = None
        if self.cfg.system_type == "scanner":
            from ..core.config.derived import scan_duration_s
            trajectory = sample_trajectory(scene, sensor, frame, scan_duration_s(self.cfg),
                                           self.cfg.scanner.motion_samples_per_s, self.scale_m)
            info["motion_samples"] = 0 if trajectory is None else len(trajectory.times_s)
        inputs = FrameInputs(frame, self.geometry, _world_matrix_m(sensor, self.scale_m), trajectory,
                             scene_time_s(scene, frame), info)
        info["main_thread_s"] = time.perf_counter() - t0
        self.main_thread_s += info["main_thread_s"]
        return inputs


