"""A module imported at its first use: ``sfft = lazy_module("scipy.fft")`` at the top of a module, then
``sfft.rfft2(...)`` imports SciPy's FFT at the first call and calls the very same function as ``from scipy import
fft as sfft`` would.  For a library that only some runs need (issue 25: what a command imports at start-up is
paid by every command; SciPy's FFT is needed only with turbulence or a noisy receiver's speckle and optics blur).
Standard library only."""
from __future__ import annotations

import importlib


class LazyModule:
    """Stands for module ``name`` until an attribute is read: then imports it (once; later reads are a lookup)."""

    __slots__ = ("_name", "_module")

    def __init__(self, name: str):
        self._name = name
        self._module = None

    def __getattr__(self, attr: str):
        module = self._module
        if module is None:
            module = self._module = importlib.import_module(self._name)
        return getattr(module, attr)

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r} ({'imported' if self._module is not None else 'not imported yet'})>"


def lazy_module(name: str) -> LazyModule:
    """The module ``name``, imported at the first attribute read."""
    return LazyModule(name)
