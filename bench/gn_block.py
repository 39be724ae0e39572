"""Benchmark of the paper's two-block GN forward core: our Warp paths against torch peers.

The core is the library's ``gnwarp.models.GNCore`` (paper section D.2 sizes): GN1 on the input
graph (edge MLP 3x512, node and global MLPs 2x256, latent 128); GN2 on [input, GN1 output] (node
output 13, no global update). The torch peers run its weights through a forward written as a
PyTorch user would (``TorchCore``). Graph shapes (``bench/harness.py``): dm_control cheetah (8
nodes incl. world, 9 joints -> 18 directed edges), swimmer6 (7 nodes, 3 root joints + 5 hinges ->
16 edges), pendulum (2 nodes, 1 hinge -> 2 edges); feature widths as in
../shared/probes/gn_torch_anchor.py (node 31, edge 64, global 32) for every shape.

Sections (``--sections``, all by default):
  peak       torch.matmul at the edge-MLP hidden shape (73728x512 @ 512x512) per precision
  main       cheetah: fwd, fwd+bwd, train step (fwd, MSE loss, bwd, clip, Adam) at batch 200 and
             4096, fwd at 65536; peers: torch eager, torch.compile default and reduce-overhead
             (fp32, tf32; fp16 / bf16 under torch.autocast), our blas path (fp32, tf32, fp16,
             bf16, fp16x3: float32-accurate GEMMs from fp16 tensor cores, compared with the fp32
             peers and the fp32 peak), our tile path (fp32)
  shapes     swimmer6 and pendulum: the same modes for torch eager / compile-ro and our blas path
  capture    our blas path with the whole training step (and the forward) in one CUDA graph
  errors     max error of every peer/precision against the float64 torch reference (batch 200)
  crossover  small MLPs (widths 16-64) at small batches: blas vs tile, to set the "auto" rule
  efl        (only when asked) the captured blas path with each edge first-layer mode forced
             ("project", "concat")
  flat       (only when asked) the captured blas path with and without ``--flat-params``
  optim      (only when asked) the captured blas path's training step with torch's Adam and with
             gnwarp.train.FlatAdam (``--optimizer`` picks the one of the other sections)
  side       (only when asked) the captured blas path's training step with the backward's
             weight-gradient GEMMs on the current stream and on 1, 2 and 3 side streams
             (``gnwarp.gn.TUNABLES.side_streams``)
  profile    (only when asked) torch.profiler kernel tables of one fwd / train step at batch 4096
             and of one train step at batch 200 (kernel count: the nodes of a captured step)
  timeline   (only when asked) every kernel of one replay of the captured training step at the
             first of ``--batches``, in start order with its stream, start, duration and the idle
             gap before it on its stream (where a captured step waits on launches, not work)

Each measurement is wrapped: a failing peer (torch.compile included) is reported, not fatal.
Rows are appended to ``<out>/gn_block_<device>.jsonl`` as they come (a timeout keeps what ran);
``<out>/gn_block_<device>.md`` is rewritten from all rows of that device after each section
(rows of earlier versions read with today's names: peers "warp-split*" as "warp-blas*", edge
first layer "split" as "project").
Timing: CUDA events (CPU: perf_counter) around each call after warm-up; median of repeats.

``--quick`` runs tiny sizes on the CPU (a smoke test of the script, not a measurement).
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
import time
import traceback
from pathlib import Path

import torch
import torch.nn as nn
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.harness import (EDGE_IN, GLOB_IN, NODE_IN, NODE_OUT, PAPER, QUICK, SHAPES, build_core,  # noqa: E402
                           capture, device_name, make_batch, median_ms, results_dir, slug, uniform_sizes)
from gnwarp.gn import TUNABLES, GNBlockConfig, flatten_parameters, graph_index, tf32_matmul  # noqa: E402
from gnwarp.gn.rules import tile_feasible  # noqa: E402
from gnwarp.graphs import GraphsTuple, graph_of  # noqa: E402
from gnwarp.models import GNCore, GNCoreConfig  # noqa: E402
from gnwarp.train import FlatAdam  # noqa: E402


def check_paper_blocks(core: GNCore, sizes: GNCoreConfig) -> None:
    """The library's core builds the blocks this benchmark has always timed: GN1 on the input
    (globals used: the input has global features), GN2 on [input, GN1 output] with NODE_OUT node
    outputs and no global update."""
    lat = sizes.latent
    hid = dict(edge_hidden=sizes.edge_hidden, node_hidden=sizes.node_hidden, global_hidden=sizes.global_hidden)
    want1 = GNBlockConfig(NODE_IN, EDGE_IN, GLOB_IN, lat, lat, lat, **hid)
    want2 = GNBlockConfig(NODE_IN + lat, EDGE_IN + lat, GLOB_IN + lat, NODE_OUT, lat, lat, update_globals=False, **hid)
    for got, want in ((core.gn1.config, want1), (core.gn2.config, want2)):
        if got != want:
            raise AssertionError(f"gnwarp.models.GNCore builds {got}, the benchmark's core is {want}")


class TorchCore(nn.Module):
    """The torch peer, written as a PyTorch user would (as gn_torch_anchor.py), on the weights of
    the library's ``GNCore``; graph index tensors are precomputed inputs, as in the anchor."""

    def __init__(self, core: GNCore):
        super().__init__()
        self.core = core

    @staticmethod
    def block(gn, v, e, u, snd, rcv, ng, eg, B: int, do_global: bool):
        e2 = gn.edge_mlp(torch.cat([e, v[snd], v[rcv], u[eg]], -1))
        agg = torch.zeros(v.shape[0], e2.shape[1], device=v.device, dtype=e2.dtype).index_add_(0, rcv, e2)
        v2 = gn.node_mlp(torch.cat([v, agg, u[ng]], -1))
        if not do_global:
            return v2, e2, u
        ge = torch.zeros(B, e2.shape[1], device=v.device, dtype=e2.dtype).index_add_(0, eg, e2)
        gv = torch.zeros(B, v2.shape[1], device=v.device, dtype=v2.dtype).index_add_(0, ng, v2)
        return v2, e2, gn.global_mlp(torch.cat([u, gv, ge], -1))

    def forward(self, v, e, u, snd, rcv, ng, eg):
        B = u.shape[0]
        v1, e1, u1 = self.block(self.core.gn1, v, e, u, snd, rcv, ng, eg, B, True)
        v2, _, _ = self.block(self.core.gn2, torch.cat([v, v1], -1), torch.cat([e, e1], -1),
                              torch.cat([u, u1], -1), snd, rcv, ng, eg, B, False)
        return v2


