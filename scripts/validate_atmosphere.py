#!/usr/bin/env python3
"""Validate the atmosphere module and write plots + a Markdown summary (docs/theory.md §1–6, §11, §12).

    .venv/bin/python scripts/validate_atmosphere.py [OUT_DIR] [--seed N] [--quick [--smallest]]

OUT_DIR defaults to runs/validation/atmosphere/ (not committed).  The committed page, docs/validation/atmosphere/,
is written by ``scripts/validate.py --update-committed`` (the atmosphere effect, scripts/validation/atmosphere.py,
calls :func:`report`); this script refuses to write there.  Writes scintillation_pdf.png, correlation.png, mtf.png,
transmission.png, si_vs_rytov.png, si_vs_beta2.png, radius_vs_beta2.png and summary.md.  The wave-optics
comparison reads the split-step runs of scripts/tabulate_scintillation.py (bench/results/scintillation_wave_optics.json).  Runtime ≈ 1 min on 2 cores (--quick: ≈ 20 s).
``--quick --smallest``: the level scripts/validate.py --quick uses (≈ 10 s of CPU; ≈ 23 s for --quick alone).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from scipy import stats  # noqa: E402

from core import atmosphere as atm  # noqa: E402

DPI = 72
ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "docs" / "validation" / "atmosphere"


def profile(ac, n):
    return 0.5 * (ac[0, :n] + ac[:n, 0])


def one_over_e(prof, pitch):
    j = np.nonzero(prof < math.exp(-1))[0][0]
    p0, p1 = prof[j - 1], prof[j]
    return (j - 1 + (p0 - math.exp(-1)) / (p0 - p1)) * pitch


#: Relative standard error of the SI measured on the product's patterns at which wave_optics_section stops
#: drawing realisations (full mode; quick mode: the QUICK value), and the most realisations it draws.  Derivation
#: (docs/atmosphere.md, "Checking the patterns against wave optics"): the check compares the pooled SI of the
#: patterns with the split-step SI, both estimates; σ_diff² = σ_pattern² + σ_wo².  σ_wo/SI ≤ 3.4 % (the
#: validation cases' si_std_err); one 0.4 m pattern's SI scatters by up to 18 % of SI (β0² 2.5–5, 1600 seeds),
#: so the former fixed 8 patterns gave σ_pattern ≈ 6.3 %, σ_diff ≈ 7.2 %: the ±10 % tolerance was 1.4 σ and
#: 6 % of 8-pattern draws fail at β0² 2.51 although the pooled SI of 1600 patterns is within 0.1 % of wave
#: optics.  Stopping at σ_pattern ≤ 2 % gives σ_diff ≤ 3.9 %: ±10 % ≥ 2.5 σ (quick: 4 % at its four cases,
#: σ_wo ≤ 2.4 %, σ_diff ≤ 4.7 %: 2.1 σ).
PATTERN_SI_REL_SE, PATTERN_SI_REL_SE_QUICK, MAX_PATTERNS = 0.02, 0.04, 128


def wave_optics_section(out, nreal_patterns=8, max_cases=None, rel_se=PATTERN_SI_REL_SE, max_patterns=MAX_PATTERNS):
    """Plots si_vs_beta2.png and radius_vs_beta2.png and returns summary rows: the split-step wave-optics runs
    (the shipped table and the off-grid validation cases of bench/results/scintillation_wave_optics.json, made by
    scripts/tabulate_scintillation.py), the product (the table model, and SI/radius measured on the patterns the
    simulator generates at the validation cases) and the paper's formulas, over β0².  At each case at least
    ``nreal_patterns`` patterns are drawn (seeds 0, 1, …), then more until the pooled SI's standard error (from
    the per-pattern spread) is ≤ ``rel_se`` of it or ``max_patterns`` are drawn (PATTERN_SI_REL_SE)."""
    import json
    from core.atmosphere import phasescreen as ps
    from core.atmosphere import wave_optics as wo
    runs = json.loads((Path(__file__).resolve().parents[1] / "bench" / "results"
                       / "scintillation_wave_optics.json").read_text())
    t = wo.load_table()
    lam, L = 532e-9, 1e3
    F = float(atm.fresnel_scale(lam, L))
    unit = float(atm.rytov_variance(1.0, lam, L, "spherical"))
    bgrid = np.geomspace(0.02, 12, 120)
    if max_cases is not None:
        runs = dict(runs, validation=runs["validation"][:max_cases])
    measured = []
    for v in runs["validation"]:
        lags = np.asarray(v["lags_m"])
        acc = None
        for seed in range(max_patterns):
            if seed >= max(nreal_patterns, 2):
                r = acc.result()
                if r["si_std_err"] <= rel_se * r["scintillation_index"]:
                    break
            p = atm.make_scintillation_pattern((-0.2, 0.2, -0.2, 0.2), v["cn2_m_23"], v["wavelength_m"], v["range_m"],
                                               np.random.default_rng(seed), wave=v["wave"],
                                               inner_scale_m=v["inner_scale_m"], max_grid_px=1024)
            if acc is None:
                acc = ps.IntensityStatistics(p.values.shape[0], p.pitch_m, lags[lags <= p.values.shape[0] * p.pitch_m / 3])
            acc.add(p.values)
        measured.append(acc.result())
    rows = []
    checks = []
    figs = {}
    for quantity in ("si", "radius"):
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
        for ax, wave in zip(axes, ("spherical", "plane")):
            w = t["waves"].index(wave)
            for j, (l0f, col) in enumerate(zip(t["l0_over_f"], ("C0", "C2", "C4"))):
                model = [wo.statistics(b / unit, lam, L, wave, l0f * F) for b in bgrid]
                y = [m["scintillation_index"] if quantity == "si" else m["correlation_radius_m"] / F for m in model]
                ax.plot(bgrid, y, col, lw=1, label=f"product (table), l0/F = {l0f:g}")
                ys = (t["scintillation_index"][w, j] if quantity == "si" else
                      [ps.one_over_e_radius_profile(t["lags_over_f"], c) for c in t["covariance"][w, j]])
                ax.plot(t["beta2"], ys, col + "o", ms=3, mfc="none", label=f"split-step, l0/F = {l0f:g}")
            if quantity == "si":
                s_w = bgrid if wave == "spherical" else bgrid / 0.406
                ax.plot(bgrid, atm.scintillation_index(atm.log_intensity_variance(s_w, wave)), "k--", lw=1,
                        label="paper formula (all-regime)")
                ax.plot(bgrid, s_w, "k:", lw=1, label="first order (β0², σ_R²)")
            else:
                rho0 = atm.coherence_radius(bgrid / unit, lam, L, wave)
                ax.plot(bgrid, atm.cell_radius(lam, L, rho0) / F, "k--", lw=1, label="paper eq. 3-6")
            for v, m in zip(runs["validation"], measured):
                if v["wave"] != wave:
                    continue
                Fv = v["fresnel_scale_m"]
                ref = v["scintillation_index"] if quantity == "si" else v["correlation_radius_over_f"]
                got = m["scintillation_index"] if quantity == "si" else m["correlation_radius_m"] / Fv
                ax.plot(v["beta2"], ref, "ks", ms=5, mfc="none")
                ax.plot(v["beta2"], got, "rx", ms=6)
            ax.plot([], [], "ks", mfc="none", label="split-step, validation case")
            ax.plot([], [], "rx", label="product pattern, measured")
            ax.set(xscale="log", yscale="log" if quantity == "si" else "linear", xlabel="β0²", title=wave)
            ax.grid(alpha=0.3)
        for ax in axes:  # every panel labelled and with its legend (scripts/validation: every plot)
            ax.set_ylabel("SI" if quantity == "si" else "1/e covariance radius / √(L/k)")
            ax.legend(fontsize=6)
        fig.tight_layout()
        name = "si_vs_beta2.png" if quantity == "si" else "radius_vs_beta2.png"
        fig.savefig(out / name, dpi=DPI)
        plt.close(fig)
        figs[quantity] = name
    for v, m in zip(runs["validation"], measured):
        st = wo.statistics(v["cn2_m_23"], v["wavelength_m"], v["range_m"], v["wave"], v["inner_scale_m"])
        Fv = v["fresnel_scale_m"]
        paper = atm.derived_turbulence(v["cn2_m_23"], v["wavelength_m"], v["range_m"], wave=v["wave"],
                                       statistics="paper")
        label = (f"{v['wave']} {v['wavelength_m'] * 1e9:.0f} nm, Cn² {v['cn2_m_23']:.0e} (β0² {v['beta2']:.3g}), "
                 f"l0 {v['inner_scale_m'] * 1e3:g} mm")
        rows.append((f"SI {label}: wave optics / product table / product pattern ({m['realizations']} patterns) "
                     "/ paper",
                     f"{v['scintillation_index']:.4f} ± {v['si_std_err']:.4f} / {st['scintillation_index']:.4f} / "
                     f"{m['scintillation_index']:.4f} ± {m['si_std_err']:.4f} / {paper['scintillation_index']:.4f}",
                     "±10 %"))
        rows.append((f"1/e radius [mm] {label}: wave optics / table / pattern / paper",
                     f"{v['correlation_radius_over_f'] * Fv * 1e3:.2f} / {st['correlation_radius_m'] * 1e3:.2f} / "
                     f"{m['correlation_radius_m'] * 1e3:.2f} / {paper['cell_radius_m'] * 1e3:.2f}", "±10 %"))
        for what, got in (("table", st), ("pattern", m)):
            checks.append({"quantity": f"SI, product {what} vs wave optics, {label}",
                           "simulated": float(got["scintillation_index"]),
                           "reference": float(v["scintillation_index"]), "tolerance": 0.10, "kind": "rel"})
            checks.append({"quantity": f"1/e radius, product {what} vs wave optics, {label}",
                           "simulated": float(got["correlation_radius_m"]) * 1e3,
                           "reference": float(v["correlation_radius_over_f"] * Fv) * 1e3, "tolerance": 0.10,
                           "kind": "rel", "unit": "mm"})
    return rows, checks


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", nargs="?", default=None, metavar="OUT_DIR",
                    help="folder for the plots and summary.md (default runs/validation/atmosphere/)")
    ap.add_argument("--update-committed", action="store_true",
                    help="refused: use scripts/validate.py --update-committed --only atmosphere")
    ap.add_argument("--seed", type=int, default=20240601)
    ap.add_argument("--quick", action="store_true", help="fewer realisations")
    ap.add_argument("--smallest", action="store_true",
                    help="with --quick: fewer realisations still and the wave-optics patterns at the first four "
                         "validation cases only (the level of scripts/validate.py --quick)")
    args = ap.parse_args(argv)
    if args.smallest and not args.quick:
        ap.error("--smallest goes with --quick (it makes the quick run smaller still)")
    if args.update_committed:
        ap.error("--update-committed: the committed report is regenerated by "
                 "scripts/validate.py --update-committed --only atmosphere (it records the checks in "
                 "docs/validation/checks.json too)")
    else:
        out = Path(args.out) if args.out is not None else ROOT / "runs" / "validation" / "atmosphere"
        try:
            out.resolve().relative_to(COMMITTED.resolve())
            ap.error(f"OUT_DIR = {args.out} is the committed report: use --update-committed to regenerate it")
        except ValueError:
            pass
    out.mkdir(parents=True, exist_ok=True)
    lines, _ = report(out, args.quick, args.seed, smallest=args.smallest)
    print("\n".join(lines))
    return 0


def report(out, quick=False, seed=20240601, smallest=False):
    """Writes the plots and summary.md into ``out``; returns (the summary's lines, the checks as dicts for
    scripts/validate.py: quantity, simulated, reference, tolerance, kind).  ``smallest`` (with ``quick``: the
    quick mode of scripts/validate.py, a few seconds) draws fewer realisations still and measures the product's
    patterns at the first four wave-optics validation cases only."""
    out = Path(out)
    rng = np.random.default_rng(seed)
    smallest = smallest and quick
    nreal = 6 if quick else 16
    t_start = time.time()
    rows = []
    checks = []

    def chk(quantity, simulated, reference, tolerance, kind="rel"):
        checks.append({"quantity": quantity, "simulated": float(simulated), "reference": float(reference),
                       "tolerance": float(tolerance), "kind": kind})

    # ---------------------------------------------------------------- scintillation: case A, 1064 nm, 2 km
    lam, L = 1064e-9, 2e3
    # log-normal, weak: case B geometry with σ² from the all-regime formula of case A's spherical wave
    s2, rho_l, pitch, n = 0.3, 0.016, 0.002, 512
    ln_fields = [atm.lognormal_pattern((n, n), pitch, s2, rho_l, rng) for _ in range(nreal)]
    allv = np.concatenate([f.ravel() for f in ln_fields])
    dec = np.concatenate([np.log(f[::20, ::20]).ravel() for f in ln_fields])
    ks = stats.kstest(dec, stats.norm(loc=-s2 / 2, scale=math.sqrt(s2)).cdf)
    ac_ln = atm.periodic_autocorrelation(ln_fields)
    r_ln = one_over_e(profile(ac_ln, n // 2), pitch)
    rows += [("log-normal σ_lnI² (target 0.3)", f"{np.var(np.log(allv)):.4f}", "±5 %"),
             ("log-normal mean (target 1)", f"{allv.mean():.4f}", "±1 %"),
             ("log-normal SI (target 0.3499)", f"{allv.var() / allv.mean() ** 2:.4f}", "±5 %"),
             ("log-normal KS D / p (decimated 2.5 ρ_l)", f"{ks.statistic:.4f} / {ks.pvalue:.3f}", "p > 0.01"),
             ("log-normal 1/e radius / ρ_l", f"{r_ln / rho_l:.4f}", "±10 %")]
    chk("log-normal σ_lnI²", np.var(np.log(allv)), s2, 0.05)
    chk("log-normal mean", allv.mean(), 1.0, 0.01)
    chk("log-normal SI", allv.var() / allv.mean() ** 2, math.expm1(s2), 0.05)
    chk("log-normal KS p-value (decimated 2.5 ρ_l)", ks.pvalue, 0.01, 0.0, "min")
    chk("log-normal 1/e radius / ρ_l", r_ln / rho_l, 1.0, 0.10)

    c = 1e-14
    s_pl = float(atm.rytov_variance(c, lam, L, "plane"))
    a, b = (float(v) for v in atm.gamma_gamma_parameters(s_pl, "plane"))
    rho0 = atm.coherence_radius(c, lam, L, "plane")
    ry, rx = float(atm.cell_radius(lam, L, rho0)), float(atm.large_scale_radius(lam, L, rho0))
    gp = ry / 4
    gg_fields = [atm.gamma_gamma_pattern((n, n), gp, a, b, rx, ry, rng) for _ in range(nreal)]
    gall = np.concatenate([f.ravel() for f in gg_fields])
    gdec = np.concatenate([f[::24, ::24].ravel() for f in gg_fields])
    gks = stats.kstest(gdec, lambda t: atm.gamma_gamma_cdf(t, a, b))
    si_gg = (1 + 1 / a) * (1 + 1 / b) - 1
    ac_gg = atm.periodic_autocorrelation(gg_fields)
    rows += [(f"gamma-gamma (case A plane, α = {a:.3f}, β = {b:.3f}) mean", f"{gall.mean():.4f}", "±2 %"),
             (f"gamma-gamma SI (target {si_gg:.4f})", f"{gall.var():.4f}", "±5 %"),
             ("gamma-gamma KS D / p (decimated 24 px)", f"{gks.statistic:.4f} / {gks.pvalue:.3f}", "p > 0.01")]
    chk("gamma-gamma (case A plane) mean", gall.mean(), 1.0, 0.02)
    chk("gamma-gamma (case A plane) SI", gall.var(), si_gg, 0.05)
    chk("gamma-gamma KS p-value (decimated 24 px)", gks.pvalue, 0.01, 0.0, "min")

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    x = np.linspace(0.01, 4, 400)
    ax[0].hist(allv[::7], bins=120, range=(0, 4), density=True, alpha=0.5, label="generated")
    ax[0].plot(x, atm.lognormal_pdf(x, s2), "k", label="eq. 3-5, σ² = 0.3")
    ax[0].set(title="log-normal pattern", xlabel="S / S_av", ylabel="pdf")
    ax[0].legend()
    ax[1].hist(gall[::7], bins=120, range=(0, 5), density=True, alpha=0.5, label="generated")
    x = np.linspace(0.01, 5, 400)
    ax[1].plot(x, atm.gamma_gamma_pdf(x, a, b), "k", label="gamma-gamma pdf")
    ax[1].plot(x, atm.lognormal_pdf(x, math.log1p(si_gg)), "k:", label="log-normal, same SI")
    ax[1].set(title=f"gamma-gamma, case A (σ_R² = {s_pl:.2f})", xlabel="I / ⟨I⟩", ylabel="pdf")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "scintillation_pdf.png", dpi=DPI)
    plt.close(fig)

    # ---------------------------------------------------------------- correlation vs cell size
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    r = np.arange(n // 8) * pitch
    ax[0].plot(r / rho_l, profile(ac_ln, n // 8), "o", ms=3, label="generated (mean of x, y)")
    ax[0].plot(r / rho_l, np.exp(-(r / rho_l) ** 2), "k", label="exp(−r²/ρ_l²)")
    ax[0].axhline(math.exp(-1), color="grey", lw=0.5)
    ax[0].set(title="log-normal: intensity correlation", xlabel="r / ρ_l", ylabel="B_I(r)/B_I(0)")
    ax[0].legend()
    rg = np.arange(n // 4) * gp
    ax[1].plot(rg * 100, profile(ac_gg, n // 4), "o", ms=3, label="generated")
    ax[1].plot(rg * 100, atm.gamma_gamma_covariance(rg, a, b, rx, ry), "k", label="model (X·Y)")
    ax[1].axvline(ry * 100, color="C1", lw=0.8, label="ρ_Y = eq. 3-6")
    ax[1].axvline(rx * 100, color="C2", lw=0.8, label="ρ_X = (L/k)/ρ_Y")
    ax[1].set(title="gamma-gamma: intensity correlation", xlabel="r [cm]", ylabel="B_I(r)/B_I(0)")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(out / "correlation.png", dpi=DPI)
    plt.close(fig)

    # ---------------------------------------------------------------- MTF curves + measured from blur
    lam_m, D, r0 = 1.064e-6, 0.1, 0.05
    nu_c = D / lam_m
    nb = 512
    bp = 128 / (nb * nu_c)
    img = np.zeros((nb, nb))
    img[nb // 2, nb // 2] = 1.0
    nu = np.linspace(0, nu_c, 300)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    ax.plot(nu / nu_c, atm.diffraction_mtf(nu, lam_m, D), "k--", label="diffraction")
    k = np.arange(0, 129)
    for label, kw, col in [("LE", dict(exposure="long"), "C0"),
                           ("SE α=1", dict(exposure="short", alpha=1.0), "C1"),
                           ("SE α=0.5", dict(exposure="short", alpha=0.5), "C2")]:
        if kw["exposure"] == "long":
            th = atm.turbulence_mtf_long(nu, lam_m, r0)
        else:
            th = atm.turbulence_mtf_short(nu, lam_m, r0, D, kw["alpha"])
        ax.plot(nu / nu_c, th, col, label=f"{label} formula")
        blurred = atm.turbulence_blur(img, bp, lam_m, r0, aperture_diameter_m=D, **kw)
        f = np.abs(np.fft.fft2(blurred))
        meas = 0.5 * (f[0, k] + f[k, 0])
        ax.plot(k / 128, meas, "o", color=col, ms=2.5, label=f"{label} measured (blurred δ)")
        for frac in (0.25, 0.5):
            kk = int(frac * 128)
            thv = float(np.interp(frac * nu_c, nu, th))
            rows.append((f"blur MTF {label} at {frac} ν_c (formula {thv:.4f})", f"{meas[kk]:.4f}", "±5 %"))
            chk(f"turbulence blur MTF {label} at {frac} ν_c", meas[kk], thv, 0.05)
    ax.set(xlabel="ν / ν_c  (ν_c = D/λ)", ylabel="MTF", title=f"turbulence MTF, r0 = {r0} m, D = {D} m")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "mtf.png", dpi=DPI)
    plt.close(fig)

    # ---------------------------------------------------------------- transmission vs range
    rr = np.linspace(0, 20e3, 400)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for v in (0.2e3, 0.5e3, 1e3, 5e3, 23e3, 50e3):
        sig = atm.extinction_from_visibility(v, 1064e-9, "kim")
        ax.plot(rr / 1e3, atm.log_two_way_transmission(sig, rr) / math.log(10), label=f"V = {v / 1e3:g} km")
    ax.set(xlabel="range [km]", ylabel="log10 T² (two-way)", title="Kim model, 1064 nm", ylim=(-60, 1))
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "transmission.png", dpi=DPI)
    plt.close(fig)
    s_fog = atm.extinction_from_visibility(200.0, 1550e-9, "kim")
    rows.append(("ln T², V = 200 m, 1550 nm, R = 50 km (= −2σR)",
                 f"{float(atm.log_two_way_transmission(s_fog, 50e3)):.2f}", "finite"))
    chk("ln T², V = 200 m, 1550 nm, R = 50 km (−2σR)", float(atm.log_two_way_transmission(s_fog, 50e3)),
        -2 * float(s_fog) * 50e3, 1e-9)

    # ---------------------------------------------------------------- split-step reference
    ss = atm.split_step_reference(1064e-9, 1e3, 6.477e-15, rng, n=512, dx_m=2e-3,
                                  realizations=4 if smallest else 8 if quick else 24)
    rho0_pl = atm.coherence_radius(6.477e-15, 1064e-9, 1e3, "plane")
    rows += [("split-step SI, σ_R² = 0.2 (docs/theory.md §12: 0.1989 ± 0.0008)",
              f"{ss['scintillation_index']:.4f} ± {ss['si_std_err']:.4f}", "±5 %"),
             ("split-step intensity 1/e radius [mm]", f"{ss['correlation_radius_m'] * 1e3:.2f}",
              f"Fresnel {float(atm.fresnel_scale(1064e-9, 1e3)) * 1e3:.2f}, eq. 3-6 "
              f"{float(atm.cell_radius(1064e-9, 1e3, rho0_pl)) * 1e3:.2f}")]
    chk("split-step SI, σ_R² = 0.2 (docs/theory.md §12: 0.1989)", ss["scintillation_index"], 0.1989, 0.05)
    s_list = [0.2] if smallest else [0.1, 0.2, 0.5] if quick else [0.1, 0.2, 0.5, 1.0]
    k0 = 2 * math.pi / 1064e-9
    ss_si = []
    for sr in s_list:
        cn2 = sr / (1.23 * k0 ** (7 / 6) * 1e3 ** (11 / 6))
        res = atm.split_step_reference(1064e-9, 1e3, cn2, rng, n=512, dx_m=2e-3, realizations=4 if smallest else 8)
        ss_si.append((sr, res["scintillation_index"], res["si_std_err"]))
    sgrid = np.geomspace(0.01, 100, 200)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    ax.loglog(sgrid, atm.scintillation_index(atm.log_intensity_variance(sgrid, "plane")), "C0",
              label="all-regime, plane")
    ax.loglog(sgrid, atm.scintillation_index(atm.log_intensity_variance(0.406 * sgrid, "spherical")), "C1",
              label="all-regime, spherical")
    ax.loglog(sgrid, sgrid, "k:", label="Rytov σ_R²")
    ax.errorbar([p[0] for p in ss_si], [p[1] for p in ss_si], yerr=[2 * p[2] for p in ss_si], fmt="ks", ms=4,
                label="split-step (plane, 512², 2 mm)")
    ax.set(xlabel="σ_R²", ylabel="SI", ylim=(5e-3, 3), title="scintillation index vs Rytov variance")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "si_vs_rytov.png", dpi=DPI)
    plt.close(fig)
    for sr, si, err in ss_si:
        th = float(atm.scintillation_index(atm.log_intensity_variance(sr, "plane")))
        rows.append((f"split-step SI at σ_R² = {sr} (all-regime formula {th:.4f})", f"{si:.4f} ± {err:.4f}",
                     "reference"))

    # ---------------------------------------------------------------- wave optics vs product vs formulas (issue 17)
    wo_rows, wo_checks = wave_optics_section(out, nreal_patterns=8 if quick else 16,
                                                max_cases=4 if smallest else None,
                                                rel_se=PATTERN_SI_REL_SE_QUICK if quick else PATTERN_SI_REL_SE)
    rows += wo_rows
    checks += wo_checks

    # ---------------------------------------------------------------- beam wander
    rc2 = float(atm.beam_wander_variance(1e-14, 2e3, 0.02))
    d = atm.beam_wander_offsets(rc2, rng, 100_000)
    rows.append((f"beam wander B1 ⟨r_c²⟩ = {rc2:.4e} m²: measured", f"{np.mean(np.sum(d ** 2, axis=1)):.4e}",
                 "±10 %"))
    chk("beam wander ⟨r_c²⟩ (B1)", np.mean(np.sum(d ** 2, axis=1)), rc2, 0.10)

    lines = ["# Atmosphere module validation", "",
             f"Generated by `scripts/validate_atmosphere.py` (seed {seed}{', quick' if quick else ''}, "
             f"{nreal} pattern realisations of 512², {time.time() - t_start:.0f} s).  "
             "References: docs/theory.md §3, §5, §6, §11, §12.", "",
             "| quantity | measured | tolerance / reference |", "|---|---|---|"]
    lines += [f"| {q} | {m} | {t} |" for q, m, t in rows]
    lines += ["", "Plots: `scintillation_pdf.png`, `correlation.png`, `mtf.png`, `transmission.png`, "
                  "`si_vs_rytov.png`, `si_vs_beta2.png` and `radius_vs_beta2.png` (split-step wave optics vs the "
                  "product vs the paper's formulas, issue 17).", ""]
    (out / "summary.md").write_text("\n".join(lines), encoding="utf-8")
    return lines, checks


if __name__ == "__main__":
    raise SystemExit(main())
