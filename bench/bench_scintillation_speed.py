"""Pattern-generation speed: the wave-optics statistics (issue 17) against the generator before it (one run).

The baseline is the scintillation package as of git ref ``--baseline`` (default: the commit before issue 17's
first change, 7344fa1), extracted with ``git archive`` into a temporary directory and timed in a subprocess
that alternates with the current code, case by case, so both see the same machine load.  Cases: the paper's
gated-viewing reference (532 nm, board at 1 km, 0.6 m footprint, spherical wave) at Cn² 2e-15 … 1e-13, and the
pipeline's grid cap (``max_grid_px=2048``).  Reports the best of ``--repeats`` times per case and the ratio
new/baseline (target ≤ 1.5).  Writes ``scintillation_speed.json`` to ``--out DIR`` (default runs/bench/;
``--update-committed``: bench/results/scintillation_speed.json).  ``--quick``: one case (Cn² 1e-14), one repeat,
the grid capped at 512 pixels.

    .venv/bin/python bench/bench_scintillation_speed.py [--repeats 5] [--baseline REF] [--out DIR | --update-committed]
        [--quick]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = (2e-15, 1e-14, 5e-14, 1e-13)
EXTENT = (-0.3, 0.3, -0.3, 0.3)

TIMER = """
import sys, time, json, numpy as np
sys.path.insert(0, {root!r})
from core.atmosphere import scintillation as sc
cn2, repeats, kw, grid = {cn2!r}, {repeats!r}, {kw!r}, {grid!r}
ts = []
for rep in range(repeats):
    t = time.perf_counter()
    p = sc.make_scintillation_pattern({extent!r}, cn2, 532e-9, 1e3, np.random.default_rng(rep), max_grid_px=grid, **kw)
    ts.append(time.perf_counter() - t)
print(json.dumps({{"seconds": min(ts), "model": p.model}}))
"""


def timed(root, cn2, repeats, kw, grid=2048):
    code = TIMER.format(root=str(root), cn2=cn2, repeats=repeats, kw=kw, extent=EXTENT, grid=grid)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", default="7344fa1")
    sys.path.insert(0, str(ROOT / "bench"))
    from benchio import add_output_arguments, output_path, write_json

    add_output_arguments(ap)
    a = ap.parse_args(argv)
    out = output_path(ap, a, "scintillation_speed.json")
    cases, grid = ((1e-14,), 512) if a.quick else (CASES, 2048)
    if a.quick:
        a.repeats = 1
    with tempfile.TemporaryDirectory() as tmp:
        blob = subprocess.run(["git", "-C", str(ROOT), "archive", a.baseline, "core"], capture_output=True,
                              check=True).stdout
        tarfile.open(fileobj=BytesIO(blob)).extractall(tmp)
        rows = []
        for cn2 in cases:
            base = timed(tmp, cn2, a.repeats, {}, grid)
            new = timed(ROOT, cn2, a.repeats, {}, grid)
            paper = timed(ROOT, cn2, a.repeats, {"statistics": "paper"}, grid)
            rows.append({"cn2_m_23": cn2, "baseline_s": base["seconds"], "baseline_model": base["model"],
                         "wave_optics_s": new["seconds"], "wave_optics_model": new["model"],
                         "paper_now_s": paper["seconds"], "ratio_wave_optics_over_baseline":
                         new["seconds"] / base["seconds"]})
            print(json.dumps(rows[-1]), flush=True)
    res = {"description": __doc__.split("\n")[0], "quick": a.quick, "max_grid_px": grid,
           "baseline_ref": a.baseline, "repeats": a.repeats,
           "extent_m": EXTENT, "wavelength_m": 532e-9, "range_m": 1e3, "cases": rows,
           "max_ratio": max(r["ratio_wave_optics_over_baseline"] for r in rows),
           "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    print(json.dumps(res, indent=1))
    print(f"wrote {write_json(out, res, indent=1)}")


if __name__ == "__main__":
    main()
