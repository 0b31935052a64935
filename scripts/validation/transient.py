"""The range profiler's waveform against an independent transient renderer: Mitsuba 3 with mitransient."""
from __future__ import annotations

import json
import math
import subprocess
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy.special import ndtr

from validation import Skipped, check, save
from validation._common import C, FWHM_PER_SIGMA, ROOT

from core.config.settings import BRDFSettings
from core.physics.brdf import evaluate_brdf
from core.run import simulate

TITLE = "Independent transient renderer: the profiler against Mitsuba 3 + mitransient"
ORDER = 45
#: the optional environment (scripts/setup_validation.sh, requirements-validation.txt)
VENV_PYTHON = ROOT / ".venv-validation" / "bin" / "python"
RENDERER = Path(__file__).with_name("_mitsuba_render.py")
#: simulator seeds and Mitsuba batches: the scatter between them gives the statistical tolerances
BATCHES = 8
#: the Steinvall BRDF is handed to Mitsuba as a table of f_r(θ) in steps of this many degrees (linear interpolation
#: of a smooth function: its error ≤ h²/8·|f''| — below 1e-5 of f_r for this material, see ``brdf_table``)
TABLE_STEP_DEG = 0.05
#: Mitsuba's path-length histogram: bins this many times finer than the simulator's, then integrated against the
#: pulse per simulator bin (as the brute-force reference of the systems page)
FINE = 10
#: the stratified 256² sub-rays' L2 bound: the systems page's bound for the sample's own 256² sub-rays (5 %); their
#: cells (9 cm at 2 km) put each edge cell's return on the plane its ray hit, a bias that shrinks with the cell
#: (measured 1.7 % here, 0.6 % for the adaptive pattern's 1024² Sobol rays: within Mitsuba's noise)
STRATIFIED_L2_BOUND = 0.05
INTRO = f"""The aircraft sample (`sample_blends/aircraft_profile.blend`: 68 triangles 2 km away, one Steinvall
material, a 12 mrad square field of view filled by a uniform beam, a 1 ns Gaussian pulse, 1001 bins of 0.2 ns)
exported through the project's own Blender scene extraction (bench/sample_scenes.py) and written as a Mitsuba 3
scene (`export_mitsuba_scene` in scripts/validation/transient.py: one PLY mesh per material and a scene
description) that `scripts/validation/_mitsuba_render.py` renders in the separate environment `.venv-validation`
(Mitsuba 3.9.1, Dr.Jit 1.5.0 on its LLVM backend, mitransient 1.3.1, pinned in requirements-validation.txt; set
up by `bash scripts/setup_validation.sh`, which also installs `libllvm19` with apt-get where no libLLVM ≥ 16 is
found).  Where that environment is missing this page's checks are skipped with the reason (CI does not set it
up).

**The Mitsuba scene.**  A pinhole `perspective` sensor at the ladar's pose and field of view (the simulator's
tan-plane square), a `point` emitter of 1 W/sr at the same point (monostatic), `transient_path` with
`max_depth = 2` (one bounce: the laser radar equation's single scattering), a `transient_hdr_film` histogramming
the optical path length emitter → surface → sensor in bins {FINE} times finer than the simulator's (0.6 cm of
path).  Mitsuba's mean pixel radiance L̄(t) per 1 W/sr turns into received energy per bin as
E(t) = η·π r_a²·E_T·L̄(t): a pixel of tan-plane area a subtends a·cos³θ sr, and the simulator's uniform beam
puts E_T·a/A_tan into it, an intensity E_T/(A_tan cos³θ); the cos³θ cancel exactly (so does A_tan).  The
path-length histogram is then integrated against the Gaussian pulse over each simulator bin.  Materials: the
Lambert case uses Mitsuba's own `diffuse` BSDF (two-sided); the sample's Steinvall BRDF is handed over as a
table of f_r(θ) every {TABLE_STEP_DEG}° (θ between the normal and the half vector, the incidence angle in the
monostatic geometry), evaluated by a two-sided BSDF written in `_mitsuba_render.py`.

**What is compared.**  Mitsuba renders {BATCHES} independent batches (their own seeds).  For each material the
simulator runs twice: with `receiver.subray_pattern = adaptive` (the single profiler pixel mixes hits and misses,
so it is refined to 1024² Sobol rays: deterministic) and with `stratified` 256² sub-rays over {BATCHES} seeds (an
unbiased Monte Carlo estimate of the energy).  Each gives three checks: the received energy (absolute: the
radiometry of both renderers must agree), the L2 distance of the two normalised waveforms relative to the norm of
Mitsuba's, and the energy-weighted mean range.  The tolerances come from the sample counts through the scatter
of the runs: the variance of a mean is s²/k (s² the sample variance over its k runs; 0 for the deterministic
adaptive run), energy and mean range may differ by 4σ.  The L2 check allows what the noise alone gives two
unbiased estimates of the same normalised waveform: the difference d of the means has the covariance C estimated
from the runs, E‖d‖² = tr C and, for Gaussian noise, sd ‖d‖² = √(2 tr C²); the tolerance is
√(tr C + 4·√(2 tr C²)) / ‖w‖ (the notes give √(tr C)/‖w‖, the noise alone).  More samples shrink these
tolerances: a systematic difference cannot hide in them.  The stratified 256² waveform's shape is held to the
systems page's bound for the sample's own 256² sub-rays instead ({STRATIFIED_L2_BOUND:.0%}): each 9 cm cell at an
edge of the aircraft puts its return on the plane its ray hit, a bias that shrinks with the cell (it shows beside
the noise in the difference plot, at the tail's grazing surfaces near 2005 m).  The sample's own *grid* is
plotted too (it aliases with the aircraft's straight edges: systems page)."""


