"""A reinforcement-learning run (``run_rl``): an agent trained off-policy in a Gymnasium vector
env of the true simulator, evaluated with its deterministic policy in a separate batched env,
resumable across calls.

    >>> r = run_rl(RLConfig(task="swimmer6", agent="svg1", out="runs/rl/svg1-s0", budget_seconds=540))
    >>> r["stop"], r["env_steps"]          # "budget": call again (same folder) to go on

Training goes in rounds: all ``num_envs`` envs start an episode together from initial states of
a seed fixed by (seed, round) and run it to its time limit. A call stops only between rounds,
so the envs (whose simulator state is not saved) restart exactly as an uninterrupted run would
go on, and a resumed run equals an uninterrupted one bit for bit on the CPU.

The folder holds ``config.json``, ``checkpoint.pt`` (agent, replay buffer, loop state, counters,
random generators; written after each evaluation and at the end of a call), ``progress.csv`` (a
row per round), ``records.jsonl`` (a ``ResultRecord`` per evaluation: experiment "rl", planner
"policy"), ``tb/`` (TensorBoard, where it imports), ``video.gif`` and ``timing.json`` (the last
checkpoint's and video's times: what ``budget_seconds`` keeps for a call's end).
"""
from __future__ import annotations

import contextlib
import json
import math
import random
import warnings
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from gnwarp.eval.records import ResultRecord, git_commit, gpu_name, write_records
from gnwarp.files import atomic_write
from gnwarp.rl.agents import restore_generator
from gnwarp.rl.config import CONFIG_FILE, RLConfig
from gnwarp.rl.loop import CollectorState, run_env_steps
from gnwarp.rl.replay import ReplayBuffer
from gnwarp.rl.run_folder import prepare_folder, run_backend
from gnwarp.rl.run_log import (AGENT_FILE, CHECKPOINT, RECORDS_FILE, TIMING_FILE, RunLog, cut_records,
                               load_checkpoint, save_checkpoint)
from gnwarp.validation import ConfigError

__all__ = ["run_rl", "build_run", "build_agent", "compile_backend", "training_env", "load_agent", "export_agent", "agent_file", "evaluate_policy", "round_seed", "eval_reset_seed", "evaluation_env", "evaluation_states",
           "check_task", "observation_of", "normalize_model", "AGENT_FILE", "frozen_policy_warning", "FrozenPolicyWarning"]


_PIECE = 50   # vector steps between progress-bar updates
VIDEO_FILE = "video.gif"
# what the budget keeps for the call's video until a call of the run has timed one (swimmer6's
# default video, 2 x 300 steps, took 25-30 s on one CPU core; the budget then uses the time measured)
VIDEO_SECONDS_GUESS = 30.0


def _read_timing(out: Path) -> dict:
    """The run folder's timing estimates {"checkpoint_seconds", "video_seconds_per_step"} (each
    a finite number >= 0) and "video_failed" (true where the last video could not be written);
    {} where the file is missing or any estimate is not such a number (an estimate only: the
    budget then guesses)."""
    try:
        d = json.loads((out / TIMING_FILE).read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(d, dict):
        return {}
    est = {k: d[k] for k in ("checkpoint_seconds", "video_seconds_per_step") if k in d}
    ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
             for v in est.values())
    return ({k: float(v) for k, v in est.items()} | ({"video_failed": True} if d.get("video_failed") is True else {})
            if ok else {})


def round_seed(seed: int, k: int, evaluation: bool = False) -> int:
    """The reset seed of training round ``k`` (or of every evaluation): env i gets it + i."""
    return int(np.random.SeedSequence([int(seed), 2 if evaluation else 1, int(k)]).generate_state(1)[0])


def eval_reset_seed(cfg: RLConfig) -> int:
    """The reset seed of every evaluation of the run ``cfg`` (``round_seed``'s evaluation seed of
    ``cfg.eval_seed``, else of the run's own seed)."""
    return round_seed(cfg.seed if cfg.eval_seed is None else cfg.eval_seed, 0, True)


def _device(name: str) -> torch.device:
    from gnwarp.interop import resolve_device
    try:
        return resolve_device(name)
    except ValueError as e:
        raise ConfigError("device", str(e)) from None


