"""What a frame of any sensor system returns: :class:`FrameResult`, and the unit of every product."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FrameResult:
    range_image: np.ndarray       # (H, W) float32, first echo range (m), NaN where none
    intensity_image: np.ndarray   # (H, W) float32, first echo peak (J per bin), 0 where none
    energy_image: np.ndarray      # (H, W) float64, received energy per pixel before binning (J)
    range_echoes: np.ndarray      # (H, W, E) float32, echoes in time order, NaN where none
    intensity_echoes: np.ndarray  # (H, W, E) float32
    points: dict                  # per-point arrays (see engine.products.points_along_rays)
    waveforms: np.ndarray | None  # (H, W, n_bins) float32 (J per bin) or None when not saved
    digital_waveforms: np.ndarray | None = None  # (H, W, n_bins) receiver output (counts), noisy mode only
    stats: dict = field(default_factory=dict)
    pulses: dict | None = None          # scanner: per-pulse record (time, pose, direction, echoes, energy)
    slices: np.ndarray | None = None    # gated viewing: (n_slices, H, W) float32 energy per slice (J)
    slice_delays_s: np.ndarray | None = None  # gated viewing: gate opening delay of each slice (s)
    units: dict = field(default_factory=dict)  # product → unit (:func:`product_units`): files, previews, metadata
    tracer: object = field(default=None, repr=False, compare=False)  # the frame's BVH (ground truth), not saved


def product_units(system_type: str, receiver_units: str | None = None) -> dict:
    """The unit of every product of a run: the one source the run folder's file descriptions, ``metadata.json``
    (``units``), the previews and the add-on's legends read.

    ``receiver_units``: the noisy receiver chain's output unit (its report's ``units``: "counts", "electrons" or
    "detections"); None or "J" for the ideal receiver.  Keys: ``range``, ``intensity`` (the intensity image, the
    echoes' and points' ``intensity``), ``energy``, ``waveforms`` (noise-free), ``counts`` (the receiver output,
    noisy only), ``slices`` (gated viewing)."""
    noisy = receiver_units not in (None, "J")
    units = {"range": "m", "energy": "J", "waveforms": "J per bin"}
    if system_type == "gated":
        # slice values: energy per slice (ideal), the receiver's output per slice (noisy; counts above the A/D
        # offset for the range and intensity)
        units["slices"] = receiver_units if noisy else "J"
        units["intensity"] = units["slices"]
    else:
        units["intensity"] = receiver_units if noisy else "J per bin"
    if noisy:
        units["counts"] = receiver_units
    return units
