"""Warp kernels of ``gnwarp/train/optim.py`` (``FlatAdam``): Adam over one flat parameter buffer
and its gradient norm.

Why flat: a training step of the paper's GN core at batch 200 has ~40 parameter tensors. Torch's
fused Adam (``multi_tensor_apply``) splits them into chunks of 65536 elements, one thread block
per chunk, so ~2M parameters occupy only a few dozen of the GPU's SMs; gradient clipping adds a
``_foreach_norm`` and a ``_foreach_mul_``. Over one flat buffer the whole update is one
element-wise kernel that fills the GPU, and the norm one tile reduction.

Scalars live on the device (``SCALARS`` slots of one small array), so a captured CUDA graph of a
training step replays correct bias corrections: ``finalize`` (one thread) advances the step count
and computes the clipping coefficient between the norm and the update.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["SUMSQ", "STEP", "LR", "COEF", "BC1", "BC2", "NORM", "SCALARS", "BLOCK", "SUMSQ_UNROLL", "sumsq_kernel",
           "ADAM_VEC", "adam_threads",
           "finalize_kernel", "adam_kernel"]

# slots of the device scalars array (the norm's tile reduction adds into slot 0: keep SUMSQ first)
SUMSQ, STEP, LR, COEF, BC1, BC2, NORM = range(7)
SCALARS = 8
BLOCK = 256  # threads per block of the tiled norm reduction (CUDA; Warp's CPU device runs 1)


def _options():
    return {"enable_backward": False}


SUMSQ_UNROLL = 4  # independent partial sums per thread of ``sumsq`` (loads in flight)


@functools.cache
def sumsq_kernel(dtype):
    """scalars_out[SUMSQ] += sum of g_in[i]**2 over i < n: each thread sums a grid-strided range,
    ``SUMSQ_UNROLL`` elements per iteration into as many partial sums (their loads independent,
    in flight together), each block reduces its threads' sums as a tile and adds the result with
    one atomic. Launch with ``wp.launch_tiled(dim=[blocks], block_dim=bd)`` and
    ``stride = blocks * bd`` (``bd`` = 1 on the CPU, where a tile block is one thread)."""
    T = dtype
    U = SUMSQ_UNROLL

    @wp.kernel(module="unique", module_options=_options())
    def sumsq(
        # Data in:
        g_in: wp.array(dtype=T),
        n: int,
        bd: int,
        stride: int,
        # Data out:
        scalars_out: wp.array(dtype=T),
    ):
        b, lane = wp.tid()
        i = b * bd + lane
        acc = wp.vector(length=U, dtype=T)
        while i + (U - 1) * stride < n:
            xs = wp.vector(length=U, dtype=T)
            for k in range(U):
                xs[k] = g_in[i + k * stride]
            for k in range(U):
                acc[k] += xs[k] * xs[k]
            i += U * stride
        while i < n:
            x = g_in[i]
            acc[0] += x * x
            i += stride
        total = T(0.0)
        for k in range(U):
            total += acc[k]
        wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(total)))  # into slot SUMSQ = 0

    return sumsq


@functools.cache
def finalize_kernel(dtype, *, clip: bool):
    """One thread, between the norm and the update: step += 1; the bias corrections of that step;
    the clipping coefficient min(1, max_norm / (norm + 1e-6)) (as torch's ``clip_grad_norm_``);
    the norm kept in scalars[NORM] and the accumulator zeroed for the next step. Launch with the
    device scalars as both ``scalars_in`` and ``scalars_out``."""
    T = dtype

    @wp.kernel(module="unique", module_options=_options())
    def finalize(
        # Data in:
        scalars_in: wp.array(dtype=T),
        beta1: T,
        beta2: T,
        max_norm: T,
        # Data out:
        scalars_out: wp.array(dtype=T),
    ):
        step = scalars_in[STEP] + T(1.0)
        norm = wp.sqrt(scalars_in[SUMSQ])
        scalars_out[STEP] = step
        scalars_out[BC1] = T(1.0) - wp.pow(beta1, step)
        scalars_out[BC2] = T(1.0) - wp.pow(beta2, step)
        scalars_out[NORM] = norm
        scalars_out[SUMSQ] = T(0.0)
        coef = T(1.0)
        if wp.static(clip):
            coef = wp.min(T(1.0), max_norm / (norm + T(1.0e-6)))
        scalars_out[COEF] = coef

    return finalize


ADAM_VEC = 4  # elements per thread of ``adam`` (strided by the thread count: coalesced, loads in flight)


def adam_threads(n: int) -> int:
    return -(-n // ADAM_VEC)


@functools.cache
def adam_kernel(dtype, *, weight_decay: bool, decoupled: bool):
    """One Adam (``decoupled``: AdamW) step of elements i = t + k * nt (k < ``ADAM_VEC``, i < n)
    of thread t of nt = ``adam_threads(n)``, in torch's formulation:
    g = coef * grad (+ wd * p for Adam's L2 decay); m = b1 m + (1 - b1) g; v = b2 v + (1 - b2) g^2;
    p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps) (AdamW first scales p by 1 - lr * wd).
    Every load is issued before the first store. Launch with the parameters, first and second
    moments as both ``*_in`` and ``*_out``."""
    T = dtype
    V = ADAM_VEC

    @wp.kernel(module="unique", module_options=_options())
    def adam(
        # Data in:
        p_in: wp.array(dtype=T),
        g_in: wp.array(dtype=T),
        m_in: wp.array(dtype=T),
        v_in: wp.array(dtype=T),
        scalars_in: wp.array(dtype=T),
        n: int,
        nt: int,
        beta1: T,
        beta2: T,
        eps: T,
        wd: T,
        # Data out:
        p_out: wp.array(dtype=T),
        m_out: wp.array(dtype=T),
        v_out: wp.array(dtype=T),
    ):
        t = wp.tid()
        ps = wp.vector(length=V, dtype=T)
        gs = wp.vector(length=V, dtype=T)
        ms = wp.vector(length=V, dtype=T)
        vs = wp.vector(length=V, dtype=T)
        for k in range(V):
            i = t + k * nt
            if i < n:
                ps[k] = p_in[i]
                gs[k] = g_in[i]
                ms[k] = m_in[i]
                vs[k] = v_in[i]
        lr = scalars_in[LR]
        coef = scalars_in[COEF]
        step = lr / scalars_in[BC1]
        sq2 = wp.sqrt(scalars_in[BC2])
        for k in range(V):
            i = t + k * nt
            if i < n:
                pi = ps[k]
                gi = gs[k] * coef
                if wp.static(weight_decay and not decoupled):
                    gi = gi + wd * pi
                if wp.static(weight_decay and decoupled):
                    pi = pi * (T(1.0) - lr * wd)
                mi = beta1 * ms[k] + (T(1.0) - beta1) * gi
                vi = beta2 * vs[k] + (T(1.0) - beta2) * gi * gi
                denom = wp.sqrt(vi) / sq2 + eps
                p_out[i] = pi - step * mi / denom
                m_out[i] = mi
                v_out[i] = vi

    return adam
