"""An ideal flash frame imports only what it uses (issue 25: "imports load only what the command uses").

In a fresh process, ``core.run`` is imported and one ideal-receiver flash frame and one profiler frame are
simulated through ``core.run.simulate``, as the README's flash demo and profiler examples do (their commands import
the same core modules through ``ladar_addon.job``).  None of the modules deferred for start-up may be loaded by
then: SciPy's FFT (speckle, phase screens, scintillation), the receiver chain and its samplers and tables, the
noisy detection, the scanner and gated systems, and the libraries no frame uses (SciPy's stats, optimize,
integrate, signal, ndimage, interpolate; Dask; matplotlib, which only the previews import).  The same process then
asks for the scanner and for the noisy receiver (``load_noisy_receiver``) and must see those modules appear, so
the check sees an import when there is one.  A regression (a module-level import put back) fails this test.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

#: deferred for start-up: loaded only by the runs that use them
DEFERRED = ("scipy.fft", "core.physics.receiver.chain", "core.physics.receiver.table_route",
            "core.physics.receiver.samplers", "core.physics.receiver.code_tables", "core.physics.receiver.speckle",
            "core.physics.receiver.geiger", "core.physics.receiver.adc", "core.physics.detection.noisy",
            "core.physics.detection.stretches", "core.physics.detection.false_alarms",
            "core.physics.detection.row_statistics", "core.physics.detection.matched_filter",
            "core.systems.scanner", "core.systems.gated", "core.systems.scan_patterns", "core.systems.returns",
            "core.physics.pulse_table")
#: never needed by a frame
UNUSED = ("scipy.stats", "scipy.optimize", "scipy.integrate", "scipy.signal", "scipy.ndimage", "scipy.interpolate",
          "dask", "distributed", "matplotlib")

DRIVER = r"""
import json, sys
import numpy as np
from core.config.settings import BRDFSettings, SimulationConfig
from core.geometry.scene import SceneGeometry
from core.run import SYSTEMS, simulate

C = 299_792_458.0
h, d = 3.0, 150.0  # a 6 m plate 150 m ahead (the sensor looks along -Z)
verts = np.array([[-h, -h, -d], [h, -h, -d], [h, h, -d], [-h, h, -d]])
scene = SceneGeometry(verts, [[0, 1, 2], [0, 2, 3]], [0, 0], [BRDFSettings()], ["plate"])
points = {}
for system in ("flash", "profiler"):
    cfg = SimulationConfig()
    cfg.system_type = system
    cfg.detector.mode = "ideal"
    if system == "flash":
        cfg.receiver.width_px = cfg.receiver.height_px = 16
    cfg.receiver.subsamples = 2
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = 0.01
    cfg.gate.n_bins, cfg.gate.bin_width_s = 256, 1e-9
    cfg.gate.gate_start_s = 2 * d / C - 64e-9
    cfg.run.threads = 1
    result = simulate(scene, np.eye(4), cfg)
    points[system] = int(len(result.points["range_m"]))
deferred, unused = DEFERRED, UNUSED
frame = {"deferred": sorted(m for m in deferred if m in sys.modules),
         "unused": sorted(m for m in unused if m in sys.modules), "points": points}
SYSTEMS["scanner"]
from core.engine.products import load_noisy_receiver
load_noisy_receiver()
after = sorted(m for m in deferred if m in sys.modules)
sys.stdout.write("<<IMPORTS>>" + json.dumps({"frame": frame, "after": after}) + "\n")
"""


def test_an_ideal_flash_or_profiler_frame_loads_no_deferred_module():
    code = f"DEFERRED = {DEFERRED!r}\nUNUSED = {UNUSED!r}\n" + DRIVER
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900, cwd=REPO)
    assert "<<IMPORTS>>" in done.stdout, done.stdout[-3000:] + done.stderr[-3000:]
    record = json.loads(done.stdout.split("<<IMPORTS>>")[1].splitlines()[0])
    frame = record["frame"]
    # the frames ran: every pixel of the 16x16 flash and the profiler's one element see the plate
    assert frame["points"] == {"flash": 256, "profiler": 1}, frame
    assert frame["deferred"] == [], frame
    assert frame["unused"] == [], frame
    # the check sees an import when there is one: the scanner and the noisy receiver load them
    expected = {"core.systems.scanner", "core.systems.scan_patterns", "core.systems.returns",
                "core.physics.pulse_table", "core.physics.receiver.chain", "core.physics.detection.noisy",
                "core.physics.detection.stretches", "core.physics.detection.false_alarms",
                "core.physics.receiver.table_route", "core.physics.receiver.speckle"}
    assert expected <= set(record["after"]), record["after"]
    assert "scipy.fft" not in record["after"]  # (speckle's FFT still waits for its first call)
