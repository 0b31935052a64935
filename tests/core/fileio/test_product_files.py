"""The scanner's saved waveforms filled in place in the run folder's ``waveforms.npy`` (core.fileio.run_folder
ProductFiles, issue 25: the README scanner example's 267 MB were built in memory, then copied out by ``np.save``).
The file must be the very bytes ``np.save`` of the in-memory result writes, on every route; a full disk is an
OSError naming the file before anything is filled, and leaves nothing."""
import errno
import io
import os

import numpy as np
import pytest

from core.config.settings import SimulationConfig
from core.fileio import run_folder
from core.fileio.run_folder import ProductFiles, write_run_files
from core.run import run_simulation, simulate
from scenes import plate
from tests.small_disk import on_tmpfs


def scan_config():
    """A small raster scan of a tilted plate (pulses with echoes spread over the gate) that saves waveforms."""
    cfg = SimulationConfig(system_type="scanner")
    cfg.scanner.pattern = "raster"
    cfg.scanner.n_lines = 6
    cfg.scanner.scan_rate_hz = 100.0
    cfg.scanner.pulse_rate_hz = 3000.0
    cfg.scanner.scan_width_rad = 0.3
    cfg.scanner.scan_height_rad = 0.2
    cfg.laser.beam_divergence_rad = 1e-3
    cfg.laser.pulse_fwhm_s = 2e-9
    cfg.gate.gate_start_s = 0.0
    cfg.gate.bin_width_s = 0.25e-9
    cfg.gate.n_bins = 1024  # 0 … 38.4 m
    cfg.run.save_waveforms = True
    cfg.run.threads = 2
    return cfg


SCENE = plate(25.0, 2.5, tilt_rad=0.5)  # narrower than the scan: pulses without an echo too


def npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(arr))
    return buf.getvalue()


def test_waveforms_filled_in_place_are_the_bytes_np_save_writes(tmp_path):
    reference = simulate(SCENE, np.eye(4), scan_config())  # in memory, as before (no run folder)
    assert type(reference.waveforms) is np.ndarray
    n_pulses = 6 * 30
    assert reference.waveforms.shape == (n_pulses, 1024)
    # pulses with and without echoes, spread over many bins: a test that can see a shifted or dropped row
    rows_with_energy = np.count_nonzero(reference.waveforms.sum(axis=1) > 0)
    assert 0 < rows_with_energy < n_pulses
    assert np.count_nonzero(reference.waveforms.any(axis=0)) > 50

    def no_copy(*args, **kwargs):
        raise AssertionError("np.save called: the waveforms were copied out, not filled in place")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(np, "save", no_copy)  # (a scanner run saves nothing else with np.save)
        path, result = run_simulation(SCENE, np.eye(4), scan_config(), tmp_path / "run")
    assert isinstance(result.waveforms, np.memmap)  # filled in the file (POSIX)
    assert os.path.basename(result.waveforms.filename) == "waveforms.npy"  # (in the staging folder, renamed since)
    assert (path / "waveforms.npy").read_bytes() == npy_bytes(reference.waveforms)
    assert np.array_equal(np.load(path / "waveforms.npy"), reference.waveforms)
    assert "waveforms.npy" in __import__("json").loads((path / "metadata.json").read_text())["files"]
    # nothing else of the run folder moved: the points as in memory
    with np.load(path / "points.npz") as npz:
        for k, v in reference.points.items():
            assert np.array_equal(npz[k], v, equal_nan=True), k


def test_without_posix_fallocate_the_waveforms_are_built_in_memory_and_saved(tmp_path, monkeypatch):
    monkeypatch.delattr(os, "posix_fallocate")
    path, result = run_simulation(SCENE, np.eye(4), scan_config(), tmp_path / "run")
    assert type(result.waveforms) is np.ndarray
    assert (path / "waveforms.npy").read_bytes() == npy_bytes(result.waveforms)


def test_a_full_disk_is_an_error_naming_waveforms_npy_before_the_scan_and_leaves_nothing(tmp_path, monkeypatch):
    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError) as err:
        run_simulation(SCENE, np.eye(4), scan_config(), tmp_path / "run")
    assert err.value.errno == errno.ENOSPC
    assert os.path.basename(err.value.filename) == "waveforms.npy"
    assert list(tmp_path.iterdir()) == []  # no run folder, no staging folder


