"""Progress is never silent for more than 2 s and shows an ETA; the terminal summary says what a run saw (issue 27).

The CLI test runs ``scripts/ladar_run.py`` on the gated sample in a fresh process and takes a timestamp of every
line as it arrives through a pipe; from the line that starts the simulation to the last one, no two lines are
more than 2 s apart (before the heartbeat: one line at 100 % after the block, then the PNG previews, 10-25 s, in
silence).  Progress lines go to stdout with the run's other messages (stderr holds errors only)."""
import io
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
MAX_GAP_S = 2.0


@pytest.mark.parametrize("elapsed, fraction, text", [(10.0, 0.25, "ETA 30 s"), (100.0, 0.5, "ETA 1 min 40 s"),
                                                      (36.0, 0.01, "ETA 59 min 24 s"),
                                                      (7300.0, 0.5, "ETA 2 h 01 min"),
                                                      (5.0, 0.0, "ETA unknown"), (5.0, 1.0, "finishing")])
def test_eta_is_linear_in_the_fraction_done(lad, elapsed, fraction, text):
    """time left = elapsed × (1 − f)/f: 10 s at 25 % → 30 s; 100 s at 50 % → 100 s; 36 s at 1 % → 3,564 s."""
    assert lad.run_inputs.format_eta(elapsed, fraction) == text


def test_heartbeat_repeats_the_last_line_until_closed(lad, monkeypatch):
    out = io.StringIO()
    lock = threading.Lock()
    stamps = []

    def emit(text, **kw):
        with lock:
            stamps.append(time.perf_counter())
            out.write(text + "\n")
        return True
    monkeypatch.setattr(lad.run_inputs, "emit", emit)
    printer = lad.run_inputs.progress_printer(heartbeat_s=0.2)
    printer(0.5, "block 1/2")
    time.sleep(1.1)
    printer.close()
    n = len(stamps)
    time.sleep(0.5)
    lines = out.getvalue().splitlines()
    assert len(stamps) == n  # closed: no more lines
    assert lines[0].startswith("ladar:  50.0% block 1/2 (") and "ETA" in lines[0]
    assert len(lines) >= 4 and all(line.startswith("ladar:  50.0% block 1/2 (") and ", ETA " in line
                                   for line in lines[1:])
    assert max(b - a for a, b in zip(stamps, stamps[1:])) < 0.2 + 0.5  # a 0.25 s poll, loaded machine margin


def test_cli_run_is_never_silent_for_more_than_2_s(tmp_path):
    cmd = [sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(REPO / "sample_blends" / "gated_board.blend"),
           "simulate", "--out", str(tmp_path / "gated"), "--no-import"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
                            cwd=tmp_path)
    lines = []
    try:
        for line in proc.stdout:
            lines.append((time.perf_counter(), line.rstrip("\n")))
        err = proc.stderr.read()
        assert proc.wait(timeout=600) == 0, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    start = next(i for i, (_, text) in enumerate(lines) if text.startswith("ladar: simulating"))
    stamps = [t for t, _ in lines[start:]]
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert max(gaps) <= MAX_GAP_S, [(round(g, 2), text) for g, (_, text) in zip(gaps, lines[start + 1:])
                                   if g > MAX_GAP_S]
    progress = [text for _, text in lines if text.startswith("ladar: ") and "%" in text]
    assert progress and all(text.endswith(("finishing)", "ETA unknown)")) or ", ETA " in text
                            for text in progress)
    summary = "\n".join(text for _, text in lines)
    # the summary: points, false alarms, SNR (none possible with the ideal receiver), gate coverage, stage times
    for head in ("echoes   1", "false    none possible: ideal receiver", "gate     ", "stages   "):
        assert head in summary, head
    assert "without loading or compiling kernels" in summary


def test_flash_demo_is_never_silent_from_process_start_to_exit(tmp_path):
    """Every gap, from the moment the process is started to the first line, between lines, and from the last line
    to the exit, is ≤ 2 s (before: 3.1 s, and 7 s on a busy machine, of silence while bpy loaded and the extension
    installed).  Timestamps are the parent's wall clock as each line arrives through the pipe, so a loaded machine
    is not excused: the start-up heartbeat's 1 s period leaves 1 s of margin for scheduling delays."""
    cmd = [sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(REPO / "sample_blends" / "flash_demo.blend"),
           "simulate", "--out", str(tmp_path / "flash")]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
                            cwd=tmp_path)
    lines = [(t0, "<process started>")]
    try:
        for line in proc.stdout:
            lines.append((time.perf_counter(), line.rstrip("\n")))
        err = proc.stderr.read()
        assert proc.wait(timeout=600) == 0, err
        lines.append((time.perf_counter(), "<process exited>"))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    gaps = [(round(b - a, 2), text) for (a, _), (b, text) in zip(lines, lines[1:])]
    assert max(g for g, _ in gaps) <= MAX_GAP_S, [(g, text) for g, text in gaps if g > MAX_GAP_S]
    texts = [text for _, text in lines]
    # each slow start-up step says what it is before it starts, in order
    steps = ["ladar: loading Blender (bpy) \u2026", "ladar: installing the extension into a temporary user folder \u2026",
             "ladar: opening flash_demo.blend \u2026"]
    assert all(s in texts for s in steps), texts[:8]
    assert [texts.index(s) for s in steps] == sorted(texts.index(s) for s in steps)
    assert texts.index(steps[-1]) < next(i for i, t in enumerate(texts) if t.startswith("ladar: simulating"))
