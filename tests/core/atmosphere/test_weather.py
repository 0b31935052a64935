"""Weather in the waveform (issue 30): volume backscatter vs the single-scattering equation, drop statistics,
overlap, shadowing, the planner's skip and the wiring into the systems (core/atmosphere/weather.py)."""
import dataclasses
import math

import numpy as np
import pytest
from scipy import integrate, stats

from core.atmosphere.weather import (Drops, Overlap, Weather, closed_form_integral,
                                     disc_overlap_fraction, draw_drops, expected_drop_count, rain_extinction_per_m,
                                     shadow_factors, size_distribution, slab_integrals,
                                     small_drop_backscatter, snow_extinction_per_m, visible_drops, weather_model)
from core.config.settings import LaserSettings, RangeGateSettings, SimulationConfig
from core.config.validate import validate_config
from core.errors import ConfigError
from core.physics.laser import pulse_cdf
from core.physics.weather_waveform import backscatter_template, slab_edges_m
from core.systems.flash import plan, simulate_frame
from scenes import C, config_for, gated_fog_pixel, plate

C2 = 0.5 * C


def _reference_bins(laser, gate, beta, alpha, r_min):
    """Each bin of W1 (O = 1, F = 1, E η π r_a² = 1) by direct adaptive quadrature of
    ∫ β e^(−2αR)/R² [P(t_{k+1} − 2R/c) − P(t_k − 2R/c)] dR."""
    tk = gate.gate_start_s + np.arange(gate.n_bins + 1) * gate.bin_width_s
    half = 8 * laser.pulse_fwhm_s
    out = np.empty(gate.n_bins)
    for k in range(gate.n_bins):
        def f(r):
            return beta * math.exp(-2 * alpha * r) / r ** 2 * (pulse_cdf(laser, tk[k + 1] - r / C2)
                                                               - pulse_cdf(laser, tk[k] - r / C2))
        out[k] = integrate.quad(f, max(r_min, C2 * (tk[k] - half)), C2 * (tk[k + 1] + half), epsabs=0,
                                epsrel=1e-11, limit=200)[0]
    return out


@pytest.mark.parametrize("fwhm_s, bin_s", [(5e-9, 1e-9), (1e-9, 2e-9)])
def test_fog_backscatter_waveform_matches_the_single_scattering_equation(fwhm_s, bin_s):
    """O = 1, fog of α = 0.02 /m (V ≈ 200 m), S = 18 sr, gate 20–80 m: the simulated waveform against the bin
    integrals of the equation within 1e-3 L2 (the issue asks 1 %; measured 1.1e-6 for 5 ns/1 ns)."""
    laser = LaserSettings(pulse_fwhm_s=fwhm_s)
    gate = RangeGateSettings(gate_start_s=2 * 20.0 / C, bin_width_s=bin_s, n_bins=int(400e-9 / bin_s))
    alpha, beta, r_min = 0.02, 0.02 / 18.0, 5.0
    wf = backscatter_template(laser, gate, 1.0, beta, alpha, Overlap("none"), r_min)
    ref = _reference_bins(laser, gate, beta, alpha, r_min)
    assert np.linalg.norm(wf - ref) / np.linalg.norm(ref) < 1e-3


def test_backscatter_integral_matches_the_closed_form():
    """Σ of the waveform = β ∫ e^(−2αR)/R² dR in closed form (E₁), gate opening at 0 and closing where the
    remaining tail is negligible: within 1e-6 relative; the slab quadrature itself within 1e-10."""
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=4000)  # 0–600 m
    alpha, beta, r_min = 0.05, 0.05 / 18.0, 5.0
    edges = slab_edges_m(laser, gate, r_min)
    integral, _ = slab_integrals(edges, alpha, Overlap("none"))
    exact = closed_form_integral(edges[0], edges[-1], alpha)
    assert integral.sum() == pytest.approx(exact, rel=1e-10)
    wf = backscatter_template(laser, gate, 1.0, beta, alpha, Overlap("none"), r_min)
    r_end = C2 * gate.n_bins * gate.bin_width_s
    # the closed form to the gate end; the energy of slabs beyond it spilling in is < 1e-12 of the total
    assert wf.sum() == pytest.approx(beta * closed_form_integral(r_min, r_end, alpha), rel=1e-6)
    # α = 0: 1/a − 1/b
    assert closed_form_integral(2.0, 4.0, 0.0) == pytest.approx(0.25)


def test_disc_overlap_worked_values():
    """Equal unit discs one radius apart share 2π/3 − √3/2 = 1.2284 (39.10 % of a disc); nested discs 1,
    disjoint 0."""
    assert disc_overlap_fraction(1.0, 1.0, 1.0) == pytest.approx((2 * np.pi / 3 - np.sqrt(3) / 2) / np.pi, rel=1e-12)
    assert disc_overlap_fraction(0.2, 1.0, 0.5) == 1.0
    assert disc_overlap_fraction(0.2, 0.3, 0.5) == 0.0
    ov = Overlap("geometric", 0.05, 0.01, 1e-3, 0.025, 1e-3)
    o = ov(np.array([0.0, 10.0, 100.0, 1e4]))
    assert o[0] == 0.0 and 0.0 < o[1] < o[2] < 1.0  # the discs touch at R = (0.05 − 0.035)/2e-3 = 7.5 m
    assert ov(7.4) == 0.0 and ov(7.6) > 0.0
    assert o[3] == pytest.approx(1.0, abs=0.01)


def test_rain_and_snow_coefficients_worked_values():
    """Rain 10 mm/h: 1.076·10^0.67 = 5.0329 dB/km; Marshall–Palmer Λ = 4.1·10^−0.21 = 2.5280 /mm; dry snow 1 mm/h
    at 1064 nm: 5.5536 dB/km."""
    assert rain_extinction_per_m(10.0) == pytest.approx(5.0329e-3 * math.log(10) / 10, rel=1e-4)
    n0, lam = size_distribution("rain", 10.0)
    assert (n0, lam) == (8000.0, pytest.approx(2.5280, rel=1e-4))
    assert snow_extinction_per_m(1.0, 1.064e-6) == pytest.approx((5.42e-5 * 1064 + 5.4958776) * math.log(10) / 1e4)
    # β of the drops below D_min → the full DSD's (2/S)(π/4) N0 2/Λ³ as D_min → ∞
    full = (2 / 18) * (np.pi / 4) * n0 * 2 / lam ** 3 * 1e-6
    assert small_drop_backscatter(n0, lam, 50.0, 18.0) == pytest.approx(full, rel=1e-12)
    assert small_drop_backscatter(n0, lam, 1.0, 18.0) < full


def _rain(rate=10.0, d_min=1.0):
    n0, lam = size_distribution("rain", rate)
    return Weather("rain", 0.0, 0.0, 18.0, n0, lam, d_min, n0 / lam * math.exp(-lam * d_min))


