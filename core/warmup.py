"""Compile the kernels ahead: every sensor system and receiver path once, on a tiny plate scene.

The compiled kernels are kept per user, source and CPU (core/jit.py), so the first run after an install
compiles what it calls (tens of seconds on a 2-core machine) and later runs load it.  ``warm_up`` does that
compiling up front — ``ladar warm-up`` on the command line (``blender -b -c ladar warm-up``,
``scripts/ladar_run.py warm-up``) — with a line of progress per case, so no simulation a user asks for later
waits for a compiler.  It runs each system type (flash, profiler, gated, scanner with each scan pattern) with the
ideal receiver and with the noisy receiver (APD with turbulence, extinction, speckle and optics MTF; PIN; Geiger
mode), the sub-ray patterns the rectangular pulse and a scanner on a moving platform: the kernels the bundled sample scenes and the settings'
choices call.  The frames are tiny (8×8 pixels, 16 scanner pulses), so a warm cache makes the whole warm-up a few
seconds of loading.
"""
from __future__ import annotations

import time
from copy import deepcopy
from pathlib import Path

import numpy as np

from .config.settings import BRDFSettings, SimulationConfig
from .geometry.motion import Trajectory
from .geometry.scene import SceneGeometry
from .jit import KERNEL_DIR, cpu_key, kernel_report
from .run import simulate

C = 299_792_458.0
RANGE_M = 60.0


def _plate() -> SceneGeometry:
    """A Lambertian and a Steinvall plate side by side, 60 m in front of a sensor looking along −Z."""
    verts, tris, mats = [], [], []
    for k, x0 in enumerate((-3.0, 0.0)):
        base = len(verts)
        verts += [[x0, -3.0, -RANGE_M], [x0 + 3.0, -3.0, -RANGE_M], [x0 + 3.0, 3.0, -RANGE_M], [x0, 3.0, -RANGE_M]]
        tris += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        mats += [k, k]
    brdfs = [BRDFSettings(), BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08)]
    return SceneGeometry(np.array(verts), np.array(tris), np.array(mats), brdfs, ["lambertian", "steinvall"])


def _base(system: str) -> SimulationConfig:
    cfg = SimulationConfig()
    cfg.system_type = system
    cfg.receiver.width_px = cfg.receiver.height_px = 8
    cfg.receiver.subsamples = 2
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.08
    cfg.gate.n_bins = 128
    cfg.gate.gate_start_s = 2 * RANGE_M / C - 40e-9
    cfg.run.save_waveforms = True
    if system == "gated":
        cfg.gated.first_delay_s = 2 * RANGE_M / C - 10e-9
        cfg.gated.n_slices = 4
        cfg.gated.delay_step_s = 5e-9
    if system == "scanner":
        cfg.scanner.pulse_rate_hz = 1000.0
        cfg.scanner.scan_rate_hz = 50.0
        cfg.scanner.n_lines = 4
        cfg.scanner.n_channels = 4
        cfg.scanner.scan_width_rad = cfg.scanner.scan_height_rad = 0.08
        cfg.scanner.cone_half_angle_rad = 0.03
        cfg.scanner.duration_s = 0.016
    return cfg


def _noisy(cfg: SimulationConfig, detector_type: str, effects: bool) -> SimulationConfig:
    cfg = deepcopy(cfg)
    cfg.detector.mode = "noisy"
    cfg.detector.detector_type = detector_type
    cfg.detector.geiger_pulses = 4
    cfg.detector.background_rate_photons_per_s = 1e6
    if effects:
        cfg.atmosphere.cn2_m_23 = 1e-14
        cfg.atmosphere.visibility_m = 10_000.0
        cfg.detector.speckle_dof = 4.0
        cfg.detector.enable_optics_mtf = True
    return cfg


