"""Command line: ``blender -b scene.blend -c ladar <command> ...`` (registered with
``bpy.utils.register_cli_command``; ``scripts/ladar_run.py`` runs the same handler through the bpy module).

Commands::

    simulate         [--out RUN_DIR] [--frame N | --frames 1-100[:STEP]] [--seed N] [--config FILE]
                     [--overwrite | --if-exists {stop,replace,new}] [--sensor NAME] [--clouds {run,frame}]
                     [--no-import] [--no-previews]
    sweep            SWEEP.toml --out DIR [--scheduler tcp://HOST:8786] [--workers N] [--restart] [--sensor NAME]
    export-config    --out FILE.json|FILE.toml [--sensor NAME] [--preset NAME] [--overwrite]
    validate-config  FILE [--sensor NAME]
    warm-up          (compile the kernels of every system ahead, with progress; no .blend file needed)

Exit codes: 0 success, 1 user error (one line on stderr, naming the bad setting), 2 command-line usage error,
130 interrupted (Ctrl-C), 143 terminated (SIGTERM, e.g. a batch scheduler or ``timeout``), 129 hung up (SIGHUP):
an interrupted run leaves nothing behind.  Output never costs a run: if the reader of stdout/stderr goes away
(``… | head -5``), the run carries on silently and is written (core.process).
"""
from __future__ import annotations

import contextlib
import json
import signal
import sys
from pathlib import Path

import bpy

from ..core.errors import ConfigError
from ..core.config.settings import SimulationConfig
from ..core.config.files import dump_config_json, dump_config_toml, load_config
from ..core.fileio.staging import release_live_claims, write_file_atomically
from ..core.process import Interrupted, deferred, emit, exit_code, interrupts_as_exceptions
from .cli_args import build_parser  # (standard library only: scripts/ladar_run.py parses with it before Blender)
from .errors import LadarError

COMMAND_ID = "ladar"


EXIT_OK, EXIT_USER_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


def _sensor(scene, name):
    from .run_inputs import active_sensor
    if name is None:
        return active_sensor(scene)
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise LadarError(f"no object named {name!r} (cameras: "
                         + ", ".join(o.name for o in bpy.data.objects if o.type == "CAMERA") + ")")
    return obj


def _write_text_atomically(path: Path, text: str, overwrite: bool = False) -> None:
    """Write ``path`` complete or not at all; an existing file is replaced only with ``overwrite`` (else
    ConfigError, even if the file appears while writing: the new file is linked into place, never over one)."""
    if not overwrite and (path.exists() or path.is_symlink()):
        raise ConfigError("out", str(path), "a file that does not exist yet (or --overwrite to replace it)")
    try:
        write_file_atomically(path, lambda f: f.write(text.encode("utf-8")), overwrite=overwrite)
    except FileExistsError:
        raise ConfigError("out", str(path), "a file that does not exist yet (it was created meanwhile; "
                                            "--overwrite to replace it)") from None


def export_config(scene, path, sensor=None, *, overwrite: bool = False, preset=None) -> Path:
    """Write the scene's settings (``config_from_blender``) to ``path`` (.json or .toml), with the real-sensor
    ``preset`` (core.presets: a name or a preset file) applied over them if given.  An existing file is replaced
    only with ``overwrite``."""
    from ..core.config.files import config_from_dict
    from .blend_config import config_from_blender

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".json", ".toml"):
        raise ConfigError("out", str(path), "a file name ending in .json or .toml")
    if path.is_dir():
        raise ConfigError("out", str(path), "a file name (a folder of that name exists)")
    if not overwrite and (path.exists() or path.is_symlink()):
        raise ConfigError("out", str(path), "a file that does not exist yet (or --overwrite to replace it)")
    cfg = config_from_blender(scene, sensor if sensor is not None else _sensor(scene, None))
    if preset is not None:
        cfg = config_from_dict({"preset": preset}, base=cfg)  # validated before anything is written
    _write_text_atomically(path, dump_config_json(cfg) + "\n" if suffix == ".json" else dump_config_toml(cfg),
                           overwrite=overwrite)
    return path


def _check_frames(frames, field: str) -> None:
    """Refuse frames Blender would clamp (``scene.frame_set`` silently moves them to its limit)."""
    prop = bpy.types.Scene.bl_rna.properties["frame_current"]
    for f in frames:
        if not prop.hard_min <= f <= prop.hard_max:
            raise ConfigError(field, f, f"a frame in [{prop.hard_min}, {prop.hard_max}] (Blender's frame range)")


#: The module whose import loads the simulator (numba, SciPy and the kernels' modules): enabling the add-on does not
#: import it (docs/performance.md, issue 25), the commands that run the simulator do (:func:`_loading_the_simulator`).
_SIMULATOR = __name__.rpartition(".")[0].rpartition(".")[0] + ".core.run"


