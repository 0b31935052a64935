"""3D flash ladar (paper §2.3, Figure 4) and the range profiler (§5.3), stage by stage.

    rays → trace → radiometry (eq. 3-1) → waveform (pulse ⊛ impulse response) → echoes → products

The receiver is processed in blocks of whole pixels (``run.chunk_rays`` rays at most, and a bounded waveform
size), on the engine's thread pool; each block is independent, so the products do not depend on the thread
count or block size.  The full waveform cube is allocated only when it is to be saved.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..config.settings import SimulationConfig
from ..config.validate import validate_config
from ..constants import SPEED_OF_LIGHT_M_S
from ..engine.atmosphere_stage import blur_cube_and_image, prepare_frame_atmosphere, turbulence_switches
from ..engine.coverage import add_tallies, coverage_record, gate_tally, gate_window_s
from ..engine.blocks import balanced_block_size, item_blocks, rows_matmul, run_blocks, worker_threads
from ..engine.frame import StageLog, open_frame
from ..engine.memory import BLOCK_WAVEFORM_BYTES
from ..engine.products import (load_noisy_receiver, statistical_noisy_echoes, noisy_echoes, points_along_rays,
                               reference_range_m)
from ..engine.result import FrameResult, product_units
from ..engine.rng import stage_seed
from ..engine.weather_stage import (mark_atmosphere_echoes, max_pixel_fraction, merge_returns, prepare_frame_weather,
                                    weather_switches)
from ..errors import ConfigError
from ..geometry.rays import Detector, tan_to_unit_direction
from ..geometry.scene import SceneGeometry
from ..geometry.trace import SceneTracer
from ..jit import kernel, stage_clock
from ..physics.detection.peaks import detect_echoes, detect_echoes_windows
from ..atmosphere.weather import add_volume_rows
from ..physics.laser import beam_half_angle_tan, cell_energy_fractions
from ..physics.propagation import path_extinction
from ..physics.radiometry import received_energy
from ..physics.solar import pixel_solar_rates, solar_enabled, tan_cell_solid_angles
from ..physics.sampling import SubraySampler, adaptive_tolerance_m, cell_returns
from ..physics.waveform import (accumulate_waveform_windows, detection_windows, flash_binning_method,
                                round_trip_time_s)

STAGES = ("build_bvh", "rays", "trace", "radiometry", "waveform", "echoes", "products")


def block_hits(prim, pixel, first_pixel, material_ids, fraction):
    """The hits of a block's rays (``prim`` ≥ 0), in ray order: (ray index, pixel − ``first_pixel``, material
    index of the hit triangle, the ray's energy fraction), one compiled pass."""
    n = int(np.count_nonzero(prim >= 0))
    index, pix, mat, frac = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, material_ids.dtype), np.empty(n)
    _block_hits(prim, pixel, first_pixel, material_ids, fraction, index, pix, mat, frac)
    return index, pix, mat, frac


@kernel
def _block_hits(prim, pixel, first_pixel, material_ids, fraction, index, pix, mat, frac):
    k = 0
    for i in range(prim.shape[0]):
        if prim[i] >= 0:
            index[k], pix[k], mat[k], frac[k] = i, pixel[i] - first_pixel, material_ids[prim[i]], fraction[i]
            k += 1


def plan(config: SimulationConfig) -> dict:
    """Which stages this run executes and which it skips (with the reason)."""
    skipped = {}
    if path_extinction(config) == 0.0:
        skipped["extinction"] = "no extinction (extinction_per_m = 0, no visibility and no aerosol layers)"
    skipped.update(turbulence_switches(config))
    skipped.update(weather_switches(config))
    if config.detector.mode == "ideal":
        skipped["receiver_chain"] = ("detector.mode = ideal: no photon, speckle, dark, gain, read-out or A/D "
                                     "noise; echoes from the noise-free waveforms")
    keeps_cube = (config.run.save_waveforms or "turbulence_blur" not in skipped
                  or "receiver_chain" not in skipped or "weather_backscatter" not in skipped)
    if not keeps_cube:
        skipped["waveform_cube"] = ("run.save_waveforms = false: waveforms are built per block for echo "
                                    "detection and discarded")
    optional = ("extinction", "beam_broadening", "scintillation", "return_scintillation", "beam_wander",
                "turbulence_blur", "weather_backscatter", "weather_drops", "receiver_chain", "waveform_cube")
    ran = list(STAGES) + [s for s in optional if s not in skipped]
    return {"stages_run": ran, "stages_skipped": skipped}