def check_task(cfg: RLConfig):
    """The task of ``cfg`` (``gnwarp.control.tasks.Task``), after checking that it has what the
    run needs: the suite's observation (observation "dmc") and, for svg<N> N >= 1, an
    ``ObservationReward``. ``ConfigError`` naming the key otherwise."""
    from gnwarp.control.tasks import get_task
    try:
        task = get_task(cfg.task)
    except (KeyError, ValueError) as e:
        raise ConfigError("task", str(e).strip("'\"")) from None
    if cfg.observation == "dmc":
        from gnwarp.rl.observations import observation_domain
        try:
            observation_domain(task.name)
        except ValueError as e:
            raise ConfigError("observation", f"task {task.name!r} has no DMC observation ({e}); "
                                             "use observation bodies (mlp networks, ddpg or svg0)") from None
    if cfg.horizon >= 1:
        from gnwarp.rl.obs_reward import ObservationReward
        try:
            ObservationReward(task.name)
        except ValueError as e:
            raise ConfigError("agent", f"{cfg.agent} needs the reward of predicted observations, which task "
                                       f"{task.name!r} lacks ({e}); use svg0 or ddpg") from None
    return task


def observation_of(cfg: RLConfig, task):
    """The observation the run's agent acts on: "bodies" or the task's ``DMCObservation``."""
    if cfg.observation == "dmc":
        from gnwarp.rl.observations import DMCObservation
        return DMCObservation(task.name)
    return "bodies"


def build_agent(cfg: RLConfig, task, obs_fn, obs_dim: int, action_low, action_high, device):
    """The run's agent (networks initialized from ``cfg.seed``; SVG(N)'s model and reward of
    predicted observations) for observations of ``obs_dim`` and the action box [low, high] [U]."""
    from gnwarp.rl.agents import make_agent
    settings = cfg.agent_config()
    D, U = int(obs_dim), len(action_low)
    torch.manual_seed(cfg.seed)
    nets, model, reward_fn = {}, None, None
    gaussian = settings.kind == "svg"
    if cfg.networks == "gn":
        from gnwarp.rl.gn_nets import GNObservationModel, make_networks
        from gnwarp.rl.obs_graph import ObservationGraph
        og = ObservationGraph(obs_fn)
        std = dict(init_std=settings.init_std) if gaussian else {}
        policy, q = make_networks("gn", og, gaussian=gaussian, hidden=cfg.hidden or (64,), latent=cfg.latent,
                                  blocks=cfg.blocks, impl=cfg.gn_impl, **std)
        nets = dict(policy=policy, q=q)
        if cfg.horizon >= 1:
            model = GNObservationModel(og, cfg.latent, cfg.model_hidden or (64,), cfg.blocks, impl=cfg.gn_impl)
    elif cfg.horizon >= 1:
        from gnwarp.rl.networks import ObservationModel
        model = ObservationModel(D, U, cfg.model_hidden or settings.hidden)
    if cfg.horizon >= 1:
        from gnwarp.rl.obs_reward import ObservationReward
        reward_fn = ObservationReward(task.name)
        model = model.to(device)

    def reward(obs, action, next_obs):   # in the agent's dtype whatever the reward computes in
        return reward_fn(obs, action, next_obs).to(obs.dtype)
    agent = make_agent(settings, D, action_low, action_high, model=model,
                       reward=reward if reward_fn is not None else None, device=device, **nets)
    backend = compile_backend(cfg, device)
    if backend != "none":
        agent.compile_update(backend, fallback=cfg.torch_compile == "auto")
    return agent, model


def compile_backend(cfg: RLConfig, device) -> str:
    """The ``torch.compile`` backend of the run's update: ``cfg.torch_compile``, where "auto" is
    "inductor" for MLP networks on CUDA with Triton importable (1.3x the training rate of SVG(1)
    on swimmer6, H200, eighth sweep) and "none" elsewhere (the CPU, GN networks)."""
    if cfg.torch_compile != "auto":
        return cfg.torch_compile
    if torch.device(device).type != "cuda" or cfg.networks != "mlp":
        return "none"
    try:
        from torch.utils._triton import has_triton
    except ImportError:
        return "none"
    return "inductor" if has_triton() else "none"


