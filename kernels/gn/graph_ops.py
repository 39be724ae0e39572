"""Warp kernels for the graph-structured work of a GN block on the blas path (launched by
``gnwarp/gn/graph_ops.py``).

The dense layers of the edge, node and global MLPs run as BLAS GEMMs (cuBLAS / CPU BLAS through
torch, bias and ReLU in the GEMM's epilogue); these kernels do everything around them that
depends on the graph:

- ``project``: the edge update's first layer in "project" mode. ``W.[e; v_s; v_r; u] = W_e e +
  W_s v_s + W_r v_r + W_u u``: the node projections ``v @ [W_s; W_r]^T`` and global projections
  ``u @ W_u^T`` are GEMMs over nodes / graphs (done once per node / graph, not once per edge);
  this kernel gathers them per edge, adds the edge's own projection and the bias, and applies
  ReLU, in one pass. ``scatter_edges`` is its backward: each gradient row added to its sender's,
  receiver's and graph's rows.
- ``concat``: the input rows of an update's first layer side by side in the compute dtype,
  gathered where a piece is read by index (the edge update's [e, v[sender], v[receiver],
  u[graph]], the node update's [v, sum of received edges, u[graph]], the global update's
  [u, sum v', sum e']): the first layer is then one GEMM. Its launch is laid out by piece
  (``concat_threads``), not by ``launch_dim``. ``route`` is its adjoint: the gradient of an
  update's input rows handed back to its inputs (stored, or added by sender / receiver /
  graph) in one pass.
- ``scatter_out``: the output epilogue of the edge and node updates: the returned copy in the
  output dtype and the atomic scatter-sums (edges -> receivers, edges -> graphs, nodes -> graphs)
  in one pass. ``gather_add_sum`` is its backward (sum of gathered rows), fused with the column
  sums of the result (the output layer's bias gradient).
- ``segment_sum``: the deterministic aggregation: each destination row sums its segment of a
  CSR layout (rows sorted by destination) in a fixed order.

Launch geometry, specialization and the loads-before-stores rule: ``kernels/gn/common.py``.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS, ROW_BATCH, acc_dtype, vec

__all__ = [
    "project_kernel", "segment_sum_kernel", "CONCAT_VEC", "concat_spans", "concat_piece_threads",
    "concat_rows_per_block", "concat_threads", "concat_kernel", "scatter_out_kernel", "ROUTE_STORE",
    "ROUTE_ADD", "route_kernel", "gather_add_sum_kernel", "scatter_edges_kernel",
]


@functools.cache
def project_kernel(width: int, dtype, *, direct: bool, sender: bool, receiver: bool, globals_: bool,
                   relu: bool):
    """The edge update's first layer from projections: hidden_out[r] = act(direct_in[r] +
    node_proj_in[senders_in[r], :W] + node_proj_in[receivers_in[r], S:S+W] +
    global_proj_in[row_graph_in[r]] + bias).

    ``node_proj_in`` holds the sender projection in columns [0, W) and the receiver projection
    after it (columns [W, 2W) when both exist).
    """
    has_direct, has_sender, has_receiver, has_global = direct, sender, receiver, globals_
    W = width
    RCV_COL = W if has_sender else 0
    V = vec(width)
    WV = width // V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=OPTIONS)
    def project(
        # Data in:
        direct_in: wp.array2d(dtype=T),
        node_proj_in: wp.array2d(dtype=T),
        global_proj_in: wp.array2d(dtype=T),
        senders_in: wp.array(dtype=wp.int32),
        receivers_in: wp.array(dtype=wp.int32),
        row_graph_in: wp.array(dtype=wp.int32),
        # Parameters:
        bias: wp.array(dtype=T),
        # Data out:
        hidden_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r = i // WV
        j0 = i - r * WV
        if wp.static(has_sender):
            s = senders_in[r]
        if wp.static(has_receiver):
            q = receivers_in[r]
        if wp.static(has_global):
            g = row_graph_in[r]
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

    return project


@functools.cache
def segment_sum_kernel(width: int, src_dtype, dst_dtype, *, perm: bool, accumulate: bool = False):
    """sum_out[s, dst_col + j] = sum over p in [offsets_in[s], offsets_in[s+1]) of
    src_in[perm_in[p], src_col + j]
    (``accumulate``: added to what sum_out holds).

    Sums in a fixed order (deterministic, bitwise reproducible). Without ``perm`` the segments
    are contiguous row ranges of ``src_in`` (nodes or edges of one graph). Rows: segments.
    """
    has_perm = perm
    V = vec(width)
    WV = width // V
    S = src_dtype
    D = dst_dtype
    A = acc_dtype(dst_dtype)

    @wp.kernel(module="unique", module_options=OPTIONS)
    def segment_sum(
        # Data in:
        src_in: wp.array2d(dtype=S),
        perm_in: wp.array(dtype=wp.int32),
        offsets_in: wp.array(dtype=wp.int32),
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
            for p in range(offsets_in[s], offsets_in[s + 1]):
                if wp.static(has_perm):
                    acc += A(src_in[perm_in[p], src_col + j])
                else:
                    acc += A(src_in[p, src_col + j])
            if wp.static(accumulate):
                sum_out[s, dst_col + j] = sum_out[s, dst_col + j] + D(acc)
            else:
                sum_out[s, dst_col + j] = D(acc)

    return segment_sum



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
    column: cat_out[r, offset + c] = p_in[row, c] for c < width, 0 for width <= c < span."""
    W, S, G, Ti, T, K, E = width, span, gathered, in_dtype, dtype, out_width, offset
    N, V = concat_piece_threads(span, max_vec)
    V = max(V, 1)  # (an absent piece is never called)

    @wp.func
    def copy_piece(
        # Data in:
        p_in: wp.array(dtype=Ti),
        index_in: wp.array(dtype=wp.int32),
        r: int,
        c0: int,
        # Data out:
        cat_out: wp.array(dtype=T),
    ):
        b = r * W
        if wp.static(G):
            b = index_in[r] * W
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
                cat_out[o + k * N] = xs[k]
            elif wp.static(k * N < S):
                if c0 + k * N < S:
                    cat_out[o + k * N] = xs[k]

    return copy_piece


