"""gnwarp: graph networks as learnable physics engines, on NVIDIA Warp and MuJoCo-Warp."""
from gnwarp.graphs import GraphsTuple

__all__ = ["GraphsTuple"]
__version__ = "0.1.0"
