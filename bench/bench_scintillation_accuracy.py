"""Scintillation accuracy: split-step wave optics vs the product vs the paper's formulas (issue 17; one run).

For every off-grid validation case of ``bench/results/scintillation_wave_optics.json`` (the split-step runs of
``scripts/tabulate_scintillation.py``: plane and spherical waves, 532 and 1064 nm, l0 = 0 and 5 mm, 1 km) this
measures, with the split-step run's own estimator (:class:`core.atmosphere.phasescreen.IntensityStatistics`:
pooled SI, var ln I, azimuthal covariance of the periodic field):

* ``table``: the default statistics of the product (:func:`core.atmosphere.wave_optics.statistics`);
* ``pattern``: the patterns the simulator draws with the default statistics (``--patterns`` patterns of 0.8 m);
* ``paper``: the paper's formulas (all-regime SI, eq. 3-6 radius) and the patterns drawn with
  ``statistics="paper"`` (the generator before issue 17);

and for each the relative SI, σ²_lnI and 1/e-radius errors and the largest covariance difference out to 3
radii.  The averaged factors: the SI of the intensity averaged over a disk of diameter D (D/F = 0.5 … 4) measured
in the split-step run against SI·A(D) of the table (A the aperture integral of its covariance) and of the paper
(all-regime SI × its aperture-averaging formula); and the footprint (return-path) variance factor of a square
footprint p × p (p/F = 0.5 … 4), the rectangle average of the covariance, from the split-step covariance against
the table's and the paper's (Gaussian box average with the eq. 3-6 radius).  Writes
``scintillation_accuracy.json`` to ``--out DIR`` (default runs/bench/; ``--update-committed``:
bench/results/scintillation_accuracy.json) and prints markdown tables.  ``--quick``: the first two cases, two
patterns each (the errors of two patterns are noisy; seconds).

    .venv/bin/python bench/bench_scintillation_accuracy.py [--patterns 16] [--out DIR | --update-committed] [--quick]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.atmosphere import phasescreen as ps  # noqa: E402
from core.atmosphere import scintillation as sc  # noqa: E402
from core.atmosphere import turbulence as tb  # noqa: E402
from core.atmosphere import wave_optics as wo  # noqa: E402
from core.atmosphere.derived import derived_turbulence  # noqa: E402
from core.physics.propagation import box_average_variance_factor  # noqa: E402

RUNS = ROOT / "bench" / "results" / "scintillation_wave_optics.json"  # input (scripts/tabulate_scintillation.py)
EXTENT = (-0.4, 0.4, -0.4, 0.4)
FOOTPRINTS_F = (0.5, 1.0, 2.0, 4.0)


def shape_error(lags_a, cov_a, lags_b, cov_b, radius):
    """Largest |C_a − C_b| on 121 lags from 0 to 3 radii (linear interpolation of both)."""
    r = np.linspace(0.0, 3.0 * radius, 121)
    return float(np.max(np.abs(np.interp(r, lags_a, cov_a) - np.interp(r, lags_b, cov_b))))


def pattern_statistics(v, statistics, n_patterns):
    lags = np.asarray(v["lags_m"])
    acc, sis = None, []
    for seed in range(n_patterns):
        p = sc.make_scintillation_pattern(EXTENT, v["cn2_m_23"], v["wavelength_m"], v["range_m"],
                                          np.random.default_rng(seed), wave=v["wave"], statistics=statistics,
                                          inner_scale_m=v["inner_scale_m"] if statistics == "wave_optics" else 0.0,
                                          max_grid_px=1024)
        values = p.values if hasattr(p, "values") else None
        if values is None:                       # a two-grid ProductPattern: sample it on a regular grid
            n = 1024
            x = EXTENT[0] + (np.arange(n) + 0.5) * (EXTENT[1] - EXTENT[0]) / n
            xx, yy = np.meshgrid(x, x, indexing="xy")
            values, pitch = p.sample(xx, yy), (EXTENT[1] - EXTENT[0]) / n
        else:
            pitch = p.pitch_m
        if acc is None:
            n = values.shape[0]
            acc = ps.IntensityStatistics(n, pitch, lags[lags <= n * pitch / 3.0])
        acc.add(values)
        sis.append(values.var() / values.mean() ** 2)
    r = acc.result()
    r["si_std_err"] = float(np.std(sis, ddof=1) / math.sqrt(n_patterns))
    r["lags_m"] = acc.lags
    r["model"] = p.model
    return r


def errors(v, si, lnv, radius, lags, cov):
    ref_r = v["correlation_radius_over_f"] * v["fresnel_scale_m"]
    out = {"si": si, "sigma2_lnI": lnv, "radius_m": radius,
           "si_rel_error": si / v["scintillation_index"] - 1.0,
           "radius_rel_error": radius / ref_r - 1.0}
    if lnv is not None:
        out["sigma2_lnI_rel_error"] = lnv / v["sigma2_lnI"] - 1.0
    if cov is not None:
        out["shape_error"] = shape_error(lags, cov, v["lags_m"], v["covariance"], ref_r)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--patterns", type=int, default=16)
    sys.path.insert(0, str(ROOT / "bench"))
    from benchio import add_output_arguments, output_path, write_json

    add_output_arguments(ap)
    a = ap.parse_args(argv)
    out_path = output_path(ap, a, "scintillation_accuracy.json")
    runs = json.loads(RUNS.read_text())
    validation = runs["validation"]
    if a.quick:
        a.patterns, validation = 2, validation[:2]
    cases = []
    for v in validation:
        t0 = time.perf_counter()
        st = wo.statistics(v["cn2_m_23"], v["wavelength_m"], v["range_m"], v["wave"], v["inner_scale_m"])
        table = errors(v, st["scintillation_index"], st["sigma2_lnI"], st["correlation_radius_m"], st["lags_m"],
                       st["covariance"])
        pw = pattern_statistics(v, "wave_optics", a.patterns)
        pattern = errors(v, pw["scintillation_index"], pw["sigma2_lnI"], pw["correlation_radius_m"], pw["lags_m"],
                         pw["covariance"])
        pattern.update(si_std_err=pw["si_std_err"], model=pw["model"])
        d = derived_turbulence(v["cn2_m_23"], v["wavelength_m"], v["range_m"], wave=v["wave"], statistics="paper")
        formula = errors(v, d["scintillation_index"], d["sigma2_lnI"], d["cell_radius_m"], None, None)
        pp = pattern_statistics(v, "paper", a.patterns)
        paper_pattern = errors(v, pp["scintillation_index"], pp["sigma2_lnI"], pp["correlation_radius_m"],
                               pp["lags_m"], pp["covariance"])
        paper_pattern.update(si_std_err=pp["si_std_err"], model=pp["model"])
        F = v["fresnel_scale_m"]
        aperture = []
        for d_f, ap_si in zip(v["aperture_over_f"], v["aperture_si"]):
            t_si = st["scintillation_index"] * wo.aperture_averaging_factor(st, d_f * F)
            p_si = d["scintillation_index"] * float(tb.aperture_averaging_factor(v["wavelength_m"], v["range_m"],
                                                                                 d_f * F, v["wave"]))
            aperture.append({"d_over_f": d_f, "wave_optics_si": ap_si, "table_si": t_si, "paper_si": p_si,
                             "table_rel_error": t_si / ap_si - 1.0, "paper_rel_error": p_si / ap_si - 1.0})
        ref_stats = {"lags_m": np.asarray(v["lags_m"]), "covariance": np.asarray(v["covariance"])}
        footprint = []
        for p_f in FOOTPRINTS_F:
            g_ref = wo.footprint_averaging_factor(ref_stats, p_f * F, p_f * F)
            g_tab = wo.footprint_averaging_factor(st, p_f * F, p_f * F)
            g_pap = float(box_average_variance_factor(p_f * F, d["cell_radius_m"])) ** 2
            footprint.append({"p_over_f": p_f, "wave_optics": g_ref, "table": g_tab, "paper": g_pap,
                              "table_rel_error": g_tab / g_ref - 1.0, "paper_rel_error": g_pap / g_ref - 1.0})
        case = {"wave": v["wave"], "wavelength_m": v["wavelength_m"], "cn2_m_23": v["cn2_m_23"], "beta2": v["beta2"],
                "inner_scale_m": v["inner_scale_m"], "fresnel_scale_m": v["fresnel_scale_m"],
                "wave_optics": {"si": v["scintillation_index"], "si_std_err": v["si_std_err"],
                                "sigma2_lnI": v["sigma2_lnI"],
                                "radius_m": v["correlation_radius_over_f"] * v["fresnel_scale_m"]},
                "table": table, "pattern": pattern, "paper_formula": formula, "paper_pattern": paper_pattern,
                "aperture": aperture, "footprint": footprint, "seconds": time.perf_counter() - t0}
        cases.append(case)
        print(json.dumps({k: case[k] for k in ("wave", "wavelength_m", "cn2_m_23", "beta2", "inner_scale_m")}),
              flush=True)
    keys = ("si_rel_error", "sigma2_lnI_rel_error", "radius_rel_error", "shape_error")
    worst = {m: {k: max(abs(c[m][k]) for c in cases if k in c[m]) for k in keys if any(k in c[m] for c in cases)}
             for m in ("table", "pattern", "paper_formula", "paper_pattern")}
    for kind in ("aperture", "footprint"):
        for m in ("table", "paper"):
            rows = [x for c in cases for x in c[kind] if kind == "footprint" or x["wave_optics_si"] >= 0.01]
            worst[f"{kind}_{m}"] = max(abs(x[f"{m}_rel_error"]) for x in rows)
    out = {"description": __doc__.split("\n")[0], "quick": a.quick, "patterns": a.patterns, "extent_m": EXTENT, "cases": cases,
           "max_abs_error": worst, "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    print(markdown(out))
    print(f"wrote {write_json(out_path, out, indent=1)}")
    return 0


def _pct(x):
    return f"{100 * x:+.1f} %"


def markdown(out):
    head = ["| case: wave, λ, Cn² (β0²), l0 | SI wave optics | table | pattern | paper formula | paper pattern | "
            "σ²_lnI wave optics | table | pattern |", "|---" * 9 + "|"]
    head2 = ["| case | 1/e radius [mm] wave optics | table | pattern | paper eq. 3-6 | paper pattern | max ΔC to 3 radii: "
             "table / pattern / paper pattern | SI·A(D) error, D/F = 0.5 … 4: table / paper | footprint factor error, "
             "p/F = 0.5 … 4: table / paper |", "|---" * 9 + "|"]
    for c in out["cases"]:
        w, t, p, f, q = c["wave_optics"], c["table"], c["pattern"], c["paper_formula"], c["paper_pattern"]
        name = (f"{c['wave']}, {c['wavelength_m'] * 1e9:.0f} nm, {c['cn2_m_23']:.1e} ({c['beta2']:.3g}), "
                f"{c['inner_scale_m'] * 1e3:g} mm")
        head.append(f"| {name} | {w['si']:.4f} ± {w['si_std_err']:.4f} | {t['si']:.4f} ({_pct(t['si_rel_error'])}) | "
                    f"{p['si']:.4f} ({_pct(p['si_rel_error'])}) | {f['si']:.4f} ({_pct(f['si_rel_error'])}) | "
                    f"{q['si']:.4f} ({_pct(q['si_rel_error'])}) | {w['sigma2_lnI']:.4f} | "
                    f"{t['sigma2_lnI']:.4f} ({_pct(t['sigma2_lnI_rel_error'])}) | "
                    f"{p['sigma2_lnI']:.4f} ({_pct(p['sigma2_lnI_rel_error'])}) |")
        ap = [x for x in c["aperture"] if x["wave_optics_si"] >= 0.01]
        ap_t = ", ".join(_pct(x["table_rel_error"]) for x in ap)
        ap_p = ", ".join(_pct(x["paper_rel_error"]) for x in ap)
        fp_t = ", ".join(_pct(x["table_rel_error"]) for x in c["footprint"])
        fp_p = ", ".join(_pct(x["paper_rel_error"]) for x in c["footprint"])
        head2.append(f"| {name} | {w['radius_m'] * 1e3:.2f} | {t['radius_m'] * 1e3:.2f} ({_pct(t['radius_rel_error'])}) | "
                     f"{p['radius_m'] * 1e3:.2f} ({_pct(p['radius_rel_error'])}) | {f['radius_m'] * 1e3:.2f} "
                     f"({_pct(f['radius_rel_error'])}) | {q['radius_m'] * 1e3:.2f} ({_pct(q['radius_rel_error'])}) | "
                     f"{t['shape_error']:.3f} / {p['shape_error']:.3f} / {q['shape_error']:.3f} | "
                     f"{ap_t} / {ap_p} | {fp_t} / {fp_p} |")
    worst = "; ".join(f"{m}: " + ", ".join(f"{k} {v:.3f}" for k, v in e.items()) if isinstance(e, dict)
                      else f"{m} {e:.3f}" for m, e in out["max_abs_error"].items())
    return "\n".join(head + [""] + head2 + ["", "Largest |error| over the cases: " + worst])


if __name__ == "__main__":
    sys.exit(main())
