"""Products every system shares: points along the pixels' centre rays, the reference range of a frame, echoes
detected on the receiver's digital waveforms, and what every frame records after its system has run: the sensor
pose (and a moving scanner's trajectory) and the ground truth of its points."""
from __future__ import annotations

import threading
import weakref

import numpy as np

from ..config.settings import SimulationConfig
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from ..geometry.groundtruth import surface_material_ids
from ..geometry.motion import split_pose
from ..geometry.rays import tan_to_unit_direction
from ..geometry.scene import SceneGeometry
from ..jit import stage_clock
from ..physics.detection.peaks import Echoes
from ..threads import map_list
from .blocks import worker_threads
from .result import FrameResult


def load_noisy_receiver() -> None:
    """Import the noisy receiver's chain and detection modules (defining their kernels) now.  They are imported
    where used (:func:`noisy_echoes`, :func:`statistical_noisy_echoes`, the systems' chain calls), so an ideal
    receiver never loads them (issue 25: start-up); a system with a noisy receiver calls this before its stage
    clocks start, so that the imports are not counted in a stage's time."""
    from ..physics.detection import false_alarms, noisy, stretches  # noqa: F401
    from ..physics.receiver import chain, conversions  # noqa: F401


def threshold_model(config: SimulationConfig, noise_sigma=None, noise_mean=None):
    """(threshold mode that runs, the known noise values it is given): ``calibrated`` takes the chain report's
    exact signal-free σ and mean (per bin, white: the bins are independent) and needs both; without them (Geiger
    histograms have no linear noise model) it falls back to ``adaptive``.  Per-pixel values (arrays: the chain's
    ``pixel_noise`` with sunlight reflected by the scene) give each pixel its own threshold."""
    mode = config.detection.noisy_threshold_mode
    if mode != "calibrated":
        return mode, {}
    if noise_sigma is None or noise_mean is None or not np.all(np.asarray(noise_sigma) > 0) \
            or config.detector.detector_type == "geiger":
        return "adaptive", {}
    if np.ndim(noise_sigma) or np.ndim(noise_mean):
        return "calibrated", {"noise_sigma": np.asarray(noise_sigma, np.float64).reshape(-1),
                              "baseline": np.asarray(noise_mean, np.float64).reshape(-1)}
    return "calibrated", {"noise_sigma": float(noise_sigma), "baseline": float(noise_mean)}


def noisy_echoes(digital, config: SimulationConfig, *, truth=None, info=None, noise_sigma=None,
                 noise_floor=0.0, noise_mean=None, found=None, shape=None, extents=None) -> Echoes:
    """Echoes on the receiver's digital waveforms (threshold, matched filter, multi-echo, interpolation:
    core/physics/detection/noisy.py), in the per-echo layout of :class:`Echoes`, with the detection SNR.

    With ``truth`` (the noise-free waveforms the chain saw, (pixels, bins) J) every echo is classified as a
    true return or a false alarm (core.physics.detection.false_alarms.classify_false_alarms): the returned Echoes carries a
    per-echo bool ``false_alarm`` attribute and ``info`` (a dict) receives the counts, rates and the Gaussian
    expectation for the noise σ ``noise_sigma`` (raw-waveform units, from the chain report).  ``noise_floor``:
    the smallest noise σ the detection assumes (the chain report's ``noise_sigma_floor``).  ``noise_mean``: the
    signal-free bins' mean (the chain report's ``noise_mean``), the baseline of the calibrated threshold.
    ``found``: echoes already detected (core.physics.detection.stretches: no ``digital``), of the (H, W, B)
    ``shape``; ``extents``: the rows' signal extents the statistical route found (the classification then scans
    the signal stretches only: classify_false_alarms)."""
    # (here, not at the top: the noisy detection and its kernels load only when a noisy receiver runs)
    from ..physics.detection.false_alarms import FALSE_ALARM_ABS_PRIMARIES, classify_false_alarms
    from ..physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel
    from ..physics.receiver.conversions import photons_per_joule

    d, g = config.detection, config.gate
    h, w, n_bins = digital.shape if shape is None else shape
    pulse = gaussian_pulse_kernel(config.laser.pulse_fwhm_s, g.bin_width_s) \
        if d.matched_filter and config.laser.pulse_shape == "gaussian" else None
    threads = worker_threads(config.run.threads)
    mode, known = threshold_model(config, noise_sigma, noise_mean)
    if found is None:
        found = detect_echoes_noisy(digital.reshape(h * w, n_bins), g.bin_width_s, g.gate_start_s,
                                    threshold_mode=mode, threshold=d.threshold_counts,
                                    k_sigma=d.k_sigma, pulse=pulse, max_echoes=d.max_echoes,
                                    interpolation=d.interpolation, min_noise_sigma=noise_floor,
                                    threads=threads, **known)
    pix, slot = np.nonzero(found.detected)
    echoes = Echoes(pixel=pix.astype(np.int64), position_bins=found.position_bins[pix, slot],
                    amplitude=found.amplitude[pix, slot], echo_index=slot.astype(np.int16),
                    n_echoes=found.n_echoes[pix].astype(np.int16), snr=found.snr[pix, slot])
    if truth is not None:
        det = config.detector
        primaries_per_j = float(photons_per_joule(config.laser.wavelength_m)) * det.quantum_efficiency
        fa, summary = classify_false_alarms(
            found, np.asarray(truth).reshape(h * w, n_bins), config.laser.pulse_fwhm_s / g.bin_width_s,
            noise_sigma=noise_sigma if det.detector_type != "geiger" else None, pulse=pulse,
            abs_level=FALSE_ALARM_ABS_PRIMARIES / primaries_per_j, threads=threads, extents=extents)
        echoes.false_alarm = fa[pix, slot]
        summary["threshold_mode"] = mode
        summary["n_pixels"] = h * w
        summary["n_bins"] = n_bins
        if info is not None:
            info.update(summary)
    return echoes


