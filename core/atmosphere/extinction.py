"""Aerosol extinction and the two-way transmission of the laser radar equation (paper §3.4 C, eq. 3-1).

docs/theory.md §6 (Kruse / Kim visibility models) and §13 (carry the link budget in log form).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Koschmieder constant for a 2 % contrast threshold: β_550 = 3.912 / V.
KOSCHMIEDER_2PCT = 3.912
_REF_WAVELENGTH_M = 550e-9

EXTINCTION_MODELS = ("kim", "kruse")


def visibility_size_exponent(visibility_m, model="kim"):
    """Wavelength exponent q(V) of the Kruse or Kim model (docs/theory.md §6).

    Kruse: q = 1.6 (V > 50 km), 1.3 (6 < V ≤ 50 km), 0.585 V^(1/3) (V ≤ 6 km, V in km).
    Kim:   same above 6 km; 0.16 V + 0.34 (1 < V ≤ 6 km); V − 0.5 (0.5 < V ≤ 1 km); 0 (V ≤ 0.5 km).
    """
    v_km = np.asarray(visibility_m, dtype=np.float64) / 1e3
    if model == "kruse":
        low = 0.585 * np.cbrt(v_km)
    elif model == "kim":
        low = np.select([v_km > 1.0, v_km > 0.5], [0.16 * v_km + 0.34, v_km - 0.5], 0.0)
    else:
        raise ValueError(f"model must be one of {EXTINCTION_MODELS}, got {model!r}")
    return np.select([v_km > 50.0, v_km > 6.0], [1.6, 1.3], low)


def extinction_from_visibility(visibility_m, wavelength_m, model="kim"):
    """One-way aerosol extinction coefficient σ_atm [1/m] from the visibility (docs/theory.md §6).

    β = (3.912 / V) (λ / 550 nm)^(−q(V)), V the 2 %-contrast meteorological visibility.  Vectorised over
    ``visibility_m`` and ``wavelength_m`` (broadcast).  Valid for haze and fog (V ≳ 0.2 km, docs/theory.md §13);
    it models aerosol scattering only (no molecular absorption lines, no rain/snow).  V ≤ 0 raises.
    """
    v = np.asarray(visibility_m, dtype=np.float64)
    lam = np.asarray(wavelength_m, dtype=np.float64)
    if np.any(~(v > 0.0)) or np.any(~np.isfinite(v)):
        raise ValueError("visibility_m must be finite and > 0")
    if np.any(~(lam > 0.0)):
        raise ValueError("wavelength_m must be > 0")
    q = visibility_size_exponent(v, model)
    return (KOSCHMIEDER_2PCT / v) * (lam / _REF_WAVELENGTH_M) ** (-q)


@dataclass(frozen=True)
class LayeredExtinction:
    """A range-layered aerosol (``atmosphere.aerosol_layers``, docs/theory.md §14 "Layers"): the extinction
    σ(R) = σ₀ + Σ_i α_i 1[s_i ≤ R < e_i] along every ray, R the range from the sensor (layers are shells of range,
    not of altitude), so the optical depth to R is τ(R) = σ₀ R + Σ_i α_i clip(R − s_i, 0, e_i − s_i) and the
    two-way transmission exp(−2τ(R)).  ``base_per_m`` = σ₀ (the homogeneous extinction of the settings, the
    weather's included); the layers hold tuples (start_m, end_m, extinction_per_m), in increasing range."""

    base_per_m: float
    start_m: tuple
    end_m: tuple
    extinction_per_m: tuple

    def layer_depth(self, range_m):
        """Σ_i α_i clip(R − s_i, 0, e_i − s_i): the layers' share of the optical depth to each range."""
        r = np.asarray(range_m, dtype=np.float64)
        out = np.zeros(r.shape)
        for s, e, a in zip(self.start_m, self.end_m, self.extinction_per_m):
            if a != 0.0:
                out += a * np.clip(r - s, 0.0, e - s)
        return out

    def optical_depth(self, range_m):
        """τ(R) = σ₀ R + :meth:`layer_depth`."""
        r = np.asarray(range_m, dtype=np.float64)
        return self.base_per_m * r + self.layer_depth(r)

    def record(self) -> dict:
        return {"base_per_m": self.base_per_m,
                "layers": [[s, e, a] for s, e, a in zip(self.start_m, self.end_m, self.extinction_per_m)]}


def log_two_way_transmission(extinction_per_m, range_m):
    """ln T² = −2 σ_atm R: log of the two-way aerial transmission of eq. 3-1 (docs/theory.md §6, §13).

    Kept in log form so that long ranges in thick fog never underflow (exp(−2σR) is 0 in float64 below
    e^(−745)); the result is exactly ``-2.0 * sigma * R`` in float64.  Add it to the other log factors of
    the radar equation and exponentiate once at the end.  A :class:`LayeredExtinction`: −2τ(R).
    """
    if isinstance(extinction_per_m, LayeredExtinction):
        return -2.0 * extinction_per_m.optical_depth(range_m)
    sigma = np.asarray(extinction_per_m, dtype=np.float64)
    r = np.asarray(range_m, dtype=np.float64)
    return -2.0 * sigma * r


def two_way_transmission(extinction_per_m, range_m):
    """T² = exp(−2 σ_atm R) (docs/theory.md §6; a :class:`LayeredExtinction`: exp(−2τ(R))).  May underflow to 0 —
    prefer :func:`log_two_way_transmission`."""
    return np.exp(log_two_way_transmission(extinction_per_m, range_m))
