"""A preset against its data sheet: figures measured by running the simulator (no ``bpy``).

Each function runs :func:`core.run.simulate` on a small analytic scene and measures one figure the way a data
sheet states it:

* :func:`scan_geometry` — a scanner inside a closed box room (every pulse hits a wall): the vertical field of
  view from the points' elevations (the span of the outermost channels' axes, as data sheets quote it), the
  horizontal field of view from their azimuths, the channel count, and the points per second: the points of one
  revolution (or line) × the rotation (line) rate, the points of one pattern period / its duration otherwise;
* :func:`camera_geometry` — a camera facing a wall: detector columns × rows with a range, and the field of view
  from the pixels' directions (outer pixel centres' span + one pixel pitch);
* :func:`detection_probability` — the fraction of pulses (scanner) or pixel-frames (camera: its central
  ``PROBE_PIXELS``² pixels over as many independent frames as the trials asked for need, :func:`camera_frames`)
  that report an echo within ``RANGE_WINDOW_M`` of a Lambertian panel of a given reflectivity at a given range,
  normal to the line of sight and larger than the beam (or the camera's field); :func:`range_at_probability` —
  the range at which that fraction is a given probability (bisected);
* :func:`range_precision` — the standard deviation of those echoes' ranges (:func:`precision_stats` with their
  number, which sets the check's standard error); :func:`precision_at_snr` — the same
  where the echoes' median peak SNR is a stated SNR (the panel's range bisected);
* :func:`false_alarms_per_pulse` — a scanner's false alarms per pulse over a range window with nothing in the
  beam (:func:`derive_k_sigma` sets the detection threshold from a maker's false-alarm figure), and
  :func:`detection_stats` — a detection probability with the false alarms of the same pulses.

A maximum range is held to the maker's definition (:func:`range_definition`: the detection probability the
maker states, 0.5 where it states none), fired by the channel it is stated for (``second_range_channel``: that
channel's relative pulse energy); one from which the preset derives a value by the range equation
(``second_range_derives``) is checked for consistency (P within 3 binomial standard errors of the definition at
R, below it at 1.2 R); a figure a preset states it does not reproduce
(:func:`not_reproduced`, with the reason) is expected to fail its check.

The scanner's detection and precision probes keep the preset's laser, receiver, gate bin width, detection and
detector settings and hold the beam on the panel (a one-line raster of zero width at the preset's pulse rate):
the radiometry of a pulse does not depend on where the scan pattern points it.
"""
from __future__ import annotations

import copy
import math

import numpy as np

from ..config.settings import BRDFSettings, SimulationConfig
from ..config.tables import channel_table_deg
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from ..geometry.scene import SceneGeometry
from ..run import simulate
from . import preset_config

#: An echo within this distance of the panel counts as its detection (false alarms elsewhere do not count).
RANGE_WINDOW_M = 1.0
#: Bins of the probe's range gate (the panel in the middle): the noise estimate needs a stretch without signal.
PROBE_BINS = 512


def _panel(range_m: float, half_size_m: float, reflectivity: float) -> SceneGeometry:
    """A square Lambertian panel facing the sensor at ``range_m`` along −Z."""
    h, z = half_size_m, -range_m
    verts = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]], float)
    return SceneGeometry(verts, [[0, 1, 2], [0, 2, 3]], [0, 0],
                         [BRDFSettings(model="lambertian", reflectance=float(reflectivity))], ["panel"])


def _box_room(half_m: float) -> SceneGeometry:
    """A closed cube (inward faces do not matter to the tracer) of half side ``half_m`` around the origin."""
    h = half_m
    v = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return SceneGeometry(v, tris, [0] * len(tris), [BRDFSettings(reflectance=0.5)], ["wall"])


def _quiet(cfg: SimulationConfig) -> SimulationConfig:
    cfg = copy.deepcopy(cfg)
    cfg.run.save_waveforms = False
    cfg.run.threads = 1
    cfg.atmosphere.extinction_per_m = 0.0
    cfg.atmosphere.visibility_m = 0.0
    cfg.atmosphere.cn2_m_23 = 0.0
    return cfg


def _gate_on(cfg: SimulationConfig, range_m: float) -> None:
    """The range gate: the preset's bin width, ``PROBE_BINS`` bins with ``range_m`` in the middle."""
    g = cfg.gate
    g.n_bins = PROBE_BINS
    g.gate_start_s = max(0.0, 2.0 * range_m / SPEED_OF_LIGHT_M_S - 0.5 * PROBE_BINS * g.bin_width_s)


