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
from gnwarp.validation import ConfigError, FloatRange, IntRange, PositiveFloat, PositiveInt, check_fields

__all__ = ["PolicyPlanner", "PolicySettings", "PolicyMPC", "PolicyMPCSettings"]


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
        return cls(agent, ObservationLayout(system, task, None if obs_fn == "bodies" else obs_fn), n, targets,
                   settings=settings)

    def __init__(self, agent, observation: Callable, n: int, targets=None, settings=None):
        self.settings = settings
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


@dataclasses.dataclass
class PolicyMPCSettings(PolicySettings):
    """A trained SVG(N >= 1) agent's run (``run``, ``device``) planned over with its own model,
    reward and Q-function (``PolicyMPC``): ``horizon`` model steps, ``iterations`` rounds a control
    step of ``samples`` Gaussian action sequences and ``policy_samples`` sequences that follow the
    policy through the model; the ``elites`` best returns set the next round's mean and standard
    deviation, weighted by exp(``temperature`` x (return - best)); the standard deviation starts at
    ``init_std`` and stays above ``min_std`` (fractions of each actuator's half range). ``seed``:
    of the draws."""
    horizon: PositiveInt = 5
    samples: PositiveInt = 256
    policy_samples: IntRange(0) = 16
    iterations: PositiveInt = 4
    elites: PositiveInt = 32
    temperature: PositiveFloat = 0.5
    init_std: FloatRange(gt=0, le=2) = 1.0
    min_std: FloatRange(gt=0, le=2) = 0.05
    seed: IntRange(0) = 0

    def __post_init__(self):
        super().__post_init__()
        if self.elites > self.samples + self.policy_samples:
            raise ConfigError("elites", f"at most samples + policy_samples ({self.samples + self.policy_samples}), "
                                        f"got {self.elites}")
        if self.min_std > self.init_std:
            raise ConfigError("min_std", f"at most init_std ({self.init_std}), got {self.min_std}")


