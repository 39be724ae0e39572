"""Probe: ReLU backward fused with the bias gradient (column sums) at the training-step shapes.

``relu_grad_sum`` (kernels/gn_block.py) took ~89 us of a 0.7 ms training step at batch 200 in
the fp16 profile (12 launches; the edge MLP's 3600 x 512 ones ~10 us each). This times variants
on the same shapes, each against torch's ``threshold_backward`` + ``sum(0)`` in the same run:

- ``ours``: the library's kernel (each thread owns 4 columns, strided by width / 4, of a chunk of
  rows; both loads unconditional), ``ours chunkN`` with N rows per thread
- ``v8 one column, conditional load``: the kernel before (one column per thread, the gradient
  loaded only where the activation is positive), rows per thread as it chose them
- ``one column, both loads``: the same with unconditional loads, 16 rows per thread
- ``torch``: ``torch.ops.aten.threshold_backward`` then ``sum(0)`` (two kernels)

Usage: ``python bench/relu_grad_probe.py [--out bench/results]`` (CUDA). Prints a table and
writes ``relu_grad_probe_<gpu>.md``.
"""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import torch
import warp as wp

from gnwarp.gn_warp import _Launcher
from gnwarp.kernels import gn_block as K
from gnwarp.optim import WP_DTYPE

wp.config.quiet = True


def v8_kernel(width: int, dtype, conditional: bool):
    """The library's kernel before: one column per thread; ``conditional``: the gradient is loaded
    only where the activation is positive (a load that waits on the activation's)."""
    RB, T = K.ROW_BATCH, dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def relu_grad_v8(act_in: wp.array2d(dtype=T), grad_in: wp.array2d(dtype=T), rows: int, chunk: int,
                     grad_out: wp.array2d(dtype=T), sum_out: wp.array(dtype=float)):
        i = wp.tid()
        ci = i // width
        j = i - ci * width
        r0 = ci * chunk
        r1 = wp.min(r0 + chunk, rows)
        acc = float(0.0)
        for rb in range(r0, r1, RB):
            gs = wp.vector(length=RB, dtype=T)
            for k in range(RB):
                r = rb + k
                if r < r1:
                    if wp.static(conditional):
                        if act_in[r, j] > T(0.0):
                            gs[k] = grad_in[r, j]
                    else:
                        a = act_in[r, j]
                        x = grad_in[r, j]
                        gs[k] = wp.where(a > T(0.0), x, T(0.0))
            for k in range(RB):
                r = rb + k
                if r < r1:
                    grad_out[r, j] = gs[k]
                    acc += float(gs[k])
        wp.atomic_add(sum_out, j, acc)

    return relu_grad_v8


def time_us(fn, reps=200):
    for _ in range(5):
        fn()
    torch.cuda.synchronize()
    g = torch.cuda.CUDAGraph()
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    from gnwarp.gn_warp import cuda_graph  # noqa: PLC0415
    with cuda_graph(g, s):
        for _ in range(20):
            fn()
    torch.cuda.synchronize()
    a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    times = []
    for _ in range(reps // 20):
        a.record()
        g.replay()
        b.record()
        torch.cuda.synchronize()
        times.append(a.elapsed_time(b) * 1e3 / 20)
    times.sort()
    return times[len(times) // 2]


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    a = p.parse_args()
    dev = torch.device("cuda")
    rows_out = []
    for dt in (torch.float16, torch.float32):
        for rows, W in ((3600, 512), (1600, 256), (73728, 512)):
            act = torch.randn(rows, W, device=dev).relu().to(dt)
            g0 = torch.randn(rows, W, device=dev).to(dt)
            g = g0.clone()
            gb = torch.zeros(W, device=dev)
            T = WP_DTYPE[dt]
            res = {}

            def ours(chunk=None, kern=None):
                c = chunk or (K.relu_chunk_rows(rows, W) if kern is None else K.chunk_rows(rows, W))
                k = kern or K.relu_grad_sum_kernel(W, True, T)
                dim = K.relu_grad_dim(rows, W, c) if kern is None else K.chunk_dim(rows, W, c)
                # a launcher per call: it launches on the current stream (the capture stream)
                return lambda: _Launcher(g).n(k, dim, act, g, rows, c, g, gb)
            variants = {"ours": ours(), "ours chunk8": ours(8), "ours chunk16": ours(16), "ours chunk32": ours(32)}
            for name, cond in (("v8 one column, conditional load", True), ("one column, both loads", False)):
                variants[name] = ours(None if cond else 16, v8_kernel(W, T, cond))
            gt = torch.empty_like(g)

            def torch_v():
                torch.ops.aten.threshold_backward(g0, act, 0, grad_input=gt)
                torch.sum(gt, 0, dtype=torch.float32, out=gb)
            variants["torch"] = torch_v
            # correctness of each variant against torch (bias sums of one call)
            expect = torch.where(act > 0, g0, torch.zeros_like(g0))
            for name, fn in variants.items():
                g.copy_(g0)
                gb.zero_()
                fn()
                torch.cuda.synchronize()
                ok = torch.equal(g if name != "torch" else gt, expect) and torch.allclose(
                    gb, expect.float().sum(0), rtol=1e-3, atol=1e-2)
                res[name] = (time_us(fn), ok)
            nbytes = 3 * rows * W * g.element_size()
            for name, (us, ok) in res.items():
                rows_out.append((str(dt).split(".")[-1], f"{rows}x{W}", name, us, nbytes / us / 1e3, ok))
                print(f"{rows_out[-1][0]:8s} {rows_out[-1][1]:10s} {name:16s} {us:8.2f} us {nbytes / us / 1e3:7.0f} GB/s"
                      f"  {'ok' if ok else 'WRONG'}", flush=True)
    name = torch.cuda.get_device_name(dev)
    slug = re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-").lower()
    lines = [f"# ReLU backward + bias sums on {name}", "", "Captured, 20 launches per replay, median; GB/s counts "
             "the act and grad reads and the grad write.", "", "| dtype | shape | variant | us | GB/s | correct |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {d} | {s} | {n} | {us:.2f} | {bw:.0f} | {ok} |" for d, s, n, us, bw, ok in rows_out]
    out = Path(a.out) / f"relu_grad_probe_{slug}.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