def statistical_noisy_echoes(truth, config: SimulationConfig, seed, info=None, spans=None):
    """The noisy receiver's echoes with detection.signal_free_bins = "statistical" when it applies
    (core.physics.detection.stretches.validity), else None.  Returns (Echoes, chain report with
    ``detector_model``) or (None, the decision as a dict for the per-bin route's report).  ``spans``: (lo, hi)
    per pixel when ``truth`` is exactly 0 outside [lo, hi) (the binning's windows): only those bins are searched
    for each pixel's signal (the same results)."""
    from ..physics.detection.noisy import gaussian_pulse_kernel  # (as in noisy_echoes)
    from ..physics.detection.stretches import detect_statistical, validity
    from ..physics.receiver.chain import ChainSettings, apply_receiver_chain, apply_receiver_chains
    from ..physics.receiver.conversions import adc_step_e, photons_per_joule

    d, g, det = config.detection, config.gate, config.detector
    model = {"threshold": d.noisy_threshold_mode, "signal_free_bins": "per_bin"}
    if d.signal_free_bins != "statistical":
        model["reason"] = "detection.signal_free_bins = per_bin (the reference)"
        return None, model
    cs = ChainSettings.from_config(config)
    probe_out = apply_receiver_chain(np.zeros((1, 1, 1), np.float32), cs, 0)  # the noise model only
    probe, law = probe_out.report, probe_out.noise_pmf
    pulse = gaussian_pulse_kernel(config.laser.pulse_fwhm_s, g.bin_width_s) \
        if d.matched_filter and config.laser.pulse_shape == "gaussian" else None
    mode, _ = threshold_model(config, probe.get("noise_sigma"), probe.get("noise_mean"))
    route, reason, err = validity(probe, det, pulse, d.k_sigma, mode, config.run.save_counts, law is not None)
    model.update(threshold=mode, reason=reason, gaussian_tail_error=err)
    if route != "statistical":
        return None, model
    gain = 1.0 if det.detector_type == "pin" else det.apd_gain
    step = adc_step_e(det.adc_bits, det.adc_full_scale_e) if det.enable_adc else 1.0
    codes_per_j = float(photons_per_joule(config.laser.wavelength_m)) * det.quantum_efficiency * gain / step
    reports = []

    def chain(cube, ss):
        out = apply_receiver_chain(cube, cs, ss)
        reports.append(out.report)
        return out.data, out.report

    def chains(cubes, seeds):
        outs = apply_receiver_chains(cubes, cs, seeds)
        reports.extend(o.report for o in outs)
        return [(o.data, o.report) for o in outs]

    h, w, n_bins = truth.shape
    extents = {}
    found, sinfo = detect_statistical(truth.reshape(h * w, n_bins), chain, probe, pulse=pulse, k_sigma=d.k_sigma,
                                      max_echoes=d.max_echoes, interpolation=d.interpolation,
                                      bin_width_s=g.bin_width_s, gate_start_s=g.gate_start_s,
                                      codes_per_joule=codes_per_j, seed=seed,
                                      min_noise_sigma=probe.get("noise_sigma_floor", 0.0), noise_law=law,
                                      threads=worker_threads(config.run.threads), extents_out=extents,
                                      spans=spans, chains=chains)
    report = dict(reports[0] if reports else probe)
    for key in ("n_adc_low", "n_adc_high", "n_mean_clipped"):
        report[key] = int(sum(r.get(key, 0) for r in reports))
    model.update(signal_free_bins="statistical", **sinfo)
    report["detector_model"] = model
    fa_info = {} if info is None else info
    echoes = noisy_echoes(None, config, truth=truth, info=fa_info, noise_sigma=probe.get("noise_sigma"),
                          noise_floor=probe.get("noise_sigma_floor", 0.0), noise_mean=probe.get("noise_mean"),
                          found=found, shape=truth.shape, extents=extents)
    report["false_alarms"] = fa_info
    return echoes, report


