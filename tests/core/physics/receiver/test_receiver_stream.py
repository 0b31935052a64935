"""The counter-based uniform stream of the receiver chain's table route (core/physics/receiver/code_tables.py:
SplitMix64 output function on key + (w + 1)·γ, two 32-bit uniforms per 64-bit word) and the compiled code sampler
that evaluates it (docs/receiver.md, "Table route").

Tolerances: known answers exact (an independent big-integer implementation of the published formula);
χ² tests at the 1e-3 level (a perfect generator fails one of them with probability 1e-3; the keys are fixed, so
each test is deterministic); correlations within 5 standard errors (1/√n) of 0.
"""
import math

import numpy as np
import pytest
from scipy import stats

from core.config.settings import DetectorSettings
from core.physics.receiver.code_tables import P_BITS, CodeTable, noise_code_pmf, uniform_uint32
from core.physics.receiver.conversions import current_to_electrons, mcintyre_excess_noise
from core.physics.receiver.samplers import poisson_inversion
from scenes import SEC8, sec8_chain as chain

MASK64 = (1 << 64) - 1


def splitmix64_reference(key, word):
    """SplitMix64 (Steele, Lea & Flood 2014) in Python integers: word w of the stream seeded with ``key``."""
    z = (key + (word + 1) * 0x9E3779B97F4A7C15) & MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK64
    return z ^ (z >> 31)


