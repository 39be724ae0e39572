"""A learned terminal value: the return to expect after a planner's horizon, from the last
planned state, fitted on closed-loop trajectories by TD(lambda) with a target network.

``TerminalValue`` is a small MLP on body-state features: the bodies' 13 numbers (the world
node dropped), quaternions sign-fixed (w >= 0), and, for systems whose reward does not depend on
where they are along some axes (cheetah, walker, hopper: x; swimmer: x and y), positions on those
axes taken relative to the root body (node 1), so the value generalizes along them. Features are
standardized by statistics of the first data it is fitted on; the network predicts the value
divided by a fixed scale (mean |reward| / (1 - gamma)).

``fit(states [E, T+1, B, 13], rewards [E, T])``: for ``rounds`` rounds, the target network (a
copy of the value, refreshed each round with weight ``tau``) gives V'(s_t); the lambda-returns
G_t = r_t + gamma ((1 - lambda) V'(s_{t+1}) + lambda G_{t+1}), bootstrapped at the last state
(episodes end by time limit, never by termination), are regressed by ``steps`` Adam steps on
minibatches. Rewards are the task's per-step rewards (``episode_rewards``: what the planner
optimizes, ``Task.reward``).

A planner takes it as ``terminal=``: ``GradientMPC``, ``SamplingPlanner`` and ``HybridPlanner``
add discount^H x value(states[:, H]) to each rollout's return (``returns.planned_return``);
``terminal=None`` is the ablation. Values do not read per-episode targets (swimmer-reach's and
JACO's targets are not features).

    >>> value = TerminalValue.for_system(system)
    >>> out = run_episodes(planner, env, task, steps=1000, qpos0=q, qvel0=v)
    >>> fit_terminal_value([out], task, value)              # {"td_error": [...], ...}
    >>> value.save("value.pt"); value = TerminalValue.load("value.pt")
    >>> planner = GradientMPC(model, task, system, n, terminal=value)
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import torch

from gnwarp.control.returns import step_rewards
from gnwarp.files import atomic_write, tensor_digest
from gnwarp.sim.systems import translation_axes
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["TerminalValue", "ValueFileError", "episode_rewards", "fit_terminal_value", "default_recentre",
           "VALUE_FORMAT", "VALUE_VERSION"]

VALUE_FORMAT, VALUE_VERSION = "gnwarp-terminal-value", 1


class ValueFileError(ValueError):
    """A terminal-value file that is not one, or whose contents do not fit; the message says how."""


def default_recentre(system) -> tuple[int, ...]:
    """Axes on which ``system`` (a ``System``, or a built-in or DMC system's name) is
    translation-invariant, recentred on the root body: its ``translation_axes``."""
    if isinstance(system, str):
        return translation_axes(system)
    return tuple(system.translation_axes)


def _check_config(nbody, hidden, recentre, gamma) -> tuple[int, tuple[int, ...], tuple[int, ...], float]:
    if isinstance(nbody, bool) or not isinstance(nbody, (int, np.integer)) or nbody < 2:
        raise ValueError(f"nbody must be an integer >= 2 (the world and at least one body), got {nbody!r}")
    hidden = tuple(hidden)
    if not hidden or any(isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1 for h in hidden):
        raise ValueError(f"hidden must be a non-empty sequence of integers >= 1, got {hidden!r}")
    recentre = tuple(recentre)
    if any(a not in (0, 1, 2) for a in recentre) or len(set(recentre)) != len(recentre):
        raise ValueError(f"recentre must hold distinct axes among 0, 1, 2, got {recentre!r}")
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not 0.0 < gamma < 1.0:
        raise ValueError(f"gamma must be a number in (0, 1), got {gamma!r}")
    return int(nbody), tuple(int(h) for h in hidden), tuple(int(a) for a in recentre), float(gamma)


class TerminalValue(torch.nn.Module):
    """V(body states [M, B, 13]) -> [M] (see the module's docstring). ``nbody``: B (the world
    included); ``hidden``: the MLP's widths; ``recentre``: translation-invariant axes;
    ``gamma``: the discount the value is fitted with."""

    def __init__(self, nbody: int, hidden=(64, 64), recentre=(), gamma: float = 0.99):
        super().__init__()
        self.nbody, self.hidden, self.recentre, self.gamma = _check_config(nbody, hidden, recentre, gamma)
        width = (self.nbody - 1) * DYN_NODE_SIZE
        layers, last = [], width
        for h in self.hidden:
            layers += [torch.nn.Linear(last, h), torch.nn.ELU()]
            last = h
        layers.append(torch.nn.Linear(last, 1))
        self.net = torch.nn.Sequential(*layers)
        self.register_buffer("mean", torch.zeros(width))
        self.register_buffer("std", torch.ones(width))
        self.register_buffer("scale", torch.ones(()))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.int64))
        mask = torch.zeros(DYN_NODE_SIZE)
        mask[list(self.recentre)] = 1.0
        self.register_buffer("recentre_mask", mask, persistent=False)   # position axes taken relative to node 1

    @classmethod
    def for_system(cls, system, **kw) -> "TerminalValue":
        """A value for ``system`` (a ``System``): its body count and translation-invariant axes."""
        kw.setdefault("recentre", default_recentre(system))
        return cls(system.nbody, **kw)

    def config(self) -> dict:
        return {"nbody": self.nbody, "hidden": list(self.hidden), "recentre": list(self.recentre),
                "gamma": self.gamma}

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """[M, (B-1) x 13] raw features of body states ``x`` [M, B, 13] (differentiable)."""
        if x.ndim != 3 or x.shape[1:] != (self.nbody, DYN_NODE_SIZE):
            raise ValueError(f"states must be [M, {self.nbody}, {DYN_NODE_SIZE}], got {list(x.shape)}")
        b = x[:, 1:]
        if self.recentre:
            b = b - b[:, :1] * self.recentre_mask.to(b.dtype)
        sign = torch.where(b[..., 3:4] < 0, -1.0, 1.0).to(b.dtype)
        b = torch.cat([b[..., :3], b[..., 3:7] * sign, b[..., 7:]], -1)
        return b.reshape(b.shape[0], -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[M] values of body states ``x`` [M, B, 13], in ``x``'s dtype and device
        (differentiable with respect to ``x``)."""
        p = self.mean
        f = (self.features(x.to(p.device, p.dtype)) - self.mean) / self.std
        return (self.net(f)[:, 0] * self.scale).to(x.device, x.dtype)

    # -- fitting --------------------------------------------------------------------------------
    def _check_data(self, states, rewards) -> tuple[torch.Tensor, torch.Tensor]:
        p = self.mean
        s, r = torch.as_tensor(states).to(p.device, p.dtype), torch.as_tensor(rewards).to(p.device, p.dtype)
        if s.ndim != 4 or s.shape[2:] != (self.nbody, DYN_NODE_SIZE) or r.shape != (s.shape[0], s.shape[1] - 1) \
                or r.shape[1] < 1:
            raise ValueError(f"states must be [E, T+1, {self.nbody}, 13] and rewards [E, T] (T >= 1), got "
                             f"{list(s.shape)} and {list(r.shape)}")
        if not (bool(torch.isfinite(s).all()) and bool(torch.isfinite(r).all())):
            raise ValueError("states and rewards must be finite (a diverged episode in the data?)")
        return s, r

    def td_error(self, states, rewards) -> float:
        """Mean squared one-step TD error r_t + gamma V(s_{t+1}) - V(s_t) of the value on
        trajectories ``states`` [E, T+1, B, 13] with ``rewards`` [E, T]."""
        s, r = self._check_data(states, rewards)
        with torch.no_grad():
            v = self(s.reshape(-1, *s.shape[2:])).reshape(s.shape[:2])
            return float((r + self.gamma * v[:, 1:] - v[:, :-1]).square().mean())

    def lambda_returns(self, values: torch.Tensor, rewards: torch.Tensor, lam: float) -> torch.Tensor:
        """[E, T] TD(lambda) targets of ``rewards`` [E, T] with bootstrap ``values`` [E, T+1]."""
        g = values[:, -1]
        out = []
        for t in range(rewards.shape[1] - 1, -1, -1):
            g = rewards[:, t] + self.gamma * ((1 - lam) * values[:, t + 1] + lam * g)
            out.append(g)
        return torch.stack(out[::-1], 1)

    def fit(self, states, rewards, *, lam: float = 0.9, rounds: int = 20, steps: int = 50, lr: float = 1e-3,
            batch: int = 256, tau: float = 1.0, seed: int = 0) -> dict:
        """Fit on trajectories ``states`` [E, T+1, B, 13] with per-step ``rewards`` [E, T] (see the
        module's docstring); the first fit also sets the feature statistics and the scale.
        Returns {"td_error": [before, after each round], "loss": [last minibatch loss per round]}."""
        if not 0.0 <= lam <= 1.0 or not 0.0 < tau <= 1.0:
            raise ValueError(f"lam must be in [0, 1] and tau in (0, 1], got lam={lam!r}, tau={tau!r}")
        if min(rounds, steps, batch) < 1:
            raise ValueError(f"rounds, steps and batch must be >= 1, got {rounds}, {steps}, {batch}")
        s, r = self._check_data(states, rewards)
        flat = s.reshape(-1, *s.shape[2:])
        if not int(self.fitted):
            f = self.features(flat)
            self.mean.copy_(f.mean(0))
            self.std.copy_(f.std(0, unbiased=False).clamp_min(1e-3))
            self.scale.fill_(max(float(r.abs().mean()), 1e-6) / (1 - self.gamma))
            self.fitted.fill_(1)
        target = copy.deepcopy(self).requires_grad_(False)
        opt = torch.optim.Adam(self.net.parameters(), lr=lr)
        gen = torch.Generator(device="cpu").manual_seed(int(seed))
        x = s[:, :-1].reshape(-1, *s.shape[2:])
        hist = {"td_error": [self.td_error(s, r)], "loss": []}
        for _ in range(rounds):
            with torch.no_grad():
                v = target(flat).reshape(s.shape[:2])
                g = self.lambda_returns(v, r, lam).reshape(-1)
            for _ in range(steps):
                idx = torch.randint(0, x.shape[0], (min(batch, x.shape[0]),), generator=gen).to(x.device)
                loss = ((self(x[idx]) - g[idx]) / self.scale).square().mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
            with torch.no_grad():
                for pt, p in zip(target.net.parameters(), self.net.parameters()):
                    pt.lerp_(p, tau)
            hist["td_error"].append(self.td_error(s, r))
            hist["loss"].append(float(loss.detach()))
        return hist

    # -- files ----------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the value (config and state_dict) to ``path``, atomically; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        sd = {k: v.detach().cpu() for k, v in self.state_dict().items()}
        blob = {"format": VALUE_FORMAT, "version": VALUE_VERSION, "config": self.config(), "state_dict": sd,
                "sha256": tensor_digest(sd)}
        with atomic_write(path) as tmp:
            torch.save(blob, tmp)
        return path

    @classmethod
    def load(cls, path, device=None) -> "TerminalValue":
        """The value saved at ``path`` (read with ``weights_only``: tensors and plain values only),
        on ``device``; ``ValueFileError`` naming what is wrong with the file."""
        path = Path(path)
        if not path.is_file():
            raise ValueFileError(f"no terminal-value file at {path}")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:   # pickle, zip or torch's weights-only refusal: all mean the file is not ours
            msg = f"{path} is not a readable terminal-value file: {type(e).__name__}: {e}"
            raise ValueFileError(msg[:500]) from None
        if not isinstance(blob, dict) or blob.get("format") != VALUE_FORMAT:
            raise ValueFileError(f"{path} is not a terminal-value file (format {VALUE_FORMAT!r} expected)")
        if blob.get("version") != VALUE_VERSION:
            raise ValueFileError(f"{path} is a terminal-value file of version {blob.get('version')!r}; this gnwarp "
                                 f"reads version {VALUE_VERSION}")
        cfg, sd = blob.get("config"), blob.get("state_dict")
        if not isinstance(cfg, dict) or set(cfg) != {"nbody", "hidden", "recentre", "gamma"}:
            raise ValueFileError(f"{path}: config must hold nbody, hidden, recentre and gamma, got {cfg!r}"[:400])
        try:
            value = cls(**cfg)
        except (TypeError, ValueError) as e:
            raise ValueFileError(f"{path}: bad config: {e}") from None
        want = value.state_dict()
        if not isinstance(sd, dict) or set(sd) != set(want):
            got = sorted(sd) if isinstance(sd, dict) else type(sd).__name__
            raise ValueFileError(f"{path}: state_dict keys {got} do not match the value's {sorted(want)}")
        for k, v in sd.items():
            if not torch.is_tensor(v) or v.shape != want[k].shape or v.dtype != want[k].dtype:
                raise ValueFileError(f"{path}: state_dict[{k!r}] must be a {want[k].dtype} tensor of shape "
                                     f"{list(want[k].shape)}, got {getattr(v, 'dtype', type(v).__name__)} "
                                     f"{list(getattr(v, 'shape', []))}")
            if v.is_floating_point() and not bool(torch.isfinite(v).all()):
                raise ValueFileError(f"{path}: state_dict[{k!r}] has NaN or Inf")
        digest = blob.get("sha256")   # (files written before it had one: none to compare)
        if digest is not None and digest != tensor_digest(sd):
            raise ValueFileError(f"{path}: its weights were changed or damaged (their SHA-256 does not match)")
        value.load_state_dict(sd)
        return value.to(device) if device is not None else value


def episode_rewards(task, states, actions, targets=None) -> torch.Tensor:
    """[E, T] per-step rewards (``Task.reward``, what planners optimize) of trajectories
    ``states`` [E, T+1, B, 13] under ``actions`` [E, T, U] (``run_episodes``' outputs)."""
    from gnwarp.control.tasks import get_task
    task = get_task(task)
    s, a = torch.as_tensor(states), torch.as_tensor(actions)
    with torch.no_grad():
        return step_rewards(task.reward, s, a.to(s.dtype), None if targets is None else torch.as_tensor(targets).to(s))


def fit_terminal_value(episodes, task, value: TerminalValue, targets=None, **fit_kw) -> dict:
    """Fit ``value`` on closed-loop ``episodes``: a ``run_episodes`` output ({"states", "actions"})
    or a list of them (their episodes concatenated; ``targets`` then a list too, or None), scored
    per step by ``task``'s reward. ``fit_kw``: ``TerminalValue.fit``'s. Returns its history."""
    outs = [episodes] if isinstance(episodes, dict) else list(episodes)
    tg = targets if isinstance(targets, (list, tuple)) else [targets] * len(outs)
    if len(tg) != len(outs):
        raise ValueError(f"{len(tg)} targets for {len(outs)} episode batches")
    states, rewards = [], []
    for out, t in zip(outs, tg):
        if not isinstance(out, dict) or "states" not in out or "actions" not in out:
            raise ValueError("episodes must be run_episodes outputs (dicts with 'states' and 'actions')")
        states.append(torch.as_tensor(out["states"]).float())
        rewards.append(episode_rewards(task, states[-1], out["actions"], t).float())
    lengths = {s.shape[1] for s in states}
    if len(lengths) != 1:
        raise ValueError(f"episode batches of different lengths {sorted(lengths)}: fit them separately")
    return value.fit(torch.cat(states), torch.cat(rewards), **fit_kw)
