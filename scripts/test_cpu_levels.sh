#!/usr/bin/env bash
# The quick physics tests with numba's code generated for each x86-64 level up to this CPU's own: a generic
# x86-64 (SSE2, what any 64-bit PC runs), AVX2 + FMA (Haswell, 2013 on) and, where the CPU has it, AVX-512
# (Skylake-SP): floating-point tolerances must hold for each (tests state them from the arithmetic, not from one
# machine's last bits).  Each level compiles the kernels once into the per-user cache (they are keyed on the
# CPU name and features).  CI runs this after the whole suite (.ci/run).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh >/dev/null
flags=$(grep -m1 '^flags' /proc/cpuinfo 2>/dev/null || true)
levels=(generic)
[[ " $flags " == *" avx2 "* && " $flags " == *" fma "* ]] && levels+=(haswell)
[[ " $flags " == *" avx512f "* ]] && levels+=(skylake-avx512)
for cpu in "${levels[@]}"; do
  echo "== numba target CPU: $cpu"
  NUMBA_CPU_NAME="$cpu" NUMBA_CPU_FEATURES="" .venv/bin/python -m pytest -q -p no:cacheprovider tests/core/physics "$@"
done
