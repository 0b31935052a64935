"""Cell range spread (core/physics/sampling.py, core.physics.laser.pulse_box_cdf, core/physics/waveform.py): a sub-ray's cell of a
tilted surface spans a range interval; its return is the pulse convolved with that interval's round-trip times.
Fixes the spurious multi-echoes of grazing ground (issue 7, sample_blends/flash_demo.blend)."""
import numpy as np
import pytest

from core.config.settings import LaserSettings, RangeGateSettings
from core.physics.laser import boxes_cdf, pulse_box_cdf, pulse_sigma_s, sorted_spreads
from core.systems.flash import simulate_frame
from core.physics.sampling import cell_time_spread_s, range_gradient_tan
from core.geometry.scene import SceneGeometry
from core.physics.waveform import accumulate_waveforms
from scenes import C, config_for


def test_pulse_box_cdf_worked_values():
    """Gaussian σ = 1 ⊛ U(2): F(t) = [P₁(t + 1) − P₁(t − 1)]/2, P₁(u) = uΦ(u) + φ(u).
    F(1) = (P₁(2) − P₁(0))/2 = (2.0084907 − 0.3989423)/2 = 0.8047742; F(0) = ½ by symmetry.
    Rectangular τ = 1 ⊛ U(1): the triangle CDF, F(0.25) = 1 − (1 − 0.25)²/2 = 0.71875."""
    laser = LaserSettings(pulse_shape="gaussian", pulse_fwhm_s=2.3548200450309493)  # σ = 1 s
    assert pulse_sigma_s(laser) == pytest.approx(1.0)
    f = pulse_box_cdf(laser, np.array([[0.0, 1.0, -1.0]]), np.array([[2.0, 0.0]]))[0]
    assert f == pytest.approx([0.5, 0.8047742, 1 - 0.8047742], abs=1e-7)
    rect = LaserSettings(pulse_shape="rectangular", pulse_fwhm_s=1.0)
    assert pulse_box_cdf(rect, np.array([[0.25, -0.25, 1.0]]), np.array([[1.0, 0.0]]))[0] == \
        pytest.approx([0.71875, 0.28125, 1.0], abs=1e-15)
    # three boxes 1, 1, 1 (Irwin–Hall n = 3 shifted by 3/2): F(0) = ½, F(0.5) = 1 − 1/6 (0.5)³·... = 0.8333…
    assert boxes_cdf(np.array([0.0, 0.5, 1.5, -1.5]), np.array([1.0, 1.0, 1.0])) == \
        pytest.approx([0.5, 5 / 6, 1.0, 0.0], abs=1e-15)


@pytest.mark.parametrize("shape,fwhm_s,method", [("gaussian", 5e-9, "exact"), ("rectangular", 5e-9, "exact"),
                                                 ("gaussian", 40e-9, "splat"), ("gaussian", 0.2e-9, "exact")])
def test_spread_waveform_matches_dense_quadrature_and_keeps_energy(shape, fwhm_s, method):
    """Each ray's box (a, b) of round-trip times replaced by ≥ 400 × 40 midpoint sub-impulses (a quadrature of the
    same integral): the analytic waveform agrees within 2e-4 of the peak; the energy in the gate is the rays'
    energy (Gaussian support ±6.1σ: 1e-9)."""
    laser = LaserSettings(pulse_shape=shape, pulse_fwhm_s=fwhm_s)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=600)
    rng = np.random.default_rng(3)
    # midpoint quadrature steps well below the pulse σ (the sub-ns pulse needs a finer one)
    n, ka, kb = (12, 400, 40) if fwhm_s > 1e-9 else (6, 2000, 200)
    pix = np.sort(rng.integers(0, 4, n))
    t = rng.uniform(150e-9, 450e-9, n)
    e = rng.uniform(0.5, 1.0, n)
    spread = np.stack([rng.uniform(0, 60e-9, n) * rng.choice([1.0, 0.01], n),
                       rng.uniform(0, 4e-9, n) * rng.choice([1.0, 0.01], n)], axis=1)
    spread[::5] = 0.0
    wf = accumulate_waveforms(pix, t, e, 4, laser, gate, method, spread_s=spread)
    ga, gb = (np.arange(ka) + 0.5) / ka - 0.5, (np.arange(kb) + 0.5) / kb - 0.5
    offsets = (ga[:, None] * spread[:, None, None, 0] + gb[None, :] * spread[:, None, None, 1]).reshape(n, -1)
    ref = accumulate_waveforms(np.repeat(pix, ka * kb), (t[:, None] + offsets).ravel(),
                               np.repeat(e / (ka * kb), ka * kb), 4, laser, gate, method)
    assert np.abs(wf - ref).max() < 2e-4 * wf.max()
    assert wf.sum() == pytest.approx(e.sum(), rel=2e-9)
    # without spread, the rays are impulses: visibly different
    assert np.abs(accumulate_waveforms(pix, t, e, 4, laser, gate, method) - ref).max() > 1e-2 * wf.max()


