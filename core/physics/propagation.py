"""Propagation physics of a frame's atmosphere (paper §3.4; docs/theory.md §3, §6, §11): the extinction coefficient
from the settings, the return-path scintillation variance and its factors per pixel, the box-average variance
factor and the footprint-averaged scintillation pattern.  :mod:`core.engine.atmosphere_stage` wires them into a
frame (effects A–E, reference range, random streams).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy.special import erf

from ..atmosphere import (extinction_from_visibility, gamma_factor_g_correlation, gaussian_random_field,
                          unit_gamma_from_gaussian)
from ..atmosphere import wave_optics as wo
from ..atmosphere.extinction import LayeredExtinction
from ..atmosphere.weather import rain_extinction_per_m, snow_extinction_per_m
from ..config.settings import SimulationConfig
from ..config.tables import aerosol_layer_table
from ..threads import map_list


def aerosol_extinction_per_m(config: SimulationConfig) -> float:
    """σ_atm (1/m) of the aerosol: from the visibility when it is set (docs/theory.md §6), else the given
    coefficient."""
    atm = config.atmosphere
    if atm.visibility_m > 0.0:
        return float(extinction_from_visibility(atm.visibility_m, config.laser.wavelength_m, atm.visibility_model))
    return atm.extinction_per_m


def effective_extinction_per_m(config: SimulationConfig) -> float:
    """σ_atm (1/m): the aerosol's (:func:`aerosol_extinction_per_m`) plus, for atmosphere.weather = rain or snow,
    the precipitation's (core/atmosphere/weather.py); exactly the aerosol's for every other weather."""
    sigma = aerosol_extinction_per_m(config)
    atm = config.atmosphere
    if atm.weather in ("rain", "snow") and atm.rain_rate_mm_h > 0.0:
        sigma += float(rain_extinction_per_m(atm.rain_rate_mm_h) if atm.weather == "rain"
                       else snow_extinction_per_m(atm.rain_rate_mm_h, config.laser.wavelength_m))
    return sigma


def path_extinction(config: SimulationConfig):
    """The extinction along every ray: :func:`effective_extinction_per_m` (a float: homogeneous, as before) or,
    with ``atmosphere.aerosol_layers``, a :class:`~core.atmosphere.extinction.LayeredExtinction` of it and the
    layers (two-way transmission exp(−2τ(R)): core.atmosphere.extinction.two_way_transmission)."""
    return with_aerosol_layers(effective_extinction_per_m(config), config.atmosphere)


def with_aerosol_layers(sigma: float, atmosphere):
    """``sigma`` (a homogeneous extinction, 1/m) as it is, or with ``atmosphere.aerosol_layers`` a
    :class:`~core.atmosphere.extinction.LayeredExtinction` of it and the layers."""
    table = aerosol_layer_table(atmosphere)
    if table is None:
        return sigma
    return LayeredExtinction(sigma, tuple(table[:, 0].tolist()), tuple(table[:, 1].tolist()),
                             tuple(table[:, 2].tolist()))


def extinction_record(extinction) -> dict:
    """The metadata of :func:`path_extinction`: ``extinction_per_m`` (the homogeneous σ) and, layered,
    ``aerosol_layers`` ([start_m, end_m, α] rows)."""
    if isinstance(extinction, LayeredExtinction):
        return {"extinction_per_m": extinction.base_per_m, "aerosol_layers": extinction.record()["layers"]}
    return {"extinction_per_m": extinction}


def return_scintillation_variance(derived: dict, pixel_footprint_m) -> dict:
    """Variance of the return-path factor of one pixel (B', core.engine.atmosphere_stage; docs/theory.md §3):
    A_sp(D) · SI_sp · g(p_x/ρ_l) · g(p_y/ρ_l).  ``derived`` from :func:`derived_turbulence` (spherical wave, with
    ``aperture_diameter_m``); ``pixel_footprint_m`` (p_x, p_y) at the reference range.  Case A of docs/theory.md
    (Cn² 1e-14, 1064 nm, 2 km, D = 5 cm): A_sp = 0.5741, SI_sp = 0.4373 → 0.2511 × g_x g_y."""
    a = float(derived["aperture_averaging"])
    si = float(derived["scintillation_index"])
    rho = float(derived["cell_radius_m"])
    g = footprint_variance_factor(derived, pixel_footprint_m[0], pixel_footprint_m[1])
    return {"aperture_averaging_factor": a, "point_scintillation_index": si, "cell_radius_m": rho,
            "pixel_footprint_m": [float(pixel_footprint_m[0]), float(pixel_footprint_m[1])],
            "footprint_averaging_factor": g, "variance": a * si * g,
            "statistics": derived.get("scintillation_statistics", "paper")}


def turbulence_model_settings(config: SimulationConfig) -> dict:
    """The scintillation-statistics keywords of :func:`derived_turbulence` from the atmosphere settings."""
    atm = config.atmosphere
    return {"statistics": atm.scintillation_statistics, "inner_scale_m": atm.inner_scale_m,
            "outer_scale_m": atm.outer_scale_m if atm.outer_scale_m > 0.0 else np.inf}


def footprint_variance_factor(derived: dict, side_x_m, side_y_m) -> float:
    """Variance factor of the point-receiver scintillation averaged over a p_x × p_y footprint.

    ``paper`` statistics: g(p_x/ρ_l) g(p_y/ρ_l) of a Gaussian covariance (:func:`box_average_variance_factor`);
    ``wave_optics``: the rectangle average of the tabulated wave-optics covariance
    (:func:`core.atmosphere.wave_optics.footprint_averaging_factor`)."""
    if derived.get("scintillation_statistics", "paper") == "wave_optics":
        st = wo.statistics(derived["cn2_m_23"], derived["wavelength_m"], derived["range_m"], derived["wave"],
                           derived["inner_scale_m"])
        return wo.footprint_averaging_factor(st, side_x_m, side_y_m)
    rho = float(derived["cell_radius_m"])
    return float(box_average_variance_factor(side_x_m, rho) * box_average_variance_factor(side_y_m, rho))


def draw_return_factor(shape, pixel_footprint_m, variance_info: dict, rng, max_grid_px: int = 2048):
    """Unit-mean gamma factors (H, W) with the variance of :func:`return_scintillation_variance` (exact
    marginal).  Pixels closer than ~2 cell radii are correlated: a gamma translation field (docs/theory.md §11) with
    Gaussian correlation of 1/e radius ρ_l on the pixel grid (periodic grid of ≥ 8 ρ_l, at most ``max_grid_px``);
    farther apart, independent draws.  Returns (values, model)."""
    var = variance_info["variance"]
    if not var > 0:
        return np.ones(shape), "none"
    alpha = 1.0 / var
    rho = variance_info["cell_radius_m"]
    px, py = variance_info["pixel_footprint_m"]
    if min(px, py) >= 2.0 * rho:
        return rng.gamma(alpha, var, size=shape), "gamma_independent_pixels"
    pitch = float(np.sqrt(px * py))  # isotropic grid (square pixels; the geometric mean otherwise)
    n_min = int(np.ceil(8 * rho / pitch))
    grid = (min(max(shape[0], n_min), max(shape[0], max_grid_px)), min(max(shape[1], n_min), max(shape[1], max_grid_px)))
    g = gaussian_random_field(grid, pitch, gamma_factor_g_correlation(alpha, rho), rng)
    return unit_gamma_from_gaussian(g[:shape[0], :shape[1]], alpha), "gamma_correlated_field"


def box_average_variance_factor(side_m, radius_m):
    """Variance factor of a field with Gaussian correlation exp(−r²/ρ²) averaged along a segment of length p:
    (ρ/p)² [√π (p/ρ) erf(p/ρ) + exp(−(p/ρ)²) − 1]  (→ 1 for p ≪ ρ, → √π ρ/p for p ≫ ρ)."""
    a = np.asarray(side_m, dtype=np.float64) / radius_m
    return (np.sqrt(np.pi) * a * erf(a) + np.exp(-a * a) - 1.0) / (a * a)


#: Row bands of :class:`FootprintAveragedPattern`, each drawn from its own stream (a fixed number: the values do
#: not depend on the thread count).
PATTERN_BANDS = 8


@dataclass
class FootprintAveragedPattern:
    """Scintillation seen by sub-rays whose footprint is larger than a scintillation cell.

    Each sub-ray collects the pattern averaged over its footprint (p_x × p_y at R_ref): unit mean, variance
    SI · g(p_x/ρ_l) · g(p_y/ρ_l) (:func:`box_average_variance_factor`), nearly independent between sub-rays
    (p > ρ_l).  A sum of many cells has gamma statistics (docs/theory.md §11), so one gamma value of that mean and
    variance is drawn per sub-ray cell of the whole frame: in PATTERN_BANDS bands of rows, each from its own
    child stream of the frame's seed sequence, on ``threads`` threads (NumPy's gamma sampler releases the GIL):
    independent of blocks and threads.
    """

    values: np.ndarray  # (H·S, W·S) indexed by [sub_y, sub_x]
    params: dict

    @classmethod
    def draw(cls, det, sub_pitch_m, derived, seed_seq: np.random.SeedSequence, threads: int = 1):
        si = derived["scintillation_index"]
        rho = derived["cell_radius_m"]
        var = float(si * footprint_variance_factor(derived, sub_pitch_m[0], sub_pitch_m[1]))
        shape = (det.height_px * det.subsamples, det.width_px * det.subsamples)
        if var > 0:  # every row is drawn by one of the bands (no ones written first: 2 MB of page faults)
            values = np.empty(shape)
            bands = [b for b in np.array_split(np.arange(shape[0]), PATTERN_BANDS) if b.size]

            def band(k):
                child = np.random.SeedSequence(seed_seq.entropy, spawn_key=tuple(seed_seq.spawn_key) + (k,))
                band_values = values[bands[k][0]:bands[k][-1] + 1]
                # Gamma(1/var, scale var): NumPy's gamma is scale × standard_gamma, drawn in place (no temporary)
                np.random.default_rng(child).standard_gamma(1.0 / var, out=band_values)
                band_values *= var

            map_list(band, range(len(bands)), threads)
        else:
            values = np.ones(shape)
        return cls(values, {"pattern_model": "footprint_averaged_gamma", "sub_ray_footprint_m": list(sub_pitch_m),
                            "cell_radius_m": rho, "point_scintillation_index": si,
                            "averaged_scintillation_index": var})


