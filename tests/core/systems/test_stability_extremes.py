"""Numerical stability past docs/theory.md §13 (issue 7), with every sub-ray pattern and the cell range spread:
property-based (hypothesis, few examples each so the suite stays fast) and worked extremes.

Extends tests/core/test_stability.py (NaN/Inf over ranges, incidence, energies, extinction, pulses; extinction
monotonicity; 10 km offsets with the grid; degenerate and coincident triangles)."""
import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.config.settings import BRDFSettings, LaserSettings
from core.errors import ConfigError
from core.physics.laser import cell_energy_fractions, pulse_box_cdf, pulse_sigma_s, sorted_spreads
from core.systems.flash import simulate_frame
from core.geometry.rays import Detector
from core.physics.sampling import SubraySampler
from core.geometry.scene import SceneGeometry, merge_meshes
from scenes import C, config_for, plate

FEW = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
PATTERNS = st.sampled_from(["grid", "stratified", "sobol", "adaptive"])


def _finite_products(res):
    assert np.all(np.isfinite(res.energy_image)) and np.all(res.energy_image >= 0)
    if res.waveforms is not None:
        assert np.all(np.isfinite(res.waveforms)) and np.all(res.waveforms >= 0)
    assert np.all(np.isfinite(res.intensity_echoes)) and np.all(res.intensity_echoes >= 0)
    r = res.range_echoes
    assert np.all(np.isnan(r) | (np.isfinite(r) & (r > 0)))
    for name, arr in res.points.items():
        if arr.dtype.kind == "f":
            assert np.all(np.isfinite(arr)), name


def _radar_equation_j(cfg, range_m, reflectance, extinction_per_m):
    """Paper eq. 3-1, Lambertian plate at normal incidence filling the field of view, uniform beam:
    E_T η (ρ/π) (π r_a²/(R² + r_a²)) e^(−2σR) (the aperture's projected solid angle, core/physics/radiometry.py)."""
    r_a = cfg.receiver.aperture_diameter_m / 2
    return (cfg.laser.pulse_energy_j * cfg.receiver.system_efficiency * reflectance / np.pi
            * np.pi * r_a ** 2 / (range_m ** 2 + r_a ** 2) * np.exp(-2 * extinction_per_m * range_m))


@FEW
@given(range_m=st.floats(1.0, 50_000.0), log_energy=st.floats(-12.0, 2.0), reflectance=st.floats(0.01, 1.0),
       extinction=st.sampled_from([0.0, 1e-5, 1e-3, 1e-2]), pattern=PATTERNS)
def test_radar_equation_holds_noise_free(range_m, log_energy, reflectance, extinction, pattern):
    """Ranges 1 m – 50 km, pulse energies 1e-12 – 100 J, extinction up to 1e-2 /m (e^(−1000) at 50 km: below
    float64, then both sides are 0): the received energy of a plate filling a 1 mrad field of view is eq. 3-1
    within 1e-4 (the off-axis cos/R² factors differ by O(fov²)), whatever the sub-ray pattern; the waveform
    holds that energy unless the pulse starts before the gate can open (t < 0, ranges under ≈ 2 m)."""
    cfg = config_for(range_m, pixels=4, subsamples=2, fov_rad=1e-3, bins=64, bin_s=1e-9, margin_bins=32)
    cfg.laser.beam_profile = "uniform"
    cfg.laser.pulse_energy_j = 10.0 ** log_energy
    cfg.atmosphere.extinction_per_m = extinction
    cfg.receiver.subray_pattern = pattern
    res = simulate_frame(plate(range_m, range_m * 0.01, BRDFSettings(reflectance=reflectance)), np.eye(4), cfg)
    _finite_products(res)
    expected = _radar_equation_j(cfg, range_m, reflectance, extinction)
    got = res.energy_image.sum()
    if expected < 1e-290:
        assert got < 1e-280
        return
    assert got == pytest.approx(expected, rel=1e-4)
    if 2 * range_m / C > 7 * pulse_sigma_s(cfg.laser):  # the gate (opening at t ≥ 0) holds the whole pulse
        assert res.waveforms.sum(dtype=np.float64) == pytest.approx(got, rel=1e-5)


