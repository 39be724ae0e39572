"""The data loop's learned terminal value (``LoopConfig.value``): a ``TerminalValue`` fitted by
TD(lambda) on every closed-loop episode the loop has stored, warm-started from the previous
iteration's value, that the next iteration's planner adds at its horizon (``terminal=``).

Files: ``value/iter-<j>.pt`` (``TerminalValue.save``) is the value iteration j plans with,
beside ``models/iter-<j>``: fitted after iteration j-1's training on the episodes of shards
1 .. j-1, starting from ``value/iter-<j-1>.pt`` (iteration 1 plans without one: no closed-loop
episode exists yet). A kill between the training and the fit re-fits from that same previous
file, so no episode is fitted on twice.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gnwarp.control.loop_store import LoopStateError
from gnwarp.validation import ConfigError, FloatRange, PositiveFloat, PositiveInt, Widths, check_fields

__all__ = ["ValueSettings", "value_path", "shard_episodes", "check_value_discount", "load_loop_value",
           "fit_loop_value"]


@dataclass
class ValueSettings:
    """The loop's terminal value. ``hidden``: the MLP's widths. ``gamma``: its discount (None:
    the planner's ``discount``, which must then be < 1); it must equal the planner's
    ``discount``, which weights the value by discount^horizon. ``lam``, ``rounds``, ``steps``,
    ``lr``, ``batch``, ``tau``: ``TerminalValue.fit``'s, each iteration."""
    hidden: Widths = (64, 64)
    gamma: FloatRange(gt=0, lt=1) | None = None
    lam: FloatRange(ge=0, le=1) = 0.9
    rounds: PositiveInt = 20
    steps: PositiveInt = 50
    lr: PositiveFloat = 1e-3
    batch: PositiveInt = 256
    tau: FloatRange(gt=0, le=1) = 1.0

    def __post_init__(self):
        check_fields(self)

    def fit_kw(self) -> dict:
        return {"lam": self.lam, "rounds": self.rounds, "steps": self.steps, "lr": self.lr, "batch": self.batch,
                "tau": self.tau}


def check_value_discount(value: ValueSettings, planner: str, settings) -> float:
    """The value's gamma: ``value.gamma``, else the planner's ``discount`` (``settings``: the
    planner's settings instance). ``ConfigError`` where the planner has no discount (it takes no
    terminal value), where its discount is 1 with no gamma given, or where the two differ."""
    discount = getattr(settings, "discount", None)
    if discount is None:
        raise ConfigError("value", f"planner {planner!r} takes no terminal value; choose gradient, hybrid, sampling "
                                   "or mppi, or leave value unset")
    gamma = value.gamma if value.gamma is not None else float(discount)
    if gamma >= 1.0:
        raise ConfigError("value.gamma", "the value needs a discount < 1: set planner_settings.discount (e.g. 0.99; "
                                         "the value's gamma follows it)")
    if abs(gamma - float(discount)) > 1e-12:
        raise ConfigError("value.gamma", f"is {gamma:g} but planner_settings.discount is {float(discount):g}; they "
                                         "must agree (the planner weights the value by discount^horizon, the value "
                                         "is a gamma-discounted return): set both to the same number")
    return float(gamma)


def value_path(out, j: int) -> Path:
    """The value file iteration ``j`` plans with."""
    return Path(out) / "value" / f"iter-{j:04d}.pt"


def shard_episodes(shard) -> tuple:
    """The whole episodes of a loop shard: (states [N, E+1, B, 13], actions [N, E, U], targets
    [N, ...] or None), its sequences of L steps put back together (sequence j of an episode
    holds steps j*L .. (j+1)*L)."""
    import torch
    meta = shard.meta["loop"]
    E = int(meta["episode_steps"])
    sp = shard["train"]
    L = sp.num_steps
    body, ctrl = np.asarray(sp.body[...]), np.asarray(sp.ctrl[...])
    if E % L or len(body) % (E // L):
        raise ValueError(f"a shard of {len(body)} sequences of {L} steps does not hold whole episodes of {E} steps")
    k = E // L
    n = len(body) // k
    body = body.reshape(n, k, L + 1, *body.shape[2:])
    states = np.concatenate([body[:, :, :L].reshape(n, E, *body.shape[3:]), body[:, -1, L:]], 1)
    actions = ctrl.reshape(n, E, ctrl.shape[-1])
    targets = meta.get("targets")
    return (torch.from_numpy(states), torch.from_numpy(actions),
            None if targets is None else torch.as_tensor(targets, dtype=torch.float32))


def _device(cfg) -> str:
    import torch
    return ("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device


def load_loop_value(cfg, out, j: int, device=None):
    """The value iteration ``j`` plans with (on ``device``, None: the loop's), or None: the loop
    has no value, or ``j`` is 1 (no episode to fit on before it)."""
    if cfg.value is None or j < 2:
        return None
    from gnwarp.control.value import TerminalValue
    return TerminalValue.load(value_path(out, j), device=_device(cfg) if device is None else device)


def _episodes_and_rewards(task, shards) -> tuple:
    from gnwarp.control.value import episode_rewards
    states, rewards = [], []
    for s in shards:
        x, a, tg = shard_episodes(s)
        states.append(x.float())
        rewards.append(episode_rewards(task, x.float(), a, tg).float())
    return states, rewards


def fit_loop_value(cfg, task, system, out, shards, j: int, gamma: float) -> dict:
    """Fit the value iteration ``j`` plans with on every episode of ``shards`` (1 .. j-1), from
    ``value/iter-<j-1>.pt`` where there is one (else a fresh value, seeded), and write
    ``value/iter-<j>.pt``. Returns the record's metrics: its file, the previous value's TD error
    on the newest shard's episodes before the fit (None without one), the TD error before and
    after each round on all episodes, episodes and seconds."""
    import torch

    from gnwarp.control.value import TerminalValue
    t0 = time.perf_counter()
    vs: ValueSettings = cfg.value
    device = _device(cfg)
    prev = value_path(out, j - 1)
    if j > 2:
        if not prev.is_file():
            raise LoopStateError(f"{prev} is missing (the value iteration {j - 1} planned with, which the fit "
                                 "continues from); restore it, or move the loop folder aside to start afresh")
        value = TerminalValue.load(prev, device=device)
        if value.gamma != gamma or value.hidden != tuple(vs.hidden):
            raise ValueError(f"{prev} holds a value of gamma {value.gamma:g}, hidden {list(value.hidden)}; the "
                             f"config asks for gamma {gamma:g}, hidden {list(vs.hidden)}")
    else:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(np.random.default_rng([cfg.seed, j, 3]).integers(1 << 31)))
            value = TerminalValue.for_system(system, hidden=tuple(vs.hidden), gamma=gamma)
        value.to(device)
    states, rewards = _episodes_and_rewards(task, shards)
    new = value.td_error(states[-1], rewards[-1]) if int(value.fitted) else None
    seed = int(np.random.default_rng([cfg.seed, j, 4]).integers(1 << 31))
    hist = value.fit(torch.cat(states), torch.cat(rewards), seed=seed, **vs.fit_kw())
    path = value.save(value_path(out, j))
    return {"file": path.relative_to(out).as_posix(), "td_error_new": new, "td_error": hist["td_error"][-1],
            "td_error_rounds": hist["td_error"], "episodes": int(sum(len(s) for s in states)),
            "seconds": time.perf_counter() - t0}