class PolicyMPC(PolicyPlanner):
    """Model-predictive control over a trained SVG(N >= 1) agent (as TD-MPC plans, with this
    agent's parts): each control step, ``settings.iterations`` rounds of sampled action sequences
    rolled through the agent's learned model ``model(obs, action) -> next_obs``, scored by its
    reward of predicted observations and, at the horizon, its Q-function at the policy's action:

        G = sum_{k<H} gamma^k r(x_k, a_k, x_{k+1}) + gamma^H Q(x_H, pi(x_H))

    The elites' weighted mean is the plan; the first action is taken and the plan shifted one
    step to start the next control step. ``policy_samples`` sequences follow the policy (sampled)
    through the model, so the planner starts from what the policy would do. Observations, targets
    and episodes as ``PolicyPlanner``."""

    def __init__(self, agent, observation: Callable, n: int, targets=None, settings: PolicyMPCSettings | None = None):
        if getattr(agent, "model", None) is None or getattr(agent, "reward", None) is None:
            raise ConfigError("run", f"planning needs the agent's learned model and reward: "
                                     f"{agent.settings.agent} has none (train svg1 .. svg5)")
        if settings is None:
            raise ConfigError("run", "PolicyMPC needs its PolicyMPCSettings")
        super().__init__(agent, observation, n, targets, settings)
        self.horizon = settings.horizon

    def reset(self, n: int, targets=None, seed: int | None = None) -> None:
        """Start ``n`` episodes: no plan held (the first step starts from the policy's), the draws
        from ``seed`` (None: the settings')."""
        super().reset(n, targets)
        s = self.settings
        self._gen = torch.Generator(self.agent.device).manual_seed(s.seed if seed is None else int(seed))
        self.plan = None    # [N, H, U]: the last plan (``act`` reads it; shifted, the next search's start)

    @torch.no_grad()
    def returns(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """G [N, M] of action sequences ``actions`` [N, M, H, U] from ``obs`` [N, D] through the
        agent's model, reward and Q-function (see the class docstring)."""
        a = self.agent
        N, M, H, U = actions.shape
        x = obs[:, None].expand(N, M, obs.shape[-1]).reshape(N * M, -1)
        acts = actions.reshape(N * M, H, U)
        gamma, total = a.settings.gamma, torch.zeros(N * M, device=obs.device, dtype=obs.dtype)
        for k in range(H):
            x2 = a.model(x, acts[:, k])
            total = total + gamma ** k * a.reward(x, acts[:, k], x2).reshape(-1)
            x = x2
        u = torch.maximum(torch.minimum(a.squash(a.policy(x)[0]), a.high), a.low)
        total = total + gamma ** H * a.q(x, u).reshape(-1)
        return total.reshape(N, M)

    @torch.no_grad()
    def _policy_sequences(self, obs: torch.Tensor, count: int, sample: bool) -> torch.Tensor:
        """[N, count, H, U]: the policy's actions along its own predicted states (``sample``: drawn
        from its Gaussian, else its mean)."""
        a = self.agent
        N, H = obs.shape[0], self.horizon
        x = obs[:, None].expand(N, count, obs.shape[-1]).reshape(N * count, -1)
        out = []
        for _ in range(H):
            mean, log_std = a.policy(x)
            if sample:
                eps = torch.randn(mean.shape, generator=self._gen, device=mean.device, dtype=mean.dtype)
                mean = mean + log_std.exp() * eps
            u = torch.maximum(torch.minimum(a.squash(mean).nan_to_num(0.0), a.high), a.low)   # finite, in the box
            out.append(u)
            x = a.model(x, u)
        return torch.stack(out, 1).reshape(N, count, H, -1)

    @torch.no_grad()
    def optimize(self, state) -> None:
        """Plan from body states ``state`` [N, B, 13]: the action to take is then ``act``'s."""
        body = torch.as_tensor(state.body if hasattr(state, "body") else state)
        if body.ndim != 3 or body.shape[0] != self.n:
            raise ValueError(f"body states must be [N={self.n}, B, 13], got {tuple(body.shape)}")
        a, s = self.agent, self.settings
        obs = a._obs(self.observation(body, self.targets))
        N, H, U = self.n, self.horizon, a.action_dim
        half, low, high = a.half, a.low, a.high
        if self.plan is None:   # the first step: the policy's mean plan
            mean = self._policy_sequences(obs, 1, sample=False)[:, 0]
        else:                   # the last plan shifted one step
            mean = torch.cat([self.plan[:, 1:], self.plan[:, -1:]], 1)
        std = (s.init_std * half).expand(N, H, U).clone()
        pol = self._policy_sequences(obs, s.policy_samples, sample=True) if s.policy_samples else None
        for _ in range(s.iterations):
            eps = torch.randn((N, s.samples, H, U), generator=self._gen, device=obs.device, dtype=obs.dtype)
            acts = torch.maximum(torch.minimum(mean[:, None] + std[:, None] * eps, high), low)
            if pol is not None:
                acts = torch.cat([acts, pol], 1)
            # a diverging rollout (NaN or infinite return) ranks last and weighs nothing
            g = self.returns(obs, acts).nan_to_num(nan=-1e30, posinf=-1e30, neginf=-1e30)
            top, idx = g.topk(s.elites, dim=1)                              # [N, K]
            elite = torch.gather(acts, 1, idx[:, :, None, None].expand(N, s.elites, H, U))
            w = torch.softmax(s.temperature * (top - top[:, :1]), dim=1)[:, :, None, None]
            mean = (w * elite).sum(1)
            std = ((w * (elite - mean[:, None]) ** 2).sum(1)).sqrt().clamp(min=s.min_std * half, max=s.init_std * half)
        self.plan = mean

    def act(self, state, time: int = 0) -> torch.Tensor:
        """The last plan's actions [N, U] ``time`` steps ahead (its last beyond the horizon;
        planned from ``state`` first if nothing is planned yet)."""
        if self.plan is None:
            self.optimize(state)
        return self.plan[:, min(max(int(time), 0), self.horizon - 1)].clone()

    def step(self, state) -> torch.Tensor:
        self.optimize(state)
        return self.act(state, 0)


PLANNERS.setdefault("policy", PlannerEntry(PolicyPlanner, PolicySettings))
PLANNERS.setdefault("policy-mpc", PlannerEntry(PolicyMPC, PolicyMPCSettings))
