"""The scene of a sweep, exported once into the sweep folder and read by every worker (no Blender needed).

``scene/scene.npz`` holds the arrays — for each distinct geometry ``g<k>_vertices_m``, ``g<k>_triangles``,
``g<k>_material_ids``; for each frame its 4×4 sensor pose ``f<i>_pose`` and, for a scanner on a moving
platform, its sampled trajectory ``f<i>_traj_times_s`` / ``f<i>_traj_matrices`` — and ``scene/scene.json`` the
rest: frames, which geometry each frame uses, start times, material names and BRDF settings, and a digest of it
all.  Both are written through hidden temporary files and renamed into place.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config.settings import BRDFSettings
from ..errors import ConfigError
from ..fileio.run_folder import json_default
from ..fileio.staging import write_file_atomically
from ..geometry.motion import Trajectory, split_pose
from ..geometry.scene import SceneGeometry
from ..geometry.trace import SceneTracer

SCENE_FORMAT = "ladar-sweep-scene"
SCENE_FORMAT_VERSION = 1


@dataclass
class SweepScene:
    """Everything a worker needs besides the settings: geometries, and per frame a pose (and trajectory).

    ``geometries``: distinct SceneGeometry objects; ``frames``: frame numbers; ``geometry_of_frame[i]``: index into
    ``geometries``; ``poses[i]``: 4×4 sensor→world (metres); ``trajectories[i]``: Trajectory or None;
    ``start_times_s[i]``: the frame's start time (the scanner's GPS-style time)."""

    geometries: list
    frames: list
    geometry_of_frame: list
    poses: list
    trajectories: list = field(default_factory=list)
    start_times_s: list = field(default_factory=list)
    info: dict = field(default_factory=dict)    # where it came from (the .blend, the export counts), recorded only

    def __post_init__(self):
        n = len(self.frames)
        if not self.trajectories:
            self.trajectories = [None] * n
        if not self.start_times_s:
            self.start_times_s = [0.0] * n
        if not n or not self.geometries:
            raise ConfigError("scene", "no frames", "at least one frame with geometry")
        if len(set(self.frames)) != n:
            raise ConfigError("frames", self.frames, "each frame once")
        for name, seq in (("geometry_of_frame", self.geometry_of_frame), ("poses", self.poses),
                          ("trajectories", self.trajectories), ("start_times_s", self.start_times_s)):
            if len(seq) != n:
                raise ConfigError(f"scene.{name}", len(seq), f"one per frame ({n})")
        self.poses = [np.asarray(p, dtype=np.float64).reshape(4, 4) for p in self.poses]
        for p in self.poses:
            split_pose(p)  # a finite, invertible pose
        for g in self.geometries:
            g.check()

    @classmethod
    def single(cls, geometry: SceneGeometry, world_from_sensor, frame: int = 0, trajectory=None,
               start_time_s: float = 0.0) -> "SweepScene":
        """One geometry seen from one pose (the Python API's usual case)."""
        return cls([geometry], [int(frame)], [0], [world_from_sensor], [trajectory], [float(start_time_s)])

    def frame_index(self, frame: int) -> int:
        try:
            return self.frames.index(int(frame))
        except ValueError:
            raise ConfigError("frames", frame, "a frame of the exported scene: "
                              + ", ".join(str(f) for f in self.frames)) from None

    def geometry(self, frame: int) -> SceneGeometry:
        return self.geometries[self.geometry_of_frame[self.frame_index(frame)]]

    def material_brdfs(self) -> dict:
        """{material name: BRDFSettings} over every geometry (first one wins)."""
        out = {}
        for g in self.geometries:
            for name, brdf in zip(g.material_names, g.materials):
                out.setdefault(name, brdf)
        return out

    def with_overrides(self, overrides: dict) -> "SweepScene":
        """The same scene with the materials of a config's ``materials`` table replaced (by name)."""
        if not overrides:
            return self
        names = set().union(*(g.material_names for g in self.geometries))
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ConfigError("materials", unknown[0],
                              "the name of a material in the scene: " + ", ".join(sorted(names)))
        geoms = [g.with_overrides({k: v for k, v in overrides.items() if k in g.material_names})
                 for g in self.geometries]
        return dataclasses.replace(self, geometries=geoms)

    # -- files ----------------------------------------------------------------------------------------------------
    def _arrays_and_json(self):
        arrays, materials = {}, []
        for k, g in enumerate(self.geometries):
            arrays[f"g{k}_vertices_m"] = g.vertices_m
            arrays[f"g{k}_triangles"] = g.triangles
            arrays[f"g{k}_material_ids"] = g.material_ids
            materials.append([[name, dataclasses.asdict(b)] for name, b in zip(g.material_names, g.materials)])
        has_traj = []
        for i, (pose, traj) in enumerate(zip(self.poses, self.trajectories)):
            arrays[f"f{i}_pose"] = pose
            if traj is not None:
                arrays[f"f{i}_traj_times_s"] = traj.times_s
                arrays[f"f{i}_traj_matrices"] = traj.matrices
            has_traj.append(traj is not None)
        meta = {"format": SCENE_FORMAT, "format_version": SCENE_FORMAT_VERSION, "frames": self.frames,
                "geometry_of_frame": self.geometry_of_frame, "start_times_s": self.start_times_s,
                "trajectory": has_traj, "materials": materials, "info": self.info}
        return arrays, meta

    def digest(self) -> str:
        """A hash of the arrays and settings (equal digests: the same sweep inputs)."""
        arrays, meta = self._arrays_and_json()
        h = hashlib.blake2b(digest_size=16)
        for name in sorted(arrays):
            a = np.ascontiguousarray(arrays[name])
            h.update(f"{name}{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
        meta = dict(meta)
        meta.pop("info")
        h.update(json.dumps(meta, sort_keys=True).encode())
        return h.hexdigest()

    def save(self, folder) -> Path:
        """Write ``folder/scene.npz`` and ``folder/scene.json`` (each atomically); returns the folder."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        arrays, meta = self._arrays_and_json()
        meta["digest"] = self.digest()
        write_file_atomically(folder / "scene.npz", lambda f: np.savez(f, **arrays))
        write_json_atomically(folder / "scene.json", meta)
        return folder

    @classmethod
    def load(cls, folder) -> "SweepScene":
        folder = Path(folder)
        try:
            meta = json.loads((folder / "scene.json").read_text(encoding="utf-8"))
            data = np.load(folder / "scene.npz")
        except (OSError, ValueError) as exc:
            raise ConfigError("sweep scene", str(folder), f"an exported sweep scene (scene.npz + scene.json): {exc}")
        if meta.get("format") != SCENE_FORMAT or meta.get("format_version") != SCENE_FORMAT_VERSION:
            raise ConfigError("sweep scene", str(folder), f"{SCENE_FORMAT} version {SCENE_FORMAT_VERSION}")
        geoms = []
        for k, mats in enumerate(meta["materials"]):
            names = [m[0] for m in mats]
            brdfs = [BRDFSettings(**m[1]) for m in mats]
            geoms.append(SceneGeometry(data[f"g{k}_vertices_m"], data[f"g{k}_triangles"],
                                       data[f"g{k}_material_ids"], brdfs, names))
        trajs = [Trajectory(data[f"f{i}_traj_times_s"], data[f"f{i}_traj_matrices"]) if t else None
                 for i, t in enumerate(meta["trajectory"])]
        poses = [data[f"f{i}_pose"] for i in range(len(meta["frames"]))]
        return cls(geoms, list(meta["frames"]), list(meta["geometry_of_frame"]), poses, trajs,
                   list(meta["start_times_s"]), dict(meta.get("info", {})))


def write_json_atomically(path, data) -> Path:
    """``json.dump`` through a hidden temporary file in the same folder, then renamed over ``path``."""
    text = json.dumps(data, indent=2, default=json_default)
    return write_file_atomically(path, lambda f: f.write(text.encode("utf-8")))


def boresight_point(scene: SweepScene, frame: int) -> np.ndarray:
    """World point where the sensor's centre ray (−Z of the sensor frame) first hits the frame's geometry."""
    origin, rot = split_pose(scene.poses[scene.frame_index(frame)])
    direction = rot @ np.array([0.0, 0.0, -1.0])
    prim, range_m, _ = SceneTracer(scene.geometry(frame)).intersect(origin, direction[None])
    if prim[0] < 0:
        raise ConfigError("sensor.range_m", "boresight misses the scene",
                          f"a sensor whose centre ray hits the scene at frame {frame} (aim it at the target)")
    return origin + direction * float(range_m[0])


def pose_at_range(pose, target_m, range_m: float) -> np.ndarray:
    """The pose moved along its line of sight so that ``target_m`` (on the boresight) is ``range_m`` away."""
    pose = np.array(pose, dtype=np.float64)
    _, rot = split_pose(pose)
    direction = rot @ np.array([0.0, 0.0, -1.0])
    pose[:3, 3] = np.asarray(target_m) - range_m * direction
    return pose
