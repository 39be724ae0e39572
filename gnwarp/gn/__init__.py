"""The graph-network block of the paper on hand-written Warp kernels (``GraphNetwork``), its
pure-torch reference, and how it runs (``RunOptions``, the measured rules' ``TUNABLES``).

Modules: ``config`` (sizes and switches), ``options`` (run options resolved per call),
``reference`` (torch reference, input checks), ``module`` (``GraphNetwork``), ``index`` (graph
index arrays), ``rules`` (measured dispatch rules), the blas path (``blas_block`` on
``graph_ops``, ``mlp``, ``first_layer``, ``fp16x3``, ``side``, ``flat``) and the tile path
(``tile_block``). Their kernels: ``gnwarp.kernels.gn``.
"""
from gnwarp.gn.config import EdgeBlockConfig, GlobalBlockConfig, GNBlockConfig, NodeBlockConfig
from gnwarp.gn.flat import flatten_parameters
from gnwarp.gn.index import GraphIndex, graph_index
from gnwarp.gn.module import GraphNetwork
from gnwarp.gn.options import PRECISIONS, RunOptions, tf32_matmul
from gnwarp.gn.reference import MLP, TorchGraphNetwork, check_graph
from gnwarp.gn.rules import TUNABLES, Tunables

__all__ = ["EdgeBlockConfig", "NodeBlockConfig", "GlobalBlockConfig", "GNBlockConfig", "GraphNetwork",
           "TorchGraphNetwork", "MLP", "check_graph", "RunOptions", "PRECISIONS", "tf32_matmul", "GraphIndex",
           "graph_index", "TUNABLES", "Tunables", "flatten_parameters"]
