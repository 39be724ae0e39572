"""The DeepMind Control Suite's tasks on graph states, on the suite's 0-1000 scale.

Each task is restated from the suite's task code (``dm_control/suite/<domain>.py``) on the body
states [N, T+1, B, 13] of ``gnwarp.state``, per control step in [0, 1], so a 1000-step episode
scores 0-1000. What the suite reads from MuJoCo's sensors and named frames is derived from the body
states and the domain model's constants (``gnwarp.sim.dmc``'s MJCF):

- subtree linear velocity (``subtreelinvel``): the mass-weighted velocity of the subtree's body
  centres of mass, each ``linvel + angvel x R ipos``;
- a body's centre of mass (``xipos``), a geom's or site's position: body pos + R offset;
- ``xmat[..., 'zz']`` (uprightness): 1 - 2 (x^2 + y^2) of the body's unit quaternion;
- a joint's position / velocity (cartpole's slider and hinge): the body's displacement along the
  joint axis, the relative angular velocity about it.

Rewards are built with ``tolerance``, a torch restatement of ``dm_control.utils.rewards.tolerance``
(the tests check it against dm_control's for every sigmoid) that autograd differentiates with
finite gradients. Where the exact reward is piecewise constant (a tolerance with margin 0: reacher,
pendulum-swingup, hopper's standing term) the task's ``reward`` is a declared smooth surrogate
(``SURROGATES``) and ``score`` the exact one.
"""
from __future__ import annotations

import functools
import math

import mujoco
import numpy as np
import torch

from gnwarp.control.task_base import Task, TaskError
from gnwarp.sim import dmc as domains
from gnwarp.state import ANGVEL, LINVEL, POS, QUAT, quat_normalize, quat_rotate

__all__ = ["tolerance", "SIGMOIDS", "dmc_tasks", "sample_dmc_targets", "randomize_joints", "SURROGATES",
           "subtree_linvel", "frame_point", "upright_zz"]

SIGMOIDS = ("gaussian", "hyperbolic", "long_tail", "reciprocal", "cosine", "linear", "quadratic", "tanh_squared")


# -- dm_control.utils.rewards.tolerance in torch ---------------------------------------------------

def _sigmoid(x: torch.Tensor, value_at_1: float, sigmoid: str) -> torch.Tensor:
    """1 at x = 0, ``value_at_1`` at x = 1 (x >= 0 here: a distance over the margin)."""
    if sigmoid in ("cosine", "linear", "quadratic"):
        if not 0 <= value_at_1 < 1:
            raise ValueError(f"value_at_margin must be nonnegative and smaller than 1, got {value_at_1}")
    elif sigmoid in SIGMOIDS:
        if not 0 < value_at_1 < 1:
            raise ValueError(f"value_at_margin must be strictly between 0 and 1, got {value_at_1}")
    else:
        raise ValueError(f"unknown sigmoid {sigmoid!r}; choose one of {SIGMOIDS}")
    if sigmoid == "gaussian":
        scale = float(np.sqrt(-2 * np.log(value_at_1)))
        return torch.exp(-0.5 * (x * scale) ** 2)
    if sigmoid == "hyperbolic":
        y = x * float(np.arccosh(1 / value_at_1))
        return 2 * torch.exp(-y) / (1 + torch.exp(-2 * y))   # 1 / cosh(y) without overflow (y >= 0)
    if sigmoid == "long_tail":
        scale = float(np.sqrt(1 / value_at_1 - 1))
        return 1 / ((x * scale) ** 2 + 1)
    if sigmoid == "reciprocal":
        return 1 / (x.abs() * (1 / value_at_1 - 1) + 1)
    if sigmoid == "tanh_squared":
        return 1 - torch.tanh(x * float(np.arctanh(np.sqrt(1 - value_at_1)))) ** 2
    scale = {"cosine": float(np.arccos(2 * value_at_1 - 1) / np.pi), "linear": 1 - value_at_1,
             "quadratic": float(np.sqrt(1 - value_at_1))}[sigmoid]
    sx = x * scale
    inside = sx.abs() < 1
    sx = torch.where(inside, sx, torch.zeros_like(sx))   # the branch not taken stays finite
    if sigmoid == "cosine":
        val = (1 + torch.cos(math.pi * sx)) / 2
    elif sigmoid == "linear":
        val = 1 - sx
    else:
        val = 1 - sx ** 2
    return torch.where(inside, val, torch.zeros_like(val))