@functools.cache
def concat_kernel(widths: tuple, gathered: tuple, in_dtypes: tuple, dtype, out_width: int, *,
                  max_vec: int = CONCAT_VEC):
    """cat_out[r] = [p0_in[r0], p1_in[r1], p2_in[r2], p3_in[r3], 0...] (columns side by side, cast
    to ``dtype``, zeros up to ``out_width``); a piece of width 0 is absent; a gathered piece k
    reads row ``index_k_in[r]``, the others row ``r``.

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
    branches. Measured on an H200 (bench/probes/concat_probe.py, bench/results/probes/concat_probe_nvidia-h200.md,
    the paper core's edge rows at batch 4096, fp32 -> fp16): a kernel where every thread tests
    all four pieces for each of its 8 columns issues a predicated load per piece and column and
    is bound by the load/store pipe (ncu: 96% busy, half the lanes predicated off): 162 us for
    the second block's 73728 x 672 rows, where this kernel takes 81 us."""
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

    @wp.kernel(module="unique", module_options=OPTIONS)
    def concat(
        # Data in (flat row-major):
        p0_in: wp.array(dtype=T0),
        p1_in: wp.array(dtype=T1),
        p2_in: wp.array(dtype=T2),
        p3_in: wp.array(dtype=T3),
        index_0_in: wp.array(dtype=wp.int32),
        index_1_in: wp.array(dtype=wp.int32),
        index_2_in: wp.array(dtype=wp.int32),
        index_3_in: wp.array(dtype=wp.int32),
        rows: int,
        # Data out (flat row-major):
        cat_out: wp.array(dtype=T),
    ):
        i = wp.tid()
        rb = i // NT
        t = i - rb * NT
        if wp.static(W0 > 0):
            if t < A1:
                j = t // N0
                r = rb * R + j
                if r < rows:
                    f0(p0_in, index_0_in, r, t - j * N0, cat_out)
        if wp.static(W1 > 0):
            if t >= A1 and t < A2:
                j = (t - A1) // N1
                r = rb * R + j
                if r < rows:
                    f1(p1_in, index_1_in, r, t - A1 - j * N1, cat_out)
        if wp.static(W2 > 0):
            if t >= A2 and t < A3:
                j = (t - A2) // N2
                r = rb * R + j
                if r < rows:
                    f2(p2_in, index_2_in, r, t - A2 - j * N2, cat_out)
        if wp.static(W3 > 0):
            if t >= A3:
                j = (t - A3) // N3
                r = rb * R + j
                if r < rows:
                    f3(p3_in, index_3_in, r, t - A3 - j * N3, cat_out)

    return concat


