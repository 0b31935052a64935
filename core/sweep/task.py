"""One sweep task — a point's settings with one seed at one frame — as a Dask worker runs it.

:func:`run_task` loads the exported scene (once per worker process, with one BVH per geometry kept for every
later task), simulates the frame (``core.run.simulate``), summarises it (:func:`summarize`) and writes the
run folder through ``core.fileio.run_folder.write_run`` (assembled in a hidden folder, renamed into place), with the summary
in its ``metadata.json`` under ``"sweep"``.  A finished run folder is never computed twice: if the task's folder
exists with its summary (a worker died after writing it, before the scheduler heard), that summary is returned.
A task that fails returns a row with ``status = "failed"`` and the error; it never raises.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ..config.files import config_from_dict
from ..config.settings import SimulationConfig
from ..constants import SPEED_OF_LIGHT_M_S
from ..errors import ConfigError
from ..fileio.locks import OWNERLESS_GRACE_S
from ..fileio.run_folder import write_run
from ..fileio.staging import BUSY
from ..engine.products import ground_truth_fill_rings, ground_truth_tolerance
from ..geometry.groundtruth import surface_material_ids
from ..geometry.motion import Trajectory, split_pose
from ..geometry.rays import Detector, tan_to_unit_direction
from ..geometry.trace import SceneTracer
from ..physics.detection.peaks import detect_echoes
from ..run import run_metadata, simulate
from .scene import SweepScene, pose_at_range

#: Summary figures of a task, in table order (docs/sweeps.md explains each).
FIGURES = ("points", "pixels_with_echo", "received_energy_j", "target_pixels", "detection_probability",
           "range_error_mean_m", "range_error_rms_m", "range_error_p95_abs_m", "target_snr_mean", "false_alarms",
           "false_alarms_per_pixel", "atmosphere_return_fraction")
#: Systems whose noise-free truth (the waveform cube before the receiver chain) the range error is measured on.
TRUTH_SYSTEMS = ("flash", "profiler")
_TRUTH_BLOCK_BYTES = 64 * 2**20

_cache = {"key": None, "scene": None, "tracers": {}}


def load_scene_cached(scene_dir: str, digest: str) -> SweepScene:
    """The exported scene, read once per worker process (and per sweep: keyed by folder and digest)."""
    key = (str(scene_dir), digest)
    if _cache["key"] != key:
        scene = SweepScene.load(scene_dir)
        _cache.update(key=key, scene=scene, tracers={})
    return _cache["scene"]


def _tracer(scene: SweepScene, frame: int):
    g = scene.geometry_of_frame[scene.frame_index(frame)]
    tracer = _cache["tracers"].get(g)
    if tracer is None:  # the whole scene (no culling): serves every pose of a range axis
        tracer = _cache["tracers"][g] = SceneTracer(scene.geometries[g])
    return tracer


def truth_echo_ranges(waveforms, config: SimulationConfig) -> np.ndarray:
    """Range (m) of every echo per pixel, (H, W, max_echoes) in time order, NaN where none, detected on the
    noise-free waveform cube (H, W, n_bins) with the noise-free detection settings: the ideal receiver's echoes,
    the truth of a noisy point."""
    h, w, n_bins = waveforms.shape
    flat = waveforms.reshape(h * w, n_bins)
    out = np.full((h * w, config.detection.max_echoes), np.nan)
    rows = max(1, _TRUTH_BLOCK_BYTES // (8 * n_bins))
    g = config.gate
    for a in range(0, h * w, rows):
        ech = detect_echoes(flat[a:a + rows].astype(np.float64), config.detection)
        time_s = g.gate_start_s + ech.position_bins * g.bin_width_s
        out[a + ech.pixel, ech.echo_index] = 0.5 * SPEED_OF_LIGHT_M_S * time_s
    return out.reshape(h, w, -1)


def truth_materials(truth, config: SimulationConfig, geometry, tracer, world_from_sensor) -> np.ndarray:
    """The material index (int16, −1: none) of the surface under each noise-free echo (``truth`` (H, W, E) of
    :func:`truth_echo_ranges`): the echo placed along its pixel's centre ray (a profiler's one element: the
    boresight) and labelled as the frame's points are (``core.geometry.groundtruth.surface_material_ids``, with the
    tolerances of ``core.engine.products.label_points``)."""
    truth = np.asarray(truth, dtype=np.float64)
    h, w, e = truth.shape
    flat = truth.reshape(h * w, e)
    origin, rot = split_pose(np.asarray(world_from_sensor, dtype=np.float64))
    tol_m, spread_rad = ground_truth_tolerance(config)
    det = Detector.from_settings(config.receiver)
    if det.n_pixels == h * w:
        pix = np.arange(h * w)
        xt, yt = det.pixel_center_tan(pix % det.width_px, pix // det.width_px)
    else:  # one element over the field of view (profiler)
        xt, yt = np.zeros(h * w), np.zeros(h * w)
    dirs = tan_to_unit_direction(np.asarray(xt, float), np.asarray(yt, float)) @ rot.T
    labels = np.full((h * w, e), -1, np.int16)
    pi, ei = np.nonzero(np.isfinite(flat))
    if len(pi):
        pos = origin + dirs[pi] * flat[pi, ei][:, None]
        labels[pi, ei] = surface_material_ids(tracer, geometry.material_ids, origin, pos, tol_m, spread_rad,
                                              fill_rings=ground_truth_fill_rings(config))
    return labels.reshape(h, w, e)


def summarize(result, config: SimulationConfig, truth=None, on_target=None) -> dict:
    """The summary figures of one simulated frame (:data:`FIGURES`); NaN where a figure is not defined.

    ``points``: echoes (points of the cloud); ``pixels_with_echo``: first echoes (pixels, or pulses of a scanner,
    with at least one echo); ``received_energy_j``: energy received by the whole frame before time binning;
    ``false_alarms``: echoes the noisy receiver flagged as noise (no true return near them);
    ``atmosphere_return_fraction``: the points that are returns of the atmosphere itself (``points["atmosphere"]``,
    atmosphere.weather) / all points (0 without weather, NaN without points).

    ``truth`` (H, W, E): the noise-free echo ranges (:func:`truth_echo_ranges`), given for noisy flash/profiler
    points; ``on_target`` (H, W, E) bool: which of them are echoes of the sweep's target (None: all are).  The
    target's pixels are those with a noise-free echo of the target (``target_pixels``).  A reported true (not
    false-alarm) echo *matches* a target echo of its pixel within :func:`match_window_m` (the pulse's half width
    in range); ``detection_probability`` = target pixels that report a matching echo / target pixels, and the
    range error is each matching echo's range minus its noise-free echo's: mean, root mean square, and the 95th
    percentile of its magnitude over the matching echoes; ``target_snr_mean``: the mean detection SNR
    (``points["snr"]``) of the matching echoes.  ``false_alarms_per_pixel``: false alarms / pixels of the frame.
    (A true echo matching none — another surface, a weaker one the noise-free detection's relative threshold leaves
    out, or the far part of a long return from a grazing surface — is neither.)"""
    pts = result.points
    echo_index = np.asarray(pts.get("echo_index", ()))
    row = {"points": int(len(pts.get("range_m", ()))), "pixels_with_echo": int((echo_index == 1).sum()),
           "received_energy_j": float(result.stats.get("received_energy_j", np.nan))}
    row.update(dict.fromkeys(FIGURES[3:], np.nan))
    false_alarm = np.asarray(pts["false_alarm"], dtype=bool) if "false_alarm" in pts else None
    if false_alarm is not None:
        row["false_alarms"] = int(false_alarm.sum())
    if row["points"]:  # returns of the atmosphere itself (atmosphere.weather; none without weather)
        atm = np.asarray(pts["atmosphere"], dtype=bool) if "atmosphere" in pts else np.zeros(0, bool)
        row["atmosphere_return_fraction"] = float(atm.sum() / row["points"])
    if truth is not None:
        truth = np.asarray(truth, dtype=np.float64)
        h, w = truth.shape[:2]
        if on_target is not None:
            truth = np.where(np.asarray(on_target, dtype=bool), truth, np.nan)
        truth = truth.reshape(h * w, -1)
        if false_alarm is not None:
            row["false_alarms_per_pixel"] = row["false_alarms"] / (h * w)
        has_truth = np.isfinite(truth).any(axis=1)
        row["target_pixels"] = int(has_truth.sum())
        if has_truth.any():
            pixel = np.asarray(pts["pixel_y"], np.int64) * w + np.asarray(pts["pixel_x"], np.int64)
            keep = has_truth[pixel] if false_alarm is None else has_truth[pixel] & ~false_alarm
            pixel = pixel[keep]
            diff = np.asarray(pts["range_m"], np.float64)[keep][:, None] - truth[pixel]
            diff = np.where(np.isfinite(diff), diff, np.inf)
            err = diff[np.arange(len(diff)), np.argmin(np.abs(diff), axis=1)] if len(diff) else diff[:, 0]
            matched = np.abs(err) <= match_window_m(config)
            err, pixel = err[matched], pixel[matched]
            row["detection_probability"] = float(len(np.unique(pixel)) / has_truth.sum())
            if len(err):
                row["range_error_mean_m"] = float(err.mean())
                row["range_error_rms_m"] = float(np.sqrt(np.mean(err ** 2)))
                row["range_error_p95_abs_m"] = float(np.percentile(np.abs(err), 95))
                if "snr" in pts:
                    row["target_snr_mean"] = float(np.mean(np.asarray(pts["snr"], np.float64)[keep][matched]))
    return row


def match_window_m(config: SimulationConfig) -> float:
    """How far (m) a reported echo may be from a noise-free echo to be that echo: half the pulse's length in range,
    c·τ/2 (τ: the pulse FWHM, or full width of a rectangular pulse), at least one bin."""
    return 0.5 * SPEED_OF_LIGHT_M_S * max(config.laser.pulse_fwhm_s, config.gate.bin_width_s)


def task_config(task: dict) -> SimulationConfig:
    """The task's settings: the point's, with the task's seed; ``run.threads = 0`` (all cores) becomes 1, since
    a worker process runs one task per thread (the products never depend on the thread count)."""
    cfg = config_from_dict(task["config"])
    cfg.run.seed = int(task["seed"])
    if cfg.run.threads == 0:
        cfg.run.threads = 1
    return cfg


def finished_row(out: Path, name: str):
    """The results row a finished task recorded in its run folder's metadata, or None if it has not finished."""
    try:
        meta = json.loads((out / "metadata.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    sweep = meta.get("sweep") or {}
    if sweep.get("task") != name or "row" not in sweep:
        return None
    return dict(sweep["row"])


def _one_line(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}" if not isinstance(exc, ConfigError) else f"ConfigError: {exc}"
    return " ".join(text.split())[:2000]


def run_task(scene_dir: str, scene_digest: str, task: dict) -> dict:
    """Run one task (see the module docstring); returns its results-table row (never raises)."""
    out = Path(task["out"])
    row = {"task": task["name"], "status": "failed", "error": "", "run_time_s": np.nan}
    try:
        existing = finished_row(out, task["name"])
        if existing is not None:
            return existing
        t0 = time.perf_counter()
        cfg = task_config(task)
        scene = load_scene_cached(scene_dir, scene_digest)
        frame = int(task["frame"])
        i = scene.frame_index(frame)
        pose, traj = scene.poses[i], scene.trajectories[i]
        if task.get("range_m") is not None:
            moved = pose_at_range(pose, task["target_m"], float(task["range_m"]))
            if traj is not None:  # the whole trajectory moves with the pose
                shift = np.eye(4)
                shift[:3, 3] = moved[:3, 3] - pose[:3, 3]
                traj = Trajectory(traj.times_s, shift @ traj.matrices)
            pose = moved
        truth_wanted = cfg.detector.mode == "noisy" and cfg.system_type in TRUTH_SYSTEMS
        sim_cfg = cfg
        if truth_wanted and not cfg.run.save_waveforms:  # the noisy chain holds the cube anyway: keep it
            sim_cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, save_waveforms=True))
        result = simulate(scene.geometry(frame), pose, sim_cfg, frame=frame, tracer=_tracer(scene, frame),
                          trajectory=traj, start_time_s=scene.start_times_s[i])
        truth = truth_echo_ranges(result.waveforms, cfg) if truth_wanted else None
        if not cfg.run.save_waveforms:
            result.waveforms = None
        on_target = None
        if truth is not None and task.get("target") is not None:
            geometry = scene.geometry(frame)
            labels = truth_materials(truth, cfg, geometry, _tracer(scene, frame), pose)
            names = list(geometry.material_names)
            on_target = labels == (names.index(task["target"]) if task["target"] in names else -2)
        row.update(summarize(result, cfg, truth, on_target))
        row.update(status="done", run_time_s=time.perf_counter() - t0)
        meta = run_metadata(cfg, result, frame, {"sweep": {"task": task["name"], "point": task["point"],
                                                           "values": task["values"], "row": row}})
        deadline = time.monotonic() + OWNERLESS_GRACE_S + 10.0
        while True:
            try:
                write_run(out, result, meta)  # claimed, built hidden, renamed into place (fileio.staging)
                return row
            except ConfigError as exc:
                # the folder appeared meanwhile (another attempt of this task finished first), or its name is
                # held: by another attempt still running, or by one killed so early that its claim has no owner
                # file yet (taken at once when the writer was of this host, else once OWNERLESS_GRACE_S old):
                # wait for either
                existing = finished_row(out, task["name"])
                if existing is not None:
                    return existing
                if BUSY not in str(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
    except Exception as exc:  # recorded in the table; the other tasks go on
        row.update(status="failed", error=_one_line(exc))
        return row
