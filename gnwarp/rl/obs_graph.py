"""Observation graphs (supplementary Figure H.3): a DMC observation vector and its actions arranged
as a graph, batched for N environments by gathers on the observation's device (no loop per env).

The arrangement follows the model's kinematic tree (``DMCObservation``'s system):

- nodes: the bodies other than the world, in body order (swimmer6: the 6 links, head first);
  a node carries the observation entries named after its body;
- edges: every hinge between two bodies (not the root's joints), once from parent to child
  (direction feature +1) and once back (-1), the forward edges first (joint order), then the
  backward ones; an edge carries the entries named after its joint, then the force of its
  actuator (when actions are given: a Q-function's graph), then the direction;
- globals: every other entry, in observation order (the root's coordinates, the target).

  ========= ======================== ============================= ===========================
  domain    node features            edge features                 globals
  ========= ======================== ============================= ===========================
  swimmer6  vx, vy, wz (own frame)   angle, [force], direction     to_target x, y
  cheetah   one-hot body identity    angle, velocity, [force], dir rootz, rooty, their and
                                                                   rootx's velocities (5)
  walker    xx, xz of the rotation   velocity, [force], direction  height, root velocities (4)
  ========= ======================== ============================= ===========================

The cheetah's observation holds nothing per body, so its nodes carry a one-hot identity
(``identity=True`` adds one to any domain). Every observation entry appears in exactly one place
(``node_index``, ``edge_index``, ``global_index``; ``flat_features`` gathers the graph back).

    >>> og = ObservationGraph("swimmer6")
    >>> g = og(obs, action)          # obs [N, 25], action [N, 5] -> GraphsTuple of N graphs
    >>> a = og.edge_actions(per_edge_values)   # [N * 10, K] -> [N, 5, K] in actuator order
"""
from __future__ import annotations

import mujoco
import torch

from gnwarp.graphs import GraphsTuple, tile
from gnwarp.rl.observations import DMCObservation

__all__ = ["ObservationGraph"]