def test_narrow_boxes_take_the_impulse_path_bit_for_bit():
    """Boxes below 1 % of σ are dropped: the waveform is the impulse one, identical to the last bit."""
    laser = LaserSettings()
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=200)
    t = np.array([50e-9, 80.3e-9, 120.7e-9])
    spread = np.full((3, 2), 0.009 * pulse_sigma_s(laser))
    assert np.all(sorted_spreads(laser, spread) == 0)
    a = accumulate_waveforms(np.array([0, 0, 1]), t, np.ones(3), 2, laser, gate, spread_s=spread)
    b = accumulate_waveforms(np.array([0, 0, 1]), t, np.ones(3), 2, laser, gate)
    assert np.array_equal(a, b)


def test_range_gradient_of_a_plane():
    """∂R/∂x from the formula matches a finite difference of the exact plane range R = D|p|/(n·p)."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[n[:, 2] > 0] *= -1  # facing the sensor (−Z forward)
    x, y = rng.uniform(-0.3, 0.3, 50), rng.uniform(-0.3, 0.3, 50)
    d_plane = rng.uniform(10, 1000, 50)

    def plane_range(xx, yy):
        p = np.stack([xx, yy, -np.ones_like(xx)], axis=1)
        return d_plane * np.linalg.norm(p, axis=1) / np.abs(np.einsum("ij,ij->i", n, p))

    r = plane_range(x, y)
    gx, gy = range_gradient_tan(x, y, r, n)
    h = 1e-6
    assert gx == pytest.approx((plane_range(x + h, y) - plane_range(x - h, y)) / (2 * h), rel=1e-5)
    assert gy == pytest.approx((plane_range(x, y + h) - plane_range(x, y - h)) / (2 * h), rel=1e-5)
    spread = cell_time_spread_s(x, y, r, n, 1e-3, 2e-3)
    assert spread[:, 0] == pytest.approx(2 / C * np.abs(gx) * 1e-3)
    assert spread[:, 1] == pytest.approx(2 / C * np.abs(gy) * 2e-3)


def grazing_ground(height_m=3.0, look_down_deg=1.5):
    """Flat ground (z = 0, Lambertian 30 %) under a sensor ``height_m`` up that looks along +Y tilted down by
    ``look_down_deg`` (as in sample_blends/flash_demo.blend).  Returns (scene, world_from_sensor)."""
    v = np.array([[-100, 0, 0.0], [100, 0, 0.0], [100, 2000, 0.0], [-100, 2000, 0.0]])
    scene = SceneGeometry(v, [[0, 1, 2], [0, 2, 3]], [0, 0])
    a = np.radians(look_down_deg)
    fwd = np.array([0.0, np.cos(a), -np.sin(a)])
    right = np.array([1.0, 0.0, 0.0])
    up = np.cross(right, fwd)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, up, -fwd], axis=1)
    pose[:3, 3] = [0.0, 0.0, height_m]
    return scene, pose


def ground_config(subsamples, spread):
    """8×8 pixels over 1° (rows look 1°–2° down: ground from 86 m to 172 m, 5–21 m of range per pixel)."""
    cfg = config_for(80.0, pixels=8, subsamples=subsamples, fov_rad=np.radians(1.0), bins=700, margin_bins=0)
    cfg.receiver.cell_range_spread = spread
    cfg.receiver.subray_pattern = "grid"
    cfg.laser.beam_profile = "uniform"
    return cfg


def test_grazing_ground_gives_one_echo_per_pixel_and_the_converged_waveform():
    """Grazing ground (the sample scene's artifact): with 4×4 point sub-rays a pixel's return is 4 separate
    pulses, so most ground pixels report several echoes; with the cell range spread every pixel has one
    echo, and its waveform is within 2 % (L2) of the converged 64×64-sub-ray waveform, against > 50 % for
    the point sub-rays (and 3 % for 16×16 point sub-rays: measured 1.1 %, 73 %, 2.8 %)."""
    ground, pose = grazing_ground()
    ref = simulate_frame(ground, pose, ground_config(64, False)).waveforms.astype(np.float64)
    point = simulate_frame(ground, pose, ground_config(4, False))
    cell = simulate_frame(ground, pose, ground_config(4, True))
    n_pixels = 8 * 8
    first = point.points["echo_index"] == 1
    assert first.sum() == n_pixels and np.sum(point.points["n_echoes"][first] > 1) > n_pixels / 2
    first = cell.points["echo_index"] == 1
    assert first.sum() == n_pixels and np.all(cell.points["n_echoes"] == 1)

    def l2(res):
        return np.linalg.norm(res.waveforms - ref) / np.linalg.norm(ref)
    assert l2(cell) < 0.02
    assert l2(point) > 0.5
    # energy is untouched by the spread (it only moves energy in time)
    assert cell.energy_image.sum() == pytest.approx(point.energy_image.sum(), rel=1e-12)
    assert cell.waveforms.sum(dtype=np.float64) == pytest.approx(cell.energy_image.sum(), rel=1e-6)


def test_tail_tables_match_scipy():
    """The cubic-Hermite tail tables (σ/128, exact values and slopes at the nodes) against SciPy on 200k points
    of [0, 12]: Φ(−m), g₁ = φ − mΦ(−m), g = (m² + 1)Φ(−m)/2 − mφ/2 within 1e-11 absolute (measured 5.3e-12, 3.9e-12
    and 2.3e-12); 0 beyond 10 (the true values are < 1e-22 there)."""
    from scipy.special import ndtr

    from core.physics.laser import _tail_interp

    m = np.linspace(0.0, 12.0, 200_001)
    phi = np.exp(-0.5 * m * m) / np.sqrt(2 * np.pi)
    tail = ndtr(-m)
    exact = (tail, phi - m * tail, 0.5 * (m * m + 1.0) * tail - 0.5 * m * phi)
    for fn, ref in enumerate(exact):
        got = np.array([_tail_interp(x, fn) for x in m])
        assert np.abs(got - ref).max() < 1e-11, fn
        assert np.all(got[m >= 10.0] == 0.0) and ref[m >= 10.0].max() < 1e-22


@pytest.mark.parametrize("a_bins,b_bins", [(0.0, 0.0), (3.7, 0.0), (5.3, 1.9), (40.0, 12.0)])
def test_exact_binning_matches_the_closed_form(a_bins, b_bins):
    """Gaussian σ = 2.12 bins ⊛ U(a) ⊛ U(b) binned by the compiled kernel against the closed form in SciPy:
    F(t) = Δ_a Δ_b P₂(t)/(ab) (two boxes), Δ_a P₁(t)/a (one), Φ(t/σ) (none), P₁(u) = σ[zΦ(z) + φ(z)],
    P₂(u) = σ²[(z² + 1)Φ(z) + zφ(z)]/2, z = u/σ, differenced at the bin edges: every bin the kernel evaluates
    (the pulse support, ±6.1σ beyond the boxes) within 1e-10 of the peak (the tables' 1e-11 at two edges, and
    the closed form's own rounding), nothing outside, energy within 2e-9 (the support drops 1e-9)."""
    from scipy.special import ndtr

    laser = LaserSettings()
    sigma = pulse_sigma_s(laser)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=300)
    t0 = np.array([100.3e-9, 151.77e-9, 200.5e-9])
    spread = np.tile([a_bins * 1e-9, b_bins * 1e-9], (3, 1))
    wf = accumulate_waveforms(np.arange(3), t0, np.ones(3), 3, laser, gate, "exact", spread_s=spread)
    edges = np.arange(gate.n_bins + 1) * 1e-9

    def p1(u):
        z = u / sigma
        return sigma * (z * ndtr(z) + np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi))

    def p2(u):
        z = u / sigma
        return sigma ** 2 * ((z * z + 1) * ndtr(z) + z * np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)) / 2

    a, b = a_bins * 1e-9, b_bins * 1e-9
    for k in range(3):
        t = edges - t0[k]
        if a == 0:
            cdf = ndtr(t / sigma)
        elif b == 0:
            cdf = (p1(t + a / 2) - p1(t - a / 2)) / a
        else:
            cdf = (p2(t + a / 2 + b / 2) - p2(t + a / 2 - b / 2) - p2(t - a / 2 + b / 2) + p2(t - a / 2 - b / 2)) / (a * b)
        ref = np.diff(cdf)
        inside = wf[k] > 0
        assert np.abs(wf[k] - ref)[inside].max() < 1e-10 * ref.max(), k
        assert ref[~inside].max() < 3e-9 * ref.max()  # beyond the support
        assert wf[k].sum() == pytest.approx(1.0, abs=2e-9)


