"""Warp kernels of ``gnwarp/models/fused_step.py``: a forward model's step around its core in one
launch a step forward and two backward, for batches of graphs of one size.

In torch, the work around the GN core of one step (the input graph from body states and
controls, the re-centring of D.4, the input normalization, the de-normalized change, the
quaternion update of D.5, the world body kept) is some hundred small kernels forward and as many
backward. Here one thread per node, edge or graph writes its row:

- ``encode``: body [N, ., B, 13] at step t and controls [N, ., U] at step t -> the normalized
  input graph: nodes [N*B, Fv] = ([static, body - centre] - mean) / std, edges [N*E, Fe] =
  ([static, control slots] - mean) / std, globals [N, Fg]. Each node thread re-sums its graph's
  moving bodies' x, y for the centre (graphs have a few bodies).
- ``decode``: normalized change [N*B, 13] -> next body: position and velocities by addition,
  orientation by the unit change's Hamilton product, re-normalized; the world body (node 0)
  kept. The centre cancels: (x - c) + d + c = x + d. With ``encode_next`` it also writes the
  next step's input graph (its dynamic node columns and edge control slots: the static columns
  stay in the buffers from the first encode), each node thread re-summing its graph's next x, y.
- ``decode_grad`` / ``encode_grad``: their vector-Jacobian products, written (never accumulated:
  no zeroing, no atomics), so the backward is deterministic. ``encode_grad`` adds the decode's
  direct term and the loss's term on the state, writes the controls' gradient at step t, and
  with ``encode_prev`` writes the previous step's input graph (the backward walks in reverse).

So a rollout's forward is one encode, then per step the core and one decode; its backward one
encode, then per step the core's forward and backward, ``decode_grad`` and ``encode_grad``.
Bodies and controls are read at a step index of [N, T, ...] arrays so the loops read and write
the trajectory buffers in place (a single step passes a [N, 1, ...] view and 0).
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools
import types

import warp as wp

__all__ = ["encode_kernel", "decode_kernel", "decode_grad_kernel", "encode_grad_kernel"]


@functools.cache
def _parts(dtype):
    """The device functions the kernels of ``dtype`` share (a namespace of ``wp.func``s)."""
    T = dtype
    V4 = wp.types.vector(4, dtype)
    V2 = wp.types.vector(2, dtype)

    @wp.func
    def qmul(a: V4, b: V4):
        """Hamilton product a (x) b of (w, x, y, z) quaternions."""
        return V4(a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
                  a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
                  a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
                  a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0])

    @wp.func
    def qmul_grad_b(a: V4, g: V4):
        """(d (a (x) b) / d b)^T g."""
        return V4(g[0] * a[0] + g[1] * a[1] + g[2] * a[2] + g[3] * a[3],
                  -g[0] * a[1] + g[1] * a[0] + g[2] * a[3] - g[3] * a[2],
                  -g[0] * a[2] - g[1] * a[3] + g[2] * a[0] + g[3] * a[1],
                  -g[0] * a[3] + g[1] * a[2] - g[2] * a[1] + g[3] * a[0])

    @wp.func
    def qmul_grad_a(b: V4, g: V4):
        """(d (a (x) b) / d a)^T g."""
        return V4(g[0] * b[0] + g[1] * b[1] + g[2] * b[2] + g[3] * b[3],
                  -g[0] * b[1] + g[1] * b[0] - g[2] * b[3] + g[3] * b[2],
                  -g[0] * b[2] + g[1] * b[3] + g[2] * b[0] - g[3] * b[1],
                  -g[0] * b[3] - g[1] * b[2] + g[2] * b[1] + g[3] * b[0])

    @wp.func
    def centre(
        # Data in:
        body_in: wp.array4d(dtype=T),
        n: int,
        tb: int,
        n_body: int,
    ):
        """Mean x, y of graph n's moving bodies (nodes 1..B-1) at step tb."""
        s = V2(T(0.0), T(0.0))
        for w in range(1, n_body):
            s += V2(body_in[n, tb, w, 0], body_in[n, tb, w, 1])
        return s / wp.max(T(n_body - 1), T(1.0))

    @wp.func
    def next_centre(
        # Data in:
        delta_in: wp.array2d(dtype=T),
        body_in: wp.array4d(dtype=T),
        n: int,
        tb: int,
        n_body: int,
        mean_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
    ):
        """Mean x, y of graph n's moving bodies after the step (the same sums ``decode`` writes)."""
        s = V2(T(0.0), T(0.0))
        for w in range(1, n_body):
            i = n * n_body + w
            s += V2(body_in[n, tb, w, 0] + (delta_in[i, 0] * std_in[0] + mean_in[0]),
                    body_in[n, tb, w, 1] + (delta_in[i, 1] * std_in[1] + mean_in[1]))
        return s / wp.max(T(n_body - 1), T(1.0))

    @wp.func
    def write_dynamic(
        # Data in:
        body_in: wp.array4d(dtype=T),
        n: int,
        tb: int,
        v: int,
        i: int,
        c: V2,
        node_mean_in: wp.array(dtype=T),
        node_std_in: wp.array(dtype=T),
        # Data out:
        nodes_out: wp.array2d(dtype=T),
    ):
        """Node row i's last 13 columns: (body[n, tb, v] - (c, 0, ...) - mean) / std."""
        fs = nodes_out.shape[1] - 13
        for k in range(13):
            x = body_in[n, tb, v, k]
            if k < 2:
                x = x - c[k]
            nodes_out[i, fs + k] = (x - node_mean_in[fs + k]) / node_std_in[fs + k]

    @wp.func
    def write_controls(
        # Data in:
        ctrl_in: wp.array3d(dtype=T),
        n: int,
        tc: int,
        r: int,
        ctrl_index_in: wp.array2d(dtype=wp.int32),
        edge_mean_in: wp.array(dtype=T),
        edge_std_in: wp.array(dtype=T),
        # Data out:
        edges_out: wp.array2d(dtype=T),
    ):
        """Edge row r's last K columns: each slot's control of graph n at step tc (0 where the
        slot has no actuator), normalized."""
        kk = ctrl_index_in.shape[1]
        fs = edges_out.shape[1] - kk
        for k in range(kk):
            c = ctrl_index_in[r, k]
            x = T(0.0)
            if c >= 0:
                x = ctrl_in[n, tc, c]
            edges_out[r, fs + k] = (x - edge_mean_in[fs + k]) / edge_std_in[fs + k]

    @wp.func
    def decode_node(
        # Data in:
        delta_in: wp.array2d(dtype=T),
        body_in: wp.array4d(dtype=T),
        n: int,
        tb: int,
        v: int,
        i: int,
        mean_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
        tn: int,
        # Data out:
        next_out: wp.array4d(dtype=T),
    ):
        """next_out[n, tn, v] from body_in[n, tb, v] and the normalized change row i."""
        if v == 0:
            for k in range(13):
                next_out[n, tn, v, k] = body_in[n, tb, v, k]
            return
        for k in range(13):
            if k < 3 or k >= 7:
                next_out[n, tn, v, k] = body_in[n, tb, v, k] + (delta_in[i, k] * std_in[k] + mean_in[k])
        a = V4(delta_in[i, 3] * std_in[3] + mean_in[3], delta_in[i, 4] * std_in[4] + mean_in[4],
               delta_in[i, 5] * std_in[5] + mean_in[5], delta_in[i, 6] * std_in[6] + mean_in[6])
        a = a / wp.max(wp.length(a), T(1e-12))
        b = V4(body_in[n, tb, v, 3], body_in[n, tb, v, 4], body_in[n, tb, v, 5], body_in[n, tb, v, 6])
        p = qmul(a, b)
        p = p / wp.max(wp.length(p), T(1e-12))
        for k in range(4):
            next_out[n, tn, v, 3 + k] = p[k]

    return types.SimpleNamespace(V2=V2, V4=V4, qmul=qmul, qmul_grad_b=qmul_grad_b, qmul_grad_a=qmul_grad_a,
                                 centre=centre, next_centre=next_centre, write_dynamic=write_dynamic,
                                 write_controls=write_controls, decode_node=decode_node)


