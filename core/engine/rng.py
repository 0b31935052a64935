"""The random-stream policy: every random number of a run comes from one run seed.

A stage of a frame draws from ``SeedSequence([seed, frame, stage])`` (and ``pulse + 1`` appended for the stream
of one pulse of the frame: a gated-viewing slice, a scanner tile), so results depend on the seed, the frame and
the stage only, never on the thread count, the block size or the order in which blocks finish.
"""
from __future__ import annotations

import numpy as np

#: Stage keys of the per-frame random streams.
RNG_STAGE = {"beam_wander": 1, "scintillation": 2, "receiver": 3, "return_scintillation": 4, "weather_drops": 5}


def stage_seed(seed: int, frame: int, stage: str, pulse: int | None = None) -> np.random.SeedSequence:
    """The seed sequence of one stage of one frame (independent streams, reproducible); ``pulse`` selects
    the stream of one pulse of the frame (a gated-viewing slice, a scanner tile)."""
    key = [int(seed), int(frame) & 0xFFFFFFFF, RNG_STAGE[stage]]
    if pulse is not None:
        key.append(int(pulse) + 1)
    return np.random.SeedSequence(key)


def stage_rng(seed: int, frame: int, stage: str, pulse: int | None = None) -> np.random.Generator:
    """The random generator of one stage of one frame (of one pulse, if given)."""
    return np.random.default_rng(stage_seed(seed, frame, stage, pulse))