#: Reference ranges already traced, per tracer (its geometry is fixed once built): (pixel grid, pose) → range.
#: A static sensor's frames (a flash sequence from one pose, a benchmark's repeats) trace the 16k pixel-centre
#: rays once; a moving sensor's poses differ and are traced each (at most _REFERENCE_KEEP kept per tracer).
_REFERENCE_RANGES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_REFERENCE_KEEP = 16
_REFERENCE_LOCK = threading.Lock()


def reference_range_m(tracer, det, origin, rot, threads: int = 1) -> float:
    """Median range of the pixel-centre rays that hit the scene: where the turbulence is evaluated.  The rays are
    traced in ``threads`` parts on the shared pool (each ray's range does not depend on the parts).  Kept per
    tracer for the pixel grid and pose (the same rays give the same median: a kept value is the traced one)."""
    o, r = np.ascontiguousarray(origin, np.float64), np.ascontiguousarray(rot, np.float64)
    key = (int(det.width_px), int(det.height_px), float(det.half_width_tan), float(det.half_height_tan),
           o.tobytes(), r.tobytes())
    with _REFERENCE_LOCK:
        kept = _REFERENCE_RANGES.get(tracer)
        if kept is not None and key in kept:
            return kept[key]
    value = _trace_reference_range(tracer, det, origin, rot, threads)
    with _REFERENCE_LOCK:
        kept = _REFERENCE_RANGES.setdefault(tracer, {})
        if len(kept) >= _REFERENCE_KEEP:
            kept.clear()
        kept[key] = value
    return value


