"""A trained agent's policy as a ``gnwarp.control.Planner``: ``optimize`` does nothing, ``act``
is the policy's deterministic action on the observation of the episodes' body states, so the
closed-loop episodes and benchmarks of ``gnwarp.control`` run it beside the planners.

    >>> planner = PolicyPlanner(agent, env.obs_layout, n=env.num_envs, targets=env.targets)
    >>> action = planner.step(env.body_states)        # [N, U]
"""
from __future__ import annotations

from typing import Callable

import torch

__all__ = ["PolicyPlanner"]


class PolicyPlanner:
    """``agent`` (``gnwarp.rl.agents``: its ``act(obs, deterministic=True)``) acting on
    ``observation(body [N, B, 13], targets) -> obs [N, D]`` (a vector env's ``obs_layout``, so the
    policy sees the observations it learned from); ``n`` episodes; ``targets`` [N, ...] of the task (None for
    a task without)."""

    needs_sim_state = False

    def __init__(self, agent, observation: Callable, n: int, targets=None):
        if not callable(observation):
            raise TypeError("observation must be a callable (body [N, B, 13], targets) -> obs [N, D], "
                            f"e.g. a vector env's obs_layout; got {type(observation).__name__}")
        self.agent, self.observation = agent, observation
        self.device = agent.device
        self.reset(n, targets)

    def reset(self, n: int, targets=None, seed: int | None = None) -> None:
        """Start ``n`` episodes (``targets`` [n, ...]; None keeps those held). A deterministic
        policy draws no random numbers: ``seed`` is unused."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be an integer >= 1, got {n!r}")
        self.n = n
        if targets is not None:
            self.targets = targets
        elif not hasattr(self, "targets"):
            self.targets = None

    def optimize(self, state) -> None:
        """Nothing to plan: the policy is already trained."""

    def act(self, state, time: int = 0) -> torch.Tensor:
        """The policy's actions [N, U] at body states ``state`` [N, B, 13] (``time`` unused: the
        policy acts on the state it is given)."""
        body = state.body if hasattr(state, "body") else state
        body = torch.as_tensor(body)
        if body.ndim != 3 or body.shape[0] != self.n:
            raise ValueError(f"body states must be [N={self.n}, B, 13], got {tuple(body.shape)}")
        return self.agent.act(self.observation(body, self.targets), deterministic=True)

    def step(self, state) -> torch.Tensor:
        self.optimize(state)
        return self.act(state, 0)
