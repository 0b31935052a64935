"""Range-layered aerosol (atmosphere.aerosol_layers, issue 30): the optical depth τ(R) = σ₀R + Σ α_i L_i(R) along
every ray, the two-way transmission exp(−2τ) of surfaces (flash, scanner, gated), drops and the volume
backscatter, the layers' β in the backscatter, against closed forms; the validation of the table; the homogeneous
case unchanged (core/atmosphere/extinction.py LayeredExtinction, docs/theory.md §14 "Layers")."""
import dataclasses
import math

import numpy as np
import pytest
from scipy import integrate

from core.atmosphere.extinction import LayeredExtinction, log_two_way_transmission, two_way_transmission
from core.atmosphere.weather import Drops, Overlap, drop_returns, layer_backscatter, layers_closed_form_integral
from core.config.settings import LaserSettings, RangeGateSettings, SimulationConfig
from core.config.validate import validate_config
from core.errors import ConfigError
from core.physics.laser import pulse_cdf
from core.physics.weather_waveform import backscatter_template
from core.systems.flash import plan, simulate_frame
from scenes import C, config_for, gated_fog_pixel, plate

C2 = 0.5 * C
#: two layers: [start_m, end_m, α (1/m), β (1/(m sr))]
TWO = [[10.0, 30.0, 0.02, 0.02 / 18.0], [40.0, 70.0, 0.05, 0.05 / 18.0]]


def _layered(base, rows):
    t = np.asarray(rows, np.float64)
    return LayeredExtinction(base, tuple(t[:, 0]), tuple(t[:, 1]), tuple(t[:, 2]))


def test_optical_depth_is_the_piecewise_integral_of_alpha():
    """τ(R) = σ₀R + Σ α_i clip(R − s_i, 0, e_i − s_i) at worked ranges (1e-15); ln T² = −2τ; a float extinction
    gives −2σR exactly as before; one layer from 0 to beyond every range is the homogeneous α bit for bit."""
    ext = _layered(1e-3, TWO)
    r = np.array([0.0, 5.0, 10.0, 20.0, 30.0, 35.0, 40.0, 55.0, 70.0, 100.0])
    want = 1e-3 * r + np.array([0, 0, 0, 0.2, 0.4, 0.4, 0.4, 0.4 + 0.75, 0.4 + 1.5, 0.4 + 1.5])
    assert np.allclose(ext.optical_depth(r), want, rtol=1e-15, atol=1e-15)
    assert np.array_equal(log_two_way_transmission(ext, r), -2.0 * ext.optical_depth(r))
    assert np.array_equal(log_two_way_transmission(0.02, r), -2.0 * 0.02 * r)
    whole = _layered(0.0, [[0.0, 1e6, 0.02, 0.0]])
    assert np.array_equal(two_way_transmission(whole, r), np.exp(-2.0 * 0.02 * r))


def _reference_bins(laser, gate, beta_of, tau_of, r_min, breaks):
    """Each bin of W1 (O = 1, F = 1, E η π r_a² = 1) by adaptive quadrature of
    ∫ β(R) e^(−2τ(R))/R² [P(t_{k+1} − 2R/c) − P(t_k − 2R/c)] dR, split at the layers' edges."""
    tk = gate.gate_start_s + np.arange(gate.n_bins + 1) * gate.bin_width_s
    half = 8 * laser.pulse_fwhm_s
    out = np.empty(gate.n_bins)
    for k in range(gate.n_bins):
        def f(r):
            return float(beta_of(r)) * math.exp(-2 * float(tau_of(r))) / r ** 2 * (
                pulse_cdf(laser, tk[k + 1] - r / C2) - pulse_cdf(laser, tk[k] - r / C2))
        lo, hi = max(r_min, C2 * (tk[k] - half)), C2 * (tk[k + 1] + half)
        pts = [b for b in breaks if lo < b < hi]
        out[k] = integrate.quad(f, lo, hi, points=pts or None, epsabs=1e-20, epsrel=1e-11, limit=400)[0]
    return out


