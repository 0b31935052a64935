#!/usr/bin/env python3
"""Run the worked sweep of docs/sweeps.md and write its table (and figure) into a folder you name.

    .venv/bin/python scripts/sweep_example.py OUT_DIR [--workers N] [--write-doc]

Runs ``scripts/ladar_run.py sample_blends/flash_demo.blend sweep docs/examples/range_visibility.toml --out
OUT_DIR/range_visibility`` (a local cluster), then writes ``OUT_DIR/table.md``: the means over the seeds of the
target's detection probability, range error RMS and SNR per range × visibility, the target, and the false alarms
per pixel — the table of docs/sweeps.md ("A worked sweep").  Nothing committed is touched unless ``--write-doc``
is given: then the table between the ``sweep-table`` markers of docs/sweeps.md is replaced and the detection
figure copied to docs/sweep_range_visibility.png.  tests/addon/test_sweep_example.py runs it and checks that
docs/sweeps.md holds the table it produces (the seeds are the sweep file's: the table is the same on every run).
"""
from __future__ import annotations

import argparse
import csv
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SWEEP = REPO / "docs" / "examples" / "range_visibility.toml"
BLEND = REPO / "sample_blends" / "flash_demo.blend"
DOC = REPO / "docs" / "sweeps.md"
FIGURE = "detection_probability_vs_sensor_range_m.png"
START, END = "<!-- sweep-table:start (scripts/sweep_example.py) -->", "<!-- sweep-table:end -->"


def _mean(values):
    values = [v for v in values if math.isfinite(v)]
    return (sum(values) / len(values), len(values)) if values else (math.nan, 0)


def table(results_csv: Path) -> str:
    """The markdown table (between the markers) of a range × visibility sweep's results.csv."""
    with open(results_csv, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    if not rows or any(r["status"] != "done" for r in rows):
        raise SystemExit(f"sweep_example: not every task of {results_csv} is done")

    def num(r, key):
        return float(r[key]) if r[key] != "" else math.nan

    ranges = sorted({num(r, "sensor.range_m") for r in rows})
    vis = sorted({num(r, "atmosphere.visibility_m") for r in rows})
    seeds = len({r["seed_index"] for r in rows})
    targets = sorted({r["target"] for r in rows})
    lines = [f"Target: `{', '.join(targets)}` (the sweep file names none: the nearest surface at the image centre). "
             f"Means over the {seeds} seeds: detection probability / range error RMS (m) / SNR of the matched echoes "
             f"(target pixels):", "",
             "| range | " + " | ".join(f"visibility {v / 1000:g} km" for v in vis) + " |",
             "|---|" + "---|" * len(vis)]
    fa = []
    for rng in ranges:
        cells = []
        for v in vis:
            sel = [r for r in rows if num(r, "sensor.range_m") == rng and num(r, "atmosphere.visibility_m") == v]
            pd, _ = _mean([num(r, "detection_probability") for r in sel])
            rms, n_rms = _mean([num(r, "range_error_rms_m") for r in sel])
            snr, _ = _mean([num(r, "target_snr_mean") for r in sel])
            pix, _ = _mean([num(r, "target_pixels") for r in sel])
            fa.extend(num(r, "false_alarms_per_pixel") for r in sel)
            cell = f"{pd:.3f} / {rms:.3f} / {snr:.1f} ({pix:.0f} px)"
            if n_rms < len(sel):
                cell += f", {n_rms} of {len(sel)} seeds with a match"
            cells.append(cell.replace("nan", "–"))
        lines.append(f"| {rng:g} m | " + " | ".join(cells) + " |")
    mean_fa, _ = _mean(fa)
    lines += ["", f"False alarms per pixel, mean over all {len(rows)} tasks: {mean_fa:.2e}."]
    return "\n".join(lines) + "\n"


def write_doc(text: str, doc: Path = DOC) -> None:
    source = doc.read_text(encoding="utf-8")
    a, b = source.index(START) + len(START), source.index(END)
    doc.write_text(source[:a] + "\n" + text + source[b:], encoding="utf-8")


def doc_table(doc: Path = DOC) -> str:
    source = doc.read_text(encoding="utf-8")
    return source[source.index(START) + len(START):source.index(END)].lstrip("\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="a new or empty folder for the sweep and table.md")
    ap.add_argument("--workers", type=int, default=None, help="local cluster size (default: one per core)")
    ap.add_argument("--write-doc", action="store_true", help="also replace the table in docs/sweeps.md and its figure")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    sweep_dir = args.out / "range_visibility"
    cmd = [sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(BLEND), "sweep", str(SWEEP), "--out",
           str(sweep_dir)] + (["--workers", str(args.workers)] if args.workers else [])
    t0 = time.perf_counter()
    res = subprocess.run(cmd)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        return res.returncode
    text = table(sweep_dir / "results.csv")
    (args.out / "table.md").write_text(text, encoding="utf-8")
    print(text + f"\nsweep_example: {wall:.1f} s; table in {args.out / 'table.md'}")
    if args.write_doc:
        write_doc(text)
        shutil.copyfile(sweep_dir / "plots" / FIGURE, REPO / "docs" / "sweep_range_visibility.png")
        print(f"sweep_example: rewrote the table of {DOC} and docs/sweep_range_visibility.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
