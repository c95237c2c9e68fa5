"""Conventions of the detector's compiled (numba) kernels, and numpy's pairwise sum.

Each stage keeps its kernels in a module beside it (`_candidates_kernels`,
`_grouping_kernels`, `_verification_kernels`, `_refinement_kernels`,
`_completion_kernels`, `_code_reader_kernels`, `_disc_fit_kernels`). A kernel fuses a chain of small numpy/OpenCV calls into one loop
with the same meaning and the same arithmetic: its results are bit-identical to the
numpy/OpenCV references in the kernel tests (the disc fit's agree to rounding: its
normal CDF is an approximation, `_disc_fit_kernels`). At 640x480 the detector would otherwise
run ~40 whole-image OpenCV calls for stage 1a and a few hundred numpy calls on small
arrays for the targets; each pass over an image-sized buffer, and each ~1 us of numpy
call overhead, costs more than the arithmetic.

Flags (`JIT`): ``cache=True`` keeps the machine code in ``__pycache__`` (or
``NUMBA_CACHE_DIR``); a fresh process loads it, and with a cold cache compiles it
(seconds): each kernel module's ``warm_up`` does either on tiny inputs, and
`app.core.detection.warm_up` calls them all, once at service start-up.
``error_model="numpy"``: a float division by zero gives inf/NaN instead of raising
(otherwise numba adds a branch that stops the loops from vectorising). ``nogil``: frames
of several cameras run on threads. No ``fastmath``: it would reorder float arithmetic
and change results.

`pairwise_sum` sums a float32 row exactly as ``x.sum(axis=-1)`` does, for the window
centroid of the candidate stage and the disc centroid of refinement. It is called from
compiled code only (compiled into its callers), so it needs no warm-up of its own.
numba's cache checks only the file of the function it compiled: after changing
`pairwise_sum`, clear the cache (or touch `_candidates_kernels.py` and
`_refinement_kernels.py`) so that its callers are compiled again.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: numba flags of every detector kernel (see the module docstring).
JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**JIT, inline="always")
def _block_sum(a: np.ndarray, start: int, n: int) -> np.float32:
    """numpy's pairwise sum of a run of at most 128 (its leaf case)."""
    if n < 8:
        res = np.float32(0.0)
        for i in range(n):
            res += a[start + i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = 8
    while i < n - n % 8:
        j = start + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[start + i]
        i += 1
    return res


@njit(**JIT)
def pairwise_sum(a: np.ndarray, start: int, n: int) -> np.float32:
    """``a[start : start + n]`` (float32) summed as numpy's ``add.reduce`` sums a
    contiguous run: halved recursively (the first half a multiple of 8) down to runs of
    at most 128, each summed in eight interleaved partial sums
    (numpy/_core/src/umath/loops_utils.h.src), so a kernel reproduces
    ``x.sum(axis=-1)`` bit for bit (numpy then adds the total to its initial 0: callers
    add 0 too). The recursion runs on an explicit stack: numba's cache cannot hold a
    recursive function (loading it crashes)."""
    if n <= 128:
        return _block_sum(a, start, n)
    # post-order walk of the halving tree: (start, n, children pushed) per node
    depth = 64
    node_start = np.empty(depth, np.int64)
    node_n = np.empty(depth, np.int64)
    node_stage = np.empty(depth, np.int64)
    values = np.empty(depth, np.float32)
    top, n_values = 0, 0
    node_start[0], node_n[0], node_stage[0] = start, n, 0
    while top >= 0:
        s, m = node_start[top], node_n[top]
        if m <= 128:
            values[n_values] = _block_sum(a, s, m)
            n_values += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if node_stage[top] == 0:  # the first half
            node_stage[top] = 1
            top += 1
            node_start[top], node_n[top], node_stage[top] = s, half, 0
        elif node_stage[top] == 1:  # the second half
            node_stage[top] = 2
            top += 1
            node_start[top], node_n[top], node_stage[top] = s + half, m - half, 0
        else:  # both summed: first + second
            n_values -= 1
            values[n_values - 1] = values[n_values - 1] + values[n_values]
            top -= 1
    return values[0]
