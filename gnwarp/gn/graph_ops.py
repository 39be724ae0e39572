"""The graph-shaped work of a GN block on the blas path, as Warp launches (``kernels/gn/graph_ops.py``):
an update's input rows gathered side by side (``concat``) and their gradient routed back
(``route``), the edge first layer from projections (``project``, ``project_grad``), the output
epilogue with its scatter-sums (``scatter_out``) and its backward (``gather_add``), and ordered
segment sums for per-graph and deterministic aggregation (``segment``).

Every function takes the block's ``ResolvedRun`` (compute / accumulation dtypes, determinism)."""
from __future__ import annotations

import torch

from gnwarp.gn.config import column_slices, pad
from gnwarp.gn.first_layer import padded
from gnwarp.interop import WP_DTYPE
from gnwarp.kernels.gn import common as C
from gnwarp.kernels.gn import graph_ops as K

__all__ = ["concat", "route", "scatter_out", "gather_add", "segment", "project", "project_grad"]


def concat(launch, run, rows, layout, pieces):
    """Input rows of an MLP whose first layer is one GEMM: the pieces of ``layout`` side by side
    in the compute dtype, zero-padded to ``pad`` columns, in one kernel. ``pieces``: {name:
    (tensor, index or None)}; a piece with an index is read at row ``index[r]``. A lone piece
    read in place is only padded (``padded``)."""
    cd = run.compute_dtype
    items = [(pieces[name][0], pieces[name][1], w) for name, w in layout]
    if len(items) == 1 and items[0][1] is None:
        return padded(items[0][0], cd)
    width = pad(sum(w for _, _, w in items))
    widths = tuple(w for _, _, w in items) + (0,) * (4 - len(items))
    threads = K.concat_threads(rows, widths, width)
    if max(rows * width, threads) >= 2 ** 31:  # element offsets and thread ids are int32
        raise ValueError(f"batch too large for one GN block launch: {rows} rows x {width} input columns "
                         f"({threads} threads) exceeds 2**31; split the batch")
    for (name, w), (t, _, _) in zip(layout, items):
        if t.dim() != 2 or t.shape[1] != w:  # the kernel reads rows of exactly ``w`` elements
            raise ValueError(f"GN block input {name!r}: expected {w} columns, got shape {tuple(t.shape)}")
    out = torch.empty(rows, width, dtype=cd, device=items[0][0].device)
    flat = [t.contiguous().view(-1) for t, _, _ in items]
    items += [(launch.placeholder(cd, 1), None, 0)] * (4 - len(items))
    flat += [t for t, _, _ in items[len(flat):]]
    kernel = K.concat_kernel(widths, tuple(i is not None for _, i, _ in items),
                             tuple(WP_DTYPE[t.dtype] for t, _, _ in items), run.wp_dtype, width)
    launch(kernel, threads, *flat,
           *(i if i is not None else launch.placeholder(torch.int32, 1) for _, i, _ in items), rows, out.view(-1))
    return out