def test_drop_counts_per_pulse_follow_the_dsd_and_the_beam_volume():
    """2000 pulses, 1 mrad beam (Ω = 7.85e-7 sr), 0.5–80 m, rain 10 mm/h, D ≥ 1 mm: the expected count per pulse is
    n Ω (r_hi³ − r_lo³)/3 = 252.6 m⁻³ × 7.854e-7 sr × 170 667 m³ = 33.86; the counts are Poisson (χ² of
    the count histogram, p > 0.001, fixed seed), the ranges follow R³ uniform and the diameters D_min + Exp(Λ) (KS, p > 0.001)."""
    w = _rain()
    omega = np.pi * 0.5e-3 ** 2
    mean = expected_drop_count(w, omega, 0.5, 80.0)
    assert mean == pytest.approx(w.drop_density_per_m3 * omega * (80.0 ** 3 - 0.5 ** 3) / 3)
    assert mean == pytest.approx(33.86, rel=1e-3)
    n_pulses = 2000
    drops = draw_drops(np.random.default_rng(1234), w, n_pulses, omega, 0.5, 80.0)
    counts = np.bincount(drops.beam, minlength=n_pulses)
    assert counts.mean() == pytest.approx(mean, abs=4 * math.sqrt(mean / n_pulses))
    # χ² goodness of fit of the count histogram against Poisson(mean): the tails lumped into two bins of ≥ 5 expected
    lo = int(stats.poisson.ppf(5 / n_pulses, mean)) + 1   # P(N ≤ lo − 1) ≥ 5/n
    hi = int(stats.poisson.isf(5 / n_pulses, mean)) - 1   # P(N > hi) ≥ 5/n
    obs = np.array([np.sum(counts < lo)] + [np.sum(counts == j) for j in range(lo, hi + 1)] + [np.sum(counts > hi)])
    exp = np.array([stats.poisson.cdf(lo - 1, mean)] + list(stats.poisson.pmf(np.arange(lo, hi + 1), mean))
                   + [stats.poisson.sf(hi, mean)]) * n_pulses
    assert exp.sum() == pytest.approx(n_pulses) and min(exp[0], exp[-1]) >= 5 and exp.min() >= 2
    assert stats.chisquare(obs, exp).pvalue > 1e-3
    r3 = (drops.range_m ** 3 - 0.5 ** 3) / (80.0 ** 3 - 0.5 ** 3)
    assert stats.kstest(r3, "uniform").pvalue > 1e-3
    assert stats.kstest(drops.diameter_mm - 1.0, "expon", args=(0, 1 / w.lam)).pvalue > 1e-3
    # sorted by (beam, range), every beam index in range
    key = drops.beam * 1000.0 + drops.range_m
    assert np.all(np.diff(key) >= 0) and drops.beam.max() < n_pulses


def test_drops_behind_a_surface_are_hidden_and_near_drops_shadow():
    """A beam of two equal sub-rays, one hitting a wall at 40 m, one missing: drops placed in the first
    (u < 0.5) are visible only before 40 m, in the second always.  Shadows multiply: f = 0.5 at 1 m and 2 m
    leave 0.25 at 3 m; a drop does not shadow itself."""
    d = Drops(np.zeros(4, np.int64), np.array([10.0, 30.0, 50.0, 60.0]), np.ones(4), np.array([0.2, 0.7, 0.3, 0.9]))
    vis = visible_drops(d, np.array([0, 0]), np.array([0.5, 0.5]), np.array([40.0, np.inf]))
    assert vis.tolist() == [True, True, False, True]
    d2 = Drops(np.zeros(2, np.int64), np.array([1.0, 2.0]), np.ones(2), np.zeros(2))
    f = np.array([0.5, 0.5])
    assert shadow_factors(d2, f, [0, 0, 0, 1], [3.0, 1.5, 0.5, 3.0]).tolist() == [0.25, 0.5, 1.0, 1.0]
    assert shadow_factors(d2, f, d2.beam, d2.range_m).tolist() == [1.0, 0.5]


def _flash(weather="none", **atm):
    cfg = config_for(30.0, pixels=8, bins=300, margin_bins=0)
    cfg.gate.gate_start_s = 0.0
    cfg.run.save_waveforms = True
    cfg.atmosphere = dataclasses.replace(cfg.atmosphere, weather=weather, **atm)
    return cfg


def test_no_weather_is_skipped_by_the_planner_at_zero_cost():
    """weather = none: the planner lists both weather stages as skipped, the frame records no weather time, and
    the products are bit-identical whatever the other weather settings hold."""
    cfg = _flash()
    p = plan(cfg)
    assert "weather_backscatter" in p["stages_skipped"] and "weather_drops" in p["stages_skipped"]
    assert "weather_backscatter" not in p["stages_run"]
    scene = plate(30.0, 0.1)
    a = simulate_frame(scene, np.eye(4), cfg)
    b = simulate_frame(scene, np.eye(4), _flash(rain_rate_mm_h=25.0, backscatter_per_m_sr=1e-3, lidar_ratio_sr=50.0))
    assert "weather" not in a.stats["stage_times_s"] and "weather" not in a.stats
    assert np.array_equal(a.waveforms, b.waveforms) and np.array_equal(a.range_image, b.range_image, equal_nan=True)
    assert "atmosphere" not in a.points
    assert weather_model(cfg.atmosphere, 1.064e-6, 0.0) is None
    fog = plan(_flash("fog", visibility_m=200.0))
    assert "weather_backscatter" in fog["stages_run"] and "weather_drops" in fog["stages_skipped"]


def test_flash_fog_adds_the_template_to_every_pixel_before_its_surface():
    """Fog V = 200 m, O = 1: a pixel whose rays all miss the plate gets F_p × the volume template (float32 cube:
    1e-6 relative); a pixel that sees the plate gets it only up to the plate's bin; the near-range echo is
    marked as the atmosphere's."""
    cfg = _flash("fog", visibility_m=200.0, overlap_model="none", backscatter_min_range_m=3.0)
    scene = plate(30.0, 0.06)  # covers the centre 2×2 pixels fully, pixel (0, 0) not (FOV ±0.15 m at 30 m)
    r = simulate_frame(scene, np.eye(4), cfg)
    a = cfg.atmosphere
    from core.physics.laser import cell_energy_fractions
    from core.geometry.rays import Detector
    from core.physics.propagation import aerosol_extinction_per_m
    from core.physics.radiometry import energy_scale
    det = Detector.from_settings(cfg.receiver)
    fx, fy = cell_energy_fractions(cfg.laser, det)
    s = det.subsamples
    f_pix = np.add.reduceat(fy, np.arange(0, len(fy), s))[:, None] * np.add.reduceat(fx, np.arange(0, len(fx), s))
    alpha = aerosol_extinction_per_m(cfg)
    tpl = backscatter_template(cfg.laser, cfg.gate, energy_scale(cfg.laser, cfg.receiver), alpha / a.lidar_ratio_sr,
                               alpha, Overlap("none"), a.backscatter_min_range_m)
    corner = r.waveforms[0, 0].astype(np.float64)
    assert np.allclose(corner, f_pix[0, 0] * tpl, rtol=1e-6, atol=1e-6 * tpl.max() * f_pix[0, 0])
    centre = r.waveforms[4, 4].astype(np.float64)
    k_plate = int(2 * 30.0 / C / cfg.gate.bin_width_s)
    assert np.allclose(centre[:k_plate - 20], f_pix[4, 4] * tpl[:k_plate - 20], rtol=1e-6,
                       atol=1e-6 * tpl.max() * f_pix[4, 4])  # (as the corner: 1e-6 of the peak, not 1e-8 J)
    assert np.all(centre[k_plate + 20:] == 0.0)
    near = r.points["range_m"] < 20.0
    assert near.any() and np.all(r.points["atmosphere"][near] == 1)
    assert r.stats["weather"]["n_atmosphere_echoes"] == int(r.points["atmosphere"].sum())


