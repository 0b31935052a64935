"""Time-of-flight scanner (issue 5): scan patterns, beam sub-rays, multi-echo, motion compensation, records."""
import dataclasses

import numpy as np
import pytest

from core.errors import ConfigError
from core.config.settings import SimulationConfig
from core.config.validate import validate
from core.geometry.motion import Trajectory
from core.run import run_simulation, simulate
from core.fileio.run_folder import read_ply, run_summary
from core.systems.scan_patterns import beam_subrays, pulse_schedule
from core.systems.scanner import windowed_echoes
from core.config.derived import n_scan_pulses, scan_duration_s
from core.geometry.scene import SceneGeometry
from scenes import C, plate


def scanner_config(pattern="raster", **scan):
    cfg = SimulationConfig(system_type="scanner")
    cfg.scanner.pattern = pattern
    for k, v in scan.items():
        setattr(cfg.scanner, k, v)
    cfg.laser.beam_divergence_rad = 1e-3
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.gate.gate_start_s = 0.0
    cfg.gate.bin_width_s = 0.25e-9
    cfg.gate.n_bins = 2048  # 0 … 76.8 m
    cfg.run.save_waveforms = False
    cfg.run.threads = 1
    return cfg


def merge(*scenes):
    v, t, m, off = [], [], [], 0
    for s in scenes:
        v.append(s.vertices_m)
        t.append(s.triangles + off)
        m.append(s.material_ids)
        off += len(s.vertices_m)
    return SceneGeometry(np.vstack(v), np.vstack(t), np.concatenate(m))


# --------------------------------------------------------------------------------------------------------------
# Patterns
# --------------------------------------------------------------------------------------------------------------
def test_raster_pattern_lines_times_and_angles():
    cfg = scanner_config("raster", n_lines=5, scan_rate_hz=100.0, pulse_rate_hz=2000.0, scan_width_rad=0.4,
                         scan_height_rad=0.2)
    assert scan_duration_s(cfg) == pytest.approx(0.05)
    assert n_scan_pulses(cfg) == 100  # 5 lines × 20 pulses
    t, d, ch, alpha = pulse_schedule(cfg)
    np.testing.assert_allclose(t, np.arange(100) / 2000.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-14)
    beta = np.arcsin(d[:, 1])
    # first line at the top (+H/2), last at the bottom, 20 pulses each sweeping −W/2 → +W/2 (left to right)
    np.testing.assert_allclose(beta[:20], 0.1, atol=1e-12)
    np.testing.assert_allclose(beta[-20:], -0.1, atol=1e-12)
    np.testing.assert_allclose(alpha[:20], -0.2 + 0.4 * np.arange(20) / 20, atol=1e-12)
    assert np.all(ch == 0)


def test_rotating_head_channels_and_azimuth():
    cfg = scanner_config("rotating", n_channels=4, scan_rate_hz=10.0, pulse_rate_hz=3600.0,
                         scan_width_rad=2 * np.pi, scan_height_rad=0.4)
    assert scan_duration_s(cfg) == pytest.approx(0.1)
    assert n_scan_pulses(cfg) == 360 * 4
    t, d, ch, alpha = pulse_schedule(cfg)
    assert list(ch[:8]) == [0, 1, 2, 3, 0, 1, 2, 3]
    np.testing.assert_allclose(np.arcsin(d[:4, 1]), np.linspace(0.2, -0.2, 4), atol=1e-12)
    # the head turns 1° per firing (10 rev/s at 3600 Hz), all channels of a firing share the time
    az = np.arctan2(d[::4, 0], -d[::4, 2])
    step = np.diff(np.unwrap(az))
    np.testing.assert_allclose(step, np.deg2rad(1.0), atol=1e-12)
    np.testing.assert_allclose(t[::4], np.arange(360) / 3600.0)


def test_palmer_cone_and_oscillating_amplitude():
    cfg = scanner_config("palmer", cone_half_angle_rad=0.3, scan_rate_hz=50.0, pulse_rate_hz=10_000.0)
    _, d, _, _ = pulse_schedule(cfg)
    np.testing.assert_allclose(np.arccos(-d[:, 2]), 0.3, atol=1e-12)  # every beam on the cone about −Z
    assert len(d) == 200
    cfg = scanner_config("oscillating", scan_width_rad=0.5, scan_rate_hz=25.0, pulse_rate_hz=10_000.0)
    _, d, _, alpha = pulse_schedule(cfg)
    assert np.abs(alpha).max() == pytest.approx(0.25, rel=1e-4)
    np.testing.assert_allclose(d[:, 1], 0.0, atol=1e-15)


