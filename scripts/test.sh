#!/usr/bin/env bash
# Set up (if needed) and run the whole test suite: core physics tests and the Blender add-on tests.
# Two pytest-xdist worker processes (LADAR_TEST_WORKERS=N for another number, 0 for one process), each test file
# whole on one worker (--dist loadfile), the slowest files first (tests/conftest.py). Arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
workers="${LADAR_TEST_WORKERS:-2}"
if ! [[ "$workers" =~ ^[0-9]+$ ]] || [ "$workers" -gt 64 ]; then
  echo "test.sh: LADAR_TEST_WORKERS = '$workers' is not a number of worker processes from 0 (one process) to 64" >&2
  exit 2
fi
bash scripts/setup.sh
# the point-cloud clients' environment (scripts/setup.sh), for tests/core/fileio/test_ply_clients.py
if [ -z "${LADAR_CLIENT_PYTHON:-}" ] && [ -x .venv-clients/bin/python ]; then
  export LADAR_CLIENT_PYTHON="$PWD/.venv-clients/bin/python"
fi
if [ "$workers" -eq 0 ]; then
  exec .venv/bin/python -m pytest "$@"
fi
exec .venv/bin/python -m pytest -n "$workers" --dist loadfile --no-loadscope-reorder "$@"
