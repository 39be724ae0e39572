"""DMC rewards from DMC observations (``gnwarp.rl.observations``): what SVG(N) needs to score the
observations a model predicts, ``reward(obs [B, D], action [B, U], next_obs [B, D]) -> [B]``, the
suite's per-step reward of the state reached (``next_obs``), differentiable in it.

- swimmer6: the suite's reward reads the nose-to-target distance only: |to_target|;
- cheetah, walker: the observation fixes the state up to the horizontal root position (which no
  reward reads): joint coordinates are rebuilt from it (cheetah: qpos[1:] and qvel as they are;
  walker: the root pitch and the joint angles from the bodies' planar orientations, rootz from the
  height), body states from those by forward kinematics (``forward_kinematics``), and the task's
  own per-step reward (``gnwarp.control.get_task(name).scorer``) reads them.

    >>> reward = ObservationReward("swimmer6")
    >>> r = reward(obs, action, next_obs)        # [B]
"""
from __future__ import annotations

import math

import mujoco
import torch

from gnwarp.control.dmc import tolerance
from gnwarp.rl.observations import DMCObservation, JointCoordinates, observation_domain
from gnwarp.rl.planar_fk import planar_chain
from gnwarp.state import quat_mul, quat_rotate

__all__ = ["forward_kinematics", "ObservationReward", "OBSERVATION_REWARD_TASKS"]

# the tasks whose reward is computed from the domain's observation
OBSERVATION_REWARD_TASKS = {"swimmer6": ("dmc-swimmer-swimmer6",), "cheetah": ("dmc-cheetah-run",),
                            "walker": ("dmc-walker-stand", "dmc-walker-walk", "dmc-walker-run")}


