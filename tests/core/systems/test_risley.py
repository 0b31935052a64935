"""The Risley-prism pattern (scanner.pattern = "risley"): directions by exact refraction through each prism's two
faces, checked against geometry computed here independently: the closed-form deviation of one prism, the
thin-prism formula with its known error bound, a ray trace written in angle form (tangential component × n1/n2),
and a Livox Mid-40-like two-prism rosette (38.4° circular field of view)."""
import numpy as np
import pytest

from core.config.files import config_from_dict
from core.errors import ConfigError
from core.systems.scan_patterns import pulse_schedule

# Livox Mid-40 prism parameters as HELIOS++ lists them (python/pyhelios/data/scanners_tls.xml, livox_mid-40):
# rotors −121.5657 Hz and 77.7430 Hz (7294 and 4664 rpm), wedges 18.7481° and 17.9634°, n = 1.51.
MID40 = {"risley_prism_hz": [-121.5657, 77.7430], "risley_wedge_deg": [18.7481, 17.9634],
         "risley_index": [1.51, 1.51]}


def _cfg(duration_s=0.01, prf=100_000.0, **scanner):
    s = {"pattern": "risley", "pulse_rate_hz": prf, "duration_s": duration_s}
    s.update(scanner)
    return config_from_dict({"system_type": "scanner", "scanner": s, "run": {"save_waveforms": False}})


def _off_axis_deg(d):
    return np.degrees(np.arccos(np.clip(-d[:, 2], -1, 1)))


