"""What a forward model is made of (``ModelConfig``, saved as JSON in checkpoints): its core's sizes
and how it runs (``RunOptions``, kept apart from the architecture so it can change at load time)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from gnwarp.gn.options import RunOptions

__all__ = ["GNCoreConfig", "MLP_SIZES", "MLPCoreConfig", "ModelConfig", "DEFAULT_RUN"]

# How models run unless told otherwise: TF32 GEMMs on CUDA (exactly fp32 on the CPU). Measured on an
# H200 (bench/results/train_loop_nvidia-h200.md, rollout_nvidia-h200.md): the captured training
# loop 702 steps/s against fp32's 467, 4096-graph rollouts 1.38 against 5.61 ms a step; and the
# 20-step rollout errors of trained models unchanged to 3 digits against fp32
# (bench/results/speed_accuracy/). fp16 is faster still (783 steps/s, 1.02 ms) with errors also
# unchanged there, but its range (65504) leaves less margin: a choice, not the default.
DEFAULT_RUN = RunOptions(precision="tf32")


@dataclass
class GNCoreConfig:
    """Sizes of the two-block GN core (D.2). Defaults are the paper's standard sizes: edge MLP
    3x512, node and global MLPs 2x256, updated edge/node/global size 128."""
    latent: int = 128
    edge_hidden: tuple[int, ...] = (512, 512, 512)
    node_hidden: tuple[int, ...] = (256, 256)
    global_hidden: tuple[int, ...] = (256, 256)

    def __post_init__(self):
        for k in ("edge_hidden", "node_hidden", "global_hidden"):
            setattr(self, k, tuple(int(h) for h in getattr(self, k)))


# Section E: the five MLP baselines, "<layers>x<width>".
MLP_SIZES = ("3x128", "3x512", "9x128", "9x512", "5x256")


@dataclass
class MLPCoreConfig:
    """MLP baseline core (E): ``layers`` hidden layers of ``width`` on the flattened graph of a
    fixed topology (``n_node`` bodies, ``n_edge`` edges; set from the training data)."""
    layers: int = 5
    width: int = 256
    n_node: int = 0
    n_edge: int = 0

    @classmethod
    def preset(cls, size: str, n_node: int = 0, n_edge: int = 0) -> "MLPCoreConfig":
        if size not in MLP_SIZES:
            raise ValueError(f"unknown MLP size {size!r}; the paper's are {MLP_SIZES}")
        layers, width = (int(s) for s in size.split("x"))
        return cls(layers, width, n_node, n_edge)


# run options that earlier versions kept in the GN core's config
_RUN_KEYS_IN_GN = ("backend", "impl", "path", "precision", "deterministic")


@dataclass
class ModelConfig:
    """What a forward model is made of; saved as JSON in checkpoints.

    ``core``: "gn" (D.2) or "mlp" (E), sized by ``gn`` / ``mlp``. ``run``: how it runs
    (``RunOptions``: implementation, path, precision, ...; default ``DEFAULT_RUN``, TF32 on
    CUDA); "fp64" makes a float64 model.
    ``recenter`` (D.4): re-centre x, y before prediction; None: decided by training (True for a
    single translation-invariant system), False when used as is. ``std_floor``: the normalizers'
    smallest standard deviation.
    """
    core: str = "gn"
    gn: GNCoreConfig = field(default_factory=GNCoreConfig)
    mlp: MLPCoreConfig = field(default_factory=MLPCoreConfig)
    run: RunOptions = field(default_factory=lambda: DEFAULT_RUN)
    recenter: bool | None = None
    std_floor: float = 1e-4

    def __post_init__(self):
        if isinstance(self.gn, dict):
            gn = dict(self.gn)
            moved = {k: gn.pop(k) for k in _RUN_KEYS_IN_GN if k in gn}
            self.gn = GNCoreConfig(**gn)
            if moved:  # an earlier version's config: its run options lived in ``gn``
                # options given as a dict beside them win (TrainConfig's old ``dtype`` arrives so);
                # a RunOptions object here is the default, which the saved options replace
                self.run = {**moved, **self.run} if isinstance(self.run, dict) else {**self.run.to_dict(), **moved}
        if isinstance(self.mlp, dict):
            self.mlp = MLPCoreConfig(**self.mlp)
        if isinstance(self.run, dict):
            self.run = RunOptions.from_dict(self.run)
        if self.core not in ("gn", "mlp"):
            raise ValueError(f"ModelConfig.core must be 'gn' or 'mlp', got {self.core!r}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["run"] = self.run.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """A config from ``to_dict``'s output (or an earlier version's: run options in ``gn``)."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown model config keys: {unknown} (known: {sorted(known)})")
        return cls(**d)
