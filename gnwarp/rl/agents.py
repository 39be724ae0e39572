"""Off-policy agents of supplementary F.3 on torch: ``DDPG`` (deterministic policy gradient, eq. 4)
and ``SVG`` (SVG(0): Gaussian policy, reparameterized gradient of Q, eq. 5; SVG(N), N >= 1: the
reparameterized gradient of sum_{k<N} gamma^k r_{t+k} + gamma^N Q(x_{t+N}, a_{t+N}) through a
differentiable model, every a_{t+k} ~ pi(.|x_{t+k})). Both learn Q by the one-step Bellman error
of eq. 3 against target networks; a time-limit truncation bootstraps, a termination does not.

    >>> agent = make_agent(AgentSettings(agent="svg1"), obs_dim, low, high, model=model, reward=reward)
    >>> action = agent.act(obs)                       # [E, U] on the agent's device
    >>> metrics = agent.update(buffer.sample(agent.settings.batch_size, gen))

Networks follow the protocols of ``gnwarp.rl.networks`` (MLPs by default; pass ``policy=`` /
``q=`` for others).
"""
from __future__ import annotations

import copy
from typing import Callable

import torch
from torch import nn

from gnwarp.rl.networks import DeterministicPolicy, GaussianPolicy, QFunction
from gnwarp.rl.replay import Transitions
from gnwarp.rl.settings import AgentSettings
from gnwarp.validation import ConfigError

__all__ = ["Agent", "DDPG", "SVG", "make_agent", "mse_model_loss", "restore_generator", "set_adam_mode"]


def set_adam_mode(optimizers, capturable: bool) -> None:
    """Adam's flags on each of ``optimizers``: fused where its parameters are on CUDA (as
    ``_adam`` builds it), ``capturable`` as given (recordable in a CUDA graph; eager steps want it
    off), and the step counts on the parameters' device where either flag needs them there. A
    loaded state brings the flags of the device it was saved on; this sets this device's."""
    for opt in optimizers:
        for g in opt.param_groups:
            g["fused"] = bool(g["params"]) and all(p.is_cuda for p in g["params"])
            g["capturable"] = bool(capturable)
            for p in g["params"]:
                st = opt.state.get(p, {})
                if isinstance(st.get("step"), torch.Tensor) and (g["fused"] or g["capturable"]):
                    st["step"] = st["step"].to(p.device, torch.float32)


def restore_generator(generator: torch.Generator, state: torch.Tensor) -> bool:
    """Set ``generator`` to a saved ``get_state()``; whether it could: a state of the other kind
    of device (CPU and CUDA generators keep states of different sizes) leaves it as it is."""
    try:
        generator.set_state(state)
    except RuntimeError:
        return False
    return True


def mse_model_loss(model, batch: Transitions) -> torch.Tensor:
    """The default joint model loss: mean squared error of ``model(obs, action)`` against the
    observed ``next_obs``, each entry in units of the model's ``delta_std`` (the spread of its
    change, ``NormalizedModel``) where it has one: every entry counts alike, so those that change
    little (swimmer6's ``to_target``, which its reward reads) are fitted as well as the large
    velocities; raw units for a model without one."""
    err = model(batch.obs, batch.action) - batch.next_obs
    scale = getattr(model, "delta_std", None)
    return (err if scale is None else err / scale).pow(2).mean()


