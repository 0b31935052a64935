"""Time-of-flight laser scanner (paper §2.1): pulses steered by a scan pattern, each with its own waveform.

Scan patterns, beam sub-rays and the rays of a block of pulses: :mod:`.scan_patterns`.

Each pulse is fired from, and its echoes registered with, the sensor pose at its own time stamp (core/geometry/motion.py),
so a scan from a moving platform lands in world coordinates; the ~µs flight time is neglected in the pose.
The point of an echo is placed along the pulse's nominal beam axis at the echo range, as a real scanner does.

Waveforms are built per pulse over a window of the range gate just wide enough for that pulse's returns
(windows of 16, 32, 64 … bins, never more than the gate), which gives the same echoes as the full gate; the full
gate is used where it must be (noisy receiver: noise and false alarms everywhere; saved waveforms).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..atmosphere import (beam_wander_offsets, beam_wander_variance, derived_turbulence, gaussian_beam_parameters,
                          long_term_beam_radius, short_term_beam_radius)
from ..atmosphere.wave_optics import gamma_gamma_fit
from ..config.derived import n_scan_pulses, scan_duration_s
from ..config.settings import SimulationConfig
from ..constants import SPEED_OF_LIGHT_M_S
from ..engine.atmosphere_stage import turbulence_switches
from ..engine.coverage import add_tallies, coverage_record, empty_tally, gate_tally, gate_window_s, tally_hit
from ..engine.blocks import item_blocks, run_blocks, worker_threads
from ..engine.frame import StageLog, open_frame
from ..engine.memory import SCAN_NOISE_TILE_PULSES
from ..engine.products import load_noisy_receiver, noisy_echoes
from ..engine.result import FrameResult, product_units
from ..engine.rng import stage_rng, stage_seed
from ..engine.weather_stage import mark_atmosphere_echoes, merge_returns, prepare_frame_weather, weather_switches
from ..atmosphere.extinction import LayeredExtinction
from ..atmosphere.weather import add_volume_rows
from ..errors import ConfigError
from ..geometry.motion import Trajectory
from ..jit import kernel, stage_clock
from ..physics.detection.peaks import Echoes, detect_echoes
from ..physics.laser import pulse_half_support_s
from ..physics.propagation import (footprint_variance_factor, path_extinction, return_scintillation_variance,
                                   turbulence_model_settings)
from ..physics.brdf import bad_material, material_brdf_at, material_table
from ..physics.radiometry import energy_at, energy_terms, received_energy
from ..physics.receiver.chain import ChainSettings, apply_receiver_chain, background_summary
from ..physics.solar import beam_solid_angle, pixel_solar_rates, solar_enabled
from ..physics.pulse_table import CentroidPulseTable
from ..physics.waveform import PulseTable, accumulate_waveforms, binning_method, round_trip_time_s
from .returns import encode_intensity, intensity_unit, peak_per_joule, quantize_range, select_returns
from ..config.tables import channel_energy_scale
from .scan_patterns import beam_subrays, pulse_schedule, scan_beams


# ----------------------------------------------------------------------------------------------------------
# Atmosphere per pulse (paper §3.4 A, B, D for a single beam)
# ----------------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class ScanAtmosphere:
    extinction_per_m: float  # or a LayeredExtinction (atmosphere.aerosol_layers: core.physics.propagation)
    width_scale: float = 1.0
    wander_r2_rad2: float = 0.0      # ⟨r_c²⟩/R_ref²: mean square angular wander of the beam centre
    scint_model: str | None = None
    scint_params: dict = dataclasses.field(default_factory=dict)
    return_variance: float = 0.0      # B': return path through the receiver aperture (aperture averaged)
    metadata: dict = dataclasses.field(default_factory=dict)
    skipped: dict = dataclasses.field(default_factory=dict)

    def draw(self, config, frame, tile, n):
        """Per-pulse wander offsets (n, 2) rad and scintillation factors (n,) for one tile of pulses."""
        wander = np.zeros((n, 2))
        scint = np.ones(n)
        if self.wander_r2_rad2 > 0:
            rng = stage_rng(config.run.seed, frame, "beam_wander", tile)
            wander = beam_wander_offsets(self.wander_r2_rad2, rng, size=n).reshape(n, 2)
        if self.scint_model is not None:
            rng = stage_rng(config.run.seed, frame, "scintillation", tile)
            p = self.scint_params
            if self.scint_model == "lognormal":
                s2 = p["sigma2_lnI"]
                scint = np.exp(np.sqrt(s2) * rng.standard_normal(n) - 0.5 * s2)
            elif self.scint_model == "gamma_gamma":
                a, b = p["alpha"], p["beta"]
                scint = rng.gamma(a, 1.0 / a, n) * rng.gamma(b, 1.0 / b, n)
            elif self.scint_model == "gamma_lognormal":
                a, s2 = p["alpha"], p["sigma2_lnY"]
                scint = rng.gamma(a, 1.0 / a, n) * np.exp(np.sqrt(s2) * rng.standard_normal(n) - 0.5 * s2)
            else:  # footprint-averaged: gamma of unit mean and the averaged variance
                var = p["averaged_scintillation_index"]
                scint = rng.gamma(1.0 / var, var, n)
        if self.return_variance > 0:
            rng = stage_rng(config.run.seed, frame, "return_scintillation", tile)
            scint = scint * rng.gamma(1.0 / self.return_variance, self.return_variance, n)
        return wander, scint


def scan_atmosphere(config: SimulationConfig, reference_range_m: float | None) -> ScanAtmosphere:
    """Turbulence of a scan evaluated at R_ref (median range of the pulse axes): beam broadening (A),
    per-pulse scintillation of the footprint (B: log-normal or gamma-gamma point statistics when the footprint
    is smaller than a cell, else a gamma law with the footprint-averaged variance), per-pulse wander (D).
    The turbulence blur (E) of an imaging receiver has no meaning for a single-element scanner (its effect on
    the beam is the broadening)."""
    atm, laser = config.atmosphere, config.laser
    out = ScanAtmosphere(path_extinction(config))
    if out.extinction_per_m == 0.0:
        out.skipped["extinction"] = "no extinction (extinction_per_m = 0, no visibility and no aerosol layers)"
    out.skipped.update(turbulence_switches(config))
    out.skipped.setdefault("turbulence_blur", "scanner: single-element receiver, no image to blur")
    active = [s for s in ("beam_broadening", "scintillation", "return_scintillation", "beam_wander")
              if s not in out.skipped]
    if not active:
        return out
    r_ref = float(reference_range_m)
    lam = laser.wavelength_m
    focus = laser.beam_focus_range_m if laser.beam_focus_range_m > 0 else np.inf
    derived = derived_turbulence(atm.cn2_m_23, lam, r_ref, wave="spherical",
                                 aperture_diameter_m=config.receiver.aperture_diameter_m,
                                 **turbulence_model_settings(config))
    beam = gaussian_beam_parameters(lam, laser.beam_waist_radius_m, r_ref, focus)
    w = float(beam["w_m"])
    r_c2 = float(beam_wander_variance(atm.cn2_m_23, r_ref, laser.beam_waist_radius_m, focus))
    meta = {"reference_range_m": r_ref, "derived": derived, "beam_wander_variance_m2": r_c2}
    if "beam_broadening" in active:
        w_lt = float(long_term_beam_radius(w, derived["rytov_variance_plane"], beam["lam"]))
        radius = float(short_term_beam_radius(w_lt, r_c2, w)) if "beam_wander" in active else w_lt
        out.width_scale = radius / w
        meta.update(free_space_radius_m=w, broadened_radius_m=radius, beam_width_scale=out.width_scale)
    if "beam_wander" in active:
        out.wander_r2_rad2 = r_c2 / r_ref ** 2
        meta["beam_wander_rms_rad"] = float(np.sqrt(out.wander_r2_rad2))
    # footprint of the (broadened) beam at R_ref: the 1/e² diameter of the divergence cone
    footprint_m = 2.0 * np.tan(0.5 * laser.beam_divergence_rad) * out.width_scale * r_ref
    footprint_y_m = (2.0 * np.tan(0.5 * laser.beam_divergence_y_rad) * out.width_scale * r_ref
                     if laser.beam_divergence_y_rad else footprint_m)  # an elliptical beam's second axis
    if "scintillation" in active:
        rho = derived["cell_radius_m"]
        si = derived["scintillation_index"]
        if max(footprint_m, footprint_y_m) > rho:
            var = float(si * footprint_variance_factor(derived, footprint_m, footprint_y_m))
            out.scint_model, out.scint_params = "footprint_gamma", {"averaged_scintillation_index": var}
        else:
            model = atm.scintillation_model
            if model == "auto":
                model = derived["pdf_model"]
            if model == "lognormal":
                out.scint_params = {"sigma2_lnI": float(np.log1p(si))}
            elif model == "gamma_lognormal":
                out.scint_params = {"alpha": float(derived["gamma_alpha"]),
                                    "sigma2_lnY": float(derived["lognormal_sigma2"])}
            elif derived["scintillation_statistics"] == "wave_optics":   # gamma-gamma fitted to the table
                a, b, _ = gamma_gamma_fit(si, derived["sigma2_lnI"])
                out.scint_params = {"alpha": a, "beta": b}
            else:
                out.scint_params = {"alpha": float(derived["gamma_alpha"]), "beta": float(derived["gamma_beta"])}
            out.scint_model = model
        meta["scintillation"] = {"model": out.scint_model, "footprint_m": footprint_m, "cell_radius_m": rho,
                                 **out.scint_params}
    if "return_scintillation" in active:
        # the receiver (aperture D) looks at the illuminated footprint: the pixel footprint of docs/theory.md §3
        info = return_scintillation_variance(derived, (footprint_m, footprint_m))
        out.return_variance = info["variance"]
        meta["return_scintillation"] = info
    out.metadata["turbulence"] = meta
    return out


# ----------------------------------------------------------------------------------------------------------
# Waveforms per pulse
# ----------------------------------------------------------------------------------------------------------
def windowed_echoes(pulse_local, time_s, energy_j, n_pulses, config: SimulationConfig, method: str,
                    table: PulseTable | None = None) -> Echoes:
    """Echoes of n_pulses pulses from their sub-ray returns (pulse_local sorted ascending), each pulse's waveform
    built over a window of the gate just wide enough for its returns.  Positions are in gate bins.  With a
    ``table`` (Gaussian pulse) each pulse's waveform is built from the tabulated pulse and its echoes detected
    in one compiled pass (:meth:`PulseTable.echoes`)."""
    gate = config.gate
    half = pulse_half_support_s(config.laser) / gate.bin_width_s
    u = (time_s - gate.gate_start_s) / gate.bin_width_s
    if table is not None:
        return table.echoes(pulse_local, u, energy_j, n_pulses, gate.n_bins, config.detection)
    keep = (energy_j > 0) & (u + half >= 0) & (u - half < gate.n_bins)
    pulse_local, u, energy_j, time_s = pulse_local[keep], u[keep], energy_j[keep], time_s[keep]
    parts = []
    if len(u) == 0:
        return _empty_echoes()
    u_min = np.full(n_pulses, np.inf)
    u_max = np.full(n_pulses, -np.inf)
    np.minimum.at(u_min, pulse_local, u)
    np.maximum.at(u_max, pulse_local, u)
    has = np.isfinite(u_min)
    need = np.zeros(n_pulses)
    need[has] = u_max[has] - u_min[has] + 2 * half + 4
    length = np.where(has, 2 ** np.ceil(np.log2(np.maximum(need, 16))), 0).astype(np.int64)
    length = np.minimum(length, gate.n_bins)
    start = np.zeros(n_pulses, np.int64)
    start[has] = np.clip(np.floor(u_min[has] - half - 1).astype(np.int64), 0, gate.n_bins - length[has])
    for win in np.unique(length[has]):
        pulses = np.flatnonzero(length == win)
        sel = np.isin(pulse_local, pulses)
        local = np.searchsorted(pulses, pulse_local[sel])
        shift_s = start[pulses][local] * gate.bin_width_s
        wgate = dataclasses.replace(gate, n_bins=int(win))
        wf = accumulate_waveforms(local, time_s[sel] - shift_s, energy_j[sel], len(pulses), config.laser,
                                  wgate, method)
        ech = detect_echoes(wf, config.detection)
        ech.position_bins = ech.position_bins + start[pulses][ech.pixel]
        ech.pixel = pulses[ech.pixel]
        parts.append(ech)
    return _merge_echoes(parts)


def _empty_echoes() -> Echoes:
    z = np.zeros(0)
    return Echoes(np.zeros(0, np.int64), z, z, np.zeros(0, np.int16), np.zeros(0, np.int16))


def _merge_echoes(parts) -> Echoes:
    if not parts:
        return _empty_echoes()
    order = np.argsort(np.concatenate([p.pixel for p in parts]), kind="stable")
    cat = {f: np.concatenate([getattr(p, f) for p in parts])[order]
           for f in ("pixel", "position_bins", "amplitude", "echo_index", "n_echoes")}
    if all(p.snr is not None for p in parts):
        cat["snr"] = np.concatenate([p.snr for p in parts])[order]
    merged = Echoes(**cat)
    if all(getattr(p, "false_alarm", None) is not None for p in parts):
        merged.false_alarm = np.concatenate([p.false_alarm for p in parts])[order]
    return merged


def _block_points(echoes: Echoes, a, t_s, channel, angle, origin, axis_world, gate, start_time_s, frame,
                  config=None, extinction_per_m: float = 0.0, peak: float | None = None,
                  channel_scale=None) -> dict:
    """The points of one block's echoes (pulse ``a + echoes.pixel``), in the products' types: each echo placed
    along its pulse's nominal axis at the echo range.  With ``config``: the echoes its scanner's return mode
    reports, ranges rounded to its range quantum, intensities in its encoding (core/systems/returns.py)."""
    if config is not None and config.scanner.return_mode != "all":
        keep = select_returns(echoes.pixel, echoes.amplitude, echoes.echo_index, echoes.n_echoes,
                              config.scanner.return_mode, config.scanner.n_returns)
        kept = Echoes(**{f.name: (None if getattr(echoes, f.name) is None else getattr(echoes, f.name)[keep])
                         for f in dataclasses.fields(Echoes)})
        if getattr(echoes, "false_alarm", None) is not None:
            kept.false_alarm = echoes.false_alarm[keep]
        echoes = kept
    p = echoes.pixel
    time_s = gate.gate_start_s + echoes.position_bins * gate.bin_width_s
    range_m = 0.5 * SPEED_OF_LIGHT_M_S * time_s
    intensity = echoes.amplitude.astype(np.float32)
    if config is not None:
        if config.scanner.range_quantum_m:
            range_m = quantize_range(range_m, config.scanner.range_quantum_m)
            time_s = 2.0 * range_m / SPEED_OF_LIGHT_M_S
        if peak is not None and channel_scale is not None:  # each channel calibrated at its own energy
            peak = peak * channel_scale[channel[p]]
        intensity = encode_intensity(echoes.amplitude, range_m, config, extinction_per_m, peak)
    points = {"position_world": origin[p] + axis_world[p] * range_m[:, None],
              "intensity": intensity, "range_m": range_m,
              "echo_index": (echoes.echo_index + 1).astype(np.int16), "n_echoes": echoes.n_echoes.astype(np.int16),
              "time_s": time_s, "gps_time_s": start_time_s + t_s[p], "pulse_index": (p + a).astype(np.int64),
              "channel": channel[p], "scan_angle_rad": angle[p].astype(np.float32),
              "frame": np.full(len(p), frame, np.int32)}
    if echoes.snr is not None:
        points["snr"] = echoes.snr.astype(np.float32)
    if getattr(echoes, "false_alarm", None) is not None:
        points["false_alarm"] = echoes.false_alarm.astype(np.uint8)
    return points


@kernel
def _gather_hits(prim, range_m, cos_theta, weight, material_ids, p_hit, mat_hit, cos_hit, range_hit, frac_hit):
    """The hits of a block's rays (m = len(weight) consecutive sub-rays per pulse), in ray order: pulse, material,
    cos θ, range and the sub-ray's energy fraction of each."""
    m = weight.shape[0]
    k = 0
    for q in range(prim.shape[0] // m):
        for j in range(m):
            i = q * m + j
            if prim[i] >= 0:
                p_hit[k], mat_hit[k] = q, material_ids[prim[i]]
                cos_hit[k], range_hit[k], frac_hit[k] = cos_theta[i], range_m[i], weight[j]
                k += 1


@kernel
def _hit_energies(prim, range_m, cos_theta, weight, material_ids, scale, two_sigma, aperture_r2, model, params, start,
                  angle_deg, brdf_per_sr, pulse_scale, scint, gate_start_s, gate_end_s, c, p_hit, range_hit, energy,
                  pulse_energy, tally):
    """:func:`_gather_hits`, the radiometry (:func:`~core.physics.radiometry.received_energy`'s kernel, a uniform
    extinction), the channel's energy scale (``pulse_scale``, one a pulse, or empty for none),
    :func:`_pulse_energy` and the gate tally (:func:`~core.engine.coverage.gate_tally`, into ``tally``) of a
    block's rays in one pass over its hits: each value by the same operations in the same order as those passes
    one after the other (bit for bit).  Returns (−1, 0), or (k, material) for the first hit k on a material index
    out of range (nothing after it done)."""
    m = weight.shape[0]
    scaled = pulse_scale.shape[0] > 0
    uniform = material_ids.shape[0] == 1  # (one material for every triangle: no look-up per hit)
    k = 0
    r_min, r_max, nan = np.inf, -np.inf, False
    for q in range(prim.shape[0] // m):
        for j in range(m):
            i = q * m + j
            if prim[i] < 0:
                continue
            mat = material_ids[0] if uniform else material_ids[prim[i]]
            if mat < 0 or mat >= model.shape[0]:
                return k, mat
            cos_t, r = cos_theta[i], range_m[i]
            f_r = material_brdf_at(model, params, start, angle_deg, brdf_per_sr, mat, cos_t)
            e = energy_at(scale, weight[j], f_r, cos_t, r, two_sigma, aperture_r2)
            if scaled:
                e = e * pulse_scale[q]
            e *= scint[q]
            pulse_energy[q] += e
            p_hit[k], range_hit[k], energy[k] = q, r, e
            tally_hit(r, e, gate_start_s, gate_end_s, c, tally)
            if k == 0:
                r_min, r_max = r, r
            if r != r:
                nan = True
            elif r < r_min:
                r_min = r
            elif r > r_max:
                r_max = r
            k += 1
    if k > 0:
        if nan:
            tally[6], tally[7] = np.nan, np.nan
        else:
            tally[6], tally[7] = r_min, r_max
    return -1, 0


@kernel
def _pulse_energy(p_hit, scint, energy, pulse_energy):
    """Each hit's energy times its pulse's scintillation factor, in place, and summed per pulse in hit order
    (``pulse_energy`` starts at zero)."""
    for k in range(p_hit.shape[0]):
        energy[k] *= scint[p_hit[k]]
        pulse_energy[p_hit[k]] += energy[k]


class _PointSink:
    """The scan's points, each block's appended in block order (``run_blocks``' ``each``) into whole-scan arrays
    of the products' types: each field allocated at a capacity of ``capacity`` points (one a pulse), of which
    only the pages written become resident, grown by half (``ndarray.resize``: ``realloc``, which moves the pages
    without copying them where the system can) when the points outgrow it, and shrunk in place to the points
    found at the end.  The blocks' own copies are dropped as they are appended: the points exist once, never as
    blocks plus their concatenation (which, the blocks' arrays left in the allocator's arenas, held them twice:
    the survey's peak).  (A capacity of pulses × detection.max_echoes would be reserved, and on some systems
    committed, up front: gigabytes for a long multi-echo scan.)"""

    def __init__(self, capacity: int):
        self.capacity, self.n, self.fields = max(1, int(capacity)), 0, None

    def append(self, part: dict) -> None:
        k = len(part["range_m"])
        if self.fields is None:
            self.fields = {name: np.empty((max(self.capacity, k),) + v.shape[1:], v.dtype)
                           for name, v in part.items()}
        elif self.n + k > len(self.fields["range_m"]):  # more points than planned: grow every field
            cap = max(self.n + k, int(1.5 * len(self.fields["range_m"])))
            for v in self.fields.values():
                v.resize((cap,) + v.shape[1:], refcheck=False)
        for name in [f for f in self.fields if f not in part]:  # (the fields every block has: as a concatenation)
            del self.fields[name]
        for name, v in self.fields.items():
            v[self.n:self.n + k] = part[name]
        self.n += k
        part.clear()

    def arrays(self) -> dict:
        """The points (the fields shrunk to their length); the sink is empty afterwards."""
        out = self.fields or {}
        for v in out.values():
            v.resize((self.n,) + v.shape[1:], refcheck=False)
        self.fields = None
        return out


# ----------------------------------------------------------------------------------------------------------
# The scan
# ----------------------------------------------------------------------------------------------------------
#: the stages of a scan in the order of the run record; StageLog.skip takes out those a run skips
STAGES_PLANNED = ("build_bvh", "rays", "trace", "radiometry", "waveform", "echoes", "products", "extinction",
                  "beam_broadening", "scintillation", "return_scintillation", "beam_wander", "weather_backscatter",
                  "weather_drops", "receiver_chain", "waveform_cube", "motion")


def simulate_scan(scene, world_from_sensor, config: SimulationConfig, *, frame: int = 0, tracer=None,
                  trajectory: Trajectory | None = None, start_time_s: float = 0.0, progress=None,
                  cancel=None, products=None) -> FrameResult:
    """Simulate one scan (one frame) of a time-of-flight scanner.  Returns a FrameResult whose images are None
    and whose ``points`` and ``pulses`` carry the products (see module docstring).  The sensor moves along
    ``trajectory`` (poses sampled in time) or stays at ``world_from_sensor``.  ``products``: the run folder being
    built (core.run.run_simulation: anything with fileio.run_folder.ProductFiles's ``zeros``): the saved waveforms
    are filled in place in its ``waveforms.npy``."""
    log = StageLog.of(("build_bvh", "rays", "trace", "radiometry", "waveform", "echoes", "products"), STAGES_PLANNED)
    fr = open_frame(scene, world_from_sensor if trajectory is None else None, config, log, tracer=tracer,
                    posed_by_trajectory=trajectory is not None)
    scene, tracer, times = fr.scene, fr.tracer, log.times
    if trajectory is None:
        trajectory = Trajectory.static(world_from_sensor)
    n_pulses = n_scan_pulses(config)
    gate, laser = config.gate, config.laser
    noisy = config.detector.mode == "noisy"
    if noisy:  # the noisy detection's modules and kernels, imported before the stage clocks (not in a stage's time)
        load_noisy_receiver()
    save = config.run.save_waveforms
    weight = beam_subrays(config.scanner.beam_subray_rings, laser.beam_profile)[2]
    m = len(weight)
    method = binning_method(laser, gate)
    table = PulseTable(laser, gate.bin_width_s) if laser.pulse_shape == "gaussian" and method == "exact" else None

    t0 = stage_clock()
    needs_ref = any(s not in turbulence_switches(config)
                    for s in ("beam_broadening", "scintillation", "beam_wander"))
    atm = scan_atmosphere(config, _reference_range(tracer, trajectory, config, n_pulses) if needs_ref else None)
    times["atmosphere"] = stage_clock() - t0
    for stage, reason in atm.skipped.items():
        log.skip(stage, reason)
    t0 = stage_clock()
    half_div = 0.5 * laser.beam_divergence_rad * atm.width_scale  # the receiver sees the beam's footprint
    wx = prepare_frame_weather(config, frame, n_pulses, np.pi * half_div ** 2, half_div, half_div, draw=False,
                               beams_at_once=SCAN_NOISE_TILE_PULSES, max_beam_fraction=float(weight.sum()))
    if wx is None:
        for stage, reason in weather_switches(config).items():
            log.skip(stage, reason)
    else:
        times["weather"] = stage_clock() - t0
        for stage, reason in weather_switches(config).items():
            log.skip(stage, reason)
    # the windowed route (no full-gate waveforms): one tabulated pulse at the sub-rays' energy centroid where it is
    # within its bound (scanner.pulse_model = centroid, core/physics/pulse_table.py)
    centroid = (table is not None and config.scanner.pulse_model == "centroid" and not (save or noisy)
                and wx is None)
    if centroid:
        table = CentroidPulseTable(laser, gate.bin_width_s)
    centroid_route = {}  # block start → (pulses on the centroid route, their largest bound ε)
    if not noisy:
        log.skip("receiver_chain", "detector.mode = ideal: echoes from the noise-free waveforms")
    if not save:
        log.skip("waveform_cube", "run.save_waveforms = false: per-pulse waveforms built in windows and discarded")
    if trajectory.is_static:
        log.skip("motion", "static sensor: one pose for every pulse")

    tile = SCAN_NOISE_TILE_PULSES
    per_block = max(1, config.run.chunk_rays // m)
    per_block = max(tile, (per_block // tile) * tile)
    if save or noisy or config.atmosphere.weather != "none":  # full-gate waveforms: bound the block's float64
        # waveform memory (~64 MiB)
        per_block = max(tile, min(per_block, (64 * 2**20 // (8 * gate.n_bins)) // tile * tile))
    blocks = item_blocks(n_pulses, per_block)
    waveforms = None if not save else np.zeros((n_pulses, gate.n_bins), np.float32) if products is None else \
        products.zeros("waveforms.npy", (n_pulses, gate.n_bins), np.float32)
    chain_settings = ChainSettings.from_config(config)
    chain_settings = dataclasses.replace(chain_settings, ifov_x_rad=laser.beam_divergence_rad,
                                         ifov_y_rad=laser.beam_divergence_y_rad or laser.beam_divergence_rad)
    # the pulse records, written by the blocks in place (their final types: no whole-scan temporaries)
    pulses = {"time_s": np.zeros(n_pulses), "gps_time_s": np.zeros(n_pulses), "origin_world": np.zeros((n_pulses, 3)),
              "direction_world": np.zeros((n_pulses, 3), np.float32), "channel": np.zeros(n_pulses, np.int16),
              "scan_angle_rad": np.zeros(n_pulses, np.float32), "n_echoes": np.zeros(n_pulses, np.int16),
              "received_energy_j": np.zeros(n_pulses)}

    window = gate_window_s(config)
    peak = peak_per_joule(config) if config.scanner.intensity_encoding != "amplitude" else None
    ch_scale = channel_energy_scale(config.scanner)  # None: every pulse at laser.pulse_energy_j
    tallies = {}  # block start → its hits against the range gate (engine/coverage.py)
    solar = noisy and solar_enabled(config)
    # clear air and a uniform extinction: the hits, their energies and the tally in one pass (_hit_energies)
    fused = wx is None and not isinstance(atm.extinction_per_m, LayeredExtinction)
    if fused:
        terms, mat_table = energy_terms(laser, config.receiver, atm.extinction_per_m), material_table(scene.materials)
        # a scene of one material index (a terrain): that index alone, read once instead of once a hit through
        # the hit triangle (a random read into a whole-scene array)
        hit_materials = scene.material_ids
        if len(hit_materials) > 1 and not np.any(hit_materials != hit_materials[0]):
            hit_materials = np.ascontiguousarray(hit_materials[:1])
        no_scale = np.zeros(0)  # (channel_energy_scale: float64, one a channel)
    if solar:  # each pulse's background from the sunlit scene (photons/s before η), in pulses.npz
        pulses["solar_background_photons_per_s"] = np.zeros(n_pulses)

    def process(block):
        a, b = block
        n = b - a
        local = {}
        t = stage_clock()
        wander = np.zeros((n, 2))
        scint = np.ones(n)
        for ta in range(a, b, tile):  # random streams per fixed tile of pulses
            tb = min(ta + tile, b)
            w_t, s_t = atm.draw(config, frame, ta // tile, tb - ta)
            wander[ta - a:tb - a], scint[ta - a:tb - a] = w_t, s_t
        t_s, channel, angle, origin, axis_world, d_world = scan_beams(
            config, trajectory, a, b, wander_rad=wander, width_scale=atm.width_scale)
        local["rays"] = stage_clock() - t
        t = stage_clock()
        prim, range_m, cos_theta = tracer.intersect(origin, d_world)
        local["trace"] = stage_clock() - t
        t = stage_clock()
        sun_rate = None
        if solar:  # sunlight the scene reflects into each pulse's receiver field of view (core/physics/solar.py)
            hit = np.flatnonzero(prim >= 0)
            sun_rate = pixel_solar_rates(config, atm.extinction_per_m, tracer, scene.materials,
                                         scene.material_ids[prim[hit]], np.repeat(origin, m, axis=0), d_world, prim,
                                         range_m, hit, hit // m, beam_solid_angle(laser) / m, n)
            pulses["solar_background_photons_per_s"][a:b] = sun_rate
        del d_world
        n_hit = int(np.count_nonzero(prim >= 0))
        drops_ret = frac_hit = None
        if fused:  # the hits, their energies, the pulses' energies and the gate tally in one compiled pass
            p_hit, range_hit, e, tallies[a] = np.empty(n_hit, np.int64), np.empty(n_hit), np.empty(n_hit), empty_tally()
            bad, mat = _hit_energies(prim, range_m, cos_theta, weight, hit_materials, *terms, *mat_table,
                                     no_scale if ch_scale is None else ch_scale[channel], scint, window[0], window[1],
                                     SPEED_OF_LIGHT_M_S, p_hit, range_hit, e, pulses["received_energy_j"][a:b],
                                     tallies[a])
            bad_material(0 if bad >= 0 else -1, np.array([mat]), len(scene.materials))
            del prim, range_m, cos_theta
            local["radiometry"] = stage_clock() - t
        else:
            p_hit, mat_hit = np.empty(n_hit, np.int64), np.empty(n_hit, scene.material_ids.dtype)
            cos_hit, range_hit, frac_hit = np.empty(n_hit), np.empty(n_hit), np.empty(n_hit)
            _gather_hits(prim, range_m, cos_theta, weight, scene.material_ids, p_hit, mat_hit, cos_hit, range_hit,
                         frac_hit)
            ray_range = np.where(prim >= 0, range_m, np.inf) if wx is not None and wx.weather.has_drops else None
            del prim, range_m, cos_theta
            e = received_energy(laser, config.receiver, atm.extinction_per_m, scene.materials, mat_hit, cos_hit,
                                range_hit, frac_hit)
            if ch_scale is not None:  # the channel's relative pulse energy (channel table, 4th column)
                e = e * ch_scale[channel[p_hit]]
            drops_ret = None
            if wx is not None and wx.weather.has_drops:  # the drops of each pulse tile (stream per tile)
                parts_d = []
                for ta in range(a, b, tile):
                    d = wx.draw(config, frame, min(ta + tile, b) - ta, ta // tile)
                    d.beam = d.beam + (ta - a)
                    parts_d.append(d)
                drops = parts_d[0] if len(parts_d) == 1 else type(parts_d[0])(
                    *(np.concatenate([getattr(d, f) for d in parts_d])
                      for f in ("beam", "range_m", "diameter_mm", "u")))
                drops_ret, shade = wx.block_returns(drops, np.repeat(np.arange(n), m), np.tile(weight, n), ray_range,
                                                    np.full(n, float(weight.sum())), p_hit, range_hit)
                e = e * shade
                if ch_scale is not None and drops_ret is not None:
                    drops_ret = (drops_ret[0], drops_ret[1], drops_ret[2] * ch_scale[channel[drops_ret[0]]])
                local["weather"] = stage_clock() - t
            _pulse_energy(p_hit, scint, e, pulses["received_energy_j"][a:b])
            tallies[a] = gate_tally(range_hit, e, window)
            local["radiometry"] = stage_clock() - t - local.get("weather", 0.0)
        t = stage_clock()
        t_rt = None if centroid else round_trip_time_s(range_hit)  # (the centroid kernel takes the ranges)
        dig = None
        if save or noisy or wx is not None:
            w_p, w_t, w_e, _ = merge_returns(p_hit, t_rt, e, None, drops_ret)
            wf = accumulate_waveforms(w_p, w_t, w_e, n, laser, gate, method)
            if wx is not None and ch_scale is None:
                add_volume_rows(wf, wx.template, np.full(n, float(weight.sum())), p_hit, t_rt, frac_hit, gate)
            elif wx is not None:  # the volume backscatter of each pulse at its channel's energy
                vol = np.zeros_like(wf)
                add_volume_rows(vol, wx.template, np.full(n, float(weight.sum())), p_hit, t_rt, frac_hit, gate)
                wf += (vol * ch_scale[channel][:, None]).astype(wf.dtype)
            if save:
                waveforms[a:b] = wf
            local["waveform"] = stage_clock() - t
            if noisy:
                t = stage_clock()
                parts = []
                for ta in range(0, n, tile):
                    tb = min(ta + tile, n)
                    cs = chain_settings if sun_rate is None else \
                        dataclasses.replace(chain_settings, pixel_background_rate=sun_rate[ta:tb][None])
                    chain = apply_receiver_chain(wf[ta:tb].astype(np.float32)[None], cs,
                                                 stage_seed(config.run.seed, frame, "receiver", (a + ta) // tile))
                    noise = chain.pixel_noise or chain.report
                    ech = noisy_echoes(chain.data, config, truth=wf[ta:tb], info={},
                                        noise_sigma=noise.get("noise_sigma"),
                                        noise_floor=chain.report.get("noise_sigma_floor", 0.0),
                                        noise_mean=noise.get("noise_mean"))
                    ech.pixel = ech.pixel + ta
                    parts.append(ech)
                    if dig is None:
                        dig = chain.report
                local["receiver_chain"] = stage_clock() - t
                echoes = _merge_echoes(parts)
            else:
                t = stage_clock()
                echoes = detect_echoes(wf, config.detection)
                local["echoes"] = stage_clock() - t
        elif centroid:
            echoes, n_c, eps = table.echoes_from_ranges(p_hit, range_hit, gate, e, n, config.detection)
            centroid_route[a] = (n_c, eps)
            local["waveform"] = stage_clock() - t
        else:
            echoes = windowed_echoes(p_hit, t_rt, e, n, config, method, table)
            local["waveform"] = stage_clock() - t  # waveform windows and echo detection together
        t = stage_clock()
        pts = _block_points(echoes, a, t_s, channel, angle, origin, axis_world, gate, start_time_s, frame,
                            config, atm.extinction_per_m, peak, ch_scale)
        if wx is not None:  # (the echoes the return mode kept, at their quantised ranges)
            pts["atmosphere"] = mark_atmosphere_echoes(config, pts["pulse_index"] - a, pts["range_m"], p_hit,
                                                       range_hit)
        pulses["time_s"][a:b], pulses["gps_time_s"][a:b] = t_s, start_time_s + t_s
        pulses["origin_world"][a:b], pulses["direction_world"][a:b] = origin, axis_world
        pulses["channel"][a:b], pulses["scan_angle_rad"][a:b] = channel, angle
        first = echoes.echo_index == 0
        pulses["n_echoes"][a:b][echoes.pixel[first]] = echoes.n_echoes[first]
        local["products"] = stage_clock() - t
        return pts, n_hit, local, dig

    threads = worker_threads(config.run.threads)
    sink = _PointSink(n_pulses)

    def append(result):  # (main thread, block order) the block's points into the scan's arrays
        t = stage_clock()
        sink.append(result[0])
        return (None, result[1], dict(result[2], products=result[2]["products"] + stage_clock() - t), result[3])

    results = run_blocks(process, blocks, threads, progress, label="pulse block", cancel=cancel, each=append)
    n_hits = sum(r[1] for r in results)
    for r in results:
        log.add_times(r[2])
    digitizer = results[0][3] if results else None
    t0 = stage_clock()
    points = sink.arrays()
    del results
    n_echo_per_pulse = pulses["n_echoes"]
    times["products"] += stage_clock() - t0
    stats = {"n_pulses": n_pulses, "subrays_per_pulse": m, "n_rays": n_pulses * m, "n_hits": n_hits,
             "n_points": int(len(points["range_m"])), "pulses_without_echo": int((n_echo_per_pulse == 0).sum()),
             "n_triangles": scene.n_triangles, "n_blocks": len(blocks), "pulses_per_block": per_block,
             "threads": max(1, min(threads, len(blocks))), "waveform_binning": method,
             "pulse_model": _pulse_model_record(config, table if centroid else None, centroid_route, n_pulses,
                                                save, noisy, wx is not None),
             "scan_duration_s": scan_duration_s(config), "stage_times_s": log.times,
             "wall_time_s": time.perf_counter() - fr.t_wall,
             "received_energy_j": float(pulses["received_energy_j"].sum()),
             "gate_coverage": coverage_record(config, add_tallies(tallies[k] for k in sorted(tallies))),
             "stages_run": log.ran, "stages_skipped": log.skipped, "memory_estimate_bytes": fr.memory["total"],
             "work_estimate_samples": fr.memory["work"],
             "notes": {"divergence_fills_fov": "ignored by the scanner: the beam is laser.beam_divergence_rad",
                       "receiver": "the receiver collects the whole footprint; width/height/fov unused"}}
    if atm.metadata:
        stats["atmosphere"] = atm.metadata
    if wx is not None:
        stats["weather"] = dict(wx.metadata, n_atmosphere_echoes=int(points["atmosphere"].sum())
                                if "atmosphere" in points else 0)
    if noisy:
        stats["receiver"] = dict(digitizer)
        if solar:  # (the first tile's record replaced by the whole scan's)
            stats["receiver"]["pixel_background"] = background_summary(pulses["solar_background_photons_per_s"])
        if "false_alarm" in points:
            n_fa = int(points["false_alarm"].sum())
            stats["receiver"]["false_alarms"] = {
                "n_false_alarms": n_fa, "per_pulse": n_fa / n_pulses,
                "rule": "an echo with no noise-free signal within 2 pulse widths (core.physics.detection.noisy)"}
    return FrameResult(range_image=None, intensity_image=None, energy_image=None, range_echoes=None,
                       intensity_echoes=None, points=points, waveforms=waveforms, stats=stats, pulses=pulses,
                       units=_scanner_units(config, noisy, stats),
                       tracer=tracer)


def _pulse_model_record(config, table, route: dict, n_pulses: int, save: bool, noisy: bool, weather: bool) -> dict:
    """Which pulse model ran (``scanner.pulse_model``) and, for the centroid model, on how many pulses."""
    if table is None:
        why = ("" if config.scanner.pulse_model == "subrays" else
               " (scanner.pulse_model = centroid applies to the ideal receiver's windowed waveforms of a Gaussian "
               "pulse binned exactly, in clear air, with run.save_waveforms = false; this run "
               + ("saves the waveforms" if save else "has the noisy receiver" if noisy else
                  "has weather" if weather else "bins its pulse otherwise") + ")")
        return {"model": "subrays", "requested": config.scanner.pulse_model, "note": "every sub-ray's return summed"
                                                                                     + why}
    n_c = int(sum(v[0] for v in route.values()))
    return {"model": "centroid", "requested": "centroid", "pulses_centroid": n_c,
            "pulses_subray_sum": n_pulses - n_c,
            "bound_relative_to_peak_bin": table.tolerance,
            "largest_bound": max((v[1] for v in route.values()), default=0.0),
            "note": "one tabulated pulse at the sub-rays' energy centroid with the second-moment correction "
                    "where its bound on every bin is within the tolerance of the pulse's peak bin, every "
                    "sub-ray summed elsewhere (core/physics/pulse_table.py; pulses without a return counted "
                    "with the sum)"}


def _scanner_units(config, noisy: bool, stats: dict) -> dict:
    units = product_units("scanner", stats["receiver"]["units"] if noisy else None)
    units["intensity"] = intensity_unit(config, units["intensity"])
    return units


def _reference_range(tracer, trajectory, config, n_pulses) -> float:
    """Median range of (up to 4096 evenly chosen) pulse axes that hit the scene: where turbulence is evaluated."""
    idx = np.unique(np.linspace(0, n_pulses - 1, min(n_pulses, 4096)).astype(np.int64))
    t_s, d_sensor, _, _ = pulse_schedule(config, indices=idx)
    origin, rot = trajectory.poses_at(t_s)
    prim, range_m, _ = tracer.intersect(origin, np.einsum("nij,nj->ni", rot, d_sensor))
    hits = range_m[prim >= 0]
    if len(hits) == 0:
        raise ConfigError("sensor", "sees nothing", "a scan pattern that hits geometry: no pulse axis hits the "
                                                    "scene (check the sensor's pose and the scan angles)")
    return float(np.median(hits))
