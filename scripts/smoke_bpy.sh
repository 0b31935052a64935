#!/usr/bin/env bash
# Packaging smoke runs (CI step after the unit tests; needs PyPI the first time, then runs from caches):
#  1. build the linux-x64 extension zip with its bundled wheels (scripts/build_extension.py; wheels cached in
#     build/wheels/);
#  2. in clean bpy environments — Blender 4.2 LTS with numpy 1.24.3 (the minimum the manifest claims) and
#     Blender 5.0.1 (the current one), each with none of the bundled packages — install the zip, enable it and
#     simulate one frame and run a two-point sweep on a local Dask worker (scripts/smoke_extension.py).
# The environments live in build/venvs/<name> and are rebuilt only when their requirements file changes.
set -euo pipefail
cd "$(dirname "$0")/.."

. scripts/lib/python311.sh
find_python311 smoke_bpy "bpy wheels are built for CPython 3.11"

clean_venv() {  # clean_venv <dir> <requirements file>
  local dir=$1 req=$2 want
  want=$(sha256sum "$req" | cut -d' ' -f1)
  if [ ! -x "$dir/bin/python" ] || [ "$(cat "$dir/.requirements.sha" 2>/dev/null)" != "$want" ]; then
    rm -rf "$dir"
    "$PY" -m venv "$dir"
    "$dir/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req"
    echo "$want" > "$dir/.requirements.sha"
  fi
}

.venv/bin/python scripts/build_extension.py --platforms linux-x64
zip=$(ls dist/ladar_simulator-*-linux_x64.zip | head -1)
for name in bpy42 bpy50; do
  clean_venv "build/venvs/$name" "scripts/requirements-$name.txt"
  "build/venvs/$name/bin/python" scripts/smoke_extension.py "$zip" --json "build/smoke-$name.json"
done
echo "smoke_bpy: the linux zip installs, simulates and sweeps (bundled Dask) on Blender 4.2 LTS and 5.0 (build/smoke-*.json)"
