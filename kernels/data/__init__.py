"""Warp kernels of the data stage (``gnwarp.data``)."""