@FEW
@given(cn2=st.sampled_from([0.0, 1e-17, 1e-15, 1e-13, 1e-12, 1e-11]), range_m=st.floats(100.0, 20_000.0),
       pattern=PATTERNS, seed=st.integers(0, 2 ** 32))
def test_turbulence_from_none_to_past_strong_stays_finite(cn2, range_m, pattern, seed):
    """Cn² 0 – 1e-11 (past the 1e-12 of docs/theory.md §13), every turbulence effect on: no NaN/Inf, energies ≥ 0."""
    cfg = config_for(range_m, pixels=8, subsamples=2, fov_rad=2e-3, bins=96, margin_bins=40)
    cfg.laser.divergence_fills_fov = False
    cfg.laser.beam_divergence_rad = 1e-3
    cfg.atmosphere.cn2_m_23 = cn2
    cfg.receiver.subray_pattern = pattern
    cfg.run.seed = seed
    _finite_products(simulate_frame(plate(range_m, range_m * 0.01), np.eye(4), cfg))


@FEW
@given(range_m=st.floats(10.0, 20_000.0), vis_lo=st.floats(50.0, 1e6), factor=st.floats(1.0, 100.0))
def test_lower_visibility_never_gives_more_energy(range_m, vis_lo, factor):
    """Visibility 50 m – 1000 km (docs/theory.md §6 models, far past the 0.2–50 km of §13):
    finite products, and the received energy never grows when the visibility drops."""
    cfg = config_for(range_m, pixels=2, subsamples=2, fov_rad=1e-3)
    scene = plate(range_m, range_m * 0.01)
    energies = []
    for vis in (min(vis_lo * factor, 1e6), vis_lo):
        cfg.atmosphere.visibility_m = vis
        res = simulate_frame(scene, np.eye(4), cfg)
        _finite_products(res)
        energies.append(res.energy_image.sum())
    assert energies[1] <= energies[0]


@FEW
@given(fwhm_s=st.sampled_from([1e-12, 1e-11, 1e-6]), tilt_deg=st.floats(0.0, 89.9), pattern=PATTERNS,
       shape=st.sampled_from(["gaussian", "rectangular"]))
def test_pulse_far_shorter_than_a_bin_or_longer_than_the_gate(fwhm_s, tilt_deg, pattern, shape):
    """1 ps pulses in 1 ns bins keep all the energy in the waveform (bin integrals, cell spread or not); a 1 µs
    pulse against a 64 ns gate leaves in it exactly the pulse fraction inside the gate (≤ 1/10 here)."""
    d = 200.0
    cfg = config_for(d, pixels=4, subsamples=2, fov_rad=1e-3, bins=64, bin_s=1e-9, margin_bins=32)
    cfg.laser.pulse_fwhm_s = fwhm_s
    cfg.laser.pulse_shape = shape
    cfg.receiver.subray_pattern = pattern
    scene = plate(d, 5.0, tilt_rad=np.radians(tilt_deg))
    try:
        res = simulate_frame(scene, np.eye(4), cfg)
    except ConfigError as exc:  # a grazing plate may be missed entirely: that must be the clear error
        assert exc.field == "sensor"
        return
    _finite_products(res)
    e, wf = res.energy_image.sum(), res.waveforms.sum(dtype=np.float64)
    if fwhm_s < 1e-9:
        if tilt_deg < 80:  # the whole return lies inside the gate
            assert wf == pytest.approx(e, rel=1e-6)
    else:
        assert wf <= 0.1 * e


def test_zero_tiny_and_huge_pulse_energies():
    """0 J is refused naming laser.pulse_energy_j; 1e-300 J gives finite, non-negative products (the radar
    equation underflows to tiny or zero energies, never NaN); the energy scales exactly linearly up to 100 J."""
    cfg = config_for(100.0, pixels=4)
    cfg.laser.pulse_energy_j = 0.0
    with pytest.raises(ConfigError) as info:
        simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
    assert info.value.field == "laser.pulse_energy_j"
    energies = {}
    for e in (1e-300, 1.0, 100.0):
        cfg.laser.pulse_energy_j = e
        res = simulate_frame(plate(100.0, 10.0), np.eye(4), cfg)
        _finite_products(res)
        energies[e] = res.energy_image
    assert np.allclose(energies[100.0], 100.0 * energies[1.0], rtol=1e-13, atol=0)
    assert energies[1e-300].sum() <= 1e-290


