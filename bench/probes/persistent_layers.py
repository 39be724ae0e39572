"""Probe (issue 38): can one persistent Warp kernel run a model step's chain of dense layers near
the 60-us goal, where one kernel a layer cannot (``../results/mpc_latency/NOTES.md``, "Next
sitting": >= ~2.2 us a launch in a CUDA graph, 36 dependent layers a step fwd+bwd, >= ~80 us)?

One launch runs ``--layers`` dependent dense layers h <- relu(h W_l + b_l) (width ``--width``,
``M`` rows) over ``B`` thread blocks that stay resident and meet at a grid-wide barrier after
each layer (thread 0 of each block: a fence and an atomic arrival on a counter, then a spin on
it; ``__syncthreads`` around). Each layer's K is split (partial sums added atomically into a
zeroed buffer; the next layer applies the bias and ReLU as it reads) so that the work spreads
over the blocks' threads as far as splits of at least 8 columns allow (at 1 row, 8192 items: at
B >= 33 some threads idle). A layer here is its work and one barrier (the last one too). A block spinning past ``SPIN_LIMIT``
reads sets an error flag, and no barrier after it waits (a wrong result, never a hang: the
blocks must all be resident, ``B`` <= the multiprocessor count and nothing else on the GPU).

Beside it, in the same process: the same chain as torch ``addmm`` + ``relu`` captured in a CUDA
graph (cuBLAS, one or two kernels a layer; float32 and TF32, the planner's default), the barrier
alone (layers of no work) and the launch alone (no layers: the two buffer fills and the launch,
taken off the others). Per (M, B): microseconds a layer (median of graph replays), the chain's
relative error against float64, and the implied 36-layer step. Each case's record is written as
soon as it is measured; a case whose barrier timed out is recorded with its error and the next
one runs. Records (one JSON line each) go to
``bench/results/probes/persistent_layers_<gpu>.jsonl``; the table is printed.

    python bench/probes/persistent_layers.py                       # on a GPU
    python bench/probes/persistent_layers.py --rows 1,16 --blocks 1,8,33,66,132

On a CPU (``--cpu``: tiny sizes, one thread, the barrier compiled out) it only checks the chain's
arithmetic against float64: Warp's CPU device runs a launch's threads one after another, so a
barrier between them cannot exist there.
"""
from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
import warp as wp

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.harness import device_name, slug  # noqa: E402
from gnwarp.interop import warp, warp_stream  # noqa: E402

SPIN_LIMIT = 1 << 20   # volatile reads a block spins at one barrier before it gives up (~1 s)
BLOCK = 256            # threads a block

_BARRIER = r"""
#if defined(__CUDA_ARCH__)
__syncthreads();
if (threadIdx.x == 0) {
    __threadfence();
    atomicAdd(counter.data, 1);
    volatile int* c = counter.data;
    volatile int* e = error.data;   // set: an earlier barrier timed out; later ones do not wait
    long long spins = 0;
    while (*c < target && !*e) {
        if (++spins > limit) { atomicExch(error.data, 1); break; }
    }
    __threadfence();
}
__syncthreads();
#endif
"""


@wp.func_native(_BARRIER)
def grid_barrier(counter: wp.array(dtype=wp.int32), error: wp.array(dtype=wp.int32), target: int, limit: int):
    ...