def route(launch, run, g_x, layout, routes, store=()):
    """Backward of ``concat``: the gradient ``g_x`` of an update's input rows handed back to its
    inputs, in one ``route_kernel`` pass. ``routes``: {piece: (out, index, segments)}: the
    piece's columns of row r are added into ``out`` at row ``index[r]`` (atomic), or at row r
    when ``index`` is None; pieces named in ``store`` are stored at row r instead (no other
    piece writes there). Pieces not in ``routes`` are left alone (read in place by their
    consumers). Deterministic mode adds the indexed pieces by ordered segment sums
    (``segments`` = (CSR perm or None, offsets)) after the pass, one launch each."""
    if not routes:
        return
    cols = column_slices(layout)
    ph = launch.placeholder
    pieces, later = [], []
    for name, (out, index, segments) in routes.items():
        sl = cols[name]
        if run.deterministic and index is not None:
            later.append((sl, out, segments))
            continue
        mode = K.ROUTE_STORE if name in store else K.ROUTE_ADD
        pieces.append(((sl.start, sl.stop - sl.start, mode, index is not None, WP_DTYPE[out.dtype]), index, out))
    if pieces:
        rows, cols_total = g_x.shape[0], sum(p[0][1] for p in pieces)
        if rows * cols_total >= 2 ** 31:  # thread ids are int32
            raise ValueError(f"batch too large for one GN block launch: {rows} rows x {cols_total} gradient "
                             "columns exceeds 2**31; split the batch")
        kernel = K.route_kernel(tuple(p[0] for p in pieces), run.wp_dtype)
        n_pad = 4 - len(pieces)
        launch(kernel, rows * cols_total, g_x,
               *[p[1] if p[1] is not None else ph(torch.int32, 1) for p in pieces], *[ph(torch.int32, 1)] * n_pad,
               *[p[2] for p in pieces], *[ph(run.compute_dtype, 2)] * n_pad)
    for sl, out, (perm, offsets) in later:
        segment(launch, run, g_x, perm, offsets, out, sl.start, 0, sl.stop - sl.start, accumulate=True)


def scatter_out(launch, run, x, out_dtype, target):
    """The block's output ``x`` in ``out_dtype`` and its sum by receiver in one pass: atomic adds
    (with the dtype cast in the same kernel), or (deterministic) ordered segment sums after it.

    ``target``: (sum array or None, row -> destination index, CSR perm or None, CSR offsets)."""
    det = run.deterministic
    sums, idx, perm, offs = target
    scatter = sums is not None and not det
    copy = x.dtype != out_dtype
    if scatter:
        ph = launch.placeholder
        out = torch.empty(x.shape, dtype=out_dtype, device=x.device) if copy else x
        launch(K.scatter_out_kernel(x.shape[1], run.wp_dtype, WP_DTYPE[out_dtype], scatter_a=True, scatter_b=False,
                                    copy=copy),
               C.launch_dim(*x.shape), x, idx, ph(torch.int32, 1), out if copy else ph(out_dtype, 2), sums,
               ph(run.acc_dtype, 2))
    else:
        out = x.to(out_dtype)
    if det and sums is not None:
        segment(launch, run, x, perm, offs, sums)
    return out


def gather_add(launch, run, rows, width, base, a, b, gb):
    """(base + src_a[index_a] + src_b[index_b] over ``rows`` rows in the compute dtype, contiguous;
    whether ``gb`` got its column sums): one kernel, which reads ``base`` (an incoming gradient)
    in its own dtype and strides and adds the column sums of its result into ``gb`` (atomics)
    when given and not deterministic. Returns (base, False) when there is nothing to gather,
    cast or sum, (None, False) when all are None."""
    (src_a, idx_a), (src_b, idx_b) = a, b
    ph = launch.placeholder
    cd = run.compute_dtype
    fused = gb is not None and not run.deterministic
    if src_a is None and src_b is None:
        if base is None:
            return None, False
        if not fused and base.dtype == cd and base.is_contiguous():
            return base, False
    if base is not None and (base.dim() != 2 or base.shape != (rows, width)):
        raise ValueError(f"gradient of a GN block output: expected shape {(rows, width)}, got {tuple(base.shape)}")
    if base is not None and min(base.stride()) <= 0:  # broadcast (expanded) gradients: one real row
        base = base.contiguous()
    out = torch.empty(rows, width, dtype=cd, device=(src_a if src_a is not None else src_b if src_b is not None
                                                     else base).device)
    chunk = C.chunk_rows(rows, width)
    kernel = K.gather_add_sum_kernel(width, run.wp_dtype, base=base is not None, gather_a=src_a is not None,
                                     gather_b=src_b is not None, bias_sum=fused,
                                     base_dtype=WP_DTYPE[base.dtype] if base is not None and base.dtype != cd else None)
    launch(kernel, C.chunk_dim(rows, width, chunk),
           base if base is not None else ph(cd, 2), src_a if src_a is not None else ph(cd, 2),
           idx_a if src_a is not None else ph(torch.int32, 1), src_b if src_b is not None else ph(cd, 2),
           idx_b if src_b is not None else ph(torch.int32, 1), rows, chunk, out,
           gb if fused else ph(run.acc_dtype, 1))
    return out, fused