def test_noisy_receiver_sees_the_fog():
    """The receiver chain gets the backscatter: the noisy digital waveform's mean over the near-range hump
    (10–25 m) rises by more than 10 noise σ over the same receiver without fog."""
    def run(weather, **kw):
        cfg = _flash(weather, **kw)
        cfg.detector.mode = "noisy"
        cfg.run.save_counts = True  # counts kept: the per-bin reference route (run.save_counts)
        return simulate_frame(plate(30.0, 0.1), np.eye(4), cfg)
    clear = run("none")
    fog = run("fog", visibility_m=200.0, overlap_model="none", backscatter_min_range_m=3.0)
    k0, k1 = int(2 * 10 / C / 1e-9), int(2 * 25 / C / 1e-9)
    d_clear = clear.digital_waveforms[..., k0:k1].astype(np.float64)
    d_fog = fog.digital_waveforms[..., k0:k1].astype(np.float64)
    sigma = d_clear.std() / math.sqrt(d_clear.size)
    assert d_fog.mean() - d_clear.mean() > 10 * max(sigma, 1e-30)


def test_rain_flash_drops_are_returns_and_reproducible():
    """Rain 50 mm/h, drops ≥ 0.5 mm, coaxial: the same seed gives the same drops and products; the drawn count
    is within 5σ of the expected count; drop echoes in front of the plate are marked as the atmosphere's."""
    cfg = _flash("rain", rain_rate_mm_h=50.0, drop_min_diameter_mm=0.5, tx_rx_offset_m=0.0)
    scene = plate(30.0, 1.0)
    a = simulate_frame(scene, np.eye(4), cfg)
    b = simulate_frame(scene, np.eye(4), cfg)
    assert np.array_equal(a.waveforms, b.waveforms)
    d = a.stats["weather"]["drops"]
    assert abs(d["drawn"] - d["expected"]) < 5 * math.sqrt(d["expected"])
    assert a.stats["stages_run"].count("weather_drops") == 1


def test_weather_inputs_are_validated():
    cfg = SimulationConfig()
    cfg.atmosphere.weather = "fog"
    with pytest.raises(ConfigError, match="atmosphere.visibility_m"):
        validate_config(cfg)
    cfg.atmosphere.weather = "rain"
    with pytest.raises(ConfigError, match="atmosphere.rain_rate_mm_h"):
        validate_config(cfg)
    cfg.atmosphere.weather = "drizzle"
    with pytest.raises(ConfigError, match="atmosphere.weather"):
        validate_config(cfg)


def test_atmosphere_returns_get_their_las_class_and_flags(tmp_path):
    """Fog, O = 1: the near-range echoes are written as class 18 (high noise), synthetic and withheld; the
    summary counts them."""
    from core.fileio.las import CLASS_ATMOSPHERE, read_las
    from core.fileio.run_folder import run_summary
    from core.run import run_simulation
    cfg = _flash("fog", visibility_m=200.0, overlap_model="none")
    cfg.run.save_waveforms = False
    path, res = run_simulation(plate(30.0, 0.06), np.eye(4), cfg, tmp_path / "fog")
    pts = read_las(path / "points.las")["points"]
    atm = res.points["atmosphere"].astype(bool)
    assert atm.sum() > 0
    assert np.all(pts["classification"][atm] == CLASS_ATMOSPHERE) and np.all(pts["withheld"][atm])
    assert np.all(pts["synthetic"]) and not np.any(pts["classification"][~atm] == CLASS_ATMOSPHERE)
    assert f"weather  {int(atm.sum())} returns of the atmosphere" in run_summary(path, res)


