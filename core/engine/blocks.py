"""Blocks on a thread pool: how a frame's work is cut into independent blocks and run with progress and cancel.

Blocks are fixed ranges of items (pixels, pulses); each block's work depends on its range only (its random
streams are keyed by item, :mod:`.rng`), so the products do not depend on the thread count or the block size.
embreex and NumPy release the GIL, so threads scale the trace and the array stages.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import Cancelled
from ..threads import imap

#: Blocks each thread gets at least, when the frame allows (:func:`balanced_block_size`).
BLOCKS_PER_THREAD = 8
#: Rows of one BLAS product in :func:`rows_matmul`: (16384 × 3)·(3 × 3) is below OpenBLAS's threading threshold
#: (m·n·k ≤ 4·65536), so the product runs on the calling thread.
MATMUL_ROWS = 16384


def worker_threads(run_threads: int) -> int:
    """Threads of a run: ``run.threads``, 0 = one per CPU."""
    return run_threads or os.cpu_count() or 1


def item_blocks(n_items: int, per_block: int) -> list[tuple[int, int]]:
    """Consecutive (start, stop) ranges of at most ``per_block`` items covering ``range(n_items)``."""
    return [(a, min(a + per_block, n_items)) for a in range(0, n_items, per_block)]


def balanced_block_size(per_block: int, n_items: int, threads: int, min_items: int, *,
                        split_one_thread: bool = False) -> int:
    """With several threads, at least ``BLOCKS_PER_THREAD`` blocks each when the frame allows (blocks of
    ≥ ``min_items``): blocks differ in cost (sky, near ground), so a few big ones leave a thread idle
    (bench_scaling: 2 threads 1.0× → 1.6× with 4 a thread; bench_flash's 8 blocks of 2048 px ranged 4-44 ms, the
    costly ones last: 8 a thread cut the frame ≈ 8 %).  ``split_one_thread``: on one thread too (progress and an
    ETA come from finished blocks: a frame of one block says nothing until it is done)."""
    if threads > 1 or split_one_thread:
        per_block = min(per_block, max(-(-n_items // (BLOCKS_PER_THREAD * threads)), min_items))
    return per_block


def run_blocks(process, blocks, threads: int, progress=None, label: str = "block", cancel=None,
               each=None) -> list:
    """``process(block)`` for every block on ``threads`` threads of the shared pool (core/threads.py; results in
    block order).  ``each(result)``, when given, is called on every result in block order as it arrives and
    its return value is kept instead (a frame-wide sum folded in block order, the block's arrays dropped).

    ``progress(fraction, text)`` before the first block (fraction 0: it loads or compiles the kernels) and after
    each block; ``cancel()`` is asked before each block starts and a true answer raises
    :class:`~core.errors.Cancelled` (blocks already running finish, nothing is returned)."""
    def guarded(block):
        if cancel is not None and cancel():
            raise Cancelled()
        return process(block)

    results = []
    if progress is not None and blocks:  # the first block loads the kernels (or compiles them: 15-40 s the first time)
        progress(0.0, "first block: kernels load from the cache, or compile on first use")
    for i, res in enumerate(imap(guarded, blocks, threads)):
        results.append(res if each is None else each(res))
        if progress is not None:
            progress((i + 1) / len(blocks), f"{label} {i + 1}/{len(blocks)}")
    return results


def rows_matmul(a, b):
    """``a @ b`` for many rows ``a`` (n, k) and a small ``b`` (k, m), as BLAS products of at most
    ``MATMUL_ROWS`` (+1) rows: one big product makes OpenBLAS spread it over its own threads, which on the
    pipeline's busy threads cost 20-30 ms instead of 0.5 ms for 131k directions.  Bit for bit the one product:
    a row's result does not depend on the other rows (no chunk of a single row, which NumPy computes without
    BLAS, unless ``a`` has one row)."""
    a = np.asarray(a)
    n = len(a)
    if n < 2:  # (one row: NumPy's own loop, whose result depends on b's layout)
        return a @ b
    b = np.ascontiguousarray(b)  # BLAS on a transposed view costs 3× more, for the same products
    if n <= MATMUL_ROWS + 1:
        return a @ b
    out = np.empty((n, b.shape[1]), np.result_type(a, b))
    starts = list(range(0, n, MATMUL_ROWS))
    if n - starts[-1] == 1:  # no one-row chunk: the last row joins the previous chunk
        starts.pop()
    for s, e in zip(starts, starts[1:] + [n]):
        np.matmul(a[s:e], b, out=out[s:e])
    return out