def test_elliptic_palmer_draws_the_ellipse_on_the_ground():
    """cone_half_angle_y_rad: on the plane z = −H the pulse k (φ = 2π f k/PRF) lands at (H tan a cos φ,
    H tan b sin φ) — the ellipse of semi-axes H tan a, H tan b at its eccentric angle; the off-nadir angle θ
    obeys tan²θ = tan²a cos²φ + tan²b sin²φ, spanning a (X–Z plane) to b (Y–Z plane).  Simulated: the points
    on a plate at 75 m lie on that ellipse."""
    a, b, H = np.radians(20.0), np.radians(14.0), 75.0
    cfg = scanner_config("palmer", cone_half_angle_rad=a, cone_half_angle_y_rad=b, scan_rate_hz=50.0,
                         pulse_rate_hz=10_000.0)
    t, d, _, _ = pulse_schedule(cfg)
    phi = 2 * np.pi * 50.0 * np.arange(200) / 10_000.0
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-15)
    x, y = H * d[:, 0] / -d[:, 2], H * d[:, 1] / -d[:, 2]
    np.testing.assert_allclose(x, H * np.tan(a) * np.cos(phi), rtol=0, atol=1e-12)
    np.testing.assert_allclose(y, H * np.tan(b) * np.sin(phi), rtol=0, atol=1e-12)
    theta = np.arccos(-d[:, 2])
    np.testing.assert_allclose(np.tan(theta) ** 2, np.tan(a) ** 2 * np.cos(phi) ** 2
                               + np.tan(b) ** 2 * np.sin(phi) ** 2, rtol=1e-12)
    assert np.degrees(np.ptp(np.arctan2(d[:, 0], -d[:, 2]))) == pytest.approx(40.0, abs=1e-9)
    assert np.degrees(np.ptp(np.arctan2(d[:, 1], -d[:, 2]))) == pytest.approx(28.0, abs=1e-9)
    # equal half angles: the circular cone (within rounding); 0: the circular cone exactly, as before
    cfg.scanner.cone_half_angle_y_rad = a
    _, d_eq, _, _ = pulse_schedule(cfg)
    cfg.scanner.cone_half_angle_y_rad = 0.0
    _, d_c, _, _ = pulse_schedule(cfg)
    np.testing.assert_allclose(d_eq, d_c, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(d_c[:, 2], -np.cos(a))
    cfg.scanner.cone_half_angle_y_rad = b
    cfg.scanner.beam_subray_rings = 0
    cfg.gate.gate_start_s = 2 * 60.0 / 299792458.0
    cfg.gate.n_bins = int(2 * 30.0 / 299792458.0 / cfg.gate.bin_width_s)  # 60–90 m
    res = simulate(plate(H, 60.0), np.eye(4), cfg)
    p = res.points["position_world"]
    assert len(p) == 200
    u, v = p[:, 0] / -p[:, 2] / np.tan(a), p[:, 1] / -p[:, 2] / np.tan(b)
    np.testing.assert_allclose(u ** 2 + v ** 2, 1.0, atol=1e-6)
    np.testing.assert_allclose(-p[:, 2], H, atol=0.2)  # the plate's plane, within a range bin


@pytest.mark.parametrize("rings", [0, 1, 2, 4])
def test_beam_subrays_carry_equal_shares_of_exact_energy(rings):
    rho, phi, w = beam_subrays(rings, "gaussian")
    m = 1 + 3 * rings * (rings + 1)
    assert len(rho) == len(phi) == len(w) == m
    assert w.sum() == pytest.approx(1.0, abs=1e-15)
    # ring k's rays sit where the Gaussian encloses the middle of that ring's cumulative energy share
    counts = [1] + [6 * k for k in range(1, rings + 1)]
    cum = np.cumsum(counts) / m
    start = 0
    for k, n in enumerate(counts):
        if k > 0:
            enclosed = 1 - np.exp(-2 * rho[start] ** 2)
            assert enclosed == pytest.approx(0.5 * (cum[k - 1] + cum[k]), rel=1e-12)
        start += n
    # azimuths of a ring are evenly spread, so the ring's centroid is on the axis
    x = (rho * np.cos(phi) * w).sum()
    assert abs(x) < 1e-12


# --------------------------------------------------------------------------------------------------------------
# Validation cases of the issue
# --------------------------------------------------------------------------------------------------------------
def test_flat_wall_raster_points_on_the_plane_within_1mm():
    tilt = np.deg2rad(30.0)
    scene = plate(40.0, 30.0, tilt_rad=tilt)
    cfg = scanner_config("raster", n_lines=30, scan_rate_hz=200.0, pulse_rate_hz=8000.0, scan_width_rad=0.5,
                         scan_height_rad=0.4, beam_subray_rings=2)
    res = simulate(scene, np.eye(4), cfg)
    pts = res.points["position_world"]
    assert len(pts) == n_scan_pulses(cfg) == 1200
    normal = np.array([0.0, np.sin(tilt), np.cos(tilt)])
    dist = (pts - np.array([0.0, 0.0, -40.0])) @ normal
    assert np.abs(dist).max() < 1e-3
    assert np.all(res.points["n_echoes"] == 1)


def test_two_planes_half_covering_the_footprint_give_two_echoes():
    # a front plate covers x < 0 of the footprint at 30 m (edge 0.1 mm left of the axis, so that no sub-ray
    # grazes it), a wall 1.5 m behind gets the other half
    front = plate(30.0, 1.0, offset=(-1.0 - 1e-4, 0.0, 0.0))
    back = plate(31.5, 5.0)
    cfg = scanner_config("raster", n_lines=1, scan_rate_hz=1000.0, pulse_rate_hz=1000.0, scan_width_rad=0.0,
                         scan_height_rad=0.0, beam_subray_rings=4)
    cfg.laser.beam_divergence_rad = 4e-3  # 12 cm footprint at 30 m
    res = simulate(merge(front, back), np.eye(4), cfg)
    p = res.points
    assert len(p["range_m"]) == 2
    assert list(p["echo_index"]) == [1, 2] and list(p["n_echoes"]) == [2, 2]
    np.testing.assert_allclose(p["range_m"], [30.0, 31.5], atol=0.005)
    # the echo energies split as the sub-rays do, each scaled by 1/R² (docs/theory.md §10): amplitude ratio within 2 %
    rho, phi, w = beam_subrays(4, "gaussian")
    x_at_front = 30.0 * np.tan(rho * 2e-3) * np.cos(phi)
    on_front = x_at_front < -1e-4
    assert 0 < on_front.sum() < len(w)
    expected = (w[~on_front].sum() / 31.5 ** 2) / (w[on_front].sum() / 30.0 ** 2)
    assert p["intensity"][1] / p["intensity"][0] == pytest.approx(expected, rel=0.02)


def test_moving_sensor_scanning_a_static_wall_is_motion_compensated():
    # the sensor flies along +x at 50 m/s while scanning an oscillating line onto a wall 20 m ahead
    cfg = scanner_config("oscillating", scan_width_rad=0.6, scan_rate_hz=20.0, pulse_rate_hz=20_000.0,
                         duration_s=0.2, beam_subray_rings=1)
    times = np.linspace(0.0, 0.2, 21)
    mats = np.repeat(np.eye(4)[None], len(times), axis=0)
    mats[:, 0, 3] = 50.0 * times
    traj = Trajectory(times, mats)
    scene = plate(20.0, 40.0)
    res = simulate(scene, np.eye(4), cfg, trajectory=traj)
    p = res.points
    pos = p["position_world"]
    np.testing.assert_allclose(pos[:, 2], -20.0, atol=1e-3)  # on the wall, not smeared in depth
    # each point is where the pulse's axis, fired from the pose at its own time, meets the wall
    t_s, d, _, _ = pulse_schedule(cfg, indices=p["pulse_index"])
    expected = np.column_stack([50.0 * t_s, np.zeros_like(t_s), np.zeros_like(t_s)]) + d * (20.0 / -d[:, 2])[:, None]
    np.testing.assert_allclose(pos, expected, atol=1e-3)
    # registered with the start pose instead, the same ranges would be off by up to the 10 m flown
    static = d * p["range_m"][:, None]
    assert np.abs(static[:, 0] - pos[:, 0]).max() > 9.0
    assert "motion" in res.stats["stages_run"]


def test_pulses_are_time_stamped_and_misses_recorded(tmp_path):
    # half of each line looks past the wall's edge: those pulses have no echo but are recorded
    scene = plate(20.0, 2.0, offset=(-2.0, 0.0, 0.0))  # covers x ∈ [−4, 0]
    cfg = scanner_config("raster", n_lines=4, scan_rate_hz=100.0, pulse_rate_hz=4000.0, scan_width_rad=0.3,
                         scan_height_rad=0.05)
    path, res = run_simulation(scene, np.eye(4), cfg, tmp_path / "scan", start_time_s=1000.0)
    pulses = np.load(path / "pulses.npz")
    assert len(pulses["time_s"]) == n_scan_pulses(cfg) == 160
    np.testing.assert_allclose(pulses["gps_time_s"], 1000.0 + np.arange(160) / 4000.0)
    x_axis = pulses["direction_world"][:, 0]
    assert set(pulses["n_echoes"][x_axis > 1e-3]) == {0}
    assert np.all(pulses["n_echoes"][x_axis < -1e-3] == 1)
    assert res.stats["pulses_without_echo"] == int((pulses["n_echoes"] == 0).sum()) > 0
    ply = read_ply(path / "points.ply")
    np.testing.assert_allclose(ply["gps_time_s"], 1000.0 + ply["pulse_index"] / 4000.0)
    assert {"echo_index", "n_echoes", "intensity", "gps_time_s", "channel"} <= set(ply)
    assert not (path / "range.exr").exists()
    from core.fileio.las import read_las
    las = read_las(path / "points.las")["points"]  # GPS time, return number and count carried into LAS 1.4
    np.testing.assert_allclose(np.sort(las["gps_time"]), np.sort(res.points["gps_time_s"]), atol=1e-9)
    assert set(las["return_number"]) == {1} and set(las["number_of_returns"]) == {1}
    summary = run_summary(path, res)
    assert "160 fired" in summary and f"{res.stats['pulses_without_echo']} without an echo" in summary


def test_windowed_waveforms_give_the_full_gate_echoes():
    # vegetation-like: three layers at different depths, partly covering the footprint
    scene = merge(plate(25.0, 0.5, offset=(0.45, 0.0, 0.0)), plate(27.0, 0.5, offset=(-0.45, 0.0, 0.0)),
                  plate(35.0, 10.0))
    cfg = scanner_config("raster", n_lines=6, scan_rate_hz=100.0, pulse_rate_hz=2000.0, scan_width_rad=0.08,
                         scan_height_rad=0.04, beam_subray_rings=3)
    cfg.laser.beam_divergence_rad = 0.02
    cfg.scanner.pulse_model = "subrays"  # the windows against the full gate, one model (the centroid pulse against
    # the sub-ray sum: tests/core/systems/test_scanner_pulse_model.py; here it gives ranges within 0.3 µm)
    a = simulate(scene, np.eye(4), cfg)
    b = simulate(scene, np.eye(4), dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, save_waveforms=True)))
    assert a.stats["n_points"] == b.stats["n_points"] > n_scan_pulses(cfg)  # several echoes per pulse
    np.testing.assert_allclose(a.points["range_m"], b.points["range_m"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.points["intensity"], b.points["intensity"], rtol=1e-6)
    assert b.waveforms.shape == (n_scan_pulses(cfg), cfg.gate.n_bins)
    # the saved waveforms hold the received energy of each pulse (pulse fully inside the gate)
    np.testing.assert_allclose(b.waveforms.sum(axis=1), b.pulses["received_energy_j"], rtol=1e-5)


def test_on_axis_pulse_energy_follows_the_radar_equation():
    cfg = scanner_config("raster", n_lines=1, scan_rate_hz=1000.0, pulse_rate_hz=1000.0, scan_width_rad=0.0,
                         scan_height_rad=0.0, beam_subray_rings=2)
    cfg.laser.beam_divergence_rad = 1e-5
    res = simulate(plate(50.0, 5.0), np.eye(4), cfg)
    rho, eta, r_a = 0.3, cfg.receiver.system_efficiency, cfg.receiver.aperture_diameter_m / 2
    expected = cfg.laser.pulse_energy_j * eta * rho * r_a ** 2 / 50.0 ** 2  # Lambertian, docs/theory.md §10
    assert res.pulses["received_energy_j"][0] == pytest.approx(expected, rel=1e-6)


# --------------------------------------------------------------------------------------------------------------
# Atmosphere, noise, determinism
# --------------------------------------------------------------------------------------------------------------
def turbulent_scan(seed=0, threads=1, chunk=262_144, divergence_rad=1e-5):
    cfg = scanner_config("raster", n_lines=40, scan_rate_hz=100.0, pulse_rate_hz=20_000.0, scan_width_rad=0.2,
                         scan_height_rad=0.2, beam_subray_rings=1)
    cfg.laser.beam_divergence_rad = divergence_rad
    cfg.atmosphere.cn2_m_23 = 1e-14
    cfg.run.seed, cfg.run.threads, cfg.run.chunk_rays = seed, threads, chunk
    cfg.gate.gate_start_s = 2 * 990 / C
    return cfg


@pytest.mark.parametrize("divergence_rad, model", [(1e-5, "point"), (1e-3, "footprint_gamma")])
def test_scan_scintillation_statistics(divergence_rad, model):
    """Per-pulse energy relative to the calm-air energy: unit mean and the variance of the model (8000 pulses:
    the sample variance of a variance-0.1…0.3 law is within ±8 % at > 4σ)."""
    scene = plate(1000.0, 300.0)
    cfg = turbulent_scan(divergence_rad=divergence_rad)
    a = simulate(scene, np.eye(4), cfg)
    meta = a.stats["atmosphere"]["turbulence"]
    scint = meta["scintillation"]
    if model == "point":  # footprint (1 cm) smaller than a cell: the point statistics of the regime
        assert scint["model"] in ("lognormal", "gamma_gamma", "gamma_lognormal")
        assert scint["footprint_m"] < scint["cell_radius_m"]
        target = meta["derived"]["scintillation_index"]
    else:  # footprint (1 m) averages many cells: gamma law of the averaged variance
        assert scint["model"] == model and scint["footprint_m"] > scint["cell_radius_m"]
        target = scint["averaged_scintillation_index"]
        assert target < 0.5 * meta["derived"]["scintillation_index"]
    # the return path through the aperture multiplies an independent unit-mean factor (aperture averaged)
    ret = meta["return_scintillation"]["variance"]
    assert 0 < ret < meta["derived"]["scintillation_index"]
    total = (1 + target) * (1 + ret) - 1
    calm = dataclasses.replace(cfg, atmosphere=dataclasses.replace(cfg.atmosphere, cn2_m_23=0.0))
    ref = simulate(scene, np.eye(4), calm)
    ratio = a.pulses["received_energy_j"] / ref.pulses["received_energy_j"]
    assert ratio.mean() == pytest.approx(1.0, abs=0.03)
    assert ratio.var() == pytest.approx(total, rel=0.08)
    # the outgoing path alone
    one_way = simulate(scene, np.eye(4), dataclasses.replace(
        cfg, atmosphere=dataclasses.replace(cfg.atmosphere, return_scintillation=False)))
    ratio = one_way.pulses["received_energy_j"] / ref.pulses["received_energy_j"]
    assert ratio.var() == pytest.approx(target, rel=0.08)
    assert "return_scintillation" in one_way.stats["stages_skipped"]


def test_scan_turbulence_is_deterministic_per_seed():
    scene = plate(1000.0, 300.0)
    a = simulate(scene, np.eye(4), turbulent_scan())
    b = simulate(scene, np.eye(4), turbulent_scan(threads=2, chunk=8192))
    assert a.stats["n_points"] == 8000
    np.testing.assert_array_equal(a.points["range_m"], b.points["range_m"])
    np.testing.assert_array_equal(a.points["intensity"], b.points["intensity"])
    c = simulate(scene, np.eye(4), turbulent_scan(seed=1))
    assert not np.array_equal(a.points["intensity"], c.points["intensity"])


def test_noisy_scanner_detects_with_snr():
    cfg = scanner_config("raster", n_lines=4, scan_rate_hz=100.0, pulse_rate_hz=4000.0, scan_width_rad=0.1,
                         scan_height_rad=0.05)
    cfg.detector.mode = "noisy"
    cfg.gate.n_bins = 512  # 30 … 49.2 m
    cfg.gate.gate_start_s = 2 * 30.0 / C
    res = simulate(plate(40.0, 10.0), np.eye(4), cfg)
    first = res.points["echo_index"] == 1
    # every pulse sees the wall (strong return), the range noise is small
    assert len(np.unique(res.points["pulse_index"][first])) == n_scan_pulses(cfg)
    near = np.abs(res.points["range_m"] - 40.0 / np.cos(0.05)) < 0.5
    assert near.sum() >= n_scan_pulses(cfg)
    assert np.all(np.isfinite(res.points["snr"])) and res.points["snr"][near].min() > 5
    assert "receiver_chain" in res.stats["stages_run"]
    # detections away from the wall's return are the counted false alarms
    np.testing.assert_array_equal(res.points["false_alarm"].astype(bool), ~near)
    assert res.stats["receiver"]["false_alarms"]["n_false_alarms"] == int((~near).sum())


def test_scanner_settings_are_validated():
    cfg = scanner_config("raster")
    cfg.scanner.pulse_rate_hz = 0.0
    with pytest.raises(ConfigError, match="scanner.pulse_rate_hz"):
        validate(cfg)
    cfg = scanner_config("raster", n_lines=10_000, pulse_rate_hz=1e6, scan_rate_hz=10.0)
    cfg.run.save_waveforms = True
    with pytest.raises(ConfigError, match="run.save_waveforms"):
        validate(cfg)
    with pytest.raises(ConfigError, match="sees nothing"):
        simulate(plate(20.0, 1.0, offset=(0.0, 100.0, 0.0)), np.eye(4),
                 dataclasses.replace(scanner_config("raster"),
                                     atmosphere=dataclasses.replace(SimulationConfig().atmosphere, cn2_m_23=1e-14)))


def test_windowed_echoes_of_nothing_is_empty():
    cfg = scanner_config()
    e = windowed_echoes(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), 5, cfg, "exact")
    assert len(e.pixel) == 0


