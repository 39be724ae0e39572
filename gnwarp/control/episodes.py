"""Closed-loop episodes on the true simulator: one runner for every ``Planner`` (gradient MPC,
sampling MPC, iLQG, random actions, or a user's planner: ``gnwarp.control.planner``).

The planner is reset for the N episodes (their targets given), then each of ``steps`` data steps
it sees the episodes' true state and returns actions [N, U] (``step``: optimize, then act); the
true ``Env`` executes them (clamped to the actuators' ranges as MuJoCo does); the true trajectory
is scored by the task's reward. A planner that plans on the simulator's state
(``needs_sim_state``: iLQG, sampling MPC on ``EnvDynamics``) gets ``env.observe()`` (qpos, qvel
and body states), every other one the body states [N, B, 13].
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from gnwarp.control.planner import Planner
from gnwarp.control.tasks import Task, get_task

__all__ = ["run_episodes", "identify_on_env"]


def _sync(device) -> None:
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def run_episodes(planner: Planner, env, task, steps: int, x0=None, *, target=None, qpos0=None, qvel0=None,
                 progress: Callable[[int], None] | None = None) -> dict:
    """Run ``planner`` (a ``Planner``) in closed loop on ``env`` (one episode per world) for
    ``steps`` steps, after ``planner.reset(N, target)``.

    ``task``: a task name or ``Task`` (its reward, with ``target``: per-episode targets, default
    the planner's ``targets``), or any ``reward(states [N, T+1, B, 13], actions [N, T, U]) -> [N]``.
    Start: ``qpos0`` / ``qvel0`` (the env is reset there), else ``x0`` (body states of an env
    already reset: ``x0 = env.reset(...)``), else the env's current state. Returns {"returns" [N]
    (the true trajectory's reward), "states" [N, steps+1, B, 13], "actions" [N, steps, U] (as
    applied), "plan_seconds" [steps] (wall time of each planning step, the device synchronized)},
    tensors on the CPU."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
    if not isinstance(planner, Planner):
        missing = [m for m in ("n", "targets", "device", "needs_sim_state", "reset", "optimize", "act", "step")
                   if not hasattr(planner, m)]
        raise TypeError(f"planner must implement gnwarp.control.planner.Planner; {type(planner).__name__} lacks "
                        f"{', '.join(missing)}")
    if isinstance(task, (str, Task)):
        task = get_task(task)
        system = getattr(getattr(env, "system", None), "name", None)
        if system is not None:   # a task of another system would score the wrong bodies, silently
            task.check_system(system, "env's system")
    elif not (callable(getattr(task, "reward", None)) or callable(task)):
        raise TypeError(f"task must be a task name, a Task or a reward callable, got {type(task).__name__}")
    if qpos0 is not None:
        x = torch.as_tensor(env.reset(qpos0, qvel0))
    elif x0 is not None:
        x = torch.as_tensor(x0)
    else:
        x = torch.as_tensor(env.body_states())
    planner.reset(x.shape[0], target)   # a fresh plan; the targets (None: the planner's own)
    if isinstance(task, Task):
        tgt = target if target is not None else planner.targets
        tgt = None if tgt is None else torch.as_tensor(tgt).detach().cpu().float()
        score = lambda s, a: task.scorer(s, a, tgt)  # noqa: E731  (exact, where planners optimize a surrogate)
    else:
        score = getattr(task, "reward", task)
    sim_state = bool(planner.needs_sim_state)
    device = planner.device
    states, actions, secs = [x.detach().cpu().float()], [], []
    for t in range(steps):
        t0 = time.perf_counter()
        a = planner.step(env.observe() if sim_state else x)
        _sync(device)
        secs.append(time.perf_counter() - t0)
        x = torch.as_tensor(env.step(a))
        applied = getattr(env, "last_ctrl", None)
        actions.append((applied if applied is not None else torch.as_tensor(a)).detach().cpu().float())
        states.append(x.detach().cpu().float())
        if progress:
            progress(t + 1)
    states_t, actions_t = torch.stack(states, 1), torch.stack(actions, 1)
    returns = torch.as_tensor(score(states_t, actions_t)).detach().cpu().float()
    return {"returns": returns, "states": states_t, "actions": actions_t, "plan_seconds": np.asarray(secs)}


def identify_on_env(model, env, *, seed: int = 0, qpos0=None, qvel0=None, x0=None):
    """System identification in closed loop (Figure 10's system-ID variant): ``model.window``
    steps of uniform random actions on the true ``env`` from its current state (or reset to
    ``qpos0`` / ``qvel0``, or ``x0`` as ``run_episodes``), then G_ID from that window.

    ``model``: a bound ``SysIDModel``. Returns (``model.with_fixed_gid(g_id)``, the model to plan
    through; the states after the window [N, B, 13], where the env now is; the window's
    ``run_episodes`` output)."""
    from gnwarp.control.sampling import RandomPlanner
    W = int(model.window)
    planner = RandomPlanner(env.actuators, env.n_worlds, seed=seed)   # unlimited actuators: [-1, 1]
    window = run_episodes(planner, env, lambda s, a: torch.zeros(s.shape[0]), W, x0, qpos0=qpos0, qvel0=qvel0)
    n = window["states"].shape[0]
    with torch.no_grad():
        g_id = model.identify(window["states"][:, :W], window["actions"][:, :W], torch.zeros(n, dtype=torch.int64))
    return model.with_fixed_gid(g_id), window["states"][:, W], window
