"""The package's version (``gnwarp.__version__``), in a module of its own so that every stage can
record it (checkpoints, datasets) without importing the package's public API."""

__version__ = "0.1.0"
