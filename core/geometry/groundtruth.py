"""Ground truth of simulated points: the scene material each point lies on (LAS classification, metadata).

A point is an echo placed along a line of sight from the sensor (a flash pixel's centre ray, a scanner pulse's
axis), but its energy came from the whole pixel or beam footprint.  Its ground truth is the surface crossed
nearest to the point's range by the line of sight or, when that line crosses none near the point (the edge of
an object), by 8 lines around it at ``spread_rad`` (the footprint's half-width: half a pixel, half the beam
divergence), each traced from the sensor through every surface it meets (up to ``max_surfaces``) until a crossing
at or past the point, and no farther than a crossing can still win (a later crossing lies farther from the point
and cannot win): the crossing whose range is
closest to the point's wins if it lies within ``tolerance_m``; otherwise the point has no surface (−1), as a
false alarm in empty air.  A footprint much wider than the objects in it (the profiler's one element over the
whole field of view) can hold an object that neither the centre line nor the 8 lines at its rim cross: with
``fill_rings`` = R > 0 the points still unlabelled then trace R rings filling the footprint (ring k of R at
``spread_rad`` × k/R, 8k lines: an even density over the disc), and the nearest crossing over all of them wins.
The points are independent: labelled in parts on the run's threads.  Never imports
bpy.
"""
from __future__ import annotations

import numpy as np

from ..threads import map_list

NO_SURFACE = -1
#: Step past a crossed surface before tracing on (m): above the float32 BVH's resolution at kilometres.
STEP_PAST_M = 1e-3
#: Lines of sight traced only as far as a crossing can still win: a line ends at its first crossing at or past
#: the point, and each cast looks no farther than the point's range plus the best error so far (at most the
#: tolerance), with a margin for Embree's float32 distances.  The same labels as tracing every line on to the
#: tolerance and beyond (tests/core/engine/test_planner.py; False only for that test's reference).
PRUNE_LINES = True
#: The margin on a cast's reach: relative, and absolute (m), far above float32 rounding at 100 km (≈ 8 mm).
REACH_MARGIN_REL, REACH_MARGIN_M = 1e-5, 0.05
#: Fewest points a thread labels at a time, and the parts a thread gets when there are enough points: one (the
#: NumPy work on a part holds the GIL; four parts a thread were slower on 2 threads than 1 thread, one faster:
#: 14k flash points 42-44 → 26-38 ms with a free second core).
MIN_PART, PARTS_PER_THREAD = 2048, 1