@contextlib.contextmanager
def _loading_the_simulator():
    """Around the imports of the simulator in a command: the first time in the process (enabling the add-on
    leaves it out) a line says so before it starts and the heartbeat repeats it while it lasts (0.5 s of CPU, more
    than 2 s on a loaded machine: issue 27, start-up is never silent for more than 2 s); afterwards nothing.  Like
    Blender's start, the import is not cut in two by a signal (core.process.deferred: SIGINT, SIGTERM or SIGHUP
    meanwhile ends the command right after it; raised inside numba's or llvmlite's start-up, which calls Python
    back from C, the exception could be printed and dropped and the signal lost, issue 31)."""
    if _SIMULATOR in sys.modules:
        yield
        return
    from .run_inputs import progress_printer

    emit("ladar: loading the simulator \u2026")
    with progress_printer() as heartbeat, deferred():
        heartbeat.set(0.0, "loading the simulator")
        yield


def _cmd_simulate(scene, args) -> int:
    from ..core.fileio.run_folder import combine_figures, figure_lines, run_summary
    from .frames import parse_frames
    from .run_inputs import progress_printer

    sensor = _sensor(scene, args.sensor)
    frames = parse_frames(args.frames) if args.frames is not None else None
    _check_frames(frames or ([args.frame] if args.frame is not None else []), "frames" if frames else "frame")
    pool = None if args.no_previews else args.preview_pool
    try:
        if pool is None and not args.no_previews and "matplotlib" not in sys.modules:
            # the previews' workers load matplotlib meanwhile (a process that has drawn before draws in process)
            from ..core.fileio.preview_worker import PreviewPool
            with deferred():  # (a signal meanwhile: raised once the pool is held here, which kills it)
                pool = PreviewPool.start()
        with _loading_the_simulator():
            from .job import SimulationJob
        if_exists = "REPLACE" if args.overwrite else (args.if_exists.upper() if args.if_exists else None)
        with progress_printer() as progress:  # (its heartbeat stops with the run)
            job = SimulationJob(scene, frames=frames, frame=args.frame, out_dir=args.out, seed=args.seed,
                                config_path=args.config, if_exists=if_exists, sensor=sensor,
                                import_results=not args.no_import,
                                clouds=args.clouds.upper() if args.clouds else None,
                                previews=not args.no_previews, progress=progress, preview_pool=pool)
            args.job = job  # an interruption after the run was moved into place says so
            job.run()
    except BaseException:
        if pool is not None:
            pool.kill()
        raise
    if pool is not None:
        pool.close()
    if frames is None:
        emit(run_summary(job.run_path, job.result))
    else:
        n_points = sum(s.get("n_points", 0) for s in job.frame_stats)
        meta = json.loads((job.run_path / "metadata.json").read_text(encoding="utf-8"))
        emit(f"run      {job.run_path}\n"
             f"frames   {len(frames)} ({frames[0]} … {frames[-1]}), {n_points} points, "
             f"{meta.get('bvh_builds')} BVH build(s), {job.source.exports} geometry export(s)")
        emit("\n".join(figure_lines(combine_figures([s["figures"] for s in job.frame_stats]))))
        emit(f"time     {job.t_end - job.t_start:.2f} s")
        for w in job.warnings():
            emit("WARNING  " + w)
    return EXIT_OK


def _cmd_sweep(scene, args) -> int:
    from .run_inputs import progress_printer

    with _loading_the_simulator():
        from ..core.sweep.runner import check_workers
        from .sweep import sweep_scene

    check_workers(args.workers)  # (before the scene is exported)
    # the sweep's lines carry its own ETA, from its tasks' times (a second one from the printer's clock, which
    # counts the cluster's start, said "1/2 tasks, ETA 3 s (7.20 s, ETA 7 s)")
    with progress_printer("ladar: sweep ", every_s=30.0, eta=False) as progress:
        outcome = sweep_scene(scene, args.file, args.out, scheduler=args.scheduler, n_workers=args.workers,
                              restart=args.restart, sensor=_sensor(scene, args.sensor), progress=progress)
    emit(outcome.summary())
    return EXIT_OK if outcome.n_failed == 0 else EXIT_USER_ERROR


def _cmd_export_config(scene, args) -> int:
    path = export_config(scene, args.out, _sensor(scene, args.sensor), overwrite=args.overwrite,
                         preset=args.preset)
    emit(f"ladar: wrote {path}")
    return 0


