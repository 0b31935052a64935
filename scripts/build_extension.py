#!/usr/bin/env python3
"""Build the per-platform extension zips, with the Python wheels the simulator needs bundled.

    python scripts/build_extension.py [--out dist] [--platforms linux-x64,windows-x64,...] [--blender BIN]
                                      [--offline] [--wheels-dir build/wheels]

1. **Wheels.** For every platform, ``pip download --only-binary=:all: --no-deps --python-version 3.11
   --implementation cp --abi cp311 --platform <tag>`` of the bundled packages (:data:`BUNDLED`, versions pinned in
   ``requirements.txt``) into ``build/wheels/<platform>/`` (kept as a cache; ``--offline`` uses only the cache).
   numpy is not bundled: Blender ships it (4.2 LTS: 1.24.3), and a second numpy would break Blender's; every
   bundled package accepts numpy 1.24.3 (matplotlib 3.10, contourpy 1.3.2: the newest that do).
   Dask (dask, distributed and all their dependencies, :data:`DASK`) is too: sweeps started from Blender run on
   it.
   A package with no wheel for a platform is reported and that platform is not built.
2. **Stage.** ``build/stage/ladar_simulator/``: the package files — exactly the entries
   ``blender_env.PACKAGE_PATHS`` lists (what ``scripts/blender_env.py`` also installs for development;
   nothing else the checkout holds) — the wheels in ``wheels/``, and a copy of ``blender_manifest.toml`` whose
   ``platforms`` and ``wheels`` lists are filled.  The repository's own manifest is not modified (it lists no wheels, so a
   development checkout validates and installs without them).
3. **Build.** Blender's own extension build, ``blender --command extension build --split-platforms``, or, with
   no Blender binary, the same tool from the ``bpy`` module (``bl_pkg/cli/blender_ext.py build``): one zip per
   platform, ``<out>/ladar_simulator-<version>-<platform>.zip`` (each holds only that platform's wheels), each
   then validated with ``extension validate``.

macOS: the embreex wheels need macOS 13 or later (``MACOS_TARGET``), so the macOS zips do too.

Exit status 0 when every requested platform was built and validated.  Wheels, stage and zips are never
committed (``/build/``, ``/dist/`` and ``/wheels/`` are in .gitignore).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from blender_env import EXTENSION_ID, package_files  # noqa: E402

#: Packages bundled as wheels (distribution names); versions come from requirements.txt.  The simulator's own:
#: scipy, embreex, OpenEXR, and matplotlib, which draws the previews (title, axes, colour bar), with its
#: dependencies (packaging: Blender lacks it), and numba with llvmlite, which compile the signal chain's kernels
#: (core/jit.py).
SIMULATOR = ("scipy", "embreex", "OpenEXR", "matplotlib", "contourpy", "cycler", "fonttools", "kiwisolver", "pillow",
             "pyparsing", "python-dateutil", "tzdata", "packaging", "numba", "llvmlite")
#: Then Dask with every dependency it has (requirements-worker.txt lists the same; packaging is above): a sweep
#: started from Blender (``blender -c ladar sweep``, ``ladar.sweep``) runs on dask.distributed.
DASK = ("dask", "distributed", "cloudpickle", "msgpack", "psutil", "tornado", "toolz", "partd", "fsspec", "PyYAML",
        "click", "Jinja2", "MarkupSafe", "zict", "tblib", "sortedcontainers", "locket", "importlib_metadata", "zipp",
        "lazy-importer")
BUNDLED = SIMULATOR + DASK
PYTHON_VERSION = "3.11"
MACOS_TARGET = "13_0"
#: Blender platform → pip ``--platform`` tags (pip accepts older macOS versions of a macOS tag by itself).
PLATFORM_TAGS = {
    # Blender 4.2+ needs glibc ≥ 2.28; pip does not expand manylinux tags downwards, so list them.
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": [f"macosx_{MACOS_TARGET}_arm64"],
    "macos-x64": [f"macosx_{MACOS_TARGET}_x86_64"],
}


def pinned_versions(requirements: Path = REPO / "requirements.txt") -> dict[str, str]:
    """``{name: version}`` of the bundled packages as pinned (``name==version``) in requirements.txt."""
    pins = {}
    for line in requirements.read_text().splitlines():
        m = re.match(r"^\s*([A-Za-z0-9_.\-]+)\s*==\s*([^\s#;]+)", line)
        if m:
            pins[m.group(1).lower()] = m.group(2)
    missing = [p for p in BUNDLED if p.lower() not in pins]
    if missing:
        raise SystemExit(f"build_extension: {', '.join(missing)} not pinned (name==version) in {requirements}")
    return {p: pins[p.lower()] for p in BUNDLED}


def _wheel_matches(wheel: Path, name: str, version: str) -> bool:
    dist, ver = wheel.name.split("-")[:2]
    return dist.lower().replace("_", "-") == name.lower().replace("_", "-") and ver == version


def download_wheels(platform: str, versions: dict, wheels_dir: Path, offline: bool = False) -> tuple[list, list]:
    """(wheel paths, packages without a wheel) for one Blender platform."""
    dest = wheels_dir / platform
    dest.mkdir(parents=True, exist_ok=True)
    found, missing = [], []
    for name, version in versions.items():
        have = [w for w in dest.glob("*.whl") if _wheel_matches(w, name, version)]
        if not have and not offline:
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
                   "--only-binary=:all:", "--no-deps", "--python-version", PYTHON_VERSION, "--implementation", "cp",
                   "--abi", "cp" + PYTHON_VERSION.replace(".", ""), "--dest", str(dest), f"{name}=={version}"]
            for tag in PLATFORM_TAGS[platform]:
                cmd += ["--platform", tag]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                print(f"  {platform}: no wheel of {name}=={version} ({proc.stderr.strip().splitlines()[-1:]})")
            have = [w for w in dest.glob("*.whl") if _wheel_matches(w, name, version)]
        if have:
            found.append(sorted(have)[-1])
        else:
            missing.append(f"{name}=={version}")
    return found, missing


def stage_package(stage_root: Path, wheels: list[Path], platforms: list[str], source: Path = REPO) -> Path:
    """Copy the package (exactly ``blender_env.PACKAGE_PATHS`` of ``source``) into ``stage_root/ladar_simulator``
    with ``wheels/`` and a filled manifest."""
    pkg = stage_root / EXTENSION_ID
    if pkg.exists():
        shutil.rmtree(pkg)
    pkg.mkdir(parents=True)
    for rel in package_files(source):
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source / rel, pkg / rel)
    (pkg / "wheels").mkdir()
    for w in wheels:
        shutil.copy2(w, pkg / "wheels" / w.name)
    manifest = pkg / "blender_manifest.toml"
    manifest.write_text(fill_manifest(manifest.read_text(), [f"./wheels/{w.name}" for w in wheels], platforms))
    return pkg


def fill_manifest(text: str, wheel_paths: list[str], platforms: list[str]) -> str:
    """The manifest text with top-level ``platforms`` and ``wheels`` lists (replacing any present)."""
    lines, skipping = [], False
    for ln in text.splitlines():
        if skipping:  # inside a multi-line list being replaced
            skipping = "]" not in ln
            continue
        if re.match(r"^\s*(platforms|wheels)\s*=", ln):
            skipping = "]" not in ln
            continue
        if ln.strip() != "# Filled by scripts/build_extension.py.":
            lines.append(ln)
    first_table = next((i for i, ln in enumerate(lines) if ln.lstrip().startswith("[")), len(lines))
    block = ["# Filled by scripts/build_extension.py.",
             "platforms = [" + ", ".join(json.dumps(p) for p in platforms) + "]",
             "wheels = ["] + [f"  {json.dumps(w)}," for w in wheel_paths] + ["]", ""]
    out = "\n".join(lines[:first_table] + block + lines[first_table:]) + "\n"
    data = tomllib.loads(out)
    assert data["wheels"] == wheel_paths and data["platforms"] == platforms
    return out


def bl_pkg_dir() -> Path | None:
    """Blender's extension tooling inside the installed ``bpy`` module (None without bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.origin:
        return None
    hits = sorted(Path(spec.origin).parent.glob("*/scripts/addons_core/bl_pkg"))
    return hits[-1] if hits else None


