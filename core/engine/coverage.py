"""Coverage of the range gate: how much of what the rays hit the gate can see.

Every hit sub-ray has a round-trip time t = 2R/c and an energy at the aperture (eq. 3-1, before time binning).
A hit is *before* the gate when t < start, *after* it when t ≥ end, and *inside* otherwise (its centre time; a
pulse straddling an edge is counted where its centre is).  The gate is ``[gate.gate_start_s, gate_start_s +
n_bins · bin_width_s)`` for the flash ladar, the profiler and the scanner, and the sweep of shutter openings
``[first_delay_s, first_delay_s + (n_slices − 1) · delay_step_s + gate_width_s)`` for gated viewing.

Each block of a frame adds its hits with :func:`gate_tally` (counts, energies, the smallest and largest hit
range), or into an :class:`OrderedTally` (the same sums whatever the blocks); :func:`coverage_record` turns the
frame's sum into the ``gate_coverage`` record of the run's statistics
(metadata.json) with a ``warning`` when less than :data:`COVERAGE_WARN_FRACTION` of the hit energy is inside the
gate: naming the gate, the ranges of the hits and the settings that would cover them.
"""
from __future__ import annotations

import math

import numpy as np

from ..config.settings import SimulationConfig
from ..constants import SPEED_OF_LIGHT_M_S
from ..jit import kernel
from ..physics.laser import pulse_half_support_s

#: Warn when less than this fraction of the hit energy falls inside the range gate.
COVERAGE_WARN_FRACTION = 0.9
#: Largest ``gate.n_bins`` (settings.RangeGateSettings) a suggestion may name.
_MAX_BINS = 1_000_000


def gate_window_s(config: SimulationConfig) -> tuple[float, float]:
    """The (start, end) round-trip times (s) the system's gate covers (module docstring)."""
    if config.system_type == "gated":
        g = config.gated
        return g.first_delay_s, g.first_delay_s + (g.n_slices - 1) * g.delay_step_s + g.gate_width_s
    g = config.gate
    return g.gate_start_s, g.gate_start_s + g.n_bins * g.bin_width_s


def empty_tally() -> np.ndarray:
    """A tally with no hits: [count before, inside, after, energy before, inside, after, min range, max range]."""
    return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, np.inf, -np.inf])


def gate_tally(range_m, energy_j, window_s) -> np.ndarray:
    """The tally (:func:`empty_tally`'s layout) of hits at ``range_m`` (m) with energies ``energy_j`` (J) against
    the gate ``window_s`` = (start, end) in round-trip time."""
    out = empty_tally()
    r, e = _tally_inputs(range_m, energy_j)
    if r.size:
        out[6], out[7] = _add_hits(r, e, window_s, out)
    return out


class OrderedTally:
    """A frame's tally folded block by block, in block order: bit for bit :func:`gate_tally` of all the frame's
    hits at once (the energies are added one by one in element order, as :func:`gate_tally` adds them; adding
    blocks' sums would group them by block), so the record does not depend on how the frame is cut into
    blocks or on the thread count.  Call :meth:`add` with each block's hits in block order."""

    def __init__(self, window_s):
        self.window_s = window_s
        self.tally = empty_tally()

    def add(self, range_m, energy_j) -> None:
        r, e = _tally_inputs(range_m, energy_j)
        if r.size == 0:
            return
        r_min, r_max = _add_hits(r, e, self.window_s, self.tally)
        self.tally[6], self.tally[7] = min(self.tally[6], r_min), max(self.tally[7], r_max)


def _tally_inputs(range_m, energy_j):
    """(ranges (n,) float64, energies (n,) or one for all (1,) float64), contiguous."""
    r = np.ascontiguousarray(np.asarray(range_m, dtype=np.float64).ravel())
    e = np.asarray(energy_j, dtype=np.float64)
    e = e.reshape(1) if e.size == 1 else np.ascontiguousarray(np.broadcast_to(e, np.shape(range_m)).ravel())
    return r, e


def _add_hits(r, e, window_s, tally) -> tuple[float, float]:
    """Add the hits (r, e) to the counts and energies of ``tally`` in place, element by element (a hit is
    before the gate when t = 2r/c < start, after it when t ≥ end, inside otherwise: a NaN range inside); returns
    the hits' smallest and largest range (NaN when a range is NaN, as ``ndarray.min``)."""
    return _tally_kernel(r, e, float(window_s[0]), float(window_s[1]), SPEED_OF_LIGHT_M_S, tally)


@kernel(inline=True)
def tally_hit(x, e, start, end, c, tally):
    """Add one hit at range ``x`` (m) with energy ``e`` (J) to the counts and energies of ``tally`` (the gate
    [start, end) in round-trip time, ``c`` the speed of light): the step :func:`gate_tally` takes for each hit,
    for a compiled pass that tallies its hits as it makes them (core/systems/scanner.py)."""
    t = 2.0 * x / c
    k = 0 if t < start else (2 if t >= end else 1)
    tally[k] += 1.0
    tally[3 + k] += e