def _simulate(scene, cfg):
    return simulate(scene, np.eye(4), cfg, ground_truth=False)


def pattern_rate_hz(cfg: SimulationConfig) -> float:
    """Pattern periods per second: revolutions (rotating, palmer), lines (raster), mirror periods (oscillating)."""
    return cfg.scanner.scan_rate_hz


#: A Risley preset's field of view is measured over this long a scan: its rosette reaches the edge of its
#: field only at the petals' tips, which one 0.1 s frame samples sparsely.
RISLEY_FOV_S = 1.0
#: A Risley preset's field of view against the maker's: the prism parameters are fitted values (HELIOS++'s, the
#: makers publish none), whose envelope differs from the published figure by up to 0.2° (Mid-40: 38.32° vs
#: 38.4°; Avia: 70.62° × 77.06° vs 70.4° × 77.2°), so the FOV is checked to this tolerance, not to 1e-6°.
RISLEY_FOV_TOL_DEG = 0.25


def fov_tolerance_deg(cfg: SimulationConfig, key: str) -> float:
    """The tolerance of a scanner's field-of-view check: the Risley tolerance, 2 azimuth steps (rotating and
    others, horizontal) or 1e-6° (vertical: the outermost channels' axes)."""
    s = cfg.scanner
    if s.pattern == "risley":
        return RISLEY_FOV_TOL_DEG
    if key == "fov_h_deg":
        return 2 * math.degrees(2 * math.pi * s.scan_rate_hz / s.pulse_rate_hz) + 1e-6
    return 1e-6


def scan_geometry(cfg: SimulationConfig) -> dict:
    """Field of view, channels and points per second of a scanner preset, from one simulated pattern period in
    a box room (ideal detector, one ray per pulse); a Risley preset over ``RISLEY_FOV_S``, its field of view as
    the span of the directions' angles in the horizontal and vertical planes (atan2 of x and y over −z)."""
    cfg = _quiet(cfg)
    cfg.detector.mode = "ideal"
    cfg.scanner.beam_subray_rings = 0
    cfg.scanner.duration_s = RISLEY_FOV_S if cfg.scanner.pattern == "risley" else 0.0
    cfg.gate.gate_start_s, cfg.gate.bin_width_s = 0.0, max(cfg.gate.bin_width_s, 1e-9)
    cfg.gate.n_bins = int(math.ceil(2 * 30.0 * math.sqrt(3) / SPEED_OF_LIGHT_M_S / cfg.gate.bin_width_s)) + 64
    res = _simulate(_box_room(30.0), cfg)
    pts = res.points
    first = pts["echo_index"] == 1
    pos = pts["position_world"][first]
    d = pos / np.linalg.norm(pos, axis=1)[:, None]
    elevation = np.degrees(np.arcsin(np.clip(d[:, 1], -1, 1)))  # to +Y (the rotating head's axis)
    azimuth = np.degrees(np.arctan2(d[:, 0], -d[:, 2]))
    s = cfg.scanner
    if s.pattern == "rotating":
        # span of the azimuths fired: a full turn shows as 360° (the largest gap between sorted azimuths removed)
        az = np.sort(azimuth)
        gaps = np.diff(np.concatenate([az, az[:1] + 360.0]))
        step = float(np.median(gaps))
        fov_h = 360.0 - float(gaps.max()) + step
        fov_v = float(elevation.max() - elevation.min())
    else:
        fov_h = float(azimuth.max() - azimuth.min())
        fov_v = float(elevation.max() - elevation.min())
    if s.pattern == "risley":
        fov_h = float(np.ptp(np.degrees(np.arctan2(d[:, 0], -d[:, 2]))))
        fov_v = float(np.ptp(np.degrees(np.arctan2(d[:, 1], -d[:, 2]))))
    if s.pattern == "palmer":  # a cone about −Z: its full angles in the X–Z (across) and Y–Z (along) planes
        fov_h = float(np.ptp(np.degrees(np.arctan2(d[:, 0], -d[:, 2]))))
        fov_v = float(np.ptp(np.degrees(np.arctan2(d[:, 1], -d[:, 2]))))
    channels = int(np.unique(pts["channel"][first]).size)
    n_points = int(first.sum())
    period_s = float(res.stats["scan_duration_s"])
    return {"fov_h_deg": fov_h, "fov_v_deg": fov_v, "channels": channels,
            "points_per_s": n_points * pattern_rate_hz(cfg) if s.pattern == "rotating" else n_points / period_s,
            "n_points": n_points,
            "channel_elevations_deg": sorted({round(float(e), 6) for e in
                                              _channel_elevations(elevation, pts["channel"][first])})}