def test_four_lane_box_cdfs_equal_the_scalar_kernel_bit_for_bit():
    """gaussian_cdf4 / gaussian_box1_cdf4 / gaussian_box2_cdf4 (the exact binning's kinds 0, 1 and 2, four edges at
    a time in LLVM vector IR) against the scalar gaussian_box_cdf_at, bit for bit, on 400 returns of random
    position, σ and box widths (a box from 0.3σ to 60σ, the second from 0.3σ to the first) over their whole
    support, plus edges placed on the hard points: t = 0, the box ends (t·/a + ½ = 0 or 1, x = a, b, a + b of the
    trapezoid), table nodes and the table's end (|u|/σ = 10 exactly and beyond)."""
    from core.jit import kernel
    from core.physics.laser import gaussian_box1_cdf4, gaussian_box2_cdf4, gaussian_box_cdf_at, gaussian_cdf4

    @kernel
    def lanes(kind, f0, n, c, dt, s, a, b, out):
        inv_s, inv_a = 1.0 / s, 1.0 / a if a > 0 else 0.0
        inv_ab = 1.0 / (a * b) if b > 0 else 0.0
        for j in range(0, n, 4):
            if kind == 0:
                gaussian_cdf4(out, j, f0 + j, c, dt, inv_s)
            elif kind == 1:
                gaussian_box1_cdf4(out, j, f0 + j, c, dt, s, inv_s, a, inv_a)
            else:
                gaussian_box2_cdf4(out, j, f0 + j, c, dt, s, inv_s, a, b, inv_ab)

    @kernel
    def scalar(kind, f0, n, c, dt, s, a, b, out):
        inv_s, inv_a = 1.0 / s, 1.0 / a if a > 0 else 0.0
        inv_ab = 1.0 / (a * b) if b > 0 else 0.0
        for j in range(n):
            t = (f0 + j - c) * dt
            out[j] = gaussian_box_cdf_at(t, s, inv_s, a, inv_a, b, inv_ab, kind)

    rng = np.random.default_rng(7)
    dt = 1e-9
    cases = []
    for _ in range(400):
        s = rng.uniform(0.4, 6.0) * dt
        a = s * np.exp(rng.uniform(np.log(0.3), np.log(60.0)))
        b = rng.uniform(0.3 * s, a)
        c = rng.uniform(10.0, 500.0)
        for kind in (0, 1, 2):
            half = (6.1 * s + 0.5 * ((a if kind else 0.0) + (b if kind == 2 else 0.0))) / dt
            f0 = float(np.floor(c - half))
            cases.append((kind, f0, int(2 * half) + 3, c, s, a if kind else 0.0, b if kind == 2 else 0.0))
    # hard points: an edge on t = 0, on the box ends, at |u|/σ on a table node, at 10 (the table's end) and beyond
    s, a, b = 2.0 * dt, 8.0 * dt, 3.0 * dt
    for c in (100.0, 100.0 - 4.0, 100.0 + 4.0, 100.0 - 1.5, 100.0 - 5.5, 100.0 - 4.0 - 20.0, 100.0 + 4.0 + 20.0,
              100.0 - 4.0 - 2.0 * 10.0 / 2.0, 100.0 + 0.5 + 2.0 * 37 / 128):
        for kind in (0, 1, 2):
            cases.append((kind, 60.0, 84, c, s, a if kind else 0.0, b if kind == 2 else 0.0))
    for kind, f0, n, c, s, a, b in cases:
        got, want = np.full(n + 4, np.nan), np.full(n, np.nan)
        lanes(kind, f0, n, c, dt, s, a, b, got)
        scalar(kind, f0, n, c, dt, s, a, b, want)
        assert np.array_equal(got[:n].view(np.int64), want.view(np.int64)), (kind, f0, n, c, s, a, b)
