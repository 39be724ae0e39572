"""Control tasks of the paper (supplementary F.2) and of the DeepMind Control Suite
(``gnwarp.control.dmc``, named "dmc-<domain>-<task>"): rewards of body-state trajectories.

A reward reads graph states, the 13 numbers of every body (``gnwarp.state``: pos 0:3, quat 3:7
(w, x, y, z), linvel 7:10, angvel 10:13, node 0 the world), so the same function scores a learned
model's predicted rollout and the true simulator's trajectory::

    reward(states [N, T+1, B, 13], actions [N, T, U], target=None) -> [N]

summed over the T steps that follow the actions (states 1..T; state 0 is where planning starts,
which the swimmer's target direction is measured from). Rewards are to be maximized.

    >>> task = get_task("pendulum-balance")            # Task(name, system, horizon, reward, ...)
    >>> r = task.reward(states, actions)                 # [N]
    >>> mine = Task("spin", "pendulum", 50, lambda s, a, target=None: s[..., 1:, 1, 11].sum(-1))
"""
from __future__ import annotations

import functools
from typing import Callable

import mujoco
import numpy as np
import torch

from gnwarp.control.dmc import dmc_tasks, sample_dmc_targets
from gnwarp.control.task_base import Reward, Task, TaskError
from gnwarp.sim.body_state import body_states
from gnwarp.state import LINVEL, POS, QUAT, quat_conj, quat_mul

__all__ = ["Task", "TASKS", "get_task", "task_names", "upright_angle", "body_index",
           "sample_targets", "episode_starts", "TaskError", "Reward"]


@functools.lru_cache(maxsize=None)
def _body_names(system: str) -> tuple[str, ...]:
    from gnwarp.sim.systems import make
    m = make(system).model
    return tuple(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(m.nbody))


def body_index(system: str, *names: str) -> list[int]:
    """Node index of each named body of a built-in system (its builder's names, world = 0)."""
    bodies = _body_names(system)
    missing = [n for n in names if n not in bodies]
    if missing:
        raise TaskError(f"{system} has no bodies {missing}; its bodies: {list(bodies)}")
    return [bodies.index(n) for n in names]


@functools.lru_cache(maxsize=None)
def _walker_head() -> float:
    """Height of the walker's head above its torso frame: the torso capsule's half length."""
    from gnwarp.sim.systems import make
    return float(make("walker").model.geom("torso").size[1])


