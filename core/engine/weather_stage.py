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

import dataclasses
import functools
import math
from dataclasses import dataclass, field

import numpy as np

from ..atmosphere.extinction import two_way_transmission
from ..atmosphere.weather import (DropCut, Drops, Overlap, Weather, atmosphere_echo_mask, draw_drops, drop_cut,
                                  drop_returns, layer_backscatter, pixel_overlap, shadow_factors, visible_drops,
                                  weather_model)
from ..config.settings import SimulationConfig
from ..config.tables import aerosol_layer_table
from ..constants import H_PLANCK_J_S, SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from ..physics.propagation import aerosol_extinction_per_m, path_extinction
from ..physics.radiometry import aperture_r2, energy_scale
from ..physics.weather_waveform import backscatter_template, pixel_backscatter_templates
from .rng import stage_rng

STAGES = ("weather_backscatter", "weather_drops")
#: Largest expected number of discrete particles held at once (a frame; a scanner's tile of pulses): 2e6 drops are
#: ~100 MB with their returns.  More is refused naming atmosphere.drop_min_diameter_mm and the value that fits.
MAX_DROPS = 2_000_000
#: Largest relative L1 error of a flash pixel's interpolated volume template, checked at the cell centres of the
#: field-angle table (:func:`build_template_table`).
TEMPLATE_TABLE_TOLERANCE = 1e-3


def _axis_nodes(n: int, step: int) -> np.ndarray:
    """Pixel indices 0, step, 2·step, … and n − 1."""
    return np.unique(np.append(np.arange(0, n, step), n - 1))


def _bilinear_weights(nodes: np.ndarray, idx):
    """(cell index, weight of the cell's second node) of pixel indices ``idx`` on the node indices ``nodes``."""
    idx = np.asarray(idx)
    if len(nodes) == 1:
        return np.zeros(idx.shape, np.int64), np.zeros(idx.shape)
    i = np.clip(np.searchsorted(nodes, idx, side="right") - 1, 0, len(nodes) - 2)
    return i, (idx - nodes[i]) / (nodes[i + 1] - nodes[i])


