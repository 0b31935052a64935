"""Enabling the add-on does not load the simulator (issue 25: the fixed price of every fresh process).

Before, enabling imported ``core.run`` and with it numba, SciPy and 84 core modules (0.75 s of CPU of a 1.6 s
start-up, measured in docs/performance.md); now the operators, the panels and the ``ladar`` command import it when
a command runs the simulator.  Checked in a fresh process (this session's add-on has it loaded by other tests):
after enabling, after the operators' ``poll`` (the status bar and the Simulate button ask for the running job at
every redraw), after ``export-config`` and after a ``validate-config`` that refuses its file, none of numba, SciPy or
``<add-on>.core.run`` is imported; a ``validate-config`` that accepts its file loads numba and SciPy for its memory
check (so the check sees an import when there is one), and prints the ``ladar: loading the simulator`` line before.
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

DRIVER = r"""
import json, sys
sys.path.insert(0, SCRIPTS)
import blender_env
blender_env.isolate_user_resources()
import bpy
addon = blender_env.install_extension()
cli = addon.ladar_addon.cli
SIM = blender_env.ADDON_MODULE + ".core.run"


def loaded():
    return {"heavy": sorted(m for m in ("numba", "llvmlite", "scipy", "matplotlib", "dask", "distributed")
                            if m in sys.modules),
            "simulator": SIM in sys.modules,
            "core_modules": sum(m.startswith(blender_env.ADDON_MODULE + ".core.") for m in sys.modules)}


states = {"enabled": loaded()}
bpy.ops.wm.read_homefile()  # the default scene: a cube, a light, a camera
states["poll"] = [bpy.ops.ladar.simulate.poll(), bpy.ops.ladar.sweep.poll(), loaded()]
codes = [cli.cli_handler(["export-config", "--out", OUT + "/settings.toml"])]
states["export_config"] = loaded()
codes.append(cli.cli_handler(["validate-config", OUT + "/bad.toml"]))
states["refused"] = loaded()
sys.stdout.write("<<ACCEPT>>\n")
codes.append(cli.cli_handler(["validate-config", OUT + "/settings.toml"]))
states["accepted"] = loaded()
sys.stdout.write("<<STATES>>" + json.dumps({"codes": codes, "states": states}) + "\n")
sys.stdout.flush()
"""


def test_enabling_the_add_on_and_commands_without_a_run_do_not_load_the_simulator(tmp_path):
    (tmp_path / "bad.toml").write_text("[laser]\npulse_energy_j = -1\n")
    driver = (f"SCRIPTS = {str(REPO / 'scripts')!r}\nOUT = {str(tmp_path)!r}\n") + DRIVER
    done = subprocess.run([sys.executable, "-c", driver], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert "<<STATES>>" in done.stdout, done.stdout[-3000:] + done.stderr[-3000:]
    record = json.loads(done.stdout.split("<<STATES>>")[1].splitlines()[0])
    codes, states = record["codes"], record["states"]
    assert codes == [0, 1, 0], done.stdout[-3000:] + done.stderr[-3000:]
    nothing = {"heavy": [], "simulator": False}
    for when in ("enabled", "export_config", "refused"):
        assert {k: states[when][k] for k in nothing} == nothing, (when, states[when])
    assert states["poll"][:2] == [True, True]
    assert {k: states["poll"][2][k] for k in nothing} == nothing, states["poll"]
    # a few of core's light modules (config, errors, staging) are enough for all of that: before, 84
    assert states["refused"]["core_modules"] < 30, states
    # the accepted file's memory check needs the physics (numba and SciPy with it), and the line says so first
    assert {"numba", "scipy"} <= set(states["accepted"]["heavy"]), states["accepted"]
    assert states["accepted"]["core_modules"] > states["refused"]["core_modules"], states
    before, after = done.stdout.split("<<ACCEPT>>")
    assert "ladar: loading the simulator" not in before
    assert after.index("ladar: loading the simulator \u2026") < after.index("is valid")
    assert "ladar: error: laser.pulse_energy_j" in done.stderr


def test_a_usage_error_or_help_is_answered_before_blender_starts(tmp_path):
    """scripts/ladar_run.py parses the command line with the command's own parser (ladar_addon/cli_args.py, the
    standard library only) before it starts Blender: argparse's usage error (2) and ``--help`` (0) come without
    the 1.5 s of CPU of Blender's start and the extension's install (no ``loading Blender`` line)."""
    names = {n.module if isinstance(n, ast.ImportFrom) else a.name
             for n in ast.walk(ast.parse((REPO / "ladar_addon" / "cli_args.py").read_text(encoding="utf-8")))
             if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
    assert names <= {"__future__", "argparse"}, names
    blend = REPO / "sample_blends" / "flash_demo.blend"

    def run(*args):
        return subprocess.run([sys.executable, str(REPO / "scripts" / "ladar_run.py"), str(blend), *args],
                              capture_output=True, text=True, timeout=120, cwd=tmp_path)

    usage = run("simulate", "--frames")
    assert usage.returncode == 2 and "--frames: expected one argument" in usage.stderr, usage.stderr
    helped = run("simulate", "--help")
    assert helped.returncode == 0 and "--frames RANGE" in helped.stdout and "exit codes:" in helped.stdout
    unknown = run("bogus")
    assert unknown.returncode == 2 and "invalid choice: 'bogus'" in unknown.stderr, unknown.stderr
    for done in (usage, helped, unknown):
        assert "loading Blender" not in done.stdout + done.stderr and "Traceback" not in done.stderr
