"""The scanner's fused pass over a block's hits (core/systems/scanner.py ``_hit_energies``) against the passes it
replaces, run one after the other as the weather route still runs them: ``_gather_hits``, ``received_energy``,
the channel scale, ``_pulse_energy`` and ``gate_tally``.  Every output must be the same bit for bit (the same
operations in the same order), so the comparison is exact equality of the bytes, not a tolerance."""
from __future__ import annotations

import numpy as np
import pytest

from core.config.settings import BRDFSettings, LaserSettings, ReceiverSettings
from core.constants import SPEED_OF_LIGHT_M_S
from core.engine.coverage import empty_tally, gate_tally
from core.physics.brdf import material_table
from core.physics.radiometry import energy_terms, received_energy
from core.systems import scanner as S

MATERIALS = [BRDFSettings(reflectance=0.3),
             BRDFSettings(model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0),
             BRDFSettings(model="table", table_angle_deg=[0.0, 10.0, 30.0, 60.0],
                          table_brdf_per_sr=[1.0, 0.5, 0.2, 0.1]),
             BRDFSettings(reflectance=0.0)]


def block(rng, n_pulses, m, n_tri, hit_fraction):
    """A block's traced rays: prim (−1 a miss), range (NaN on a miss), cos θ (0 on a miss)."""
    n = n_pulses * m
    prim = np.where(rng.random(n) < hit_fraction, rng.integers(0, n_tri, n), -1).astype(np.int32)
    range_m = np.where(prim >= 0, rng.uniform(1e-3, 400.0, n), np.nan)
    first = np.flatnonzero(prim >= 0)[:3]  # a hit at contact, one far beyond the gate, one inside it
    range_m[first] = [1e-6, 1e4, 150.0][:len(first)]
    cos_theta = np.where(prim >= 0, rng.uniform(-0.05, 1.0, n), 0.0)
    return prim, range_m, cos_theta


def by_passes(prim, range_m, cos_theta, weight, material_ids, sigma, pulse_scale, scint, window, laser, rx):
    """The passes one after the other (the scanner's route with weather, less the weather)."""
    n_hit = int(np.count_nonzero(prim >= 0))
    p_hit, mat_hit = np.empty(n_hit, np.int64), np.empty(n_hit, material_ids.dtype)
    cos_hit, range_hit, frac_hit = np.empty(n_hit), np.empty(n_hit), np.empty(n_hit)
    S._gather_hits(prim, range_m, cos_theta, weight, material_ids, p_hit, mat_hit, cos_hit, range_hit, frac_hit)
    e = received_energy(laser, rx, sigma, MATERIALS, mat_hit, cos_hit, range_hit, frac_hit)
    if pulse_scale is not None:
        e = e * pulse_scale[p_hit]
    pulse_energy = np.zeros(len(scint))
    S._pulse_energy(p_hit, scint, e, pulse_energy)
    return p_hit, range_hit, e, pulse_energy, gate_tally(range_hit, e, window)


def fused(prim, range_m, cos_theta, weight, material_ids, sigma, pulse_scale, scint, window, laser, rx):
    n_hit = int(np.count_nonzero(prim >= 0))
    p_hit, range_hit, e, tally = np.empty(n_hit, np.int64), np.empty(n_hit), np.empty(n_hit), empty_tally()
    pulse_energy = np.zeros(len(scint))
    bad, mat = S._hit_energies(prim, range_m, cos_theta, weight, material_ids, *energy_terms(laser, rx, sigma),
                               *material_table(MATERIALS), np.zeros(0) if pulse_scale is None else pulse_scale,
                               scint, window[0], window[1], SPEED_OF_LIGHT_M_S, p_hit, range_hit, e, pulse_energy,
                               tally)
    return (bad, mat), (p_hit, range_hit, e, pulse_energy, tally)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("uniform", [False, True])
def test_fused_pass_is_bit_for_bit_the_passes_it_replaces(seed, uniform):
    rng = np.random.default_rng(seed)
    n_pulses, m, n_tri = int(rng.integers(1, 400)), int(rng.choice([1, 7, 19])), 5000
    weight = rng.dirichlet(np.ones(m))
    material_ids = rng.integers(0, len(MATERIALS), n_tri)
    if uniform:  # the scanner's one-material shortcut: the ids array cut to one entry
        material_ids[:] = seed % len(MATERIALS)
    prim, range_m, cos_theta = block(rng, n_pulses, m, n_tri, [0.0, 0.3, 1.0, 0.9, 0.5, 0.7][seed])
    sigma = [0.0, 1e-3, 0.05, 0.0, 2.0, 1e-4][seed]
    pulse_scale = rng.uniform(0.5, 2.0, n_pulses) if seed % 2 else None
    scint = rng.gamma(2.0, 0.5, n_pulses)
    window = (2 * 100.0 / SPEED_OF_LIGHT_M_S, 2 * 250.0 / SPEED_OF_LIGHT_M_S)
    laser, rx = LaserSettings(), ReceiverSettings()
    ref = by_passes(prim, range_m, cos_theta, weight, material_ids, sigma, pulse_scale, scint, window, laser, rx)
    ids = material_ids[:1].copy() if uniform else material_ids
    status, out = fused(prim, range_m, cos_theta, weight, ids, sigma, pulse_scale, scint, window, laser, rx)
    assert status == (-1, 0)
    for a, b in zip(out, ref):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()
    if prim.max() >= 0:  # the comparison saw energies in every gate class it could
        assert out[4][:3].sum() == np.count_nonzero(prim >= 0)


def test_fused_pass_reports_the_first_hit_on_a_bad_material():
    rng = np.random.default_rng(1)
    prim, range_m, cos_theta = block(rng, 50, 3, 100, 1.0)
    material_ids = np.zeros(100, np.int64)
    material_ids[prim[40]] = len(MATERIALS) + 2
    first = int(np.flatnonzero(material_ids[prim] == len(MATERIALS) + 2)[0])
    status, _ = fused(prim, range_m, cos_theta, np.full(3, 1 / 3), material_ids, 0.0, None, np.ones(50),
                      (0.0, 1e-6), LaserSettings(), ReceiverSettings())
    assert status == (first, len(MATERIALS) + 2)
    with pytest.raises(IndexError, match=f"material index {len(MATERIALS) + 2} out of range"):
        by_passes(prim, range_m, cos_theta, np.full(3, 1 / 3), material_ids, 0.0, None, np.ones(50), (0.0, 1e-6),
                  LaserSettings(), ReceiverSettings())