def test_pulse_table_matches_the_exact_bin_integrals():
    from core.config.settings import LaserSettings, RangeGateSettings
    from core.systems.scanner import PulseTable
    from core.physics.waveform import accumulate_waveforms

    rng = np.random.default_rng(3)
    for fwhm_bins in (0.7, 2.0, 6.0):
        laser = LaserSettings(pulse_fwhm_s=fwhm_bins * 1e-9)
        gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=64)
        pix = np.sort(rng.integers(0, 50, 400))
        u = rng.uniform(10, 50, 400)
        e = rng.uniform(0.5, 2.0, 400)
        exact = accumulate_waveforms(pix, u * 1e-9, e, 50, laser, gate, "exact")
        table = PulseTable(laser, 1e-9).waveforms(pix, u, e, 50, 64)
        # interpolation error ≲ 5e-7/σ² of the peak (σ in bins); energy identical
        assert np.abs(table - exact).max() < 2e-6 * exact.max()
        np.testing.assert_allclose(table.sum(axis=1), exact.sum(axis=1), rtol=1e-9)


# --------------------------------------------------------------------------------------------------------------
# Issue 14: sub-ray rings without a common line through the centre
# --------------------------------------------------------------------------------------------------------------
def _side_fraction(rings, angle_rad, offset):
    """Energy share of the sub-rays on the closed side n·p ≥ −offset of a line through the beam centre at
    ``angle_rad`` (offset in units of the 1/e² half-angle θ)."""
    rho, phi, w = beam_subrays(rings, "gaussian")
    normal = np.array([np.cos(angle_rad + np.pi / 2), np.sin(angle_rad + np.pi / 2)])
    proj = rho * (normal[0] * np.cos(phi) + normal[1] * np.sin(phi))
    return float(w[proj >= -offset].sum())


