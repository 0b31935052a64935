"""Validation of the range-layered aerosol (``atmosphere.aerosol_layers``; docs/theory.md §14 W4).

``run(out_dir, quick)`` returns the checks and writes ``weather_layers_backscatter.png``: the volume-backscatter
waveform of two aerosol layers in clear air (overlap O = 1) against β(R) e^(−2τ(R))/R² (τ the layers' piecewise
optical depth) integrated over each bin by adaptive quadrature, and the waveform's sum against the piecewise closed
form (core.atmosphere.weather.layers_closed_form_integral).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

TITLE = "weather: aerosol layers"
INTRO = """Two aerosol layers in clear air (10–30 m α = 0.02 /m, 40–70 m α = 0.05 /m, β = α/18 sr), overlap O = 1,
5 ns pulse, 1 ns bins: every ray's transmission is e^(−2τ(R)), τ(R) = Σ α_i clip(R − s_i, 0, e_i − s_i), and the
backscatter β(R) e^(−2τ(R))/R² (docs/theory.md §14 W4).  The reference is the equation integrated over each bin
by adaptive quadrature (split at the layers' edges) and, for the sum, the closed form per layer."""

C = 299_792_458.0


def run(out_dir: Path, quick: bool) -> list[dict]:
    from core.atmosphere.extinction import LayeredExtinction
    from core.atmosphere.weather import Overlap, layer_backscatter, layers_closed_form_integral
    from core.config.settings import LaserSettings, RangeGateSettings
    from core.physics.weather_waveform import backscatter_template
    from validation import check
    from validation.weather import plot_waveform, reference_bins

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = np.array([[10.0, 30.0, 0.02, 0.02 / 18.0], [40.0, 70.0, 0.05, 0.05 / 18.0]])
    ext = LayeredExtinction(0.0, tuple(rows[:, 0]), tuple(rows[:, 1]), tuple(rows[:, 2]))
    beta_of, edges = layer_backscatter(rows), np.unique(rows[:, :2])
    laser = LaserSettings(pulse_fwhm_s=5e-9)
    gate = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=400 if quick else 667)  # 0–60 / 0–100 m
    sim = backscatter_template(laser, gate, 1.0, 0.0, ext, Overlap("none"), 1.0, profile=beta_of, breaks_m=edges)
    ref = reference_bins(laser, gate, lambda r: float(beta_of(r)), lambda r: float(ext.optical_depth(r)), 1.0,
                         tuple(edges))
    l2 = float(np.linalg.norm(sim - ref) / np.linalg.norm(ref))
    checks = [check("two aerosol layers, backscatter waveform, relative L2 error over the gate (O = 1)", l2, 0.0,
                    1e-2, kind="max")]
    whole = RangeGateSettings(gate_start_s=0.0, bin_width_s=1e-9, n_bins=600)  # 0–90 m: both layers whole
    total = backscatter_template(laser, whole, 1.0, 0.0, ext, Overlap("none"), 1.0, profile=beta_of,
                                 breaks_m=edges).sum()
    exact = layers_closed_form_integral(rows)
    checks.append(check("two aerosol layers, Σ bins vs Σ β_i e^(−2(τ(s_i) − α_i s_i)) ∫ e^(−2α_i R)/R² dR "
                        "(piecewise closed form)", total, exact, 1e-6))
    plot_waveform(out_dir / "weather_layers_backscatter.png", gate, sim, ref, l2,
                  "Two aerosol layers (10–30 m α = 0.02, 40–70 m α = 0.05 /m, S = 18 sr), O = 1, 5 ns pulse",
                  floor=1e-6)
    return checks


if __name__ == "__main__":
    for c in run(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("validation_weather_layers"), quick=True):
        print(c)
