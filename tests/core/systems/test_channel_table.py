"""The rotating head's per-channel table (core/config/tables.py, core/systems/scan_patterns.py): elevation,
azimuth offset and fire-time offset per channel, inline or from a CSV file; bad tables named by row and
column."""
import numpy as np
import pytest

from core.config import SimulationConfig
from core.config.files import config_from_dict, dump_config_toml, load_config
from core.errors import ConfigError
from core.systems.scan_patterns import pulse_schedule

TABLE = [[2.0, -1.5, 0.0], [-0.5, 0.0, 2e-6], [-8.25, 3.0, 5e-6]]


def _cfg(**scanner):
    base = {"pattern": "rotating", "n_channels": 3, "pulse_rate_hz": 1000.0, "scan_rate_hz": 10.0,
            "scan_width_rad": 2 * np.pi}
    base.update(scanner)
    return config_from_dict({"system_type": "scanner", "scanner": base, "run": {"save_waveforms": False}})


def test_table_directions_times_and_azimuths_match_the_formula():
    """Channel c of firing k: t = k/PRF + τ_c, α = −W/2 + 2π f t + Δα_c, β = β_c; d = (cos β sin α, sin β,
    −cos β cos α), computed here from the table."""
    cfg = _cfg(channel_table=TABLE)
    t, d, ch, _ = pulse_schedule(cfg, 0, 30)
    k, c = np.arange(30) // 3, np.arange(30) % 3
    tab = np.array(TABLE)
    t_exp = k / 1000.0 + tab[c, 2]
    a = -np.pi + 2 * np.pi * 10.0 * t_exp + np.radians(tab[c, 1])
    b = np.radians(tab[c, 0])
    np.testing.assert_array_equal(ch, c)
    np.testing.assert_allclose(t, t_exp, rtol=0, atol=1e-15)
    np.testing.assert_allclose(d[:, 0], np.cos(b) * np.sin(a), atol=1e-12)
    np.testing.assert_allclose(d[:, 1], np.sin(b), atol=1e-12)
    np.testing.assert_allclose(d[:, 2], -np.cos(b) * np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arcsin(d[:, 1])), tab[c, 0], atol=1e-9)


def test_no_table_keeps_the_evenly_spaced_channels():
    """Without a table the elevations are H/2 … −H/2 evenly, fired together (today's pattern)."""
    cfg = _cfg(scan_height_rad=0.4)
    t, d, ch, _ = pulse_schedule(cfg, 0, 6)
    np.testing.assert_allclose(np.arcsin(d[:3, 1]), [0.2, 0.0, -0.2], atol=1e-12)
    assert t[0] == t[1] == t[2] == 0.0 and t[3] == 1e-3


def test_csv_file_gives_the_same_pattern(tmp_path):
    p = tmp_path / "channels.csv"
    p.write_text("# my sensor\nelevation_deg,azimuth_offset_deg,fire_offset_s\n"
                 + "\n".join(",".join(repr(v) for v in row) for row in TABLE) + "\n")
    a = pulse_schedule(_cfg(channel_table=TABLE), 0, 12)
    b = pulse_schedule(_cfg(channel_table_file=str(p)), 0, 12)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_inline_table_round_trips_through_toml(tmp_path):
    cfg = _cfg(channel_table=TABLE)
    p = tmp_path / "c.toml"
    p.write_text(dump_config_toml(cfg))
    assert load_config(p).scanner.channel_table == TABLE


@pytest.mark.parametrize("text, where", [
    ("1,2,0\n1,x,0\n3,0,0\n", "row 2 column 2 (azimuth_offset_deg)"),
    ("1,2,0\n95,0,0\n3,0,0\n", "row 2 column 1 (elevation_deg)"),
    ("# c\n1,2,0\n1,2\n3,0,0\n", "row 3"),
    ("1,2,0\n1,2,0\n3,0,2.5\n", "row 3 column 3 (fire_offset_s)"),
    ("elev,az,t\n1,2,0\n", "row 1"),
])
def test_bad_csv_names_row_and_column(tmp_path, text, where):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        _cfg(channel_table_file=str(p))
    assert where in str(err.value) and "bad.csv" in str(err.value)
    assert len(str(err.value).splitlines()) == 1