def _venv_reason() -> str | None:
    """None when the Mitsuba environment works; else the reason (the exact failure)."""
    if not VENV_PYTHON.exists():
        return (f"the optional Mitsuba environment {VENV_PYTHON.relative_to(ROOT)} is missing "
                "(set it up with `bash scripts/setup_validation.sh`)")
    try:
        proc = subprocess.run([str(VENV_PYTHON), str(RENDERER), "--check"], capture_output=True, text=True,
                              timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{VENV_PYTHON.relative_to(ROOT)} does not run: {exc}"
    if proc.returncode != 0:
        last = (proc.stderr.strip() or proc.stdout.strip() or f"exit status {proc.returncode}").splitlines()[-1]
        return f"Mitsuba in {VENV_PYTHON.relative_to(ROOT)} fails its check: {last}"
    return None


def environment_reason() -> str | None:
    """Why the transient comparison cannot run here (None: it can)."""
    return _venv_reason()


def brdf_table(brdf: BRDFSettings, step_deg: float = TABLE_STEP_DEG) -> np.ndarray:
    """f_r [1/sr] at θ = 0, step, …, 90° from the simulator's own BRDF evaluation (the material's definition)."""
    theta = np.arange(0.0, 90.0 + 0.5 * step_deg, step_deg)
    return evaluate_brdf(brdf, np.cos(np.radians(theta)))


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(faces)}\n"
            "property list uchar int vertex_indices\nend_header\n").encode("ascii")
    face_rows = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", 3)])
    face_rows["n"], face_rows["v"] = 3, faces
    path.write_bytes(head + np.asarray(vertices, "<f4").tobytes() + face_rows.tobytes())


