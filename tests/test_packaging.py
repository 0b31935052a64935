"""scripts/build_extension.py offline: pins, the filled manifest, per-platform zips from Blender's own build.

The real thing (download the wheels, install the linux zip into clean bpy 4.2 LTS and 5.0 environments and
simulate a frame) needs PyPI, so it is the CI step ``scripts/smoke_bpy.sh`` rather than a unit test.  Here the
wheels are stand-ins with real wheel file names, which is all Blender's build uses to split the platforms.
"""
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import build_extension as be  # noqa: E402

PURE = ["cycler-0.12.1-py3-none-any.whl", "packaging-26.3-py3-none-any.whl", "pyparsing-3.3.3-py3-none-any.whl",
        "python_dateutil-4.0.0-py3-none-any.whl", "tzdata-2026.6-py2.py3-none-any.whl"]
WHEELS = {
    "linux-x64": ["scipy-1.15.3-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
                  "embreex-4.4.0.post1-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl",
                  "openexr-3.5.3-cp311-cp311-manylinux_2_28_x86_64.whl",
                  "matplotlib-3.10.9-cp311-cp311-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
                  "contourpy-1.3.2-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
                  "fonttools-4.68.0-cp311-cp311-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
                  "kiwisolver-1.5.1-cp311-cp311-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
                  "pillow-13.0.0-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl",
                  "numba-0.61.2-cp311-cp311-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
                  "llvmlite-0.44.0-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"] + PURE,
    "windows-x64": ["scipy-1.15.3-cp311-cp311-win_amd64.whl", "embreex-4.4.0.post1-cp311-cp311-win_amd64.whl",
                    "openexr-3.5.3-cp311-cp311-win_amd64.whl", "matplotlib-3.10.9-cp311-cp311-win_amd64.whl",
                    "contourpy-1.3.2-cp311-cp311-win_amd64.whl", "fonttools-4.68.0-cp311-cp311-win_amd64.whl",
                    "kiwisolver-1.5.1-cp311-cp311-win_amd64.whl", "pillow-13.0.0-cp311-cp311-win_amd64.whl",
                    "numba-0.61.2-cp311-cp311-win_amd64.whl", "llvmlite-0.44.0-cp311-cp311-win_amd64.whl"] + PURE,
}


#: Dask and its dependencies (scripts/build_extension.py DASK): pure wheels go into every platform's zip ...
DASK_PURE = ["dask-2026.8.0-py3-none-any.whl", "distributed-2026.8.0-py3-none-any.whl",
             "cloudpickle-3.1.3-py3-none-any.whl", "toolz-1.2.0-py3-none-any.whl", "partd-1.4.2-py3-none-any.whl",
             "fsspec-2026.9.0-py3-none-any.whl", "click-8.5.1-py3-none-any.whl", "jinja2-3.1.6-py3-none-any.whl",
             "zict-3.0.0-py2.py3-none-any.whl", "tblib-3.2.2-py3-none-any.whl",
             "sortedcontainers-2.4.0-py2.py3-none-any.whl", "locket-1.0.0-py2.py3-none-any.whl",
             "importlib_metadata-10.2.0-py3-none-any.whl",
             "zipp-4.1.2-py3-none-any.whl", "lazy_importer-0.1.0-py3-none-any.whl"]
# ... the compiled ones only into their platform's
WHEELS["linux-x64"] += ["msgpack-1.2.4-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
                        "psutil-7.2.2-cp36-abi3-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
                        "tornado-6.6.1-cp39-abi3-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
                        "pyyaml-6.0.4-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
                        "markupsafe-3.0.4-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"] + DASK_PURE
WHEELS["windows-x64"] += ["msgpack-1.2.4-cp311-cp311-win_amd64.whl", "psutil-7.2.2-cp37-abi3-win_amd64.whl",
                          "tornado-6.6.1-cp39-abi3-win_amd64.whl", "pyyaml-6.0.4-cp311-cp311-win_amd64.whl",
                          "markupsafe-3.0.4-cp311-cp311-win_amd64.whl"] + DASK_PURE


