"""The data loop (as PETS, MBPO and TD-MPC run it): plan with the learned model in closed loop on
the true simulator, add the visited transitions to the dataset, train on, plan again.

``run_loop(LoopConfig(task=..., out=...))`` works in a folder (``gnwarp.control.loop_store``
describes it) and resumes there. First (iteration 0) it simulates random spline episodes as
``gnwarp generate`` does (the seed data) and trains a model on them for ``initial_train_steps``.
Then each iteration i:

1. copies the training run's last checkpoint to ``models/iter-<i>`` and plans with it: N episodes
   of E steps batched on the true simulator (``run_episodes`` on ``gnwarp.sim.make_env``), from
   the task's own random initial states (``task.initial`` where the task has it) or the
   generator's (``gnwarp.data.initial_states``);
2. measures, before any training on them, the model's one-step and rollout errors on the states
   the episodes visited, beside the same errors on the data it has trained on (the paper's
   Figure H.1; ``gnwarp.eval.metrics.evaluate``);
3. writes the transitions as the shard ``data/iter-<i>.h5`` (a valid dataset: ``gnwarp check``),
   with the returns and errors in its meta["loop"];
4. trains ``train_steps`` more steps from the last checkpoint on the seed data and every shard
   (``Trainer`` resuming ``model/last``);
   with ``value`` set, fits the learned terminal value on every stored episode
   (``gnwarp.control.loop_value``: ``value/iter-<i+1>.pt``, which the next iteration's planner
   adds at its horizon);
5. appends a results record (``records.jsonl``) and writes ``state.json``.

Env steps (a record's ``env_steps``) are the control steps whose data trained the weights: the
seed data's train split and every shard, counted when they have been trained on (the seed data's
valid split, read for validation only, is not counted). A kill at any point resumes at the last
finished step: a shard written is kept (planning is not redone), training resumes from its last
checkpoint, a record written for an unfinished iteration is replaced.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from gnwarp.control.loop_store import (CONFIG_FILE, RECORDS_FILE, SEED_DATA, LoopState, LoopStateError, concat_train,
                                       episode_dataset, read_state, shard_path, subset, train_env_steps, write_json,
                                       write_state)
from gnwarp.control.loop_value import ValueSettings, check_value_discount, fit_loop_value, load_loop_value
from gnwarp.validation import (ConfigError, Count, Flag, FloatRange, PositiveFloat, PositiveInt, check_fields,
                               check_keys, described)

__all__ = ["LoopConfig", "run_loop", "LoopStateError", "RESUMABLE", "make_loop_planner", "loop_system",
           "ENSEMBLE_PLANNERS", "member_folder", "member_checkpoint"]

log = logging.getLogger("gnwarp.loop")

# what a resumed loop may change (how long it runs, where, its folder moved); every other field must match config.json
RESUMABLE = ("out", "iterations", "chunk", "budget_seconds", "progress", "device", "backend")
# the planners that plan over an ensemble of models (scoring candidates through each)
ENSEMBLE_PLANNERS = ("sampling", "mppi", "hybrid")
# TrainConfig keys the loop sets itself
_LOOP_TRAIN_KEYS = ("data", "out", "steps", "resume", "patience", "max_seconds", "progress", "device")


@dataclass
class LoopConfig:
    """A data loop. ``task``: a task name (``gnwarp.control.TASKS``). ``out``: the loop folder.
    ``system``: the system controlled (None: the task's). ``planner``: a name of
    ``gnwarp.control.PLANNERS`` planning through the learned model; ``planner_settings``: its
    settings' fields (e.g. {"iterations": 10, "horizon": 30}). ``episodes``: episodes planned
    together each iteration. ``episode_steps``: control steps an episode (None: the task's
    ``episode_steps`` where it has one, else ``seq_len``); a multiple of ``seq_len``.
    ``iterations``: iterations to finish in all (a resumed loop goes on to it). ``train_steps``:
    training steps each iteration; ``initial_train_steps``: on the seed data before the first.
    ``seed_sequences`` / ``seed_valid``: random spline sequences of the seed data's train and
    valid splits; ``seq_len``: steps of a stored sequence (the seed data's and every shard's).
    ``eval_episodes``: episodes planned with the model each iteration's training gives, their
    returns a record of their own (variant "loop-eval"), their data kept out of the dataset and
    of the env steps, every ``eval_every`` iterations and at the last. ``eval_sequences``:
    sequences the errors are measured on (new data and trained data each); ``error_horizon``: the
    rollout error's steps. ``train``: ``TrainConfig`` keys (model, batch
    size, learning rate, ...; not those the loop sets: data, out, steps, resume, patience,
    max_seconds, progress, device). ``seed``: of the seed data, initial states, targets and the
    planner. ``backend``: the true simulator. ``device``: the model's. ``chunk``: iterations at
    most in one call. ``budget_seconds``: start no iteration in this call that the last one's
    duration says would end past it, the call's first excepted (every call makes progress; the
    seed data and its training are not budgeted). Both bind one call: ``gnwarp loop`` does not
    take them from a resumed folder's config.json.
    ``value``: a learned terminal value (``gnwarp.control.loop_value.ValueSettings``; a table,
    ``{}`` its defaults) fitted after each iteration's training and added by the planner at its
    horizon; None: none (the ablation). Its gamma must equal ``planner_settings.discount``.
    ``ensemble``: models trained on the same data from different seeds (member k > 0 in
    ``model-<k>``, training seed ``train.seed + k``), the sampling planners (sampling, mppi,
    hybrid: CEM refinement) planning over all of them, candidates ranked by mean -
    ``ensemble_penalty`` x spread of their returns (``gnwarp.control.sampling.EnsembleDynamics``);
    errors are member 0's.
    """
    task: str = described("pendulum-balance", "task name (gnwarp.control.TASKS)")
    out: str = described("runs/loop", "the loop folder (resumed where it holds a loop)")
    system: str | None = described(None, "system to control (unset: the task's)")
    planner: str = described("gradient", "planner name (gnwarp.control.PLANNERS) planning through the model, "
                                          "or policy: a trained gnwarp rl agent (planner_settings.run)")
    planner_settings: dict = field(default_factory=dict)
    episodes: PositiveInt = described(16, "episodes planned together each iteration")
    episode_steps: PositiveInt | None = described(None, "control steps per episode (unset: the task's episode "
                                                        "length, else seq_len); a multiple of seq_len")
    iterations: Count = described(10, "iterations to finish in all (a resumed loop goes on to this many)")
    train_steps: PositiveInt = described(2000, "training steps each iteration")
    initial_train_steps: PositiveInt = described(10000, "training steps on the seed data before the first iteration")
    seed_sequences: PositiveInt = described(200, "random spline sequences of the seed data's train split")
    seed_valid: Count = described(20, "random spline sequences of the seed data's valid split (validation only)")
    seq_len: PositiveInt = described(100, "steps of every stored sequence (seed data and shards)")
    eval_episodes: Count = described(0, "evaluation episodes after each iteration's training (not added to the "
                                        "data, not counted as env steps; 0: none)")
    eval_every: PositiveInt = described(1, "evaluation episodes every this many iterations (and at the last)")
    eval_sequences: PositiveInt = described(32, "sequences the one-step and rollout errors are measured on")
    error_horizon: PositiveInt = described(20, "steps of the rollout error")
    train: dict = field(default_factory=dict)
    seed: Count = described(0, "seed of the seed data, initial states, targets and planner")
    backend: Literal["auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu"] = described(
        "auto", "true simulator (auto: MuJoCo-Warp on a GPU, else MuJoCo C)")
    device: Literal["auto", "cpu", "cuda"] = described("auto", "the model's device")
    chunk: PositiveInt | None = described(None, "iterations at most in this call (unset: up to iterations)")
    budget_seconds: PositiveFloat | None = described(None, "stop before an iteration expected to end past this many "
                                                           "seconds of this call (its first always starts)")
    progress: Flag = described(True, "progress bars")
    ensemble: PositiveInt = described(1, "models trained on the same data from different seeds, planned over "
                                         "together (sampling, mppi, hybrid; 1: one model)")
    ensemble_penalty: FloatRange(ge=0) = described(1.0, "ensemble candidates ranked by mean - this x spread of "
                                                        "their returns over the models")
    value: ValueSettings | None = described(None, "learned terminal value settings (a table; {}: defaults; unset: "
                                                  "no value)")

    def __post_init__(self):
        check_fields(self)
        for name in ("planner_settings", "train"):
            if not all(isinstance(k, str) for k in getattr(self, name)):
                raise ConfigError(name, "must be a table with string keys")
        given = sorted(set(self.train) & set(_LOOP_TRAIN_KEYS))
        if given:
            raise ConfigError(f"train.{given[0]}", f"is set by the loop itself (it sets {', '.join(_LOOP_TRAIN_KEYS)})")
        if self.episode_steps is not None and self.episode_steps % self.seq_len:
            raise ConfigError("episode_steps", f"must be a multiple of seq_len ({self.seq_len}): episodes are stored "
                                               f"as sequences of seq_len steps, got {self.episode_steps}")
        from gnwarp.control.planner import get_planner
        try:
            entry = get_planner(self.planner)
        except ValueError as e:
            raise ConfigError("planner", str(e)) from None
        if self.planner == "ilqg":
            raise ConfigError("planner", "ilqg plans on the true simulator, not through the learned model; choose "
                                         "another planner")
        try:
            settings = entry.make_settings(**{k: v for k, v in self.planner_settings.items()})
        except ConfigError as e:
            raise e.within("planner_settings") from None
        except TypeError as e:
            raise ConfigError("planner_settings", f"{e}") from None
        if self.value is not None:
            check_value_discount(self.value, self.planner, settings)
        if self.ensemble > 1 and self.planner not in ENSEMBLE_PLANNERS:
            raise ConfigError("ensemble", f"planner {self.planner!r} plans through one model; an ensemble plans "
                                          f"with {', '.join(ENSEMBLE_PLANNERS)}")
        self.train_config(1)   # refused here, not after the seed data is simulated

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "LoopConfig":
        return cls(**check_keys(cls, d, "data-loop config keys"))

    def train_config(self, steps: int, member: int = 0):
        """The ``TrainConfig`` training ensemble ``member`` to ``steps`` total steps in
        ``<out>/model`` (member k > 0: ``<out>/model-<k>``, seed ``train.seed + k``)."""
        from gnwarp.train.config import TrainConfig
        extra = {} if member == 0 else {"seed": int(self.train.get("seed", 0)) + int(member)}
        try:
            return TrainConfig.from_dict({**self.train, **extra, "out": str(Path(self.out) / member_folder(member)),
                                          "steps": int(steps),
                                          "resume": True, "patience": None, "max_seconds": None,
                                          "progress": self.progress, "device": self.device})
        except ConfigError as e:
            raise e.within("train") from None

    def episode_length(self, task) -> int:
        """Control steps per episode: ``episode_steps``, else the task's, else ``seq_len``."""
        steps = self.episode_steps or getattr(task, "episode_steps", None) or self.seq_len
        if steps % self.seq_len:
            raise ConfigError("episode_steps", f"the task's episodes of {steps} steps are no multiple of seq_len "
                                               f"({self.seq_len}); set episode_steps or seq_len")
        return int(steps)


