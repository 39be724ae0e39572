"""Which static columns a model reads: feature layouts, and data mapped onto them.

A dataset keeps only the static feature columns that vary over its system instances and records
the dropped ones with their constant value (``FeatureLayout``, built by
``gnwarp.data.convert.static_arrays``). A model trained on it keeps that layout, several datasets
trained on together get one merged layout (``merge_layouts``), and any other data is mapped onto
a model's layout by column name (``map_static``), or refused with ``LayoutMismatchError``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from gnwarp.state import DYN_NODE_SIZE

__all__ = ["FeatureLayout", "varying_columns", "merge_layouts", "map_static", "LayoutMismatchError"]

# the layout's attribute of the column names of each kind of static feature
_NAMES = {"globals": "global_names", "nodes": "node_names", "edges": "edge_names"}


@dataclass
class FeatureLayout:
    """Names of the kept static columns, and the dropped constant ones with their value.

    The dynamic layout is fixed: DYN_NODE_NAMES per node, ``n_ctrl_slots`` controls per edge,
    ``n_global_ctrl`` controls on the globals (actuators on no joint edge: 0 wherever
    ``gnwarp.data.convert`` made the layout, which refuses such actuators; models refuse layouts
    with any).
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
        attr = _NAMES[kind]
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


class LayoutMismatchError(ValueError):
    """Data whose static features cannot be mapped onto a model's feature layout."""


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-5 * max(1.0, abs(a), abs(b))  # datasets store static features as float32


def map_static(layout: FeatureLayout, data_layout: FeatureLayout, static: dict, strict: bool = True) -> dict:
    """A dataset's ``static`` arrays laid out as ``layout`` (a model's).

    Kept columns are mapped by name (``FeatureLayout.map_static``). ``strict``: also refuse data
    where a column the model saw as constant has another value (the model could not tell the
    difference), e.g. a Pendulum model on Cartpole data. Raises ``LayoutMismatchError``.
    """
    if data_layout.n_ctrl_slots > layout.n_ctrl_slots:
        raise LayoutMismatchError(f"the data has {data_layout.n_ctrl_slots} control slots per edge, the model "
                                  f"{layout.n_ctrl_slots}")
    if strict:
        bad = []
        for kind, attr in _NAMES.items():
            theirs = set(getattr(data_layout, attr))
            const = data_layout.dropped.get(kind, {})
            for name, v in layout.dropped.get(kind, {}).items():
                if name in theirs:
                    bad.append(f"{kind}.{name} (constant {v:g} for the model, varying in the data)")
                elif name in const and not _close(const[name], v):
                    bad.append(f"{kind}.{name} (model: {v:g}, data: {const[name]:g})")
        if bad:
            more = f" and {len(bad) - 8} more" if len(bad) > 8 else ""
            raise LayoutMismatchError("the data's static features do not match the model's feature layout: "
                                      + "; ".join(bad[:8]) + more)
    out = dict(static)
    try:
        for kind in _NAMES:
            out[kind] = layout.map_static(data_layout, kind, np.asarray(static[kind][...])).astype(np.float32)
    except ValueError as e:
        raise LayoutMismatchError(f"the data does not fit the model's feature layout: {e}") from None
    ec = np.asarray(static["edge_ctrl"][...])
    if ec.shape[-1] < layout.n_ctrl_slots:  # fewer actuators per joint than the model's data had
        pad = -np.ones(ec.shape[:-1] + (layout.n_ctrl_slots - ec.shape[-1],), dtype=ec.dtype)
        out["edge_ctrl"] = np.concatenate([ec, pad], -1)
        if "edge_ctrl_gain" in static:
            gain = np.asarray(static["edge_ctrl_gain"][...])
            out["edge_ctrl_gain"] = np.concatenate([gain, np.zeros(pad.shape, dtype=gain.dtype)], -1)
    return out


def merge_layouts(layouts: list[FeatureLayout]) -> FeatureLayout:
    """One layout for several datasets: a column is kept if any dataset keeps it or the datasets'
    constants for it differ; the rest stay dropped with their common constant."""
    if len(layouts) == 1:
        return layouts[0]
    out = {}
    dropped = {}
    for kind, attr in _NAMES.items():
        order: list[str] = []
        for lay in layouts:
            for n in list(getattr(lay, attr)) + list(lay.dropped.get(kind, {})):
                if n not in order:
                    order.append(n)
        keep, const = [], {}
        for n in order:
            vals = [lay.dropped.get(kind, {}).get(n) for lay in layouts]
            if any(n in getattr(lay, attr) for lay in layouts) or len({v for v in vals}) > 1:
                if all(n in getattr(lay, attr) or n in lay.dropped.get(kind, {}) for lay in layouts):
                    keep.append(n)
                else:
                    raise LayoutMismatchError(f"static {kind} feature '{n}' is missing from some of the datasets")
            else:
                const[n] = vals[0]
        out[attr] = keep
        dropped[kind] = const
    return FeatureLayout(out["global_names"], out["node_names"], out["edge_names"], dropped,
                         n_ctrl_slots=max(lay.n_ctrl_slots for lay in layouts),
                         n_global_ctrl=max(lay.n_global_ctrl for lay in layouts))