def _channel_elevations(elevation, channel):
    return [float(np.median(elevation[channel == c])) for c in np.unique(channel)]


def camera_geometry(cfg: SimulationConfig, distance_m: float = 50.0) -> dict:
    """Pixels with a range and the field of view of a camera preset (flash, profiler, gated), facing a wall."""
    cfg = _quiet(cfg)
    cfg.detector.mode = "ideal"
    cfg.receiver.subsamples = 1
    half = 2.0 * distance_m * math.tan(0.5 * max(cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad)) + 1.0
    _aim(cfg, distance_m)
    res = _simulate(_panel(distance_m, half, 0.8), cfg)
    r = np.asarray(res.range_image, float)
    ok = np.isfinite(r)
    rx = cfg.receiver
    # pixel centres' directions: the range image's pixels in the sensor frame (x right, y up, −z forward)
    tx = (np.arange(rx.width_px) + 0.5) / rx.width_px - 0.5
    ty = (np.arange(rx.height_px) + 0.5) / rx.height_px - 0.5
    ang_x = np.degrees(np.arctan(2 * tx * math.tan(0.5 * rx.fov_x_rad)))
    ang_y = np.degrees(np.arctan(2 * ty * math.tan(0.5 * rx.fov_y_rad)))
    cols, rows = np.nonzero(ok.any(axis=0))[0], np.nonzero(ok.any(axis=1))[0]
    pitch_x = float(np.diff(ang_x).mean()) if len(ang_x) > 1 else math.degrees(rx.fov_x_rad)
    pitch_y = float(np.diff(ang_y).mean()) if len(ang_y) > 1 else math.degrees(rx.fov_y_rad)
    return {"width_px": int(len(cols)), "height_px": int(len(rows)), "n_pixels": int(ok.sum()),
            "fov_h_deg": float(ang_x[cols].max() - ang_x[cols].min() + pitch_x),
            "fov_v_deg": float(ang_y[rows].max() - ang_y[rows].min() + pitch_y)}


def _aim(cfg: SimulationConfig, range_m: float) -> None:
    """A camera's gate (flash, profiler) or gate sweep (gated) around ``range_m``."""
    if cfg.system_type == "gated":
        g = cfg.gated
        span = (g.n_slices - 1) * g.delay_step_s
        g.first_delay_s = max(0.0, 2.0 * range_m / SPEED_OF_LIGHT_M_S - 0.5 * span - 0.5 * g.gate_width_s)
    else:
        _gate_on(cfg, range_m)


#: A camera's detection and precision probes use its central pixels (at most this many a side) ...
PROBE_PIXELS = 32
#: ... over as many independent frames as reach the probe's ``n`` trials (pixel-frames): 2000 trials are
#: 2 frames of 32 × 32 = 1024 pixels, so a camera's detection probability has the scanners' binomial standard
#: error (≤ 0.5/√2048 = 1.1 %) and its precision about 2000 ranges.  Frame k runs with seed + k × this stride.
CAMERA_SEED_STRIDE = 7919