def test_two_layer_backscatter_waveform_matches_the_piecewise_equation_and_its_integral():
    """Two layers in clear air (10–30 m α = 0.02, 40–70 m α = 0.05, β = α/18), O = 1, 5 ns pulse, 1 ns bins from 0
    to 150 m: the simulated waveform against the bin integrals of β(R) e^(−2τ(R))/R² within 1e-3 L2 (the
    homogeneous test's bound; the issue asks 1 %), its sum against the closed form (piecewise E₁) within 1e-6
    (the tail beyond the gate < 1e-9 of it), and the waveform is zero where no layer reaches (the gap between
    the layers is only the pulse's spread of their edges)."""
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=1000)
    ext, table = _layered(0.0, TWO), np.asarray(TWO)
    beta = layer_backscatter(table)
    edges = np.unique(table[:, :2])
    wf = backscatter_template(laser, gate, 1.0, 0.0, ext, Overlap("none"), 1.0, profile=beta, breaks_m=edges)
    ref = _reference_bins(laser, gate, beta, ext.optical_depth, 1.0, edges)
    assert np.linalg.norm(wf - ref) / np.linalg.norm(ref) < 1e-3
    assert wf.sum() == pytest.approx(layers_closed_form_integral(TWO), rel=1e-6)
    t = 2 * np.array([5.0, 35.0, 90.0]) / C  # before, between and after the layers (≥ 3 FWHM from an edge)
    assert np.all(wf[(t / gate.bin_width_s).astype(int)] < 1e-9 * wf.max())


def _flash_cfg(**atm):
    cfg = config_for(30.0, pixels=8, bins=300, margin_bins=0)
    cfg.gate.gate_start_s = 0.0
    cfg.run.save_waveforms = True
    cfg.atmosphere = dataclasses.replace(cfg.atmosphere, **atm)
    return cfg


def test_a_surface_behind_layers_gets_exactly_exp_minus_2_sum_alpha_l():
    """Flash, a plate at 30 m filling the view, no weather (extinction only), homogeneous σ₀ = 1e-3 /m: two
    layers wholly in front of it (5–10 m α = 0.02, 15–20 m α = 0.05) scale every pixel's waveform by
    exp(−2(0.02·5 + 0.05·5)) = exp(−0.7) (float32 cube: 1e-6), a layer behind the plate changes nothing (bit for
    bit); the planner runs the extinction stage for layers alone; the metadata records them."""
    base = _flash_cfg(extinction_per_m=1e-3)
    scene = plate(30.0, 1.0)
    a = simulate_frame(scene, np.eye(4), base)
    lay = _flash_cfg(extinction_per_m=1e-3, aerosol_layers=[[5.0, 10.0, 0.02], [15.0, 20.0, 0.05]])
    b = simulate_frame(scene, np.eye(4), lay)
    wa, wb = a.waveforms.astype(np.float64), b.waveforms.astype(np.float64)
    assert wa.sum() > 0
    on = wa > 1e-3 * wa.max()
    assert np.allclose(wb[on] / wa[on], math.exp(-0.7), rtol=2e-6, atol=0)
    assert np.array_equal(a.range_image, b.range_image, equal_nan=True)
    behind = simulate_frame(scene, np.eye(4), _flash_cfg(extinction_per_m=1e-3, aerosol_layers=[[31.0, 40.0, 0.5]]))
    assert np.array_equal(behind.waveforms, a.waveforms)
    only = _flash_cfg(aerosol_layers=[[5.0, 10.0, 0.02]])
    assert "extinction" in plan(only)["stages_run"] and "extinction" in plan(base)["stages_run"]
    assert "extinction" in plan(_flash_cfg())["stages_skipped"]
    assert b.stats["atmosphere"]["aerosol_layers"] == [[5.0, 10.0, 0.02], [15.0, 20.0, 0.05]]


