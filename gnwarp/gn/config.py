"""Sizes and switches of one GN block (graph_nets style), and the column layout of its MLPs'
first layers: one source of truth for which inputs each update reads.

Also the validation every gnwarp configuration shares (``GNBlockConfig``, ``RunOptions``,
``ModelConfig``, ``TrainConfig``): each dataclass field's annotation says what it allows (pydantic
types with constraints, e.g. ``PositiveInt``), ``check_fields`` validates a config against its
annotations in ``__post_init__``, and every refusal is one ``ConfigError`` that names the key path
(``model.gn.latent``) and the allowed values, whether the value came from Python, a config file or
``gnwarp train --set``.
"""
from __future__ import annotations

import dataclasses
import sys
import types
import typing
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, Sequence, Union

import numpy as np
import pydantic
from pydantic import BeforeValidator, Field, Strict

__all__ = ["EdgeBlockConfig", "NodeBlockConfig", "GlobalBlockConfig", "GNBlockConfig", "column_slices",
           "layout_width", "pad", "ConfigError", "Allowed", "check_fields", "check_keys", "allowed_values",
           "MAX_WIDTH", "MAX_LAYERS", "IntRange", "FloatRange", "Flag", "Count", "PositiveInt", "PositiveFloat",
           "InputWidth", "Width", "Widths", "LayerCount"]


# -- validation of configurations ------------------------------------------------------------------
class ConfigError(ValueError):
    """A refused configuration value: ``path`` is the key (dotted through nested configs:
    ``model.gn.latent``; empty for a whole-config problem), ``reason`` what is wrong, with the
    allowed values."""

    def __init__(self, path: str, reason: str):
        self.path, self.reason = path, reason
        super().__init__(f"{path}: {reason}" if path else reason)

    def __reduce__(self):
        return type(self), (self.path, self.reason)

    def within(self, prefix: str) -> "ConfigError":
        """The same error seen from the config that holds this one under key ``prefix``."""
        return type(self)(f"{prefix}.{self.path}" if self.path else prefix, self.reason)


@dataclass(frozen=True)
class Allowed:
    """Annotation metadata: how a refusal describes the allowed values (``Annotated[int, ...,
    Allowed("an integer >= 1")]``)."""
    text: str


def _no_bool(v):
    if isinstance(v, (bool, np.bool_)):  # pydantic reads True as 1; a config never means that
        raise ValueError("a boolean is not a number")
    return v


def _plain_bool(v):
    return bool(v) if isinstance(v, np.bool_) else v


def _bounds(lo, hi, gt=None) -> str:
    n = lambda x: str(x) if isinstance(x, int) else f"{x:g}"  # noqa: E731
    if gt is not None:
        return f"> {n(gt)}" + (f" and <= {n(hi)}" if hi is not None else "")
    if hi is None:
        return f">= {n(lo)}"
    return f"from {n(lo)} to {n(hi)}"


def IntRange(lo: int, hi: int | None = None):
    """An integer type from ``lo`` to ``hi`` (inclusive; None: no upper bound)."""
    return Annotated[int, BeforeValidator(_no_bool), Field(ge=lo, le=hi), Allowed(f"an integer {_bounds(lo, hi)}")]


def FloatRange(gt: float | None = None, ge: float | None = None, le: float | None = None):
    """A finite number type: > ``gt`` (or >= ``ge``), <= ``le``."""
    text = f"a finite number {_bounds(ge, le, gt)}" if (gt is not None or ge is not None) else "a finite number"
    return Annotated[float, BeforeValidator(_no_bool), Field(gt=gt, ge=ge, le=le, allow_inf_nan=False), Allowed(text)]


MAX_WIDTH = 1 << 16    # widest layer a config may ask for (a 65536 x 65536 layer is 16 GiB in float32)
MAX_LAYERS = 64        # most hidden layers of one MLP
Flag = Annotated[bool, BeforeValidator(_plain_bool), Strict(), Allowed("true or false")]
Count = IntRange(0)                 # an integer >= 0
PositiveInt = IntRange(1)           # an integer >= 1
Width = IntRange(1, MAX_WIDTH)
InputWidth = IntRange(0, 1 << 20)     # input widths: a model's static features plus latents
LayerCount = IntRange(0, MAX_LAYERS)
PositiveFloat = FloatRange(gt=0)        # a finite number > 0
Widths = Annotated[tuple[Width, ...], Field(max_length=MAX_LAYERS),
                   Allowed(f"a list of at most {MAX_LAYERS} layer widths, each an integer from 1 to {MAX_WIDTH}")]