def export_mitsuba_scene(scene, pose, cfg, folder: Path, *, pixels: int, spp: int, batches: int, seed: int,
                         fine: int = FINE) -> dict:
    """Write the Mitsuba scene of a profiler run into ``folder``: one PLY mesh per material (world metres) and
    ``scene.json`` (pose, field of view, time window, sample counts, materials).  Returns the description."""
    folder.mkdir(parents=True, exist_ok=True)
    rx, gate = cfg.receiver, cfg.gate
    if not math.isclose(rx.fov_x_rad, rx.fov_y_rad) or rx.width_px != rx.height_px:
        raise ValueError("export_mitsuba_scene: a square field of view and pixel grid only (the profiler sample)")
    if cfg.laser.beam_profile != "uniform" or not cfg.laser.divergence_fills_fov:
        raise ValueError("export_mitsuba_scene: laser.beam_profile = 'uniform' filling the field of view only")
    origin = np.asarray(pose, float)[:3, 3]
    materials = []
    tri = np.asarray(scene.triangles)
    mids = np.asarray(scene.material_ids)
    for k, brdf in enumerate(scene.materials):
        sel = tri[mids == k]
        if not len(sel):
            continue
        used, inverse = np.unique(sel.reshape(-1), return_inverse=True)
        _write_ply(folder / f"mesh_{k}.ply", scene.vertices_m[used], inverse.reshape(-1, 3))
        if brdf.model == "lambertian":
            materials.append({"kind": "lambert", "reflectance": float(brdf.reflectance), "mesh": f"mesh_{k}.ply"})
        else:
            materials.append({"kind": "table", "step_deg": TABLE_STEP_DEG, "values": brdf_table(brdf).tolist(),
                              "mesh": f"mesh_{k}.ply"})
    r = np.linalg.norm(scene.vertices_m - origin, axis=1)
    bin_opl = C * gate.bin_width_s / fine
    start_opl = C * gate.gate_start_s
    desc = {"world_from_sensor": np.asarray(pose, float).tolist(),
            "fov_x_deg": math.degrees(2 * math.atan(math.tan(rx.fov_x_rad / 2))),
            # Mitsuba starts camera rays on the near-clip plane: their path length is short by near_clip/cos θ
            "near_clip_m": 1e-4, "far_clip_m": float(2 * r.max()),
            "pixels": int(pixels), "spp": int(spp), "batches": int(batches), "seed": int(seed),
            "bins": int(gate.n_bins * fine), "start_opl_m": start_opl, "bin_opl_m": bin_opl,
            "threads": int(max(1, cfg.run.threads)), "materials": materials}
    (folder / "scene.json").write_text(json.dumps(desc), encoding="utf-8")
    return desc


def pulse_waveform(fine_hist: np.ndarray, cfg, fine: int = FINE) -> np.ndarray:
    """Energy per simulator bin from a histogram over path-length bins ``fine`` times finer: each fine bin's
    energy at its centre time, integrated against the Gaussian pulse over every bin."""
    gate = cfg.gate
    edges = gate.gate_start_s + np.arange(gate.n_bins + 1) * gate.bin_width_s
    tc = gate.gate_start_s + (np.arange(len(fine_hist)) + 0.5) * gate.bin_width_s / fine
    keep = fine_hist != 0
    sig = cfg.laser.pulse_fwhm_s / FWHM_PER_SIGMA
    return fine_hist[keep] @ np.diff(ndtr((edges[None, :] - tc[keep][:, None]) / sig), axis=1)


def render_mitsuba(scene, pose, cfg, *, pixels, spp, batches, seed):
    """(per-batch waveforms (batches, n_bins) J per bin, seconds) from Mitsuba."""
    with tempfile.TemporaryDirectory(prefix="mitsuba-") as tmp:
        folder = Path(tmp)
        export_mitsuba_scene(scene, pose, cfg, folder / "scene", pixels=pixels, spp=spp, batches=batches,
                             seed=seed)
        out = folder / "out.npz"
        proc = subprocess.run([str(VENV_PYTHON), str(RENDERER), str(folder / "scene"), str(out)],
                              capture_output=True, text=True, timeout=3600)
        if proc.returncode != 0:
            raise RuntimeError(f"Mitsuba render failed: {proc.stderr.strip()[-2000:]}")
        data = np.load(out)
        transient, secs = data["transient"], float(data["seconds"])
    scale = (cfg.receiver.system_efficiency * math.pi * (cfg.receiver.aperture_diameter_m / 2) ** 2
             * cfg.laser.pulse_energy_j)
    return np.stack([pulse_waveform(row * scale, cfg) for row in transient]), secs


def simulator_batches(scene, pose, cfg, pattern, seeds):
    out = []
    for s in seeds:
        cfg.receiver.subray_pattern = pattern
        cfg.run.seed = s
        out.append(simulate(scene, pose, cfg).waveforms.reshape(-1).astype(np.float64))
    return np.stack(out)


