"""The configuration of a training run (``TrainConfig``, saved with every checkpoint)."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Annotated, Literal, Union

from pydantic import Field

from gnwarp.validation import (Allowed, BatchSize, ConfigError, Seed, Count, Flag, FloatRange, PositiveFloat,
                               PositiveInt,
                               check_fields, check_keys)
from gnwarp.models.config import ModelConfig

__all__ = ["TrainConfig", "SCHEDULES", "ConfigError"]

SCHEDULES = {"fast": 50_000, "slow": 200_000}   # D.8: learning-rate decay period in steps

# the allowed values of TrainConfig's fields (gnwarp.gn.config validates them)
DecaySteps = Annotated[Union[PositiveInt, Literal["fast", "slow"]],
                       Allowed("an integer >= 1, or 'fast' (50000) or 'slow' (200000)")]
Paths = Annotated[list[str], Allowed("a list of file paths (strings)")]
Decay = FloatRange(gt=0, le=1)
NonNegativeFloat = FloatRange(ge=0)
AverageDecay = FloatRange(ge=0, lt=1)   # ema: 0 (off) or a decay below 1
Device = Annotated[str, Field(pattern=r"^(auto|cpu|cuda(:[0-9]+)?)$"), Allowed("'auto', 'cpu', 'cuda' or 'cuda:N'")]


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
    ``optimizer``: "adam" (torch.optim.Adam + clip_grad_norm_), "flat_adam"
    (``gnwarp.train.FlatAdam``: the same update and clipping over one flat buffer in Warp
    kernels; faster on the GPU, see docs/gn_kernels.md) or "auto" (default: flat_adam on CUDA, adam
    elsewhere). A run resumes with the optimizer it was started with (under "auto", the kind
    its saved optimizer state is).
    ``capture``: on CUDA, replay the training step (and the validation rollouts) from CUDA
    graphs once warm (``gnwarp.interop.Graphed``); batches of graphs of varying sizes run eagerly.
    How the model runs (implementation, precision; "fp64" trains in float64) is ``model.run``.
    ``on_config_change``: when ``resume`` finds a run in ``out`` it cannot continue as configured
    (its checkpoint's model differs from ``model``: run options may change, sizes not; or its
    log.csv records progress but no checkpoint is left), "error" refuses, naming what differs;
    "restart" moves the old run's files to ``out/replaced-<n>/`` and starts a new run.
    ``overlap_allreduce``: over several ranks with FlatAdam, average GN2's gradients while GN1's
    backward runs (two all-reduces a step, the first overlapped: ``gnwarp.train.overlap``); False
    (default; overlapping was no faster on 2 H100s, bench/results/distributed): one all-reduce of
    every gradient after the backward.
    ``grad_clip``: the gradients' global norm is clipped to it (> 0; None: no clipping).
    ``ema`` (beyond the paper; default 0, off): the decay of an exponential moving average of the
    weights (Polyak averaging, ``gnwarp.train.WeightAverage``; e.g. 0.999, about the last 1000
    steps), updated after every step. Validation and every checkpoint's model use the averages
    (``last`` also keeps the live weights, to resume from); the optimizer steps the live weights.
    ``lr_decay``: in (0, 1]. Every value is validated against its field's type (above): a wrong
    type, a zero or negative interval or an impossible size raises one ``ConfigError`` naming the
    key path (``model.gn.latent``) and the allowed values, from Python, a config file or ``--set``.
    """
    data: Paths = field(default_factory=list)
    out: str = "runs/model"
    model: ModelConfig = field(default_factory=ModelConfig)
    steps: Count = 100_000
    max_seconds: PositiveFloat | None = None
    batch_size: BatchSize = 200
    lr: PositiveFloat = 1e-4
    lr_decay: Decay = 0.975
    lr_decay_steps: DecaySteps = "fast"
    grad_clip: PositiveFloat | None = 1.0
    ema: AverageDecay = 0.0
    noise_std: NonNegativeFloat = 0.003
    rotation_loss: Literal["normalized", "paper"] = "normalized"
    normalizer_warmup: Count = 20
    valid_every: PositiveInt = 1000
    valid_sequences: PositiveInt = 100
    valid_horizon: PositiveInt = 20
    patience: PositiveInt | None = 20
    checkpoint_every: PositiveInt = 1000
    log_every: PositiveInt = 50
    seed: Seed = 0
    device: Device = "auto"
    resume: Flag = True
    on_config_change: Literal["error", "restart"] = "error"
    progress: Flag = True
    optimizer: Literal["auto", "adam", "flat_adam"] = "auto"
    capture: Flag = True
    overlap_allreduce: Flag = False

    def __post_init__(self):
        if isinstance(self.data, (str, os.PathLike)):
            self.data = [self.data]
        if isinstance(self.data, (list, tuple)):
            self.data = [os.fspath(d) if isinstance(d, os.PathLike) else d for d in self.data]
        if isinstance(self.out, os.PathLike):
            self.out = os.fspath(self.out)
        # every value against its annotation (types, ranges, allowed words; ``model`` from a dict):
        # one ConfigError naming the key path, e.g. "model.gn.latent", and the allowed values
        check_fields(self)

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
        if not isinstance(d, dict):
            check_keys(cls, d)
        d = dict(d)
        if "dtype" in d:
            dtype = d.pop("dtype")
            if dtype not in ("float32", "float64"):
                raise ConfigError("dtype", f"must be 'float32' or 'float64' (an earlier version's key), got {dtype!r}")
            if dtype == "float64":
                model = d.get("model", {})
                model = model.to_dict() if isinstance(model, ModelConfig) else dict(check_keys(ModelConfig, model))
                model["run"] = {**model.get("run", {}), "precision": "fp64"}
                d["model"] = model
        return cls(**check_keys(cls, d, "training config keys"))