def torch_inputs(g: GraphsTuple):
    """The torch peer's inputs: features, indices and the graph of each node / edge, precomputed
    (as the GraphIndex is for ours)."""
    ng, eg = graph_of(g.n_node, g.nodes.shape[0]), graph_of(g.n_edge, g.edges.shape[0])
    return (g.nodes, g.edges, g.globals, g.senders, g.receivers, ng, eg)


def core_flops(shape: str, sizes: GNCoreConfig, projected: bool = False) -> int:
    """Multiply-add FLOPs (x2) of one graph's forward. ``projected=False``: the concatenated first
    layers of the reference (the anchor's count, used for every peer's TFLOP/s); ``projected=True``:
    what our blas path executes with projected first layers (node / global projections once per
    node / graph)."""
    n, snd, _ = SHAPES[shape]
    E, N = len(snd), n
    lat = sizes.latent

    def mlp(rows, d, hs, o):
        f = 0
        for h in (*hs, o):
            f += 2 * rows * d * h
            d = h
        return f

    def block(fv, fe, fu, vo, eo, uo, glob):
        eh, nh, gh = sizes.edge_hidden, sizes.node_hidden, sizes.global_hidden
        if projected:  # first layers: edge rows per edge, node projections per node, global per graph
            h0 = eh[0] if eh else eo
            f = 2 * E * fe * h0 + 2 * N * fv * 2 * h0 + 2 * fu * h0 + (mlp(E, h0, eh[1:], eo) if eh else 0)
            hn = nh[0] if nh else vo
            f += 2 * N * (fv + eo) * hn + 2 * fu * hn + (mlp(N, hn, nh[1:], vo) if nh else 0)
        else:
            f = mlp(E, fe + 2 * fv + fu, eh, eo) + mlp(N, fv + eo + fu, nh, vo)
        if glob:
            f += mlp(1, fu + vo + eo, gh, uo)
        return f

    f1 = block(NODE_IN, EDGE_IN, GLOB_IN, lat, lat, lat, True)
    f2 = block(NODE_IN + lat, EDGE_IN + lat, GLOB_IN + lat, NODE_OUT, lat, lat, False)
    return f1 + f2


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


# -- peers --------------------------------------------------------------------------------------
TORCH_PEERS = ("torch-eager", "torch-compile", "torch-compile-ro")
OUR_PRECISIONS = ("fp32", "tf32", "fp16", "bf16", "fp16x3")
# fp16x3 is float32-accurate (error against float64 within ~2x of IEEE fp32's): its peers and
# matmul peak are fp32's; torch has no such mode
PEER_PRECISION = {"fp16x3": "fp32"}
WARP_PEERS = ("warp-blas", "warp-tile")
# earlier rows' names, read as today's: peers "warp-split*" are the blas path's, the edge
# first layer's mode "split" is "project"
RENAMED = {"peer": {"warp-split": "warp-blas", "warp-split-graph": "warp-blas-graph"}, "efl": {"split": "project"}}


def renamed(row: dict) -> dict:
    """A results row with earlier names read as today's."""
    return {k: RENAMED.get(k, {}).get(v, v) if isinstance(v, str) else v for k, v in row.items()}