def segment(launch, run, src, perm, offsets, out, src_col=0, dst_col=0, width=None, accumulate=False):
    """out[s, dst_col:dst_col + width] (+)= the sum of rows [offsets[s], offsets[s+1]) of ``src``
    (through ``perm`` when given, from ``src_col``): ordered, deterministic sums."""
    W = src.shape[1] if width is None else width
    k = K.segment_sum_kernel(W, WP_DTYPE[src.dtype], WP_DTYPE[out.dtype], perm=perm is not None, accumulate=accumulate)
    launch(k, C.launch_dim(out.shape[0], W), src, perm if perm is not None else launch.placeholder(torch.int32, 1),
           offsets, src_col, dst_col, out)


def project(launch, run, gi, direct, node_proj, glob_proj, sender: bool, receiver: bool, bias, relu: bool):
    """The edge update's first layer in "project" mode: [E, H] rows direct[r] + node_proj[sender]
    + node_proj[receiver] (receiver columns after the sender's) + glob_proj[graph] + bias, ReLU if
    ``relu``, in one pass; ``direct`` / ``node_proj`` / ``glob_proj`` may be None (absent)."""
    E, H = gi.n_edges, bias.shape[0]
    ph = launch.placeholder(run.compute_dtype, 2)
    h = torch.empty(E, H, dtype=run.compute_dtype, device=bias.device)
    kernel = K.project_kernel(H, run.wp_dtype, direct=direct is not None, sender=sender, receiver=receiver,
                              globals_=glob_proj is not None, relu=relu)
    launch(kernel, C.launch_dim(E, H), direct if direct is not None else ph,
           node_proj if node_proj is not None else ph, glob_proj if glob_proj is not None else ph,
           gi.senders, gi.receivers, gi.edge_graph, bias, h)
    return h


def project_grad(launch, run, gi, g0, node_pieces, p_nodes, p_glob):
    """Backward of ``project`` (the edge update's first layer in "project" mode): sums of the rows of ``g0`` by sender
    (columns [0, H) of ``p_nodes``) and by receiver (the next H columns), in one atomic pass or
    (deterministic) ordered segment sums; and by graph (``p_glob``): ordered sums over each
    graph's rows, from the receivers' sums when they exist (N rows instead of E; each edge's
    receiver is in the edge's graph)."""
    H = g0.shape[1]
    if p_nodes is not None:
        if run.deterministic:
            for k, name in enumerate(node_pieces):
                perm = gi.send_perm if name == "sender_nodes" else gi.recv_perm
                offs = gi.send_offsets if name == "sender_nodes" else gi.recv_offsets
                segment(launch, run, g0, perm, offs, p_nodes, 0, k * H, H)
        else:
            kernel = K.scatter_edges_kernel(H, run.wp_dtype, run.wp_acc, sender="sender_nodes" in node_pieces,
                                            receiver="receiver_nodes" in node_pieces, globals_=False)
            launch(kernel, C.launch_dim(*g0.shape), g0, gi.senders, gi.receivers, gi.edge_graph, p_nodes,
                   launch.placeholder(run.acc_dtype, 2))
    if p_glob is not None:
        if p_nodes is not None and "receiver_nodes" in node_pieces:
            rcv_col = node_pieces.index("receiver_nodes") * H
            segment(launch, run, p_nodes, None, gi.node_offsets, p_glob, rcv_col, 0, H)
        else:
            segment(launch, run, g0, None, gi.edge_offsets, p_glob)