@pytest.mark.parametrize("rings", [1, 2, 4, 8, 16])
def test_half_plane_through_the_centre_gets_half_the_energy(rings):
    """An edge through (just beside) the beam centre, along the axes, the diagonals or any direction: the rays on
    its side carry the true Gaussian fraction Φ(2δ/θ) to within one ray's share (the old layout put two rays of
    every ring on the x and y axes: 217 rays, 117 on one side, 0.540 instead of 0.5015)."""
    from scipy.special import ndtr

    m = 1 + 3 * rings * (rings + 1)
    axes = [0.0, np.pi / 4, np.pi / 2, 3 * np.pi / 4]
    for angle in axes + list(np.random.default_rng(rings).uniform(0, np.pi, 200)):
        # an edge along the axes or diagonals: the centre ray's half share at most; any other direction: at most
        # the opposite rays of two rings within δ of the edge (16 rings: 408 lines, ≥ 0.09° apart)
        limit = 0.5 / m + 1e-3 if angle in axes else 4.5 / m
        for delta in (0.0019, -0.0019, 0.0):  # δ/θ; the case: Φ(2 × 0.0019) = 0.5015
            true = float(ndtr(2 * delta)) if delta else 0.5
            got = _side_fraction(rings, angle, delta)
            assert abs(got - true) <= limit, (angle, delta, got, true)


