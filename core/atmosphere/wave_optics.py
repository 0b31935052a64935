"""Point-receiver scintillation statistics tabulated from converged split-step wave optics (issue 17).

The formulas of the paper's model (docs/theory.md §2–3: the all-regime σ_lnI² of Andrews 1999, the eq. 3-6 cell
radius and a Gaussian covariance shape) are first-order theory plus heuristics; once turbulence is moderate
they are not what wave optics gives.  This module serves the statistics of our own split-step simulations
(:func:`core.atmosphere.phasescreen.split_step_intensity`, plane and spherical waves, modified von Kármán
spectrum with inner scale l0, L0 = ∞), run and cached by ``scripts/tabulate_scintillation.py`` and shipped as
``core/atmosphere/data/scintillation_wave_optics.npz``:

* axes: the wave (plane, spherical), the strength β0² = 0.5 Cn² k^(7/6) L^(11/6) (the spherical Rytov variance,
  for both waves), and the scaled inner scale l0/F, F = √(L/k) the Fresnel scale;
* values: the scintillation index SI = ⟨I²⟩/⟨I⟩² − 1, σ²_lnI = var(ln I), the normalised intensity
  covariance C(r) = B_I(r)/B_I(0) at lags r/F (0 … 8–10), and the SI of the intensity averaged over a disk of
  diameter D (D/F = 0.5, 1, 2, 4) as a check of the aperture-averaging integral.

Interpolation: ln SI, ln σ²_lnI and C are interpolated linearly in (ln β0², l0/F).  Below the smallest β0² the
first-order (Rytov) scaling holds: SI, σ²_lnI ∝ β0², C unchanged.  Above the largest β0² the table is
extrapolated (flagged ``"extrapolated"``): SI → 1 like the saturation law of strong-turbulence theory,
SI − 1 ∝ (β0²)^(−2/5), matched at the last point; C kept at its last shape.  C is tapered to 0 over
6–8 F (``TAPER_F``).  l0/F beyond the last column uses
the last column (flagged ``"inner_scale_clamped"``).  The outer scale is not an axis: the tabulation script
measures its effect (``outer`` part) and ``docs/atmosphere.md`` states it.
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
from scipy.special import polygamma

from . import turbulence as tb
from .phasescreen import one_over_e_radius_profile

TABLE_PATH = Path(__file__).resolve().parent / "data" / "scintillation_wave_optics.npz"
#: The covariance is tapered to 0 between these lags [units of F] (cos²): the split-step runs measure it to
#: box/3 = 8 F, and an abrupt end of C there puts a ring of negative spectral power into the pattern
#: generator's Gaussian fields (its clipping then cost up to 0.067 in the generated covariance; 0.012 with
#: the taper).  The tapered values are ≤ 0.017 in magnitude in every table point.
TAPER_F = (6.0, 8.0)
#: L0/F from which the outer scale changes the SI by < 1 % (split-step, paired runs at L0/F = 100: −0.3 … −0.8 %;
#: at L0/F = 20: −5 … −12 %); the table is for L0 = ∞.
OUTER_SCALE_NEGLIGIBLE_F = 100.0

#: Names of the scintillation statistics models (``atmosphere.scintillation_statistics``).
STATISTICS_MODELS = ("wave_optics", "paper")


@functools.lru_cache(maxsize=1)
def load_table(path: str | None = None) -> dict:
    """The shipped table as a dict of arrays (cached).  Covariance lags beyond a run's box are 0."""
    with np.load(path or TABLE_PATH) as z:
        t = {k: z[k] for k in z.files}
    t["covariance"] = np.nan_to_num(t["covariance"].astype(np.float64), nan=0.0)
    t["waves"] = [str(w) for w in t["waves"]]
    return t


def _bracket(axis, x):
    """Index j and weight w with x ≈ (1 − w) axis[j] + w axis[j+1], clamped to the axis."""
    axis = np.asarray(axis, dtype=np.float64)
    if x <= axis[0]:
        return 0, 0.0
    if x >= axis[-1]:
        return len(axis) - 2, 1.0
    j = int(np.searchsorted(axis, x) - 1)
    return j, float((x - axis[j]) / (axis[j + 1] - axis[j]))


def _bilinear(values, jb, wb, jl, wl):
    """values[..., l0 index, β index, ...] at the two brackets (l0 axis first, then β0²)."""
    v00, v01 = values[jl, jb], values[jl, jb + 1]
    v10, v11 = values[jl + 1, jb], values[jl + 1, jb + 1]
    return (1 - wl) * ((1 - wb) * v00 + wb * v01) + wl * ((1 - wb) * v10 + wb * v11)


def scaled_parameters(cn2_m_23, wavelength_m, range_m, inner_scale_m=0.0):
    """(β0², l0/F, F) of a path: the table's coordinates."""
    beta2 = float(tb.rytov_variance(cn2_m_23, wavelength_m, range_m, "spherical"))
    fresnel = float(tb.fresnel_scale(wavelength_m, range_m))
    return beta2, float(inner_scale_m) / fresnel, fresnel