@kernel
def _tally_kernel(r, e, start, end, c, tally):
    one = e.shape[0] == 1 and r.shape[0] != 1
    r_min, r_max, nan = r[0], r[0], False
    for i in range(r.shape[0]):
        x = r[i]
        tally_hit(x, e[0] if one else e[i], start, end, c, tally)
        if x != x:
            nan = True
        elif x < r_min:
            r_min = x
        elif x > r_max:
            r_max = x
    if nan:
        return np.nan, np.nan
    return r_min, r_max


def add_tallies(tallies) -> np.ndarray:
    """The sum of blocks' tallies (counts and energies added, the range extremes kept)."""
    out = empty_tally()
    for t in tallies:
        out[:6] += t[:6]
        out[6], out[7] = min(out[6], t[6]), max(out[7], t[7])
    return out


def _r(t_s: float) -> float:
    return 0.5 * SPEED_OF_LIGHT_M_S * t_s


def covering_settings(config: SimulationConfig, r_min_m: float, r_max_m: float) -> dict:
    """Settings whose gate covers hits from ``r_min_m`` to ``r_max_m`` with a margin of the pulse's support
    (the bin width, delay step and gate width kept), as {"group.field": value}."""
    margin = pulse_half_support_s(config.laser) + 2e-9
    t0 = max(0.0, 2.0 * r_min_m / SPEED_OF_LIGHT_M_S - margin)
    t1 = 2.0 * r_max_m / SPEED_OF_LIGHT_M_S + margin
    if config.system_type == "gated":
        g = config.gated
        start = math.floor(t0 * 1e9) * 1e-9  # whole ns, at or before t0
        n = max(1, math.ceil((t1 - start - g.gate_width_s) / g.delay_step_s) + 1)
        return {"gated.first_delay_s": start, "gated.n_slices": int(min(n, 100_000))}
    g = config.gate
    start = math.floor(t0 * 1e9) * 1e-9  # whole ns, at or before t0
    n = math.ceil((t1 - start) / g.bin_width_s)
    return {"gate.gate_start_s": start, "gate.n_bins": int(min(n, _MAX_BINS))}


def _fmt_setting(name: str, value) -> str:
    if name.endswith("_s"):
        return f"{name} = {value:.4g} s ({value * 1e9:.6g} ns)" if value < 1e-6 else \
            f"{name} = {value:.4g} s ({value * 1e6:.6g} µs)"
    return f"{name} = {value}"


def coverage_record(config: SimulationConfig, tally) -> dict:
    """The frame's ``gate_coverage`` record: the gate (times and ranges), the fractions of the hit sub-rays and
    of their energy before, inside and after it, the ranges of the hits, and — when less than
    :data:`COVERAGE_WARN_FRACTION` of the hit energy is inside — a one-line ``warning`` with the settings that
    would cover the hits (``suggested_settings``)."""
    t = np.asarray(tally, dtype=np.float64)
    start, end = gate_window_s(config)
    n, e = t[0:3].sum(), t[3:6].sum()
    keys = ("before", "inside", "after")
    rec = {"gate_s": [start, end], "gate_range_m": [_r(start), _r(end)],
           "hit_subrays": int(n), "hit_energy_j": float(e),
           "subray_fraction": {k: (float(t[i] / n) if n > 0 else 0.0) for i, k in enumerate(keys)},
           "energy_fraction": {k: (float(t[3 + i] / e) if e > 0 else 0.0) for i, k in enumerate(keys)},
           "hit_range_m": [float(t[6]), float(t[7])] if n > 0 else None,
           "warn_below": COVERAGE_WARN_FRACTION, "warning": None}
    if n > 0 and e > 0 and rec["energy_fraction"]["inside"] < COVERAGE_WARN_FRACTION:
        fix = covering_settings(config, t[6], t[7])
        rec["suggested_settings"] = fix
        what = "the slice sweep" if config.system_type == "gated" else "the range gate"
        ef, sf = rec["energy_fraction"], rec["subray_fraction"]
        rec["warning"] = (
            f"only {100 * ef['inside']:.1f} % of the hit energy ({100 * sf['inside']:.1f} % of the "
            f"{int(n)} hit sub-rays) is inside {what} {_r(start):.1f}–{_r(end):.1f} m "
            f"({100 * ef['before']:.1f} % before, {100 * ef['after']:.1f} % after); the hits are at "
            f"{t[6]:.1f}–{t[7]:.1f} m: set " + ", ".join(_fmt_setting(k, v) for k, v in fix.items())
            + " to cover them")
    return rec