@pytest.mark.parametrize("table, where", [
    ([[1, 2, 0], [1, True, 0], [0, 0, 0]], "scanner.channel_table row 2 column 2"),
    ([[1, 2, 0], [1, 2, 0], [0, 0]], "scanner.channel_table row 3"),
    ([[1, 2, 0], [1, 2, float("nan")], [0, 0, 0]], "scanner.channel_table row 2 column 3"),
])
def test_bad_inline_table_names_row_and_column(table, where):
    with pytest.raises(ConfigError, match=where.replace(".", r"\.")):
        _cfg(channel_table=table)


def test_row_count_must_match_n_channels_and_one_source_only(tmp_path):
    with pytest.raises(ConfigError, match=r"scanner\.n_channels = 4 .*3, the number of rows"):
        _cfg(channel_table=TABLE, n_channels=4)
    p = tmp_path / "c.csv"
    p.write_text("1,2,0\n")
    with pytest.raises(ConfigError, match=r"scanner\.channel_table_file"):
        _cfg(channel_table=TABLE, channel_table_file=str(p))
    with pytest.raises(ConfigError, match=r"an existing CSV file"):
        _cfg(channel_table_file=str(tmp_path / "missing.csv"))


def test_default_config_has_no_table():
    s = SimulationConfig().scanner
    assert s.channel_table == [] and s.channel_table_file == ""


def test_inline_cells_are_numbers_not_text():
    with pytest.raises(ConfigError, match=r"scanner\.channel_table row 1 column 1 \(elevation_deg\)"):
        _cfg(channel_table=[["1.5", 0, 0], [0, 0, 0], [0, 0, 0]])


def test_a_prism_table_kept_by_another_pattern_is_still_checked():
    with pytest.raises(ConfigError, match=r"scanner\.risley_index\[0\]"):
        _cfg(risley_prism_hz=[1.0], risley_wedge_deg=[10.0], risley_index=["glass"])


# --------------------------------------------------------------------------------------------------------------
# Relative pulse energy (4th column)
# --------------------------------------------------------------------------------------------------------------
TABLE4 = [[2.0, -1.5, 0.0, 1.0], [-0.5, 0.0, 2e-6, 0.25], [-8.25, 3.0, 5e-6, 2.0]]


def test_fourth_column_read_inline_and_from_csv(tmp_path):
    from core.config.tables import channel_energy_scale, channel_table_deg

    p = tmp_path / "c4.csv"
    p.write_text("elevation_deg,azimuth_offset_deg,fire_offset_s,relative_pulse_energy\n"
                 + "\n".join(",".join(repr(v) for v in row) for row in TABLE4) + "\n")
    a, b = _cfg(channel_table=TABLE4), _cfg(channel_table_file=str(p))
    np.testing.assert_array_equal(channel_table_deg(a.scanner), np.array(TABLE4))
    np.testing.assert_array_equal(channel_table_deg(b.scanner), np.array(TABLE4))
    np.testing.assert_array_equal(channel_energy_scale(a.scanner), [1.0, 0.25, 2.0])
    t = tmp_path / "c4.toml"  # the fourth column round-trips through a config file
    t.write_text(dump_config_toml(a))
    assert load_config(t).scanner.channel_table == TABLE4
    # the pattern is the 3-column table's
    for x, y in zip(pulse_schedule(a, 0, 12), pulse_schedule(_cfg(channel_table=TABLE), 0, 12)):
        np.testing.assert_array_equal(x, y)
    # all ones, or no column: no scaling
    assert channel_energy_scale(_cfg(channel_table=[r[:3] + [1.0] for r in TABLE4]).scanner) is None
    assert channel_energy_scale(_cfg(channel_table=TABLE).scanner) is None


