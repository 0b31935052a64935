"""Gated viewing honours receiver.subray_pattern: stratified and Sobol sub-rays (issue 32).

Reference: a plate at 1 km whose straight edge crosses the field of view obliquely.  With a uniform beam every
pixel receives its fully covered energy (a run of the same plate without the edge, on the grid: the energy per
unit tan-plane area varies across a pixel by cos³θ, < 1e-5 here) times the exact fraction of its tan-plane square
on the plate's side of the edge (the polygon clipped by the line).  The patterns are Monte Carlo / quasi Monte Carlo
estimates of that fraction; their spread over seeds is the sampling error the tests hold them to.
"""
import numpy as np
import pytest

from core.config.settings import SimulationConfig
from core.errors import ConfigError
from core.geometry.rays import Detector
from core.geometry.scene import SceneGeometry
from core.run import simulate
from scenes import C, plate

D = 1000.0
#: the edge: points (x, y) of the tan plane with NX·x + NY·y ≤ OFF are on the plate
ANGLE = np.radians(27.0)
NX, NY, OFF = np.cos(ANGLE), np.sin(ANGLE), 0.37e-3


def gated_config(subsamples, pattern, seed=0, pixels=8, fov=8e-3):
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px = cfg.receiver.height_px = pixels
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = fov
    cfg.receiver.subsamples = subsamples
    cfg.receiver.subray_pattern = pattern
    cfg.laser.beam_profile = "uniform"
    cfg.laser.pulse_fwhm_s = 10e-9
    g = cfg.gated
    g.gate_width_s, g.delay_step_s, g.n_slices = 20e-9, 10e-9, 6
    g.first_delay_s = 2 * D / C - 3 * g.delay_step_s
    cfg.run.threads = 1
    cfg.run.seed = seed
    return cfg


def edge_plate():
    """A plate at D (sensor frame, looking along −Z) bounded by the line NX·x + NY·y = OFF of the tan plane, its
    other edges far outside the field of view."""
    t = np.array([-NY, NX])             # along the edge
    n = np.array([NX, NY])              # out of the plate
    p0 = OFF * n
    big = 0.05
    corners = [p0 - big * t, p0 + big * t, p0 + big * t - big * n, p0 - big * t - big * n]
    verts = np.array([[x * D, y * D, -D] for x, y in corners])
    return SceneGeometry(verts, [[0, 1, 2], [0, 2, 3]], [0, 0])


def clipped_fraction(x0, x1, y0, y1):
    """Exact fraction of the square [x0, x1] × [y0, y1] with NX·x + NY·y ≤ OFF (Sutherland–Hodgman, one line)."""
    poly = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    out = []
    for k in range(4):
        a, b = poly[k], poly[(k + 1) % 4]
        fa, fb = NX * a[0] + NY * a[1] - OFF, NX * b[0] + NY * b[1] - OFF
        if fa <= 0:
            out.append(a)
        if fa * fb < 0:
            s = fa / (fa - fb)
            out.append((a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1])))
    if len(out) < 3:
        return 0.0
    xs, ys = np.array(out).T
    area = 0.5 * abs(np.dot(xs, np.roll(ys, -1)) - np.dot(ys, np.roll(xs, -1)))
    return min(area / ((x1 - x0) * (y1 - y0)), 1.0)


def reference_energy(cfg):
    """Per-pixel energy image of the edge plate (full-coverage energy × exact covered fraction), the covered
    fraction, and the variance of one stratified run per pixel: one uniform point in each of the S² cells of equal
    weight E/S², a hit with the cell's covered fraction p_c, so Var = (E/S²)² Σ_c p_c (1 − p_c)."""
    full = simulate(plate(D, 50.0), np.eye(4), gated_config(4, "grid")).energy_image
    det = Detector.from_settings(cfg.receiver)
    s = cfg.receiver.subsamples
    px, py = det.pixel_pitch_tan
    frac = np.zeros((det.height_px, det.width_px))
    var = np.zeros_like(frac)
    for iy in range(det.height_px):
        for ix in range(det.width_px):
            x0 = -det.half_width_tan + ix * px
            y1 = det.half_height_tan - iy * py
            frac[iy, ix] = clipped_fraction(x0, x0 + px, y1 - py, y1)
            p = np.array([clipped_fraction(x0 + i * px / s, x0 + (i + 1) * px / s, y1 - (j + 1) * py / s,
                                           y1 - j * py / s) for i in range(s) for j in range(s)])
            p = np.clip(p, 0.0, 1.0)
            var[iy, ix] = (full[iy, ix] / s ** 2) ** 2 * np.sum(p * (1 - p))
    return full * frac, frac, var


@pytest.fixture(scope="module")
def reference():
    return reference_energy(gated_config(4, "grid"))