def test_product_files_zeros(tmp_path):
    assert type(ProductFiles().zeros("w.npy", (3, 4), np.float32)) is np.ndarray
    arr = ProductFiles(tmp_path / "f").zeros("w.npy", (3, 4), np.float32)
    assert isinstance(arr, np.memmap) and arr.shape == (3, 4) and arr.dtype == np.float32 and not arr.any()
    # the blocks are reserved (no sparse file that a full disk could turn into a SIGBUS while filling)
    st = os.stat(tmp_path / "f" / "w.npy")
    assert st.st_size == arr.offset + 48 and st.st_blocks * 512 >= st.st_size
    arr[1] = [1, 2, 3, 4]
    assert (tmp_path / "f" / "w.npy").read_bytes() == npy_bytes(arr)


def test_write_run_files_still_refuses_an_existing_folder_it_did_not_map_into(tmp_path):
    """The folder may exist only when ProductFiles made it for its arrays."""
    (tmp_path / "w").mkdir()
    result = simulate(SCENE, np.eye(4), scan_config())
    with pytest.raises(FileExistsError):
        write_run_files(tmp_path / "w", result, {"format": "ladar-run"})
    # an in-memory array of the same name is written, not mistaken for a mapped one
    assert not run_folder._mapped_onto(result.waveforms, tmp_path / "x" / "waveforms.npy")


def test_a_sequence_fills_each_frames_waveforms_in_place(tmp_path, monkeypatch):
    from core.sequence import run_sequence

    save = np.save
    monkeypatch.setattr(np, "save", lambda path, *a, **k: (_ for _ in ()).throw(AssertionError(path))
                        if str(path).endswith("waveforms.npy") else save(path, *a, **k))
    path, _ = run_sequence([1, 2], lambda f: SCENE, lambda f: np.eye(4), scan_config(), tmp_path / "seq")
    monkeypatch.undo()
    for f in (1, 2):
        reference = simulate(SCENE, np.eye(4), scan_config(), frame=f)
        assert (path / f"frame_{f:04d}" / "waveforms.npy").read_bytes() == npy_bytes(reference.waveforms)


_SCAN_ON_A_SMALL_DISK = """
import errno, json, os, sys
sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[1] + "/tests/core"); sys.path.insert(0, sys.argv[1] + "/tests/core/fileio")
from pathlib import Path
import numpy as np
from core.run import run_simulation
from test_product_files import SCENE, scan_config
disk = Path(sys.argv[2])
cfg = scan_config()
cfg.gate.n_bins = 8192  # 180 pulses x 8192 bins x 4 B = 5.9 MB of waveforms on a 4 MB disk
try:
    run_simulation(SCENE, np.eye(4), cfg, disk / "run")
    out = ["written"]
except OSError as exc:
    out = ["OSError", exc.errno, os.path.basename(exc.filename or "")]
print("RESULT " + json.dumps(out + [sorted(p.name for p in disk.iterdir())]), flush=True)
"""


@pytest.mark.skipif(not hasattr(os, "posix_fallocate"), reason="posix_fallocate")
def test_waveforms_larger_than_a_real_small_disk_are_one_oserror_not_a_sigbus(tmp_path):
    """On a 4 MB tmpfs (a private mount namespace, where allowed) the 5.9 MB of mapped waveforms: the blocks'
    reservation fails with ENOSPC naming waveforms.npy before the scan fills anything (a sparse mapping would
    end the process with SIGBUS), and the disk holds nothing of the run."""
    import json
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[3]
    disk = tmp_path / "disk"
    disk.mkdir()
    script = tmp_path / "scan_on_a_small_disk.py"
    script.write_text(_SCAN_ON_A_SMALL_DISK)
    done = on_tmpfs(disk, f"exec {sys.executable} {script} {repo} {disk}", size="4m")
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])  # (a SIGBUS would be -7)
    line = next((x for x in done.stdout.splitlines() if x.startswith("RESULT ")), None)
    assert line, done.stdout[-2000:] + done.stderr[-2000:]
    assert json.loads(line[len("RESULT "):]) == ["OSError", errno.ENOSPC, "waveforms.npy", []]
