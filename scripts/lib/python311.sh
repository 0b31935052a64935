# Sourced by scripts/setup.sh, scripts/smoke_bpy.sh and scripts/setup_validation.sh (bash).
# find_python311 <who> <why>: sets PY to the first of python3.11, python3 that is CPython 3.11, or prints
# "<who>: Python 3.11 is required (<why>); found: ..." on stderr and exits 1.
find_python311() {
  local who=$1 why=$2 cand
  PY=""
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
      PY="$cand"; return 0
    fi
  done
  echo "$who: Python 3.11 is required ($why); found: $(python3 --version 2>&1 || echo 'no python3')" >&2
  exit 1
}
