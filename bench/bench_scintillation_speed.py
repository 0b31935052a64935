"""Pattern-generation speed: the wave-optics statistics (issue 17) against the generator before it (one run).

The baseline is the scintillation package as of git ref ``--baseline`` (default: the commit before issue 17's
first change, 7344fa1), extracted with ``git archive`` into a temporary directory and timed in a subprocess
that alternates with the current code, case by case, so both see the same machine load.  Cases: the paper's
gated-viewing reference (532 nm, board at 1 km, 0.6 m footprint, spherical wave) at Cn² 2e-15 … 1e-13, and the
pipeline's grid cap (``max_grid_px=2048``).  Reports the best of ``--repeats`` times per case and the ratio
new/baseline (target ≤ 1.5).  Writes bench/results/scintillation_speed.json.

    python bench/bench_scintillation_speed.py [--repeats 5] [--baseline REF]
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
cn2, repeats, kw = {cn2!r}, {repeats!r}, {kw!r}
ts = []
for rep in range(repeats):
    t = time.perf_counter()
    p = sc.make_scintillation_pattern({extent!r}, cn2, 532e-9, 1e3, np.random.default_rng(rep), max_grid_px=2048, **kw)
    ts.append(time.perf_counter() - t)
print(json.dumps({{"seconds": min(ts), "model": p.model}}))
"""


def timed(root, cn2, repeats, kw):
    code = TIMER.format(root=str(root), cn2=cn2, repeats=repeats, kw=kw, extent=EXTENT)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", default="7344fa1")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "scintillation_speed.json"))
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        blob = subprocess.run(["git", "-C", str(ROOT), "archive", a.baseline, "core"], capture_output=True,
                              check=True).stdout
        tarfile.open(fileobj=BytesIO(blob)).extractall(tmp)
        rows = []
        for cn2 in CASES:
            base = timed(tmp, cn2, a.repeats, {})
            new = timed(ROOT, cn2, a.repeats, {})
            paper = timed(ROOT, cn2, a.repeats, {"statistics": "paper"})
            rows.append({"cn2_m_23": cn2, "baseline_s": base["seconds"], "baseline_model": base["model"],
                         "wave_optics_s": new["seconds"], "wave_optics_model": new["model"],
                         "paper_now_s": paper["seconds"], "ratio_wave_optics_over_baseline":
                         new["seconds"] / base["seconds"]})
            print(json.dumps(rows[-1]), flush=True)
    res = {"description": __doc__.split("\n")[0], "baseline_ref": a.baseline, "repeats": a.repeats,
           "extent_m": EXTENT, "wavelength_m": 532e-9, "range_m": 1e3, "cases": rows,
           "max_ratio": max(r["ratio_wave_optics_over_baseline"] for r in rows),
           "date": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}
    Path(a.out).write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