def test_validation_module_passes_and_plots(tmp_path):
    """scripts/validation/weather.py (the validation report's weather section), quick form."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[3] / "scripts" / "validation" / "weather.py"
    spec = importlib.util.spec_from_file_location("validation_weather", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    checks = mod.run(tmp_path, quick=True)
    assert len(checks) == 6 and all(c["passed"] for c in checks)
    assert set(checks[0]) == {"quantity", "simulated", "reference", "tolerance", "passed"}
    assert (tmp_path / "weather_fog_backscatter.png").stat().st_size > 10_000


def test_too_many_drops_are_refused_naming_the_diameter_that_fits():
    """A 12° flash field of view of 8×8 px, gate 0–300 m, rain 25 mm/h, D ≥ 1 mm: ~1e9 drops are in the beams and
    2.8e7 of them above the default detectability cut (0.01 photo-electrons; the pixels are large, so the near ones
    all count); the frame is refused naming atmosphere.drop_min_diameter_mm and the diameter that brings the drawn
    count under the 2e6 limit (bisection over the shells' counts n(D ≥ max(D_min, D_k)))."""
    cfg = _flash("rain", rain_rate_mm_h=25.0)
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = np.radians(12.0)
    cfg.gate.n_bins = 2000
    with pytest.raises(ConfigError, match=r"atmosphere.drop_min_diameter_mm = 1.0 is not allowed: at least (\d\.\d\d) mm"
                       ) as err:
        simulate_frame(plate(30.0, 100.0), np.eye(4), cfg)
    need = float(str(err.value).split("at least ")[1].split(" mm")[0])
    ok = dataclasses.replace(cfg, atmosphere=dataclasses.replace(cfg.atmosphere, drop_min_diameter_mm=need))
    r = simulate_frame(plate(30.0, 100.0), np.eye(4), ok)
    assert 1e6 < r.stats["weather"]["drops"]["expected"] <= 2e6


def test_gated_slices_of_a_pixel_seeing_only_fog_match_the_equation():
    """Gated viewing in fog (V = 200 m, O = 1): a pixel with no surface collects in slice k
    F_p E η π r_a² β ∫ e^(−2αR)/R² g(2R/c − d_k) dR (g the slice response); against adaptive quadrature: relative
    L2 over the gate within the 1 % the issue asks (1.9e-3 measured), and within 1e-3 in every slice that holds
    more than 1 % of the largest and sees no range nearer than 5 m.  Nearer, lumping each slab (Δ = FWHM/4 =
    0.375 m) at its centroid errs by about Δ²/(4R²) (1.4e-3 at 5 m, 2.4e-3 measured in the slice at 1.5 m).
    (Until session 28 this compared with np.allclose's default atol of 1e-8 against slices of 1e-13 J, which
    could not fail.)"""
    from core.systems.gated import gate_response

    r, cfg, delays, scale, alpha = gated_fog_pixel(visibility_m=200.0)
    g, beta = cfg.gated, alpha / 18.0
    ref = np.array([integrate.quad(lambda x: math.exp(-2 * alpha * x) / x ** 2
                                   * gate_response(cfg.laser, g.gate_width_s, g.shutter_edge_s, x / C2 - d),
                                   2.0, C2 * (d + g.gate_width_s + 1e-7), limit=400, epsrel=1e-10)[0]
                    for d in delays]) * scale * beta
    sim = r.slices[:, 0, 0].astype(np.float64)
    assert np.linalg.norm(sim - ref) <= 1e-2 * np.linalg.norm(ref)
    far = (ref > 0.01 * ref.max()) & (C2 * (delays - cfg.laser.pulse_fwhm_s) >= 5.0)
    assert far.sum() >= 10
    assert np.allclose(sim[far], ref[far], rtol=1e-3, atol=0.0), np.max(np.abs(sim[far] / ref[far] - 1))


# ------------------------------------------------------------------------------------------------------------
# The detectability cut (atmosphere.drop_cut_photoelectrons): only the drops that can matter are drawn
# ------------------------------------------------------------------------------------------------------------
def _count_chi2_pvalue(counts, mean):
    """χ² of a count histogram against Poisson(mean), tails lumped into bins of ≥ 5 expected."""
    n = len(counts)
    lo = int(stats.poisson.ppf(5 / n, mean)) + 1
    hi = int(stats.poisson.isf(5 / n, mean)) - 1
    obs = np.array([np.sum(counts < lo)] + [np.sum(counts == j) for j in range(lo, hi + 1)] + [np.sum(counts > hi)])
    exp = np.array([stats.poisson.cdf(lo - 1, mean)] + list(stats.poisson.pmf(np.arange(lo, hi + 1), mean))
                   + [stats.poisson.sf(hi, mean)]) * n
    return stats.chisquare(obs, exp).pvalue


def test_cut_draw_is_the_brute_force_draw_above_the_cut():
    """Rain 10 mm/h, D ≥ 1 mm, 1 mrad beam, 0.5–80 m, a cut rising from D_min to 3 mm over 20 geometric shells:
    20000 beams drawn with the cut against 20000 drawn brute force and kept above the cut.  Counts per beam are
    Poisson with the shells' expected sum (χ², p > 0.001, fixed seeds) and agree with the filtered brute force
    (4σ); the ranges agree (two-sample KS, p > 0.001) and with the analytic CDF Σ_k μ_k (R³ − r_k³)/(r_{k+1}³ − r_k³)
    (KS, p > 0.001); D − D_k is Exp(Λ) (KS, p > 0.001)."""
    from core.atmosphere.weather import DropCut
    w = _rain()
    omega = np.pi * 0.5e-3 ** 2
    edges = np.geomspace(0.5, 80.0, 21)
    d_cut = np.linspace(1.0, 3.0, 20)
    cut = DropCut(edges, d_cut, omega, w.n0, w.lam, 1.0, 18.0, 0.0)
    mu = cut.expected_per_beam()
    # worked value of one shell: n(D ≥ D_k) Ω (r_{k+1}³ − r_k³)/3
    assert mu[7] == pytest.approx(w.n0 / w.lam * math.exp(-w.lam * d_cut[7]) * omega
                                  * (edges[8] ** 3 - edges[7] ** 3) / 3, rel=1e-12)
    n_beams = 20000
    dc = draw_drops(np.random.default_rng(7), w, n_beams, omega, 0.5, 80.0, cut=cut)
    db = draw_drops(np.random.default_rng(8), w, n_beams, omega, 0.5, 80.0)
    k_b = np.clip(np.searchsorted(edges, db.range_m, side="right") - 1, 0, 19)
    db = db.take(db.diameter_mm >= d_cut[k_b])
    mean = mu.sum()
    c_c = np.bincount(dc.beam, minlength=n_beams)
    c_b = np.bincount(db.beam, minlength=n_beams)
    assert _count_chi2_pvalue(c_c, mean) > 1e-3 and _count_chi2_pvalue(c_b, mean) > 1e-3
    assert abs(c_c.mean() - c_b.mean()) < 4 * math.sqrt(2 * mean / n_beams)
    assert stats.ks_2samp(dc.range_m, db.range_m).pvalue > 1e-3

    def cdf(r):
        k = np.clip(np.searchsorted(edges, r, side="right") - 1, 0, 19)
        inside = (r ** 3 - edges[k] ** 3) / (edges[k + 1] ** 3 - edges[k] ** 3)
        return (np.concatenate([[0.0], np.cumsum(mu)])[k] + mu[k] * inside) / mean
    assert stats.kstest(dc.range_m, cdf).pvalue > 1e-3
    k_c = np.clip(np.searchsorted(edges, dc.range_m, side="right") - 1, 0, 19)
    assert np.all(dc.diameter_mm >= d_cut[k_c])
    assert stats.kstest(dc.diameter_mm - d_cut[k_c], "expon", args=(0, 1 / w.lam)).pvalue > 1e-3


def test_cross_section_and_continuum_against_independent_forms():
    """σ(R) = ∫ N(D) min(πD²/4, Ω R²) dD against adaptive quadrature (1e-9 relative) where the beam's
    cross-section falls inside [D_lo, D_hi]; a cut above every drop (all continuum) with Ω = 1e-3 sr, wide enough
    that no drop fills the beam (D* = 36 mm at 1 m): β(R) = (2/S)(π/4) N₀ ∫_{D_min}^∞ D² e^(−ΛD) dD · R²/(R² + r_a²) · e^(−σ (R − r_lo)) and the
    mean shadow e^(−σ (R − r_lo)), σ constant (closed forms, 1e-9)."""
    from core.atmosphere.weather import DropCut, drop_cross_section_per_m
    w = _rain(25.0)
    omega, r = 1e-6, 2.0   # Ω R² = 4e-6 m²: D* = 2.26 mm
    num = integrate.quad(lambda d: w.n0 * math.exp(-w.lam * d) * min(math.pi / 4 * (d * 1e-3) ** 2, omega * r * r),
                         1.0, 4.0, points=[2e3 * math.sqrt(omega * r * r / math.pi)], epsabs=0, epsrel=1e-12)[0]
    assert drop_cross_section_per_m(w.n0, w.lam, 1.0, 4.0, omega, r) == pytest.approx(num, rel=1e-9)
    omega = 1e-3
    edges = np.geomspace(1.0, 100.0, 11)
    cut = DropCut(edges, np.full(10, np.inf), omega, w.n0, w.lam, 1.0, 18.0, 0.025 ** 2)
    assert cut.expected_per_beam().sum() == 0.0
    x = w.lam
    m2 = math.exp(-x) * (1 / x + 2 / x ** 2 + 2 / x ** 3)     # ∫_1^∞ D² e^(−ΛD) dD
    sigma = w.n0 * math.pi / 4 * m2 * 1e-6
    rr = np.array([1.0, 3.7, 50.0, 99.0])
    assert np.allclose(cut.mean_shadow(rr), np.exp(-sigma * (rr - 1.0)), rtol=1e-9, atol=0)
    beta = (2 / 18.0) * sigma * rr ** 2 / (rr ** 2 + 0.025 ** 2) * np.exp(-sigma * (rr - 1.0))
    assert np.allclose(cut.beta_profile(rr), beta, rtol=1e-9, atol=0)


def _rain_frames(cut_pe, seeds):
    """Waveform rows of 32×32-px flash frames (0.02 rad, coaxial, gate 0–60 m, plate at 45 m filling the field of
    view), rain 50 mm/h, D ≥ 0.5 mm, with this detectability cut."""
    rows = []
    for seed in seeds:
        cfg = config_for(45.0, pixels=32, subsamples=2, fov_rad=0.02, bins=400, margin_bins=0)
        cfg.gate.gate_start_s = 0.0
        cfg.run.save_waveforms = True
        cfg.run.seed = seed
        cfg.atmosphere = dataclasses.replace(cfg.atmosphere, weather="rain", rain_rate_mm_h=50.0,
                                             drop_min_diameter_mm=0.5, tx_rx_offset_m=0.0,
                                             drop_cut_photoelectrons=cut_pe)
        r = simulate_frame(plate(45.0, 5.0), np.eye(4), cfg)
        rows.append(r.waveforms.reshape(-1, 400).astype(np.float64))
    return np.concatenate(rows), r.stats["weather"]["drops"]


def test_cut_keeps_the_mean_waveform_of_the_brute_force_draw():
    """The flash frame of :func:`_rain_frames`, 4 frames × 1024 pixels each: brute force (cut 0: 5.2e4 drops a frame)
    against cut 300 e- (1.3e4 drawn) and cut 1e6 e- (only the drops hiding ≥ 1 % of their beam: 1.8e3).  The mean
    energy of each 7.5 m window from 7.5 m to the plate's echo (the drop returns, the continuum, and the plate
    seen through the drops' mean shadow, which is 9 % at 45 m) agrees: χ² of the six windows' differences over
    their standard errors, p > 0.001 (fixed seeds).  Cut 0.01 e- (the default) draws every drop here (the pixels
    are small and the drops bright): the same frames bit for bit as cut 0."""
    brute, info0 = _rain_frames(0.0, range(4))
    assert info0["drawn"] > 4e4
    win = lambda w: w.reshape(len(w), 8, 50).sum(axis=2)[:, 1:7]   # noqa: E731
    wb = win(brute)
    for cut_pe, most in ((300.0, 2e4), (1e6, 3e3)):
        other, info = _rain_frames(cut_pe, range(10, 14))
        assert info["drawn"] < most
        wo = win(other)
        z = (wb.mean(0) - wo.mean(0)) / np.sqrt(wb.var(0, ddof=1) / len(wb) + wo.var(0, ddof=1) / len(wo))
        assert stats.chi2.sf(np.sum(z ** 2), df=len(z)) > 1e-3, (cut_pe, z)
    same, _ = _rain_frames(0.01, range(1))
    assert np.array_equal(same, brute[:1024])


def test_gated_cut_keeps_the_mean_slices_of_the_brute_force_draw():
    """Gated viewing (16×16 px, 0.02 rad, slices of 20 ns every 10 ns from 0, plate at 40 m) in 50 mm/h rain,
    D ≥ 0.5 mm, coaxial: brute force (cut 0) against cut 1e6 e- (only the drops hiding ≥ 1 % of their beam drawn,
    the rest through the slab table's β profile and the mean shadow), 6 frames each: the pixels' mean of every
    other slice (no two share a delay window) agrees, χ² of the differences over their standard errors, p > 0.001
    (fixed seeds)."""
    from core.systems.gated import simulate_gated

    def slices(cut_pe, seeds):
        out, drawn = [], 0
        for seed in seeds:
            cfg = SimulationConfig(system_type="gated")
            cfg.receiver.width_px = cfg.receiver.height_px = 16
            cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.02
            g = cfg.gated
            g.gate_width_s, g.delay_step_s, g.n_slices, g.first_delay_s = 20e-9, 10e-9, 28, 0.0
            cfg.atmosphere = dataclasses.replace(cfg.atmosphere, weather="rain", rain_rate_mm_h=50.0,
                                                 drop_min_diameter_mm=0.5, tx_rx_offset_m=0.0,
                                                 drop_cut_photoelectrons=cut_pe)
            cfg.run.threads, cfg.run.seed = 1, seed
            r = simulate_gated(plate(40.0, 5.0), np.eye(4), cfg)
            out.append(r.slices.reshape(g.n_slices, -1).T.astype(np.float64))
            drawn += r.stats["weather"]["drops"]["drawn"]
        return np.concatenate(out)[:, 1::2], drawn

    b, n_b = slices(0.0, range(6))
    c, n_c = slices(1e6, range(20, 26))
    assert n_c < 0.2 * n_b
    z = (b.mean(0) - c.mean(0)) / np.sqrt(b.var(0, ddof=1) / len(b) + c.var(0, ddof=1) / len(c))
    assert stats.chi2.sf(np.sum(z ** 2), df=len(z)) > 1e-3, z


def test_scanner_cut_keeps_the_mean_waveform_of_the_brute_force_draw():
    """Scanner (raster of 1000 pulses, 1 µJ, 1 mrad beam, 7 sub-rays, plate at 40 m, gate 0–60 m) in 50 mm/h
    rain, D ≥ 0.5 mm, coaxial: brute force (cut 0, ~100 drops a pulse) against a cut of 1e6 e- (only the drops
    hiding ≥ 1 % of the beam drawn, D ≥ 2 mm at 20 m; drawn per pulse tile) over 3 scans each: the mean energy
    of five 7.5 m windows
    from 7.5 m to the plate's echo agrees, χ² of the differences over their standard errors, p > 0.001 (fixed
    seeds)."""
    from core.systems.scanner import simulate_scan

    def rows(cut_pe, seeds):
        out = []
        for seed in seeds:
            cfg = SimulationConfig(system_type="scanner")
            s = cfg.scanner
            s.pattern, s.n_lines, s.scan_rate_hz, s.pulse_rate_hz = "raster", 10, 200.0, 20000.0
            s.scan_width_rad, s.scan_height_rad, s.beam_subray_rings = 0.1, 0.1, 1
            cfg.laser.beam_divergence_rad, cfg.laser.pulse_fwhm_s, cfg.laser.pulse_energy_j = 1e-3, 2e-9, 1e-6
            cfg.gate.gate_start_s, cfg.gate.bin_width_s, cfg.gate.n_bins = 0.0, 1e-9, 400
            cfg.run.save_waveforms, cfg.run.threads, cfg.run.seed = True, 1, seed
            cfg.atmosphere = dataclasses.replace(cfg.atmosphere, weather="rain", rain_rate_mm_h=50.0,
                                                 drop_min_diameter_mm=0.5, tx_rx_offset_m=0.0,
                                                 drop_cut_photoelectrons=cut_pe)
            r = simulate_scan(plate(40.0, 10.0), np.eye(4), cfg)
            out.append(np.asarray(r.waveforms, np.float64).reshape(-1, 400))
        w = np.concatenate(out)
        return w.reshape(len(w), 8, 50).sum(axis=2)[:, 1:6]   # the plate's echo is in the fifth window

    b = rows(0.0, range(3))
    c = rows(1e6, range(30, 33))
    assert len(b) == 3000
    z = (b.mean(0) - c.mean(0)) / np.sqrt(b.var(0, ddof=1) / len(b) + c.var(0, ddof=1) / len(c))
    assert stats.chi2.sf(np.sum(z ** 2), df=len(z)) > 1e-3, z


def test_volume_rows_hidden_behind_surfaces_and_without_any_hit():
    """add_volume_rows: beam 0 (F = 0.6) has sub-rays of 0.2 and 0.3 hitting surfaces in bins 2 and 4, beam 1
    (F = 0.4) none: row 0 gets the template × (0.6, 0.6, 0.4, 0.4, 0.1, 0.1), row 1 × 0.4 everywhere; a block with
    no hit at all gets F × the template (float32 rows as the flash cube, float64 as the scanner's)."""
    from types import SimpleNamespace
    from core.atmosphere.weather import add_volume_rows
    gate = SimpleNamespace(gate_start_s=0.0, bin_width_s=1e-9)
    tpl = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    for dtype in (np.float32, np.float64):
        rows = np.zeros((2, 6), dtype)
        add_volume_rows(rows, tpl, [0.6, 0.4], [0, 0], [2.5e-9, 4.5e-9], [0.2, 0.3], gate)
        assert np.allclose(rows[0], tpl * [0.6, 0.6, 0.4, 0.4, 0.1, 0.1], rtol=1e-6, atol=0)
        assert np.allclose(rows[1], tpl * 0.4, rtol=1e-6, atol=0)
        rows = np.zeros((2, 6), dtype)
        add_volume_rows(rows, tpl, [0.6, 0.4], np.zeros(0, np.int64), np.zeros(0), np.zeros(0), gate)
        assert np.allclose(rows, np.outer([0.6, 0.4], tpl), rtol=1e-6, atol=0)


# ------------------------------------------------------------------------------------------------------------
# Per-pixel overlap of a flash (pixel_overlap, the field-angle template table)
# ------------------------------------------------------------------------------------------------------------
_OV = Overlap("geometric", 0.05, 0.01, 0.1, 0.025, 2e-3)


def test_pixel_overlap_of_the_on_axis_pixel_is_the_overlap_bit_for_bit():
    """t = 0: pixel_overlap and its template are today's Overlap and backscatter_template exactly; model none: 1;
    offset 0: every pixel 1 (the overlap is the offset's parallax only)."""
    from core.atmosphere.weather import pixel_overlap
    from core.physics.weather_waveform import pixel_backscatter_templates
    r = np.linspace(0.01, 50.0, 4001)
    assert np.array_equal(pixel_overlap(_OV, r, 0.0, 0.0), _OV(r))
    assert 0.0 < _OV(0.5) < 1.0  # the case is not trivial
    assert np.all(pixel_overlap(Overlap("none"), r, 0.07, -0.03) == 1.0)
    zero = dataclasses.replace(_OV, offset_m=0.0)
    assert np.all(pixel_overlap(zero, r[:, None], np.array([0.0, 0.05, 0.099]), 0.03) == 1.0)
    laser = LaserSettings(pulse_fwhm_s=2e-9)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=200)
    ref = backscatter_template(laser, gate, 1.0, 1e-3, 0.02, _OV, 0.05)
    assert np.array_equal(pixel_backscatter_templates(laser, gate, 1.0, 1e-3, 0.02, _OV, 0.05, [0.0], [0.0])[0], ref)