def uniforms_reference(key, n):
    out = []
    for w in range((n + 1) // 2):
        z = splitmix64_reference(key, w)
        out += [z & 0xFFFFFFFF, z >> 32]
    return np.array(out[:n], dtype=np.uint64)


@pytest.mark.parametrize("key", [0, 1, 1234567, 0x9E3779B97F4A7C15, MASK64, 0xDEADBEEFCAFEF00D])
def test_stream_equals_big_integer_reference(key):
    """Known answers: the first 1001 uniforms (odd count: the last word's high half unused) and uniforms at
    scattered indices up to 2³⁹ (counters beyond 32 bits, key + counter·γ wrapping modulo 2⁶⁴)."""
    assert np.array_equal(uniform_uint32(key, 1001).astype(np.uint64), uniforms_reference(key, 1001))
    idx = np.array([0, 1, 2, 3, 1023, 1024, 1025, 2 ** 31 - 1, 2 ** 31, 2 ** 32 + 7, 2 ** 39 + 2, 2 ** 39 + 3])
    expected = [(splitmix64_reference(key, i // 2) >> (32 * (i % 2))) & 0xFFFFFFFF for i in idx.tolist()]
    assert uniform_uint32(key, idx).tolist() == expected


def test_reference_reproduces_published_splitmix64_outputs():
    """The reference itself against the outputs of the published SplitMix64 generator (Vigna's splitmix64.c,
    state x = 1234567: next() adds γ, then mixes)."""
    assert [splitmix64_reference(1234567, w) for w in range(5)] == [
        6457827717110365317, 3203168211198807973, 9817491932198370423, 4593380528125082431,
        16408922859458223821]


def test_uniforms_at_indices_equal_the_stream():
    """The bins with signal recompute their uniform from the index: the same numbers as the sequential pass."""
    key = np.uint64(0x0123456789ABCDEF)
    full = uniform_uint32(key, 5000)
    idx = np.random.default_rng(0).permutation(5000)[:1500]
    assert np.array_equal(uniform_uint32(key, idx), full[idx])
    gen_key = np.random.default_rng(5).integers(0, 2 ** 64, dtype=np.uint64)  # a Generator: one key drawn from it
    assert np.array_equal(uniform_uint32(np.random.default_rng(5), 100), uniform_uint32(gen_key, 100))


def chi2_uniform_p(counts):
    e = counts.sum() / counts.size
    return stats.chi2.sf(np.sum((counts - e) ** 2) / e, counts.size - 1)


@pytest.mark.parametrize("key", [7, 2 ** 63 + 11])
def test_uniformity_of_high_and_low_bits(key):
    """2²⁰ uniforms: χ² of the top 16 bits (65536 cells, 16 expected per cell), of the low 16 bits and of the
    low 8 bits (256 cells), at the 1e-3 level; the mean of u/2³² within 5 standard errors of 1/2."""
    r = uniform_uint32(key, 1 << 20)
    assert chi2_uniform_p(np.bincount(r >> 16, minlength=65536)) > 1e-3
    assert chi2_uniform_p(np.bincount(r & 0xFFFF, minlength=65536)) > 1e-3
    assert chi2_uniform_p(np.bincount(r & 0xFF, minlength=256)) > 1e-3
    u = r / 2.0 ** 32
    assert abs(u.mean() - 0.5) < 5 * np.sqrt(1 / 12 / u.size)


def test_consecutive_uniforms_are_uncorrelated():
    """Serial correlation of consecutive uniforms (both halves of a word, and across words) and at lag 2, within
    5/√n of 0; the pairs (u_i, u_i+1) by a 2-D χ² on 16 × 16 cells at the 1e-3 level."""
    u = uniform_uint32(99, 1 << 20) / 2.0 ** 32
    n = u.size
    for lag in (1, 2, 3):
        assert abs(np.corrcoef(u[:-lag], u[lag:])[0, 1]) < 5 / np.sqrt(n - lag), lag
    for start in (0, 1):  # pairs inside one word, and pairs across two words
        a, b = u[start:n - 1:2], u[start + 1::2]
        cells = (a * 16).astype(int) * 16 + (b * 16).astype(int)
        assert chi2_uniform_p(np.bincount(cells, minlength=256)) > 1e-3, start


@pytest.mark.parametrize("keys", [(1000, 1001), (0, 1 << 63), "chain"])
def test_streams_of_neighbouring_keys_are_independent(keys):
    """Streams of adjacent integer keys, of keys differing in the top bit only, and of the chain's neighbouring
    blocks (keys drawn from one SeedSequence): correlation within 5/√n of 0, 2-D χ² of (u_a, u_b) at 1e-3."""
    if keys == "chain":
        keys = np.random.SeedSequence(2024, spawn_key=(3,)).generate_state(2, np.uint64)
    n = 1 << 19
    a, b = (uniform_uint32(k, n) / 2.0 ** 32 for k in keys)
    assert abs(np.corrcoef(a, b)[0, 1]) < 5 / np.sqrt(n)
    cells = (a * 16).astype(int) * 16 + (b * 16).astype(int)
    assert chi2_uniform_p(np.bincount(cells, minlength=256)) > 1e-3


F_SEC8 = float(mcintyre_excess_noise(100.0, 0.02))
DS_SEC8 = float(current_to_electrons(1e-9, 1e-9))


def sec8_table(offset=16, top=4095, dtype=np.uint16, step=500.0):
    k0, p = noise_code_pmf(step, n_mult=2.0, gain=100.0, excess_noise=F_SEC8, surface_dark_e=DS_SEC8,
                           surface_dark_poisson=True, gauss_var_e2=300.0 ** 2)
    return CodeTable(k0, p, offset, top, dtype)


@pytest.mark.parametrize("n", [1, 2, 1023, 1024, 1025, 3001, 262144])
def test_stream_sampler_equals_the_lookup_of_the_stream(n):
    """The compiled sampler (uniforms made chunk by chunk inside it) gives exactly the codes and clip counts of
    the level-1 + binary-search look-up of the same uniforms, for every length (chunk edges, odd lengths)."""
    table = sec8_table(offset=0)  # offset 0: the low tail is clipped (counted)
    out = np.empty(n, np.uint16)
    lo, hi = table.sample_stream(42, out)
    r = uniform_uint32(42, n)
    ref = np.empty(n, np.uint16)
    assert (lo, hi) == table.sample(r, ref)
    assert np.array_equal(out, ref)
    entry = np.searchsorted(table.T, r.astype(np.uint64), side="right")
    assert np.array_equal(out, table.code[entry]) and lo == np.count_nonzero(entry == 0)


def test_stream_sampler_code_frequencies_match_the_table():
    """2²⁰ codes from the stream against the table's (2^-32-rounded) probabilities: χ² at the 1e-3 level (cells
    with < 5 expected lumped), and the clipped count within 5 standard errors."""
    table = sec8_table(offset=0)
    n = 1 << 20
    out = np.empty(n, np.uint16)
    lo, _ = table.sample_stream(2 ** 40 + 3, out)
    p = np.diff(np.concatenate([[0], table.T.astype(np.int64)])) / 2.0 ** P_BITS
    codes = table.code.astype(np.int64)
    e = np.bincount(codes, weights=p, minlength=int(codes.max()) + 1) * n  # entries of one code merged (code 0)
    h = np.bincount(out, minlength=e.size)
    assert h.size == e.size and h[e == 0].sum() == 0
    big = e >= 5
    chi2 = np.sum((h[big] - e[big]) ** 2 / e[big]) + (h[~big].sum() - e[~big].sum()) ** 2 / max(e[~big].sum(), 1e-9)
    assert stats.chi2.sf(chi2, np.count_nonzero(big)) > 1e-3
    assert abs(lo - n * p[0]) < 5 * np.sqrt(n * p[0]) and p[0] > 0.1


# ----------------------------------------------------------------------------------------------- the chain


def returns_cube(shape=(96, 80, 300)):
    """Returns of varying strength (0 … 60 primaries) in a few bins of every pixel (5 blocks of the table route)."""
    rng = np.random.default_rng(1)
    cube = np.zeros(shape, np.float32)
    h, w, b = shape
    j = rng.integers(0, b - 4, (h, w))
    e = rng.uniform(0, 2.8e-17, (h, w)).astype(np.float32)
    for d in range(4):
        np.put_along_axis(cube, (j + d)[..., None], e[..., None] * (1 - 0.2 * d), axis=2)
    return cube


def test_table_route_is_identical_on_any_thread_count():
    """Blocks own their streams (and the bins drawn per bin are drawn in block order after them): 1, 2, 3 and 5
    threads give the same codes and report, bit for bit."""
    cube = returns_cube()
    ref = chain(cube, 11, threads=1)
    nt = ref.report["noise_table"]
    assert ref.report["noise_sampling"] == "table" and nt["caught_bins_from_tables"] > 0 and nt["caught_bins_per_bin"] > 0
    for threads in (2, 3, 5):
        out = chain(cube, 11, threads=threads)
        assert np.array_equal(out.data, ref.data) and out.report == ref.report, threads


def test_table_route_signal_free_bins_use_the_block_streams():
    """The codes of the signal-free bins are the table's codes of the uniforms of each block's stream (key k of
    the keys drawn from the seed's child (3,), uniform index = bin index in the block)."""
    from core.physics.receiver.conversions import background_photons
    from core.physics.receiver.table_route import noise_tables

    cube = returns_cube((20, 16, 300))  # 320 pixels: 1747 per block of 2^19 samples → one block
    out = chain(cube, np.random.SeedSequence(77))
    key = np.random.SeedSequence(77, spawn_key=(3,)).generate_state(1, np.uint64)[0]
    d = DetectorSettings(**{"mode": "noisy", **SEC8})
    b_mult = float(background_photons(5e9, 1e-9)) * 0.4 + float(current_to_electrons(1e-12, 1e-9))
    table, _ = noise_tables(500.0, b_mult, 100.0, F_SEC8, True, DS_SEC8, 300.0, 16, 12, np.dtype(np.uint16).str)
    ref = np.empty(cube.size, np.uint16)
    table.sample(uniform_uint32(key, cube.size), ref)
    free = cube.reshape(-1) == 0
    assert d.adc_bits == 12 and free.sum() > 0.9 * cube.size
    assert np.array_equal(out.data.reshape(-1)[free], ref[free])


BAD = {"nan": (np.nan, "NaN or Inf"), "inf": (np.inf, "NaN or Inf"), "-inf": (-np.inf, "NaN or Inf"),
       "negative": (-1e-20, "negative energies")}


@pytest.mark.parametrize("bad", list(BAD))
@pytest.mark.parametrize("route", ["table", "per-bin", "float64", "optics_mtf"])
def test_bad_input_gets_the_same_error_on_every_route(bad, route):
    """NaN/±Inf or a negative energy anywhere (first bin, last bin of the last block, inside a 64-bin stretch):
    ValueError naming it, on the table route (checked by the compiled block scan), the per-bin route, a float64
    cube and with the optics MTF (checked up front).  A NaN together with a negative energy is a NaN error."""
    value, message = BAD[bad]
    det = {"per-bin": dict(enable_adc=False), "optics_mtf": dict(enable_optics_mtf=True)}.get(route, {})
    for where in (0, -1, 4100):
        cube = returns_cube((24, 24, 300))
        cube.reshape(-1)[where] = value
        if route == "float64":
            cube = cube.astype(np.float64)
        with pytest.raises(ValueError, match=message):
            chain(cube, 3, **det)
    cube = returns_cube((24, 24, 300))
    cube[3, 4, 5], cube[20, 20, 200] = -1.0, value
    with pytest.raises(ValueError, match="NaN or Inf" if bad != "negative" else "negative energies"):
        chain(cube, 3, **det)


def test_valid_edge_values_pass_the_check():
    """−0.0 and the largest float32 are valid energies (not negative, finite) on the table route."""
    cube = returns_cube((8, 8, 300))
    cube[0, 0, :3] = -0.0
    cube[1, 1, 7] = np.finfo(np.float32).max
    out = chain(cube, 1)
    assert out.report["noise_sampling"] == "table" and out.report["n_mean_clipped"] == 1


# ------------------------------------------------------------------------- Poisson counts of the signal bins
def poisson_inversion_reference(lam, p0, u):
    """The same inversion in Python floats."""
    if u < p0:
        return 0
    p = f = p0
    k = 0
    while k < 64:
        k += 1
        p *= lam / k
        f += p
        if u < f:
            break
    return k


def test_poisson_inversion_equals_reference():
    """Known answers: 20000 (mean, uniform) pairs over the inversion's range, and the extreme uniforms."""
    rng = np.random.default_rng(8)
    lam = np.concatenate([10.0 ** rng.uniform(-8, np.log10(7.999), 19990), [1e-12, 0.5, 7.999, 3.0, 3.0]])
    u = np.concatenate([rng.uniform(0, 1, 19990), [0.0, 1 - 2.0 ** -53, 1 - 2.0 ** -53, 0.0, 0.049787068367863944]])
    p0 = np.exp(-lam)
    args = list(zip(lam.tolist(), p0.tolist(), u.tolist()))
    got = [poisson_inversion(*a) for a in args]
    assert got == [poisson_inversion_reference(*a) for a in args]
    assert got[-5] == 0 and got[-2] == 0 and 20 < got[-3] < 64 and got[-1] == 1  # u = F_0 exactly: k = 1


@pytest.mark.parametrize("lam", [1e-4, 0.05, 0.7, 3.0, 7.99])
def test_poisson_inversion_of_the_stream_matches_the_pmf(lam):
    """2e5 counts from the 53-bit uniforms of a stream (as the chain makes them) against the Poisson pmf: χ² at
    the 1e-3 level (cells with < 5 expected lumped), mean and variance within 5 standard errors."""
    n = 200_000
    w = uniform_uint32(31, 2 * n).view(np.uint64)  # (the 64-bit words of the stream, little-endian)
    u = (w >> np.uint64(11)).astype(np.float64) * 2.0 ** -53
    k = np.array([poisson_inversion(lam, math.exp(-lam), x) for x in u.tolist()])
    h = np.bincount(k, minlength=80)[:80]
    e = stats.poisson.pmf(np.arange(80), lam) * n
    big = e >= 5
    chi2 = np.sum((h[big] - e[big]) ** 2 / e[big]) + (h[~big].sum() - e[~big].sum()) ** 2 / max(e[~big].sum(), 1e-9)
    assert stats.chi2.sf(chi2, max(np.count_nonzero(big), 1)) > 1e-3
    assert abs(k.mean() - lam) < 5 * np.sqrt(lam / n)
    assert abs(k.var() - lam) < 5 * np.sqrt((lam + 2 * lam ** 2) / n)


@pytest.mark.parametrize("n_s", [0.02, 3.0])
def test_signal_bins_drawn_by_inversion_match_the_formula(n_s):
    """Signal means below 8 (Poisson by inversion, caught codes from the tables): 262144 bins have the §8 mean and
    variance within 2 %."""
    from core.physics.receiver.conversions import energy_to_photons, linear_detector_moments

    e = n_s / float(energy_to_photons(1.0, 1.064e-6, 0.4))
    out = chain(np.full((64, 64, 64), e, np.float32), 12)
    assert out.report["noise_table"]["caught_bins_from_tables"] > 0
    b = 5e9 * 1e-9 * 0.4 + current_to_electrons(1e-12, 1e-9)
    x = (out.data.astype(np.float64) - 16) * 500.0
    mean_e, var_e = linear_detector_moments(n_s, b, 100.0, F_SEC8, 0.0, DS_SEC8, 300.0, 500.0)
    assert x.mean() == pytest.approx(mean_e, rel=0.02)
    assert x.var() == pytest.approx(var_e, rel=0.02)


def test_zero_count_shortcut_decides_as_the_exp():
    """A signal bin with u < (1 − λ) − margin has count 0 without its e^(−λ) (table_route._ZERO_MARGIN): the
    decision must be the one of u < e^(−λ) computed by NumPy's exp, also for uniforms just below 1 − λ and for
    tiny λ, where e^(−λ) and 1 − λ round to neighbouring doubles."""
    from core.physics.receiver import table_route

    margin = table_route._ZERO_MARGIN
    assert 0 < margin < 1e-9
    rng = np.random.default_rng(16)
    lam = np.concatenate([10.0 ** rng.uniform(-17, 1, 20_000), [0.0, 1e-300, 2.0 ** -53, 2.0 ** -40, 1.0]])
    step = 2.0 ** -53
    ks = np.concatenate([np.arange(0, 4096), 2 ** np.arange(12, 40)]).astype(np.float64)
    for lo in range(0, lam.size, 2000):
        lm = lam[lo:lo + 2000, None]
        b = 1.0 - lm
        # uniforms on the 2⁻⁵³ grid just below and around 1 − λ, and random ones
        u = np.clip(np.floor(b / step) * step - ks[None, :] * step, 0.0, 1.0 - step)
        u = np.concatenate([u, rng.integers(0, 2 ** 53, (lm.size, 64)) * step], axis=1)
        shortcut = u < b - margin
        assert not np.any(shortcut & ~(u < np.exp(-lm)))
        assert shortcut[:, -64:].mean() > 0.4  # (it decides most random ones)