def upright_angle(quat: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
    """Angle (rad, in [0, pi]) between orientations ``quat`` [..., 4] and ``target`` (default the
    identity: every built-in pole and link points up at its identity orientation). Its gradient
    is finite everywhere, also at 0."""
    q = quat if target is None else quat_mul(quat_conj(target.expand_as(quat)), quat)
    return 2.0 * torch.atan2(torch.linalg.vector_norm(q[..., 1:], dim=-1), q[..., 0].abs())


@functools.lru_cache(maxsize=None)
def _index_tensor(idx: tuple, device: str) -> torch.Tensor:
    return torch.tensor(idx, device=device)


def _bodies(x: torch.Tensor, idx: list[int]) -> torch.Tensor:
    """``x[:, :, idx]`` without a host-to-device copy once warm (a slice when ``idx`` is a run of
    consecutive bodies, else an index tensor kept per device), so that a reward can be recorded
    in a CUDA graph (a captured planning iteration)."""
    if list(idx) == list(range(idx[0], idx[0] + len(idx))):
        return x[:, :, idx[0]:idx[0] + len(idx)]
    return x.index_select(2, _index_tensor(tuple(idx), str(x.device)))


def _steps(states: torch.Tensor) -> torch.Tensor:
    """The states after each action, [N, T, B, 13]."""
    return states[:, 1:]


# -- the rewards of F.2 ----------------------------------------------------------------------------

def _balance(bodies: tuple[str, ...], system: str) -> Reward:
    def reward(states, actions, target=None):
        idx = body_index(system, *bodies)
        return -upright_angle(_bodies(_steps(states), idx)[..., QUAT]).sum((1, 2))
    return reward


def _swimmer_reach(states, actions, target=None):
    """Head displacement from the previous step projected on the target direction (from the head
    at state 0 to the target, in the x-y plane), minus 0.01 x the squared projection of the head's
    offset from state 0 on the perpendicular direction (how far it strays from the line)."""
    if target is None:
        raise TaskError("swimmer-reach needs target= (the target position [N, 2] or [N, 3] per episode)")
    head = states[:, :, 1, :2]                                       # [N, T+1, 2]
    d = target[:, :2].to(head) - head[:, 0]
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(1e-9)
    perp = torch.stack([-d[:, 1], d[:, 0]], -1)
    along = ((head[:, 1:] - head[:, :-1]) * d[:, None]).sum(-1)
    off = ((head[:, 1:] - head[:, :1]) * perp[:, None]).sum(-1)
    return (along - 0.01 * off.square()).sum(1)


def _torso(feature: Callable[[torch.Tensor], torch.Tensor]) -> Reward:
    """A reward of the torso's state (node 1 of cheetah and walker) summed over the steps."""
    def reward(states, actions, target=None):
        return feature(_steps(states)[:, :, 1]).sum(1)
    return reward


def _walker_feet_to_head(states, actions, target=None):
    """Sum over both feet of the squared height of the head (top of the torso) above the foot."""
    s = _steps(states)
    q = s[:, :, 1, QUAT]                                   # w, x, y, z
    # z of the torso's axis (0, 0, head) rotated by q: head * (1 - 2 (x^2 + y^2))
    head_z = s[:, :, 1, 2] + _walker_head() * (1 - 2 * (q[..., 1].square() + q[..., 2].square()))
    feet = body_index("walker", "right_foot", "left_foot")
    return (head_z[..., None] - _bodies(s, feet)[..., 2]).square().sum((1, 2))


def _pose_loss(x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """D.7.4's dynamic-state loss on poses: squared position error + 1 - (q . q_target)^2."""
    pos = (x[..., POS] - target[..., POS]).square().sum(-1)
    dot = (x[..., QUAT] * target[..., QUAT]).sum(-1)
    return pos + 1.0 - dot.square()


def _jaco_pose(full: bool) -> Reward:
    def reward(states, actions, target=None):
        s = _steps(states)
        if target is None:
            raise TaskError(f"jaco-{'full' if full else 'palm'}-pose needs target= (poses "
                            f"{'[N, B, 7]' if full else '[N, 7]'}: position and w, x, y, z per episode)")
        target = target.to(s)
        if full:
            if target.ndim != 3 or target.shape[1] != s.shape[2] or target.shape[2] < 7:
                raise TaskError(f"jaco-full-pose's target must be [N, {s.shape[2]}, >= 7], got {tuple(target.shape)}")
            return -_pose_loss(s[:, :, 1:], target[:, None, 1:]).sum((1, 2))   # the world excluded
        if target.ndim != 2 or target.shape[1] < 7:
            raise TaskError(f"jaco-palm-pose's target must be [N, >= 7], got {tuple(target.shape)}")
        palm = body_index("jaco", "hand")[0]
        return -_pose_loss(s[:, :, palm], target[:, None]).sum(1)
    return reward


# -- tasks -----------------------------------------------------------------------------------------

def _tasks() -> dict[str, Task]:
    t = [
        Task("pendulum-balance", "pendulum", 50, _balance(("pole",), "pendulum"),
             doc="minus the pole's angle from upright"),
        Task("cartpole-balance", "cartpole", 100, _balance(("pole_1",), "cartpole"),
             doc="minus the pole's angle from upright"),
        Task("acrobot-swingup", "acrobot", 100, _balance(("upper_arm", "lower_arm"), "acrobot"),
             doc="minus both links' angles from upright"),
        Task("swimmer-reach", "swimmer", 100, _swimmer_reach, target="position",
             doc="head displacement towards the target, minus 0.01 x squared offset from the line"),
        Task("cheetah-forward", "cheetah", 20, _torso(lambda x: x[..., LINVEL][..., 0]),
             doc="torso's horizontal velocity"),
        Task("cheetah-height", "cheetah", 20, _torso(lambda x: x[..., 2]), doc="torso's height"),
        Task("cheetah-vspeed", "cheetah", 20, _torso(lambda x: x[..., 9].square()),
             doc="torso's squared vertical speed"),
        Task("cheetah-spin", "cheetah", 20, _torso(lambda x: x[..., 10:13].square().sum(-1)),
             doc="torso's squared angular speed"),
        Task("walker-forward", "walker", 20, _torso(lambda x: x[..., LINVEL][..., 0]),
             doc="torso's horizontal velocity"),
        Task("walker-height", "walker", 20, _torso(lambda x: x[..., 2]), doc="torso's height"),
        Task("walker-verticality", "walker", 20,
             _balance(("torso", "right_thigh", "right_leg", "left_thigh", "left_leg"), "walker"),
             doc="minus the angles of torso, thighs and legs from upright"),
        Task("walker-feet-to-head", "walker", 20, _walker_feet_to_head,
             doc="squared heights of the head above each foot"),
        Task("jaco-palm-pose", "jaco", 20, _jaco_pose(False), target="pose",
             doc="minus the palm's pose loss to a target pose"),
        Task("jaco-full-pose", "jaco", 20, _jaco_pose(True), target="poses",
             doc="minus the pose loss of every body to target poses"),
    ]
    t += dmc_tasks()   # the DeepMind Control Suite's, "dmc-<domain>-<task>" (gnwarp.control.dmc)
    return {x.name: x for x in t}


TASKS: dict[str, Task] = _tasks()


def task_names() -> list[str]:
    return list(TASKS)


_ALIASES = {"swimmer6": "dmc-swimmer-swimmer6"}


def get_task(name, system: str | None = None) -> Task:
    """The task ``name`` (a ``Task`` passes through); a name that is no task resolves to
    "dmc-" + name where that is one ("cheetah-run" -> "dmc-cheetah-run"; the paper's own names,
    e.g. "cartpole-balance", stay the paper's). With ``system``, also check it applies to that
    system. ``TaskError`` names the known tasks or the mismatch."""
    if isinstance(name, str) and name not in TASKS:
        name = _ALIASES.get(name, "dmc-" + name if "dmc-" + name in TASKS else name)
    task = name if isinstance(name, Task) else TASKS.get(name)
    if task is None:
        raise TaskError(f"unknown task {name!r}; known tasks: {', '.join(TASKS)}")
    if system is not None:
        task.check_system(system)
    return task


def sample_targets(task: Task, system, n: int, seed: int = 0, distance: float = 1.0) -> torch.Tensor | None:
    """Per-episode targets of ``task`` for ``system`` (a ``System``), float32, or None.

    Swimmer: positions [n, 3] ``distance`` m (default 1) from the origin in a random direction. JACO: the body states
    [n, B, 13] of random joint configurations (``gnwarp.data.initial_states``), reachable poses. DMC's reacher and
    swimmer: positions [n, 3] as the suite draws them (``gnwarp.control.dmc.sample_dmc_targets``; ``distance`` unused).
    """
    if task.target is None:
        return None
    rng = np.random.default_rng(seed)
    if task.suite == "dmc":
        return torch.tensor(sample_dmc_targets(task.name, n, rng), dtype=torch.float32)
    if task.target == "position":
        a = rng.uniform(-np.pi, np.pi, n)
        return torch.tensor(distance * np.stack([np.cos(a), np.sin(a), np.zeros(n)], -1), dtype=torch.float32)
    from gnwarp.data.generation import initial_states
    qpos, _ = initial_states(system, n, rng)
    m = system.model
    d = mujoco.MjData(m)
    out = []
    for q in qpos:
        d.qpos[:] = q
        d.qvel[:] = 0
        mujoco.mj_forward(m, d)
        out.append(body_states(m, d))
    poses = torch.tensor(np.stack(out), dtype=torch.float32)
    return poses[:, body_index(system.name, "hand")[0]] if task.target == "pose" else poses


def episode_starts(task: Task, system, n: int, seed) -> tuple[np.ndarray, np.ndarray, torch.Tensor | None]:
    """(qpos [n, nq], qvel [n, nv] float64, targets [n, ...] float32 or None) of ``n`` episodes of
    ``task`` on ``system`` (a ``System``): the task's ``initial`` (else
    ``gnwarp.data.generation.initial_states``) from a generator (``seed``: an int, or a numpy
    ``Generator`` drawn from in place), then the targets (``sample_targets``) seeded by a number
    drawn from that generator, so that targets are independent of the initial states (the same
    seed for both would tie, e.g., reacher's target angle to its shoulder angle)."""
    rng = np.random.default_rng(seed)   # a Generator passes through
    init = task.initial
    if init is None:
        from gnwarp.data.generation import initial_states as init
    qpos, qvel = init(system, n, rng)
    qpos = np.asarray(qpos, dtype=np.float64).reshape(n, -1)
    qvel = np.asarray(qvel, dtype=np.float64).reshape(n, -1)
    targets = None
    if task.target is not None:
        targets = sample_targets(task, system, n, seed=int(rng.integers(2 ** 63 - 1)))
    return qpos, qvel, targets
