"""Atmosphere and turbulence: the report of scripts/validate_atmosphere.py, folded into the validation report."""
from __future__ import annotations

from pathlib import Path

from validation import check
from validation._common import ROOT

TITLE = "Atmosphere and turbulence"
ORDER = 60
INTRO = """Extinction, scintillation (log-normal, gamma-gamma and the wave-optics table against split-step
propagation), turbulence blur (MTF), beam wander: the checks of `scripts/validate_atmosphere.py` (which still
runs on its own and writes the detailed page linked below, with every row of its tables, including the
reference-only rows that are not checks: split-step SI against the all-regime formula and the paper's formulas
against wave optics).  Quick mode draws fewer realisations and measures the patterns at the first four wave-optics validation cases only.  References: docs/theory.md §3, §5, §6, §11, §12; the wave-optics runs in
bench/results/scintillation_wave_optics.json (scripts/tabulate_scintillation.py).  A KS p-value is checked as
p ≥ 0.01."""


def run(out_dir: Path, quick: bool) -> list[dict]:
    import sys
    if str(ROOT / "scripts") not in sys.path:
        sys.path.insert(0, str(ROOT / "scripts"))
    import validate_atmosphere
    _, raw = validate_atmosphere.report(out_dir, quick=quick, smallest=True)
    return [check(c["quantity"], c["simulated"], c["reference"], c["tolerance"], c.get("kind", "rel"),
                  unit=c.get("unit", "")) for c in raw]