@pytest.mark.parametrize("rings", [2, 8, 16])
def test_no_line_through_the_centre_carries_rays_of_two_rings(rings):
    rho, phi, w = beam_subrays(rings, "gaussian")
    counts = [1] + [6 * k for k in range(1, rings + 1)]
    ring = np.repeat(np.arange(rings + 1), counts)
    line = phi[ring > 0] % np.pi
    ring = ring[ring > 0]
    diff = np.abs((line[:, None] - line[None, :] + np.pi / 2) % np.pi - np.pi / 2)
    other = ring[:, None] != ring[None, :]
    assert diff[other].min() > np.radians(0.05)
    axes = np.abs((line[:, None] - np.array([0, np.pi / 4, np.pi / 2, 3 * np.pi / 4])[None, :] + np.pi / 2)
                  % np.pi - np.pi / 2)
    assert axes.min() > np.radians(0.05)
    assert np.array_equal(beam_subrays(2, "gaussian")[1], phi[: 19])  # a ring's offset does not depend on R
    assert w.sum() == pytest.approx(1.0, abs=1e-15) and np.ptp(w) == 0


def test_scanner_pulse_on_a_vertical_edge_through_the_beam_centre():
    """End to end: pulses along −Z onto a plate whose vertical edge passes 0.1 mm beside the beam axis at 50 m
    (beam 1/e² radius 25 mm): received energy / that of a whole plate = Φ(2δ/(θR)) within one ray's share."""
    from scipy.special import ndtr

    cfg = scanner_config("palmer", cone_half_angle_rad=0.0, pulse_rate_hz=1000.0, scan_rate_hz=10.0,
                         duration_s=0.004, beam_subray_rings=8)
    delta = 1e-4
    half = SceneGeometry(np.array([[-delta, -5.0, -50.0], [5.0, -5.0, -50.0], [5.0, 5.0, -50.0],
                                   [-delta, 5.0, -50.0]]), [[0, 1, 2], [0, 2, 3]], [0, 0])
    got = simulate(half, np.eye(4), cfg).stats["received_energy_j"]
    whole = simulate(plate(50.0, 5.0), np.eye(4), cfg).stats["received_energy_j"]
    theta_r = 0.5 * cfg.laser.beam_divergence_rad * 50.0
    assert got / whole == pytest.approx(float(ndtr(2 * delta / theta_r)), abs=1.0 / 217)