@settings(max_examples=60, deadline=None)
@given(a_sigma=st.floats(0.0, 1e6), b_sigma=st.floats(0.0, 1e3), t_sigma=st.floats(-1e7, 1e7),
       shape=st.sampled_from(["gaussian", "rectangular"]))
def test_pulse_box_cdf_is_a_cdf_for_any_spread(a_sigma, b_sigma, t_sigma, shape):
    """Box widths 0 – 1e6 σ (grazing cells), any time: the CDF is finite, in [0, 1], non-decreasing and
    symmetric F(t) + F(−t) = 1 (1e-12)."""
    laser = LaserSettings(pulse_shape=shape, pulse_fwhm_s=5e-9)
    sigma = pulse_sigma_s(laser)
    spread = sorted_spreads(laser, np.array([[a_sigma * sigma, b_sigma * sigma]]))
    t = t_sigma * sigma + np.array([[-1e-9, 0.0, 1e-9]])
    f = pulse_box_cdf(laser, np.concatenate([t, -t], axis=1), spread)[0]
    assert np.all(np.isfinite(f)) and np.all((f >= 0) & (f <= 1))
    assert f[0] <= f[1] <= f[2]
    assert f[:3] + f[3:] == pytest.approx(np.ones(3), abs=1e-12)


@FEW
@given(pattern=st.sampled_from(["grid", "stratified", "sobol"]), s=st.integers(1, 9), seed=st.integers(0, 2 ** 40),
       offset=st.tuples(st.floats(-0.02, 0.02), st.floats(-0.02, 0.02)), scale=st.floats(0.2, 5.0))
def test_every_pattern_carries_the_exact_pixel_energy(pattern, s, seed, offset, scale):
    """Any pattern, S, seed, beam offset (wander) and width (broadening): each pixel's weights sum to the erf
    energy of the beam over the pixel (1e-12), and the detector's to the erf energy over the field of view."""
    laser = LaserSettings(divergence_fills_fov=False, beam_divergence_rad=0.01)
    det = Detector(5, 3, s, 0.01, 0.006)
    fx, fy = cell_energy_fractions(laser, det, offset, scale)
    smp = SubraySampler(det, pattern, (fx, fy), seed, laser=laser, beam_offset_tan=offset,
                        beam_width_scale=scale).block(0, det.n_pixels)
    sums = np.bincount(smp.pixel, weights=smp.weight, minlength=det.n_pixels)
    ix, iy = np.arange(det.n_pixels) % 5, np.arange(det.n_pixels) // 5
    exact = fx.reshape(5, s).sum(1)[ix] * fy.reshape(3, s).sum(1)[iy]
    assert np.allclose(sums, exact, rtol=1e-12, atol=1e-300)
    assert sums.sum() == pytest.approx(fx.sum() * fy.sum(), rel=1e-12)


@FEW
@given(offset_km=st.floats(-10.0, 10.0), distance_m=st.floats(50.0, 3000.0), pattern=PATTERNS,
       tilt_deg=st.floats(0.0, 60.0))
def test_far_from_the_origin_keeps_millimetre_range_with_every_pattern(offset_km, distance_m, pattern, tilt_deg):
    """The same tilted plate and sensor at the origin and moved up to 10 km away, any pattern (jittered rays
    evaluated at their cell centre on the hit plane), FOV culling on: every echo range agrees within 1 mm and
    the energies within 1e-9 (float64 refinement of the float32 BVH hit; docs/theory.md §13)."""
    shift = np.array([offset_km * 1000.0, -offset_km * 700.0, offset_km * 300.0])
    base = plate(distance_m, distance_m * 0.05, tilt_rad=np.radians(tilt_deg))
    cfg = config_for(distance_m, pixels=4, subsamples=2, fov_rad=0.002, bin_s=0.5e-9)
    cfg.receiver.subray_pattern = pattern
    here = simulate_frame(base, np.eye(4), cfg)
    pose = np.eye(4)
    pose[:3, 3] = shift
    far = simulate_frame(SceneGeometry(base.vertices_m + shift, base.triangles, base.material_ids), pose, cfg)
    assert np.array_equal(np.isnan(here.range_echoes), np.isnan(far.range_echoes))
    assert np.nanmax(np.abs(here.range_echoes - far.range_echoes)) < 1e-3
    assert far.energy_image == pytest.approx(here.energy_image, rel=1e-9)