def surface_material_ids(tracer, material_ids, origin, position, tolerance_m: float, spread_rad: float = 0.0,
                         max_surfaces: int = 8, threads: int = 1, fill_rings: int = 0) -> np.ndarray:
    """Material index (int16, −1 for none) of the surface under each point (module docstring).

    ``tracer``: a :class:`core.trace.SceneTracer` of the scene; ``material_ids``: the scene's material index per
    triangle; ``origin``: the sensor position (3,) or one per point (n, 3); ``position``: the points (n, 3),
    world coordinates (m).  ``fill_rings``: rings of lines filling the footprint for the points its rim leaves
    unlabelled (0: none).  ``threads``: the points are labelled in parts of at least ``MIN_PART`` points on up
    to that many threads of the shared pool (core/threads.py); each point's label does not depend on the parts.
    """
    position = np.asarray(position, dtype=np.float64).reshape(-1, 3)
    origin = np.broadcast_to(np.asarray(origin, dtype=np.float64), position.shape)
    n = len(position)
    parts = max(1, min(int(threads) * PARTS_PER_THREAD, n // MIN_PART))
    if parts == 1:
        return _material_ids(tracer, material_ids, origin, position, tolerance_m, spread_rad, max_surfaces,
                             fill_rings)
    bounds = [(n * i // parts, n * (i + 1) // parts) for i in range(parts)]
    out = map_list(lambda ab: _material_ids(tracer, material_ids, origin[ab[0]:ab[1]], position[ab[0]:ab[1]],
                                            tolerance_m, spread_rad, max_surfaces, fill_rings), bounds, threads)
    return np.concatenate(out)


def _material_ids(tracer, material_ids, origin, position, tolerance_m, spread_rad, max_surfaces, fill_rings=0):
    best_err, best_prim = _nearest_crossing(tracer, origin, position, tolerance_m, max_surfaces, None)
    # the lines around the centre only for points whose centre line found no surface (edges of objects)
    rest = np.flatnonzero(~(best_err <= tolerance_m))
    if spread_rad > 0 and len(rest):
        sub_err, sub_prim = _around(tracer, origin[rest], position[rest], tolerance_m, spread_rad, max_surfaces)
        best_err[rest], best_prim[rest] = sub_err, sub_prim
    rest = np.flatnonzero(~(best_err <= tolerance_m))
    if spread_rad > 0 and fill_rings > 0 and len(rest):  # the footprint's inside, ring by ring
        for k in range(1, int(fill_rings) + 1):
            sub_err, sub_prim = _around(tracer, origin[rest], position[rest], tolerance_m,
                                        spread_rad * k / fill_rings, max_surfaces, lines=8 * k)
            better = sub_err < best_err[rest]
            best_err[rest[better]], best_prim[rest[better]] = sub_err[better], sub_prim[better]
    out = np.full(len(position), NO_SURFACE, np.int16)
    found = (best_prim >= 0) & (best_err <= tolerance_m)
    out[found] = np.asarray(material_ids)[best_prim[found]]
    return out


def _around(tracer, origin, position, tolerance_m, spread_rad, max_surfaces, lines=8):
    """The nearest crossing over ``lines`` lines at ``spread_rad`` around each point's line of sight."""
    best_err = np.full(len(position), np.inf)
    best_prim = np.full(len(position), -1, np.int64)
    axis = position - origin
    axis /= np.maximum(np.linalg.norm(axis, axis=1), 1e-300)[:, None]
    helper = np.where(np.abs(axis[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u, axis=1)[:, None]
    v = np.cross(axis, u)
    for phi in np.arange(lines) * (2.0 * np.pi / lines):
        d = axis + np.tan(spread_rad) * (np.cos(phi) * u + np.sin(phi) * v)
        d /= np.linalg.norm(d, axis=1)[:, None]
        err, prim = _nearest_crossing(tracer, origin, position, tolerance_m, max_surfaces, d)
        better = err < best_err
        best_err[better], best_prim[better] = err[better], prim[better]
    return best_err, best_prim


def _nearest_crossing(tracer, origin, position, tolerance_m, max_surfaces, direction):
    """(|range error| (n,), triangle (n,), −1 for none) of the crossing nearest to each point's range along
    ``direction`` (default: towards the point)."""
    n = len(position)
    delta = position - origin
    target = np.linalg.norm(delta, axis=1)
    ok = target > 0
    if direction is None:
        direction = np.zeros((n, 3))
        direction[ok] = delta[ok] / target[ok, None]
    best_err = np.full(n, np.inf)
    best_prim = np.full(n, -1, np.int64)
    travelled = np.zeros(n)
    active = np.flatnonzero(ok)
    for _ in range(max_surfaces):
        if len(active) == 0:
            break
        start = origin[active] + direction[active] * travelled[active, None]
        reach = None
        if PRUNE_LINES:  # a crossing beyond the point's range + min(best error, tolerance) cannot change the label
            bound = target[active] + np.minimum(best_err[active], tolerance_m) - travelled[active]
            reach = bound * (1.0 + REACH_MARGIN_REL) + REACH_MARGIN_M
        prim, rng, _ = tracer.intersect(start, np.ascontiguousarray(direction[active]), max_range_m=reach)
        hit = prim >= 0
        total = travelled[active] + np.where(hit, rng, np.inf)
        err = np.abs(total - target[active])
        better = hit & (err < best_err[active])
        best_err[active[better]] = err[better]
        best_prim[active[better]] = prim[better]
        # a line goes on past a crossing before the point (up to ``tolerance_m`` past it, without
        # PRUNE_LINES): a crossing at or past the point ends it, since every later crossing lies farther from the
        # point (its range exceeds this one's by ≥ STEP_PAST_M) and cannot win; the labels are the same
        go_on = hit & (total < target[active] + (0.0 if PRUNE_LINES else tolerance_m))
        travelled[active[go_on]] = total[go_on] + STEP_PAST_M
        active = active[go_on]
    return best_err, best_prim