def _aircraft():
    import sys
    sys.path.insert(0, str(ROOT / "bench"))
    from sample_scenes import load_blend
    scene, pose, cfg = load_blend("aircraft_profile")
    assert cfg.system_type == "profiler" and cfg.laser.beam_profile == "uniform" and \
        cfg.laser.pulse_shape == "gaussian", "the aircraft sample changed: update this page"
    assert cfg.atmosphere.visibility_m == 0 and cfg.atmosphere.extinction_per_m == 0 and \
        cfg.atmosphere.cn2_m_23 == 0, "the sample has an atmosphere now: the Mitsuba scene has none"
    assert cfg.detector.mode == "ideal"
    cfg.run.threads = 1
    return scene, pose, cfg


def _var_of_mean(batches, axis=0):
    """Variance of the mean of the rows (0 for a single, deterministic row)."""
    k = len(batches)
    return batches.var(axis=axis, ddof=1) / k if k > 1 else np.zeros_like(batches[0]) if axis == 0 else 0.0


def compare(label, sim, mit, r, checks, *, l2_bound=None, note=""):
    """Checks of one simulator setting against Mitsuba: received energy, L2 distance of the normalised waveforms,
    energy-weighted mean range.  ``sim``/``mit`` (runs, bins): seeds/batches; the tolerances come from their
    scatter (a single simulator row is deterministic: Mitsuba's noise alone).  ``l2_bound``: a stated bound for
    the L2 check instead (a known discretisation bias).  Returns (simulator mean, Mitsuba mean, σ per bin)."""
    ks, km = len(sim), len(mit)
    ms, mm = sim.mean(axis=0), mit.mean(axis=0)
    e_s, e_m = ms.sum(), mm.sum()
    sig_e = math.sqrt(_var_of_mean(sim.sum(axis=1)) + _var_of_mean(mit.sum(axis=1)))
    runs = f"{ks} seeds, {km} batches" if ks > 1 else f"{km} batches"
    checks.append(check(f"{label}: received energy", e_s, e_m, 4 * sig_e / e_m, unit="J",
                        note=f"{note}±4σ of the {runs}"))
    # normalised waveforms of every run; the noise of the difference of the two means has the covariance A^T A,
    # A stacking the runs' deviations scaled by 1/√(k(k−1)) (rank ≤ ks + km − 2)
    ns_b, nm_b = sim / sim.sum(axis=1, keepdims=True), mit / mit.sum(axis=1, keepdims=True)
    ns, nm = ms / e_s, mm / e_m
    parts = [(nm_b - nm_b.mean(axis=0)) / math.sqrt(km * (km - 1))]
    if ks > 1:
        parts.append((ns_b - ns_b.mean(axis=0)) / math.sqrt(ks * (ks - 1)))
    a = np.concatenate(parts)
    mean_d2 = float(np.sum(a * a))                         # E‖d‖² = tr C
    sd_d2 = math.sqrt(2.0 * float(np.sum((a @ a.T) ** 2)))  # sd ‖d‖² = √(2 tr C²) for Gaussian noise
    norm = float(np.linalg.norm(nm))
    l2 = float(np.linalg.norm(ns - nm) / norm)
    noise = math.sqrt(mean_d2) / norm
    if l2_bound is None:
        checks.append(check(f"{label}: L2 distance of the normalised waveforms / ‖Mitsuba‖", l2, 0.0,
                            math.sqrt(mean_d2 + 4 * sd_d2) / norm, kind="max",
                            note=f"{note}√(E‖d‖² + 4 sd‖d‖²) of the noise; the noise alone {noise:.2g}"))
    else:
        checks.append(check(f"{label}: L2 distance of the normalised waveforms / ‖Mitsuba‖", l2, 0.0, l2_bound,
                            kind="max", note=f"{note}stated bound; the noise alone {noise:.2g}"))
    mean_s = np.sum(sim * r, axis=1) / sim.sum(axis=1)
    mean_m = np.sum(mit * r, axis=1) / mit.sum(axis=1)
    sig_r = math.sqrt(_var_of_mean(mean_s) + _var_of_mean(mean_m))
    checks.append(check(f"{label}: energy-weighted mean range", float(mean_s.mean()), float(mean_m.mean()),
                        4 * sig_r, kind="abs", unit="m", note=f"{note}±4σ"))
    sigma = np.sqrt(_var_of_mean(sim) + _var_of_mean(mit))
    return ms, mm, sigma


