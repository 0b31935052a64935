"""The radar equation as a product of its factors (core/physics/radiometry.py) against an extended-precision
evaluation of eq. 3-1: per-ray energies within the rounding bound of the float64 arithmetic (below), exact zeros
where the log form gives zeros, finite and ≥ 0 everywhere (zero factors, grazing and normal incidence, tiny and
huge ranges, extinction off, on and thick fog), for the Lambertian, Steinvall and table BRDFs; and the compiled
BRDFs against their closed forms.

Why the reference is in extended precision: the float64 log-space sum the product replaced carries errors of
u·|ln E_r| (u = 2⁻⁵³; |ln E_r| reaches 1,400 on this grid), and NumPy's float64 log/exp/arccos take CPU-specific
SIMD paths (AVX-512 SVML: up to 4 ulp), so a float64 reference moves with the CPU (2.07e-12 on an AVX-512
Xeon against 1.4e-13 on AVX2).  NumPy's long double (x87 80-bit on x86-64, u_ext = 2⁻⁶⁴) runs the C library's
scalar logl/expl on every CPU, so the reference's own error (≈ 1,400·2⁻⁶⁴ < 1e-16) is negligible and what is
compared is the kernel's float64 rounding alone.

The bound, per ray (:func:`rounding_bound`): rel. error ≤ u·(64 + 8·S), S the sum of the magnitudes of the
natural logarithms the kernel forms or exponentiates:
* the product path rounds ≈ 10 multiplications/divisions (≤ u each) and exponentiates the rounded argument
  −2σR (absolute error ≤ u·2σR → relative u·2σR) with a ≤ 1-ulp exp (glibc's on every x86-64 CPU; 4 ulp
  allowed for a vectorised math library);
* the log path sums five logs (each ≤ 4 ulp of its value: ≤ 4u·|tᵢ|) with five additions (≤ u·S each) and
  exponentiates: ≤ 4u·S + 5u·S + 4u, i.e. ≤ 9u·S — taken as 8u·S plus the constant (S ≥ 1 where the log path
  runs: it runs only where a factor leaves the normal range, |ln| > 700);
* the Steinvall lobe's exponent x = −tan²θ/s² − 6 ln cos θ has absolute error ≤ u·(4|x| + 4/s² + 12|ln cos θ|)
  (1 − cos²θ loses the digits of cos²θ ≈ 1: u/(cos²θ s²) = u(tan²θ + 1)/s²), counted in S; the table BRDF is
  NumPy's interpolation at the same θ (math.acos, the C library's scalar acos as in the kernel), so it adds
  nothing.
The constant 64 covers the ≈ 20 roundings of the product path and of E_T η π r_a² with a factor 3 to spare; the
largest measured ratio rel/(u·(64 + 8·S)) is printed by the tests (0.26 on AVX2 hardware when written).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from core.config.settings import BRDFSettings, LaserSettings, ReceiverSettings
from core.physics.brdf import evaluate_brdf, evaluate_materials
from core.physics.radiometry import energy_scale, received_energy

TINY = np.finfo(np.float64).tiny  # below it float64 loses precision: both forms round to the subnormal grid
U = 2.0 ** -53  # float64 unit roundoff
LD = np.longdouble
assert np.finfo(LD).eps <= 2.0 ** -63, "the reference needs x87 extended precision (x86-64)"

MATERIALS = [
    BRDFSettings(model="lambertian", reflectance=0.25),
    BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0),
    BRDFSettings(model="steinvall", specular_a=1e3, slope_s=10.0, diffuse_b=0.0, diffuse_m=0.0),
    BRDFSettings(model="steinvall", specular_a=0.0, slope_s=0.2, diffuse_b=0.3, diffuse_m=40.0),
    BRDFSettings(model="table", table_angle_deg=[0.0, 10.0, 30.0, 60.0], table_brdf_per_sr=[1.0, 0.5, 0.2, 0.1]),
    BRDFSettings(model="table", table_angle_deg=[20.0, 45.0, 80.0], table_brdf_per_sr=[3.0, 0.0, 0.0]),
    BRDFSettings(model="lambertian", reflectance=0.0),
]


def table_theta_deg(cos_theta):
    """θ in degrees as the kernel forms it: the C library's scalar acos, times 180/π (np.degrees' constant).
    NumPy's vectorised arccos differs from it in the last bits on some CPUs (AVX-512)."""
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0).ravel()
    return (np.array([math.acos(x) for x in c]) * (180.0 / math.pi)).reshape(np.shape(cos_theta))


