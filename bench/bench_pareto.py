"""Run time against error for the flash ladar (issue 7): sub-rays per pixel × sub-ray pattern × time-bin width,
against a converged reference, plus the scintillation pattern's grid pitch and number of realisations.

Scenes: ``sample_blends/flash_demo.blend`` as saved (edges along the pixel axes: boxes, board panels, bollards,
grazing ground) and the same with the sensor rolled 17° about its line of sight (slanted edges).  For each
scene a reference is computed once (Sobol 64×64 sub-rays per pixel, bins 2× finer than the scene's; cached in
bench/results/cache/) and every setting is compared with it:

* ``waveform_l2``: ‖w − w_ref‖/‖w_ref‖ over the whole cube, the reference summed to the run's bins (exact:
  bins hold integrals);
* ``energy_rms``: RMS over the pixels of E − E_ref, relative to the mean E_ref of the pixels with returns;
  ``energy_total``: |ΣE/ΣE_ref − 1|;
* ``range_rmse_edges_m``: RMS first-echo range error over the edge pixels (several echoes in the reference,
  a neighbour more than 1 m away or without an echo), where both have an echo; ``range_rmse_m`` over all
  pixels; ``echo_count_mismatch``: fraction of pixels whose number of echoes differs from the reference.

Times are the best of ``--repeat`` runs of ``simulate_frame`` on one thread with the BVH built once (the
machine has 2 shared cores).  ``grid (point sub-rays)`` is the paper's model: grid, cell range spread off.

Scintillation (cheap, no ray tracing): log-normal patterns at σ² = 0.3 with 2, 4, 8 samples per correlation
radius and 1, 4, 16 realisations: SI error against e^σ² − 1 and 1/e correlation radius error against ρ_l.

Writes ``pareto.json``, ``pareto.png`` and ``pareto.md`` (the tables) to ``--out DIR`` (default runs/bench/).
``--update-committed`` writes bench/results/pareto.json, docs/pareto.png and the tables between the ``pareto``
markers of docs/performance.md instead.  ``--quick``: the unrolled scene only, a 16×16 Sobol reference, seven
settings and a small scintillation sweep, one run each (under a minute; never committed).

    .venv/bin/python bench/bench_pareto.py [--quick] [--repeat 3] [--out DIR | --update-committed]
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from core.systems.flash import simulate_frame  # noqa: E402
from core.fileio.run_folder import software_versions  # noqa: E402
from core.geometry.trace import SceneTracer  # noqa: E402
from sample_scenes import CACHE, flash_demo  # noqa: E402
from benchio import add_output_arguments, output_folder, write_json  # noqa: E402

DOC = ROOT / "docs" / "performance.md"
PLOT = ROOT / "docs" / "pareto.png"
REF_SUBSAMPLES, REF_BIN_FACTOR = 64, 2
QUICK_REF_SUBSAMPLES = 16


def rolled(pose, deg):
    """The sensor turned by ``deg`` about its line of sight (sensor −Z)."""
    a = math.radians(deg)
    roll = np.eye(4)
    roll[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    return pose @ roll


def with_settings(cfg, *, pattern="grid", subsamples=4, bin_factor=1.0, spread=True, refine=4):
    """A copy of the scene's config with the swept settings (bin width × bin_factor, same gate)."""
    rx = dataclasses.replace(cfg.receiver, subray_pattern=pattern, subsamples=subsamples, cell_range_spread=spread,
                             subray_refine=refine)
    n_bins = int(round(cfg.gate.n_bins / bin_factor))
    gate = dataclasses.replace(cfg.gate, bin_width_s=cfg.gate.bin_width_s * bin_factor, n_bins=n_bins)
    run = dataclasses.replace(cfg.run, threads=1, save_waveforms=True)
    return dataclasses.replace(cfg, receiver=rx, gate=gate, run=run)