@pytest.mark.parametrize("pattern", ["stratified", "sobol"])
def test_a_full_plate_gives_the_grid_energy_and_ranges(pattern):
    """Every jittered ray carries its cell's exact beam energy and is evaluated at its cell's centre on the plane
    it hit: on a plate filling the field of view the patterns give the grid's energy (1e-6) and its ranges from
    the slices within the second-order error of that first-order step, ½·D·δ² with δ the half diagonal of a cell
    (R = D·√(1 + x² + y²) is convex: 1.6e-5 m here), where the raw jittered ranges would move the slices by up to
    D·θ·δ (1e-3 relative)."""
    grid = simulate(plate(D, 50.0), np.eye(4), gated_config(4, "grid"))
    other = simulate(plate(D, 50.0), np.eye(4), gated_config(4, pattern, seed=3))
    np.testing.assert_allclose(other.energy_image, grid.energy_image, rtol=1e-6)
    cell = 8e-3 / 8 / 4
    bound = 0.5 * D * 2 * (cell / 2) ** 2
    diff = np.abs(other.range_image - grid.range_image)
    ulp = float(np.spacing(np.float32(D)))  # the range image is float32
    assert np.isfinite(diff).all() and diff.max() <= bound + ulp, (diff.max(), bound)
    assert diff.max() > 0  # the rays did move


def test_stratified_energy_is_unbiased_within_its_sampling_error(reference):
    """Over 12 seeds the mean stratified energy of every pixel meets the exact reference within 4 standard errors
    of the stratified estimator (its variance from the cells' covered fractions), and the seeds' scatter over the
    edge pixels is that variance (Σ of squared deviations / Σ Var within the 12·(pixels) degrees of freedom:
    between 0.5 and 1.6)."""
    ref, frac, var = reference
    n = 12
    runs = np.stack([simulate(edge_plate(), np.eye(4), gated_config(4, "stratified", seed=s)).energy_image
                     for s in range(1, n + 1)])
    edge = var > 0
    assert edge.sum() >= 6
    floor = 1e-6 * ref.max()  # cos³θ across a pixel
    assert np.all(np.abs(runs.mean(axis=0) - ref) <= 4 * np.sqrt(var / n) + floor)
    ratio = np.sum((runs - ref)[:, edge] ** 2) / (n * var[edge].sum())
    print(f"stratified scatter / theory: {ratio:.3f}")
    assert 0.5 < ratio < 1.6, ratio
    totals = runs.sum(axis=(1, 2))
    assert abs(totals.mean() - ref.sum()) <= 4 * np.sqrt(var.sum() / n) + floor * ref.size


def test_grid_and_stratified_agree_within_the_sampling_error(reference):
    """One stratified run and the grid (same S) give the same total energy within 4× the stratified spread."""
    ref, _, var = reference
    grid = simulate(edge_plate(), np.eye(4), gated_config(4, "grid")).energy_image.sum()
    one = simulate(edge_plate(), np.eye(4), gated_config(4, "stratified", seed=1)).energy_image.sum()
    assert abs(one - grid) <= 4 * np.sqrt(var.sum()) + abs(grid - ref.sum())
    assert abs(grid - ref.sum()) <= 0.01 * ref.sum()  # the grid's own (aliasing) error on this edge


def test_sobol_converges_to_the_exact_energy(reference):
    """Sobol nets (S a power of two: one point per cell) converge on the edge pixels: the RMS error over pixels
    and 4 seeds falls from S = 2 to S = 16 at least as fast as N^(-1/2) (Monte Carlo) — a net does better,
    ≈ N^(-3/4) for an edge — and S = 3 (not a power of two: intensity weights) is unbiased too."""
    ref, frac, var = reference
    edge = var > 0
    rms = {}
    for s in (2, 4, 8, 16):
        err = np.stack([simulate(edge_plate(), np.eye(4), gated_config(s, "sobol", seed=k)).energy_image - ref
                        for k in range(4)])
        rms[s] = float(np.sqrt(np.mean(err[:, edge] ** 2)))
    for a, b in ((2, 4), (4, 8), (8, 16)):
        assert rms[b] < rms[a]
    print("sobol RMS error by S:", rms)
    assert rms[16] <= rms[2] * (4.0 / 256.0) ** 0.5, rms  # N from 4 to 256 rays per pixel
    runs = np.stack([simulate(edge_plate(), np.eye(4), gated_config(3, "sobol", seed=k)).energy_image
                     for k in range(12)])
    totals = runs.sum(axis=(1, 2))
    se = totals.std(ddof=1) / np.sqrt(len(runs))
    assert se > 0 and abs(totals.mean() - ref.sum()) <= 4 * se + 1e-6 * ref.sum()


def test_patterns_are_reproducible_and_seeded():
    a = simulate(edge_plate(), np.eye(4), gated_config(4, "stratified", seed=5))
    b = simulate(edge_plate(), np.eye(4), gated_config(4, "stratified", seed=5))
    c = simulate(edge_plate(), np.eye(4), gated_config(4, "stratified", seed=6))
    np.testing.assert_array_equal(a.slices, b.slices)
    assert not np.array_equal(a.slices, c.slices)


def test_adaptive_is_refused_for_the_gated_system():
    cfg = gated_config(4, "adaptive")
    with pytest.raises(ConfigError) as err:
        simulate(edge_plate(), np.eye(4), cfg)
    msg = str(err.value)
    assert err.value.field == "receiver.subray_pattern" and "adaptive" in msg and "'stratified'" in msg
    assert "\n" not in msg
