"""gnwarp: graph networks as learnable physics engines, on NVIDIA Warp and MuJoCo-Warp."""

from gnwarp.version import __version__  # noqa: F401


def _find_kernels():
    """``gnwarp.kernels`` is the top-level ``kernels/`` folder, mapped by the install (package-dir).
    Run from a source checkout without installing (PYTHONPATH=.), map it here the same way."""
    import importlib.util
    import sys
    from pathlib import Path
    try:
        import gnwarp.kernels  # noqa: F401
        return
    except ModuleNotFoundError:
        pass
    src = Path(__file__).resolve().parent.parent / "kernels"
    spec = importlib.util.spec_from_file_location("gnwarp.kernels", src / "__init__.py",
                                                  submodule_search_locations=[str(src)])
    if spec is None:
        raise ModuleNotFoundError("gnwarp.kernels: install gnwarp (pip install .) or run from its source checkout")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["gnwarp.kernels"] = mod
    spec.loader.exec_module(mod)


_find_kernels()

# the public API: the stages by name, and the handful of objects a user calls, imported on first
# use (PEP 562) so that ``import gnwarp.cli`` and ``gnwarp --help`` do not load torch and Warp
_LAZY = {"GraphsTuple": "gnwarp.graphs", "GraphNetwork": "gnwarp.gn", "GNBlockConfig": "gnwarp.gn",
         "RunOptions": "gnwarp.gn", "TUNABLES": "gnwarp.gn", "flatten_parameters": "gnwarp.gn",
         "ForwardModel": "gnwarp.models", "ModelConfig": "gnwarp.models", "Trainer": "gnwarp.train",
         "TrainConfig": "gnwarp.train", "load_model": "gnwarp.train", "FlatAdam": "gnwarp.train",
         "cuda_graph": "gnwarp.interop", "systems": "gnwarp.sim"}
# (the function ``train`` stays in ``gnwarp.train``: at the top it would hide that subpackage)
_SUBPACKAGES = ("data", "eval", "sim", "gn", "models", "train", "control", "demo", "cli")

# (``gnwarp.eval`` stays out of __all__: a star import would hide Python's builtin ``eval``)
__all__ = ["GraphsTuple", "GraphNetwork", "GNBlockConfig", "RunOptions", "TUNABLES", "ForwardModel", "ModelConfig",
           "Trainer", "TrainConfig", "load_model", "FlatAdam", "flatten_parameters", "cuda_graph", "systems",
           "sim", "data"]


def __getattr__(name: str):
    """``gnwarp.<name>``: a public object or a subpackage, imported on first use."""
    import importlib
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBPACKAGES:
        value = importlib.import_module(f"gnwarp.{name}")
    else:
        raise AttributeError(f"module 'gnwarp' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY) | set(_SUBPACKAGES))