def statistics(cn2_m_23, wavelength_m, range_m, wave="spherical", inner_scale_m=0.0, table=None):
    """Wave-optics point-receiver statistics of a path (module docstring).

    Returns a dict: ``scintillation_index``, ``sigma2_lnI``, ``lags_m`` and ``covariance`` (normalised,
    C(0) = 1), ``correlation_radius_m`` (1/e point of C), ``beta2``, ``l0_over_fresnel``, ``fresnel_scale_m``,
    ``extrapolated`` (β0² above the table), ``first_order_scaled`` (below it), ``inner_scale_clamped``.
    Cn² = 0 gives SI = 0 and C = 1 at lag 0.
    """
    if wave not in tb.WAVE_TYPES:
        raise ValueError(f"wave must be one of {tb.WAVE_TYPES}, got {wave!r}")
    t = load_table() if table is None else table
    beta2, l0f, fresnel = scaled_parameters(cn2_m_23, wavelength_m, range_m, inner_scale_m)
    lags_m = t["lags_over_f"] * fresnel
    w = t["waves"].index(wave)
    b_axis = np.log(t["beta2"])
    lb = math.log(beta2) if beta2 > 0 else -np.inf
    jb, wb = _bracket(b_axis, lb)
    jl, wl = _bracket(t["l0_over_f"], l0f)
    si = math.exp(_bilinear(np.log(t["scintillation_index"][w]), jb, wb, jl, wl))
    lnv = math.exp(_bilinear(np.log(t["sigma2_lnI"][w]), jb, wb, jl, wl))
    x = np.clip((t["lags_over_f"] - TAPER_F[0]) / (TAPER_F[1] - TAPER_F[0]), 0.0, 1.0)
    cov = _bilinear(t["covariance"][w], jb, wb, jl, wl) * np.cos(0.5 * np.pi * x) ** 2
    b_lo, b_hi = float(t["beta2"][0]), float(t["beta2"][-1])
    if beta2 < b_lo:
        si *= beta2 / b_lo
        lnv *= beta2 / b_lo
    elif beta2 > b_hi:
        if si > 1.0:      # σ²_lnI is kept at its last value (it saturates as well)
            si = 1.0 + (si - 1.0) * (b_hi / beta2) ** 0.4
    radius = one_over_e_radius_profile(lags_m, cov)
    return {"scintillation_index": si, "sigma2_lnI": lnv, "lags_m": lags_m, "covariance": cov,
            "correlation_radius_m": radius, "beta2": beta2, "l0_over_fresnel": l0f, "fresnel_scale_m": fresnel,
            "wave": wave, "extrapolated": bool(beta2 > b_hi), "first_order_scaled": bool(0 < beta2 < b_lo),
            "inner_scale_clamped": bool(l0f > float(t["l0_over_f"][-1]))}


def covariance_function(stats):
    """C(r) [r in m] of a :func:`statistics` result: linear interpolation, 0 beyond the tabulated lags."""
    lags, cov = stats["lags_m"], stats["covariance"]
    return lambda r: np.interp(np.asarray(r, dtype=np.float64), lags, cov, right=0.0)


# ----------------------------------------------------------------------------------------------------------
# Averaging over an aperture or a footprint (linear in the covariance: exact given C)
# ----------------------------------------------------------------------------------------------------------
def aperture_averaging_factor(stats, aperture_diameter_m, n_nodes=400):
    """A = SI(D)/SI(0) = (16/π) ∫₀¹ x [acos x − x√(1 − x²)] C(xD) dx for a circular aperture of diameter D
    (the disk's self-overlap weights the covariance; midpoint rule on ``n_nodes``)."""
    d = float(aperture_diameter_m)
    if d <= 0.0:
        return 1.0
    x = (np.arange(n_nodes) + 0.5) / n_nodes
    kern = x * (np.arccos(x) - x * np.sqrt(1.0 - x * x))
    return float(16.0 / math.pi * np.sum(kern * covariance_function(stats)(x * d)) / n_nodes)


def footprint_averaging_factor(stats, side_x_m, side_y_m, n_nodes=96):
    """Variance factor of the pattern averaged over a p_x × p_y rectangle:
    ∫∫ (1 − |x|/p_x)(1 − |y|/p_y) C(√(x² + y²)) dx dy / (p_x p_y) over |x| < p_x, |y| < p_y (midpoint rule)."""
    px, py = float(side_x_m), float(side_y_m)
    if px <= 0.0 and py <= 0.0:
        return 1.0
    c = covariance_function(stats)
    u = (np.arange(n_nodes) + 0.5) / n_nodes          # |x|/p_x on (0, 1); both signs by symmetry
    wx = 1.0 - u
    if px <= 0.0 or py <= 0.0:
        p = max(px, py)
        return float(2.0 * np.sum(wx * c(u * p)) / n_nodes)
    r = np.hypot(u[:, None] * px, u[None, :] * py)
    return float(4.0 * np.sum(wx[:, None] * wx[None, :] * c(r)) / n_nodes**2)


