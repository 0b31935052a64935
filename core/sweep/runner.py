"""Run a sweep on Dask: the client side (docs/sweeps.md).

:func:`run_sweep` checks everything first (the sweep file, every point's settings, the sweep folder), then

1. writes the sweep folder: ``sweep.json`` (what defines the results: the normalised sweep, the base settings,
   the scene digest — its *fingerprint*), a copy of the sweep file and the exported scene (``scene/``);
2. connects to Dask — a ``LocalCluster`` of worker processes sized to the cores, or the scheduler at
   ``scheduler`` — and makes the core importable there: the core's source is staged as a package named
   ``ladar_core_<hash of its files>`` (a new name whenever the code changes, so a long-lived cluster never runs
   stale code) which a local cluster's workers inherit and a remote cluster receives through
   ``distributed``'s ``UploadDirectory`` plugin (workers need the pinned packages of requirements-worker.txt,
   nothing else: no Blender, no copy of this repository);
3. submits every task (point × seed × frame) whose run folder is not already there, records each as it
   completes (a failure in ``failed/<task>.json``, the others go on) and reports progress (done/total, ETA);
4. writes ``results.csv`` (one row per task) and ``plots/<figure>_vs_<axis>.png``.

Re-running the same sweep into the same folder resumes it: finished tasks are read back from their run folders,
failed and missing ones run again.  A sweep folder whose fingerprint differs (a changed sweep file, base settings
or scene) is refused unless ``restart`` is asked, which discards its runs and starts again.  Each task's seed
derives from the sweep seed and its point and seed index (``spec.task_seed``), so the results do not depend on
the number of workers or the order the tasks ran in.
"""
from __future__ import annotations

import csv
import hashlib
import importlib
import io
import json
import math
import os
import pickle
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config.files import config_to_dict
from ..config.settings import SimulationConfig
from ..errors import Cancelled, ConfigError
from ..fileio.preview import sweep_plot_png
from ..fileio.run_folder import software_versions
from ..fileio.staging import remove_abandoned_staging, write_file_atomically
from ..geometry.motion import split_pose
from ..geometry.trace import SceneTracer
from ..version import __version__
from .scene import SweepScene, boresight_point, json_default, write_json_atomically
from .spec import RANGE_AXIS, SweepSpec, base_config, load_sweep, point_configs, task_seeds
from .shipping import ship_core, shipped_call, stage_core
from .task import FIGURES, finished_row

SWEEP_FORMAT = "ladar-sweep"
SWEEP_FORMAT_VERSION = 1
#: Sub-folders and files of a sweep folder that ``restart`` discards (never anything else).
OWNED = ("runs", "failed", "scene", "plots", "results.csv", "sweep.json", "sweep_file.toml", "sweep_file.json")


@dataclass
class SweepOutcome:
    path: Path                      # the sweep folder
    rows: list                      # one dict per task (results.csv), in task order
    n_tasks: int = 0
    n_done: int = 0
    n_failed: int = 0
    n_run: int = 0                  # tasks run by this call
    n_resumed: int = 0              # tasks found finished in the folder (not run again)
    wall_time_s: float = 0.0
    n_workers: int = 0
    plots: list = field(default_factory=list)
    target: dict = field(default_factory=dict)   # sweep_target: the material the figures measure, and why

    def summary(self) -> str:
        return (f"sweep    {self.path}\n"
                f"tasks    {self.n_done}/{self.n_tasks} done, {self.n_failed} failed; {self.n_run} run now on "
                f"{self.n_workers} worker(s), {self.n_resumed} finished before; {self.wall_time_s:.1f} s\n"
                + (f"target   {self.target.get('material')!r} ({self.target.get('chosen')})\n" if self.target else "")
                + f"table    {self.path / 'results.csv'}" + (f"\nplots    {len(self.plots)} in {self.path / 'plots'}"
                                                               if self.plots else ""))


@dataclass
class SweepPlan:
    """Everything checked and derived before anything is written."""
    spec: SweepSpec
    scene: SweepScene
    base: SimulationConfig
    tasks: list
    fingerprint: str
    manifest: dict
    out_dir: Path | None = None     # the sweep folder the tasks' run folders were named in (resolved)