def steinvall_exponent(brdf, cos_theta):
    """The Steinvall lobe's exponent −tan²θ/s² − 6 ln cos θ in long double (cos θ clamped as the kernel does)."""
    c = np.clip(np.asarray(cos_theta, dtype=LD), LD(1e-150), LD(1.0))
    tan2 = np.maximum((1 - c * c) / (c * c), LD(0))
    return -tan2 / LD(brdf.slope_s) ** 2 - 6 * np.log(c), c


def reference_brdf(brdf, cos_theta):
    """f_r in long double: the closed forms of docs/theory.md §10; tables by np.interp in degrees (float64, at
    the kernel's θ: the interpolation is the code's promise, value for value)."""
    if brdf.model == "lambertian":
        return np.full(np.shape(cos_theta), LD(brdf.reflectance) / LD(np.pi) if brdf.reflectance else LD(0))
    if brdf.model == "table":
        return np.interp(table_theta_deg(cos_theta), np.asarray(brdf.table_angle_deg, float),
                         np.asarray(brdf.table_brdf_per_sr, float)).astype(LD)
    exponent, c = steinvall_exponent(brdf, cos_theta)
    specular = LD(brdf.specular_a) * np.exp(np.minimum(exponent, LD(700))) if brdf.specular_a else LD(0)
    return specular + LD(brdf.diffuse_b) * c ** LD(brdf.diffuse_m)


def brdf_log_terms(brdf, cos_theta):
    """The BRDF's part of S (module docstring): |x| + 1/s² + 6|ln cos θ| + m|ln cos θ| for Steinvall, 0 else."""
    if brdf.model != "steinvall":
        return np.zeros(np.shape(cos_theta))
    exponent, c = steinvall_exponent(brdf, cos_theta)
    lnc = np.abs(np.log(c))
    return np.abs(np.minimum(exponent, LD(700))).astype(float) + 1.0 / brdf.slope_s ** 2 + \
        ((6.0 + brdf.diffuse_m) * lnc).astype(float)


def reference_energy(laser, rx, sigma, materials, ids, cos_theta, range_m, fraction):
    """Eq. 3-1 in long double, as exp of the log-space sum (zeros where a factor is zero), with the aperture's
    projected solid angle π r_a²/(R² + r_a²)."""
    ids, cos_theta, range_m = np.asarray(ids), np.asarray(cos_theta, float), np.asarray(range_m, float)
    fraction = np.broadcast_to(np.asarray(fraction, float), cos_theta.shape)
    f_r = np.zeros(len(ids), dtype=LD)
    for k, m in enumerate(materials):
        f_r[ids == k] = reference_brdf(m, cos_theta[ids == k])
    radius = LD(0.5) * LD(rx.aperture_diameter_m)
    scale = LD(laser.pulse_energy_j) * LD(rx.system_efficiency) * LD(np.pi) * radius * radius
    c = np.clip(cos_theta.astype(LD), LD(0), LD(1))
    r = range_m.astype(LD)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # the aperture's projected solid angle π r_a²/(R² + r_a²) (core/physics/radiometry.py)
        log_e = (np.log(scale) + np.log(fraction.astype(LD)) + np.log(f_r) + np.log(c)
                 - np.log(r * r + radius * radius) - 2 * LD(sigma) * r)
        return np.exp(log_e)


