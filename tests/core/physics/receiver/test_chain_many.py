"""apply_receiver_chains (session 31): several cubes through the chain with their blocks drawn in one parallel
pass and their per-bin tails in another — the outputs of one apply_receiver_chain call per cube, bit for bit
(codes and reports), on the table route (with signal bins caught by tables and per bin), the per-bin route, the
ideal and Geiger modes, on 1–3 threads; and a bad cube raises as the separate call does, nothing returned."""
import numpy as np
import pytest

from core.config.settings import DetectorSettings
from core.physics.receiver.chain import ChainSettings, apply_receiver_chain, apply_receiver_chains
from scenes import SEC8


def settings(threads, **det):
    return ChainSettings(DetectorSettings(**{"mode": "noisy", **SEC8, "threads": threads, **det}),
                         wavelength_m=1.064e-6, bin_width_s=1e-9)


def cubes():
    """Window cubes like the statistical route's: (1, rows, L), signal of 1e-19 … 1e-15 J a bin (a few to a few
    thousand photo-electrons: the caught-count tables and the per-bin tail), one over two blocks of 2¹⁹."""
    rng = np.random.default_rng(31)
    out = []
    for rows, L in ((9000, 128), (700, 256), (40, 64), (3, 512)):
        c = np.zeros((1, rows, L), np.float32)
        hot = rng.random((rows, L)) < 0.5
        c[0][hot] = (10.0 ** rng.uniform(-19, -15, hot.sum())).astype(np.float32)
        out.append(c)
    return out


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("det", [{}, {"mode": "ideal"}, {"detector_type": "geiger", "geiger_pulses": 4},
                                 {"enable_excess_noise": False, "enable_background": False}])
def test_many_equals_one_call_each(threads, det):
    cs = settings(threads, **det)
    cb = cubes()
    seeds = [np.random.SeedSequence(7, spawn_key=(1, k)) for k in range(len(cb))]
    many = apply_receiver_chains(cb, cs, seeds)
    for c, sd, m in zip(cb, seeds, many):
        one = apply_receiver_chain(c, cs, sd)
        assert m.data.dtype == one.data.dtype and m.data.tobytes() == one.data.tobytes()
        assert m.report == one.report
    if not det:  # the cases this is for: tables and per-bin tail both used
        nt = many[0].report["noise_table"]
        assert nt["caught_bins_from_tables"] > 0 and nt["caught_bins_per_bin"] > 0


def test_many_per_bin_route_equals_one_call_each():
    cs = settings(2)
    cb = cubes()[1:]
    many = apply_receiver_chains(cb, cs, [5, 6, 7], noise_table=False)
    for c, sd, m in zip(cb, [5, 6, 7], many):
        one = apply_receiver_chain(c, cs, sd, noise_table=False)
        assert m.report["noise_sampling"] == "per-bin" and m.data.tobytes() == one.data.tobytes()


def test_many_bad_cube_raises():
    cb = cubes()
    cb[2][0, 5, 3] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        apply_receiver_chains(cb, settings(2), [1, 2, 3, 4])
