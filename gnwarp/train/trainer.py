"""Training of forward models (supplementary D.7, D.8): the ``Trainer`` and ``train(config)``.

A ``Trainer`` fits a ``ForwardModel`` to one or more datasets: Adam with gradient clipping,
learning rate ``lr * lr_decay ** (step // lr_decay_steps)`` (paper: 1e-4, 0.975, every 50k steps
"fast" or 200k "slow"), batches of ``batch_size`` graphs drawn uniformly over (sequence, step) of
each train split, several datasets mixed in equal proportion, normalizers accumulated from the
training batches, validation by the 20-step rollout error on the valid split, best checkpoint
kept, early stopping. A run folder holds::

    <out>/last/   the latest checkpoint (training resumes from it)
    <out>/best/   the checkpoint with the lowest validation error
    <out>/log.csv losses, learning rate and validation errors

Its seams, for the stages that reuse it (captured steps, system identification, recurrent
teacher forcing, RL learners, distributed ranks): ``place_model`` (the model as it trains),
``make_sampler`` / ``sampler`` (where batches come from), ``loss`` (the objective of a batch),
``step`` (one optimization step), ``validate``, ``checkpoint`` and ``callbacks`` (called as
``callback(trainer, event, info)`` for the events "log", "validate", "checkpoint" and "end").
The loop's checkpoints are copied to the CPU at their step and written by a background thread
(``CheckpointWriter``), so training does not wait on the disk; "checkpoint" comes once the folder
is in place, and the run's end waits for every write. Override a method in a subclass, or replace
``trainer.sampler``, to change one seam.

Several ranks (``torchrun``, ``gnwarp.distributed``): each rank draws its own ``batch_size``
graphs (the batch is per rank; the step's batch is ``batch_size`` x ranks), the model starts
from rank 0's weights, the gradients (FlatAdam's one flat buffer: one all-reduce a step, inside
the captured step, or two with ``overlap_allreduce``) and each batch's normalizer sums are summed over the ranks, so every rank
takes the step one process would take on the joint batch. Rank 0 validates and decides (best,
early stopping, the time budget) for all, writes log.csv and the checkpoints; a checkpoint holds
every rank's sampler state, and a run resumes with any number of ranks (the same number continues
exactly; with another, the ranks past the saved ones draw fresh streams).
"""
from __future__ import annotations

import contextlib
import csv
import math
import os
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from gnwarp.data.dataset import load
from gnwarp.data.layout import merge_layouts
from gnwarp.distributed import launched, ranks as join_ranks
from gnwarp.eval.metrics import rollout_error
from gnwarp.files import atomic_write
from gnwarp.graphs import GraphsTuple
from gnwarp.interop import Graphed, capture_problem, default_generator, registers_generators
from gnwarp.models.factory import build_model
from gnwarp.models.forward import ForwardModel
from gnwarp.models.normalizer import Normalizer
from gnwarp.train.checkpoint import (CheckpointError, CheckpointWriter, checkpoint_config, clean_debris,
                                     load_checkpoint, model_config_changes, recover_checkpoint)
from gnwarp.train.config import TrainConfig
from gnwarp.train.optim import FlatAdam, WeightAverage
from gnwarp.train.overlap import GradientBuckets
from gnwarp.train.sampler import BatchSampler

__all__ = ["Trainer", "train", "LOG_FIELDS"]

LOG_FIELDS = ("step", "seconds", "lr", "loss", "pos", "quat", "linvel", "angvel", "valid_error")


def _data_info(datasets) -> list[dict]:
    keys = ("system", "parameterized", "dt", "num_steps", "seed", "splits", "translation_invariant")
    return [{k: d.meta.get(k) for k in keys} for d in datasets]


