"""Learned forward models (paper D.1-D.5, E): ``ForwardModel`` on a GN core (``GNCore``) or the MLP
baseline's core (``MLPCore``), with input / output ``Normalizer``s; their configs."""
from gnwarp.models.config import MLP_SIZES, GNCoreConfig, MLPCoreConfig, ModelConfig
from gnwarp.models.cores import GNCore, MLPCore
from gnwarp.models.forward import ForwardModel, MLPForwardModel, StepContext, input_sizes
from gnwarp.models.normalizer import Normalizer

__all__ = ["ForwardModel", "MLPForwardModel", "ModelConfig", "GNCoreConfig", "MLPCoreConfig", "MLP_SIZES", "GNCore",
           "MLPCore", "Normalizer", "StepContext", "input_sizes"]
