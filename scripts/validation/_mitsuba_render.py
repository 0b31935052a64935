"""Render an exported profiler scene with Mitsuba 3 + mitransient (run by .venv-validation's Python, never by .venv).

    .venv-validation/bin/python scripts/validation/_mitsuba_render.py SCENE_DIR OUT.npz
    .venv-validation/bin/python scripts/validation/_mitsuba_render.py --check

SCENE_DIR is written by ``scripts/validation/transient.py`` (``export_mitsuba_scene``): ``scene.json`` (the sensor's
pose and field of view, the film, the time window, the sample counts, one entry per material) and one PLY mesh
per material.  This script imports nothing of the project: everything it knows of the simulator's scene is in
those files.

The scene: a pinhole ``perspective`` sensor at the ladar's pose with its field of view, a ``point`` emitter of
radiant intensity 1 W/sr at the same point (the monostatic transmitter), ``transient_path`` with
``max_depth = 2`` (one bounce, as the laser radar equation), a ``transient_hdr_film`` histogramming the optical
path length (emitter → surface → sensor) in the bins given.  Materials: ``lambert`` → Mitsuba's own ``diffuse``
BSDF (two-sided); ``table`` → :class:`MonostaticTable`, a BSDF written here that interpolates f_r(θ) [1/sr]
tabulated against the angle θ between the surface normal and the half vector of the two directions (for the
monostatic geometry θ is the incidence angle), two-sided.

Output: ``transient`` (batches, bins) — the mean over the film's pixels of the pixel radiance [W m⁻² sr⁻¹ per
1 W/sr of emitter] in each path-length bin, one row per independent batch (its own seed); ``steady`` (batches,)
the same summed over time; the settings used.
"""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

os.environ.setdefault("MI_DEFAULT_VARIANT", "llvm_ad_mono")
VARIANT = "llvm_ad_mono"