def _env_kw(cfg: RLConfig, obs_fn, threads: int | None = None) -> dict:
    """``make_vector_env``'s settings of the run's envs (``threads``: MuJoCo C's, default the run's)."""
    kw = dict(backend=run_backend(cfg), episode_steps=cfg.episode_steps, output="torch", observation=obs_fn)
    threads = threads if threads is not None else cfg.sim_threads
    if threads is not None and run_backend(cfg) == "mujoco":
        kw["nthread"] = threads
    return kw


def training_env(cfg: RLConfig, threads: int | None = None, task=None, obs_fn=None, seed: int | None = None):
    """The run's training env ("same_step" autoreset, ``num_envs`` envs; ``threads``: MuJoCo C's,
    default the run's; the task and observation: the run's, unless given; ``seed``: its
    generators' before the first seeded reset), seeded at each round's reset: what ``run_rl``
    trains in and a slim copy's rebuild steps (``gnwarp.rl.slim.rebuild_buffer``; a module-level
    function of a config, so that worker processes can make their own)."""
    from gnwarp.control.vector_env import make_vector_env
    task = task if task is not None else check_task(cfg)
    obs_fn = obs_fn if obs_fn is not None else observation_of(cfg, task)
    return make_vector_env(task, cfg.num_envs, autoreset_mode="same_step", seed=seed, **_env_kw(cfg, obs_fn, threads))


def evaluation_env(cfg: RLConfig, task=None, obs_fn=None):
    """The run's evaluation env: ``eval_episodes`` envs whose first states are those of
    ``eval_reset_seed(cfg)`` (the task and observation: the run's, unless given)."""
    from gnwarp.control.vector_env import make_vector_env
    task = task if task is not None else check_task(cfg)
    obs_fn = obs_fn if obs_fn is not None else observation_of(cfg, task)
    return make_vector_env(task, cfg.eval_episodes, seed=eval_reset_seed(cfg), **_env_kw(cfg, obs_fn))


def evaluation_states(env) -> dict:
    """{"initial_qpos" [N][nq], "targets" [N][3] or None} of a freshly reset evaluation env: what
    each episode of an evaluation starts from (4 decimals), for the run's first record (a target's
    distance decides most of a swimmer6 return: ``bench/rl_targets.py``)."""
    def listed(x):
        x = x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)
        return np.round(x.astype(np.float64), 4).tolist()
    return dict(initial_qpos=listed(env.observe().qpos), targets=None if env.targets is None else listed(env.targets))


def build_run(cfg: RLConfig) -> dict:
    """The run's parts: {"task", "env" (training, same_step autoreset), "eval_env", "agent",
    "buffer", "generator" (the replay's sampling), "device"}; networks initialized from
    ``cfg.seed``."""
    task = check_task(cfg)
    device = _device(cfg.device)
    obs_fn = observation_of(cfg, task)
    env = training_env(cfg, task=task, obs_fn=obs_fn, seed=round_seed(cfg.seed, 0))
    eval_env = evaluation_env(cfg, task, obs_fn)
    D, U = env.single_observation_space.shape[0], env.single_action_space.shape[0]
    agent, model = build_agent(cfg, task, obs_fn, D, env.single_action_space.low, env.single_action_space.high,
                               device)
    buffer = ReplayBuffer(cfg.buffer_size, D, U, num_envs=cfg.num_envs, device=device)
    generator = torch.Generator(device).manual_seed(cfg.seed)
    return dict(task=task, env=env, eval_env=eval_env, agent=agent, buffer=buffer, generator=generator,
                device=device, model=model)


