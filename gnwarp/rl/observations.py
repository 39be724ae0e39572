"""The DeepMind Control Suite's own observations of swimmer6, cheetah and walker, computed from
body states [..., B, 13] (``gnwarp.state``) and the model's constants, so that the true simulator
and a learned model (which gives body states only) observe alike.

- ``joint_coordinates``: qpos [..., nq] and qvel [..., nv] of a tree of slide and hinge joints from
  body states: each body's pose relative to its parent's frame (``body_pos``, ``body_quat``)
  undone joint by joint as MuJoCo's kinematics composes it (slides along their axes, then at most
  one hinge about its anchor). Hinge angles come out in (-pi, pi]: a limited hinge equals its qpos,
  an unlimited one (a planar root's pitch) equals it up to a multiple of 2 pi.
- ``DMCObservation(name)``: a callable ``(body [..., B, 13], target=None) -> [..., D]`` in
  ``body``'s dtype, the suite's ``get_observation`` entries flattened in its dict order:

  ================ ===== =================================================================
  domain           D     entries
  ================ ===== =================================================================
  swimmer6         25    joints (5 hinge angles), to_target (2: target minus nose in the
                         head's frame, x y), body_velocities (6 x (vx, vy, wz): each link's
                         velocity in its own frame, head first)
  cheetah          17    position (qpos[1:]: rootz, rooty, 6 joint angles), velocity (qvel, 9)
  walker           24    orientations (7 x (xx, xz) of each body's rotation matrix), height
                         (torso z), velocity (qvel, 9)
  ================ ===== =================================================================

  Swimmer6 needs the episode's target [N, 2 or 3] (``sample_targets``); ``names`` names every
  entry, ``parts`` maps each dict key to its slice. Pass it as the vector environment's
  ``observation=`` to train on the suite's observation.

    >>> obs = DMCObservation("swimmer6")
    >>> env = make_vector_env("swimmer6", 16, observation=obs)      # obs [16, 25] float32
"""
from __future__ import annotations

import math

import mujoco
import torch

from gnwarp.state import ANGVEL, DYN_NODE_SIZE, LINVEL, POS, QUAT, quat_conj, quat_mul, quat_normalize, quat_rotate

__all__ = ["JointCoordinates", "joint_coordinates", "DMCObservation", "DMC_OBSERVATIONS", "observation_domain", "wrap_angle"]

# the suite's observation of each domain, and the systems / tasks that name it
DMC_OBSERVATIONS = {"swimmer6": "dmc-swimmer6", "cheetah": "dmc-cheetah", "walker": "dmc-walker"}
_ALIASES = {"dmc-swimmer6": "swimmer6", "dmc-swimmer-swimmer6": "swimmer6", "swimmer6": "swimmer6",
            "dmc-cheetah": "cheetah", "cheetah-run": "cheetah", "dmc-cheetah-run": "cheetah", "cheetah": "cheetah",
            "dmc-walker": "walker", "walker": "walker"}
_SLIDE, _HINGE = int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE)


def observation_domain(name) -> str:
    """The DMC observation ("swimmer6", "cheetah", "walker") of a domain, system or task name
    (``"dmc-walker-walk"``, ``"cheetah-run"``, a ``System`` or ``Task`` with such a name)."""
    key = getattr(name, "system", None) if not isinstance(name, str) else name
    key = getattr(name, "name", None) if key is None or not isinstance(key, str) else key
    if isinstance(key, str):
        k = key.strip().lower()
        if k in _ALIASES:
            return _ALIASES[k]
        for prefix in ("dmc-walker-", "walker-"):
            if k.startswith(prefix):
                return "walker"
    raise ValueError(f"no DMC observation for {name!r}: known domains are {', '.join(DMC_OBSERVATIONS)} "
                     "(systems dmc-swimmer6 / dmc-cheetah / dmc-walker and their tasks)")


def _name(m: mujoco.MjModel, obj, i: int, fallback: str) -> str:
    return mujoco.mj_id2name(m, obj, i) or f"{fallback}{i}"


def _floats(values) -> tuple[float, ...]:
    """A model array's row as Python floats (constants, not NumPy scalars: a traced function
    (``torch.compile``) branches on them as on any number)."""
    return tuple(float(v) for v in values)