class Trainer:
    """Fits a ``ForwardModel`` as ``config`` says (see the module docstring).

    ``datasets``: ``Dataset`` objects to use instead of loading ``config.data``. ``model``: an
    initial model (else built from ``config.model``, or resumed from ``<out>/last``: its weights,
    optimizer and sampler state). Whichever it is, it runs as ``config.model.run`` says
    (implementation, precision: "fp64" trains in float64). ``callbacks``: functions
    ``callback(trainer, event, info)``.
    """

    # whether this trainer runs over several ranks (a subclass with its own step says False)
    runs_on_ranks = True

    def __init__(self, config: TrainConfig, datasets=None, model: ForwardModel | None = None,
                 callbacks: list[Callable] = ()):
        if not self.runs_on_ranks and launched():
            raise ValueError(f"{type(self).__name__} trains in one process: start it without torchrun")
        self.config = config
        self.out = Path(config.out)
        self.ranks = join_ranks(config.device)   # rank 0 of 1 unless started by torchrun
        self.device = self.ranks.device
        self.callbacks = list(callbacks)
        torch.manual_seed(config.seed)
        if datasets is None:
            if not config.data:
                raise ValueError("no training data: set `data` to one or more dataset files")
            datasets = [load(p, lazy=True) for p in config.data]
        self.datasets = list(datasets)
        training = None
        if self._prepare_out_once(model):  # with resume: recovers what killed runs left, refuses what it cannot resume
            model, training = self._load_last()
        elif model is None:
            model = build_model(config.model, self.datasets)
        self.model = self.place_model(model)
        if self.ranks.distributed:
            self._join_model()
        self.sampler = self.make_sampler()
        self.valid = [d for d in self.datasets if len(d["valid"]) > 0]
        if not self.valid and self.ranks.main:   # allowed (a last model is still a model), but said
            warnings.warn("no dataset has a valid split: nothing is validated, and best/ will be the last model, "
                          "not a validated one (generate with valid sequences, e.g. -n's paper proportions)",
                          stacklevel=2)
        cuda = self.device.type == "cuda"
        # a CUDA graph replays the device's default generator by itself; others need registering
        self.generator = (default_generator(self.device) if cuda and config.capture and not registers_generators()
                          else torch.Generator(device=self.device))
        self.generator.manual_seed(self._rank_seed(0))
        self.optimizer = self.make_optimizer(self._optimizer_kind(training))
        # ``config.ema``: the weights' moving average, which validation and checkpoints use
        self.average = WeightAverage(self.average_tensors(), config.ema) if config.ema > 0 else None
        # over ranks: GN2's gradients averaged while GN1's backward runs (``config.overlap_allreduce``)
        self.buckets = (GradientBuckets.for_model(self.ranks, self.optimizer, self.model)
                        if config.overlap_allreduce and isinstance(self.optimizer, FlatAdam) else None)
        self.state = {"step": 0, "best_error": math.inf, "best_step": -1, "bad_validations": 0, "seconds": 0.0}
        if training is not None:
            self._restore(training)
        # what is recorded is the model trained: its config, whether new, passed in or resumed
        self.info = {"train": {**config.to_dict(), "model": self.model.config.to_dict()},
                     "data": _data_info(self.datasets)}
        self._running: dict[str, torch.Tensor] = {}   # loss sums since the last log row, on the device
        self._running_sum: torch.Tensor | None = None  # the same sums as one vector
        self._n_running = 0
        self._lr = None                               # the learning rate the optimizer holds now
        self._terms: dict[str, torch.Tensor] = {}     # the last step's loss terms
        self.captured = None
        self._valid_engines: dict = {}
        self._writer: CheckpointWriter | None = None  # background checkpoint writes
        if config.capture and cuda:
            problem = capture_problem(self.device, self.sampler.static_shapes, self.generator)
            if problem is None:
                own = self.generator if self.generator is not default_generator(self.device) else None
                self.captured = Graphed(self._device_step, warmup=2, generator=own)
            else:
                warnings.warn(f"training steps run uncaptured: {problem}")

    # -- ranks -----------------------------------------------------------------------------------
    def _rank_seed(self, step: int) -> int:
        """The sampler's seed on this rank: ``config.seed`` on rank 0 (a single process is one)."""
        r = self.ranks.rank
        return (self.config.seed + r * 1_000_003 + (step * 7_919 if r else 0)) % (1 << 63)

    def _prepare_out_once(self, model) -> bool:
        """``_prepare_out`` on rank 0 (the others wait for its answer and share it)."""
        return self.ranks.on_main(f"preparing {self.out}", lambda: self._prepare_out(model))

    def _join_model(self) -> None:
        """Every rank starts from rank 0's weights and normalizer sums; each batch's normalizer
        sums are summed over the ranks from now on."""
        with torch.no_grad():
            for t in self.model.state_dict().values():
                if isinstance(t, torch.Tensor) and t.numel():
                    self.ranks.broadcast_(t)
        for m in self.model.modules():
            if isinstance(m, Normalizer):
                m.ranks = self.ranks

    def _validate_on_main(self) -> float:
        """``validate()`` on rank 0, its error (or its failure) shared with every rank."""
        return self.ranks.on_main("validation", self.validate)

    def reduce_gradients(self) -> None:
        """Average the gradients over the ranks (one all-reduce of FlatAdam's flat buffer, or with
        ``overlap_allreduce`` the rest of it after GN2's span went out during the backward; else
        of the gradients packed in one buffer); nothing for a single process."""
        if not self.ranks.distributed:
            return
        if self.buckets is not None:
            self.buckets.reduce()
            return
        if isinstance(self.optimizer, FlatAdam):
            self.ranks.all_reduce_(self.optimizer.fold_grads(), mean=True)
            return
        grads = [p.grad for p in self.model.parameters() if p.grad is not None]
        if grads:
            flat = torch.cat([g.reshape(-1) for g in grads])
            self.ranks.all_reduce_(flat, mean=True)
            o = 0
            for g in grads:
                g.copy_(flat[o:o + g.numel()].view_as(g))
                o += g.numel()

    # -- seams -----------------------------------------------------------------------------------
    def _optimizer_kind(self, training: dict | None) -> str:
        """``config.optimizer``, "auto" resolved: the kind a resumed run's saved state is, else
        FlatAdam on CUDA (one flat update, faster there) and torch's Adam elsewhere."""
        kind = self.config.optimizer
        if kind != "auto":
            return kind
        saved = training.get("optimizer") if isinstance(training, dict) else None
        if isinstance(saved, dict):
            return "flat_adam" if saved.get("format") == "gnwarp.FlatAdam/1" else "adam"
        return "flat_adam" if self.device.type == "cuda" else "adam"

    def place_model(self, model):
        """The model as it trains: run as ``config.model.run`` says, on the device, in its
        parameter dtype."""
        run = self.config.model.run
        return model.set_options(run).to(device=self.device, dtype=run.param_dtype)

    def make_sampler(self):
        """Where batches come from: an object with ``sample(batch_size, generator)`` (its result
        is ``loss``'s arguments) and ``static_shapes`` (whether a step may be captured)."""
        return BatchSampler(self.datasets, self.model, self.device)

    def make_optimizer(self, kind: str | None = None) -> torch.optim.Optimizer:
        """torch's Adam (clipping in ``step``) or FlatAdam (clipping inside), as ``kind`` (default:
        ``config.optimizer``, "auto" resolved) says."""
        c = self.config
        kind = kind or self._optimizer_kind(None)
        if kind == "flat_adam":
            return FlatAdam(self.model.parameters(), lr=c.lr, max_grad_norm=c.grad_clip)
        if self.device.type == "cuda":  # capturable: the learning rate and step count on the device
            return torch.optim.Adam(self.model.parameters(), lr=torch.tensor(c.lr, device=self.device),
                                    capturable=True, foreach=True)
        return torch.optim.Adam(self.model.parameters(), lr=c.lr)

    def average_tensors(self) -> list[torch.Tensor]:
        """What ``config.ema`` averages: FlatAdam's one flat buffer, else the model's parameters."""
        return [self.optimizer.flat] if isinstance(self.optimizer, FlatAdam) else list(self.model.parameters())

    def sample(self) -> tuple[GraphsTuple, torch.Tensor]:
        """One training batch: (input graphs, true next states [sum(n_node), 13])."""
        return self.sampler.sample(self.config.batch_size, self.generator)

    def loss(self, graph: GraphsTuple, target: torch.Tensor, accumulate: bool = True) -> dict[str, torch.Tensor]:
        """The loss terms of a batch (``ForwardModel.loss`` with the config's noise and rotation
        loss); ``accumulate``: update the normalizers from it first."""
        c = self.config
        return self.model.loss(graph, target, noise_std=c.noise_std, accumulate=accumulate,
                               rotation_scale=c.rotation_loss, generator=self.generator)

    def step(self) -> dict[str, torch.Tensor]:
        """One optimization step at the schedule's learning rate: sample, loss, backward, clip,
        update, the loss terms added to the running sums of the next log row (replayed from a CUDA
        graph once warm, see ``captured``); then the step count advances. Returns the loss terms
        (device tensors, overwritten by the next captured step; nothing here syncs with the host)."""
        self.set_lr(self.config.lr_at(self.state["step"]))
        if self.captured is not None:
            self.captured()
        else:
            self._device_step()
        self.state["step"] += 1
        self._n_running += 1
        return self._terms

    def set_lr(self, lr: float) -> None:
        """Give the optimizer this learning rate (into its device scalar when it has one)."""
        if lr == self._lr:
            return
        for group in self.optimizer.param_groups:
            if isinstance(group["lr"], torch.Tensor):
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr
        if isinstance(self.optimizer, FlatAdam):
            self.optimizer.sync_lr()
        self._lr = lr

    def _device_step(self) -> None:
        """The device work of one step (what ``captured`` records): no host sync, no reallocation
        of anything read between steps."""
        batch = self.sample()
        # keep the batch: a captured step reads its index tensors (cached per batch size by the
        # graph builder, which may drop them) at every replay
        self._batch = batch
        with self.buckets.armed() if self.buckets is not None else contextlib.nullcontext():
            terms = self.loss(*batch)
        self.optimizer.zero_grad(set_to_none=True)
        terms["loss"].backward()
        self.reduce_gradients()
        if not isinstance(self.optimizer, FlatAdam) and self.config.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip)
        self.optimizer.step()
        if self.average is not None:
            self.average.update()
        # summed on the device, in place, into one vector (``_running`` holds views of its
        # entries by name); read once per log line
        vec = torch.stack([v.detach() for v in terms.values()])
        if self._running_sum is None or self._running_sum.shape != vec.shape:
            self._running_sum = torch.zeros_like(vec)
            self._running = {k: self._running_sum[i] for i, k in enumerate(terms)}
        self._running_sum.add_(vec)
        self._terms = terms

    def averaged(self):
        """A context with the weights' moving average in their place (``config.ema``; without
        it, the weights as they are)."""
        return self.average.applied() if self.average is not None else contextlib.nullcontext()

    def validate(self) -> float:
        """Mean normalized ``valid_horizon``-step rollout error over the datasets with a valid
        split (the rollouts replayed from CUDA graphs when the step is captured)."""
        c = self.config
        self.model.eval()
        errs = [rollout_error(self.model, d, "valid", c.valid_horizon, c.valid_sequences,
                              engine=self._valid_engine(k, d)) for k, d in enumerate(self.valid)]
        self.model.train()
        return float(np.mean(errs)) if errs else math.nan

    def _valid_engine(self, k: int, ds):
        """The captured validation rollouts of dataset ``k`` (None when steps run uncaptured)."""
        if self.captured is None:
            return None
        if k not in self._valid_engines:
            sp, c = ds["valid"], self.config
            n = min(c.valid_sequences, len(sp))
            self._valid_engines[k] = self.model.rollout_engine(np.asarray(sp.instance[:n]),
                                                               min(c.valid_horizon, sp.num_steps),
                                                               self.model.graph_builder(ds))
        return self._valid_engines[k]

    def checkpoint(self, name: str, wait: bool = True) -> Path:
        """Write ``<out>/<name>`` (model, optimizer, sampler and run state). ``wait=False`` (the
        training loop's): the state is copied now and written by a background thread while
        training goes on; the "checkpoint" event comes once the folder is in place. Over several
        ranks it is a collective (rank 0 gathers every rank's sampler state): every rank calls it."""
        st = self.state
        readable = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in st.items()}
        path = self.out / name
        generators = self.ranks.gather_objects(self.generator.get_state().cpu()) if self.ranks.distributed else None
        if not self.ranks.main:   # rank 0 writes; the others only hand it their sampler states
            return path
        if self._writer is None:
            self._writer = CheckpointWriter()
        with self.averaged():   # the model saved is the averaged one; the live weights go with the training state
            training = {"optimizer": self.optimizer.state_dict(), "state": dict(st),
                        "generator": self.generator.get_state()}
            if generators is not None:
                training["rank_generators"] = generators
            if self.average is not None:
                training["average"] = self.average.state_dict()
            self._writer.submit(name, path, self.model, training, {**self.info, "state": readable})
        self._checkpoints_written(wait)
        return path

    def _checkpoints_written(self, wait: bool = False) -> None:
        """Emit "checkpoint" for the background writes finished (all, with ``wait``)."""
        if self._writer is not None and self.ranks.main:
            for name, path in self._writer.done(wait):
                self.emit("checkpoint", name=name, path=path)

    @property
    def description(self) -> str:
        """What the progress bar names the model."""
        return str(self.model.config.core)

    @property
    def log_fields(self) -> tuple[str, ...]:
        """The columns of log.csv: ``LOG_FIELDS`` (a subclass with more loss terms adds them)."""
        return LOG_FIELDS

    def warmup(self) -> None:
        """Normalizer statistics from a few batches before the first gradient step, so the first
        steps do not train against identity transforms."""
        if self.state["step"] == 0 and self.model.norm_nodes.count.item() == 0:
            with torch.no_grad():
                for _ in range(self.config.normalizer_warmup):
                    self.loss(*self.sample())

    def emit(self, event: str, **info) -> None:
        for cb in self.callbacks:
            cb(self, event, info)

    # -- the loop -------------------------------------------------------------------------------
    def _prepare_out(self, model: ForwardModel | None) -> bool:
        """Before a run in ``out``: put back checkpoints that runs killed while saving them left
        aside and remove the rest of their debris. Returns whether to resume from ``out/last``
        (``resume`` and a checkpoint there whose model is the one the config asks for). A run it
        cannot continue (another model; log.csv rows but no checkpoint left) raises
        ``CheckpointError``, or with ``on_config_change="restart"`` is moved to ``out/replaced-<n>``."""
        c, out, last = self.config, self.out, self.out / "last"
        if c.resume:
            recover_checkpoint(out / "best")
            recover_checkpoint(last, fallbacks=[out / "best"])  # the newest intact one
        clean_debris(out, ("last", "best", "log.csv"))
        if not c.resume:
            return False
        if last.is_dir():
            wanted = model.config if model is not None else c.model
            saved = checkpoint_config(last)
            try:
                changes = self._config_changes(saved["model"], wanted)
            except (KeyError, TypeError, ValueError) as e:
                raise CheckpointError(f"{last}: config.json does not describe a model ({e})") from None
            if not changes:
                return True
            problem = (f"{last} holds a model other than the config asks for ({'; '.join(changes)}); "
                       "resuming cannot change a model's sizes (run options may change)")
        else:
            steps = _logged_steps(out / "log.csv")
            if not steps:
                return False
            problem = (f"{out / 'log.csv'} records training up to step {max(steps)} but no checkpoint is left to "
                       f"resume from ({last} is missing and nothing a killed run left could be restored); "
                       "refusing to start again from step 0 over it")
        if c.on_config_change != "restart":
            raise CheckpointError(f"{problem}. Set on_config_change='restart' to move the old run to "
                                  f"{out}/replaced-<n>/ and start a new one, or choose another out")
        dest = _move_aside(out)
        warnings.warn(f"{problem}: moved it to {dest} and starting a new run (on_config_change='restart')")
        return False

    def _load_last(self):
        """(model, training state) of ``<out>/last``, to resume from."""
        model, training, _ = load_checkpoint(self.out / "last", self.device)
        if merge_layouts([d.layout for d in self.datasets]).to_dict() != model.layout.to_dict():
            warnings.warn(f"resuming {self.out / 'last'}: the datasets' merged layout differs from the model's; "
                          "mapping them onto the model's layout")
        return model, training

    def _config_changes(self, saved: dict, wanted) -> list[str]:
        """What differs between ``<out>/last``'s model config and the one asked for (see
        ``model_config_changes``); a subclass with another model kind compares its own."""
        return model_config_changes(saved, wanted)

    def _restore(self, training: dict) -> None:
        try:
            self.optimizer.load_state_dict(training["optimizer"])
        except (ValueError, KeyError) as exc:
            raise CheckpointError(f"{self.out / 'last'}: its optimizer state does not fit optimizer="
                                  f"{self.config.optimizer!r} ({exc}); resume with the optimizer the run started "
                                  "with, or set resume=False") from exc
        saved = training.get("average")
        if saved is not None:   # the model loaded holds the averages; the live weights come back from here
            try:
                if self.average is not None:
                    self.average.load_state_dict(saved)
                else:   # resumed without averaging: only the live weights go on
                    WeightAverage.restore_live(self.average_tensors(), saved)
            except ValueError as exc:
                raise CheckpointError(f"{self.out / 'last'}: {exc}") from exc
        self.state.update(training["state"])
        self._lr = None  # the loaded optimizer state brought its own learning rate
        saved = training.get("rank_generators") or [training["generator"]]
        r = self.ranks.rank
        if r >= len(saved):   # more ranks than the run had: this rank draws a fresh stream
            self.generator.manual_seed(self._rank_seed(self.state["step"]))
            return
        try:
            self.generator.set_state(saved[r])
        except (RuntimeError, TypeError):  # resumed on another kind of device: a fresh sampler stream
            warnings.warn("could not restore the batch sampler's random state; reseeding it")
            self.generator.manual_seed(self._rank_seed(self.state["step"]) + self.state["step"])

    def _after_step(self, bar, log, t_start: float) -> str | None:
        """Bookkeeping after a step: the log row (``log(row)``), validation, checkpoints; a
        reason to stop or None."""
        c, st = self.config, self.state
        step = st["step"]
        lr = c.lr_at(step - 1)  # the rate the step ran at
        st["seconds"] = time.perf_counter() - t_start
        bar.update(1)
        row = None
        logs = step % c.log_every == 0 or step == c.steps
        if logs:
            if self._running_sum is not None:   # the mean over the ranks' batches
                self.ranks.all_reduce_(self._running_sum, mean=True)
            sums = self._running_sum.tolist() if self._running_sum is not None else []
            vals = {k: v / self._n_running for k, v in zip(self._running, sums)}
            if not all(math.isfinite(v) for v in vals.values()):
                raise FloatingPointError(f"training diverged at step {step}: losses {vals}")
            if self._running_sum is not None:
                self._running_sum.zero_()
            self._n_running = 0
            row = {"step": step, "seconds": round(st["seconds"], 3), "lr": lr, **vals, "valid_error": ""}
            bar.set_postfix(loss=f"{vals['loss']:.4g}", best=f"{st['best_error']:.4g}")
        timed_out = c.max_seconds is not None and st["seconds"] >= c.max_seconds
        if self.ranks.distributed:   # rank 0's clock decides, at log rows (the ranks agree on when to stop)
            timed_out = bool(self.ranks.broadcast_object(timed_out)) if logs else False
        if self.valid and (step % c.valid_every == 0 or step == c.steps or timed_out):
            with self.averaged():
                err = self._validate_on_main()
            row = row or {"step": step, "seconds": round(st["seconds"], 3), "lr": lr}
            row["valid_error"] = err
            if err < st["best_error"]:
                st.update(best_error=err, best_step=step, bad_validations=0)
                self.checkpoint("best", wait=False)
            else:
                st["bad_validations"] += 1
            bar.set_postfix(loss=row.get("loss", ""), valid=f"{err:.4g}", best=f"{st['best_error']:.4g}")
            self.emit("validate", step=step, error=err)
        if row is not None and self.ranks.main:
            log(row)
            self.emit("log", row=row)
        if step % c.checkpoint_every == 0:
            self.checkpoint("last", wait=False)
        self._checkpoints_written()
        if c.patience is not None and st["bad_validations"] >= c.patience:
            return "early stopping"
        return "time budget" if timed_out else None

    def run(self) -> dict:
        """Train until ``steps``, the time budget, early stopping or Ctrl-C; returns a summary
        (paths, steps, best error, timing)."""
        from tqdm.auto import tqdm

        c, st, out = self.config, self.state, self.out
        main = self.ranks.main   # rank 0 writes the log and shows the progress bar
        self.warmup()
        out.mkdir(parents=True, exist_ok=True)
        log_path = out / "log.csv"
        new_log = not log_path.exists() or st["step"] == 0
        if main and not new_log:  # rows past the checkpoint resumed from (a killed run's) are run again
            _trim_log(log_path, st["step"])
        start_step = st["step"]
        t_start = time.perf_counter() - st["seconds"]
        bar = tqdm(total=c.steps, initial=start_step, desc=f"train {self.description}", unit="step",
                   disable=not (c.progress and main), dynamic_ncols=True, smoothing=0.05)
        self.model.train()
        fields = self.log_fields if new_log or not main else _log_header(log_path)   # a resumed log keeps its columns
        opened = open(log_path, "w" if new_log else "a", newline="") if main else open(os.devnull, "w")
        with opened as log_file:
            writer = csv.DictWriter(log_file, fields, extrasaction="ignore")
            if new_log:
                writer.writeheader()

            def log(row):  # every row on disk as it comes
                writer.writerow(row)
                log_file.flush()
            try:
                stop = "steps"
                while st["step"] < c.steps:
                    self.step()
                    reason = self._after_step(bar, log, t_start)
                    if reason:
                        stop = reason
                        break
            except KeyboardInterrupt:  # keep what was learned; training resumes from <out>/last
                if self.ranks.distributed:   # the ranks may be at different points of a step: no last collective
                    raise
                stop = "interrupted"
            finally:
                bar.close()
        self.checkpoint("last")
        # no validation split: the last model is the best we know (rank 0's folder decides for all)
        if self.ranks.broadcast_object(not (out / "best").is_dir()):
            self.checkpoint("best")
        steps_run = st["step"] - start_step
        summary = {"out": str(out), "best": str(out / "best"), "last": str(out / "last"), "steps": st["step"],
                   "best_step": st["best_step"], "best_error": st["best_error"], "stop": stop,
                   # the run's steps and seconds over all its calls, and the steps this call added
                   "seconds": st["seconds"], "steps_per_second": st["step"] / max(st["seconds"], 1e-9),
                   "steps_this_call": steps_run,
                   "rank": self.ranks.rank, "ranks": self.ranks.world,
                   # the steps validation rolled out: the config's, cut to the shortest valid sequences
                   "valid_horizon": min([self.config.valid_horizon] + [d["valid"].num_steps for d in self.valid])
                   if self.valid else None}
        self.emit("end", summary=summary)
        return summary


