"""Learned forward models (paper D.1-D.5, E): ``ForwardModel`` on a GN core (``GNCore``) or the MLP
baseline's core (``MLPCore``), with input / output ``Normalizer``s; their configs. The inference
side (D.2, D.7.2): the recurrent GN core (``RecurrentGNCore``) and system identification
(``SysIDModel``: G_ID from a window of dynamic graphs, in place of the static graph; ``gid``:
G_ID saved, loaded and held fixed); ``build_model`` and ``build_sysid_model`` size a new model for its
datasets."""
from gnwarp.models.config import MLP_SIZES, GNCoreConfig, MLPCoreConfig, ModelConfig
from gnwarp.models.cores import GNCore, MLPCore
from gnwarp.models.forward import ForwardModel, MLPForwardModel, StepContext, input_sizes
from gnwarp.models.normalizer import Normalizer
from gnwarp.models.recurrent import RecurrentGNConfig, RecurrentGNCore
from gnwarp.models.gid import FixedGIDModel, GIDError, load_gid, save_gid
from gnwarp.models.sysid import SysIDModel
from gnwarp.models.sysid_config import SysIDConfig
from gnwarp.models.sysid_graphs import NominalGraph, StackedWindow
from gnwarp.models.factory import build_model, build_sysid_model

__all__ = ["ForwardModel", "MLPForwardModel", "ModelConfig", "GNCoreConfig", "MLPCoreConfig", "MLP_SIZES", "GNCore",
           "MLPCore", "Normalizer", "StepContext", "input_sizes", "RecurrentGNConfig", "RecurrentGNCore", "SysIDConfig",
           "SysIDModel", "NominalGraph", "StackedWindow", "save_gid", "load_gid", "GIDError", "FixedGIDModel", "build_model",
           "build_sysid_model"]