def test_scanner_and_gated_surfaces_see_the_layers_too():
    """The same two layers in front of a plate at 40 m: the scanner's waveforms and the gated slices scale by
    exp(−0.7) (1e-6; float32 slices), the homogeneous part unchanged."""
    from core.systems.gated import simulate_gated
    from core.systems.scanner import simulate_scan
    layers = [[5.0, 10.0, 0.02], [15.0, 20.0, 0.05]]
    scan = SimulationConfig(system_type="scanner")
    s = scan.scanner
    s.pattern, s.n_lines, s.scan_rate_hz, s.pulse_rate_hz = "raster", 4, 200.0, 4000.0
    s.scan_width_rad, s.scan_height_rad = 0.05, 0.05
    scan.gate.gate_start_s, scan.gate.bin_width_s, scan.gate.n_bins = 0.0, 1e-9, 400
    scan.run.save_waveforms, scan.run.threads = True, 1
    scan.atmosphere.extinction_per_m = 1e-3
    gated = SimulationConfig(system_type="gated")
    gated.receiver.width_px = gated.receiver.height_px = 8
    gated.receiver.fov_x_rad = gated.receiver.fov_y_rad = 0.01
    g = gated.gated
    g.gate_width_s, g.delay_step_s, g.n_slices, g.first_delay_s = 20e-9, 5e-9, 10, 2 * 40.0 / C - 30e-9
    gated.run.threads = 1
    gated.atmosphere.extinction_per_m = 1e-3
    for cfg, run, get in ((scan, simulate_scan, lambda r: np.asarray(r.waveforms, np.float64)),
                          (gated, simulate_gated, lambda r: np.asarray(r.slices, np.float64))):
        a = get(run(plate(40.0, 5.0), np.eye(4), cfg))
        lay = dataclasses.replace(cfg, atmosphere=dataclasses.replace(cfg.atmosphere, aerosol_layers=layers))
        b = get(run(plate(40.0, 5.0), np.eye(4), lay))
        on = a > 1e-3 * a.max()
        assert on.sum() > 10 and np.allclose(b[on] / a[on], math.exp(-0.7), rtol=2e-6, atol=0), cfg.system_type


def test_weather_stage_applies_the_layers_to_the_volume_and_the_drops():
    """prepare_frame_weather with weather = custom (β₀ = 0), no homogeneous extinction, O = 1 and the two layers:
    the frame's volume template sums to E η π r_a² × the closed form (1e-6); drops see exp(−2τ(R)) (W2 with the
    layered transmission = W2 with a float α times exp(−2 Σ α_i L_i(R)), 1e-14)."""
    from core.engine.weather_stage import prepare_frame_weather
    from core.physics.radiometry import energy_scale
    cfg = _flash_cfg(weather="custom", backscatter_per_m_sr=0.0, overlap_model="none", aerosol_layers=TWO)
    cfg.gate.n_bins, cfg.gate.bin_width_s, cfg.laser.pulse_fwhm_s = 1000, 1e-9, 5e-9
    validate_config(cfg)
    wx = prepare_frame_weather(cfg, 0, 64, 1e-6, 1e-3, 1e-3)
    assert wx.template.sum() == pytest.approx(energy_scale(cfg.laser, cfg.receiver) * layers_closed_form_integral(TWO),
                                              rel=1e-6)
    assert wx.metadata["aerosol_layers"] == TWO
    drops = Drops(np.array([0, 0, 1]), np.array([8.0, 25.0, 60.0]), np.array([1.0, 2.0, 3.0]), np.zeros(3))
    ext = _layered(1e-3, TWO)
    e_l, f_l = drop_returns(drops, [0.5, 0.5], 1e-6, 1.0, 1e-4, ext, 18.0, Overlap("none"))
    e_h, f_h = drop_returns(drops, [0.5, 0.5], 1e-6, 1.0, 1e-4, 1e-3, 18.0, Overlap("none"))
    assert np.allclose(e_l, e_h * np.exp(-2.0 * np.array([0.0, 0.3, 0.4 + 1.0])), rtol=1e-14, atol=0)
    assert np.array_equal(f_l, f_h)


