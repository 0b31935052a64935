"""Sub-ray patterns (core/physics/sampling.py, receiver.subray_pattern): exact energy per pixel, stratification,
determinism whatever the blocks, and better accuracy than the regular grid at an edge."""
import dataclasses

import numpy as np
import pytest

from core.config.settings import BRDFSettings, DetectionSettings, LaserSettings
from core.physics.detection.peaks import detect_echoes
from core.physics.laser import cell_energy_fractions
from core.systems.flash import simulate_frame
from core.geometry.rays import Detector, block_subray_tan, tan_to_unit_direction
from core.physics.sampling import SubraySampler, hash_uniform
from core.geometry.scene import SceneGeometry, merge_meshes
from scenes import config_for, plate


def _sampler(pattern, s=4, seed=3, laser=None, offset=(0.0, 0.0), scale=1.0, w=6, h=5, refine=4):
    det = Detector(w, h, s, 0.01, 0.008)
    laser = laser or LaserSettings(divergence_fills_fov=False, beam_divergence_rad=0.012)
    fr = cell_energy_fractions(laser, det, offset, scale)
    fine = cell_energy_fractions(laser, dataclasses.replace(det, subsamples=s * refine), offset, scale)
    return det, fr, SubraySampler(det, pattern, fr, seed, laser=laser, beam_offset_tan=offset,
                                  beam_width_scale=scale, refine=refine, fine_fractions=fine)


def test_unit_directions_are_the_normalised_tan_plane_vectors():
    """(x, y, −1)/√(x² + y² + 1): unit length within 3e-16, the tan-plane point recovered within 1e-15, and bit
    for bit NumPy's stack-and-norm of the vectors (the compiled pass sums (x² + y²) + 1 in its order)."""
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-2.0, 2.0, (3, 1001)), rng.uniform(-2.0, 2.0, (3, 1001))
    d = tan_to_unit_direction(x, y)
    assert d.shape == (3, 1001, 3) and d.dtype == np.float64
    assert np.abs(np.linalg.norm(d, axis=-1) - 1.0).max() <= 3e-16
    assert np.allclose(d[..., 0] / -d[..., 2], x, rtol=1e-15, atol=0) and np.all(d[..., 2] < 0)
    v = np.stack([x, y, -np.ones_like(x)], axis=-1)
    assert np.array_equal(d, v / np.linalg.norm(v, axis=-1, keepdims=True))
    assert np.array_equal(tan_to_unit_direction(0.0, 0.0), [0.0, 0.0, -1.0])


@pytest.mark.parametrize("pattern,s", [("grid", 4), ("stratified", 4), ("sobol", 4), ("sobol", 3),
                                       ("stratified", 1), ("sobol", 8), ("adaptive", 2)])
