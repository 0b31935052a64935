"""Where a benchmark writes its JSON: the folder the user names with ``--out DIR`` (default ``runs/bench/``, which
git ignores), never over the committed figures in ``bench/results/`` unless asked with ``--update-committed``.

Every benchmark script has the same three options:

* ``--out DIR``: the folder for the JSON (created; the file name is the benchmark's, e.g. ``flash.json``);
* ``--update-committed``: regenerate the committed figures, ``bench/results/<name>.json`` (and, for the scripts
  that keep tables in the docs, those tables): the only way a benchmark writes a committed file;
* ``--quick``: small sizes, a few seconds to a minute, for the tests (tests/test_bench_quick.py); never committed.

The JSON is written to a temporary file beside it and renamed into place, so a failed run leaves no half file.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "bench" / "results"
DEFAULT_DIR = ROOT / "runs" / "bench"


def add_output_arguments(ap: argparse.ArgumentParser, quick_help: str | None = "small sizes, seconds (a smoke run "
                         "for the tests; its figures are not comparable and never committed)") -> None:
    """``--out DIR``, ``--update-committed`` and (unless ``quick_help`` is None) ``--quick``."""
    ap.add_argument("--out", type=Path, default=None, metavar="DIR",
                    help="folder for the JSON (default runs/bench/, not committed)")
    ap.add_argument("--update-committed", action="store_true",
                    help="regenerate the committed figures in bench/results/ (and the docs tables this benchmark "
                         "keeps), instead of writing to --out")
    if quick_help is not None:
        ap.add_argument("--quick", action="store_true", help=quick_help)


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def output_folder(ap: argparse.ArgumentParser, args) -> Path:
    """The folder the JSON goes to (created), after checking the options; ``ap.error`` (exit 2) on a bad one."""
    if args.update_committed:
        if args.out is not None:
            ap.error(f"--out {args.out} and --update-committed: choose one (--update-committed writes "
                     f"bench/results/)")
        if getattr(args, "quick", False):
            ap.error("--quick and --update-committed: a quick run's figures are never committed")
        return COMMITTED
    folder = DEFAULT_DIR if args.out is None else Path(args.out)
    if folder.suffix == ".json":
        ap.error(f"--out = {folder} is a file name: --out takes a folder (the JSON is named after the benchmark)")
    if _inside(folder, COMMITTED):
        ap.error(f"--out = {folder} is inside bench/results/ (the committed figures): use --update-committed to "
                 f"regenerate them, or name another folder")
    if folder.exists() and not folder.is_dir():
        ap.error(f"--out = {folder} exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def output_path(ap: argparse.ArgumentParser, args, name: str) -> Path:
    """``output_folder(ap, args) / name``."""
    return output_folder(ap, args) / name


def write_json(path: Path, report, *, indent=2, default=None) -> Path:
    """Write ``report`` as JSON to ``path`` through a temporary file renamed into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(report, indent=indent, default=default) + "\n", encoding="utf-8")
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