def load_agent(folder, device: str = "auto") -> tuple:
    """(agent, cfg, observation) of the ``gnwarp rl`` run in ``folder``: its ``config.json``
    (checked as ``RLConfig``) and the agent's state in its ``checkpoint.pt``, or in the
    ``agent.pt`` of a folder that ``export_agent`` wrote (validated; no code runs), on ``device``
    ("auto", "cpu", "cuda"); ``observation`` is the run's ("bodies" or its ``DMCObservation``).
    FileNotFoundError names a missing file."""
    from gnwarp.control.vector_env import make_vector_env
    folder = Path(folder)
    state_file = agent_file(folder)
    from gnwarp.validation import read_config_file
    cfg = RLConfig.from_dict({**read_config_file(folder / CONFIG_FILE, "RLConfig keys"), "device": device})
    task = check_task(cfg)
    obs_fn = observation_of(cfg, task)
    # one env of MuJoCo C for the spaces (the agent's sizes and action box)
    env = make_vector_env(task, 1, backend="mujoco", episode_steps=cfg.episode_steps, output="torch",
                          observation=obs_fn)
    try:
        D, space = env.single_observation_space.shape[0], env.single_action_space
    finally:
        env.close()
    state = _agent_state(state_file)   # before building: a bad file fails first
    devices = list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []
    with torch.random.fork_rng(devices=devices):   # building seeds torch: leave the caller's RNG as it was
        agent, _ = build_agent(cfg, task, obs_fn, D, space.low, space.high, _device(cfg.device))
    agent.load_state_dict(state)
    return agent, cfg, obs_fn


def agent_file(folder) -> Path:
    """The file holding the trained agent of a ``gnwarp rl`` run folder (``checkpoint.pt``) or of
    an ``export_agent`` folder (``agent.pt``); FileNotFoundError names what is missing."""
    folder = Path(folder)
    states = [folder / n for n in (CHECKPOINT, AGENT_FILE) if (folder / n).is_file()]
    if not (folder / CONFIG_FILE).is_file() or not states:
        missing = CONFIG_FILE if not (folder / CONFIG_FILE).is_file() else f"{CHECKPOINT} (or an exported {AGENT_FILE})"
        raise FileNotFoundError(f"no gnwarp rl run in {folder}: its {missing} is missing")
    return states[0]


def _agent_state(path: Path) -> dict:
    """The agent's state in a run's checkpoint or an exported agent file (RLCheckpointError if
    the file holds none)."""
    from gnwarp.rl.run_log import RLCheckpointError
    state = load_checkpoint(path).get("agent")
    if not isinstance(state, dict):
        raise RLCheckpointError(f"{path} holds no agent state")
    return state


def export_agent(run, dest) -> Path:
    """The trained agent of the run in folder ``run`` alone, without its replay buffer and loop
    state (kilobytes to a few MB instead of hundreds: to share, commit or copy off a machine),
    into folder ``dest``: its ``config.json`` and ``agent.pt`` (the same checked format as the
    checkpoint). ``load_agent(dest)``, planner "policy" and ``gnwarp mpc --policy`` read it like
    the run; it cannot resume training. Returns ``dest``."""
    run, dest = Path(run), Path(dest)
    if agent_file(run).name != CHECKPOINT:   # an export is not a run
        raise FileNotFoundError(f"no gnwarp rl run in {run}: its {CHECKPOINT} is missing")
    if dest.resolve() == run.resolve():
        raise ValueError(f"export_agent writes into another folder than the run's ({run})")
    if (dest / CHECKPOINT).exists() or ((dest / CONFIG_FILE).exists() and not (dest / AGENT_FILE).exists()):
        raise ValueError(f"{dest} holds a gnwarp rl run or another program's {CONFIG_FILE}: export into an empty "
                         "folder or an earlier export")
    from gnwarp.validation import read_config_file
    cfg = read_config_file(run / CONFIG_FILE, "RLConfig keys")
    RLConfig.from_dict(cfg)   # a broken config fails here, not when the export is loaded
    cfg["out"] = str(dest)    # the folder names itself
    state = _agent_state(run / CHECKPOINT)
    dest.mkdir(parents=True, exist_ok=True)
    save_checkpoint(dest / AGENT_FILE, dict(agent=state))
    with atomic_write(dest / CONFIG_FILE) as tmp:
        Path(tmp).write_text(json.dumps(cfg, indent=1) + "\n")
    return dest


