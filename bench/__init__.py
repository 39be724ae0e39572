"""Benchmarks, probes and the paper's experiments: scripts, run from anywhere by path.

- ``gn_block.py``, ``datagen.py``: the benchmarks (the GN core against torch; data generation)
- ``probes/``: one kernel of the library, with its tuning knobs, against torch (CUDA)
- ``experiments/``: the paper's experiments on the library's ``run_demo`` / ``Trainer`` / ``load_model``
- ``harness.py``: what they share (imported as ``bench.harness``; a package, so that no other
  ``bench`` on the path can shadow it)
- ``results/``: what they wrote
"""
