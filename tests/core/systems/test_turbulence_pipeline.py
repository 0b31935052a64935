"""The atmosphere stages wired into the flash pipeline (paper §3.4 A–E)."""
import numpy as np
import pytest

from core.atmosphere import (beam_wander_offsets, beam_wander_variance, derived_turbulence,
                             extinction_from_visibility, gaussian_beam_parameters, long_term_beam_radius,
                             short_term_beam_radius, turbulence_blur)
from core.systems.flash import simulate_frame
from core.engine.rng import stage_rng
from core.geometry.rays import Detector
from scenes import config_for, plate

R = 1000.0


def turbulent_config(pixels=32, **atm):
    cfg = config_for(R, pixels=pixels, subsamples=2, fov_rad=2e-3, bins=128, bin_s=1e-9, margin_bins=40)
    cfg.laser.wavelength_m = 532e-9
    cfg.laser.divergence_fills_fov = False
    cfg.laser.beam_divergence_rad = 1e-3
    cfg.atmosphere.cn2_m_23 = 1e-14
    for k, v in atm.items():
        setattr(cfg.atmosphere, k, v)
    return cfg


def test_cn2_zero_is_bit_identical_and_skips_every_turbulence_stage():
    """Cn² = 0 with every effect switched on gives exactly the products of the default settings."""
    scene = plate(R, 30.0)
    base = config_for(R, pixels=16, fov_rad=2e-3)
    ref = simulate_frame(scene, np.eye(4), base)
    cfg = config_for(R, pixels=16, fov_rad=2e-3)
    cfg.atmosphere.cn2_m_23 = 0.0
    cfg.atmosphere.turbulence_blur = "short"
    res = simulate_frame(scene, np.eye(4), cfg)
    assert np.array_equal(res.waveforms, ref.waveforms)
    assert np.array_equal(res.energy_image, ref.energy_image)
    assert np.array_equal(res.range_image, ref.range_image, equal_nan=True)
    for stage in ("beam_broadening", "scintillation", "return_scintillation", "beam_wander", "turbulence_blur"):
        assert stage in res.stats["stages_skipped"]
        assert stage not in res.stats["stages_run"]
    assert "atmosphere" not in res.stats


def test_visibility_sets_extinction():
    """visibility 5 km at 1064 nm (Kim) gives σ = 0.3687/km (docs/theory.md §6) in the radar equation."""
    cfg = config_for(R, pixels=4, fov_rad=2e-3)
    cfg.laser.beam_profile = "uniform"
    clear = simulate_frame(plate(R, 30.0), np.eye(4), cfg).energy_image.sum()
    cfg.atmosphere.visibility_m = 5000.0
    hazy = simulate_frame(plate(R, 30.0), np.eye(4), cfg)
    sigma = extinction_from_visibility(5000.0, 1.064e-6, "kim")
    assert sigma == pytest.approx(0.3687e-3, rel=5e-4)
    assert hazy.energy_image.sum() / clear == pytest.approx(np.exp(-2 * sigma * R), rel=1e-4)
    assert hazy.stats["atmosphere"]["extinction_per_m"] == pytest.approx(sigma)


def _centroid_m(res, cfg):
    det = Detector.from_settings(cfg.receiver)
    iy, ix = np.mgrid[0:det.height_px, 0:det.width_px]
    xt, yt = det.pixel_center_tan(ix, iy)
    e = res.energy_image
    return np.array([np.sum(e * xt), np.sum(e * yt)]) / e.sum() * R


def test_beam_wander_moves_the_illumination_by_the_drawn_offset():
    """D: the energy centroid on a plate moves by the recorded per-pulse offset (within 2 % of the rms wander),
    the offset is the draw of the frame's own random stream, and ⟨r_c²⟩ is the 2.42 formula."""
    cfg = turbulent_config(pixels=64, beam_broadening=False, scintillation=False, turbulence_blur="none")
    cfg.atmosphere.cn2_m_23 = 1e-13
    cfg.laser.beam_divergence_rad = 2e-4
    res = simulate_frame(plate(R, 30.0), np.eye(4), cfg, frame=3)
    meta = res.stats["atmosphere"]["turbulence"]
    var = beam_wander_variance(1e-13, meta["reference_range_m"], cfg.laser.beam_waist_radius_m)
    assert meta["beam_wander_variance_m2"] == pytest.approx(var, rel=1e-12)
    offset = np.array(meta["beam_wander_offset_m"])
    assert np.array_equal(offset, beam_wander_offsets(var, stage_rng(cfg.run.seed, 3, "beam_wander")))
    assert np.linalg.norm(_centroid_m(res, cfg) - offset) < 0.02 * np.sqrt(var)
    other = simulate_frame(plate(R, 30.0), np.eye(4), cfg, frame=4).stats["atmosphere"]["turbulence"]
    assert other["beam_wander_offset_m"] != meta["beam_wander_offset_m"]


