"""Burst illumination / gated viewing (paper §2.2, §5.1; docs/theory.md §9).

A flood-illuminating laser, a camera and a shutter that opens for ``gate_width_s`` at a delay d_k after the
pulse; a sweep of delays d_k = first_delay + k·step gives range slices, one laser pulse per slice.

Slice k of a pixel collects, from every sub-ray i (energy E_i arriving at the round-trip time t_i),

    S_k = Σ_i E_i · g(t_i − d_k),   g(τ) = ∫ p(t − τ) s(t) dt                                         (gate)

the pulse p (unit energy) convolved with the shutter transmission s (1 on [0, W], linear edges of duration e
centred on 0 and W, so W stays the full width at half transmission).  g is evaluated in closed form from the
pulse CDF P and its integral Q (Q' = P):

    e = 0:  g(τ) = P(W − τ) − P(−τ)
    e > 0:  g(τ) = [Q(W + e/2 − τ) − Q(W − e/2 − τ) − Q(e/2 − τ) + Q(−e/2 − τ)] / e

so no time bins are needed at all; the scene is traced once and every slice reuses the same rays.  Turbulence
(scintillation pattern, beam wander) is drawn per slice (each slice is a different pulse), the turbulence blur
and the receiver chain apply to each slice image.

Range from the slice stack, per pixel (profile I_k = S_k against the delay d_k; the gate's centre sees a return
at t when d_k + W/2 = t):

* ``centroid``  t = Σ I_k (d_k + W/2) / Σ I_k over the slices within the profile's support around the maximum;
* ``peak``      the position of the profile's peak, fitted: least squares of A·g(t − d_k) over the slices around
  the maximum (g the slice response below, known), started at the centre of the half-maximum run of slices —
  a flat-topped profile (gate ≫ step) has no single maximum slice to interpolate;
* ``two_gate``  adjacent gates (step = W), the strongest adjacent pair E1, E2: r = E2/(E1 + E2); the pulse
  centre is at t = d_1 + W − P⁻¹(1 − r) (rectangular pulse of width τ: t0 = T − τ + rτ for its start).
  Exact while the pulse straddles the boundary between the two gates; a pulse shorter than the gate that falls
  entirely inside one gate gives r = 0 or 1 and only the gate is known — the method wants τ ≈ T.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy.special import ndtri

from ..config.settings import LaserSettings, SimulationConfig
from ..constants import SPEED_OF_LIGHT_M_S
from ..engine.atmosphere_stage import blur_cube_and_image, prepare_frame_atmosphere, turbulence_switches
from ..engine.coverage import OrderedTally, coverage_record, gate_window_s
from ..engine.blocks import balanced_block_size, item_blocks, run_blocks, worker_threads
from ..engine.frame import StageLog, open_frame
from ..engine.memory import GATE_MAX_TERMS, check_memory, estimate_gated_memory, held_bytes
from ..engine.products import points_along_rays, reference_range_m
from ..engine.result import FrameResult, product_units
from ..engine.rng import stage_seed
from ..engine.weather_stage import (build_template_table, mark_atmosphere_echoes, max_pixel_fraction,
                                   prepare_frame_weather, weather_switches)
from ..physics.weather_waveform import gated_slab_table, pixel_gated_slab_tables
from ..errors import ConfigError
from ..geometry.rays import Detector, block_subray_tan, tan_to_unit_direction
from ..jit import stage_clock
from ..physics.laser import FWHM_TO_SIGMA, beam_half_angle_tan, cell_energy_fractions, pulse_cdf, pulse_half_support_s
from ..physics.radiometry import received_energy
from ..physics.sampling import SubraySampler, cell_returns
from ..physics.solar import pixel_solar_rates, solar_enabled, tan_cell_solid_angles
from ..physics.waveform import round_trip_time_s



def pulse_cdf_integral(laser, x_s):
    """Q(x) = ∫_{−∞}^{x} P(t) dt of the pulse CDF P (s).  Gaussian: x Φ(x/σ) + σ φ(x/σ); rectangular of
    width τ: 0, (x + τ/2)²/(2τ), x below, across and above the pulse."""
    x = np.asarray(x_s, dtype=np.float64)
    if laser.pulse_shape == "gaussian":
        sigma = laser.pulse_fwhm_s * FWHM_TO_SIGMA
        z = x / sigma
        return x * pulse_cdf(laser, x) + sigma * np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)
    tau = laser.pulse_fwhm_s
    y = np.clip(x + 0.5 * tau, 0.0, tau)
    return np.where(x > 0.5 * tau, x, y * y / (2 * tau))


def gate_response(laser, gate_width_s, edge_s, tau_s):
    """g(τ): the fraction of a pulse centred τ after the gate opens that the shutter transmits (see module)."""
    tau = np.asarray(tau_s, dtype=np.float64)
    w = gate_width_s
    if edge_s <= 0:
        return np.clip(pulse_cdf(laser, w - tau) - pulse_cdf(laser, -tau), 0.0, 1.0)
    h = 0.5 * edge_s
    q = (pulse_cdf_integral(laser, w + h - tau) - pulse_cdf_integral(laser, w - h - tau)
         - pulse_cdf_integral(laser, h - tau) + pulse_cdf_integral(laser, -h - tau))
    return np.clip(q / edge_s, 0.0, 1.0)


def slice_delays_s(config: SimulationConfig) -> np.ndarray:
    g = config.gated
    return g.first_delay_s + g.delay_step_s * np.arange(g.n_slices)


def pulse_cdf_inverse(laser, q):
    """P⁻¹(q): time (relative to the pulse centre) before which the fraction q of the pulse has arrived."""
    q = np.clip(np.asarray(q, dtype=np.float64), 0.0, 1.0)
    if laser.pulse_shape == "gaussian":
        return laser.pulse_fwhm_s * FWHM_TO_SIGMA * ndtri(np.clip(q, 1e-15, 1 - 1e-15))
    return (q - 0.5) * laser.pulse_fwhm_s


def detection_threshold(peak, config: SimulationConfig, noise_sigma=None):
    """The level a pixel's strongest slice must reach to give a range (the gated detection rule, docs/systems.md):

        max(gated.min_peak_fraction × the frame's strongest slice, gated.min_signal_j (ideal receiver),
            gated.k_sigma × σ (noisy receiver: σ the noise of a slice without signal, in its output units))

    ``peak``: every pixel's strongest slice (the frame's maximum is taken over them).  ``noise_sigma``: one σ, or
    one per pixel (an array like ``peak``: sunlight reflected by the scene), which gives one level per pixel."""
    g = config.gated
    frame_peak = float(np.max(peak)) if np.size(peak) else 0.0
    level = g.min_peak_fraction * frame_peak
    if noise_sigma is None:
        level = max(level, g.min_signal_j)
    elif np.ndim(noise_sigma):
        level = np.maximum(level, g.k_sigma * np.asarray(noise_sigma, np.float64).reshape(-1))
    else:
        level = max(level, g.k_sigma * float(noise_sigma))
    return level


def _level_record(threshold, noise_sigma) -> dict:
    """The metadata's threshold and noise σ: the numbers, or (one per pixel) their smallest and largest."""
    if not np.ndim(threshold) and not np.ndim(noise_sigma):
        return {"threshold": threshold, "noise_sigma": noise_sigma}
    t, s = np.asarray(threshold, np.float64), np.asarray(noise_sigma, np.float64)
    return {"threshold": {"min": float(t.min()), "max": float(t.max())},
            "noise_sigma": {"min": float(s.min()), "max": float(s.max())}}