def extension_command(blender: str | None) -> list[str]:
    """The command prefix that runs Blender's ``extension`` sub-commands."""
    if blender:
        return [blender, "--factory-startup", "--command", "extension"]
    pkg = bl_pkg_dir()
    if pkg is None:
        raise SystemExit("build_extension: neither a Blender binary (--blender) nor the bpy module is available")
    return [sys.executable, str(pkg / "cli" / "blender_ext.py")]


def _valid_tags_args(blender: str | None) -> list[str]:
    if blender:
        return []
    tags = bl_pkg_dir().parent.parent / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    return ["--valid-tags", str(tags)]


def build(stage_pkg: Path, out_dir: Path, blender: str | None) -> list[Path]:
    """Blender's ``extension build --split-platforms``; returns the zips it made (each validated)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    version = tomllib.loads((stage_pkg / "blender_manifest.toml").read_text())["version"]
    for old in out_dir.glob(f"{EXTENSION_ID}-{version}-*.zip"):
        old.unlink()
    cmd = extension_command(blender) + ["build", "--split-platforms", "--source-dir", str(stage_pkg),
                                        "--output-dir", str(out_dir)] + _valid_tags_args(blender)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    print(proc.stdout.strip())
    if proc.returncode != 0:
        raise SystemExit(f"build_extension: extension build failed:\n{proc.stdout}\n{proc.stderr}")
    zips = sorted(out_dir.glob(f"{EXTENSION_ID}-{version}-*.zip"))
    for z in zips:
        proc = subprocess.run(extension_command(blender) + ["validate", str(z)] + _valid_tags_args(blender),
                              capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"build_extension: {z.name} does not validate:\n{proc.stdout}\n{proc.stderr}")
    return zips


def zip_summary(path: Path) -> dict:
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
    return {"zip": path.name, "size_mib": round(path.stat().st_size / 2**20, 1),
            "wheels": sorted(n.split("/")[-1] for n in names if n.endswith(".whl"))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "dist", help="output folder of the zips (default: dist/)")
    ap.add_argument("--platforms", default=",".join(PLATFORM_TAGS),
                    help="comma-separated Blender platforms (default: all of " + ", ".join(PLATFORM_TAGS) + ")")
    ap.add_argument("--wheels-dir", type=Path, default=REPO / "build" / "wheels",
                    help="wheel cache, one folder per platform (default: build/wheels/)")
    ap.add_argument("--stage-dir", type=Path, default=REPO / "build" / "stage")
    ap.add_argument("--blender", default=shutil.which("blender"),
                    help="Blender binary for 'extension build' (default: blender on PATH, else the bpy module's "
                         "blender_ext.py)")
    ap.add_argument("--offline", action="store_true", help="use only wheels already in --wheels-dir")
    args = ap.parse_args(argv)

    platforms = [p.strip() for p in args.platforms.split(",") if p.strip()]
    unknown = [p for p in platforms if p not in PLATFORM_TAGS]
    if unknown:
        ap.error(f"unknown platform(s) {', '.join(unknown)}; known: {', '.join(PLATFORM_TAGS)}")
    versions = pinned_versions()
    print(f"build_extension: bundling {', '.join(f'{k}=={v}' for k, v in versions.items())} for "
          f"{', '.join(platforms)}")
    wheels, built_platforms, skipped = [], [], {}
    for platform in platforms:
        found, missing = download_wheels(platform, versions, args.wheels_dir, args.offline)
        if missing:
            skipped[platform] = missing
            continue
        built_platforms.append(platform)
        wheels += [w for w in found if w.name not in {x.name for x in wheels}]
    for platform, missing in skipped.items():
        print(f"build_extension: {platform} skipped, no wheel of {', '.join(missing)}")
    if not built_platforms:
        return 1
    stage = stage_package(args.stage_dir, wheels, built_platforms)
    zips = build(stage, args.out, args.blender)
    summary = [zip_summary(z) for z in zips]
    for s in summary:
        print(f"  {s['zip']}: {s['size_mib']} MiB, wheels: {', '.join(s['wheels'])}")
    return 0 if not skipped and len(zips) == len(built_platforms) else 1


if __name__ == "__main__":
    sys.exit(main())
