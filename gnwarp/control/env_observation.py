"""The observation vector of the vector environments (``gnwarp.control.vector_env``): a fixed
float32 layout made from body states only, so that the true simulator and a learned model give
the same observation for the same states, and a policy trained on one runs on the other.

Layout, per environment, bodies 1 .. B-1 in the model's body order (node 0, the world, dropped),
13 numbers each (``gnwarp.state``: pos x, y, z, quat w, x, y, z, linvel, angvel, world frame):

- a translation-invariant system (``System.translation_invariant``: swimmer, cheetah, walker;
  DMC's cheetah, walker, hopper, swimmer6):
  horizontal positions (x, y) relative to the root body (node 1), whose own x, y are left out,
  so the policy never sees where in the plane the system is (13 (B-1) - 2 numbers);
- any other system: the 13 numbers of every body as they are (13 (B-1) numbers);
- then the task's target, when it has one (``Task.target``): "position" targets [N, 3] as the
  target minus the root body's position (3); "pose" targets [N, >= 7] as their position and
  orientation (7); "poses" targets [N, B, >= 7] as every non-world body's (7 (B-1)); any other
  kind flattened as it is.

Quaternions are kept as the simulator gives them (no sign canonicalization: that would jump
where w crosses 0, e.g. a pendulum hanging down). ``ObservationLayout.names`` names every entry.

    >>> layout = ObservationLayout(systems.make("cheetah"), get_task("cheetah-forward"))
    >>> obs = layout(body)              # body [N, B, 13] -> [N, layout.size] float32
"""
from __future__ import annotations

from typing import Callable

import mujoco
import torch

from gnwarp.state import DYN_NODE_NAMES, DYN_NODE_SIZE

__all__ = ["ObservationLayout"]

TARGET_KINDS = ("position", "pose", "poses")


def _body_name(model: mujoco.MjModel, i: int) -> str:
    return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, i) or f"body{i}"


class ObservationLayout:
    """The observation of ``system`` (a ``System``) for ``task`` (a ``Task``; its ``target``
    kind decides the target's part), or a user's ``custom(body [N, B, 13], target) -> [N, D]``.

    ``layout(body, target=None)`` -> [N, size] float32 on ``body``'s device; ``size``: D;
    ``names``: D entry names (``"<body>.<field>"``, ``"target.<field>"``; ``custom``: ``obs<i>``);
    ``translation_invariant``: whether horizontal positions are relative to the root body."""

    def __init__(self, system, task=None, custom: Callable | None = None):
        if custom is not None and not callable(custom):
            raise TypeError(f"observation must be 'bodies' or a callable (body, target) -> [N, D], "
                            f"got {type(custom).__name__}")
        self.system, self.custom = system, custom
        self.target_kind = getattr(task, "target", None)
        self.translation_invariant = bool(getattr(system, "translation_invariant", False))
        self.nbody = int(system.model.nbody)
        if self.nbody < 2:
            raise ValueError(f"{system.name} has no body besides the world: nothing to observe")
        self.names = self._names() if custom is None else []
        self.size = len(self.names)

    def _names(self) -> list[str]:
        m, out = self.system.model, []
        for b in range(1, self.nbody):
            name = _body_name(m, b)
            skip = ("pos_x", "pos_y") if (b == 1 and self.translation_invariant) else ()
            rel = self.translation_invariant and b > 1
            out += [f"{name}.{'rel_' if rel and f in ('pos_x', 'pos_y') else ''}{f}" for f in DYN_NODE_NAMES
                    if f not in skip]
        kind = self.target_kind
        if kind == "position":
            out += ["target.rel_x", "target.rel_y", "target.rel_z"]
        elif kind == "pose":
            out += [f"target.{f}" for f in DYN_NODE_NAMES[:7]]
        elif kind == "poses":
            out += [f"target.{_body_name(m, b)}.{f}" for b in range(1, self.nbody) for f in DYN_NODE_NAMES[:7]]
        return out   # another kind of target: its entries are named once one is seen (bind_size)

    @property
    def sized(self) -> bool:
        """Whether ``size`` is known without a call: False for a ``custom`` observation or a
        target kind outside ``TARGET_KINDS`` (flattened: sized by ``bind_size``)."""
        return self.custom is None and self.target_kind in (None, *TARGET_KINDS)

    def bind_size(self, body: torch.Tensor, target) -> None:
        """Fix ``size`` and ``names`` from one call on body states [N, B, 13] and targets."""
        if self.sized:
            return
        d = int(self(body, target).shape[1])
        if self.custom is not None:
            self.names = [f"obs{i}" for i in range(d)]
        else:
            base = len(self.names)
            self.names = self.names + [f"target.{i}" for i in range(d - base)]
        self.size = d

    def __call__(self, body: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
        """Observations [N, size] float32 of body states ``body`` [N, B, 13] (and the episodes'
        targets [N, ...] for a task with one)."""
        if body.ndim != 3 or body.shape[1] != self.nbody or body.shape[2] != DYN_NODE_SIZE:
            raise ValueError(f"body states must be [N, {self.nbody}, {DYN_NODE_SIZE}], got {tuple(body.shape)}")
        if self.custom is not None:
            out = torch.as_tensor(self.custom(body, target))
            if out.ndim != 2 or out.shape[0] != body.shape[0]:
                raise ValueError(f"the observation callable must return [N={body.shape[0]}, D], got {tuple(out.shape)}")
            return out.to(body.device, torch.float32)
        x = body[:, 1:].to(torch.float32)                          # the world dropped
        root = x[:, 0, :3]
        if self.translation_invariant:
            rel = x.clone()
            rel[:, :, :2] = x[:, :, :2] - root[:, None, :2]
            parts = [rel[:, 0, 2:], rel[:, 1:].reshape(x.shape[0], -1)]
        else:
            parts = [x.reshape(x.shape[0], -1)]
        if self.target_kind is not None:
            if target is None:
                raise ValueError(f"a task with {self.target_kind!r} targets needs them in the observation")
            t = torch.as_tensor(target).to(body.device, torch.float32)
            if self.target_kind == "position":
                parts.append(t.reshape(t.shape[0], -1)[:, :3] - root)
            elif self.target_kind == "pose":
                parts.append(t.reshape(t.shape[0], -1)[:, :7])
            elif self.target_kind == "poses":
                parts.append(t[:, 1:, :7].reshape(t.shape[0], -1))
            else:
                parts.append(t.reshape(t.shape[0], -1))
        return torch.cat(parts, 1)