class ObservationGraph:
    """The Figure H.3 graph of a DMC observation (module docstring).

    ``observation``: a ``DMCObservation`` or a name it takes; ``identity``: one-hot body ids on
    the nodes (default: only where the nodes would carry no feature). Attributes: ``n_node`` V,
    ``n_joint`` J (edges: 2 J), ``nu`` U, ``obs_size`` D; ``node_size``, ``edge_size(with_action)``,
    ``global_size``; ``node_names``, ``edge_names``, ``global_names``; index tensors (CPU, int64)
    ``node_index`` [V, Fv], ``edge_index`` [J, Fe], ``global_index`` [Fu] into the observation,
    ``edge_actuator`` [J] (the actuator driving each joint, U for none), ``actuator_edge`` [U]
    (the joint each actuator drives); ``senders`` / ``receivers`` [2 J] of one graph."""

    def __init__(self, observation, identity: bool | None = None):
        self.observation = observation if isinstance(observation, DMCObservation) else DMCObservation(observation)
        ob = self.observation
        m = ob.model
        self.obs_size, self.nu = ob.size, int(m.nu)
        body = lambda b: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"body{b}"   # noqa: E731
        joint = lambda j: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"   # noqa: E731
        self.bodies = [body(b) for b in range(1, m.nbody)]
        self.n_node = len(self.bodies)
        hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
        self.joints = [j for j in range(m.njnt) if int(m.jnt_type[j]) == hinge and m.body_parentid[m.jnt_bodyid[j]] != 0]
        self.joint_names = [joint(j) for j in self.joints]
        self.n_joint = len(self.joints)
        if self.n_joint == 0:
            raise ValueError(f"{ob.system.name} has no joint between two bodies: no edges")
        child = [int(m.jnt_bodyid[j]) for j in self.joints]
        parent = [int(m.body_parentid[b]) for b in child]
        fwd_s = torch.tensor([p - 1 for p in parent], dtype=torch.int64)
        fwd_r = torch.tensor([c - 1 for c in child], dtype=torch.int64)
        self.senders = torch.cat([fwd_s, fwd_r])
        self.receivers = torch.cat([fwd_r, fwd_s])

        node_cols = {b: [] for b in self.bodies}
        edge_cols = {j: [] for j in self.joint_names}
        glob = []
        for i, name in enumerate(ob.names):
            parts = name.split(".")
            if len(parts) >= 3 and parts[1] in node_cols:            # "<key>.<body>.<field>"
                node_cols[parts[1]].append(i)
            elif len(parts) == 2 and parts[1] in edge_cols:          # "<key>.<joint>"
                edge_cols[parts[1]].append(i)
            else:
                glob.append(i)
        widths = {len(v) for v in node_cols.values()}
        if len(widths) != 1:
            raise ValueError(f"{ob.system.name}: bodies carry different numbers of observation entries")
        if len({len(v) for v in edge_cols.values()}) != 1:
            raise ValueError(f"{ob.system.name}: joints carry different numbers of observation entries")
        self.node_index = torch.tensor([node_cols[b] for b in self.bodies], dtype=torch.int64).reshape(self.n_node, -1)
        self.edge_index = torch.tensor([edge_cols[j] for j in self.joint_names], dtype=torch.int64).reshape(self.n_joint, -1)
        self.global_index = torch.tensor(glob, dtype=torch.int64)
        self.identity = bool(self.node_index.shape[1] == 0) if identity is None else bool(identity)
        if self.node_index.shape[1] == 0 and not self.identity:
            raise ValueError(f"{ob.system.name}'s nodes carry no observation entry: keep identity on")

        joint_of = {j: k for k, j in enumerate(self.joints)}
        self.edge_actuator = torch.full((self.n_joint,), self.nu, dtype=torch.int64)
        self.actuator_edge = torch.empty(self.nu, dtype=torch.int64)
        for u in range(self.nu):
            j = int(m.actuator_trnid[u, 0])
            if int(m.actuator_trntype[u]) != int(mujoco.mjtTrn.mjTRN_JOINT) or j not in joint_of:
                raise ValueError(f"{ob.system.name}: actuator {u} drives no joint between two bodies")
            if int(self.edge_actuator[joint_of[j]]) != self.nu:
                raise ValueError(f"{ob.system.name}: joint {joint(j)!r} has two actuators")
            self.edge_actuator[joint_of[j]] = u
            self.actuator_edge[u] = joint_of[j]

        fv = [f"{ob.names[i].split('.', 1)[0]}.{ob.names[i].rsplit('.', 1)[1]}" for i in self.node_index[0].tolist()]
        self.node_names = fv + ([f"is.{b}" for b in self.bodies] if self.identity else [])
        self.edge_obs_names = [ob.names[i].split(".", 1)[0] for i in self.edge_index[0].tolist()]
        self.global_names = [ob.names[i] for i in glob]
        self._templates: dict = {}

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def node_size(self) -> int:
        return len(self.node_names)

    def edge_size(self, with_action: bool) -> int:
        """Edge feature width: the joint's entries, its force when ``with_action``, the direction."""
        return len(self.edge_names(with_action))

    def edge_names(self, with_action: bool) -> list[str]:
        return self.edge_obs_names + (["force"] if with_action else []) + ["direction"]

    @property
    def global_size(self) -> int:
        return len(self.global_names)

    @property
    def n_edge(self) -> int:
        return 2 * self.n_joint

    def __deepcopy__(self, memo):
        # a fixed description of the model (its MjSpec does not copy): copies of networks share it
        return self

    def __repr__(self) -> str:
        return (f"ObservationGraph({self.observation.domain!r}, nodes={self.n_node}x{self.node_size}, "
                f"edges={self.n_edge}x({len(self.edge_obs_names)}+[force]+direction), globals={self.global_size})")

    # -- building ------------------------------------------------------------------------------
    def _template(self, device) -> dict:
        key = str(device)
        if key not in self._templates:
            self._templates[key] = {
                "graph": GraphsTuple(nodes=None, edges=None, receivers=self.receivers.to(device),
                                     senders=self.senders.to(device), globals=None,
                                     # counts on the host: ``tile`` reads them, and a read from the
                                     # device would sync (and break a CUDA-graph capture)
                                     n_node=torch.tensor([self.n_node]), n_edge=torch.tensor([self.n_edge])),
                "node": self.node_index.to(device), "edge": self.edge_index.to(device),
                "global": self.global_index.to(device), "act": self.edge_actuator.to(device),
                "act_edge": self.actuator_edge.to(device),
                "eye": torch.eye(self.n_node, device=device),
                "dir": torch.cat([torch.ones(self.n_joint, device=device), -torch.ones(self.n_joint, device=device)]),
            }
        return self._templates[key]

    def __call__(self, obs: torch.Tensor, action: torch.Tensor | None = None) -> GraphsTuple:
        """GraphsTuple of N graphs from observations [N, D] (and actions [N, U]: a Q-function's
        graph), features in ``obs``'s dtype on its device; differentiable in both."""
        if obs.ndim != 2 or obs.shape[1] != self.obs_size:
            raise ValueError(f"{self.observation.domain} observations must be [N, {self.obs_size}], "
                             f"got {tuple(obs.shape)}")
        n = obs.shape[0]
        t = self._template(obs.device)
        nodes = obs[:, t["node"]]                                        # [N, V, Fv]
        if self.identity:
            nodes = torch.cat([nodes, t["eye"].to(obs.dtype).expand(n, -1, -1)], -1)
        joint = obs[:, t["edge"]]                                        # [N, J, Fe]
        if action is not None:
            if action.ndim != 2 or action.shape != (n, self.nu):
                raise ValueError(f"actions must be [N={n}, {self.nu}], got {tuple(action.shape)}")
            padded = torch.cat([action.to(obs.dtype), action.new_zeros(n, 1, dtype=obs.dtype)], 1)
            joint = torch.cat([joint, padded[:, t["act"], None]], -1)
        edges = torch.cat([joint.repeat(1, 2, 1), t["dir"].to(obs.dtype)[None, :, None].expand(n, -1, 1)], -1)
        return tile(t["graph"], n, nodes=nodes, edges=edges, globals=obs[:, t["global"]])

    # -- reading back --------------------------------------------------------------------------
    def edge_actions(self, values: torch.Tensor) -> torch.Tensor:
        """Per-edge values [N * 2 J, K] of a batch's graphs -> [N, U, K] in actuator order, read
        from each joint's forward (parent to child) edge."""
        if values.ndim != 2 or values.shape[0] % self.n_edge:
            raise ValueError(f"per-edge values must be [N * {self.n_edge}, K], got {tuple(values.shape)}")
        n = values.shape[0] // self.n_edge
        per_graph = values.reshape(n, self.n_edge, values.shape[1])
        return per_graph[:, self._template(values.device)["act_edge"]]

    def flat_features(self, g: GraphsTuple) -> torch.Tensor:
        """The observations [N, D] gathered back from a graph of ``__call__``'s layout (node,
        forward edge and global features in their observation places)."""
        n = g.globals.shape[0]
        t = self._template(g.globals.device)
        out = g.globals.new_zeros(n, self.obs_size)
        fv = self.node_index.shape[1]
        out[:, t["node"].reshape(-1)] = g.nodes.reshape(n, self.n_node, -1)[:, :, :fv].reshape(n, -1)
        fe = self.edge_index.shape[1]
        out[:, t["edge"].reshape(-1)] = g.edges.reshape(n, self.n_edge, -1)[:, :self.n_joint, :fe].reshape(n, -1)
        out[:, t["global"]] = g.globals
        return out
