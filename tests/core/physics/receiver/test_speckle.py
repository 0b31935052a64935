"""Speckle statistics (docs/theory.md §7) and optics MTFs (docs/theory.md §5).

Reference values at 4 significant digits (rel 5e-4); sampled contrast within 5 %; MTF measured from a
simulated edge within 5 % of the formula.
"""
import numpy as np
import pytest

from core.physics.receiver.speckle import (apply_mtf, mtf_diffraction, mtf_optics, mtf_pixel, mtf_speckle,
                                           negative_binomial_counts, optics_mtf_2d, sample_speckle_gain,
                                           speckle_contrast, speckle_dof_approx, speckle_dof_exact,
                                           speckle_gain_field, speckle_gamma_pdf)

REL4 = 5e-4
S1 = (0.1, 0.5, 1.064e-6, 2000.0)
S2 = (0.05, 0.2, 1.55e-6, 5000.0)


def test_speckle_dof_cases():
    assert speckle_dof_exact(*S1) == pytest.approx(363.1, rel=REL4)
    assert speckle_dof_approx(*S1) == pytest.approx(341.5, rel=REL4)
    assert speckle_dof_exact(*S2) == pytest.approx(2.263, rel=REL4)
    assert speckle_dof_approx(*S2) == pytest.approx(2.027, rel=REL4)


def test_speckle_dof_limits():
    # a tiny aperture (A_R ≪ A_c) sees one speckle: M → 1
    assert speckle_dof_exact(1e-4, 0.5, 1.064e-6, 2000.0) == pytest.approx(1.0, rel=1e-3)


def test_gamma_pdf_values():
    np.testing.assert_allclose(speckle_gamma_pdf([0.5, 1.0, 2.0], 4.0), [0.7218, 0.7815, 0.1145], rtol=REL4)
    # M = 1: fully developed speckle, exponential
    np.testing.assert_allclose(speckle_gamma_pdf([0.0, 1.0], 1.0), [1.0, np.exp(-1)], rtol=1e-12)


@pytest.mark.parametrize("M", [1.0, 4.0, 30.0, 363.1])
def test_sampled_contrast(M):
    w = sample_speckle_gain(200_000, M, np.random.default_rng(int(M)))
    assert w.mean() == pytest.approx(1.0, rel=0.01)
    assert w.std() / w.mean() == pytest.approx(speckle_contrast(M), rel=0.05)


def test_correlated_speckle_field_marginal_and_grain():
    rng = np.random.default_rng(4)
    M = 4.0
    # coherent cut-off 0.1 cycles/pixel: grain ~ several pixels
    f = speckle_gain_field((256, 256), M, rng, correlated=True, wavelength_m=1e-6, aperture_diameter_m=0.1,
                           ifov_rad=2e-6)
    assert f.mean() == pytest.approx(1.0, rel=0.05)
    assert f.std() == pytest.approx(0.5, rel=0.05)
    # neighbouring pixels are correlated, distant ones are not
    g = f - f.mean()
    c1 = np.mean(g[:, 1:] * g[:, :-1]) / g.var()
    c40 = np.mean(g[:, 40:] * g[:, :-40]) / g.var()
    assert c1 > 0.5 and abs(c40) < 0.05


def test_negative_binomial_variance():
    rng = np.random.default_rng(6)
    n = negative_binomial_counts(np.full(300_000, 25.0), 2.263, rng)
    assert n.mean() == pytest.approx(25.0, rel=0.02)
    assert n.var() == pytest.approx(25.0 + 25.0 ** 2 / 2.263, rel=0.02)


# --------------------------------------------------------------------------------------------- §5 MTFs
LAM, D = 1.064e-6, 0.1
NU_C = D / LAM  # 9.398e4 cycles/rad


def test_mtf_reference_values():
    assert NU_C == pytest.approx(9.398e4, rel=REL4)
    np.testing.assert_allclose(mtf_diffraction([0.25 * NU_C, 0.5 * NU_C], D, LAM), [0.6850, 0.3910], rtol=REL4)
    assert mtf_pixel(25e3, 20e-6) == pytest.approx(0.6366, rel=REL4)  # 25 cycles/mm, 20 µm
    assert mtf_diffraction(NU_C * 1.2, D, LAM) == 0.0
    assert mtf_speckle(0.25 * NU_C, D, LAM) == pytest.approx(0.6850, rel=REL4)


def test_total_mtf_with_long_exposure_term():
    f, nu, r0 = 0.5, 25e3, 0.05  # focal length, 25 cycles/mm, r0
    nu_a = nu * f
    le = np.exp(-3.44 * (LAM * nu_a / r0) ** (5 / 3))  # §5 long-exposure turbulence MTF, inline
    assert le * mtf_optics(nu_a, D, LAM, ifov_rad=20e-6 / f) == pytest.approx(0.3624, rel=REL4)


@pytest.mark.parametrize("pixel", [False, True])
def test_mtf_measured_from_edge(pixel):
    """Blur a sharp vertical edge with the discrete optics filter, differentiate the edge spread function,
    Fourier transform the line spread function and compare with the formula (cut-off 0.4 cycles/pixel)."""
    n = 512
    ifov = 0.4 * LAM / D  # diffraction cut-off at 0.4 cycles/pixel
    img = np.zeros((64, n))
    img[:, n // 2:] = 1.0
    mtf2 = optics_mtf_2d(img.shape, LAM, D, ifov, pixel=pixel)
    blurred, _ = apply_mtf(img, mtf2)
    esf = blurred[32]
    lsf = np.diff(esf)[n // 4: 3 * n // 4]  # the rising edge only (the periodic falling edge is far away)
    spec = np.abs(np.fft.rfft(lsf, 4096))
    spec /= spec[0]
    f_px = np.fft.rfftfreq(4096)
    for f in (0.05, 0.1, 0.2, 0.3):
        i = int(round(f * 4096))
        # the difference of the unblurred discrete edge is a unit impulse, so |FT(LSF)| is the filter itself
        want = mtf_diffraction(f_px[i] / ifov, D, LAM) * (abs(np.sinc(f_px[i])) if pixel else 1.0)
        assert spec[i] == pytest.approx(want, rel=0.05, abs=0.005)
