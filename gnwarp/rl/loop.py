"""The off-policy training loop's inner part: act in a vector environment, store the steps in the
replay buffer, take the settings' share of gradient updates, and count finished episodes' returns.

    >>> state = CollectorState(obs=env.reset(seed=0)[0], num_envs=env.num_envs)
    >>> out = run_env_steps(agent, env, buffer, state, steps=1000, generator=gen)
    >>> out["returns"], out["metrics"]          # finished episodes' returns, the last update's losses

The env must autoreset in "same_step" mode (every step a real transition; ``reached_obs`` gives
the final observation of an ended episode).
"""
from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import torch

from gnwarp.rl.graphed import Updater
from gnwarp.rl.replay import ReplayBuffer, reached_obs

__all__ = ["CollectorState", "run_env_steps", "PROFILE_RANGES"]

# the loop's parts as named ranges of a torch.profiler trace (rl.act, rl.env_step, rl.store,
# rl.updates): off unless a profiler wants them (bench/rl_loop.py --profile sets it), since a
# range costs ~10 us even with no profiler running
PROFILE_RANGES = False


def _span(name: str):
    if PROFILE_RANGES:
        from torch.profiler import record_function
        return record_function(name)
    return contextlib.nullcontext()


@dataclasses.dataclass
class CollectorState:
    """What the loop carries between calls: the envs' current observations ``obs`` [E, D],
    each env's return so far ``episode_return`` [E] and the fraction of an update owed ``owed``."""
    obs: object
    num_envs: int
    episode_return: np.ndarray | None = None
    owed: float = 0.0

    def __post_init__(self):
        if self.episode_return is None:
            self.episode_return = np.zeros(self.num_envs)

    def state_dict(self) -> dict:
        """Tensors and plain values (a NumPy env's observations as a tensor, flagged)."""
        numpy_obs = self.obs is not None and not isinstance(self.obs, torch.Tensor)
        obs = None if self.obs is None else (torch.from_numpy(np.array(self.obs)) if numpy_obs else self.obs.cpu())
        return dict(obs=obs, numpy_obs=numpy_obs, num_envs=self.num_envs,
                    episode_return=torch.as_tensor(self.episode_return.copy()), owed=self.owed)

    @classmethod
    def from_state_dict(cls, d: dict, device=None) -> "CollectorState":
        obs = d["obs"]
        if obs is not None and d.get("numpy_obs", not isinstance(obs, torch.Tensor)):
            obs = obs.numpy().copy() if isinstance(obs, torch.Tensor) else np.array(obs)
        elif obs is not None and device is not None:
            obs = obs.to(device)
        ret = d["episode_return"]
        ret = ret.numpy().copy() if isinstance(ret, torch.Tensor) else np.array(ret)
        return cls(obs, int(d["num_envs"]), ret, float(d["owed"]))


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _on_env_device(action: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
    """``action`` on the device of the env's observations ``obs`` (where it simulates: the CPU for
    MuJoCo C behind torch output, the GPU for MuJoCo-Warp; read from the observations, which any
    wrapper passes on), copied now rather than inside ``env.step``."""
    return action if obs.device == action.device else action.to(obs.device)


def run_env_steps(agent, env, buffer: ReplayBuffer, state: CollectorState, steps: int, generator: torch.Generator,
                  model_sequence: int | None = None, updater: Updater | None = None) -> dict:
    """``steps`` steps of the vector ``env`` (``steps x num_envs`` env steps) with ``agent.act``:
    each step stored in ``buffer``; once ``agent.env_steps >= update_after``,
    ``updates_per_step x num_envs`` updates per step on batches of ``batch_size`` from ``buffer``
    (drawn with ``generator``; ``model_sequence``: the model's batch as sequences of that many
    steps), by ``updater`` (``gnwarp.rl.graphed.Updater``, made once and passed to every call: on
    CUDA it records the update in a CUDA graph once; None: eager updates). ``state`` is advanced
    in place. With ``act_ahead`` (the agent's settings) each next action but the call's first is
    picked, and copied to the env's side (the host for a NumPy env or a CPU simulator), before
    the previous step's updates are launched: with the agent on CUDA and the env on the CPU those
    updates run while the CPU steps the environment (an env on the GPU queues behind them: no
    overlap); the policy acts one step's updates behind. Without it each action follows the
    updates, strictly in turn. Either way the env steps are counted as the actions are taken (the
    update schedule is the same), and no action is left picked between calls, so a call's first
    step runs in turn: the numbers depend on how the steps are split into calls (``run_rl``
    splits each round the same way, so a resumed run equals an uninterrupted one).
    Returns {"returns": [finished episodes' returns], "metrics": the last update's losses (floats)
    or {}, "updates": updates taken}."""
    from gymnasium.vector import AutoresetMode
    mode = getattr(env, "metadata", {}).get("autoreset_mode")
    if mode is not None and AutoresetMode(mode) != AutoresetMode.SAME_STEP:
        raise ValueError(f"the env autoresets in {mode} mode; make it with autoreset_mode=\"same_step\"")
    s = agent.settings
    if updater is None:
        updater = Updater(agent, buffer, generator, model_sequence, capture=False)
    elif (updater.agent, updater.buffer, updater.generator, updater.model_sequence) != (
            agent, buffer, generator, model_sequence):
        raise ValueError("the updater was made for another agent, buffer, generator or model_sequence")
    returns, metrics, updates = [], {}, 0
    torch_env = isinstance(state.obs, torch.Tensor)
    ahead = bool(getattr(s, "act_ahead", False))
    steps = int(steps)
    picked = host = None   # an action picked ahead, and its copy on the env's side (the host: NumPy or a CPU simulator)
    for i in range(steps):   # the ranges "rl." where PROFILE_RANGES is set
        with _span("rl.act"):
            action = picked if picked is not None else agent.act(state.obs, count=False, check=False)
        agent.count_env_steps(state.num_envs)
        with _span("rl.env_step"):
            next_obs, reward, terminated, truncated, infos = env.step(
                host if picked is not None else (action if torch_env else _numpy(action)))
        picked = host = None
        with _span("rl.store"):
            buffer.add(state.obs, action, reward, reached_obs(next_obs, infos), terminated, truncated)
        state.episode_return += _numpy(reward)
        ended = _numpy(terminated) | _numpy(truncated)
        returns += state.episode_return[ended].tolist()
        state.episode_return[ended] = 0.0
        state.obs = next_obs
        if ahead and i + 1 < steps:   # the next action now: its host copy waits for it, not for the updates
            with _span("rl.act"):
                picked = agent.act(state.obs, count=False, check=False)
                host = _on_env_device(picked, state.obs) if torch_env else _numpy(picked)
        if agent.env_steps >= s.update_after:
            state.owed += s.updates_per_step * state.num_envs
            n = int(state.owed)
            if n:
                with _span("rl.updates"):
                    metrics = updater.run(n)
                state.owed -= n
                updates += n
    return {"returns": returns, "metrics": {k: float(v) for k, v in metrics.items()}, "updates": updates}