@torch.no_grad()
def evaluate_policy(agent, env, seed: int, keep: int = 0, keep_steps: int | None = None):
    """One episode in each env of ``env`` (reset with ``seed``) with the agent's deterministic
    policy; their returns. With ``keep`` > 0, also the body states of the first ``keep`` envs'
    first ``keep_steps`` steps (None: all) [keep, steps + 1, B, 13] (CPU, float64): (returns, states)."""
    if int(keep) < 0 or (keep_steps is not None and int(keep_steps) < 0):
        raise ValueError(f"keep and keep_steps must be >= 0, got {keep} and {keep_steps}")
    obs, _ = env.reset(seed=seed)
    total = torch.zeros(env.num_envs, dtype=torch.float64)
    keep = min(int(keep), env.num_envs)
    last = env.episode_steps if keep_steps is None else min(int(keep_steps), env.episode_steps)
    states = [env.body_states[:keep].double().cpu()] if keep else None
    for t in range(env.episode_steps):
        obs, reward, _, _, infos = env.step(agent.act(obs, deterministic=True))
        total += torch.as_tensor(reward, dtype=torch.float64).cpu()
        if keep and t < last:   # the step's own state: at the time limit the env reset already
            ended = "final_body_states" in infos
            states.append((torch.as_tensor(infos["final_body_states"]) if ended else env.body_states)[:keep]
                          .double().cpu())
    return (total.tolist(), torch.stack(states, 1)) if keep else total.tolist()


def frozen_policy_warning(previous: dict, outputs: torch.Tensor, agent, saturated: float | None = None) -> bool:
    """Warn (``FrozenPolicyWarning``) when the policy's unbounded outputs at a fixed batch of
    observations (the evaluation's first states, ``agent.policy_output``) are exactly those of the
    previous evaluation although the agent updated in between: the policy no longer changes, as
    one whose squashed output sits on tanh's flat ends does (its gradient vanishes there). Equal
    returns alone would not say so (a sparse task scores 0 whatever the actions). ``previous``
    holds the last evaluation's (``outputs``, ``updates``) and is updated here; ``saturated``:
    the share of those actions at the bounds, for the message. True when it warned."""
    old = previous.get("outputs")
    same = (old is not None and old.shape == outputs.shape and bool(torch.equal(old, outputs))
            and agent.updates > previous["updates"])
    if same:
        warnings.warn(
            f"the policy at {agent.env_steps} env steps gives exactly the outputs it gave at the previous "
            f"evaluation, {agent.updates - previous['updates']} updates ago: it no longer changes"
            + (f" ({saturated:.0%} of its deterministic actions there sit at the action bounds)"
               if saturated is not None else "")
            + ". A policy whose squashed output sits on tanh's flat ends gets no gradient; agent_settings "
            "squash_penalty (e.g. 1e-3) or a lower policy_lr keeps it off them", FrozenPolicyWarning, stacklevel=2)
    previous.update(outputs=outputs.detach().clone(), updates=agent.updates)
    return same


class FrozenPolicyWarning(UserWarning):
    """An RL run's policy stopped changing (``frozen_policy_warning``)."""


def _rng_states() -> dict:
    d = dict(torch=torch.get_rng_state(), numpy=np.random.get_state(), python=random.getstate())
    if torch.cuda.is_available():
        d["cuda"] = torch.cuda.get_rng_state_all()
    return d


