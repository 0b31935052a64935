"""What a benchmark ran on: the CPU and the SIMD level NumPy and the compiled kernels use.

The pipeline's ratios to the bare Embree cast depend on it: Embree traces at much the same speed with AVX2 or
AVX-512, while NumPy's float64 log/exp/cos have SIMD code for AVX-512 only (elsewhere the C library's, 5-10× slower
per element) and the kernels' counting passes and filters run on half as wide vectors.
"""
from __future__ import annotations

import os
import platform


def machine_info() -> dict:
    """CPU model, logical CPUs, NumPy's detected SIMD extensions (the AVX ones), LLVM's host CPU name, numba."""
    info = {"cpu": platform.processor() or platform.machine(), "logical_cpus": os.cpu_count()}
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        from numpy.core._multiarray_umath import __cpu_features__ as feats
        info["numpy_simd"] = sorted(k for k, v in feats.items() if v and k.startswith(("AVX", "FMA", "NEON", "ASIMD")))
    except ImportError:  # pragma: no cover - NumPy 2 moved it
        from numpy._core._multiarray_umath import __cpu_features__ as feats
        info["numpy_simd"] = sorted(k for k, v in feats.items() if v and k.startswith(("AVX", "FMA", "NEON", "ASIMD")))
    try:
        import llvmlite.binding as llvm
        import numba

        info["llvm_host_cpu"] = llvm.get_host_cpu_name()
        info["numba"] = numba.__version__
    except ImportError:  # pragma: no cover - numba is a requirement
        pass
    return info