class Runner:
    def __init__(self, args):
        self.args = args
        self.device = torch.device(args.device)
        self.sizes = QUICK if args.quick else PAPER
        self.rows = []
        self.peaks = {}
        self.device_name = device_name(self.device)
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.jsonl = self.out / f"gn_block_{slug(self.device_name)}{'_quick' if args.quick else ''}.jsonl"
        self.md = self.jsonl.with_suffix(".md")
        torch.manual_seed(0)
        self.base = build_core(self.sizes).to(self.device)  # one set of weights for every peer
        if args.quick:
            check_paper_blocks(self.base, self.sizes)
        self.efl = args.edge_first_layer                # our peers' edge first-layer mode
        self.det = args.deterministic                   # our peers' aggregation: segment sums
        self.opt = args.optimizer                       # our peers' optimizer: torch Adam or FlatAdam
        self.flatp = args.flat_params                   # our peers' parameters in one flat buffer
        self.emu = (tuple(int(x) for x in args.emulate_min.split(",")) if args.emulate_min else None)
        self.side_default = TUNABLES.side_streams
        if args.side_streams is not None:               # our backward's side streams (weight-gradient GEMMs)
            self.side = args.side_streams

    @property
    def side(self) -> int:
        return TUNABLES.side_streams

    @side.setter
    def side(self, n: int):
        TUNABLES.side_streams = n

    def record(self, **row):
        if row.get("peer", "").startswith("warp") and self.efl != "auto":
            row["efl"] = self.efl
        if row.get("peer", "").startswith("warp") and self.det:
            row["det"] = True
        if row.get("peer", "").startswith("warp") and row.get("mode") == "train" and self.opt == "flat":
            row["opt"] = "flat"
        if row.get("peer", "").startswith("warp") and self.flatp:
            row["flatp"] = True
        if row.get("peer", "").startswith("warp") and row.get("precision") == "fp16x3" and self.emu is not None:
            row["emu"] = "%d,%d" % self.emu
        if row.get("peer", "").startswith("warp") and row.get("mode") in ("train", "fwdbwd") and \
                self.side != self.side_default:
            row["side"] = self.side
        row = dict(device=self.device_name, quick=self.args.quick, torch=torch.__version__,
                   warp=wp.__version__, time=time.strftime("%Y-%m-%d %H:%M:%S"), **row)
        self.rows.append(row)
        with open(self.jsonl, "a") as f:
            f.write(json.dumps(row) + "\n")
        status = row.get("error")
        if status:
            print(f"  {row.get('shape', ''):9s} B={row.get('batch', ''):<6} {row.get('mode', ''):7s} "
                  f"{row['peer']:18s} {row.get('precision', ''):5s}  FAILED: {status[:160]}", flush=True)
        elif "ms" in row:
            print(f"  {row.get('shape', ''):9s} B={row['batch']:<6} {row['mode']:7s} {row['peer']:18s} "
                  f"{row['precision']:5s} {row['ms']:9.3f} ms {row['graph_steps_per_s']:12.4g} g/s "
                  f"{row['tflops']:8.3f} TFLOP/s  {100 * (row.get('frac_peak') or 0):5.1f}% peak", flush=True)

    # -- one measurement --------------------------------------------------------------------------
    def measure(self, peer, precision, shape, B, mode, sizes=None, extra=None):
        """Time ``mode`` (fwd | fwdbwd | train) of ``peer`` at ``precision``; record a row."""
        args, dev = self.args, self.device
        sizes = sizes or self.sizes
        base = dict(peer=peer, precision=precision, shape=shape, batch=B, mode=mode, **(extra or {}))
        try:
            fn, cleanup = self.make_step(peer, precision, shape, B, mode, sizes)
        except Exception as exc:  # noqa: BLE001 - report and go on
            self.record(**base, error=f"setup: {type(exc).__name__}: {exc}")
            if args.verbose:
                traceback.print_exc()
            return None
        try:
            with tf32_matmul(peer.startswith("torch") and precision == "tf32"):
                ms = median_ms(fn, dev, args.reps, args.warmup)
        except Exception as exc:  # noqa: BLE001
            self.record(**base, error=f"{type(exc).__name__}: {exc}")
            if args.verbose:
                traceback.print_exc()
            return None
        finally:
            cleanup()
        flops = core_flops(shape, sizes) * B * (3 if mode != "fwd" else 1)
        tflops = flops / ms / 1e9
        peak = self.peaks.get(PEER_PRECISION.get(precision, precision))
        self.record(**base, ms=round(ms, 4), graph_steps_per_s=B / ms * 1e3, tflops=round(tflops, 4),
                    frac_peak=(tflops / peak) if peak else None, model_gflop=flops / 1e9)
        return ms

    def make_step(self, peer, precision, shape, B, mode, sizes):
        """(fn, cleanup): a closure running one step, and what to call afterwards."""
        dev = self.device
        g, target = make_batch(shape, B, dev)
        if sizes is not self.sizes:
            torch.manual_seed(0)
            model = build_core(sizes).to(dev)
        else:
            model = copy.deepcopy(self.base)
        params = list(model.parameters())
        captured = peer.endswith("-graph")
        if peer.startswith("torch"):
            if precision not in ("fp32", "tf32", "fp16", "bf16"):
                raise ValueError(f"unknown precision {precision!r}")
            tc = TorchCore(model)
            x = torch_inputs(g)
            if peer == "torch-eager":
                fwd = tc
            else:
                # fresh dynamo caches: compiled code is keyed on TorchCore.forward's code object, and
                # past the recompile limit dynamo silently runs eager
                torch._dynamo.reset()
                fwd = torch.compile(tc, dynamic=False,
                                    mode="reduce-overhead" if peer == "torch-compile-ro" else None)

            amp = _autocast(precision, dev)

            def run():
                with amp():
                    return fwd(*x)
        else:
            path = "tile" if peer.startswith("warp-tile") else "blas"
            # emulate_min: fp16x3's rule (rows, hidden width), None: the library's
            model.set_options(model.options.replace(impl="warp", path=path, precision=precision,
                                                    edge_first_layer=self.efl, deterministic=self.det,
                                                    emulate_min=self.emu))
            if path == "tile":
                run = model.options.resolve(params[0].dtype)
                why = tile_feasible(model.gn1.config, run, dev) or tile_feasible(model.gn2.config, run, dev)
                if why:
                    raise ValueError(f"tile path not feasible: {why}")
            # static topology: built once, as the torch peer's index inputs
            idx = graph_index(g, deterministic=self.det)
            if self.flatp:  # parameters as views of one buffer: one cast launch per block in fp16 / bf16
                flatten_parameters(params)

            def run():
                return model(g, idx)

        if mode == "fwd":
            def step():
                with torch.no_grad():
                    run()
        else:
            opt = None
            flat = mode == "train" and self.opt == "flat" and peer.startswith("warp")
            if flat:  # gnwarp.train.FlatAdam: clipping and Adam over one flat buffer
                opt = FlatAdam(params, 1e-4, max_grad_norm=1.0)
            elif mode == "train":
                opt = torch.optim.Adam(params, 1e-4, fused=dev.type == "cuda", capturable=captured)

            def step():
                if opt is not None:
                    opt.zero_grad(set_to_none=True)
                loss = ((run().float() - target) ** 2).mean()
                loss.backward()
                if opt is not None:
                    if not flat:
                        torch.nn.utils.clip_grad_norm_(params, 1.0)
                    opt.step()
                elif not captured:
                    for p in params:
                        p.grad = None

        if not captured:
            return step, (lambda: None)
        if dev.type != "cuda":
            raise RuntimeError("CUDA graph capture needs a CUDA device")
        return capture(step), (lambda: None)  # the whole step as one CUDA graph

    # -- sections -------------------------------------------------------------------------------
    def section_peak(self):
        dev = self.device
        M, K, N = (73728, 512, 512) if not self.args.quick else (2048, 256, 256)
        for prec, dt in (("fp32", torch.float32), ("tf32", torch.float32), ("fp16", torch.float16),
                         ("bf16", torch.bfloat16)):
            try:
                a = torch.randn(M, K, device=dev).to(dt)
                b = torch.randn(K, N, device=dev).to(dt)
                with tf32_matmul(prec == "tf32"):
                    ms = median_ms(lambda: torch.mm(a, b), dev, max(self.args.reps, 20), 5)
                tf = 2 * M * K * N / ms / 1e9
                self.peaks[prec] = tf
                self.record(peer="torch.mm", precision=prec, mode="peak", shape=f"{M}x{K}@{K}x{N}", batch=0,
                            ms=round(ms, 4), graph_steps_per_s=0.0, tflops=round(tf, 3), frac_peak=1.0)
            except Exception as exc:  # noqa: BLE001
                self.record(peer="torch.mm", precision=prec, mode="peak", error=f"{type(exc).__name__}: {exc}")

    def section_main(self):
        a = self.args
        for B in a.batches:
            for mode in ("fwd", "fwdbwd", "train"):
                self.run_peers("cheetah", B, mode)
        for B in a.fwd_batches:
            self.run_peers("cheetah", B, "fwd")

    def run_peers(self, shape, B, mode, peers=None):
        a = self.args
        for peer in peers or a.peers:
            if peer in ("torch-compile", "torch-compile-ro") and mode not in a.compile_modes:
                continue
            precs = list(a.precisions)
            if peer == "warp-tile":
                precs = [p for p in precs if p == "fp32"]
            elif peer.startswith("torch"):
                precs = [p for p in precs if p not in PEER_PRECISION]
            for prec in precs:
                self.measure(peer, prec, shape, B, mode)

    def section_shapes(self):
        a = self.args
        peers = [p for p in a.peers if p in ("torch-eager", "torch-compile-ro", "warp-blas")]
        for shape in ("swimmer6", "pendulum"):
            for B in a.batches:
                for mode in ("fwd", "train"):
                    self.run_peers(shape, B, mode, peers)

    def section_capture(self):
        if self.device.type != "cuda":
            self.record(peer="warp-blas-graph", mode="train", error="CUDA graph capture needs a CUDA device")
            return
        for B in self.args.batches:
            for mode in ("train", "fwd"):
                for prec in [p for p in self.args.precisions if p in OUR_PRECISIONS]:
                    self.measure("warp-blas-graph", prec, "cheetah", B, mode)

    def _ablation(self, attr, values, cases):
        """Our captured blas path at each (batch, mode) of ``cases`` and each precision, with the
        Runner setting ``attr`` (one of our peers' options) set to each of ``values`` in turn."""
        if self.device.type != "cuda":
            self.record(peer="warp-blas-graph", mode=cases[0][1], error="CUDA graph capture needs a CUDA device")
            return
        old = getattr(self, attr)
        try:
            for value in values:
                setattr(self, attr, value)
                for B, mode in cases:
                    for prec in [p for p in self.args.precisions if p in OUR_PRECISIONS]:
                        self.measure("warp-blas-graph", prec, "cheetah", B, mode)
        finally:
            setattr(self, attr, old)

    def section_efl(self):
        """The edge first layer forced to each mode (the ``edge_first_layer`` rule): forward at
        batch 4096, training steps at 200 and 4096."""
        self._ablation("efl", ("project", "concat"), ((4096, "fwd"), (200, "train"), (4096, "train")))

    def section_optim(self):
        """The training step with torch's fused Adam + clip_grad_norm_ and with
        gnwarp.train.FlatAdam (same clipping, same update), at each of ``--batches``."""
        self._ablation("opt", ("torch", "flat"), tuple((B, "train") for B in self.args.batches))

    def section_flat(self):
        """The parameters as they are and moved into one flat buffer
        (``gnwarp.flatten_parameters``): forward at 4096, training step (torch Adam) at 200."""
        self._ablation("flatp", (False, True), ((4096, "fwd"), (200, "train")))

    def section_side(self):
        """The backward's weight-gradient GEMMs on the current stream and on 1, 2 and 3 side
        streams (``gnwarp.gn.TUNABLES.side_streams``): training steps at each of ``--batches``."""
        self._ablation("side", (0, 1, 2, 3), tuple((B, "train") for B in self.args.batches))

    def section_errors(self):
        dev = self.device
        g, _ = make_batch("cheetah", 200 if not self.args.quick else 16, dev, seed=1)
        ref_model = copy.deepcopy(self.base).double()
        g64 = g._replace(nodes=g.nodes.double(), edges=g.edges.double(), globals=g.globals.double())
        with torch.no_grad():
            expect = TorchCore(ref_model)(*torch_inputs(g64))
        for peer in self.args.peers:
            for prec in self.args.precisions:
                if (peer == "warp-tile" and prec != "fp32") or (peer.startswith("torch") and prec in PEER_PRECISION):
                    continue
                row = dict(peer=peer, precision=prec, mode="error", shape="cheetah", batch=g.n_node.shape[0])
                try:
                    model = copy.deepcopy(self.base)
                    with torch.no_grad():
                        if peer.startswith("torch"):
                            tc = TorchCore(model)
                            if peer != "torch-eager":
                                torch._dynamo.reset()
                                tc = torch.compile(tc, dynamic=False,
                                                   mode="reduce-overhead" if peer == "torch-compile-ro" else None)
                            with tf32_matmul(prec == "tf32"), _autocast(prec, dev)():
                                out = tc(*torch_inputs(g))
                        else:
                            # fp16x3: the layers that emulate at batch 4096, here too
                            model.set_options(model.options.replace(
                                impl="warp", path="tile" if peer == "warp-tile" else "blas", precision=prec,
                                edge_first_layer=self.efl, deterministic=self.det,
                                emulate_min=(0, TUNABLES.emulate_min_width)))
                            out = model(g)
                    err = ((out.double() - expect).abs().max() / expect.abs().max()).item()
                    self.record(**row, max_rel_err=err)
                    print(f"  error vs float64: {peer:18s} {prec:5s} {err:.3e}", flush=True)
                except Exception as exc:  # noqa: BLE001
                    self.record(**row, error=f"{type(exc).__name__}: {exc}")

    def section_crossover(self):
        """Blas vs tile on small MLPs (all widths w, latent w), for the "auto" rule."""
        widths = (16, 32, 64) if not self.args.quick else (8, 16)
        batches = (1, 16, 200) if not self.args.quick else (1, 8)
        peers = ["warp-blas", "warp-tile"]
        if self.device.type == "cuda":
            peers += ["warp-blas-graph", "warp-tile-graph"]
        for w in widths:
            sizes = uniform_sizes(w)
            for B in batches:
                for mode in ("fwd", "fwdbwd"):
                    for peer in peers:
                        self.measure(peer, "fp32", "cheetah", B, mode, sizes=sizes, extra=dict(width=w))

    def section_profile(self):
        """torch.profiler kernel tables of one step (where does the time go), written to
        ``<out>/gn_block_<device>_profile.txt``; one summary line per step printed (device
        kernels and memsets launched, their total device time). Not timed rows; cheap."""
        from torch.autograd import DeviceType  # noqa: PLC0415
        from torch.profiler import ProfilerActivity, profile  # noqa: PLC0415
        dev = self.device
        cuda = dev.type == "cuda"
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        big, small = (4096, 200) if not self.args.quick else (16, 4)
        path = self.jsonl.with_name(self.jsonl.stem + "_profile.txt")
        peers = [p for p in self.args.peers if p in ("warp-blas", "torch-eager")] or ["warp-blas"]
        with open(path, "w") as f:
            for peer in peers:
                for prec in [p for p in self.args.precisions if p in OUR_PRECISIONS]:
                    for B, mode in ((big, "fwd"), (big, "train"), (small, "train")):
                        try:
                            fn, _ = self.make_step(peer, prec, "cheetah", B, mode, self.sizes)
                            with tf32_matmul(peer.startswith("torch") and prec == "tf32"):
                                for _ in range(3):
                                    fn()
                                sync(dev)
                                with profile(activities=acts) as prof:
                                    fn()
                                    sync(dev)
                            key = "self_device_time_total" if cuda else "self_cpu_time_total"
                            try:
                                table = prof.key_averages().table(sort_by=key, row_limit=30)
                            except Exception:  # noqa: BLE001 - older torch: the cuda_ name
                                table = prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=30)
                            kern = [e for e in prof.events() if e.device_type == DeviceType.CUDA]
                            dev_us = sum(getattr(e, "device_time", 0.0) or 0.0 for e in kern)
                            head = (f"== {peer} {prec} {mode} cheetah B={B}: {len(kern)} device kernels/memsets, "
                                    f"{dev_us / 1e3:.3f} ms device time")
                            print(head, flush=True)
                            f.write(head + "\n" + table + "\n")
                        except Exception as exc:  # noqa: BLE001
                            print(f"== {peer} {prec} {mode} B={B}: profile failed: {exc}", flush=True)
        print(f"wrote {path}")

    def section_timeline(self):
        """Kernel timeline of one replay of our captured training step (torch.profiler's trace of
        the graph's kernels), per precision, at the first of ``--batches``: written to
        ``<out>/gn_block_<device>_timeline.txt``; one summary line per precision printed (span,
        kernels per stream, busy and idle time of the main stream). Not timed rows."""
        from torch.profiler import ProfilerActivity, profile  # noqa: PLC0415
        if self.device.type != "cuda":
            print("timeline: needs a CUDA device (a captured step)", flush=True)
            return
        B = self.args.batches[0]
        path = self.jsonl.with_name(self.jsonl.stem + "_timeline.txt")
        with open(path, "w") as f:
            for prec in [p for p in self.args.precisions if p in OUR_PRECISIONS]:
                try:
                    fn, _ = self.make_step("warp-blas-graph", prec, "cheetah", B, "train", self.sizes)
                    for _ in range(5):
                        fn()
                    sync(self.device)
                    with profile(activities=[ProfilerActivity.CUDA]) as prof:
                        fn()
                        sync(self.device)
                    trace = self.jsonl.with_name(f"_trace_{prec}.json")
                    prof.export_chrome_trace(str(trace))
                    events = json.load(open(trace))["traceEvents"]
                    trace.unlink()
                    lines, head = timeline_table(events)
                    head = f"== warp-blas-graph {prec} train cheetah B={B} (side streams {self.side}): {head}"
                    print(head, flush=True)
                    f.write(head + "\n" + "\n".join(lines) + "\n\n")
                except Exception as exc:  # noqa: BLE001
                    print(f"== timeline {prec}: failed: {type(exc).__name__}: {exc}", flush=True)
                    if self.args.verbose:
                        traceback.print_exc()
        print(f"wrote {path}")

    # -- report ---------------------------------------------------------------------------------
    def write_markdown(self):
        rows = [renamed(json.loads(line)) for line in open(self.jsonl)] if self.jsonl.exists() else []
        # a re-run replaces earlier rows of the same measurement
        key = ("peer", "precision", "shape", "batch", "mode", "width", "efl", "det", "opt", "flatp", "side", "emu")
        rows = list({tuple(r.get(k) for k in key): r for r in rows}.values())
        # the versions the rows were measured with (a rewrite elsewhere must not name its own)
        versions = ", ".join(f"{k} {'/'.join(sorted({str(r.get(k)) for r in rows if r.get(k)}))}"
                             for k in ("torch", "warp")) if rows else f"torch {torch.__version__}"
        lines = [f"# GN block benchmark on {self.device_name}", "",
                 f"{versions}; paper two-block core "
                 f"({'QUICK tiny sizes' if self.args.quick else 'edge MLP 3x512, node/global 2x256, latent 128'}). "
                 "TFLOP/s from the reference FLOP count (concatenated first layers; training step = 3x forward; "
                 "our blas path executes ~12% fewer FLOPs); % peak against the measured torch.mm peak of the "
                 "same precision. Median of repeats; CUDA events after warm-up.", ""]
        peaks = [r for r in rows if r.get("mode") == "peak" and "tflops" in r]
        if peaks:
            lines += ["## Measured matmul peak (torch.mm)", "", "| precision | shape | TFLOP/s |", "|---|---|---|"]
            lines += [f"| {r['precision']} | {r['shape']} | {r['tflops']:.2f} |" for r in peaks] + [""]
        timed = [r for r in rows if r.get("mode") in ("fwd", "fwdbwd", "train") and "batch" in r]
        notes = [r for r in rows if r.get("mode") in ("fwd", "fwdbwd", "train") and "batch" not in r]
        lines += [f"- {r['peer']} ({r['mode']}): {_md(r.get('error', ''))}" for r in notes] + ([""] if notes else [])
        for shape in dict.fromkeys(r.get("shape") for r in timed):
            lines += [f"## {shape}", "", "| batch | mode | peer | precision | ms | graph-steps/s | TFLOP/s | % peak |",
                      "|---|---|---|---|---|---|---|---|"]
            for r in timed:
                if r.get("shape") != shape:
                    continue
                label = r["peer"] + (f" (w={r['width']})" if "width" in r else "") + \
                    (f" [edge first layer: {r['efl']}]" if r.get("efl") else "") + \
                    (" [deterministic]" if r.get("det") else "") + (" [FlatAdam]" if r.get("opt") == "flat" else "") + \
                    (" [flat params]" if r.get("flatp") else "") + \
                    (" [fp16x3 from rows, width %s]" % r["emu"] if r.get("emu") else "") + \
                    (" [no side stream]" if r.get("side") in (False, 0) else
                     f" [side streams: {r['side']}]" if r.get("side") is not None else "")
                if r.get("error"):
                    lines.append(f"| {r.get('batch', '')} | {r['mode']} | {label} | {r.get('precision', '')} | failed: "
                                 f"{_md(r['error'][:120])} | | | |")
                else:
                    fp = r.get("frac_peak")
                    lines.append(f"| {r['batch']} | {r['mode']} | {label} | {r['precision']} | {r['ms']:.3f} | "
                                 f"{r['graph_steps_per_s']:.4g} | {r['tflops']:.3f} | "
                                 f"{'' if fp is None else f'{100 * fp:.1f}'} |")
            lines.append("")
        errs = [r for r in rows if r.get("mode") == "error"]
        if errs:
            lines += ["## Error against the float64 torch reference (max |err| / max |ref|)", "",
                      "| peer | precision | error |", "|---|---|---|"]
            for r in errs:
                val = f"failed: {_md(r['error'][:100])}" if r.get("error") else f"{r['max_rel_err']:.2e}"
                lines.append(f"| {r['peer']} | {r['precision']} | {val} |")
            lines.append("")
        lines += self.goals(rows)
        self.md.write_text("\n".join(lines) + "\n")
        print(f"\nwrote {self.jsonl} and {self.md}")

    def goals(self, rows):
        ok = [r for r in rows if "ms" in r and r.get("shape") == "cheetah" and "width" not in r and "emu" not in r]
        peaks = {r["precision"]: r["tflops"] for r in rows if r.get("mode") == "peak" and "tflops" in r}
        for r in ok:  # rows timed without a peak measurement in their run: the latest peak
            pp = PEER_PRECISION.get(r.get("precision"), r.get("precision"))
            if not r.get("frac_peak") and pp in peaks:
                r["frac_peak"] = r["tflops"] / peaks[pp]

        def best(pred):
            c = [r for r in ok if pred(r)]
            return min(c, key=lambda r: r["ms"]) if c else None
        out = ["## Goals", ""]
        r = best(lambda r: r["mode"] == "train" and r["batch"] == 200 and r["peer"].startswith("warp"))
        got = "n/a" if r is None else f"{r['ms']:.3f} ms ({r['peer']}, {r['precision']})"
        out.append(f"- training step at batch 200 <= 0.5 ms: best of ours {got}")
        for prec in OUR_PRECISIONS:
            pp = PEER_PRECISION.get(prec, prec)
            ours = best(lambda r: r["mode"] == "fwd" and r["batch"] == 4096 and r["peer"].startswith("warp")
                        and r["precision"] == prec)
            peer = best(lambda r: r["mode"] == "fwd" and r["batch"] == 4096 and r["peer"].startswith("torch")
                        and r["precision"] == pp)
            if ours and peer:
                out.append(f"- forward at batch 4096, {prec}{f' (vs torch {pp})' if pp != prec else ''}: ours "
                           f"{ours['ms']:.3f} ms ({ours['peer']}) vs best torch "
                           f"{peer['ms']:.3f} ms ({peer['peer']}): {peer['ms'] / ours['ms']:.2f}x (goal >= 1.5x); "
                           f"{100 * (ours.get('frac_peak') or 0):.1f}% of {pp} matmul peak (goal >= 50%)")
            top = [r for r in ok if r["mode"] == "fwd" and r["batch"] > 4096 and r["peer"].startswith("warp")
                   and r["precision"] == prec and r.get("frac_peak")]
            if top:
                r = max(top, key=lambda r: r["frac_peak"])
                out.append(f"  - at batch {r['batch']}: {100 * r['frac_peak']:.1f}% of peak ({r['peer']}, {r['ms']:.3f} ms)")
        cross = [r for r in rows if "width" in r and "ms" in r]
        if cross:
            out += ["", "### Path crossover (blas vs tile, fp32, cheetah)", "",
                    "| width | batch | mode | blas ms | tile ms | winner |", "|---|---|---|---|---|---|"]
            for graph in ("", "-graph"):
                keyed = {}
                for r in cross:
                    if r["peer"] in (f"warp-blas{graph}", f"warp-tile{graph}"):
                        keyed.setdefault((r["width"], r["batch"], r["mode"]), {})[r["peer"].split("-")[1]] = r["ms"]
                for (w, B, mode), d in sorted(keyed.items()):
                    if "blas" in d and "tile" in d:
                        win = "tile" if d["tile"] < d["blas"] else "blas"
                        out.append(f"| {w} | {B} | {mode}{' (captured)' if graph else ''} | {d['blas']:.3f} | "
                                   f"{d['tile']:.3f} | {win} |")
        return out + [""]