def test_non_manifold_degenerate_and_coincident_geometry():
    """A fan of three triangles on one edge (non-manifold), zero-area and collinear triangles, and two
    coincident plates of different materials: products finite, each ray takes one hit, and the coincident
    plates give an energy between the two materials' own (never their sum)."""
    base = plate(100.0, 10.0)
    fan_v = np.array([[-1.0, -1.0, -90.0], [1.0, -1.0, -90.0], [0.0, 1.0, -92.0], [0.0, 1.0, -88.0],
                      [0.0, 1.5, -90.0], [3.0, 0.0, -90.0], [3.0, 0.0, -90.0], [4.0, 0.0, -90.0],
                      [5.0, 0.0, -90.0], [6.0, 0.0, -90.0]])
    fan_t = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4], [5, 6, 7], [7, 8, 9], [5, 5, 5]])
    scene = merge_meshes([(base.vertices_m, base.triangles, base.material_ids, ["plate"], [BRDFSettings()]),
                          (fan_v, fan_t, np.zeros(len(fan_t)), ["fan"], [BRDFSettings(reflectance=0.9)])])
    for pattern in ("grid", "sobol", "adaptive"):
        cfg = config_for(100.0, pixels=8, fov_rad=0.05, margin_bins=40)
        cfg.receiver.subray_pattern = pattern
        _finite_products(simulate_frame(scene, np.eye(4), cfg))
    dark = plate(100.0, 10.0, BRDFSettings(reflectance=0.1))
    bright = plate(100.0, 10.0, BRDFSettings(reflectance=0.5))
    both = merge_meshes([(dark.vertices_m, dark.triangles, dark.material_ids, ["dark"], dark.materials),
                         (bright.vertices_m, bright.triangles, bright.material_ids, ["bright"], bright.materials)])
    cfg = config_for(100.0, pixels=8)
    e_both = simulate_frame(both, np.eye(4), cfg).energy_image.sum()
    e_dark = simulate_frame(dark, np.eye(4), cfg).energy_image.sum()
    e_bright = simulate_frame(bright, np.eye(4), cfg).energy_image.sum()
    assert e_dark * (1 - 1e-12) <= e_both <= e_bright * (1 + 1e-12)


def test_empty_scene_and_scene_outside_the_view_give_clear_errors():
    """No triangles: ConfigError on scene.triangles; geometry entirely beside the field of view (culled to
    nothing) or behind the sensor: ConfigError on sensor saying every ray missed."""
    cfg = config_for(100.0, pixels=4)
    with pytest.raises(ConfigError) as info:
        simulate_frame(SceneGeometry(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)), np.eye(4), cfg)
    assert info.value.field == "scene.triangles"
    beside = plate(100.0, 1.0, offset=(50.0, 0.0, 0.0))
    for fov_culling in (True, False):
        with pytest.raises(ConfigError) as info:
            simulate_frame(beside, np.eye(4), cfg, fov_culling=fov_culling)
        assert info.value.field == "sensor" and "rays missed" in str(info.value)