@pytest.mark.parametrize("n", [1.45, 1.51, 1.8])
@pytest.mark.parametrize("w_deg", [2.0, 10.0, 20.0])
def test_one_prism_deviation_closed_form(n, w_deg):
    """Normal incidence on the flat face, exit through the inclined face (wedge < 0): sin(δ + w) = n sin w.
    Inclined face first (wedge > 0): sin r = sin w / n, then sin δ = n sin(w − r) at the flat face."""
    w = np.radians(w_deg)
    exit_incl = np.degrees(np.arcsin(n * np.sin(w)) - w)
    r = np.arcsin(np.sin(w) / n)
    entry_incl = np.degrees(np.arcsin(n * np.sin(w - r)))
    for wedge, expected in ((-w_deg, exit_incl), (w_deg, entry_incl)):
        _, d, _, _ = pulse_schedule(_cfg(risley_prism_hz=[50.0], risley_wedge_deg=[wedge], risley_index=[n]),
                                    0, 200)
        np.testing.assert_allclose(_off_axis_deg(d), expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("w_deg", [0.5, 2.0, 5.0])
def test_thin_prism_formula_within_its_error_bound(w_deg):
    """The first-order deviation (n − 1) w differs from the exact one (flat face first) by n(n² − 1) w³ / 6 to
    third order: the simulated deviation lies within 1.2 × that bound of (n − 1) w, and beyond 0.8 × it (the
    pattern is exact, not the small-angle formula)."""
    n, w = 1.51, np.radians(w_deg)
    _, d, _, _ = pulse_schedule(_cfg(risley_prism_hz=[10.0], risley_wedge_deg=[-w_deg], risley_index=[n]), 0, 10)
    delta = np.radians(_off_axis_deg(d))
    bound = n * (n * n - 1) * w ** 3 / 6
    err = delta - (n - 1) * w
    assert np.all(err <= 1.2 * bound) and np.all(err >= 0.8 * bound)


def _trace_angle_form(t, f, wedge_deg, index, incident):
    """An independent trace: at each face, the component of the ray along the face (tangential) scales by
    n1/n2 and the normal component follows from |d| = 1; faces built from rotation matrices."""
    d = np.array(incident, dtype=float)
    for fi, wi, ni in zip(f, wedge_deg, index):
        psi = -2 * np.pi * fi * t
        tilt = np.radians(abs(wi))
        # the inclined face's normal: +Z turned by the tilt about the axis perpendicular to azimuth psi
        rz = np.array([[np.cos(psi), -np.sin(psi), 0], [np.sin(psi), np.cos(psi), 0], [0, 0, 1]])
        ry = np.array([[np.cos(tilt), 0, np.sin(tilt)], [0, 1, 0], [-np.sin(tilt), 0, np.cos(tilt)]])
        incl = rz @ ry @ np.array([0.0, 0.0, 1.0])
        if wi < 0:
            incl = np.array([-incl[0], -incl[1], incl[2]])
        faces = [(incl, 1.0, ni), (np.array([0.0, 0, 1]), ni, 1.0)] if wi > 0 else \
            [(np.array([0.0, 0, 1]), 1.0, ni), (incl, ni, 1.0)]
        for normal, n1, n2 in faces:
            along = np.dot(d, normal) * normal
            tang = (d - along) * (n1 / n2)
            d = tang - normal * np.sqrt(1.0 - np.dot(tang, tang))
    return d


def test_mid40_rosette_point_for_point():
    """1 000 pulses spread over one second of the Mid-40 rosette agree with the angle-form trace within 0.01°
    (and within 1e-9°: the same physics, only rounding differs)."""
    cfg = _cfg(duration_s=1.0, **MID40)
    idx = np.linspace(0, 99_999, 1000).astype(np.int64)
    t, d, _, _ = pulse_schedule(cfg, indices=idx)
    ref = np.array([_trace_angle_form(ti, MID40["risley_prism_hz"], MID40["risley_wedge_deg"],
                                      MID40["risley_index"], [0.0, 0.0, -1.0]) for ti in t])
    err_deg = np.degrees(2 * np.arcsin(0.5 * np.linalg.norm(d - ref, axis=1)))
    assert err_deg.max() < 0.01
    assert err_deg.max() < 1e-9  # the same physics: only rounding differs


def test_mid40_rosette_covers_its_circular_field_of_view():
    """The Mid-40's published field of view is a 38.4° circle: the rosette's largest off-axis angle is within
    0.15° of 19.2° (the prisms aligned: here 19.16°), the smallest near 0 (prisms opposed), and it fills the
    circle: the fraction of 1°×1° cells (projected angles) inside a 36° circle that hold a point grows from 0.1 s
    to 1 s and is ≥ 0.95 after 1 s (measured 0.61 at 0.1 s, 1.00 at 1 s)."""
    t, d, _, _ = pulse_schedule(_cfg(duration_s=1.0, **MID40))
    off = _off_axis_deg(d)
    assert abs(off.max() - 19.2) < 0.15 and off.min() < 0.1
    x = np.degrees(np.arctan2(d[:, 0], -d[:, 2]))
    y = np.degrees(np.arctan2(d[:, 1], -d[:, 2]))
    cells = np.stack(np.meshgrid(np.arange(-18, 18) + 0.5, np.arange(-18, 18) + 0.5), -1).reshape(-1, 2)
    inside = np.hypot(cells[:, 0], cells[:, 1]) < 18.0 - 0.71

    def coverage(n):
        hit = np.zeros((36, 36), bool)
        ix, iy = np.floor(x[:n] + 18).astype(int), np.floor(y[:n] + 18).astype(int)
        ok = (ix >= 0) & (ix < 36) & (iy >= 0) & (iy < 36)
        hit[iy[ok], ix[ok]] = True
        return hit.reshape(-1)[(np.floor(cells[:, 1] + 18) * 36 + np.floor(cells[:, 0] + 18)).astype(int)][
            inside].mean()

    c01, c1 = coverage(10_000), coverage(100_000)
    assert 0.4 < c01 < c1 and c1 >= 0.95, (c01, c1)


def test_emitters_are_channels_fired_together():
    """Six emitters (Avia-like, offsets in β): six pulses per firing time, channel = emitter; with the prisms'
    wedges tiny (1e-3°) each beam leaves within 1e-3° of its own entry direction."""
    emitters = [[0.0, b] for b in (-3.0, -1.9, -0.6, 0.6, 1.9, 3.0)]
    cfg = _cfg(risley_prism_hz=[10.0], risley_wedge_deg=[1e-3], risley_index=[1.5], risley_emitters_deg=emitters)
    t, d, ch, _ = pulse_schedule(cfg, 0, 12)
    assert list(ch) == [0, 1, 2, 3, 4, 5] * 2 and np.all(t[:6] == 0.0)
    beta = np.degrees(np.arcsin(d[:6, 1]))
    np.testing.assert_allclose(beta, [-3.0, -1.9, -0.6, 0.6, 1.9, 3.0], atol=1e-3)


@pytest.mark.parametrize("scanner, match", [
    ({"risley_prism_hz": [1.0], "risley_wedge_deg": [10.0], "risley_index": [1.5, 1.5]},
     r"scanner\.risley_index = '2 values' .*one per prism"),
    ({"risley_prism_hz": [1.0], "risley_wedge_deg": [0.0], "risley_index": [1.5]}, r"risley_wedge_deg\[0\]"),
    ({"risley_prism_hz": [1.0], "risley_wedge_deg": [], "risley_index": []}, r"1 to 8 prisms"),
    ({"risley_prism_hz": [1.0], "risley_wedge_deg": [10.0], "risley_index": [0.5]}, r"risley_index\[0\]"),
    ({"risley_prism_hz": [1.0, -1.3], "risley_wedge_deg": [45.0, 45.0], "risley_index": [2.0, 2.0]},
     r"total internal reflection"),
    ({"risley_prism_hz": [1.0], "risley_wedge_deg": [10.0], "risley_index": [1.5],
      "risley_emitters_deg": [[0.0, 1.0], [0.0]]}, r"risley_emitters_deg row 2"),
])
def test_bad_prisms_are_refused(scanner, match):
    with pytest.raises(ConfigError, match=match):
        _cfg(**scanner)
