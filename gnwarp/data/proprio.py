"""A partly observed JACO: the arm seen through proprioception only (paper C.3, D.7.3).

The paper's Real JACO data (joint angles as cosine and sine, and joint velocities, per body, every
40 ms, in place of the 13 state variables) does not exist here; this module builds its setting in
simulation. ``proprio_jaco`` makes the simulated arm variant, ``observe`` turns joint positions and
velocities into per-body observations, and ``ProprioData`` holds a dataset's observation sequences
with a ``GraphBuilder`` that makes input graphs from them::

    nodes = [static node features, cos q, sin q, qdot]   per body (the world: [.., 1, 0, 0])
    edges = [static edge features, controls]             as ``GraphBuilder`` makes them

    >>> from gnwarp.data import proprio
    >>> pd = proprio.ProprioData.simulate(proprio.proprio_jaco(), (64, 8, 8), num_steps=100, seed=0)
    >>> tr = pd.split("train")              # obs [S, T+1, B, 3], ctrl [S, T, U], instance [S]
    >>> g = pd.graphs(tr.instance, tr.obs[:, 0], tr.ctrl[:, 0])
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import torch

from gnwarp.data.builder import GraphBuilder
from gnwarp.graphs import GraphsTuple
from gnwarp.sim.systems import System, check_model, make

__all__ = ["OBS_NAMES", "OBS_SIZE", "proprio_jaco", "joint_of_body", "observe", "ProprioSplit", "ProprioData"]

OBS_NAMES = ("cos", "sin", "qvel")
OBS_SIZE = len(OBS_NAMES)


def proprio_jaco(lag: float = 0.2, servo_scale: float = 0.1, dt: float = 0.04) -> System:
    """The JACO (``make("jaco")``, 10 ms physics steps) recorded every ``dt`` (40 ms, as the Real
    JACO), with a hidden actuator state.

    What is added, and why: seen through proprioception the stock arm is nearly Markov: all its
    state is in (q, qdot), and its stiff velocity servos (kv = 500, a time constant armature/kv of
    ~8 ms) follow the commanded velocity within a physics step or two. A one-step model then has
    nothing to gain from memory, and recurrent vs feed-forward compares nothing. So each actuator
    gets (1) a first-order lag on its command (MuJoCo ``dyntype="filter"``, time constant ``lag``
    s; the filtered command is MuJoCo's ``act``, never observed) and (2) a softer servo (kv times
    ``servo_scale``: ~80 ms on the large joints), so that the joint velocity does not simply show
    the filtered command. ``lag=0`` leaves the commands unfiltered; ``servo_scale=1`` keeps kv.

    Measured with linear least squares on 64 sequences (fraction of the variance of the one-step
    change of the arm's joint velocities left unexplained, from the current observation and
    control / with two more past observations and controls): stock arm 0.21 / 0.19; lag 0.2 s
    with the stock servo 0.05 / 0.016; lag 0.2 s and kv / 10 (the default) 0.27 / 0.016.
    """
    if not (lag >= 0 and servo_scale > 0 and dt > 0):
        raise ValueError(f"need lag >= 0, servo_scale > 0 and dt > 0; got {lag}, {servo_scale}, {dt}")
    base = make("jaco")
    substeps = int(round(dt / base.timestep))
    if substeps < 1 or abs(substeps * base.timestep - dt) > 1e-9:
        raise ValueError(f"dt must be a multiple of the JACO's physics timestep {base.timestep}, got {dt}")
    spec = base.spec.copy()
    for act in spec.actuators:
        if lag > 0:
            act.dyntype = mujoco.mjtDyn.mjDYN_FILTER
            act.dynprm[0] = lag
        act.gainprm[0] *= servo_scale   # velocity servo: force = kv * (act - qdot)
        act.biasprm[2] *= servo_scale
    model = spec.compile()
    check_model(model, "jaco_proprio")
    return System(name="jaco_proprio", model=model, dt=float(dt), substeps=substeps,
                  params={"lag": float(lag), "servo_scale": float(servo_scale)}, source="builtin", spec=spec)


def joint_of_body(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(qpos address [nbody], dof address [nbody]) of each body's one hinge joint, -1 for bodies
    without a joint (the world). Bodies with several joints or a non-hinge joint raise ValueError:
    proprioception here is one angle per body."""
    qadr = np.full(model.nbody, -1, dtype=np.int64)
    vadr = np.full(model.nbody, -1, dtype=np.int64)
    for b in range(model.nbody):
        n = int(model.body_jntnum[b])
        if n == 0:
            continue
        j = int(model.body_jntadr[b])
        if n > 1 or int(model.jnt_type[j]) != mujoco.mjtJoint.mjJNT_HINGE:
            raise ValueError(f"body {b} ({mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)}) has {n} joint(s) "
                             "or a non-hinge joint; proprioceptive observations need one hinge per body")
        qadr[b], vadr[b] = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
    return qadr, vadr