def test_no_layers_is_the_homogeneous_run_bit_for_bit():
    """aerosol_layers = [] (the default) in fog: the frame is that of a config that never had the setting
    (the homogeneous path: a float extinction everywhere)."""
    cfg = _flash_cfg(weather="fog", visibility_m=200.0)
    assert cfg.atmosphere.aerosol_layers == []
    from core.physics.propagation import path_extinction
    assert isinstance(path_extinction(cfg), float)
    a = simulate_frame(plate(30.0, 0.06), np.eye(4), cfg)
    b = simulate_frame(plate(30.0, 0.06), np.eye(4), dataclasses.replace(
        cfg, atmosphere=dataclasses.replace(cfg.atmosphere, aerosol_layers=[])))
    assert np.array_equal(a.waveforms, b.waveforms)


@pytest.mark.parametrize("rows, where, allowed", [
    ("fog", "atmosphere.aerosol_layers", "a list of rows"),
    ([[0.0, 10.0]], "atmosphere.aerosol_layers row 1", "3 columns"),
    ([[0.0, 10.0, 0.01], [10.0, 20.0, 0.01, 1e-3]], "atmosphere.aerosol_layers row 2", "3 columns like row 1"),
    ([[10.0, 5.0, 0.01]], r"atmosphere.aerosol_layers row 1 column 2 \(end_m\)", "beyond the row's start_m"),
    ([[0.0, 10.0, 0.01], [5.0, 20.0, 0.01]], r"atmosphere.aerosol_layers row 2 column 1 \(start_m\)",
     "not overlapping"),
    ([[0.0, 10.0, 2.0]], r"atmosphere.aerosol_layers row 1 column 3 \(extinction_per_m\)", r"\[0, 1\] 1/m"),
    ([[0.0, 10.0, 0.01, -1.0]], r"row 1 column 4 \(backscatter_per_m_sr\)", r"\[0, 1\] 1/\(m sr\)"),
    ([[0.0, float("nan"), 0.01]], r"row 1 column 2 \(end_m\)", "a finite number"),
    ([[-1.0, 10.0, 0.01]], r"row 1 column 1 \(start_m\)", r"\[0, 1e\+06\] m"),
])
def test_bad_layers_are_refused_naming_the_row_and_column(rows, where, allowed):
    cfg = SimulationConfig()
    cfg.atmosphere.aerosol_layers = rows
    with pytest.raises(ConfigError, match=where + ".*" + allowed):
        validate_config(cfg)


def test_three_column_rows_take_beta_from_the_lidar_ratio(tmp_path):
    """A row without β: β = α/S (S = lidar_ratio_sr); the table read from a config dict, and through a TOML
    config file written by dump_config_toml and read by load_config (the layers survive the round trip)."""
    from core.config import config_from_dict, dump_config_toml, load_config
    from core.config.tables import aerosol_layer_table
    cfg = config_from_dict({"atmosphere": {"aerosol_layers": [[0, 50, 0.02]], "lidar_ratio_sr": 20.0}})
    assert aerosol_layer_table(cfg.atmosphere).tolist() == [[0.0, 50.0, 0.02, 0.001]]
    cfg.atmosphere.aerosol_layers = TWO
    path = tmp_path / "layers.toml"
    path.write_text(dump_config_toml(cfg), encoding="utf-8")
    assert load_config(path).atmosphere.aerosol_layers == TWO


def test_the_documented_layer_example_loads():
    """docs/atmosphere.md's config-file example of a fog bank: the TOML block that sets aerosol_layers is a valid
    config whose layer table is [40, 60, 0.02, 0.02/S]."""
    import re
    import tomllib
    from pathlib import Path
    from core.config import config_from_dict
    from core.config.tables import aerosol_layer_table
    text = (Path(__file__).resolve().parents[3] / "docs" / "atmosphere.md").read_text(encoding="utf-8")
    blocks = [b for b in re.findall(r"```toml\n(.*?)```", text, re.S) if "aerosol_layers" in b]
    assert len(blocks) == 1
    cfg = config_from_dict(tomllib.loads(blocks[0]))
    table = aerosol_layer_table(cfg.atmosphere)
    assert table.tolist() == [[40.0, 60.0, 0.02, 0.02 / cfg.atmosphere.lidar_ratio_sr]]


