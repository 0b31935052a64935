"""Scene geometry handed from Blender (or a test) to the simulator: world-space triangles with materials."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config.settings import DEFAULT_BRDF, BRDFSettings
from ..config.validate import validate
from ..errors import ConfigError


@dataclass
class SceneGeometry:
    """Triangles in world coordinates (metres) with a material per triangle.

    vertices_m    (N, 3) float64 world coordinates
    triangles     (M, 3) int32 vertex indices
    material_ids  (M,)   int32 index into ``materials`` (and ``material_names``)
    materials     BRDF of each material; ``material_names`` their names (config overrides match by name)

    Checked once: :meth:`check` validates everything and remembers the arrays it validated (their memory, shape,
    strides and dtype); :meth:`ensure_checked` (every frame, core/engine/frame.py) repeats the array checks only
    when an array was replaced since, and the materials (a few settings) every time.  An array changed *in place*
    (the same memory written through ``scene.vertices_m[...] = …`` or any other view of it) is not seen: call
    :meth:`check` after such a change (it always validates), or make a new SceneGeometry.
    """

    vertices_m: np.ndarray
    triangles: np.ndarray
    material_ids: np.ndarray
    materials: list = field(default_factory=lambda: [DEFAULT_BRDF])
    material_names: list = field(default_factory=lambda: ["default"])

    def __post_init__(self):
        self.vertices_m = _real_array("scene.vertices_m", self.vertices_m, (None, 3),
                                      "an (N, 3) array of real x, y, z coordinates (m)")
        self.triangles = _index_array("scene.triangles", self.triangles, (None, 3),
                                      "an (M, 3) array of whole-number vertex indices")
        self.material_ids = _index_array("scene.material_ids", self.material_ids, (None,),
                                         "an (M,) array of whole-number material indices, one per triangle")

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def _arrays_key(self) -> tuple:
        """What identifies the arrays :meth:`check` validated: each one's memory address, shape, strides, dtype
        (and the number of materials, the range of the material indices)."""
        return tuple((a.__array_interface__["data"][0], a.shape, a.strides, a.dtype.str)
                     for a in (self.vertices_m, self.triangles, self.material_ids)) + (len(self.materials),)

    def check(self) -> None:
        """Validate shapes, indices and values; raise ConfigError naming the bad part."""
        self._checked_arrays = None
        if self.n_triangles == 0:
            raise ConfigError("scene.triangles", 0, "at least one triangle of a visible mesh object")
        if not np.all(np.isfinite(self.vertices_m)):
            raise ConfigError("scene.vertices_m", "NaN/Inf", "finite coordinates")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices_m):
            raise ConfigError("scene.triangles", "index out of range",
                              f"vertex indices in [0, {len(self.vertices_m) - 1}]")
        if self.material_ids.shape[0] != self.n_triangles:
            raise ConfigError("scene.material_ids", self.material_ids.shape[0],
                              f"one material index per triangle ({self.n_triangles})")
        self._check_names()
        if self.material_ids.min() < 0 or self.material_ids.max() >= len(self.materials):
            raise ConfigError("scene.material_ids", "index out of range",
                              f"material indices in [0, {len(self.materials) - 1}]")
        self._check_materials()
        self._checked_arrays = self._arrays_key()

    def ensure_checked(self) -> bool:
        """:meth:`check`, unless these very arrays passed it before (class docstring): then only the materials are
        checked again (a few settings).  Returns True if the arrays were checked now."""
        if getattr(self, "_checked_arrays", None) is not None and self._checked_arrays == self._arrays_key():
            self._check_names()
            self._check_materials()
            return False
        self.check()
        return True

    def _check_names(self) -> None:
        if len(self.materials) != len(self.material_names):
            raise ConfigError("scene.material_names", len(self.material_names),
                              f"one name per material ({len(self.materials)})")

    def _check_materials(self) -> None:
        for name, brdf in zip(self.material_names, self.materials):
            if not isinstance(brdf, BRDFSettings):
                raise ConfigError(f"materials.{name}", brdf, "BRDF settings")
            validate(brdf, f"materials.{name}.")

    def with_overrides(self, overrides: dict) -> "SceneGeometry":
        """A copy whose materials are replaced by the config's ``materials`` table (by name)."""
        if not overrides:
            return self
        unknown = set(overrides) - set(self.material_names)
        if unknown:
            raise ConfigError("materials", sorted(unknown)[0],
                              "the name of a material in the scene: " + ", ".join(self.material_names))
        mats = [overrides.get(n, m) for n, m in zip(self.material_names, self.materials)]
        out = SceneGeometry(self.vertices_m, self.triangles, self.material_ids, mats, list(self.material_names))
        if out._arrays_key() == getattr(self, "_checked_arrays", None):  # the same arrays: checked already
            out._checked_arrays = self._checked_arrays
        return out