def reference(name, scene, pose, cfg, tracer, subsamples=REF_SUBSAMPLES):
    """The converged reference of a scene (cached): waveforms at bins 2× finer, energy, first-echo range."""
    ref_cfg = with_settings(cfg, pattern="sobol", subsamples=subsamples, bin_factor=1.0 / REF_BIN_FACTOR)
    ref_cfg.run.threads = 0  # all cores: the reference is not timed
    key = hashlib.sha1(json.dumps([dataclasses.asdict(ref_cfg), scene.vertices_m.tobytes().hex()[:4096],
                                   pose.tolist()], sort_keys=True, default=str).encode()).hexdigest()[:12]
    path = CACHE / f"pareto_ref_{name}_{key}.npz"
    if path.exists():
        data = np.load(path)
        return {k: data[k] for k in data.files}
    CACHE.mkdir(parents=True, exist_ok=True)
    print(f"reference {name}: {subsamples}×{subsamples} Sobol sub-rays, bins ÷{REF_BIN_FACTOR} …", flush=True)
    t = time.perf_counter()
    res = simulate_frame(scene, pose, ref_cfg, tracer=tracer)
    out = {"waveforms": res.waveforms, "energy": res.energy_image, "range": res.range_image,
           "n_echoes": np.isfinite(res.range_echoes).sum(axis=2), "time_s": np.array(time.perf_counter() - t)}
    np.savez_compressed(path, **out)
    return out


def edge_pixels(ref):
    """Pixels with several echoes in the reference, or a 3×3 neighbour > 1 m away or without an echo."""
    r = ref["range"].astype(np.float64)
    h, w = r.shape
    pad = np.pad(r, 1, constant_values=np.nan)
    has = np.isfinite(r)
    edge = ref["n_echoes"] > 1
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nb = pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
            edge |= has & (~np.isfinite(nb) | (np.abs(nb - r) > 1.0))
    return edge


def errors(res, ref, bin_factor, edges):
    ref_wf = ref["waveforms"].astype(np.float64)
    h, w, n = res.waveforms.shape
    f = int(round(REF_BIN_FACTOR * bin_factor))
    ref_b = ref_wf.reshape(h, w, n, f).sum(axis=3)
    wf = res.waveforms.astype(np.float64)
    e, e_ref = res.energy_image, ref["energy"]
    lit = e_ref > 0
    r, r_ref = res.range_image.astype(np.float64), ref["range"].astype(np.float64)
    both = np.isfinite(r) & np.isfinite(r_ref)
    diff = np.where(both, r - r_ref, np.nan)
    n_echoes = np.isfinite(res.range_echoes).sum(axis=2)

    def rms(x):
        x = x[np.isfinite(x)]
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")
    return {"waveform_l2": float(np.linalg.norm(wf - ref_b) / np.linalg.norm(ref_b)),
            "energy_rms": float(np.sqrt(np.mean((e - e_ref) ** 2)) / e_ref[lit].mean()),
            "energy_total": float(abs(e.sum() / e_ref.sum() - 1.0)),
            "range_rmse_edges_m": rms(diff[edges]), "range_rmse_m": rms(diff),
            "echo_count_mismatch": float(np.mean(n_echoes != ref["n_echoes"]))}


