"""The GN block's measured dispatch rules, and the one object that holds their constants.

Every choice the block makes from measurements (which path, how the edge first layer runs, which
MLPs fp16x3 emulates, how many side streams the backward uses) reads ``TUNABLES``; change a field
to re-tune (``gnwarp.gn.TUNABLES.side_streams = 0``), and re-derive the defaults from
``bench/gn_block.py`` when kernels, Warp or the GPU change. The functions take a ``ResolvedRun``
(``gnwarp.gn.options``) for the precision and modes.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gnwarp.gn.config import GNBlockConfig, column_slices, layout_width, pad

__all__ = ["Tunables", "TUNABLES", "choose_path", "tile_feasible", "edge_concat", "emulates", "choose_fused"]


@dataclass
class Tunables:
    """Measured constants of the GN block (defaults: one NVIDIA H200; provenance in the rules below).

    side_streams: side CUDA streams the backward spreads its weight-gradient GEMMs over (0: all
        on the current stream); 2-3 measured no faster than 1 (bench/gn_block.py --sections
        side; bench/results/gn_block/NOTES.md). Read when a backward runs: a
        captured graph keeps the choice it was captured with.
    emulate_min_rows, emulate_min_width: fp16x3 emulates an MLP from this many rows and this
        hidden width (``emulates``).
    edge_concat_max_k: fp32 / fp64 run the edge first layer on concatenated rows up to this many
        extra GEMM columns (``edge_concat``).
    tile_max_width, tile_min_edges, tile_max_edges: where "auto" picks the tile path on CUDA
        (``choose_path``).
    tile_smem_budget: bytes of shared memory the weights of one fused tile kernel may take.
    tile_mathdx: tile GEMMs through cuBLASDx (Warp's default; 1-2.5 min to compile each kernel
        for sm_90) or Warp's plain shared-memory GEMM (seconds).
    fused_step_max_graphs: rollout engines on CUDA run the fused model step up to this many
        graphs (``choose_fused``).
    """
    side_streams: int = 1
    emulate_min_rows: int = 16384
    emulate_min_width: int = 512
    edge_concat_max_k: int = 256
    tile_max_width: int = 16
    tile_min_edges: int = 288
    tile_max_edges: int = 3600
    tile_smem_budget: int = 160 * 1024
    tile_mathdx: bool = True
    fused_step_max_graphs: int = 1 << 20


TUNABLES = Tunables()


# -- the edge update's first layer ----------------------------------------------------------------
# The edge update's first layer runs on concatenated input rows [e, v_s, v_r, u] (one kernel
# writes them, then one GEMM with bias and ReLU in its epilogue, like the node update) or from
# projections (node / global projections as GEMMs over nodes / graphs, the edge rows' own
# projection as a GEMM, and ``project`` adding the gathered projections per edge). Concat costs
# 2 * extra_K FLOPs per edge and hidden unit (extra_K = padded sender + receiver + global widths)
# plus the concatenated row written and read; project costs the direct projection written and
# read back plus two gathered hidden rows, at ~1.3 TB/s, and four more launches (forward) / ~6
# (backward). Measured (H200, paper core on cheetah graphs, captured; the second block has
# extra_K = 480; the v7 ablation in bench/results/gn_block/NOTES.md, where "split"
# is today's "project"): with tensor cores (tf32, fp16, bf16) concat wins everywhere: forward at
# batch 4096 tf32 1.40 vs 1.52 ms, fp16 1.05 vs 1.21; training step at 200 tf32 0.89 vs 0.96, at
# 4096 fp16 3.71 vs 4.25. In plain fp32 the extra FLOPs run at the SIMT rate (48 TFLOP/s):
# project wins at 4096 (forward 5.82 vs 6.16 ms, training step 17.8 vs 18.6) and loses narrowly
# at 200 (1.69 vs 1.66), so fp32 / fp64 keep the extra_K rule (concat up to 256, as for the
# paper's first block). fp16x3 takes concat where it emulates (its first layer then emulates
# too) and fp32's rule below its rows.
def edge_concat(config: GNBlockConfig, run, n_edges: int) -> bool:
    """Whether the edge update's first layer runs on concatenated rows for a batch of ``n_edges``
    edges: ``run``'s edge_first_layer "concat" / "project" forces it; "auto" applies the rule above."""
    mode = run.options.edge_first_layer
    if mode != "auto":
        return mode == "concat"
    if run.tensor_cores or (run.emulate is not None and n_edges >= run.emulate[0]):
        return True
    cols = column_slices(config.edge_layout)
    extra = sum(pad(cols[n].stop - cols[n].start) for n in ("sender_nodes", "receiver_nodes", "globals") if n in cols)
    return extra <= TUNABLES.edge_concat_max_k


# -- fp16x3 ---------------------------------------------------------------------------------------
# Measured on an H200 (torch.mm peers in the same run; bench/results/fp32_emulation_probe_nvidia-
# h200.md; errors against float64): at 73728 x 512 @ 512 x 512 IEEE fp32 takes 0.82-0.84 ms, the
# one GEMM of the three fp16 products 0.16-0.17 ms (bf16x6, range-safe without scales: 0.57 ms;
# tf32x3: 0.45 ms) and the pieces pass 0.17 ms. At 32768 x 256 @ 256 x 256 emulation loses (IEEE
# 0.12 ms); the node MLPs' width-256 layers emulated made the paper core's forward 2% slower.
# Hence: an MLP emulates when its hidden width is >= emulate_min_width on >= emulate_min_rows
# rows: layers 1..L, and layer 0 too when it is one GEMM on the concatenated input rows. Paper
# core at batch 4096 (bench/results/gn_block/gn_block_nvidia-h200.md): forward 5.70 -> 3.45-3.48 ms
# captured, error against float64 ~1.0e-6 (IEEE fp32: 4.1-4.3e-7).
def emulates(run, rows: int, hidden_width: int) -> bool:
    """Whether an MLP with this hidden width runs its layers as fp16x3 GEMMs on ``rows`` rows."""
    return run.emulate is not None and rows >= run.emulate[0] and hidden_width >= run.emulate[1]


