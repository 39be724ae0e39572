"""Hand-written NVIDIA Warp kernels of gnwarp (installed as ``gnwarp.kernels``)."""
