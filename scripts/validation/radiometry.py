"""Radiometry: received energy of whole flash frames against the laser radar equation (paper eq. 3-1, 3-4)."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from validation import check, save
from validation._common import BRDFSettings, flash_config, plate

from core.physics.brdf import evaluate_brdf
from core.systems.flash import simulate_frame

TITLE = "Radiometry: the laser radar equation"
ORDER = 10
INTRO = """Each point is a whole flash frame (8×8 pixels, 2×2 sub-rays each, uniform beam over the field of
view) on a plate that fills the field of view, traced and binned by `core.systems.flash.simulate_frame`; the
simulated quantity is the frame's total received energy.  The reference is the laser radar equation
(paper eq. 3-1 with the aperture's projected solid angle, docs/theory.md §10):

E_r = E_T · η_sys · f_r(θ) cos θ · π r_a²/(R² + r_a²) · exp(−2σR)

integrated over the field of view by an independent quadrature (600 × 600 midpoint cells in the tan-plane, the
uniform beam's energy shared equally; each cell's range and incidence angle from the plate's plane): the
simulator's 8×8×2×2 sub-rays must reproduce it within 0.1 %.  E_T = 1 mJ, η_sys as the default receiver,
aperture 5 cm.  BRDFs: Lambertian (ρ = 0.4), Steinvall (eq. 3-3: A = 0.05 sr⁻¹, s = 0.2,
B = 0.08 sr⁻¹, m = 1) and a tabulated f_r(θ) (the `table` model: linear in θ between the tabulated angles)."""

REFLECTANCE = 0.4
BRDFS = {
    "Lambertian ρ=0.4": BRDFSettings(model="lambertian", reflectance=REFLECTANCE),
    "Steinvall": BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0),
    "table": BRDFSettings(model="table", table_angle_deg=[0.0, 10.0, 30.0, 50.0, 70.0, 85.0],
                          table_brdf_per_sr=[0.60, 0.35, 0.18, 0.12, 0.08, 0.05]),
}
TOL = 1e-3  # relative: 0.1 %


def radar_equation(cfg, range_m, f_r, cos_theta, sigma):
    r_a = cfg.receiver.aperture_diameter_m / 2
    return (cfg.laser.pulse_energy_j * cfg.receiver.system_efficiency * f_r * cos_theta * math.pi * r_a ** 2
            / (range_m ** 2 + r_a ** 2) * math.exp(-2 * sigma * range_m))


def quadrature(cfg, range_m, brdf, tilt_rad=0.0, sigma=0.0, n=600):
    """Eq. 3-1 summed over n×n equal tan-plane cells of the field of view (uniform beam), plate through
    (0, 0, −R0) with normal (0, sin θ, cos θ): range R0 cos θ √(1 + x² + y²)/(cos θ − y sin θ)."""
    t = math.tan(cfg.receiver.fov_x_rad / 2)
    c = (np.arange(n) + 0.5) / n * 2 * t - t
    x, y = np.meshgrid(c, c)
    norm = np.sqrt(1 + x ** 2 + y ** 2)
    ct, st = math.cos(tilt_rad), math.sin(tilt_rad)
    rng = range_m * ct * norm / (ct - y * st)
    cos_inc = np.abs(y * st - ct) / norm
    f_r = evaluate_brdf(brdf, cos_inc.ravel()).reshape(cos_inc.shape)
    r_a = cfg.receiver.aperture_diameter_m / 2
    e = (cfg.laser.pulse_energy_j / n ** 2 * cfg.receiver.system_efficiency * f_r * cos_inc * math.pi * r_a ** 2
         / (rng ** 2 + r_a ** 2) * np.exp(-2 * sigma * rng))
    return float(e.sum())


def frame_energy(range_m, brdf, tilt_rad=0.0, sigma=0.0):
    cfg = flash_config(range_m)
    cfg.laser.beam_profile = "uniform"
    cfg.atmosphere.extinction_per_m = sigma
    half = 0.05 * range_m / max(math.cos(tilt_rad), 0.05)
    res = simulate_frame(plate(range_m, half, brdf, tilt_rad=tilt_rad), np.eye(4), cfg)
    return float(np.sum(res.energy_image, dtype=np.float64)), cfg


def run(out_dir: Path, quick: bool) -> list[dict]:
    checks = []
    lam = BRDFS["Lambertian ρ=0.4"]
    # ---- range 10 m – 10 km, with and without extinction
    ranges = [10.0, 100.0, 1e3, 1e4] if quick else list(np.geomspace(10.0, 1e4, 13))
    sigmas = [0.0, 1e-4] if quick else [0.0, 1e-4, 1e-3]
    curves = {}
    for sigma in sigmas:
        sim, ref = [], []
        for r in ranges:
            e, cfg = frame_energy(r, lam, sigma=sigma)
            e_ref = quadrature(cfg, r, lam, sigma=sigma)
            sim.append(e)
            ref.append(e_ref)
            if e_ref > 1e-300:
                checks.append(check(f"E_r, Lambertian, R = {r:.4g} m, σ = {sigma:g} /m", e, e_ref, TOL, unit="J"))
        curves[sigma] = (np.array(sim), np.array(ref))
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    rr = np.geomspace(10, 1e4, 200)
    for k, sigma in enumerate(sigmas):
        sim, ref = curves[sigma]
        col = f"C{k}"
        line = [radar_equation(cfg, r, REFLECTANCE / math.pi, 1.0, sigma) for r in rr]
        ax[0].loglog(rr, line, col, lw=1, label=f"eq. 3-1, σ = {sigma:g} /m")
        ax[0].loglog(ranges, sim, col + "o", ms=4, mfc="none", label=f"simulated frame, σ = {sigma:g} /m")
        ok = ref > 1e-300
        ax[1].semilogx(np.array(ranges)[ok], (sim[ok] / ref[ok] - 1) * 100, col + "o-", ms=4,
                       label=f"σ = {sigma:g} /m")
    ax[0].set(title="received energy vs range (Lambertian plate)", xlabel="range R [m]",
              ylabel="received energy E_r [J]", ylim=(1e-30, 1e-3))
    ax[0].legend(fontsize=7)
    ax[1].axhspan(-TOL * 100, TOL * 100, color="0.9", label="tolerance ±0.1 %")
    ax[1].set(title="relative error vs eq. 3-1", xlabel="range R [m]", ylabel="simulated / equation − 1 [%]")
    ax[1].legend(fontsize=7)
    save(fig, out_dir / "energy_vs_range.png")

    # ---- incidence angle, three BRDFs (R = 100 m)
    angles = [0.0, 30.0, 60.0, 80.0] if quick else [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0]
    r0 = 100.0
    fig, ax = plt.subplots(figsize=(6.5, 4))
    th = np.linspace(0, 85, 300)
    for k, (name, brdf) in enumerate(BRDFS.items()):
        sims = []
        for a in angles:
            e, cfg = frame_energy(r0, brdf, tilt_rad=math.radians(a))
            e_ref = quadrature(cfg, r0, brdf, tilt_rad=math.radians(a))
            sims.append(e)
            checks.append(check(f"E_r, {name}, incidence {a:g}°, R = 100 m", e, e_ref, TOL, unit="J"))
        cth = np.cos(np.radians(th))
        # the curve is the centre ray's value (the quadrature is the checked reference)
        ax.semilogy(th, [radar_equation(cfg, r0, float(f), c, 0.0)
                         for f, c in zip(evaluate_brdf(brdf, cth), cth)], f"C{k}", lw=1,
                    label=f"eq. 3-1 at the centre ray, {name}")
        ax.semilogy(angles, sims, f"C{k}o", ms=4, mfc="none", label=f"simulated frame, {name}")
    ax.set(title="received energy vs incidence angle (R = 100 m)", xlabel="incidence angle θ [deg]",
           ylabel="received energy E_r [J]")
    ax.legend(fontsize=7)
    save(fig, out_dir / "energy_vs_incidence.png")
    return checks