# -- path choice ----------------------------------------------------------------------------------
def _mlp_weight_elems(in_size, hidden, out_size) -> int:
    sizes = [in_size, *hidden, out_size]
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


def tile_feasible(config: GNBlockConfig, run, device: torch.device) -> str | None:
    """None if the fused tile path can run this block, else the reason why not."""
    if run.deterministic:
        return "deterministic mode needs ordered segment sums (tile scatters are atomic)"
    if not run.ieee:
        return f"tile path runs fp32/fp64 only (precision={run.precision!r})"
    if device.type == "cuda":
        c = config
        budget = TUNABLES.tile_smem_budget  # all weights of one MLP plus a few row tiles on one SM (H200: 227 KB)
        for name, layout, hid, out in (("edge", c.edge_layout, c.edge_hidden, c.edge_out),
                                       ("node", c.node_layout, c.node_hidden, c.node_out),
                                       ("global", c.global_layout, c.global_hidden, c.global_out)):
            if not layout:
                continue
            nbytes = 4 * _mlp_weight_elems(layout_width(layout), hid, out)
            if nbytes > budget:
                return (f"{name} MLP weights take {nbytes // 1024} KB, over the {budget // 1024} KB "
                        f"shared-memory budget of one fused tile kernel")
    return None


def choose_path(config: GNBlockConfig, run, device: torch.device, n_edges: int) -> str:
    """The "auto" rule: the blas path (Warp graph kernels + BLAS GEMMs) unless the fused tile path
    is feasible and was measured faster for such a block.

    Why blas is the default: Warp's tile GEMM runs at 18 GFLOP/s on the 2-core CPU against 172
    for CPU BLAS, and at 28-34 TFLOP/s on an H200 against cuBLAS's 48 (fp32) / 205 (tf32) / 527
    (fp16) (../shared/notes/warp-mujoco.md), and paper-size MLPs (3x512) do not fit a fused
    kernel's shared memory at all. The tile path can only pay where launches dominate:

    - CUDA (bench/gn_block.py crossover on an H200, paper core on cheetah graphs with every width
      w, fp32, both paths in one CUDA graph, as in a training loop): tile wins at w=16 from batch
      16 up to 200 (the largest measured: 3600 edges; fwd 0.13 vs 0.20 ms, fwd+bwd 0.54 vs 0.79 ms
      at 200), blas wins at batch 1, and at w=32 (fwd+bwd 0.82 vs 1.27 ms at 200) and w=64
      (fwd 0.19 vs 0.43 ms; the w=64 backward does not fit shared memory). Uncaptured, the tile
      path's 3 launches per block beat the blas path's ~10 at every w <= 64 measured, but
      captured loops are the fast way to run either.
    - CPU (same crossover on the 2-core CPU, one thread): tile within 10% at batch 1 with w=16
      (fwd 0.97 vs 1.06 ms) and slower everywhere else (w=16, batch 200: fwd 11.7 vs 6.0 ms,
      fwd+bwd 41 vs 17 ms): always blas.

    Hence: tile on CUDA when every hidden / output width <= ``tile_max_width`` and the batch has
    ``tile_min_edges`` to ``tile_max_edges`` edges (cheetah graphs have 18 edges: 288 edges =
    batch 16, 3600 = batch 200; outside that range: unmeasured or slower); else blas. A tile
    kernel found too large for the device's shared memory when it is built falls back to blas.
    """
    if tile_feasible(config, run, device) is not None or device.type != "cuda":
        return "blas"
    c = config
    widths = (*c.edge_hidden, *c.node_hidden, *c.global_hidden, c.edge_out, c.node_out, c.global_out)
    t = TUNABLES
    if max(widths) <= t.tile_max_width and t.tile_min_edges <= n_edges <= t.tile_max_edges:
        return "tile"
    return "blas"


# -- the fused model step -------------------------------------------------------------------------
# A rollout engine's step either runs ``ForwardModel.next_nodes`` (torch glue around the core:
# ~370 CUDA kernels and ~1160 aten ops per step forward + backward on a pendulum, ~1.5 us of device
# time each, measured on an H100 under torch.profiler: one episode, horizon 50) or ``FusedStep``
# (gnwarp/models/fused_step.py: encode, core, decode; the backward in a few more launches). At a
# small batch every launch costs more than its work; at a large batch the glue's kernels are
# bandwidth-bound and still cost: in a gradient planner's iteration on an H100 (TF32, 2026-11-27,
# bench/results/mpc_latency/NOTES.md) the fused step was faster at every size measured, 1.71x at
# 4096 pendulums x horizon 100 (68 against 116 ms) and 1.21x at 4096 cheetahs x horizon 20 (an
# earlier rollout benchmark, before the backward replayed the forward's blocks, had it slower at
# 4096; fused against unfused without a store, store=False, is not measured at large batch). So
# the rule fuses on CUDA at any batch (the bound keeps only an unmeasured extreme on the
# unfused step) and never on the CPU (no launch latency to save there: the unfused step stays
# the reference).
def choose_fused(n_graphs: int, device) -> bool:
    """Whether a rollout engine of ``n_graphs`` graphs on ``device`` runs the fused model step
    when it is not told (``RolloutEngine(fused=None)``): on CUDA up to
    ``TUNABLES.fused_step_max_graphs`` graphs (about a million: every measured size)."""
    return torch.device(device).type == "cuda" and n_graphs <= TUNABLES.fused_step_max_graphs
