"""Command line: ``blender -b scene.blend -c ladar <command> ...`` (registered with
``bpy.utils.register_cli_command``; ``scripts/ladar_run.py`` runs the same handler through the bpy module).

Commands::

    simulate         --out RUN_DIR [--frame N] [--seed N] [--config FILE] [--overwrite] [--sensor NAME]
                     [--no-import]
    export-config    --out FILE.json|FILE.toml [--sensor NAME]
    validate-config  FILE [--sensor NAME]

Exit codes: 0 success, 1 user error (one line on stderr, naming the bad setting), 2 command-line usage error.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import bpy

from ..core.config import ConfigError, SimulationConfig, dump_config_json, dump_config_toml, load_config
from .errors import LadarError

COMMAND_ID = "ladar"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="blender -b scene.blend -c ladar",
                     description="Ladar simulator: simulate the scene's ladar sensor, export or check configs.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sim = sub.add_parser("simulate", help="simulate one frame of the ladar sensor and write a run folder")
    sim.add_argument("--out", required=True, metavar="DIR",
                     help="the run folder to write (must not exist unless --overwrite)")
    sim.add_argument("--frame", type=int, default=None, help="scene frame (default: the current frame)")
    sim.add_argument("--seed", type=int, default=None, help="run seed (default: the scene's or the config's)")
    sim.add_argument("--config", default=None, metavar="FILE",
                     help="JSON or TOML settings that override the .blend's")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    sim.add_argument("--sensor", default=None, metavar="NAME",
                     help="camera object to simulate (default: Scene > Ladar > Sensor, else the scene camera)")
    sim.add_argument("--no-import", action="store_true",
                     help="do not add the point cloud and images to the (unsaved) scene")

    exp = sub.add_parser("export-config", help="write the sensor's settings as a JSON or TOML config file")
    exp.add_argument("--out", required=True, metavar="FILE", help="output file ending in .json or .toml")
    exp.add_argument("--sensor", default=None, metavar="NAME", help="camera object (default: active sensor)")

    val = sub.add_parser("validate-config", help="check a JSON or TOML config file against the settings schema")
    val.add_argument("file", metavar="FILE")
    val.add_argument("--sensor", default=None, metavar="NAME",
                     help="camera whose settings the file overrides (default: the active sensor, if any)")
    return parser


def _sensor(scene, name):
    from .simulate import active_sensor
    if name is None:
        return active_sensor(scene)
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise LadarError(f"no object named {name!r} (cameras: "
                         + ", ".join(o.name for o in bpy.data.objects if o.type == "CAMERA") + ")")
    return obj


def _write_text_atomically(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def export_config(scene, path, sensor=None) -> Path:
    """Write the scene's settings (``config_from_blender``) to ``path`` (.json or .toml)."""
    from .properties import config_from_blender

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".toml"):
        raise ConfigError("out", str(path), "a file name ending in .json or .toml")
    cfg = config_from_blender(scene, sensor if sensor is not None else _sensor(scene, None))
    _write_text_atomically(path, dump_config_json(cfg) + "\n" if suffix == ".json" else dump_config_toml(cfg))
    return path


def _cmd_simulate(scene, args) -> int:
    from .simulate import simulate_scene

    sensor = _sensor(scene, args.sensor)
    run_path, result = simulate_scene(scene, out_dir=args.out, frame=args.frame, seed=args.seed,
                                      config_path=args.config, overwrite=args.overwrite, sensor=sensor,
                                      import_results=not args.no_import)
    from ..core.runio import run_summary

    print(run_summary(run_path, result), flush=True)
    return 0


def _cmd_export_config(scene, args) -> int:
    path = export_config(scene, args.out, _sensor(scene, args.sensor))
    print(f"ladar: wrote {path}", flush=True)
    return 0


def _cmd_validate_config(scene, args) -> int:
    from .properties import config_from_blender

    base = None
    if args.sensor is not None or (scene is not None and (scene.ladar.sensor or scene.camera) is not None):
        base = config_from_blender(scene, _sensor(scene, args.sensor))
    load_config(args.file, base=base if base is not None else SimulationConfig())
    print(f"ladar: {args.file} is valid", flush=True)
    return 0


COMMANDS = {"simulate": _cmd_simulate, "export-config": _cmd_export_config,
            "validate-config": _cmd_validate_config}


def cli_handler(argv) -> int:
    """Entry point of ``blender -c ladar``: returns the exit code (never exits the process)."""
    parser = build_parser()
    try:
        args = parser.parse_args(list(argv))
    except SystemExit as exc:  # usage errors (2) and --help (0)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    scene = bpy.context.scene
    try:
        return COMMANDS[args.command](scene, args)
    except (ConfigError, LadarError) as exc:
        print(f"ladar: error: {exc}", file=sys.stderr, flush=True)
        return 1
    except OSError as exc:
        print(f"ladar: error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), file=sys.stderr,
              flush=True)
        return 1


def register():
    """Register the ``ladar`` command; returns the handle for :func:`unregister`."""
    if not hasattr(bpy.utils, "register_cli_command"):  # pragma: no cover - Blender < 4.2
        return None
    return bpy.utils.register_cli_command(COMMAND_ID, cli_handler)


def unregister(handle) -> None:
    if handle is not None:
        bpy.utils.unregister_cli_command(handle)