@functools.cache
def scatter_out_kernel(width: int, dtype, out_dtype, *, scatter_a: bool, scatter_b: bool, copy: bool):
    """copy_out[r] = x_in[r] (in the output dtype); sum_a_out[index_a_in[r]] += x_in[r];
    sum_b_out[index_b_in[r]] += x_in[r] (atomic adds in the accumulation dtype).

    The output epilogue of the edge and node updates (the output bias is already in ``x_in``,
    added by the GEMM's epilogue): the sums add the stored values, so they equal the sum of what
    is returned."""
    V = vec(width)
    WV = width // V
    T = dtype
    O = out_dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=OPTIONS)
    def scatter_out(
        # Data in:
        x_in: wp.array2d(dtype=T),
        index_a_in: wp.array(dtype=wp.int32),
        index_b_in: wp.array(dtype=wp.int32),
        # Data out:
        copy_out: wp.array2d(dtype=O),
        sum_a_out: wp.array2d(dtype=A),
        sum_b_out: wp.array2d(dtype=A),
    ):
        i = wp.tid()
        r = i // WV
        j0 = i - r * WV
        if wp.static(scatter_a):
            a = index_a_in[r]
        if wp.static(scatter_b):
            b = index_b_in[r]
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


ROUTE_STORE, ROUTE_ADD = "store", "add"


def _route_piece(col: int, mode: str, indexed: bool, in_dtype, out_dtype):
    """One piece of ``route_kernel``: column ``col + j`` of row r of the gradient stored at
    g_out[r, j] or added (atomic) at g_out[index_in[r] if ``indexed`` else r, j]."""
    C, Ti, O = col, in_dtype, out_dtype

    @wp.func
    def route(
        # Data in:
        g_in: wp.array2d(dtype=Ti),
        index_in: wp.array(dtype=wp.int32),
        r: int,
        j: int,
        # Data out:
        g_out: wp.array2d(dtype=O),
    ):
        x = O(g_in[r, C + j])
        if wp.static(mode == ROUTE_STORE):
            g_out[r, j] = x
        else:
            d = r
            if wp.static(indexed):
                d = index_in[r]
            wp.atomic_add(g_out, d, j, x)

    return route


@functools.cache
def route_kernel(pieces: tuple, in_dtype):
    """Adjoint of ``concat_kernel``: the gradient of concatenated input rows ``g_in`` handed back
    to the inputs it is built from, piece by piece, in one pass. ``pieces``: up to four
    (col, width, mode, indexed, out_dtype): columns [col, col + width) of each row r are stored
    at ``g_k_out[r]`` (mode ``ROUTE_STORE``: the edge update's own input) or added, atomically,
    at ``g_k_out[index_k_in[r]]`` (``ROUTE_ADD`` with ``indexed``: the sender / receiver node
    columns, the graph's global columns) or at ``g_k_out[r]`` (``ROUTE_ADD``: a row-aligned input whose
    gradient also receives other pieces' sums). Columns of no piece (padding, or an input whose
    gradient is read in place) get no thread: launch ``rows * sum of widths`` threads, one per
    element, consecutive threads on consecutive columns of a row (coalesced loads and atomics).
    One launch per update, where separate launches would take one scatter per indexed piece, a
    per-graph segment sum, and the casts and adds that merge them (measured on an H200:
    bench/results/gn_block/NOTES.md)."""
    ps = list(pieces) + [(0, 0, ROUTE_STORE, False, in_dtype)] * (4 - len(pieces))
    W0, W1, W2, W3 = (p[1] for p in ps)
    A1, A2, A3 = W0, W0 + W1, W0 + W1 + W2
    WA = A3 + W3
    f0, f1, f2, f3 = (_route_piece(p[0], p[2], p[3], in_dtype, p[4]) for p in ps)
    O0, O1, O2, O3 = (p[4] for p in ps)
    Ti = in_dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def route(
        # Data in:
        g_in: wp.array2d(dtype=Ti),
        index_0_in: wp.array(dtype=wp.int32),
        index_1_in: wp.array(dtype=wp.int32),
        index_2_in: wp.array(dtype=wp.int32),
        index_3_in: wp.array(dtype=wp.int32),
        # Data out:
        g_0_out: wp.array2d(dtype=O0),
        g_1_out: wp.array2d(dtype=O1),
        g_2_out: wp.array2d(dtype=O2),
        g_3_out: wp.array2d(dtype=O3),
    ):
        t = wp.tid()
        r = t // WA
        c = t - r * WA
        if wp.static(W0 > 0):
            if c < A1:
                f0(g_in, index_0_in, r, c, g_0_out)
        if wp.static(W1 > 0):
            if c >= A1 and c < A2:
                f1(g_in, index_1_in, r, c - A1, g_1_out)
        if wp.static(W2 > 0):
            if c >= A2 and c < A3:
                f2(g_in, index_2_in, r, c - A2, g_2_out)
        if wp.static(W3 > 0):
            if c >= A3:
                f3(g_in, index_3_in, r, c - A3, g_3_out)

    return route