def test_beam_broadening_widens_and_conserves_energy():
    """A: the beam's rms radius on the plate grows by W_ST/W (wander on) or W_LT/W (wander off); the energy
    on a plate that catches the whole beam is unchanged (within 0.5 %)."""
    cfg = turbulent_config(pixels=64, scintillation=False, turbulence_blur="none", beam_wander=False)
    cfg.atmosphere.cn2_m_23 = 1e-13
    cfg.laser.beam_divergence_rad = 4e-4
    off = turbulent_config(pixels=64)
    off.laser.beam_divergence_rad = 4e-4
    off.atmosphere.cn2_m_23 = 0.0
    scene = plate(R, 30.0)
    res, ref = simulate_frame(scene, np.eye(4), cfg), simulate_frame(scene, np.eye(4), off)
    assert res.energy_image.sum() == pytest.approx(ref.energy_image.sum(), rel=5e-3)

    def rms(r):
        det = Detector.from_settings(cfg.receiver)
        iy, ix = np.mgrid[0:det.height_px, 0:det.width_px]
        xt, _ = det.pixel_center_tan(ix, iy)
        return np.sqrt(np.sum(r.energy_image * xt ** 2) / r.energy_image.sum())

    meta = res.stats["atmosphere"]["turbulence"]
    beam = gaussian_beam_parameters(532e-9, 0.01, meta["reference_range_m"])
    d = derived_turbulence(1e-13, 532e-9, meta["reference_range_m"])
    w_lt = long_term_beam_radius(beam["w_m"], d["rytov_variance_plane"], beam["lam"])
    assert meta["beam_width_scale"] == pytest.approx(w_lt / beam["w_m"], rel=1e-12)
    assert rms(res) / rms(ref) == pytest.approx(w_lt / beam["w_m"], rel=0.01)
    cfg.atmosphere.beam_wander = True
    meta2 = simulate_frame(scene, np.eye(4), cfg).stats["atmosphere"]["turbulence"]
    w_st = short_term_beam_radius(w_lt, meta2["beam_wander_variance_m2"], beam["w_m"])
    assert meta2["beam_width_scale"] == pytest.approx(w_st / beam["w_m"], rel=1e-12)


def test_scintillation_multiplies_the_illumination():
    """B: with one sub-ray per pixel the energy ratio (turbulent / calm) is the pattern itself: unit mean
    (within 5 % over ~4000 px and many cells), SI within 15 % of the all-regime value at R_ref, and a new
    pattern per frame."""
    cfg = turbulent_config(pixels=64, beam_broadening=False, beam_wander=False, turbulence_blur="none",
                           return_scintillation=False,  # the outgoing pattern alone (return path: its own test)
                           scintillation_statistics="paper")
    cfg.receiver.subsamples = 1
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 2e-4  # 0.2 m footprint, cells of ~1 cm
    cfg.laser.beam_profile = "uniform"
    calm = turbulent_config(pixels=64)
    calm.receiver.subsamples = 1
    calm.receiver.fov_x_rad = calm.receiver.fov_y_rad = 2e-4
    calm.laser.beam_profile = "uniform"
    calm.atmosphere.cn2_m_23 = 0.0
    scene = plate(R, 30.0)
    ratio = simulate_frame(scene, np.eye(4), cfg).energy_image / simulate_frame(scene, np.eye(4), calm).energy_image
    d = derived_turbulence(1e-14, 532e-9, R, statistics="paper")
    assert ratio.mean() == pytest.approx(1.0, abs=0.05)
    assert ratio.var() / ratio.mean() ** 2 == pytest.approx(d["scintillation_index"], rel=0.15)
    again = simulate_frame(scene, np.eye(4), cfg, frame=1).energy_image
    assert not np.array_equal(again, ratio * simulate_frame(scene, np.eye(4), calm).energy_image)


