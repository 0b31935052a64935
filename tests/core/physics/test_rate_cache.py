"""The statistical route's importance-sampled false-alarm rates kept on disk (core.physics.detection.stretches
``rate_model``): a new process loads the very arrays the sampling made; a damaged or foreign file is sampled again;
a folder that cannot be written costs nothing but the sampling."""
from __future__ import annotations

import numpy as np
import pytest

from core.physics.detection import stretches as S
from core.physics.detection.noisy import gaussian_pulse_kernel

PULSE = gaussian_pulse_kernel(3e-9, 1e-9)
CODES = np.arange(380, 421)
PROBS = np.exp(-0.5 * ((CODES - 400) / 4.0) ** 2)
PROBS /= PROBS.sum()
ARGS = (48, PULSE, 4.0, 3.5 * 4.0 / float(np.sqrt(np.sum(PULSE ** 2))))  # bins, pulse, σ, threshold


def _model(base=400.0):
    return S.rate_model(*ARGS, law=(CODES, PROBS), base=base)


def _same(a, b):
    assert np.array_equal(a.rates, b.rates) and np.array_equal(a.rel_se, b.rel_se)
    assert np.array_equal(a.cls, b.cls) and a.u == b.u
    assert len(a.pools) == len(b.pools)
    for (ya, wa), (yb, wb) in zip(a.pools, b.pools):
        assert np.array_equal(ya, yb) and np.array_equal(wa, wb)
    ra, rb = np.random.default_rng(1), np.random.default_rng(1)
    assert np.array_equal(a.triples(0, 50, ra), b.triples(0, 50, rb))


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setattr(S, "CACHE_DIR", tmp_path)
    S._RATE_CACHE.clear()
    yield tmp_path / "false_alarm_rates"
    S._RATE_CACHE.clear()


def test_rates_from_disk_are_the_sampled_ones(cache):
    sampled = _model()
    files = list(cache.glob("*.npz"))
    assert len(files) == 1 and sampled.rates[0] > 0
    S._RATE_CACHE.clear()  # a new process: memory empty, the file there
    loaded = _model()
    assert loaded is not sampled
    _same(sampled, loaded)
    # the same numbers as sampling without any cache (fixed seed)
    fresh = S.LatticeRates(ARGS[0], PULSE, CODES, PROBS, 400.0, ARGS[3])
    _same(fresh, loaded)
    # another input is another file
    S._RATE_CACHE.clear()
    _model(base=401.0)
    assert len(list(cache.glob("*.npz"))) == 2


def test_damaged_or_foreign_file_is_sampled_again(cache):
    sampled = _model()
    path = next(cache.glob("*.npz"))
    path.write_bytes(path.read_bytes()[:1000])  # cut short
    S._RATE_CACHE.clear()
    _same(sampled, _model())
    # a file of another key under this key's name: its tag differs, so it is not used
    S._RATE_CACHE.clear()
    _model(base=401.0)
    other = [p for p in cache.glob("*.npz") if p != path][0]
    path.write_bytes(other.read_bytes())
    S._RATE_CACHE.clear()
    again = _model()
    _same(sampled, again)


def test_unwritable_cache_folder_still_samples(tmp_path, monkeypatch):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setattr(S, "CACHE_DIR", blocker)
    S._RATE_CACHE.clear()
    try:
        m = _model()
        assert m.rates[0] > 0
        assert blocker.read_text().startswith("a file")
    finally:
        S._RATE_CACHE.clear()
