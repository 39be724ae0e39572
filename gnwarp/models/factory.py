"""Model factories: a new ``ForwardModel`` (``build_model``) or ``SysIDModel``
(``build_sysid_model``) sized for the datasets it will read."""
from __future__ import annotations

import dataclasses

import numpy as np

from gnwarp.data.layout import merge_layouts
from gnwarp.models.config import ModelConfig, check_model_size
from gnwarp.models.forward import ForwardModel, input_sizes
from gnwarp.models.sysid import SysIDModel
from gnwarp.models.sysid_config import SysIDConfig
from gnwarp.models.sysid_graphs import nominal_graph, source_places

__all__ = ["build_model", "build_sysid_model"]


def _model_config(config) -> ModelConfig:
    if not isinstance(config, ModelConfig):
        raise TypeError(f"a model is built from a ModelConfig (a TrainConfig's is its .model), got "
                        f"{type(config).__name__}")
    return dataclasses.replace(config)


def _recenter(mcfg: ModelConfig, datasets) -> None:
    """D.4: re-centre single-system models of translation-invariant systems (unless set)."""
    if mcfg.recenter is None:
        mcfg.recenter = len(datasets) == 1 and bool(datasets[0].meta.get("translation_invariant", False))


def build_model(config: ModelConfig, datasets) -> ForwardModel:
    """A new ``ForwardModel`` from ``config`` for ``datasets``: their merged feature layout,
    re-centring decided (D.4), the MLP baseline's fixed topology read from the data."""
    mcfg = _model_config(config)
    layout = merge_layouts([d.layout for d in datasets])
    _recenter(mcfg, datasets)
    if mcfg.core == "mlp":
        B = {int(d.meta["max_bodies"]) for d in datasets}
        E = {int(d.meta["max_edges"]) for d in datasets}
        uniform = all(np.all(np.asarray(d.static["n_node"]) == d.meta["max_bodies"]) for d in datasets)
        if len(B) > 1 or len(E) > 1 or not uniform:
            raise ValueError("the MLP baseline needs one fixed topology; these datasets mix graph sizes")
        mcfg.mlp = dataclasses.replace(mcfg.mlp, n_node=B.pop(), n_edge=E.pop())
    check_model_size(mcfg, input_sizes(layout))  # an impossible size: an error naming it, before allocating
    return ForwardModel(mcfg, layout)


def build_sysid_model(config: ModelConfig, datasets, sysid: SysIDConfig | None = None) -> SysIDModel:
    """A new ``SysIDModel`` for ``datasets``: the forward model from ``config`` (re-centring
    decided as ``build_model`` does, D.4), GN_p and the window from ``sysid`` (default
    ``SysIDConfig()``); ``param_places`` (with ``local_params``) and ``nominal`` (with
    ``nominal_static``) filled from the data where unset."""
    sysid = sysid or SysIDConfig()
    mcfg = _model_config(config)
    _recenter(mcfg, datasets)
    if mcfg.core != "gn":
        raise ValueError("system identification trains the GN forward model (model.core = 'gn')")
    if sysid.local_params and sysid.param_places is None:   # where the data's parameters live
        places = {source_places(d) for d in datasets}
        if len(places) > 1:
            raise ValueError("local_params: the datasets place their parameters differently (train one system)")
        sysid = dataclasses.replace(sysid, param_places=places.pop())
    if sysid.nominal_static and sysid.nominal is None:   # the training data's system as designed
        if len(datasets) != 1:
            raise ValueError(f"nominal_static reads one dataset's nominal static graph; got {len(datasets)} datasets "
                             f"(train on one)")
        sysid = dataclasses.replace(sysid, nominal=nominal_graph(datasets[0]))
    return SysIDModel(dataclasses.replace(sysid, forward=mcfg), merge_layouts([d.layout for d in datasets]))