def run(out_dir: Path, quick: bool) -> list[dict]:
    reason = environment_reason()
    if reason is not None:
        raise Skipped(reason)
    scene, pose, cfg = _aircraft()
    pixels, spp = (32, 256) if quick else (64, 1024)
    seeds = list(range(1, BATCHES + 1))
    t = cfg.gate.gate_start_s + (np.arange(cfg.gate.n_bins) + 0.5) * cfg.gate.bin_width_s
    r = 0.5 * C * t
    checks, curves = [], {}
    steinvall = scene.materials[0]
    for label, brdf in (("Lambert ρ = 0.3", BRDFSettings(model="lambertian", reflectance=0.3)),
                        ("Steinvall (the sample's paint)", steinvall)):
        scene.materials[0] = brdf
        mit, secs = render_mitsuba(scene, pose, cfg, pixels=pixels, spp=spp, batches=BATCHES, seed=11)
        adaptive = simulator_batches(scene, pose, cfg, "adaptive", [1])
        ma, mm, sigma = compare(f"{label}, adaptive", adaptive, mit, r, checks)
        strat = simulator_batches(scene, pose, cfg, "stratified", seeds)
        ms, _, _ = compare(f"{label}, stratified 256²", strat, mit, r, checks, l2_bound=STRATIFIED_L2_BOUND)
        extra = {f"stratified 256² ({BATCHES} seeds)": ms}
        if brdf is steinvall:
            extra["grid 256², the sample's settings"] = simulator_batches(scene, pose, cfg, "grid", [1])[0]
        curves[label] = (ma, mm, sigma, extra)
    scene.materials[0] = steinvall
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex="col", gridspec_kw={"height_ratios": [2, 1]})
    for col, (label, (ms, mm, sigma, extra)) in enumerate(curves.items()):
        ax, res = axes[0, col], axes[1, col]
        nz = np.nonzero(mm > mm.max() * 1e-4)[0]
        sl = slice(max(nz[0] - 20, 0), min(nz[-1] + 20, len(r)))
        ax.plot(r[sl], mm[sl] * 1e15, "k", lw=1.6, label=f"Mitsuba 3 + mitransient ({BATCHES} batches)")
        ax.plot(r[sl], ms[sl] * 1e15, "C1--", lw=1.2, label="simulator, adaptive")
        for k, (name, wf) in enumerate(extra.items()):
            ax.plot(r[sl], wf[sl] * 1e15, f"C{2 + k}:", lw=1.0, label=f"simulator, {name}")
        ax.set(title=f"aircraft profile, {label}", xlabel="range c·t/2 [m]", ylabel="energy per bin [fJ]")
        ax.legend(fontsize=7)
        res.fill_between(r[sl], -2 * sigma[sl] * 1e15, 2 * sigma[sl] * 1e15, color="0.85",
                         label="±2σ of Mitsuba's mean (sample counts)")
        res.plot(r[sl], (ms[sl] - mm[sl]) * 1e15, "C1", lw=0.8, label="simulator (adaptive) − Mitsuba")
        for k, (name, wf) in enumerate(extra.items()):
            res.plot(r[sl], (wf[sl] - mm[sl]) * 1e15, f"C{2 + k}", lw=0.6, alpha=0.8,
                     label=f"simulator ({name.split(' (')[0].split(',')[0]}) − Mitsuba")
        res.set(title="difference", xlabel="range c·t/2 [m]", ylabel="Δ energy per bin [fJ]")
        res.legend(fontsize=6)
    save(fig, out_dir / "profiler_vs_mitsuba.png")
    return checks
