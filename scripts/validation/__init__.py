"""Effect modules of the validation report (``scripts/validate.py``).

Every module in this folder whose name does not start with ``_`` is one effect of the report.  scripts/validate.py
finds them itself (no list to edit): adding ``weather.py`` here adds a page ``weather.md`` and its checks to the
summary.

The interface of an effect module ``<effect>.py``:

``TITLE: str`` (optional)
    The page's heading (default: the module name).
``INTRO: str`` (optional)
    Markdown shown under the heading: what is compared with what, and the references (docs/theory.md §…).
``ORDER: int`` (optional)
    Position in the summary (smaller first; default 100, then by name).
``run(out_dir: Path, quick: bool) -> list[dict]``
    ``out_dir`` is the effect's own folder (``<report>/<effect>/``, already created): every plot goes there (PNG,
    each axes with a title, axis labels with units and a legend: use :func:`save`).  ``quick`` asks for a small run
    (the whole report's quick mode must finish in about a minute, numba kernels warm).  Returns the checks, each a
    dict made with :func:`check`:

    ``quantity``  (str)   what is compared, unique within the effect, the same text in quick and full mode;
    ``simulated`` (float) what the code produced;
    ``reference`` (float) the theory or independent value it is compared with;
    ``tolerance`` (float) the allowed difference, read with ``kind``;
    ``passed``    (bool)  whether ``simulated`` is within ``tolerance`` of ``reference``;
    optional ``kind``: ``"rel"`` (default: |sim − ref| ≤ tol·|ref|), ``"abs"`` (|sim − ref| ≤ tol),
    ``"max"`` (sim ≤ ref + tol) or ``"min"`` (sim ≥ ref − tol); ``unit`` (str); ``note`` (str, shown in the table).

    Quick and full mode must be comparable: a check of the same ``quantity`` in both modes compares the same thing.
    Random draws use fixed seeds, so a quick run reproduces the quick values that scripts/validate.py records
    beside the full ones in ``checks.json`` (tests/test_validation_report.py compares them within each check's
    tolerance).  ``run`` writes nothing outside ``out_dir``.  An exception in ``run`` is reported as a failed
    check of that effect; the other effects still run.

After adding or changing an effect module, regenerate its part of the committed report (the other effects' results
are kept) and commit docs/validation/:

    .venv/bin/python scripts/validate.py --update-committed --only <effect>

Until then tests/test_validation_report.py fails, naming the effect or check that the report lacks.
"""
from __future__ import annotations

import math
from pathlib import Path

KINDS = ("rel", "abs", "max", "min")


def within(simulated: float, reference: float, tolerance: float, kind: str = "rel") -> bool:
    """Whether ``simulated`` meets ``reference`` within ``tolerance`` read as ``kind`` (see the module docstring)."""
    s, r, t = float(simulated), float(reference), float(tolerance)
    if not (math.isfinite(s) and math.isfinite(r)):
        return False
    if kind == "rel":
        return abs(s - r) <= t * abs(r)
    if kind == "abs":
        return abs(s - r) <= t
    if kind == "max":
        return s <= r + t
    if kind == "min":
        return s >= r - t
    raise ValueError(f"check kind = {kind!r}: allowed {', '.join(KINDS)}")


def allowed_difference(reference: float, tolerance: float, kind: str = "rel") -> float:
    """The absolute difference a check's tolerance allows (``rel``: tol·|ref|; else tol)."""
    return float(tolerance) * abs(float(reference)) if kind == "rel" else float(tolerance)


def check(quantity: str, simulated: float, reference: float, tolerance: float, kind: str = "rel", unit: str = "",
          note: str = "") -> dict:
    """One check dict, ``passed`` computed from ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"check kind = {kind!r}: allowed {', '.join(KINDS)}")
    if not (float(tolerance) >= 0.0):
        raise ValueError(f"check tolerance = {tolerance!r}: allowed ≥ 0")
    return {"quantity": str(quantity), "simulated": float(simulated), "reference": float(reference),
            "tolerance": float(tolerance), "passed": within(simulated, reference, tolerance, kind), "kind": kind,
            "unit": unit, "note": note}


def save(fig, path: Path, dpi: int = 80) -> Path:
    """Save ``fig`` to ``path`` after checking that every axes has a title, both axis labels and a legend
    (ValueError naming the plot and the missing part otherwise), then close it."""
    import matplotlib.pyplot as plt
    for i, ax in enumerate(fig.get_axes()):
        if not ax.get_visible() or getattr(ax, "_colorbar", None) is not None or ax.get_label() == "<colorbar>":
            continue
        missing = [name for name, ok in (("title", ax.get_title()), ("x label", ax.get_xlabel()),
                                         ("y label", ax.get_ylabel()), ("legend", ax.get_legend()))
                   if not ok]
        if missing:
            plt.close(fig)
            raise ValueError(f"plot {Path(path).name}, axes {i}: missing {', '.join(missing)}")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


class Skipped(Exception):
    """Raised by an effect's ``run`` when it cannot run on this machine (an optional environment is missing);
    the message is the exact reason.  scripts/validate.py lists the effect as skipped with that reason and keeps
    the effect's results already in the report (they are not overwritten by a skip)."""