def _trace_reference_range(tracer, det, origin, rot, threads):
    """:func:`reference_range_m` traced."""
    pix = np.arange(det.n_pixels)
    xt, yt = det.pixel_center_tan(pix % det.width_px, pix // det.width_px)
    dirs = tan_to_unit_direction(np.asarray(xt, float), np.asarray(yt, float)) @ rot.T
    prim, range_m = np.empty(len(dirs), np.int32), np.empty(len(dirs))

    def trace(part):
        a, b = part
        prim[a:b], range_m[a:b], _ = tracer.intersect(origin, dirs[a:b])

    step = -(-len(dirs) // max(1, threads))
    map_list(trace, [(a, min(a + step, len(dirs))) for a in range(0, len(dirs), step)], threads)
    hits = range_m[prim >= 0]
    if len(hits) == 0:
        raise ConfigError("sensor", "sees nothing", "a field of view containing geometry: no pixel-centre ray "
                                                    "hits the scene (check the sensor's pose and field of view)")
    return float(np.median(hits))


def points_along_rays(det, origin, rot, pixel, range_m, amp, echo_index, n_echoes, time_s, frame):
    """Point cloud: each echo placed along its pixel's centre ray (sensor and world coordinates)."""
    px, py = pixel % det.width_px, pixel // det.width_px
    xt, yt = det.pixel_center_tan(px, py)
    d_sensor = tan_to_unit_direction(np.asarray(xt, float), np.asarray(yt, float))
    pos_sensor = d_sensor * range_m[:, None]
    pos_world = origin + pos_sensor @ rot.T
    return {"position_world": pos_world, "position_sensor": pos_sensor,
            "intensity": amp.astype(np.float32), "range_m": range_m.astype(np.float64),
            "echo_index": (echo_index + 1).astype(np.int16), "n_echoes": n_echoes.astype(np.int16),
            "pixel_x": px.astype(np.int32), "pixel_y": py.astype(np.int32), "time_s": time_s,
            "frame": np.full(len(range_m), frame, np.int32)}


def pose_record(world_from_sensor) -> dict:
    """A sensor pose as metadata: the 4×4 sensor→world matrix, position (m) and orientation (unit quaternion,
    scalar first).  The sensor frame is Blender's camera frame: +X right, +Y up, looking along −Z."""
    from scipy.spatial.transform import Rotation

    m = np.asarray(world_from_sensor, dtype=np.float64)
    origin, rot = split_pose(m)
    x, y, z, w = Rotation.from_matrix(rot).as_quat()
    return {"world_from_sensor": m.tolist(), "position_m": origin.tolist(), "quaternion_wxyz": [w, x, y, z],
            "frame": "sensor +X right, +Y up, looking along -Z (Blender camera); world = Blender world, metres"}


def record_pose(result: FrameResult, world_from_sensor, trajectory=None) -> None:
    """``stats["sensor_pose"]`` (the frame's pose, :func:`pose_record`) and, for a moving scanner,
    ``stats["trajectory"]``: the sampled poses it flew (times from the scan's start, positions, quaternions)."""
    result.stats["sensor_pose"] = pose_record(world_from_sensor)
    if trajectory is not None and not trajectory.is_static:
        from scipy.spatial.transform import Rotation

        origins, rots = zip(*(split_pose(m) for m in trajectory.matrices))
        q = Rotation.from_matrix(np.array(rots)).as_quat()
        result.stats["trajectory"] = {"times_s": trajectory.times_s.tolist(),
                                      "position_m": np.array(origins).tolist(),
                                      "quaternion_wxyz": q[:, [3, 0, 1, 2]].tolist(),
                                      "note": "sensor poses sampled over the scan, interpolated per pulse "
                                              "(linear positions, slerp orientations); pulses.npz holds each "
                                              "pulse's origin and direction"}


def ground_truth_tolerance(config: SimulationConfig) -> tuple:
    """(range tolerance m, angular spread rad) within which a point is on a surface (:func:`label_points`)."""
    spread_s = 2.0 * config.laser.pulse_fwhm_s + 4.0 * config.gate.bin_width_s
    if config.system_type == "gated":
        spread_s += config.gated.gate_width_s + config.gated.delay_step_s
    rx = config.receiver
    if config.system_type == "scanner":  # the beam's footprint half-width
        spread_rad = 0.5 * max(config.laser.beam_divergence_rad, config.laser.beam_divergence_y_rad)
    elif config.system_type == "profiler":  # one element over the whole field of view
        spread_rad = 0.5 * max(rx.fov_x_rad, rx.fov_y_rad)
    else:  # half a pixel
        spread_rad = 0.5 * max(rx.fov_x_rad / rx.width_px, rx.fov_y_rad / rx.height_px)
    return 0.5 * SPEED_OF_LIGHT_M_S * spread_s, spread_rad


#: Rings of lines filling the profiler's footprint (core.geometry.groundtruth ``fill_rings``): 32 rings, 4,224
#: lines, 0.19 mrad apart over a 12 mrad field of view (0.4 m at 2 km), for the few echoes the rim leaves unlabelled.
PROFILER_FILL_RINGS = 32


def ground_truth_fill_rings(config: SimulationConfig) -> int:
    """Rings of lines filling the footprint for points its centre and rim leave unlabelled: the profiler's one
    element sees objects far smaller than its field of view (``PROFILER_FILL_RINGS``); 0 for pixels and beams."""
    return PROFILER_FILL_RINGS if config.system_type == "profiler" else 0


def label_points(result: FrameResult, scene: SceneGeometry, world_from_sensor, config: SimulationConfig, *,
                 needed: bool = True) -> None:
    """Ground truth of the frame's points (core.geometry.groundtruth): ``points["material_id"]`` (−1: no surface near)
    and the scene's material names in ``stats["material_names"]``; a false alarm keeps its label (its flag says
    it is noise).  The tolerance: c/2 × (2 pulse widths + 4 bins, + the gate width and delay step when gated);
    the lines of sight spread over half a pixel (the beam's half divergence for the scanner, half the field of
    view for the profiler).  The points are labelled on the run's threads (``run.threads``) of the shared pool.
    In the stage plan (``stages_run`` / ``stages_skipped``): skipped when ``needed`` is false (the caller writes
    no product that holds it) or when there is no traced scene or no point positions."""
    pts = result.points
    if not needed or result.tracer is None or "position_world" not in pts:
        result.stats.setdefault("stages_skipped", {})["ground_truth"] = (
            "no product of this run uses the points' materials" if not needed
            else "no traced scene or no point positions")
        return
    if result.pulses is not None and "pulse_index" in pts:
        origin = np.asarray(result.pulses["origin_world"])[pts["pulse_index"]]
    else:
        origin = np.asarray(world_from_sensor, dtype=np.float64)[:3, 3]
    tolerance_m, spread_rad = ground_truth_tolerance(config)
    t0 = stage_clock()
    pts["material_id"] = surface_material_ids(result.tracer, scene.material_ids, origin, pts["position_world"],
                                              tolerance_m, spread_rad,
                                              threads=worker_threads(config.run.threads),
                                              fill_rings=ground_truth_fill_rings(config))
    result.stats.setdefault("stages_run", []).append("ground_truth")
    result.stats["material_names"] = list(scene.material_names)
    result.stats.setdefault("stage_times_s", {})["ground_truth"] = stage_clock() - t0
