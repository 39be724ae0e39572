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

# the public API: the stages by name, and the handful of objects a user calls
from gnwarp import data, eval, sim  # noqa: E402, F401  (eval: reachable as gnwarp.eval)
from gnwarp.gn import TUNABLES, GNBlockConfig, GraphNetwork, RunOptions, flatten_parameters  # noqa: E402
from gnwarp.graphs import GraphsTuple  # noqa: E402
from gnwarp.interop import cuda_graph  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402
from gnwarp.sim import systems  # noqa: E402
# (the function ``train`` stays in ``gnwarp.train``: at the top it would hide that subpackage)
from gnwarp.train import FlatAdam, TrainConfig, Trainer, load_model  # noqa: E402

# (``gnwarp.eval`` stays out of __all__: a star import would hide Python's builtin ``eval``)
__all__ = ["GraphsTuple", "GraphNetwork", "GNBlockConfig", "RunOptions", "TUNABLES", "ForwardModel", "ModelConfig",
           "Trainer", "TrainConfig", "load_model", "FlatAdam", "flatten_parameters", "cuda_graph", "systems",
           "sim", "data"]