def range_from_slices(slices, delays_s, config: SimulationConfig, noise_sigma: float | None = None):
    """Per-pixel range (m, NaN where no detection) and peak slice value from a stack (n_slices, H, W).

    A pixel gives a range when its strongest slice is > 0 and reaches :func:`detection_threshold` (``noise_sigma``:
    the noisy receiver's σ per slice in the stack's units, the stack holding the signal above the noise mean)."""
    g, laser = config.gated, config.laser
    n, h, w = slices.shape
    prof = slices.reshape(n, -1).astype(np.float64)
    k = np.argmax(prof, axis=0)
    cols = np.arange(prof.shape[1])
    peak = prof[k, cols]
    valid = (peak > 0) & (peak >= detection_threshold(peak, config, noise_sigma))
    t = np.full(prof.shape[1], np.nan)
    step, width = g.delay_step_s, g.gate_width_s
    if g.range_method == "centroid":
        # the profile of one surface spans the gate, the pulse and the shutter edges: sum over the slices within
        # ±reach of the maximum, from running sums (no (2·reach + 1) × pixels array: reach may be huge)
        half = 0.5 * width + pulse_half_support_s(laser) + g.shutter_edge_s
        reach = min(int(np.ceil(half / step)) + 1, n)
        lo, hi = np.maximum(k - reach, 0), np.minimum(k + reach, n - 1) + 1
        rel = (delays_s - delays_s[0])[:, None]
        c0 = np.zeros((n + 1, prof.shape[1]))
        np.cumsum(prof, axis=0, out=c0[1:])
        total = c0[hi, cols] - c0[lo, cols]
        np.cumsum(prof * rel, axis=0, out=c0[1:])
        moment = c0[hi, cols] - c0[lo, cols]
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(valid, delays_s[0] + moment / total + 0.5 * width, np.nan)
    elif g.range_method == "peak":
        t[valid] = _fit_slice_response(prof[:, valid], k[valid], delays_s, config)
    else:  # two_gate: strongest adjacent pair
        if n < 2:
            raise ConfigError("gated.n_slices", n, "at least 2 slices for the two-gate ratio method")
        pair = prof[:-1] + prof[1:]
        j = np.argmax(pair, axis=0)
        e1, e2 = prof[j, cols], prof[j + 1, cols]
        with np.errstate(invalid="ignore", divide="ignore"):
            r = e2 / (e1 + e2)
        t = np.where(valid, delays_s[j] + width - pulse_cdf_inverse(laser, 1.0 - r), np.nan)
    range_m = 0.5 * SPEED_OF_LIGHT_M_S * t
    return range_m.reshape(h, w), peak.reshape(h, w)