def best_time(fn, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def series(quick):
    """(label, settings) of the sweep."""
    if quick:
        return [("grid (point sub-rays)", dict(pattern="grid", subsamples=2, spread=False)),
                ("grid", dict(pattern="grid", subsamples=1)), ("grid", dict(pattern="grid", subsamples=2)),
                ("stratified", dict(pattern="stratified", subsamples=2)),
                ("sobol", dict(pattern="sobol", subsamples=2)),
                ("adaptive", dict(pattern="adaptive", subsamples=2, refine=2)),
                ("bins grid", dict(pattern="grid", subsamples=2, bin_factor=2.0))]
    s_grid = (1, 2, 4, 8) if quick else (1, 2, 4, 8, 16)
    s_other = (2, 4, 8) if quick else (2, 4, 8, 16)
    out = [("grid (point sub-rays)", dict(pattern="grid", subsamples=s, spread=False)) for s in (2, 4, 8)]
    out += [("grid", dict(pattern="grid", subsamples=s)) for s in s_grid]
    out += [("stratified", dict(pattern="stratified", subsamples=s)) for s in s_other]
    out += [("sobol", dict(pattern="sobol", subsamples=s)) for s in s_other]
    out += [("adaptive", dict(pattern="adaptive", subsamples=s, refine=4)) for s in (2, 4, 8)]
    out += [("adaptive", dict(pattern="adaptive", subsamples=s, refine=2)) for s in (4, 8)]
    bins = (0.5, 2.0) if quick else (0.5, 2.0, 4.0)
    out += [(f"bins {pat}", dict(pattern=pat, subsamples=4, bin_factor=b)) for pat in ("grid", "sobol") for b in bins]
    return out


def time_to_reach(points, target_err, key):
    """Shortest time among ``points`` whose error ``key`` is at or below ``target_err`` (None if none)."""
    ok = [p["time_s"] for p in points if p["errors"][key] <= target_err]
    return min(ok) if ok else None


def summarise(scene_rows, key="waveform_l2"):
    """For each grid setting: the fastest other pattern reaching its error, and the time ratio."""
    out = []
    grid = [r for r in scene_rows if r["series"] == "grid"]
    others = {}
    for r in scene_rows:
        if r["series"] in ("stratified", "sobol", "adaptive"):
            others.setdefault(r["series"], []).append(r)
    for g in grid:
        best = None
        for name, pts in others.items():
            t = time_to_reach(pts, g["errors"][key], key)
            if t is not None and (best is None or t < best[1]):
                who = min((p for p in pts if p["errors"][key] <= g["errors"][key]), key=lambda p: p["time_s"])
                best = (name, t, who["label"])
        out.append({"grid": g["label"], "grid_time_s": g["time_s"], "grid_error": g["errors"][key],
                    "best": None if best is None else best[2],
                    "best_time_s": None if best is None else best[1],
                    "time_ratio": None if best is None else best[1] / g["time_s"]})
    return out


def scintillation_sweep(repeat, quick=False):
    """Log-normal pattern statistics vs grid pitch and realisations (σ² = 0.3, ρ_l = 1 m, 64 ρ_l square).

    The pattern is exact at its nodes; the pipeline reads it by bilinear interpolation, which smooths it most
    at the cell centres: ``si_centres_error`` (SI of the values there) shows what a coarse pitch costs,
    ``si_error`` and ``radius_error`` (nodes) the statistical spread of a finite number of realisations."""
    from core.atmosphere.phasescreen import one_over_e_radius
    from core.atmosphere.scintillation import lognormal_pattern

    s2, rho = 0.3, 1.0
    si_exact = math.exp(s2) - 1.0
    rows = []
    for spc in ((2, 4) if quick else (2, 4, 8)):
        pitch = rho / spc
        n = int(64 * spc)
        for reals in ((1, 4) if quick else (1, 4, 16)):
            rng = np.random.default_rng(7)

            def make():
                return [lognormal_pattern((n, n), pitch, s2, rho, rng) for _ in range(reals)]
            t, pats = best_time(make, repeat)
            stack = np.stack(pats)
            centres = 0.25 * (stack + np.roll(stack, 1, 1) + np.roll(stack, 1, 2) + np.roll(stack, (1, 1), (1, 2)))
            si = float(np.mean(stack ** 2) / np.mean(stack) ** 2 - 1.0)
            si_c = float(np.mean(centres ** 2) / np.mean(centres) ** 2 - 1.0)
            acov = np.zeros(n)
            for p in pats:
                d = p - p.mean()
                spec = np.abs(np.fft.fft(d, axis=1)) ** 2
                acov += np.fft.ifft(spec, axis=1).real.mean(axis=0)
            acov /= acov[0]
            radius = one_over_e_radius(acov[: n // 2], pitch)
            rows.append({"samples_per_radius": spc, "realizations": reals, "time_s": t,
                         "si": si, "si_error": abs(si / si_exact - 1.0), "si_centres_error": abs(si_c / si_exact - 1.0),
                         "radius_m": radius, "radius_error": abs(radius / rho - 1.0)})
    return {"sigma2_lnI": s2, "si_exact": si_exact, "cell_radius_m": rho, "rows": rows}


def fmt(x, digits=3):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    if isinstance(x, float):
        return f"{x:.{digits}g}"
    return str(x)


def markdown(report):
    lines = [f"Generated by `bench/bench_pareto.py`{' --quick' if report['quick'] else ''} "
             f"({report['created']}, one thread, best of {report['repeat']}).", ""]
    for sc in report["scenes"]:
        lines += [f"**{sc['name']}** ({sc['n_pixels']} pixels, {sc['n_edge_pixels']} edge pixels; reference "
                  f"{report['reference_subsamples']}×{report['reference_subsamples']} Sobol rays, "
                  f"{sc['reference_time_s']:.0f} s):", "",
                  "| series | S | refine | bin (ns) | time (s) | waveform L2 | energy RMS | range RMSE edges (m) "
                  "| echo-count mismatch |", "|---|---|---|---|---|---|---|---|---|"]
        for r in sc["rows"]:
            e = r["errors"]
            lines.append(f"| {r['series']} | {r['subsamples']} | {r.get('refine') or ''} | "
                         f"{r['bin_width_s'] * 1e9:g} | {r['time_s']:.3f} | {fmt(e['waveform_l2'])} | "
                         f"{fmt(e['energy_rms'])} | {fmt(e['range_rmse_edges_m'])} | {fmt(e['echo_count_mismatch'])} |")
        lines += ["", "Fastest other pattern reaching each grid setting's waveform L2 error:", "",
                  "| grid | grid time (s) | grid error | reached by | its time (s) | time ratio |",
                  "|---|---|---|---|---|---|"]
        for s in sc["summary_waveform_l2"]:
            lines.append(f"| {s['grid']} | {s['grid_time_s']:.3f} | {fmt(s['grid_error'])} | {s['best'] or '—'} | "
                         f"{fmt(s['best_time_s'])} | {fmt(s['time_ratio'], 2)} |")
        lines += ["", "… and each grid setting's range RMSE at edges (m):", "",
                  "| grid | grid time (s) | grid error (m) | reached by | its time (s) | time ratio |",
                  "|---|---|---|---|---|---|"]
        for s in sc["summary_range_rmse_edges_m"]:
            lines.append(f"| {s['grid']} | {s['grid_time_s']:.3f} | {fmt(s['grid_error'])} | {s['best'] or '—'} | "
                         f"{fmt(s['best_time_s'])} | {fmt(s['time_ratio'], 2)} |")
        lines.append("")
    sc = report["scintillation"]
    lines += [f"**Scintillation pattern** (log-normal, σ² = {sc['sigma2_lnI']}, SI = {sc['si_exact']:.4f}, "
              f"ρ_l = {sc['cell_radius_m']} m, 64 ρ_l square):", "",
              "| samples per ρ_l | realisations | time (s) | SI error (nodes) | SI error (bilinear, cell centres) "
              "| 1/e radius error |", "|---|---|---|---|---|---|"]
    for r in sc["rows"]:
        lines.append(f"| {r['samples_per_radius']} | {r['realizations']} | {r['time_s']:.3f} | "
                     f"{fmt(r['si_error'])} | {fmt(r['si_centres_error'])} | {fmt(r['radius_error'])} |")
    return "\n".join(lines)


def write_doc_block(text, marker="pareto"):
    begin, end = f"<!-- {marker}:begin -->", f"<!-- {marker}:end -->"
    doc = DOC.read_text(encoding="utf-8")
    if begin not in doc:
        raise SystemExit(f"{DOC} has no {begin} … {end} block")
    head, rest = doc.split(begin, 1)
    _, tail = rest.split(end, 1)
    DOC.write_text(f"{head}{begin}\n{text}\n{end}{tail}", encoding="utf-8")


def plot(report, path=PLOT):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [("waveform_l2", "waveform L2 error"), ("range_rmse_edges_m", "range RMSE at edges (m)")]
    fig, axes = plt.subplots(len(keys), len(report["scenes"]), figsize=(6 * len(report["scenes"]), 8.5),
                             squeeze=False)
    styles = {"grid": "o-", "grid (point sub-rays)": "x:", "stratified": "s-", "sobol": "^-", "adaptive": "D-",
              "bins grid": "o--", "bins sobol": "^--"}
    for j, sc in enumerate(report["scenes"]):
        for i, (key, label) in enumerate(keys):
            ax = axes[i, j]
            for name, style in styles.items():
                pts = sorted((r for r in sc["rows"] if r["series"] == name), key=lambda r: r["time_s"])
                if name == "adaptive":
                    for refine in sorted({r["refine"] for r in pts}):
                        sub = [r for r in pts if r["refine"] == refine]
                        ax.plot([r["time_s"] for r in sub], [r["errors"][key] for r in sub], style,
                                label=f"adaptive ×{refine}")
                        for r in sub:
                            ax.annotate(str(r["subsamples"]), (r["time_s"], r["errors"][key]), fontsize=7)
                    continue
                if not pts:
                    continue
                ax.plot([r["time_s"] for r in pts], [r["errors"][key] for r in pts], style, label=name)
                for r in pts:
                    tag = f"{r['bin_width_s'] * 1e9:g} ns" if name.startswith("bins") else str(r["subsamples"])
                    ax.annotate(tag, (r["time_s"], r["errors"][key]), fontsize=7)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("run time (s, one thread)")
            ax.set_ylabel(label)
            ax.set_title(sc["name"], fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    add_output_arguments(ap)
    args = ap.parse_args(argv)
    folder = output_folder(ap, args)
    if args.quick:
        args.repeat = 1
    ref_subsamples = QUICK_REF_SUBSAMPLES if args.quick else REF_SUBSAMPLES

    scene, pose, cfg = flash_demo()
    tracer = SceneTracer(scene)
    report = {"benchmark": "flash Pareto: run time vs error (issue 7)", "quick": args.quick, "repeat": args.repeat,
              "created": time.strftime("%Y-%m-%d"), "reference_subsamples": ref_subsamples, "scenes": [],
              "software": software_versions()}
    scenes = [("flash_demo", pose)] + ([] if args.quick else [("flash_demo rolled 17°", rolled(pose, 17.0))])
    for name, p in scenes:
        ref = reference(name.replace(" ", "_").replace("°", "deg"), scene, p, cfg, tracer, ref_subsamples)
        edges = edge_pixels(ref)
        rows = []
        for label, kw in series(args.quick):
            run_cfg = with_settings(cfg, **kw)
            t, res = best_time(lambda: simulate_frame(scene, p, run_cfg, tracer=tracer), args.repeat)
            row = {"series": label, "label": f"{kw['pattern']} S={kw['subsamples']}"
                   + (f" ×{kw['refine']}" if kw['pattern'] == "adaptive" else "")
                   + (f" bin×{kw['bin_factor']:g}" if "bin_factor" in kw else "")
                   + ("" if kw.get("spread", True) else " point"),
                   "subsamples": kw["subsamples"], "refine": kw.get("refine") if kw["pattern"] == "adaptive" else None,
                   "bin_width_s": run_cfg.gate.bin_width_s, "time_s": t, "n_rays": res.stats["n_rays"],
                   "stage_times_s": res.stats["stage_times_s"],
                   "errors": errors(res, ref, kw.get("bin_factor", 1.0), edges)}
            rows.append(row)
            print(f"{name:24s} {row['label']:28s} {t:7.3f} s  " + "  ".join(f"{k} {v:.4g}" for k, v in row["errors"].items()),
                  flush=True)
        report["scenes"].append({"name": name, "n_pixels": int(edges.size), "n_edge_pixels": int(edges.sum()),
                                 "reference_time_s": float(ref["time_s"]), "rows": rows,
                                 "summary_waveform_l2": summarise(rows, "waveform_l2"),
                                 "summary_range_rmse_edges_m": summarise(rows, "range_rmse_edges_m")})
    report["scintillation"] = scintillation_sweep(args.repeat, args.quick)
    text = markdown(report)
    write_json(folder / "pareto.json", report, indent=1)
    if args.update_committed:
        plot(report)
        write_doc_block(text)
    else:
        plot(report, folder / "pareto.png")
        (folder / "pareto.md").write_text(text + "\n", encoding="utf-8")
    print(text)
    print(f"wrote {folder / 'pareto.json'}")


if __name__ == "__main__":
    main()