def cases() -> list[tuple[str, SimulationConfig]]:
    """(name, config) of every case the warm-up runs."""
    out = []
    for system in ("flash", "profiler", "gated", "scanner"):
        cfg = _base(system)
        out.append((f"{system}, ideal receiver", cfg))
        lean = deepcopy(cfg)
        lean.run.save_waveforms = False
        out.append((f"{system}, ideal receiver, waveforms not saved", lean))
        if system == "scanner":  # (the default centroid pulse above; the reference's sub-ray sums here)
            ref = deepcopy(lean)
            ref.scanner.pulse_model = "subrays"
            out.append(("scanner, ideal receiver, waveforms not saved, sub-ray sum pulse model", ref))
        out.append((f"{system}, noisy APD, turbulence, fog, speckle", _noisy(cfg, "apd", True)))
        if system in ("flash", "scanner"):
            out.append((f"{system}, noisy PIN", _noisy(cfg, "pin", False)))
            out.append((f"{system}, Geiger mode", _noisy(cfg, "geiger", False)))
    for pattern in ("oscillating", "rotating", "palmer"):
        cfg = _base("scanner")
        cfg.scanner.pattern = pattern
        out.append((f"scanner, {pattern} pattern", cfg))
    for pattern in ("stratified", "sobol", "adaptive"):
        cfg = _base("flash")
        cfg.receiver.subray_pattern = pattern
        out.append((f"flash, {pattern} sub-rays", cfg))
    cfg = _base("flash")
    cfg.laser.pulse_shape = "rectangular"
    out.append(("flash, rectangular pulse", cfg))
    for rings in (0, 2):
        cfg = _base("scanner")
        cfg.scanner.pattern = "oscillating"
        cfg.scanner.beam_subray_rings = rings
        cfg.run.save_waveforms = False
        cfg.detection.max_echoes = 5
        out.append((f"scanner on a moving platform, {rings} sub-ray rings", cfg))
    return out


def _trajectory(cfg: SimulationConfig) -> Trajectory:
    """A platform flying 10 m/s along x over the scan, turning slowly (both interpolations)."""
    times = np.linspace(0.0, cfg.scanner.duration_s, 3)
    mats = []
    for t in times:
        m = np.eye(4)
        a = 0.1 * t
        m[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
        m[0, 3] = 10.0 * t
        mats.append(m)
    return Trajectory(times, np.array(mats))


def marker() -> Path:
    """The file a finished warm-up leaves in this source's kernel folder (core/jit.py ``KERNEL_DIR``: every
    import name's, or a second copy's own) for this CPU."""
    return KERNEL_DIR / f"WARM-{cpu_key()}"


def is_warm() -> bool:
    """A warm-up of this source and CPU has finished in this kernel folder (its kernels are in the cache)."""
    try:
        return marker().is_file()
    except OSError:
        return False


def warm_up(progress=print, cancel=None, fraction=None) -> dict:
    """Run every case of :func:`cases` once (nothing is written); ``progress(line)`` after each (and
    ``fraction(done / total)``).  ``cancel()`` true stops between cases.  Returns the kernel report (loaded,
    compiled, seconds) of the whole warm-up; a finished one leaves :func:`marker`."""
    before = kernel_report()
    scene = _plate()
    pose = np.eye(4)
    todo = cases()
    t0 = time.perf_counter()
    for i, (name, cfg) in enumerate(todo, 1):
        if cancel is not None and cancel():
            break
        moving = name.startswith("scanner on a moving platform")
        simulate(scene, pose, cfg, cancel=cancel,
                 trajectory=_trajectory(cfg) if moving else None)
        k = kernel_report(before)
        progress(f"warm-up  [{i}/{len(todo)}] {name}: {k['compiled']} kernels compiled, {k['loaded']} loaded "
                 f"so far ({time.perf_counter() - t0:.1f} s)")
        if fraction is not None:
            fraction(i / len(todo))
    else:
        try:
            marker().parent.mkdir(parents=True, exist_ok=True)
            marker().write_text("every case of core/warmup.py ran\n")
        except OSError:  # an unwritable cache: nothing is kept anyway
            pass
    return kernel_report(before)