def member_folder(member: int) -> str:
    """The training run of ensemble ``member``, relative to the loop folder."""
    return "model" if member == 0 else f"model-{member}"


def member_checkpoint(out, j: int, member: int) -> Path:
    """The checkpoint ensemble ``member`` plans with at iteration ``j``."""
    return Path(out) / "models" / (f"iter-{j:04d}" if member == 0 else f"iter-{j:04d}-m{member}")


def loop_system(cfg: LoopConfig, task):
    """The ``System`` the loop controls: ``cfg.system``, else the task's (a family: its fixed system)."""
    from gnwarp.sim.systems import make
    s = make(cfg.system or task.system)
    task.check_system(s.name)
    return s


def _check_folder_config(out: Path, cfg: LoopConfig) -> None:
    """Write ``config.json`` in a new loop folder; in one that holds a loop, refuse a config that
    differs from it in a field other than ``RESUMABLE``."""
    path = out / CONFIG_FILE
    mine = json.loads(json.dumps(cfg.to_dict()))
    if path.exists():
        try:
            saved = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise LoopStateError(f"{path} is not valid JSON ({e}); restore it or choose another out") from None
        # a key the folder's config lacks (written before the key existed) holds its default
        defaults = json.loads(json.dumps(LoopConfig(task=cfg.task).to_dict()))
        saved = {**defaults, **saved}
        diff = [k for k in sorted(set(mine) | set(saved)) if k not in RESUMABLE and mine.get(k) != saved.get(k)]
        if diff:
            shown = "; ".join(f"{k}: {saved.get(k)!r} in the folder, {mine.get(k)!r} asked" for k in diff[:4])
            raise ConfigError(diff[0], f"{out} holds a loop of another config ({shown}); a resumed loop may change "
                                       f"only {', '.join(RESUMABLE)}. Choose another out")
    write_json(path, mine)


