"""Opening a frame, and the record of what ran: what every sensor system does before and around its physics.

    open_frame: validate the settings → the memory and work plan (refuses what would not fit or not end) →
                (the system's own preflight) → material overrides →
                scene check (once per scene: SceneGeometry.ensure_checked) → sensor pose → BVH (reuse the caller's when it serves this scene, else build it,
                on the triangles inside the field of view when the system culls)
    StageLog:   stage times, the stages run (in order) and the stages skipped with the reason, for metadata.json

A system then cuts its work into blocks (:mod:`.blocks`), draws its random numbers from the run seed
(:mod:`.rng`), and returns a :class:`~.result.FrameResult` with ``log.record()`` in its stats.
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from ..config.settings import SimulationConfig
from ..config.validate import validate_config
from ..geometry.culling import frustum_triangles
from ..geometry.motion import split_pose
from ..geometry.scene import SceneGeometry
from ..geometry.trace import SceneTracer
from ..heap import keep_freed_blocks
from ..jit import stage_clock
from .memory import check_memory


@dataclass
class StageLog:
    """Stage timing (seconds per stage) and the run/skip record of one frame."""

    times: dict = field(default_factory=dict)
    ran: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)

    @classmethod
    def of(cls, stages=(), ran=(), skipped=None) -> "StageLog":
        """A log whose ``stages`` start at 0 s, with the planned ``ran`` list and ``skipped`` reasons."""
        return cls(times=dict.fromkeys(stages, 0.0), ran=list(ran), skipped=dict(skipped or {}))

    @contextmanager
    def timed(self, stage: str):
        """Time the ``with`` body as ``stage`` (replacing an earlier time of that stage)."""
        t0 = stage_clock()
        try:
            yield
        finally:
            self.times[stage] = stage_clock() - t0

    def add_times(self, local: dict) -> None:
        """Add a block's stage times (blocks run in parallel: the sums are thread-seconds)."""
        for stage, seconds in local.items():
            self.times[stage] = self.times.get(stage, 0.0) + seconds

    def skip(self, stage: str, reason: str, *, keep_earlier: bool = False) -> None:
        """Record ``stage`` as skipped for ``reason`` (and not run); ``keep_earlier``: an earlier reason stays."""
        if keep_earlier and stage in self.skipped:
            return
        self.skipped[stage] = reason
        self.ran = [s for s in self.ran if s != stage]

    def record(self) -> dict:
        """The metadata entries: ``stage_times_s``, ``stages_run``, ``stages_skipped``."""
        return {"stage_times_s": self.times, "stages_run": self.ran, "stages_skipped": self.skipped}


@dataclass
class Frame:
    """An opened frame: the validated settings, the scene with the config's materials, the pose and the BVH."""

    config: SimulationConfig
    scene: SceneGeometry
    tracer: SceneTracer
    origin: np.ndarray | None      # (3,) sensor position in the world, None for a trajectory-only frame
    rot: np.ndarray | None         # (3, 3) sensor→world rotation
    built: bool                    # the BVH was built for this frame (else the caller's was reused)
    bvh: dict                      # how: built, culled (triangles traced / total) or reused
    t_wall: float                  # perf_counter() when the frame was opened
    memory: dict = None            # the memory and work estimate (engine.memory.check_memory)
    preflight: object = None       # what the system's preflight returned


def open_frame(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, log: StageLog, *,
               tracer: SceneTracer | None = None, preflight=None, frustum_tan=None,
               fov_culling: bool | None = None, posed_by_trajectory: bool = False) -> Frame:
    """Open one frame (module docstring).  Raises ConfigError on bad settings, scene or pose.

    ``world_from_sensor``: 4×4 sensor→world matrix; None only with ``posed_by_trajectory`` (the system poses every
    pulse from a trajectory), otherwise a ConfigError like any other matrix that is not a finite 4×4.
    ``tracer``: a BVH built on this scene's geometry (static scenes: one BVH for all frames) is reused.
    The memory and work estimate of the frame (:func:`~.memory.check_memory`, every system) refuses, naming the
    setting to change, a frame that would not fit or not end, before anything is built; it is ``Frame.memory``.
    ``preflight(config)``: the system's own check after those, before anything is built.
    ``fov_culling``: None for a system that traces the whole scene; True (False) for one that builds its BVH on
    the triangles inside the frustum ``frustum_tan`` = (half width, half height) in tan units (or says it does not).
    The BVH's time is logged as ``build_bvh``; reuse and culling are recorded in ``log``."""
    t_wall = time.perf_counter()
    keep_freed_blocks()  # a frame's large arrays reuse the previous frame's memory (core/heap.py; once per process)
    validate_config(config)  # a SimulationConfig (not None, a dict or a settings group) with valid settings
    memory = check_memory(config)
    checked = preflight(config) if preflight is not None else None
    given, scene = scene, scene.with_overrides(config.materials)
    if scene.ensure_checked():  # once per scene: again only if an array was replaced (SceneGeometry docstring)
        log.ran.append("scene_check")
        if scene is not given and scene._arrays_key() == given._arrays_key():
            given._checked_arrays = scene._checked_arrays  # the caller's scene: its next frame's copy is checked
    else:
        log.skip("scene_check", "the scene's arrays were checked at an earlier frame and not replaced since "
                                "(materials checked again)")
    origin, rot = (None, None) if world_from_sensor is None and posed_by_trajectory else split_pose(world_from_sensor)
    t0 = stage_clock()
    bvh = {}
    built = tracer is None or not tracer.serves(scene)
    if built:
        keep = None
        if fov_culling:  # objects outside the field of view are not traced
            keep = frustum_triangles(scene.vertices_m, scene.triangles, origin, rot, *frustum_tan)
            bvh = {"triangles_traced": int(keep.sum()), "triangles_total": scene.n_triangles,
                   "time_s": stage_clock() - t0}
            log.ran.append("fov_culling")
        elif fov_culling is not None:
            log.skip("fov_culling", "fov_culling = False: the whole scene is traced")
        tracer = SceneTracer(scene, keep=keep)
        bvh["bvh"] = "built on the triangles in the field of view" if keep is not None else "built"
    elif fov_culling is not None:
        bvh["bvh"] = "reused"
        log.skip("fov_culling", "static geometry: the given BVH of the whole scene is reused (no rebuild, no culling)")
        log.skip("build_bvh", "static geometry: the given BVH is reused")
    else:
        bvh["bvh"] = "reused"
        log.skip("build_bvh", "the caller's BVH of this scene was reused")
    log.times["build_bvh"] = stage_clock() - t0
    return Frame(config=config, scene=scene, tracer=tracer, origin=origin, rot=rot, built=built, bvh=bvh,
                 t_wall=t_wall, memory=memory, preflight=checked)
