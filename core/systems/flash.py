"""One frame of a 3D flash ladar (paper Figure 4), stage by stage.

    rays → trace → radiometry (eq. 3-1) → waveform (pulse ⊛ impulse response) → echoes → products

The receiver is processed in blocks of whole pixels (``run.chunk_rays`` rays at most, and a bounded waveform
size), on a thread pool; each block is independent, so the products do not depend on the thread count or block
size.  The full waveform cube is allocated only when it is to be saved.
"""
from __future__ import annotations

import dataclasses
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..version import __version__
from ..errors import Cancelled, ConfigError
from ..config.settings import SimulationConfig, config_to_dict, validate
from ..physics.detection.peaks import Echoes, detect_echoes, detect_echoes_windows
from ..physics.detection.noisy import detect_echoes_noisy, gaussian_pulse_kernel
from ..physics.receiver.chain import ChainSettings, apply_receiver_chain
from ..physics.laser import cell_energy_fractions
from ..geometry.motion import split_pose
from ..physics.propagation import (blur_cube_and_image, effective_extinction_per_m, prepare_frame_atmosphere,
                                   stage_seed, turbulence_switches)
from ..physics.radiometry import received_energy
from ..geometry.rays import Detector, tan_to_unit_direction
from ..fileio.run_folder import software_versions, write_run_files
from ..fileio.staging import claim_run_dir
from ..geometry.culling import frustum_triangles
from ..engine.memory import BLOCK_WAVEFORM_BYTES, check_flash_memory
from ..physics.sampling import SubraySampler, adaptive_tolerance_m, cell_returns
from ..geometry.scene import SceneGeometry
from ..geometry.trace import SceneTracer
from ..constants import SPEED_OF_LIGHT_M_S
from ..physics.waveform import accumulate_waveform_windows, binning_method, round_trip_time_s

STAGES = ("build_bvh", "rays", "trace", "radiometry", "waveform", "echoes", "products")


@dataclass
class FrameResult:
    range_image: np.ndarray       # (H, W) float32, first echo range (m), NaN where none
    intensity_image: np.ndarray   # (H, W) float32, first echo peak (J per bin), 0 where none
    energy_image: np.ndarray      # (H, W) float64, received energy per pixel before binning (J)
    range_echoes: np.ndarray      # (H, W, E) float32, echoes in time order, NaN where none
    intensity_echoes: np.ndarray  # (H, W, E) float32
    points: dict                  # per-point arrays (see _points)
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


def plan(config: SimulationConfig) -> dict:
    """Which stages this run executes and which it skips (with the reason)."""
    skipped = {}
    if effective_extinction_per_m(config) == 0.0:
        skipped["extinction"] = "no extinction (extinction_per_m = 0 and no visibility)"
    skipped.update(turbulence_switches(config))
    if config.detector.mode == "ideal":
        skipped["receiver_chain"] = ("detector.mode = ideal: no photon, speckle, dark, gain, read-out or A/D "
                                     "noise; echoes from the noise-free waveforms")
    keeps_cube = (config.run.save_waveforms or "turbulence_blur" not in skipped
                  or "receiver_chain" not in skipped)
    if not keeps_cube:
        skipped["waveform_cube"] = ("run.save_waveforms = false: waveforms are built per block for echo "
                                    "detection and discarded")
    optional = ("extinction", "beam_broadening", "scintillation", "return_scintillation", "beam_wander",
                "turbulence_blur", "receiver_chain", "waveform_cube")
    ran = list(STAGES) + [s for s in optional if s not in skipped]
    return {"stages_run": ran, "stages_skipped": skipped}


