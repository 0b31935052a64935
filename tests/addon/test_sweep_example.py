"""The worked sweep of docs/sweeps.md is what the code produces: ``scripts/sweep_example.py`` runs the full example
(docs/examples/range_visibility.toml on the flash demo, 120 tasks on a local cluster — the full configuration, not
a reduced one: 1–2 minutes on an idle 2-core machine once the kernels are compiled, several under load) into a
temporary folder and writes its table there; the table in docs/sweeps.md must be exactly that one (same sweep
seed, same task seeds: the table does not depend on the machine or the number of workers), and the committed
page and figure must be untouched by the run (only ``--write-doc`` rewrites them).

The same run is the test of the README's sweep command (``scripts/ladar_run.py sample_blends/flash_demo.blend sweep
docs/examples/range_visibility.toml --out …``, which the script runs with its output passed through) and of
``scripts/sweep_plots.py DIR`` on its folder: never silent for more than 2 s, one ETA a progress line, the plots
counted, and no committed file changed.  tests/test_documented_commands.py ran a cut-down copy of the same sweep
(2 tasks, one worker) for those checks: a Blender process, a Dask cluster and 24 plots for nothing this run does not
check on the whole sweep."""
from __future__ import annotations

import csv
import hashlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
import sweep_example  # noqa: E402

from tests.silence import timed_run  # noqa: E402


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_docs_worked_sweep_table_is_what_the_example_produces(tmp_path):
    from tests.test_bench_quick import committed_state

    git_before = committed_state() if (REPO / ".git").exists() else None
    doc, figure = REPO / "docs" / "sweeps.md", REPO / "docs" / "sweep_range_visibility.png"
    before = (_digest(doc), _digest(figure))
    res = timed_run([sys.executable, str(REPO / "scripts" / "sweep_example.py"), str(tmp_path / "ex")], cwd=REPO,
                    timeout=1800)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    produced = (tmp_path / "ex" / "table.md").read_text(encoding="utf-8")
    assert sweep_example.doc_table(doc) == produced
    assert (_digest(doc), _digest(figure)) == before  # nothing committed was rewritten
    assert "| 500 m | " in produced and "Target: `" in produced
    # the README's sweep command, as the script ran it (formerly test_readme_sweep_example_runs_quick)
    assert not res.silences(), res.silences()  # from the process's start to its exit (issue 27)
    progress = [t for _, t in res.lines if t.startswith("ladar: sweep ") and "%" in t]
    assert all(t.count("ETA") <= 1 for t in progress), progress  # one ETA a line: the sweep's, from its tasks
    assert any(re.search(r"120/120 tasks; plots \d+/\d+ \(", t) for t in progress), progress  # the plots count
    out_dir = tmp_path / "ex" / "range_visibility"
    with open(out_dir / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 120 and all(r["status"] == "done" for r in rows), rows
    # scripts/sweep_plots.py DIR draws the plots again from the table
    for png in (out_dir / "plots").glob("*.png"):
        png.unlink()
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "sweep_plots.py"), str(out_dir)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert list((out_dir / "plots").glob("*.png"))
    if git_before is not None:
        assert committed_state() == git_before  # the runs left every committed file as it was


def test_write_doc_replaces_only_the_table(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(f"before\n{sweep_example.START}\nold table\n{sweep_example.END}\nafter\n", encoding="utf-8")
    sweep_example.write_doc("| new |\n", page)
    assert page.read_text(encoding="utf-8") == (f"before\n{sweep_example.START}\n| new |\n{sweep_example.END}\n"
                                                f"after\n")
    assert sweep_example.doc_table(page) == "| new |\n"