# --------------------------------------------------------------------------------------------------------------
# Planning: every point validated, every task named and seeded
# --------------------------------------------------------------------------------------------------------------
def plan_sweep(spec: SweepSpec, scene: SweepScene, base: SimulationConfig | None = None,
               out_dir=None) -> SweepPlan:
    """Validate every point's settings and build the task list (writes nothing).  Raises ConfigError."""
    base = base_config(spec, base)
    scene = scene.with_overrides(base.materials)
    frames = spec.frames if spec.frames is not None else [scene.frames[0]]
    for f in frames:
        scene.frame_index(f)  # a frame the scene was exported for
    configs = point_configs(spec, base, scene.material_brdfs())
    targets = {}
    if RANGE_AXIS in spec.axis_names:
        targets = {f: boresight_point(scene, f).tolist() for f in frames}
    target = sweep_target(spec, scene, frames[0])
    wp = max(4, len(str(len(configs) - 1)))
    ws = max(2, len(str(spec.seeds - 1)))
    tasks = []
    out = Path(out_dir).resolve() if out_dir is not None else Path("sweep")
    runs = str(out / "runs") + os.sep
    seed_indices = np.arange(spec.seeds)
    for p, (values, cfg, range_m) in enumerate(configs):
        cfg_dict = config_to_dict(cfg)
        seeds = task_seeds(spec.seed, np.full(spec.seeds, p), seed_indices).tolist()
        for s in range(spec.seeds):
            seed = seeds[s]
            for f in frames:
                name = f"p{p:0{wp}d}-s{s:0{ws}d}" + (f"-f{f:04d}" if len(frames) > 1 else "")
                tasks.append({"name": name, "point": p, "seed_index": s, "seed": seed, "frame": f,
                              "values": values, "config": cfg_dict, "range_m": range_m,
                              "target_m": targets.get(f), "target": target["material"], "out": runs + name})
    normal = spec.normalized()
    normal["frames"] = frames
    fp_data = {"spec": normal, "base": config_to_dict(base), "scene": scene.digest()}
    fingerprint = hashlib.sha256(json.dumps(fp_data, sort_keys=True, default=str).encode()).hexdigest()
    manifest = {"format": SWEEP_FORMAT, "format_version": SWEEP_FORMAT_VERSION, "fingerprint": fingerprint,
                "sweep": normal, "base_settings": fp_data["base"], "scene_digest": fp_data["scene"],
                "source": spec.source, "n_points": len(configs), "n_tasks": len(tasks),
                "axes": spec.axis_names, "figures": list(FIGURES), "target": target,
                "simulator_version": __version__,
                "software": software_versions(), "created_unix_s": time.time(),
                "tasks": [{k: t[k] for k in ("name", "point", "seed_index", "seed", "frame", "values")}
                          for t in tasks]}
    return SweepPlan(spec, scene, base, tasks, fingerprint, manifest, out)


def sweep_target(spec: SweepSpec, scene: SweepScene, frame: int) -> dict:
    """The surface whose detection the figures measure: ``{"material": name or None, "chosen": how}`` — the sweep
    file's ``target`` (a material of the scene), else the material of the nearest surface at the image centre (the
    centre ray's first hit) at the base pose of the sweep's first frame.  Raises ConfigError for an unknown name."""
    names = sorted(set().union(*(g.material_names for g in scene.geometries)))
    if spec.target is not None:
        if spec.target not in names:
            raise ConfigError("target", spec.target, "the name of a material in the scene: " + ", ".join(names))
        return {"material": spec.target, "chosen": "the sweep file's target"}
    origin, rot = split_pose(scene.poses[scene.frame_index(frame)])
    geometry = scene.geometry(frame)
    prim, _, _ = SceneTracer(geometry).intersect(origin, (rot @ np.array([0.0, 0.0, -1.0]))[None])
    if prim[0] < 0:
        return {"material": None, "chosen": "default: nothing at the image centre (no target: its figures are empty)"}
    return {"material": geometry.material_names[int(geometry.material_ids[prim[0]])],
            "chosen": f"default: the nearest surface at the image centre at frame {frame}"}


