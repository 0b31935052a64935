"""Receiver: photons to digital counts (paper §3.1 Figure 4; docs/theory.md §5, §7, §8).  See docs/receiver.md.

One module per concern: :mod:`.conversions` (elementary §8 conversions and moments), :mod:`.adc`
(A/D conversion), :mod:`.samplers` (exact fast Poisson and gain samplers), :mod:`.code_tables` (the exact
A/D code distribution of signal-free bins), :mod:`.speckle` (optics MTF and target speckle), :mod:`.geiger`
(photon counting) and :mod:`.chain` (the chain that applies them to a waveform cube).

This package namespace re-exports the public names so ``core.physics.receiver`` (and the old
``core.receiver``) keeps its API; code inside ``core`` imports from the defining modules.
"""
from ...config.settings import DetectorSettings
from ...constants import H_PLANCK_J_S, Q_ELECTRON_C, SPEED_OF_LIGHT_M_S
from .adc import adc_convert, adc_dtype
from .chain import STEPS, ChainOutput, ChainSettings, apply_receiver_chain
from .code_tables import CaughtCodeTables, CodeTable, noise_code_pmf, uniform_uint32
from .conversions import (adc_step_e, background_photons, bin_moments, current_to_electrons, energy_to_photons,
                          linear_detector_moments, mcintyre_excess_noise, noise_sigma_floor, photons_per_joule,
                          snr_linear)
from .geiger import coates_correction, geiger_detection_probability, geiger_histogram, pileup_probabilities
from .samplers import gamma_gain, poisson_dense, poisson_sparse_counts, poisson_uniform_rows

__all__ = ["DetectorSettings", "H_PLANCK_J_S", "Q_ELECTRON_C", "SPEED_OF_LIGHT_M_S", "adc_convert", "adc_dtype",
           "STEPS", "ChainOutput", "ChainSettings", "apply_receiver_chain", "CaughtCodeTables", "CodeTable",
           "noise_code_pmf", "uniform_uint32", "adc_step_e", "background_photons", "bin_moments",
           "current_to_electrons", "energy_to_photons", "linear_detector_moments", "mcintyre_excess_noise",
           "noise_sigma_floor",
           "photons_per_joule", "snr_linear", "coates_correction", "geiger_detection_probability",
           "geiger_histogram", "pileup_probabilities", "gamma_gain", "poisson_dense", "poisson_sparse_counts",
           "poisson_uniform_rows"]
