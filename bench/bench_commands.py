"""What the user waits for: the whole command's wall time of each README example, cold and warm.

    .venv/bin/python bench/bench_commands.py [--out DIR | --update-committed] [--quick] [--repeat N]

For each README example (``scripts/ladar_run.py sample_blends/<scene>.blend simulate --out …``) it times, in a
fresh process each time:

* **cold**: an empty kernel cache (``LADAR_KERNEL_CACHE`` pointing at a new folder): the first run after an
  install, compiling every kernel it calls;
* **warm**: the same cache again, from a new temporary Blender user folder (as every ``ladar_run.py`` run is):
  every kernel loaded from the cache (the run's ``kernels`` record must say 0 compiled, else the benchmark fails).

The project's bytecode is written first (:func:`write_bytecode`).  Next to each wall time it reports the
command's CPU time (user + system of the process and its threads, from ``getrusage`` of the finished child: on a
shared machine the wall time mostly measures the other jobs) and the load average when it started, and what the
run itself records: the frame's wall time, the seconds loading or compiling kernels, and the stage times without
them.  Then, on the last warm run's folder, it times the PNG previews alone
(``core.fileio.preview.write_run_previews`` after deleting the run's PNGs, in a fresh process each time, the
matplotlib import included; median of the warm repeats): how many, wall and CPU seconds.  The load average (1, 5,
15 min) at the start and the end is recorded beside the figures.  Writes ``commands.json`` into ``--out``
(default ``runs/bench``; ``--update-committed``: ``bench/results``, bench/benchio.py).  ``--quick``: the flash
demo only, one warm repeat.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
from benchio import add_output_arguments, output_path, write_json  # noqa: E402

EXAMPLES = ("flash_demo", "gated_board", "forest_scan", "aircraft_profile")
#: The project's Python folders whose bytecode is written before the clocks (:func:`write_bytecode`).
BYTECODE_DIRS = ("core", "ladar_addon", "operators", "panels", "scripts")


def write_bytecode() -> None:
    """Write the project's missing or stale bytecode (``__pycache__``, git-ignored) before anything is timed, as a
    user's Python does at its first run: where ``PYTHONDONTWRITEBYTECODE`` is set (the shared development machine)
    Python never writes it, and every timed command compiled the ~130 project modules it imports again (0.5-0.7 s
    of CPU a command, issue 25) unless the test suite had written them (tests/conftest.py does the same)."""
    import compileall

    for name in BYTECODE_DIRS:
        compileall.compile_dir(REPO / name, quiet=2, workers=1)
    compileall.compile_file(REPO / "__init__.py", quiet=2)


def _children_cpu_s() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def run_once(scene: str, cache: Path, work: Path, keep: bool = False) -> dict:
    """One command in a fresh process; ``keep``: leave its run folder (``run_folder`` in the result)."""
    out = work / f"{scene}-{time.monotonic_ns()}"
    env = dict(os.environ, LADAR_KERNEL_CACHE=str(cache))
    load = os.getloadavg()[0]
    c0, t0 = _children_cpu_s(), time.perf_counter()
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "ladar_run.py"),
                           str(REPO / "sample_blends" / f"{scene}.blend"), "simulate", "--out", str(out)],
                          capture_output=True, text=True, env=env, cwd=work)
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - c0
    if done.returncode != 0:
        raise SystemExit(f"bench_commands: {scene} failed:\n{done.stderr[-2000:]}")
    meta = json.loads((out / "metadata.json").read_text())
    if not keep:
        shutil.rmtree(out, ignore_errors=True)
    return {"command_wall_s": wall, "command_cpu_s": cpu, "load_average_1min": load,
            "frame_wall_s": meta["wall_time_s"],
            "kernels": meta["kernels"], "stage_times_sum_s": sum(meta["stage_times_s"].values()),
            **({"run_folder": str(out)} if keep else {})}


#: Run in a fresh process on a run folder: its PNG previews drawn again, timed (matplotlib, which the previews
#: import on first use, included; the core's own import not).
PREVIEWS = """
import json, sys, time
from core.fileio.preview import write_run_previews
c0, t0 = time.process_time(), time.perf_counter()
written = write_run_previews(sys.argv[1])
print(json.dumps({"n_png": len(written), "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}))
"""


def time_previews(run_folder: Path, repeat: int) -> dict:
    """The run's PNG previews drawn ``repeat`` times, each in a fresh process after deleting them: the median
    run's count, wall and CPU seconds, and every repeat's wall seconds."""
    runs = []
    for _ in range(repeat):
        for png in run_folder.rglob("*.png"):
            png.unlink()
        done = subprocess.run([sys.executable, "-c", PREVIEWS, str(run_folder)], capture_output=True, text=True,
                              cwd=REPO)
        if done.returncode != 0:
            raise SystemExit(f"bench_commands: previews of {run_folder} failed:\n{done.stderr[-2000:]}")
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    runs.sort(key=lambda r: r["wall_s"])
    return {**runs[len(runs) // 2], "wall_s_each": [r["wall_s"] for r in runs]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_output_arguments(ap, quick_help="the flash demo only, one warm repeat")
    ap.add_argument("--repeat", type=int, default=3, help="warm runs per example (the median is reported)")
    args = ap.parse_args(argv)
    path = output_path(ap, args, "commands.json")
    scenes = EXAMPLES[:1] if args.quick else EXAMPLES
    repeat = 1 if args.quick else args.repeat
    write_bytecode()
    results = {}
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_commands_") as tmp:
        work = Path(tmp)
        for scene in scenes:
            cache = work / f"cache-{scene}"
            cold = run_once(scene, cache, work)
            warm = [run_once(scene, cache, work, keep=k == repeat - 1) for k in range(repeat)]
            if any(w["kernels"]["compiled"] for w in warm):
                raise SystemExit(f"bench_commands: a warm run of {scene} compiled kernels: {warm}")
            run_folder = Path(warm[-1].pop("run_folder"))
            previews = time_previews(run_folder, repeat)
            shutil.rmtree(run_folder, ignore_errors=True)
            warm.sort(key=lambda w: w["command_wall_s"])
            median = warm[len(warm) // 2]
            results[scene] = {"cold": cold, "warm_median": median,
                              "warm_command_wall_s": [w["command_wall_s"] for w in warm],
                              "warm_command_cpu_s": [w["command_cpu_s"] for w in warm], "previews": previews}
            print(f"{scene:18s} cold {cold['command_wall_s']:6.1f} s (kernels {cold['kernels']['compiled']} "
                  f"compiled, {cold['kernels']['load_and_compile_s']:.1f} s)   warm {median['command_wall_s']:5.1f} s "
                  f"wall, {median['command_cpu_s']:5.1f} s CPU (frame {median['frame_wall_s']:.2f} s, kernels "
                  f"loaded in {median['kernels']['load_and_compile_s']:.2f} s)   previews: {previews['n_png']} PNG "
                  f"{previews['wall_s']:.2f} s wall, {previews['cpu_s']:.2f} s CPU   load {os.getloadavg()[0]:.1f}",
                  flush=True)
    record = {"benchmark": "commands", "machine": {"cpu": platform.processor() or platform.machine(),
                                                    "cores": os.cpu_count()},
              "quick": args.quick, "examples": results,
              "load_average_1_5_15_min": {"start": list(load_start), "end": list(os.getloadavg())}}
    write_json(path, record, indent=1)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
