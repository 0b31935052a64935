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


def test_nan_in_json_is_the_same_as_nan_and_differs_from_a_number(tmp_path):
    """A statistic of no values is NaN in both runs (a sweep row's): the same result, not a difference (before:
    NaN != NaN was reported); NaN against a number is still a difference."""
    for name, value in (("a", float("nan")), ("b", float("nan")), ("c", 0.5)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metadata.json").write_text(json.dumps({"sweep": {"row": {"snr": value}}}))
    assert compare_runs.compare(tmp_path / "a", tmp_path / "b", compare_runs.IGNORED_KEYS) == ([], 1)
    diffs, _ = compare_runs.compare(tmp_path / "a", tmp_path / "c", compare_runs.IGNORED_KEYS)
    assert len(diffs) == 1 and "sweep.row.snr" in diffs[0], diffs


def _png(path: Path, pixels, **text):
    """``pixels`` as a PNG at ``path``: Pillow's own encoder (its filters, zlib level 6) unless ``level`` is given
    in ``text`` (then zlib at that level, no filters: other bytes for the same picture)."""
    import numpy as np
    from PIL import Image, PngImagePlugin

    level = text.pop("level", None)
    info = PngImagePlugin.PngInfo()
    for key, value in text.items():
        info.add_text(key, value)
    kwargs = {} if level is None else {"compress_level": level}
    Image.fromarray(np.asarray(pixels, dtype=np.uint8), "RGBA").save(path, pnginfo=info, dpi=(100, 100), **kwargs)


def test_pngs_are_compared_as_pictures_not_bytes(tmp_path):
    """The same picture compressed otherwise is the same result; one pixel's one channel changed by one, or a
    text chunk changed, is reported (issue 25: the previews' PNG encoding changed, their pixels did not)."""
    import numpy as np

    rng = np.random.default_rng(5)
    pixels = rng.integers(0, 256, (30, 40, 4), dtype=np.uint8)
    pixels[:, :20] = (12, 34, 56, 255)  # a flat half: the encoders' filters and levels give other bytes
    for name in "abcd":
        (tmp_path / name).mkdir()
    _png(tmp_path / "a" / "range.png", pixels, Title="Range", Description="x: pixel column")
    _png(tmp_path / "b" / "range.png", pixels, Title="Range", Description="x: pixel column", level=1)
    assert (tmp_path / "a" / "range.png").read_bytes() != (tmp_path / "b" / "range.png").read_bytes()
    assert compare_runs.compare(tmp_path / "a", tmp_path / "b", compare_runs.IGNORED_KEYS) == ([], 1)

    changed = pixels.copy()
    changed[17, 3, 1] += 1
    _png(tmp_path / "c" / "range.png", changed, Title="Range", Description="x: pixel column", level=1)
    diffs, _ = compare_runs.compare(tmp_path / "a", tmp_path / "c", compare_runs.IGNORED_KEYS)
    assert diffs == ["range.png: pixels differ (1 of 1200)"], diffs

    _png(tmp_path / "d" / "range.png", pixels, Title="Range – slice 2", Description="x: pixel column")
    diffs, _ = compare_runs.compare(tmp_path / "a", tmp_path / "d", compare_runs.IGNORED_KEYS)
    assert diffs == ["range.png: text chunks differ (Title)"], diffs
