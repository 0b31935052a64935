"""Field-of-view culling: the triangles a sensor cannot see are left out of the BVH (the planner's
"objects outside the field of view are not traced").

The receiver's rays all leave the sensor origin inside the frustum |x| ≤ t_x d, |y| ≤ t_y d (sensor frame,
d = −z the depth along the line of sight, t the tangents of the half fields of view).  The frustum is the
intersection of four half-spaces through the origin; a triangle whose three vertices are all outside one of
them lies entirely outside the convex frustum and no ray can hit it.  The test is exact and conservative
(triangles that straddle a plane are kept); geometry behind the sensor falls outside two opposite planes.
Range is not culled: geometry beyond the gate still receives (and is counted in) energy, and nothing behind a
visible surface is hit anyway.
"""
from __future__ import annotations

import numpy as np

#: Relative widening of the frustum's tangents: keeps triangles grazing its side planes despite rounding.
FRUSTUM_MARGIN = 1e-6


def frustum_triangles(vertices_m, triangles, origin_m, rot, half_width_tan, half_height_tan,
                      margin: float = FRUSTUM_MARGIN):
    """Boolean mask (M,) of the triangles that may intersect the sensor frustum.

    ``rot`` is the sensor→world rotation (columns: sensor axes in world coordinates), ``origin_m`` the sensor
    position; the frustum's half fields of view are given by their tangents."""
    v = (np.asarray(vertices_m, dtype=np.float64) - np.asarray(origin_m, dtype=np.float64)) @ np.asarray(rot)
    tx = half_width_tan * (1.0 + margin)
    ty = half_height_tan * (1.0 + margin)
    depth = -v[:, 2]
    # per vertex: outside each of the four half-spaces (x ≤ t_x d, −x ≤ t_x d, y ≤ t_y d, −y ≤ t_y d)
    out = np.stack([v[:, 0] > tx * depth, -v[:, 0] > tx * depth, v[:, 1] > ty * depth, -v[:, 1] > ty * depth],
                   axis=1)
    tri = np.asarray(triangles)
    all_out = out[tri[:, 0]] & out[tri[:, 1]] & out[tri[:, 2]]  # (M, 4): every vertex outside that plane
    return ~all_out.any(axis=1)
