"""Hand-written NVIDIA Warp kernels of gnwarp (installed as ``gnwarp.kernels``).

Every ``@wp.kernel`` (and every ``@wp.func`` that takes an array) lists its parameters in
sections, after MuJoCo-Warp's ``_src/smooth.py``: ``# Model:`` (fixed structure of the
system), ``# Parameters:`` (learned weights), ``# Data in:`` (arrays ending in ``_in``, and the
scalars of the launch) and ``# Data out:`` (everything the kernel writes, ending in ``_out``).
An output may be read where the kernel accumulates into it (``+=``, atomic adds) or reads back
what it wrote; an array updated by any other formula in place is passed twice, as ``*_in`` and
``*_out``. ``tests/test_kernel_convention.py`` checks this.
"""
