"""scripts/compare_runs.py, the refactoring check: timing fields are left out of the comparison (a sequence's
per-frame wall times included), anything else that differs is reported."""
import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("compare_runs", REPO / "scripts" / "compare_runs.py")
compare_runs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare_runs)


def _run(folder: Path, wall, value):
    folder.mkdir()
    (folder / "sequence.json").write_text(json.dumps({
        "format": "ladar-sequence", "frame_wall_time_s": wall, "wall_time_s": sum(wall),
        "frames": [{"n_points": value, "stage_times_s": {"trace": wall[0]}}]}))
    (folder / "points.bin").write_bytes(bytes([value]))


def test_timing_fields_are_ignored_and_everything_else_is_compared(tmp_path):
    ignored = compare_runs.IGNORED_KEYS
    _run(tmp_path / "a", [0.51, 0.49], 7)
    _run(tmp_path / "b", [0.73, 0.12], 7)
    _run(tmp_path / "c", [0.51, 0.49], 8)
    assert compare_runs.compare(tmp_path / "a", tmp_path / "b", ignored) == ([], 2)
    diffs, n = compare_runs.compare(tmp_path / "a", tmp_path / "c", ignored)
    assert n == 2 and len(diffs) == 2
    assert any(d.startswith("sequence.json") and "n_points" in d for d in diffs), diffs
    assert any(d.startswith("points.bin: bytes differ") for d in diffs), diffs