def _gated_fog_layer_slices():
    """(simulated slices, reference slices) of a gated pixel seeing only haze with a fog layer 15–25 m (α_l = 0.02 /m,
    β_l = α_l/18 sr⁻¹, O = 1): the reference is F_p E η π r_a² ∫ β(R) e^(−2τ(R))/R² g(2R/c − d_k) dR with
    β(R) = (α₀ + α_l 1[layer])/18 and τ(R) = α₀R + α_l clip(R − 15, 0, 10) (g the slice response), by adaptive
    quadrature split at the layer's edges."""
    from core.systems.gated import gate_response

    r, cfg, delays, scale, alpha = gated_fog_pixel(visibility_m=2000.0, aerosol_layers=[[15.0, 25.0, 0.02]])
    g, c2 = cfg.gated, C / 2.0

    def integrand(x, d):
        inside = 15.0 <= x < 25.0
        beta = (alpha + (0.02 if inside else 0.0)) / 18.0
        tau = alpha * x + 0.02 * min(max(x - 15.0, 0.0), 10.0)
        return beta * math.exp(-2 * tau) / x ** 2 * gate_response(cfg.laser, g.gate_width_s, g.shutter_edge_s,
                                                                  x / c2 - d)

    ref = np.array([integrate.quad(integrand, 2.0, c2 * (d + g.gate_width_s + 1e-7), args=(d,), points=[15.0, 25.0],
                                   limit=400, epsrel=1e-10)[0] for d in delays]) * scale
    return r.slices[:, 0, 0].astype(np.float64), ref


def test_gated_slices_of_a_pixel_seeing_only_a_fog_layer_match_the_equation():
    """Gated viewing in haze with a fog layer (:func:`_gated_fog_layer_slices`): relative L2 over the gate within
    the 1 % the issue asks (1.6e-3 measured; with a layer β 5 % off in the reference: 2.9e-2).  The slice just past
    the layer's far edge is 1 % off on its own: the slab lumping's second-order error, next test."""
    sim, ref = _gated_fog_layer_slices()
    assert np.linalg.norm(sim - ref) <= 1e-2 * np.linalg.norm(ref), np.linalg.norm(sim - ref) / np.linalg.norm(ref)


def test_gated_slice_past_a_fog_layers_far_edge_converges_as_the_slab_width_squared(monkeypatch):
    """The slice that sees the layer's far edge (25 m) only through its gate's rising edge (delay 170 ns, 1.5 % of the
    largest slice) is 1.0 % off with the default 4 slabs per width: each slab is lumped at its energy centroid, an
    error of order (Δ/w)² per slab (w the pulse-smoothed gate edge), which inside a homogeneous medium its
    neighbours' errors largely cancel but which nothing cancels where β drops 19× at the layer's end.  Being the
    lumping, it falls as Δ²: with 16 slabs per width (Δ/4) it must fall by at least 10× (16 in theory; measured
    −1.02e-2 → −7.3e-4, 14×; docs/theory.md §14)."""
    import functools

    import core.systems.gated as gated
    from core.physics.weather_waveform import gated_slab_table

    err = {}
    for spw in (4, 16):
        monkeypatch.setattr(gated, "gated_slab_table", functools.partial(gated_slab_table, slabs_per_width=spw))
        sim, ref = _gated_fog_layer_slices()
        err[spw] = (sim[17] - ref[17]) / ref[17]
    assert 0.5e-2 <= abs(err[4]) <= 2e-2, err  # the error the docs state (1 %)
    assert abs(err[16]) <= abs(err[4]) / 10.0, err
