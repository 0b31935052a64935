"""The scanner's output (core/systems/returns.py): return modes strongest / last / dual / first-N, the range
quantum and the intensity encodings (calibrated reflectivity, 8-bit intensity), checked with numbers."""
import numpy as np
import pytest

from core.config.settings import BRDFSettings, SimulationConfig
from core.config.validate import validate
from core.errors import ConfigError
from core.geometry.scene import SceneGeometry
from core.run import simulate
from core.systems.returns import select_returns
from scenes import plate


def merge(*scenes):
    v, t, m, mats, names, off = [], [], [], [], [], 0
    for s in scenes:
        v.append(s.vertices_m)
        t.append(s.triangles + off)
        m.append(s.material_ids + len(mats))
        mats += list(s.materials)
        names += [f"m{len(names)}"]
        off += len(s.vertices_m)
    return SceneGeometry(np.vstack(v), np.vstack(t), np.concatenate(m), mats, names)


def _cfg(**scanner):
    cfg = SimulationConfig(system_type="scanner")
    s = cfg.scanner
    s.pattern, s.n_lines, s.scan_rate_hz, s.pulse_rate_hz = "raster", 1, 1000.0, 1000.0
    s.scan_width_rad = s.scan_height_rad = 0.0
    s.beam_subray_rings = 4
    for k, v in scanner.items():
        setattr(s, k, v)
    cfg.laser.beam_divergence_rad = 4e-3
    cfg.laser.pulse_fwhm_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 2e-9, 0.25e-9, 2048
    cfg.run.save_waveforms, cfg.run.threads = False, 1
    validate(cfg)
    return cfg


def two_echo_scene(front_reflectance=0.1, back_reflectance=0.9):
    """A front plate covering x < 0 of the footprint at 30 m (weak), a wall 1.5 m behind (strong)."""
    front = plate(30.0, 1.0, BRDFSettings(reflectance=front_reflectance), offset=(-1.0 - 1e-4, 0.0, 0.0))
    back = plate(31.5, 5.0, BRDFSettings(reflectance=back_reflectance))
    return merge(front, back)


@pytest.mark.parametrize("front, back, strongest_m", [(0.1, 0.9, 31.5), (0.9, 0.1, 30.0)])
def test_two_echo_pulse_in_every_mode(front, back, strongest_m):
    """A 2-echo pulse: all → both; strongest → the stronger; last → the farther (31.5 m); dual → both (the
    strongest is the last in the first case: then the second strongest joins it); first_n with n = 1 → the
    nearer."""
    scene = two_echo_scene(front, back)
    ranges = {}
    for mode in ("all", "strongest", "last", "dual", "first_n"):
        p = simulate(scene, np.eye(4), _cfg(return_mode=mode, n_returns=1)).points
        ranges[mode] = np.round(p["range_m"], 2).tolist()
        assert np.all(p["n_echoes"] == 2)  # the pulse's detected echoes, whatever is reported
    assert ranges["all"] == [30.0, 31.5]
    assert ranges["strongest"] == [strongest_m]
    assert ranges["last"] == [31.5]
    assert ranges["dual"] == [30.0, 31.5]
    assert ranges["first_n"] == [30.0]


def test_select_returns_by_numbers():
    """Pixel 0: amplitudes 1, 5, 2 → strongest #1, last #2, dual {1, 2}; pixel 1: 4, 9 (strongest is last) →
    dual {0, 1}; pixel 2: one echo → every mode keeps it (dual once)."""
    pixel = np.array([0, 0, 0, 1, 1, 2])
    amp = np.array([1.0, 5.0, 2.0, 4.0, 9.0, 3.0])
    idx = np.array([0, 1, 2, 0, 1, 0])
    n = np.array([3, 3, 3, 2, 2, 1])
    sel = {m: np.flatnonzero(select_returns(pixel, amp, idx, n, m, 2)).tolist()
           for m in ("all", "strongest", "last", "dual", "first_n")}
    assert sel == {"all": [0, 1, 2, 3, 4, 5], "strongest": [1, 4, 5], "last": [2, 4, 5], "dual": [1, 2, 3, 4, 5],
                   "first_n": [0, 1, 3, 4, 5]}


def test_range_quantum_error_at_most_half_a_quantum():
    """Ranges rounded to q = 4 mm: every reported range a multiple of q, within q/2 of the unrounded one, and
    the point on the beam axis at that range."""
    wall = plate(20.0, 10.0, tilt_rad=np.radians(40))
    cfg = _cfg(pattern="oscillating", scan_width_rad=0.6, scan_rate_hz=10.0, pulse_rate_hz=5000.0)
    free = simulate(wall, np.eye(4), cfg).points
    cfg.scanner.range_quantum_m = 0.004
    q = simulate(wall, np.eye(4), cfg).points
    assert len(q["range_m"]) == len(free["range_m"]) > 400
    k = q["range_m"] / 0.004
    np.testing.assert_allclose(k, np.round(k), rtol=0, atol=1e-6)
    err = np.abs(q["range_m"] - free["range_m"])
    assert err.max() <= 0.002 + 1e-12 and err.max() > 0.0015  # the bound, and nearly reached over 500 ranges
    np.testing.assert_allclose(np.linalg.norm(q["position_world"], axis=1), q["range_m"], rtol=1e-12)


@pytest.mark.parametrize("reflectance", [0.1, 0.35, 0.8])
def test_calibrated_reflectivity_of_lambertian_panels(reflectance):
    """A Lambertian panel of reflectance ρ filling the beam, normal to it, at 25 m and 60 m: the calibrated
    reflectivity reads round(100 ρ) ± 2 (the echo's sub-bin position changes its sampled peak by < 2 %), and the
    8-bit intensity round(255 ρ) ± 5."""
    for r in (25.0, 60.0):
        panel = plate(r, 5.0, BRDFSettings(reflectance=reflectance))
        cfg = _cfg(beam_subray_rings=2, intensity_encoding="reflectivity")
        cfg.laser.beam_divergence_rad = 1e-4
        p = simulate(panel, np.eye(4), cfg)
        assert abs(p.points["intensity"][0] - 100 * reflectance) <= 2
        assert "reflectivity" in p.units["intensity"]
        cfg.scanner.intensity_encoding = "intensity8"
        p = simulate(panel, np.eye(4), cfg)
        assert abs(p.points["intensity"][0] - 255 * reflectance) <= 5


def test_retro_reflector_encodes_above_100():
    """A specular (Steinvall) panel returning ~30× a white Lambertian one: 101 + 154·log10(gain)/3 within 3
    codes; the gain computed here from the BRDF at normal incidence, f_r = A + B vs 1/π."""
    brdf = BRDFSettings(model="steinvall", specular_a=9.0, slope_s=0.2, diffuse_b=0.3, diffuse_m=1.0)
    panel = plate(30.0, 5.0, brdf)
    cfg = _cfg(beam_subray_rings=0, intensity_encoding="reflectivity")
    cfg.laser.beam_divergence_rad = 1e-5
    code = simulate(panel, np.eye(4), cfg).points["intensity"][0]
    gain = (9.0 + 0.3) * np.pi
    assert abs(code - (101 + 154 * np.log10(gain) / 3)) <= 3


def test_encoding_needs_the_ideal_detector():
    cfg = _cfg()
    cfg.scanner.intensity_encoding = "reflectivity"
    cfg.detector.mode = "noisy"
    with pytest.raises(ConfigError, match=r"scanner\.intensity_encoding"):
        validate(cfg)
