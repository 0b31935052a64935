"""``scanner.pulse_model``: the centroid pulse (the default) against the sub-ray sum (the reference) on whole scans —
an airborne survey over the HELIOS++ benchmark's terrain, and a canopy over a ground with a wall's edge (multi-echo
pulses) — within the bounds core/physics/pulse_table.py derives; the metadata names the model that ran."""
import dataclasses

import numpy as np
import pytest

from core.config.settings import BRDFSettings, SimulationConfig
from core.geometry.motion import Trajectory
from core.geometry.scene import SceneGeometry
from core.physics.pulse_table import CENTROID_BIN_TOLERANCE
from core.systems.scanner import simulate_scan

C = 299_792_458.0


def terrain(n=101):
    """The HELIOS++ benchmark's terrain (bench/bench_helios_survey.py), z = sin x · cos y over ±50 m, coarser."""
    x = np.linspace(-50.0, 50.0, n)
    gx, gy = np.meshgrid(x, x)
    verts = np.stack([gx.ravel(), gy.ravel(), (np.sin(gx) * np.cos(gy)).ravel()], axis=1)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    return SceneGeometry(verts, tris, np.zeros(len(tris), int), [BRDFSettings(reflectance=0.3)], ["terrain"])


def survey_config(duration_s=0.02):
    """bench_helios_survey.py's survey (oscillating ±20°, 500 kHz, 19 sub-rays, 4 ns pulse, 0.25 ns bins)."""
    cfg = SimulationConfig(system_type="scanner")
    s = cfg.scanner
    s.pattern, s.pulse_rate_hz, s.scan_rate_hz = "oscillating", 500e3, 100.0
    s.scan_width_rad, s.duration_s, s.beam_subray_rings = np.deg2rad(40.0), duration_s, 2
    cfg.laser.beam_divergence_rad, cfg.laser.pulse_fwhm_s, cfg.laser.wavelength_m = 0.5e-3, 4e-9, 1.064e-6
    cfg.laser.divergence_fills_fov = False
    cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2 * 95.0 / C, 0.25e-9, 640
    cfg.run.save_waveforms = False
    cfg.run.threads = 1
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    mats = np.repeat(np.eye(4)[None], 2, axis=0)
    mats[:, :3, :3] = rot
    x0 = -0.5 * 30.0 * duration_s
    mats[:, :3, 3] = [[x0, 0.0, 100.7], [-x0, 0.0, 100.7]]
    return cfg, Trajectory(np.array([0.0, duration_s]), mats)


def both(scene, cfg, traj=None, pose=np.eye(4)):
    out = {}
    for model in ("subrays", "centroid"):
        c = dataclasses.replace(cfg, scanner=dataclasses.replace(cfg.scanner, pulse_model=model))
        out[model] = simulate_scan(scene, pose, c, trajectory=traj)
    return out["subrays"], out["centroid"]


def range_bound_m(cfg):
    """3 ε σ'² bins in metres (core/physics/pulse_table.py): σ'² = σ² + 1/12, σ the pulse's in bins."""
    sigma_bins = cfg.laser.pulse_fwhm_s / (2 * np.sqrt(2 * np.log(2))) / cfg.gate.bin_width_s
    return 3 * CENTROID_BIN_TOLERANCE * (sigma_bins ** 2 + 1 / 12) * cfg.gate.bin_width_s * C / 2


def assert_within_bounds(ref, got, cfg, min_centroid_share):
    """Same pulses and echo counts; ranges within the bound; intensities within 3 ε, but for the detector's own
    flat tops (tests/core/physics/test_pulse_table.py); the metadata names the model and its share."""
    rec = got.stats["pulse_model"]
    assert rec["model"] == "centroid" and ref.stats["pulse_model"]["model"] == "subrays"
    assert rec["pulses_centroid"] >= min_centroid_share * ref.stats["n_pulses"], rec
    assert rec["largest_bound"] <= CENTROID_BIN_TOLERANCE
    np.testing.assert_array_equal(got.pulses["n_echoes"], ref.pulses["n_echoes"])
    for f in ("pulse_index", "echo_index", "n_echoes"):
        np.testing.assert_array_equal(got.points[f], ref.points[f])
    bound = range_bound_m(cfg)
    assert bound < (C * cfg.laser.pulse_fwhm_s / 2) / 1000  # 1/1000 of the pulse's range resolution
    dr = np.abs(got.points["range_m"] - ref.points["range_m"])
    assert dr.max() <= bound, (dr.max(), bound)
    rel = np.abs(got.points["intensity"].astype(float) / ref.points["intensity"] - 1)
    flat = rel > 3 * CENTROID_BIN_TOLERANCE
    sigma2 = (cfg.laser.pulse_fwhm_s / 2.3548 / cfg.gate.bin_width_s) ** 2 + 1 / 12
    assert flat.sum() <= max(2, 1e-3 * len(rel)) and (rel[flat] <= 1.01 * np.expm1(1 / (8 * sigma2))).all()
    return dr, rel


