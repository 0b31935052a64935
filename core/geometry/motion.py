"""Sensor motion: a trajectory of poses sampled in time, interpolated per pulse (paper §2.1, moving platforms).

The add-on samples the sensor object's ``matrix_world`` at sub-frames over the scan; the core interpolates the
position linearly and the orientation by spherical linear interpolation (scipy ``Slerp``), so every pulse is
fired from, and its points registered with, the pose at its own time stamp.  Times are float64 seconds from the
start of the scan (or frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError


def split_pose(world_from_sensor):
    """(origin (3,), rotation (3, 3) with unit columns) of a 4×4 sensor-to-world matrix (scale removed)."""
    m = _real_array("sensor.matrix_world", world_from_sensor, (4, 4), "a finite 4×4 matrix")
    if not np.all(np.isfinite(m)):
        raise ConfigError("sensor.matrix_world", "non-finite values", "a finite 4×4 matrix")
    rot = m[:3, :3]
    # each column divided by its largest element first: the norm of a column of 1e200s (or of subnormals) would
    # overflow to inf (underflow to 0) and leave a rotation of zero columns
    peak = np.max(np.abs(rot), axis=0)
    if np.any(peak == 0):
        raise ConfigError("sensor.matrix_world", "zero scale", "an invertible rotation (non-zero scale)")
    rot = rot / peak
    rot = rot / np.linalg.norm(rot, axis=0)
    if abs(np.linalg.det(rot)) < 1e-9:  # two axes (nearly) parallel: the pose flattens its rays onto a plane
        raise ConfigError("sensor.matrix_world", "degenerate axes", "an invertible rotation (independent axes)")
    return m[:3, 3].copy(), rot


def _real_array(name: str, value, shape: tuple, allowed: str) -> np.ndarray:
    """``value`` as float64 if it is an array of real numbers of ``shape`` (None: any length); ConfigError
    naming ``name``, its shape and dtype otherwise (never reshaped)."""
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):
        raise ConfigError(name, "not a rectangular array", allowed) from None
    if a.dtype.kind not in "iuf" or len(a.shape) != len(shape) or any(
            n is not None and m != n for m, n in zip(a.shape, shape)):
        raise ConfigError(name, f"shape {a.shape}, dtype {a.dtype}", f"{allowed} of real numbers")
    return a.astype(np.float64)


@dataclass
class Trajectory:
    """Sensor poses at increasing times: ``times_s`` (n,) and ``matrices`` (n, 4, 4) sensor→world."""

    times_s: np.ndarray
    matrices: np.ndarray

    def __post_init__(self):
        self.times_s = _real_array("trajectory.times_s", self.times_s, (None,), "(n,) times in seconds")
        self.matrices = _real_array("trajectory.matrices", self.matrices, (None, 4, 4),
                                    "(n, 4, 4) sensor→world matrices")
        if len(self.times_s) != len(self.matrices) or len(self.times_s) == 0:
            raise ConfigError("trajectory", f"{len(self.times_s)} times, {len(self.matrices)} poses",
                              "as many poses as times (at least one)")
        if not np.all(np.isfinite(self.times_s)) or np.any(np.diff(self.times_s) <= 0):
            raise ConfigError("trajectory.times_s", "not strictly increasing", "strictly increasing finite times")
        parts = []
        for i, m in enumerate(self.matrices):
            try:
                parts.append(split_pose(m))
            except ConfigError as exc:  # named as the trajectory's pose, not the sensor's
                raise ConfigError(f"trajectory.matrices[{i}]", exc.value, exc.allowed) from None
        self._origins = np.array([p[0] for p in parts])
        rots = np.array([p[1] for p in parts])
        # a reflection (negative determinant) cannot be interpolated as a rotation
        if np.any(np.linalg.det(rots) < 0):
            raise ConfigError("trajectory.matrices", "a mirrored pose", "proper rotations (no negative scale)")
        from scipy.spatial.transform import Rotation, Slerp  # here: 0.4 s of start-up for the runs without motion

        self._rotations = Rotation.from_matrix(rots)
        #: every pose has the same orientation (a static sensor, or one that only translates)
        self.rotation_is_constant = bool(np.all(rots == rots[0]))
        self.rotation0 = rots[0]
        self._slerp = (Slerp(self.times_s, self._rotations) if len(self.times_s) > 1 and not self.rotation_is_constant
                       else None)

    @classmethod
    def static(cls, world_from_sensor) -> "Trajectory":
        return cls(np.zeros(1), np.asarray(world_from_sensor, dtype=np.float64)[None])

    @property
    def is_static(self) -> bool:
        return len(self.times_s) == 1 or (np.allclose(self.matrices, self.matrices[0], rtol=0, atol=0))

    def poses_at(self, t_s):
        """Origins (n, 3) and rotations (n, 3, 3) at times ``t_s`` (clamped to the sampled interval)."""
        t = np.clip(np.asarray(t_s, dtype=np.float64), self.times_s[0], self.times_s[-1])
        origin = np.stack([np.interp(t, self.times_s, self._origins[:, k]) for k in range(3)], axis=1)
        if self._slerp is None:
            return origin, np.broadcast_to(self.rotation0, (len(t), 3, 3))
        return origin, self._slerp(t).as_matrix()
