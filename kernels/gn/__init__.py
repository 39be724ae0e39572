"""Warp kernels of the GN block (``gnwarp.gn``), one module per launching module."""
