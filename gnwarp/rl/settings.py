"""The agents' settings (``AgentSettings``): which agent ("ddpg", "svg0", "svg<N>"), a preset of
the values the source leaves to choose ("paper", "spinningup"), and every value checked on
construction (``ConfigError`` naming the key and the allowed values)."""
from __future__ import annotations

import dataclasses
import re
from typing import Literal

from gnwarp.validation import (BatchSize, ConfigError, Count, Flag, FloatRange, PositiveFloat, PositiveInt, Widths,
                               check_fields)

__all__ = ["AgentSettings", "PRESETS", "MAX_HORIZON", "agent_names", "settings_tag"]

MAX_HORIZON = 50   # longest SVG(N) model rollout accepted

# values a preset fills where the settings leave None: "paper" copies the target networks every
# 1000 gradient steps (F.3.1) and takes the rest, which the paper does not give, from "spinningup"
# (SpinningUp's DDPG: Polyak 0.995, 256x2 MLPs, batch 100, 10k random start steps)
PRESETS: dict[str, dict] = {
    "spinningup": dict(target_update="polyak", hidden=(256, 256), batch_size=100, start_steps=10_000),
    "paper": dict(target_update="hard", hidden=(256, 256), batch_size=100, start_steps=10_000),
}


def agent_names() -> str:
    return "ddpg, svg0 (model-free SVG), svg<N> for N = 1 .. " + str(MAX_HORIZON) + " (SVG(N) through a model)"