def _gauss_over_disc(c, b, s, w, n=200):
    """∫ exp(−2|x − s|²/w²) over the disc of radius b centred at c (polar Gauss–Legendre, n × n)."""
    xg, wg = np.polynomial.legendre.leggauss(n)
    rr, ph = np.meshgrid(0.5 * b * (xg + 1), np.pi * (xg + 1), indexing="ij")
    x, y = c[0] + rr * np.cos(ph) - s[0], c[1] + rr * np.sin(ph) - s[1]
    return float((np.exp(-2 * (x * x + y * y) / w ** 2) * rr * (0.5 * b * wg)[:, None] * (np.pi * wg)[None, :]).sum())


def _tilt_and_quadrature(ov, tx, ty, rng_m):
    """(quadrature, model, b/w) of the tilt O_p/O of the pixel t = (tx, ty) at ``rng_m``: the Gaussian beam (1/e²
    radius w at the depth z, centred at the offset d·(cos φ, sin φ) or at 0) over the pixel's view disc (radius b,
    centre z t), over the same for the on-axis pixel; and pixel_overlap's O_p/O."""
    from core.atmosphere.weather import pixel_overlap
    z = rng_m / math.sqrt(1 + tx * tx + ty * ty)
    w, b = ov.tx_radius_m + z * ov.tx_half_angle, ov.rx_radius_m + z * ov.rx_half_angle
    w0, b0 = ov.tx_radius_m + rng_m * ov.tx_half_angle, ov.rx_radius_m + rng_m * ov.rx_half_angle
    c = (z * tx, z * ty)
    d = (ov.offset_m * math.cos(ov.offset_angle_rad), ov.offset_m * math.sin(ov.offset_angle_rad))
    quad = (_gauss_over_disc(c, b, d, w) / _gauss_over_disc(c, b, (0, 0), w)
            / (_gauss_over_disc((0, 0), b0, d, w0) / _gauss_over_disc((0, 0), b0, (0, 0), w0)))
    return quad, float(pixel_overlap(ov, rng_m, tx, ty) / ov(rng_m)), b / w


