"""The weather stage of a frame: returns of the atmosphere itself added to every beam's waveform (core/atmosphere/
weather.py for the physics; docs/theory.md §14).

A *beam* is what owns one waveform: a flash pixel (its share of the flash) or a scanner pulse.  Per frame the
stage computes once the volume-backscatter waveform of a beam of energy fraction 1 (the template: it depends on
the gate, the pulse, α, β and the overlap only) and draws the frame's discrete particles (rain, snow) from
``SeedSequence([seed, frame, weather_drops(, pulse)])`` (:mod:`.rng`).  Per block of beams the system then

1. appends the visible drops (in front of the surface of the sub-ray cell they fall in) to its surface returns
   as returns of their own, and shadows every later return of the same beam (:meth:`FrameWeather.block_returns`);
2. adds the template, hidden behind each sub-ray's surface, to the beams' waveform rows
   (:func:`~core.atmosphere.weather.add_volume_rows`), before the receiver chain.

With ``atmosphere.weather = none`` the planner skips both (:func:`weather_switches`) and nothing here runs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..atmosphere.weather import (Drops, Overlap, Weather, atmosphere_echo_mask, backscatter_template, draw_drops,
                                  drop_returns, expected_drop_count, shadow_factors, visible_drops, weather_model)
from ..config.settings import SimulationConfig
from ..constants import SPEED_OF_LIGHT_M_S
from ..physics.propagation import aerosol_extinction_per_m, effective_extinction_per_m
from ..physics.radiometry import aperture_r2, energy_scale
from .rng import stage_rng

STAGES = ("weather_backscatter", "weather_drops")
#: Largest expected number of discrete particles held at once (a frame; a scanner's tile of pulses): 2e6 drops are
#: ~100 MB with their returns.  More is refused naming atmosphere.drop_min_diameter_mm and the value that fits.
MAX_DROPS = 2_000_000


def weather_switches(config: SimulationConfig) -> dict:
    """The weather stages this run skips, with the reason (none skipped: both run)."""
    atm = config.atmosphere
    if atm.weather == "none":
        reason = "atmosphere.weather = none: extinction only, no returns from the atmosphere"
        return {s: reason for s in STAGES}
    skipped = {}
    if atm.weather not in ("rain", "snow"):
        skipped["weather_drops"] = f"atmosphere.weather = {atm.weather}: no discrete particles (rain or snow only)"
    return skipped


def echo_tolerance_m(config: SimulationConfig) -> float:
    """An echo farther than this from every surface hit of its beam is a return of the atmosphere."""
    return 0.5 * SPEED_OF_LIGHT_M_S * (2.0 * config.laser.pulse_fwhm_s + config.gate.bin_width_s)


@dataclass
class FrameWeather:
    weather: Weather
    overlap: Overlap
    template: np.ndarray           # (n_bins,) J per bin for a beam of fraction 1
    alpha_per_m: float
    scale_jm2: float
    aperture_r2: float
    omega_sr: float                # solid angle of one beam
    drop_range_m: tuple = (0.0, 0.0)
    drops: Drops | None = None
    metadata: dict = field(default_factory=dict)

    def draw(self, config: SimulationConfig, frame: int, n_beams: int, stream: int | None = None) -> Drops | None:
        """The particles of ``n_beams`` beams from the stream ``weather_drops`` of the frame (of a pulse tile when
        ``stream`` is given); None without discrete particles."""
        if not self.weather.has_drops:
            return None
        return draw_drops(stage_rng(config.run.seed, frame, "weather_drops", stream), self.weather, n_beams,
                          self.omega_sr, *self.drop_range_m)

    def drops_of(self, a: int, b: int) -> Drops | None:
        """The drops of beams [a, b), beam indices local to the block."""
        if self.drops is None or len(self.drops) == 0:
            return None
        lo, hi = np.searchsorted(self.drops.beam, [a, b])
        if hi <= lo:
            return None
        d = self.drops.take(slice(lo, hi))
        d.beam = d.beam - a
        return d

    def block_returns(self, drops: Drops | None, ray_beam, ray_weight, ray_range_m, beam_fraction, hit_beam,
                      hit_range_m):
        """For a block's drops: (beam, range, energy) of the visible ones, and the shadow factor of each surface
        hit (``hit_beam``, ``hit_range_m``; ones without drops).  ``ray_*``: every sub-ray of the block sorted by
        beam, a missed ray with range inf; ``beam_fraction``: the energy fraction of each beam."""
        if drops is None:
            return None, np.ones(len(hit_beam))
        vis = drops.take(visible_drops(drops, ray_beam, ray_weight, ray_range_m))
        e, f = drop_returns(vis, beam_fraction, self.omega_sr, self.scale_jm2, self.aperture_r2, self.alpha_per_m,
                            self.weather.lidar_ratio_sr, self.overlap)
        e = e * shadow_factors(vis, f, vis.beam, vis.range_m)
        return (vis.beam, vis.range_m, e), shadow_factors(vis, f, hit_beam, hit_range_m)


def check_drop_count(weather: Weather, expected: float) -> None:
    """ConfigError when ``expected`` particles would be held at once (:data:`MAX_DROPS`): the message names
    atmosphere.drop_min_diameter_mm, the count, and the smallest diameter that fits (N(D ≥ D) ∝ e^(−ΛD))."""
    if expected <= MAX_DROPS:
        return
    need = weather.d_min_mm + math.log(expected / MAX_DROPS) / weather.lam
    from ..errors import ConfigError
    raise ConfigError("atmosphere.drop_min_diameter_mm", weather.d_min_mm,
                      f"at least {math.ceil(need * 100) / 100:.2f} mm here: {expected:.3g} drops of "
                      f"≥ {weather.d_min_mm} mm would be drawn at once in this field of view and gate (at most "
                      f"{MAX_DROPS:.0e}); the smaller ones are then volume backscatter (or narrow the field of view "
                      f"or the gate)")


def prepare_frame_weather(config: SimulationConfig, frame: int, n_beams: int, omega_sr: float,
                          tx_half_angle: float, rx_half_angle: float, pulse: int | None = None,
                          draw: bool = True, beams_at_once: int | None = None) -> FrameWeather | None:
    """The weather of one frame (of one pulse stream when ``pulse`` is given), None for weather = none; with
    ``draw`` the particles of all ``n_beams`` beams are drawn now (else per tile of ``beams_at_once`` beams:
    :meth:`FrameWeather.draw`).  Refuses (ConfigError) more than :data:`MAX_DROPS` particles at once."""
    atm, laser, gate = config.atmosphere, config.laser, config.gate
    w = weather_model(atm, laser.wavelength_m, aerosol_extinction_per_m(config))
    if w is None:
        return None
    rx = config.receiver
    overlap = Overlap(atm.overlap_model, atm.tx_rx_offset_m, laser.beam_waist_radius_m, tx_half_angle,
                      0.5 * rx.aperture_diameter_m, rx_half_angle)
    alpha = effective_extinction_per_m(config)
    scale = energy_scale(laser, rx)
    template = backscatter_template(laser, gate, scale, w.backscatter_per_m_sr, alpha, overlap,
                                    atm.backscatter_min_range_m)
    out = FrameWeather(w, overlap, template, alpha, scale, aperture_r2(rx), omega_sr)
    out.metadata = {"model": w.record(), "overlap": overlap.record(),
                    "volume_energy_per_beam_j": float(template.sum())}
    if w.has_drops:
        c2 = 0.5 * SPEED_OF_LIGHT_M_S
        r_lo = max(atm.backscatter_min_range_m, c2 * gate.gate_start_s)
        r_hi = c2 * (gate.gate_start_s + gate.n_bins * gate.bin_width_s)
        out.drop_range_m = (r_lo, r_hi)
        per_beam = expected_drop_count(w, omega_sr, r_lo, r_hi)
        check_drop_count(w, per_beam * (n_beams if draw or beams_at_once is None else min(n_beams, beams_at_once)))
        out.metadata["drops"] = {"range_m": [r_lo, r_hi], "beam_solid_angle_sr": omega_sr,
                                 "expected": expected_drop_count(w, omega_sr, r_lo, r_hi) * n_beams}
        if draw:
            out.drops = out.draw(config, frame, n_beams, pulse)
            out.metadata["drops"]["drawn"] = len(out.drops)
    return out


def merge_returns(pix, t_s, e, spread, drops_ret):
    """Surface returns (sorted by beam) with the drop returns appended, sorted by beam again (stable)."""
    if drops_ret is None or len(drops_ret[0]) == 0:
        return pix, t_s, e, spread
    d_beam, d_range, d_e = drops_ret
    pix2 = np.concatenate([pix, d_beam])
    order = np.argsort(pix2, kind="stable")
    t2 = np.concatenate([t_s, 2.0 * d_range / SPEED_OF_LIGHT_M_S])[order]
    e2 = np.concatenate([e, d_e])[order]
    sp2 = None if spread is None else np.concatenate([spread, np.zeros((len(d_beam), 2))])[order]
    return pix2[order], t2, e2, sp2


def mark_atmosphere_echoes(config: SimulationConfig, echo_beam, echo_range_m, hit_beam, hit_range_m):
    """uint8 per echo: 1 for a return of the atmosphere (no surface hit of its beam near it)."""
    return atmosphere_echo_mask(echo_beam, echo_range_m, hit_beam, hit_range_m,
                                echo_tolerance_m(config)).astype(np.uint8)
