"""A shell command run on a tmpfs mounted in a private mount namespace (``unshare -rm``), where this machine
allows one: the full-disk and mount-point tests' one way to get a small or separate file system without root."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest


def on_tmpfs(mount: Path, then: str, *, size: str | None = None, timeout: float = 600,
             **run_kwargs) -> subprocess.CompletedProcess:
    """Mount a tmpfs (of ``size``, e.g. ``"4m"``; the default size if None) on ``mount``, print ``MOUNTED``, then
    run the shell command ``then``; its output captured as text.  Skips the calling test where ``unshare`` is
    missing or the mount is not allowed (a container without user namespaces)."""
    options = f"-o size={size} " if size else ""
    cmd = f"mount -t tmpfs {options}tmpfs {mount} && echo MOUNTED && {then}"
    try:
        done = subprocess.run(["unshare", "-rm", "sh", "-c", cmd], capture_output=True, text=True, timeout=timeout,
                              **run_kwargs)
    except FileNotFoundError:
        pytest.skip("no unshare(1)")
    if "MOUNTED" not in done.stdout:
        pytest.skip(f"cannot mount here: {done.stderr.strip()[-200:]}")
    return done