def test_pixel_overlap_tilt_matches_a_quadrature_of_the_beam_over_the_pixels_view():
    """The per-pixel factor O_p/O against an independent quadrature: the Gaussian beam (1/e² radius
    w = r_t + z θ_t, centre at the offset d or at 0) integrated over the pixel's view (a disc of radius
    b = r_a + z θ_r at z t, z the depth of range R on the pixel's axis), with/without offset, over the same for the
    on-axis pixel.  The model replaces the disc by a Gaussian of equal variance, an error of second order in b/w:
    documented accuracy |ratio − 1| ≤ 0.2 (b/w)² for b/w ≤ 0.4 (measured ≤ 0.17 (b/w)²: 2 % at R = 0.5 m,
    6e-5 at 10 m), ≤ 0.3 at b/w ≈ 0.73 (R = 0.2 m here, measured 0.26)."""
    from core.atmosphere.weather import pixel_overlap
    ov = Overlap("geometric", 0.05, 0.01, 0.125, 0.025, 1.5e-3)
    strong = 0
    for tx, ty in [(0.1, 0.07), (-0.1, 0.0), (0.05, 0.02), (-0.03, -0.09), (0.0, 0.1), (0.1, -0.1)]:
        for rng_m in (0.2, 0.5, 1.0, 3.0, 10.0, 100.0):
            quad, t, b_w = _tilt_and_quadrature(ov, tx, ty, rng_m)
            bound = 0.2 * b_w ** 2 if b_w <= 0.4 else 0.3
            assert abs(quad / t - 1) <= bound, (tx, ty, rng_m, quad, t)
            strong += abs(math.log(t)) > 0.5
    assert strong >= 4  # the cases test a tilt far from 1
    assert float(pixel_overlap(ov, 1.0, 0.1, 0.0, beam_profile="uniform")) == float(ov(1.0))


