"""Warp kernels of ``gnwarp.models``."""
