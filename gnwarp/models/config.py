"""What a forward model is made of (``ModelConfig``, saved as JSON in checkpoints): its core's sizes
and how it runs (``RunOptions``, kept apart from the architecture so it can change at load time)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

from gnwarp.gn.config import EdgeBlockConfig, GlobalBlockConfig, GNBlockConfig, NodeBlockConfig
from gnwarp.validation import (ConfigError, Count, Flag, LayerCount, PositiveFloat, Width, Widths, check_fields,
                               check_keys)
from gnwarp.gn.options import RunOptions
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["GNCoreConfig", "core_blocks", "MLP_SIZES", "MLPCoreConfig", "ModelConfig", "DEFAULT_RUN", "ConfigError", "MAX_WEIGHTS",
           "weight_count", "check_model_size"]

# How models run unless told otherwise: TF32 GEMMs on CUDA (exactly fp32 on the CPU). Measured on an
# H200 (bench/results/train_loop/train_loop_nvidia-h200.md, rollout/rollout_nvidia-h200.md): the captured training
# loop 702 steps/s against fp32's 467, 4096-graph rollouts 1.38 against 5.61 ms a step; and the
# 20-step rollout errors of trained models unchanged to 3 digits against fp32
# (bench/results/speed_accuracy/). fp16 is faster still (783 steps/s, 1.02 ms) with errors also
# unchanged there, but its range (65504) leaves less margin: a choice, not the default.
DEFAULT_RUN = RunOptions(precision="tf32")


@dataclass
class GNCoreConfig:
    """Sizes and wiring of the GN core (D.2). Defaults are the paper's: two GN blocks with a graph
    skip, edge MLP 3x512, node and global MLPs 2x256, updated edge/node/global size 128.

    The wiring switches are the ablation of Figure H.2: ``blocks`` 1 makes a single GN without a
    global update (an interaction network); ``skip`` False feeds GN2 GN1's output graph alone
    instead of [input, GN1 output]; ``gn1_edges`` / ``gn1_nodes`` / ``gn1_globals`` False keep the
    input's edges / nodes / globals in GN1's output graph in place of its updated ones (GN1 still
    computes them for its own later updates; without ``gn1_globals`` it has no global update).
    """
    latent: Width = 128
    edge_hidden: Widths = (512, 512, 512)
    node_hidden: Widths = (256, 256)
    global_hidden: Widths = (256, 256)
    blocks: Literal[1, 2] = 2
    skip: Flag = True
    gn1_edges: Flag = True
    gn1_nodes: Flag = True
    gn1_globals: Flag = True

    def __post_init__(self):
        check_fields(self)  # types and ranges (gnwarp.gn.config): one ConfigError naming the key

    @classmethod
    def from_dict(cls, d: dict) -> "GNCoreConfig":
        return cls(**check_keys(cls, d))


# Section E: the five MLP baselines, "<layers>x<width>".
MLP_SIZES = ("3x128", "3x512", "9x128", "9x512", "5x256")


@dataclass
class MLPCoreConfig:
    """MLP baseline core (E): ``layers`` hidden layers of ``width`` on the flattened graph of a
    fixed topology (``n_node`` bodies, ``n_edge`` edges; set from the training data)."""
    layers: LayerCount = 5
    width: Width = 256
    n_node: Count = 0
    n_edge: Count = 0

    def __post_init__(self):
        check_fields(self)

    @classmethod
    def from_dict(cls, d: dict) -> "MLPCoreConfig":
        return cls(**check_keys(cls, d))

    @classmethod
    def preset(cls, size: str, n_node: int = 0, n_edge: int = 0) -> "MLPCoreConfig":
        if size not in MLP_SIZES:
            raise ValueError(f"unknown MLP size {size!r}; the paper's are {MLP_SIZES}")
        layers, width = (int(s) for s in size.split("x"))
        return cls(layers, width, n_node, n_edge)


# run options that earlier versions kept in the GN core's config
_RUN_KEYS_IN_GN = ("backend", "impl", "path", "precision", "deterministic")


@dataclass
class ModelConfig:
    """What a forward model is made of; saved as JSON in checkpoints.

    ``core``: "gn" (D.2) or "mlp" (E), sized by ``gn`` / ``mlp``. ``run``: how it runs
    (``RunOptions``: implementation, path, precision, ...; default ``DEFAULT_RUN``, TF32 on
    CUDA); "fp64" makes a float64 model.
    ``recenter`` (D.4): re-centre x, y before prediction; None: decided by training (True for a
    single translation-invariant system), False when used as is. ``std_floor``: the normalizers'
    smallest standard deviation.
    """
    core: Literal["gn", "mlp"] = "gn"
    gn: GNCoreConfig = field(default_factory=GNCoreConfig)
    mlp: MLPCoreConfig = field(default_factory=MLPCoreConfig)
    run: RunOptions = field(default_factory=lambda: DEFAULT_RUN)
    recenter: Flag | None = None
    std_floor: PositiveFloat = 1e-4

    def __post_init__(self):
        if isinstance(self.gn, dict) and any(k in self.gn for k in _RUN_KEYS_IN_GN):
            gn = dict(self.gn)
            moved = {k: gn.pop(k) for k in _RUN_KEYS_IN_GN if k in gn}
            self.gn = gn
            # an earlier version's config: its run options lived in ``gn``; options given as a
            # dict beside them win (an earlier version's TrainConfig ``dtype`` arrives so); a RunOptions object
            # here is the default, which the saved options replace
            self.run = {**moved, **self.run} if isinstance(self.run, dict) else {**self.run.to_dict(), **moved}
        check_fields(self)  # types and ranges, nested dicts made configs: one ConfigError naming the key

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["run"] = self.run.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """A config from ``to_dict``'s output (or an earlier version's: run options in ``gn``);
        unknown keys and refused values raise ``ConfigError``."""
        return cls(**check_keys(cls, d, "model config keys"))


# The most weight elements a model may have (4 GiB in float32; the paper's core has ~1e6):
# a config asking for more is refused before anything is allocated.
MAX_WEIGHTS = 1 << 30


def _mlp_weights(n_in: int, hidden, n_out: int) -> int:
    sizes = [int(n) for n in (n_in, *hidden, n_out)]
    return sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:]))


def weight_count(config: ModelConfig, sizes: dict[str, int]) -> int:
    """The number of weight elements of a model of ``config`` on inputs of widths ``sizes``
    ({"nodes", "edges", "globals"}), computed from the config alone (as ``GNCore`` / ``MLPCore``
    build them; normalizers not counted)."""
    fv, fe, fg = int(sizes["nodes"]), int(sizes["edges"]), int(sizes["globals"])
    if config.core == "mlp":
        m = config.mlp
        return _mlp_weights(fg + m.n_node * fv + m.n_edge * fe, [m.width] * m.layers, m.n_node * 13)
    total = 0
    for b in core_blocks(config.gn, sizes):
        width = lambda layout: sum(w for _, w in layout)  # noqa: E731
        total += _mlp_weights(width(b.edge_layout), b.edge_hidden, b.edge_out)
        total += _mlp_weights(width(b.node_layout), b.node_hidden, b.node_out)
        if b.global_layout:
            total += _mlp_weights(width(b.global_layout), b.global_hidden, b.global_out)
    return total


def core_blocks(c: GNCoreConfig, sizes: dict[str, int]) -> tuple[GNBlockConfig, ...]:
    """The ``GNBlockConfig`` of each block of a GN core of config ``c`` on inputs of widths
    ``sizes`` ({"nodes", "edges", "globals"}): GN1 (latent-sized outputs; no global input when the
    graphs carry no global features, it still makes globals for GN2) and GN2 (the 13 normalized
    state changes per node, no global update since only its nodes are read), wired as ``c`` says;
    or the one block of ``blocks=1``."""
    fv, fe, fg = int(sizes["nodes"]), int(sizes["edges"]), int(sizes["globals"])
    L = c.latent
    hidden = dict(edge_hidden=c.edge_hidden, node_hidden=c.node_hidden, global_hidden=c.global_hidden)

    def uses(g: bool) -> dict:
        return dict(edge_block=EdgeBlockConfig(use_globals=g), node_block=NodeBlockConfig(use_globals=g),
                    global_block=GlobalBlockConfig(use_globals=g))
    if c.blocks == 1:
        return (GNBlockConfig(fv, fe, fg, node_out=DYN_NODE_SIZE, edge_out=L, global_out=L, **hidden, **uses(fg > 0),
                              update_globals=False),)
    gn1 = GNBlockConfig(fv, fe, fg, node_out=L, edge_out=L, global_out=L, **hidden, **uses(fg > 0),
                        update_globals=c.gn1_globals)
    n1, e1, g1 = (L if c.gn1_nodes else fv), (L if c.gn1_edges else fe), (L if c.gn1_globals else fg)
    n2, e2, g2 = (fv + n1, fe + e1, fg + g1) if c.skip else (n1, e1, g1)
    gn2 = GNBlockConfig(n2, e2, g2, node_out=DYN_NODE_SIZE, edge_out=L, global_out=L, **hidden, **uses(g2 > 0),
                        update_globals=False)
    return gn1, gn2


def check_model_size(config: ModelConfig, sizes: dict[str, int], limit: int = MAX_WEIGHTS,
                     where: str = "model") -> int:
    """``weight_count`` of ``config``, or ValueError when a size is not a positive integer or the
    model would have more than ``limit`` weight elements: the error names the key most to blame
    (``<where>.gn.latent``, ...) and the count, before anything is allocated."""
    core = config.gn if config.core == "gn" else config.mlp
    keys = (("latent", "edge_hidden", "node_hidden", "global_hidden") if config.core == "gn"
            else ("layers", "width", "n_node", "n_edge"))
    for k in keys:
        v = getattr(core, k)
        low = 0 if k in ("layers", "n_node", "n_edge") else 1
        for x in (v if isinstance(v, tuple) else (v,)):
            if (isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x != int(x)
                    or x < low):
                want = ("widths must be positive integers" if isinstance(v, tuple) else
                        "must be an integer >= 0" if low == 0 else "must be a positive integer")
                raise ValueError(f"{where}.{config.core}.{k} {want}, got {v!r}")
    n = weight_count(config, sizes)
    if n <= limit:
        return n
    default = GNCoreConfig() if config.core == "gn" else MLPCoreConfig()

    def without(k):  # the count with key k back at its default
        return weight_count(dataclasses.replace(config, **{config.core: dataclasses.replace(core, **{
            k: getattr(default, k)})}), sizes)
    worst = min(keys, key=without)
    raise ValueError(f"{where}.{config.core}.{worst} = {getattr(core, worst)!r} makes a model of {n:.3g} weight "
                     f"elements ({4 * n / 2**30:.3g} GiB in float32), more than the limit of {limit:.3g}; "
                     "choose smaller sizes")
