"""Atmosphere physics (paper §3.4 A–E; docs/theory.md §1–6, §11–13): pure, vectorised numpy/scipy functions.

* :mod:`.extinction`    — aerosol extinction from visibility, two-way transmission in log form (C).
* :mod:`.turbulence`    — Rytov variance, ρ0/r0, cell size, σ_lnI², gamma-gamma α/β, beam spread and
  wander, turbulence MTFs (A, B, D, E).
* :mod:`.derived`       — :func:`derived_turbulence`, every derived quantity of a path for the run metadata.
* :mod:`.scintillation` — seeded random realisations: log-normal / gamma-gamma patterns in target-plane
  metres, beam-wander offsets, turbulence blur (B, D, E).
* :mod:`.phasescreen`   — split-step phase-screen reference (plane and spherical waves), for validation and
  for the wave-optics table.
* :mod:`.wave_optics`   — point-receiver SI, σ²_lnI and covariance tabulated from split-step wave optics (the
  default scintillation statistics).

See ``docs/atmosphere.md``.
"""
from .extinction import (EXTINCTION_MODELS, LayeredExtinction, extinction_from_visibility,
                         log_two_way_transmission, two_way_transmission, visibility_size_exponent)
from .phasescreen import (IntensityStatistics, one_over_e_radius, periodic_autocorrelation, phase_screens,
                          split_step_intensity, split_step_plane_wave, split_step_reference, von_karman_phase_psd,
                          wave_optics_statistics)
from .scintillation import (ProductPattern, ScintillationPattern, beam_wander_offsets, field_spectrum, gamma_factor_g_correlation,
                            gamma_gamma_covariance, gamma_gamma_pattern, gaussian_g_width, gaussian_random_field,
                            gaussian_random_field_pair, unit_gamma_transform,
                            lognormal_g_correlation, lognormal_pattern, make_scintillation_pattern,
                            sample_pattern, seed_speckle_lognormal_pattern, speckle_correlation_radius_px,
                            turbulence_blur, turbulence_mtf_grid, unit_gamma_from_gaussian)
from .wave_optics import STATISTICS_MODELS
from .derived import derived_turbulence
from .turbulence import (WAVE_TYPES, aperture_averaging_factor, beam_wander_variance, cell_radius,
                         coherence_radius, diffraction_mtf, fresnel_scale, fried_parameter,
                         gamma_gamma_cdf, gamma_gamma_parameters, gamma_gamma_pdf, gaussian_beam_parameters,
                         gaussian_beam_scintillation_weak, large_scale_radius, log_intensity_variance,
                         log_intensity_variance_terms, lognormal_pdf, long_term_beam_radius, pixel_mtf,
                         rytov_variance, scintillation_index, short_term_beam_radius, turbulence_mtf_long,
                         turbulence_mtf_short, turbulence_regime, two_way_scintillation_index, wavenumber)
