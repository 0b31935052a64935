"""The radar equation as a product of its factors (core/physics/radiometry.py) against the log-space sum it
replaced: per-ray energies within 1e-12 relative, exact zeros where the log form gives zeros, finite and ≥ 0
everywhere (zero factors, grazing and normal incidence, tiny and huge ranges, extinction off, on and thick fog),
for the Lambertian, Steinvall and table BRDFs; and the compiled BRDFs against their closed forms."""
from __future__ import annotations

import math

import numpy as np
import pytest

from core.config.settings import BRDFSettings, LaserSettings, ReceiverSettings
from core.physics.brdf import evaluate_brdf, evaluate_materials
from core.physics.radiometry import received_energy

TINY = np.finfo(np.float64).tiny  # below it float64 loses precision: both forms round to the subnormal grid

MATERIALS = [
    BRDFSettings(model="lambertian", reflectance=0.25),
    BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0),
    BRDFSettings(model="steinvall", specular_a=1e3, slope_s=10.0, diffuse_b=0.0, diffuse_m=0.0),
    BRDFSettings(model="steinvall", specular_a=0.0, slope_s=0.2, diffuse_b=0.3, diffuse_m=40.0),
    BRDFSettings(model="table", table_angle_deg=[0.0, 10.0, 30.0, 60.0], table_brdf_per_sr=[1.0, 0.5, 0.2, 0.1]),
    BRDFSettings(model="table", table_angle_deg=[20.0, 45.0, 80.0], table_brdf_per_sr=[3.0, 0.0, 0.0]),
    BRDFSettings(model="lambertian", reflectance=0.0),
]


def reference_brdf(brdf, cos_theta):
    """The NumPy BRDFs the kernels replaced (docs/theory.md §10, core/physics/brdf.py's docstring)."""
    if brdf.model == "lambertian":
        return np.full(np.shape(cos_theta), brdf.reflectance / np.pi)
    if brdf.model == "table":
        theta = np.degrees(np.arccos(np.clip(cos_theta, 0.0, 1.0)))
        return np.interp(theta, np.asarray(brdf.table_angle_deg, float), np.asarray(brdf.table_brdf_per_sr, float))
    c = np.clip(cos_theta, 1e-150, 1.0)
    tan2 = np.maximum((1.0 - c * c) / (c * c), 0.0)
    with np.errstate(over="ignore"):
        exponent = -tan2 / brdf.slope_s ** 2 - 6.0 * np.log(c)
    specular = brdf.specular_a * np.exp(np.minimum(exponent, 700.0)) if brdf.specular_a else 0.0
    return specular + brdf.diffuse_b * c ** brdf.diffuse_m


def reference_energy(laser, rx, sigma, materials, ids, cos_theta, range_m, fraction):
    """Eq. 3-1 summed in log space and exponentiated once (the implementation the product replaced)."""
    f_r = np.zeros(len(ids))
    for k, m in enumerate(materials):
        f_r[ids == k] = reference_brdf(m, cos_theta[ids == k])
    area = np.pi * (0.5 * rx.aperture_diameter_m) ** 2
    with np.errstate(divide="ignore"):
        log_e = (np.log(laser.pulse_energy_j) + np.log(fraction) + np.log(rx.system_efficiency) + np.log(f_r)
                 + np.log(np.clip(cos_theta, 0.0, 1.0)) + np.log(area) - 2.0 * np.log(range_m)
                 - 2.0 * sigma * range_m)
    return np.exp(log_e)


def rays():
    """Every material × incidence × range × fraction combination."""
    deg = np.array([0.0, 1e-6, 5.0, 10.0, 20.0, 25.0, 30.0, 44.9, 45.0, 60.0, 75.0, 85.0, 89.0, 89.999])
    cos = np.concatenate([np.cos(np.radians(deg)), [1.0, 1e-3, 1e-8, 1e-30, 1e-150, 1e-300, 5e-324, 0.0, -1e-7,
                                                    float(np.float32(np.cos(np.float32(np.pi / 2))))]])
    rng = np.array([1e-3, 0.5, 1.0, 10.0, 300.0, 1234.5, 1e4, 2e4, 1e5, 1e7, 1e30, 1e100, 1e150, 1e160, 1e200])
    frac = np.array([1.0, 0.37, 1e-6, 1e-12, 1e-200, 0.0])
    m, c, r, f = np.meshgrid(np.arange(len(MATERIALS)), cos, rng, frac, indexing="ij")
    return m.ravel(), c.ravel(), r.ravel(), f.ravel()


def compare(new, ref):
    """Max relative deviation on the normal results; zeros exact; subnormals within rounding of the grid."""
    assert np.all(np.isfinite(new)) and np.all(new >= 0)
    assert np.all(new[ref == 0] == 0)
    normal = ref >= TINY
    rel = np.abs(new[normal] - ref[normal]) / ref[normal]
    sub = (ref > 0) & ~normal
    assert np.all(np.abs(new[sub] - ref[sub]) <= 1e-12 * ref[sub] + 2 * 5e-324)
    return float(rel.max()) if rel.size else 0.0


