"""Ray tracing with embreex (float32 BVH) refined to float64 distances.

Embree works in float32.  The BVH is built on vertices translated by a reference point (the scene's
bounding-box centre) to keep float32 resolution, and each hit distance is then recomputed in float64 as the
exact intersection of the ray with the hit triangle's plane, so ranges keep sub-millimetre accuracy even
kilometres away from the origin (docs/theory.md §13: float32 at 10 km has a 1 mm ulp).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError
from ..jit import kernel
from .scene import SceneGeometry

#: Farthest a traced vertex may be from the traced geometry's centre (its bounding box's): Embree holds the
#: geometry in float32 relative to that centre, whose steps are 1 m at 1e7 m.  A stray vertex 1.5e8 m away (a
#: mis-scaled object) made a plate 100 m in front of the sensor vanish without a word (issue 31's hostile suite).
MAX_TRACED_SPAN_M = 1e7


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
        self.triangle_ids = None if keep is None else np.flatnonzero(np.asarray(keep, dtype=bool))
        tris = scene.triangles if self.triangle_ids is None else scene.triangles[self.triangle_ids]
        self.n_traced = len(tris)
        used = v[np.unique(tris)] if self.triangle_ids is not None and len(tris) else v
        self.reference_m = 0.5 * (used.min(axis=0) + used.max(axis=0)) if len(used) else np.zeros(3)
        span = float(np.max(np.abs(used - self.reference_m))) if len(used) else 0.0
        if span > MAX_TRACED_SPAN_M:
            raise ConfigError("scene.vertices_m", f"traced geometry reaching {span:.3g} m from its centre",
                              f"traced geometry within {MAX_TRACED_SPAN_M:g} m of its centre (Embree traces in "
                              f"float32 about that centre: {np.spacing(np.float32(min(span, 3e38))):.3g} m steps there, "
                              f"which make nearby surfaces vanish; remove or hide the far-away objects)")
        self._embree = None
        if len(tris):
            self._embree = EmbreeScene()
            TriangleMesh(self._embree, (v - self.reference_m).astype(np.float32), tris)
            # embreex builds the BVH at the scene's first query: build it now, so the BVH is ready (and its
            # time counted) when the tracer is
            self._embree.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32),
                             query="INTERSECT")
        # plane of each traced triangle in float64 world coordinates (scene-indexed): its unit normal, and
        # whether it is degenerate (untraced triangles count as degenerate); its vertex v₀ is read from the scene
        m = scene.n_triangles
        self.unit_normal = np.zeros((m, 3))
        self.degenerate = np.ones(m, bool)
        if len(tris):
            _triangle_planes(v, scene.triangles, np.zeros(0, np.int64) if self.triangle_ids is None
                             else self.triangle_ids, self.unit_normal, self.degenerate)

    def serves(self, scene: SceneGeometry) -> bool:
        """True if this BVH was built on ``scene``'s geometry (the same vertex and triangle arrays): material
        overrides (``SceneGeometry.with_overrides``) share the arrays, so they reuse the BVH."""
        return (self.triangle_ids is None and _same_view(self.scene.vertices_m, scene.vertices_m)
                and _same_view(self.scene.triangles, scene.triangles))

    def bare_cast(self, origin_m, directions):
        """The bare embreex ray cast (the benchmarks' floor): Embree's primitive ids (−1 on a miss; indices into
        the traced subset when the BVH holds one), no refinement."""
        o = np.broadcast_to((np.asarray(origin_m) - self.reference_m).astype(np.float32), directions.shape)
        if self._embree is None:
            return np.full(len(directions), -1, np.int32)
        return np.asarray(self._embree.run(np.ascontiguousarray(o), np.ascontiguousarray(directions, np.float32),
                                           query="INTERSECT"), dtype=np.int32)

    def intersect(self, origin_m, directions, max_range_m=None, normals_out=None):
        """Trace rays along unit directions (n, 3) float64 from one origin (3,), one origin per ray (n, 3), or one
        origin per group of consecutive rays (n/k, 3) — the k sub-rays of a beam — (world, float64).
        ``max_range_m`` (n,), optional: Embree looks for each ray's nearest hit up to that distance only (its
        float32 distance; a caller that needs every hit up to a range adds a margin for the float32 rounding).

        Returns (prim (n,) int32, −1 on a miss; range_m (n,) float64, NaN on a miss; cos_theta (n,) float64,
        the cosine of the incidence angle, |d·n|, 0 on a miss).  ``normals_out`` (n, 3) float64, optional: filled
        with each hit's world-frame unit normal (``unit_normal[prim]``, read once by the refinement; rows of
        misses are left as they were), so a later stage need not look the hit triangles up again.
        """
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        origins = np.ascontiguousarray(np.asarray(origin_m, dtype=np.float64).reshape(-1, 3))
        n = len(directions)
        if (len(origins) == 0 and n) or (len(origins) and n % len(origins)):
            raise ValueError(f"{len(origins)} ray origins for {n} rays: one origin, one per ray, or one per group "
                             "of consecutive rays")
        k = n // len(origins) if len(origins) else 0
        o32, d32 = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
        _rays_float32(origins, k, np.asarray(self.reference_m, np.float64), directions, o32, d32)
        if self._embree is None:
            prim = np.full(n, -1, np.int32)
        else:
            far = None if max_range_m is None else np.ascontiguousarray(max_range_m, dtype=np.float32)
            prim = np.asarray(self._embree.run(o32, d32, dists=far, query="INTERSECT"), dtype=np.int32)
        del o32, d32
        range_m, cos_theta = np.empty(n), np.empty(n)
        ids = self.triangle_ids if self.triangle_ids is not None else np.zeros(0, np.int64)
        normals = np.zeros((0, 3)) if normals_out is None else normals_out
        if normals.shape[0] not in (0, n) or normals.dtype != np.float64:
            raise ValueError("normals_out needs (n, 3) float64, one row per ray")
        _refine_hits(prim, ids, self.degenerate, self.unit_normal, self.scene.vertices_m, self.scene.triangles,
                     origins, k, directions, range_m, cos_theta, normals)
        return prim, range_m, cos_theta


@kernel
def _rays_float32(origins, k, reference, directions, o32, d32):
    """The float32 rays Embree traces: origins (one per group of k consecutive rays) relative to the BVH's
    reference point."""
    for g in range(origins.shape[0]):
        for i in range(g * k, (g + 1) * k):
            for c in range(3):
                o32[i, c] = origins[g, c] - reference[c]
                d32[i, c] = directions[i, c]


@kernel
def _triangle_planes(vertices, triangles, ids, unit_normal, degenerate):
    """Unit normal n = (v₁ − v₀) × (v₂ − v₀) / |…| of the triangles ``ids`` (all when empty) and
    whether each is degenerate (|…| = 0; its cross product is then left unscaled), each term rounded as NumPy's
    ``cross``, ``linalg.norm`` ((x² + y²) + z²) and division round it (no whole-scene temporaries)."""
    every = ids.shape[0] == 0
    for i in range(triangles.shape[0] if every else ids.shape[0]):
        p = i if every else ids[i]
        i0, i1, i2 = triangles[p, 0], triangles[p, 1], triangles[p, 2]
        x0, y0, z0 = vertices[i0, 0], vertices[i0, 1], vertices[i0, 2]
        ax, ay, az = vertices[i1, 0] - x0, vertices[i1, 1] - y0, vertices[i1, 2] - z0
        bx, by, bz = vertices[i2, 0] - x0, vertices[i2, 1] - y0, vertices[i2, 2] - z0
        nx = ay * bz - az * by
        ny = az * bx - ax * bz
        nz = ax * by - ay * bx
        norm = math.sqrt((nx * nx + ny * ny) + nz * nz)
        degenerate[p] = norm == 0.0
        d = norm if norm != 0.0 else 1.0
        unit_normal[p, 0], unit_normal[p, 1], unit_normal[p, 2] = nx / d, ny / d, nz / d


@kernel
def _refine_hits(prim, triangle_ids, degenerate, unit_normal, vertices, triangles, origins, k, directions, range_m,
                 cos_theta, normal_out):
    """The float64 refinement of Embree's hits, in place (``prim``: Embree's primitive ids, turned into the
    scene's triangle indices through ``triangle_ids`` when the BVH holds a subset): a hit on a degenerate
    triangle, or whose plane lies behind the origin, becomes a miss (prim −1); otherwise range
    t = ((v₀ − o)·n)/(d·n) along the ray and cos θ = |d·n| on the hit triangle's plane (unit normal n, first
    vertex v₀), o the origin of the ray's group of k.  Each dot product is summed as (x₀y₀ + x₂y₂) + x₁y₁, the
    order of NumPy's einsum over three components.  ``normal_out`` (n, 3), or (0, 3) for none: each hit's n."""
    mapped = triangle_ids.shape[0] > 0
    normals = normal_out.shape[0] > 0
    for g in range(origins.shape[0]):
        for i in range(g * k, (g + 1) * k):
            _refine_hit(prim, i, g, mapped, triangle_ids, degenerate, unit_normal, vertices, triangles, origins,
                        directions, range_m, cos_theta, normals, normal_out)


@kernel
def _refine_hit(prim, i, r, mapped, triangle_ids, degenerate, unit_normal, vertices, triangles, origins,
                directions, range_m, cos_theta, normals, normal_out):
    range_m[i], cos_theta[i] = np.nan, 0.0
    p = prim[i]
    if p < 0:
        return
    if mapped:
        p = triangle_ids[p]
        prim[i] = p
    if degenerate[p]:
        prim[i] = -1
        return
    n0, n1, n2 = unit_normal[p, 0], unit_normal[p, 1], unit_normal[p, 2]
    v = triangles[p, 0]
    dn = (directions[i, 0] * n0 + directions[i, 2] * n2) + directions[i, 1] * n1
    wn = (((vertices[v, 0] - origins[r, 0]) * n0 + (vertices[v, 2] - origins[r, 2]) * n2)
          + (vertices[v, 1] - origins[r, 1]) * n1)
    t = wn / (dn if dn != 0.0 else np.inf)
    if t > 0:
        range_m[i] = t
        cos_theta[i] = abs(dn)
        if normals:
            normal_out[i, 0], normal_out[i, 1], normal_out[i, 2] = n0, n1, n2
    else:
        prim[i] = -1
