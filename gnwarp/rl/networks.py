"""MLP networks of the agents and the protocols any other network (the observation-graph ones)
follows to take their place:

- a deterministic policy: ``policy(obs [B, D]) -> u [B, U]``, unbounded (the agent squashes it
  into the action box);
- a Gaussian policy: ``policy(obs [B, D]) -> (mean [B, U], log_std [B, U])`` of the unbounded
  action (the agent samples ``mean + exp(log_std) * eps`` and squashes it);
- a Q-function: ``q(obs [B, D], action [B, U]) -> [B]``;
- a model (SVG(N)): ``model(obs [B, D], action [B, U]) -> next_obs [B, D]``, differentiable in both.
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["mlp", "DeterministicPolicy", "GaussianPolicy", "QFunction", "ObservationModel"]


def mlp(inputs: int, hidden: tuple[int, ...], outputs: int) -> nn.Sequential:
    """Linear layers ``inputs -> hidden... -> outputs`` with ReLU between them (none after the last)."""
    widths = (inputs, *hidden, outputs)
    layers: list[nn.Module] = []
    for i in range(len(widths) - 1):
        layers.append(nn.Linear(widths[i], widths[i + 1]))
        if i < len(widths) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class DeterministicPolicy(nn.Module):
    """``obs [B, D] -> u [B, U]``: an MLP of ``hidden`` widths."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...]):
        super().__init__()
        self.net = mlp(obs_dim, hidden, action_dim)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)


class GaussianPolicy(nn.Module):
    """``obs [B, D] -> (mean [B, U], log_std [B, U])``: an MLP of ``hidden`` widths with two heads;
    ``log_std`` squashed smoothly into [``log_std_min``, ``log_std_max``], starting near
    ``log(init_std)``."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...], init_std: float = 0.5,
                 log_std_min: float = -5.0, log_std_max: float = 1.0):
        super().__init__()
        if not log_std_min < torch.log(torch.tensor(init_std)).item() < log_std_max:
            raise ValueError(f"init_std {init_std} lies outside exp([{log_std_min}, {log_std_max}])")
        self.net = mlp(obs_dim, hidden, 2 * action_dim)
        self.lo, self.hi = float(log_std_min), float(log_std_max)
        # the head's bias puts log_std at log(init_std) for a zero last layer output
        t = (2 * (torch.log(torch.tensor(init_std)).item() - self.lo) / (self.hi - self.lo)) - 1
        with torch.no_grad():
            self.net[-1].bias[action_dim:] = torch.atanh(torch.tensor(t))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, raw = self.net(obs).chunk(2, dim=-1)
        log_std = self.lo + 0.5 * (self.hi - self.lo) * (torch.tanh(raw) + 1)
        return mean, log_std


class QFunction(nn.Module):
    """``(obs [B, D], action [B, U]) -> [B]``: an MLP of ``hidden`` widths on their concatenation."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...]):
        super().__init__()
        self.net = mlp(obs_dim + action_dim, hidden, 1)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], dim=-1)).squeeze(-1)


class NormalizedModel(nn.Module):
    """What every observation model shares: buffers ``obs_mean``, ``obs_std`` and ``delta_std``
    [D] (saved with the weights; 0, 1 and 1 until ``normalize_from`` sets them from data), the
    normalized input ``normalized(obs)`` and the next observation ``step(obs, change)`` =
    obs + change x delta_std."""

    def __init__(self, obs_dim: int):
        super().__init__()
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))
        self.register_buffer("delta_std", torch.ones(obs_dim))

    @torch.no_grad()
    def normalize_from(self, obs: torch.Tensor, next_obs: torch.Tensor, min_std: float = 1e-6) -> None:
        """Set ``obs_mean``, ``obs_std`` and ``delta_std`` from transitions obs, next_obs [B >= 2, D]
        (standard deviations at least ``min_std``)."""
        if obs.shape != next_obs.shape or obs.ndim != 2 or obs.shape[1] != self.obs_mean.numel() or obs.shape[0] < 2:
            raise ValueError(f"obs and next_obs must both be [B >= 2, {self.obs_mean.numel()}], "
                             f"got {tuple(obs.shape)} and {tuple(next_obs.shape)}")
        self.obs_mean.copy_(obs.mean(0))
        self.obs_std.copy_(obs.std(0).clamp_min(min_std))
        self.delta_std.copy_((next_obs - obs).std(0).clamp_min(min_std))

    def normalized(self, obs: torch.Tensor) -> torch.Tensor:
        return (obs - self.obs_mean) / self.obs_std

    def step(self, obs: torch.Tensor, change: torch.Tensor) -> torch.Tensor:
        return obs + change * self.delta_std


class ObservationModel(NormalizedModel):
    """A model ``(obs [B, D], action [B, U]) -> next_obs [B, D]``: ``obs`` plus an MLP's change of
    the normalized ``(obs - obs_mean) / obs_std`` and the action, in units of ``delta_std``
    (``NormalizedModel``)."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...]):
        super().__init__(obs_dim)
        self.net = mlp(obs_dim + action_dim, hidden, obs_dim)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.step(obs, self.net(torch.cat([self.normalized(obs), action], -1)))
