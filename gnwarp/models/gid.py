"""G_ID as a value (paper D.2, D.3): the latent static graph a ``SysIDModel`` identifies, saved
and loaded with its checksum (``save_gid`` / ``load_gid``), and held fixed in place of the static
graph for rollout engines and planners (``FixedGIDModel``, from ``SysIDModel.with_fixed_gid``).
A G_ID that is missing, corrupt or of another model's widths or topology raises ``GIDError``."""
from __future__ import annotations

from pathlib import Path

import torch

from gnwarp.data.builder import GraphTemplate
from gnwarp.files import atomic_write, tensor_digest
from gnwarp.graphs import GraphsTuple
from gnwarp.models.recurrent import KINDS
from gnwarp.models.rollout import RolloutEngine, RolloutInputs

__all__ = ["GIDError", "FixedGIDModel", "save_gid", "load_gid"]


class GIDError(ValueError):
    """A G_ID file that is missing, corrupt or not a G_ID; or a G_ID that does not fit a rollout."""


class FixedGIDModel:
    """A ``SysIDModel`` whose static graph is one fixed G_ID (``SysIDModel.with_fixed_gid``):
    ``template``, ``context``, ``next_nodes``, ``rollout_inputs``, ``bind`` and ``rollout_engine``
    as a ``ForwardModel``'s (the ``gnwarp.dynamics.Dynamics`` protocol), so ``RolloutEngine``
    (captured forward and adjoint backward) and ``GradientMPC`` run on it. The G_ID's graphs must be the rollouts' (checked when a template
    is made: ``GIDError``)."""

    def __init__(self, model, g_id: GraphsTuple):   # model: a SysIDModel (which imports this module)
        if not isinstance(g_id, GraphsTuple):
            raise GIDError(f"g_id must be a GraphsTuple (from identify or load_gid), got {type(g_id).__name__}")
        self.sysid = model
        dev, dt = model.device, model.dtype
        self.g_id = g_id._replace(**{k: None if getattr(g_id, k) is None else getattr(g_id, k).to(dev, dt)
                                     for k in KINDS})
        self.layout = model.layout
        self.checkpoint_info = getattr(model, "checkpoint_info", None)

    @property
    def builder(self):
        return self.sysid.builder

    @property
    def device(self) -> torch.device:
        return self.sysid.device

    @property
    def dtype(self) -> torch.dtype:
        return self.sysid.dtype

    @property
    def core(self):
        """The forward model's core (a ``RolloutEngine`` asks it which block outputs to keep)."""
        return self.sysid.forward_model.core

    def bind(self, source, strict: bool = True) -> "FixedGIDModel":
        self.sysid.bind(source, strict)
        return self

    def parameters(self):
        """The underlying ``SysIDModel``'s parameters (a rollout engine's backward freezes them)."""
        return self.sysid.parameters()

    def template(self, instance, builder=None) -> GraphTemplate:
        builder = builder if builder is not None else self.sysid.builder
        if builder is None:
            raise ValueError("no graphs to read: call model.bind(dataset_or_system) first")
        tmpl = GraphTemplate(builder, torch.as_tensor(instance))
        self.sysid.check_gid(self.g_id, tmpl.topology)
        return tmpl

    def context(self, graph: GraphsTuple, stats: bool = True):
        return self.sysid.forward_model.context(self.sysid.with_gid(graph, self.g_id), stats)

    def next_nodes(self, graph: GraphsTuple, ctx=None) -> torch.Tensor:
        return self.sysid.forward_model.next_nodes(self.sysid.with_gid(graph, self.g_id), ctx)

    def rollout_inputs(self, template: GraphTemplate, n_ctrl: int | None, ctrl_policy: str = "clamp",
                       check: bool = True, builder=None) -> RolloutInputs:
        """Checks and control clamping of rollouts over ``template`` (``RolloutEngine`` reads
        them here): the actuators' ranges come from the bound source (``SysIDModel.rollout_inputs``),
        so a template of another ``builder`` takes only ``ctrl_policy="none"`` (ValueError)."""
        if builder is not None and builder is not self.builder:
            if ctrl_policy != "none":
                raise ValueError("this model reads the actuator ranges from its bound source: bind it to that "
                                 "source, or pass ctrl_policy='none' with another builder")
            return RolloutInputs(template, self.layout, n_ctrl, ctrl_policy, check)
        return self.sysid.rollout_inputs(template.instance, n_ctrl, ctrl_policy, check)

    def rollout_engine(self, instance, horizon: int, builder=None, ctrl_policy: str = "clamp", check: bool = True,
                       graphs: bool = True, store: bool | str = "auto", store_bytes: int | None = None,
                       fused: bool | None = None) -> RolloutEngine:
        """A ``RolloutEngine`` on the fixed G_ID; controls clamped to the bound source's actuator
        ranges (``ctrl_policy``), which are read from the bound source only: another ``builder``
        needs ``ctrl_policy="none"``. Its steps are never fused (``fused=True`` raises; the fused
        step reads the static graph, not a G_ID)."""
        return RolloutEngine(self, instance, horizon, builder, ctrl_policy=ctrl_policy, check=check, graphs=graphs,
                             store=store, store_bytes=store_bytes, fused=fused)