@dataclasses.dataclass
class AgentSettings:
    """``agent``: "ddpg" (deterministic policy, F.3.1), "svg0" (Gaussian policy, reparameterized
    gradient of Q, eq. 5) or "svg<N>" (the gradient of N model steps' discounted rewards plus the
    discounted Q at the last predicted state, N >= 1). ``preset``: "spinningup" or "paper"; fills
    the keys left None. ``gamma``: the discount. ``hidden``: widths of the MLP policy and Q (None:
    the preset's). ``batch_size``: transitions per update (None: the preset's). ``start_steps``:
    env steps of uniform random actions before the policy acts (None: the preset's).
    ``update_after``: env steps before the first update (for the training loop). ``updates_per_step``:
    gradient updates per env step (for the training loop). ``act_ahead`` (for the training loop):
    pick each step's action before the previous step's updates rather than after them (the
    policy acts one step's updates behind), so that with the agent on CUDA a CPU simulator steps
    while the GPU updates; False: strictly in turn. ``target_update``: "hard" (copy every
    ``target_period`` updates) or "polyak" (``target <- polyak * target + (1 - polyak) * online``
    after every update); None: the preset's. ``policy_lr``, ``q_lr``, ``model_lr``: Adam's step
    sizes. ``action_noise``: DDPG's Gaussian exploration noise, a fraction of the action box's
    half width. ``init_std``: the Gaussian policy's initial standard deviation (of the unbounded
    action). ``entropy_weight``: weight of the Gaussian policy's mean log-std added to its
    objective (0: the plain value gradient). ``squash_penalty``: weight of the mean square of the
    policy's unbounded output (before tanh) added to its loss: it keeps the deterministic action off
    tanh's flat ends, where the value gradient vanishes and Adam's normalized steps push further (0:
    none). ``squash``: "tanh" maps the policy's unbounded output
    into the action box; "none" takes it as the action (clamped to the box only when acting).
    ``train_model``: SVG(N) trains its model jointly on the replayed transitions (when it has
    parameters). ``model_noise`` (SVG(N), N >= 1): "none", the predicted states as the model gives
    them (the paper's); "inferred", the first predicted state is the replayed next state moved by
    the model's change from the replayed action to the policy's (``SVG.policy_objective``). ``max_grad_norm``: each network's gradient norm is clipped to it before its Adam
    step (None: not clipped). ``seed``: of the agent's generator (random actions, exploration and policy noise)."""
    agent: str = "ddpg"
    preset: Literal["spinningup", "paper"] = "spinningup"
    gamma: FloatRange(ge=0, le=1) = 0.99
    hidden: Widths | None = None
    batch_size: BatchSize | None = None
    start_steps: Count | None = None
    update_after: Count = 1000
    updates_per_step: FloatRange(gt=0) = 1.0
    act_ahead: Flag = False
    target_update: Literal["hard", "polyak"] | None = None
    target_period: PositiveInt = 1000
    polyak: FloatRange(ge=0, le=1) = 0.995
    policy_lr: PositiveFloat = 1e-3
    q_lr: PositiveFloat = 1e-3
    model_lr: PositiveFloat = 1e-3
    action_noise: FloatRange(ge=0) = 0.1
    init_std: FloatRange(gt=0.0068, lt=2.7) = 0.5
    entropy_weight: FloatRange(ge=0) = 0.0
    squash_penalty: FloatRange(ge=0) = 0.0
    squash: Literal["tanh", "none"] = "tanh"
    train_model: Flag = True
    model_noise: Literal["none", "inferred"] = "none"
    max_grad_norm: PositiveFloat | None = None
    seed: Count = 0

    def __post_init__(self):
        if not isinstance(self.agent, str):
            raise ConfigError("agent", f"must be a string naming the agent ({agent_names()}), got {self.agent!r}")
        name = self.agent.strip().lower()
        m = re.fullmatch(r"svg\(?(-?\d+)\)?", name)
        if name != "ddpg" and m is None:
            raise ConfigError("agent", f"unknown agent {self.agent!r} (known: {agent_names()})")
        if m is not None:
            n = int(m.group(1))
            if n < 0 or n > MAX_HORIZON:
                raise ConfigError("agent", f"SVG(N) needs a model horizon N from 1 to {MAX_HORIZON} "
                                           f"(svg0: the model-free agent), got N = {n}")
            name = f"svg{n}"
        self.agent = name
        check_fields(self)
        if self.model_noise != "none" and self.horizon < 1:
            raise ConfigError("model_noise", f"{self.model_noise!r} moves SVG(N)'s predicted states: {self.agent} "
                                             "predicts none (svg1 .. svg<N>)")
        for key, value in PRESETS[self.preset].items():
            if getattr(self, key) is None:
                setattr(self, key, value)

    @property
    def kind(self) -> str:
        """"ddpg" or "svg"."""
        return "ddpg" if self.agent == "ddpg" else "svg"

    @property
    def horizon(self) -> int:
        """SVG(N)'s N (0 for svg0 and ddpg)."""
        return 0 if self.agent == "ddpg" else int(self.agent[3:])

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# keys a run's name and its results' grouping carry on their own (or that are not a variant)
_UNTAGGED = ("agent", "preset", "seed", "act_ahead", "updates_per_step")


def _text(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def settings_tag(settings: dict, strict: bool = True) -> str:
    """The agent settings of ``settings`` (an ``AgentSettings``' dict, whole or only the keys set;
    ``agent`` and ``preset`` included) that differ from that agent's and preset's defaults, as
    ``key=value`` joined by commas, sorted ("" for none): the variant that a run's name and its
    learning curve carry. Its seed, ``act_ahead`` and ``updates_per_step`` are not part of it.
    ``strict``: an unknown key (or agent, or preset) raises ``ConfigError``; else (records of
    another version) such a key is tagged as it is."""
    agent, preset = settings.get("agent", "ddpg"), settings.get("preset", "spinningup")
    try:
        default = AgentSettings(agent=agent, preset=preset).to_dict()
    except ConfigError:
        if strict:
            raise
        default = {}
    out = []
    for key in sorted(set(settings) - set(_UNTAGGED)):
        if key not in default and strict:
            raise ConfigError(key, "unknown agent setting")
        value = settings[key]
        value = tuple(value) if isinstance(value, list) else value
        if value is None or value == default.get(key, object()):
            continue
        text = "x".join(map(_text, value)) if isinstance(value, tuple) else _text(value)
        out.append(f"{key}={text}")
    return ",".join(out)