def simulate_frame(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, *, frame: int = 0,
                   tracer: SceneTracer | None = None, progress=None, cancel=None,
                   fov_culling: bool = True) -> FrameResult:
    """Simulate one flash-ladar frame.  Raises ConfigError on bad input, Cancelled if ``cancel()`` is true.

    ``tracer``: a SceneTracer built on this scene's geometry (static scenes: one BVH for all frames); otherwise
    one is built, on the triangles inside the field of view only when ``fov_culling`` (core/geometry/culling.py)."""
    t_wall = time.perf_counter()
    validate(config)
    memory = check_flash_memory(config)  # refuse, naming the setting to change, what would not fit
    scene = scene.with_overrides(config.materials)
    scene.check()
    origin, rot = split_pose(world_from_sensor)
    times = dict.fromkeys(STAGES, 0.0)
    det = Detector.from_settings(config.receiver)
    run_plan = plan(config)

    t0 = time.perf_counter()
    culling = {}
    if tracer is None or not tracer.serves(scene):
        keep = None
        if fov_culling:  # objects outside the field of view are not traced
            keep = frustum_triangles(scene.vertices_m, scene.triangles, origin, rot, det.half_width_tan,
                                     det.half_height_tan)
            culling = {"triangles_traced": int(keep.sum()), "triangles_total": scene.n_triangles,
                       "time_s": time.perf_counter() - t0}
            run_plan["stages_run"].append("fov_culling")
        else:
            run_plan["stages_skipped"]["fov_culling"] = "fov_culling = False: the whole scene is traced"
        tracer = SceneTracer(scene, keep=keep)
        culling["bvh"] = "built on the triangles in the field of view" if keep is not None else "built"
    else:
        culling["bvh"] = "reused"
        run_plan["stages_skipped"]["fov_culling"] = ("static geometry: the given BVH of the whole scene is reused "
                                                     "(no rebuild, no culling)")
        run_plan["stages_skipped"]["build_bvh"] = "static geometry: the given BVH is reused"
        run_plan["stages_run"] = [s for s in run_plan["stages_run"] if s != "build_bvh"]
    times["build_bvh"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    needs_reference = any(s not in run_plan["stages_skipped"]
                          for s in ("beam_broadening", "scintillation", "beam_wander", "turbulence_blur"))
    atm = prepare_frame_atmosphere(config, det, _reference_range(tracer, det, origin, rot) if needs_reference
                                   else None, frame)
    times["atmosphere"] = time.perf_counter() - t0
    for stage, reason in atm.skipped.items():  # decided with the frame's geometry (e.g. negligible blur)
        if stage not in run_plan["stages_skipped"]:
            run_plan["stages_skipped"][stage] = reason
            run_plan["stages_run"] = [s for s in run_plan["stages_run"] if s != stage]
    fx, fy = cell_energy_fractions(config.laser, det, atm.beam_offset_tan, atm.beam_width_scale)
    gate = config.gate
    blur = atm.blur_r0_m is not None
    noisy = config.detector.mode == "noisy"
    whole_cube = blur or noisy  # echoes are detected after a whole-cube stage
    method = binning_method(config.laser, gate)
    s2 = det.rays_per_pixel
    per_block = max(1, min(config.run.chunk_rays // s2, BLOCK_WAVEFORM_BYTES // (8 * gate.n_bins)))
    # several threads: at least 4 blocks each when the frame allows (≥ 8192 rays a block): blocks differ in
    # cost (sky, near ground), so a few big ones leave a thread idle (bench_scaling: 2 threads 1.0× → 1.6×)
    n_threads = config.run.threads or os.cpu_count() or 1
    if n_threads > 1:
        per_block = min(per_block, max(-(-det.n_pixels // (4 * n_threads)), -(-8192 // s2)))
    blocks = [(a, min(a + per_block, det.n_pixels)) for a in range(0, det.n_pixels, per_block)]
    keep_cube = config.run.save_waveforms or whole_cube
    waveforms = np.zeros((det.n_pixels, gate.n_bins), np.float32) if keep_cube else None
    energy = np.zeros(det.n_pixels)
    max_spread_s = 1000.0 * gate.n_bins * gate.bin_width_s
    rx = config.receiver
    fine = None
    if rx.subray_pattern == "adaptive":
        det_fine = dataclasses.replace(det, subsamples=det.subsamples * rx.subray_refine)
        fine = cell_energy_fractions(config.laser, det_fine, atm.beam_offset_tan, atm.beam_width_scale)
    sampler = SubraySampler(det, rx.subray_pattern, (fx, fy), config.run.seed, laser=config.laser,
                            beam_offset_tan=atm.beam_offset_tan, beam_width_scale=atm.beam_width_scale,
                            refine=rx.subray_refine, fine_fractions=fine)
    refined = []  # (refined pixels, rays) per block, adaptive pattern

    def trace_tan(x_tan, y_tan):
        return tracer.intersect(origin, tan_to_unit_direction(x_tan, y_tan) @ rot.T)

    def process(block):
        if cancel is not None and cancel():
            raise Cancelled()
        a, b = block
        local = {}
        t = time.perf_counter()
        smp = sampler.block(a, b)  # receiver.subray_pattern (core/physics/sampling.py)
        local["rays"] = time.perf_counter() - t
        t = time.perf_counter()
        prim, range_m, cos_theta = trace_tan(smp.x_tan, smp.y_tan)
        local["trace"] = time.perf_counter() - t
        if sampler.adaptive:  # second pass over the pixels whose rays disagree
            t = time.perf_counter()
            smp, (prim, range_m, cos_theta), bad = sampler.refine_pass(
                smp, (prim, range_m, cos_theta), trace_tan, lambda p: tracer.unit_normal[p] @ rot,
                scene.material_ids, adaptive_tolerance_m(config.laser, gate))
            refined.append((len(bad), (b - a) * s2 + len(bad) * (det.subsamples * rx.subray_refine) ** 2))
            local["refine"] = time.perf_counter() - t
        x_tan, y_tan, pixel, sub_x, sub_y, fraction = smp.x_tan, smp.y_tan, smp.pixel, smp.sub_x, smp.sub_y, smp.weight
        t = time.perf_counter()
        hit = prim >= 0
        spread, range_hit, cos_hit = None, range_m[hit], cos_theta[hit]
        if config.receiver.cell_range_spread:  # each cell's surface spans a range interval (core/physics/sampling.py)
            spread, range_hit, cos_hit = cell_returns(smp.take(hit), range_hit, cos_hit,
                                                      tracer.unit_normal[prim[hit]] @ rot, max_spread_s)
        e = received_energy(config.laser, config.receiver, atm.extinction_per_m, scene.materials,
                            scene.material_ids[prim[hit]], cos_hit, range_hit, fraction[hit])
        if atm.pattern is not None:
            e *= atm.scintillation_at(x_tan[hit], y_tan[hit], sub_x[hit], sub_y[hit])
        pix_local = pixel[hit] - a
        energy[a:b] = np.bincount(pix_local, weights=e, minlength=b - a)
        local["radiometry"] = time.perf_counter() - t
        t = time.perf_counter()
        # only pixels with returns get a waveform row (the others stay zero)
        active = np.unique(pix_local)
        # one window of bins per pixel: a short return in a long gate costs its window only
        wf = accumulate_waveform_windows(np.searchsorted(active, pix_local), round_trip_time_s(range_hit), e,
                                         len(active), config.laser, gate, method, spread_s=spread)
        if waveforms is not None:
            wf.scatter_into(waveforms, a + active)
        local["waveform"] = time.perf_counter() - t
        if whole_cube:  # echoes are detected after the whole-cube stages
            return None, int(hit.sum()), local
        t = time.perf_counter()
        echoes = detect_echoes_windows(wf, config.detection)
        echoes.pixel = active[echoes.pixel] + a
        local["echoes"] = time.perf_counter() - t
        return echoes, int(hit.sum()), local

    threads = config.run.threads or os.cpu_count() or 1
    results = []
    with ThreadPoolExecutor(max_workers=min(threads, len(blocks))) as pool:
        for i, res in enumerate(pool.map(process, blocks)):
            results.append(res)
            if progress is not None:
                progress((i + 1) / len(blocks), f"block {i + 1}/{len(blocks)}")
    n_hits = sum(r[1] for r in results)
    for _, _, local in results:
        for k, v in local.items():
            times[k] = times.get(k, 0.0) + v
    if n_hits == 0:
        raise ConfigError("sensor", "sees nothing",
                          f"a field of view containing geometry: all {det.n_pixels * s2} rays missed the "
                          f"{scene.n_triangles} triangles of the scene (check the sensor's pose and field of view)")

    energy_image = energy.reshape(det.height_px, det.width_px)
    digital = None
    receiver_report = None
    if blur:
        t0 = time.perf_counter()
        cube = waveforms.reshape(det.height_px, det.width_px, gate.n_bins)
        energy_image = blur_cube_and_image(cube, energy_image, det, config, atm.blur_r0_m)
        times["turbulence_blur"] = time.perf_counter() - t0
    if noisy:
        t0 = time.perf_counter()
        chain = apply_receiver_chain(waveforms.reshape(det.height_px, det.width_px, gate.n_bins),
                                     ChainSettings.from_config(config), stage_seed(config.run.seed, frame, "receiver"))
        digital, receiver_report = chain.data, chain.report
        times["receiver_chain"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        fa_info = {}
        echo_parts = [_noisy_echoes(digital, config, truth=waveforms, info=fa_info,
                                    noise_sigma=receiver_report.get("noise_sigma"))]
        receiver_report["false_alarms"] = fa_info  # noise detections counted against the noise-free cube
        times["echoes"] = time.perf_counter() - t0
    elif blur:
        t0 = time.perf_counter()
        echo_parts = []
        for a, b in blocks:
            ech = detect_echoes(waveforms[a:b].astype(np.float64), config.detection)
            ech.pixel += a
            echo_parts.append(ech)
        times["echoes"] = time.perf_counter() - t0
    else:
        echo_parts = [r[0] for r in results]
    if whole_cube and not config.run.save_waveforms:
        waveforms = None
    t0 = time.perf_counter()
    snr = np.concatenate([e.snr for e in echo_parts]) if noisy else None
    pixel = np.concatenate([e.pixel for e in echo_parts])
    pos_bins = np.concatenate([e.position_bins for e in echo_parts])
    amp = np.concatenate([e.amplitude for e in echo_parts])
    echo_index = np.concatenate([e.echo_index for e in echo_parts])
    n_echoes = np.concatenate([e.n_echoes for e in echo_parts])
    time_s = gate.gate_start_s + pos_bins * gate.bin_width_s
    range_m = 0.5 * SPEED_OF_LIGHT_M_S * time_s
    points = _points(det, origin, rot, pixel, range_m, amp, echo_index, n_echoes, time_s, frame)
    if snr is not None:
        points["snr"] = snr.astype(np.float32)
    flags = [getattr(e, "false_alarm", None) for e in echo_parts]
    if noisy and all(f is not None for f in flags):
        points["false_alarm"] = np.concatenate(flags).astype(np.uint8)  # 1: no true return near this echo
    h, w, e_max = det.height_px, det.width_px, config.detection.max_echoes
    range_echoes = np.full((h * w, e_max), np.nan, np.float32)
    intensity_echoes = np.zeros((h * w, e_max), np.float32)
    range_echoes[pixel, echo_index] = range_m
    intensity_echoes[pixel, echo_index] = amp
    range_echoes = range_echoes.reshape(h, w, e_max)
    intensity_echoes = intensity_echoes.reshape(h, w, e_max)
    times["products"] = time.perf_counter() - t0

    stats = {"n_rays": det.n_pixels * s2, "n_hits": n_hits, "n_points": int(len(range_m)),
             "n_triangles": scene.n_triangles, "n_blocks": len(blocks), "pixels_per_block": per_block,
             "threads": min(threads, len(blocks)), "waveform_binning": method,
             "stage_times_s": times, "wall_time_s": time.perf_counter() - t_wall,
             "received_energy_j": float(energy_image.sum())}
    stats.update(run_plan)
    stats["bvh"] = culling  # built, culled or reused (static geometry)
    stats["memory_estimate_bytes"] = memory["total"]
    stats["subray_pattern"] = config.receiver.subray_pattern
    if refined:
        stats["adaptive"] = {"refined_pixels": int(sum(r[0] for r in refined)),
                             "rays_per_pixel_refined": (det.subsamples * config.receiver.subray_refine) ** 2}
        stats["n_rays"] = int(sum(r[1] for r in refined))
    if atm.metadata:
        stats["atmosphere"] = atm.metadata
    if receiver_report is not None:
        stats["receiver"] = receiver_report
    return FrameResult(range_image=range_echoes[:, :, 0].copy(), intensity_image=intensity_echoes[:, :, 0].copy(),
                       energy_image=energy_image, range_echoes=range_echoes,
                       intensity_echoes=intensity_echoes, points=points,
                       waveforms=None if waveforms is None else waveforms.reshape(h, w, gate.n_bins),
                       digital_waveforms=digital, stats=stats,
                       units=product_units(config.system_type, receiver_report and receiver_report["units"]),
                       tracer=tracer)


def run_blocks(process, blocks, threads: int, progress=None, label: str = "block"):
    """``process(block)`` for every block on a thread pool (results in block order); progress after each."""
    results = []
    with ThreadPoolExecutor(max_workers=max(1, min(threads, len(blocks)))) as pool:
        for i, res in enumerate(pool.map(process, blocks)):
            results.append(res)
            if progress is not None:
                progress((i + 1) / len(blocks), f"{label} {i + 1}/{len(blocks)}")
    return results


def _noisy_echoes(digital, config: SimulationConfig, *, truth=None, info=None, noise_sigma=None) -> Echoes:
    """Echoes on the receiver's digital waveforms (threshold, matched filter, multi-echo, interpolation:
    core/physics/detection/noisy.py), in the pipeline's per-echo layout, with the detection SNR.

    With ``truth`` (the noise-free waveforms the chain saw, (pixels, bins) J) every echo is classified as a
    true return or a false alarm (core.physics.detection.noisy.classify_false_alarms): the returned Echoes carries a
    per-echo bool ``false_alarm`` attribute and ``info`` (a dict) receives the counts, rates and the Gaussian
    expectation for the noise σ ``noise_sigma`` (raw-waveform units, from the chain report)."""
    d, g = config.detection, config.gate
    h, w, n_bins = digital.shape
    pulse = gaussian_pulse_kernel(config.laser.pulse_fwhm_s, g.bin_width_s) \
        if d.matched_filter and config.laser.pulse_shape == "gaussian" else None
    found = detect_echoes_noisy(digital.reshape(h * w, n_bins).astype(np.float32), g.bin_width_s, g.gate_start_s,
                                threshold_mode=d.noisy_threshold_mode, threshold=d.threshold_counts,
                                k_sigma=d.k_sigma, pulse=pulse, max_echoes=d.max_echoes,
                                interpolation=d.interpolation)
    pix, slot = np.nonzero(found.detected)
    echoes = Echoes(pixel=pix.astype(np.int64), position_bins=found.position_bins[pix, slot],
                    amplitude=found.amplitude[pix, slot], echo_index=slot.astype(np.int16),
                    n_echoes=found.n_echoes[pix].astype(np.int16), snr=found.snr[pix, slot])
    if truth is not None:
        from ..physics.detection.noisy import FALSE_ALARM_ABS_PRIMARIES, classify_false_alarms
        from ..physics.receiver.conversions import photons_per_joule
        det = config.detector
        primaries_per_j = float(photons_per_joule(config.laser.wavelength_m)) * det.quantum_efficiency
        fa, summary = classify_false_alarms(
            found, np.asarray(truth).reshape(h * w, n_bins), config.laser.pulse_fwhm_s / g.bin_width_s,
            noise_sigma=noise_sigma if det.detector_type != "geiger" else None, pulse=pulse,
            abs_level=FALSE_ALARM_ABS_PRIMARIES / primaries_per_j)
        echoes.false_alarm = fa[pix, slot]
        summary["threshold_mode"] = d.noisy_threshold_mode
        summary["n_pixels"] = h * w
        summary["n_bins"] = n_bins
        if info is not None:
            info.update(summary)
    return echoes


def _reference_range(tracer, det, origin, rot) -> float:
    """Median range of the pixel-centre rays that hit the scene: where the turbulence is evaluated."""
    pix = np.arange(det.n_pixels)
    xt, yt = det.pixel_center_tan(pix % det.width_px, pix // det.width_px)
    prim, range_m, _ = tracer.intersect(origin, tan_to_unit_direction(np.asarray(xt, float), np.asarray(yt, float))
                                        @ rot.T)
    hits = range_m[prim >= 0]
    if len(hits) == 0:
        raise ConfigError("sensor", "sees nothing", "a field of view containing geometry: no pixel-centre ray "
                                                    "hits the scene (check the sensor's pose and field of view)")
    return float(np.median(hits))


def _points(det, origin, rot, pixel, range_m, amp, echo_index, n_echoes, time_s, frame):
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


def run_metadata(config: SimulationConfig, result: FrameResult, frame: int, extra: dict | None = None) -> dict:
    meta = {"format": "ladar-run", "format_version": 1, "simulator_version": __version__,
            "system_type": config.system_type, "frame": frame, "seed": config.run.seed,
            "settings": config_to_dict(config), "software": software_versions(),
            "created_unix_s": time.time()}
    meta.update(result.stats)
    if extra:
        meta.update(extra)
    return meta


def simulate(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, *, frame: int = 0, tracer=None,
             trajectory=None, start_time_s: float = 0.0, progress=None, cancel=None) -> FrameResult:
    """Simulate one frame of the sensor system ``config.system_type`` (paper §2):

    * ``flash``    3D flash ladar (:func:`simulate_frame`);
    * ``profiler`` range profiler (§5.3): the flash model with one detector element (receiver width/height are
      ignored) whose field of view holds the target, all returning energy in one waveform;
    * ``scanner``  time-of-flight scanner (core/systems/scanner.py), the sensor moving along ``trajectory`` if given;
    * ``gated``    burst illumination / gated viewing (core/systems/gated.py).
    """
    kind = config.system_type
    if kind == "scanner":
        from .scanner import simulate_scan
        result = simulate_scan(scene, world_from_sensor, config, frame=frame, tracer=tracer, trajectory=trajectory,
                               start_time_s=start_time_s, progress=progress, cancel=cancel)
    elif kind == "gated":
        from .gated import simulate_gated
        result = simulate_gated(scene, world_from_sensor, config, frame=frame, tracer=tracer, progress=progress,
                                cancel=cancel)
    elif kind == "profiler":
        validate(config)
        single = dataclasses.replace(config, receiver=dataclasses.replace(config.receiver, width_px=1, height_px=1))
        result = simulate_frame(scene, world_from_sensor, single, frame=frame, tracer=tracer, progress=progress,
                                cancel=cancel)
        result.stats["notes"] = {"receiver": "range profiler: one detector element over the receiver field of "
                                             "view (receiver.width_px/height_px ignored)"}
    else:
        result = simulate_frame(scene, world_from_sensor, config, frame=frame, tracer=tracer, progress=progress,
                                cancel=cancel)
    label_points(result, scene, world_from_sensor, config)
    record_pose(result, world_from_sensor, trajectory if kind == "scanner" else None)
    return result


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


def label_points(result: FrameResult, scene: SceneGeometry, world_from_sensor, config: SimulationConfig) -> None:
    """Ground truth of the frame's points (core.geometry.groundtruth): ``points["material_id"]`` (−1: no surface near)
    and the scene's material names in ``stats["material_names"]``; a false alarm keeps its label (its flag says
    it is noise).  The tolerance: c/2 × (2 pulse widths + 4 bins, + the gate width and delay step when gated);
    the lines of sight spread over half a pixel (the beam's half divergence for the scanner, half the field of
    view for the profiler)."""
    from ..geometry.groundtruth import surface_material_ids

    pts = result.points
    if result.tracer is None or "position_world" not in pts:
        return
    if result.pulses is not None and "pulse_index" in pts:
        origin = np.asarray(result.pulses["origin_world"])[pts["pulse_index"]]
    else:
        origin = np.asarray(world_from_sensor, dtype=np.float64)[:3, 3]
    spread_s = 2.0 * config.laser.pulse_fwhm_s + 4.0 * config.gate.bin_width_s
    if config.system_type == "gated":
        spread_s += config.gated.gate_width_s + config.gated.delay_step_s
    rx = config.receiver
    if config.system_type == "scanner":  # the beam's footprint half-width
        spread_rad = 0.5 * config.laser.beam_divergence_rad
    elif config.system_type == "profiler":  # one element over the whole field of view
        spread_rad = 0.5 * max(rx.fov_x_rad, rx.fov_y_rad)
    else:  # half a pixel
        spread_rad = 0.5 * max(rx.fov_x_rad / rx.width_px, rx.fov_y_rad / rx.height_px)
    t0 = time.perf_counter()
    pts["material_id"] = surface_material_ids(result.tracer, scene.material_ids, origin, pts["position_world"],
                                              0.5 * SPEED_OF_LIGHT_M_S * spread_s, spread_rad)
    result.stats["material_names"] = list(scene.material_names)
    result.stats.setdefault("stage_times_s", {})["ground_truth"] = time.perf_counter() - t0


def run_simulation(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, out_dir, *, frame: int = 0,
                   overwrite: bool = False, extra_metadata: dict | None = None, tracer=None, progress=None,
                   cancel=None, trajectory=None, start_time_s: float = 0.0):
    """Simulate a frame of any system type and write its run folder.  Returns (run_path, FrameResult).

    Nothing is written if the settings or the scene are invalid, if the folder exists and ``overwrite`` is
    false (with ``overwrite``: if it is not a previous run of this tool), if another run is writing it, or if the
    run is cancelled.  The folder's name is claimed before the simulation starts (fileio.staging).
    """
    with claim_run_dir(out_dir, if_exists="replace" if overwrite else "stop") as claim:
        result = simulate(scene, world_from_sensor, config, frame=frame, tracer=tracer, trajectory=trajectory,
                          start_time_s=start_time_s, progress=progress, cancel=cancel)
        if cancel is not None and cancel():
            raise Cancelled()
        write_run_files(claim.work, result, run_metadata(config, result, frame, extra_metadata))
        path = claim.commit()
    return path, result