def rounding_bound(laser, rx, sigma, materials, ids, cos_theta, range_m, fraction):
    """Per-ray relative bound u·(64 + 8·S) of the kernel's float64 rounding (module docstring)."""
    ids, cos_theta, range_m = np.asarray(ids), np.asarray(cos_theta, float), np.asarray(range_m, float)
    fraction = np.broadcast_to(np.asarray(fraction, float), cos_theta.shape)
    s = np.zeros(len(ids))
    for k, m in enumerate(materials):
        s[ids == k] = brdf_log_terms(m, cos_theta[ids == k])
    scale = energy_scale(laser, rx)
    with np.errstate(divide="ignore"):
        s += (abs(math.log(scale)) if scale > 0 else 0.0) + np.abs(np.log(np.where(fraction > 0, fraction, 1.0)))
        # ln(R² + r_a²) is formed as 2 ln max(R, r_a) + log1p(…) (≤ ln 2)
        s += np.abs(np.log(np.clip(cos_theta, TINY, 1.0)))
        s += 2 * np.abs(np.log(np.maximum(np.maximum(range_m, TINY), 0.5 * rx.aperture_diameter_m))) + math.log(2)
        s += 2 * sigma * range_m
    return U * (64.0 + 8.0 * s)


def rays():
    """Every material × incidence × range × fraction combination."""
    deg = np.array([0.0, 1e-6, 5.0, 10.0, 20.0, 25.0, 30.0, 44.9, 45.0, 60.0, 75.0, 85.0, 89.0, 89.999])
    cos = np.concatenate([np.cos(np.radians(deg)), [1.0, 1e-3, 1e-8, 1e-30, 1e-150, 1e-300, 5e-324, 0.0, -1e-7,
                                                    float(np.float32(np.cos(np.float32(np.pi / 2))))]])
    rng = np.array([1e-3, 0.5, 1.0, 10.0, 300.0, 1234.5, 1e4, 2e4, 1e5, 1e7, 1e30, 1e100, 1e150, 1e160, 1e200])
    frac = np.array([1.0, 0.37, 1e-6, 1e-12, 1e-200, 0.0])
    m, c, r, f = np.meshgrid(np.arange(len(MATERIALS)), cos, rng, frac, indexing="ij")
    return m.ravel(), c.ravel(), r.ravel(), f.ravel()


def compare(new, ref, bound):
    """Max of the relative deviation over its bound on the normal results (≤ 1 passes); zeros exact; results
    on float64's subnormal grid within the bound plus one step of that grid (5e-324)."""
    assert np.all(np.isfinite(new)) and np.all(new >= 0)
    assert np.all(new[ref == 0] == 0)
    normal = ref >= TINY
    rel = (np.abs(new[normal].astype(LD) - ref[normal]) / ref[normal]).astype(float)
    sub = (ref > 0) & ~normal
    assert np.all(np.abs(new[sub].astype(LD) - ref[sub]) <= bound[sub] * ref[sub] + LD(5e-324))
    return float((rel / bound[normal]).max()) if rel.size else 0.0


def checked(laser, rx, sigma, ids, cos, rng, frac):
    """(kernel energies, long-double reference, bound).  Where f_r itself is below float64's normal range (a
    grazing ray on a cos⁴⁰θ lobe) float64 cannot hold it to better than a step of the subnormal grid, so the
    reference takes the kernel's own f_r there: the product's arithmetic is what is compared."""
    new = received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, frac)
    ref = reference_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, frac)
    f64 = evaluate_materials(MATERIALS, ids, cos)
    tiny_fr = (f64 > 0) & (f64 < TINY)
    if tiny_fr.any():
        sub_materials = MATERIALS + [BRDFSettings(model="lambertian", reflectance=1.0)]
        r = reference_energy(laser, rx, sigma, sub_materials, np.full(int(tiny_fr.sum()), len(MATERIALS)),
                             cos[tiny_fr], rng[tiny_fr], np.broadcast_to(frac, cos.shape)[tiny_fr])
        ref[tiny_fr] = r * LD(np.pi) * f64[tiny_fr].astype(LD)  # f_r = 1/π there: replaced by the kernel's
    bound = rounding_bound(laser, rx, sigma, MATERIALS, ids, cos, rng, frac)
    return new, ref, bound


