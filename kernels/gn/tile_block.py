"""Fused Warp-tile kernels of a GN block on the tile path (launched by ``gnwarp/gn/tile_block.py``):
one launch per update does gather, the whole MLP (``wp.tile_matmul``) and the scatter-sums.

One kernel factory serves the three updates. A thread block owns ``tile_rows`` consecutive rows
(edges, nodes or graphs). Up to four input pieces (slots) form the first layer's input, in the
order of the config's layout; each slot is absent, read as contiguous rows (``ROWS``) or gathered
through its index array (``GATHER``: ``tile_load_indexed``). The first layer is the sum of one
``tile_matmul`` per piece with that piece's block of the weight, so the concatenated input is
never formed. Up to two scatter-sums of the output (``tile_atomic_add_indexed``) follow.

Edge update: x0 = edges (rows), x1 = nodes[senders], x2 = nodes[receivers], x3 =
globals[edge_graph]; sums: to receivers, to graphs. Node update: x0 = nodes, x1 = aggregated
edges (rows), x2 = globals[node_graph]; sum: to graphs. Global update: x0 = globals, x1 = node
sums, x2 = edge sums (rows).

Weights come packed: ``w_in`` stacks every layer's W^T ([in, out]) by rows, padded to the widest
layer; ``b_in`` holds one bias per row. Index arrays are padded to a multiple of ``tile_rows``
with -1: a gathered row with index -1 reads zeros and a scatter to -1 is skipped, so the padded
rows of the last tile change nothing.

Backward: Warp's autodiff (adjoint launch of the same kernel).
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["ABSENT", "ROWS", "GATHER", "MAX_HIDDEN", "update_tile_kernel"]

ABSENT, ROWS, GATHER = 0, 1, 2
MAX_HIDDEN = 4


@functools.cache
def update_tile_kernel(tile_rows: int, slots: tuple[tuple[int, int], ...], hidden: tuple[int, ...],
                       out_size: int, n_scatter: int, dtype, *, mathdx: bool = True):
    """Kernel for one update. ``slots``: four (mode, width) pairs; ``hidden``: hidden widths
    (at most ``MAX_HIDDEN``); ``n_scatter``: number of scatter-sums of the output (0-2);
    ``mathdx``: CUDA tile GEMMs through cuBLASDx (Warp's default; ~1-2.5 min to compile per
    kernel for sm_90) or Warp's plain shared-memory GEMM (seconds to compile).
    Launch with ``wp.launch_tiled(dim=[ceil(rows / tile_rows)], block_dim=...)``."""
    if len(hidden) > MAX_HIDDEN:
        raise ValueError(f"the tile path supports at most {MAX_HIDDEN} hidden layers, got {len(hidden)}")
    T = dtype
    TM = tile_rows
    (M0, F0), (M1, F1), (M2, F2), (M3, F3) = slots
    widths = (*hidden, out_size)
    H0 = widths[0]
    # packed-weight row offsets: first-layer pieces in slot order, then layers 1..L
    R0 = 0
    R1 = R0 + (F0 if M0 else 0)
    R2 = R1 + (F1 if M1 else 0)
    R3 = R2 + (F2 if M2 else 0)
    D0 = R3 + (F3 if M3 else 0)
    L = len(hidden)
    row_off = [D0]
    for w in widths[:-1]:
        row_off.append(row_off[-1] + w)
    # layer l (1..L): W^T [widths[l-1], widths[l]] at rows row_off[l-1]
    K1, N1, O1 = (widths[0], widths[1], row_off[0]) if L >= 1 else (1, 1, 0)
    K2, N2, O2 = (widths[1], widths[2], row_off[1]) if L >= 2 else (1, 1, 0)
    K3, N3, O3 = (widths[2], widths[3], row_off[2]) if L >= 3 else (1, 1, 0)
    K4, N4, O4 = (widths[3], widths[4], row_off[3]) if L >= 4 else (1, 1, 0)
    # zero widths of absent slots would be invalid tile shapes; the code using them is removed
    F0, F1, F2, F3 = (max(f, 1) for f in (F0, F1, F2, F3))

    @wp.func
    def relu(x: T):
        return wp.max(x, T(0.0))

    @wp.kernel(module="unique", module_options={"enable_mathdx_gemm": mathdx})
    def update_tile(
        # Data in:
        x0_in: wp.array2d(dtype=T),
        x1_in: wp.array2d(dtype=T),
        x2_in: wp.array2d(dtype=T),
        x3_in: wp.array2d(dtype=T),
        index0_in: wp.array(dtype=wp.int32),
        index1_in: wp.array(dtype=wp.int32),
        index2_in: wp.array(dtype=wp.int32),
        index3_in: wp.array(dtype=wp.int32),
        scatter0_index_in: wp.array(dtype=wp.int32),
        scatter1_index_in: wp.array(dtype=wp.int32),
        # Parameters:
        w_in: wp.array2d(dtype=T),
        b_in: wp.array2d(dtype=T),
        # Data out:
        y_out: wp.array2d(dtype=T),
        sum0_out: wp.array2d(dtype=T),
        sum1_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r0 = i * TM
        z = wp.tile_broadcast(wp.tile_load(b_in, shape=(1, H0), offset=(0, 0)), shape=(TM, H0))
        # first layer: one matmul per input piece with its weight block
        if wp.static(M0 == ROWS):
            z = z + wp.tile_matmul(wp.tile_load(x0_in, shape=(TM, F0), offset=(r0, 0)),
                                   wp.tile_load(w_in, shape=(F0, H0), offset=(R0, 0)))
        if wp.static(M0 == GATHER):
            i0 = wp.tile_load(index0_in, shape=TM, offset=r0)
            z = z + wp.tile_matmul(wp.tile_load_indexed(x0_in, indices=i0, shape=(TM, F0), axis=0),
                                   wp.tile_load(w_in, shape=(F0, H0), offset=(R0, 0)))
        if wp.static(M1 == ROWS):
            z = z + wp.tile_matmul(wp.tile_load(x1_in, shape=(TM, F1), offset=(r0, 0)),
                                   wp.tile_load(w_in, shape=(F1, H0), offset=(R1, 0)))
        if wp.static(M1 == GATHER):
            i1 = wp.tile_load(index1_in, shape=TM, offset=r0)
            z = z + wp.tile_matmul(wp.tile_load_indexed(x1_in, indices=i1, shape=(TM, F1), axis=0),
                                   wp.tile_load(w_in, shape=(F1, H0), offset=(R1, 0)))
        if wp.static(M2 == ROWS):
            z = z + wp.tile_matmul(wp.tile_load(x2_in, shape=(TM, F2), offset=(r0, 0)),
                                   wp.tile_load(w_in, shape=(F2, H0), offset=(R2, 0)))
        if wp.static(M2 == GATHER):
            i2 = wp.tile_load(index2_in, shape=TM, offset=r0)
            z = z + wp.tile_matmul(wp.tile_load_indexed(x2_in, indices=i2, shape=(TM, F2), axis=0),
                                   wp.tile_load(w_in, shape=(F2, H0), offset=(R2, 0)))
        if wp.static(M3 == ROWS):
            z = z + wp.tile_matmul(wp.tile_load(x3_in, shape=(TM, F3), offset=(r0, 0)),
                                   wp.tile_load(w_in, shape=(F3, H0), offset=(R3, 0)))
        if wp.static(M3 == GATHER):
            i3 = wp.tile_load(index3_in, shape=TM, offset=r0)
            z = z + wp.tile_matmul(wp.tile_load_indexed(x3_in, indices=i3, shape=(TM, F3), axis=0),
                                   wp.tile_load(w_in, shape=(F3, H0), offset=(R3, 0)))
        # hidden layers: ReLU, then the next linear layer
        if wp.static(L >= 1):
            z = wp.tile_matmul(wp.tile_map(relu, z), wp.tile_load(w_in, shape=(K1, N1), offset=(O1, 0))) \
                + wp.tile_broadcast(wp.tile_load(b_in, shape=(1, N1), offset=(1, 0)), shape=(TM, N1))
        if wp.static(L >= 2):
            z = wp.tile_matmul(wp.tile_map(relu, z), wp.tile_load(w_in, shape=(K2, N2), offset=(O2, 0))) \
                + wp.tile_broadcast(wp.tile_load(b_in, shape=(1, N2), offset=(2, 0)), shape=(TM, N2))
        if wp.static(L >= 3):
            z = wp.tile_matmul(wp.tile_map(relu, z), wp.tile_load(w_in, shape=(K3, N3), offset=(O3, 0))) \
                + wp.tile_broadcast(wp.tile_load(b_in, shape=(1, N3), offset=(3, 0)), shape=(TM, N3))
        if wp.static(L >= 4):
            z = wp.tile_matmul(wp.tile_map(relu, z), wp.tile_load(w_in, shape=(K4, N4), offset=(O4, 0))) \
                + wp.tile_broadcast(wp.tile_load(b_in, shape=(1, N4), offset=(4, 0)), shape=(TM, N4))
        wp.tile_store(y_out, z, offset=(r0, 0))
        # scatter-sums of the output rows (padded rows carry index -1: skipped)
        if wp.static(n_scatter >= 1):
            s0 = wp.tile_load(scatter0_index_in, shape=TM, offset=r0)
            wp.tile_atomic_add_indexed(sum0_out, indices=s0, t=z, axis=0)
        if wp.static(n_scatter >= 2):
            s1 = wp.tile_load(scatter1_index_in, shape=TM, offset=r0)
            wp.tile_atomic_add_indexed(sum1_out, indices=s1, t=z, axis=0)

    return update_tile
