"""The tabulated pulse ⊛ box (``gate.binning = "table"``, core/physics/waveform.py ``BoxTable``) against the exact
binning, the reference: each return's bins within the table's error bound (derived from its row step, h = 1/N
bin), a coarse table measurably outside the fine table's bound, and a flash frame's products within it."""
import dataclasses

import numpy as np
import pytest

from core.config.settings import BRDFSettings, LaserSettings, RangeGateSettings
from core.physics import waveform as W
from core.physics.laser import GAUSS_BOX_FOLD, gaussian_box_terms, pulse_sigma_s, sorted_spreads

#: The exact method's own error per bin and unit energy (core/physics/laser.py: its tail tables are within
#: 5.3e-12, 3.9e-12 and 2.3e-12 of Φ(−m), g₁ and g; a bin is two CDFs, a box CDF two (e₁/a) or four (e₂/(ab))
#: table values): 2·5.3e-12, 4·3.9e-12·σ/a, 8·2.3e-12·σ²/(ab).
EXACT_PHI, EXACT_E1, EXACT_E2 = 5.3e-12, 3.9e-12, 2.3e-12


def returns(sigma_bins, n=4000, seed=1):
    """n returns in a 400-bin gate: a pulse of σ = ``sigma_bins`` bins, cells spanning random boxes (a tenth
    impulses, a ≥ b, many below the fold of 0.3σ): (laser, gate, times, spreads, kinds, a, b in s)."""
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    dt = pulse_sigma_s(laser) / sigma_bins
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=dt, n_bins=400)
    rng = np.random.default_rng(seed)
    t = rng.uniform(100, 300, n) * dt
    sig = pulse_sigma_s(laser)
    a = rng.uniform(0, 3, n) * sig * (rng.random(n) < 0.9)
    b = rng.uniform(0, 1, n) * a * (rng.random(n) < 0.8)
    sp = np.stack([a, b], axis=1)
    _, a_k, b_k, kind = gaussian_box_terms(laser, sorted_spreads(laser, sp))
    return laser, gate, t, sp, kind, a_k, b_k


def table_errors(sigma_bins, rows):
    """Per return: the largest |table − exact| over its bins, the bound for it (table + the exact method's own
    error), and the return's largest exact bin."""
    laser, gate, t, sp, kind, a, b = returns(sigma_bins)
    n = len(t)
    pix = np.arange(n)
    ref = W.accumulate_waveform_windows(pix, t, np.ones(n), n, laser, gate, "exact", spread_s=sp)
    tab = W._table_windows(pix, t, np.ones(n), n, laser, gate, sp, rows)
    assert np.array_equal(tab.start, ref.start) and np.array_equal(tab.length, ref.length)  # the same bins
    d_ref, d_tab = ref.dense(), tab.dense()
    sig = pulse_sigma_s(laser)
    ab = a / gate.bin_width_s, b / gate.bin_width_s
    delta_max = 2 * (GAUSS_BOX_FOLD * sig / gate.bin_width_s) ** 2 / 12  # σ_eff² − σ², both boxes folded
    eb = W.box_table(sig / gate.bin_width_s, rows).error_bound(delta_max)
    with np.errstate(divide="ignore"):
        bound = np.select([kind == 0, kind == 1],
                          [eb["impulse"] + 2 * EXACT_PHI, 2 * eb["box"] / ab[0] + 4 * EXACT_E1 * sig / a],
                          4 * eb["trapezoid"] / (ab[0] * ab[1]) + 8 * EXACT_E2 * sig ** 2 / (a * b))
    return np.abs(d_tab - d_ref).max(axis=1), bound, d_ref.max(axis=1), kind


@pytest.mark.parametrize("sigma_bins", [4.25, 1.0])
def test_table_is_within_its_bound_of_the_exact_binning(sigma_bins):
    err, bound, peak, kind = table_errors(sigma_bins, None)
    assert set(np.unique(kind)) == {0, 1, 2}
    assert np.all(err <= bound), (err / bound).max()
    # the documented figure: within 2e-8 of the return's largest bin
    assert np.max(err / peak) <= 2e-8


def test_a_coarse_table_is_outside_the_fine_tables_bound():
    """The comparison resolves the table's own error: with 4 rows a bin (h = 1/4) the impulses and trapezoids
    miss the default table's bound (16 rows a bin at σ = 4.25 bins), and the error falls as h⁴ (4 → 8 rows:
    ÷ 8 … 32, Hermite's 16)."""
    err4, _, _, kind = table_errors(4.25, 4)
    err8, _, _, _ = table_errors(4.25, 8)
    _, bound, _, _ = table_errors(4.25, None)
    assert W.box_table_rows(4.25) == 16
    for k in (0, 2):
        assert np.max(err4[kind == k] - bound[kind == k]) > 0, k
    trapezoid = kind == 2
    assert 8 <= err4[trapezoid].max() / err8[trapezoid].max() <= 32