def make_loop_planner(cfg: LoopConfig, model, task, system, n: int, targets, env, seed: int = 0, terminal=None):
    """The planner ``cfg.planner`` through ``model`` (a learned model, or a list of them: an
    ensemble, ``gnwarp.control.sampling.ensemble_dynamics``) for ``n`` episodes, ``seed`` added to
    its settings' seed: ``gnwarp.control.planner.make_planner`` with ``cfg.planner_settings``,
    the sampling planners drawing in ``env.ctrlrange``; ``terminal``: the value at its horizon."""
    from gnwarp.control.planner import get_planner, make_planner, planner_settings
    entry = get_planner(cfg.planner)
    fields = dict(cfg.planner_settings)
    if "seed" in {f.name for f in dataclasses.fields(entry.settings)}:
        fields["seed"] = int(fields.get("seed", 0)) + int(seed)
    if isinstance(model, (list, tuple)):
        from gnwarp.control.sampling import ensemble_dynamics
        from gnwarp.control.tasks import get_task
        settings = planner_settings(cfg.planner, fields)
        horizon = settings.horizon or get_task(task, system.name).horizon
        model = ensemble_dynamics([m.bind(system) for m in model], n, settings.samples, horizon, cfg.ensemble_penalty)
    return make_planner(cfg.planner, model, task, system, n, fields, targets, terminal=terminal,
                        ctrlrange=env.ctrlrange)