@pytest.mark.parametrize("rings", [0, 2])
@pytest.mark.parametrize("moving", [False, True])
def test_subray_directions_follow_the_beam_geometry(rings, moving):
    """The compiled sub-ray directions (scan_patterns.scan_rays): sub-ray j of a beam of centre c is
    cos ρ_j c + sin ρ_j (cos φ_j u + sin φ_j v), u = c × ŷ/|c × ŷ|, v = u × c, turned into the world by the pose:
    within 4e-16 of that formula evaluated here (1e-16 is the rounding of one product), unit length to 1e-15,
    at the angle ρ_j·θ/2·width_scale from the beam axis (its sine to 1e-12)."""
    from scipy.spatial.transform import Rotation

    from core.systems.scan_patterns import scan_rays

    cfg = SimulationConfig(system_type="scanner")
    cfg.scanner.pattern, cfg.scanner.beam_subray_rings = "palmer", rings
    cfg.laser.beam_divergence_rad = 2e-3
    mats = np.repeat(np.eye(4)[None], 3, axis=0)
    angles = [[0, 0, 0], [0.1, 0.2, 0.3], [0.3, -0.2, 1.0]] if moving else [[0.2, 0.1, -0.4]] * 3
    mats[:, :3, :3] = Rotation.from_euler("xyz", angles).as_matrix()
    mats[:, :3, 3] = [[0, 0, 100], [10, 0, 100], [20, 5, 90]]
    traj = Trajectory(np.array([0.0, 0.005, 0.01]), mats)
    cfg.scanner.duration_s = 0.01
    t_s, _, _, origin, axis_world, o_world, d_world = scan_rays(cfg, traj, 0, 2000, width_scale=1.3)
    n = len(t_s)
    rho_unit, phi, weight = beam_subrays(rings)
    m = len(weight)
    c = pulse_schedule(cfg, 0, n)[1]
    u = np.stack([-c[:, 2], np.zeros(n), c[:, 0]], axis=1)
    u /= np.sqrt(u[:, 0] ** 2 + u[:, 2] ** 2)[:, None]
    v = np.cross(u, c)
    rho = rho_unit * 0.5 * cfg.laser.beam_divergence_rad * 1.3
    d = (np.cos(rho)[None, :, None] * c[:, None, :]
         + np.sin(rho)[None, :, None] * (np.cos(phi)[None, :, None] * u[:, None, :]
                                          + np.sin(phi)[None, :, None] * v[:, None, :]))
    rot = traj.poses_at(t_s)[1]
    expect = np.einsum("nij,nmj->nmi", rot, d).reshape(-1, 3)
    assert d_world.shape == (n * m, 3) and o_world.shape == (n * m, 3)
    assert np.max(np.abs(d_world - expect)) <= 4e-16
    assert np.max(np.abs(np.linalg.norm(d_world, axis=1) - 1.0)) <= 1e-15
    sin_off_axis = np.linalg.norm(np.cross(d_world.reshape(n, m, 3), axis_world[:, None, :]), axis=2)
    assert np.max(np.abs(sin_off_axis - np.sin(rho)[None, :])) <= 1e-12
    np.testing.assert_array_equal(o_world, np.repeat(origin, m, axis=0))


# --------------------------------------------------------------------------------------------------------------
# Issue 16: the survey's memory (streamed products, the trace's shared beam origins)
# --------------------------------------------------------------------------------------------------------------
def _soup(rng, n_tri=4000, n_degenerate=40):
    """Random triangles far from the origin (float32 alone would lose millimetres), some degenerate."""
    v = rng.normal(size=(3000, 3)) * 5.0 + np.array([1e4, -2e4, 300.0])
    tris = rng.integers(0, 3000, size=(n_tri, 3))
    tris[:n_degenerate, 2] = tris[:n_degenerate, 1]
    return SceneGeometry(v, tris, np.zeros(n_tri, int))


