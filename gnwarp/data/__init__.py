"""Data: MuJoCo models as graphs, the feature layout models read, datasets of simulated sequences
(HDF5) and the input graphs built from them.

    >>> from gnwarp import data
    >>> ds = data.generate("cartpole", 1000, num_steps=100)   # simulate under random controls
    >>> ds.save("cartpole.h5"); ds = data.load("cartpole.h5")
    >>> g = ds.graphs("train", seq=[0, 1], t=[5, 7])           # input graphs, torch

Modules: ``convert`` (MjModel -> static graph), ``layout`` (which static columns a model reads),
``format`` (the file layout), ``checks`` (validation of its arrays),
``dataset`` (``Dataset``, ``load``, ``check``), ``generation`` (simulating datasets), ``builder`` (input graphs).
"""
from gnwarp.data.builder import GraphBuilder, GraphTemplate, graph_builder
from gnwarp.data.convert import static_arrays, static_graph
from gnwarp.data.dataset import Dataset, Split, load
from gnwarp.data.format import FORMAT, SPLITS, VERSION, DatasetError
from gnwarp.data.generation import PAPER_SIZES, generate, initial_states, split_sizes
from gnwarp.data.layout import FeatureLayout, LayoutMismatchError, map_static, merge_layouts, varying_columns

__all__ = ["generate", "initial_states", "split_sizes", "PAPER_SIZES", "load", "Dataset", "Split", "DatasetError",
           "SPLITS", "FORMAT", "VERSION", "GraphBuilder", "GraphTemplate", "graph_builder", "FeatureLayout",
           "LayoutMismatchError", "map_static", "merge_layouts", "varying_columns", "static_graph", "static_arrays"]