# ----------------------------------------------------------------------------------------------------------
# Gamma-gamma parameters matching SI and σ²_lnI
# ----------------------------------------------------------------------------------------------------------
def gamma_gamma_fit(scintillation_index, sigma2_lnI):
    """(α, β, matched) of the gamma-gamma law with SI = (1 + 1/α)(1 + 1/β) − 1 and, where the family allows
    it, var(ln I) = ψ₁(α) + ψ₁(β) = σ²_lnI (ψ₁ the trigamma function); α ≥ β (X the weaker, large-scale
    factor).  With SI fixed, var(ln I) runs from ≈ ψ₁(1/SI) (α → ∞; α is capped at 10⁴/t_max, t_max the
    α = β value of 1/α) to 2ψ₁(α = β); a target outside that range takes the nearer end (``matched`` False).
    SI = 0 gives α = β = ∞."""
    si = float(scintillation_index)
    if si <= 0.0:
        return math.inf, math.inf, True
    t_max = math.sqrt(1.0 + si) - 1.0

    def lnv(t):
        u = (1.0 + si) / (1.0 + t) - 1.0
        out = float(polygamma(1, 1.0 / u))
        return out + (float(polygamma(1, 1.0 / t)) if t > 0 else 0.0)

    t_min = 1e-4 * t_max                   # α ≤ 1e4/t_max: finite, and X ≈ 1 to 1e-4 of the SI
    v0, v1 = lnv(t_min), lnv(t_max)
    target = float(sigma2_lnI)
    lo, hi = min(v0, v1), max(v0, v1)
    if not lo <= target <= hi:
        t = t_min if abs(target - v0) <= abs(target - v1) else t_max
        matched = False
    else:
        from scipy.optimize import brentq  # here: scipy.optimize is 0.2 s of every run's start-up

        t = brentq(lambda x: lnv(x) - target, t_min, t_max, xtol=1e-14) if v0 != v1 else t_min
        matched = True
    u = (1.0 + si) / (1.0 + t) - 1.0
    return 1.0 / t, 1.0 / u, matched


def shared_factor_correlation(cov, scintillation_index, var_x, var_y):
    """b(r) with (1 + b·v_X)(1 + b·v_Y) − 1 = SI·C(r), the normalised covariance both factors X, Y of a product
    I = X·Y share (v_X, v_Y their variances: 1/α of a gamma, e^(σ²) − 1 of a log-normal) so that the product has
    the covariance SI·C (the positive root; b = C when one factor is constant)."""
    t, u = float(var_x), float(var_y)
    si = float(scintillation_index)

    def b(r):
        x = si * cov(r)
        if t * u == 0.0:
            return np.clip(x / (t + u), -1.0, 1.0)
        disc = np.maximum((t + u) ** 2 + 4.0 * t * u * x, 0.0)
        return np.clip((np.sqrt(disc) - (t + u)) / (2.0 * t * u), -1.0, 1.0)
    return b


def gamma_lognormal_fit(scintillation_index, sigma2_lnI):
    """(α, σ², matched) of the gamma × log-normal law I = X·Y (X unit-mean gamma of shape α, Y = e^(σg − σ²/2))
    with SI = (1 + 1/α) e^(σ²) − 1 and var(ln I) = ψ₁(α) + σ² = σ²_lnI.

    With SI fixed, var(ln I) rises monotonically from ln(1 + SI) (pure log-normal, α → ∞; capped at
    α = 10⁶/SI) to ψ₁(1/SI) (pure gamma, σ² = 0), a range that holds every wave-optics point of the table — the
    gamma-gamma law cannot: in strong turbulence wave optics has SI ≈ 2.7 with var(ln I) ≈ 2.3, below the
    gamma-gamma minimum 2ψ₁(α = β) ≈ 3.0 (fewer deep fades).  A target outside the range takes the nearer end
    (``matched`` False).  SI = 0 gives α = ∞, σ² = 0.
    """
    si = float(scintillation_index)
    if si <= 0.0:
        return math.inf, 0.0, True
    t_min, t_max = 1e-6 * si, si

    def lnv(t):
        return float(polygamma(1, 1.0 / t)) + math.log((1.0 + si) / (1.0 + t))

    target = float(sigma2_lnI)
    v0, v1 = lnv(t_min), lnv(t_max)
    if target <= v0:
        t, matched = t_min, target >= v0 * (1 - 1e-9)
    elif target >= v1:
        t, matched = t_max, target <= v1 * (1 + 1e-9)
    else:
        from scipy.optimize import brentq

        t, matched = brentq(lambda x: lnv(x) - target, t_min, t_max, xtol=1e-14 * si), True
    return 1.0 / t, math.log((1.0 + si) / (1.0 + t)), matched
