"""Warp kernels for the graph-structured work of a GN block (the "split" path).

The dense hidden layers of the edge, node and global MLPs run as BLAS GEMMs (torch.mm); these
kernels do everything around them that depends on the graph:

- ``first_layer``: the split first layer. ``W.[e; v_s; v_r; u] = W_e e + W_s v_s + W_r v_r + W_u u``:
  the node projections ``v @ [W_s; W_r]^T`` and global projections ``u @ W_u^T`` are GEMMs over
  nodes / graphs (done once per node / graph, not once per edge); this kernel gathers them per
  row, adds the row's own projection and the bias, and applies ReLU, in one pass.
- ``bias_act``: bias + ReLU epilogue of a hidden GEMM.
- ``output_epilogue``: bias of the output GEMM, fused with atomic scatter-sums of the result
  (edges -> receivers, edges -> graphs, nodes -> graphs).
- ``segment_sum``: the deterministic aggregation: each destination row sums its segment of a
  CSR layout (rows sorted by destination) in a fixed order.
- ``scatter_add``: atomic scatter-sum of rows (backward of the gathers, default mode).
- ``gather_add``: backward of the scatters (sum of gathered rows).
- ``relu_grad``: backward of ReLU, from the saved activation.

Each factory is specialized on the feature width (a compile-time constant), on which inputs exist
(a block built without an input has no code for it: ``wp.static`` removes the branch; the array
argument of a disabled input is a zero-size placeholder that is never read) and on the storage
dtype. Arithmetic accumulates in float32 (float64 for float64 storage). Factories are cached, so
a kernel is built once per configuration.

Launches are 1-D, ``dim = launch_dim(rows, width)``: each thread owns ``vec(width)`` consecutive
features of one row (up to 4: more bytes in flight per thread), neighbouring threads the next
ones, so accesses coalesce; with the width a compile-time constant, the row / column split of the
thread index is a multiply-shift, not the 64-bit division of a 2-D launch. Kernels that update
in place take the same tensor as ``*_in`` and ``*_out``; each thread reads its elements before
writing them.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = [
    "acc_dtype",
    "vec",
    "launch_dim",
    "first_layer_kernel",
    "bias_act_kernel",
    "output_epilogue_kernel",
    "segment_sum_kernel",
    "scatter_add_kernel",
    "gather_add_kernel",
    "relu_grad_kernel",
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
        j0 = (i - r * WV) * V
        if wp.static(has_sender):
            s = senders[r]
        if wp.static(has_receiver):
            q = receivers[r]
        if wp.static(has_global):
            g = row_graph[r]
        for k in range(V):
            j = j0 + k
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
            hidden_out[r, j] = T(x)

    return first_layer


@functools.cache
def bias_act_kernel(width: int, relu: bool, dtype):
    """act_out[r, j] = act(pre_in[r, j] + bias[j]); may run in place."""
    V = vec(width)
    WV = width // V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def bias_act(
        # Data in:
        pre_in: wp.array2d(dtype=T),
        # Parameters:
        bias: wp.array(dtype=T),
        # Data out:
        act_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r = i // WV
        j0 = (i - r * WV) * V
        for k in range(V):
            j = j0 + k
            x = A(pre_in[r, j]) + A(bias[j])
            if wp.static(relu):
                x = wp.max(x, A(0.0))
            act_out[r, j] = T(x)

    return bias_act


@functools.cache
def output_epilogue_kernel(width: int, add_bias: bool, scatter_a: bool, scatter_b: bool, dtype):
    """out[r] = pre_in[r] + bias; sum_a_out[index_a[r]] += out[r]; sum_b_out[index_b[r]] += out[r].

    The scatter-sums are atomic adds in the accumulation dtype.
    """
    V = vec(width)
    WV = width // V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def output_epilogue(
        # Data in:
        pre_in: wp.array2d(dtype=T),
        index_a: wp.array(dtype=wp.int32),
        index_b: wp.array(dtype=wp.int32),
        # Parameters:
        bias: wp.array(dtype=T),
        # Data out:
        out: wp.array2d(dtype=T),
        sum_a_out: wp.array2d(dtype=A),
        sum_b_out: wp.array2d(dtype=A),
    ):
        i = wp.tid()
        r = i // WV
        j0 = (i - r * WV) * V
        if wp.static(scatter_a):
            a = index_a[r]
        if wp.static(scatter_b):
            b = index_b[r]
        for k in range(V):
            j = j0 + k
            x = A(pre_in[r, j])
            if wp.static(add_bias):
                x += A(bias[j])
                out[r, j] = T(x)
            # the sums add the rounded stored value, so they equal the sum of what is returned
            y = A(T(x))
            if wp.static(scatter_a):
                wp.atomic_add(sum_a_out, a, j, y)
            if wp.static(scatter_b):
                wp.atomic_add(sum_b_out, b, j, y)

    return output_epilogue


@functools.cache
def segment_sum_kernel(width: int, has_perm: bool, src_dtype, dst_dtype):
    """sum_out[s, dst_col + j] = sum over p in [offsets[s], offsets[s+1]) of src_in[perm[p], src_col + j].

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
        j0 = (i - s * WV) * V
        for k in range(V):
            j = j0 + k
            acc = A(0.0)
            for p in range(offsets[s], offsets[s + 1]):
                if wp.static(has_perm):
                    acc += A(src_in[perm[p], src_col + j])
                else:
                    acc += A(src_in[p, src_col + j])
            sum_out[s, dst_col + j] = D(acc)

    return segment_sum