def test_blur_is_the_turbulence_mtf_and_conserves_energy():
    """E: the energy image of a small bright target equals the calm image blurred by the long-exposure MTF
    with the spherical r0 at R_ref; total energy conserved within 1 % (target far from the border)."""
    from core.config.settings import BRDFSettings
    from core.geometry.scene import merge_meshes
    back = plate(R, 30.0, BRDFSettings(reflectance=0.01))
    spot = plate(R - 1.0, 0.05, BRDFSettings(reflectance=0.9))
    scene = merge_meshes([(back.vertices_m, back.triangles, back.material_ids, ["back"], back.materials),
                          (spot.vertices_m, spot.triangles, spot.material_ids, ["spot"], spot.materials)])
    cfg = turbulent_config(pixels=48, beam_broadening=False, beam_wander=False, scintillation=False)
    cfg.atmosphere.cn2_m_23 = 1e-13
    calm = turbulent_config(pixels=48)
    calm.atmosphere.cn2_m_23 = 0.0
    res, ref = simulate_frame(scene, np.eye(4), cfg), simulate_frame(scene, np.eye(4), calm)
    det = Detector.from_settings(cfg.receiver)
    r0 = res.stats["atmosphere"]["turbulence"]["blur_r0_m"]
    pitch = (2 * det.half_height_tan / 48, 2 * det.half_width_tan / 48)
    expected = turbulence_blur(ref.energy_image, pitch, 532e-9, r0, exposure="long")
    assert np.allclose(res.energy_image, np.maximum(expected, 0), rtol=1e-9, atol=1e-12 * expected.max())
    assert res.energy_image.sum() == pytest.approx(ref.energy_image.sum(), rel=0.01)
    assert res.energy_image.max() < 0.9 * ref.energy_image.max()  # the spot is visibly blurred
    # the waveform cube is blurred slice by slice: the same total energy as the blurred image
    assert res.waveforms.sum(dtype=np.float64) == pytest.approx(res.energy_image.sum(), rel=1e-4)


def test_footprint_averaged_scintillation_and_negligible_blur():
    """B with sub-ray footprints larger than a cell: per-sub-ray factors have unit mean and the box-averaged
    variance SI·g(p_x/ρ)·g(p_y/ρ) (within 10 % over 4096 sub-rays); E is skipped, and said so, when the PSF
    is far below a pixel (MTF at Nyquist > 0.999)."""
    from core.physics.propagation import box_average_variance_factor
    cfg = turbulent_config(pixels=64, beam_broadening=False, beam_wander=False, return_scintillation=False,
                           scintillation_statistics="paper")
    cfg.receiver.subsamples = 1
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.2  # 200 m footprint: 3 m per sub-ray ≫ 1 cm cells
    cfg.laser.beam_profile = "uniform"
    calm = turbulent_config(pixels=64)
    calm.receiver.subsamples = 1
    calm.receiver.fov_x_rad = calm.receiver.fov_y_rad = 0.2
    calm.laser.beam_profile = "uniform"
    calm.atmosphere.cn2_m_23 = 0.0
    scene = plate(R, 200.0)
    res = simulate_frame(scene, np.eye(4), cfg)
    ratio = res.energy_image / simulate_frame(scene, np.eye(4), calm).energy_image
    meta = res.stats["atmosphere"]["turbulence"]
    pat = meta["scintillation_pattern"]
    assert pat["pattern_model"] == "footprint_averaged_gamma"
    p = pat["sub_ray_footprint_m"]
    expected = (pat["point_scintillation_index"] * box_average_variance_factor(p[0], pat["cell_radius_m"])
                * box_average_variance_factor(p[1], pat["cell_radius_m"]))
    assert pat["averaged_scintillation_index"] == pytest.approx(expected, rel=1e-12)
    assert ratio.mean() == pytest.approx(1.0, abs=3 * np.sqrt(expected / ratio.size) + 1e-3)
    assert ratio.var() == pytest.approx(expected, rel=0.1)
    assert "turbulence_blur" in res.stats["stages_skipped"] and "turbulence_blur" not in res.stats["stages_run"]
    assert meta["blur_mtf_at_nyquist"] > 0.999


def test_box_average_variance_factor_limits():
    """g → 1 − a²/6 for a ≪ 1 and → √π/a for a ≫ 1 (a = p/ρ)."""
    from core.physics.propagation import box_average_variance_factor
    assert box_average_variance_factor(1e-3, 1.0) == pytest.approx(1 - 1e-6 / 6, rel=1e-9)
    assert box_average_variance_factor(1e3, 1.0) == pytest.approx(np.sqrt(np.pi) / 1e3, rel=1e-3)