def timeline_table(events):
    """(lines, summary) of the device kernels / memsets / copies of a chrome trace (torch.profiler's
    ``export_chrome_trace``), in start order: index, stream, start (us from the first), duration,
    the idle gap before it on its stream, name. Summary: span, kernels per stream, and the main
    stream's (the one with the most kernels) busy and idle time."""
    ks = [e for e in events if e.get("ph") == "X" and e.get("cat") in ("kernel", "gpu_memset", "gpu_memcpy")]
    if not ks:
        return [], "no device events in the trace"
    ks.sort(key=lambda e: e["ts"])
    t0 = ks[0]["ts"]
    end: dict = {}
    count: dict = {}
    busy: dict = {}
    idle: dict = {}
    lines = [f"{'#':>4} {'stream':>6} {'start':>9} {'dur':>8} {'gap':>7}  name (us)"]
    for k, e in enumerate(ks):
        st = e.get("args", {}).get("stream", -1)
        gap = e["ts"] - end[st] if st in end else 0.0
        end[st] = max(end.get(st, 0.0), e["ts"] + e["dur"])
        count[st] = count.get(st, 0) + 1
        busy[st] = busy.get(st, 0.0) + e["dur"]
        idle[st] = idle.get(st, 0.0) + max(gap, 0.0)
        lines.append(f"{k:4d} {st:6d} {e['ts'] - t0:9.1f} {e['dur']:8.2f} {gap:7.2f}  {e['name'][:110]}")
    span = max(end.values()) - t0
    main = max(count, key=count.get)
    per = ", ".join(f"stream {s}: {n}" for s, n in sorted(count.items()))
    return lines, (f"{len(ks)} device events over {span:.1f} us ({per}); main stream {main}: busy "
                   f"{busy[main]:.1f} us, idle {idle[main]:.1f} us between its events")


