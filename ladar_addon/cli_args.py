"""The ``ladar`` command line's parser: the standard library only (no bpy, no simulator), so that
``scripts/ladar_run.py`` refuses a usage error and answers ``--help`` before it starts Blender (about 1 s of CPU
less for each; ``cli.py`` parses the same command line again with it when it runs the command)."""
from __future__ import annotations

import argparse

_EPILOG = """exit codes: 0 success, 1 user error (one line on stderr naming the bad setting), 2 usage error,
130 interrupted (Ctrl-C), 143 terminated (SIGTERM), 129 hung up (SIGHUP): nothing of the run is left behind"""

_SIMULATE_EPILOG = """examples:
  blender -b scene.blend -c ladar simulate --out runs/r1 --seed 7
  blender -b scene.blend -c ladar simulate --frames 1-100 --out runs/seq --config sweep.toml
  blender -b scene.blend -c ladar simulate --frames 1-100:10 --if-exists new

One frame writes a run folder (range/intensity/energy EXR + PNG previews, points.ply/.npz, metadata.json, ...);
--frames writes a sequence folder: frame_NNNN/ run folders, points_merged.ply/.npz (world coordinates),
images/<product>_NNNN.exr image sequences and metadata.json.  Static geometry is exported once and its BVH
reused for every frame.  A run is assembled in a hidden folder and renamed into place when complete.
--overwrite replaces only a previous run of this simulator (a folder with its metadata.json); any other existing
folder is refused.  Two runs never write the same folder at once: the second one refuses, or with --if-exists
new takes the next free name.

""" + _EPILOG


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="blender -b scene.blend -c ladar", epilog=_EPILOG,
                     formatter_class=argparse.RawDescriptionHelpFormatter,
                     description="Ladar simulator: simulate the scene's ladar sensor (one frame or a frame range), "
                                 "export or check configs.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sim = sub.add_parser("simulate", help="simulate the ladar sensor (a frame or a frame range) into a run folder",
                         description="Simulate the scene's ladar sensor and write a run folder.",
                         epilog=_SIMULATE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sim.add_argument("--out", default=None, metavar="DIR",
                     help="the run folder to write (default: <Scene > Ladar > Output Folder>/<sensor>_f<frame>, "
                          "or _f<first>-<last> for --frames)")
    which = sim.add_mutually_exclusive_group()
    which.add_argument("--frame", type=int, default=None, metavar="N",
                       help="scene frame (default: the current frame)")
    which.add_argument("--frames", default=None, metavar="RANGE",
                       help='a frame range into one sequence folder: "1-100", "1-100:5" (every 5th) or "1,4,10-12"')
    sim.add_argument("--seed", type=int, default=None, metavar="N",
                     help="run seed (default: the scene's or the config's)")
    sim.add_argument("--config", default=None, metavar="FILE",
                     help="JSON or TOML settings that override the .blend's (versioned schema; for sweeps)")
    exists = sim.add_mutually_exclusive_group()
    exists.add_argument("--overwrite", action="store_true",
                        help="replace an existing run folder, if it is a previous run of this simulator (same as "
                             "--if-exists replace)")
    exists.add_argument("--if-exists", choices=("stop", "replace", "new"), default=None,
                        help="when the run folder exists: stop with an error (default), replace it, or use the "
                             "next free name (<name>_2, ...)")
    sim.add_argument("--sensor", default=None, metavar="NAME",
                     help="camera object to simulate (default: Scene > Ladar > Sensor, else the scene camera)")
    sim.add_argument("--clouds", choices=("run", "frame"), default=None,
                     help="--frames: one merged point cloud (run) or one per frame (frame) in the scene "
                          "(default: the scene's setting)")
    sim.add_argument("--no-import", action="store_true",
                     help="do not add the point cloud and images to the (unsaved) scene")
    sim.add_argument("--no-previews", action="store_true", help="do not write false-colour PNG previews")

    swp = sub.add_parser("sweep", help="run a parameter sweep (a TOML sweep file) on Dask into a sweep folder",
                         description="Export the scene once, run every point × seed × frame of the sweep file on "
                                     "Dask and write a results table and plots (docs/sweeps.md).", epilog=_EPILOG)
    swp.add_argument("file", metavar="SWEEP.toml", help="the sweep file (sweep_version = 1; axes, seeds, frames)")
    swp.add_argument("--out", required=True, metavar="DIR",
                     help="the sweep folder (re-running the same sweep into it resumes it)")
    swp.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="a running Dask scheduler, e.g. tcp://host:8786 (default: a local cluster, one worker "
                          "process per core)")
    swp.add_argument("--workers", type=int, default=None, metavar="N",
                     help="worker processes of the local cluster (default: one per core)")
    swp.add_argument("--restart", action="store_true",
                     help="discard the sweep folder's runs, table and plots and start again (needed when the "
                          "sweep file, the base settings or the scene changed)")
    swp.add_argument("--sensor", default=None, metavar="NAME", help="camera object (default: active sensor)")

    exp = sub.add_parser("export-config", help="write the sensor's settings as a JSON or TOML config file",
                         epilog=_EPILOG)
    exp.add_argument("--out", required=True, metavar="FILE", help="output file ending in .json or .toml")
    exp.add_argument("--sensor", default=None, metavar="NAME", help="camera object (default: active sensor)")
    exp.add_argument("--preset", default=None, metavar="NAME",
                     help="apply a real-sensor preset (docs/sensors.md: e.g. velodyne_vlp16, or a preset .toml "
                          "file) over the sensor's settings before writing them")
    exp.add_argument("--overwrite", action="store_true", help="replace FILE if it exists (default: refuse)")

    val = sub.add_parser("validate-config", help="check a JSON or TOML config file against the settings schema",
                         epilog=_EPILOG)
    val.add_argument("file", metavar="FILE")
    val.add_argument("--sensor", default=None, metavar="NAME",
                     help="camera whose settings the file overrides (default: the active sensor, if any)")

    sub.add_parser("warm-up", help="compile the simulator's kernels ahead (once per install and CPU), with progress",
                   epilog=_EPILOG)
    return parser