def _fake_wheels(root: Path, platforms=("linux-x64", "windows-x64")):
    for platform in platforms:
        (root / platform).mkdir(parents=True)
        for name in WHEELS[platform]:
            with zipfile.ZipFile(root / platform / name, "w") as z:
                z.writestr(name.split("-")[0] + "/__init__.py", "")


def test_pins_come_from_requirements():
    """scipy 1.15.3, matplotlib 3.10.9 and contourpy 1.3.2: the newest that still support the numpy 1.24.3 of
    Blender 4.2 LTS; matplotlib's dependencies bundled with it (Blender has none of them); numba 0.61.2 (llvmlite
    0.44.0) supports numpy 1.24–2.2, i.e. Blender 4.2 … 5.0 (the compiled signal-chain kernels)."""
    pins = be.pinned_versions()
    assert {k: pins[k] for k in be.SIMULATOR} == {
        "scipy": "1.15.3", "embreex": "4.4.0.post1", "OpenEXR": "3.5.3", "matplotlib": "3.10.9", "contourpy": "1.3.2",
        "cycler": "0.12.1", "fonttools": "4.68.0", "kiwisolver": "1.5.1", "pillow": "13.0.0", "pyparsing": "3.3.3",
        "python-dateutil": "4.0.0", "tzdata": "2026.6", "packaging": "26.3", "numba": "0.61.2",
        "llvmlite": "0.44.0"}
    assert pins["dask"] == pins["distributed"] == "2026.8.0"  # sweeps from Blender (docs/sweeps.md)
    text = (REPO / "requirements.txt").read_text()
    assert all(f"{k}=={v}" in text for k, v in pins.items())


def test_the_bundled_dask_is_what_a_sweep_worker_installs():
    """The extension bundles Dask with the same closed, pinned set of packages a worker installs."""
    worker = [ln.split("==")[0] for ln in (REPO / "requirements-worker.txt").read_text().splitlines()
              if "==" in ln and not ln.startswith("#")]
    assert set(worker) - {"numpy"} <= set(be.BUNDLED)  # Blender ships numpy
    assert set(be.DASK) <= set(worker)


def test_fill_manifest_adds_platforms_and_wheels_and_leaves_the_repository_alone():
    source = (REPO / "blender_manifest.toml").read_text()
    repo_manifest = tomllib.loads(source)
    assert "wheels" not in repo_manifest and "platforms" not in repo_manifest  # a dev checkout needs no wheels
    filled = be.fill_manifest(source, ["./wheels/a.whl", "./wheels/b.whl"], ["linux-x64", "windows-x64"])
    data = tomllib.loads(filled)
    assert data["wheels"] == ["./wheels/a.whl", "./wheels/b.whl"]
    assert data["platforms"] == ["linux-x64", "windows-x64"]
    assert {k: v for k, v in data.items() if k not in ("wheels", "platforms")} == repo_manifest
    again = tomllib.loads(be.fill_manifest(filled, ["./wheels/c.whl"], ["macos-arm64"]))  # replaced, not doubled
    assert again["wheels"] == ["./wheels/c.whl"] and again["platforms"] == ["macos-arm64"]
    ignored = (REPO / ".gitignore").read_text().split()
    assert {"/build/", "/dist/", "/wheels/"} <= set(ignored)  # wheels, stage and zips are never committed


def test_offline_build_splits_the_platforms(tmp_path, capsys):
    wheels = tmp_path / "wheels"
    _fake_wheels(wheels)
    code = be.main(["--offline", "--platforms", "linux-x64,windows-x64", "--wheels-dir", str(wheels),
                    "--stage-dir", str(tmp_path / "stage"), "--out", str(tmp_path / "dist"), "--blender", ""])
    assert code == 0, capsys.readouterr().out
    zips = {p.name: p for p in (tmp_path / "dist").glob("*.zip")}
    assert set(zips) == {"ladar_simulator-0.1.0-linux_x64.zip", "ladar_simulator-0.1.0-windows_x64.zip"}
    for platform, name in (("linux-x64", "linux_x64"), ("windows-x64", "windows_x64")):
        with zipfile.ZipFile(zips[f"ladar_simulator-0.1.0-{name}.zip"]) as z:
            names = z.namelist()
            manifest = tomllib.loads(z.read("blender_manifest.toml").decode())
        assert sorted(n for n in names if n.endswith(".whl")) == sorted(f"wheels/{w}" for w in WHEELS[platform])
        assert manifest["build"]["generated"]["platforms"] == [platform]
        assert len(manifest["wheels"]) == 2 * (10 + 5) + len(PURE) + len(DASK_PURE)
        assert manifest["platforms"] == ["linux-x64", "windows-x64"]
        for required in ("__init__.py", "core/fileio/las.py", "core/physics/brdf.py", "ladar_addon/materials.py",
                         "presets/ladar_simulator/sensor/Airborne_1064_nm_full_waveform.py",
                         "presets/ladar_simulator/material/Retroreflective_sheeting.py"):
            assert required in names
        assert not any(n.split("/")[0] in {"tests", "scripts", "bench", "docs", ".venv", "build", "dist"}
                       for n in names)
    assert (tmp_path / "stage" / "ladar_simulator" / "wheels").is_dir()