def _errors(model, ds, split: str, n: int, horizon: int, rng) -> dict:
    """The model's one-step and ``horizon``-step rollout errors (normalized, ``evaluate``'s
    "mean") on up to ``n`` random sequences of ``ds``'s ``split``."""
    from gnwarp.eval.metrics import evaluate
    S = len(ds[split])
    idx = np.arange(S) if S <= n else rng.choice(S, n, replace=False)
    h = min(int(horizon), ds[split].num_steps)
    r = evaluate(model, subset(ds, split, idx), "test", None, (h,))
    roll = r[f"rollout_{h}"]
    return {"one_step": r["one_step"]["mean"], "rollout": roll["mean"], "rollout_steps": h,
            "sequences": int(len(idx)), "finite": bool(r["finite"])}


def _episodes(cfg: LoopConfig, rk, task, system, model_path: Path, n: int, steps: int, key: list, bar) -> tuple:
    """``n`` episodes of ``steps`` steps planned through the checkpoint ``model_path`` on the
    true simulator, their initial states, targets and planner seeded by ``key``, the planner
    adding the loop's value of the same iteration (``value/<model_path's name>.pt``) where it has
    one. Every rank (``rk``) draws every initial state and target; each plans and runs its share
    of the episodes (``Ranks.map_sharded``), gathered on rank 0. Returns, on rank 0, ({"states"
    [n, steps+1, B, 13], "actions" [n, steps, U], "returns" [n]} as numpy, qpos [n, steps+1, nq],
    qvel [n, steps+1, nv], meta: returns, initial states, targets, seconds, backend, model, value;
    the model); on the other ranks (None, None, None, None, the model)."""
    import torch

    from gnwarp.control.tasks import sample_targets
    from gnwarp.data.generation import initial_states
    from gnwarp.train.checkpoint import load_model
    rng = np.random.default_rng([cfg.seed, *key])
    init = getattr(task, "initial", None)
    qpos0, qvel0 = init(system, n, rng) if init is not None else initial_states(system, n, rng)
    stream = int(np.random.default_rng([cfg.seed, *key]).integers(1 << 31))   # targets' and planner's seeds
    targets = sample_targets(task, system, n, seed=stream)
    device = rk.device if rk.distributed else (None if cfg.device == "auto" else cfg.device)
    model = load_model(model_path, device=device)
    j = int(model_path.name.split("-")[-1])
    members = [model] + [load_model(member_checkpoint(model_path.parent.parent, j, k), device=device)
                         for k in range(1, cfg.ensemble)]
    value = load_loop_value(cfg, model_path.parent.parent, j, device=model.device)

    def plan(idx: list) -> list:
        """This rank's episodes ``idx`` (of the n), planned together: (states, actions, qpos, qvel, return,
        simulator backend) each."""
        from gnwarp.control.episodes import run_episodes
        from gnwarp.sim.env import make_env
        m = len(idx)
        pick = (lambda a: a) if m == n else (lambda a: None if a is None else a[np.asarray(idx)])
        tgt = targets if targets is None or m == n else targets[torch.as_tensor(idx)]
        env = make_env(system, m, backend=cfg.backend)
        planner = make_loop_planner(cfg, members if cfg.ensemble > 1 else model, task, system, m, tgt, env,
                                    stream + rk.rank * 1_000_003, terminal=value)   # each rank its own draws
        x0 = env.reset(pick(qpos0), pick(qvel0))
        qs, vs = [np.asarray(env.qpos.cpu(), np.float32)], [np.asarray(env.qvel.cpu(), np.float32)]

        def progress(t):   # every state's qpos / qvel, for the dataset
            qs.append(np.asarray(env.qpos.cpu(), np.float32))
            vs.append(np.asarray(env.qvel.cpu(), np.float32))
            bar.update(1)
        out = run_episodes(planner, env, task, steps, x0, target=tgt, progress=progress)
        env.close()
        qs, vs = np.stack(qs, 1), np.stack(vs, 1)
        x, u = out["states"].cpu().numpy(), out["actions"].cpu().numpy()
        r = out["returns"].double().cpu().numpy()
        return [(x[e], u[e], qs[e], vs[e], float(r[e]), env.backend) for e in range(m)]

    t0 = time.perf_counter()
    # one process plans the n episodes together; on several ranks each its share, gathered on rank 0
    done = rk.map_sharded(range(n), plan, batched=True, what="loop episodes")
    if not rk.main:
        return None, None, None, None, model
    states, actions, qpos, qvel = (np.stack([e[k] for e in done]) for k in range(4))
    returns = [e[4] for e in done]
    meta = {"returns": returns, "episode_steps": steps,
            "plan_seconds": time.perf_counter() - t0, "initial_qpos": np.asarray(qpos0, np.float64).tolist(),
            "initial_qvel": np.asarray(qvel0, np.float64).tolist(),
            "targets": None if targets is None else torch.as_tensor(targets).double().tolist(),
            "backend": done[0][5], "model": f"models/{model_path.name}"}
    if value is not None:
        meta["value"] = f"value/{model_path.name}.pt"
    return {"states": states, "actions": actions, "returns": np.asarray(returns)}, qpos, qvel, meta, model


