"""Receiver: photons to digital counts (paper §3.1 Figure 4; docs/theory.md §5, §7, §8).  See docs/receiver.md.

One module per concern: :mod:`.conversions` (elementary §8 conversions and moments), :mod:`.adc`
(A/D conversion), :mod:`.samplers` (exact fast Poisson and gain samplers), :mod:`.code_tables` (the exact
A/D code distribution of signal-free bins), :mod:`.speckle` (optics MTF and target speckle), :mod:`.geiger`
(photon counting) and :mod:`.chain` (the chain that applies them to a waveform cube).

This package namespace re-exports the public names so ``core.physics.receiver`` (and the old
``core.receiver``) keeps its API; code inside ``core`` imports from the defining modules.

The names are resolved at first use (PEP 562 ``__getattr__``): importing one light module of the package (the
flash frame's ``conversions``) does not load the chain, its samplers, tables and speckle (SciPy's FFT) and their
kernels, which an ideal receiver never runs (issue 25: start-up).
"""
from importlib import import_module as _import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (what the names are, for readers and checkers; at run time ``__getattr__`` imports them)
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

#: each public name -> the module (relative to this package, or absolute in ``core``) that defines it
_HOMES = {
    "DetectorSettings": "...config.settings",
    "H_PLANCK_J_S": "...constants", "Q_ELECTRON_C": "...constants", "SPEED_OF_LIGHT_M_S": "...constants",
    "adc_convert": ".adc", "adc_dtype": ".adc",
    "STEPS": ".chain", "ChainOutput": ".chain", "ChainSettings": ".chain", "apply_receiver_chain": ".chain",
    "CaughtCodeTables": ".code_tables", "CodeTable": ".code_tables", "noise_code_pmf": ".code_tables",
    "uniform_uint32": ".code_tables",
    **dict.fromkeys(("adc_step_e", "background_photons", "bin_moments", "current_to_electrons", "energy_to_photons",
                     "linear_detector_moments", "mcintyre_excess_noise", "noise_sigma_floor", "photons_per_joule",
                     "snr_linear"), ".conversions"),
    **dict.fromkeys(("coates_correction", "geiger_detection_probability", "geiger_histogram",
                     "pileup_probabilities"), ".geiger"),
    **dict.fromkeys(("gamma_gain", "poisson_dense", "poisson_sparse_counts", "poisson_uniform_rows"), ".samplers"),
}
_SUBMODULES = ("adc", "chain", "code_tables", "conversions", "geiger", "samplers", "speckle", "table_route")

__all__ = list(_HOMES)


def __getattr__(name):
    if name in _HOMES:
        value = getattr(_import_module(_HOMES[name], __name__), name)
    elif name in _SUBMODULES:
        value = _import_module("." + name, __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_HOMES) | set(_SUBMODULES))