def _as_array(path: str, value, allowed: str) -> np.ndarray:
    try:
        a = np.asarray(value)
    except (ValueError, TypeError):  # ragged nested lists
        raise ConfigError(path, f"a {type(value).__name__} that is not a rectangular array", allowed) \
            from None
    if a.dtype.kind not in "iuf":  # bool, complex, strings, objects (None, ragged lists)
        raise ConfigError(path, f"an array of dtype {a.dtype}", allowed)
    return a


def _check_shape(path: str, a: np.ndarray, shape: tuple, allowed: str) -> None:
    if a.ndim != len(shape) or any(want is not None and got != want for got, want in zip(a.shape, shape)):
        if not (a.size == 0 and a.ndim == 1 and len(shape) == 2):  # [] for "no triangles"
            raise ConfigError(path, f"an array of shape {a.shape}, dtype {a.dtype}", allowed)


def _real_array(path: str, value, shape: tuple, allowed: str) -> np.ndarray:
    """``value`` as a C-contiguous float64 array of ``shape`` (None: any length), or ConfigError."""
    a = _as_array(path, value, allowed)
    _check_shape(path, a, shape, allowed)
    return np.ascontiguousarray(a, dtype=np.float64).reshape((-1,) + tuple(shape[1:]))


#: Largest index an int32 index array can hold.
_MAX_INDEX = np.iinfo(np.int32).max


def _index_array(path: str, value, shape: tuple, allowed: str) -> np.ndarray:
    """``value`` as a C-contiguous int32 array of ``shape`` (None: any length), or ConfigError: whole numbers
    only (floats with a fraction are refused, not truncated), in [0, 2³¹ − 1] (never wrapped)."""
    a = _as_array(path, value, allowed)
    _check_shape(path, a, shape, allowed)
    if a.size:
        if a.dtype.kind == "f":
            bad = ~np.isfinite(a) | (a != np.floor(a))
            if bad.any():
                raise ConfigError(path, f"{a.reshape(-1)[np.argmax(bad.reshape(-1))]!r} in an array of dtype "
                                        f"{a.dtype}", allowed + " (no fractions)")
        lo, hi = a.min(), a.max()
        if lo < 0 or hi > _MAX_INDEX:
            raise ConfigError(path, f"index {lo if lo < 0 else hi} (dtype {a.dtype})",
                              f"{allowed} in [0, {_MAX_INDEX}]")
    return np.ascontiguousarray(a, dtype=np.int32).reshape((-1,) + tuple(shape[1:]))


def merge_meshes(parts) -> SceneGeometry:
    """Concatenate ``(vertices_m, triangles, material_name_per_triangle_index, names, brdfs)`` parts.

    Each part is a tuple ``(vertices (n,3), triangles (m,3), local_material_ids (m,), names, brdfs)``; materials
    with the same name are shared.
    """
    all_v, all_t, all_m = [], [], []
    names: list[str] = []
    brdfs: list[BRDFSettings] = []
    index = {}
    offset = 0
    for verts, tris, local_ids, part_names, part_brdfs in parts:
        verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
        tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        lut = np.empty(max(len(part_names), 1), dtype=np.int32)
        for i, (n, b) in enumerate(zip(part_names, part_brdfs)):
            if n not in index:
                index[n] = len(names)
                names.append(n)
                brdfs.append(b)
            lut[i] = index[n]
        if not part_names:
            if "default" not in index:
                index["default"] = len(names)
                names.append("default")
                brdfs.append(DEFAULT_BRDF)
            lut[0] = index["default"]
        ids = np.clip(np.asarray(local_ids, dtype=np.int64).reshape(-1), 0, len(lut) - 1)
        all_v.append(verts)
        all_t.append(tris + offset)
        all_m.append(lut[ids])
        offset += len(verts)
    if not all_v:
        return SceneGeometry(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int32), [DEFAULT_BRDF],
                             ["default"])
    if not names:
        names, brdfs = ["default"], [DEFAULT_BRDF]
    return SceneGeometry(np.concatenate(all_v), np.concatenate(all_t), np.concatenate(all_m), brdfs, names)