@dataclass
class TemplateTable:
    """Volume templates of flash pixels tabulated over the pixel grid (field angle): exact at the node pixels
    (columns ``nodes_x`` × rows ``nodes_y``), between them bilinear in pixel index of the templates' logarithm
    (geometric: exact for the tilt exp(c_x tan_x + c_y tan_y) of the overlap), bin by bin; a bin that is zero at
    any node is zero (:func:`build_template_table`)."""

    width_px: int
    nodes_x: np.ndarray
    nodes_y: np.ndarray
    templates: np.ndarray          # (len(nodes_y), len(nodes_x), n_bins)
    checked_error: float = 0.0     # the largest relative L1 error found at the cell centres
    n_computed: int = 0            # templates computed (nodes and checks)

    def interpolate(self, cols, rows) -> np.ndarray:
        """(n, n_bins) templates of the pixels at (cols, rows)."""
        ix, wx = _bilinear_weights(self.nodes_x, cols)
        iy, wy = _bilinear_weights(self.nodes_y, rows)
        t = self.templates
        jx = np.minimum(ix + 1, len(self.nodes_x) - 1)
        jy = np.minimum(iy + 1, len(self.nodes_y) - 1)
        wx, wy = wx[:, None].astype(np.float32), wy[:, None].astype(np.float32)
        lt = self.log_templates
        g = (1.0 - wx) * lt[iy, ix]
        g += wx * lt[iy, jx]
        g *= 1.0 - wy
        h = (1.0 - wx) * lt[jy, ix]
        h += wx * lt[jy, jx]
        h *= wy
        g += h
        return np.exp(g, out=g)

    def __post_init__(self):
        # geometric interpolation: the overlap's tilt is exp(linear in tan_x) (core.atmosphere.weather.pixel_overlap);
        # float32 as the cube it is added to; a bin that is zero at a node: log −1e30 (exp → 0)
        positive = np.all(self.templates > 0.0, axis=(0, 1))
        self.log_templates = np.where(positive[None, None, :], np.log(np.where(positive[None, None, :],
                                                                              self.templates, 1.0)),
                                      -1e30).astype(np.float32)

    def entries(self, cols, rows, m, n_cols: int) -> np.ndarray:
        """Row ``m[i]`` (of length ``n_cols``) of each template seen as an (n_bins/n_cols, n_cols) table, at the
        pixels (cols[i], rows[i]), interpolated as :meth:`interpolate`: (n, n_cols)."""
        ix, wx = _bilinear_weights(self.nodes_x, cols)
        iy, wy = _bilinear_weights(self.nodes_y, rows)
        jx = np.minimum(ix + 1, len(self.nodes_x) - 1)
        jy = np.minimum(iy + 1, len(self.nodes_y) - 1)
        lt = self.log_templates.reshape(len(self.nodes_y), len(self.nodes_x), -1, n_cols)
        wx, wy = wx[:, None].astype(np.float32), wy[:, None].astype(np.float32)
        g = ((1.0 - wy) * ((1.0 - wx) * lt[iy, ix, m] + wx * lt[iy, jx, m])
             + wy * ((1.0 - wx) * lt[jy, ix, m] + wx * lt[jy, jx, m]))
        return np.exp(g).astype(np.float64)

    def rows_of(self, a: int, b: int) -> np.ndarray:
        """(b − a, n_bins) templates of the pixels a … b − 1 (row-major)."""
        p = np.arange(a, b)
        cols = p % self.width_px
        rows, inv = np.unique(p // self.width_px, return_inverse=True)
        # along y once per image row of the block, then along x per pixel (the same bilinear form)
        iy, wy = _bilinear_weights(self.nodes_y, rows)
        jy = np.minimum(iy + 1, len(self.nodes_y) - 1)
        wy = wy[:, None, None].astype(np.float32)
        lt = self.log_templates
        by_row = (1.0 - wy) * lt[iy] + wy * lt[jy]          # (rows, nodes_x, n_bins)
        ix, wx = _bilinear_weights(self.nodes_x, cols)
        jx = np.minimum(ix + 1, len(self.nodes_x) - 1)
        wx = wx[:, None].astype(np.float32)
        g = (1.0 - wx) * by_row[inv, ix]
        g += wx * by_row[inv, jx]
        return np.exp(g, out=g)


def build_template_table(det, templates_at, tolerance: float = TEMPLATE_TABLE_TOLERANCE,
                         first_nodes: int = 3, max_bytes: float | None = None) -> TemplateTable:
    """Tabulate ``templates_at(tan_x (K,), tan_y (K,)) → (K, n_bins)`` over the detector's pixel centres: nodes
    every ``step`` pixels (and the last pixel) starting from about ``first_nodes`` per axis; the templates at the
    cell centres are computed exactly and compared with the interpolation (relative L1 of each template), and the
    step halved until the largest error is at most ``tolerance`` (step 1: every pixel exact).  Templates are
    computed once per pixel (cached across refinements).  ``max_bytes``: ConfigError (naming
    atmosphere.overlap_model) when the templates held would exceed it."""
    w, h = det.width_px, det.height_px
    cache = {}

    def get(cols, rows):
        cc, rr = np.meshgrid(cols, rows)
        need = [(c, r) for c, r in zip(cc.ravel().tolist(), rr.ravel().tolist()) if (c, r) not in cache]
        if need and cache and max_bytes is not None:
            row_bytes = 8 * next(iter(cache.values())).size
            if (len(cache) + len(need)) * row_bytes > max_bytes:
                raise ConfigError("atmosphere.overlap_model", "geometric",
                                  f"none here, or tx_rx_offset_m = 0: each pixel's own overlap needs "
                                  f"{(len(cache) + len(need)) * row_bytes / 1e6:.0f} MB of tabulated templates "
                                  f"(more than run.max_memory_bytes = {max_bytes:.3g}) to keep the interpolation "
                                  f"within {tolerance:g} (or shorten the gate or the slice sweep)")
        if need:
            nc, nr = np.array(need).T
            tx, ty = det.pixel_center_tan(nc, nr)
            for key, t in zip(need, templates_at(tx, ty)):
                cache[key] = t
        return np.stack([cache[(c, r)] for c, r in zip(cc.ravel().tolist(), rr.ravel().tolist())]).reshape(
            len(rows), len(cols), -1)

    step = max(1, -(-max(w, h) // max(1, first_nodes - 1)))
    while True:
        nx, ny = _axis_nodes(w, step), _axis_nodes(h, step)
        table = TemplateTable(w, nx, ny, get(nx, ny))
        if step == 1:
            break
        cx = (nx[:-1] + nx[1:]) // 2 if len(nx) > 1 else nx
        cy = (ny[:-1] + ny[1:]) // 2 if len(ny) > 1 else ny
        exact = get(cx, cy)
        cc, rr = np.meshgrid(cx, cy)
        approx = table.interpolate(cc.ravel(), rr.ravel()).reshape(exact.shape)
        total = np.abs(exact).sum(axis=-1)
        err = np.abs(approx - exact).sum(axis=-1) / np.where(total > 0, total, 1.0)
        table.checked_error = float(err.max())
        if table.checked_error <= tolerance:
            break
        step = max(1, step // 2)
    table.n_computed = len(cache)
    return table


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
    alpha_per_m: object            # α (a float), or a LayeredExtinction (atmosphere.aerosol_layers)
    scale_jm2: float
    aperture_r2: float
    omega_sr: float                # solid angle of one beam
    drop_range_m: tuple = (0.0, 0.0)
    drops: Drops | None = None
    cut: DropCut | None = None     # the detectability cut of the particles (None without particles)
    table: TemplateTable | None = None  # flash pixels' own templates (per-pixel overlap), None: ``template``
    metadata: dict = field(default_factory=dict)
    layer_beta: object = None      # β(R) of the aerosol layers (core.atmosphere.weather.layer_backscatter), or None
    layer_edges_m: np.ndarray | None = None  # the layers' start and end ranges (None without layers)

    def templates_of(self, a: int, b: int) -> np.ndarray:
        """The volume templates of beams a … b − 1: (b − a, n_bins) from the pixel table, else ``template``."""
        return self.template if self.table is None else self.table.rows_of(a, b)

    def draw(self, config: SimulationConfig, frame: int, n_beams: int, stream: int | None = None) -> Drops | None:
        """The particles of ``n_beams`` beams from the stream ``weather_drops`` of the frame (of a pulse tile when
        ``stream`` is given); None without discrete particles."""
        if not self.weather.has_drops:
            return None
        return draw_drops(stage_rng(config.run.seed, frame, "weather_drops", stream), self.weather, n_beams,
                          self.omega_sr, *self.drop_range_m, cut=self.cut)

    @property
    def beta_profile(self):
        """The backscatter profile β(R) added to the volume's constant β: the undrawn particles' (the cut) plus the
        aerosol layers' (None without either)."""
        parts = [p for p in (None if self.cut is None or self.cut.is_trivial else self.cut.beta_profile,
                             self.layer_beta) if p is not None]
        if len(parts) < 2:
            return parts[0] if parts else None
        return lambda r: parts[0](r) + parts[1](r)

    @property
    def profile_breaks_m(self):
        """Where :attr:`beta_profile` or the extinction jumps (the cut's shell edges, the layers' edges), None
        without either."""
        parts = [e for e in (None if self.cut is None or self.cut.is_trivial else self.cut.edges_m,
                             self.layer_edges_m) if e is not None]
        return np.unique(np.concatenate(parts)) if parts else None

    def mean_shadow(self, range_m):
        """The mean transmission through the undrawn particles nearer than each range (ones without a cut)."""
        if self.cut is None:
            return np.ones(np.shape(range_m))
        return self.cut.mean_shadow(range_m)

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
                      hit_range_m, beam_tan=None):
        """For a block's drops: (beam, range, energy) of the visible ones, and the shadow factor of each surface
        hit (``hit_beam``, ``hit_range_m``; ones without drops).  ``ray_*``: every sub-ray of the block sorted by
        beam, a missed ray with range inf; ``beam_fraction``: the energy fraction of each beam.  Both carry the
        mean shadow of the undrawn particles nearer than them (:meth:`mean_shadow`).  ``beam_tan``: (tan_x, tan_y) of
        each beam of the block, for the per-pixel overlap of a flash (used with a :attr:`table`)."""
        hit_shadow = self.mean_shadow(np.asarray(hit_range_m, np.float64))
        if drops is None:
            return None, hit_shadow
        vis = drops.take(visible_drops(drops, ray_beam, ray_weight, ray_range_m))
        overlap = self.overlap
        if self.table is not None and beam_tan is not None:
            tx, ty = np.asarray(beam_tan[0])[vis.beam], np.asarray(beam_tan[1])[vis.beam]
            overlap = functools.partial(pixel_overlap, self.overlap, tan_x=tx, tan_y=ty)
        e, f = drop_returns(vis, beam_fraction, self.omega_sr, self.scale_jm2, self.aperture_r2, self.alpha_per_m,
                            self.weather.lidar_ratio_sr, overlap)
        e = e * shadow_factors(vis, f, vis.beam, vis.range_m) * self.mean_shadow(vis.range_m)
        return (vis.beam, vis.range_m, e), shadow_factors(vis, f, hit_beam, hit_range_m) * hit_shadow


def max_pixel_fraction(det, fx, fy) -> float:
    """The largest share of the pulse energy in one pixel, from the per-axis sub-cell fractions (fx (W·S,),
    fy (H·S,): core.physics.laser.cell_energy_fractions)."""
    s = det.subsamples
    return float(np.asarray(fx).reshape(det.width_px, s).sum(axis=1).max()
                 * np.asarray(fy).reshape(det.height_px, s).sum(axis=1).max())


def check_drop_count(weather: Weather, expected: float, cut: DropCut | None = None, n_beams: int = 1) -> None:
    """ConfigError when ``expected`` particles would be held at once (:data:`MAX_DROPS`): the message names
    atmosphere.drop_min_diameter_mm, the count, and the smallest diameter that fits: N(D ≥ D) ∝ e^(−ΛD) when
    every particle ≥ D_min is drawn; with a detectability ``cut`` (of ``n_beams`` beams at once), the smallest
    D_min for which the shells' counts n(D ≥ max(D_min, D_k)) sum to at most the limit (bisection)."""
    if expected <= MAX_DROPS:
        return
    need = weather.d_min_mm + math.log(expected / MAX_DROPS) / weather.lam
    if cut is not None and not cut.is_trivial:
        def count(d):
            c = dataclasses.replace(cut, d_cut_mm=np.maximum(cut.d_cut_mm, d), d_min_mm=d)
            return float(c.expected_per_beam().sum()) * n_beams
        lo, hi, step = weather.d_min_mm, weather.d_min_mm, 1.0 / weather.lam
        while count(hi) > MAX_DROPS:
            lo, hi, step = hi, hi + step, 2.0 * step
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if count(mid) > MAX_DROPS else (lo, mid)
        need = hi
    raise ConfigError("atmosphere.drop_min_diameter_mm", weather.d_min_mm,
                      f"at least {math.ceil(need * 100) / 100:.2f} mm here: {expected:.3g} drops of "
                      f"≥ {weather.d_min_mm} mm would be drawn at once in this field of view and gate (at most "
                      f"{MAX_DROPS:.0e}); the smaller ones are then volume backscatter (or narrow the field of view "
                      f"or the gate, or raise atmosphere.drop_cut_photoelectrons)")


def prepare_frame_weather(config: SimulationConfig, frame: int, n_beams: int, omega_sr: float,
                          tx_half_angle: float, rx_half_angle: float, pulse: int | None = None,
                          draw: bool = True, beams_at_once: int | None = None,
                          max_beam_fraction: float = 1.0, drop_range_m: tuple | None = None,
                          detector=None) -> FrameWeather | None:
    """The weather of one frame (of one pulse stream when ``pulse`` is given), None for weather = none; with
    ``draw`` the particles of all ``n_beams`` beams are drawn now (else per tile of ``beams_at_once`` beams:
    :meth:`FrameWeather.draw`).  ``max_beam_fraction``: the largest energy fraction of a beam (a flash pixel's
    share), which sets the detectability cut (:func:`~core.atmosphere.weather.drop_cut`; larger = more drops
    drawn, never wrong).  ``drop_range_m``: (near, far) of the particles (default: from
    ``atmosphere.backscatter_min_range_m`` or the gate's start to the gate's end; gated viewing passes its slice
    sweep's span).  ``detector``: a flash detector whose pixels get their own overlap (a :class:`TemplateTable`
    when ``atmosphere.overlap_model = geometric``).  Refuses (ConfigError) more than :data:`MAX_DROPS` particles at
    once."""
    atm, laser, gate = config.atmosphere, config.laser, config.gate
    w = weather_model(atm, laser.wavelength_m, aerosol_extinction_per_m(config))
    if w is None:
        return None
    rx = config.receiver
    layers = aerosol_layer_table(atm)
    overlap = Overlap(atm.overlap_model, atm.tx_rx_offset_m, laser.beam_waist_radius_m, tx_half_angle,
                      0.5 * rx.aperture_diameter_m, rx_half_angle, math.radians(atm.tx_rx_offset_angle_deg))
    alpha = path_extinction(config)  # a float, or layered (two_way_transmission: e^(−2τ(R)))
    scale = energy_scale(laser, rx)
    ra2 = aperture_r2(rx)
    cut = None
    if w.has_drops:
        c2 = 0.5 * SPEED_OF_LIGHT_M_S
        if drop_range_m is None:
            drop_range_m = (c2 * gate.gate_start_s, c2 * (gate.gate_start_s + gate.n_bins * gate.bin_width_s))
        r_lo = max(atm.backscatter_min_range_m, drop_range_m[0])
        r_hi = max(r_lo, drop_range_m[1])
        # photo-electrons of a particle hiding the whole beam (W2 with f = 1) at the largest beam fraction
        pe_per_j = config.detector.quantum_efficiency * laser.wavelength_m / (H_PLANCK_J_S * SPEED_OF_LIGHT_M_S)
        k = scale * max_beam_fraction * (2.0 / w.lidar_ratio_sr) * pe_per_j

        def full_beam_pe(r):
            return k * overlap(r) * two_way_transmission(alpha, r) / (r * r + ra2)

        cut = drop_cut(w, omega_sr, r_lo, r_hi, full_beam_pe, atm.drop_cut_photoelectrons, ra2)
    out = FrameWeather(w, overlap, np.zeros(0), alpha, scale, ra2, omega_sr, cut=cut)
    if layers is not None:
        out.layer_beta = layer_backscatter(layers)
        out.layer_edges_m = np.unique(layers[:, :2])
    profile, breaks = out.beta_profile, out.profile_breaks_m
    template = backscatter_template(laser, gate, scale, w.backscatter_per_m_sr, alpha, overlap,
                                    atm.backscatter_min_range_m, profile=profile, breaks_m=breaks)
    out.template = template
    out.metadata = {"model": w.record(), "overlap": overlap.record(),
                    "volume_energy_per_beam_j": float(template.sum())}
    if layers is not None:
        out.metadata["aerosol_layers"] = layers.tolist()
    if (detector is not None and overlap.model != "none" and overlap.offset_m > 0.0 and laser.beam_profile != "uniform"
            and np.any(template)):  # else every pixel's overlap is the on-axis one (core.atmosphere.weather)
        def templates_at(tx, ty):
            return pixel_backscatter_templates(laser, gate, scale, w.backscatter_per_m_sr, alpha, overlap,
                                               atm.backscatter_min_range_m, tx, ty, profile=profile,
                                               breaks_m=breaks)
        out.table = build_template_table(detector, templates_at, max_bytes=config.run.max_memory_bytes)
        out.metadata["overlap"]["per_pixel"] = {"nodes": [len(out.table.nodes_x), len(out.table.nodes_y)],
                                                "templates_computed": out.table.n_computed,
                                                "checked_error": out.table.checked_error}
    if w.has_drops:
        out.drop_range_m = (r_lo, r_hi)
        per_beam = float(cut.expected_per_beam().sum())
        at_once = n_beams if draw or beams_at_once is None else min(n_beams, beams_at_once)
        check_drop_count(w, per_beam * at_once, cut, at_once)
        out.metadata["drops"] = {"range_m": [r_lo, r_hi], "beam_solid_angle_sr": omega_sr,
                                 "expected": per_beam * n_beams,
                                 "cut_photoelectrons": atm.drop_cut_photoelectrons,
                                 "cut_diameter_mm": [float(np.min(cut.d_cut_mm)),  # None: no drop drawn in some shell
                                                     float(np.max(cut.d_cut_mm)) if np.all(np.isfinite(cut.d_cut_mm))
                                                     else None]}
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