def test_pixel_overlap_tilt_at_the_field_corners_within_the_documented_bound():
    """The corners of a ±0.1 field (|t| = 0.14), where the tilt away from the transmitter is strongest, against
    the same quadrature: |ratio − 1| ≤ 0.25 (b/w)² for b/w ≤ 0.4, ≤ 0.35 above (theory §14: measured 0.24 (b/w)²
    at R = 0.5 m, 0.334 at R = 0.2 m)."""
    ov = Overlap("geometric", 0.05, 0.01, 0.125, 0.025, 1.5e-3)
    for tx, ty in [(0.1, 0.1), (0.1, -0.1), (-0.1, 0.1), (-0.1, -0.1)]:
        for rng_m in (0.2, 0.5, 1.0, 3.0, 10.0):
            quad, t, b_w = _tilt_and_quadrature(ov, tx, ty, rng_m)
            bound = 0.25 * b_w ** 2 if b_w <= 0.4 else 0.35
            assert abs(quad / t - 1) <= bound, (tx, ty, rng_m, quad, t)


@pytest.mark.parametrize("angle_deg", [90.0, -135.0, 30.0, 180.0])
def test_pixel_overlap_follows_the_offset_direction(angle_deg):
    """atmosphere.tx_rx_offset_angle_deg turns the transmitter about the receiver's axis: the tilt O_p/O of a
    pixel against the quadrature of the Gaussian beam centred at d·(cos φ, sin φ) over the pixel's view (the same
    documented bound as along +x); turning both the offset and the pixel by φ gives the φ = 0 value (rotation,
    1e-12 relative); a pixel across the offset (t ⊥ u) sees the on-axis overlap (1e-12); the pixels on the
    transmitter's side see more than the mirrored ones."""
    from core.atmosphere.weather import pixel_overlap
    base = Overlap("geometric", 0.05, 0.01, 0.125, 0.025, 1.5e-3)
    phi = math.radians(angle_deg)
    ov = dataclasses.replace(base, offset_angle_rad=phi)
    u = (math.cos(phi), math.sin(phi))
    # the pixels of the +x test above turned by φ (the equal-variance step's error is the same there)
    for tx0, ty0 in [(0.1, 0.07), (-0.1, 0.0), (0.05, 0.02), (-0.03, -0.09), (0.0, 0.1), (0.1, -0.1)]:
        tx, ty = tx0 * u[0] - ty0 * u[1], tx0 * u[1] + ty0 * u[0]
        for rng_m in (0.2, 0.5, 1.0, 3.0, 10.0):
            quad, t, b_w = _tilt_and_quadrature(ov, tx, ty, rng_m)
            bound = 0.2 * b_w ** 2 if b_w <= 0.4 else 0.3
            assert abs(quad / t - 1) <= bound, (angle_deg, tx, ty, rng_m, quad, t)
            # the same pixel seen from the unturned offset: the pixel turned back by −φ
            assert float(pixel_overlap(ov, rng_m, tx, ty)) == pytest.approx(
                float(pixel_overlap(base, rng_m, tx0, ty0)), rel=1e-12)
        across = float(pixel_overlap(ov, 1.0, -0.08 * u[1], 0.08 * u[0]))
        assert across == pytest.approx(float(ov(1.0)), rel=1e-12)
    toward = float(pixel_overlap(ov, 1.0, 0.08 * u[0], 0.08 * u[1]))
    away = float(pixel_overlap(ov, 1.0, -0.08 * u[0], -0.08 * u[1]))
    assert toward > 1.5 * away  # a strong tilt: exp(8 z t d/(w² + b²)) ≈ 3 here
    assert np.array_equal(pixel_overlap(dataclasses.replace(base, offset_angle_rad=0.0), 2.0, 0.05, 0.03),
                          pixel_overlap(base, 2.0, 0.05, 0.03))


def test_flash_offset_direction_setting_turns_the_near_range_clutter():
    """A flash frame in fog with the transmitter above the receiver (tx_rx_offset_angle_deg = 90): the top
    pixels (+y) collect more near-range backscatter than the bottom ones, left and right alike (1e-3, the
    table's tolerance); at 0 the right side (+x) does; the setting is validated."""
    sums = {}
    for angle in (0.0, 90.0):
        cfg = _flash("fog", visibility_m=200.0, backscatter_min_range_m=0.05, tx_rx_offset_m=0.1,
                     tx_rx_offset_angle_deg=angle)
        wf = simulate_frame(plate(30.0, 0.06), np.eye(4), cfg).waveforms.astype(np.float64)
        near = wf[:, :, :150].sum(axis=2)  # 0–22.5 m, in front of the plate (the fog from ~6 m here)
        sums[angle] = {"top": near[0, 3:5].sum(), "bottom": near[7, 3:5].sum(),
                       "left": near[3:5, 0].sum(), "right": near[3:5, 7].sum()}
    up, flat = sums[90.0], sums[0.0]
    assert up["top"] > 1.05 * up["bottom"]
    assert up["left"] == pytest.approx(up["right"], rel=2e-3)
    assert flat["right"] > 1.05 * flat["left"]
    assert flat["top"] == pytest.approx(flat["bottom"], rel=2e-3)
    cfg = _flash("fog", visibility_m=200.0, tx_rx_offset_angle_deg=200.0)
    with pytest.raises(ConfigError, match="tx_rx_offset_angle_deg"):
        validate_config(cfg)


def _table_case():
    from core.geometry.rays import Detector
    from core.physics.weather_waveform import pixel_backscatter_templates
    det = Detector(64, 48, 1, 0.1, 0.075)
    laser = LaserSettings(pulse_fwhm_s=2e-9)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=200)
    ov = Overlap("geometric", 0.05, 0.01, float(np.hypot(0.1, 0.075)), 0.025, 0.075 / 48)

    def at(tx, ty):
        return pixel_backscatter_templates(laser, gate, 1.0, 1e-3, 0.02, ov, 0.05, tx, ty)
    return det, at


