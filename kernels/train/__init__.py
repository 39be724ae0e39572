"""Warp kernels of training (``gnwarp.train``)."""