def tolerance(x: torch.Tensor, bounds=(0.0, 0.0), margin: float = 0.0, sigmoid: str = "gaussian",
              value_at_margin: float = 0.1) -> torch.Tensor:
    """``dm_control.utils.rewards.tolerance`` on a tensor: 1 where ``bounds[0] <= x <= bounds[1]``,
    else ``sigmoid`` of the distance to the nearest bound over ``margin`` (``value_at_margin`` at
    one margin; 0 outside the bounds when margin is 0). Same shape and dtype as ``x``; gradients
    are finite everywhere (zero where the value is constant)."""
    lower, upper = float(bounds[0]), float(bounds[1])
    if lower > upper:
        raise ValueError("Lower bound must be <= upper bound.")
    if margin < 0:
        raise ValueError("`margin` must be non-negative.")
    x = torch.as_tensor(x)
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    in_bounds = (lower <= x) & (x <= upper)
    if margin == 0:
        return in_bounds.to(x.dtype)
    d = torch.zeros_like(x)  # distance to the nearest bound, 0 inside (an infinite bound adds nothing)
    if math.isfinite(lower):
        d = d + (lower - x).clamp_min(0)
    if math.isfinite(upper):
        d = d + (x - upper).clamp_min(0)
    value = _sigmoid(d / margin, float(value_at_margin), sigmoid)
    return torch.where(in_bounds, torch.ones_like(value), value)


# -- what the suite's sensors read, from body states --------------------------------------------

def upright_zz(quat: torch.Tensor) -> torch.Tensor:
    """``xmat[..., 'zz']``: z of the body's z axis, from quaternions [..., 4] (normalized here)."""
    q = quat_normalize(quat)
    return 1 - 2 * (q[..., 1] ** 2 + q[..., 2] ** 2)