def _cmd_validate_config(scene, args) -> int:
    """What ``simulate`` would refuse before running: the settings, the material names the file overrides (the
    scene's exported materials) and the run's memory and work (core.engine.memory, without the memory free now)."""
    from .export import scene_geometry_from_depsgraph
    from .run_inputs import build_config

    sensor = None
    if args.sensor is not None or (scene is not None and (scene.ladar.sensor or scene.camera) is not None):
        sensor = _sensor(scene, args.sensor)
        cfg, blend_materials = build_config(scene, sensor, config_path=args.file)  # as simulate builds it
    else:
        cfg, blend_materials = load_config(args.file, base=SimulationConfig()), {}
    changed = {n: b for n, b in cfg.materials.items() if blend_materials.get(n) != b}
    if changed and scene is not None:  # simulate matches these by name against the exported scene
        scene_geometry_from_depsgraph(bpy.context.evaluated_depsgraph_get(),
                                      exclude={sensor.name} if sensor is not None else ()).with_overrides(changed)
    with _loading_the_simulator():  # (after the settings are checked: a refused file never loads it)
        from ..core.engine.memory import check_memory
    check_memory(cfg, available=None)
    emit(f"ladar: {args.file} is valid")
    return 0


def _cmd_warm_up(scene, args) -> int:
    """Compile (or load) every system's kernels on a tiny built-in scene (core/warmup.py); writes nothing.  A
    line per case when it is done, and while one compiles (10-40 s the first time) the heartbeat's line every
    second: the case, the time so far and the ETA (issue 27: never silent for more than 2 s)."""
    from .run_inputs import progress_printer

    with _loading_the_simulator():
        from ..core.warmup import cases, warm_up
    names = [name for name, _ in cases()]
    n = len(names)

    def running(i):
        return f"[{i + 1}/{n}] {names[i]}" if i < n else "done"

    emit("ladar: compiling the kernels of every sensor system (once per install and CPU; later runs load them)")
    with progress_printer("ladar: warm-up ") as printer:
        printer.set(0.0, running(0))
        k = warm_up(progress=printer.say, fraction=lambda f: printer.set(f, running(round(f * n))))
    emit(f"ladar: kernels ready: {k['compiled']} compiled, {k['loaded']} loaded from the cache "
         f"({k['load_and_compile_s']:.1f} s)")
    return 0


COMMANDS = {"simulate": _cmd_simulate, "sweep": _cmd_sweep, "export-config": _cmd_export_config,
            "validate-config": _cmd_validate_config, "warm-up": _cmd_warm_up}


def cli_handler(argv, preview_pool=None) -> int:
    """Entry point of ``blender -c ladar``: returns the exit code (never exits the process).

    SIGINT, SIGTERM and SIGHUP end the command like Ctrl-C (core.process): the run's staging folder is removed
    and the exit code is 128 + the signal.  ``preview_pool``: the previews' workers the caller started early
    (``scripts/ladar_run.py``, core.fileio.preview_worker); ``simulate`` uses and ends them (without it,
    ``simulate`` starts its own)."""
    from ..core.errors import Cancelled

    parser = build_parser()
    try:
        args = parser.parse_args(list(argv))
    except SystemExit as exc:  # usage errors (2) and --help (0)
        return exc.code if isinstance(exc.code, int) else (EXIT_OK if exc.code is None else EXIT_USAGE)
    args.preview_pool = preview_pool
    scene = bpy.context.scene
    with interrupts_as_exceptions():
        try:
            return COMMANDS[args.command](scene, args)
        except (ConfigError, LadarError) as exc:
            emit(f"ladar: error: {exc}", err=True)
            return EXIT_USER_ERROR
        except OSError as exc:  # a full disk, a vanished folder, a permission changed, in any writer
            job = getattr(args, "job", None)
            nothing = (args.command == "simulate" and not (job is not None and job.claim is not None
                                                           and job.claim.committed))
            emit(f"ladar: error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": ")
                 + ("; nothing of the run was written" if nothing else ""), err=True)
            return EXIT_USER_ERROR
        except (KeyboardInterrupt, Cancelled) as exc:
            how = f" ({exc.signal_name})" if isinstance(exc, Interrupted) and exc.signum != signal.SIGINT else ""
            job = getattr(args, "job", None)
            if args.command == "sweep":
                emit(f"ladar: interrupted{how}: the finished points are kept in {args.out}; the same command "
                     f"resumes the sweep", err=True)
            elif job is not None and job.claim is not None and job.claim.committed:
                emit(f"ladar: interrupted{how} after the run was written to {job.run_path}", err=True)
            else:
                emit(f"ladar: interrupted{how}: nothing of the run was written", err=True)
            return exit_code(exc) if isinstance(exc, KeyboardInterrupt) else EXIT_INTERRUPTED
        finally:
            # a claim still held here was taken when the signal came (before its holder's clean-up could start)
            release_live_claims()


def register():
    """Register the ``ladar`` command; returns the handle for :func:`unregister`."""
    if not hasattr(bpy.utils, "register_cli_command"):  # pragma: no cover - Blender < 4.2
        return None
    return bpy.utils.register_cli_command(COMMAND_ID, cli_handler)


def unregister(handle) -> None:
    if handle is not None:
        bpy.utils.unregister_cli_command(handle)