def _collect(cfg: LoopConfig, rk, task, system, model_path: Path, trained, iteration: int, steps: int, bar):
    """Plan ``cfg.episodes`` episodes of ``steps`` steps with the checkpoint ``model_path`` on
    the true simulator (on every rank, each its share); on rank 0, measure the model's errors on
    them and on ``trained`` (the training data) and write them as the shard
    ``shard_path(iteration)``. Returns, on every rank, the shard ``Dataset`` (its
    meta["loop"]: returns, errors, initial states, targets, seconds; the other ranks read it
    from the file rank 0 wrote)."""
    from gnwarp.data.dataset import load
    out, qpos, qvel, meta, model = _episodes(cfg, rk, task, system, model_path, cfg.episodes, steps, [iteration],
                                             bar)
    path = Path(cfg.out) / shard_path(iteration)
    made = []

    def write():
        loop_meta = {"iteration": iteration, "planner": cfg.planner, **meta}
        shard = episode_dataset(trained, out["states"], out["actions"], qpos, qvel, cfg.seq_len, loop_meta)
        t1 = time.perf_counter()
        ev_rng = np.random.default_rng([cfg.seed, iteration, 1])
        loop_meta["errors"] = {"new": _errors(model, shard, "train", cfg.eval_sequences, cfg.error_horizon, ev_rng),
                               "trained": _errors(model, trained, "train", cfg.eval_sequences, cfg.error_horizon,
                                                  ev_rng)}
        loop_meta["eval_seconds"] = time.perf_counter() - t1
        shard.save(path)
        made.append(shard)
    rk.on_main(f"writing {path}", write)
    return made[0] if made else load(path, lazy=False)


def _train(cfg: LoopConfig, data, steps: int) -> dict:
    """Train every ensemble member (resuming its ``last``) on ``data`` until ``steps`` total
    steps; returns member 0's result."""
    import gc

    from gnwarp.train.trainer import Trainer
    results = []
    for k in range(cfg.ensemble):
        trainer = Trainer(cfg.train_config(steps, k), datasets=[data])
        results.append(trainer.run())
        del trainer   # its device copy of the data and its captured graphs go before the next's
        gc.collect()
    return results[0]


