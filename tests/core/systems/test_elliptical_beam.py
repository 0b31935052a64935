"""Elliptical scanner beam (laser.beam_divergence_y_rad, laser.beam_orientation_rad; both divergences full angles
at the 1/e² intensity points): the sub-rays' second moments follow the elliptical profile, each keeps its equal
share of the energy, and a circular beam is bit-for-bit what it was."""
import dataclasses

import numpy as np
import pytest

from core.config.settings import SimulationConfig
from core.geometry.motion import Trajectory
from core.run import simulate
from core.systems.scan_patterns import beam_subrays, scan_beams
from scenes import plate


def _cfg(div=2e-3, div_y=0.0, psi=0.0, rings=6, profile="gaussian"):
    cfg = SimulationConfig(system_type="scanner")
    s = cfg.scanner
    s.pattern, s.n_lines, s.scan_rate_hz, s.pulse_rate_hz = "raster", 1, 1000.0, 1000.0
    s.scan_width_rad = s.scan_height_rad = 0.0
    s.beam_subray_rings = rings
    cfg.laser.beam_divergence_rad, cfg.laser.beam_divergence_y_rad = div, div_y
    cfg.laser.beam_orientation_rad, cfg.laser.beam_profile = psi, profile
    cfg.laser.pulse_fwhm_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2e-9, 0.25e-9, 2048
    cfg.run.save_waveforms, cfg.run.threads = False, 1
    return cfg


def _subray_angles(cfg):
    """Projected angles (x, y) rad of the sub-rays of the on-axis pulse (direction −Z)."""
    *_, d = scan_beams(cfg, Trajectory.static(np.eye(4)), 0, 1)
    return np.arctan2(d[:, 0], -d[:, 2]), np.arctan2(d[:, 1], -d[:, 2])


@pytest.mark.parametrize("psi", [0.0, 0.5, -1.2])
def test_second_moments_follow_the_elliptical_gaussian(psi):
    """I ∝ exp(−2x'²/a² − 2y'²/b²) (a, b the 1/e² half angles) has ⟨x'²⟩ = a²/4, ⟨y'²⟩ = b²/4, ⟨x'y'⟩ = 0.
    The 817 equal-energy sub-rays of 16 rings reproduce them within 5 %: each ray sits at its ring's energy
    midpoint, which cuts the Gaussian's tail (measured 3.9 % low on both axes; 9 % with 6 rings, 27 % with 1),
    the same factor as the circular beam's; ⟨x'y'⟩ vanishes and the ratio ⟨y'²⟩/⟨x'²⟩ = b²/a² within 1e-9 (the
    map from the circular pattern is linear)."""
    a, b = 1.5e-3, 0.2e-3  # half angles: Livox-like 3 mrad × 0.4 mrad 1/e² full angles
    x, y = _subray_angles(_cfg(div=2 * a, div_y=2 * b, psi=psi, rings=16))
    w = beam_subrays(16)[2]
    xe = x * np.cos(psi) + y * np.sin(psi)  # into the ellipse's axes
    ye = -x * np.sin(psi) + y * np.cos(psi)
    mxx, myy, mxy = (w * xe * xe).sum(), (w * ye * ye).sum(), (w * xe * ye).sum()
    assert mxx == pytest.approx(a * a / 4, rel=0.05)
    assert myy == pytest.approx(b * b / 4, rel=0.05)
    assert abs(mxy) < 1e-6 * a * b
    assert (myy / mxx) == pytest.approx((b / a) ** 2, rel=1e-6)
    rc, _, wc = beam_subrays(16)
    circular = (wc * rc * rc).sum() / 2  # ⟨x²⟩ of the unit circular pattern
    assert mxx / a ** 2 == pytest.approx(circular, rel=1e-6)


def test_uniform_elliptical_profile_moments():
    """Uniform over the ellipse: ⟨x'²⟩ = a²/4, ⟨y'²⟩ = b²/4 (as for a disc of radius a: ρ²/2 averaged); the
    127 sub-rays within 0.1 % (measured 6e-5)."""
    a, b = 1e-3, 3e-3
    x, y = _subray_angles(_cfg(div=2 * a, div_y=2 * b, profile="uniform"))
    w = beam_subrays(6, "uniform")[2]
    assert (w * x * x).sum() == pytest.approx(a * a / 4, rel=1e-3)
    assert (w * y * y).sum() == pytest.approx(b * b / 4, rel=1e-3)


def test_circular_beam_is_bit_for_bit_unchanged():
    """Second divergence 0: the sub-rays are the circular formula ρ = ρ/θ · θ/2 of before, exactly (the
    orientation is then unused)."""
    cfg = _cfg(div=2e-3)
    *_, d0 = scan_beams(cfg, Trajectory.static(np.eye(4)), 0, 1)
    cfg.laser.beam_orientation_rad = 0.7
    *_, d1 = scan_beams(cfg, Trajectory.static(np.eye(4)), 0, 1)
    rho, phi, _ = beam_subrays(6)
    r = rho * 0.5 * 2e-3
    expected = np.stack([np.sin(r) * np.cos(phi), np.sin(r) * np.sin(phi), -np.cos(r)], -1)
    np.testing.assert_array_equal(d0, d1)
    np.testing.assert_allclose(d0, expected, rtol=0, atol=1e-15)


def test_total_energy_is_conserved_on_a_wall():
    """A wall filling both footprints: the elliptical and the circular beam return the same energy (each
    sub-ray 1/m of the pulse; only the sub-rays' ranges differ, by < 1e-5 relative at these angles)."""
    wall = plate(20.0, 5.0)
    circ = simulate(wall, np.eye(4), _cfg(div=3e-3, rings=3)).pulses["received_energy_j"][0]
    ell = simulate(wall, np.eye(4), _cfg(div=3e-3, div_y=0.5e-3, psi=0.3, rings=3)).pulses["received_energy_j"][0]
    assert ell == pytest.approx(circ, rel=1e-5)
    w = beam_subrays(3)[2]
    assert w.sum() == pytest.approx(1.0, abs=1e-15) and np.ptp(w) == 0.0


def test_subrays_fill_the_oriented_ellipse():
    """With the wide axis turned vertical (ψ = π/2) every sub-ray lies on the ellipse (x/b)² + (y/a)² = ρ_k² of
    its ring (ρ_k the ring's radius in units of the half angle; small angles: 1e-6 relative)."""
    a, b, psi = 2e-3, 0.5e-3, np.pi / 2
    x, y = _subray_angles(_cfg(div=2 * a, div_y=2 * b, psi=psi, rings=4))
    rho = beam_subrays(4)[0]
    np.testing.assert_allclose(np.sqrt((x / b) ** 2 + (y / a) ** 2), rho, rtol=1e-6, atol=1e-12)
    assert np.abs(y).max() > 3 * np.abs(x).max()