@functools.cache
def encode_kernel(dtype, recenter: bool):
    """Kernel ``(body_in [N, T1, B, 13], tb, ctrl_in [N, T, U], tc, static_nodes_in [N*B, Fv-13],
    static_edges_in [N*E, Fe-K], static_globals_in [N, Fg], ctrl_index_in [N*E, K] int32 (-1: no
    actuator), node_mean_in, node_std_in [Fv], edge_mean_in, edge_std_in [Fe], glob_mean_in,
    glob_std_in [Fg], n_graph, n_body, n_edge, nodes_out [N*B, Fv], edges_out [N*E, Fe],
    globals_out [N, Fg])`` over N*(B + E + 1) threads: node rows, edge rows, then graph rows of the
    normalized input graph at body step ``tb`` and control step ``tc``. ``recenter``: subtract
    each graph's mean x, y over its moving bodies (nodes 1..B-1) from its moving bodies."""
    T = dtype
    CENTRE = 1 if recenter else 0
    P = _parts(dtype)
    V2, centre, write_dynamic, write_controls = P.V2, P.centre, P.write_dynamic, P.write_controls

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def encode(
        # Data in:
        body_in: wp.array4d(dtype=T),
        tb: int,
        ctrl_in: wp.array3d(dtype=T),
        tc: int,
        static_nodes_in: wp.array2d(dtype=T),
        static_edges_in: wp.array2d(dtype=T),
        static_globals_in: wp.array2d(dtype=T),
        ctrl_index_in: wp.array2d(dtype=wp.int32),
        node_mean_in: wp.array(dtype=T),
        node_std_in: wp.array(dtype=T),
        edge_mean_in: wp.array(dtype=T),
        edge_std_in: wp.array(dtype=T),
        glob_mean_in: wp.array(dtype=T),
        glob_std_in: wp.array(dtype=T),
        n_graph: int,
        n_body: int,
        n_edge: int,
        # Data out:
        nodes_out: wp.array2d(dtype=T),
        edges_out: wp.array2d(dtype=T),
        globals_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        nv = n_graph * n_body
        ne = n_graph * n_edge
        if i < nv:
            n = i // n_body
            v = i - n * n_body
            for j in range(static_nodes_in.shape[1]):
                nodes_out[i, j] = (static_nodes_in[i, j] - node_mean_in[j]) / node_std_in[j]
            c = V2(T(0.0), T(0.0))
            if wp.static(CENTRE == 1):
                if v != 0:
                    c = centre(body_in, n, tb, n_body)
            write_dynamic(body_in, n, tb, v, i, c, node_mean_in, node_std_in, nodes_out)
        elif i < nv + ne:
            r = i - nv
            n = r // n_edge
            for j in range(static_edges_in.shape[1]):
                edges_out[r, j] = (static_edges_in[r, j] - edge_mean_in[j]) / edge_std_in[j]
            write_controls(ctrl_in, n, tc, r, ctrl_index_in, edge_mean_in, edge_std_in, edges_out)
        else:
            n = i - nv - ne
            for j in range(static_globals_in.shape[1]):
                globals_out[n, j] = (static_globals_in[n, j] - glob_mean_in[j]) / glob_std_in[j]

    return encode


@functools.cache
def decode_kernel(dtype, encode_next: bool, recenter: bool):
    """Kernel ``(delta_in [N*B, 13], body_in [N, T1, B, 13], tb, mean_in [13], std_in [13],
    ctrl_in [N, T, U], tc, ctrl_index_in [N*E, K] int32, node_mean_in, node_std_in, edge_mean_in,
    edge_std_in, n_graph, n_body, n_edge, tn, next_out [N, T2, B, 13], nodes_out [N*B, Fv],
    edges_out [N*E, Fe])`` over N*B threads (N*(B + E) with ``encode_next``): d = delta * std +
    mean; next = body + d for position and velocities, orientation (d_q / |d_q|) (x) q
    re-normalized (norms at least 1e-12); node 0 of each graph (the world) copied. Reads step
    ``tb``, writes step ``tn``. ``encode_next``: also the next input graph's dynamic node columns
    (re-centred when ``recenter``) and its edges' control slots at control step ``tc`` (the
    control arrays and the graph outputs are not read or written otherwise)."""
    T = dtype
    ENC = 1 if encode_next else 0
    CENTRE = 1 if recenter else 0
    P = _parts(dtype)
    V2, next_centre, write_dynamic, write_controls, decode_node = (P.V2, P.next_centre, P.write_dynamic,
                                                                   P.write_controls, P.decode_node)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def decode(
        # Data in:
        delta_in: wp.array2d(dtype=T),
        body_in: wp.array4d(dtype=T),
        tb: int,
        mean_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
        ctrl_in: wp.array3d(dtype=T),
        tc: int,
        ctrl_index_in: wp.array2d(dtype=wp.int32),
        node_mean_in: wp.array(dtype=T),
        node_std_in: wp.array(dtype=T),
        edge_mean_in: wp.array(dtype=T),
        edge_std_in: wp.array(dtype=T),
        n_graph: int,
        n_body: int,
        n_edge: int,
        tn: int,
        # Data out:
        next_out: wp.array4d(dtype=T),
        nodes_out: wp.array2d(dtype=T),
        edges_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        nv = n_graph * n_body
        if i < nv:
            n = i // n_body
            v = i - n * n_body
            decode_node(delta_in, body_in, n, tb, v, i, mean_in, std_in, tn, next_out)
            if wp.static(ENC == 1):
                c = V2(T(0.0), T(0.0))
                if wp.static(CENTRE == 1):
                    if v != 0:
                        c = next_centre(delta_in, body_in, n, tb, n_body, mean_in, std_in)
                # its own next state, just written by this thread
                write_dynamic(next_out, n, tn, v, i, c, node_mean_in, node_std_in, nodes_out)
        else:
            if wp.static(ENC == 1):
                r = i - nv
                write_controls(ctrl_in, r // n_edge, tc, r, ctrl_index_in, edge_mean_in, edge_std_in, edges_out)

    return decode


@functools.cache
def decode_grad_kernel(dtype):
    """Kernel ``(delta_in [N*B, 13], body_in [N, T1, B, 13], tb, g_next_in [N*B, 13], mean_in,
    std_in [13], n_body, g_delta_out [N*B, 13], g_body_out [N*B, 13])`` over N*B threads: the
    vector-Jacobian product of ``decode`` with ``g_next_in``: the gradient of the normalized change
    and the direct gradient of the body state (the world body: the identity, no change)."""
    T = dtype
    P = _parts(dtype)
    V4, qmul, qmul_grad_b, qmul_grad_a = P.V4, P.qmul, P.qmul_grad_b, P.qmul_grad_a

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def decode_grad(
        # Data in:
        delta_in: wp.array2d(dtype=T),
        body_in: wp.array4d(dtype=T),
        tb: int,
        g_next_in: wp.array2d(dtype=T),
        mean_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
        n_body: int,
        # Data out:
        g_delta_out: wp.array2d(dtype=T),
        g_body_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        n = i // n_body
        v = i - n * n_body
        if v == 0:
            for k in range(13):
                g_body_out[i, k] = g_next_in[i, k]
                g_delta_out[i, k] = T(0.0)
            return
        for k in range(13):
            if k < 3 or k >= 7:
                g_body_out[i, k] = g_next_in[i, k]
                g_delta_out[i, k] = g_next_in[i, k] * std_in[k]
        eps = T(1e-12)
        a_raw = V4(delta_in[i, 3] * std_in[3] + mean_in[3], delta_in[i, 4] * std_in[4] + mean_in[4],
                   delta_in[i, 5] * std_in[5] + mean_in[5], delta_in[i, 6] * std_in[6] + mean_in[6])
        la = wp.length(a_raw)
        ra = wp.max(la, eps)
        a = a_raw / ra
        b = V4(body_in[n, tb, v, 3], body_in[n, tb, v, 4], body_in[n, tb, v, 5], body_in[n, tb, v, 6])
        p_raw = qmul(a, b)
        lp = wp.length(p_raw)
        rp = wp.max(lp, eps)
        q = p_raw / rp
        gq = V4(g_next_in[i, 3], g_next_in[i, 4], g_next_in[i, 5], g_next_in[i, 6])
        # through y = x / max(|x|, eps): (g - y (y . g)) / r where |x| >= eps, else g / r
        gp = gq / rp
        if lp >= eps:
            gp = (gq - q * wp.dot(q, gq)) / rp
        gb = qmul_grad_b(a, gp)
        ga = qmul_grad_a(b, gp)
        gr = ga / ra
        if la >= eps:
            gr = (ga - a * wp.dot(a, ga)) / ra
        for k in range(4):
            g_body_out[i, 3 + k] = gb[k]
            g_delta_out[i, 3 + k] = gr[k] * std_in[3 + k]

    return decode_grad


@functools.cache
def encode_grad_kernel(dtype, recenter: bool, add: bool, encode_prev: bool):
    """Kernel ``(g_nodes_in [N*B, Fv], g_edges_in [N*E, Fe], g_direct_in [N*B, 13], g_add_in
    [N, T1, B, 13], ta, ctrl_index_in [N*E, K] int32, node_std_in [Fv], edge_std_in [Fe], body_in
    [N, T1, B, 13], tb, ctrl_in [N, T, U], tp, node_mean_in, edge_mean_in, n_graph, n_body, n_edge,
    n_ctrl, tc, g_body_out [N*B, 13], g_ctrl_out [N, T, U], nodes_out [N*B, Fv], edges_out
    [N*E, Fe])`` over N*(B + U) threads (N*(B + U + E) with ``encode_prev``): the vector-Jacobian
    product of ``encode`` (re-centring included when ``recenter``) with the gradients of the
    normalized nodes and edges, plus ``g_direct_in`` and (when ``add``) ``g_add_in`` at step
    ``ta``, into ``g_body_out``; each control's gradient (the sum over the edge slots that read it)
    into ``g_ctrl_out`` at step ``tc``. ``encode_prev``: also the input graph of ``body_in`` at step
    ``tb`` and ``ctrl_in`` at step ``tp`` (dynamic node columns and control slots; the arrays it
    needs are not read or written otherwise)."""
    T = dtype
    CENTRE = 1 if recenter else 0
    ADD = 1 if add else 0
    PREV = 1 if encode_prev else 0
    P = _parts(dtype)
    V2, centre, write_dynamic, write_controls = P.V2, P.centre, P.write_dynamic, P.write_controls

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def encode_grad(
        # Data in:
        g_nodes_in: wp.array2d(dtype=T),
        g_edges_in: wp.array2d(dtype=T),
        g_direct_in: wp.array2d(dtype=T),
        g_add_in: wp.array4d(dtype=T),
        ta: int,
        ctrl_index_in: wp.array2d(dtype=wp.int32),
        node_std_in: wp.array(dtype=T),
        edge_std_in: wp.array(dtype=T),
        body_in: wp.array4d(dtype=T),
        tb: int,
        ctrl_in: wp.array3d(dtype=T),
        tp: int,
        node_mean_in: wp.array(dtype=T),
        edge_mean_in: wp.array(dtype=T),
        n_graph: int,
        n_body: int,
        n_edge: int,
        n_ctrl: int,
        tc: int,
        # Data out:
        g_body_out: wp.array2d(dtype=T),
        g_ctrl_out: wp.array3d(dtype=T),
        nodes_out: wp.array2d(dtype=T),
        edges_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        nv = n_graph * n_body
        nu = n_graph * n_ctrl
        if i < nv:
            n = i // n_body
            v = i - n * n_body
            fs = g_nodes_in.shape[1] - 13
            for k in range(13):
                g = g_nodes_in[i, fs + k] / node_std_in[fs + k] + g_direct_in[i, k]
                if wp.static(ADD == 1):
                    g += g_add_in[n, ta, v, k]
                if wp.static(CENTRE == 1):
                    if k < 2 and v != 0:
                        s = T(0.0)
                        for w in range(1, n_body):
                            s += g_nodes_in[n * n_body + w, fs + k]
                        g -= s / node_std_in[fs + k] / wp.max(T(n_body - 1), T(1.0))
                g_body_out[i, k] = g
            if wp.static(PREV == 1):
                c = V2(T(0.0), T(0.0))
                if wp.static(CENTRE == 1):
                    if v != 0:
                        c = centre(body_in, n, tb, n_body)
                write_dynamic(body_in, n, tb, v, i, c, node_mean_in, node_std_in, nodes_out)
        elif i < nv + nu:
            r = i - nv
            n = r // n_ctrl
            u = r - n * n_ctrl
            kk = ctrl_index_in.shape[1]
            fs = g_edges_in.shape[1] - kk
            acc = T(0.0)
            for e in range(n * n_edge, (n + 1) * n_edge):
                for k in range(kk):
                    if ctrl_index_in[e, k] == u:
                        acc += g_edges_in[e, fs + k] / edge_std_in[fs + k]
            g_ctrl_out[n, tc, u] = acc
        else:
            if wp.static(PREV == 1):
                r = i - nv - nu
                write_controls(ctrl_in, r // n_edge, tp, r, ctrl_index_in, edge_mean_in, edge_std_in, edges_out)

    return encode_grad
