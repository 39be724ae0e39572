"""MuJoCo model and state -> graphs (paper, sections G.1 and G.2).

Bodies are nodes (the world included), joints are edges in both directions between the joint's
body and its parent body. The *static* graph holds model parameters; the *dynamic* graph holds
each body's absolute pose and world-frame velocities and, on each edge, the control of the
actuator that drives the joint. The conversion is generic over ``mujoco.MjModel``.

Feature columns carry names (``FeatureLayout``); a dataset keeps only the static columns that
vary over it and records the dropped ones with their constant value, so a model can map any
other dataset to the inputs it was trained on (``FeatureLayout.map_static``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import mujoco
import numpy as np

from gnwarp.graphs import GraphsTuple

# Dynamic node layout (13 per body): position, orientation (w, x, y, z), linear and angular
# velocity of the body frame in world coordinates (mj_objectVelocity(mjOBJ_XBODY, flg_local=0)).
DYN_NODE_NAMES = ("pos_x", "pos_y", "pos_z", "quat_w", "quat_x", "quat_y", "quat_z",
                  "linvel_x", "linvel_y", "linvel_z", "angvel_x", "angvel_y", "angvel_z")
POS, QUAT, LINVEL, ANGVEL = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)
DYN_NODE_SIZE = 13


def _enum_names(enum) -> list[str]:
    return [k for k in enum.__members__ if not k.startswith("mjN")]


def _onehot(values: np.ndarray, n: int) -> np.ndarray:
    values = np.asarray(values, dtype=np.int64)
    out = np.zeros(values.shape + (n,))
    np.put_along_axis(out, np.clip(values, 0, n - 1)[..., None], 1.0, axis=-1)
    return out


def _bits(flags: int, n: int) -> np.ndarray:
    return np.array([(int(flags) >> k) & 1 for k in range(n)], dtype=np.float64)


def _cols(prefix: str, n: int) -> list[str]:
    return [prefix] if n == 1 else [f"{prefix}_{k}" for k in range(n)]


# -- topology ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Topology:
    """Graph topology of a model: one edge pair per joint; actuators mapped onto joint edges."""
    nbody: int
    senders: np.ndarray          # [n_edge] body index
    receivers: np.ndarray        # [n_edge]
    edge_joint: np.ndarray       # [n_edge] joint index of each edge
    edge_direction: np.ndarray   # [n_edge] +1 parent->child, -1 child->parent
    edge_ctrl: np.ndarray        # [n_edge, n_slot] ctrl index driving the edge's joint (-1: none)
    global_ctrl: np.ndarray      # [n_gctrl] ctrl indices of actuators not on a joint (tendons, sites)

    @property
    def n_edge(self) -> int:
        return int(self.senders.shape[0])

    def graph(self) -> GraphsTuple:
        """A single-graph GraphsTuple with this topology and no features."""
        return GraphsTuple(nodes=None, edges=None, receivers=self.receivers.copy(), senders=self.senders.copy(),
                           globals=None, n_node=np.array([self.nbody]), n_edge=np.array([self.n_edge]))


def topology(model: mujoco.MjModel) -> Topology:
    jb = np.asarray(model.jnt_bodyid, dtype=np.int64)
    parent = np.asarray(model.body_parentid, dtype=np.int64)[jb]
    nj = model.njnt
    snd = np.concatenate([parent, jb])
    rcv = np.concatenate([jb, parent])
    joint = np.concatenate([np.arange(nj), np.arange(nj)])
    direction = np.concatenate([np.ones(nj), -np.ones(nj)])
    # actuators acting directly on a joint drive that joint's edges
    per_joint: list[list[int]] = [[] for _ in range(nj)]
    unmapped: list[int] = []
    ctrladr = np.asarray(getattr(model, "actuator_ctrladr", np.arange(model.nu)), dtype=np.int64)
    for a in range(model.nu):  # loop over actuators once per model, not per state
        trn = int(model.actuator_trntype[a])
        if trn in (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT):
            per_joint[int(model.actuator_trnid[a, 0])].append(int(ctrladr[a]))
        else:
            unmapped.append(int(ctrladr[a]))
    n_slot = max([1] + [len(p) for p in per_joint])
    ectrl = -np.ones((nj, n_slot), dtype=np.int64)
    for j, p in enumerate(per_joint):
        ectrl[j, :len(p)] = p
    return Topology(model.nbody, snd, rcv, joint, direction, np.concatenate([ectrl, ectrl]),
                    np.array(unmapped, dtype=np.int64))


# -- static graph ------------------------------------------------------------------------------

def static_global_features(model: mujoco.MjModel) -> tuple[np.ndarray, list[str]]:
    """[F_g] global features from ``model.opt`` (G.2) and their names."""
    o = model.opt
    ndis = len(_enum_names(mujoco.mjtDisableBit))
    nen = len(_enum_names(mujoco.mjtEnableBit))
    parts = [
        ("timestep", [o.timestep]), ("gravity", o.gravity), ("wind", o.wind), ("magnetic", o.magnetic),
        ("density", [o.density]), ("viscosity", [o.viscosity]), ("impratio", [o.impratio]),
        ("o_margin", [o.o_margin]), ("o_solref", o.o_solref), ("o_solimp", o.o_solimp),
        ("o_friction", o.o_friction),
        ("integrator", _onehot(o.integrator, len(_enum_names(mujoco.mjtIntegrator)))),
        ("cone", _onehot(o.cone, len(_enum_names(mujoco.mjtCone)))),
        ("enableflags", _bits(o.enableflags, nen)), ("disableflags", _bits(o.disableflags, ndis)),
    ]
    vals, names = [], []
    for n, v in parts:
        v = np.asarray(v, dtype=np.float64).reshape(-1)
        vals.append(v)
        names += _cols(n, v.size)
    return np.concatenate(vals), names


def static_node_features(model: mujoco.MjModel) -> tuple[np.ndarray, list[str]]:
    """[nbody, F_v] body features (G.2) and their names."""
    parts = [("body_mass", model.body_mass[:, None]), ("body_pos", model.body_pos),
             ("body_quat", model.body_quat), ("body_inertia", model.body_inertia),
             ("body_ipos", model.body_ipos), ("body_iquat", model.body_iquat)]
    names = sum((_cols(n, np.asarray(v).shape[1]) for n, v in parts), [])
    return np.concatenate([np.asarray(v, dtype=np.float64) for _, v in parts], 1), names


def static_edge_features(model: mujoco.MjModel, topo: Topology | None = None) -> tuple[np.ndarray, list[str]]:
    """[n_edge, F_e] joint (and driving actuator) features per directed edge (G.2), and names."""
    topo = topo or topology(model)
    j = topo.edge_joint
    # dof properties averaged over the joint's dofs
    dofnum = np.diff(np.append(model.jnt_dofadr, model.nv))
    jdof = np.repeat(np.arange(model.njnt), dofnum)

    def per_joint(x):
        s = np.zeros(model.njnt)
        np.add.at(s, jdof, np.asarray(x, dtype=np.float64))
        return s / np.maximum(dofnum, 1)

    jparts = [
        ("direction", topo.edge_direction[:, None]),
        ("motorized", (topo.edge_ctrl[:, :1] >= 0).astype(np.float64)),
        ("jnt_type", _onehot(model.jnt_type[j], len(_enum_names(mujoco.mjtJoint)))),
        ("jnt_axis", model.jnt_axis[j]), ("jnt_pos", model.jnt_pos[j]),
        ("jnt_solimp", model.jnt_solimp[j]), ("jnt_solref", model.jnt_solref[j]),
        ("jnt_stiffness", model.jnt_stiffness[j, None]), ("jnt_limited", model.jnt_limited[j, None]),
        ("jnt_range", model.jnt_range[j]), ("jnt_margin", model.jnt_margin[j, None]),
        ("dof_damping", per_joint(model.dof_damping)[j, None]),
        ("dof_armature", per_joint(model.dof_armature)[j, None]),
        ("dof_frictionloss", per_joint(model.dof_frictionloss)[j, None]),
    ]
    # actuator of the first slot of each edge (zeros where none)
    ctrladr = np.asarray(getattr(model, "actuator_ctrladr", np.arange(model.nu)), dtype=np.int64)
    ctrl_to_act = -np.ones(max(model.nu, int(ctrladr.max(initial=-1)) + 1), dtype=np.int64)
    ctrl_to_act[ctrladr] = np.arange(model.nu)
    first = topo.edge_ctrl[:, 0]
    act = np.where(first >= 0, ctrl_to_act[np.maximum(first, 0)] if model.nu else -1, -1)
    has = (act >= 0)[:, None].astype(np.float64)
    a = np.maximum(act, 0)

    def A(x, n=None):
        if model.nu == 0:
            return np.zeros((len(j), n if n is not None else np.asarray(x).shape[-1]))
        return np.asarray(x, dtype=np.float64).reshape(model.nu, -1)[a] * has

    aparts = [
        ("act_biastype", A(_onehot(model.actuator_biastype, len(_enum_names(mujoco.mjtBias))))),
        ("act_biasprm", A(model.actuator_biasprm)), ("act_cranklength", A(model.actuator_cranklength)),
        ("act_ctrllimited", A(model.actuator_ctrllimited)), ("act_ctrlrange", A(model.actuator_ctrlrange)),
        ("act_dyntype", A(_onehot(model.actuator_dyntype, len(_enum_names(mujoco.mjtDyn))))),
        ("act_dynprm", A(model.actuator_dynprm)), ("act_forcelimited", A(model.actuator_forcelimited)),
        ("act_forcerange", A(model.actuator_forcerange)),
        ("act_gaintype", A(_onehot(model.actuator_gaintype, len(_enum_names(mujoco.mjtGain))))),
        ("act_gainprm", A(model.actuator_gainprm)), ("act_gear", A(model.actuator_gear)),
        ("act_acc0", A(model.actuator_acc0)), ("act_length0", A(model.actuator_length0)),
        ("act_lengthrange", A(model.actuator_lengthrange)),
    ]
    vals, names = [], []
    for n, v in jparts + aparts:
        v = np.asarray(v, dtype=np.float64).reshape(len(j), -1)
        vals.append(v)
        names += _cols(n, v.shape[1])
    return np.concatenate(vals, 1), names


@dataclass
class StaticGraph:
    """Static graph of one model: features with column names, and its topology."""
    globals: np.ndarray       # [F_g]
    nodes: np.ndarray         # [nbody, F_v]
    edges: np.ndarray         # [n_edge, F_e]
    global_names: list[str]
    node_names: list[str]
    edge_names: list[str]
    topology: Topology


def static_graph(model: mujoco.MjModel) -> StaticGraph:
    topo = topology(model)
    g, gn = static_global_features(model)
    v, vn = static_node_features(model)
    e, en = static_edge_features(model, topo)
    return StaticGraph(g, v, e, gn, vn, en, topo)


# -- layouts ------------------------------------------------------------------------------------

@dataclass
class FeatureLayout:
    """Names of the kept static columns, and the dropped constant ones with their value.

    The dynamic layout is fixed: DYN_NODE_NAMES per node, ``n_ctrl_slots`` controls per edge,
    ``n_global_ctrl`` controls on the globals (actuators not on a joint).
    """
    global_names: list[str]
    node_names: list[str]
    edge_names: list[str]
    dropped: dict[str, dict[str, float]] = field(default_factory=lambda: {"globals": {}, "nodes": {}, "edges": {}})
    n_ctrl_slots: int = 1
    n_global_ctrl: int = 0

    @property
    def sizes(self) -> dict[str, int]:
        """Input sizes of the full (static + dynamic) graph."""
        return {"globals": len(self.global_names) + self.n_global_ctrl,
                "nodes": len(self.node_names) + DYN_NODE_SIZE,
                "edges": len(self.edge_names) + self.n_ctrl_slots}

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureLayout":
        return cls(**d)

    def map_static(self, other: "FeatureLayout", kind: str, values: np.ndarray) -> np.ndarray:
        """Map ``values`` [..., F] laid out as ``other`` to this layout; ``kind``: globals|nodes|edges.

        A column this layout keeps is taken from ``other`` where ``other`` kept it, else from
        ``other``'s dropped constant; a column neither has raises ValueError naming it.
        """
        attr = {"globals": "global_names", "nodes": "node_names", "edges": "edge_names"}[kind]
        mine = getattr(self, attr)
        theirs = {n: i for i, n in enumerate(getattr(other, attr))}
        const = other.dropped.get(kind, {})
        out = np.empty(values.shape[:-1] + (len(mine),), dtype=values.dtype)
        for k, n in enumerate(mine):
            if n in theirs:
                out[..., k] = values[..., theirs[n]]
            elif n in const:
                out[..., k] = const[n]
            else:
                raise ValueError(f"static {kind} feature '{n}' expected by the model is missing from the data")
        return out


def varying_columns(values: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Boolean [F]: which columns of values [..., F] are not constant over the valid rows."""
    flat = values.reshape(-1, values.shape[-1])
    if mask is not None:
        flat = flat[mask.reshape(-1)]
    if flat.shape[0] == 0:
        return np.zeros(values.shape[-1], dtype=bool)
    return ~np.all(flat == flat[:1], axis=0)


# -- dynamic graph ------------------------------------------------------------------------------

def body_states(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """[nbody, 13] dynamic node features of one MjData (after mj_forward / kinematics + velocities).

    Reference implementation on MuJoCo C; batched producers (the simulators) must agree with it.
    """
    out = np.zeros((model.nbody, DYN_NODE_SIZE))
    out[:, POS] = data.xpos
    out[:, QUAT] = data.xquat
    vel = np.zeros(6)
    for b in range(model.nbody):
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, b, vel, 0)
        out[b, LINVEL] = vel[3:]
        out[b, ANGVEL] = vel[:3]
    return out


def edge_controls(topo: Topology, ctrl: np.ndarray) -> np.ndarray:
    """[..., n_edge, n_slot] controls per edge from ctrl [..., nu] (0 where no actuator)."""
    idx = topo.edge_ctrl
    c = np.take(ctrl, np.maximum(idx, 0), axis=-1)
    return np.where(idx >= 0, c, 0.0)