def test_template_table_interpolation_error_is_within_its_tolerance_at_every_pixel():
    """The field-angle table (nodes refined until the cell-centre check passes) against every pixel's exact
    template: relative L1 ≤ the tolerance (1e-3) at all 3072 pixels, with fewer templates computed than pixels;
    the pixels on the transmitter's side (+x) see more near-range backscatter than the mirrored ones."""
    from core.engine.weather_stage import TEMPLATE_TABLE_TOLERANCE, build_template_table
    det, at = _table_case()
    table = build_template_table(det, at)
    cols, rows = np.meshgrid(np.arange(det.width_px), np.arange(det.height_px))
    tx, ty = det.pixel_center_tan(cols.ravel(), rows.ravel())
    exact = at(tx, ty)
    approx = table.rows_of(0, det.n_pixels)
    err = np.abs(approx - exact).sum(axis=1) / np.abs(exact).sum(axis=1)
    assert err.max() <= TEMPLATE_TABLE_TOLERANCE
    assert table.n_computed < det.n_pixels
    spread = np.abs(exact - exact.mean(axis=0)).sum(axis=1) / np.abs(exact).sum(axis=1)
    assert spread.max() > 10 * TEMPLATE_TABLE_TOLERANCE  # the pixels do differ: the table is not trivial
    near = slice(0, 10)  # 0–1.5 m
    right, left = exact.reshape(48, 64, -1)[24, 60, near].sum(), exact.reshape(48, 64, -1)[24, 3, near].sum()
    assert right > 1.05 * left


def test_flash_geometric_overlap_gives_each_pixel_its_own_template():
    """Fog, geometric overlap, 8×8 px flash: a pixel whose rays all miss the plate gets F_p × its own (tabulated)
    template (float32 cube: 1e-6); the corner pixels' templates differ from the on-axis one; the frame records
    the table.  Drops of a rain frame use their pixel's overlap (the frame runs)."""
    cfg = _flash("fog", visibility_m=200.0, backscatter_min_range_m=0.05)
    cfg.atmosphere.tx_rx_offset_m = 0.1
    r = simulate_frame(plate(30.0, 0.06), np.eye(4), cfg)
    from core.engine.weather_stage import prepare_frame_weather
    from core.geometry.rays import Detector
    from core.physics.laser import beam_half_angle_tan, cell_energy_fractions
    det = Detector.from_settings(cfg.receiver)
    px, py = det.pixel_pitch_tan
    wx = prepare_frame_weather(cfg, 0, det.n_pixels, px * py, beam_half_angle_tan(cfg.laser, det),
                               0.5 * min(px, py), detector=det)
    assert wx.table is not None and r.stats["weather"] is not None
    fx, fy = cell_energy_fractions(cfg.laser, det)
    s = det.subsamples
    f_pix = np.add.reduceat(fy, np.arange(0, len(fy), s))[:, None] * np.add.reduceat(fx, np.arange(0, len(fx), s))
    for p in (0, 7, 56, 63):
        tpl = wx.templates_of(p, p + 1)[0]
        got = r.waveforms[p // 8, p % 8].astype(np.float64)
        assert np.allclose(got, f_pix[p // 8, p % 8] * tpl, rtol=1e-6, atol=1e-6 * tpl.max())
    corner = wx.templates_of(0, 1)[0]
    assert np.abs(corner - wx.template).sum() > 0.01 * wx.template.sum()  # the pixels' own overlap matters here
    rain = _flash("rain", rain_rate_mm_h=25.0, drop_min_diameter_mm=2.0)
    assert simulate_frame(plate(30.0, 0.06), np.eye(4), rain).waveforms.shape[:2] == (8, 8)


def test_gated_geometric_overlap_gives_each_pixel_its_own_slices():
    """Gated viewing in fog with the geometric overlap (offset 10 cm, slices from 0 m): a pixel with no surface
    collects F_p × its own slab table's last row (pixel_gated_slab_tables at its field angle) within the table's
    1e-3 (relative L1 over the slices; float32 slices); the corner pixels on the +x and −x sides differ; the
    on-axis case is the existing one (overlap none: test above)."""
    from core.systems.gated import gate_response, simulate_gated
    from core.physics.laser import beam_half_angle_tan, cell_energy_fractions
    from core.geometry.rays import Detector
    from core.physics.weather_waveform import pixel_gated_slab_tables
    from core.engine.weather_stage import TEMPLATE_TABLE_TOLERANCE, prepare_frame_weather
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px = cfg.receiver.height_px = 8
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.2
    cfg.laser.pulse_fwhm_s = 2e-9
    g = cfg.gated
    g.gate_width_s, g.delay_step_s, g.n_slices, g.first_delay_s = 4e-9, 2e-9, 30, 0.0
    cfg.atmosphere = dataclasses.replace(cfg.atmosphere, weather="fog", visibility_m=200.0, tx_rx_offset_m=0.1,
                                         backscatter_min_range_m=0.05)
    cfg.run.threads = 1
    r = simulate_gated(plate(40.0, 2.0), np.eye(4), cfg)  # the centre pixels see it, the corners do not
    assert r.stats["weather"]["overlap"]["per_pixel"]["templates_computed"] > 1
    det = Detector.from_settings(cfg.receiver)
    fx, fy = cell_energy_fractions(cfg.laser, det)
    s = det.subsamples
    px, py = det.pixel_pitch_tan
    wx = prepare_frame_weather(cfg, 0, det.n_pixels, px * py, beam_half_angle_tan(cfg.laser, det), 0.5 * min(px, py))
    delays = g.first_delay_s + g.delay_step_s * np.arange(g.n_slices)
    sims = {}
    for col, row in ((0, 0), (7, 0), (0, 7), (7, 7)):
        tx, ty = det.pixel_center_tan(col, row)
        tab = pixel_gated_slab_tables(cfg.laser, delays, g.gate_width_s, g.shutter_edge_s, wx.scale_jm2,
                                      wx.weather.backscatter_per_m_sr, wx.alpha_per_m, wx.overlap,
                                      cfg.atmosphere.backscatter_min_range_m,
                                      lambda tau: gate_response(cfg.laser, g.gate_width_s, g.shutter_edge_s, tau),
                                      [tx], [ty])[0].reshape(-1, g.n_slices)
        f_p = fx[col * s:(col + 1) * s].sum() * fy[row * s:(row + 1) * s].sum()
        ref = f_p * tab[-1]
        sim = r.slices[:, row, col].astype(np.float64)
        assert np.abs(sim - ref).sum() <= TEMPLATE_TABLE_TOLERANCE * ref.sum() + 1e-6 * ref.sum()
        sims[(col, row)] = sim.sum() / f_p
    assert sims[(7, 0)] > 1.05 * sims[(0, 0)]  # +x: the transmitter's side sees more near-range fog


def test_template_table_beyond_the_memory_limit_is_refused_naming_the_setting():
    """A table that would hold more than max_bytes of templates: ConfigError naming atmosphere.overlap_model."""
    from core.engine.weather_stage import build_template_table
    det, at = _table_case()
    with pytest.raises(ConfigError, match="atmosphere.overlap_model"):
        build_template_table(det, at, max_bytes=20 * 8 * 200)  # 20 templates of 200 bins: the first level is 13
