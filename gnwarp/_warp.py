"""One place that imports and initializes Warp quietly."""
from __future__ import annotations

import functools


@functools.lru_cache(maxsize=None)
def warp():
    """The ``warp`` module, initialized once with its banner silenced."""
    import warp as wp
    wp.config.quiet = True
    wp.init()
    return wp


def cuda_available() -> bool:
    try:
        return warp().get_cuda_device_count() > 0
    except Exception:  # noqa: BLE001 - no usable Warp CUDA runtime means no CUDA here
        return False
