"""Speckle: contrast of the integrated speckle against the number of speckle degrees of freedom M."""
from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy import special

from validation import check, save
from validation.receiver import chain, photons_per_j

TITLE = "Speckle: contrast vs degrees of freedom"
ORDER = 50
INTRO = """Fully developed speckle integrated over M speckle degrees of freedom (the receiver aperture over the
coherence area, docs/theory.md §7) multiplies each pixel's signal per pulse by a unit-mean gamma variate of
shape M: contrast σ/mean = 1/√M, and photon counts become negative binomial with variance N̄ + N̄²/M.

Simulated: the receiver chain (`apply_receiver_chain`, PIN, quantum efficiency 1, no dark current, background,
read noise or A/D) with `speckle_dof` = M, one bin per pixel, N̄ = 2000 photo-electrons.  The speckle contrast is
recovered from the output's variance as √(var − N̄)/N̄ (the Poisson part removed) and compared with 1/√M; the
pdf of count/N̄ is compared with the gamma pdf of shape M (whose width dominates Poisson's for M ≤ 64 here).
Tolerance: 4 standard errors of a gamma variance estimate, √((2 + 6/M)/n) relative on the variance, half that on
the contrast."""

NBAR = 2000.0


def run(out_dir: Path, quick: bool) -> list[dict]:
    checks = []
    side = 256 if quick else 512
    n = side * side
    ms = [1.0, 4.0, 16.0, 64.0] if quick else [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0]
    e = NBAR / photons_per_j()
    contrasts, samples = [], {}
    for k, m in enumerate(ms):
        x = chain(np.full((side, side, 1), e, np.float32), 100 + k, detector_type="pin", quantum_efficiency=1.0,
                  enable_dark_current=False, enable_background=False, enable_read_noise=False, enable_adc=False,
                  speckle_dof=m).data.astype(np.float64).ravel()
        c = math.sqrt(max(x.var() - x.mean(), 0.0)) / x.mean()
        contrasts.append(c)
        samples[m] = x / NBAR
        tol = 0.5 * 4 * math.sqrt((2 + 6 / m) / n) * (1 + m / NBAR)  # Poisson removal adds var N̄ (relative M/N̄)
        checks.append(check(f"speckle contrast, M = {m:g} (1/√M)", c, 1 / math.sqrt(m), tol))
        checks.append(check(f"count variance, M = {m:g} (N̄ + N̄²/M)", x.var(), NBAR + NBAR ** 2 / m,
                            4 * math.sqrt((2 + 6 / m) / n)))
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    mm = np.geomspace(0.8, 200, 100)
    ax[0].loglog(mm, 1 / np.sqrt(mm), "k", label="1/√M")
    ax[0].loglog(ms, contrasts, "C0o", label=f"receiver chain, N̄ = {NBAR:g}, {n} pixels")
    ax[0].set(title="speckle contrast vs degrees of freedom", xlabel="speckle degrees of freedom M",
              ylabel="contrast σ_W / W̄")
    ax[0].legend(fontsize=7)
    w = np.linspace(0.005, 3, 300)
    for j, m in enumerate([1.0, 4.0, 16.0]):
        ax[1].hist(samples[m], bins=120, range=(0, 3), density=True, alpha=0.35, color=f"C{j}",
                   label=f"chain count/N̄, M = {m:g}")
        pdf = np.exp(m * np.log(m) + special.xlogy(m - 1, w) - m * w - special.gammaln(m))
        ax[1].plot(w, pdf, f"C{j}", lw=1.2, label=f"gamma pdf, M = {m:g}")
    ax[1].set(title="integrated speckle pdf", xlabel="W / W̄", ylabel="probability density")
    ax[1].legend(fontsize=7)
    save(fig, out_dir / "speckle_contrast.png")
    return checks
