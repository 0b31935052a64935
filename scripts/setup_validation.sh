#!/usr/bin/env bash
# Set up the optional validation environment .venv-validation (git-ignored): Mitsuba 3 + mitransient pinned in
# requirements-validation.txt, used by scripts/validation/transient.py (the profiler against an independent
# transient renderer) through scripts/validation/_mitsuba_render.py.  Dr.Jit's LLVM backend needs libLLVM >= 16:
# on Debian/Ubuntu this installs libllvm19 with apt-get when no libLLVM >= 16 is found.  Idempotent; nothing else
# of the project depends on it (scripts/setup.sh runs it only with LADAR_SETUP_VALIDATION=1).
set -euo pipefail
cd "$(dirname "$0")/.."

. scripts/lib/python311.sh
find_python311 setup_validation "the validation environment is pinned for CPython 3.11"

have_llvm() {  # Dr.Jit's LLVM backend: DRJIT_LIBLLVM_PATH, or a libLLVM >= 16 the loader finds
  if [ -n "${DRJIT_LIBLLVM_PATH:-}" ]; then [ -e "$DRJIT_LIBLLVM_PATH" ]; return; fi
  ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])'
}
if ! have_llvm; then
  if command -v apt-get >/dev/null 2>&1; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
  else
    echo "setup_validation: no libLLVM >= 16 found and no apt-get: install one and set DRJIT_LIBLLVM_PATH" >&2
    exit 1
  fi
fi

stamp=.venv-validation/.requirements.sha
want=$(sha256sum requirements-validation.txt | cut -d' ' -f1)
if [ ! -x .venv-validation/bin/python ]; then
  "$PY" -m venv .venv-validation
fi
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  .venv-validation/bin/python -m pip install --quiet -r requirements-validation.txt
  echo "$want" > "$stamp"
fi
.venv-validation/bin/python scripts/validation/_mitsuba_render.py --check
