"""Warp kernels for the graph-structured work of a GN block (the "split" path).

The dense layers of the edge, node and global MLPs run as BLAS GEMMs (cuBLAS / CPU BLAS through
torch, bias and ReLU in the GEMM's epilogue); these kernels do everything around them that
depends on the graph:

- ``first_layer``: the split first layer of the edge update. ``W.[e; v_s; v_r; u] = W_e e + W_s v_s
  + W_r v_r + W_u u``: the node projections ``v @ [W_s; W_r]^T`` and global projections
  ``u @ W_u^T`` are GEMMs over nodes / graphs (done once per node / graph, not once per edge);
  this kernel gathers them per edge, adds the edge's own projection and the bias, and applies
  ReLU, in one pass.
- ``concat``: the input rows of an update's first layer side by side in the compute dtype,
  gathered where a piece is read by index (the edge update's [e, v[sender], v[receiver],
  u[graph]], the node update's [v, sum of received edges, u[graph]], the global update's
  [u, sum v', sum e']): the first layer is then one GEMM. Its launch is laid out by piece
  (``concat_threads``), not by ``launch_dim``.
- ``scatter_out``: the output epilogue of the edge and node updates: the returned copy in the
  output dtype and the atomic scatter-sums (edges -> receivers, edges -> graphs, nodes -> graphs)
  in one pass.
- ``segment_sum``: the deterministic aggregation: each destination row sums its segment of a
  CSR layout (rows sorted by destination) in a fixed order.
- ``scatter_edges``: backward of the split edge first layer: each row of its gradient added to
  its sender's, receiver's and graph's rows (atomic) in one pass.
- ``split``: the adjoint of ``concat``: the gradient of an update's input rows routed back to
  its inputs (stored, or added by sender / receiver / graph) in one pass.
- ``prep``: a block's parameters in the compute dtype and its first-layer weights as aligned,
  zero-padded blocks, in one launch per forward.
- ``gather_add_sum``: backward of the scatter-sums (sum of gathered rows), fused with the column
  sums of the result (the output layer's bias gradient).
- ``relu_grad_sum``: backward of ReLU from the saved activation, fused with the column sums of
  the result (the bias gradient of the layer below).

Each factory is specialized on the feature width (a compile-time constant), on which inputs exist
(a block built without an input has no code for it: ``wp.static`` removes the branch; the array
argument of a disabled input is a zero-size placeholder that is never read) and on the storage
dtype. Arithmetic accumulates in float32 (float64 for float64 storage). Factories are cached, so
a kernel is built once per configuration.

Launches are 1-D. Row kernels use ``dim = launch_dim(rows, width)``: each thread owns
``vec(width)`` features of one row (up to 4: more bytes in flight per thread), strided by
``width // vec(width)`` so that each load and store instruction of a warp touches 32
consecutive elements (fully coalesced; a thread owning 4 adjacent features would make every
instruction touch 4x the sectors, and every store a partial-sector write); with the width a
compile-time constant, the row / column split of the thread index is a multiply-shift, not the 64-bit
division of a 2-D launch. Chunked kernels (the column sums) use ``chunk_dim``: one thread per
(chunk of rows, column); ``relu_grad_sum`` uses ``relu_grad_dim``: one thread per (chunk of rows,
``vec(width)`` columns). Kernels that update in place take the same tensor as ``*_in`` and
``*_out``; each thread reads its elements before writing them.

Loads before stores: each thread first loads all its elements (``vec(width)`` features, or
``ROW_BATCH`` rows in the chunked kernels) into a local vector and only then stores or scatters
them. The CUDA compiler cannot move a load above a store to another array that might alias it,
so a load-store-load-store sequence keeps one 2-4 byte load in flight per thread. Loading
first keeps ``vec(width)`` loads in flight. Measured on an H200 (bench/results/
gn_block_nvidia-h200_notes.md): a plain fp32 -> fp16 copy goes from 176 us with one element per
thread to 93 us with four loaded first (49.5M elements); the GN forward and training step gained
1-7%. (The concat kernel's own bottleneck turned out to be branching, not memory: see
``concat_kernel``.)
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = [
    "acc_dtype",
    "vec",
    "launch_dim",
    "chunk_rows",
    "chunk_dim",
    "first_layer_kernel",
    "CONCAT_VEC",
    "concat_spans",
    "concat_piece_threads",
    "concat_rows_per_block",
    "concat_threads",
    "concat_kernel",
    "scatter_out_kernel",
    "SPLIT_STORE",
    "SPLIT_ADD",
    "split_kernel",
    "segment_sum_kernel",
    "scatter_edges_kernel",
    "gather_add_sum_kernel",
    "PREP_SLOTS",
    "PREP_VEC",
    "prep_threads",
    "prep_kernel",
    "relu_chunk_rows",
    "relu_grad_dim",
    "relu_grad_sum_kernel",
    "unpack_kernel",
    "EMU_BLOCK",
    "emu_group",
    "emu_split_kernel",
]


def acc_dtype(dtype):
    """Accumulation dtype for a storage dtype: float64 stays float64, everything else float32."""
    return wp.float64 if dtype == wp.float64 else wp.float32


def vec(width: int) -> int:
    """Features per thread for a row of ``width`` features."""
    return 4 if width % 4 == 0 else 2 if width % 2 == 0 else 1


def launch_dim(rows: int, width: int) -> int:
    """1-D launch size of the kernels below for ``rows`` rows of ``width`` features."""
    return rows * (width // vec(width))


def _options():
    # Backward is hand-written (see module docstring), so skip generating adjoints: halves the
    # compile time of each kernel.
    return {"enable_backward": False}


@functools.cache
def first_layer_kernel(width: int, has_direct: bool, has_sender: bool, has_receiver: bool,
                       has_global: bool, relu: bool, dtype):
    """hidden_out[r] = act(direct_in[r] + node_proj_in[senders[r], :W] + node_proj_in[receivers[r], S:S+W]
    + global_proj_in[row_graph[r]] + bias).

    ``node_proj_in`` holds the sender projection in columns [0, W) and the receiver projection
    after it (columns [W, 2W) when both exist).
    """
    W = width
    RCV_COL = W if has_sender else 0
    V = vec(width)
    WV = width // V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def first_layer(
        # Data in:
        direct_in: wp.array2d(dtype=T),
        node_proj_in: wp.array2d(dtype=T),
        global_proj_in: wp.array2d(dtype=T),
        senders: wp.array(dtype=wp.int32),
        receivers: wp.array(dtype=wp.int32),
        row_graph: wp.array(dtype=wp.int32),
        # Parameters:
        bias: wp.array(dtype=T),
        # Data out:
        hidden_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r = i // WV
        j0 = i - r * WV
        if wp.static(has_sender):
            s = senders[r]
        if wp.static(has_receiver):
            q = receivers[r]
        if wp.static(has_global):
            g = row_graph[r]
        ys = wp.vector(length=V, dtype=T)
        for k in range(V):  # every load of the thread first (see the module docstring), then stores
            j = j0 + k * WV
            x = A(bias[j])
            if wp.static(has_direct):
                x += A(direct_in[r, j])
            if wp.static(has_sender):
                x += A(node_proj_in[s, j])
            if wp.static(has_receiver):
                x += A(node_proj_in[q, RCV_COL + j])
            if wp.static(has_global):
                x += A(global_proj_in[g, j])
            if wp.static(relu):
                x = wp.max(x, A(0.0))
            ys[k] = T(x)
        for k in range(V):
            hidden_out[r, j0 + k * WV] = ys[k]

    return first_layer


@functools.cache
def segment_sum_kernel(width: int, has_perm: bool, src_dtype, dst_dtype, accumulate: bool = False):
    """sum_out[s, dst_col + j] = sum over p in [offsets[s], offsets[s+1]) of src_in[perm[p], src_col + j]
    (``accumulate``: added to what sum_out holds).

    Sums in a fixed order (deterministic, bitwise reproducible). Without ``perm`` the segments
    are contiguous row ranges of ``src_in`` (nodes or edges of one graph). Rows: segments.
    """
    V = vec(width)
    WV = width // V
    S = src_dtype
    D = dst_dtype
    A = acc_dtype(dst_dtype)

    @wp.kernel(module="unique", module_options=_options())
    def segment_sum(
        # Data in:
        src_in: wp.array2d(dtype=S),
        perm: wp.array(dtype=wp.int32),
        offsets: wp.array(dtype=wp.int32),
        src_col: int,
        dst_col: int,
        # Data out:
        sum_out: wp.array2d(dtype=D),
    ):
        i = wp.tid()
        s = i // WV
        j0 = i - s * WV
        for k in range(V):
            j = j0 + k * WV
            acc = A(0.0)
            for p in range(offsets[s], offsets[s + 1]):
                if wp.static(has_perm):
                    acc += A(src_in[perm[p], src_col + j])
                else:
                    acc += A(src_in[p, src_col + j])
            if wp.static(accumulate):
                sum_out[s, dst_col + j] = sum_out[s, dst_col + j] + D(acc)
            else:
                sum_out[s, dst_col + j] = D(acc)

    return segment_sum


# -- fused split path: input rows, output epilogue, column sums -----------------------------------
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


CONCAT_VEC = 8


def concat_spans(widths: tuple, out_width: int) -> tuple:
    """Output columns each piece of ``concat_kernel`` writes: its width, the last present piece's
    also the zero padding up to ``out_width``."""
    last = max(k for k, w in enumerate(widths) if w > 0)
    return tuple(w + (out_width - sum(widths) if k == last else 0) for k, w in enumerate(widths))


def concat_piece_threads(span: int, max_vec: int = CONCAT_VEC) -> tuple:
    """(threads per row, columns per thread) of one piece of ``concat_kernel``: as few threads
    as cover ``span`` columns at ``max_vec`` each, but at least 8 (so a row's threads read at
    least 32 bytes of fp32 per load: a whole memory sector), rounded up to a power of two below
    a warp (several rows then share a warp) and to whole warps above; each thread as few
    columns as cover the span."""
    if span == 0:
        return 0, 0
    n = max(-(-span // max_vec), min(8, span))
    n = 32 * -(-n // 32) if n > 16 else 1 << (n - 1).bit_length()
    return n, -(-span // n)


def concat_rows_per_block(widths: tuple, out_width: int, max_vec: int = CONCAT_VEC) -> int:
    """Rows that ``concat_kernel``'s threads take together: enough that every piece's threads
    fill whole warps (32 / the fewest threads per row of any piece)."""
    return 32 // min(min(concat_piece_threads(s, max_vec)[0], 32)
                     for s in concat_spans(widths, out_width) if s > 0)


def concat_threads(rows: int, widths: tuple, out_width: int, max_vec: int = CONCAT_VEC) -> int:
    """Launch size of ``concat_kernel`` for ``rows`` rows."""
    R = concat_rows_per_block(widths, out_width, max_vec)
    return -(-rows // R) * R * sum(concat_piece_threads(s, max_vec)[0] for s in concat_spans(widths, out_width))


def _concat_piece(width: int, span: int, gathered: bool, in_dtype, dtype, out_width: int, offset: int,
                  max_vec: int):
    """One piece of ``concat_kernel``'s rows, as a function of the row and the thread's first
    column: out[r, offset + c] = p_in[row, c] for c < width, 0 for width <= c < span."""
    W, S, G, Ti, T, K, E = width, span, gathered, in_dtype, dtype, out_width, offset
    N, V = concat_piece_threads(span, max_vec)
    V = max(V, 1)  # (an absent piece is never called)

    @wp.func
    def copy_piece(p_in: wp.array(dtype=Ti), index: wp.array(dtype=wp.int32), r: int, c0: int,
                   out: wp.array(dtype=T)):
        b = r * W
        if wp.static(G):
            b = index[r] * W
        xs = wp.vector(length=V, dtype=T)  # zero: the padding columns
        for k in range(V):
            if wp.static((k + 1) * N <= W):  # every thread's column k is inside the row
                xs[k] = T(p_in[b + c0 + k * N])
            elif wp.static(k * N < W):
                if c0 + k * N < W:
                    xs[k] = T(p_in[b + c0 + k * N])
        o = r * K + E + c0
        for k in range(V):
            if wp.static((k + 1) * N <= S):
                out[o + k * N] = xs[k]
            elif wp.static(k * N < S):
                if c0 + k * N < S:
                    out[o + k * N] = xs[k]

    return copy_piece


@functools.cache
def concat_kernel(widths: tuple, gathered: tuple, in_dtypes: tuple, dtype, out_width: int,
                  max_vec: int = CONCAT_VEC):
    """out[r] = [p0_in[r0], p1_in[r1], p2_in[r2], p3_in[r3], 0...] (columns side by side, cast to
    ``dtype``, zeros up to ``out_width``); a piece of width 0 is absent; a gathered piece k
    reads row ``index_k[r]``, the others row ``r``.

    Builds the input rows of an MLP whose first layer is one GEMM: the node update's
    [v, sum of received edges, u[graph of node]], the global update's [u, sum v', sum e'] and
    the edge update's [e, v[sender], v[receiver], u[graph of edge]]; zero-padded to a width
    cuBLAS's fast kernels take.

    The arrays are flat (1-D views of contiguous row-major tensors, ``rows * width`` < 2**31):
    with the widths compile-time constants, an element's offset is one int32 multiply-add per
    row. Launch over ``concat_threads(rows, ...)`` threads. Each piece gets its own threads
    (``concat_piece_threads``: up to ``max_vec`` columns each, strided by the piece's thread
    count so each load of a warp is coalesced, all loads before the stores), and rows are taken
    ``concat_rows_per_block`` at a time so that every warp works on one piece: no warp
    branches. Measured on an H200 (bench/concat_probe.py, bench/results/concat_probe_nvidia-h200.md,
    the paper core's edge rows at batch 4096, fp32 -> fp16): v9's kernel, where every thread
    tested all four pieces for each of its 8 columns, issued a predicated load per piece and
    column and was bound by the load/store pipe (ncu: 96% busy, half the lanes predicated off):
    162 us for the second block's 73728 x 672 rows, where this kernel takes 81 us."""
    S = concat_spans(widths, out_width)
    R = concat_rows_per_block(widths, out_width, max_vec)
    N0, N1, N2, N3 = (concat_piece_threads(s, max_vec)[0] for s in S)
    # each block of R rows: piece k's threads are [A_k, A_k + R * N_k), row-major (j, c0)
    A1 = R * N0
    A2 = A1 + R * N1
    A3 = A2 + R * N2
    NT = A3 + R * N3
    W0, W1, W2, W3 = widths
    offsets = (0, W0, W0 + W1, W0 + W1 + W2)
    f0, f1, f2, f3 = (_concat_piece(widths[k], S[k], gathered[k], in_dtypes[k], dtype, out_width, offsets[k], max_vec)
                      for k in range(4))
    T0, T1, T2, T3 = in_dtypes
    T = dtype

    @wp.kernel(module="unique", module_options=_options())
    def concat(
        # Data in (flat row-major):
        p0_in: wp.array(dtype=T0),
        p1_in: wp.array(dtype=T1),
        p2_in: wp.array(dtype=T2),
        p3_in: wp.array(dtype=T3),
        index_0: wp.array(dtype=wp.int32),
        index_1: wp.array(dtype=wp.int32),
        index_2: wp.array(dtype=wp.int32),
        index_3: wp.array(dtype=wp.int32),
        rows: int,
        # Data out (flat row-major):
        out: wp.array(dtype=T),
    ):
        i = wp.tid()
        rb = i // NT
        t = i - rb * NT
        if wp.static(W0 > 0):
            if t < A1:
                j = t // N0
                r = rb * R + j
                if r < rows:
                    f0(p0_in, index_0, r, t - j * N0, out)
        if wp.static(W1 > 0):
            if t >= A1 and t < A2:
                j = (t - A1) // N1
                r = rb * R + j
                if r < rows:
                    f1(p1_in, index_1, r, t - A1 - j * N1, out)
        if wp.static(W2 > 0):
            if t >= A2 and t < A3:
                j = (t - A2) // N2
                r = rb * R + j
                if r < rows:
                    f2(p2_in, index_2, r, t - A2 - j * N2, out)
        if wp.static(W3 > 0):
            if t >= A3:
                j = (t - A3) // N3
                r = rb * R + j
                if r < rows:
                    f3(p3_in, index_3, r, t - A3 - j * N3, out)

    return concat


@functools.cache
def scatter_out_kernel(width: int, scatter_a: bool, scatter_b: bool, copy: bool, dtype, out_dtype):
    """copy_out[r] = x_in[r] (in the output dtype); sum_a_out[index_a[r]] += x_in[r];
    sum_b_out[index_b[r]] += x_in[r] (atomic adds in the accumulation dtype).

    The output epilogue of the edge and node updates (the output bias is already in ``x_in``,
    added by the GEMM's epilogue): the sums add the stored values, so they equal the sum of what
    is returned."""
    V = vec(width)
    WV = width // V
    T = dtype
    O = out_dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def scatter_out(
        # Data in:
        x_in: wp.array2d(dtype=T),
        index_a: wp.array(dtype=wp.int32),
        index_b: wp.array(dtype=wp.int32),
        # Data out:
        copy_out: wp.array2d(dtype=O),
        sum_a_out: wp.array2d(dtype=A),
        sum_b_out: wp.array2d(dtype=A),
    ):
        i = wp.tid()
        r = i // WV
        j0 = i - r * WV
        if wp.static(scatter_a):
            a = index_a[r]
        if wp.static(scatter_b):
            b = index_b[r]
        xs = wp.vector(length=V, dtype=A)
        for k in range(V):
            xs[k] = A(x_in[r, j0 + k * WV])
        for k in range(V):
            j = j0 + k * WV
            y = xs[k]
            if wp.static(copy):
                copy_out[r, j] = O(y)
            if wp.static(scatter_a):
                wp.atomic_add(sum_a_out, a, j, y)
            if wp.static(scatter_b):
                wp.atomic_add(sum_b_out, b, j, y)

    return scatter_out


SPLIT_STORE, SPLIT_ADD = "store", "add"


def _split_piece(col: int, mode: str, indexed: bool, in_dtype, out_dtype):
    """One piece of ``split_kernel``: column ``col + j`` of row r of the gradient stored at
    out[r, j] or added (atomic) at out[index[r] if ``indexed`` else r, j]."""
    C, Ti, O = col, in_dtype, out_dtype

    @wp.func
    def route(g_in: wp.array2d(dtype=Ti), index: wp.array(dtype=wp.int32), r: int, j: int,
              out: wp.array2d(dtype=O)):
        x = O(g_in[r, C + j])
        if wp.static(mode == SPLIT_STORE):
            out[r, j] = x
        else:
            d = r
            if wp.static(indexed):
                d = index[r]
            wp.atomic_add(out, d, j, x)

    return route


@functools.cache
def split_kernel(pieces: tuple, in_dtype):
    """Adjoint of ``concat_kernel``: the gradient of concatenated input rows ``g_in`` handed back
    to the inputs it was built from, piece by piece, in one pass. ``pieces``: up to four
    (col, width, mode, indexed, out_dtype): columns [col, col + width) of each row r are stored
    at ``out_k[r]`` (mode ``SPLIT_STORE``: the edge update's own input) or added, atomically, at
    ``out_k[index_k[r]]`` (``SPLIT_ADD`` with ``indexed``: the sender / receiver node columns,
    the graph's global columns) or at ``out_k[r]`` (``SPLIT_ADD``: a row-aligned input whose
    gradient also receives other pieces' sums). Columns of no piece (padding, or an input whose
    gradient is read in place) get no thread: launch ``rows * sum of widths`` threads, one per
    element, consecutive threads on consecutive columns of a row (coalesced loads and atomics).
    Replaces, per update, one scatter launch per indexed piece, a per-graph segment sum, and the
    casts and adds that merged them (measured on an H200: bench/results/gn_block_nvidia-h200_notes.md)."""
    ps = list(pieces) + [(0, 0, SPLIT_STORE, False, in_dtype)] * (4 - len(pieces))
    W0, W1, W2, W3 = (p[1] for p in ps)
    A1, A2, A3 = W0, W0 + W1, W0 + W1 + W2
    WA = A3 + W3
    f0, f1, f2, f3 = (_split_piece(p[0], p[2], p[3], in_dtype, p[4]) for p in ps)
    O0, O1, O2, O3 = (p[4] for p in ps)
    Ti = in_dtype

    @wp.kernel(module="unique", module_options=_options())
    def split(
        # Data in:
        g_in: wp.array2d(dtype=Ti),
        index_0: wp.array(dtype=wp.int32),
        index_1: wp.array(dtype=wp.int32),
        index_2: wp.array(dtype=wp.int32),
        index_3: wp.array(dtype=wp.int32),
        # Data out:
        out_0: wp.array2d(dtype=O0),
        out_1: wp.array2d(dtype=O1),
        out_2: wp.array2d(dtype=O2),
        out_3: wp.array2d(dtype=O3),
    ):
        t = wp.tid()
        r = t // WA
        c = t - r * WA
        if wp.static(W0 > 0):
            if c < A1:
                f0(g_in, index_0, r, c, out_0)
        if wp.static(W1 > 0):
            if c >= A1 and c < A2:
                f1(g_in, index_1, r, c - A1, out_1)
        if wp.static(W2 > 0):
            if c >= A2 and c < A3:
                f2(g_in, index_2, r, c - A2, out_2)
        if wp.static(W3 > 0):
            if c >= A3:
                f3(g_in, index_3, r, c - A3, out_3)

    return split


def relu_chunk_rows(rows: int, width: int) -> int:
    """Rows per thread of ``relu_grad_sum``: 8 for small layers, 16 from 1M elements (measured on
    an H200 with ``bench/relu_grad_probe.py``: 16 rows won at 3600 x 512 and 73728 x 512, 8 at
    1600 x 256)."""
    return 8 if rows * width < (1 << 20) else 16


def relu_grad_dim(rows: int, width: int, chunk: int) -> int:
    """Launch size of ``relu_grad_sum``: one thread per (chunk of rows, ``vec(width)`` columns)."""
    return ((rows + chunk - 1) // chunk) * (width // vec(width)) if rows > 0 else 0


@functools.cache
def relu_grad_sum_kernel(width: int, has_sum: bool, dtype):
    """grad_out[r, j] = grad_in[r, j] where act_in[r, j] > 0, else 0 (ReLU backward from the
    saved activation; may run in place), and sum_out[j] += that gradient summed over the rows
    (the bias gradient of the layer). Launch ``relu_grad_dim(rows, width, chunk)`` threads: each
    owns ``vec(width)`` columns (strided by width / vec, so a warp's accesses stay coalesced) of
    a chunk of rows; both loads are unconditional (a select, not a load that waits on the
    activation's). Measured against the one-column, conditional-load version on an H200
    (bench/results/relu_grad_probe_nvidia-h200.md, fp16): 3600 x 512 9.3 vs 11.9 us, 73728 x 512
    125 vs 157 us."""
    W = width
    V = vec(width)
    Q = width // V
    RB = ROW_BATCH
    RBV = RB * V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def relu_grad_sum(
        # Data in:
        act_in: wp.array2d(dtype=T),
        grad_in: wp.array2d(dtype=T),
        rows: int,
        chunk: int,
        # Data out:
        grad_out: wp.array2d(dtype=T),
        sum_out: wp.array(dtype=A),
    ):
        i = wp.tid()
        ci = i // Q
        j0 = i - ci * Q
        r0 = ci * chunk
        r1 = wp.min(r0 + chunk, rows)
        acc = wp.vector(length=V, dtype=A)
        for rb in range(r0, r1, RB):  # RB rows loaded, then stored (in place: read before written)
            gs = wp.vector(length=RBV, dtype=T)
            for k in range(RB):
                r = rb + k
                if r < r1:
                    for c in range(V):
                        a = act_in[r, j0 + c * Q]
                        x = grad_in[r, j0 + c * Q]
                        gs[k * V + c] = wp.where(a > T(0.0), x, T(0.0))
            for k in range(RB):
                r = rb + k
                if r < r1:
                    for c in range(V):
                        grad_out[r, j0 + c * Q] = gs[k * V + c]
                        acc[c] += A(gs[k * V + c])
        if wp.static(has_sum):
            for c in range(V):
                wp.atomic_add(sum_out, j0 + c * Q, acc[c])

    return relu_grad_sum


@functools.cache
def gather_add_sum_kernel(width: int, has_base: bool, has_a: bool, has_b: bool, has_sum: bool, dtype,
                          base_dtype=None):
    """out[r] = base_in[r] + src_a_in[index_a[r]] + src_b_in[index_b[r]] (backward of the
    scatter-sums: each row receives the gradient of the sums it was added into), and
    sum_out[j] += out[:, j] summed over the rows (the output layer's bias gradient). Chunked.

    ``base_in`` (the gradient of the block's output, as autograd hands it over) is read in its
    own dtype (``base_dtype``, default ``dtype``) and strides: no cast or copy before."""
    W = width
    RB = ROW_BATCH
    T = dtype
    Tb = dtype if base_dtype is None else base_dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def gather_add_sum(
        # Data in:
        base_in: wp.array2d(dtype=Tb),
        src_a_in: wp.array2d(dtype=T),
        index_a: wp.array(dtype=wp.int32),
        src_b_in: wp.array2d(dtype=T),
        index_b: wp.array(dtype=wp.int32),
        rows: int,
        chunk: int,
        # Data out:
        out: wp.array2d(dtype=T),
        sum_out: wp.array(dtype=A),
    ):
        i = wp.tid()
        ci = i // W
        j = i - ci * W
        r0 = ci * chunk
        r1 = wp.min(r0 + chunk, rows)
        acc = A(0.0)
        for rb in range(r0, r1, RB):  # RB rows loaded, then stored
            ys = wp.vector(length=RB, dtype=T)
            for k in range(RB):
                r = rb + k
                if r < r1:
                    x = A(0.0)
                    if wp.static(has_base):
                        x += A(base_in[r, j])
                    if wp.static(has_a):
                        x += A(src_a_in[index_a[r], j])
                    if wp.static(has_b):
                        x += A(src_b_in[index_b[r], j])
                    ys[k] = T(x)
            for k in range(RB):
                r = rb + k
                if r < r1:
                    out[r, j] = ys[k]
                    acc += A(ys[k])
        if wp.static(has_sum):
            wp.atomic_add(sum_out, j, acc)

    return gather_add_sum


@functools.cache
def scatter_edges_kernel(width: int, has_sender: bool, has_receiver: bool, has_global: bool, src_dtype,
                         dst_dtype):
    """Backward of the split first layer of the edge update, one read of each gradient row:
    nodes_out[senders[r], :W] += g_in[r]; nodes_out[receivers[r], RCV:RCV+W] += g_in[r];
    globals_out[edge_graph[r]] += g_in[r] (atomic). RCV = W when both node pieces exist, else 0."""
    V = vec(width)
    WV = width // V
    RCV_COL = width if has_sender else 0
    S = src_dtype
    D = dst_dtype

    @wp.kernel(module="unique", module_options=_options())
    def scatter_edges(
        # Data in:
        g_in: wp.array2d(dtype=S),
        senders: wp.array(dtype=wp.int32),
        receivers: wp.array(dtype=wp.int32),
        edge_graph: wp.array(dtype=wp.int32),
        # Data out:
        nodes_out: wp.array2d(dtype=D),
        globals_out: wp.array2d(dtype=D),
    ):
        i = wp.tid()
        r = i // WV
        j0 = i - r * WV
        if wp.static(has_sender):
            s = senders[r]
        if wp.static(has_receiver):
            q = receivers[r]
        if wp.static(has_global):
            g = edge_graph[r]
        xs = wp.vector(length=V, dtype=D)
        for k in range(V):
            xs[k] = D(g_in[r, j0 + k * WV])
        for k in range(V):
            j = j0 + k * WV
            x = xs[k]
            if wp.static(has_sender):
                wp.atomic_add(nodes_out, s, j, x)
            if wp.static(has_receiver):
                wp.atomic_add(nodes_out, q, RCV_COL + j, x)
            if wp.static(has_global):
                wp.atomic_add(globals_out, g, j, x)

    return scatter_edges


# -- aligned weight blocks ----------------------------------------------------------------------
@functools.cache
def unpack_kernel(segments: tuple, cols: int, mat_dtype, flat_dtype, accumulate: bool):
    """The gradient of a first-layer weight from the aligned blocks its GEMM wrote (``prep_kernel``'s
    layout): ``mat[i, c] = flat[off + (row0 + i) * stride + (c - col0)]`` (``accumulate``: +=, into
    a gradient accumulator) for the columns c in [col0, col0 + width) of each segment (col0,
    width, off, stride, row0) of a row-major [rows, cols] matrix; four segments at most (edges,
    sender / receiver nodes stacked, globals). One thread per matrix element."""
    segs = list(segments) + [(0, 0, 0, 1, 0)] * (4 - len(segments))
    (C0, W0, O0, S0, R0), (C1, W1, O1, S1, R1), (C2, W2, O2, S2, R2), (C3, W3, O3, S3, R3) = segs
    M = mat_dtype
    F = flat_dtype

    @wp.kernel(module="unique", module_options=_options())
    def unpack(
        mat: wp.array2d(dtype=M),
        flat: wp.array(dtype=F),
    ):
        t = wp.tid()
        i = t // cols
        c = t - i * cols
        d = int(-1)
        if wp.static(W0 > 0):
            if c >= C0 and c < C0 + W0:
                d = O0 + (R0 + i) * S0 + (c - C0)
        if wp.static(W1 > 0):
            if c >= C1 and c < C1 + W1:
                d = O1 + (R1 + i) * S1 + (c - C1)
        if wp.static(W2 > 0):
            if c >= C2 and c < C2 + W2:
                d = O2 + (R2 + i) * S2 + (c - C2)
        if wp.static(W3 > 0):
            if c >= C3 and c < C3 + W3:
                d = O3 + (R3 + i) * S3 + (c - C3)
        if d >= 0:
            if wp.static(accumulate):
                mat[i, c] = mat[i, c] + M(flat[d])
            else:
                mat[i, c] = M(flat[d])

    return unpack


PREP_SLOTS = 6  # block segments of ``prep_kernel``: edge first layer 4 (edges, senders, receivers, globals) + node + global
PREP_VEC = 8    # elements per thread of ``prep_kernel``


def prep_threads(n_cast: int, blocks: tuple, max_vec: int = PREP_VEC) -> tuple:
    """(threads of the cast region, total launch size) of ``prep_kernel``."""
    nc = -(-n_cast // max_vec)
    return nc, nc + sum(-(-rows * stride // max_vec) for _, rows, _, stride, _ in blocks)


def _prep_block(dst_off: int, n: int, stride: int, width: int, col0: int, mat_dtype, dtype, max_vec: int):
    """One block segment of ``prep_kernel``: dst[d0 + dst_off + i * stride + c] = mat[i, col0 + c]
    for c < width, 0 for width <= c < stride (the padding), for the ``max_vec`` elements
    j = j0 + k * NT (k < max_vec, j < n = rows * stride) of the thread j0 of NT."""
    O, S, W, C, M, T, V = dst_off, stride, width, col0, mat_dtype, dtype, max_vec
    NT = -(-n // V)

    @wp.func
    def block(mat: wp.array2d(dtype=M), j0: int, d0: int, dst: wp.array(dtype=T)):
        xs = wp.vector(length=V, dtype=T)  # zero: the padding
        for k in range(V):  # every load first, then the stores
            j = j0 + k * NT
            if j < n:
                i = j // S
                c = j - i * S
                if c < W:
                    xs[k] = T(mat[i, C + c])
        for k in range(V):
            j = j0 + k * NT
            if j < n:
                dst[d0 + O + j] = xs[k]

    return block


@functools.cache
def prep_kernel(blocks: tuple, mat_dtype, dtype, max_vec: int = PREP_VEC):
    """A GN block's parameters made ready for its GEMMs, in one launch (every forward, since the
    optimizer changes them): the first ``n_cast_threads`` threads cast ``src`` (the block's
    parameters as one flat span, FlatAdam's buffer) to the compute dtype, ``dst[i] = src[i]``
    for i < n_cast; the rest write the first-layer weights as aligned, zero-padded blocks from
    up to ``PREP_SLOTS`` block segments ``blocks`` = ((dst_off, rows, width, stride, col0), ...):
    rows x stride elements each at ``dst[d0 + dst_off ...]``, read from columns
    [col0, col0 + width) of the segment's matrix ``mat_k``. Each thread owns ``max_vec``
    elements strided by its region's thread count (coalesced; loads before stores). Launch
    ``prep_threads(n_cast, blocks)[1]`` threads. Replaces a cast launch and, per first layer, a
    zero fill and a pack launch."""
    V = max_vec
    bs = list(blocks) + [(0, 0, 0, 1, 0)] * (PREP_SLOTS - len(blocks))
    counts = [-(-rows * stride // V) for _, rows, _, stride, _ in bs]
    starts = [0]
    for n in counts:
        starts.append(starts[-1] + n)
    S0, S1, S2, S3, S4, S5, S6 = starts
    N0, N1, N2, N3, N4, N5 = counts
    f0, f1, f2, f3, f4, f5 = (_prep_block(b[0], b[1] * b[3], b[3], b[2], b[4], mat_dtype, dtype, V) for b in bs)
    M = mat_dtype
    T = dtype

    @wp.kernel(module="unique", module_options=_options())
    def prep(src: wp.array(dtype=M), n_cast: int, n_cast_threads: int, d0: int,
             mat_0: wp.array2d(dtype=M), mat_1: wp.array2d(dtype=M), mat_2: wp.array2d(dtype=M),
             mat_3: wp.array2d(dtype=M), mat_4: wp.array2d(dtype=M), mat_5: wp.array2d(dtype=M),
             dst: wp.array(dtype=T)):
        t = wp.tid()
        if t < n_cast_threads:
            xs = wp.vector(length=V, dtype=T)
            for k in range(V):
                i = t + k * n_cast_threads
                if i < n_cast:
                    xs[k] = T(src[i])
            for k in range(V):
                i = t + k * n_cast_threads
                if i < n_cast:
                    dst[i] = xs[k]
        else:
            b = t - n_cast_threads
            if wp.static(N0 > 0):
                if b < S1:
                    f0(mat_0, b, d0, dst)
            if wp.static(N1 > 0):
                if b >= S1 and b < S2:
                    f1(mat_1, b - S1, d0, dst)
            if wp.static(N2 > 0):
                if b >= S2 and b < S3:
                    f2(mat_2, b - S2, d0, dst)
            if wp.static(N3 > 0):
                if b >= S3 and b < S4:
                    f3(mat_3, b - S3, d0, dst)
            if wp.static(N4 > 0):
                if b >= S4 and b < S5:
                    f4(mat_4, b - S4, d0, dst)
            if wp.static(N5 > 0):
                if b >= S5 and b < S6:
                    f5(mat_5, b - S5, d0, dst)

    return prep


# -- fp16x3: float32-accurate GEMMs from three fp16 tensor-core products ---------------------------
# threads per row of ``emu_split_kernel`` on CUDA (one warp, one block per row). Paper core's
# fp16x3 forward at batch 4096 on an H200, captured: 32 threads 3.44 ms, 64 3.57, 128 3.96
EMU_BLOCK = 32
EMU_VEC = 4     # column groups each thread loads before it computes and stores


def emu_group(width: int) -> int:
    """Columns per vector load / store of ``emu_split_kernel`` (16-byte float32 loads)."""
    return 4 if width % 4 == 0 else 2 if width % 2 == 0 else 1


@functools.cache
def emu_split_kernel(width: int, epilogue: bool, relu: bool, write_f32: bool, split: bool, weights: bool):
    """One float32 row per block (``wp.launch_tiled``, dim = rows; any block size, 1 on the CPU):
    the operand pieces of the fp16x3 GEMM, optionally after the epilogue of the GEMM before.

    ``epilogue``: y = src * row_inv[r] * col_inv[c] + bias[c] (the previous fp16x3 GEMM's
    output unscaled), ReLU if ``relu``, written to ``dst`` if ``write_f32`` (may be ``src``:
    each thread reads its elements before it writes them); else y = src.
    ``split``: the row's scale s = 2^k puts its largest |y| in [2^14, 2^15) (fp16's range holds
    y * s and its remainder; k from the exponent bits, no log), hi = fp16(y * s),
    lo = fp16(y * s - hi), written as pieces[r] = [hi | lo | hi] (activations) or
    [hi | hi | lo] (``weights``), so that one GEMM of pieces over 3 * width columns sums
    hi*Whi + lo*Whi + hi*Wlo; ``inv_out[r]`` = 1 / s (exact: a power of two). The row maximum
    is a block reduction (tile max). NaN stays NaN; an all-zero row gets any scale.

    Arrays are of ``emu_group(width)``-vectors (row-major tensors viewed [rows, cols / g, g]):
    each thread loads 16 bytes at a time, consecutive threads consecutive groups."""
    g = emu_group(width)
    G = width // g
    V = EMU_VEC
    F = wp.types.vector(g, wp.float32)
    H = wp.types.vector(g, wp.float16)
    R = wp.types.matrix(shape=(V, g), dtype=wp.float32)  # the V groups a thread holds

    @wp.func
    def unscale(y: F, ri: wp.float32, ci: F, b: F):
        out = F()
        for j in range(g):
            x = y[j] * ri * ci[j] + b[j]
            if wp.static(relu):
                x = wp.max(x, wp.float32(0.0))
            out[j] = x
        return out

    @wp.kernel(module="unique", module_options=_options())
    def emu_split(src: wp.array2d(dtype=F), row_inv: wp.array(dtype=wp.float32), col_inv: wp.array(dtype=F),
                  bias: wp.array(dtype=F), dst: wp.array2d(dtype=F), pieces: wp.array2d(dtype=H),
                  inv_out: wp.array(dtype=wp.float32)):
        r, lane = wp.tid()
        nb = wp.block_dim()
        ri = wp.float32(1.0)
        if wp.static(epilogue):
            ri = row_inv[r]
        m = wp.float32(0.0)
        for c0 in range(0, G, nb * V):
            ys = R()
            for k in range(V):
                c = c0 + k * nb + lane
                if c < G:
                    ys[k] = src[r, c]
            for k in range(V):
                c = c0 + k * nb + lane
                if c < G:
                    y = ys[k]
                    if wp.static(epilogue):
                        y = unscale(y, ri, col_inv[c], bias[c])
                        if wp.static(write_f32):
                            dst[r, c] = y
                    for j in range(g):
                        m = wp.max(m, wp.abs(y[j]))
        if wp.static(split):
            mx = wp.tile_extract(wp.tile_max(wp.tile(m)), 0)
            e = (wp.cast(mx, wp.int32) >> 23) & 255
            eb = wp.clamp(268 - e, 1, 253)  # 2^(eb - 127) * mx in [2^14, 2^15)
            s = wp.cast(eb << 23, wp.float32)
            if lane == 0:
                inv_out[r] = wp.cast((254 - eb) << 23, wp.float32)
            for c0 in range(0, G, nb * V):
                ys = R()
                for k in range(V):
                    c = c0 + k * nb + lane
                    if c < G:
                        if wp.static(epilogue and write_f32):
                            ys[k] = dst[r, c]
                        else:
                            ys[k] = src[r, c]
                for k in range(V):
                    c = c0 + k * nb + lane
                    if c < G:
                        y = ys[k]
                        if wp.static(epilogue and not write_f32):
                            y = unscale(y, ri, col_inv[c], bias[c])
                        hi = H()
                        lo = H()
                        for j in range(g):
                            x = y[j] * s
                            h = wp.float16(x)
                            hi[j] = h
                            lo[j] = wp.float16(x - wp.float32(h))
                        pieces[r, c] = hi
                        if wp.static(weights):
                            pieces[r, G + c] = hi
                            pieces[r, 2 * G + c] = lo
                        else:
                            pieces[r, G + c] = lo
                            pieces[r, 2 * G + c] = hi

    return emu_split