def observe(qpos, qvel, model: mujoco.MjModel) -> torch.Tensor:
    """Proprioceptive observations: ``qpos`` [..., nq], ``qvel`` [..., nv] (numpy or torch) ->
    [..., nbody, 3] = (cos q, sin q, qdot) of each body's joint; (1, 0, 0) for bodies without one."""
    qpos, qvel = torch.as_tensor(np.asarray(qpos)), torch.as_tensor(np.asarray(qvel))
    qadr, vadr = (torch.as_tensor(a) for a in joint_of_body(model))
    has = qadr >= 0
    q = torch.where(has, qpos[..., qadr.clamp(min=0)], 0.0)
    v = torch.where(has, qvel[..., vadr.clamp(min=0)], 0.0)
    return torch.stack([torch.cos(q), torch.sin(q), v], -1).float()


@dataclasses.dataclass
class ProprioSplit:
    """One split's observation sequences: ``obs`` [S, T+1, B, 3], ``ctrl`` [S, T, U], ``instance`` [S]."""
    obs: torch.Tensor
    ctrl: torch.Tensor
    instance: torch.Tensor

    def __len__(self) -> int:
        return int(self.obs.shape[0])

    def to(self, device) -> "ProprioSplit":
        return ProprioSplit(self.obs.to(device), self.ctrl.to(device), self.instance.to(device))

    def windows(self, n: int, length: int, generator: torch.Generator | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` random windows of ``length`` observations: (obs [n, length, B, 3],
        ctrl [n, length-1, U], instance [n]), each from a random sequence and start, drawn on the
        generator's device (the CPU without one; a generator on the split's device: no host sync)."""
        S, T1 = self.obs.shape[:2]
        if not 2 <= length <= T1:
            raise ValueError(f"windows of {length} observations from sequences of {T1}")
        gdev = generator.device if generator is not None else torch.device("cpu")
        seq = torch.randint(0, S, (n,), generator=generator, device=gdev)
        start = torch.randint(0, T1 - length + 1, (n,), generator=generator, device=gdev)
        t = start[:, None] + torch.arange(length, device=gdev)
        dev = self.obs.device
        seq, t = seq.to(dev), t.to(dev)
        return self.obs[seq[:, None], t], self.ctrl[seq[:, None], t[:, :-1]], self.instance[seq]


class ProprioData:
    """A dataset's proprioceptive view: its splits as ``ProprioSplit``s and input graphs of
    observations (``graphs``). ``dataset``: a ``gnwarp.data.Dataset`` (its qpos, qvel, ctrl and
    static graphs); ``system``: the system it was simulated from (its joints map qpos to bodies;
    default ``make(dataset.meta["system"])``, which only knows built-in names)."""

    def __init__(self, dataset, system: System | None = None, device=None, dtype=torch.float32):
        self.dataset = dataset
        self.system = system if system is not None else make(dataset.meta["system"])
        if self.system.model.nbody != int(dataset.meta["max_bodies"]):
            raise ValueError(f"system '{self.system.name}' has {self.system.model.nbody} bodies, the dataset "
                             f"{dataset.meta['max_bodies']}")
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.builder = GraphBuilder(dataset.static, device=self.device, dtype=dtype)
        sizes = dataset.layout.sizes
        self.sizes = {"nodes": len(dataset.layout.node_names) + OBS_SIZE, "edges": sizes["edges"],
                      "globals": sizes["globals"]}
        self.movable = torch.as_tensor(joint_of_body(self.system.model)[0] >= 0)  # [B] bodies with a joint
        self._splits: dict[str, ProprioSplit] = {}

    @classmethod
    def simulate(cls, system: System, num_sequences, num_steps: int = 100, seed: int = 0,
                 backend: str = "auto", device=None) -> "ProprioData":
        """A fresh simulation of ``system`` (``gnwarp.data.generate``) seen through proprioception."""
        from gnwarp.data.generation import generate
        ds = generate(system, num_sequences, num_steps=num_steps, seed=seed, backend=backend, progress=False)
        return cls(ds, system, device)

    def split(self, name: str) -> ProprioSplit:
        """The observation sequences of split ``name`` (converted once, kept)."""
        if name not in self._splits:
            s = self.dataset[name]
            obs = observe(np.asarray(s.qpos[...], np.float64), np.asarray(s.qvel[...], np.float64), self.system.model)
            self._splits[name] = ProprioSplit(obs.to(self.device, self.builder.dtype),
                                              torch.as_tensor(np.asarray(s.ctrl[...]), dtype=self.builder.dtype,
                                                              device=self.device),
                                              torch.as_tensor(np.asarray(s.instance[...]), dtype=torch.int64,
                                                              device=self.device))
        return self._splits[name]

    def graphs(self, instance: torch.Tensor, obs: torch.Tensor, ctrl: torch.Tensor) -> GraphsTuple:
        """Input graphs of N observations: ``instance`` [N], ``obs`` [N, B, 3], ``ctrl`` [N, U]."""
        if obs.shape[-1] != OBS_SIZE:
            raise ValueError(f"observations must be [N, B, {OBS_SIZE}], got {tuple(obs.shape)}")
        return self.builder(instance, obs, ctrl)