def _copy_members(cfg: LoopConfig, out: Path, j: int, keep: bool = False) -> None:
    """Copy every member's last checkpoint to what iteration ``j`` plans with (``keep``: not
    over a copy already there)."""
    for k in range(cfg.ensemble):
        dst = member_checkpoint(out, j, k)
        if not (keep and dst.exists()):
            _copy_checkpoint(out / member_folder(k) / "last", dst)


def _copy_checkpoint(src: Path, dst: Path) -> None:
    """Copy a checkpoint folder, atomically (a kill leaves the old one or none)."""
    from gnwarp.files import atomic_write
    dst.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(dst, folder=True) as tmp:
        for f in sorted(src.iterdir()):
            shutil.copy2(f, tmp / f.name)


def _seed_data(cfg: LoopConfig, system, out: Path):
    """The seed data: ``data/seed.h5`` when a killed call wrote it, else simulated here (random
    spline controls, as ``gnwarp generate``) and written."""
    from gnwarp.data.dataset import load
    from gnwarp.data.generation import generate
    path = out / SEED_DATA
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        ds = generate(system, {"train": cfg.seed_sequences, "valid": cfg.seed_valid, "test": 0}, num_steps=cfg.seq_len,
                      seed=cfg.seed, backend=cfg.backend, progress=cfg.progress)
        ds.save(path)
    ds = load(path, lazy=False)
    if ds["train"].num_steps != cfg.seq_len or len(ds["train"]) != cfg.seed_sequences:
        raise LoopStateError(f"{path} holds {len(ds['train'])} x {ds['train'].num_steps} steps, the config asks for "
                             f"{cfg.seed_sequences} x {cfg.seq_len}")
    return ds


def _trim_records(path: Path, iterations: int | None) -> None:
    """Drop the records of iterations past ``iterations`` (written before a kill that left the
    state behind them). ``iterations`` None: the folder has no loop state; records past iteration
    0 there (the state was lost) and records of another experiment are refused, not dropped."""
    from gnwarp.eval.records import read_records, write_records
    if not path.exists():
        return
    recs = read_records(path)
    foreign = [r for r in recs if r.experiment != "loop"]
    if foreign:
        raise ValueError(f"{path} holds records of experiment {foreign[0].experiment!r}, not of a data loop: "
                         "run the loop in another folder")
    if iterations is None and any(int(r.metrics.get("iteration", 0)) > 0 for r in recs):
        raise ValueError(f"{path} holds records of iterations past 0 but the folder has no loop state "
                         f"(its state.json is gone): starting over would drop them. Run the loop in "
                         "another folder, or move the records away to start this one over")
    keep = [r for r in recs if int(r.metrics.get("iteration", 0)) <= (iterations or 0)]
    if len(keep) != len(recs):
        write_records(path, keep, append=False)


def _record(cfg: LoopConfig, task, system, m: dict, state: LoopState, model_env_steps: int, seconds: dict,
            variant: str = "loop", fitted: dict | None = None):
    """The results record of an iteration's episodes (``m``: their meta: returns, initial states,
    ...; "loop": the data episodes, "loop-eval": the evaluation episodes; ``fitted``: the value
    fit after the iteration's training, ``fit_loop_value``'s metrics)."""
    from gnwarp.eval.records import ResultRecord, git_commit, gpu_name
    returns = m["returns"]
    metrics = {"iteration": m["iteration"], "mean_return": float(np.mean(returns)), "errors": m.get("errors"),
               "model_env_steps": model_env_steps, "train_steps": state.train_steps, **seconds}
    if m.get("errors") is None:
        del metrics["errors"]
    if fitted is not None:
        metrics["value"] = fitted
    config = {"protocol": "loop", "planner_settings": cfg.planner_settings, "model": m["model"],
              "backend": m["backend"], "initial_qpos": m["initial_qpos"], "initial_qvel": m["initial_qvel"],
              "targets": m["targets"],
              "loop": {k: v for k, v in cfg.to_dict().items() if k != "planner_settings"}}
    if m.get("value") is not None:
        config["value"] = m["value"]   # the value file the episodes planned with
    return ResultRecord(experiment="loop", task=task.name, system=system.name, planner=cfg.planner, dynamics="learned",
                        variant=variant, seed=cfg.seed, episodes=len(returns), episode_steps=int(m["episode_steps"]),
                        returns=returns, control_dt=float(system.dt), action_repeat=int(system.substeps),
                        env_steps=state.env_steps, metrics=metrics, config=config, commit=git_commit(),
                        gpu=gpu_name(), date=time.strftime("%Y-%m-%d %H:%M:%S"))