@pytest.mark.parametrize("table, where", [
    ([[1, 2, 0, 1], [1, 2, 0], [0, 0, 0, 1]], r"row 2 .*4 columns like row 1"),
    ([[1, 2, 0], [1, 2, 0, 1], [0, 0, 0]], r"row 2 .*3 columns like row 1"),
    ([[1, 2, 0, 1], [1, 2, 0, 0.0], [0, 0, 0, 1]], r"row 2 column 4 \(relative_pulse_energy\) = 0\.0.*\[0\.001, 1000\]"),
    ([[1, 2, 0, 1], [1, 2, 0, 1], [0, 0, 0, 2e3]], r"row 3 column 4 \(relative_pulse_energy\)"),
])
def test_bad_fourth_column_names_row_and_column(table, where):
    with pytest.raises(ConfigError, match=where):
        _cfg(channel_table=table)


def _two_channel_run(relative, **atmosphere):
    """Two channels along −Z (same elevation, offset, fire time) at relative energies ``relative`` (None: the
    3-column table), 10 firings while the head turns 6e-5 rad, a 30 % plate at 50 m."""
    from core.config.files import config_from_dict
    from core.run import simulate
    from scenes import plate

    rows = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    if relative is not None:
        rows = [r + [x] for r, x in zip(rows, relative)]
    cfg = config_from_dict({"system_type": "scanner",
                            "scanner": {"pattern": "rotating", "n_channels": 2, "pulse_rate_hz": 1000.0,
                                        "scan_rate_hz": 1e-3, "scan_width_rad": 0.0, "duration_s": 0.01,
                                        "beam_subray_rings": 2, "channel_table": rows,
                                        "intensity_encoding": "reflectivity"},
                            "laser": {"beam_divergence_rad": 1e-5},
                            "gate": {"gate_start_s": 2 * 40.0 / 299792458.0, "n_bins": 200},
                            "atmosphere": atmosphere,
                            "run": {"save_waveforms": bool(atmosphere)}})
    return cfg, simulate(plate(50.0, 5.0), np.eye(4), cfg)


def test_relative_pulse_energy_scales_each_channels_return_by_the_radar_equation():
    """Channel 2 at 0.25 of the energy: its pulses receive 0.25 × E η ρ r_a² / R² (Lambertian, on axis), channel
    1's the full figure, and the calibrated reflectivity of both is the plate's (each channel calibrated at its
    own energy).  With the column all ones the products equal the 3-column table's bit for bit."""
    cfg, res = _two_channel_run([1.0, 0.25])
    rho, eta, r_a = 0.3, cfg.receiver.system_efficiency, cfg.receiver.aperture_diameter_m / 2
    full = cfg.laser.pulse_energy_j * eta * rho * r_a ** 2 / 50.0 ** 2
    e, ch = res.pulses["received_energy_j"], res.pulses["channel"]
    assert len(e) == 20
    np.testing.assert_allclose(e[ch == 0], full, rtol=1e-6)
    np.testing.assert_allclose(e[ch == 1], 0.25 * full, rtol=1e-6)
    pts = res.points
    assert set(pts["channel"].tolist()) == {0, 1}
    np.testing.assert_allclose(pts["intensity"], 30.0, atol=0.5)  # 0–100 diffuse scale
    _, a = _two_channel_run(None)
    _, b = _two_channel_run([1.0, 1.0])
    for key in a.points:
        np.testing.assert_array_equal(a.points[key], b.points[key])
    np.testing.assert_array_equal(a.pulses["received_energy_j"], b.pulses["received_energy_j"])


def test_relative_pulse_energy_scales_the_volume_backscatter_too():
    """In fog the saved waveform of a channel at 0.5 is half the other's, bin by bin (same direction and
    geometry: surface and volume backscatter both scale with the pulse energy)."""
    _, res = _two_channel_run([1.0, 0.5], weather="fog", visibility_m=200.0)
    wf, ch = res.waveforms.astype(np.float64), res.pulses["channel"]
    assert wf[ch == 0].sum() > 0
    vol = wf[ch == 0][:, :100]  # the bins before the plate: volume backscatter only
    assert vol.sum() > 0
    np.testing.assert_allclose(wf[ch == 1], 0.5 * wf[ch == 0], rtol=1e-6, atol=1e-7 * wf.max())