@pytest.mark.parametrize("sigma", [0.0, 1e-4, 0.05, 2.0])
@pytest.mark.parametrize("laser_e, eta", [(1e-3, 0.5), (0.2, 1.0), (1e-9, 0.05)])
def test_product_matches_log_space_sum(sigma, laser_e, eta):
    laser = LaserSettings(pulse_energy_j=laser_e)
    rx = ReceiverSettings(system_efficiency=eta)
    ids, cos, rng, frac = rays()
    new = received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, frac)
    with np.errstate(invalid="ignore", over="ignore"):
        ref = reference_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, frac)
    assert np.all(np.isfinite(ref) | (rng > 1e150))  # the log form's 0·inf at R = inf (never a hit's range)
    ok = np.isfinite(ref)
    assert compare(new[ok], ref[ok]) <= 1e-12
    assert (ref[ok] == 0).any() and (ref[ok] >= TINY).any()
    if sigma == 0.0:  # the grid reaches the subnormal results too
        assert ((ref[ok] > 0) & (ref[ok] < TINY)).any()
    # one number for every ray's fraction gives the same energies as the per-ray array
    one = received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, 0.37)
    assert np.array_equal(one, received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, np.full(len(ids), 0.37)))


def test_random_rays_and_max_deviation():
    """Random rays (ranges 1 m – 20 km, any incidence, fractions 1e-8 – 1, σ up to 0.02 /m): the deviation is
    rounding, mostly the log sum's (its error grows with |ln E_r|: 1.4e-13 at most when written)."""
    gen = np.random.default_rng(7)
    n = 200_000
    ids = gen.integers(0, len(MATERIALS) - 1, n)
    cos = gen.uniform(-0.01, 1.0, n)
    rng = 10 ** gen.uniform(0.0, 4.3, n)
    frac = 10 ** gen.uniform(-8, 0, n)
    laser, rx = LaserSettings(), ReceiverSettings()
    worst = 0.0
    for sigma in (0.0, 3.9e-4, 0.02):
        worst = max(worst, compare(received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, frac),
                                   reference_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, frac)))
    print(f"max relative deviation product vs log sum: {worst:.3g}")
    assert worst <= 1e-12


def test_zero_factors_give_exact_zeros():
    """A zero pulse energy, efficiency, fraction, BRDF, or cos θ ≤ 0 gives an exact 0 (never NaN), also with a
    zero or infinite range or thick fog."""
    ids = np.zeros(5, int)
    cos = np.array([1.0, 0.5, 0.0, -0.2, 1.0])
    rng = np.array([0.0, 1e-300, 100.0, 1e300, np.inf])
    for laser, rx in ((LaserSettings(pulse_energy_j=0.0), ReceiverSettings()),
                      (LaserSettings(), ReceiverSettings(system_efficiency=0.0))):
        for sigma in (0.0, 5.0):
            assert np.array_equal(received_energy(laser, rx, sigma, MATERIALS[:1], ids, cos, rng, 1.0), np.zeros(5))
    laser, rx = LaserSettings(), ReceiverSettings()
    assert np.array_equal(received_energy(laser, rx, 0.0, MATERIALS, ids + 6, cos, rng, 1.0), np.zeros(5))
    assert np.array_equal(received_energy(laser, rx, 0.0, MATERIALS, ids, cos, rng, 0.0), np.zeros(5))
    e = received_energy(laser, rx, 0.0, MATERIALS, ids, np.array([0.0, -1e-7, 0.0, -1.0, -0.5]), rng, 1.0)
    assert np.array_equal(e, np.zeros(5))
    far = received_energy(laser, rx, 5.0, MATERIALS, ids[:2], cos[:2], np.array([10.0, 1e4]), 1.0)
    assert far[0] > 0 and far[1] == 0.0  # thick fog: e^(−1e5) is an exact 0


def test_compiled_brdfs_match_their_closed_forms():
    """f_r of every model against the NumPy closed forms (tables: np.interp in degrees) to 1 ulp-level."""
    cos = np.concatenate([np.cos(np.radians(np.linspace(0.0, 90.0, 1801))), [1.0 + 1e-7, -1e-7, 1e-300, 0.0]])
    for brdf in MATERIALS:
        new, ref = evaluate_brdf(brdf, cos), reference_brdf(brdf, cos)
        assert np.all(np.isfinite(new)) and np.all(new >= 0)
        assert np.allclose(new, ref, rtol=4e-16 if brdf.model != "steinvall" else 1e-14, atol=0), brdf
        if brdf.model == "table":  # np.interp's arithmetic, value for value
            assert np.array_equal(new, ref)
    ids = np.arange(len(cos)) % len(MATERIALS)
    f = evaluate_materials(MATERIALS, ids, cos)
    for k, brdf in enumerate(MATERIALS):
        assert np.array_equal(f[ids == k], evaluate_brdf(brdf, cos[ids == k]))
    assert float(evaluate_brdf(MATERIALS[1], 1.0)) == pytest.approx(0.13, rel=1e-12)
    with pytest.raises(IndexError):
        evaluate_materials(MATERIALS[:2], np.array([0, 2]), np.array([1.0, 1.0]))
    assert math.isfinite(float(evaluate_brdf(MATERIALS[2], 1e-300)))
