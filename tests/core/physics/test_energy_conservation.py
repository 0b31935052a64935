"""Energy is conserved at every range (issue 31): the received energy never exceeds what the target intercepts.

The far-field aperture factor π r_a²/R² grew without bound near the sensor (a reflectance-1 plate returned 2.2×
the pulse energy at 1 cm and 222× at 1 mm).  The projected solid angle of the aperture disc, π r_a²/(R² + r_a²)
(core/physics/radiometry.py), is bounded by π: a Lambertian plate of reflectance ρ returns E_T·η·F·ρ·r_a²/(R² + r_a²)
≤ E_T·F, F the fraction of the pulse it intercepts — checked per ray against that formula and through a whole
flash frame, from 1 mm to 10 km."""
import numpy as np
import pytest

from core.geometry.rays import Detector
from core.physics.laser import cell_energy_fractions
from core.config.settings import BRDFSettings, LaserSettings, ReceiverSettings
from core.physics.radiometry import received_energy
from core.run import simulate
from scenes import config_for, plate

RANGES = np.geomspace(1e-3, 1e4, 29)  # 1 mm … 10 km


def test_a_white_lambertian_plate_returns_at_most_the_intercepted_energy_per_ray():
    laser = LaserSettings(pulse_energy_j=1e-3)
    rx = ReceiverSettings(system_efficiency=1.0, aperture_diameter_m=0.05)
    white = [BRDFSettings(model="lambertian", reflectance=1.0)]
    r_a = 0.025
    for fraction in (1.0, 0.3, 1e-6):
        e = received_energy(laser, rx, 0.0, white, np.zeros(len(RANGES), int), np.ones(len(RANGES)), RANGES,
                            fraction)
        ratio = e / laser.pulse_energy_j
        # the formula: F·ρ·r_a²/(R² + r_a²) (f_r = ρ/π times the projected solid angle π r_a²/(R² + r_a²))
        np.testing.assert_allclose(ratio, fraction * r_a ** 2 / (RANGES ** 2 + r_a ** 2), rtol=1e-12)
        assert np.all(ratio <= fraction)
        assert ratio[0] > 0.99 * fraction  # at 1 mm nearly all of it comes back into the 5 cm aperture
    # far away it is the paper's far-field π r_a²/R² to a relative (r_a/R)²: 1.6e-8 at 200 m
    e200 = received_energy(laser, rx, 0.0, white, [0], [1.0], [200.0], 1.0)[0]
    far = laser.pulse_energy_j * r_a ** 2 / 200.0 ** 2
    assert e200 / far - 1 == pytest.approx(-(r_a / 200.0) ** 2, rel=1e-6)


@pytest.mark.parametrize("range_m", [1e-3, 1e-2, 0.1, 1.0, 10.0, 200.0, 1e4])
def test_a_whole_flash_frame_on_a_white_plate_returns_at_most_the_pulse(range_m):
    """A reflectance-1 plate filling the field of view at ``range_m``: the frame's received energy (all
    pixels, before binning) over the pulse energy is at most the fraction of the pulse the plate intercepts
    (the pixels' share of the beam, ≤ 1)."""
    cfg = config_for(range_m, pixels=8, subsamples=2, fov_rad=0.01)
    cfg.receiver.system_efficiency = 1.0
    scene = plate(range_m, max(1.0, 0.1 * range_m), brdf=BRDFSettings(model="lambertian", reflectance=1.0))
    res = simulate(scene, np.eye(4), cfg)
    received = float(np.nansum(res.energy_image))
    fx, fy = cell_energy_fractions(cfg.laser, Detector.from_settings(cfg.receiver))
    intercepted = float(fx.sum() * fy.sum())  # the pixels' share of the beam: all on the plate
    ratio = received / cfg.laser.pulse_energy_j
    assert 0.0 < intercepted <= 1.0 + 1e-12
    assert 0.0 < ratio <= intercepted, (ratio, intercepted)
    r_a = 0.5 * cfg.receiver.aperture_diameter_m  # and it is the formula, F·r_a²/(R² + r_a²) at normal incidence
    assert ratio == pytest.approx(intercepted * r_a ** 2 / (range_m ** 2 + r_a ** 2), rel=1e-3)
