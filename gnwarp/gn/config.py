"""Sizes and switches of one GN block (graph_nets style), and the column layout of its MLPs'
first layers: one source of truth for which inputs each update reads. Values are validated by
``gnwarp.validation`` (a refusal is a ``ConfigError`` naming the key).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

from gnwarp.validation import ConfigError, check_fields, Flag, InputWidth, Width, Widths

__all__ = ["EdgeBlockConfig", "NodeBlockConfig", "GlobalBlockConfig", "GNBlockConfig", "column_slices",
           "layout_width", "pad"]


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