def test_a_platform_without_a_wheel_is_not_built(tmp_path, capsys):
    wheels = tmp_path / "wheels"
    _fake_wheels(wheels, platforms=("linux-x64",))
    (wheels / "linux-x64" / WHEELS["linux-x64"][1]).unlink()  # no embreex for linux
    (wheels / "windows-x64").mkdir()
    for name in WHEELS["windows-x64"]:
        (wheels / "windows-x64" / name).write_bytes(b"")
    code = be.main(["--offline", "--platforms", "linux-x64,windows-x64", "--wheels-dir", str(wheels),
                    "--stage-dir", str(tmp_path / "stage"), "--out", str(tmp_path / "dist"), "--blender", ""])
    out = capsys.readouterr().out
    assert code == 1
    assert "linux-x64 skipped, no wheel of embreex==4.4.0.post1" in out
    assert [p.name for p in (tmp_path / "dist").glob("*.zip")] == ["ladar_simulator-0.1.0-windows_x64.zip"]


def test_unknown_platform_is_an_argument_error():
    with pytest.raises(SystemExit) as err:
        be.main(["--platforms", "linux-arm64", "--offline"])
    assert err.value.code == 2


def _tree(root: Path) -> set:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()}


def test_stage_packages_exactly_the_listed_entries(tmp_path):
    """Issue 14: the zips held every untracked folder of the checkout; now only blender_env.PACKAGE_PATHS."""
    src = tmp_path / "checkout"
    wanted = ["__init__.py", "blender_manifest.toml", "README.md", "core/__init__.py", "core/fileio/las.py",
              "ladar_addon/__init__.py", "operators/__init__.py", "panels/__init__.py",
              "presets/ladar_simulator/sensor/A.py", "sample_blends/flash_demo.blend"]
    junk = ["my_scans/scan.npy", "runs/r1/metadata.json", "notes.txt", "wheels/x.whl", "dist/old.zip",
            ".venv/bin/python", "core/__pycache__/las.cpython-311.pyc", "core/.scratch.py", "tests/test_x.py",
            "scripts/demo.sh", "docs/a.md", "sample_blends/build_samples.py", "sample_blends/flash_demo.blend1",
            "pyproject.toml", "requirements.txt", "old_extension.zip"]
    for rel in wanted + junk:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text("x")
    (src / "blender_manifest.toml").write_text((REPO / "blender_manifest.toml").read_text())
    pkg = be.stage_package(tmp_path / "stage", [], ["linux-x64"], source=src)
    assert _tree(pkg) == set(wanted)
    # a checkout missing a needed entry is refused, not packaged incomplete
    (src / "panels" / "__init__.py").unlink()
    (src / "panels").rmdir()
    with pytest.raises(FileNotFoundError, match="panels"):
        be.stage_package(tmp_path / "stage", [], ["linux-x64"], source=src)


def test_every_tracked_entry_is_packaged_or_declared_development_only():
    import subprocess

    import blender_env

    proc = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip("not a git checkout")
    tracked = [Path(p) for p in proc.stdout.splitlines()]
    packaged = set(blender_env.package_files(REPO))
    for path in tracked:
        dev = any(path.parts[0] == d or str(path) == d for d in blender_env.DEVELOPMENT_ONLY)
        assert (path in packaged) != dev, f"{path}: packaged {path in packaged}, development-only {dev}"