def _bounds(low, high, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    low = torch.as_tensor(low, dtype=dtype, device=device).reshape(-1)
    high = torch.as_tensor(high, dtype=dtype, device=device).reshape(-1)
    if low.shape != high.shape or low.numel() == 0:
        raise ConfigError("action_low", f"action_low {tuple(low.shape)} and action_high {tuple(high.shape)} "
                                        "must be equal, non-empty shapes")
    if not (torch.isfinite(low).all() and torch.isfinite(high).all() and (high > low).all()):
        raise ConfigError("action_low", "the action box needs finite bounds with high > low in every entry")
    return low, high


class _EagerFirst:
    """``fn`` eagerly on its first call (the caches it fills on first use, such as a reward's
    model constants, are then plain values to the tracer), compiled by ``torch.compile`` with
    ``backend`` from the second on; that call also compiles the backward (not lazily at the first
    ``backward()``), so that a compiler's failure shows there. With ``fallback``, such a failure
    (a ``TorchDynamoException``: no Triton, a backend error) warns and leaves ``fn`` eager
    (``fell_back``); errors of ``fn`` itself surface at its eager first call either way."""

    def __init__(self, fn, backend, fallback: bool = False):
        self.fn, self.calls, self.backend, self.fallback, self.fell_back = fn, 0, backend, fallback, False
        self.compiled = torch.compile(fn, backend=backend, dynamic=False)

    def __call__(self, *args, **kwargs):
        self.calls += 1
        if self.calls == 1:
            return self.fn(*args, **kwargs)
        if self.calls > 2:
            return self.compiled(*args, **kwargs)
        from torch._dynamo.exc import TorchDynamoException
        try:
            with _backward_compiled_now():
                return self.compiled(*args, **kwargs)
        except TorchDynamoException as e:
            if not self.fallback:
                raise
            import warnings
            warnings.warn(f"torch.compile ({self.backend}) of the update failed, the update runs eagerly: "
                          f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}", stacklevel=2)
            self.compiled, self.fell_back = self.fn, True
            return self.fn(*args, **kwargs)


def _backward_compiled_now():
    """AOTAutograd compiling the backward with the forward (torch's
    ``force_non_lazy_backward_lowering``; a no-op where this torch has no such setting)."""
    import contextlib
    try:
        import torch._functorch.config as functorch_config
    except ImportError:
        return contextlib.nullcontext()
    if not hasattr(functorch_config, "force_non_lazy_backward_lowering"):   # patch() raises only on entry
        return contextlib.nullcontext()
    return functorch_config.patch(force_non_lazy_backward_lowering=True)


def _adam(net, lr: float) -> torch.optim.Adam | None:
    """Adam on ``net``'s trainable parameters (None for a network without any: a fixed one)."""
    params = [p for p in net.parameters() if p.requires_grad] if isinstance(net, nn.Module) else []
    if not params:
        return None
    # one fused kernel per step on CUDA (updates of small MLPs are launch-bound; its step count
    # lives on the device); gnwarp.rl.graphed.Updater makes it capturable before recording
    return torch.optim.Adam(params, lr=lr, fused=all(p.is_cuda for p in params))


class Agent:
    """What both agents share: the action box (``low``, ``high`` [U]), the policy and its target,
    the Q-function and its target, their Adam optimizers, the generator, the counters ``updates``
    (gradient steps) and ``env_steps`` (actions taken by ``act`` when not deterministic)."""

    def __init__(self, settings: AgentSettings, obs_dim: int, action_low, action_high, policy: nn.Module,
                 q: nn.Module | None, device, dtype):
        self.settings, self.obs_dim = settings, int(obs_dim)
        self.device, self.dtype = torch.device(device), dtype
        self.low, self.high = _bounds(action_low, action_high, self.device, dtype)
        self.action_dim = self.low.numel()
        self.mid, self.half = (self.high + self.low) / 2, (self.high - self.low) / 2
        hidden = settings.hidden
        self.policy = policy.to(self.device, dtype)
        self.q = (q if q is not None else QFunction(self.obs_dim, self.action_dim, hidden)).to(self.device, dtype)
        self.policy_target, self.q_target = copy.deepcopy(self.policy), copy.deepcopy(self.q)
        for p in (*self.policy_target.parameters(), *self.q_target.parameters()):
            p.requires_grad_(False)
        self._online = [*self.policy.parameters(), *self.q.parameters()]
        self._targets = [*self.policy_target.parameters(), *self.q_target.parameters()]
        self.policy_opt = _adam(self.policy, settings.policy_lr)
        self.q_opt = _adam(self.q, settings.q_lr)
        self.generator = torch.Generator(self.device).manual_seed(settings.seed)
        self.updates, self.env_steps = 0, 0
        self.loads = 0    # load_state_dict calls
        self.compiled = None   # the torch.compile backend of the update's losses (compile_update)

    # -- actions --------------------------------------------------------------------------------
    def squash(self, u: torch.Tensor) -> torch.Tensor:
        """The unbounded policy output ``u`` [..., U] as an action: into the box by tanh, or as is."""
        return self.mid + self.half * torch.tanh(u) if self.settings.squash == "tanh" else u

    def policy_output(self, obs: torch.Tensor) -> torch.Tensor:
        """The policy's unbounded deterministic output ``u`` [B, U] at ``obs`` [B, D] (the action
        without exploration is ``squash(u)``)."""
        raise NotImplementedError

    @torch.no_grad()
    def saturated(self, obs) -> float:
        """The share of action components at ``obs`` [B, D] whose deterministic action sits at the
        box's bounds: tanh of the output beyond 0.99 (its gradient below 0.02), or clipped when the
        output is not squashed. A policy stuck there no longer learns from its gradient."""
        u = self.policy_output(self._obs(obs))
        if self.settings.squash == "tanh":
            return float((torch.tanh(u).abs() > 0.99).float().mean())
        return float(((u <= self.low) | (u >= self.high)).float().mean())

    def _obs(self, obs) -> torch.Tensor:
        obs = torch.as_tensor(obs, device=self.device, dtype=self.dtype)
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim:
            raise ValueError(f"obs has shape {tuple(obs.shape)}; expected [envs, {self.obs_dim}]")
        return obs

    def _random_actions(self, n: int) -> torch.Tensor:
        u = torch.rand(n, self.action_dim, generator=self.generator, device=self.device, dtype=self.dtype)
        return self.low + (self.high - self.low) * u

    def _noise(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, self.action_dim, generator=self.generator, device=self.device, dtype=self.dtype)

    @torch.no_grad()
    def act(self, obs, deterministic: bool = False, count: bool = True, check: bool = True) -> torch.Tensor:
        """Actions [E, U] (in the action box) for observations ``obs`` [E, D]: the policy's mean
        when ``deterministic``; else exploring (uniform random for the first ``start_steps`` env
        steps), counting E env steps (``count`` False: the caller counts them with
        ``count_env_steps`` when it takes them). ``check``: refuse NaN / Inf observations
        (``ValueError`` naming the env; one host sync on CUDA: the training loop, whose replay
        buffer checks what it stores, leaves it off)."""
        obs = self._obs(obs)
        if check:
            bad = ~torch.isfinite(obs)
            if bool(bad.any()):
                e, d = (int(i) for i in bad.nonzero()[0])
                raise ValueError(f"obs of env {e} has NaN or Inf (feature {d}): the policy would act on it")
        if deterministic:
            return self._explore(obs, False)
        n = obs.shape[0]
        a = self._random_actions(n) if self.env_steps < self.settings.start_steps else self._explore(obs, True)
        if count:
            self.count_env_steps(n)
        return a

    def count_env_steps(self, n: int) -> None:
        """Count ``n`` env steps taken (``act`` does, unless told not to)."""
        self.env_steps += int(n)

    # -- learning -------------------------------------------------------------------------------
    def target_action(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        raise NotImplementedError

    def update_noise_shape(self, batch: int) -> tuple[int, ...] | None:
        """The shape of the standard normal noise one update on ``batch`` transitions draws (None:
        it draws none)."""
        return None

    def q_target_values(self, batch: Transitions, noise: torch.Tensor | None = None) -> torch.Tensor:
        """y = r + gamma (1 - terminated) Q'(x', a') [B] (eq. 3): a truncated step bootstraps.
        ``noise`` [B, U]: the target policy's (SVG; None: drawn)."""
        with torch.no_grad():
            a2 = self.target_action(batch.next_obs, noise)
            q2 = self.q_target(batch.next_obs, a2)
            return batch.reward + self.settings.gamma * (~batch.terminated).to(q2.dtype) * q2

    def q_loss(self, batch: Transitions, noise: torch.Tensor | None = None) -> torch.Tensor:
        """Mean squared Bellman error of the online Q on ``batch`` (eq. 3)."""
        return (self.q(batch.obs, batch.action) - self.q_target_values(batch, noise)).pow(2).mean()

    def policy_loss(self, obs: torch.Tensor, noise: torch.Tensor | None = None, ground=None) -> torch.Tensor:
        """The policy's loss at ``obs`` [B, D]; ``noise``: its draws; ``ground``: the replayed
        (action [B, U], next_obs [B, D]) of these observations, for SVG(N)'s ``model_noise``
        "inferred" (None otherwise)."""
        raise NotImplementedError

    def optimizers(self) -> list[torch.optim.Optimizer]:
        """The agent's optimizers (policy, Q and, SVG(N), the model's), those that exist."""
        return [o for o in (self.q_opt, self.policy_opt, getattr(self, "model_opt", None)) if o is not None]

    def _step(self, opt, loss, params) -> None:
        if opt is None:
            return
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        for p, g in zip(params, grads):
            p.grad = g
        if self.settings.max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(params, self.settings.max_grad_norm)
        opt.step()
        opt.zero_grad(set_to_none=True)

    def update(self, batch: Transitions, model_batch: Transitions | None = None,
               noise: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """One gradient step of Q (eq. 3) and of the policy on ``batch`` (transitions [B]), then
        (SVG(N)) of the model on ``model_batch`` (any shape its ``model_loss`` takes, e.g.
        sequences [B, L]; None: ``batch``), then the target networks. ``noise``: the update's
        standard normal draws, of ``update_noise_shape(B)`` (None: drawn from the agent's
        generator). Returns {"q_loss", "policy_loss", "model_loss"...} as 0-dim tensors (no host
        sync)."""
        self._check_batch(batch)
        shape = self.update_noise_shape(len(batch))
        if shape is not None and noise is None:
            noise = self._noise(*shape[:-1])
        elif shape is not None and tuple(noise.shape) != shape:
            raise ValueError(f"noise has shape {tuple(noise.shape)}; expected {shape}")
        metrics = self.update_step(batch, model_batch, noise)
        self.count_update()
        return metrics

    def update_step(self, batch: Transitions, model_batch: Transitions | None,
                    noise: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """The device work of ``update`` (no host sync, no check, the counter untouched): what a
        CUDA graph records (``gnwarp.rl.graphed.Updater``); ``count_update`` follows each."""
        target_noise, policy_noise = (None, None) if noise is None else (noise[0], noise[1:])
        q_loss = self.q_loss(batch, target_noise)
        self._step(self.q_opt, q_loss, self.q_opt.param_groups[0]["params"] if self.q_opt else [])
        ground = (batch.action, batch.next_obs) if self.settings.model_noise == "inferred" else None
        pi_loss = self.policy_update_loss(batch.obs, policy_noise, ground)
        self._step(self.policy_opt, pi_loss, self.policy_opt.param_groups[0]["params"] if self.policy_opt else [])
        metrics = {"q_loss": q_loss.detach(), "policy_loss": pi_loss.detach()}
        metrics.update(self._extra_update(batch if model_batch is None else model_batch))
        if self.settings.target_update == "polyak" and self._online:
            with torch.no_grad():
                torch._foreach_lerp_(self._targets, self._online, 1 - self.settings.polyak)
        return metrics

    def policy_update_loss(self, obs: torch.Tensor, noise: torch.Tensor | None = None, ground=None) -> torch.Tensor:
        """The policy's loss of an update: ``policy_loss`` plus ``squash_penalty`` x the mean
        square of its unbounded output (kept off tanh's flat ends)."""
        loss = self.policy_loss(obs, noise, ground)
        if self.settings.squash_penalty > 0:
            loss = loss + self.settings.squash_penalty * self.policy_output(obs).square().mean()
        return loss

    def compile_update(self, backend: str = "inductor", fallback: bool = False) -> None:
        """Compile the update's losses with ``torch.compile`` (``backend``: "inductor" generates
        fused kernels; "aot_eager" only traces, a check of the tracing): the Q loss, the policy's
        and (SVG(N)) the model's, each a forward and a backward of fewer, larger kernels than the
        eager operations (an update of small MLPs is hundreds of kernels). The first update runs
        eagerly (filling what is made on first use), the second compiles (tens of seconds with
        inductor); a CUDA graph (``Updater``: after both) records the compiled kernels as it records
        eager ones. Floating-point sums may round differently from the eager
        update's. Networks that call Warp kernels (GN) are compiled around them (graph breaks).
        ``fallback``: a compiler's failure warns and leaves the update eager (else it raises)."""
        if backend not in ("inductor", "aot_eager"):
            raise ConfigError("torch_compile", f"a torch.compile backend: inductor or aot_eager, got {backend!r}")
        if self.compiled is not None:
            raise RuntimeError(f"the update's losses are compiled already ({self.compiled})")
        for name in self._compiled_losses():
            setattr(self, name, _EagerFirst(getattr(self, name), backend, fallback))
        self.compiled = backend

    @property
    def compile_used(self) -> str:
        """The backend the update's losses run compiled with: ``compiled``, or "none" where they
        run eagerly (never compiled, or back to eager after a compiler's failure)."""
        if self.compiled is None or any(getattr(getattr(self, n), "fell_back", False) for n in self._compiled_losses()):
            return "none"
        return self.compiled

    def _compiled_losses(self) -> tuple[str, ...]:
        return ("q_loss", "policy_update_loss")

    def count_update(self) -> None:
        """Count an update done by ``update_step``; with hard target updates, copy the networks
        into their targets every ``target_period`` updates."""
        self.updates += 1
        s = self.settings
        if s.target_update == "hard" and self.updates % s.target_period == 0:
            with torch.no_grad():
                for net, tgt in ((self.policy, self.policy_target), (self.q, self.q_target)):
                    tgt.load_state_dict(net.state_dict())

    def _extra_update(self, batch: Transitions) -> dict[str, torch.Tensor]:
        return {}

    def _check_batch(self, batch: Transitions) -> None:
        if batch.obs.ndim != 2 or batch.obs.shape[1] != self.obs_dim or batch.action.shape[-1] != self.action_dim:
            raise ValueError(f"a batch of obs {tuple(batch.obs.shape)} and actions {tuple(batch.action.shape)}; "
                             f"expected [B, {self.obs_dim}] and [B, {self.action_dim}] (single transitions)")

    # -- saving ---------------------------------------------------------------------------------
    def _modules(self) -> dict[str, object]:
        return {"policy": self.policy, "q": self.q, "policy_target": self.policy_target, "q_target": self.q_target,
                "policy_opt": self.policy_opt, "q_opt": self.q_opt}

    def state_dict(self) -> dict:
        """Everything needed to continue bit for bit: networks, targets, optimizers, counters,
        the generator's state and the settings."""
        d = {k: m.state_dict() for k, m in self._modules().items() if m is not None}
        d.update(settings=self.settings.to_dict(), updates=self.updates, env_steps=self.env_steps,
                 generator=self.generator.get_state())
        return d

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()``; one saved with other settings is refused. A state saved on
        another kind of device (a CUDA-trained agent loaded on the CPU) loads too: the optimizers
        take this device's flags, and the generator keeps its seed where the saved state is of
        the other kind (``restore_generator``), so such a load acts the same but does not resume
        the exploration noise bit for bit. Settings saved before a key existed take its default."""
        saved, mine = dict(state["settings"]), self.settings.to_dict()
        unknown = sorted(set(saved) - set(mine))
        if unknown:
            raise ConfigError(unknown[0], f"the saved agent has settings this version does not know ({unknown})")
        saved = {**AgentSettings(**saved).to_dict(), **saved}   # keys added since: their defaults
        if saved != mine:
            diff = sorted(k for k in mine if saved.get(k) != mine[k])
            raise ConfigError(diff[0] if diff else "", f"the saved agent has other settings ({diff})")
        for k, m in self._modules().items():
            if m is not None:
                try:
                    m.load_state_dict(state[k])
                except (RuntimeError, KeyError) as e:   # another network's shapes (networks, task, sizes)
                    detail = str(e).strip().splitlines()
                    raise ConfigError("", f"the saved agent's {k} does not fit this agent's (another networks, task "
                                          f"or sizes: {detail[-1].strip() if detail else type(e).__name__})") from None
        floats = [(f"{k}.{n}", t) for k, m in self._modules().items() if isinstance(m, nn.Module)
                  for n, t in m.state_dict().items() if t.is_floating_point()]
        finite = torch.stack([torch.isfinite(t).all() for _, t in floats]).tolist() if floats else []   # one sync
        bad = next((name for (name, _), ok in zip(floats, finite) if not ok), None)
        if bad is not None:
            raise ValueError(f"the saved agent's {bad} holds NaN or Inf: it diverged or the file was damaged")
        set_adam_mode(self.optimizers(), capturable=False)   # this device's flags; eager steps (an Updater records anew)
        self.updates, self.env_steps = int(state["updates"]), int(state["env_steps"])
        restore_generator(self.generator, state["generator"])
        self.loads += 1   # the optimizers' state tensors are new: a recorded update is stale


class DDPG(Agent):
    """DDPG (F.3.1): deterministic policy ``policy(obs) -> u`` (default: an MLP), action
    ``squash(u)``; exploration adds Gaussian noise of ``action_noise`` x the box's half width."""

    def __init__(self, settings: AgentSettings, obs_dim: int, action_low, action_high, policy=None, q=None,
                 device="cpu", dtype=torch.float32):
        if settings.kind != "ddpg":
            raise ConfigError("agent", f"DDPG got settings of agent {settings.agent!r}")
        low = torch.as_tensor(action_low).reshape(-1)
        policy = policy if policy is not None else DeterministicPolicy(obs_dim, low.numel(), settings.hidden)
        super().__init__(settings, obs_dim, action_low, action_high, policy, q, device, dtype)

    def _explore(self, obs: torch.Tensor, noisy: bool) -> torch.Tensor:
        a = self.squash(self.policy(obs))
        if noisy and self.settings.action_noise > 0:
            a = a + self.settings.action_noise * self.half * self._noise(obs.shape[0])
        return torch.maximum(torch.minimum(a, self.high), self.low)

    def target_action(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """squash(mu'(x)); ``noise`` is unused (DDPG's target policy is deterministic)."""
        return self.squash(self.policy_target(obs))

    def policy_output(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy(obs)

    def policy_loss(self, obs: torch.Tensor, noise: torch.Tensor | None = None, ground=None) -> torch.Tensor:
        """-mean_B Q(x, squash(mu(x))) (eq. 4); ``noise`` and ``ground`` are unused."""
        return -self.q(obs, self.squash(self.policy(obs))).mean()


class SVG(Agent):
    """SVG(N) with a Q-function (F.3.2): a Gaussian policy ``policy(obs) -> (mean, log_std)``
    (default: an MLP), actions ``squash(mean + exp(log_std) eps)``. N = ``settings.horizon``; for
    N >= 1 ``model(obs, action) -> next_obs`` and ``reward(obs, action, next_obs) -> [B]`` must be
    differentiable torch callables on the agent's device and dtype. With ``train_model`` and a
    model with parameters, each update also takes an Adam step of ``model_loss(model, batch)``
    (default ``mse_model_loss``) on the model."""

    def __init__(self, settings: AgentSettings, obs_dim: int, action_low, action_high, model=None,
                 reward: Callable | None = None, policy=None, q=None, model_loss: Callable | None = None,
                 device="cpu", dtype=torch.float32):
        if settings.kind != "svg":
            raise ConfigError("agent", f"SVG got settings of agent {settings.agent!r}")
        self.horizon = settings.horizon
        if self.horizon >= 1 and (model is None or reward is None):
            missing = " and ".join(n for n, v in (("model", model), ("reward", reward)) if v is None)
            raise ConfigError("agent", f"{settings.agent} predicts {self.horizon} steps ahead and needs a "
                                       f"differentiable {missing}: give model(obs, action) -> next_obs and "
                                       "reward(obs, action, next_obs), or use svg0")
        low = torch.as_tensor(action_low).reshape(-1)
        policy = policy if policy is not None else GaussianPolicy(obs_dim, low.numel(), settings.hidden,
                                                                  init_std=settings.init_std)
        super().__init__(settings, obs_dim, action_low, action_high, policy, q, device, dtype)
        self.model, self.reward = (model, reward) if self.horizon >= 1 else (None, None)
        self.model_loss = model_loss or mse_model_loss
        self.model_opt = _adam(self.model, settings.model_lr) if settings.train_model else None

    def _sample(self, net, obs: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        mean, log_std = net(obs)
        return self.squash(mean + log_std.exp() * eps)

    def _explore(self, obs: torch.Tensor, noisy: bool) -> torch.Tensor:
        if not noisy:
            return self.squash(self.policy(obs)[0])
        return torch.maximum(torch.minimum(self._sample(self.policy, obs, self._noise(obs.shape[0])), self.high),
                             self.low)

    def target_action(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """a' ~ pi'(.|x'): the target policy's sample with ``noise`` [B, U] (None: drawn)."""
        return self._sample(self.policy_target, obs, self._noise(obs.shape[0]) if noise is None else noise)

    def update_noise_shape(self, batch: int) -> tuple[int, ...]:
        """[N + 2, B, U]: the target policy's noise, then ``policy_objective``'s N + 1."""
        return (self.horizon + 2, int(batch), self.action_dim)

    def policy_output(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy(obs)[0]

    def policy_objective(self, obs: torch.Tensor, noise: torch.Tensor | None = None, ground=None) -> torch.Tensor:
        """J [B]: sum_{k<N} gamma^k r_k + gamma^N Q(x_N, a_N) from x_0 = ``obs`` [B, D], with
        a_k = squash(mean(x_k) + std(x_k) ``noise[k]``) and x_{k+1} = model(x_k, a_k); ``noise``
        [N + 1, B, U] (None: drawn from the agent's generator). N = 0: Q(x_0, a_0) (eq. 5).
        ``ground`` = (a [B, U], x' [B, D]), the replayed transition from x_0: then
        x_1 = x' + model(x_0, a_0) - model(x_0, a), the model's residual on the replayed
        transition held fixed (its noise inferred from the data, after SVG(1) with replay in
        Heess et al. 2015, here without its policy-noise inference and importance weights): J is
        scored near the states the environment reached, and its gradient still flows through the
        model. Later steps have no data: x_{k+1} = model(x_k, a_k)."""
        n, gamma = self.horizon, self.settings.gamma
        if noise is None:
            noise = self._noise(n + 1, obs.shape[0])
        elif noise.shape != (n + 1, obs.shape[0], self.action_dim):
            raise ValueError(f"noise has shape {tuple(noise.shape)}; expected {(n + 1, obs.shape[0], self.action_dim)}")
        x, total = obs, 0.0
        for k in range(n):
            a = self._sample(self.policy, x, noise[k])
            x2 = self.model(x, a)
            if k == 0 and ground is not None:
                with torch.no_grad():   # the model's residual on the replayed transition, held fixed
                    residual = ground[1] - self.model(x, ground[0])
                x2 = x2 + residual
            total = total + gamma ** k * self.reward(x, a, x2)
            x = x2
        return total + gamma ** n * self.q(x, self._sample(self.policy, x, noise[n]))

    def policy_loss(self, obs: torch.Tensor, noise: torch.Tensor | None = None, ground=None) -> torch.Tensor:
        """-mean_B J (``policy_objective``, ``ground`` as there) - entropy_weight x the policy's
        mean log-std at ``obs``."""
        loss = -self.policy_objective(obs, noise, ground).mean()
        if self.settings.entropy_weight > 0:
            loss = loss - self.settings.entropy_weight * self.policy(obs)[1].sum(-1).mean()
        return loss

    def model_update_loss(self, batch: Transitions) -> torch.Tensor:
        """The model's loss of an update: ``model_loss(model, batch)``."""
        return self.model_loss(self.model, batch)

    def _compiled_losses(self) -> tuple[str, ...]:
        return super()._compiled_losses() + (("model_update_loss",) if self.model_opt is not None else ())

    def _extra_update(self, batch: Transitions) -> dict[str, torch.Tensor]:
        if self.model_opt is None:
            return {}
        loss = self.model_update_loss(batch)
        self._step(self.model_opt, loss, self.model_opt.param_groups[0]["params"])
        return {"model_loss": loss.detach()}

    def _modules(self) -> dict[str, object]:
        d = super()._modules()
        if isinstance(self.model, nn.Module):
            d["model"] = self.model
        if self.model_opt is not None:
            d["model_opt"] = self.model_opt
        return d


def make_agent(settings: AgentSettings, obs_dim: int, action_low, action_high, model=None, reward=None,
               **kwargs) -> Agent:
    """The agent ``settings.agent`` names: ``DDPG`` or ``SVG`` (``model`` and ``reward`` for
    svg<N>, N >= 1). ``kwargs``: ``policy``, ``q``, ``device``, ``dtype`` (and SVG's ``model_loss``)."""
    if settings.kind == "ddpg":
        if kwargs.pop("model_loss", None) is not None:
            raise ConfigError("agent", "ddpg trains no model: model_loss is for svg<N>")
        return DDPG(settings, obs_dim, action_low, action_high, **kwargs)
    return SVG(settings, obs_dim, action_low, action_high, model=model, reward=reward, **kwargs)
