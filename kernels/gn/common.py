"""Shared helpers of the GN block's Warp kernels: accumulation dtype, launch geometry, options.

Each kernel factory in ``kernels/gn/`` is specialized on the feature width (a compile-time
constant), on which inputs exist (a block built without an input has no code for it:
``wp.static`` removes the branch; the array argument of a disabled input is a zero-size
placeholder that is never read) and on the storage dtype. Arithmetic accumulates in float32
(float64 for float64 storage). Factories are cached (``functools.cache``), so a kernel is built
once per configuration; their switches are keyword arguments.

Launches are 1-D. Row kernels use ``dim = launch_dim(rows, width)``: each thread owns
``vec(width)`` features of one row (up to 4: more bytes in flight per thread), strided by
``width // vec(width)`` so that each load and store instruction of a warp touches 32
consecutive elements (fully coalesced; a thread owning 4 adjacent features would make every
instruction touch 4x the sectors, and every store a partial-sector write); with the width a
compile-time constant, the row / column split of the thread index is a multiply-shift, not the
64-bit division of a 2-D launch. Chunked kernels (the column sums) use ``chunk_dim``: one thread
per (chunk of rows, column). Kernels that update in place take the same tensor as ``*_in`` and
``*_out``; each thread reads its elements before writing them.

Loads before stores: each thread first loads all its elements (``vec(width)`` features, or
``ROW_BATCH`` rows in the chunked kernels) into a local vector and only then stores or scatters
them. The CUDA compiler cannot move a load above a store to another array that might alias it,
so a load-store-load-store sequence keeps one 2-4 byte load in flight per thread. Loading
first keeps ``vec(width)`` loads in flight. Measured on an H200 (bench/results/
gn_block_nvidia-h200_notes.md): a plain fp32 -> fp16 copy takes 176 us with one element per
thread and 93 us with four loaded first (49.5M elements); the GN forward and training step are
1-7% faster with loads first.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import warp as wp

__all__ = ["acc_dtype", "vec", "launch_dim", "OPTIONS", "ROW_BATCH", "chunk_rows", "chunk_dim"]


def acc_dtype(dtype):
    """Accumulation dtype for a storage dtype: float64 stays float64, everything else float32."""
    return wp.float64 if dtype == wp.float64 else wp.float32


def vec(width: int) -> int:
    """Features per thread for a row of ``width`` features."""
    return 4 if width % 4 == 0 else 2 if width % 2 == 0 else 1


def launch_dim(rows: int, width: int) -> int:
    """1-D launch size of the kernels below for ``rows`` rows of ``width`` features."""
    return rows * (width // vec(width))


# Backward is hand-written (the blas path's autograd Function), so skip generating adjoints:
# halves the compile time of each kernel.
OPTIONS = {"enable_backward": False}

# Chunked kernels (the column sums): one thread per (chunk of ``chunk`` consecutive rows, column);
# a warp reads 32 consecutive columns of one row (coalesced), and each thread adds its chunk's
# column sum into ``sum_out`` with one atomic (bias gradients without a separate pass over the rows).
# Rows a chunked kernel loads before it stores them (see "Loads before stores" above).
ROW_BATCH = 4


def chunk_rows(rows: int, width: int) -> int:
    """Rows per thread of the chunked kernels: enough threads to fill the GPU (~256K), at least
    8 rows per atomic, at most 64."""
    return max(8, min(64, (rows * width) // (1 << 18)))


def chunk_dim(rows: int, width: int, chunk: int) -> int:
    return ((rows + chunk - 1) // chunk) * width if rows > 0 else 0

