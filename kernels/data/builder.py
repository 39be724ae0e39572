"""Warp kernel of ``gnwarp/data/builder.py`` (``GraphBuilder.sequence_batch``): a batch's input
graphs and targets from stored sequences in one launch.

A batch of N (sequence, step) pairs of one topology is N copies of the system's graph: node rows
[static node features, body state at t], edge rows [static edge features, the controls at t of the
edge's actuator slots, each times its weight], one global row, and the body states at t + 1 as targets. In torch that is
~12 kernels (gathers of the states, controls and static features, the control routing, concats);
here one thread writes one row.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["sample_batch_kernel"]


@functools.cache
def sample_batch_kernel(dtype):
    """Kernel ``(seq_in [N] int64, t_in [N] int64, instance_in [S] int64, body_in [S, T+1, B, 13],
    ctrl_in [S, T, U], s_nodes_in [I, B, Fv], s_edges_in [I, E, Fe], s_globals_in [I, Fg],
    edge_ctrl_in [I, E, K] int64 (-1: no actuator), edge_gain_in [I, E, K] (each slot's control
    weight: a tendon's coefficient on the joint, 1 for a joint actuator), nodes_out [N*B, Fv+13], edges_out [N*E, Fe+K],
    globals_out [N, Fg], target_out [N*B, 13])`` over N * (B + E + 1) threads: graph g = tid //
    (B + E + 1) writes node row r < B, edge row r - B < E, else its global row, r = tid % (B + E +
    1); I is the instance of seq_in[g]."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def sample_batch(
        # Data in:
        seq_in: wp.array(dtype=wp.int64),
        t_in: wp.array(dtype=wp.int64),
        instance_in: wp.array(dtype=wp.int64),
        body_in: wp.array4d(dtype=T),
        ctrl_in: wp.array3d(dtype=T),
        s_nodes_in: wp.array3d(dtype=T),
        s_edges_in: wp.array3d(dtype=T),
        s_globals_in: wp.array2d(dtype=T),
        edge_ctrl_in: wp.array3d(dtype=wp.int64),
        edge_gain_in: wp.array3d(dtype=T),
        # Data out:
        nodes_out: wp.array2d(dtype=T),
        edges_out: wp.array2d(dtype=T),
        globals_out: wp.array2d(dtype=T),
        target_out: wp.array2d(dtype=T),
    ):
        tid = wp.tid()
        B = body_in.shape[2]
        E = s_edges_in.shape[1]
        g = tid // (B + E + 1)
        r = tid - g * (B + E + 1)
        sq = int(seq_in[g])
        st = int(t_in[g])
        inst = int(instance_in[sq])
        if r < B:
            row = g * B + r
            fv = s_nodes_in.shape[2]
            for k in range(fv):
                nodes_out[row, k] = s_nodes_in[inst, r, k]
            for k in range(13):
                nodes_out[row, fv + k] = body_in[sq, st, r, k]
                target_out[row, k] = body_in[sq, st + 1, r, k]
        elif r < B + E:
            e = r - B
            row = g * E + e
            fe = s_edges_in.shape[2]
            for k in range(fe):
                edges_out[row, k] = s_edges_in[inst, e, k]
            for k in range(edge_ctrl_in.shape[2]):
                c = int(edge_ctrl_in[inst, e, k])
                v = T(0.0)
                if c >= 0:
                    v = ctrl_in[sq, st, c] * edge_gain_in[inst, e, k]
                edges_out[row, fe + k] = v
        else:
            for k in range(s_globals_in.shape[1]):
                globals_out[g, k] = s_globals_in[inst, k]

    return sample_batch
