"""A/D conversion of electrons to digital counts (docs/theory.md §8)."""
from __future__ import annotations

import numpy as np

from .conversions import adc_step_e


def adc_dtype(bits: int):
    return np.uint16 if bits <= 16 else (np.uint32 if bits <= 32 else np.uint64)


def adc_convert(electrons, bits, full_scale_e, offset_counts=0, out=None, overwrite_input=False):
    """A/D conversion (docs/theory.md §8): code = clip(rint(e/Δ) + offset, 0, 2**bits − 1), Δ = full scale/2**bits.

    Returns ``(codes, n_low, n_high)``: the number of samples clipped at code 0 and at full scale
    (saturation) — clipping is always reported, never silent.  Quantization adds variance Δ²/12.
    ``overwrite_input`` lets a float32/float64 input be used as scratch space (no copy).
    """
    e = np.asarray(electrons)
    step = adc_step_e(bits, full_scale_e)
    top = float(2 ** int(bits) - 1)
    wdt = np.float64 if bits > 23 else np.float32
    work = e if (overwrite_input and e.dtype == wdt) else e.astype(wdt, copy=True)
    work *= work.dtype.type(1.0 / step)
    np.rint(work, out=work)
    if offset_counts:
        work += work.dtype.type(offset_counts)
    n_low = int(np.count_nonzero(work < 0))
    n_high = int(np.count_nonzero(work > top))
    if n_low or n_high:
        np.clip(work, 0, top, out=work)
    if out is None:
        return work.astype(adc_dtype(bits)), n_low, n_high
    np.copyto(out, work, casting="unsafe")
    return out, n_low, n_high