@functools.cache
def scatter_add_kernel(width: int, src_dtype, dst_dtype):
    """sum_out[index[r], dst_col + j] += src_in[r, src_col + j] (atomic)."""
    V = vec(width)
    WV = width // V
    S = src_dtype
    D = dst_dtype

    @wp.kernel(module="unique", module_options=_options())
    def scatter_add(
        # Data in:
        src_in: wp.array2d(dtype=S),
        index: wp.array(dtype=wp.int32),
        src_col: int,
        dst_col: int,
        # Data out:
        sum_out: wp.array2d(dtype=D),
    ):
        i = wp.tid()
        r = i // WV
        j0 = (i - r * WV) * V
        d = index[r]
        for k in range(V):
            j = j0 + k
            wp.atomic_add(sum_out, d, dst_col + j, D(src_in[r, src_col + j]))

    return scatter_add


@functools.cache
def gather_add_kernel(width: int, has_base: bool, has_a: bool, has_b: bool, dtype):
    """out[r] = base_in[r] + src_a_in[index_a[r]] + src_b_in[index_b[r]] (backward of the
    scatter-sums: each row receives the gradient of the sums it was added into)."""
    V = vec(width)
    WV = width // V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=_options())
    def gather_add(
        # Data in:
        base_in: wp.array2d(dtype=T),
        src_a_in: wp.array2d(dtype=T),
        index_a: wp.array(dtype=wp.int32),
        src_b_in: wp.array2d(dtype=T),
        index_b: wp.array(dtype=wp.int32),
        # Data out:
        out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r = i // WV
        j0 = (i - r * WV) * V
        if wp.static(has_a):
            a = index_a[r]
        if wp.static(has_b):
            b = index_b[r]
        for k in range(V):
            j = j0 + k
            x = A(0.0)
            if wp.static(has_base):
                x += A(base_in[r, j])
            if wp.static(has_a):
                x += A(src_a_in[a, j])
            if wp.static(has_b):
                x += A(src_b_in[b, j])
            out[r, j] = T(x)

    return gather_add


@functools.cache
def relu_grad_kernel(width: int, dtype):
    """grad_out[r, j] = grad_in[r, j] where act_in[r, j] > 0, else 0 (ReLU backward from the
    saved activation, as torch does); may run in place."""
    V = vec(width)
    WV = width // V
    T = dtype

    @wp.kernel(module="unique", module_options=_options())
    def relu_grad(
        # Data in:
        act_in: wp.array2d(dtype=T),
        grad_in: wp.array2d(dtype=T),
        # Data out:
        grad_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r = i // WV
        j0 = (i - r * WV) * V
        for k in range(V):
            j = j0 + k
            g = T(0.0)
            if act_in[r, j] > T(0.0):
                g = grad_in[r, j]
            grad_out[r, j] = g

    return relu_grad