def _setup():
    import mitsuba as mi
    mi.set_variant(VARIANT)
    import drjit as dr
    import mitransient  # noqa: F401  (registers transient_path, transient_hdr_film)

    class MonostaticTable(mi.BSDF):
        """f_r(θ_h) from a table (θ_h in degrees, uniform steps from 0), linear interpolation; two-sided; sampled
        as a cosine-weighted hemisphere (only the emitter sampling of a one-bounce path uses its value)."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.step_deg = float(props["step_deg"])
            values = np.asarray(json.loads(props["values"]), dtype=np.float64)
            self.n = len(values)
            self.table = mi.Float(values.astype(np.float32))
            reflection = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [reflection]
            self.m_flags = reflection

        def _f(self, wi, wo):
            h = dr.normalize(wi + wo)
            theta = dr.acos(dr.clip(dr.abs(h.z), 0.0, 1.0)) * (180.0 / dr.pi)
            x = dr.clip(theta / self.step_deg, 0.0, self.n - 1.000001)
            i = mi.UInt32(dr.floor(x))
            w = x - mi.Float(i)
            a = dr.gather(mi.Float, self.table, i)
            b = dr.gather(mi.Float, self.table, i + 1)
            return a + w * (b - a)

        def eval(self, ctx, si, wo, active=True):
            same = (si.wi.z * wo.z) > 0
            return dr.select(active & same, self._f(si.wi, wo) * dr.abs(wo.z), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            same = (si.wi.z * wo.z) > 0
            return dr.select(active & same, mi.warp.square_to_cosine_hemisphere_pdf(mi.Vector3f(wo.x, wo.y,
                                                                                                dr.abs(wo.z))), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            wo = mi.Vector3f(wo.x, wo.y, dr.select(si.wi.z < 0, -wo.z, wo.z))
            bs = mi.BSDFSample3f()
            bs.wo = wo
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(mi.Vector3f(wo.x, wo.y, dr.abs(wo.z)))
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = 0
            value = dr.select(active & (bs.pdf > 0), self._f(si.wi, wo) * dr.abs(wo.z) / bs.pdf, 0.0)
            return bs, mi.Spectrum(value)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"MonostaticTable[{self.n} values, {self.step_deg} deg steps]"

    mi.register_bsdf("monostatic_table", lambda props: MonostaticTable(props))
    return mi, dr


def scene_dict(mi, folder, desc):
    pose = np.asarray(desc["world_from_sensor"], dtype=np.float64)
    # the ladar looks along its −Z with +Y up; Mitsuba's sensors look along +Z with +Y up: rotate by π about Y
    to_world = pose @ np.diag([-1.0, 1.0, -1.0, 1.0])
    origin = pose[:3, 3]
    d = {"type": "scene",
         "integrator": {"type": "transient_path", "max_depth": 2, "camera_unwarp": False,
                        "temporal_filter": "box"},
         "sensor": {"type": "perspective", "fov_axis": "x", "fov": float(desc["fov_x_deg"]),
                    "near_clip": float(desc["near_clip_m"]), "far_clip": float(desc["far_clip_m"]),
                    "to_world": mi.ScalarTransform4f(to_world.tolist()),
                    "sampler": {"type": "independent", "sample_count": int(desc["spp"])},
                    "film": {"type": "transient_hdr_film", "width": int(desc["pixels"]),
                             "height": int(desc["pixels"]), "temporal_bins": int(desc["bins"]),
                             "start_opl": float(desc["start_opl_m"]), "bin_width_opl": float(desc["bin_opl_m"]),
                             "rfilter": {"type": "box"}}},
         "emitter": {"type": "point", "position": [float(v) for v in origin],
                     "intensity": {"type": "spectrum", "value": 1.0}}}
    for k, m in enumerate(desc["materials"]):
        if m["kind"] == "lambert":
            bsdf = {"type": "twosided", "bsdf": {"type": "diffuse",
                                                  "reflectance": {"type": "spectrum", "value": m["reflectance"]}}}
        elif m["kind"] == "table":
            bsdf = {"type": "monostatic_table", "step_deg": float(m["step_deg"]), "values": json.dumps(m["values"])}
        else:
            raise ValueError(f"material {k}: kind = {m['kind']!r}: allowed lambert, table")
        d[f"mesh_{k}"] = {"type": "ply", "filename": os.path.join(folder, m["mesh"]), "face_normals": True,
                          "bsdf": bsdf}
    return d


def render(folder, out):
    mi, dr = _setup()
    desc = json.loads(open(os.path.join(folder, "scene.json"), encoding="utf-8").read())
    if int(desc.get("threads", 0)) > 0:
        dr.set_thread_count(int(desc["threads"]))
    scene = mi.load_dict(scene_dict(mi, folder, desc))
    rows, steady = [], []
    t0 = time.perf_counter()
    for b in range(int(desc["batches"])):
        st, tr = mi.render(scene, seed=int(desc["seed"]) + 7919 * b, spp=int(desc["spp"]))
        tr = np.asarray(tr, dtype=np.float64)  # (height, width, bins, channels)
        rows.append(tr[..., 0].mean(axis=(0, 1)))
        steady.append(float(np.asarray(st, dtype=np.float64)[..., 0].mean()))
    np.savez(out, transient=np.asarray(rows), steady=np.asarray(steady), seconds=time.perf_counter() - t0,
             mitsuba=mi.MI_VERSION, variant=VARIANT, settings=json.dumps({k: v for k, v in desc.items()
                                                                          if k != "materials"}))


def check():
    """Exit 0 and print the versions when Mitsuba, its LLVM backend and mitransient work; else the reason."""
    mi, dr = _setup()
    import mitransient
    x = dr.arange(mi.Float, 4) * 2.0  # runs a kernel on the LLVM backend
    assert float(dr.sum(x)[0] if hasattr(dr.sum(x), "__len__") else dr.sum(x)) == 12.0
    print(f"mitsuba {mi.MI_VERSION}, drjit {dr.__version__}, mitransient {mitransient.__version__}, "
          f"variant {VARIANT}: ok")


if __name__ == "__main__":
    if sys.argv[1:] == ["--check"]:
        check()
    elif len(sys.argv) == 3:
        render(sys.argv[1], sys.argv[2])
    else:
        sys.exit(__doc__)
