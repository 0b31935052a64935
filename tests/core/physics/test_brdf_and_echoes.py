"""BRDF (docs/theory.md §10) and echo interpolation (docs/theory.md §9) against the worked values of docs/theory.md."""
import numpy as np
import pytest

from core.physics.brdf import directional_hemispherical_reflectance, evaluate_brdf, steinvall_brdf
from core.config.settings import BRDFSettings, DetectionSettings
from core.physics.detection.peaks import detect_echoes, interpolate_peak


@pytest.mark.parametrize("deg,expected", [(0, 0.1300), (10, 0.1040), (30, 0.06931), (60, 0.04000)])
def test_steinvall_values(deg, expected):
    """f_r(θ) for A = 0.05, s = 0.2, B = 0.08, m = 1 (docs/theory.md §10), to 4 significant digits."""
    value = steinvall_brdf(np.cos(np.radians(deg)), 0.05, 0.2, 0.08, 1.0)
    assert float(value) == pytest.approx(expected, rel=5e-4)


def test_steinvall_directional_hemispherical_reflectance():
    """ρ_DH(0) = 0.2262 for the same parameters (docs/theory.md §10)."""
    b = BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0)
    assert directional_hemispherical_reflectance(b) == pytest.approx(0.2262, rel=5e-4)


def test_grazing_incidence_is_finite():
    """cos θ = 0, a float32 cos(π/2) < 0 and tiny cosines give finite, non-negative values (no NaN/Inf)."""
    cos = np.array([0.0, np.float32(np.cos(np.float32(np.pi / 2))), 1e-300, 1e-12, 1e-3, -1e-7])
    for s in (0.01, 0.2, 5.0):
        v = steinvall_brdf(cos, 0.05, s, 0.08, 1.0)
        assert np.all(np.isfinite(v)) and np.all(v >= 0)
    b = BRDFSettings(model="steinvall", specular_a=1e3, slope_s=10.0, diffuse_b=0.1, diffuse_m=0.0)
    assert np.all(np.isfinite(evaluate_brdf(b, cos)))


def test_lambertian_is_reflectance_over_pi():
    b = BRDFSettings(model="lambertian", reflectance=0.5)
    assert np.allclose(evaluate_brdf(b, np.array([1.0, 0.3])), 0.5 / np.pi, rtol=1e-15)


def test_interpolation_worked_values():
    """Samples (0.4296, 0.9560, 0.7827) of a σ = 1 sampled Gaussian at t0 = 0.3: parabolic δ = 0.2523,
    Gaussian δ = 0.3000 (docs/theory.md §9)."""
    y = (0.4296, 0.9560, 0.7827)
    d_par, _ = interpolate_peak(*y, method="parabolic")
    d_gau, peak = interpolate_peak(*y, method="gaussian")
    assert float(d_par) == pytest.approx(0.2523, abs=5e-5)
    assert float(d_gau) == pytest.approx(0.3000, abs=5e-5)
    assert float(peak) == pytest.approx(1.0, abs=1e-3)


def test_detect_echoes_orders_and_limits():
    """Three peaks, max_echoes = 2: the two strongest are kept, reported in time order, with exact positions
    for sampled Gaussians (σ = 2 bins)."""
    j = np.arange(200) + 0.5
    wf = (1.0 * np.exp(-0.5 * ((j - 50.3) / 2) ** 2) + 0.2 * np.exp(-0.5 * ((j - 100.0) / 2) ** 2)
          + 0.6 * np.exp(-0.5 * ((j - 150.7) / 2) ** 2))
    echoes = detect_echoes(wf[None, :], DetectionSettings(max_echoes=2, relative_threshold=0.01))
    assert list(echoes.echo_index) == [0, 1]
    assert list(echoes.n_echoes) == [2, 2]
    assert echoes.position_bins == pytest.approx([50.3, 150.7], abs=1e-9)
    assert echoes.amplitude == pytest.approx([1.0, 0.6], rel=1e-9)


def test_relative_threshold_drops_weak_echoes():
    j = np.arange(100) + 0.5
    wf = np.exp(-0.5 * ((j - 30) / 2) ** 2) + 0.04 * np.exp(-0.5 * ((j - 70) / 2) ** 2)
    assert len(detect_echoes(wf[None, :], DetectionSettings(relative_threshold=0.05)).pixel) == 1
    assert len(detect_echoes(wf[None, :], DetectionSettings(relative_threshold=0.03)).pixel) == 2
    assert len(detect_echoes(np.zeros((3, 10)), DetectionSettings()).pixel) == 0