def frame_point(body: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """World position of a point at ``offset`` [3] in a body's frame (a geom, a site, the centre
    of mass): pos + R offset, from body states [..., 13] -> [..., 3]."""
    return body[..., POS] + quat_rotate(quat_normalize(body[..., QUAT]), offset.expand_as(body[..., POS]))


def subtree_linvel(bodies: torch.Tensor, mass: torch.Tensor, ipos: torch.Tensor) -> torch.Tensor:
    """MuJoCo's ``subtreelinvel`` of a subtree from its bodies' states [..., K, 13], masses [K]
    and centres of mass in their frames [K, 3]: sum_k m_k (v_k + w_k x R_k ipos_k) / sum_k m_k."""
    r = quat_rotate(quat_normalize(bodies[..., QUAT]), ipos.expand_as(bodies[..., POS]))
    v = bodies[..., LINVEL] + torch.linalg.cross(bodies[..., ANGVEL], r, dim=-1)
    return (mass[:, None] * v).sum(-2) / mass.sum()


# -- model constants ----------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def _model(system: str) -> mujoco.MjModel:
    from gnwarp.sim.systems import make
    return make(system).model


def _id(m: mujoco.MjModel, obj, name: str) -> int:
    i = mujoco.mj_name2id(m, obj, name)
    if i < 0:
        raise TaskError(f"the DMC model has no {obj.name.removeprefix('mjOBJ_').lower()} {name!r}")
    return int(i)


def _subtree(m: mujoco.MjModel, root: int) -> list[int]:
    """Bodies of ``root``'s subtree (itself included), in body order."""
    out = []
    for b in range(m.nbody):
        a = b
        while a > 0 and a != root:
            a = int(m.body_parentid[a])
        if a == root:
            out.append(b)
    return out


_CONSTANTS: dict[str, dict] = {}


def _constants(system: str) -> dict:
    """Numpy constants the rewards of ``system`` read: body indices, masses, offsets, sizes; made
    once (a plain dict, which ``torch.compile`` reads as constants once filled)."""
    c = _CONSTANTS.get(system)
    if c is None:
        c = _CONSTANTS[system] = _make_constants(system)
    return c


def _make_constants(system: str) -> dict:
    m = _model(system)
    B, G, S, J = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_JOINT
    c: dict = {}
    if system in ("dmc-cheetah", "dmc-walker", "dmc-hopper"):
        torso = _id(m, B, "torso")
        sub = _subtree(m, torso)
        c.update(torso=torso, subtree=sub, mass=m.body_mass[sub].copy(), ipos=m.body_ipos[sub].copy())
    if system == "dmc-hopper":
        foot = _id(m, B, "foot")
        c.update(foot=foot, torso_ipos=m.body_ipos[c["torso"]].copy(), foot_ipos=m.body_ipos[foot].copy())
    if system == "dmc-swimmer6":
        nose, target = _id(m, G, "nose"), _id(m, G, "target")
        c.update(head=int(m.geom_bodyid[nose]), nose=m.geom_pos[nose].copy(), target_size=float(m.geom_size[target, 0]),
                 target_z=float(m.geom_pos[target, 2]))
    if system == "dmc-reacher":
        finger, target = _id(m, G, "finger"), _id(m, G, "target")
        c.update(finger_body=int(m.geom_bodyid[finger]), finger=m.geom_pos[finger].copy(),
                 finger_size=float(m.geom_size[finger, 0]), target_z=float(m.geom_pos[target, 2]))
    if system == "dmc-cartpole":
        slider, hinge = _id(m, J, "slider"), _id(m, J, "hinge_1")
        cart, pole = int(m.jnt_bodyid[slider]), int(m.jnt_bodyid[hinge])
        if m.body_parentid[cart] != 0:
            raise TaskError("dmc-cartpole: the cart must hang from the world")
        axis = np.zeros(3)
        mujoco.mju_rotVecQuat(axis, m.jnt_axis[slider], m.body_quat[cart])
        c.update(cart=cart, pole=pole, slider_axis=axis, cart_pos0=m.body_pos[cart].copy(),
                 slider_qpos0=float(m.qpos0[m.jnt_qposadr[slider]]), hinge_axis=m.jnt_axis[hinge].copy())
    if system == "dmc-pendulum":
        c.update(pole=_id(m, B, "pole"))
    if system == "dmc-acrobot":
        tip, target = _id(m, S, "tip"), _id(m, S, "target")
        if m.site_bodyid[target] != 0:
            raise TaskError("dmc-acrobot: the target site must be fixed in the world")
        c.update(lower=int(m.site_bodyid[tip]), tip=m.site_pos[tip].copy(), target=m.site_pos[target].copy(),
                 target_radius=float(m.site_size[target, 0]))
    return c


_TENSORS: dict = {}


def _const(system: str, key: str, like: torch.Tensor) -> torch.Tensor:
    """A numpy constant as a tensor on ``like``'s device and dtype, kept per device (so a reward
    can be recorded in a CUDA graph once warm)."""
    k = (system, key, str(like.device), like.dtype)
    t = _TENSORS.get(k)
    if t is None:
        t = _TENSORS[k] = torch.as_tensor(np.asarray(_constants(system)[key]), dtype=like.dtype).to(like.device)
    return t


def _after(states: torch.Tensor) -> torch.Tensor:
    """The states after each action [N, T, B, 13]."""
    if states.ndim != 4 or states.shape[-1] != 13:
        raise TaskError(f"states must be [N, T+1, B, 13], got {tuple(states.shape)}")
    return states[:, 1:]


def _target_xy(target, like: torch.Tensor, task: str) -> torch.Tensor:
    if target is None:
        raise TaskError(f"{task} needs target= (the target position [N, 2] or [N, 3] per episode: "
                        "sample_targets gives DMC's)")
    t = torch.as_tensor(target).to(device=like.device, dtype=like.dtype)
    if t.ndim != 2 or t.shape[0] != like.shape[0] or t.shape[1] not in (2, 3):
        raise TaskError(f"{task}'s target must be [N={like.shape[0]}, 2 or 3], got {tuple(t.shape)}")
    return t[:, None, :2]


# -- per-step rewards: (states after each action [N, T, B, 13], actions [N, T, U], target) -> [N, T]

def _speed(system: str, s: torch.Tensor) -> torch.Tensor:
    """The torso's subtree linear velocity along x (the suite's ``torso_subtreelinvel``[0])."""
    sub = _constants(system)["subtree"]
    bodies = s[:, :, sub[0]:sub[-1] + 1] if sub == list(range(sub[0], sub[-1] + 1)) else s[:, :, sub]
    return subtree_linvel(bodies, _const(system, "mass", s), _const(system, "ipos", s))[..., 0]


def _cheetah_run(s, a, target):
    return tolerance(_speed("dmc-cheetah", s), bounds=(10.0, math.inf), margin=10.0, value_at_margin=0,
                     sigmoid="linear")


def _walker(move_speed: float):
    def step(s, a, target):
        torso = s[:, :, _constants("dmc-walker")["torso"]]
        standing = tolerance(torso[..., 2], bounds=(1.2, math.inf), margin=1.2 / 2)
        upright = (1 + upright_zz(torso[..., QUAT])) / 2
        stand = (3 * standing + upright) / 4
        if move_speed == 0:
            return stand
        move = tolerance(_speed("dmc-walker", s), bounds=(move_speed, math.inf), margin=move_speed / 2,
                         value_at_margin=0.5, sigmoid="linear")
        return stand * (5 * move + 1) / 6
    return step


def _hopper(hopping: bool, smooth: bool):
    def step(s, a, target):
        c = _constants("dmc-hopper")
        height = (frame_point(s[:, :, c["torso"]], _const("dmc-hopper", "torso_ipos", s))[..., 2]
                  - frame_point(s[:, :, c["foot"]], _const("dmc-hopper", "foot_ipos", s))[..., 2])
        standing = (tolerance(height, (0.6, 2.0), margin=0.3) if smooth   # the surrogate
                    else tolerance(height, (0.6, 2.0)))
        if hopping:
            return standing * tolerance(_speed("dmc-hopper", s), bounds=(2.0, math.inf), margin=1.0,
                                        value_at_margin=0.5, sigmoid="linear")
        small_control = tolerance(a.to(s), margin=1, value_at_margin=0, sigmoid="quadratic").mean(-1)
        return standing * (small_control + 4) / 5
    return step


def _swimmer(s, a, target):
    c = _constants("dmc-swimmer6")
    nose = frame_point(s[:, :, c["head"]], _const("dmc-swimmer6", "nose", s))[..., :2]
    # the suite measures nose-to-target in the head's frame, whose z stays the world's (a planar swimmer)
    dist = _distance(_target_xy(target, s, "dmc-swimmer-swimmer6") - nose)
    size = c["target_size"]
    return tolerance(dist, bounds=(0, size), margin=5 * size, sigmoid="long_tail")


def _distance(v: torch.Tensor) -> torch.Tensor:
    """|v| over the last axis, with a finite gradient at 0."""
    sq = (v ** 2).sum(-1)
    safe = torch.where(sq > 0, sq, torch.ones_like(sq))
    return torch.where(sq > 0, safe.sqrt(), torch.zeros_like(sq))


def _reacher(target_size: float, smooth: bool):
    def step(s, a, target):
        c = _constants("dmc-reacher")
        finger = frame_point(s[:, :, c["finger_body"]], _const("dmc-reacher", "finger", s))[..., :2]
        dist = _distance(_target_xy(target, s, "dmc-reacher") - finger)
        radii = target_size + c["finger_size"]
        if smooth:  # the surrogate: 1 inside, a long tail over the arena's 0.1 m scale outside
            return tolerance(dist, (0, radii), margin=0.1, sigmoid="long_tail")
        return tolerance(dist, (0, radii))
    return step


def _cartpole(s, a, target):
    c = _constants("dmc-cartpole")
    cart, pole = s[:, :, c["cart"]], s[:, :, c["pole"]]
    cart_x = (((cart[..., POS] - _const("dmc-cartpole", "cart_pos0", s)) * _const("dmc-cartpole", "slider_axis", s))
              .sum(-1) + c["slider_qpos0"])
    hinge_axis = _const("dmc-cartpole", "hinge_axis", s).expand_as(pole[..., POS])
    axis = quat_rotate(quat_normalize(pole[..., QUAT]), hinge_axis)
    hinge_vel = ((pole[..., ANGVEL] - cart[..., ANGVEL]) * axis).sum(-1)
    upright = (upright_zz(pole[..., QUAT]) + 1) / 2
    centered = (1 + tolerance(cart_x, margin=2)) / 2
    small_control = (4 + tolerance(a[..., 0].to(s), margin=1, value_at_margin=0, sigmoid="quadratic")) / 5
    small_velocity = (1 + tolerance(hinge_vel, margin=5)) / 2
    return upright * small_control * small_velocity * centered


_COSINE_BOUND = math.cos(math.radians(8))


def _pendulum(smooth: bool):
    def step(s, a, target):
        zz = upright_zz(s[:, :, _constants("dmc-pendulum")["pole"], QUAT])
        if smooth:  # the surrogate: 1 inside, linear in the cosine down to 0 hanging straight down
            return tolerance(zz, (_COSINE_BOUND, 1), margin=1 + _COSINE_BOUND, sigmoid="linear", value_at_margin=0)
        return tolerance(zz, (_COSINE_BOUND, 1))
    return step


def _acrobot(s, a, target):
    c = _constants("dmc-acrobot")
    tip = frame_point(s[:, :, c["lower"]], _const("dmc-acrobot", "tip", s))
    dist = _distance(_const("dmc-acrobot", "target", s) - tip)
    return tolerance(dist, bounds=(0, c["target_radius"]), margin=1)


def _summed(step):
    """A per-step reward as a Task reward: summed over the T steps after state 0 -> [N]. The
    per-step rewards [N, T] stay reachable as ``reward.step(states[:, 1:], actions, target)``."""
    def reward(states, actions, target=None):
        return step(_after(states), actions, target).sum(1)
    reward.step = step
    return reward


# -- initial states (the suite's initialize_episode) --------------------------------------------

def randomize_joints(model: mujoco.MjModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """qpos [n, nq] as the suite's ``randomize_limited_and_rotational_joints``: limited hinges and
    slides uniform in their range, unlimited hinges uniform in [-pi, pi], balls and free joints'
    orientations uniform on the unit sphere (limited balls: a random axis, angle up to the limit),
    every other coordinate at ``qpos0``."""
    qpos = np.tile(np.asarray(model.qpos0, dtype=np.float64), (n, 1))
    J = mujoco.mjtJoint
    for j in range(model.njnt):
        t, a = int(model.jnt_type[j]), int(model.jnt_qposadr[j])
        lo, hi = model.jnt_range[j]
        if model.jnt_limited[j]:
            if t in (J.mjJNT_HINGE, J.mjJNT_SLIDE):
                qpos[:, a] = rng.uniform(lo, hi, n)
            elif t == J.mjJNT_BALL:
                for k in range(n):
                    axis = rng.standard_normal(3)
                    quat = np.zeros(4)
                    mujoco.mju_axisAngle2Quat(quat, axis / np.linalg.norm(axis), rng.random() * hi)
                    qpos[k, a:a + 4] = quat
        elif t == J.mjJNT_HINGE:
            qpos[:, a] = rng.uniform(-np.pi, np.pi, n)
        elif t == J.mjJNT_BALL:
            q = rng.standard_normal((n, 4))
            qpos[:, a:a + 4] = q / np.linalg.norm(q, axis=1, keepdims=True)
        elif t == J.mjJNT_FREE:
            q = rng.random((n, 4))   # as the suite draws it (rand, not randn)
            qpos[:, a + 3:a + 7] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return qpos


def _random_joints(system, n, rng):
    m = system.model
    return randomize_joints(m, n, rng), np.zeros((n, m.nv))


def _cheetah_initial(system, n, rng):
    """Limited joints uniform in their range, then 200 physics steps at zero control on MuJoCo C,
    as the suite's legacy step takes them: the first finishes (mj_step2) the step begun at the
    reset pose qpos0, the rest are full steps."""
    m = system.model
    limited = np.flatnonzero(m.jnt_limited == 1)
    qpos = np.tile(np.asarray(m.qpos0, dtype=np.float64), (n, 1))
    adr = m.jnt_qposadr[limited]
    lo, hi = m.jnt_range[limited].T
    qpos[:, adr] = rng.uniform(lo, hi, (n, len(limited)))
    return settle(m, qpos, 200)


def settle(model: mujoco.MjModel, qpos: np.ndarray, nstep: int) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, qvel) [n, nq], [n, nv] after ``nstep`` physics steps at zero control from ``qpos``
    at rest, taken as the suite's ``physics.step(nstep)`` inside its reset: after ``mj_forward``
    at qpos0 (the suite's runs with actuation off, the same at the reset's zero control of motors),
    the first step finishes (``mj_step2``) from the stages computed there."""
    d = mujoco.MjData(model)
    out_q, out_v = np.empty_like(qpos), np.empty((len(qpos), model.nv))
    for k, q in enumerate(qpos):
        mujoco.mj_resetData(model, d)
        mujoco.mj_forward(model, d)
        d.qpos[:] = q
        if model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:
            mujoco.mj_step(model, d, nstep)
        else:
            mujoco.mj_step2(model, d)
            if nstep > 1:
                mujoco.mj_step(model, d, nstep - 1)
        out_q[k], out_v[k] = d.qpos, d.qvel
    return out_q, out_v


def _cartpole_initial(swing_up: bool):
    def initial(system, n, rng):
        m = system.model
        qpos, nv = np.tile(np.asarray(m.qpos0, dtype=np.float64), (n, 1)), m.nv
        if swing_up:
            qpos[:, 0] = 0.01 * rng.standard_normal(n)
            qpos[:, 1] = np.pi + 0.01 * rng.standard_normal(n)
            qpos[:, 2:] = 0.1 * rng.standard_normal((n, nv - 2))
        else:
            qpos[:, 0] = rng.uniform(-0.1, 0.1, n)
            qpos[:, 1:] = rng.uniform(-0.034, 0.034, (n, nv - 1))
        return qpos, 0.01 * rng.standard_normal((n, nv))
    return initial


def _named_hinges(*names: str):
    """Initial states with the named joints uniform in [-pi, pi] (pendulum, acrobot), at rest."""
    def initial(system, n, rng):
        m = system.model
        qpos = np.tile(np.asarray(m.qpos0, dtype=np.float64), (n, 1))
        adr = [int(m.jnt_qposadr[_id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]) for j in names]
        qpos[:, adr] = rng.uniform(-np.pi, np.pi, (n, len(adr)))
        return qpos, np.zeros((n, m.nv))
    return initial


# -- targets --------------------------------------------------------------------------------------

def sample_dmc_targets(task: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Per-episode target positions [n, 3] (x, y, the model's target z) as the suite draws them:
    reacher at radius U(0.05, 0.2) and angle U(0, 2 pi) (x = r sin, y = r cos); swimmer uniform in
    a box of half-width 0.3 (probability 0.2) or 2."""
    if task.startswith("dmc-reacher"):
        angle, radius = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.05, 0.20, n)
        z = _constants("dmc-reacher")["target_z"]
        return np.stack([radius * np.sin(angle), radius * np.cos(angle), np.full(n, z)], -1)
    if task == "dmc-swimmer-swimmer6":
        box = np.where(rng.random(n) < 0.2, 0.3, 2.0)
        xy = rng.uniform(-1.0, 1.0, (n, 2)) * box[:, None]
        return np.concatenate([xy, np.full((n, 1), _constants("dmc-swimmer6")["target_z"])], -1)
    raise TaskError(f"task {task!r} has no per-episode target")


