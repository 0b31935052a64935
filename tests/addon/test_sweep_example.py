"""The worked sweep of docs/sweeps.md is what the code produces: ``scripts/sweep_example.py`` runs the full example
(docs/examples/range_visibility.toml on the flash demo, 120 tasks on a local cluster — the full configuration, not
a reduced one: 1–2 minutes on an idle 2-core machine once the kernels are compiled, several under load) into a
temporary folder and writes its table there; the table in docs/sweeps.md must be exactly that one (same sweep
seed, same task seeds: the table does not depend on the machine or the number of workers), and the committed
page and figure must be untouched by the run (only ``--write-doc`` rewrites them)."""
from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))
import sweep_example  # noqa: E402


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_docs_worked_sweep_table_is_what_the_example_produces(tmp_path):
    doc, figure = REPO / "docs" / "sweeps.md", REPO / "docs" / "sweep_range_visibility.png"
    before = (_digest(doc), _digest(figure))
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "sweep_example.py"), str(tmp_path / "ex")],
                         capture_output=True, text=True, timeout=1800)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    produced = (tmp_path / "ex" / "table.md").read_text(encoding="utf-8")
    assert sweep_example.doc_table(doc) == produced
    assert (_digest(doc), _digest(figure)) == before  # nothing committed was rewritten
    assert "| 500 m | " in produced and "Target: `" in produced


def test_write_doc_replaces_only_the_table(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(f"before\n{sweep_example.START}\nold table\n{sweep_example.END}\nafter\n", encoding="utf-8")
    sweep_example.write_doc("| new |\n", page)
    assert page.read_text(encoding="utf-8") == (f"before\n{sweep_example.START}\n| new |\n{sweep_example.END}\n"
                                                f"after\n")
    assert sweep_example.doc_table(page) == "| new |\n"