def _log_header(path: Path) -> list[str]:
    """The columns of an existing log.csv (``LOG_FIELDS`` when it has no header)."""
    with open(path, newline="") as f:
        return csv.DictReader(f).fieldnames or list(LOG_FIELDS)


def _logged_steps(path: Path) -> list[int]:
    """The steps of the complete rows of a log.csv (none when it is missing)."""
    if not path.is_file():
        return []
    steps = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            try:
                if None not in row and None not in row.values():
                    steps.append(int(row["step"]))
            except (KeyError, TypeError, ValueError):
                pass
    return steps


def _trim_log(path: Path, step: int) -> None:
    """Keep the header and the complete rows up to ``step`` of a log.csv (rewritten atomically):
    a run resumed from a checkpoint at ``step`` writes the later rows again."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        fields = reader.fieldnames or LOG_FIELDS
    keep = []
    for row in rows:
        try:
            if None not in row and None not in row.values() and int(row["step"]) <= step:
                keep.append(row)
        except (KeyError, TypeError, ValueError):
            pass
    if len(keep) == len(rows):
        return
    with atomic_write(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fields)
        w.writeheader()
        w.writerows(keep)


def _move_aside(out: Path) -> Path:
    """Move a run's log.csv, last and best into a new ``out/replaced-<n>``; return that folder."""
    n = 1
    while (out / f"replaced-{n}").exists():
        n += 1
    dest = out / f"replaced-{n}"
    dest.mkdir(parents=True)
    for name in ("log.csv", "last", "best"):
        if (out / name).exists():
            os.replace(out / name, dest / name)
    return dest


def train(config: TrainConfig, datasets=None, model: ForwardModel | None = None, callbacks=()) -> dict:
    """Train (or resume) a forward model: ``Trainer(config, datasets, model, callbacks).run()``."""
    return Trainer(config, datasets, model, callbacks).run()
