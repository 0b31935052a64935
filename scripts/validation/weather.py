"""Validation of the weather model (issue 30; core/atmosphere/weather.py, docs/theory.md §14).

``run(out_dir, quick)`` returns checks {"quantity", "simulated", "reference", "tolerance", "passed"} and writes
``weather_fog_backscatter.png``: the simulated volume-backscatter waveform of a homogeneous fog (overlap O = 1)
against the single-scattering lidar equation integrated over each bin by adaptive quadrature (the range-layered
case: weather_layers.py).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

C = 299_792_458.0


def reference_bins(laser, gate, beta_of, tau_of, r_min, breaks=()):
    """Each bin of ∫ β(R) e^(−2τ(R))/R² [P(t_{k+1} − 2R/c) − P(t_k − 2R/c)] dR by adaptive quadrature (split at
    ``breaks``, where β jumps); ``beta_of``, ``tau_of``: callables of the range (homogeneous: β, αR)."""
    from scipy import integrate
    from core.physics.laser import pulse_cdf
    c2 = 0.5 * C
    tk = gate.gate_start_s + np.arange(gate.n_bins + 1) * gate.bin_width_s
    half = 8 * laser.pulse_fwhm_s
    out = np.empty(gate.n_bins)
    for k in range(gate.n_bins):
        def f(r):
            return beta_of(r) * math.exp(-2 * tau_of(r)) / r ** 2 * (pulse_cdf(laser, tk[k + 1] - r / c2)
                                                                    - pulse_cdf(laser, tk[k] - r / c2))
        lo, hi = max(r_min, c2 * (tk[k] - half)), c2 * (tk[k + 1] + half)
        pts = [b for b in breaks if lo < b < hi]
        out[k] = integrate.quad(f, lo, hi, points=pts or None, epsabs=1e-20 if pts or breaks else 0,
                                epsrel=1e-11, limit=400 if breaks else 200)[0]
    return out


def _check(quantity, simulated, reference, tolerance, passed):
    return {"quantity": quantity, "simulated": float(simulated), "reference": float(reference),
            "tolerance": float(tolerance), "passed": bool(passed)}


def run(out_dir: Path, quick: bool) -> list[dict]:
    from scipy import stats
    from core.atmosphere.extinction import extinction_from_visibility
    from core.atmosphere.weather import (Overlap, Weather, closed_form_integral, draw_drops,
                                         expected_drop_count, rain_extinction_per_m, size_distribution)
    from core.config.settings import LaserSettings, RangeGateSettings
    from core.physics.weather_waveform import backscatter_template

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    checks = []
    # 1. fog of 200 m visibility at 1064 nm, S = 18 sr, O = 1, gate 10-70 m (1 ns bins), 5 ns pulse
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    n_bins = 200 if quick else 400
    gate = RangeGateSettings(gate_start_s=2 * 10.0 / C, bin_width_s=1e-9, n_bins=n_bins)
    alpha = float(extinction_from_visibility(200.0, 1.064e-6, "kim"))
    beta, r_min = alpha / 18.0, 3.0
    sim = backscatter_template(laser, gate, 1.0, beta, alpha, Overlap("none"), r_min)
    ref = reference_bins(laser, gate, lambda r: beta, lambda r: alpha * r, r_min)
    l2 = float(np.linalg.norm(sim - ref) / np.linalg.norm(ref))
    checks.append(_check("fog backscatter waveform, relative L2 error over the gate (V = 200 m, O = 1)", l2, 0.0,
                         1e-2, l2 < 1e-2))
    # 2. the integral against the closed form (gate from 0 to 600 m: every slab's pulse inside)
    gate2 = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=4000)
    total = backscatter_template(laser, gate2, 1.0, beta, alpha, Overlap("none"), r_min).sum()
    exact = beta * closed_form_integral(r_min, 0.5 * C * gate2.n_bins * gate2.bin_width_s, alpha)
    checks.append(_check("fog backscatter energy, Σ bins vs β·∫e^(−2αR)/R² dR (closed form, E1), J per J·m²",
                         total, exact, 1e-6 * exact, abs(total - exact) <= 1e-6 * exact))
    # 3. rain drops per pulse: the mean count and a chi-square test of the Poisson counts
    n0, lam = size_distribution("rain", 10.0)
    w = Weather("rain", 0.0, 0.0, 18.0, n0, lam, 1.0, n0 / lam * math.exp(-lam))
    omega = math.pi * 0.5e-3 ** 2
    mean = expected_drop_count(w, omega, 0.5, 80.0)
    n_pulses = 500 if quick else 4000
    drops = draw_drops(np.random.default_rng(2026), w, n_pulses, omega, 0.5, 80.0)
    counts = np.bincount(drops.beam, minlength=n_pulses)
    se = math.sqrt(mean / n_pulses)
    checks.append(_check("rain 10 mm/h, drops ≥ 1 mm per pulse (1 mrad beam, 0.5–80 m): mean count",
                         counts.mean(), mean, 4 * se, abs(counts.mean() - mean) <= 4 * se))
    lo = int(stats.poisson.ppf(5 / n_pulses, mean)) + 1
    hi = int(stats.poisson.isf(5 / n_pulses, mean)) - 1
    obs = np.array([np.sum(counts < lo)] + [np.sum(counts == j) for j in range(lo, hi + 1)] + [np.sum(counts > hi)])
    exp = np.array([stats.poisson.cdf(lo - 1, mean)] + list(stats.poisson.pmf(np.arange(lo, hi + 1), mean))
                   + [stats.poisson.sf(hi, mean)]) * n_pulses
    p = float(stats.chisquare(obs, exp).pvalue)
    checks.append(_check("rain drop counts per pulse: χ² p-value against Poisson (must exceed 0.001)", p, 1e-3,
                         0.0, p > 1e-3))
    r3 = (drops.range_m ** 3 - 0.5 ** 3) / (80.0 ** 3 - 0.5 ** 3)
    p_ks = float(stats.kstest(r3, "uniform").pvalue)
    checks.append(_check("rain drop ranges: KS p-value against uniform in volume (must exceed 0.001)", p_ks, 1e-3,
                         0.0, p_ks > 1e-3))
    a_db = rain_extinction_per_m(10.0) / (math.log(10) / 1e4)
    checks.append(_check("rain 10 mm/h extinction, dB/km (1.076 R^0.67)", a_db, 1.076 * 10 ** 0.67, 1e-9,
                         abs(a_db - 1.076 * 10 ** 0.67) < 1e-9))
    plot_waveform(out_dir / "weather_fog_backscatter.png", gate, sim, ref, l2,
                  "Fog backscatter, V = 200 m at 1064 nm, S = 18 sr, overlap O = 1, 5 ns pulse")
    return checks


def plot_waveform(path, gate, sim, ref, l2, title, floor=None):
    """The simulated waveform over the reference bins (log scale; ``floor``: the lowest value shown, relative to
    the peak)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    r = 0.5 * C * (gate.gate_start_s + (np.arange(gate.n_bins) + 0.5) * gate.bin_width_s)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ax.semilogy(r, ref, "k-", lw=2.5, alpha=0.5, label="single-scattering equation (bin integrals, quadrature)")
    ax.semilogy(r, sim, "C1--", lw=1.2, label=f"simulated waveform (relative L2 error {l2:.1e})")
    ax.set_title(title, fontsize=10)
    if floor is not None:  # the gaps between the layers: down to the pulse's tails, not to zero
        ax.set_ylim(floor * max(ref.max(), sim.max()), 2 * max(ref.max(), sim.max()))
    ax.set_xlabel("range (m)")
    ax.set_ylabel("energy per 1 ns bin (J per J·m² of E·η·A_r)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    for c in run(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("validation_weather"), quick=True):
        print(c)
