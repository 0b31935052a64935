"""B': scintillation of the return path through the receiver aperture (core/physics/propagation.py; docs/theory.md §3):
aperture averaging A_sp = (1 + 0.33 d²)^(−7/6) applied to the spherical-wave SI of the path target → receiver,
averaged over each pixel's footprint.  Tolerances: formula values to 1e-3 (docs/theory.md's 4 digits); the
variance of the applied factor over ≥ 4e4 independent realizations within 5 % (its standard error is
√((κ4 + 2)/n) ≤ 1.3 % for these gamma shapes)."""
import copy

import numpy as np
import pytest

from core.atmosphere import derived_turbulence
from core.systems.flash import simulate_frame
from core.physics.propagation import box_average_variance_factor, draw_return_factor, return_scintillation_variance
from scenes import config_for, plate


def test_variance_formula_case_a():
    """docs/theory.md case A (Cn² 1e-14, 1064 nm, 2 km), D = 5 cm: A_sp = 0.5741, SI_sp = 0.4373, point footprint:
    variance 0.2511; a 5 cm footprint multiplies it by g(p/ρ_l)² with ρ_l = 0.01543 m (eq. 3-6, spherical)."""
    d = derived_turbulence(1e-14, 1.064e-6, 2000.0, aperture_diameter_m=0.05, statistics="paper")
    v = return_scintillation_variance(d, (1e-6, 1e-6))
    assert v["aperture_averaging_factor"] == pytest.approx(0.5741, rel=2e-4)
    assert v["point_scintillation_index"] == pytest.approx(0.4373, rel=2e-4)
    assert v["variance"] == pytest.approx(0.5741 * 0.4373, rel=1e-3)
    w = return_scintillation_variance(d, (0.05, 0.05))
    assert w["cell_radius_m"] == pytest.approx(0.01543, rel=1e-3)
    assert w["variance"] == pytest.approx(v["variance"] * box_average_variance_factor(0.05, 0.01543) ** 2, rel=1e-3)


@pytest.mark.parametrize("footprint_m", [0.004, 0.05])  # correlated field (p < 2ρ_l) / independent pixels
def test_applied_factor_has_the_formula_variance(footprint_m):
    d = derived_turbulence(1e-14, 1.064e-6, 2000.0, aperture_diameter_m=0.05, statistics="paper")
    info = return_scintillation_variance(d, (footprint_m, footprint_m))
    rng = np.random.default_rng(7)
    if footprint_m < 2 * info["cell_radius_m"]:  # correlated field: samples 8 px = 2.1 ρ_l apart (corr. 0.01)
        vals, model = [], None
        for _ in range(160):
            f, model = draw_return_factor((128, 128), (footprint_m,) * 2, info, rng)
            vals.append(f[::8, ::8].ravel())
        x = np.concatenate(vals)
        assert model == "gamma_correlated_field"
    else:
        x, model = draw_return_factor((256, 256), (footprint_m,) * 2, info, rng)
        x = x.ravel()
        assert model == "gamma_independent_pixels"
    assert x.mean() == pytest.approx(1.0, abs=4 * np.sqrt(info["variance"] / x.size))
    assert x.var() == pytest.approx(info["variance"], rel=0.05)


def test_pipeline_applies_the_return_factor_per_pixel():
    """Same seed with and without the return path: the outgoing pattern is the same stream, so the energy ratio
    of each pixel is its return factor: unit mean and the metadata variance A·SI·g_x·g_y within 5 % over 16
    frames of 64 × 64 pixels (independent pixels); every sub-ray of a pixel gets the same factor."""
    R = 1000.0
    base = config_for(R, pixels=64, subsamples=2, fov_rad=0.02, bins=128, bin_s=1e-9, margin_bins=40)
    base.laser.wavelength_m = 532e-9
    base.laser.beam_profile = "uniform"
    base.atmosphere.cn2_m_23 = 1e-14
    base.atmosphere.scintillation_statistics = "paper"
    base.atmosphere.beam_broadening = False
    base.atmosphere.beam_wander = False
    base.atmosphere.turbulence_blur = "none"
    scene = plate(R, 30.0)
    ratios, var = [], None
    off_cfg = copy.deepcopy(base)
    off_cfg.atmosphere.return_scintillation = False
    for frame in range(16):
        off = simulate_frame(scene, np.eye(4), off_cfg, frame=frame)
        on = simulate_frame(scene, np.eye(4), base, frame=frame)
        info = on.stats["atmosphere"]["turbulence"]["return_scintillation"]
        var = info["variance"]
        assert info["model"] == "gamma_independent_pixels"
        assert "return_scintillation" in off.stats["stages_skipped"]
        ratios.append((on.energy_image / off.energy_image).ravel())
    x = np.concatenate(ratios)
    d = derived_turbulence(1e-14, 532e-9, R, aperture_diameter_m=base.receiver.aperture_diameter_m,
                           statistics="paper")
    p = 0.02 * R / 64
    assert var == pytest.approx(d["aperture_averaging"] * d["scintillation_index"]
                                * box_average_variance_factor(p, d["cell_radius_m"]) ** 2, rel=1e-3)
    assert x.mean() == pytest.approx(1.0, abs=4 * np.sqrt(var / x.size))
    assert x.var() == pytest.approx(var, rel=0.05)