def allowed_values(tp) -> str:
    """Words for what an annotation allows (its ``Allowed`` text where it has one)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        for m in tp.__metadata__:
            if isinstance(m, Allowed):
                return m.text
        return allowed_values(args[0])
    if origin in (Union, types.UnionType):
        return " or ".join(allowed_values(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if tp is type(None):
        return "None"
    if origin in (list, tuple, Sequence):
        return f"a list of {allowed_values(args[0])}" if args else "a list"
    if dataclasses.is_dataclass(tp):
        return f"a table of {tp.__name__} keys"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp)))


def _nested_class(tp):
    """The config dataclass an annotation holds (through Annotated / Optional), else None."""
    if typing.get_origin(tp) is Annotated:
        return _nested_class(typing.get_args(tp)[0])
    if typing.get_origin(tp) in (Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return _nested_class(inner[0]) if len(inner) == 1 else None
    return tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None


_FIELD_CHECKS: dict[type, dict[str, tuple]] = {}


def _field_checks(cls) -> dict[str, tuple]:
    """{field: (annotation, pydantic TypeAdapter or None, nested config class or None)} of a
    dataclass, built once per class. A field whose annotation cannot be read is not checked here."""
    checks = _FIELD_CHECKS.get(cls)
    if checks is None:
        module = vars(sys.modules[cls.__module__])
        checks = {}
        for f in dataclasses.fields(cls):
            tp = f.type
            try:
                if isinstance(tp, str):
                    tp = eval(tp, dict(module), dict(vars(cls)))  # noqa: S307 (our own annotations)
                nested = _nested_class(tp)
                adapter = None if nested is not None else pydantic.TypeAdapter(tp)
            except Exception:  # an annotation pydantic cannot read: left to the class's own checks
                tp, nested, adapter = None, None, None
            checks[f.name] = (tp, adapter, nested)
        _FIELD_CHECKS[cls] = checks
    return checks


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


def _nested_value(name: str, tp, cls, v):
    if isinstance(v, cls) or (v is None and _accepts_none(tp)):
        return v
    if isinstance(v, dict):
        try:
            return cls.from_dict(dict(v)) if hasattr(cls, "from_dict") else cls(**check_keys(cls, v))
        except ConfigError as e:
            raise e.within(name) from None
    raise ConfigError(name, f"must be {allowed_values(tp)}, got {_short(v)}")


def _accepts_none(tp) -> bool:
    return typing.get_origin(tp) in (Union, types.UnionType) and type(None) in typing.get_args(tp)


def check_fields(obj) -> None:
    """Validate every field of the dataclass ``obj`` against its annotation and store the
    validated value (``[1, 2]`` becomes ``(1, 2)`` for a tuple, a dict a nested config); raise
    ``ConfigError`` naming the first refused field and the allowed values."""
    for name, (tp, adapter, nested) in _field_checks(type(obj)).items():
        v = getattr(obj, name)
        if nested is not None:
            new = _nested_value(name, tp, nested, v)
        elif adapter is not None:
            try:
                new = adapter.validate_python(v)
            except pydantic.ValidationError:
                raise ConfigError(name, f"must be {allowed_values(tp)}, got {_short(v)}") from None
        else:
            continue
        if new is not v:
            object.__setattr__(obj, name, new)


def check_keys(cls, d: Any, what: str | None = None) -> dict:
    """``d`` as a dict of ``cls``'s fields; ConfigError for a non-dict or unknown keys (naming
    the first, listing the known ones)."""
    if not isinstance(d, dict):
        raise ConfigError("", f"a {cls.__name__} needs a table (dict) of keys, got {_short(d)}")
    known = sorted(f.name for f in dataclasses.fields(cls))
    unknown = sorted(str(k) for k in set(d) - set(known))
    if unknown:
        raise ConfigError(unknown[0], f"unknown {what or cls.__name__ + ' keys'} {unknown} (known: {known})")
    return d


@dataclass(frozen=True)
class EdgeBlockConfig:
    """Inputs of the edge update phi_e."""
    use_edges: Flag = True
    use_sender_nodes: Flag = True
    use_receiver_nodes: Flag = True
    use_globals: Flag = True

    def __post_init__(self):
        check_fields(self)


@dataclass(frozen=True)
class NodeBlockConfig:
    """Inputs of the node update phi_v."""
    use_received_edges: Flag = True
    use_nodes: Flag = True
    use_globals: Flag = True

    def __post_init__(self):
        check_fields(self)


@dataclass(frozen=True)
class GlobalBlockConfig:
    """Inputs of the global update phi_u."""
    use_edges: Flag = True
    use_nodes: Flag = True
    use_globals: Flag = True

    def __post_init__(self):
        check_fields(self)


@dataclass(frozen=True)
class GNBlockConfig:
    """Sizes and switches of one GN block.

    ``node_size``, ``edge_size``, ``global_size``: input feature widths (0: the graph carries no
    such features; then no switch may use them). ``*_out``: output widths of the three updates.
    ``*_hidden``: hidden layer widths of each MLP (may be empty: a single linear layer).
    Defaults are the paper's sizes (section D.2: edge MLP 3x512, node and global 2x256, latent 128).
    Every value is validated (``check_fields``): a refusal is a ``ConfigError`` naming the key.
    """
    node_size: InputWidth
    edge_size: InputWidth
    global_size: InputWidth
    node_out: Width = 128
    edge_out: Width = 128
    global_out: Width = 128
    edge_hidden: Widths = (512, 512, 512)
    node_hidden: Widths = (256, 256)
    global_hidden: Widths = (256, 256)
    edge_block: EdgeBlockConfig = field(default_factory=EdgeBlockConfig)
    node_block: NodeBlockConfig = field(default_factory=NodeBlockConfig)
    global_block: GlobalBlockConfig = field(default_factory=GlobalBlockConfig)
    update_globals: Flag = True

    def __post_init__(self):
        check_fields(self)  # types and ranges of every field, nested block switches included
        eb, nb, gb = self.edge_block, self.node_block, self.global_block
        wants = {
            "node_size": [("edge_block.use_sender_nodes", eb.use_sender_nodes),
                          ("edge_block.use_receiver_nodes", eb.use_receiver_nodes),
                          ("node_block.use_nodes", nb.use_nodes)],
            "edge_size": [("edge_block.use_edges", eb.use_edges)],
            "global_size": [("edge_block.use_globals", eb.use_globals),
                            ("node_block.use_globals", nb.use_globals),
                            ("global_block.use_globals", gb.use_globals and self.update_globals)],
        }
        for size_name, uses in wants.items():
            if getattr(self, size_name) == 0:
                on = [n for n, u in uses if u]
                if on:
                    raise ConfigError(size_name, f"{size_name}=0 but {', '.join(on)} is set: switch it off or "
                                                 "give the size")
        for block, layout in (("edge", self.edge_layout), ("node", self.node_layout),
                              ("global", self.global_layout)):
            if block == "global" and not self.update_globals:
                continue
            if not layout:
                raise ConfigError(f"{block}_block", f"the {block} update uses no input: set at least one of its "
                                                    "use_* switches")

    # One source of truth for the column blocks of each MLP's first layer: [(piece, width)].
    @property
    def edge_layout(self) -> tuple[tuple[str, int], ...]:
        eb = self.edge_block
        return tuple((n, w) for n, w, on in (
            ("edges", self.edge_size, eb.use_edges),
            ("sender_nodes", self.node_size, eb.use_sender_nodes),
            ("receiver_nodes", self.node_size, eb.use_receiver_nodes),
            ("globals", self.global_size, eb.use_globals)) if on)

    @property
    def node_layout(self) -> tuple[tuple[str, int], ...]:
        nb = self.node_block
        return tuple((n, w) for n, w, on in (
            ("nodes", self.node_size, nb.use_nodes),
            ("received_edges", self.edge_out, nb.use_received_edges),
            ("globals", self.global_size, nb.use_globals)) if on)

    @property
    def global_layout(self) -> tuple[tuple[str, int], ...]:
        gb = self.global_block
        if not self.update_globals:
            return ()
        return tuple((n, w) for n, w, on in (
            ("globals", self.global_size, gb.use_globals),
            ("nodes", self.node_out, gb.use_nodes),
            ("edges", self.edge_out, gb.use_edges)) if on)

    @property
    def needs_nodes(self) -> bool:
        return self.edge_block.use_sender_nodes or self.edge_block.use_receiver_nodes or self.node_block.use_nodes

    @property
    def needs_edges(self) -> bool:
        return self.edge_block.use_edges

    @property
    def needs_globals(self) -> bool:
        return any(n == "globals" for n, _ in self.edge_layout + self.node_layout + self.global_layout)

    @property
    def aggregates_to_nodes(self) -> bool:
        """Whether edge outputs are summed per receiver (the node update reads them)."""
        return self.node_block.use_received_edges

    @property
    def edges_to_globals(self) -> bool:
        return self.update_globals and self.global_block.use_edges

    @property
    def nodes_to_globals(self) -> bool:
        return self.update_globals and self.global_block.use_nodes


def column_slices(layout: Sequence[tuple[str, int]]) -> dict[str, slice]:
    """{piece: slice of first-layer weight columns} for a layout."""
    out, c = {}, 0
    for name, w in layout:
        out[name] = slice(c, c + w)
        c += w
    return out


def layout_width(layout: Sequence[tuple[str, int]]) -> int:
    """Total width of a layout: the MLP's input size."""
    return sum(w for _, w in layout)


def pad(cols: int) -> int:
    """Padded width of a first-layer GEMM operand: a multiple of 8 elements (16 bytes in fp16 /
    bf16, 32 in fp32), which cuBLAS's fast (Hopper) kernels need for their K and leading
    dimensions; widths such as 31 or 159 otherwise fall back to Ampere / Turing kernels."""
    return -(-cols // 8) * 8