#: Gauss–Newton iterations of the ``peak`` fit (it stops earlier once the steps are below 1e-6 of a slice step).
PEAK_FIT_ITERATIONS = 12
#: Candidates on each side of the ``peak`` fit's start (spacing ≤ a quarter of the profile's edge when it allows).
PEAK_FIT_GRID = 16


def _fit_slice_response(prof, k, delays_s, config: SimulationConfig):
    """Return time t (s) per pixel: the least-squares fit of A·g(t − d_k) to the profile I_k (g the slice response
    :func:`gate_response`, A fitted for each t).  ``prof`` (n_slices, P) with every pixel's maximum at ``k``.

    Start: the centre of the half-maximum run of slices around the maximum (+ W/2) — the plateau's centre, within
    about half a slice step for a flat-topped profile; then the best of candidates around it spaced at most a
    quarter of the profile's edge (pulse FWHM + shutter edge) apart where :data:`PEAK_FIT_GRID` allows; then
    Gauss–Newton on t over the slices that can see a return near it (steps at most one candidate spacing, each
    the best of the full and halved step).  It uses the slices on the profile's edges: g is known, so a sample
    on an edge places it exactly; a profile without a sample on an edge keeps the plateau's centre."""
    g, laser = config.gated, config.laser
    n, npix = prof.shape
    if npix == 0:
        return np.zeros(0)
    step, width, edge = g.delay_step_s, g.gate_width_s, g.shutter_edge_s
    cols = np.arange(npix)
    peak = prof[k, cols]
    idx = np.arange(n)[:, None]
    below = prof < 0.5 * peak
    last_on = np.where(below & (idx > k), idx, n).min(axis=0) - 1
    first_on = np.where(below & (idx < k), idx, -1).max(axis=0) + 1
    t = 0.5 * (delays_s[first_on] + delays_s[last_on]) + 0.5 * width
    support = pulse_half_support_s(laser) + 0.5 * edge
    half = int(np.ceil((width + 2 * support) / step)) + 2
    length = min(n, 2 * half + 1)
    start = np.clip(k - half, 0, n - length)
    win = start[None, :] + np.arange(length)[:, None]          # (L, P) slice indices
    y = prof[win, cols[None, :]]
    d = delays_s[win]

    def fit(tt, y=y, d=d):
        resp = gate_response(laser, width, edge, tt[None, :] - d)
        norm = (resp * resp).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            amp = np.where(norm > 0, (y * resp).sum(axis=0) / norm, 0.0)
        return ((y - amp * resp) ** 2).sum(axis=0), amp, resp

    # a grid of candidates around the start, finer than the profile's edges (a start whose model samples all
    # fall on the flat parts has no gradient), then Gauss–Newton from the best
    ramp = laser.pulse_fwhm_s + edge
    n_side = int(min(PEAK_FIT_GRID, np.ceil(4.0 * (0.5 * step + ramp) / ramp)))
    spacing = (0.5 * step + ramp) / n_side
    best, _, _ = fit(t)
    best_t = t
    for j in range(-n_side, n_side + 1):
        if j:
            trial = t + j * spacing
            c = fit(trial)[0]
            better = c < best
            best, best_t = np.where(better, c, best), np.where(better, trial, best_t)
    t = best_t
    h = 1e-3 * min(step, ramp)
    active = np.arange(npix)  # pixels still moving
    for _ in range(PEAK_FIT_ITERATIONS):
        ya, da, ta = y[:, active], d[:, active], t[active]
        cost, amp, resp = fit(ta, ya, da)
        slope = (gate_response(laser, width, edge, (ta + h)[None, :] - da)
                 - gate_response(laser, width, edge, (ta - h)[None, :] - da)) / (2 * h)
        jac = amp * slope                                       # −∂r/∂t, r = y − A g(t − d)
        info = (jac * jac).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            delta = np.where(info > 0, (jac * (ya - amp * resp)).sum(axis=0) / info, 0.0)
        delta = np.clip(np.nan_to_num(delta), -spacing, spacing)
        best, best_t = cost, ta
        for trial in (ta + delta, ta + 0.5 * delta):
            c = fit(trial, ya, da)[0]
            better = c < best
            best, best_t = np.where(better, c, best), np.where(better, trial, best_t)
        t[active] = best_t
        active = active[(np.abs(best_t - ta) > 1e-6 * step)]
        if not len(active):
            break
    return t