def simulate_frame(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, *, frame: int = 0,
                   tracer: SceneTracer | None = None, trajectory=None, start_time_s: float = 0.0, progress=None,
                   cancel=None, fov_culling: bool = True) -> FrameResult:
    """Simulate one flash-ladar frame.  Raises ConfigError on bad input, Cancelled if ``cancel()`` is true.

    The systems' common signature (core.run.SYSTEMS); a flash frame is one pulse from one pose,
    ``world_from_sensor`` (``trajectory`` and ``start_time_s`` are not used).
    ``tracer``: a SceneTracer built on this scene's geometry (static scenes: one BVH for all frames); otherwise
    one is built, on the triangles inside the field of view only when ``fov_culling`` (core/geometry/culling.py)."""
    validate_config(config)  # before the detector and the plan are derived from it (open_frame checks again)
    det = Detector.from_settings(config.receiver)
    run_plan = plan(config)
    log = StageLog.of(STAGES, run_plan["stages_run"], run_plan["stages_skipped"])
    # the memory and work plan refuses, naming the setting to change, what would not fit or not end
    fr = open_frame(scene, world_from_sensor, config, log, tracer=tracer,
                    frustum_tan=(det.half_width_tan, det.half_height_tan),
                    fov_culling=fov_culling and not (solar_enabled(config) and config.detector.mode == "noisy"))
    scene, tracer, origin, rot, memory = fr.scene, fr.tracer, fr.origin, fr.rot, fr.memory
    needs_reference = any(s not in log.skipped
                          for s in ("beam_broadening", "scintillation", "beam_wander", "turbulence_blur"))
    threads = worker_threads(config.run.threads)
    with log.timed("atmosphere"):
        r_ref = reference_range_m(tracer, det, origin, rot, threads) if needs_reference else None
        atm = prepare_frame_atmosphere(config, det, r_ref, frame)
    for stage, reason in atm.skipped.items():  # decided with the frame's geometry (e.g. negligible blur)
        log.skip(stage, reason, keep_earlier=True)
    fx, fy = cell_energy_fractions(config.laser, det, atm.beam_offset_tan, atm.beam_width_scale)
    with log.timed("weather"):  # returns of the atmosphere itself (engine/weather_stage.py), None without weather
        px_tan, py_tan = det.pixel_pitch_tan
        wx = prepare_frame_weather(config, frame, det.n_pixels, px_tan * py_tan,
                                   beam_half_angle_tan(config.laser, det) * atm.beam_width_scale,
                                   0.5 * min(px_tan, py_tan), max_beam_fraction=max_pixel_fraction(det, fx, fy),
                                   detector=det)
    if wx is None:
        del log.times["weather"]
    hits_of_blocks = {}  # block start → (pixel, range) of its surface hits: which echoes are the atmosphere's
    gate = config.gate
    blur = atm.blur_r0_m is not None
    noisy = config.detector.mode == "noisy"
    whole_cube = blur or noisy  # echoes are detected after a whole-cube stage
    method = flash_binning_method(config.laser, gate)  # metadata: waveform_binning
    s2 = det.rays_per_pixel
    per_block = max(1, min(config.run.chunk_rays // s2, BLOCK_WAVEFORM_BYTES // (8 * gate.n_bins)))
    # several threads: at least 8 blocks each when the frame allows (≥ 8192 rays a block)
    per_block = balanced_block_size(per_block, det.n_pixels, threads, -(-8192 // s2))
    blocks = item_blocks(det.n_pixels, per_block)
    keep_cube = config.run.save_waveforms or whole_cube or wx is not None
    # every block writes its pixels' whole rows (WaveformWindows.write_rows)
    waveforms = np.empty((det.n_pixels, gate.n_bins), np.float32) if keep_cube else None
    # each pixel's window of bins in the cube (zeros outside it) while no whole-cube stage adds to the rows: the
    # statistical detector model then searches the windows alone for each pixel's signal
    spans = (np.zeros(det.n_pixels, np.int64), np.zeros(det.n_pixels, np.int64)) \
        if noisy and not blur and wx is None else None
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
    window = gate_window_s(config)
    tallies = {}  # block start → its hits against the range gate (engine/coverage.py)
    whole_windows = {}  # block start → its pixels binned over their whole windows (points only: detection_windows)
    # sunlight reflected by the scene into each pixel (core/physics/solar.py; shadow rays need the whole scene:
    # no field-of-view culling), photons/s before η
    sun_rate = np.zeros(det.n_pixels) if noisy and solar_enabled(config) else None

    def trace_tan(x_tan, y_tan, normals_out=None):
        return tracer.intersect(origin, rows_matmul(tan_to_unit_direction(x_tan, y_tan), rot.T),
                                normals_out=normals_out)

    def process(block):
        a, b = block
        local = {}
        t = stage_clock()
        smp = sampler.block(a, b)  # receiver.subray_pattern (core/physics/sampling.py)
        local["rays"] = stage_clock() - t
        t = stage_clock()
        # the cell model's normals written by the refinement, which reads them anyway (a 2M-triangle scene: a
        # second random look-up per hit cost ≈ 50 ns); the adaptive pattern's second pass merges hits: looked up
        normals = (np.empty((len(smp.x_tan), 3)) if config.receiver.cell_range_spread and not sampler.adaptive
                   else None)
        prim, range_m, cos_theta = trace_tan(smp.x_tan, smp.y_tan, normals)
        local["trace"] = stage_clock() - t
        if sampler.adaptive:  # second pass over the pixels whose rays disagree
            t = stage_clock()
            smp, (prim, range_m, cos_theta), bad = sampler.refine_pass(
                smp, (prim, range_m, cos_theta), trace_tan, lambda p: rows_matmul(tracer.unit_normal[p], rot),
                scene.material_ids, adaptive_tolerance_m(config.laser, gate))
            refined.append((len(bad), (b - a) * s2 + len(bad) * (det.subsamples * rx.subray_refine) ** 2))
            local["refine"] = stage_clock() - t
        x_tan, y_tan, pixel, sub_x, sub_y, fraction = smp.x_tan, smp.y_tan, smp.pixel, smp.sub_x, smp.sub_y, smp.weight
        t = stage_clock()
        index, pix_local, mat_hit, frac_hit = block_hits(prim, pixel, a, scene.material_ids, fraction)
        if sun_rate is not None:
            omega = tan_cell_solid_angles(x_tan[index], y_tan[index], det.pixel_pitch_tan,
                                          np.bincount(pixel - a, minlength=b - a)[pix_local])
            sun_rate[a:b] = pixel_solar_rates(config, atm.extinction_per_m, tracer, scene.materials, mat_hit, origin,
                                              rows_matmul(tan_to_unit_direction(x_tan, y_tan), rot.T), prim,
                                              range_m, index, pix_local, omega, b - a)
        if config.receiver.cell_range_spread:  # each cell's surface spans a range interval (core/physics/sampling.py)
            if normals is None:
                spread, range_hit, cos_hit = cell_returns(smp, index, range_m, cos_theta, prim, tracer.unit_normal,
                                                          rot, max_spread_s)
            else:  # (each ray its own row of normals)
                spread, range_hit, cos_hit = cell_returns(smp, index, range_m, cos_theta,
                                                          np.arange(len(prim), dtype=prim.dtype), normals, rot,
                                                          max_spread_s)
        else:
            spread, range_hit, cos_hit = None, range_m[index], cos_theta[index]
        e = received_energy(config.laser, config.receiver, atm.extinction_per_m, scene.materials, mat_hit, cos_hit,
                            range_hit, frac_hit)
        atm.scale_by_scintillation(e, index, x_tan, y_tan, sub_x, sub_y)
        drops_ret = None
        if wx is not None:  # drops in front of the surfaces: returns of their own, shadows on what lies behind
            beam_fraction = np.bincount(pixel - a, weights=fraction, minlength=b - a)
            ray_range = np.where(prim >= 0, range_m, np.inf)
            drops_ret, shade = wx.block_returns(wx.drops_of(a, b), pixel - a, fraction, ray_range, beam_fraction,
                                                pix_local, range_hit,
                                                beam_tan=det.pixel_center_tan(np.arange(a, b) % det.width_px,
                                                                              np.arange(a, b) // det.width_px))
            e = e * shade
            hits_of_blocks[a] = (pix_local + a, range_hit)
        energy[a:b] = np.bincount(pix_local, weights=e, minlength=b - a)
        tallies[a] = gate_tally(range_hit, e, window)
        local["radiometry"] = stage_clock() - t
        t = stage_clock()
        # one window of bins per pixel: a short return in a long gate costs its window only, a pixel without
        # returns nothing (its row of the cube stays zero)
        t_hit = round_trip_time_s(range_hit)
        w_pix, w_t, w_e, w_spread = merge_returns(pix_local, t_hit, e, spread, drops_ret)
        if waveforms is None and spans is None:  # points only: binned where the echo detection reads
            wf, whole_windows[a] = detection_windows(w_pix, w_t, w_e, b - a, config.laser, gate, method,
                                                     config.detection, spread_s=w_spread)
        else:
            wf = accumulate_waveform_windows(w_pix, w_t, w_e, b - a, config.laser, gate, method, spread_s=w_spread)
        if waveforms is not None:
            wf.write_rows(waveforms, np.arange(a, b))
            if spans is not None:
                spans[0][a:b], spans[1][a:b] = wf.start, wf.start + wf.length
        local["waveform"] = stage_clock() - t
        if wx is not None:
            t = stage_clock()
            add_volume_rows(waveforms[a:b], wx.templates_of(a, b), beam_fraction, pix_local, t_hit, frac_hit, gate)
            local["weather"] = stage_clock() - t
            if not whole_cube:
                t = stage_clock()
                echoes = detect_echoes(waveforms[a:b].astype(np.float64), config.detection)
                echoes.pixel += a
                local["echoes"] = stage_clock() - t
                return echoes, len(index), local
        if whole_cube:  # echoes are detected after the whole-cube stages
            return None, len(index), local
        t = stage_clock()
        echoes = detect_echoes_windows(wf, config.detection)
        echoes.pixel += a
        local["echoes"] = stage_clock() - t
        return echoes, len(index), local

    results = run_blocks(process, blocks, threads, progress, cancel=cancel)
    n_hits = sum(r[1] for r in results)
    for _, _, local in results:
        log.add_times(local)
    if n_hits == 0:
        raise ConfigError("sensor", "sees nothing",
                          f"a field of view containing geometry: all {det.n_pixels * s2} rays missed the "
                          f"{scene.n_triangles} triangles of the scene (check the sensor's pose and field of view)")

    energy_image = energy.reshape(det.height_px, det.width_px)
    digital = None
    receiver_report = None
    if blur:
        with log.timed("turbulence_blur"):
            cube = waveforms.reshape(det.height_px, det.width_px, gate.n_bins)
            energy_image = blur_cube_and_image(cube, energy_image, det, config, atm.blur_r0_m)
    if noisy:  # the noisy receiver's modules and kernels, imported before the stage clocks (not in the stage times)
        load_noisy_receiver()
    statistical, t_model = None, 0.0
    if noisy and sun_rate is not None:  # one noise level per pixel: every bin simulated
        model = {"threshold": config.detection.noisy_threshold_mode, "signal_free_bins": "per_bin",
                 "reason": "sunlight reflected by the scene: a background rate per pixel (per-bin route)"}
    elif noisy:  # detection.signal_free_bins = "statistical": chain and detection on the signal stretches only
        t_model = stage_clock()
        statistical, model = statistical_noisy_echoes(
            waveforms.reshape(det.height_px, det.width_px, gate.n_bins), config,
            stage_seed(config.run.seed, frame, "receiver"), spans=spans)
        t_model = stage_clock() - t_model  # (the route's decision; when it ran, the chain and the detection)
        if statistical is not None:
            echo_parts, receiver_report = [statistical], model
            log.times["receiver_chain"] = t_model
    if noisy and statistical is None:
        from ..physics.receiver.chain import ChainSettings, apply_receiver_chain  # (see load_noisy_receiver)

        with log.timed("receiver_chain"):
            cs = ChainSettings.from_config(config)
            if sun_rate is not None:
                cs.pixel_background_rate = sun_rate.reshape(det.height_px, det.width_px)
            chain = apply_receiver_chain(waveforms.reshape(det.height_px, det.width_px, gate.n_bins), cs,
                                         stage_seed(config.run.seed, frame, "receiver"))
            digital, receiver_report = chain.data, chain.report
            noise = chain.pixel_noise or receiver_report
        log.times["receiver_chain"] += t_model
        with log.timed("echoes"):
            fa_info = {}
            echo_parts = [noisy_echoes(digital, config, truth=waveforms, info=fa_info,
                                       noise_sigma=noise.get("noise_sigma"),
                                       noise_floor=receiver_report.get("noise_sigma_floor", 0.0),
                                       noise_mean=noise.get("noise_mean"))]
            receiver_report["false_alarms"] = fa_info  # noise detections counted against the noise-free cube
            model["threshold"] = fa_info.get("threshold_mode", model["threshold"])
            receiver_report["detector_model"] = model  # which threshold and signal-free route ran, and why
    elif blur and not noisy:
        with log.timed("echoes"):
            echo_parts = []
            for a, b in blocks:
                ech = detect_echoes(waveforms[a:b].astype(np.float64), config.detection)
                ech.pixel += a
                echo_parts.append(ech)
    elif not noisy:
        echo_parts = [r[0] for r in results]
    if whole_cube and not config.run.save_waveforms:
        waveforms = None
    t0 = stage_clock()
    snr = np.concatenate([e.snr for e in echo_parts]) if noisy else None
    pixel = np.concatenate([e.pixel for e in echo_parts])
    pos_bins = np.concatenate([e.position_bins for e in echo_parts])
    amp = np.concatenate([e.amplitude for e in echo_parts])
    echo_index = np.concatenate([e.echo_index for e in echo_parts])
    n_echoes = np.concatenate([e.n_echoes for e in echo_parts])
    time_s = gate.gate_start_s + pos_bins * gate.bin_width_s
    range_m = 0.5 * SPEED_OF_LIGHT_M_S * time_s
    points = points_along_rays(det, origin, rot, pixel, range_m, amp, echo_index, n_echoes, time_s, frame)
    if snr is not None:
        points["snr"] = snr.astype(np.float32)
    flags = [getattr(e, "false_alarm", None) for e in echo_parts]
    if noisy and all(f is not None for f in flags):
        points["false_alarm"] = np.concatenate(flags).astype(np.uint8)  # 1: no true return near this echo
    if wx is not None:  # 1: no surface hit of the pixel near this echo: a return of the atmosphere
        hp = [hits_of_blocks[k] for k in sorted(hits_of_blocks)]
        points["atmosphere"] = mark_atmosphere_echoes(
            config, pixel, range_m, np.concatenate([h[0] for h in hp]) if hp else np.zeros(0, np.int64),
            np.concatenate([h[1] for h in hp]) if hp else np.zeros(0))
    h, w, e_max = det.height_px, det.width_px, config.detection.max_echoes
    range_echoes = np.full((h * w, e_max), np.nan, np.float32)
    intensity_echoes = np.zeros((h * w, e_max), np.float32)
    range_echoes[pixel, echo_index] = range_m
    intensity_echoes[pixel, echo_index] = amp
    range_echoes = range_echoes.reshape(h, w, e_max)
    intensity_echoes = intensity_echoes.reshape(h, w, e_max)
    log.times["products"] = stage_clock() - t0

    stats = {"n_rays": det.n_pixels * s2, "n_hits": n_hits, "n_points": int(len(range_m)),
             "n_triangles": scene.n_triangles, "n_blocks": len(blocks), "pixels_per_block": per_block,
             "threads": min(threads, len(blocks)), "waveform_binning": method,
             "stage_times_s": log.times, "wall_time_s": time.perf_counter() - fr.t_wall,
             "received_energy_j": float(energy_image.sum())}
    stats["gate_coverage"] = coverage_record(config, add_tallies(tallies[k] for k in sorted(tallies)))
    stats.update(stages_run=log.ran, stages_skipped=log.skipped)
    stats["bvh"] = fr.bvh  # built, culled or reused (static geometry)
    stats["memory_estimate_bytes"] = memory["total"]
    stats["work_estimate_samples"] = memory["work"]
    stats["subray_pattern"] = config.receiver.subray_pattern
    if whole_windows:  # points only (waveform.detection_windows): the pixels whose waveform was binned whole
        stats["waveform_windows"] = {"binned": "where the echo detection reads them (points only)",
                                     "pixels_binned_whole": int(sum(whole_windows.values()))}
    if refined:
        stats["adaptive"] = {"refined_pixels": int(sum(r[0] for r in refined)),
                             "rays_per_pixel_refined": (det.subsamples * config.receiver.subray_refine) ** 2}
        stats["n_rays"] = int(sum(r[1] for r in refined))
    if atm.metadata:
        stats["atmosphere"] = atm.metadata
    if wx is not None:
        stats["weather"] = dict(wx.metadata, n_atmosphere_echoes=int(points["atmosphere"].sum()))
    if receiver_report is not None:
        stats["receiver"] = receiver_report
    return FrameResult(range_image=range_echoes[:, :, 0].copy(), intensity_image=intensity_echoes[:, :, 0].copy(),
                       energy_image=energy_image, range_echoes=range_echoes,
                       intensity_echoes=intensity_echoes, points=points,
                       waveforms=None if waveforms is None else waveforms.reshape(h, w, gate.n_bins),
                       digital_waveforms=digital, stats=stats,
                       units=product_units(config.system_type, receiver_report and receiver_report["units"]),
                       tracer=tracer)



def simulate_profiler(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, *, frame: int = 0,
                      tracer: SceneTracer | None = None, trajectory=None, start_time_s: float = 0.0, progress=None,
                      cancel=None) -> FrameResult:
    """Range profiler (paper §5.3): the flash model with one detector element (receiver width/height are
    ignored) whose field of view holds the target, all returning energy in one waveform."""
    validate_config(config)
    single = dataclasses.replace(config, receiver=dataclasses.replace(config.receiver, width_px=1, height_px=1))
    result = simulate_frame(scene, world_from_sensor, single, frame=frame, tracer=tracer, progress=progress,
                            cancel=cancel)
    result.stats["notes"] = {"receiver": "range profiler: one detector element over the receiver field of "
                                         "view (receiver.width_px/height_px ignored)"}
    return result