def run_loop(config: LoopConfig) -> dict:
    """Run (or resume) the data loop in ``config.out`` until ``config.iterations`` iterations are
    finished or the time budget is spent. Returns {"iterations": finished, "env_steps",
    "train_steps", "records": path, "stop": "iterations" | "chunk" | "budget", "seconds": this call's}.

    Under ``torchrun`` every rank runs it together (``gnwarp.distributed``): rank 0 alone writes
    the folder (config, seed data, checkpoint copies, shards, values, records, state), the others
    reading what it wrote; each rank plans its share of the episodes, gathered on rank 0; the
    ranks train together (``Trainer``); rank 0's clock and state decide when to stop."""
    from tqdm.auto import tqdm

    from gnwarp.control.tasks import get_task
    from gnwarp.data.dataset import load
    from gnwarp.distributed import ranks
    from gnwarp.eval.records import write_records
    from gnwarp.control.planner import check_plan_memory, planner_settings
    from gnwarp.files import check_output_path
    from gnwarp.interop import resolve_device
    cfg = config
    t_call = time.perf_counter()
    out = check_output_path(cfg.out, folder=True)
    task = get_task(cfg.task)
    system = loop_system(cfg, task)
    steps = cfg.episode_length(task)
    settings = planner_settings(cfg.planner, cfg.planner_settings)
    gamma = None if cfg.value is None else check_value_discount(cfg.value, cfg.planner, settings)
    rk = ranks(cfg.device)   # rank 0 of 1 unless started by torchrun
    # before the folder is written (a corrected rerun is then taken); every rank checks its share on
    # its device, and one rank's refusal stops them all
    refused = None
    try:
        for n in {cfg.episodes, cfg.eval_episodes} - {0}:
            check_plan_memory(cfg.planner, settings, len(rk.shard(n)), task, system,
                              rk.device if rk.distributed else resolve_device(cfg.device), models=cfg.ensemble,
                              hint="Use a shorter planner_settings.horizon (or fewer samples or episodes)")
    except ValueError as e:
        refused = str(e)
    every = rk.gather_objects(refused)
    refused = rk.broadcast_object(next((r for r in every if r), None) if rk.main else None)
    if refused:
        raise ValueError(refused)
    records = out / RECORDS_FILE

    def prepare():   # rank 0: the folder checked, its records trimmed, the seed data there
        out.mkdir(parents=True, exist_ok=True)
        _check_folder_config(out, cfg)
        st = read_state(out)
        _trim_records(records, st.iteration if st is not None else None)
        _seed_data(cfg, system, out)
        return st
    state = rk.on_main(f"preparing {out}", prepare)
    seed = load(out / SEED_DATA, lazy=False)
    if state is None:   # iteration 0: the model trained on the seed data
        log.info("training on the seed data: %d sequences x %d steps", len(seed["train"]), cfg.seq_len)
        r = _train(cfg, concat_train(seed, []), cfg.initial_train_steps)
        state = LoopState(iteration=0, env_steps=train_env_steps(seed), train_steps=int(r["steps"]),
                          seconds=time.perf_counter() - t_call)
        state = rk.on_main("writing the loop state", lambda: write_state(out, state) or state)
    shards = [load(out / s, lazy=False) for s in state.shards]
    counted = train_env_steps(seed) + sum(train_env_steps(s) for s in shards)
    if counted != state.env_steps:
        raise LoopStateError(f"{out / 'state.json'} counts {state.env_steps} env steps, its data files hold {counted}; "
                             "restore the state file or the data files")
    bars = cfg.progress and rk.main
    bar = tqdm(total=cfg.iterations, initial=min(state.iteration, cfg.iterations), desc=f"loop {task.name}",
               unit="it", disable=not bars, dynamic_ncols=True, position=0)
    stop, first = "iterations", state.iteration
    while state.iteration < cfg.iterations:
        spent = time.perf_counter() - t_call
        why = None
        if cfg.chunk is not None and state.iteration - first >= cfg.chunk:
            why = "chunk"
        elif (cfg.budget_seconds is not None and state.iteration > first
              and spent + (state.last_seconds or 0.0) > cfg.budget_seconds):
            why = "budget"   # (a call's first iteration always starts: every call makes progress)
        why = rk.broadcast_object(why)   # rank 0's clock decides: every rank leaves together
        if why is not None:
            stop = why
            break
        t0 = time.perf_counter()
        i = state.iteration + 1
        trained = concat_train(seed, shards)
        path = out / shard_path(i)
        if rk.broadcast_object(path.exists()):   # planned before a kill: kept, not planned again
            shard = load(path, lazy=False)
        else:
            plan_model = member_checkpoint(out, i, 0)
            rk.on_main(f"copying the models iteration {i} plans with", lambda: _copy_members(cfg, out, i, keep=True))
            ebar = tqdm(total=steps, desc=f"episodes {i}", unit="step", disable=not bars, leave=False,
                        dynamic_ncols=True, position=1)
            shard = _collect(cfg, rk, task, system, plan_model, trained, i, steps, ebar)
            ebar.close()
        # the times the shard's planning took (kept in its meta: the same after a kill)
        plan_s, eval_s = (shard.meta.get("loop", {}).get(k) for k in ("plan_seconds", "eval_seconds"))
        t1 = time.perf_counter()
        model_env_steps = state.env_steps
        r = _train(cfg, concat_train(seed, shards + [shard]), state.train_steps + cfg.train_steps)
        shards.append(shard)
        seconds = {"plan_seconds": plan_s, "eval_seconds": eval_s, "train_seconds": time.perf_counter() - t1}
        # the model the next iteration plans with, and the evaluation episodes' (after a kill, the same weights)
        next_model = member_checkpoint(out, i + 1, 0)

        def after_training():   # rank 0: the next models copied, the value fitted on every episode
            _copy_members(cfg, out, i + 1)
            if cfg.value is None:
                return None
            # from value/iter-<i> (not a file a killed call wrote): each episode fitted once
            return fit_loop_value(cfg, task, system, out, shards, i + 1, gamma)
        fitted = rk.on_main(f"copying the models of iteration {i + 1}", after_training)
        if fitted is not None:
            seconds["value_seconds"] = fitted.pop("seconds")
        evaluation = None
        if cfg.eval_episodes and (i % cfg.eval_every == 0 or i == cfg.iterations):
            t2 = time.perf_counter()
            ebar = tqdm(total=steps, desc=f"evaluation {i}", unit="step", disable=not bars, leave=False,
                        dynamic_ncols=True, position=1)
            evaluation = _episodes(cfg, rk, task, system, next_model, cfg.eval_episodes, steps, [i, 2], ebar)[3]
            ebar.close()
            seconds["evaluation_seconds"] = time.perf_counter() - t2
        seconds["iteration_seconds"] = time.perf_counter() - t0
        new = LoopState(iteration=i, env_steps=state.env_steps + train_env_steps(shard), train_steps=int(r["steps"]),
                        shards=state.shards + [shard_path(i).as_posix()],
                        seconds=state.seconds + seconds["iteration_seconds"], last_seconds=seconds["iteration_seconds"])

        def finish():   # rank 0: the records, then the state (a record past the state is dropped on resume)
            rec = _record(cfg, task, system, shard.meta["loop"], new, model_env_steps, seconds, fitted=fitted)
            recs = [rec] + ([_record(cfg, task, system, {**evaluation, "iteration": i}, new, new.env_steps, seconds,
                                     "loop-eval")] if evaluation is not None else [])
            write_records(records, recs)
            write_state(out, new)
            return new, rec.metrics
        state, metrics = rk.on_main(f"writing the records of iteration {i}", finish)
        bar.update(1)
        bar.set_postfix(ret=f"{metrics['mean_return']:.4g}", env_steps=state.env_steps)
        if rk.main:
            log.info("iteration %d: mean return %.4g, env steps %d, errors on new data %.3g (one-step) %.3g "
                     "(rollout)", i, metrics["mean_return"], state.env_steps, metrics["errors"]["new"]["one_step"],
                     metrics["errors"]["new"]["rollout"])
    bar.close()
    return {"iterations": state.iteration, "env_steps": state.env_steps, "train_steps": state.train_steps,
            "records": str(records), "stop": stop, "seconds": time.perf_counter() - t_call, "out": str(out),
            "ranks": rk.world}
