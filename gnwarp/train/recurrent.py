"""Teacher-forcing training of the recurrent one-step model on observation graphs (D.7.3):
``TeacherForcingTrainer``, a ``Trainer`` whose batches are windows of observations.

Its seams change as ``SysIDTrainer``'s do: ``sample`` draws ``batch_size`` random windows of
``window`` observations from the train split of a ``ProprioData`` (``WindowSampler``); ``loss`` is
``RecurrentForwardModel.loss`` (the hidden graph carried through each window, the targets its
next observations); ``validate`` is that loss on the first window of each of the first
``valid_sequences`` valid sequences; checkpoints hold the model's config, its input sizes and
its weights (``load_recurrent`` reads them back onto a ``ProprioData``'s graphs). Everything else
is the ``Trainer``'s: the learning-rate schedule, gradient clipping, weight averaging, the run
folder (``last``, ``best``, ``log.csv``), resume and, on CUDA, steps replayed from CUDA graphs
(one graph with normalizer accumulation, one without).

    >>> cfg = TrainConfig(out="runs/jaco_rnn", steps=2000, batch_size=32, lr=1e-3)
    >>> TeacherForcingTrainer(cfg, data, model).run()      # data: ProprioData, model: RecurrentForwardModel

``TrainConfig.model`` and ``TrainConfig.data`` are not read: the model comes built (its run
options are its own ``config.run``) and the data is the ``ProprioData`` passed in.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from gnwarp.data.proprio import ProprioData, ProprioSplit
from gnwarp.interop import Graphed, resolve_device
from gnwarp.models.recurrent_forward import RecurrentForwardConfig, RecurrentForwardModel
from gnwarp.train.checkpoint import CheckpointError, load_training, load_weights, read_checkpoint
from gnwarp.train.config import TrainConfig
from gnwarp.train.trainer import Trainer

__all__ = ["TeacherForcingTrainer", "WindowSampler", "load_recurrent", "train_teacher_forcing", "KIND"]

KIND = "recurrent_forward"   # config.json's "kind" of these checkpoints


class WindowSampler:
    """Random windows of a split: ``sample(n, generator)`` -> (instance [n], obs [n, window, B, 3],
    ctrl [n, window-1, U]), drawn on the generator's device (``ProprioSplit.windows``)."""

    static_shapes = True   # every window has one shape: a step may be captured

    def __init__(self, split: ProprioSplit, window: int):
        T1 = int(split.obs.shape[1])
        if len(split) == 0:
            raise ValueError("the train split has no sequences")
        if not 2 <= window <= T1:
            raise ValueError(f"window must be 2..{T1} observations (the train split's sequences hold {T1}), "
                             f"got {window}")
        self.split, self.window = split, window

    def sample(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        obs, ctrl, inst = self.split.windows(n, self.window, generator)
        return inst, obs, ctrl


class TeacherForcingTrainer(Trainer):
    """Trains a ``RecurrentForwardModel`` with teacher forcing on ``data`` (a ``ProprioData``); see
    the module docstring.

    ``window``: observations per training window (the paper's 21: 20 inputs, 20 targets).
    ``normalizer_steps``: the normalizers accumulate during the first ``normalizer_steps`` steps
    (and the ``normalizer_warmup`` batches before them); None: every step. ``model``: the model
    to train, on ``data``'s graphs; a rerun into the same ``out`` resumes from ``<out>/last``
    (weights, optimizer, sampler and run state) when its checkpoint holds a model of the same
    sizes. ``config.device`` must resolve to ``data``'s device.
    """

    runs_on_ranks = False   # its own sampler and normalizers are not reduced over ranks

    def __init__(self, config: TrainConfig, data: ProprioData, model: RecurrentForwardModel, window: int = 21,
                 normalizer_steps: int | None = None, callbacks=()):
        if not isinstance(data, ProprioData):
            raise TypeError(f"data must be a gnwarp.data.proprio.ProprioData, got {type(data).__name__}")
        if not isinstance(model, RecurrentForwardModel):
            raise TypeError(f"model must be a RecurrentForwardModel, got {type(model).__name__}")
        if isinstance(window, bool) or not isinstance(window, int):
            raise ValueError(f"window must be an int (observations per training window), got {window!r}")
        if normalizer_steps is not None and (isinstance(normalizer_steps, bool) or not isinstance(normalizer_steps, int)
                                             or normalizer_steps < 0):
            raise ValueError(f"normalizer_steps must be None or an int >= 0, got {normalizer_steps!r}")
        device = resolve_device(config.device)
        if _device_key(device) != _device_key(data.device):
            raise ValueError(f"the observations are on {data.device}, config.device {config.device!r} is {device}: "
                             f"make the ProprioData with device='{device}' or set device='{data.device}'")
        self.data, self.window, self.normalizer_steps = data, window, normalizer_steps
        self.accumulating = True   # whether the next step's loss updates the normalizers
        self._given = model        # resuming rebuilds the model with its run options
        super().__init__(config, [data.dataset], model, callbacks)
        self.info["kind"] = KIND
        self.info["sizes"] = dict(self.model.sizes)
        self.info["train"]["window"] = window
        self.info["train"]["normalizer_steps"] = normalizer_steps
        self._replays = {}
        if self.captured is not None:   # the accumulation is in the recorded step: a second graph without it
            self._replays = {True: self.captured,
                             False: Graphed(self._device_step, warmup=2, generator=self.captured.generator)}

    # -- seams ------------------------------------------------------------------------------
    def place_model(self, model: RecurrentForwardModel) -> RecurrentForwardModel:
        """The model on the device; how it runs is its own ``config.run``."""
        return model.to(self.device)

    def make_sampler(self) -> WindowSampler:
        return WindowSampler(self.data.split("train"), self.window)

    def loss(self, instance: torch.Tensor, obs: torch.Tensor, ctrl: torch.Tensor,
             accumulate: bool | None = None) -> dict[str, torch.Tensor]:
        """{"loss": the teacher-forcing loss of the windows}; ``accumulate`` (default: whether this
        step still accumulates, ``normalizer_steps``): update the normalizers from them first."""
        acc = self.accumulating if accumulate is None else accumulate
        return {"loss": self.model.loss(instance, obs, ctrl, accumulate=acc)}

    def step(self) -> dict[str, torch.Tensor]:
        self.accumulating = self.normalizer_steps is None or self.state["step"] < self.normalizer_steps
        if self._replays:
            self.captured = self._replays[self.accumulating]
        return super().step()

    @torch.no_grad()
    def validate(self) -> float:
        """The teacher-forcing loss of the first ``window`` observations of each of the first
        ``valid_sequences`` valid sequences (NaN without a valid split)."""
        sp = self.data.split("valid")
        n = min(self.config.valid_sequences, len(sp))
        T1 = min(self.window, int(sp.obs.shape[1]))
        if n == 0 or T1 < 2:
            return math.nan
        return float(self.model.loss(sp.instance[:n], sp.obs[:n, :T1], sp.ctrl[:n, :T1 - 1]))

    @property
    def description(self) -> str:
        return "recurrent" if self.model.recurrent else "feed-forward"

    @property
    def log_fields(self) -> tuple[str, ...]:
        return ("step", "seconds", "lr", "loss", "valid_error")

    def _config_changes(self, saved: dict, wanted: RecurrentForwardConfig) -> list[str]:
        if not isinstance(saved, dict) or "recurrent" not in saved:
            return ["model: another kind of checkpoint, not a recurrent one-step model's"]
        want = json.loads(json.dumps(wanted.to_dict()))   # tuples as the JSON lists saved
        changes = [f"model.core.{k}: {v!r} -> {want['core'].get(k)!r}"
                   for k, v in (saved.get("core") or {}).items() if v != want["core"].get(k)]
        changes += [f"model.{k}: {saved.get(k)!r} -> {want[k]!r}" for k in ("recurrent", "std_floor")
                    if saved.get(k) != want[k]]
        return changes   # run options may change

    def _load_last(self):
        """Resuming: the model of ``<out>/last`` (run as the model given says) and its training state."""
        last = self.out / "last"
        return load_recurrent(last, self.data, self.device, run=self._given.config.run), load_training(last)


def load_recurrent(path, data: ProprioData, device=None, run=None) -> RecurrentForwardModel:
    """A ``RecurrentForwardModel`` from a checkpoint folder a ``TeacherForcingTrainer`` wrote
    (manifest and checksums checked, weights read with ``weights_only=True`` and checked
    finite), reading ``data``'s graphs (the observation graphs of the system it trained on:
    its input sizes must match), on ``device`` (default: ``data``'s). ``run``: run options in
    place of the saved ones."""
    path, cfg = read_checkpoint(Path(path))
    if cfg.get("kind") != KIND:
        raise CheckpointError(f"{path} is not a recurrent one-step model's checkpoint (kind {cfg.get('kind')!r})")
    try:
        config = RecurrentForwardConfig.from_dict(cfg["model"])
        sizes = {k: int(cfg["sizes"][k]) for k in ("nodes", "edges", "globals")}
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: config.json does not describe a recurrent one-step model ({e})") from None
    if sizes != data.sizes:
        raise CheckpointError(f"{path}: the model reads graphs of sizes {sizes}, the data's are {data.sizes}")
    if run is not None:
        config.run = run
    model = RecurrentForwardModel(config, sizes, data.graphs, data.movable)
    try:
        model.load_state_dict(load_weights(path))
    except Exception as e:  # noqa: BLE001 - weights of another architecture
        raise CheckpointError(f"{path}: cannot load the weights ({type(e).__name__}: {e})") from None
    model.checkpoint_info = cfg
    return model.to(data.device if device is None else resolve_device(device))


def train_teacher_forcing(config: TrainConfig, data: ProprioData, model: RecurrentForwardModel, window: int = 21,
                          normalizer_steps: int | None = None, callbacks=()) -> dict:
    """Train (or resume) a recurrent one-step model:
    ``TeacherForcingTrainer(config, data, model, window, normalizer_steps, callbacks).run()``."""
    return TeacherForcingTrainer(config, data, model, window, normalizer_steps, callbacks).run()


def _device_key(device) -> tuple:
    d = torch.device(device)
    return d.type, (d.index or 0) if d.type == "cuda" else None
