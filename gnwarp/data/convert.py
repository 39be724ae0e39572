"""MuJoCo model and state -> graphs (paper, sections G.1 and G.2).

Bodies are nodes (the world included), joints are edges in both directions between the joint's
body and its parent body. The *static* graph holds model parameters; the *dynamic* graph holds
each body's absolute pose and world-frame velocities and, on each edge, the control of the
actuator that drives the joint (the body states themselves are read by ``gnwarp.sim.body_state``).
An actuator on a fixed tendon (joint wraps only) drives the edges of every joint its tendon spans,
its control weighted there by the joint's tendon coefficient; actuators of other transmissions
(sites, bodies, slider-cranks, spatial tendons) are refused (``check_actuators``).
The conversion is generic over ``mujoco.MjModel``.

Feature columns carry names; ``static_arrays`` pads the static graphs of several system instances
and keeps only the columns that vary over them, recording the dropped ones in a ``FeatureLayout``
(``gnwarp.data.layout``) with their constant value.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from gnwarp.data.layout import FeatureLayout, varying_columns
from gnwarp.graphs import GraphsTuple

__all__ = ["UnsupportedActuatorError", "unsupported_actuators", "check_actuators", "Topology", "topology", "static_global_features", "static_node_features", "static_edge_features",
           "StaticGraph", "static_graph", "static_arrays", "edge_controls"]


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

_JOINT_TRN = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))
_TENDON_TRN = int(mujoco.mjtTrn.mjTRN_TENDON)
_WRAP_JOINT = int(mujoco.mjtWrap.mjWRAP_JOINT)


class UnsupportedActuatorError(ValueError):
    """A model has an actuator whose transmission the graph cannot carry (a control on no joint edge)."""


def _name(model: mujoco.MjModel, obj, i: int, kind: str) -> str:
    n = mujoco.mj_id2name(model, obj, int(i))
    return f"{kind} {i} {n!r}" if n else f"{kind} {i}"


def _trn_name(trn: int) -> str:
    try:
        return mujoco.mjtTrn(trn).name.removeprefix("mjTRN_").lower()
    except ValueError:
        return f"type {trn}"


def _tendon_joints(model: mujoco.MjModel, tendon: int) -> dict[int, float] | None:
    """{joint: summed coefficient} of a fixed tendon (every wrap a joint), None for a spatial one."""
    adr, num = int(model.tendon_adr[tendon]), int(model.tendon_num[tendon])
    out: dict[int, float] = {}
    for w in range(adr, adr + num):  # a tendon's few wraps, once per model
        if int(model.wrap_type[w]) != _WRAP_JOINT:
            return None
        j = int(model.wrap_objid[w])
        out[j] = out.get(j, 0.0) + float(model.wrap_prm[w])
    return out


def unsupported_actuators(model: mujoco.MjModel) -> list[str]:
    """Descriptions of the actuators whose control the graph cannot carry: transmissions other than
    a joint or a fixed tendon (site, body, slider-crank, spatial tendon), each naming the actuator,
    its transmission and, for a tendon, the wrap that is not a joint. Empty when all are carried."""
    out = []
    for a in range(model.nu):  # loop over actuators once per model
        trn = int(model.actuator_trntype[a])
        if trn in _JOINT_TRN:
            continue
        act = _name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator")
        if trn == _TENDON_TRN:
            t = int(model.actuator_trnid[a, 0])
            if _tendon_joints(model, t) is not None:
                continue
            kinds = sorted({mujoco.mjtWrap(int(k)).name.removeprefix("mjWRAP_").lower()
                            for k in model.wrap_type[model.tendon_adr[t]:model.tendon_adr[t] + model.tendon_num[t]]
                            if int(k) != _WRAP_JOINT})
            out.append(f"{act} drives spatial {_name(model, mujoco.mjtObj.mjOBJ_TENDON, t, 'tendon')} (it wraps "
                       f"{', '.join(kinds)}, not only joints)")
        else:
            out.append(f"{act} has a {_trn_name(trn)} transmission")
    return out


def check_actuators(model: mujoco.MjModel, where: str = "model") -> None:
    """Raise ``UnsupportedActuatorError`` naming ``where`` and every actuator whose control the graph
    cannot carry (``unsupported_actuators``); the graph carries actuators on joints and on fixed
    tendons (joint wraps only)."""
    bad = unsupported_actuators(model)
    if bad:
        raise UnsupportedActuatorError(
            f"{where}: {len(bad)} actuator(s) the graph cannot carry: " + "; ".join(bad) + ". Supported "
            "transmissions: joint and jointinparent (the control on the joint's edges) and fixed tendons, whose "
            "wraps are all joints (the control times each joint's coefficient on that joint's edges)")


@dataclass(frozen=True)
class Topology:
    """Graph topology of a model: one edge pair per joint; actuators mapped onto joint edges."""
    nbody: int
    senders: np.ndarray          # [n_edge] body index
    receivers: np.ndarray        # [n_edge]
    edge_joint: np.ndarray       # [n_edge] joint index of each edge
    edge_direction: np.ndarray   # [n_edge] +1 parent->child, -1 child->parent
    edge_ctrl: np.ndarray        # [n_edge, n_slot] ctrl index driving the edge's joint (-1: none)
    # [n_edge, n_slot] weight of each slot's control (a tendon's coefficient on the joint, 1 for a
    # joint actuator, 0 where none); None when no actuator drives a tendon (every weight 1)
    edge_ctrl_gain: np.ndarray | None = None

    @property
    def n_edge(self) -> int:
        return int(self.senders.shape[0])

    def graph(self) -> GraphsTuple:
        """A single-graph GraphsTuple with this topology and no features."""
        return GraphsTuple(nodes=None, edges=None, receivers=self.receivers.copy(), senders=self.senders.copy(),
                           globals=None, n_node=np.array([self.nbody]), n_edge=np.array([self.n_edge]))


def topology(model: mujoco.MjModel) -> Topology:
    """The graph topology of ``model``: joint actuators on their joint's edges (earlier slots),
    then fixed-tendon actuators on the edges of each joint their tendon spans, in actuator order.
    Raises ``UnsupportedActuatorError`` for actuators of other transmissions."""
    check_actuators(model)
    jb = np.asarray(model.jnt_bodyid, dtype=np.int64)
    parent = np.asarray(model.body_parentid, dtype=np.int64)[jb]
    nj = model.njnt
    snd = np.concatenate([parent, jb])
    rcv = np.concatenate([jb, parent])
    joint = np.concatenate([np.arange(nj), np.arange(nj)])
    direction = np.concatenate([np.ones(nj), -np.ones(nj)])
    per_joint: list[list[tuple[int, float]]] = [[] for _ in range(nj)]
    tendon: list[tuple[int, dict[int, float]]] = []
    ctrladr = np.asarray(getattr(model, "actuator_ctrladr", np.arange(model.nu)), dtype=np.int64)
    for a in range(model.nu):  # loop over actuators once per model, not per state
        if int(model.actuator_trntype[a]) in _JOINT_TRN:
            per_joint[int(model.actuator_trnid[a, 0])].append((int(ctrladr[a]), 1.0))
        else:  # a fixed tendon (check_actuators refused the rest)
            tendon.append((int(ctrladr[a]), _tendon_joints(model, int(model.actuator_trnid[a, 0]))))
    for c, coef in tendon:  # after every joint actuator: a joint's own actuator keeps the first slot
        for j, w in coef.items():
            if w != 0.0:
                per_joint[j].append((c, w))
    n_slot = max([1] + [len(p) for p in per_joint])
    ectrl = -np.ones((nj, n_slot), dtype=np.int64)
    gain = np.zeros((nj, n_slot))
    for j, p in enumerate(per_joint):
        for k, (c, w) in enumerate(p):
            ectrl[j, k], gain[j, k] = c, w
    return Topology(model.nbody, snd, rcv, joint, direction, np.concatenate([ectrl, ectrl]),
                    np.concatenate([gain, gain]) if tendon else None)


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


def static_arrays(instances) -> tuple[dict[str, np.ndarray], FeatureLayout, dict]:
    """Static graphs of several system instances (``System``s of one family), padded to the most
    bodies B and edges E, the columns constant over all of them dropped.

    Returns (static, layout, meta): ``static`` the arrays of a dataset's ``/static`` group
    (globals [I, F_g], nodes [I, B, F_v], edges [I, E, F_e] float32; senders, receivers [I, E] and
    edge_ctrl [I, E, K] int64, -1 = padding or none; n_node, n_edge [I]; and, only where an
    actuator drives a tendon, edge_ctrl_gain [I, E, K] float32, each slot's control weight, 0 where
    none), ``layout`` the ``FeatureLayout`` of the kept columns, ``meta`` {"n_global_ctrl" (0:
    every actuator is on joint edges), "full_sizes"}.
    """
    graphs = [static_graph(s.model) for s in instances]
    g0 = graphs[0]
    I = len(graphs)
    B = max(g.nodes.shape[0] for g in graphs)
    E = max(g.edges.shape[0] for g in graphs)
    K = max(g.topology.edge_ctrl.shape[1] for g in graphs)
    Fg, Fv, Fe = g0.globals.shape[0], g0.nodes.shape[1], g0.edges.shape[1]
    glob = np.stack([g.globals for g in graphs])
    nodes = np.zeros((I, B, Fv))
    edges = np.zeros((I, E, Fe))
    snd = -np.ones((I, E), dtype=np.int64)
    rcv = -np.ones((I, E), dtype=np.int64)
    ectrl = -np.ones((I, E, K), dtype=np.int64)
    gained = any(g.topology.edge_ctrl_gain is not None for g in graphs)
    gain = np.zeros((I, E, K))
    n_node = np.zeros(I, dtype=np.int64)
    n_edge = np.zeros(I, dtype=np.int64)
    for i, g in enumerate(graphs):  # one row per system instance, not per state
        nb, ne = g.nodes.shape[0], g.edges.shape[0]
        nodes[i, :nb], edges[i, :ne] = g.nodes, g.edges
        snd[i, :ne], rcv[i, :ne] = g.topology.senders, g.topology.receivers
        ec = g.topology.edge_ctrl
        ectrl[i, :ne, :ec.shape[1]] = ec
        gain[i, :ne, :ec.shape[1]] = (g.topology.edge_ctrl_gain if g.topology.edge_ctrl_gain is not None
                                      else (ec >= 0).astype(np.float64))
        n_node[i], n_edge[i] = nb, ne
    node_mask = np.arange(B)[None] < n_node[:, None]
    edge_mask = np.arange(E)[None] < n_edge[:, None]
    kg = varying_columns(glob)
    kv = varying_columns(nodes, node_mask)
    ke = varying_columns(edges, edge_mask)

    def dropped(names, keep, vals, mask=None):
        flat = vals.reshape(-1, vals.shape[-1])
        row = flat[mask.reshape(-1)][0] if mask is not None else flat[0]
        return {n: float(row[k]) for k, n in enumerate(names) if not keep[k]}

    layout = FeatureLayout(
        global_names=[n for n, k in zip(g0.global_names, kg) if k],
        node_names=[n for n, k in zip(g0.node_names, kv) if k],
        edge_names=[n for n, k in zip(g0.edge_names, ke) if k],
        dropped={"globals": dropped(g0.global_names, kg, glob),
                 "nodes": dropped(g0.node_names, kv, nodes, node_mask),
                 "edges": dropped(g0.edge_names, ke, edges, edge_mask)},
        n_ctrl_slots=K, n_global_ctrl=0)
    static = {"globals": glob[:, kg].astype(np.float32), "nodes": nodes[..., kv].astype(np.float32),
              "edges": edges[..., ke].astype(np.float32), "senders": snd, "receivers": rcv,
              "n_node": n_node, "n_edge": n_edge, "edge_ctrl": ectrl}
    if gained:  # only then: the static arrays of joint-actuated systems keep their format
        static["edge_ctrl_gain"] = gain.astype(np.float32)
    meta = {"n_global_ctrl": 0, "full_sizes": {"globals": Fg, "nodes": Fv, "edges": Fe}}
    return static, layout, meta


# -- dynamic graph ------------------------------------------------------------------------------

def edge_controls(topo: Topology, ctrl: np.ndarray) -> np.ndarray:
    """[..., n_edge, n_slot] controls per edge from ctrl [..., nu] (0 where no actuator; a tendon
    actuator's control times the joint's coefficient). The numpy reference of
    ``gnwarp.data.builder.edge_control_values``, which input graphs are built with."""
    idx = topo.edge_ctrl
    c = np.take(ctrl, np.maximum(idx, 0), axis=-1)
    if topo.edge_ctrl_gain is not None:
        c = c * topo.edge_ctrl_gain
    return np.where(idx >= 0, c, 0.0)