def manifest_text(manifest: dict) -> str:
    """``sweep.json``: indented JSON, with one line per task (JSON's C encoder: 10⁵ tasks in well under a second,
    against seconds for the indenting encoder)."""
    head = {k: v for k, v in manifest.items() if k != "tasks"}
    text = json.dumps(head, indent=2, default=json_default)
    encode = json.JSONEncoder(default=json_default).encode  # one encoder (json.dumps makes one per call)
    tasks = ",\n    ".join(map(encode, manifest.get("tasks", ())))
    return text[:-2] + (',\n  "tasks": [\n    ' + tasks + "\n  ]\n}" if tasks else ',\n  "tasks": []\n}')


def _differences(old: dict, plan: SweepPlan) -> str:
    what = []
    if old.get("sweep") != json.loads(json.dumps(plan.manifest["sweep"])):
        what.append("the sweep file")
    if old.get("base_settings") != json.loads(json.dumps(plan.manifest["base_settings"])):
        what.append("the base settings")
    if old.get("scene_digest") != plan.manifest["scene_digest"]:
        what.append("the scene")
    return " and ".join(what) or "the sweep"


def prepare_folder(plan: SweepPlan, out_dir, *, restart: bool = False) -> Path:
    """Create (or check, to resume) the sweep folder; write the manifest and the scene.  Returns the folder."""
    out = Path(out_dir).resolve()
    manifest_path = out / "sweep.json"
    if out.exists() and not out.is_dir():
        raise ConfigError("out", str(out), "a folder path (a file of that name exists)")
    if manifest_path.is_file():
        try:
            old = json.loads(manifest_path.read_text(encoding="utf-8"))
        except ValueError:
            old = {}
        if old.get("fingerprint") != plan.fingerprint and not restart:
            raise ConfigError("out", str(out), f"the folder of this same sweep: it holds a sweep run with "
                              f"different inputs ({_differences(old, plan)} changed); restart it "
                              f"(--restart: its runs are discarded) or choose another folder")
        if restart:  # asked: whatever the folder holds of a sweep is discarded
            for name in OWNED:
                p = out / name
                if p.is_dir():
                    shutil.rmtree(p)
                elif p.exists():
                    p.unlink()
    elif out.exists() and any(out.iterdir()):
        raise ConfigError("out", str(out), "a new or empty folder, or the folder of this same sweep (to resume it)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "runs").mkdir(exist_ok=True)
    if not manifest_path.is_file():
        if plan.spec.source and Path(plan.spec.source).is_file():
            src = Path(plan.spec.source)
            shutil.copyfile(src, out / ("sweep_file" + src.suffix.lower()))
        scene_dir = out / "scene"
        plan.scene.save(scene_dir)
        text = manifest_text(plan.manifest)  # last: a folder without it is not a sweep yet
        write_file_atomically(manifest_path, lambda f: f.write(text.encode("utf-8")))
    elif not (out / "scene" / "scene.json").is_file():
        plan.scene.save(out / "scene")
    remove_abandoned_staging(out / "runs")  # what workers killed while writing left (their claims are gone)
    return out


# --------------------------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------------------------
def table_columns(axis_names) -> list:
    return (["task", "point", "seed_index", "frame", *axis_names, "seed", "status", "error", "run_time_s",
             "target", *FIGURES, "run"])


def task_row(task: dict, result: dict | None, root: Path) -> dict:
    """A results-table row: the task's identity and swept values, then its result (or status "pending")."""
    row = {"task": task["name"], "point": task["point"], "seed_index": task["seed_index"], "frame": task["frame"],
           **task["values"], "seed": task["seed"], "status": "pending", "error": "", "run_time_s": math.nan,
           "target": task.get("target") or ""}
    row.update(dict.fromkeys(FIGURES, math.nan))
    if result:
        row.update({k: v for k, v in result.items() if k in row and k not in ("task", "target")})
    row["run"] = os.path.relpath(task["out"], root) if row["status"] == "done" else ""
    return row


def _cell(v):
    if isinstance(v, float):
        return "" if math.isnan(v) else repr(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def write_table(path, rows: list, columns: list) -> Path:
    """CSV (header + one line per row; empty cells where a figure is not defined), written atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_cell(r.get(c, "")) for c in columns])
    return write_file_atomically(path, lambda f: f.write(buf.getvalue().encode("utf-8")))


def read_table(path) -> list:
    """The rows of a results.csv as dicts of strings (empty string: not defined)."""
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _read_finished(task: dict):
    return finished_row(Path(task["out"]), task["name"])


def figure_statistics(rows: list, axis: str, figure: str, other_axes: list) -> list:
    """[(label of the other axes' values, x values, mean, std, n)] of ``figure`` against ``axis`` over the done
    rows: the mean and standard deviation across seeds (and frames) at each x, one series per combination of the
    other axes."""
    groups = {}
    for r in rows:
        if r["status"] != "done":
            continue
        v = r.get(figure)
        if not isinstance(v, (int, float)) or not math.isfinite(v):
            continue
        key = tuple((a, r[a]) for a in other_axes)
        groups.setdefault(key, {}).setdefault(r[axis], []).append(float(v))
    out = []
    for key, by_x in groups.items():
        xs = sorted(by_x)
        label = ", ".join(f"{a} = {v:g}" if isinstance(v, (int, float)) else f"{a} = {v}" for a, v in key)
        out.append((label, xs, [float(np.mean(by_x[x])) for x in xs], [float(np.std(by_x[x])) for x in xs],
                    [len(by_x[x]) for x in xs]))
    return out


def write_plots(folder: Path, rows: list, axis_names: list, axis_values: dict, progress=None) -> list:
    """``plots/<figure>_vs_<axis>.png`` for every figure defined somewhere and every numeric axis.
    ``progress(done, total)`` before the first plot and after each (24 plots take seconds)."""
    folder.mkdir(exist_ok=True)
    todo = []
    for axis in axis_names:
        values = axis_values[axis]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            continue  # a categorical axis (strings, booleans): see the table
        positive = min(values) > 0
        log_x = positive and len(values) > 2 and max(values) / min(values) >= 50
        others = [a for a in axis_names if a != axis]
        for figure in FIGURES:
            series = figure_statistics(rows, axis, figure, others)
            if series:
                todo.append((folder / f"{figure}_vs_{axis.replace('.', '_')}.png", series, axis, figure, log_x))
    written = []
    if progress is not None:
        progress(0, len(todo))
    for path, series, axis, figure, log_x in todo:
        sweep_plot_png(path, series, xlabel=axis, ylabel=figure, log_x=log_x, overwrite=True)
        written.append(path)
        if progress is not None:
            progress(len(written), len(todo))
    return written


def _number_or_text(text: str):
    if text == "":
        return math.nan
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def replot(folder) -> list:
    """Draw a sweep folder's plots again from its ``results.csv`` and ``sweep.json`` (e.g. after a cancelled sweep,
    over the tasks done so far); returns the plot paths."""
    folder = Path(folder)
    try:
        manifest = json.loads((folder / "sweep.json").read_text(encoding="utf-8"))
        rows = read_table(folder / "results.csv")
    except (OSError, ValueError) as exc:
        raise ConfigError("sweep folder", str(folder), f"a folder with sweep.json and results.csv ({exc})") from None
    axes = {name: values for name, values in manifest["sweep"]["axes"]}
    parsed = [{k: (v if k in ("task", "status", "error", "run") else _number_or_text(v)) for k, v in r.items()}
              for r in rows]
    return write_plots(folder / "plots", parsed, list(axes), axes)


# --------------------------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------------------------
#: Most bytes the client reads from a scheduler address before it knows a Dask scheduler answers there: a Dask
#: peer's first message (its handshake, about 100 bytes) starts with its length, which distributed's client
#: allocates as read — a wrong or hostile service could make it allocate anything (issue 31).
HANDSHAKE_MAX_BYTES = 64 * 1024
#: Seconds to connect to a scheduler (and to hear its handshake).
CONNECT_TIMEOUT_S = 20.0
_ADDRESS_FORM = "a Dask scheduler's address tcp://HOST:PORT (e.g. tcp://127.0.0.1:8786; PORT in [1, 65535])"


def scheduler_address(address) -> tuple:
    """(``scheme://host:port``, scheme, host, port) of a scheduler address given as ``tcp://HOST:PORT``,
    ``tls://HOST:PORT`` or ``HOST:PORT`` (IPv6 hosts in brackets).  Raises ConfigError if it is not one."""
    text = str(address).strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    host, colon, port = rest.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if (scheme not in ("tcp", "tls") or not colon or not host or not port.isdigit() or not 0 < int(port) < 65536
            or any(c in host for c in "/[]@? \t")):
        raise ConfigError("scheduler", address, _ADDRESS_FORM)
    shown = f"[{host}]" if ":" in host else host
    return f"{scheme}://{shown}:{int(port)}", scheme, host, int(port)


def _recv_exactly(sock, n: int, deadline: float) -> bytes:
    import socket

    data = bytearray()
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout()
        sock.settimeout(left)
        chunk = sock.recv(min(n - len(data), 65536))
        if not chunk:
            raise ConnectionResetError("the connection was closed")
        data += chunk
    return bytes(data)


def probe_scheduler(address, timeout_s: float = CONNECT_TIMEOUT_S) -> str:
    """Check that a Dask peer answers at ``address`` (a TCP one: its handshake, at most
    :data:`HANDSHAKE_MAX_BYTES` read, within ``timeout_s``) before a ``distributed.Client`` trusts it; returns
    the normalised address.  Raises ConfigError with one line saying what was found instead."""
    import socket
    import struct

    normal, scheme, host, port = scheduler_address(address)
    if scheme != "tcp":  # TLS frames its records itself; its own handshake refuses a service that is not TLS
        return normal
    deadline = time.monotonic() + timeout_s
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            (n,) = struct.unpack("<Q", _recv_exactly(sock, 8, deadline))
            if not 0 < n <= HANDSHAKE_MAX_BYTES:
                raise ConfigError("scheduler", address, f"{_ADDRESS_FORM}: something answers there that is not a "
                                  f"Dask scheduler (its first message claims {n} bytes; a Dask handshake is at "
                                  f"most {HANDSHAKE_MAX_BYTES})")
            body = _recv_exactly(sock, n, deadline)
    except socket.timeout:
        raise ConfigError("scheduler", address, f"{_ADDRESS_FORM}: no Dask scheduler answered there within "
                                                f"{timeout_s:g} s") from None
    except OSError as exc:
        raise ConfigError("scheduler", address, f"{_ADDRESS_FORM}: cannot connect "
                                                f"({exc.strerror or type(exc).__name__})") from None
    if b"pickle-protocol" not in body:
        raise ConfigError("scheduler", address, f"{_ADDRESS_FORM}: something answers there that is not a Dask "
                                                f"scheduler (no Dask handshake)")
    return normal


def max_local_workers() -> int:
    """Most worker processes a local cluster may start: 4 per core of this machine (each is single-threaded and
    holds its own scene, BVH and kernels; more only compete for the cores and the memory)."""
    return 4 * (os.cpu_count() or 1)


def check_workers(n_workers):
    """``n_workers`` (None: one per core) if it is a whole number in [1, :func:`max_local_workers`]; ConfigError
    otherwise (issue 31: ``--workers 100000`` was accepted and started that many processes)."""
    if n_workers is None:
        return None
    hi = max_local_workers()
    if isinstance(n_workers, bool) or not isinstance(n_workers, int) or not 1 <= n_workers <= hi:
        raise ConfigError("workers", n_workers, f"a whole number in [1, {hi}] (worker processes of the local "
                                                f"cluster: at most 4 per core of this machine)")
    return n_workers


def open_client(scheduler: str | None = None, n_workers: int | None = None):
    """(client, cluster or None): a Client of the scheduler at ``scheduler`` (checked first by
    :func:`probe_scheduler`) or of a new LocalCluster of ``n_workers`` single-threaded worker processes (default:
    one per core)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - dask/distributed are requirements
        raise ConfigError("scheduler", "dask", "an installed dask/distributed (pip install -r "
                                               "requirements-worker.txt)") from exc
    if scheduler:
        address = probe_scheduler(scheduler)
        try:
            return Client(address, timeout=f"{CONNECT_TIMEOUT_S:g}s"), None
        except (OSError, TimeoutError, ValueError) as exc:
            raise ConfigError("scheduler", scheduler, f"the address of a running Dask scheduler "
                                                      f"({' '.join(str(exc).split())[:300]})") from None
    n = check_workers(n_workers) or os.cpu_count() or 1
    stage_core()  # before the workers start: they inherit its folder on sys.path (no upload, no restart)
    # (the nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536; their frames set glibc's thresholds themselves:
    # core/heap.py)
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                           silence_logs=40)
    return Client(cluster), cluster


def run_sweep(sweep, scene: SweepScene, out_dir, *, base: SimulationConfig | None = None, scheduler=None,
              client=None, n_workers: int | None = None, restart: bool = False, progress=None, cancel=None,
              plots: bool = True, plan: SweepPlan | None = None) -> SweepOutcome:
    """Run a sweep (a SweepSpec or the path of a sweep file) over ``scene`` into the folder ``out_dir``.

    ``base``: the settings the sweep starts from (default settings if None; the sweep file's ``base`` and
    ``[settings]`` apply over it).  ``scheduler``: a Dask scheduler address (``tcp://host:8786``); ``client``:
    an existing ``distributed.Client`` (neither: a LocalCluster of ``n_workers`` processes, default one per core).
    ``restart``: discard what the sweep folder holds (its runs, table, plots) and start again.
    ``progress(fraction, text)`` is called as tasks finish; ``cancel()`` returning true stops the sweep (finished
    tasks are kept; run it again to resume).  Raises ConfigError (nothing written) if any point's settings are
    bad, or Cancelled.  ``plan``: the :func:`plan_sweep` of this sweep, scene, base and folder when the caller
    made it already (SweepJob validates every point in its constructor): not planned a second time (at 10⁵ tasks
    planning takes 5-15 s).
    """
    t0 = time.perf_counter()
    if scheduler and client is None:
        scheduler_address(scheduler)  # a malformed address: one line, before anything else
    check_workers(n_workers)
    if plan is not None and plan.out_dir != Path(out_dir).resolve():
        raise ValueError(f"the plan was made for the sweep folder {plan.out_dir}, not {out_dir}")
    if plan is None:
        spec = sweep if isinstance(sweep, SweepSpec) else load_sweep(sweep)
        plan = plan_sweep(spec, scene, base, out_dir)
    spec = plan.spec
    own_client, cluster = None, None
    if scheduler and client is None:  # an unreachable or wrong scheduler is refused before anything is written
        own_client, _ = open_client(scheduler)
        client = own_client
    try:
        out = prepare_folder(plan, out_dir, restart=restart)
    except BaseException:
        if own_client is not None:
            own_client.close()
        raise
    tasks = plan.tasks
    results = {}
    with os.scandir(out / "runs") as entries:  # one listing, not one failed open per task of a new sweep
        present = {e.name for e in entries if not e.name.startswith(".")}
    for t in tasks:
        if t["name"] in present:
            row = _read_finished(t)
            if row is not None:
                results[t["name"]] = row
    pending = [t for t in tasks if t["name"] not in results]
    n_total, n_before = len(tasks), len(results)
    failed_dir = out / "failed"
    outcome = SweepOutcome(out, [], n_tasks=n_total, target=plan.manifest["target"])
    try:
        if pending:
            if client is None:
                own_client, cluster = open_client(scheduler, n_workers)
                client = own_client
            name = ship_core(client)
            run_task = importlib.import_module(f"{name}.sweep.task").run_task
            outcome.n_workers = len(client.scheduler_info().get("workers", {}))
            _run_tasks(client, run_task, out, plan, pending, results, failed_dir, n_total, n_before, progress,
                       cancel)
    finally:
        if own_client is not None:
            own_client.close()
        if cluster is not None:
            cluster.close()
        remove_abandoned_staging(out / "runs")
        outcome.rows = [task_row(t, results.get(t["name"]), out) for t in tasks]
        write_table(out / "results.csv", outcome.rows, table_columns(spec.axis_names))
    outcome.n_done = sum(r["status"] == "done" for r in outcome.rows)
    outcome.n_failed = sum(r["status"] == "failed" for r in outcome.rows)
    outcome.n_run = len(results) - n_before
    outcome.n_resumed = n_before
    if plots:
        outcome.plots = write_plots(
            out / "plots", outcome.rows, spec.axis_names, {a.name: a.values for a in spec.axes},
            progress=None if progress is None else (
                lambda done, total: progress(1.0, f"{n_total}/{n_total} tasks; plots {done}/{total}")))
    outcome.wall_time_s = time.perf_counter() - t0
    return outcome


#: Tasks submitted to the scheduler at a time: the client keeps between one and two batches in flight and submits
#: the next as tasks finish (a large sweep starts at once and the client's and scheduler's memory stay bounded).
SUBMIT_BATCH = 500
#: The first submission: small, so that the scheduler (in this process for a local cluster) hands out the first
#: task at once; the rest follows in SUBMIT_BATCH batches as tasks finish.  With 1000 tasks in the first submission
#: the first result of a warm worker came 4-5 s after it under a load of 12 (0.4 s for one task).
FIRST_BATCH = 50


def _run_tasks(client, run_task, out, plan, pending, results, failed_dir, n_total, n_before, progress, cancel):
    from itertools import islice

    from distributed import as_completed

    digest = plan.manifest["scene_digest"]
    scene_dir = str(out / "scene")
    tag = plan.fingerprint[:10]
    queue = iter(pending)
    futures = {}  # in flight: key -> (future, task)
    ac = as_completed()

    def submit(n):
        batch = list(islice(queue, n))
        if not batch:
            return
        # the scheduler unpickles what it receives: pickle.loads and bytes (shipping.shipped_call), never the core
        futs = client.map(pickle.loads, [shipped_call(run_task, scene_dir, digest, t) for t in batch],
                          key=[f"ladar-sweep-{tag}-{t['name']}" for t in batch], pure=False)
        for fut, t in zip(futs, batch):
            futures[fut.key] = (fut, t)
            ac.add(fut)

    t_start = time.perf_counter()
    n_failed = 0
    n_done = len(results)

    def report():
        run_now = n_done - n_before
        elapsed = time.perf_counter() - t_start
        eta = (n_total - n_done) * elapsed / run_now if run_now else math.nan
        progress(n_done / n_total, f"{n_done}/{n_total} tasks" + (f", {n_failed} failed" if n_failed else "")
                 + (f", ETA {eta:.0f} s" if math.isfinite(eta) else ""))

    try:
        submit(FIRST_BATCH)
        if progress is not None:
            report()  # at once: the sweep has started
        while futures:
            # asked before every batch, not only while none is ready: tasks that keep finishing (small ones, two
            # workers) left no idle moment, and a cancelled sweep went on for thousands of tasks (4,000 seen at load
            # 12 before the cancel was noticed)
            if cancel is not None and cancel():
                raise Cancelled()
            batch = ac.next_batch(block=False)
            if not batch:
                time.sleep(0.05)
                continue
            for fut in batch:
                _, task = futures.pop(fut.key)
                try:
                    row = fut.result()
                except Exception as exc:  # the task never returned (e.g. its workers kept dying)
                    row = {"task": task["name"], "status": "failed",
                           "error": " ".join(f"{type(exc).__name__}: {exc}".split())[:2000], "run_time_s": math.nan}
                results[task["name"]] = row
                n_done += 1
                fail_file = failed_dir / f"{task['name']}.json"
                if row["status"] == "done":
                    fail_file.unlink(missing_ok=True)
                else:
                    n_failed += 1
                    failed_dir.mkdir(exist_ok=True)
                    write_json_atomically(fail_file, {"task": {k: task[k] for k in ("name", "point", "seed_index",
                                                                                    "seed", "frame", "values")},
                                                      "error": row["error"]})
                fut.release()
            if len(futures) <= SUBMIT_BATCH:
                submit(SUBMIT_BATCH)
            if progress is not None:
                report()
    except BaseException:
        client.cancel([f for f, _ in futures.values()])
        raise