def test_wave_optics_return_variance_uses_the_tabulated_statistics():
    """Default statistics: the return-path variance is A·SI·g with SI the wave-optics spherical SI, A the aperture
    integral of the wave-optics covariance (validated against split-step disk averages in
    test_wave_optics_scintillation) and g its rectangle average over the footprint (to 1e-12); a footprint far below
    a cell averages nothing (g within 1e-3 of 1)."""
    from core.atmosphere import wave_optics as wo
    d = derived_turbulence(1e-14, 1.064e-6, 2000.0, aperture_diameter_m=0.05)
    st = wo.statistics(1e-14, 1.064e-6, 2000.0, "spherical")
    assert d["scintillation_statistics"] == "wave_optics"
    v = return_scintillation_variance(d, (0.03, 0.02))
    a = wo.aperture_averaging_factor(st, 0.05)
    g = wo.footprint_averaging_factor(st, 0.03, 0.02)
    assert v["statistics"] == "wave_optics"
    assert v["variance"] == pytest.approx(a * st["scintillation_index"] * g, rel=1e-12)
    assert return_scintillation_variance(d, (1e-6, 1e-6))["footprint_averaging_factor"] == pytest.approx(1.0, abs=1e-3)


def test_footprint_averaged_pattern_bands_independent_of_threads():
    """The footprint-averaged scintillation pattern is drawn in fixed row bands, each from its own child stream of
    the frame's seed sequence: the same values on 1 and 3 threads; unit mean and the stated variance within 4
    standard errors over the 262,144 sub-rays (gamma: SE of the variance √((κ4 + 2)/n)·var, κ4 = 6 var)."""
    from types import SimpleNamespace

    from core.physics.propagation import FootprintAveragedPattern

    d = derived_turbulence(1e-14, 1.064e-6, 2000.0, aperture_diameter_m=0.05, statistics="paper")
    det = SimpleNamespace(height_px=128, width_px=128, subsamples=4)
    seq = np.random.SeedSequence([7, 0, 2])
    one = FootprintAveragedPattern.draw(det, (0.02, 0.02), d, seq, threads=1)
    three = FootprintAveragedPattern.draw(det, (0.02, 0.02), d, seq, threads=3)
    assert np.array_equal(one.values, three.values)
    v = one.params["averaged_scintillation_index"]
    n = one.values.size
    assert v > 0.01
    assert abs(one.values.mean() - 1.0) <= 4 * np.sqrt(v / n)
    assert abs(one.values.var() - v) <= 4 * np.sqrt((6 * v + 2) / n) * v
    assert not np.array_equal(one.values[:64], one.values[64:128])  # the bands are different streams
    # each band is NumPy's Gamma(1/v, v) of its own child stream (drawn in place since session 32: the same numbers)
    from core.physics.propagation import PATTERN_BANDS
    rows = np.array_split(np.arange(one.values.shape[0]), PATTERN_BANDS)
    for k, r in enumerate(rows):
        child = np.random.SeedSequence(seq.entropy, spawn_key=tuple(seq.spawn_key) + (k,))
        want = np.random.default_rng(child).gamma(1.0 / v, v, (r.size, one.values.shape[1]))
        assert np.array_equal(one.values[r[0]:r[-1] + 1], want)
