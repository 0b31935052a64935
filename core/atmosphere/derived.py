"""All derived turbulence quantities of one path for the run metadata (docs/theory.md §1–3; issue 17).

:func:`derived_turbulence` combines the formulas of :mod:`core.atmosphere.turbulence` (the paper's statistics)
with the split-step wave-optics table of :mod:`core.atmosphere.wave_optics` (the default statistics).  It lives
in its own module because the table module builds on the formulas' module.
"""
from __future__ import annotations

import math

import numpy as np

from . import wave_optics as wo
from .turbulence import (STRICT_RYTOV_LIMIT, WAVE_TYPES, WEAK_LIMIT, aperture_averaging_factor, cell_radius,
                         check_wave, coherence_radius, fresnel_scale, fried_parameter, gamma_gamma_parameters,
                         large_scale_radius, log_intensity_variance_terms, rytov_variance, turbulence_regime)


def _py(x):
    x = float(x)
    return x if math.isfinite(x) else None


def derived_turbulence(cn2_m_23, wavelength_m, range_m, *, wave="spherical", aperture_diameter_m=None,
                       lognormal_max_rytov=WEAK_LIMIT, statistics="wave_optics", inner_scale_m=0.0,
                       outer_scale_m=np.inf):
    """All derived turbulence quantities of one path, as a JSON-ready dict (scalars, and the small ``wave_optics``
    dict of the table coordinates).

    Keys (SI; an infinite value, e.g. ρ0 without turbulence, is reported as None):
    rytov_variance_plane (σ_R²), rytov_variance_spherical (β0²), rho0_plane_m, rho0_spherical_m,
    r0_plane_m, r0_spherical_m, fresnel_scale_m, cell_radius_m (eq. 3-6 with ρ0 of ``wave``),
    large_scale_radius_m, regime, wave, sigma2_lnI, sigma2_lnX, sigma2_lnY, scintillation_index,
    gamma_alpha, gamma_beta, pdf_model ("none", "lognormal", "gamma_gamma" or "gamma_lognormal"), rytov_strict
    (σ_R² ≤ 0.3), lognormal_sigma2 (wave optics),
    and aperture_averaging (when ``aperture_diameter_m`` is given); scintillation_statistics, inner_scale_m,
    outer_scale_m (None = ∞).

    ``statistics="paper"``: the formulas of :mod:`core.atmosphere.turbulence` (all-regime σ_lnI², eq. 3-6 cell radius, weak-turbulence
    aperture averaging), pdf model by ``lognormal_max_rytov``.  ``"wave_optics"`` (default): the point-receiver
    statistics of the split-step wave-optics table (:mod:`core.atmosphere.wave_optics`, with ``inner_scale_m``)
    replace sigma2_lnI, scintillation_index, cell_radius_m (the 1/e radius of the tabulated covariance) and
    aperture_averaging (the aperture integral of the tabulated covariance); pdf_model is "gamma_lognormal", the
    product of a gamma (shape gamma_alpha) and a log-normal (variance lognormal_sigma2 of its log) fitted to SI
    and σ²_lnI (the family that matches both in every regime; sigma2_lnX = ln(1 + 1/α), sigma2_lnY = σ²,
    gamma_beta None); ``wave_optics`` holds the table coordinates and flags, and
    ``paper_scintillation_index`` the formula's SI for comparison.  The outer scale is recorded (the table is
    for L0 = ∞; its measured effect on SI is < 1 % for L0 ≥ 100 F, and ``wave_optics`` flags
    ``outer_scale_effect_above_1_percent`` below that: docs/atmosphere.md).
    """
    check_wave(wave)
    if statistics not in ("wave_optics", "paper"):
        raise ValueError(f"statistics must be 'wave_optics' or 'paper', got {statistics!r}")
    s_pl = float(rytov_variance(cn2_m_23, wavelength_m, range_m, "plane"))
    s_sp = float(rytov_variance(cn2_m_23, wavelength_m, range_m, "spherical"))
    s_w = s_pl if wave == "plane" else s_sp
    rho0 = {w: float(coherence_radius(cn2_m_23, wavelength_m, range_m, w)) for w in WAVE_TYPES}
    r0 = {w: float(fried_parameter(cn2_m_23, wavelength_m, range_m, w)) for w in WAVE_TYPES}
    sx, sy = (float(v) for v in log_intensity_variance_terms(s_w, wave))
    a, b = (float(v) for v in gamma_gamma_parameters(s_w, wave))
    regime = turbulence_regime(s_pl)
    if s_pl <= 0.0:
        model = "none"
    elif s_pl < lognormal_max_rytov:
        model = "lognormal"
    else:
        model = "gamma_gamma"
    out = {
        "cn2_m_23": float(cn2_m_23), "wavelength_m": float(wavelength_m), "range_m": float(range_m),
        "wave": wave,
        "rytov_variance_plane": s_pl, "rytov_variance_spherical": s_sp,
        "rho0_plane_m": _py(rho0["plane"]), "rho0_spherical_m": _py(rho0["spherical"]),
        "r0_plane_m": _py(r0["plane"]), "r0_spherical_m": _py(r0["spherical"]),
        "fresnel_scale_m": float(fresnel_scale(wavelength_m, range_m)),
        "cell_radius_m": float(cell_radius(wavelength_m, range_m, rho0[wave])),
        "large_scale_radius_m": _py(large_scale_radius(wavelength_m, range_m, rho0[wave])),
        "regime": regime, "rytov_strict": bool(s_pl <= STRICT_RYTOV_LIMIT),
        "sigma2_lnX": sx, "sigma2_lnY": sy, "sigma2_lnI": sx + sy,
        "scintillation_index": float(np.expm1(sx + sy)),
        "gamma_alpha": _py(a), "gamma_beta": _py(b), "pdf_model": model,
    }
    out.update(scintillation_statistics=statistics, inner_scale_m=float(inner_scale_m),
               outer_scale_m=_py(outer_scale_m))
    if statistics == "wave_optics" and s_pl > 0.0:
        st = wo.statistics(cn2_m_23, wavelength_m, range_m, wave, inner_scale_m)
        ga, s2, matched = wo.gamma_lognormal_fit(st["scintillation_index"], st["sigma2_lnI"])
        out.update(paper_scintillation_index=out["scintillation_index"],
                   scintillation_index=st["scintillation_index"], sigma2_lnI=st["sigma2_lnI"],
                   sigma2_lnX=float(np.log1p(1.0 / ga)), sigma2_lnY=s2,
                   gamma_alpha=_py(ga), gamma_beta=None, lognormal_sigma2=s2,
                   cell_radius_m=st["correlation_radius_m"], pdf_model="gamma_lognormal",
                   wave_optics={"beta2": st["beta2"], "l0_over_fresnel": st["l0_over_fresnel"],
                                "extrapolated": st["extrapolated"], "first_order_scaled": st["first_order_scaled"],
                                "inner_scale_clamped": st["inner_scale_clamped"], "pdf_fit_matched": matched,
                                "outer_scale_over_fresnel": _py(outer_scale_m / st["fresnel_scale_m"]),
                                "outer_scale_effect_above_1_percent": bool(outer_scale_m / st["fresnel_scale_m"]
                                                                           < wo.OUTER_SCALE_NEGLIGIBLE_F),
                                "table": wo.TABLE_PATH.name})
        if aperture_diameter_m is not None:
            out["aperture_averaging"] = wo.aperture_averaging_factor(st, aperture_diameter_m)
    elif aperture_diameter_m is not None:
        out["aperture_averaging"] = float(aperture_averaging_factor(wavelength_m, range_m,
                                                                    aperture_diameter_m, wave))
    return out