@functools.cache
def gather_add_sum_kernel(width: int, dtype, *, base: bool, gather_a: bool, gather_b: bool, bias_sum: bool,
                          base_dtype=None):
    """grad_out[r] = base_in[r] + src_a_in[index_a_in[r]] + src_b_in[index_b_in[r]] (backward of
    the scatter-sums: each row receives the gradient of the sums it is added into), and
    sum_out[j] += grad_out[:, j] summed over the rows (the output layer's bias gradient). Chunked.

    ``base_in`` (the gradient of the block's output, as autograd hands it over) is read in its
    own dtype (``base_dtype``, default ``dtype``) and strides: no cast or copy before."""
    has_base, has_a, has_b, has_sum = base, gather_a, gather_b, bias_sum
    W = width
    RB = ROW_BATCH
    T = dtype
    Tb = dtype if base_dtype is None else base_dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=OPTIONS)
    def gather_add_sum(
        # Data in:
        base_in: wp.array2d(dtype=Tb),
        src_a_in: wp.array2d(dtype=T),
        index_a_in: wp.array(dtype=wp.int32),
        src_b_in: wp.array2d(dtype=T),
        index_b_in: wp.array(dtype=wp.int32),
        rows: int,
        chunk: int,
        # Data out:
        grad_out: wp.array2d(dtype=T),
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
                        x += A(src_a_in[index_a_in[r], j])
                    if wp.static(has_b):
                        x += A(src_b_in[index_b_in[r], j])
                    ys[k] = T(x)
            for k in range(RB):
                r = rb + k
                if r < r1:
                    grad_out[r, j] = ys[k]
                    acc += A(ys[k])
        if wp.static(has_sum):
            wp.atomic_add(sum_out, j, acc)

    return gather_add_sum


@functools.cache
def scatter_edges_kernel(width: int, src_dtype, dst_dtype, *, sender: bool, receiver: bool, globals_: bool):
    """Backward of ``project_kernel`` (the edge update's first layer in "project" mode), one read of each gradient row:
    nodes_out[senders_in[r], :W] += g_in[r]; nodes_out[receivers_in[r], RCV:RCV+W] += g_in[r];
    globals_out[edge_graph_in[r]] += g_in[r] (atomic). RCV = W when both node pieces exist, else 0."""
    has_sender, has_receiver, has_global = sender, receiver, globals_
    V = vec(width)
    WV = width // V
    RCV_COL = width if has_sender else 0
    S = src_dtype
    D = dst_dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def scatter_edges(
        # Data in:
        g_in: wp.array2d(dtype=S),
        senders_in: wp.array(dtype=wp.int32),
        receivers_in: wp.array(dtype=wp.int32),
        edge_graph_in: wp.array(dtype=wp.int32),
        # Data out:
        nodes_out: wp.array2d(dtype=D),
        globals_out: wp.array2d(dtype=D),
    ):
        i = wp.tid()
        r = i // WV
        j0 = i - r * WV
        if wp.static(has_sender):
            s = senders_in[r]
        if wp.static(has_receiver):
            q = receivers_in[r]
        if wp.static(has_global):
            g = edge_graph_in[r]
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