def camera_frames(cfg: SimulationConfig, n: int) -> int:
    """Frames a camera probe runs: ⌈n / pixels of the probe window⌉ (at least one)."""
    rx = cfg.receiver
    pixels = min(rx.width_px, PROBE_PIXELS) * min(rx.height_px, PROBE_PIXELS)
    return max(1, -(-int(n) // pixels))


def _central_window(cfg: SimulationConfig) -> None:
    """Keep a camera's central ``PROBE_PIXELS``² pixels (same pixel footprint, the tan-plane grid cropped) and
    the beam as it was: a beam that filled the whole field of view keeps that divergence (its 1/e² radius on the
    full diagonal, core/physics/laser.py beam_half_angle_tan), so each kept pixel receives what it did."""
    rx, laser = cfg.receiver, cfg.laser
    if rx.width_px <= PROBE_PIXELS and rx.height_px <= PROBE_PIXELS:
        return
    tx, ty = math.tan(0.5 * rx.fov_x_rad), math.tan(0.5 * rx.fov_y_rad)
    if laser.divergence_fills_fov:
        laser.divergence_fills_fov = False
        laser.beam_divergence_rad = 2.0 * math.atan(math.hypot(tx, ty))
    w, h = min(rx.width_px, PROBE_PIXELS), min(rx.height_px, PROBE_PIXELS)
    rx.fov_x_rad = 2.0 * math.atan(tx * w / rx.width_px)
    rx.fov_y_rad = 2.0 * math.atan(ty * h / rx.height_px)
    rx.width_px, rx.height_px = w, h


#: The last scanner probe's false alarms (echoes outside ``RANGE_WINDOW_M`` of the panel) and the length of
#: range gate they were counted over (m): :func:`detection_stats` reads them.
_last_probe: dict = {}


def _gate_span_m(cfg: SimulationConfig) -> float:
    return cfg.gate.n_bins * cfg.gate.bin_width_s * SPEED_OF_LIGHT_M_S / 2.0


def _probe(cfg: SimulationConfig, range_m: float, reflectivity: float, n: int, seed: int,
           channel: int | None = None):
    """Ranges of the echoes near the panel and the number of trials (pulses or pixels).  ``channel`` (a scanner's
    channel-table row, from 1): the beam is that channel's, at its relative_pulse_energy (a one-channel rotating
    head along −Z turning 2π·10⁻³ rad/s: well within the panel for the probe's pulses)."""
    cfg = _quiet(cfg)
    cfg.run.seed = int(seed)
    if cfg.system_type == "scanner":
        s = cfg.scanner
        table = channel_table_deg(s) if channel is not None and s.pattern == "rotating" else None
        if table is not None and not 1 <= channel <= len(table):
            raise ConfigError("published.second_range_channel", channel,
                              f"a channel-table row from 1 to {len(table)}")
        if table is not None and table.shape[1] > 3:
            s.pattern, s.n_channels, s.scan_width_rad = "rotating", 1, 0.0
            s.channel_table, s.channel_table_file = [[0.0, 0.0, 0.0, float(table[channel - 1, 3])]], ""
            s.scan_rate_hz = 1e-3
        else:
            s.pattern, s.n_lines, s.scan_width_rad, s.scan_height_rad = "raster", 1, 0.0, 0.0
            s.scan_rate_hz = s.pulse_rate_hz / n
        s.duration_s = n / s.pulse_rate_hz
        s.beam_subray_rings = 0
        _gate_on(cfg, range_m)
        half = max(2.0, 3.0 * cfg.laser.beam_divergence_rad * range_m)
        res = _simulate(_panel(range_m, half, reflectivity), cfg)
        pts = res.points
        near = np.abs(pts["range_m"] - range_m) < RANGE_WINDOW_M
        idx = pts["pulse_index"][near]
        r = pts["range_m"][near]
        _, first = np.unique(idx, return_index=True)  # one detection per pulse (the first echo near the panel)
        _last_probe.update(false_alarms=int((~near).sum()), gate_m=_gate_span_m(cfg) - 2.0 * RANGE_WINDOW_M,
                           snr=np.asarray(pts["snr"][near][first], float) if "snr" in pts else None)
        return r[first], int(res.stats["n_pulses"])
    _central_window(cfg)
    rx = cfg.receiver
    half = 2.0 * range_m * math.tan(0.5 * max(rx.fov_x_rad, rx.fov_y_rad)) + 1.0
    _aim(cfg, range_m)
    scene = _panel(range_m, half, reflectivity)
    frames = camera_frames(cfg, n)
    kept, false_alarms, trials = [], 0, 0
    for k in range(frames):  # independent frames (seeds seed, seed + 7919, …) until n pixel trials
        cfg.run.seed = int(seed) + CAMERA_SEED_STRIDE * k
        r = np.asarray(_simulate(scene, cfg).range_image, float).ravel()
        near = np.isfinite(r) & (np.abs(r - range_m) < RANGE_WINDOW_M)
        kept.append(r[near])
        false_alarms += int((np.isfinite(r) & ~near).sum())
        trials += int(r.size)
    _last_probe.update(false_alarms=false_alarms, gate_m=math.nan, frames=frames)
    return np.concatenate(kept), trials


def detection_probability(cfg: SimulationConfig, range_m: float, reflectivity: float, n: int = 2000,
                          seed: int = 1) -> float:
    """Fraction of ``n`` pulses (scanner) or of the camera's pixel-frames (central pixels × ⌈n / pixels⌉
    frames) with an echo within ``RANGE_WINDOW_M`` of a Lambertian panel of ``reflectivity`` at ``range_m``."""
    r, trials = _probe(cfg, range_m, reflectivity, n, seed)
    return len(r) / trials


def detection_stats(cfg: SimulationConfig, range_m: float, reflectivity: float, n: int = 2000,
                    seed: int = 1, channel: int | None = None) -> dict:
    """:func:`detection_probability` with the false alarms of the same pulses: ``p`` (detection probability),
    ``trials``, ``false_alarms`` (a scanner's echoes farther than ``RANGE_WINDOW_M`` from the panel) and
    ``gate_m`` (the length of range gate they were counted over; NaN for a camera)."""
    _last_probe.clear()
    r, trials = _probe(cfg, range_m, reflectivity, n, seed, channel)
    return {"p": len(r) / trials, "trials": trials, **_last_probe}


def false_alarms_per_pulse(cfg: SimulationConfig, window_m: float, n: int = 200_000, seed: int = 4) -> float:
    """False alarms per pulse of a scanner preset over a range window [0, ``window_m``] with nothing in the beam
    (``n`` pulses into an empty gate of that length): the rate a maker's false-alarm figure is compared with."""
    cfg = _quiet(cfg)
    cfg.run.seed = int(seed)
    s = cfg.scanner
    s.pattern, s.n_lines, s.scan_width_rad, s.scan_height_rad = "raster", 1, 0.0, 0.0
    s.scan_rate_hz = s.pulse_rate_hz / n
    s.duration_s = n / s.pulse_rate_hz
    s.beam_subray_rings = 0
    g = cfg.gate
    g.gate_start_s = 0.0
    g.n_bins = max(16, int(math.ceil(2.0 * window_m / SPEED_OF_LIGHT_M_S / g.bin_width_s)))
    far = 10.0 * window_m + 1000.0  # a panel far outside the gate: the beam meets nothing within it
    res = _simulate(_panel(far, 1.0, 0.01), cfg)
    return len(res.points["range_m"]) / int(res.stats["n_pulses"])


def derive_k_sigma(cfg: SimulationConfig, rate_per_pulse: float, window_m: float, n: int = 200_000,
                   seed: int = 4, steps: int = 8) -> float:
    """The detection threshold (``detection.k_sigma``, calibrated mode) at which the scanner's false alarms
    over [0, ``window_m``] are ``rate_per_pulse`` (bisection on [3, 10] σ, ``n`` empty-gate pulses per step,
    the same seed at every step): how a preset's unpublished threshold is derived from its maker's
    false-alarm figure.  Resolution: the Poisson error of the count (1/√(rate·n), 22 % for 1e-4 × 2e5) over
    the slope d ln(rate)/dk (about 2 per σ on the shipped scanners), i.e. about 0.1 σ."""
    cfg = copy.deepcopy(cfg)
    lo, hi = 3.0, 10.0
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        cfg.detection.k_sigma = mid
        if false_alarms_per_pulse(cfg, window_m, n, seed) > rate_per_pulse:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def range_precision(cfg: SimulationConfig, range_m: float, reflectivity: float, n: int = 2000,
                    seed: int = 2) -> float:
    """Standard deviation (m) of the ranges of the panel's echoes (≥ 10 echoes needed, else NaN)."""
    return precision_stats(cfg, range_m, reflectivity, n, seed)["sigma_m"]


def precision_stats(cfg: SimulationConfig, range_m: float, reflectivity: float, n: int = 2000,
                    seed: int = 2) -> dict:
    """:func:`range_precision` with the number of echoes it is the standard deviation of (``n_echoes``; a
    camera's pixels that missed the panel give none) and of trials (``trials``): the check's standard error is
    σ/√(2(n_echoes − 1)), from the echoes actually measured."""
    r, trials = _probe(cfg, range_m, reflectivity, n, seed)
    sigma = float(np.std(r, ddof=1)) if len(r) >= 10 else float("nan")
    return {"sigma_m": sigma, "n_echoes": int(len(r)), "trials": int(trials)}


def precision_limit(sigma_published: float, n_echoes: int) -> float:
    """The most a simulated 1σ may exceed the published one: 3 relative standard errors of a standard
    deviation of ``n_echoes`` values, 1/√(2(n − 1)) each."""
    return sigma_published * (1 + 3 / math.sqrt(2 * (max(int(n_echoes), 2) - 1)))


def range_at_probability(cfg: SimulationConfig, reflectivity: float, p_def: float = 0.5, n: int = 2000,
                         seed: int = 26, lo_m: float = 1.0, hi_m: float = 1.0e5, steps: int = 16) -> float:
    """The range (m) at which a Lambertian panel of ``reflectivity`` is detected with probability ``p_def``:
    bisection in log range on [lo_m, hi_m] (``steps`` bisections, the same seed at every step; resolution
    (hi/lo)^(2^-steps), 1.0002 for the defaults, below the statistical one: the binomial error of P over the
    slope dP/d ln R).  The simulator's own maximum range, for a preset whose source states none, and for
    testing that a range check can fail."""
    a, b = math.log(lo_m), math.log(hi_m)
    for _ in range(steps):
        mid = 0.5 * (a + b)
        if detection_probability(cfg, math.exp(mid), reflectivity, n, seed) >= p_def:
            a = mid
        else:
            b = mid
    return math.exp(0.5 * (a + b))


def precision_at_snr(cfg: SimulationConfig, snr: float, reflectivity: float = 0.8, n: int = 2000,
                     seed: int = 25, steps: int = 12) -> dict:
    """A scanner's range precision where its echoes have the peak SNR ``snr`` (the points' ``snr``: peak
    amplitude over the raw waveform's noise σ): the panel's range is bisected in log range on [0.5 m, 10 km]
    until the median SNR of its echoes is ``snr`` (``steps`` bisections, the same seed at every step), then
    the standard deviation of the ranges there.  Returns ``range_m``, ``snr`` (the median reached),
    ``sigma_m`` and ``n_echoes``."""
    lo, hi = math.log(0.5), math.log(1.0e4)

    def probe(log_r):
        _last_probe.clear()
        r, _ = _probe(cfg, math.exp(log_r), reflectivity, n, seed)
        s = _last_probe.get("snr")
        return r, (float(np.median(s)) if s is not None and len(s) else 0.0)

    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if probe(mid)[1] > snr:
            lo = mid
        else:
            hi = mid
    r, med = probe(0.5 * (lo + hi))
    return {"range_m": math.exp(0.5 * (lo + hi)), "snr": med,
            "sigma_m": float(np.std(r, ddof=1)) if len(r) >= 10 else float("nan"), "n_echoes": int(len(r))}


def derive_pulse_energy(cfg: SimulationConfig, range_m: float, reflectivity: float, n: int = 2000,
                        seed: int = 3, steps: int = 16, p_def: float = 0.5) -> float:
    """The pulse energy at which the simulator detects a ``reflectivity`` panel at ``range_m`` with probability
    ``p_def`` (the maker's definition of its maximum range; ``n`` trials each): whole decades (10^k J) from the one nearest the preset's energy until the
    probability crosses p_def, then ``steps`` bisections in log energy inside that decade — the same result from
    any starting energy.  How a preset's unpublished pulse energy is derived from its maker's one
    maximum-range figure.  Its statistical resolution: the binomial error of P (≤ 0.5/√n) over the slope
    dP/d(ln E) at P = p_def (about 1 % in energy for n = 2000 on the shipped scanners)."""
    cfg = copy.deepcopy(cfg)

    def detected(log10_e):
        cfg.laser.pulse_energy_j = 10.0 ** log10_e
        return detection_probability(cfg, range_m, reflectivity, n, seed) >= p_def

    k = round(math.log10(cfg.laser.pulse_energy_j))
    if detected(k):
        while k > -30 and detected(k - 1):
            k -= 1
        lo, hi = k - 1, k
    else:
        while k < 2 and not detected(k + 1):
            k += 1
        lo, hi = k, k + 1
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if detected(mid):
            hi = mid
        else:
            lo = mid
    return 10.0 ** (0.5 * (lo + hi))


#: Pulses of the detection and precision probes (a camera: its central pixels).
N_PULSES = 2000


def range_definition(published: dict) -> float:
    """The detection probability at which the maker defines its maximum ranges (``range_detection_probability``;
    0.5 where the maker states none)."""
    return float(published.get("range_detection_probability", 0.5))


def not_reproduced(published: dict, key: str) -> str | None:
    """The preset's stated reason why the simulator does not reproduce the published figure ``key`` (its check
    is then expected to fail, and the test asserts that it does), else None."""
    return (published.get("not_reproduced") or {}).get(key)


def false_alarm_text(stats: dict, window_m: float | None) -> str:
    """The false alarms of a scanner probe, and their rate per pulse over the maker's range window [0, window_m]
    (scaled by the window over the gate they were counted in)."""
    k, n, gate = stats.get("false_alarms"), stats["trials"], stats.get("gate_m", math.nan)
    if k is None or not math.isfinite(gate):
        return ""
    text = f"; false alarms {k} in {n} pulses over {gate:.0f} m of gate"
    if window_m:
        scale = window_m / gate / n
        # none seen: the 95 % Poisson upper limit of 3.0 counts
        rate = f"< {3.0 * scale:.1e}" if k == 0 else f"{k * scale:.1e}"
        text += f" ({rate} per pulse over 0–{window_m:g} m)"
    return text


def data_sheet_rows(preset) -> list[dict]:
    """The preset's published figures next to the simulated ones, with the criterion each is held to (the same
    as tests/core/test_sensor_presets.py): rows of ``figure``, ``published``, ``simulated``, ``criterion``,
    ``ok`` (True / False; None for a figure shown but not checked, the one a value was derived from) and
    ``known`` (the preset's reason when the figure is one it states it does not reproduce: ``ok`` is then
    expected to be False).  Figures without a ``[published]`` key are left out."""
    pub, cfg = preset.published, preset_config(preset.path)
    p_def = range_definition(pub)
    window = pub.get("max_range_m")
    rows = []

    def row(key, figure, published, simulated, criterion, ok):
        rows.append({"key": key, "figure": figure, "published": published, "simulated": simulated,
                     "criterion": criterion, "ok": None if ok is None else bool(ok),
                     "known": not_reproduced(pub, key)})

    if {"fov_h_deg", "fov_v_deg", "channels", "points_per_s", "width_px", "height_px"} & set(pub):
        if cfg.system_type == "scanner":
            g = scan_geometry(cfg)
            risley = cfg.scanner.pattern == "risley"
            for key, label in (("fov_h_deg", "horizontal FOV"), ("fov_v_deg", "vertical FOV")):
                if key in pub:
                    tol = fov_tolerance_deg(cfg, key)
                    crit = (f"±{tol:g}° (fitted prism parameters, over {RISLEY_FOV_S:g} s)" if risley else
                            f"within 2 azimuth steps ({tol:.3f}°)" if key == "fov_h_deg" else "±0.000001°")
                    row(key, label, f"{pub[key]:g}°", f"{g[key]:.2f}°", crit, abs(g[key] - pub[key]) <= tol)
            if "channels" in pub:
                elev = g["channel_elevations_deg"]
                text = f"{g['channels']}" + (f" ({elev[0]:+.2f}° … {elev[-1]:+.2f}°)" if len(elev) > 1 else "")
                row("channels", "channels", f"{pub['channels']}", text, "equal", g["channels"] == pub["channels"])
            if "channel_elevations_deg" in pub:
                want, got = sorted(pub["channel_elevations_deg"]), g["channel_elevations_deg"]
                err = max((abs(a - b) for a, b in zip(got, want)), default=0.0) if len(got) == len(want) else math.inf
                row("channel_elevations_deg", "channel elevations",
                    f"{len(want)} angles, {want[0]:+g}° … {want[-1]:+g}°",
                    f"largest difference {err:.4f}°", "each within 0.01°", err <= 0.01)
            if "points_per_s" in pub:
                rate = f" at {pub['rotation_hz']:g} Hz" if "rotation_hz" in pub else ""
                row("points_per_s", "points per second" + rate, f"{pub['points_per_s']:,.0f}",
                    f"{g['points_per_s']:,.0f}", "±4 %", abs(g["points_per_s"] / pub["points_per_s"] - 1) <= 0.04)
        else:
            g = camera_geometry(cfg)
            for key, label in (("width_px", "columns"), ("height_px", "rows")):
                if key in pub:
                    row(key, f"detector {label}", f"{pub[key]}", f"{g[key]}", "equal", g[key] == pub[key])
            for key, label in (("fov_h_deg", "horizontal FOV"), ("fov_v_deg", "vertical FOV")):
                if key in pub:
                    row(key, label, f"{pub[key]:g}°", f"{g[key]:.3f}°", "±0.001°", abs(g[key] - pub[key]) <= 1e-3)
    if "false_alarm_rate" in pub and cfg.system_type == "scanner":
        rate = false_alarms_per_pulse(cfg, window, seed=31)  # another seed than the derivation's
        row("false_alarm_rate", f"false alarms per pulse over 0–{window:g} m (threshold derived from it)",
            f"{pub['false_alarm_rate']:.1e}", f"{rate:.1e}",
            "(not a check: detection.k_sigma is set so that the rate is the maker's)", None)
    if "max_range_m" in pub:
        st = detection_stats(cfg, pub["max_range_m"], pub["max_range_reflectivity"], N_PULSES, seed=3)
        row("max_range_m", f"max range @ {pub['max_range_reflectivity']:.0%} (energy derived from it)",
            f"{pub['max_range_m']:g} m", f"P = {st['p']:.2f}" + false_alarm_text(st, window),
            f"(not a check: the pulse energy is set so that P ≈ {p_def:g})", None)
    if "second_range_m" in pub:
        r, rho = pub["second_range_m"], pub["second_reflectivity"]
        ch = pub.get("second_range_channel")
        s1 = detection_stats(cfg, r, rho, N_PULSES, seed=21, channel=ch)
        s2 = detection_stats(cfg, 1.2 * r, rho, N_PULSES, seed=22, channel=ch)
        label = f"max range @ {rho:.0%}" + (f" (channel {ch})" if ch else "")
        sim = f"P = {s1['p']:.2f} at {r:g} m, {s2['p']:.2f} at {1.2 * r:g} m" + false_alarm_text(s1, window)
        if "second_range_derives" in pub:  # derived by the range equation: the simulator must agree with it
            se = math.sqrt(p_def * (1 - p_def) / s1["trials"])
            row("second_range_m", label + f" ({pub['second_range_derives']} derived from it)", f"{r:g} m", sim,
                f"P = {p_def:g} ± 3 binomial standard errors ({3 * se:.3f}) at R, < {p_def:g} at 1.2 R",
                abs(s1["p"] - p_def) <= 3 * se and s2["p"] < p_def)
        else:
            row("second_range_m", label, f"{r:g} m", sim, f"P ≥ {p_def:g} at R, < {p_def:g} at 1.2 R",
                s1["p"] >= p_def > s2["p"])
    if "detected_range_m" in pub:
        r, rho = pub["detected_range_m"], pub["detected_reflectivity"]
        p = detection_probability(cfg, r, rho, N_PULSES, seed=23)
        row("detected_range_m", f"detected @ {rho:.0%}", f"{r:g} m", f"P = {p:.2f}", f"P ≥ {p_def:g}", p >= p_def)
    for snr, sigma_pub in pub.get("precision_at_snr", []):
        st = precision_at_snr(cfg, snr, pub.get("precision_reflectivity", 0.8), N_PULSES)
        limit = precision_limit(sigma_pub, st["n_echoes"])
        row("precision_at_snr", f"precision (1σ) at SNR {snr:g}", f"{sigma_pub * 100:g} cm",
            f"{st['sigma_m'] * 100:.2f} cm at {st['range_m']:.1f} m (median SNR {st['snr']:.0f}, "
            f"{st['n_echoes']} echoes)", "≤ published + 3 standard errors", st["sigma_m"] <= limit)
    if "precision_m" in pub:
        rho = pub.get("precision_reflectivity", 0.5)
        st = precision_stats(cfg, pub["precision_range_m"], rho, N_PULSES, seed=24)
        s = st["sigma_m"]
        row("precision_m", f"precision (1σ) at {pub['precision_range_m']:g} m, {rho:.0%}",
            f"{pub['precision_m'] * 100:g} cm", f"{s * 100:.2f} cm ({st['n_echoes']} echoes)",
            "≤ published + 3 standard errors", s <= precision_limit(pub["precision_m"], st["n_echoes"]))
    return rows