# -- G_ID files -----------------------------------------------------------------------------------
GID_FORMAT, GID_VERSION = "gnwarp-gid", 1
_FIELDS = ("nodes", "edges", "globals", "senders", "receivers", "n_node", "n_edge")


def _digest(tensors: dict) -> str:
    return tensor_digest(tensors, _FIELDS)


def save_gid(path, g_id: GraphsTuple) -> Path:
    """Write G_ID to ``path`` (``torch.save`` of plain tensors and its sha256), atomically."""
    path = Path(path)
    tensors = {k: (torch.zeros(0) if getattr(g_id, k) is None else getattr(g_id, k)).detach().cpu().contiguous()
               for k in _FIELDS}
    payload = {"format": GID_FORMAT, "version": GID_VERSION, "tensors": tensors, "sha256": _digest(tensors),
               "none": [k for k in KINDS if getattr(g_id, k) is None]}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as tmp:
        torch.save(payload, tmp)
    return path


def load_gid(path, device=None) -> GraphsTuple:
    """A G_ID written by ``save_gid``, read with ``weights_only=True`` and checked: format,
    checksum, shapes consistent with its topology, finite values. Raises ``GIDError``."""
    path = Path(path)
    try:
        p = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - missing, truncated or not a tensor file
        raise GIDError(f"{path}: cannot read a G_ID ({type(e).__name__}: {e})") from None
    if not isinstance(p, dict) or p.get("format") != GID_FORMAT or not isinstance(p.get("tensors"), dict):
        raise GIDError(f"{path} is not a G_ID file (format {p.get('format') if isinstance(p, dict) else None!r})")
    if int(p.get("version", -1)) > GID_VERSION:
        raise GIDError(f"{path} has G_ID version {p.get('version')}, newer than this gnwarp ({GID_VERSION})")
    t = p["tensors"]
    if set(t) != set(_FIELDS) or not all(isinstance(v, torch.Tensor) for v in t.values()):
        raise GIDError(f"{path}: a G_ID holds the tensors {_FIELDS}, got {sorted(t)}")
    if _digest(t) != p.get("sha256"):
        raise GIDError(f"{path} is corrupt: its tensors do not match their checksum")
    none = set(p.get("none", []))
    n_node, n_edge = t["n_node"].long(), t["n_edge"].long()
    rows = {"nodes": int(n_node.sum()), "edges": int(n_edge.sum()), "globals": n_node.shape[0]}
    for k in KINDS:
        if k not in none and (t[k].ndim != 2 or t[k].shape[0] != rows[k] or not t[k].is_floating_point()):
            raise GIDError(f"{path}: G_ID {k} of shape {tuple(t[k].shape)} do not fit its topology ({rows[k]} rows)")
        if k not in none and not bool(torch.isfinite(t[k]).all()):
            raise GIDError(f"{path}: G_ID {k} hold NaN or Inf")
    if t["senders"].shape != t["receivers"].shape or t["senders"].shape[0] != rows["edges"]:
        raise GIDError(f"{path}: G_ID senders / receivers do not fit its {rows['edges']} edges")
    g = GraphsTuple(**{k: (None if k in none else v.to(device)) for k, v in t.items()})
    return g
