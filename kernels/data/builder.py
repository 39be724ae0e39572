"""Warp kernel of ``gnwarp/data/builder.py`` (``GraphBuilder.sequence_batch``): a batch's input
graphs and targets from stored sequences in one launch.

A batch of N (sequence, step) pairs of one topology is N copies of the system's graph: node rows
[static node features, body state at t], edge rows [static edge features, the controls at t of the
edge's actuator slots], one global row, and the body states at t + 1 as targets. In torch that is
~12 kernels (gathers of the states, controls and static features, the control routing, concats);
here one thread writes one row.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["sample_batch_kernel"]


@functools.cache
def sample_batch_kernel(dtype):
    """Kernel ``(seq [N] int64, t [N] int64, instance [S] int64, body [S, T+1, B, 13], ctrl [S, T, U],
    s_nodes [I, B, Fv], s_edges [I, E, Fe], s_globals [I, Fg], edge_ctrl [I, E, K] int64 (-1: no
    actuator), nodes [N*B, Fv+13], edges [N*E, Fe+K], globals [N, Fg], target [N*B, 13])`` over
    N * (B + E + 1) threads: graph g = tid // (B + E + 1) writes node row r < B, edge row r - B
    < E, else its global row, r = tid % (B + E + 1); I is the instance of seq[g]."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def sample_batch(seq: wp.array(dtype=wp.int64), t: wp.array(dtype=wp.int64), instance: wp.array(dtype=wp.int64),
                     body: wp.array4d(dtype=T), ctrl: wp.array3d(dtype=T), s_nodes: wp.array3d(dtype=T),
                     s_edges: wp.array3d(dtype=T), s_globals: wp.array2d(dtype=T),
                     edge_ctrl: wp.array3d(dtype=wp.int64), nodes: wp.array2d(dtype=T), edges: wp.array2d(dtype=T),
                     globals: wp.array2d(dtype=T), target: wp.array2d(dtype=T)):
        tid = wp.tid()
        B = body.shape[2]
        E = s_edges.shape[1]
        g = tid // (B + E + 1)
        r = tid - g * (B + E + 1)
        sq = int(seq[g])
        st = int(t[g])
        inst = int(instance[sq])
        if r < B:
            row = g * B + r
            fv = s_nodes.shape[2]
            for k in range(fv):
                nodes[row, k] = s_nodes[inst, r, k]
            for k in range(13):
                nodes[row, fv + k] = body[sq, st, r, k]
                target[row, k] = body[sq, st + 1, r, k]
        elif r < B + E:
            e = r - B
            row = g * E + e
            fe = s_edges.shape[2]
            for k in range(fe):
                edges[row, k] = s_edges[inst, e, k]
            for k in range(edge_ctrl.shape[2]):
                c = int(edge_ctrl[inst, e, k])
                v = T(0.0)
                if c >= 0:
                    v = ctrl[sq, st, c]
                edges[row, fe + k] = v
        else:
            for k in range(s_globals.shape[1]):
                globals[g, k] = s_globals[inst, k]

    return sample_batch
