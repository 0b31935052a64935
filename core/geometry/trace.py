"""Ray tracing with embreex (float32 BVH) refined to float64 distances.

Embree works in float32.  The BVH is built on vertices translated by a reference point (the scene's
bounding-box centre) to keep float32 resolution, and each hit distance is then recomputed in float64 as the
exact intersection of the ray with the hit triangle's plane, so ranges keep sub-millimetre accuracy even
kilometres away from the origin (docs/theory.md §13: float32 at 10 km has a 1 mm ulp).
"""
from __future__ import annotations

import numpy as np

from ..jit import kernel
from .scene import SceneGeometry


def _same_view(a: np.ndarray, b: np.ndarray) -> bool:
    """The same memory seen the same way (SceneGeometry re-wraps its arrays in new view objects)."""
    return a is b or (a.__array_interface__["data"][0] == b.__array_interface__["data"][0] and a.shape == b.shape
                      and a.strides == b.strides and a.dtype == b.dtype)


class SceneTracer:
    """A committed embreex scene for one SceneGeometry, reusable for any number of rays and frames.

    ``keep`` (bool mask over the triangles, optional) builds the BVH on a subset only — the triangles inside a
    sensor's field of view (core/geometry/culling.py); hits are still reported with the scene's triangle indices.
    Such a tracer is made for one view and does not :meth:`serve` other frames.
    """

    def __init__(self, scene: SceneGeometry, keep=None):
        from embreex.mesh_construction import TriangleMesh
        from embreex.rtcore_scene import EmbreeScene

        self.scene = scene
        v = scene.vertices_m
        m = scene.n_triangles
        self.triangle_ids = None if keep is None else np.flatnonzero(np.asarray(keep, dtype=bool))
        tris = scene.triangles if self.triangle_ids is None else scene.triangles[self.triangle_ids]
        self.n_traced = len(tris)
        used = v[np.unique(tris)] if self.triangle_ids is not None and len(tris) else v
        self.reference_m = 0.5 * (used.min(axis=0) + used.max(axis=0)) if len(used) else np.zeros(3)
        self._embree = None
        if len(tris):
            self._embree = EmbreeScene()
            TriangleMesh(self._embree, (v - self.reference_m).astype(np.float32), tris)
        # plane of each traced triangle in float64 world coordinates: unit normal and v0 (scene-indexed)
        tri = v[tris]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(normal, axis=1)
        if self.triangle_ids is None:
            self.degenerate = norm == 0.0
            self.unit_normal = normal / np.where(self.degenerate, 1.0, norm)[:, None]
            self.v0 = tri[:, 0]
        else:
            self.degenerate = np.ones(m, bool)
            self.unit_normal = np.zeros((m, 3))
            self.v0 = np.zeros((m, 3))
            self.degenerate[self.triangle_ids] = norm == 0.0
            self.unit_normal[self.triangle_ids] = normal / np.where(norm == 0.0, 1.0, norm)[:, None]
            self.v0[self.triangle_ids] = tri[:, 0]

    def _cast(self, o32, d32):
        """Scene triangle index of the first hit of each ray (−1 on a miss)."""
        if self._embree is None:
            return np.full(len(d32), -1, np.int32)
        prim = np.asarray(self._embree.run(o32, d32, query="INTERSECT"), dtype=np.int32)
        if self.triangle_ids is not None:
            prim = np.where(prim >= 0, self.triangle_ids[np.maximum(prim, 0)], -1).astype(np.int32)
        return prim

    def serves(self, scene: SceneGeometry) -> bool:
        """True if this BVH was built on ``scene``'s geometry (the same vertex and triangle arrays): material
        overrides (``SceneGeometry.with_overrides``) share the arrays, so they reuse the BVH."""
        return (self.triangle_ids is None and _same_view(self.scene.vertices_m, scene.vertices_m)
                and _same_view(self.scene.triangles, scene.triangles))

    def bare_cast(self, origin_m, directions):
        """Primitive ids only: the bare embreex ray cast (used as the benchmark floor)."""
        o = np.broadcast_to((np.asarray(origin_m) - self.reference_m).astype(np.float32), directions.shape)
        return self._cast(np.ascontiguousarray(o), np.ascontiguousarray(directions, dtype=np.float32))

    def intersect(self, origin_m, directions):
        """Trace rays from one origin (3,) or one origin per ray (n, 3) (world, float64) along unit directions
        (n, 3) float64.

        Returns (prim (n,) int32, −1 on a miss; range_m (n,) float64, NaN on a miss; cos_theta (n,) float64,
        the cosine of the incidence angle, |d·n|, 0 on a miss).
        """
        origin_m = np.asarray(origin_m, dtype=np.float64)
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        origins = np.ascontiguousarray(origin_m.reshape(-1, 3))
        n = len(directions)
        o32, d32 = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        _rays_float32(origins, np.asarray(self.reference_m, np.float64), directions, o32, d32)
        prim = self._cast(o32, d32)
        range_m, cos_theta = np.full(n, np.nan), np.zeros(n)
        _refine_hits(prim, self.degenerate, origins, directions, self.unit_normal, self.v0, range_m, cos_theta)
        return prim, range_m, cos_theta


@kernel
def _rays_float32(origins, reference, directions, o32, d32):
    """The float32 rays Embree traces: origins relative to the BVH's reference point (one origin or one per ray)."""
    single = origins.shape[0] == 1
    for i in range(directions.shape[0]):
        r = 0 if single else i
        for c in range(3):
            o32[i, c] = origins[r, c] - reference[c]
            d32[i, c] = directions[i, c]


@kernel
def _refine_hits(prim, degenerate, origins, directions, unit_normal, v0, range_m, cos_theta):
    """The float64 refinement of Embree's hits, in place: a hit on a degenerate triangle, or whose plane lies
    behind the origin, becomes a miss (prim −1); otherwise range t = ((v₀ − o)·n)/(d·n) along the ray and
    cos θ = |d·n| on the hit triangle's plane (unit normal n).  Each dot product is summed as
    (x₀y₀ + x₂y₂) + x₁y₁, the order of NumPy's einsum over three components."""
    single = origins.shape[0] == 1
    for i in range(prim.shape[0]):
        p = prim[i]
        if p < 0:
            continue
        if degenerate[p]:
            prim[i] = -1
            continue
        r = 0 if single else i
        n0, n1, n2 = unit_normal[p, 0], unit_normal[p, 1], unit_normal[p, 2]
        dn = (directions[i, 0] * n0 + directions[i, 2] * n2) + directions[i, 1] * n1
        wn = ((v0[p, 0] - origins[r, 0]) * n0 + (v0[p, 2] - origins[r, 2]) * n2) + (v0[p, 1] - origins[r, 1]) * n1
        t = wn / (dn if dn != 0.0 else np.inf)
        if t > 0:
            range_m[i] = t
            cos_theta[i] = abs(dn)
        else:
            prim[i] = -1