def _autocast(precision: str, device):
    """The torch peers' reduced precision: ``torch.autocast`` in fp16 / bf16 (GEMMs in that dtype,
    reductions and index_add_ as autocast leaves them), as a PyTorch user would write it."""
    import contextlib  # noqa: PLC0415
    if precision not in ("fp16", "bf16"):
        return contextlib.nullcontext
    dt = torch.float16 if precision == "fp16" else torch.bfloat16
    return lambda: torch.autocast(device.type, dtype=dt)


def _md(s: str) -> str:
    return s.replace("|", "/").replace("\n", " ")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny sizes on the CPU: smoke test of this script")
    p.add_argument("--out", default=results_dir("gn_block"))
    p.add_argument("--device", default=None, help="default: cuda if available, else cpu")
    p.add_argument("--sections", default="peak,main,shapes,capture,errors,crossover")
    p.add_argument("--peers", default=",".join(TORCH_PEERS + WARP_PEERS))
    p.add_argument("--precisions", default=",".join(OUR_PRECISIONS))
    p.add_argument("--batches", default="200,4096", help="batches of fwd / fwd+bwd / train")
    p.add_argument("--fwd-batches", default="65536", help="extra forward-only batches")
    p.add_argument("--compile-modes", default="fwd,train",
                   help="modes timed for the torch.compile peers (each is a fresh compile, ~0.5-1 min on GPU)")
    p.add_argument("--reps", type=int, default=30)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--tile-mathdx", type=int, default=0,
                   help="1: fused tile GEMMs through cuBLASDx (1-2.5 min compile per kernel on sm_90); "
                        "0: Warp's plain tile GEMM (seconds)")
    p.add_argument("--edge-first-layer", default="auto", choices=("auto", "concat", "project"),
                   help="our peers' RunOptions(edge_first_layer=...)")
    p.add_argument("--deterministic", action="store_true",
                   help="our peers aggregate with ordered segment sums (RunOptions(deterministic=True))")
    p.add_argument("--optimizer", default="torch", choices=("torch", "flat"),
                   help="our peers' training step: torch's fused Adam + clip_grad_norm_, or gnwarp.train.FlatAdam")
    p.add_argument("--flat-params", action="store_true",
                   help="our peers' parameters moved into one buffer first (gnwarp.flatten_parameters)")
    p.add_argument("--side-streams", type=int, default=None,
                   help="side streams of our backward's weight-gradient GEMMs, 0: none "
                        "(gnwarp.gn.TUNABLES.side_streams; default: the library's)")
    p.add_argument("--emulate-min", default=None, metavar="ROWS,WIDTH",
                   help="fp16x3: emulate MLP layers from this many rows and hidden width (default: the library's rule)")
    p.add_argument("--verbose", action="store_true")
    a = p.parse_args(argv)
    if a.device is None:
        a.device = "cuda" if torch.cuda.is_available() and not a.quick else "cpu"
    if a.quick:
        if "--batches" not in (argv or sys.argv):
            a.batches = "4,16"
        if "--fwd-batches" not in (argv or sys.argv):
            a.fwd_batches = "64"
        a.reps, a.warmup = min(a.reps, 3), min(a.warmup, 1)
        # one intra-op thread: on a small shared CPU, OpenMP workers spinning after each torch op
        # steal the core that runs the Warp kernels (timings then swing by 100x)
        torch.set_num_threads(1)
    a.batches = [int(x) for x in a.batches.split(",") if x]
    a.fwd_batches = [int(x) for x in a.fwd_batches.split(",") if x]
    a.peers = [x for x in a.peers.split(",") if x]
    a.precisions = [x for x in a.precisions.split(",") if x]
    a.compile_modes = [x for x in a.compile_modes.split(",") if x]
    TUNABLES.tile_mathdx = bool(a.tile_mathdx)

    r = Runner(a)
    print(f"GN block benchmark on {r.device_name} (torch {torch.__version__}, warp "
          f"{wp.__version__}); rows -> {r.jsonl}", flush=True)
    for section in a.sections.split(","):
        print(f"\n== {section}", flush=True)
        t0 = time.time()
        if section != "peak" and not r.peaks and section in ("main", "shapes", "capture", "efl", "optim", "flat",
                                                               "side"):
            r.section_peak()  # the % of peak column needs it
        getattr(r, f"section_{section}")()
        print(f"   ({time.time() - t0:.1f} s)", flush=True)
        r.write_markdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
