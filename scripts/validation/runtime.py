"""Run time against error: for each system, the error of cheaper settings against a converged result, and the
time per frame they cost (the Pareto front)."""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from validation import check, save
from validation._common import BRDFSettings, SimulationConfig, cylinder, flash_config, plate, uv_sphere

from core.config.settings import DetectorSettings
from core.geometry.scene import merge_meshes
from core.run import simulate

TITLE = "Run time against error (Pareto fronts)"
ORDER = 70
INTRO = """For each system, settings are swept on one scene and each run is compared with a converged run of the
same system (far more sub-rays, finer bins); the time is the wall-clock time of one frame on one thread
(`run.threads = 1`, kernels compiled beforehand, best of the repeats) on the machine that generated this page —
times are *not* checked (a shared machine's load moves them), errors are.

* **flash** (24 × 24 pixels, 40 mrad, 2 ns pulse) on a tilted plate with a sphere and a cylinder in front: sub-rays
  per pixel side S ∈ {1, 2, 4, 8} × pattern {grid, sobol} × bin width {1, 0.25, 0.1 ns} (0.1 ns bins switch the
  binning from exact bin integrals to splatting + FFT: σ_pulse > 8 bins); and the noisy §8 APD receiver.  Error:
  ‖w − w_ref‖/‖w_ref‖ over the waveform cube, the reference (Sobol 32 × 32 sub-rays, 0.05 ns bins) summed to the
  run's bins; for the noisy receiver, the same on its output converted back to joules (noise included).
* **gated** (the flash scene, 24 × 24 pixels, 40 slices 1 ns apart, 4 ns gate, 2 ns pulse): S ∈ {1, 2, 4, 8} ×
  pattern {grid, sobol} (the gated system refuses only `adaptive`).  Error: ‖s − s_ref‖/‖s_ref‖ over the slice
  stack (energy per slice and pixel), reference grid 32 × 32.
* **scanner** (raster, 20 × 20 pulses over the same scene): sub-ray rings per beam ∈ {0, 1, 2, 4}.  Error: RMS of
  the per-pulse received energy relative to the reference (8 rings), and of the first-echo range.
* **profiler** (the aircraft sample): S ∈ {32, 64, 128, 256} × pattern {grid, sobol, adaptive}.  Error: L2 against
  the brute-force ray-grid reference of the systems page (4800² rays).

Quick mode sweeps fewer settings (S ∈ {1, 4}, 1 ns bins, rings {0, 2}, profiler grid and adaptive at S ∈ {32,
128}).  Checks: for each system and pattern, the error with the most sub-rays is below the error with the fewest
(the sweep converges), and the error of one mid-cost setting is below a stated bound (flash Sobol S = 4: 3 %; gated grid S = 4: 5 %;
scanner 2 rings: 5 %; profiler adaptive S = 128: 1 %).  The table of every setting's time and error is [runtime/timings.md](runtime/timings.md)."""


def mixed_scene():
    lam = BRDFSettings(model="lambertian", reflectance=0.3)
    stv = BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0)
    back = plate(104.0, 20.0, lam, tilt_rad=math.radians(50))
    sv, st = uv_sphere((-0.8, 0.3, -100.0), 0.9, 48, 96)
    cv, ct = cylinder((0.0, -1.0, -101.0), 0.5, 3.0, 96)
    return merge_meshes([(back.vertices_m, back.triangles, back.material_ids, ["wall"], [lam]),
                         (sv, st, np.zeros(len(st), int), ["sphere"], [stv]),
                         (cv, ct, np.zeros(len(ct), int), ["cylinder"], [lam])])


def timed(fn, repeat):
    best, out = math.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def flash_cfg(subsamples, pattern, bin_s, detector="ideal"):
    span = 80e-9
    cfg = flash_config(100.0, pixels=24, subsamples=subsamples, fov_rad=0.04, bins=int(round(span / bin_s)),
                       bin_s=bin_s, margin_bins=int(round(25e-9 / bin_s)))
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.receiver.subray_pattern = pattern
    if detector == "noisy":
        cfg.detector = DetectorSettings(mode="noisy", quantum_efficiency=0.4, apd_gain=100.0, apd_k_eff=0.02,
                                        read_noise_e=300.0, adc_bits=12, adc_full_scale_e=500.0 * 4096,
                                        adc_offset_counts=16, background_rate_photons_per_s=5e9)
        cfg.run.save_counts = True  # the digital waveforms are compared below: the per-bin route keeps them
    return cfg


