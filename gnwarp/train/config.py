"""The configuration of a training run (``TrainConfig``, saved with every checkpoint)."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

from gnwarp.models.config import ModelConfig

__all__ = ["TrainConfig", "SCHEDULES"]

SCHEDULES = {"fast": 50_000, "slow": 200_000}   # D.8: learning-rate decay period in steps


@dataclass
class TrainConfig:
    """Everything a training run needs; saved with every checkpoint.

    ``data``: dataset files (several are mixed in equal proportion within each batch).
    ``lr_decay_steps``: steps per x``lr_decay`` (an int, or "fast" / "slow" for the paper's 50k / 200k).
    ``noise_std``: std of the Gaussian noise on input dynamic nodes (D.7.1), in state units.
    ``rotation_loss``: "normalized" or "paper" (see ``ForwardModel.loss``).
    ``max_seconds``: stop after this much training time (None: ``steps`` only).
    ``patience``: stop after this many validations without improvement (None: never).
    ``device``: "auto" (CUDA when present), "cpu", "cuda", "cuda:1", ...
    ``optimizer``: "adam" (torch.optim.Adam + clip_grad_norm_) or "flat_adam"
    (``gnwarp.train.FlatAdam``: the same update and clipping over one flat buffer in Warp
    kernels; faster on the GPU, see README). A run resumes with the optimizer it was started with.
    ``capture``: on CUDA, replay the training step (and the validation rollouts) from CUDA
    graphs once warm (``gnwarp.train.capture``); batches of graphs of varying sizes run eagerly.
    How the model runs (implementation, precision; "fp64" trains in float64) is ``model.run``.
    """
    data: list[str] = field(default_factory=list)
    out: str = "runs/model"
    model: ModelConfig = field(default_factory=ModelConfig)
    steps: int = 100_000
    max_seconds: float | None = None
    batch_size: int = 200
    lr: float = 1e-4
    lr_decay: float = 0.975
    lr_decay_steps: int | str = "fast"
    grad_clip: float = 1.0
    noise_std: float = 0.003
    rotation_loss: str = "normalized"
    normalizer_warmup: int = 20
    valid_every: int = 1000
    valid_sequences: int = 100
    valid_horizon: int = 20
    patience: int | None = 20
    checkpoint_every: int = 1000
    log_every: int = 50
    seed: int = 0
    device: str = "auto"
    resume: bool = True
    progress: bool = True
    optimizer: str = "adam"
    capture: bool = True

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = ModelConfig.from_dict(self.model)
        if isinstance(self.data, (str, os.PathLike)):
            self.data = [str(self.data)]
        self.data = [str(d) for d in self.data]
        if isinstance(self.lr_decay_steps, str):
            if self.lr_decay_steps not in SCHEDULES:
                raise ValueError(f"lr_decay_steps must be an int or one of {sorted(SCHEDULES)}, "
                                 f"got {self.lr_decay_steps!r}")
        if self.batch_size < 1 or self.steps < 0:
            raise ValueError("batch_size must be >= 1 and steps >= 0")
        if self.optimizer not in ("adam", "flat_adam"):
            raise ValueError(f"optimizer must be 'adam' or 'flat_adam', got {self.optimizer!r}")

    @property
    def decay_steps(self) -> int:
        return SCHEDULES[self.lr_decay_steps] if isinstance(self.lr_decay_steps, str) else int(self.lr_decay_steps)

    def lr_at(self, step: int) -> float:
        return self.lr * self.lr_decay ** (step // self.decay_steps)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """A config from a dict (``to_dict``'s, a config file's); unknown keys raise ValueError.
        An earlier version's ``dtype`` key is read as the model's precision ("float64": "fp64")."""
        d = dict(d)
        if "dtype" in d:
            dtype = d.pop("dtype")
            if dtype not in ("float32", "float64"):
                raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
            if dtype == "float64":
                model = d.get("model", {})
                model = model.to_dict() if isinstance(model, ModelConfig) else dict(model)
                model["run"] = {**model.get("run", {}), "precision": "fp64"}
                d["model"] = model
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown training config keys: {unknown} (known: {sorted(known)})")
        return cls(**d)
