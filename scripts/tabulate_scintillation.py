"""Tabulate point-receiver scintillation from converged split-step wave optics (issue 17).

Runs :func:`core.atmosphere.phasescreen.wave_optics_statistics` (plane and spherical waves, modified von Kármán
spectrum with inner scale l0, constant Cn²) over the governing parameters, all lengths in units of the Fresnel
scale F = √(L/k) (the paraxial problem depends on λ and L only through them):

* β0² = 0.5 Cn² k^(7/6) L^(11/6) (the spherical-wave Rytov variance, used as the strength axis for both waves);
* l0/F (0 = no inner scale); L0 = ∞ for the table (the outer-scale check runs L0/F = 20 and 100).

Each point is cached as JSON under ``bench/results/cache/scintillation/`` (key = every parameter that changes
the result), so an interrupted run resumes and ``--assemble`` can rebuild the table without re-running.
Grid per point: pitch dx = min(0.05 F, ρ0/6) (ρ0 the wave's coherence radius), box ≥ max(24 F, 8 F²/ρ0)
(≥ 8 large-scale radii L/(kρ0)), screens = max(10, (10 σ_R²)^(6/11)); realizations until the SI standard
error is ≤ 1.5 % (at least 12 — 32 for plane waves at β0² ≥ 2 — at most 48).

    python scripts/tabulate_scintillation.py table [--waves spherical,plane] [--l0 0,0.5]   # the table runs
    python scripts/tabulate_scintillation.py convergence    # halved pitch, doubled screens at chosen points
    python scripts/tabulate_scintillation.py paired         # halved pitch with the same turbulence (paired)
    python scripts/tabulate_scintillation.py outer          # L0/F = 20, 100 against L0 = ∞
    python scripts/tabulate_scintillation.py validate       # off-grid cases at 532/1064 nm, l0 = 0 and 5 mm
    python scripts/tabulate_scintillation.py assemble       # → core/atmosphere/data/scintillation_wave_optics.npz
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy import fft as sfft

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.atmosphere import phasescreen as ps  # noqa: E402
from core.atmosphere import turbulence as tb  # noqa: E402

CACHE = ROOT / "bench" / "results" / "cache" / "scintillation"
TABLE = ROOT / "core" / "atmosphere" / "data" / "scintillation_wave_optics.npz"
RESULTS = ROOT / "bench" / "results" / "scintillation_wave_optics.json"
WAVELENGTH_M = 532e-9
RANGE_M = 1000.0
BETA2 = (0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)
L0_OVER_F = (0.0, 0.5)
#: Covariance lags of the table, in units of F.
LAGS_F = np.round(np.concatenate([np.arange(0.0, 3.0, 0.025), np.arange(3.0, 10.001, 0.1)]), 6)
#: Aperture diameters of the direct aperture-averaging measurement, in units of F.
APERTURES_F = (0.5, 1.0, 2.0, 4.0)
#: Off-grid validation cases (wave, λ, Cn² at L = 1 km, l0 [m]): the issue's gated-viewing reference path
#: (532 nm, Cn² 2e-15 … 1e-13) and 1064 nm, with l0 = 0 and a realistic 5 mm.
VALIDATION = (("spherical", 532e-9, 2e-15, 0.0), ("spherical", 532e-9, 1e-14, 0.0), ("spherical", 532e-9, 5e-14, 0.0),
              ("spherical", 532e-9, 1e-13, 0.0), ("spherical", 532e-9, 1e-14, 5e-3), ("spherical", 532e-9, 5e-14, 5e-3),
              ("spherical", 1064e-9, 5e-14, 5e-3), ("spherical", 1064e-9, 2e-13, 5e-3), ("plane", 532e-9, 1e-14, 0.0),
              ("plane", 532e-9, 1e-13, 0.0), ("plane", 1064e-9, 1e-13, 5e-3), ("spherical", 532e-9, 1.8e-13, 0.0),
              ("spherical", 1064e-9, 4e-13, 5e-3), ("plane", 1064e-9, 4e-13, 0.0))
SI_REL_ERR = 0.015
MIN_REALIZATIONS = 12
#: Plane waves from β0² = 2 (σ_R² ≈ 5) on: at least 32 realizations.  Their covariance has a large-scale tail
#: (cells ~ F²/ρ0, a few per box side) whose aperture average at D = 4 F scattered by ±10 % between neighbouring
#: 12-realization points although the SI had converged to 1.5 %.
MIN_REALIZATIONS_STRONG_PLANE = 32


def min_realizations(wave, beta2):
    return MIN_REALIZATIONS_STRONG_PLANE if wave == "plane" and beta2 >= 2.0 else MIN_REALIZATIONS


def fresnel(wavelength_m=WAVELENGTH_M, range_m=RANGE_M):
    return float(tb.fresnel_scale(wavelength_m, range_m))


def cn2_for(beta2, wavelength_m=WAVELENGTH_M, range_m=RANGE_M):
    """Cn² giving the spherical Rytov variance β0² (docs/theory.md §1, coefficient 0.50)."""
    return beta2 / float(tb.rytov_variance(1.0, wavelength_m, range_m, "spherical"))


def grid_for(wave, beta2, wavelength_m=WAVELENGTH_M, range_m=RANGE_M, refine=1):
    """(n, dx_m, n_screens) of the rule in the module docstring; ``refine`` = 2 halves the pitch (same box)."""
    F = fresnel(wavelength_m, range_m)
    cn2 = cn2_for(beta2, wavelength_m, range_m)
    rho0 = float(tb.coherence_radius(cn2, wavelength_m, range_m, wave))
    dx = min(0.05 * F, rho0 / 6.0)
    box = max(24.0 * F, 8.0 * F * F / rho0)
    n = sfft.next_fast_len(int(math.ceil(box / dx)))
    n = n + (n % 2)
    screens = max(10, ps.default_screen_count(cn2, wavelength_m, range_m))
    return n * refine, dx / refine, screens


def run_point(wave, beta2, l0_over_f, *, wavelength_m=WAVELENGTH_M, range_m=RANGE_M, refine=1, screens_factor=1,
              outer_over_f=math.inf, max_realizations=48, seed=17, force=False, cached_only=False):
    F = fresnel(wavelength_m, range_m)
    n, dx, screens = grid_for(wave, beta2, wavelength_m, range_m, refine)
    screens *= screens_factor
    n_min = min(min_realizations(wave, beta2), max_realizations)
    params = {"wave": wave, "beta2": beta2, "l0_over_f": l0_over_f, "outer_over_f": outer_over_f,
              "wavelength_m": wavelength_m, "range_m": range_m, "n": n, "dx_over_f": dx / F, "n_screens": screens,
              "seed": seed, "si_rel_err": SI_REL_ERR, "min_realizations": n_min, "max_realizations": max_realizations}

    def cache_path(p):
        key = hashlib.sha1(json.dumps(p, sort_keys=True).encode()).hexdigest()[:12]
        return CACHE / f"{wave}_b{beta2:g}_l{l0_over_f:g}_L{outer_over_f:g}_{key}.json"
    path = cache_path(params)
    if path.exists() and not force:
        return json.loads(path.read_text())
    if n_min > MIN_REALIZATIONS and not force:
        # a run with the smaller minimum that went on to ≥ n_min realizations is this run (same random stream,
        # the stopping rule first held at its count): reuse it
        old = cache_path(dict(params, min_realizations=MIN_REALIZATIONS))
        if old.exists() and json.loads(old.read_text())["realizations"] >= n_min:
            out = dict(json.loads(old.read_text()), min_realizations=n_min)
            path.write_text(json.dumps(out, indent=1))
            return out
    if cached_only:
        return None
    rng = np.random.default_rng([seed, int(beta2 * 1e4), int(l0_over_f * 1e4), 1 if wave == "plane" else 2,
                                 refine, screens_factor])
    cn2 = cn2_for(beta2, wavelength_m, range_m)
    lags = LAGS_F[LAGS_F * F <= n * dx / 3.0] * F
    acc = ps.IntensityStatistics(n, dx, lags, [d * F for d in APERTURES_F])
    t0 = time.perf_counter()
    while True:
        acc.add(ps.split_step_intensity(wavelength_m, range_m, cn2, rng, wave=wave, n=n, dx_m=dx, n_screens=screens,
                                        outer_scale_m=outer_over_f * F, inner_scale_m=l0_over_f * F,
                                        subharmonics=False, dtype=np.complex64))
        if acc.count >= n_min:
            r = acc.result()
            if r["si_std_err"] <= SI_REL_ERR * r["scintillation_index"] or acc.count >= max_realizations:
                break
    r = acc.result()
    out = dict(params, scintillation_index=r["scintillation_index"], si_std_err=r["si_std_err"],
               sigma2_lnI=r["sigma2_lnI"], correlation_radius_over_f=r["correlation_radius_m"] / F,
               lags_over_f=(lags / F).round(6).tolist(), covariance=[round(float(c), 6) for c in r["covariance"]],
               aperture_over_f=list(APERTURES_F), aperture_si=r["aperture_si"], realizations=r["realizations"],
               seconds=time.perf_counter() - t0)
    CACHE.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(f"{wave:9s} b0²={beta2:<5g} l0/F={l0_over_f:<4g} L0/F={outer_over_f:<5g} n={n} dx/F={dx / F:.4f} "
          f"screens={screens} SI={out['scintillation_index']:.4f}±{out['si_std_err']:.4f} "
          f"ρ/F={out['correlation_radius_over_f']:.3f} real={out['realizations']} {out['seconds']:.0f}s", flush=True)
    return out


def assemble():
    """Collect the cached table points into the shipped .npz (lags beyond a point's box are left NaN)."""
    waves = ("plane", "spherical")
    shape = (len(waves), len(L0_OVER_F), len(BETA2))
    si = np.full(shape, np.nan)
    err = np.full(shape, np.nan)
    lnv = np.full(shape, np.nan)
    cov = np.full(shape + (len(LAGS_F),), np.nan)
    ap = np.full(shape + (len(APERTURES_F),), np.nan)
    for a, w in enumerate(waves):
        for b, l0 in enumerate(L0_OVER_F):
            for c, b2 in enumerate(BETA2):
                n, dx, screens = grid_for(w, b2)
                hits = sorted(CACHE.glob(f"{w}_b{b2:g}_l{l0:g}_Linf_*.json"))
                pts = [json.loads(h.read_text()) for h in hits]
                pts = [p for p in pts if p["n"] == n and p["n_screens"] == screens and p["seed"] == 17
                       and p["min_realizations"] == min_realizations(w, b2) and p["max_realizations"] == 48]
                if not pts:
                    continue
                p = pts[0]
                si[a, b, c], err[a, b, c], lnv[a, b, c] = p["scintillation_index"], p["si_std_err"], p["sigma2_lnI"]
                cov[a, b, c, :len(p["covariance"])] = p["covariance"]
                ap[a, b, c] = p["aperture_si"]
    missing = int(np.isnan(si).sum())
    assemble_results(waves, si, lnv, cov)
    TABLE.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(TABLE, waves=np.array(waves), beta2=np.array(BETA2), l0_over_f=np.array(L0_OVER_F),
                        lags_over_f=LAGS_F, aperture_over_f=np.array(APERTURES_F), scintillation_index=si,
                        si_std_err=err, sigma2_lnI=lnv, covariance=cov.astype(np.float32), aperture_si=ap,
                        wavelength_m=WAVELENGTH_M, range_m=RANGE_M)
    print(f"wrote {TABLE} ({TABLE.stat().st_size} bytes), {missing} points missing")


def paired_pitch_convergence(wave, beta2, l0_over_f, realizations=12, seed=17, kind="half_pitch"):
    """Convergence with the same turbulence, so that the ratio of the statistics has a small error.

    ``kind="half_pitch"``: each realization's screens are drawn on the fine grid (n·2, dx/2) and spectrally
    truncated to the table's grid (n, dx).  ``kind="double_screens"``: 2 × the screens are drawn on the table's
    grid, and the table's run uses the sums of neighbouring pairs (the same turbulence lumped into half as many
    screens).  Cached like the other points (file prefix "paired_")."""
    F = fresnel()
    n, dx, screens = grid_for(wave, beta2)
    params = {"kind": "paired_" + kind, "wave": wave, "beta2": beta2, "l0_over_f": l0_over_f, "n": n,
              "dx_over_f": dx / F, "n_screens": screens, "realizations": realizations, "seed": seed}
    key = hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:12]
    path = CACHE / f"paired_{kind}_{wave}_b{beta2:g}_l{l0_over_f:g}_{key}.json"
    if path.exists():
        return json.loads(path.read_text())
    rng = np.random.default_rng([seed, int(beta2 * 1e4), int(l0_over_f * 1e4), 7])
    cn2 = cn2_for(beta2)
    lags = LAGS_F[LAGS_F * F <= n * dx / 3.0] * F
    nf, dxf = (2 * n, dx / 2) if kind == "half_pitch" else (n, dx)
    coarse, fine = ps.IntensityStatistics(n, dx, lags), ps.IntensityStatistics(nf, dxf, lags)
    kf = np.fft.fftfreq(2 * n, 1.0 / (2 * n))
    keep = (kf >= -n // 2) & (kf < n // 2)           # the coarse grid's frequencies, in its FFT order
    si_c, si_f, t0 = [], [], time.perf_counter()
    for _ in range(realizations):
        ns_f = screens if kind == "half_pitch" else 2 * screens
        scr = ps.split_step_screens(WAVELENGTH_M, RANGE_M, cn2, rng, wave=wave, n=nf, dx_m=dxf, n_screens=ns_f,
                                    inner_scale_m=l0_over_f * F, subharmonics=False)
        if kind == "half_pitch":
            low = np.fft.ifft2(np.fft.fft2(scr)[:, keep][:, :, keep] / 4.0).real
        else:
            low = scr[0::2] + scr[1::2]
        for acc, s_, d_, nn, sc_ in ((fine, si_f, dxf, nf, scr), (coarse, si_c, dx, n, low)):
            i = ps.split_step_intensity(WAVELENGTH_M, RANGE_M, cn2, rng, wave=wave, n=nn, dx_m=d_, n_screens=len(sc_),
                                        dtype=np.complex64, screens=sc_)
            acc.add(i)
            s_.append(i.var() / i.mean() ** 2)
    rc, rf = coarse.result(), fine.result()
    ratio = np.asarray(si_f) / np.asarray(si_c)
    out = dict(params, si_coarse=rc["scintillation_index"], si_fine=rf["scintillation_index"],
               si_ratio=rf["scintillation_index"] / rc["scintillation_index"],
               si_ratio_std_err=float(np.std(ratio, ddof=1) / math.sqrt(realizations)),
               sigma2_lnI_ratio=rf["sigma2_lnI"] / rc["sigma2_lnI"],
               radius_ratio=rf["correlation_radius_m"] / rc["correlation_radius_m"],
               max_covariance_difference=float(np.max(np.abs(rf["covariance"] - rc["covariance"]))),
               seconds=time.perf_counter() - t0)
    path.write_text(json.dumps(out, indent=1))
    print(f"paired {kind} {wave} b0²={beta2:g} l0/F={l0_over_f:g}: SI {out['si_coarse']:.4f} → {out['si_fine']:.4f}, "
          f"ratio {out['si_ratio']:.4f} ± {out['si_ratio_std_err']:.4f}, radius ×{out['radius_ratio']:.4f}, "
          f"max ΔC {out['max_covariance_difference']:.4f} ({out['seconds']:.0f} s)", flush=True)
    return out


def _summary(p):
    F = p["range_m"] / (2 * math.pi / p["wavelength_m"])
    F = math.sqrt(F)
    keys = ("wave", "beta2", "l0_over_f", "outer_over_f", "wavelength_m", "range_m", "n", "dx_over_f", "n_screens",
            "scintillation_index", "si_std_err", "sigma2_lnI", "correlation_radius_over_f", "realizations",
            "aperture_over_f", "aperture_si", "seconds")
    out = {k: p[k] for k in keys}
    out["outer_over_f"] = None if not math.isfinite(p["outer_over_f"]) else p["outer_over_f"]
    out["fresnel_scale_m"] = F
    return out


def assemble_results(waves, si, lnv, cov):
    """bench/results/scintillation_wave_optics.json: the validation runs (full covariance), the convergence and
    outer-scale runs against their base points, and the leave-one-out interpolation error of the table."""
    val = []
    for w, lam, cn2, l0 in VALIDATION:
        b2 = round(float(tb.rytov_variance(cn2, lam, RANGE_M, "spherical")), 6)
        p = run_point(w, b2, round(l0 / fresnel(lam), 6), wavelength_m=lam, cached_only=True)
        if p is None:
            continue
        F = fresnel(lam)
        val.append(dict(_summary(p), cn2_m_23=cn2, inner_scale_m=l0, lags_m=[x * F for x in p["lags_over_f"]],
                        covariance=p["covariance"]))
    conv, outer = [], []
    for w in waves:
        for b2 in BETA2:
            for l0 in L0_OVER_F:
                base = run_point(w, b2, l0, cached_only=True)
                if base is None:
                    continue
                for kind, kw in (("half_pitch", dict(refine=2, max_realizations=12)),
                                 ("double_screens", dict(screens_factor=2, max_realizations=16))):
                    q = run_point(w, b2, l0, cached_only=True, **kw)
                    if q is not None:
                        conv.append({"kind": kind, "base": _summary(base), "variant": _summary(q),
                                     "si_ratio": q["scintillation_index"] / base["scintillation_index"],
                                     "radius_ratio": q["correlation_radius_over_f"] / base["correlation_radius_over_f"],
                                     "max_covariance_difference": float(np.max(np.abs(
                                         np.array(q["covariance"][:len(base["covariance"])])
                                         - np.array(base["covariance"][:len(q["covariance"])]))))})
                if l0 == 0.0:
                    for L0 in (20.0, 100.0):
                        q = run_point(w, b2, 0.0, outer_over_f=L0, cached_only=True)
                        if q is not None:
                            outer.append({"base": _summary(base), "variant": _summary(q),
                                          "si_ratio": q["scintillation_index"] / base["scintillation_index"],
                                          "radius_ratio": q["correlation_radius_over_f"]
                                          / base["correlation_radius_over_f"]})
    paired = [json.loads(f.read_text()) for f in sorted(CACHE.glob("paired_*.json"))]
    # leave-one-out: each interior β0² point predicted from its neighbours (linear in ln β0², ln SI)
    loo = []
    lb = np.log(BETA2)
    for a, w in enumerate(waves):
        for b, l0 in enumerate(L0_OVER_F):
            for c in range(1, len(BETA2) - 1):
                trio = si[a, b, c - 1:c + 2], lnv[a, b, c - 1:c + 2]
                if np.isnan(trio[0]).any():
                    continue
                f = (lb[c] - lb[c - 1]) / (lb[c + 1] - lb[c - 1])
                pred = [math.exp((1 - f) * math.log(v[0]) + f * math.log(v[2])) / v[1] - 1 for v in trio]
                c3 = np.nan_to_num(cov[a, b, c - 1:c + 2], nan=0.0)
                radius = [ps.one_over_e_radius_profile(LAGS_F, x) for x in ((1 - f) * c3[0] + f * c3[2], c3[1])]
                loo.append({"wave": w, "l0_over_f": l0, "beta2": BETA2[c], "si_error": pred[0],
                            "sigma2_lnI_error": pred[1], "radius_error": radius[0] / radius[1] - 1,
                            "covariance_max_difference": float(np.max(np.abs((1 - f) * c3[0] + f * c3[2] - c3[1])))})
    out = {"description": "Split-step wave-optics runs of scripts/tabulate_scintillation.py (issue 17)",
           "validation": val, "convergence": conv, "paired": paired, "outer_scale": outer,
           "leave_one_out": loo,
           "max_leave_one_out_si_error": max((abs(x["si_error"]) for x in loo), default=None),
           "max_leave_one_out_sigma2_lnI_error": max((abs(x["sigma2_lnI_error"]) for x in loo), default=None),
           "max_leave_one_out_radius_error": max((abs(x["radius_error"]) for x in loo), default=None)}
    RESULTS.write_text(json.dumps(out, indent=1))
    print(f"wrote {RESULTS}: {len(val)} validation, {len(conv)} convergence, {len(outer)} outer-scale runs")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("part", choices=("table", "convergence", "paired", "outer", "assemble", "point", "validate"))
    ap.add_argument("--waves", default="spherical,plane")
    ap.add_argument("--l0", default=",".join(f"{v:g}" for v in L0_OVER_F))
    ap.add_argument("--beta2", default=",".join(f"{v:g}" for v in BETA2))
    ap.add_argument("--wavelength", type=float, default=WAVELENGTH_M)
    ap.add_argument("--refine", type=int, default=1)
    ap.add_argument("--screens-factor", type=int, default=1)
    ap.add_argument("--reverse", action="store_true", help="validate: run the cases last to first")
    a = ap.parse_args(argv)
    waves = a.waves.split(",")
    l0s = [float(v) for v in a.l0.split(",")]
    b2s = [float(v) for v in a.beta2.split(",")]
    if a.part == "assemble":
        assemble()
    elif a.part == "table":
        for l0 in l0s:
            for w in waves:
                for b2 in b2s:
                    run_point(w, b2, l0)
    elif a.part == "point":
        for l0 in l0s:
            for w in waves:
                for b2 in b2s:
                    run_point(w, b2, l0, wavelength_m=a.wavelength, refine=a.refine, screens_factor=a.screens_factor)
    elif a.part == "validate":
        for w, lam, cn2, l0 in (VALIDATION[::-1] if a.reverse else VALIDATION):
            b2 = round(float(tb.rytov_variance(cn2, lam, RANGE_M, "spherical")), 6)
            run_point(w, b2, round(l0 / fresnel(lam), 6), wavelength_m=lam)
    elif a.part == "paired":
        for w in waves:
            for b2 in b2s:
                for l0 in l0s:
                    paired_pitch_convergence(w, b2, l0)
                    paired_pitch_convergence(w, b2, l0, kind="double_screens")
    elif a.part == "convergence":
        for w in waves:
            for b2 in b2s:
                for l0 in l0s:
                    run_point(w, b2, l0, refine=2, max_realizations=12)
                    run_point(w, b2, l0, screens_factor=2, max_realizations=16)
    elif a.part == "outer":
        for w in waves:
            for b2 in b2s:
                for L0 in (20.0, 100.0):
                    run_point(w, b2, 0.0, outer_over_f=L0)


if __name__ == "__main__":
    main()
