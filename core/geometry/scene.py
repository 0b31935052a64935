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
    """

    vertices_m: np.ndarray
    triangles: np.ndarray
    material_ids: np.ndarray
    materials: list = field(default_factory=lambda: [DEFAULT_BRDF])
    material_names: list = field(default_factory=lambda: ["default"])

    def __post_init__(self):
        self.vertices_m = np.ascontiguousarray(self.vertices_m, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32).reshape(-1, 3)
        self.material_ids = np.ascontiguousarray(self.material_ids, dtype=np.int32).reshape(-1)

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def check(self) -> None:
        """Validate shapes, indices and values; raise ConfigError naming the bad part."""
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
        if len(self.materials) != len(self.material_names):
            raise ConfigError("scene.material_names", len(self.material_names),
                              f"one name per material ({len(self.materials)})")
        if self.material_ids.min() < 0 or self.material_ids.max() >= len(self.materials):
            raise ConfigError("scene.material_ids", "index out of range",
                              f"material indices in [0, {len(self.materials) - 1}]")
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
        return SceneGeometry(self.vertices_m, self.triangles, self.material_ids, mats, list(self.material_names))


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