@wp.kernel(module="unique", module_options={"enable_backward": False})
def chain_kernel(
    # Data in:
    weights: wp.array3d(dtype=wp.float32),   # [layers, width, width]: h_l = relu(h_{l-1} W_l + b_l)
    bias: wp.array2d(dtype=wp.float32),      # [layers, width]
    x: wp.array2d(dtype=wp.float32),         # [rows, width]: h_0 (activated)
    # Work space and out:
    sums: wp.array3d(dtype=wp.float32),      # [3, rows, width]: layer l adds into sums[l % 3]; sums[0] zero at launch
    counter: wp.array(dtype=wp.int32),       # zero at launch
    error: wp.array(dtype=wp.int32),
    # Sizes:
    layers: int, splits: int, threads: int, blocks: int, work: int,
):
    """One thread of the persistent chain (module docstring); ``work`` 0: barriers only."""
    tid = wp.tid()
    rows, width = x.shape[0], x.shape[1]
    chunk = (width + splits - 1) // splits
    for layer in range(layers):
        cur = layer % 3
        if work != 0:
            nxt = (layer + 1) % 3   # last read by layer - 1: zero it for layer + 1
            item = tid
            while item < rows * width:
                sums[nxt, item // width, item % width] = 0.0
                item += threads
            item = tid
            while item < rows * width * splits:
                s = item % splits
                j = (item // splits) % width
                m = item // (splits * width)
                acc = float(0.0)
                k0 = s * chunk
                k1 = wp.min(k0 + chunk, width)
                for k in range(k0, k1):
                    h = float(0.0)
                    if layer == 0:
                        h = x[m, k]
                    else:
                        h = wp.max(sums[(layer + 2) % 3, m, k] + bias[layer - 1, k], 0.0)
                    acc += h * weights[layer, k, j]
                wp.atomic_add(sums, cur, m, j, acc)
                item += threads
        grid_barrier(counter, error, (layer + 1) * blocks, SPIN_LIMIT)


def reference(w: np.ndarray, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The chain in float64."""
    h = x.astype(np.float64)
    for layer in range(w.shape[0]):
        h = np.maximum(h @ w[layer].astype(np.float64) + b[layer].astype(np.float64), 0.0)
    return h


class Chain:
    """The persistent chain's buffers and its launch on ``device`` (a torch device)."""

    def __init__(self, w: torch.Tensor, b: torch.Tensor, x: torch.Tensor, blocks: int, splits: int,
                 work: bool = True, layers: int | None = None):
        """``layers``: how many of ``w``'s layers a call runs (default all; 0 times the launch alone)."""
        warp()
        L, K, N = w.shape
        if K != N or x.shape[1] != K or b.shape != (L, N):
            raise ValueError(f"weights {tuple(w.shape)}, bias {tuple(b.shape)}, input {tuple(x.shape)}: "
                             "a chain of square layers of one width")
        dev = x.device
        threads = blocks * (BLOCK if dev.type == "cuda" else 1)
        if dev.type != "cuda" and blocks != 1:
            raise ValueError(f"blocks={blocks} on {dev}: Warp's CPU device runs threads one after another, "
                             "so only one thread (one block) computes the chain there")
        if dev.type == "cuda":
            sms = torch.cuda.get_device_properties(dev).multi_processor_count
            if not 1 <= blocks <= sms:
                raise ValueError(f"blocks={blocks}: 1 to {sms} (the multiprocessors: all must be resident)")
        self.w, self.b, self.x = w.contiguous(), b.contiguous(), x.contiguous()
        self.sums = torch.zeros(3, x.shape[0], N, device=dev)
        self.counter = torch.zeros(1, device=dev, dtype=torch.int32)
        self.error = torch.zeros(1, device=dev, dtype=torch.int32)
        self.blocks, self.splits, self.threads, self.work = blocks, splits, threads, int(work)
        self.wd = wp.device_from_torch(dev)
        self.layers = L if layers is None else layers
        if not 0 <= self.layers <= L:
            raise ValueError(f"layers={layers}: 0 to {L}")

    def __call__(self) -> None:
        self.sums[0].zero_()
        self.counter.zero_()
        arr = lambda t: wp.from_torch(t, return_ctype=True)  # noqa: E731
        stream = warp_stream(torch.cuda.current_stream(self.x.device)) if self.x.is_cuda else None
        wp.launch(chain_kernel, dim=self.threads, device=self.wd, stream=stream,
                  block_dim=BLOCK if self.x.is_cuda else 1,
                  inputs=[arr(self.w), arr(self.b), arr(self.x), arr(self.sums), arr(self.counter), arr(self.error),
                          self.layers, self.splits, self.threads, self.blocks, self.work])

    def output(self) -> torch.Tensor:
        """h_L after a call: the last layer's sums with its bias and ReLU."""
        return torch.relu(self.sums[(self.layers - 1) % 3] + self.b[-1])


def splits_for(rows: int, width: int, blocks: int) -> int:
    """K-splits so that the items (rows x width x splits) about fill ``blocks`` blocks' threads,
    each split at least 8 wide."""
    want = max(1, (blocks * BLOCK) // (rows * width))
    return int(min(want, max(1, width // 8)))


def _inputs(layers: int, width: int, rows: int, device, seed: int):
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(layers, width, width, generator=g) * (2.0 / width) ** 0.5   # He: the scale stays
    b = torch.randn(layers, width, generator=g) * 0.1
    x = torch.relu(torch.randn(rows, width, generator=g))
    return w.to(device), b.to(device), x.to(device)


def check(chain: Chain) -> float:
    """The chain's relative error against float64 (after one call)."""
    chain()
    if chain.x.is_cuda:
        torch.cuda.synchronize()
    if int(chain.error.item()):
        raise RuntimeError(f"a block waited past {SPIN_LIMIT} reads at a barrier (blocks={chain.blocks}): "
                           "not every block was resident")
    ref = reference(chain.w.cpu().numpy(), chain.b.cpu().numpy(), chain.x.cpu().numpy())
    out = chain.output().double().cpu().numpy()
    return float(np.linalg.norm(out - ref) / max(np.linalg.norm(ref), 1e-30))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", default="1,16", help="comma-separated rows M of each layer's input")
    ap.add_argument("--blocks", default="1,8,33,66,132", help="comma-separated thread blocks B (<= the SMs)")
    ap.add_argument("--layers", type=int, default=36)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--reps", type=int, default=50, help="graph replays timed (median)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "probes")
    ap.add_argument("--cpu", action="store_true", help="check the arithmetic on the CPU (tiny sizes) and stop")
    a = ap.parse_args(argv)
    warp()
    if a.cpu or not torch.cuda.is_available():
        w, b, x = _inputs(4, 16, 2, torch.device("cpu"), 0)
        err = check(Chain(w, b, x, blocks=1, splits=3))
        print(f"cpu: chain of 4 layers, width 16, 2 rows, one thread: relative error {err:.2e} against float64")
        return 0 if err < 1e-5 else 1
    from bench.harness import captured_us  # noqa: PLC0415
    dev = torch.device("cuda:0")
    gpu = device_name(dev)
    sms = torch.cuda.get_device_properties(dev).multi_processor_count
    rows_list = [int(v) for v in a.rows.split(",")]
    blocks_list = [int(v) for v in a.blocks.split(",") if int(v) <= sms]
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / f"persistent_layers_{slug(gpu)}.jsonl"
    print(f"{gpu}: {a.layers} layers of width {a.width}, one persistent launch a chain; records in {path}")
    print("| rows | blocks | K-splits | persistent us / layer | barrier alone us | launch us | torch graph us / "
          "layer fp32 / tf32 | 36 layers us | rel. error |")
    print("|---|---|---|---|---|---|---|---|---|", flush=True)

    def timed(fn) -> float:
        return captured_us(fn, reps=a.reps * 10, per_replay=10)
    for rows in rows_list:
        w, b, x = _inputs(a.layers, a.width, rows, dev, rows)

        def torch_chain(w=w, b=b, x=x):
            h = x
            for layer in range(a.layers):
                h = torch.relu(torch.addmm(b[layer], h, w[layer]))
            return h
        ref = reference(w.cpu().numpy(), b.cpu().numpy(), x.cpu().numpy())
        tf32 = torch.backends.cuda.matmul.allow_tf32
        try:
            torch.backends.cuda.matmul.allow_tf32 = False
            got = torch_chain().double().cpu().numpy()
            torch_err = float(np.linalg.norm(got - ref) / max(np.linalg.norm(ref), 1e-30))
            torch_us = timed(torch_chain) / a.layers
            torch.backends.cuda.matmul.allow_tf32 = True
            torch_tf32_us = timed(torch_chain) / a.layers
        finally:
            torch.backends.cuda.matmul.allow_tf32 = tf32
        for blocks in blocks_list:
            splits = splits_for(rows, a.width, blocks)
            rec = dict(probe="persistent_layers", gpu=gpu, rows=rows, width=a.width, layers=a.layers, blocks=blocks,
                       splits=splits, threads_per_block=BLOCK, torch_graph_us_per_layer=round(torch_us, 3),
                       torch_graph_tf32_us_per_layer=round(torch_tf32_us, 3), torch_rel_error=torch_err,
                       date=datetime.now(timezone.utc).isoformat(timespec="seconds"))
            try:
                chain = Chain(w, b, x, blocks, splits)
                bare = Chain(w, b, x, blocks, splits, work=False)
                launch = Chain(w, b, x, blocks, splits, layers=0)
                err = check(chain)
                bare()
                torch.cuda.synchronize()
                if int(bare.error.item()):
                    raise RuntimeError(f"blocks={blocks}: a barrier of the bare chain timed out")
                t0, t_chain, t_bare = timed(launch), timed(chain), timed(bare)
                if int(chain.error.item()) or int(bare.error.item()):
                    raise RuntimeError(f"blocks={blocks}: a barrier timed out while timing")
                us, bar = (t_chain - t0) / a.layers, (t_bare - t0) / a.layers
                rec.update(us_per_layer=round(us, 3), barrier_us=round(bar, 3), launch_us=round(t0, 3), rel_error=err)
                line = (f"| {rows} | {blocks} | {splits} | {us:.2f} | {bar:.2f} | {t0:.1f} | "
                        f"{torch_us:.2f} / {torch_tf32_us:.2f} | {36 * us:.0f} | {err:.1e} |")
            except RuntimeError as e:   # a timed-out barrier: recorded, the next case runs
                rec.update(error=str(e))
                line = f"| {rows} | {blocks} | {splits} | {e} |  |  |  |  |  |"
            with open(path, "a") as f:
                f.write(json.dumps(rec) + "\n")
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