def test_table_keeps_the_energy():
    """Each return's bins sum to its energy less the pulse's tails beyond its bins (< 2e-9 here), as the exact
    method's."""
    laser, gate, t, sp, kind, a, b = returns(4.25, n=500)
    n = len(t)
    for method in ("table", "exact"):
        win = W.accumulate_waveform_windows(np.arange(n), t, np.ones(n), n, laser, gate, method, spread_s=sp)
        assert np.abs(win.dense().sum(axis=1) - 1.0).max() < 2e-9, method


def test_flash_frame_table_against_exact():
    """A tilted plate (every kind of cell box) seen with both binnings: the cube within 2e-8 of its largest bin,
    the ranges within 1e-6 m, the metadata naming the binning that ran."""
    from core.systems.flash import simulate_frame

    from scenes import config_for, plate

    scene = plate(50.0, 3.0, BRDFSettings(reflectance=0.3), tilt_rad=1.0)
    cfg = config_for(50.0, pixels=16, subsamples=4, fov_rad=0.08, bins=256, bin_s=0.5e-9)
    cfg.run.save_waveforms = True
    res = {}
    for binning in ("table", "exact"):
        c = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, binning=binning))
        res[binning] = simulate_frame(scene, np.eye(4), c)
        assert res[binning].stats["waveform_binning"] == binning
    wt32, we32 = res["table"].waveforms, res["exact"].waveforms
    wt, we = wt32.astype(np.float64), we32.astype(np.float64)
    assert we.max() > 0
    # per bin: the bound per unit energy of the worst kind (folded boxes ≥ 0.3σ wide, products ≥ 0.09σ²) times
    # the pixel's energy, plus one float32 step of the cube's value (both cubes are rounded to float32)
    sig_b = pulse_sigma_s(cfg.laser) / cfg.gate.bin_width_s
    eb = W.box_table(sig_b).error_bound(2 * (GAUSS_BOX_FOLD * sig_b) ** 2 / 12)
    per_e = max(eb["impulse"] + 2 * EXACT_PHI, 2 * eb["box"] / (0.3 * sig_b) + 4 * EXACT_E1 / 0.3,
                4 * eb["trapezoid"] / (0.09 * sig_b ** 2) + 8 * EXACT_E2 / 0.09)
    allowed = per_e * we.sum(axis=2, keepdims=True) + np.spacing(np.maximum(np.abs(wt32), np.abs(we32)))
    assert np.all(np.abs(wt - we) <= allowed)
    assert np.abs(wt - we).max() <= 1e-7 * we.max()  # (the documented figure, float32 rounding included)
    rt, re = res["table"].range_image, res["exact"].range_image
    assert np.array_equal(np.isnan(rt), np.isnan(re)) and np.count_nonzero(~np.isnan(re)) > 100
    assert np.nanmax(np.abs(rt.astype(np.float64) - re)) <= 1e-6


def test_narrow_pulse_and_rectangular_pulse_stay_exact():
    laser, gate = LaserSettings(pulse_fwhm_s=1e-9), RangeGateSettings(bin_width_s=1e-9)
    assert W.flash_binning_method(laser, gate) == "exact"  # σ = 0.42 bin < TABLE_MIN_SIGMA_BINS
    assert W.flash_binning_method(LaserSettings(pulse_fwhm_s=5e-9), gate) == "table"
    assert W.flash_binning_method(LaserSettings(pulse_fwhm_s=5e-9, pulse_shape="rectangular"), gate) == "exact"
    assert W.flash_binning_method(LaserSettings(pulse_fwhm_s=5e-9),
                                  dataclasses.replace(gate, binning="exact")) == "exact"
    assert W.flash_binning_method(LaserSettings(pulse_fwhm_s=30e-9), gate) == "splat"


def test_trace_writes_each_hits_normal_bit_for_bit():
    """``SceneTracer.intersect(normals_out=…)``: the refinement's own read of each hit triangle's unit normal, the
    values the flash cell model looked up before (``unit_normal[prim]``), bit for bit."""
    from core.geometry.trace import SceneTracer

    from scenes import plate

    scene = plate(20.0, 2.0, tilt_rad=0.7)
    tracer = SceneTracer(scene)
    rng = np.random.default_rng(3)
    d = np.column_stack([rng.uniform(-0.15, 0.15, 500), rng.uniform(-0.15, 0.15, 500), -np.ones(500)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    normals = np.full((500, 3), np.nan)
    prim, range_m, cos_theta = tracer.intersect(np.zeros(3), d, normals_out=normals)
    prim0, range0, cos0 = tracer.intersect(np.zeros(3), d)
    hit = prim >= 0
    assert 50 < hit.sum() < 500
    assert np.array_equal(prim, prim0) and np.array_equal(range_m, range0, equal_nan=True)
    assert np.array_equal(cos_theta, cos0)
    assert np.array_equal(normals[hit], tracer.unit_normal[prim[hit]]) and np.isnan(normals[~hit]).all()
    with pytest.raises(ValueError, match="normals_out"):
        tracer.intersect(np.zeros(3), d, normals_out=np.empty((3, 3)))
