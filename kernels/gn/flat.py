"""Warp kernel of ``gnwarp/gn/flat.py``: a GN block's parameter gradients added into the flat
gradient buffer of its parameters (``main_grad``, ``FlatAdam``'s)."""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS

__all__ = ["accumulate_kernel"]


@functools.cache
def accumulate_kernel(src_dtype, dst_dtype):
    """dst_out[dst_off_k + j] += src_in[src_off_k + j] for j < n_k of each segment k of
    ``table_in`` [S, 2] (src_off, dst_off), segment k covering threads [starts_in[k],
    starts_in[k + 1]): a GN block's weight
    (or bias) gradients, packed in its own buffer, added into the optimizer's flat gradient with
    the dtype cast, in one launch. One thread per element; segments found by a linear scan."""
    S = src_dtype
    D = dst_dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def accumulate(
        # Data in:
        src_in: wp.array(dtype=S),
        table_in: wp.array2d(dtype=wp.int32),
        starts_in: wp.array(dtype=wp.int32),
        n_seg: int,
        # Data out:
        dst_out: wp.array(dtype=D),
    ):
        t = wp.tid()
        k = int(0)
        while k + 1 < n_seg and t >= starts_in[k + 1]:
            k += 1
        j = t - starts_in[k]
        x = D(src_in[table_in[k, 0] + j])
        d = table_in[k, 1] + j
        dst_out[d] = dst_out[d] + x

    return accumulate
