#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite: core physics tests and the Blender add-on tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# the point-cloud clients' environment (scripts/setup.sh), for tests/core/fileio/test_ply_clients.py
if [ -z "${LADAR_CLIENT_PYTHON:-}" ] && [ -x .venv-clients/bin/python ]; then
  export LADAR_CLIENT_PYTHON="$PWD/.venv-clients/bin/python"
fi
exec .venv/bin/python -m pytest "$@"
