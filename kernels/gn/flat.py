"""Warp kernel of ``gnwarp/gn/flat.py``: a GN block's parameter gradients added into the flat
gradient buffer of its parameters (``main_grad``, ``FlatAdam``'s)."""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS

__all__ = ["accumulate_kernel"]


@functools.cache
def accumulate_kernel(src_dtype, dst_dtype):
    """dst[dst_off_k + j] += src[src_off_k + j] for j < n_k of each segment k of ``table`` [S, 2]
    (src_off, dst_off), segment k covering threads [starts[k], starts[k + 1]): a GN block's weight
    (or bias) gradients, packed in its own buffer, added into the optimizer's flat gradient with
    the dtype cast, in one launch. One thread per element; segments found by a linear scan."""
    S = src_dtype
    D = dst_dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def accumulate(src: wp.array(dtype=S), table: wp.array2d(dtype=wp.int32), starts: wp.array(dtype=wp.int32),
                   n_seg: int, dst: wp.array(dtype=D)):
        t = wp.tid()
        k = int(0)
        while k + 1 < n_seg and t >= starts[k + 1]:
            k += 1
        j = t - starts[k]
        x = D(src[table[k, 0] + j])
        d = table[k, 1] + j
        dst[d] = dst[d] + x

    return accumulate