def two_gate_range_m(e1, e2, gate_width_s, pulse_width_s, first_delay_s=0.0, pulse_shape="rectangular"):
    """Two-gate ratio range (docs/theory.md §9) for adjacent gates [d, d+T], [d+T, d+2T]."""
    laser = LaserSettings(pulse_shape=pulse_shape, pulse_fwhm_s=pulse_width_s)
    r = e2 / (e1 + e2)
    return 0.5 * SPEED_OF_LIGHT_M_S * (first_delay_s + gate_width_s - pulse_cdf_inverse(laser, 1.0 - r))


#: the stages of a sweep in the order of the run record; StageLog.skip takes out those a run skips
STAGES_PLANNED = ("build_bvh", "rays", "trace", "radiometry", "gating", "extinction", "beam_broadening",
                  "scintillation", "return_scintillation", "beam_wander", "turbulence_blur", "weather_backscatter",
                  "weather_drops", "receiver_chain", "products")


def simulate_gated(scene, world_from_sensor, config: SimulationConfig, *, frame: int = 0, tracer=None,
                   trajectory=None, start_time_s: float = 0.0, progress=None, cancel=None) -> FrameResult:
    """Simulate one gated-viewing sweep (all slices of one frame).  Returns a FrameResult with ``slices``
    (n_slices, H, W), the range image from the slices, points and metadata.  The systems' common signature
    (core.run.SYSTEMS): the sweep is fired from one pose, ``world_from_sensor`` (``trajectory`` and
    ``start_time_s`` are not used)."""
    pattern = config.receiver.subray_pattern
    if pattern == "adaptive":  # refused, not silently ignored (docs/performance.md)
        raise ConfigError("receiver.subray_pattern", pattern,
                          "'grid', 'stratified' or 'sobol' for the gated system (adaptive refinement is implemented "
                          "for the flash and profiler systems only: its range-step tolerance comes from their "
                          "time bins)")
    log = StageLog.of(("build_bvh", "rays", "trace", "radiometry", "gating", "products"), STAGES_PLANNED)
    fr = open_frame(scene, world_from_sensor, config, log, tracer=tracer)
    scene, tracer, origin, rot = fr.scene, fr.tracer, fr.origin, fr.rot
    times = log.times
    det = Detector.from_settings(config.receiver)
    g, laser = config.gated, config.laser
    delays = slice_delays_s(config)
    n_sl = g.n_slices

    # atmosphere: deterministic parts once, random parts (wander, scintillation) per slice (one pulse each)
    t0 = stage_clock()
    switches = turbulence_switches(config)
    needs_ref = any(s not in switches for s in ("beam_broadening", "scintillation", "beam_wander", "turbulence_blur"))
    r_ref = reference_range_m(tracer, det, origin, rot, worker_threads(config.run.threads)) if needs_ref else None
    per_slice_random = any(s not in switches for s in ("scintillation", "beam_wander"))
    atm_slices = [prepare_frame_atmosphere(config, det, r_ref, frame, pulse=0 if per_slice_random else None)]
    # one realisation per slice: check the sweep's memory with the first one's size before drawing the others
    memory = check_memory(config, estimate=estimate_gated_memory(config, pattern_bytes=held_bytes(atm_slices[0])))
    atm_slices += [prepare_frame_atmosphere(config, det, r_ref, frame, pulse=k)
                   for k in (range(1, n_sl) if per_slice_random else [])]
    atm = atm_slices[0]
    fractions = [cell_energy_fractions(laser, det, a.beam_offset_tan, a.beam_width_scale) for a in atm_slices]
    # receiver.subray_pattern: the rays are drawn once for the sweep; a ray carries its cell's exact beam energy
    # in each slice (fractions[j]), except Sobol nets with S not a power of two, whose rays are weighted by the
    # beam at the point (core/physics/sampling.py): each slice's own beam (wander, broadening) weighs them
    samplers = None
    if pattern != "grid":
        samplers = [SubraySampler(det, pattern, fr_j, config.run.seed, laser=laser,
                                  beam_offset_tan=a.beam_offset_tan, beam_width_scale=a.beam_width_scale)
                    for fr_j, a in zip(fractions, atm_slices)]
    point_weights = pattern == "sobol" and det.subsamples & (det.subsamples - 1) != 0
    times["atmosphere"] = stage_clock() - t0
    t0 = stage_clock()
    for stage, reason in weather_switches(config).items():
        log.skip(stage, reason)
    px_tan, py_tan = det.pixel_pitch_tan  # the drops are drawn once: frozen during the sweep (ms)
    sweep_support = pulse_half_support_s(laser) + 0.5 * g.shutter_edge_s  # drops the slices can see
    wx = prepare_frame_weather(config, frame, det.n_pixels, px_tan * py_tan,
                               beam_half_angle_tan(laser, det) * atm.beam_width_scale, 0.5 * min(px_tan, py_tan),
                               max_beam_fraction=max(max_pixel_fraction(det, fx, fy) for fx, fy in fractions),
                               drop_range_m=(0.5 * SPEED_OF_LIGHT_M_S * max(0.0, float(delays.min()) - sweep_support),
                                             0.5 * SPEED_OF_LIGHT_M_S * (float(delays.max()) + g.gate_width_s
                                                                       + sweep_support)))
    vol_t = vol_table = None
    if wx is not None:
        vol_t, vol_table = gated_slab_table(
            laser, delays, g.gate_width_s, g.shutter_edge_s, wx.scale_jm2, wx.weather.backscatter_per_m_sr,
            wx.alpha_per_m, wx.overlap, config.atmosphere.backscatter_min_range_m,
            lambda tau: gate_response(laser, g.gate_width_s, g.shutter_edge_s, tau), profile=wx.beta_profile,
            breaks_m=wx.profile_breaks_m)
        ov = wx.overlap
        if ov.model != "none" and ov.offset_m > 0.0 and laser.beam_profile != "uniform" and np.any(vol_table):
            # each pixel's own overlap (theory §14 W3): its table interpolated over the field (as the flash's
            # templates); the slab times (which slab a surface hides) stay the on-axis pixel's
            def tables_at(tx, ty):
                return pixel_gated_slab_tables(
                    laser, delays, g.gate_width_s, g.shutter_edge_s, wx.scale_jm2, wx.weather.backscatter_per_m_sr,
                    wx.alpha_per_m, ov, config.atmosphere.backscatter_min_range_m,
                    lambda tau: gate_response(laser, g.gate_width_s, g.shutter_edge_s, tau), tx, ty,
                    profile=wx.beta_profile, breaks_m=wx.profile_breaks_m)
            wx.table = build_template_table(det, tables_at, max_bytes=config.run.max_memory_bytes)
            wx.metadata["overlap"]["per_pixel"] = {"nodes": [len(wx.table.nodes_x), len(wx.table.nodes_y)],
                                                   "templates_computed": wx.table.n_computed,
                                                   "checked_error": wx.table.checked_error}
        times["weather"] = stage_clock() - t0
    hits_of_blocks = {}

    s2 = det.rays_per_pixel
    threads = worker_threads(config.run.threads)
    # at least 8 blocks a thread (of ≥ 8192 rays) when the frame allows, on one thread too: the blocks share the
    # threads and give the progress its steps (a frame of one block showed no ETA until it was done).  Every
    # product is the same for any cut: a pixel's slices and energies come from its own rays, the gate coverage
    # is folded in block order (OrderedTally)
    per_block = balanced_block_size(max(1, config.run.chunk_rays // s2), det.n_pixels, threads, -(-8192 // s2),
                                    split_one_thread=True)
    blocks = item_blocks(det.n_pixels, per_block)
    slices = np.zeros((n_sl, det.n_pixels))
    energy = np.zeros((len(atm_slices), det.n_pixels))
    support = pulse_half_support_s(laser) + 0.5 * g.shutter_edge_s
    window = gate_window_s(config)
    tally = OrderedTally(window)  # the hits against the slice sweep (engine/coverage.py), in block order
    # sunlight reflected by the scene into each pixel (core/physics/solar.py), photons/s before η
    sun_rate = np.zeros(det.n_pixels) if config.detector.mode == "noisy" and solar_enabled(config) else None

    def process(block):
        a, b = block
        local = {}
        t = stage_clock()
        if samplers is None:  # the S×S cell centres
            x_tan, y_tan, pixel, sub_x, sub_y = block_subray_tan(det, a, b)
            weights = None
        else:
            smp = samplers[0].block(a, b)
            x_tan, y_tan, pixel, sub_x, sub_y = smp.x_tan, smp.y_tan, smp.pixel, smp.sub_x, smp.sub_y
            weights = [sj.weights_of(smp) for sj in samplers] if point_weights else None
        d_world = tan_to_unit_direction(x_tan, y_tan) @ rot.T
        local["rays"] = stage_clock() - t
        t = stage_clock()
        prim, range_m, cos_theta = tracer.intersect(origin, d_world)
        local["trace"] = stage_clock() - t
        t = stage_clock()
        hit = prim >= 0
        if sun_rate is not None:
            idx = np.flatnonzero(hit)
            omega = tan_cell_solid_angles(x_tan[idx], y_tan[idx], det.pixel_pitch_tan,
                                          np.bincount(pixel - a, minlength=b - a)[pixel[idx] - a])
            sun_rate[a:b] = pixel_solar_rates(config, atm.extinction_per_m, tracer, scene.materials,
                                              scene.material_ids[prim[idx]], origin, d_world, prim, range_m, idx,
                                              pixel[idx] - a, omega, b - a)
        if samplers is not None and config.receiver.cell_range_spread:
            # a jittered ray stands for its cell: range and cos θ where the cell centre's ray meets the plane the
            # ray hit (as the flash system: a plane gives the grid's slices; only edges inside a cell differ)
            idx = np.nonzero(hit)[0]
            _, range_c, cos_c = cell_returns(smp, idx, range_m, cos_theta, prim, tracer.unit_normal, rot)
            range_m, cos_theta = range_m.copy(), cos_theta.copy()
            range_m[idx], cos_theta[idx] = range_c, cos_c
        e_unit = received_energy(laser, config.receiver, atm.extinction_per_m, scene.materials,
                                 scene.material_ids[prim[hit]], cos_theta[hit], range_m[hit], 1.0)
        pix = pixel[hit] - a
        sx, sy, xt, yt = sub_x[hit], sub_y[hit], x_tan[hit], y_tan[hit]
        drops_ret, shade = None, 1.0
        out = np.zeros((n_sl, b - a))
        if wx is not None:  # drops: returns of their own, shadowing what lies behind; the volume from the table
            fx0, fy0 = fractions[0]
            weight = fy0[sub_y] * fx0[sub_x] if weights is None else weights[0]
            beam_fraction = np.bincount(pixel - a, weights=weight, minlength=b - a)
            drops_ret, shade = wx.block_returns(wx.drops_of(a, b), pixel - a, weight,
                                                np.where(hit, range_m, np.inf), beam_fraction, pix, range_m[hit],
                                                beam_tan=det.pixel_center_tan(np.arange(a, b) % det.width_px,
                                                                              np.arange(a, b) // det.width_px))
            hits_of_blocks[a] = (pix + a, range_m[hit])
            m_hit = np.searchsorted(vol_t, round_trip_time_s(range_m[hit]))
            if wx.table is None:
                out += (beam_fraction[:, None] * vol_table[-1][None, :]).T
            else:  # each pixel's own table (interpolated over the field)
                p_all = np.arange(a, b)
                last = wx.table.entries(p_all % det.width_px, p_all // det.width_px,
                                        np.full(b - a, len(vol_table) - 1), n_sl)
                out += (beam_fraction[:, None] * last).T
            if len(pix):
                if wx.table is None:
                    seen = vol_table[m_hit] - vol_table[-1][None, :]  # (hits, slices): minus the hidden volume
                else:
                    seen = (wx.table.entries((pix + a) % det.width_px, (pix + a) // det.width_px, m_hit, n_sl)
                            - last[pix])
                hw = weight[hit]
                for k in range(n_sl):
                    out[k] += np.bincount(pix, weights=hw * seen[:, k], minlength=b - a)
        per_slice = []
        for j, (fx, fy) in enumerate(fractions):
            e = e_unit * fy[sy] * fx[sx] * shade if weights is None else e_unit * weights[j][hit] * shade
            if atm_slices[j].pattern is not None:
                e = e * atm_slices[j].scintillation_at(xt, yt, sx, sy)
            energy[j, a:b] = np.bincount(pix, weights=e, minlength=b - a)
            per_slice.append(e)
        hits_e = (range_m[hit], per_slice[0])  # (folded into the tally in block order)
        local["radiometry"] = stage_clock() - t
        t = stage_clock()
        t_rt = round_trip_time_s(range_m[hit])
        if drops_ret is not None and len(drops_ret[0]):
            pix = np.concatenate([pix, drops_ret[0]])
            t_rt = np.concatenate([t_rt, round_trip_time_s(drops_ret[1])])
            per_slice = [np.concatenate([e, drops_ret[2]]) for e in per_slice]
        # only the slices whose gate can see a ray: d_k − support < t − … < d_k + W + support
        lo = np.searchsorted(delays, t_rt - g.gate_width_s - support, side="left")
        hi = np.searchsorted(delays, t_rt + support, side="right")
        span = int((hi - lo).max()) if len(t_rt) else 0
        e_mat = np.stack(per_slice, axis=0) if len(per_slice) > 1 else None  # (n_slices, rays)
        if span > 0:
            step_rays = max(1, GATE_MAX_TERMS // span)
            for c in range(0, len(t_rt), step_rays):
                sl = slice(c, c + step_rays)
                kk = lo[sl, None] + np.arange(span)[None, :]
                ok = kk < n_sl
                kc = np.minimum(kk, n_sl - 1)
                resp = gate_response(laser, g.gate_width_s, g.shutter_edge_s, t_rt[sl, None] - delays[kc])
                if e_mat is None:
                    w_e = per_slice[0][sl, None] * resp
                else:
                    w_e = e_mat[kc, np.arange(c, min(c + step_rays, len(t_rt)))[:, None]] * resp
                w_e = np.where(ok, w_e, 0.0)
                flat = kc * (b - a) + pix[sl, None]
                out += np.bincount(flat[ok], weights=w_e[ok], minlength=n_sl * (b - a)).reshape(n_sl, b - a)
        slices[:, a:b] = out
        local["gating"] = stage_clock() - t
        return int(hit.sum()), local, hits_e

    def fold(result):
        n, local, hits_e = result
        tally.add(*hits_e)
        return n, local

    results = run_blocks(process, blocks, threads, progress, cancel=cancel, each=fold)
    n_hits = sum(r[0] for r in results)
    for _, local in results:
        log.add_times(local)
    if n_hits == 0:
        raise ConfigError("sensor", "sees nothing",
                          f"a field of view containing geometry: all {det.n_pixels * s2} rays missed the "
                          f"{scene.n_triangles} triangles of the scene")
    h, w = det.height_px, det.width_px
    cube = np.ascontiguousarray(slices.T.reshape(h, w, n_sl))  # (H, W, slices)
    energy_image = energy.mean(axis=0).reshape(h, w)
    for stage, reason in atm.skipped.items():
        log.skip(stage, reason)
    if atm.blur_r0_m is not None:
        with log.timed("turbulence_blur"):
            energy_image = blur_cube_and_image(cube, energy_image, det, config, atm.blur_r0_m)
    receiver_report = pixel_noise = None
    data = cube
    if config.detector.mode == "noisy":
        # (here, before the stage clock: an ideal receiver never loads the chain and its kernels)
        from ..physics.receiver.chain import ChainSettings, apply_receiver_chain

        with log.timed("receiver_chain"):
            chain = dataclasses.replace(ChainSettings.from_config(config), bin_width_s=g.gate_width_s)
            if sun_rate is not None:
                chain.pixel_background_rate = sun_rate.reshape(h, w)
            out = apply_receiver_chain(cube.astype(np.float32), chain,
                                       stage_seed(config.run.seed, frame, "receiver"))
            data, receiver_report = out.data, out.report
            pixel_noise = out.pixel_noise
    else:
        log.skip("receiver_chain", "detector.mode = ideal: noise-free slice energies")
    t0 = stage_clock()
    stack = np.moveaxis(np.asarray(data, dtype=np.float32), 2, 0)  # (slices, H, W)
    noise_sigma = None
    if receiver_report is not None and pixel_noise is not None and "noise_sigma" in pixel_noise:
        # each pixel's own noise (sunlight reflected by the scene): its mean and σ
        profile = stack - pixel_noise["noise_mean"].astype(np.float32)[None]
        noise_sigma = pixel_noise["noise_sigma"]
    elif receiver_report is not None and receiver_report.get("noise_sigma") is not None:
        # ranges from the signal above the mean output of a slice without signal (A/D pedestal, dark, background)
        profile = stack - np.float32(receiver_report["noise_mean"])
        noise_sigma = float(receiver_report["noise_sigma"])
    elif config.detector.mode == "noisy" and config.detector.enable_adc and \
            config.detector.detector_type != "geiger":
        profile = stack - np.float32(config.detector.adc_offset_counts)  # ranges from counts above the pedestal
    else:
        profile = stack
    range_image, peak_image = range_from_slices(np.maximum(profile, 0.0), delays, config, noise_sigma)
    range_image = range_image.astype(np.float32)
    pix = np.flatnonzero(np.isfinite(range_image.reshape(-1)))
    rng_m = range_image.reshape(-1)[pix].astype(np.float64)
    amp = peak_image.reshape(-1)[pix]
    zeros = np.zeros(len(pix), np.int16)
    points = points_along_rays(det, origin, rot, pix, rng_m, amp, zeros, zeros + 1, 2 * rng_m / SPEED_OF_LIGHT_M_S,
                               frame)
    if wx is not None:  # 1: no surface hit of the pixel near the range: a return of the atmosphere
        hp = [hits_of_blocks[k] for k in sorted(hits_of_blocks)]
        points["atmosphere"] = mark_atmosphere_echoes(
            config, pix, rng_m, np.concatenate([h[0] for h in hp]) if hp else np.zeros(0, np.int64),
            np.concatenate([h[1] for h in hp]) if hp else np.zeros(0))
    times["products"] = stage_clock() - t0
    log.skip("waveform", "gated viewing: the gate response is evaluated in closed form per ray, no time bins")
    stats = {"n_rays": det.n_pixels * s2, "n_hits": n_hits, "n_points": int(len(pix)),
             "n_triangles": scene.n_triangles, "n_blocks": len(blocks), "n_slices": n_sl,
             "slice_delays_s": delays, "ray_traces": 1, "threads": max(1, min(threads, len(blocks))),
             "range_method": g.range_method, "stage_times_s": log.times,
             "detection": {**_level_record(detection_threshold(peak_image, config, noise_sigma), noise_sigma),
                           "pixels_detected": int(len(pix)),
                           "rule": "strongest slice ≥ max(min_peak_fraction × the frame's strongest slice, "
                                   + ("k_sigma × noise σ" if noise_sigma is not None else "min_signal_j") + ")"},
             "wall_time_s": time.perf_counter() - fr.t_wall, "received_energy_j": float(energy_image.sum()),
             "stages_run": log.ran, "stages_skipped": log.skipped, "memory_estimate_bytes": memory["total"],
             "work_estimate_samples": memory["work"],
             "gate_coverage": coverage_record(config, tally.tally)}
    if atm.metadata:
        stats["atmosphere"] = atm.metadata
        if per_slice_random:
            stats["atmosphere"]["per_slice_random"] = "scintillation and wander drawn per slice (one pulse each)"
    if wx is not None:
        stats["weather"] = dict(wx.metadata, n_atmosphere_echoes=int(points["atmosphere"].sum()))
    if receiver_report is not None:
        stats["receiver"] = receiver_report
    range_echoes = range_image[:, :, None].copy()
    intensity = peak_image.astype(np.float32)
    return FrameResult(range_image=range_image, intensity_image=intensity, energy_image=energy_image,
                       range_echoes=range_echoes, intensity_echoes=intensity[:, :, None].copy(), points=points,
                       waveforms=None, digital_waveforms=None, stats=stats,
                       slices=np.ascontiguousarray(stack), slice_delays_s=delays,
                       units=product_units("gated", receiver_report and receiver_report["units"]),
                       tracer=tracer)