def test_weights_sum_to_the_exact_erf_energy_of_each_pixel(pattern, s):
    """Gaussian beam off-centre and widened: a pixel's ray weights sum to ∫ over the pixel of the beam
    = ¼[erf(√2x₁/w) − erf(√2x₀/w)][erf(√2y₁/w) − erf(√2y₀/w)] (rel. 1e-12), refined pixels included."""
    det, (fx, fy), smp = _sampler(pattern, s, offset=(0.002, -0.001), scale=1.3)
    pix = smp.block(0, det.n_pixels)
    if pattern == "adaptive":
        pix = smp.refined(np.array([0, 7, 29]))
    sums = np.bincount(pix.pixel, weights=pix.weight, minlength=det.n_pixels)
    ix, iy = np.arange(det.n_pixels) % det.width_px, np.arange(det.n_pixels) // det.width_px
    exact = fx.reshape(det.width_px, s).sum(1)[ix] * fy.reshape(det.height_px, s).sum(1)[iy]
    present = np.unique(pix.pixel)
    assert sums[present] == pytest.approx(exact[present], rel=1e-12)
    # the rays lie in their pixel, and sub_x/sub_y name the base cell that holds them
    px, py = det.pixel_pitch_tan
    col = np.floor((pix.x_tan + det.half_width_tan) / px).astype(int)
    row = np.floor((det.half_height_tan - pix.y_tan) / py).astype(int)
    assert np.array_equal(col, pix.pixel % det.width_px) and np.array_equal(row, pix.pixel // det.width_px)
    cx = np.floor((pix.x_tan + det.half_width_tan) / (px / s)).astype(int)
    assert np.array_equal(cx, pix.sub_x)


@pytest.mark.parametrize("pattern", ["stratified", "sobol"])
def test_one_ray_per_cell_and_jointly_stratified(pattern):
    """S = 8: each of the 64 cells of a pixel holds exactly one ray; the Sobol net is also stratified in every
    1/64 × 1 and 1 × 1/64 strip (a (0, 6, 2)-net), the jittered grid is not."""
    det, _, smp = _sampler(pattern, 8)
    pix = smp.block(0, det.n_pixels)
    s2 = 64
    cells = (pix.sub_y * 1000 + pix.sub_x).reshape(-1, s2)
    assert all(len(np.unique(c)) == s2 for c in cells)
    px, _ = det.pixel_pitch_tan
    u = ((pix.x_tan + det.half_width_tan) / px) % 1.0
    strips = np.floor(u * s2).astype(int).reshape(-1, s2)
    distinct = np.array([len(np.unique(c)) for c in strips])
    if pattern == "sobol":
        assert np.all(distinct == s2)
    else:
        assert distinct.mean() < 0.8 * s2


@pytest.mark.parametrize("pattern", ["stratified", "sobol"])
def test_samples_do_not_depend_on_blocks_and_follow_the_seed(pattern):
    det, fr, smp = _sampler(pattern, 4)
    whole = smp.block(0, det.n_pixels)
    parts = [smp.block(a, min(a + 7, det.n_pixels)) for a in range(0, det.n_pixels, 7)]
    assert np.array_equal(np.concatenate([p.x_tan for p in parts]), whole.x_tan)
    assert np.array_equal(np.concatenate([p.y_tan for p in parts]), whole.y_tan)
    other = SubraySampler(det, pattern, fr, seed=4).block(0, det.n_pixels)
    assert not np.array_equal(other.x_tan, whole.x_tan)
    again = SubraySampler(det, pattern, fr, seed=3).block(0, det.n_pixels)
    assert np.array_equal(again.x_tan, whole.x_tan)


def test_hash_uniform_is_uniform_and_counter_based():
    """Mean 1/2 and variance 1/12 within 5σ of their sampling error over 10⁶ counters; 10 equal bins each
    within 5σ of 10⁵; the value depends only on (counter, key)."""
    u = hash_uniform(np.arange(1_000_000, dtype=np.uint64), 12345)
    assert np.all((u >= 0) & (u < 1))
    assert abs(u.mean() - 0.5) < 5 * np.sqrt(1 / 12 / 1e6)
    assert abs(u.var() - 1 / 12) < 5 * np.sqrt(1 / 180 / 1e6)
    counts = np.bincount((u * 10).astype(int), minlength=10)
    assert np.all(np.abs(counts - 1e5) < 5 * np.sqrt(1e5 * 0.9))
    assert np.array_equal(hash_uniform(np.arange(5, 10, dtype=np.uint64), 12345), u[5:10])


def _edge_scene(angle_deg=0.0):
    """A bright plate (50 %) whose corner lies in the field of view, its edges turned by ``angle_deg`` from the
    pixel axes (uniform beam: a pixel's energy follows its covered fraction), with a dark plate (5 %) 3 m
    behind filling the rest: a range and material step along the edges."""
    near = plate(100.0, 2.0, offset=(-2.0 + 0.13, -2.0 + 0.21, 0.0))
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    c = np.array([0.0, 0.0, -100.0])
    near_v = (near.vertices_m - c) @ rot.T + c
    far = plate(103.0, 5.0)
    return merge_meshes([(near_v, near.triangles, near.material_ids, ["near"], [BRDFSettings(reflectance=0.5)]),
                         (far.vertices_m, far.triangles, far.material_ids, ["far"], [BRDFSettings(reflectance=0.05)])])


def _edge_config(pattern, s):
    cfg = config_for(100.0, pixels=12, subsamples=s, fov_rad=0.01, bins=160, bin_s=0.5e-9, margin_bins=40)
    cfg.laser.beam_profile = "uniform"
    cfg.receiver.subray_pattern = pattern
    return cfg


def _energy_errors(scene, cases):
    """RMS energy-image error relative to the mean against 64×64 grid rays per pixel, and the run stats."""
    ref = simulate_frame(scene, np.eye(4), _edge_config("grid", 64)).energy_image
    out = {}
    for pattern, s in cases:
        res = simulate_frame(scene, np.eye(4), _edge_config(pattern, s))
        out[pattern, s] = (np.sqrt(np.mean((res.energy_image - ref) ** 2)) / ref.mean(), res.stats)
    return out


def test_sobol_and_adaptive_beat_the_grid_at_axis_aligned_edges():
    """Edges along the pixel axes at a fixed offset inside the pixels (man-made scenes): the grid's error
    does not drop from 4×4 to 8×8 rays (2.8 % both, measured); Sobol's 4×4 is half the grid's and its 8×8 a
    fifth; adaptive 2×2 (refining the 16 edge pixels to 8×8) beats the 16×16 grid with < 1/16 of its rays."""
    err = _energy_errors(_edge_scene(0.0), [("grid", 4), ("grid", 8), ("grid", 16), ("sobol", 4), ("sobol", 8),
                                           ("adaptive", 2)])
    grid4, grid8, grid16 = err["grid", 4][0], err["grid", 8][0], err["grid", 16][0]
    assert grid4 > 0.02 and grid8 > 0.75 * grid4
    assert err["sobol", 4][0] < 0.6 * grid4 and err["sobol", 8][0] < 0.25 * grid8
    adaptive, stats = err["adaptive", 2]
    assert 12 <= stats["adaptive"]["refined_pixels"] <= 20  # the pixels along the corner's two edges
    assert stats["n_rays"] == 144 * 4 + stats["adaptive"]["refined_pixels"] * 64
    assert adaptive < grid16 and stats["n_rays"] < 144 * 16 * 16 / 16


def test_adaptive_beats_the_grid_at_slanted_edges():
    """Edges at 17° to the pixel axes (the grid's good case: 1.5 % at 4×4, 0.3 % at 8×8, measured): adaptive
    4×4 refined to 16×16 on the 16 edge pixels errs < 0.6 %, a third of the 4×4 grid's."""
    err = _energy_errors(_edge_scene(17.0), [("grid", 4), ("adaptive", 4)])
    adaptive, stats = err["adaptive", 4]
    assert stats["adaptive"]["refined_pixels"] >= 12
    assert adaptive < 0.4 * err["grid", 4][0] and adaptive < 0.006


def test_adaptive_refines_range_steps_and_material_edges_only():
    """Pixels refined: none on a flat tilted plate alone (its ranges follow its plane), one column where two
    materials meet on one plane, the pixels along an edge with a 3 m range step."""
    cfg = _edge_config("adaptive", 2)
    tilted = plate(100.0, 5.0, tilt_rad=1.2)
    assert simulate_frame(tilted, np.eye(4), cfg).stats["adaptive"]["refined_pixels"] == 0
    left = plate(100.0, 2.5, offset=(-2.5 + 0.13, 0.0, 0.0))
    right = plate(100.0, 2.5, offset=(2.5 + 0.13, 0.0, 0.0))
    two = merge_meshes([(left.vertices_m, left.triangles, left.material_ids, ["a"], [BRDFSettings(reflectance=0.1)]),
                        (right.vertices_m, right.triangles, right.material_ids, ["b"],
                         [BRDFSettings(reflectance=0.5)])])
    res = simulate_frame(two, np.eye(4), cfg)
    assert res.stats["adaptive"]["refined_pixels"] == 12  # one column of 12 pixels holds the seam
    same = merge_meshes([(left.vertices_m, left.triangles, left.material_ids, ["a"], [BRDFSettings()]),
                         (right.vertices_m, right.triangles, right.material_ids, ["a"], [BRDFSettings()])])
    assert simulate_frame(same, np.eye(4), cfg).stats["adaptive"]["refined_pixels"] == 0  # one plane, one material


@pytest.mark.parametrize("pattern", ["stratified", "sobol", "adaptive"])
def test_products_do_not_depend_on_threads_or_chunking(pattern):
    scene = _edge_scene()
    ref = None
    for threads, chunk in ((1, 100_000_000), (2, 1024)):
        cfg = _edge_config(pattern, 4)
        cfg.run.threads, cfg.run.chunk_rays = threads, chunk
        res = simulate_frame(scene, np.eye(4), cfg)
        if ref is None:
            ref = res
            continue
        assert res.stats["n_blocks"] > 1
        assert np.array_equal(res.waveforms, ref.waveforms)
        assert np.array_equal(res.energy_image, ref.energy_image)
        assert np.array_equal(res.range_image, ref.range_image, equal_nan=True)


def test_plateau_wiggles_are_one_echo_but_resolved_pulses_are_two():
    """min_dip: a flat-topped return with 1e-5 wiggles is one echo (it used to be three); two Gaussian pulses
    2.2σ apart (a 1.3 % dip) are two, 2.0σ apart (no dip: the Sparrow limit) one."""
    w = np.zeros((1, 200))
    w[0, 50:150] = 1.0 + 1e-5 * np.sin(np.arange(100))
    assert len(detect_echoes(w, DetectionSettings()).pixel) == 1
    assert len(detect_echoes(w, DetectionSettings(min_dip=0.0)).pixel) > 1
    x = np.arange(200) + 0.5
    for sep, n in ((2.2, 2), (2.0, 1)):
        pulses = np.exp(-0.5 * ((x - 100) / 2.0) ** 2) + np.exp(-0.5 * ((x - 100 - 2.0 * sep) / 2.0) ** 2)
        assert len(detect_echoes(pulses[None], DetectionSettings()).pixel) == n


@pytest.mark.parametrize("s", [1, 3, 4])
def test_grid_rays_are_the_cell_centres_bit_for_bit(s):
    """The grid pattern (compiled) gives block_subray_tan's cell centres and the cells' fy·fx energies bit for
    bit, for any block of pixels; no offsets; the cell sizes of the pattern."""
    det, (fx, fy), smp = _sampler("grid", s, offset=(0.002, -0.001), scale=1.3)
    for a, b in ((0, det.n_pixels), (3, 17), (det.n_pixels - 1, det.n_pixels)):
        got = smp.block(a, b)
        x, y, pix, sx, sy = block_subray_tan(det, a, b)
        assert np.array_equal(got.x_tan, x) and np.array_equal(got.y_tan, y)
        assert np.array_equal(got.pixel, pix) and np.array_equal(got.sub_x, sx) and np.array_equal(got.sub_y, sy)
        assert np.array_equal(got.weight, fy[sy] * fx[sx])
        assert not got.offset_x_tan.any() and not got.offset_y_tan.any()
        assert np.all(got.cell_x_tan == det.pixel_pitch_tan[0] / s)
        assert np.all(got.cell_y_tan == det.pixel_pitch_tan[1] / s)


@pytest.mark.parametrize("pattern,s", [("grid", 4), ("stratified", 4), ("sobol", 4), ("sobol", 3)])
def test_weights_of_gives_another_beams_weights_to_the_same_rays(pattern, s):
    """The gated system draws its rays once (the first slice's sampler) and weighs them per slice with that slice's
    beam: ``weights_of`` of a sampler with another beam offset/width gives exactly the weights that sampler would
    draw for the same rays (same positions: the positions depend on the seed only), and the drawing sampler's own
    weights back."""
    laser = LaserSettings(beam_profile="gaussian", divergence_fills_fov=False, beam_divergence_rad=4e-3)
    a = _sampler(pattern, s=s, laser=laser)[2]
    b = _sampler(pattern, s=s, laser=laser, offset=(2e-4, -1e-4), scale=1.3)[2]
    sa, sb = a.block(3, 17), b.block(3, 17)
    np.testing.assert_array_equal(sa.x_tan, sb.x_tan)
    np.testing.assert_array_equal(a.weights_of(sa), sa.weight)
    np.testing.assert_array_equal(b.weights_of(sa), sb.weight)
    assert not np.allclose(sa.weight, sb.weight)
