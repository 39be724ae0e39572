"""A trained agent's policy as a ``gnwarp.control.Planner``: ``optimize`` does nothing, ``act``
is the policy's deterministic action on the observation of the episodes' body states, so the
closed-loop episodes and benchmarks of ``gnwarp.control`` run it beside the planners.

    >>> planner = PolicyPlanner(agent, env.obs_layout, n=env.num_envs, targets=env.targets)
    >>> action = planner.step(env.body_states)        # [N, U]

It is registered as planner "policy" (``gnwarp.control.PLANNERS``; settings ``PolicySettings``:
the folder of a ``gnwarp rl`` run), so ``make_planner("policy", ...)`` and the data loop
(``LoopConfig(planner="policy", planner_settings={"run": "runs/rl/svg1-s0"})``: the model's
error on the states the trained agent visits, the paper's Figure H.1) run a trained agent.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Literal

import torch

from gnwarp.control.planner import PLANNERS, PlannerEntry
from gnwarp.validation import ConfigError, check_fields

__all__ = ["PolicyPlanner", "PolicySettings"]


@dataclasses.dataclass
class PolicySettings:
    """``run``: the folder of a ``gnwarp rl`` run (its ``config.json`` and ``checkpoint.pt``), or
    one that ``export_agent`` wrote (``agent.pt``), whose trained policy acts; ``device``: the
    policy's ("auto": CUDA where there is one)."""
    run: str = ""
    device: Literal["auto", "cpu", "cuda"] = "auto"

    def __post_init__(self):
        check_fields(self)
        if not isinstance(self.run, str) or not self.run.strip():
            raise ConfigError("run", "must name the folder of a gnwarp rl run (its config.json and checkpoint.pt) "
                                     "or of an exported agent (config.json and agent.pt)")
        from gnwarp.rl.run import agent_file
        try:   # refused before anything is simulated
            agent_file(self.run)
        except FileNotFoundError as e:
            raise ConfigError("run", str(e)) from None


class PolicyPlanner:
    """``agent`` (``gnwarp.rl.agents``: its ``act(obs, deterministic=True)``) acting on
    ``observation(body [N, B, 13], targets) -> obs [N, D]`` (a vector env's ``obs_layout``, so the
    policy sees the observations it learned from); ``n`` episodes; ``targets`` [N, ...] of the task (None for
    a task without)."""

    needs_sim_state = False
    settings = None   # a PolicySettings when made from one (``for_model``)

    @classmethod
    def for_model(cls, dynamics, task, system, n: int, settings: PolicySettings, targets=None) -> "PolicyPlanner":
        """``make_planner``'s builder: the trained policy of the run ``settings.run`` for ``n``
        episodes of ``task`` on ``system`` (``dynamics`` unused: a policy does not plan). The
        run's task and action count must be these; ``ConfigError`` names what differs."""
        from gnwarp.control.env_observation import ObservationLayout
        from gnwarp.control.tasks import get_task
        from gnwarp.rl.run import load_agent
        from gnwarp.sim.systems import System, make
        task = get_task(task) if isinstance(task, str) else task
        agent, cfg, obs_fn = load_agent(settings.run, settings.device)
        trained = get_task(cfg.task).name
        if trained != task.name:
            raise ConfigError("run", f"the policy in {settings.run} was trained on task {trained!r}, not {task.name!r}")
        system = system if isinstance(system, System) else make(system)
        if system.nu != agent.action_dim:
            raise ConfigError("run", f"the policy in {settings.run} gives {agent.action_dim} actions; "
                                     f"{system.name} has {system.nu} actuators")
        planner = cls(agent, ObservationLayout(system, task, None if obs_fn == "bodies" else obs_fn), n, targets)
        planner.settings = settings
        return planner

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


PLANNERS.setdefault("policy", PlannerEntry(PolicyPlanner, PolicySettings))
