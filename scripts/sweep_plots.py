#!/usr/bin/env python3
"""Draw a sweep folder's plots again from its results table (``core.sweep.runner.replot``).

    .venv/bin/python scripts/sweep_plots.py SWEEP_DIR

A sweep draws its plots when every task has run; one that was cancelled (or whose table was merged by hand)
gets them here: ``SWEEP_DIR/plots/<figure>_vs_<axis>.png`` from ``results.csv`` and ``sweep.json``, over the
tasks done so far.  Exit status 0, or 1 with one line naming what is wrong.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.errors import ConfigError  # noqa: E402
from core.sweep.runner import replot  # noqa: E402


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) != 1 or argv[0] in ("-h", "--help"):
        print(__doc__, file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    try:
        paths = replot(argv[0])
    except ConfigError as exc:
        print(f"sweep_plots: error: {exc}", file=sys.stderr)
        return 1
    print(f"sweep_plots: {len(paths)} plots in {Path(argv[0]) / 'plots'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