@pytest.mark.parametrize("pattern", ["stratified", "sobol", "adaptive"])
def test_same_seed_same_products_whatever_threads_and_chunks_with_turbulence(pattern):
    """Jittered sub-rays and a scintillation pattern: the same seed gives bit-identical products for 1 or 2
    threads and any block size; another seed gives different ones (jitter and scintillation)."""
    scene = plate(1000.0, 30.0, tilt_rad=0.4)
    runs = []
    for threads, chunk, seed in ((1, 100_000_000, 5), (2, 1024, 5), (2, 1024, 6)):
        cfg = config_for(1000.0, pixels=32, subsamples=2, fov_rad=2e-3, bins=128, margin_bins=40)
        cfg.laser.divergence_fills_fov = False
        cfg.laser.beam_divergence_rad = 1e-3
        cfg.atmosphere.cn2_m_23 = 1e-14
        cfg.atmosphere.turbulence_blur = "none"
        cfg.receiver.subray_pattern = pattern
        cfg.run.threads, cfg.run.chunk_rays, cfg.run.seed = threads, chunk, seed
        runs.append(simulate_frame(scene, np.eye(4), cfg))
    a, b, other = runs
    assert b.stats["n_blocks"] > 1
    assert np.array_equal(a.waveforms, b.waveforms) and np.array_equal(a.energy_image, b.energy_image)
    assert not np.array_equal(a.energy_image, other.energy_image)


def test_full_physics_frame_is_the_same_on_any_thread_count_and_block_size():
    """Every effect at once — turbulence with footprint-averaged scintillation and the return path, visibility,
    the noisy APD with A/D (table route, counter-based streams), noisy detection and false alarms: the digital
    cube, every point field and the false-alarm record are bit-identical on 1 or 2 threads (pipeline and
    receiver) and any block size; another seed gives another cube."""
    scene = plate(1000.0, 30.0, tilt_rad=0.4)
    runs = []
    for threads, chunk, seed in ((1, 100_000_000, 5), (2, 1024, 5), (2, 1024, 6)):
        cfg = config_for(1000.0, pixels=32, subsamples=2, fov_rad=2e-2, bins=256, margin_bins=40)
        cfg.atmosphere.cn2_m_23 = 1e-14
        cfg.atmosphere.visibility_m = 10e3
        cfg.detector.mode, cfg.detector.detector_type = "noisy", "apd"
        cfg.run.threads = cfg.detector.threads = threads
        cfg.run.chunk_rays, cfg.run.seed = chunk, seed
        cfg.run.save_counts = True  # counts kept: the per-bin reference route (run.save_counts)
        runs.append(simulate_frame(scene, np.eye(4), cfg))
    a, b, other = runs
    assert b.stats["n_blocks"] > 1
    assert a.stats["atmosphere"]["turbulence"]["scintillation_pattern"]["pattern_model"] == "footprint_averaged_gamma"
    assert a.stats["receiver"]["noise_sampling"] == "table"
    assert np.array_equal(a.digital_waveforms, b.digital_waveforms)
    assert a.points.keys() == b.points.keys() and len(a.points["range_m"]) > 100
    for k in a.points:
        assert np.array_equal(a.points[k], b.points[k]), k
    assert a.stats["receiver"]["false_alarms"] == b.stats["receiver"]["false_alarms"]
    assert not np.array_equal(a.digital_waveforms, other.digital_waveforms)


@pytest.mark.parametrize("a_sigma", [1e3, 1e4, 3e4, 1e5, 1e6])
@pytest.mark.parametrize("b_sigma", [0.5, 1.0, 10.0])
def test_a_rectangular_pulse_on_a_very_wide_cell_is_exact_on_its_flat_top(a_sigma, b_sigma):
    """The cases hypothesis found for the test above (rectangular pulse, cell boxes of 1e4–1e5 σ and ~1 σ,
    t = 0): the three-box CDF was a difference of integrals losing w₁/w₃ ulps, F(0) + F(−0) = 1 − 2.3e-12
    (3.4e-11 at 1e6 σ).  Where the two narrow boxes lie inside the wide one, the CDF is the wide box's, exactly:
    F(t) = 1/2 + t/a (1e-14)."""
    laser = LaserSettings(pulse_shape="rectangular", pulse_fwhm_s=5e-9)
    sigma = pulse_sigma_s(laser)
    a = a_sigma * sigma
    spread = sorted_spreads(laser, np.array([[a, b_sigma * sigma]]))
    t = np.array([[0.0, -0.0, 0.1 * a, -0.3 * a, 0.45 * a]])
    f = pulse_box_cdf(laser, t, spread)[0]
    assert np.abs(f - (0.5 + t[0] / a)).max() <= 1e-14
