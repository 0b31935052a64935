"""Every benchmark script in bench/ runs in its ``--quick`` mode (small sizes, seconds) into a temporary ``--out``
folder, and writes well-formed JSON holding the figures its docstring and the docs describe; and running them
leaves every committed file as it was (they write to the folder named, never to bench/results/).

The benchmarks whose subject is a process of their own run as a fresh process, as a user runs them
(:data:`FRESH_PROCESS`: whole commands cold and warm, Blender's module, a Dask cluster, child processes); the
others, which import the core and time it, run their ``main(argv)`` in the test process with the same arguments:
a fresh process cost each of them 1.5-2 s of CPU (Python, NumPy, numba and the core imported, its kernels loaded)
for nothing the test checks.  The benchmarks' command line is tested in a fresh process by
:func:`test_output_options_refuse_the_committed_folder_without_the_flag`.

Measured on the shared 2-core machine with warm kernel caches, CPU s at load 7-8: commands 24 (its cold run
compiles the flash demo's kernels into an empty cache, by design), scaling 13, sweep 8, pareto 8, the in-process
ones 0.1-3 each; the file 68 s of CPU (96 s with every benchmark in a fresh process).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

import benchio  # noqa: E402


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0


def _get(doc, dotted):
    for key in dotted.split("/"):
        assert isinstance(doc, dict) and key in doc, f"no {dotted!r} (missing {key!r})"
        doc = doc[key]
    return doc


#: benchmark → (JSON file, fields that must be finite and > 0 (paths with "/"), a further check or None)
BENCHMARKS = {
    "bench_flash": ("flash.json", ["bare_embreex_cast_s", "pipeline_s", "ratio_pipeline_to_bare_cast",
                                   "ratio_points_only_to_bare_cast", "ratio_full_physics_to_bare_cast",
                                   "floor/thread_s", "stage_ratio_to_floor/pipeline/trace",
                                   "stage_ratio_to_floor/full_physics/receiver_chain",
                                   "flash_demo_noisy_vs_ideal/ratio_noisy_to_ideal", "n_points",
                                   "cpu_time (process, all threads; best of the repeats)/floor_cpu_s",
                                   "cpu_time (process, all threads; best of the repeats)/full_physics/"
                                   "cpu_ratio_to_floor", "thread_scaling_1_to_2/full_physics/relative_to_floor",
                                   "thread_scaling_1_to_2/pipeline/cpu_growth_1_to_2/frame"],
                    lambda d: d["hit_fraction"] > 0 and len(d["load_average_1_5_15_min"]["end"]) == 3),
    "bench_turbulence": ("turbulence.json", ["cases/wide_12deg/calm_s", "cases/wide_12deg/turbulent_s",
                                             "cases/narrow_0.06deg/calm_s", "cases/narrow_0.06deg/turbulent_s"],
                         lambda d: all(math.isfinite(c["overhead_fraction"]) and c["overhead_fraction"] > -1
                                       for c in d["cases"].values())),
    "bench_radiometry": ("radiometry.json", ["threads_1/core/radiometry_min_s", "threads_1/core/frame_median_s",
                                             "threads_2/core/radiometry_min_s", "threads_2/core/frame_median_s"], None),
    "bench_receiver": ("receiver.json", ["floor_best_s", "max_ratio", "max_ratio_in_scope", "typical_ratio"],
                       lambda d: len(d["scenes"]) >= 5 and all(_positive(s["ratio"]) and _positive(s["ratio_1thread"])
                                                               for s in d["scenes"].values())),
    "bench_systems": ("systems.json", ["scanner/pulses_per_s", "scanner/rays_per_s",
                                       "scanner/ratio_pipeline_to_bare_cast", "scanner/floor/thread_s",
                                       "gated/ratio_30_to_1_slices"],
                      lambda d: d["gated"]["traced_once"] is True),
    "bench_helios_survey": ("helios_survey.json", ["pulses_per_s/1", "pulses_per_s/2", "thread_scaling_1_to_2",
                                                   "ratio_pipeline_to_bare_cast/1", "ratio_pipeline_to_bare_cast/2",
                                                   "floor/2/thread_s", "stage_ratio_to_floor/2/trace",
                                                   "thread_scaling_against_floor/relative_to_floor",
                                                   "cpu_ratio_pipeline_to_floor (process CPU, all threads)/2",
                                                   "vs_helios/pulses_per_s_2_threads",
                                                   "peak_rss_bytes (scene, kernels and one survey run)"],
                            lambda d: d["survey"]["n_pulses"] == 10_000),
    "bench_phasescreen": ("phasescreen.json", ["wall_time_s"],
                          lambda d: all(_positive(c["split_step"]["scintillation_index"])
                                        and _positive(c["fast_model"]["scintillation_index"])
                                        for c in d["cases"].values()) and isinstance(d["agrees"], bool)),
    "bench_scintillation_speed": ("scintillation_speed.json", ["max_ratio", "cases/0/baseline_s",
                                                               "cases/0/wave_optics_s"], None),
    "bench_scintillation_accuracy": ("scintillation_accuracy.json", ["max_abs_error/table/si_rel_error"],
                                     lambda d: len(d["cases"]) == 2),
    "bench_export": ("export.json", [], lambda d: len(d["cases"]) == 4
                     and all(_positive(c["export_s"]) and _positive(c["triangles_per_s"]) for c in d["cases"].values())),
    "bench_sequence": ("sequence.json", ["static/wall_s", "moving/wall_s", "moving_over_static",
                                         "modal/cancel_to_stopped_s"],
                       lambda d: d["static"]["exports"] == 1 and d["static"]["bvh_builds"] == 1
                       and d["moving"]["exports"] == d["frames"] and d["modal"]["state"] == "cancelled"
                       and d["modal"]["left_behind"] == [] and d["modal_moving"]["state"] == "done"),
    "bench_sweep": ("sweep.json", ["serial/points_per_s", "dask/1/points_per_s", "dask/1/speedup_vs_serial",
                                   "dask/1/noop_round_trip_s"], lambda d: d["tasks"] == 4),
    "bench_pareto": ("pareto.json", ["scenes/0/reference_time_s"],
                     lambda d: all(_positive(r["time_s"]) and math.isfinite(r["errors"]["waveform_l2"])
                                   for r in d["scenes"][0]["rows"]) and len(d["scintillation"]["rows"]) == 4),
    "bench_commands": ("commands.json", ["examples/flash_demo/cold/command_wall_s",
                                         "examples/flash_demo/warm_median/command_wall_s",
                                         "examples/flash_demo/warm_median/command_cpu_s"],
                       lambda d: d["examples"]["flash_demo"]["cold"]["kernels"]["compiled"] > 0
                       and d["examples"]["flash_demo"]["warm_median"]["kernels"]["compiled"] == 0),
    "bench_weather": ("weather.json", ["bare_embreex_cast_s", "cases/fog_200m/ratio_frame_to_bare_cast",
                                       "cases/fog_200m/weather_stage_thread_s",
                                       "cases/rain_25mm_h/weather_stage_thread_s", "ratio_fog_frame_to_clear_frame",
                                       "template_time_vs_error/2/time_s"],
                      lambda d: d["cases"]["fog_200m"]["atmosphere_echoes"] > 0
                      and d["cases"]["clear"]["atmosphere_echoes"] == 0 and len(d["template_time_vs_error"]) == 4),
    "bench_scaling": ("scaling.json", ["pipeline_vs_bare/0/ratio_pipeline_to_bare",
                                       "pipeline_vs_bare/0/floor/thread_s", "scene/0/bvh_build_s",
                                       "sensor/0/frame_s", "culling/frame_culled_s", "sample/frame_s"],
                      lambda d: d["culling"]["identical_products"] is True),
}


def _list_index(doc, dotted):
    out = doc
    for key in dotted.split("/"):
        out = out[int(key)] if isinstance(out, list) else _get(out, key)
    return out


def committed_state() -> tuple[str, str]:
    """``git status`` of the tracked files and a digest of their differences from HEAD (catches a further change
    to a file that was already modified)."""
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                            text=True, check=True).stdout
    diff = subprocess.run(["git", "diff", "HEAD", "--binary"], cwd=REPO, capture_output=True, check=True).stdout
    return status, hashlib.sha256(diff).hexdigest()


@pytest.fixture(scope="module")
def git_before():
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    return committed_state()


def test_every_benchmark_script_is_listed():
    scripts = sorted(p.stem for p in (REPO / "bench").glob("bench_*.py"))
    assert scripts == sorted(BENCHMARKS), "a new benchmark needs a --quick entry in BENCHMARKS"
    assert set(FRESH_PROCESS) <= set(BENCHMARKS)


#: quick modes that stay slow: bench_sequence starts Blender's Python module, whose add-on path compiles the kernels
#: again in each new process (20 s on a quiet machine, 120 s with the cores busy)
SLOW = {"bench_sequence"}


#: benchmarks run as a fresh process (their subject is one): the rest run ``main(argv)`` in the test process
FRESH_PROCESS = {
    "bench_commands": "times whole commands, each a fresh process, from an empty kernel cache and a filled one",
    "bench_sequence": "imports Blender's bpy module (which must not be imported into a core test process)",
    "bench_export": "imports Blender's bpy module",
    "bench_sweep": "starts a Dask cluster of worker processes and times the client's process",
    "bench_scaling": "starts child processes and times them",
}


def run_quick(name: str, out: Path, capsys) -> None:
    """``bench/<name>.py --quick --out OUT``: in a fresh process for :data:`FRESH_PROCESS`, else its ``main``
    here (bench/ is on sys.path, as for the script itself).  Fails on a non-zero exit."""
    argv = ["--quick", "--out", str(out)]
    if name in FRESH_PROCESS:
        proc = subprocess.run([sys.executable, str(REPO / "bench" / f"{name}.py"), *argv], cwd=REPO,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return
    try:
        code = importlib.import_module(name).main(argv)
    except SystemExit as exc:  # argparse's errors, and a benchmark's own exit
        code = exc.code
    err = capsys.readouterr().err
    assert not isinstance(code, (int, str)) or code == 0, f"{name}: exit {code!r}\n{err[-3000:]}"


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in sorted(BENCHMARKS)])
def test_quick_mode(name, tmp_path, git_before, capsys):
    json_name, positive, check = BENCHMARKS[name]
    run_quick(name, tmp_path, capsys)
    doc = json.loads((tmp_path / json_name).read_text(encoding="utf-8"))
    assert doc.get("quick") is True
    for field in positive:
        value = _list_index(doc, field)
        assert _positive(value), f"{json_name}: {field} = {value!r} is not finite and > 0"
    if check is not None:
        assert check(doc), f"{json_name}: check failed"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left


def test_quick_runs_left_the_committed_files_alone(git_before):
    """Runs after the quick modes (pytest keeps the file's order): bench/results/ and the docs are unchanged."""
    assert committed_state() == git_before


def test_output_options_refuse_the_committed_folder_without_the_flag(tmp_path, capsys, monkeypatch):
    """``--out bench/results`` (or a file name) is refused; ``--update-committed`` with ``--quick`` too.  The
    first through the script's command line in a fresh process (exit status 2, the message on stderr); the
    others through the same ``main(argv)`` in this process (the same parser and checks, benchio.output_folder)."""
    cases = ((["--quick", "--out", "bench/results"], "--update-committed"),
             (["--quick", "--out", str(tmp_path / "x.json")], "takes a folder"),
             (["--quick", "--update-committed"], "never committed"))
    argv, message = cases[0]
    proc = subprocess.run([sys.executable, str(REPO / "bench" / "bench_receiver.py"), *argv], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and message in proc.stderr, (argv, proc.stderr)
    monkeypatch.chdir(REPO)  # (relative paths as from the repository, like the command above)
    main = importlib.import_module("bench_receiver").main
    for argv, message in cases:
        with pytest.raises(SystemExit) as exit_:
            main(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and message in err, (argv, err)
    assert benchio.DEFAULT_DIR == REPO / "runs" / "bench"
    ignored = subprocess.run(["git", "check-ignore", "-q", "runs/bench/flash.json"], cwd=REPO)
    assert ignored.returncode == 0, "runs/ must be git-ignored"