# -- the tasks ------------------------------------------------------------------------------------

# The tasks whose planner reward is a declared surrogate of the exact (piecewise constant) reward.
SURROGATES = {
    "dmc-hopper-stand": "standing as tolerance(height, (0.6, 2), margin=0.3) (gaussian) for the exact margin 0",
    "dmc-hopper-hop": "standing as tolerance(height, (0.6, 2), margin=0.3) (gaussian) for the exact margin 0",
    "dmc-reacher-easy": "tolerance(dist, (0, radii), margin=0.1, sigmoid='long_tail') for the exact margin 0",
    "dmc-reacher-hard": "tolerance(dist, (0, radii), margin=0.1, sigmoid='long_tail') for the exact margin 0",
    "dmc-pendulum-swingup": "tolerance(cos, (cos 8 deg, 1), margin=1 + cos 8 deg, sigmoid='linear', "
                            "value_at_margin=0) for the exact margin 0",
}


def dmc_tasks() -> list[Task]:
    """The DMC tasks as ``Task`` records (suite "dmc", 1000-step episodes); their systems load on
    first use (dm_control needed then, not here)."""
    def task(name, system, horizon, step, initial, doc, exact=None, target=None):
        steps = domains.domain(system).episode_steps
        return Task(name, system, horizon, _summed(step), target=target, doc=doc,
                    score=None if exact is None else _summed(exact), episode_steps=steps, initial=initial,
                    suite="dmc")

    walker_doc = "standing (torso height >= 1.2, upright){} as the suite's walker"
    return [
        task("dmc-cheetah-run", "dmc-cheetah", 20, _cheetah_run, _cheetah_initial,
             "the torso subtree's forward speed, linear up to 10 m/s"),
        task("dmc-walker-stand", "dmc-walker", 20, _walker(0), _random_joints, walker_doc.format("")),
        task("dmc-walker-walk", "dmc-walker", 20, _walker(1), _random_joints,
             walker_doc.format(" times forward speed >= 1 m/s")),
        task("dmc-walker-run", "dmc-walker", 20, _walker(8), _random_joints,
             walker_doc.format(" times forward speed >= 8 m/s")),
        task("dmc-hopper-stand", "dmc-hopper", 25, _hopper(False, True), _random_joints,
             "torso over foot in [0.6, 2] m, times small controls", exact=_hopper(False, False)),
        task("dmc-hopper-hop", "dmc-hopper", 25, _hopper(True, True), _random_joints,
             "torso over foot in [0.6, 2] m, times forward speed >= 2 m/s", exact=_hopper(True, False)),
        task("dmc-swimmer-swimmer6", "dmc-swimmer6", 30, _swimmer, _random_joints,
             "nose within the target (long-tailed outside)", target="position"),
        task("dmc-reacher-easy", "dmc-reacher", 25, _reacher(0.05, True), _random_joints,
             "finger within the 5 cm target", exact=_reacher(0.05, False), target="position"),
        task("dmc-reacher-hard", "dmc-reacher", 25, _reacher(0.015, True), _random_joints,
             "finger within the 1.5 cm target", exact=_reacher(0.015, False), target="position"),
        task("dmc-cartpole-balance", "dmc-cartpole", 100, _cartpole, _cartpole_initial(False),
             "upright pole, centred cart, small control and pole velocity, from near upright"),
        task("dmc-cartpole-swingup", "dmc-cartpole", 100, _cartpole, _cartpole_initial(True),
             "upright pole, centred cart, small control and pole velocity, from hanging down"),
        task("dmc-pendulum-swingup", "dmc-pendulum", 50, _pendulum(True), _named_hinges("hinge"),
             "pole within 8 degrees of upright", exact=_pendulum(False)),
        task("dmc-acrobot-swingup", "dmc-acrobot", 100, _acrobot, _named_hinges("shoulder", "elbow"),
             "tip within the target (gaussian, margin 1 m)"),
    ]
