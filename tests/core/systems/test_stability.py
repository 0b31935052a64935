"""Numerical stability of the flash pipeline over and past the sane ranges of docs/theory.md §13 (hypothesis)."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.config.settings import BRDFSettings
from core.systems.flash import simulate_frame
from core.geometry.scene import SceneGeometry
from scenes import C, config_for, plate

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _finite_products(res):
    assert np.all(np.isfinite(res.energy_image)) and np.all(res.energy_image >= 0)
    assert np.all(np.isfinite(res.waveforms)) and np.all(res.waveforms >= 0)
    assert np.all(np.isfinite(res.intensity_image)) and np.all(res.intensity_image >= 0)
    r = res.range_image
    assert np.all(np.isnan(r) | (np.isfinite(r) & (r > 0)))
    for name, arr in res.points.items():
        if arr.dtype.kind == "f":
            assert np.all(np.isfinite(arr)), name


@FAST
@given(range_m=st.floats(1.0, 50_000.0), tilt_deg=st.floats(0.0, 89.99),
       energy_j=st.sampled_from([1e-12, 1e-6, 1e-3, 10.0, 100.0]),
       extinction=st.sampled_from([0.0, 1e-5, 1e-3, 2e-2, 1.0]),
       fwhm_s=st.sampled_from([1e-11, 1e-10, 5e-9, 1e-7]),
       shape=st.sampled_from(["gaussian", "rectangular"]),
       brdf=st.sampled_from([BRDFSettings(), BRDFSettings(model="steinvall", specular_a=50.0, slope_s=0.01,
                                                          diffuse_b=1e-3, diffuse_m=3.0)]))
def test_no_nan_or_negative_energy_anywhere(range_m, tilt_deg, energy_j, extinction, fwhm_s, shape, brdf):
    """Ranges 1 m – 50 km, incidence up to 89.99°, pulses much shorter than a bin and longer than the gate,
    pulse energies 1e-12 – 100 J, extinction 0 – 1 /m: every product is finite and non-negative."""
    cfg = config_for(range_m, pixels=4, subsamples=2, bins=64, bin_s=1e-9, margin_bins=32)
    cfg.laser.pulse_energy_j = energy_j
    cfg.laser.pulse_fwhm_s = fwhm_s
    cfg.laser.pulse_shape = shape
    cfg.atmosphere.extinction_per_m = extinction
    scene = plate(range_m, range_m * 0.2, brdf, tilt_rad=np.radians(tilt_deg))
    try:
        res = simulate_frame(scene, np.eye(4), cfg)
    except ValueError as exc:  # a grazing plate may be missed entirely: that must be the clear error
        assert "rays missed" in str(exc)
        return
    _finite_products(res)


@FAST
@given(range_m=st.floats(10.0, 20_000.0), sigma_lo=st.floats(0.0, 1e-3), extra=st.floats(0.0, 1e-2))
def test_more_extinction_never_gives_more_energy(range_m, sigma_lo, extra):
    """E_r is non-increasing in σ, and the ratio is exactly the extra two-way loss e^(−2ΔσR) (uniform plate)."""
    cfg = config_for(range_m, pixels=2, subsamples=2)
    cfg.laser.beam_profile = "uniform"
    scene = plate(range_m, range_m * 0.1)
    cfg.atmosphere.extinction_per_m = sigma_lo
    e_lo = simulate_frame(scene, np.eye(4), cfg).energy_image
    cfg.atmosphere.extinction_per_m = sigma_lo + extra
    e_hi = simulate_frame(scene, np.eye(4), cfg).energy_image
    assert np.all(e_hi <= e_lo)
    # the ratio per pixel is e^(−2Δσ R_i) with R_i ≥ range_m (off-axis rays are longer)
    ratio = e_hi.sum() / e_lo.sum() if e_lo.sum() > 0 else 0.0
    assert ratio <= np.exp(-2 * extra * range_m) * (1 + 1e-9)


@FAST
@given(offset_km=st.floats(-10.0, 10.0), distance_m=st.floats(50.0, 3000.0))
def test_far_from_origin_keeps_millimetre_range(offset_km, distance_m):
    """A scene and sensor 10 km from the origin: range error stays below 1 mm (float64 refinement of the
    float32 BVH hit)."""
    shift = np.array([offset_km * 1000.0, -offset_km * 700.0, offset_km * 300.0])
    base = plate(distance_m, distance_m * 0.05)
    scene = SceneGeometry(base.vertices_m + shift, base.triangles, base.material_ids)
    pose = np.eye(4)
    pose[:3, 3] = shift
    cfg = config_for(distance_m, pixels=4, subsamples=2, fov_rad=0.002, bin_s=0.5e-9)
    res = simulate_frame(scene, pose, cfg)
    center = np.abs(res.points["position_sensor"][:, 2] + distance_m)
    assert center.max() < 1e-3


def test_degenerate_and_coincident_triangles():
    """Zero-area triangles are never hit (no NaN normal); a duplicated (coincident) plate gives the same energy
    as one plate (each ray takes one hit)."""
    base = plate(100.0, 10.0)
    v = np.concatenate([base.vertices_m, [[0, 0, -50.0], [0, 0, -50.0], [1, 0, -50.0]]])
    tris = np.concatenate([base.triangles, [[4, 5, 6], [0, 0, 0]]])
    scene = SceneGeometry(v, tris, np.zeros(len(tris)))
    cfg = config_for(100.0, pixels=8)
    res = simulate_frame(scene, np.eye(4), cfg)
    ref = simulate_frame(base, np.eye(4), cfg)
    _finite_products(res)
    assert res.energy_image.sum() == pytest.approx(ref.energy_image.sum(), rel=1e-12)
    dup = SceneGeometry(np.concatenate([base.vertices_m, base.vertices_m]),
                        np.concatenate([base.triangles, base.triangles + 4]), np.zeros(4))
    assert simulate_frame(dup, np.eye(4), cfg).energy_image.sum() == pytest.approx(ref.energy_image.sum(),
                                                                                    rel=1e-12)