def test_trace_planes_and_ranges_are_the_numpy_formulas_bit_for_bit():
    """The tracer's plane table (computed by a kernel, without whole-scene temporaries) is NumPy's
    cross / linalg.norm bit for bit; each hit's range is ((v₀ − o)·n)/(d·n) and cos θ = |d·n| (einsum's
    summation order) bit for bit; hits on degenerate triangles are misses; with the BVH on a subset (culling)
    the hits are the same, with the scene's triangle numbers."""
    from core.geometry.trace import SceneTracer

    rng = np.random.default_rng(7)
    scene = _soup(rng)
    tri = scene.vertices_m[scene.triangles]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normal, axis=1)
    unit = normal / np.where(norm == 0.0, 1.0, norm)[:, None]
    tracer = SceneTracer(scene)
    assert np.array_equal(tracer.unit_normal, unit) and np.array_equal(tracer.degenerate, norm == 0.0)
    origin = scene.vertices_m.mean(axis=0) + rng.normal(size=(50_000, 3)) * 8.0
    d = rng.normal(size=(50_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    prim, range_m, cos_theta = tracer.intersect(origin, d)
    hit = prim >= 0
    assert hit.sum() > 5000 and not tracer.degenerate[prim[hit]].any()
    n_hit = unit[prim[hit]]
    dn = np.einsum("ij,ij->i", d[hit], n_hit)
    wn = np.einsum("ij,ij->i", tri[prim[hit], 0] - origin[hit], n_hit)
    assert np.array_equal(range_m[hit], wn / dn) and np.array_equal(cos_theta[hit], np.abs(dn))
    assert np.isnan(range_m[~hit]).all() and (cos_theta[~hit] == 0).all()
    keep = rng.random(scene.n_triangles) < 0.5
    keep[np.unique(prim[hit])] = True
    culled = SceneTracer(scene, keep=keep).intersect(origin, d)
    for got, want in zip(culled, (prim, range_m, cos_theta)):
        assert np.array_equal(got, want, equal_nan=True)


def test_trace_shares_one_origin_among_a_group_of_rays():
    """One origin per group of k consecutive rays (a beam's sub-rays) traces exactly as the origin repeated
    per ray; one origin for all rays as well; an origin count that divides no group is refused."""
    from core.geometry.trace import SceneTracer

    rng = np.random.default_rng(8)
    scene = _soup(rng)
    tracer = SceneTracer(scene)
    origin = scene.vertices_m.mean(axis=0) + rng.normal(size=(2000, 3)) * 8.0
    d = rng.normal(size=(2000 * 7, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    grouped = tracer.intersect(origin, d)
    per_ray = tracer.intersect(np.repeat(origin, 7, axis=0), d)
    assert (grouped[0] >= 0).sum() > 1000
    for got, want in zip(grouped, per_ray):
        assert np.array_equal(got, want, equal_nan=True)
    for got, want in zip(tracer.intersect(origin[0], d), tracer.intersect(np.repeat(origin[:1], len(d), 0), d)):
        assert np.array_equal(got, want, equal_nan=True)
    with pytest.raises(ValueError, match="3 ray origins for 14000 rays"):
        tracer.intersect(origin[:3], d)
    for origins in (origin[:0], origin[0]):  # no rays (e.g. no active ray left): empty results
        prim, range_m, cos_theta = tracer.intersect(origins, d[:0])
        assert prim.shape == range_m.shape == cos_theta.shape == (0,)


def test_scan_products_are_streamed_and_the_same_for_any_threads_and_blocks():
    """The blocks write the pulse records in place and build their own points: the products are the same bit
    for bit for 1 or 2 threads and any block size, and every product array owns exactly its data (no view
    keeping a larger buffer alive: the echo arrays of each block used to hold n_hits × max_echoes slots until the
    end of the scan)."""
    cfg = scanner_config("oscillating", pulse_rate_hz=200e3, scan_rate_hz=100.0, scan_width_rad=0.6,
                         duration_s=0.05, beam_subray_rings=2)
    cfg.laser.beam_divergence_rad = 5e-3
    cfg.gate.gate_start_s = 2 * 20.0 / C
    cfg.gate.n_bins = 1024
    mats = np.repeat(np.eye(4)[None], 2, axis=0)
    mats[:, :3, 3] = [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    traj = Trajectory(np.array([0.0, 0.05]), mats)
    scene = merge(plate(40.0, 30.0), plate(30.0, 4.0, offset=(2.0, 0.0, 0.0)))
    runs = []
    for threads, chunk in ((1, 262_144), (2, 4096 * 19), (2, 8192 * 19)):
        cfg.run.threads, cfg.run.chunk_rays = threads, chunk
        runs.append(simulate(scene, np.eye(4), cfg, trajectory=traj))
    ref = runs[0]
    assert [r.stats["n_blocks"] for r in runs] == [1, 3, 2]
    assert ref.stats["n_points"] > ref.stats["n_pulses"]  # the small plate gives second echoes
    for res in runs:
        for group, ref_group in ((res.points, ref.points), (res.pulses, ref.pulses)):
            assert list(group) == list(ref_group)
            for name, arr in group.items():
                assert arr.dtype == ref_group[name].dtype and np.array_equal(arr, ref_group[name]), name
                assert arr.base is None or arr.base.nbytes == arr.nbytes, name
    # the tabulated pulse's echoes of one block own exactly their data
    from core.physics.waveform import PulseTable

    rng = np.random.default_rng(4)
    pulse = np.sort(rng.integers(0, 500, 9500))
    ech = windowed_echoes(pulse, cfg.gate.gate_start_s + rng.uniform(0, 200e-9, 9500), np.ones(9500), 500, cfg,
                          "exact", PulseTable(cfg.laser, cfg.gate.bin_width_s))
    assert 500 <= len(ech.pixel) <= 500 * cfg.detection.max_echoes
    for name in ("pixel", "position_bins", "amplitude", "echo_index", "n_echoes"):
        assert getattr(ech, name).base is None, name


def test_point_sink_appends_blocks_as_their_concatenation():
    """The scan's points are appended block by block into whole-scan arrays (scanner._PointSink): the same arrays
    as the blocks' concatenation, bit for bit, in the products' types; grown when the blocks bring more points
    than the planned capacity; a field some block lacks is left out (as the concatenation of the fields every
    block has); the result owns exactly its data."""
    from core.systems.scanner import _PointSink

    rng = np.random.default_rng(7)
    parts = []
    for k in (5, 0, 17, 3, 11):
        parts.append({"range_m": rng.uniform(0, 100, k), "position_world": rng.normal(size=(k, 3)),
                      "echo_index": rng.integers(1, 4, k).astype(np.int16),
                      "intensity": rng.uniform(0, 1, k).astype(np.float32), "snr": rng.uniform(0, 9, k)})
    del parts[3]["snr"]
    expect = {name: np.concatenate([p[name] for p in parts]) for name in parts[0] if name != "snr"}
    sink = _PointSink(8)  # fewer than the 36 points: grows twice
    for p in parts:
        sink.append(dict(p))
    out = sink.arrays()
    assert list(out) == list(expect)
    for name, arr in out.items():
        assert arr.dtype == expect[name].dtype and arr.shape == expect[name].shape, name
        assert np.array_equal(arr, expect[name]), name
        assert arr.base is None and arr.nbytes == expect[name].nbytes, name
    assert _PointSink(4).arrays() == {}


def _table_echoes_reference(table, pulse, u, energy, n_bins, det):
    """The tabulated echoes as every return added by ``table_add_return`` (clipped to the window) and detected by
    ``detect_row``: the definition the compiled pass must match bit for bit."""
    from core.physics.detection.peaks import INTERPOLATION, detect_row
    from core.physics.waveform import table_add_return

    cap = len(u) * det.max_echoes
    out = [np.empty(cap, np.int64), np.empty(cap), np.empty(cap), np.empty(cap, np.int16), np.empty(cap, np.int16)]
    cand, k_out = np.empty(n_bins, np.int64), 0
    for p in np.unique(pulse):
        rows = [r for r in np.flatnonzero(pulse == p)
                if energy[r] > 0 and u[r] + table.half >= 0 and u[r] - table.half < n_bins]
        if not rows:
            continue
        lo = min(max(int(np.floor(u[r])) - table.k, 0) for r in rows)
        hi = max(min(int(np.floor(u[r])) + table.k, n_bins - 1) for r in rows)
        buf = np.zeros(hi - lo + 1)
        for r in rows:
            table_add_return(buf, lo, len(buf), u[r], energy[r], table.rows, table.k)
        k_out = detect_row(buf, 0, len(buf), lo, float(det.threshold_j), float(det.relative_threshold),
                           float(det.min_dip), int(det.max_echoes), INTERPOLATION[det.interpolation], cand, out[0],
                           int(p), out[1], out[2], out[3], out[4], k_out)
    return [a[:k_out] for a in out]


def test_tabulated_echoes_are_the_per_return_sums_bit_for_bit():
    """PulseTable.echoes adds a return whose support lies inside its pulse's window over the zero-padded table
    (a fixed-width loop): the same waveform sums, hence echoes, bit for bit as every return added clipped
    (``table_add_return``) — for pulses whose sub-rays land close together (the whole-support path), spread
    over many bins (partly clipped), cut by either end of the gate, with zero, NaN and infinite energies."""
    from core.config.settings import DetectionSettings, LaserSettings
    from core.physics.waveform import PulseTable

    rng = np.random.default_rng(11)
    table = PulseTable(LaserSettings(pulse_fwhm_s=4e-9), 0.25e-9)
    assert table.wide.shape[1] % 8 == 0 and table.wide.shape[1] >= table.rows.shape[1]
    n_bins, n_pulses = 300, 400
    centre = rng.uniform(-30, 330, n_pulses)  # some pulses cut by the gate's start or end
    spread = np.where(rng.uniform(size=n_pulses) < 0.7, 1.5, 60.0)  # close together, or several echoes
    pulse = np.sort(rng.integers(0, n_pulses, 19 * n_pulses))
    u = centre[pulse] + rng.uniform(-1, 1, len(pulse)) * spread[pulse]
    energy = rng.uniform(0.1, 2.0, len(pulse)) * 1e-12
    energy[rng.choice(len(pulse), 40, replace=False)] = 0.0
    energy[rng.choice(len(pulse), 3, replace=False)] = np.nan
    for det in (DetectionSettings(), DetectionSettings(interpolation="parabolic", max_echoes=5, min_dip=0.0)):
        got = table.echoes(pulse, u, energy, n_pulses, n_bins, det)
        ref = _table_echoes_reference(table, pulse, u, energy, n_bins, det)
        assert len(ref[0]) > n_pulses  # several echoes in the spread pulses
        for name, r in zip(("pixel", "position_bins", "amplitude", "echo_index", "n_echoes"), ref):
            g = getattr(got, name)
            assert g.dtype == r.dtype and np.array_equal(g.view(np.uint8), r.view(np.uint8)), name
    # an infinite energy: its pulse's peak is infinite, not NaN (the padded columns are not added)
    inf_e = energy.copy()
    inf_e[np.flatnonzero(np.abs(u - 150) < 100)[0]] = np.inf
    got = table.echoes(pulse, u, inf_e, n_pulses, n_bins, DetectionSettings())
    ref = _table_echoes_reference(table, pulse, u, inf_e, n_bins, DetectionSettings())
    assert np.array_equal(got.amplitude, ref[2]) and np.array_equal(got.position_bins, ref[1], equal_nan=True)