def _axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Quaternions [..., 4] of rotations by ``angle`` [...] about unit ``axis`` [3]."""
    h = angle / 2
    return torch.cat([torch.cos(h)[..., None], torch.sin(h)[..., None] * axis], -1)


def forward_kinematics(model: mujoco.MjModel, qpos: torch.Tensor, qvel: torch.Tensor,
                       coords: JointCoordinates | None = None, planar: bool = True) -> torch.Tensor:
    """Body states [..., B, 13] (world first) of a tree of slide and hinge joints at joint
    coordinates qpos [..., nq], qvel [..., nv] (the joints ``JointCoordinates`` reads), composed as
    MuJoCo's kinematics: slides along their axes, then one hinge about its anchor. Differentiable.
    ``coords``: the model's ``JointCoordinates`` to reuse (its constants stay on the device).
    ``planar``: a chain that moves in the x-z plane only (cheetah, walker, hopper) runs as a
    ``PlanarChain`` in float32 / float64 (False: body by body, as any other)."""
    coords = coords if coords is not None else JointCoordinates(model)   # validates the joint structure
    chain = planar_chain(coords) if planar and qpos.dtype in (torch.float32, torch.float64) else None
    if chain is not None:   # the same states in a third of the operations (gnwarp/rl/planar_fk.py)
        return chain(qpos, qvel)
    if qpos.shape[-1] != coords.nq or qvel.shape[-1] != coords.nv or qpos.shape[:-1] != qvel.shape[:-1]:
        raise ValueError(f"qpos [..., {coords.nq}] and qvel [..., {coords.nv}] with the same leading shape expected, "
                     f"got {tuple(qpos.shape)} and {tuple(qvel.shape)}")
    lead = qpos.shape[:-1]
    c3 = lambda v: coords.constant(tuple(v), qpos).expand(*lead, len(v))   # noqa: E731
    zero = qpos.new_zeros(*lead, 3)
    pos, quat = [zero], [c3((1.0, 0.0, 0.0, 0.0))]
    lin, ang = [zero], [zero]
    for b, p, bpos, bquat, slides, hinge in coords.bodies:
        if b != len(pos):
            raise ValueError("bodies must follow their parents in body order")
        xp, qp, vp, wp = pos[p], quat[p], lin[p], ang[p]
        q0 = quat_mul(qp, c3(bquat))
        x = xp + quat_rotate(qp, c3(bpos))
        v = vp
        for qa, da, axis, ref, _ in slides:
            ax = quat_rotate(q0, c3(axis))
            x = x + ax * (qpos[..., qa] - ref)[..., None]
            v = v + ax * qvel[..., da, None]
        v = v + torch.linalg.cross(wp, x - xp, dim=-1)   # the parent's rotation carries the slid point too
        q, w = q0, wp
        if hinge is not None:
            qa, da, axis, ref, hpos = hinge
            anchor = x + quat_rotate(q0, c3(hpos))
            v_anchor = v + torch.linalg.cross(wp, anchor - x, dim=-1)
            q = quat_mul(q0, _axis_angle(coords.constant(tuple(axis), qpos), qpos[..., qa] - ref))
            w = wp + quat_rotate(q0, c3(axis)) * qvel[..., da, None]
            x = anchor - quat_rotate(q, c3(hpos))
            v = v_anchor + torch.linalg.cross(w, x - anchor, dim=-1)
        pos.append(x)
        quat.append(q)
        lin.append(v)
        ang.append(w)
    return torch.cat([torch.stack(pos, -2), torch.stack(quat, -2), torch.stack(lin, -2), torch.stack(ang, -2)], -1)


class ObservationReward:
    """The suite's per-step reward of ``task`` from DMC observations (module docstring):
    ``reward(obs, action, next_obs) -> [B]`` (``obs`` unused: the suite scores the state reached;
    ``action`` [B, U] may be None: these rewards do not read it).

    ``task``: a task name of ``OBSERVATION_REWARD_TASKS`` (``"swimmer6"``, ``"cheetah-run"``,
    ``"walker-walk"``, ...); ``observation``: its ``DMCObservation`` (built when omitted);
    ``planar``: ``forward_kinematics``' (False: body by body, e.g. to compare)."""

    def __init__(self, task: str, observation: DMCObservation | None = None, planar: bool = True):
        from gnwarp.control.tasks import get_task
        self.task = get_task(task)
        self.domain = observation_domain(self.task.name)
        if self.task.name not in OBSERVATION_REWARD_TASKS[self.domain]:
            raise ValueError(f"no observation reward for task {self.task.name!r}: one of "
                             f"{', '.join(t for ts in OBSERVATION_REWARD_TASKS.values() for t in ts)}")
        self.observation = observation if observation is not None else DMCObservation(self.domain)
        if self.observation.domain != self.domain:
            raise ValueError(f"task {self.task.name!r} needs the {self.domain} observation, "
                             f"got {self.observation.domain}")
        ob = self.observation
        m = ob.model
        self.model, self.planar = m, bool(planar)
        if self.domain == "swimmer6":
            t = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "target")
            self.target_size = float(m.geom_size[t, 0])
            return
        self.step = getattr(self.task.scorer, "step", None)
        if self.step is None:
            raise ValueError(f"task {self.task.name!r} has no per-step reward")
        if self.domain == "walker":
            hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
            # each body's pitch about world y (planar): hinge angle = (child - parent) pitch along its axis
            self.root_pitch = [j for j in range(m.njnt) if m.jnt_bodyid[j] == 1 and m.jnt_type[j] == hinge]
            self.limb_joints = [j for j in range(m.njnt) if m.jnt_bodyid[j] != 1]
            for j in self.root_pitch + self.limb_joints:
                if m.jnt_type[j] != hinge or abs(abs(float(m.jnt_axis[j, 1])) - 1) > 1e-12:
                    raise ValueError("the walker observation's joints must be hinges about y")
            self.height_offset = float(m.body_pos[1, 2])
            self.rootz = [j for j in range(m.njnt) if m.jnt_bodyid[j] == 1 and m.jnt_type[j] != hinge
                          and abs(float(m.jnt_axis[j, 2]) - 1) < 1e-12]
            # the same as index lists, for ``joints`` in a few operations: a hinge's pitch difference
            # (its body's - its parent's; columns of the pitch with the world's 0 in front, so body b
            # is column b and the root's parent, the world, column 0) along its axis, then rootz
            hinges = self.root_pitch + self.limb_joints
            self._child = [int(m.jnt_bodyid[j]) for j in hinges]
            self._parent = [int(m.body_parentid[b]) for b in self._child]
            self._axis = [float(m.jnt_axis[j, 1]) for j in hinges]
            set_ = [int(m.jnt_qposadr[j]) for j in hinges + self.rootz]
            rest = [a for a in range(m.nq) if a not in set_]     # rootx: 0
            self._qpos_order = [(set_ + rest).index(a) for a in range(m.nq)]
            self._consts: dict = {}

    def __deepcopy__(self, memo):
        # a fixed description of the model (its MjSpec does not copy): copies of networks share it
        return self

    def __repr__(self) -> str:
        return f"ObservationReward({self.task.name!r})"

    def joints(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(qpos [..., nq], qvel [..., nv]) rebuilt from observations [..., D] (cheetah, walker),
        the horizontal root position 0."""
        ob, m = self.observation, self.model
        if self.domain == "cheetah":
            pos, vel = obs[..., ob.parts["position"]], obs[..., ob.parts["velocity"]]
            return torch.cat([pos.new_zeros(*pos.shape[:-1], 1), pos], -1), vel
        if self.domain != "walker":
            raise ValueError(f"{self.domain}: joint coordinates are not rebuilt from its observation")
        orient = obs[..., ob.parts["orientations"]].reshape(*obs.shape[:-1], -1, 2)
        pitch = torch.atan2(orient[..., 1], orient[..., 0])                   # [..., B-1] about world y
        c = self._walker_constants(obs)
        pitch = torch.cat([pitch.new_zeros(*pitch.shape[:-1], 1), pitch], -1)   # column b: body b's
        rel = pitch.index_select(-1, c["child"]) - pitch.index_select(-1, c["parent"])
        rel = rel - (2 * math.pi) * torch.round(rel / (2 * math.pi))
        z = obs[..., ob.parts["height"]][..., :1].expand(*obs.shape[:-1], len(self.rootz)) - self.height_offset
        rest = obs.new_zeros(*obs.shape[:-1], m.nq - len(self._axis) - len(self.rootz))
        qpos = torch.cat([rel * c["axis"], z, rest], -1).index_select(-1, c["order"])
        return qpos, obs[..., ob.parts["velocity"]]

    def _walker_constants(self, like: torch.Tensor) -> dict:
        key = (like.device, like.dtype)
        c = self._consts.get(key)
        if c is None:
            index = lambda v: torch.tensor(v, dtype=torch.long, device=like.device)   # noqa: E731
            c = self._consts[key] = dict(child=index(self._child), parent=index(self._parent),
                                         axis=torch.tensor(self._axis, dtype=like.dtype, device=like.device),
                                         order=index(self._qpos_order))
        return c

    def __call__(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        ob = self.observation
        if next_obs.ndim != 2 or next_obs.shape[1] != ob.size:
            raise ValueError(f"{self.domain} observations must be [B, {ob.size}], got {tuple(next_obs.shape)}")
        if self.domain == "swimmer6":
            d = next_obs[:, ob.parts["to_target"]]
            sq = (d * d).sum(-1)
            # |d| with a finite gradient at 0
            dist = torch.where(sq > 0, torch.where(sq > 0, sq, torch.ones_like(sq)).sqrt(), torch.zeros_like(sq))
            return tolerance(dist, bounds=(0, self.target_size), margin=5 * self.target_size, sigmoid="long_tail")
        qpos, qvel = self.joints(next_obs)
        body = forward_kinematics(self.model, qpos, qvel, ob.coords, planar=self.planar)
        a = action if action is not None else next_obs.new_zeros(next_obs.shape[0], self.model.nu)
        return self.step(body[:, None], a[:, None], None)[:, 0]