def l2(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def sweep_flash(scene, quick, repeat):
    ref_bin = 0.05e-9
    ref = simulate(scene, np.eye(4), flash_cfg(32, "sobol", ref_bin)).waveforms.astype(np.float64)
    rows = []
    subs = [1, 4] if quick else [1, 2, 4, 8]
    bins = [1e-9] if quick else [1e-9, 0.25e-9, 0.1e-9]
    for pattern in ("grid", "sobol"):
        for s in subs:
            for b in bins:
                cfg = flash_cfg(s, pattern, b)
                f = int(round(b / ref_bin))
                t, res = timed(lambda: simulate(scene, np.eye(4), cfg), repeat)
                r = ref.reshape(ref.shape[0], ref.shape[1], -1, f).sum(axis=3)
                rows.append({"label": f"{pattern} S={s} bin {b * 1e9:g} ns", "pattern": pattern, "s": s, "bin": b,
                             "time": t, "error": l2(res.waveforms.astype(np.float64), r)})
    cfg = flash_cfg(4, "sobol", 1e-9, "noisy")
    t, res = timed(lambda: simulate(scene, np.eye(4), cfg), repeat)
    d = cfg.detector
    e_per_count = 500.0 / (d.quantum_efficiency * d.apd_gain) / (cfg.laser.wavelength_m / (6.62607015e-34 * 299_792_458.0))
    wf = (res.digital_waveforms.astype(np.float64) - d.adc_offset_counts) * e_per_count
    r = ref.reshape(ref.shape[0], ref.shape[1], -1, 20).sum(axis=3)
    rows.append({"label": "noisy §8 APD, sobol S=4 bin 1 ns", "pattern": "noisy", "s": 4, "bin": 1e-9, "time": t,
                 "error": l2(wf, r)})
    return rows


def gated_cfg(subsamples, pattern):
    cfg = SimulationConfig(system_type="gated")
    cfg.receiver.width_px, cfg.receiver.height_px = 24, 24
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.04
    cfg.receiver.subsamples = subsamples
    cfg.receiver.subray_pattern = pattern
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.laser.beam_profile = "uniform"
    g = cfg.gated
    g.gate_width_s, g.delay_step_s, g.n_slices = 4e-9, 1e-9, 40
    g.first_delay_s = 2 * 97.0 / 299_792_458.0
    cfg.run.threads = 1
    return cfg


def sweep_gated(scene, quick, repeat):
    ref = simulate(scene, np.eye(4), gated_cfg(32, "grid")).slices.astype(np.float64)
    rows = []
    for pattern in ("grid", "sobol"):
        for s in ([1, 4] if quick else [1, 2, 4, 8]):
            cfg = gated_cfg(s, pattern)
            t, res = timed(lambda: simulate(scene, np.eye(4), cfg), repeat)
            rows.append({"label": f"{pattern} S={s}", "pattern": pattern, "s": s, "time": t,
                         "error": l2(res.slices.astype(np.float64), ref)})
    return rows


def scanner_cfg(rings):
    cfg = SimulationConfig(system_type="scanner")
    sc = cfg.scanner
    sc.pattern, sc.n_lines, sc.scan_rate_hz, sc.pulse_rate_hz = "raster", 20, 100.0, 2000.0
    sc.scan_width_rad, sc.scan_height_rad, sc.beam_subray_rings = 0.04, 0.04, rings
    cfg.laser.beam_divergence_rad = 2e-3
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.gate.gate_start_s = 2 * 90.0 / 299_792_458.0
    cfg.gate.bin_width_s = 0.25e-9
    cfg.gate.n_bins = 800
    cfg.run.save_waveforms = False
    cfg.run.threads = 1
    return cfg


def sweep_scanner(scene, quick, repeat):
    ref = simulate(scene, np.eye(4), scanner_cfg(8)).pulses["received_energy_j"]
    rows = []
    for rings in ([0, 2] if quick else [0, 1, 2, 4]):
        cfg = scanner_cfg(rings)
        t, res = timed(lambda: simulate(scene, np.eye(4), cfg), repeat)
        e = res.pulses["received_energy_j"]
        rows.append({"label": f"rings={rings}", "pattern": "rings", "s": rings, "time": t,
                     "error": float(np.sqrt(np.mean((e - ref) ** 2)) / ref.mean())})
    return rows


def sweep_profiler(quick, repeat):
    from validation.systems import aircraft
    scene, pose, cfg, ref = aircraft(4800)
    rows = []
    for pattern in (("grid", "adaptive") if quick else ("grid", "sobol", "adaptive")):
        for s in ([32, 128] if quick else [32, 64, 128, 256]):  # noqa: B007
            c = dataclasses.replace(cfg, receiver=dataclasses.replace(cfg.receiver, subsamples=s,
                                                                      subray_pattern=pattern))
            t, res = timed(lambda: simulate(scene, pose, c), repeat)
            rows.append({"label": f"{pattern} S={s}", "pattern": pattern, "s": s, "time": t,
                         "error": l2(res.waveforms.reshape(-1).astype(np.float64), ref)})
    return rows


def pareto(rows):
    pts = sorted(rows, key=lambda r: (r["time"], r["error"]))
    front, best = [], math.inf
    for r in pts:
        if r["error"] < best:
            front.append(r)
            best = r["error"]
    return front


BOUNDS = {"flash": ("sobol S=4 bin 1 ns", 0.03), "gated": ("grid S=4", 0.05), "scanner": ("rings=2", 0.05),
          "profiler": ("adaptive S=128", 0.01)}
METRIC = {"flash": "waveform L2 error (relative)", "gated": "slice-stack L2 error (relative)",
          "scanner": "RMS pulse-energy error (relative)", "profiler": "waveform L2 error (relative)"}


def run(out_dir: Path, quick: bool) -> list[dict]:
    import os
    from matplotlib.ticker import NullFormatter
    repeat = 1 if quick else 3
    load = os.getloadavg()[0]
    scene = mixed_scene()
    results = {"flash": sweep_flash(scene, quick, repeat), "gated": sweep_gated(scene, quick, repeat),
               "scanner": sweep_scanner(scene, quick, repeat), "profiler": sweep_profiler(quick, repeat)}
    checks = []
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    for ax, (system, rows) in zip(axes, results.items()):
        patterns = sorted({r["pattern"] for r in rows})
        for j, p in enumerate(patterns):
            sel = [r for r in rows if r["pattern"] == p]
            ax.loglog([r["time"] * 1e3 for r in sel], [max(r["error"], 1e-7) for r in sel], f"C{j}o", ms=4,
                      mfc="none", label=p)
            if p not in ("noisy",):
                bins = sorted({r.get("bin") for r in sel}, key=lambda x: -(x or 0))
                for b in bins:
                    ss = sorted([r for r in sel if r.get("bin") == b], key=lambda r: r["s"])
                    if len(ss) >= 2:
                        lo, hi = ss[0], ss[-1]
                        where = f", bin {b * 1e9:g} ns" if b else ""
                        # the quantity names no S: quick mode sweeps fewer (the note says which)
                        checks.append(check(f"{system}, {p}{where}: error(most sub-rays) / error(fewest)",
                                            hi["error"] / lo["error"], 1.0, 0.0, kind="max",
                                            note=f"S = {hi['s']} vs {lo['s']}; < 1: the sweep converges"))
        front = pareto(rows)
        ax.loglog([r["time"] * 1e3 for r in front], [max(r["error"], 1e-7) for r in front], "k-", lw=0.8,
                  label="Pareto front")
        for r in front:
            ax.annotate(r["label"], (r["time"] * 1e3, max(r["error"], 1e-7)), fontsize=5, xytext=(3, 3),
                        textcoords="offset points")
        label, bound = BOUNDS[system]
        row = next(r for r in rows if r["label"] == label)
        checks.append(check(f"{system}: error of {label}", row["error"], 0.0, bound, kind="max"))
        ax.set(title=f"{system}: time vs error", xlabel="time per frame, 1 thread [ms]", ylabel=METRIC[system])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.legend(fontsize=6)
    save(fig, out_dir / "pareto_fronts.png")
    lines = ["| system | setting | time per frame [ms] | error | on the Pareto front |", "|---|---|---|---|---|"]
    for system, rows in results.items():
        front = {id(r) for r in pareto(rows)}
        for r in sorted(rows, key=lambda r: r["time"]):
            lines.append(f"| {system} | {r['label']} | {r['time'] * 1e3:.1f} | {r['error']:.3g} | "
                         f"{'yes' if id(r) in front else ''} |")
    (out_dir / "timings.md").write_text("# Time and error of every setting\n\nTimes of the run that generated "
                                        f"this page (best of {repeat}; load average {load:.1f} on the machine "
                                        "when it started: times are not checked).\n\n" + "\n".join(lines) + "\n", encoding="utf-8")
    return checks