class JointCoordinates:
    """qpos and qvel of ``model`` (an ``MjModel``) from body states; see the module docstring.

    Every body's joints must be slides followed by at most one hinge (no ball or free joint, no
    hinge before a slide), the slides' axes orthonormal. ``coords(body [..., B, 13])`` ->
    (qpos [..., nq], qvel [..., nv]) in ``body``'s dtype and device."""

    def __init__(self, model: mujoco.MjModel):
        self.nbody, self.nq, self.nv = int(model.nbody), int(model.nq), int(model.nv)
        self.parent = [int(p) for p in model.body_parentid]
        self.bodies = []   # (body, parent, body_pos, body_quat, [(qpos adr, axis, ref)], hinge or None)
        for b in range(1, self.nbody):
            js = range(int(model.body_jntadr[b]), int(model.body_jntadr[b]) + int(model.body_jntnum[b]))
            slides, hinge = [], None
            for j in js:
                kind = int(model.jnt_type[j])
                name = _name(model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint")
                if kind not in (_SLIDE, _HINGE):
                    raise ValueError(f"joint {name!r} is neither a slide nor a hinge: its coordinates are not "
                                     "derived from body states here")
                if hinge is not None:
                    raise ValueError(f"joint {name!r} follows a hinge in its body: only slides then one hinge "
                                     "per body are derived from body states")
                entry = (int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j]), _floats(model.jnt_axis[j]),
                         float(model.qpos0[model.jnt_qposadr[j]]), _floats(model.jnt_pos[j]))
                if kind == _SLIDE:
                    slides.append(entry)
                else:
                    hinge = entry
            if len(slides) > 1:
                a = torch.tensor([s[2] for s in slides], dtype=torch.float64)
                if not torch.allclose(a @ a.T, torch.eye(len(slides), dtype=torch.float64), atol=1e-9):
                    raise ValueError(f"body {_name(model, mujoco.mjtObj.mjOBJ_BODY, b, 'body')!r}: its slide axes "
                                     "are not orthonormal")
            self.bodies.append((b, self.parent[b], _floats(model.body_pos[b]), _floats(model.body_quat[b]), slides,
                                hinge))
        self._cache: dict = {}

    def constant(self, values: tuple, like: torch.Tensor) -> torch.Tensor:
        """``values`` as a tensor of ``like``'s dtype and device, made once (no host copy per call)."""
        key = (values, like.device, like.dtype)
        t = self._cache.get(key)
        if t is None:
            t = self._cache[key] = torch.tensor(values, dtype=like.dtype, device=like.device)
        return t

    def _tables(self, like: torch.Tensor) -> dict:
        """Every body's constants and every joint's entry as tensors of ``like``'s dtype and
        device, made once: the bodies are composed together, a few operations for the whole
        tree (not a few tens per body)."""
        key = ("tables", like.device, like.dtype)
        t = self._cache.get(key)
        if t is None:
            f = dict(dtype=like.dtype, device=like.device)
            i = dict(dtype=torch.long, device=like.device)
            hinges = [(k, h) for k, (*_, h) in enumerate(self.bodies) if h is not None]
            slides = [(k, sl) for k, (*_, sls, _) in enumerate(self.bodies) for sl in sls]
            t = self._cache[key] = dict(
                body=torch.tensor([b for b, *_ in self.bodies], **i),
                parent=torch.tensor([p for _, p, *_ in self.bodies], **i),
                pos=torch.tensor([bp for _, _, bp, *_ in self.bodies], **f).reshape(-1, 3),
                quat=torch.tensor([bq for _, _, _, bq, *_ in self.bodies], **f).reshape(-1, 4),
                anchor=torch.tensor([h[4] if h is not None else (0.0, 0.0, 0.0) for *_, h in self.bodies],
                                    **f).reshape(-1, 3),
                h_of=torch.tensor([k for k, _ in hinges], **i), h_qpos=torch.tensor([h[0] for _, h in hinges], **i),
                h_dof=torch.tensor([h[1] for _, h in hinges], **i),
                h_axis=torch.tensor([h[2] for _, h in hinges], **f).reshape(-1, 3),
                h_ref=torch.tensor([h[3] for _, h in hinges], **f),
                s_of=torch.tensor([k for k, _ in slides], **i), s_qpos=torch.tensor([sl[0] for _, sl in slides], **i),
                s_dof=torch.tensor([sl[1] for _, sl in slides], **i),
                s_axis=torch.tensor([sl[2] for _, sl in slides], **f).reshape(-1, 3),
                s_ref=torch.tensor([sl[3] for _, sl in slides], **f))
        return t

    def __call__(self, body: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if body.ndim < 2 or body.shape[-2] != self.nbody or body.shape[-1] != DYN_NODE_SIZE:
            raise ValueError(f"body states must be [..., {self.nbody}, {DYN_NODE_SIZE}], got {tuple(body.shape)}")
        lead = body.shape[:-2]
        T = self._tables(body)
        qpos = body.new_zeros(*lead, self.nq)
        qvel = body.new_zeros(*lead, self.nv)
        quat = quat_normalize(body[..., QUAT])
        # every moving body [..., K, .] beside its parent's state
        pb, bb = body[..., T["parent"], :], body[..., T["body"], :]
        xp, qp, vp, wp = pb[..., POS], quat[..., T["parent"], :], pb[..., LINVEL], pb[..., ANGVEL]
        xb, qb, vb, wb = bb[..., POS], quat[..., T["body"], :], bb[..., LINVEL], bb[..., ANGVEL]
        K = T["body"].numel()
        q0 = quat_mul(qp, T["quat"].expand(*lead, K, 4))        # each body's frame before its joints
        rel = quat_mul(quat_conj(q0), qb)                        # its joints' rotation, in that frame
        if T["h_of"].numel():
            k, axis = T["h_of"], T["h_axis"].expand(*lead, -1, 3)
            r = rel[..., k, :]
            s, w = (r[..., 1:] * axis).sum(-1), r[..., 0]
            # the angle from cos and sin of the full angle: the same for q and -q
            qpos[..., T["h_qpos"]] = torch.atan2(2 * w * s, w * w - s * s) + T["h_ref"]
            qvel[..., T["h_dof"]] = ((wb[..., k, :] - wp[..., k, :]) * quat_rotate(qb[..., k, :], axis)).sum(-1)
        if T["s_of"].numel():
            # hinge about anchor c: pos = p0 + R0 (d + c) - Rb c, so d = R0^T (pos - p0) - c + rel c
            c = T["anchor"].expand(*lead, K, 3)
            p0 = xp + quat_rotate(qp, T["pos"].expand(*lead, K, 3))
            d = quat_rotate(quat_conj(q0), xb - p0) - c + quat_rotate(rel, c)
            anchor = xb + quat_rotate(qb, c)
            v_anchor = vb + torch.linalg.cross(wb, anchor - xb, dim=-1)
            v_rel = v_anchor - vp - torch.linalg.cross(wp, anchor - xp, dim=-1)
            k, axis = T["s_of"], T["s_axis"].expand(*lead, -1, 3)
            qpos[..., T["s_qpos"]] = (d[..., k, :] * axis).sum(-1) + T["s_ref"]
            qvel[..., T["s_dof"]] = (v_rel[..., k, :] * quat_rotate(q0[..., k, :], axis)).sum(-1)
        return qpos, qvel


def joint_coordinates(model: mujoco.MjModel, body: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(qpos [..., nq], qvel [..., nv]) of ``model`` from body states [..., B, 13] (``JointCoordinates``)."""
    return JointCoordinates(model)(body)


def _rotmat_rows(q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(xx, xz) entries of the rotation matrix of unit quaternions [..., 4]."""
    w, x, y, z = q.unbind(-1)
    return 1 - 2 * (y * y + z * z), 2 * (x * z + w * y)


class DMCObservation:
    """The suite's observation of a DMC domain from body states (module docstring).

    ``name``: a domain, system or task name (``observation_domain``). Attributes: ``domain``,
    ``system`` (the ``System``), ``size`` D, ``names`` [D], ``parts`` {dict key: slice},
    ``coords`` (its ``JointCoordinates``). ``obs(body [..., B, 13], target=None)`` -> [..., D]."""

    def __init__(self, name):
        from gnwarp.sim.systems import make
        self.domain = observation_domain(name)
        self.system = make(DMC_OBSERVATIONS[self.domain])
        m = self.system.model
        self.model, self.nbody = m, int(m.nbody)
        self.coords = JointCoordinates(m)
        bodies = [_name(m, mujoco.mjtObj.mjOBJ_BODY, b, "body") for b in range(self.nbody)]
        joints = [_name(m, mujoco.mjtObj.mjOBJ_JOINT, j, "joint") for j in range(m.njnt)]
        qpos_names = [joints[j] for j in range(m.njnt)]   # slides and hinges: one qpos and one dof each
        if m.nq != m.njnt or m.nv != m.njnt:
            raise ValueError(f"{self.system.name}: expected one coordinate per joint")
        if self.domain == "swimmer6":
            nose = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "nose")
            target = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "target")
            self.head = int(m.geom_bodyid[nose])
            self.nose = tuple(float(v) for v in m.geom_pos[nose])
            self.target_z = float(m.geom_pos[target, 2])
            self.hinges = list(range(3, m.nq))   # the suite's joints(): qpos[3:]
            parts = [("joints", [f"joints.{qpos_names[i]}" for i in self.hinges]),
                     ("to_target", ["to_target.x", "to_target.y"]),
                     ("body_velocities", [f"body_velocities.{bodies[b]}.{f}" for b in range(1, self.nbody)
                                          for f in ("vx", "vy", "wz")])]
        elif self.domain == "cheetah":
            parts = [("position", [f"position.{n}" for n in qpos_names[1:]]),
                     ("velocity", [f"velocity.{n}" for n in qpos_names])]
        else:
            self.torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
            parts = [("orientations", [f"orientations.{bodies[b]}.{f}" for b in range(1, self.nbody)
                                       for f in ("xx", "xz")]),
                     ("height", ["height"]),
                     ("velocity", [f"velocity.{n}" for n in qpos_names])]
        self.names, self.parts, k = [], {}, 0
        for key, names in parts:
            self.parts[key] = slice(k, k + len(names))
            self.names += names
            k += len(names)
        self.size = len(self.names)

    def __deepcopy__(self, memo):
        # a fixed description of the model (its MjSpec does not copy): copies of networks share it
        return self

    def __repr__(self) -> str:
        return f"DMCObservation({self.domain!r}, size={self.size})"

    def __call__(self, body: torch.Tensor, target=None) -> torch.Tensor:
        body = torch.as_tensor(body)
        if body.ndim < 2 or body.shape[-2] != self.nbody or body.shape[-1] != DYN_NODE_SIZE:
            raise ValueError(f"{self.system.name} body states must be [..., {self.nbody}, {DYN_NODE_SIZE}], "
                             f"got {tuple(body.shape)}")
        if not body.is_floating_point():
            body = body.to(torch.float32)
        return getattr(self, f"_{self.domain}")(body, target)

    def _swimmer6(self, body, target):
        lead = body.shape[:-2]
        if target is None:
            raise ValueError("the swimmer6 observation needs the episode's target [N, 2 or 3] (sample_targets)")
        t = torch.as_tensor(target).to(body.device, body.dtype)
        if t.shape[-1] not in (2, 3) or t.shape[:-1] != lead[:t.ndim - 1]:
            raise ValueError(f"swimmer6 target must be [N, 2 or 3] for body states {tuple(body.shape)}, "
                             f"got {tuple(t.shape)}")
        if t.shape[-1] == 2:
            t = torch.cat([t, t.new_full((*t.shape[:-1], 1), self.target_z)], -1)
        while t.ndim < len(lead) + 1:    # one target per episode, shared by its steps [N, T, ...]
            t = t.unsqueeze(-2)
        t = t.expand(*lead, 3)
        qpos, _ = self.coords(body)
        quat = quat_normalize(body[..., QUAT])
        head = body[..., self.head, :]
        qh = quat[..., self.head, :]
        nose = head[..., POS] + quat_rotate(qh, self.coords.constant(self.nose, body).expand(*lead, 3))
        to_target = quat_rotate(quat_conj(qh), t - nose)[..., :2]
        inv = quat_conj(quat[..., 1:, :])
        v = quat_rotate(inv, body[..., 1:, LINVEL])
        w = quat_rotate(inv, body[..., 1:, ANGVEL])
        vel = torch.stack([v[..., 0], v[..., 1], w[..., 2]], -1).reshape(*lead, -1)
        return torch.cat([qpos[..., self.hinges], to_target, vel], -1)

    def _cheetah(self, body, target):
        qpos, qvel = self.coords(body)
        return torch.cat([qpos[..., 1:], qvel], -1)

    def _walker(self, body, target):
        _, qvel = self.coords(body)
        q = quat_normalize(body[..., 1:, QUAT])
        xx, xz = _rotmat_rows(q)
        orient = torch.stack([xx, xz], -1).reshape(*body.shape[:-2], -1)
        return torch.cat([orient, body[..., self.torso, 2:3], qvel], -1)


def wrap_angle(x: torch.Tensor) -> torch.Tensor:
    """Angles mapped to (-pi, pi]."""
    return x - 2 * math.pi * torch.ceil((x - math.pi) / (2 * math.pi))