def test_survey_over_the_benchmark_terrain_within_the_bounds():
    """10 000 pulses of the HELIOS++ survey over its terrain (coarser): the points of both models agree within the
    bounds; most pulses (sub-rays within ~1 bin of each other) take the centroid route."""
    cfg, traj = survey_config()
    ref, got = both(terrain(), cfg, traj)
    assert ref.stats["n_points"] == got.stats["n_points"] > 9000
    dr, _ = assert_within_bounds(ref, got, cfg, 0.8)
    assert dr.max() < 0.1 * range_bound_m(cfg)  # (measured: µm; the bound is the worst case)


def canopy_scene(rng):
    """Leaves (random 0.25 m squares at 28–34 m, a third of the area) above a ground at 40 m, and a wall's edge
    (a plate at 36 m over half of the view): many pulses see two or three surfaces."""
    verts, tris = [], []

    def quad(cx, cy, z, hx, hy):
        k = len(verts)
        verts.extend([[cx - hx, cy - hy, -z], [cx + hx, cy - hy, -z], [cx + hx, cy + hy, -z], [cx - hx, cy + hy, -z]])
        tris.extend([[k, k + 1, k + 2], [k, k + 2, k + 3]])

    quad(0.0, 0.0, 40.0, 20.0, 20.0)       # ground
    quad(-4.5, 0.0, 36.0, 4.5, 6.0)        # wall (its edge at x = 0)
    for _ in range(500):
        quad(rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(28, 34), 0.125, 0.125)
    return SceneGeometry(np.array(verts), np.array(tris), np.zeros(len(tris), int), [BRDFSettings(reflectance=0.4)],
                         ["surface"])


def test_canopy_and_edge_multi_echo_pulses_within_the_bounds():
    """A raster over leaves, a wall's edge and the ground, 4 ns pulse in 0.25 ns bins, 19 sub-rays of a 20 mrad
    beam (0.6–0.8 m footprints: several surfaces a pulse): the same echo counts pulse by pulse (many pulses with
    2–3 echoes), the multi-echo pulses summed sub-ray by sub-ray (bit for bit), the rest within the bounds."""
    cfg = SimulationConfig(system_type="scanner")
    s = cfg.scanner
    s.pattern, s.n_lines, s.scan_rate_hz, s.pulse_rate_hz = "raster", 40, 100.0, 4000.0
    s.scan_width_rad = s.scan_height_rad = 0.25
    s.beam_subray_rings = 2
    cfg.laser.beam_divergence_rad, cfg.laser.pulse_fwhm_s = 20e-3, 4e-9
    cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2 * 20.0 / C, 0.25e-9, 1024
    cfg.detection.max_echoes = 4
    cfg.run.save_waveforms, cfg.run.threads = False, 1
    ref, got = both(canopy_scene(np.random.default_rng(3)), cfg)
    ne = ref.pulses["n_echoes"]
    assert (ne >= 2).sum() >= 1000 and (ne == 1).sum() >= 100, np.bincount(ne)  # (measured 187 / 1413)
    assert_within_bounds(ref, got, cfg, 0.04)  # (measured: 83 of the 187 single-echo pulses)
    multi = ref.points["n_echoes"] >= 2
    for f in ("range_m", "intensity"):
        np.testing.assert_array_equal(got.points[f][multi], ref.points[f][multi])


@pytest.mark.parametrize("case, why", [("save", "saves the waveforms"), ("noisy", "has the noisy receiver"),
                                       ("fog", "has weather")])
def test_routes_the_centroid_does_not_cover_run_the_sum_and_say_so(case, why):
    """Saved waveforms, the noisy receiver, weather: the sub-ray sum, bit for bit, and the metadata says why."""
    cfg, traj = survey_config(0.004)
    if case == "save":
        cfg.run.save_waveforms = True
    elif case == "noisy":
        cfg.detector.mode = "noisy"
    else:
        cfg.atmosphere.weather, cfg.atmosphere.visibility_m = "fog", 200.0
    ref, got = both(terrain(41), cfg, traj)
    rec = got.stats["pulse_model"]
    assert rec["model"] == "subrays" and rec["requested"] == "centroid" and why in rec["note"], rec
    assert ref.stats["n_points"] > 1000
    for f in ref.points:
        np.testing.assert_array_equal(got.points[f], ref.points[f])
    if case == "save":
        np.testing.assert_array_equal(got.waveforms, ref.waveforms)