def _set_rng_states(d: dict) -> None:
    torch.set_rng_state(d["torch"])
    name, keys, *rest = d["numpy"]    # the checkpoint holds the key array as a tensor
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), *rest))
    random.setstate(d["python"])
    if "cuda" in d and torch.cuda.is_available() and len(d["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(d["cuda"])


def normalize_model(model, buffer: ReplayBuffer) -> bool:
    """Set the model's normalization from the stored transitions (at least 2); whether it did."""
    n = buffer.filled
    if model is None or not hasattr(model, "normalize_from") or n * buffer.num_envs < 2:
        return False
    model.normalize_from(buffer.obs[:n].reshape(-1, buffer.obs_dim), buffer.next_obs[:n].reshape(-1, buffer.obs_dim))
    return True


def _rebuild(cfg: RLConfig, buffer: ReplayBuffer, episode_steps: int) -> None:
    """A slim copy's replay buffer rebuilt (``gnwarp.rl.slim.rebuild_buffer``): on MuJoCo C in
    worker processes of one thread each, on a GPU simulator in this process."""
    from functools import partial

    from gnwarp.rl.slim import rebuild_buffer
    cpu_sim = run_backend(cfg) == "mujoco"
    rebuild_buffer(buffer, partial(training_env, cfg, 1 if cpu_sim else None), partial(round_seed, cfg.seed),
                   episode_steps, workers=None if cpu_sim else 1, progress=cfg.progress)


def run_rl(cfg: RLConfig) -> dict:
    """Train (or go on training) the run of ``cfg`` in ``cfg.out`` until ``cfg.env_steps``, the
    ``chunk`` or the ``budget_seconds``. Returns {"stop": "done" | "chunk" | "budget",
    "env_steps", "updates", "rounds", "seconds" (this call), "records" (path), "last_eval"
    (the last evaluation's returns or None), "video" (the path of video.gif when this call
    wrote one, else None)}."""
    from tqdm.auto import tqdm
    started = time.perf_counter()
    check_task(cfg)
    out, resume, cfg = prepare_folder(cfg)
    parts = build_run(cfg)
    env, eval_env, agent, buffer, gen = (parts[k] for k in ("env", "eval_env", "agent", "buffer", "generator"))
    task, model = parts["task"], parts["model"]
    E, T = cfg.num_envs, env.episode_steps
    per_round = E * T
    total_rounds = math.ceil(cfg.env_steps / per_round)
    state = CollectorState(None, E)
    c = dict(round=0, episodes=0, seconds=0.0, last_eval=None, normalized=False)
    keep_until = None
    if resume:
        try:
            ck = load_checkpoint(out / CHECKPOINT)
            agent.load_state_dict(ck["agent"])
            buffer.load_state_dict(ck["buffer"])
            if buffer.pending_digest is not None:   # a slim copy (gnwarp.rl.slim): its transitions simulated again
                _rebuild(cfg, buffer, T)
            if not restore_generator(gen, ck["generator"]):
                warnings.warn(f"{out} was saved on another kind of device: its replay sampling and the agent's "
                              "exploration noise go on from their seeds, not bit for bit", RuntimeWarning, stacklevel=2)
            state = CollectorState.from_state_dict(ck["collector"], parts["device"])
            c = ck["counters"]
            _set_rng_states(ck["rng"])
            keep_until = agent.env_steps
        except BaseException:   # a refused checkpoint or rebuild: the envs made above closed
            env.close()
            eval_env.close()
            raise
    log = bar = None   # closed in the finally below with the envs, whatever raises first
    try:
        records_path = out / RECORDS_FILE
        cut_records(records_path, keep_until)
        log = RunLog(out, keep_until, cfg.tensorboard)
        from gnwarp.rl.graphed import Updater
        updater = Updater(agent, buffer, gen,
                          capture=cfg.cuda_graph and parts["device"].type == "cuda")
        meta = dict(commit=git_commit(), gpu=gpu_name(parts["device"]) if parts["device"].type == "cuda" else "cpu")
        dynamics = "true_mujoco_c" if run_backend(cfg) == "mujoco" else "true_mjwarp"

        def checkpoint():
            t = time.perf_counter()
            save_checkpoint(out / CHECKPOINT, dict(
                agent=agent.state_dict(), buffer=buffer.state_dict(), generator=gen.get_state(),
                collector=state.state_dict(), counters=dict(c), rng=_rng_states(), config=cfg.to_dict(),
                env=dict(round=c["round"], episode_steps=T, num_envs=E, control_steps=agent.env_steps)))
            timing["checkpoint_seconds"] = time.perf_counter() - t

        video_steps = cfg.video_episodes * min(cfg.video_steps, T)   # the video's episode-steps

        def evaluates(env_steps: int, rnd: int) -> bool:
            """Whether the round ending at ``env_steps`` (round ``rnd``, counted from 1) evaluates: the
            first end past a multiple of ``eval_every`` since the last evaluation, and the last round."""
            return env_steps // cfg.eval_every > c["last_eval"] // cfg.eval_every or rnd == total_rounds

        def finish_reserve(next_evaluates: bool) -> float:
            """Seconds the call's end takes after its last round: the final checkpoint (as long as
            the last one took) and, where this call will write a video (it evaluated, or the next
            round evaluates), the video (at the rate an earlier call of the run wrote one, else
            ``VIDEO_SECONDS_GUESS``)."""
            vid = 0.0
            if video_steps and (video or next_evaluates):
                per = timing.get("video_seconds_per_step")
                vid = VIDEO_SECONDS_GUESS if per is None else per * video_steps
            return timing.get("checkpoint_seconds", 0.0) + vid

        video = {}   # the body states of this call's last evaluation, for video.gif
        timing = _read_timing(out) if resume else {}   # seconds of the last checkpoint, of a video's step

        previous = {}   # the evaluation's first states ("probe"); the last evaluation's policy outputs there, updates

        def evaluate():
            returns = evaluate_policy(agent, eval_env, eval_reset_seed(cfg), keep=cfg.video_episodes,
                                      keep_steps=cfg.video_steps)
            if cfg.video_episodes:
                returns, video["states"] = returns
                video["env_steps"] = agent.env_steps
            first_of_run = c["last_eval"] is None
            if "probe" not in previous:   # the evaluation's first states: the same at every evaluation
                first, _ = eval_env.reset(seed=eval_reset_seed(cfg))
                previous["probe"] = torch.as_tensor(first, device=agent.device, dtype=agent.dtype)
            # on record once (the run's first evaluation): what each episode starts from, every time
            states = evaluation_states(eval_env) if first_of_run else {}
            with torch.no_grad():
                frozen_policy_warning(previous, agent.policy_output(previous["probe"]), agent,
                                      agent.saturated(previous["probe"]))
            c["last_eval"] = agent.env_steps
            rec = ResultRecord(
                experiment="rl", task=task.name, planner="policy", dynamics=dynamics,
                variant=f"{cfg.agent}/{cfg.preset}/{cfg.networks}", system=env.system.name, seed=cfg.seed,
                episodes=len(returns), episode_steps=eval_env.episode_steps, control_dt=float(env.dt),
                returns=returns, env_steps=agent.env_steps,
                metrics=dict(updates=agent.updates, episodes=c["episodes"], seconds=round(c["seconds"], 3)),
                config=dict(agent=cfg.agent, preset=cfg.preset, networks=cfg.networks, observation=cfg.observation,
                            num_envs=E, utd=cfg.utd, eval_episodes=cfg.eval_episodes, eval_seed=cfg.eval_seed,
                            update_compile=agent.compile_used,   # this call's: a resume may change it
                            agent_settings=agent.settings.to_dict(), **states),
                date=datetime.now(timezone.utc).isoformat(timespec="seconds"), **meta)
            write_records(records_path, [rec])
            return returns

        last_eval = None
        if c["last_eval"] is None:
            last_eval = evaluate()
            checkpoint()
        bar = tqdm(total=total_rounds * per_round, initial=min(agent.env_steps, total_rounds * per_round), unit="step",
                   unit_scale=True, desc=f"{cfg.agent} {task.name}", disable=not cfg.progress, dynamic_ncols=True)
        rounds_cap = math.ceil(cfg.chunk / per_round) if cfg.chunk else None
        done_here, last_round_s, stop = 0, 0.0, "done"
        while c["round"] < total_rounds:
            elapsed = time.perf_counter() - started
            if rounds_cap is not None and done_here >= rounds_cap:
                stop = "chunk"
                break
            next_evaluates = evaluates(agent.env_steps + per_round, c["round"] + 1)
            if (cfg.budget_seconds is not None and done_here
                    and elapsed + last_round_s + finish_reserve(next_evaluates) > cfg.budget_seconds):
                stop = "budget"
                break
            t0 = time.perf_counter()
            state.obs, _ = env.reset(seed=round_seed(cfg.seed, c["round"]))
            state.episode_return[:] = 0.0
            left, returns, metrics = T, [], {}
            while left > 0:
                piece = min(left, _PIECE)
                s = agent.settings
                if model is not None and not c["normalized"] and agent.env_steps < s.update_after:
                    # the model's normalization from the data before its first update
                    before = math.ceil((s.update_after - agent.env_steps) / E) - 1
                    if before < piece:
                        if before > 0:
                            returns += run_env_steps(agent, env, buffer, state, before, gen,
                                                     updater=updater)["returns"]
                            left -= before
                            bar.update(before * E)
                        normalize_model(model, buffer)
                        c["normalized"] = True   # once, before the first update
                        continue
                r = run_env_steps(agent, env, buffer, state, piece, gen, updater=updater)
                returns += r["returns"]
                metrics = r["metrics"] or metrics
                left -= piece
                bar.update(piece * E)
            c["round"] += 1
            c["episodes"] += len(returns)
            train_s = time.perf_counter() - t0
            c["seconds"] += train_s
            done_here += 1
            row = dict(env_steps=agent.env_steps, round=c["round"], updates=agent.updates, episodes=c["episodes"],
                       seconds=c["seconds"], round_seconds=train_s, train_return=float(np.mean(returns)) if returns else None,
                       saturated=agent.saturated(state.obs), **metrics)   # deterministic actions at the bounds
            evaluating = evaluates(agent.env_steps, c["round"])
            if evaluating:
                last_eval = evaluate()
                row.update(eval_median=float(np.median(last_eval)), eval_mean=float(np.mean(last_eval)))
            log.add(row)
            bar.set_postfix(ret=f"{row['train_return'] or 0:.1f}",
                            eval=f"{np.median(last_eval):.1f}" if last_eval else "-", refresh=False)
            if evaluating:
                checkpoint()
            last_round_s = time.perf_counter() - t0   # with its evaluation and checkpoint: the budget's unit
        if c["round"] >= total_rounds:
            stop = "done"
        checkpoint()
        if (stop == "done" and not video and video_steps and not (out / VIDEO_FILE).exists()
                and not timing.get("video_failed")):
            # a finished run without its video (a call killed while writing it): the last
            # evaluation's episodes again, not recorded (the same seed and policy: the same states)
            _, video["states"] = evaluate_policy(agent, eval_env, eval_reset_seed(cfg),
                                                 keep=cfg.video_episodes, keep_steps=cfg.video_steps)
            video["env_steps"] = agent.env_steps
        if video:
            t = time.perf_counter()
            try:
                write_video(out / VIDEO_FILE, video["states"], env.system, f"{cfg.agent} {task.name}, "
                            f"deterministic policy after {video['env_steps']} env steps", cfg.renderer)
            except Exception as e:  # noqa: BLE001 - training is saved; a video that fails is reported, not fatal
                video.clear()
                timing["video_failed"] = True   # a finished run does not evaluate again for it
                warnings.warn(f"no video written ({type(e).__name__}: {e}); renderer 'matplotlib' needs no "
                              "OpenGL", RuntimeWarning, stacklevel=2)
            if video and video_steps:   # written: its rate for the next call's budget
                timing["video_seconds_per_step"] = (time.perf_counter() - t) / video_steps
                timing.pop("video_failed", None)
        with atomic_write(out / TIMING_FILE) as tmp:   # for the next call's budget
            Path(tmp).write_text(json.dumps(timing))
    finally:   # each closed even where an earlier close raises
        with contextlib.ExitStack() as closing:
            for close in (eval_env.close, env.close, getattr(log, "close", None), getattr(bar, "close", None)):
                if close is not None:   # called last to first: the bar, the log, the envs
                    closing.callback(close)
    return dict(stop=stop, env_steps=agent.env_steps, updates=agent.updates, rounds=c["round"],
                seconds=time.perf_counter() - started, records=str(records_path), last_eval=last_eval,
                video=str(out / VIDEO_FILE) if video else None)


def write_video(path: Path, states: torch.Tensor, system, title: str, renderer: str = "auto",
                fps_max: float = 25.0, marks=None) -> Path:
    """A GIF of episodes' body states [K, T+1, B, 13] at ``path`` (at most ``fps_max`` frames a
    second of simulated time; ``marks`` [K, 3]: each episode's target, drawn by the matplotlib
    renderer), written whole or not at all (``gnwarp.eval.video.write_video``)."""
    from gnwarp.eval.animation import animate_system
    animate_system(states.numpy(), system, path, title=title, renderer=renderer, fps_max=fps_max, marks=marks)
    return path
