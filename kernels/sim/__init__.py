"""Warp kernels of the simulation stage (``gnwarp.sim``), one module per launching module."""
