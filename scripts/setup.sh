#!/usr/bin/env bash
# Set up the project on a fresh machine: a Python 3.11 virtual environment in .venv with the pinned
# requirements (bpy 5.0.1 from PyPI, numpy, scipy, embreex, OpenEXR, test tools). Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."

. scripts/lib/python311.sh
find_python311 setup "the bpy 5.0.1 wheel is built for CPython 3.11"

stamp=.venv/.requirements.sha
want=$(sha256sum requirements.txt | cut -d' ' -f1)
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
  .venv/bin/python -m pip install --quiet --upgrade pip
fi
# A changed requirements.txt installs into the existing environment (a .venv that is a link to a shared one is
# used as it is: `python -m venv` cannot create over the link).
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  .venv/bin/python -m pip install --quiet -r requirements.txt
  echo "$want" > "$stamp"
fi

# The bpy module needs a few X11/GL client libraries even headless; install them only if missing.
if ! .venv/bin/python -c 'import bpy' >/dev/null 2>&1; then
  if command -v apt-get >/dev/null 2>&1; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libxrender1 libxxf86vm1 libxfixes3 libxi6 \
      libxkbcommon0 libsm6 libice6 libgl1 libegl1 libglib2.0-0 >/dev/null
  fi
  .venv/bin/python -c 'import bpy' || { echo "setup: 'import bpy' fails; see the error above" >&2; exit 1; }
fi
# Test dependency: PROJ's projinfo (Debian's proj-bin, PROJ 9.1 as PDAL and GDAL use it) checks that the LAS
# files' coordinate system parses (tests/core/test_las_interop.py).
if ! command -v projinfo >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq proj-bin >/dev/null
fi
command -v projinfo >/dev/null 2>&1 || { echo "setup: projinfo (package proj-bin) is missing" >&2; exit 1; }
# Test-only clients that read the outputs back (tests/core/fileio/test_ply_clients.py, test_cloudcompare_las.py):
# CloudCompare's command-line mode under xvfb (Debian's cloudcompare, xvfb; libusb-1.0-0 for Open3D), and Open3D, plyfile and trimesh in
# their own environment .venv-clients (requirements-clients.txt; about 1.2 GB, kept out of .venv).  Not fatal: a
# client that cannot be installed is skipped by its tests.  LADAR_SETUP_CLIENTS=0 leaves this step out.
if [ "${LADAR_SETUP_CLIENTS:-1}" != 0 ]; then
  if { ! command -v CloudCompare >/dev/null 2>&1 || ! command -v xvfb-run >/dev/null 2>&1 \
        || ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; } && command -v apt-get >/dev/null 2>&1; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq cloudcompare xvfb libusb-1.0-0 \
        >/dev/null; } || echo "setup: warning: cloudcompare/xvfb/libusb not installed; their tests will be skipped" >&2
  fi
  cstamp=.venv-clients/.requirements.sha
  cwant=$(sha256sum requirements-clients.txt | cut -d' ' -f1)
  if [ ! -x .venv-clients/bin/python ] || [ "$(cat "$cstamp" 2>/dev/null)" != "$cwant" ]; then
    { "$PY" -m venv .venv-clients && .venv-clients/bin/python -m pip install --quiet -r requirements-clients.txt \
        && echo "$cwant" > "$cstamp"; } \
      || echo "setup: warning: Open3D/plyfile/trimesh not installed in .venv-clients; their tests will be skipped" >&2
  fi
fi
# Optional: the validation report's independent transient renderer (Mitsuba 3 + mitransient in .venv-validation,
# libllvm19 from apt-get where needed): only with LADAR_SETUP_VALIDATION=1; CI and the tests do not need it (the
# report's transient page and its test are skipped, with the reason, without it).
if [ "${LADAR_SETUP_VALIDATION:-0}" = 1 ]; then
  bash scripts/setup_validation.sh
fi
echo "setup: .venv ready ($(.venv/bin/python --version))"