@pytest.mark.parametrize("sigma", [0.0, 1e-4, 0.05, 2.0])
@pytest.mark.parametrize("laser_e, eta", [(1e-3, 0.5), (0.2, 1.0), (1e-9, 0.05)])
def test_product_matches_extended_precision(sigma, laser_e, eta):
    laser = LaserSettings(pulse_energy_j=laser_e)
    rx = ReceiverSettings(system_efficiency=eta)
    ids, cos, rng, frac = rays()
    new, ref, bound = checked(laser, rx, sigma, ids, cos, rng, frac)
    assert np.all(np.isfinite(ref) | (rng > 1e150))  # the log form's 0·inf at R = inf (never a hit's range)
    ok = np.isfinite(ref)
    worst = compare(new[ok], ref[ok], bound[ok])
    print(f"largest deviation / bound: {worst:.3g}")
    assert worst <= 1.0
    assert (ref[ok] == 0).any() and (ref[ok] >= TINY).any()
    if sigma == 0.0:  # the grid reaches the subnormal results too
        assert ((ref[ok] > 0) & (ref[ok] < TINY)).any()
    # one number for every ray's fraction gives the same energies as the per-ray array
    one = received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, 0.37)
    assert np.array_equal(one, received_energy(laser, rx, sigma, MATERIALS, ids, cos, rng, np.full(len(ids), 0.37)))


def test_random_rays_and_max_deviation():
    """Random rays (ranges 1 m – 20 km, any incidence, fractions 1e-8 – 1, σ up to 0.02 /m) within the rounding
    bound; and, for a scale a reader knows, within 1e-12 relative (the deviation grows with 2σR, the exponent
    here: 1.2e-13 at most when written)."""
    gen = np.random.default_rng(7)
    n = 200_000
    ids = gen.integers(0, len(MATERIALS) - 1, n)
    cos = gen.uniform(-0.01, 1.0, n)
    rng = 10 ** gen.uniform(0.0, 4.3, n)
    frac = 10 ** gen.uniform(-8, 0, n)
    laser, rx = LaserSettings(), ReceiverSettings()
    worst, worst_rel = 0.0, 0.0
    for sigma in (0.0, 3.9e-4, 0.02):
        new, ref, bound = checked(laser, rx, sigma, ids, cos, rng, frac)
        worst = max(worst, compare(new, ref, bound))
        normal = ref >= TINY
        worst_rel = max(worst_rel, float((np.abs(new[normal] - ref[normal]) / ref[normal]).max()))
    print(f"largest deviation / bound: {worst:.3g}; largest relative deviation: {worst_rel:.3g}")
    assert worst <= 1.0
    assert worst_rel <= 1e-12  # here S ≤ 400 (|ln E_r| up to ≈ 120, 2σR ≤ 800): u·(64 + 8·400) = 3.6e-13


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
        if brdf.model == "table":  # np.interp's arithmetic at the kernel's θ, value for value
            assert np.array_equal(new, ref.astype(float)), brdf
            continue
        # Lambertian: ρ/π rounded once (≤ u/2 + π's own rounding); Steinvall: the exponent's rounding
        # (module docstring) plus exp, the products and the sum, each ≤ 4 ulp (u·(16 + 4·S))
        bound = U * (16.0 + 4.0 * brdf_log_terms(brdf, cos))
        normal = ref >= TINY
        rel = (np.abs(new[normal].astype(LD) - ref[normal]) / ref[normal]).astype(float)
        assert np.all(rel <= bound[normal]), (brdf, float((rel / bound[normal]).max()))
        assert np.all(np.abs(new[~normal].astype(LD) - ref[~normal]) <= LD(5e-324)), brdf
    ids = np.arange(len(cos)) % len(MATERIALS)
    f = evaluate_materials(MATERIALS, ids, cos)
    for k, brdf in enumerate(MATERIALS):
        assert np.array_equal(f[ids == k], evaluate_brdf(brdf, cos[ids == k]))
    assert float(evaluate_brdf(MATERIALS[1], 1.0)) == pytest.approx(0.13, rel=1e-12)
    with pytest.raises(IndexError):
        evaluate_materials(MATERIALS[:2], np.array([0, 2]), np.array([1.0, 1.0]))
    assert math.isfinite(float(evaluate_brdf(MATERIALS[2], 1e-300)))
