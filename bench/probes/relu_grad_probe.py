"""Probe: ReLU backward fused with the bias gradient (column sums) at the training-step shapes:
the library's ``relu_grad_sum_kernel`` (``gnwarp.kernels.gn.mlp``) against torch.

``relu_grad_sum`` took ~89 us of a 0.7 ms training step at batch 200 in the fp16 profile (12
launches; the edge MLP's 3600 x 512 ones ~10 us each). This times, on the same shapes and in the
same run:

- ``ours``: the library's kernel with its rows per thread (``relu_chunk_rows``), and
  ``ours chunkN`` with N rows per thread (its tuning knob)
- ``torch``: ``torch.ops.aten.threshold_backward`` then ``sum(0)`` (two kernels)

The committed table ``bench/results/probes/relu_grad_probe_nvidia-h200.md`` also holds two
one-column kernels this script does not run (their code is in git history): ``v8 one column,
conditional load`` and ``one column, both loads``.

Usage: ``python bench/probes/relu_grad_probe.py [--out DIR]`` (CUDA). Prints a table and writes
``relu_grad_probe_<gpu>.md``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import captured_us, results_dir, slug  # noqa: E402
from gnwarp.interop import WP_DTYPE, Launcher  # noqa: E402
from gnwarp.kernels.gn.mlp import relu_chunk_rows, relu_grad_dim, relu_grad_sum_kernel  # noqa: E402


def variants(act, g0, g, gb) -> dict:
    """{variant: fn}: each writes the ReLU gradient of ``g0`` at ``act`` into ``g`` (ours: in
    place, from ``g`` holding ``g0``) and adds its column sums into ``gb``."""
    rows, W = act.shape
    kern = relu_grad_sum_kernel(W, WP_DTYPE[act.dtype], bias_sum=True)

    def ours(chunk):
        # a launcher per call: it launches on the current stream (the capture stream)
        return lambda: Launcher(g)(kern, relu_grad_dim(rows, W, chunk), act, g, rows, chunk, g, gb)
    res = {"ours": ours(relu_chunk_rows(rows, W))}
    res.update({f"ours chunk{c}": ours(c) for c in (8, 16, 32)})
    gt = torch.empty_like(g)

    def torch_fn():
        torch.ops.aten.threshold_backward(g0, act, 0, grad_input=gt)
        torch.sum(gt, 0, dtype=torch.float32, out=gb)
    res["torch"] = torch_fn
    return res, gt


def check(name, fn, act, g0, g, gb, gt) -> bool:
    """One call of ``fn`` gives the ReLU gradient and its column sums."""
    expect = torch.where(act > 0, g0, torch.zeros_like(g0))
    g.copy_(g0)
    gb.zero_()
    fn()
    if g.is_cuda:
        torch.cuda.synchronize()
    return torch.equal(g if name != "torch" else gt, expect) and torch.allclose(
        gb, expect.float().sum(0), rtol=1e-3, atol=1e-2)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=results_dir("probes"))
    a = p.parse_args()
    dev = torch.device("cuda")
    rows_out = []
    for dt in (torch.float16, torch.float32):
        for rows, W in ((3600, 512), (1600, 256), (73728, 512)):
            act = torch.randn(rows, W, device=dev).relu().to(dt)
            g0 = torch.randn(rows, W, device=dev).to(dt)
            g = g0.clone()
            gb = torch.zeros(W, device=dev)
            fns, gt = variants(act, g0, g, gb)
            nbytes = 3 * rows * W * g.element_size()
            for name, fn in fns.items():
                ok = check(name, fn, act, g0, g, gb, gt)
                us = captured_us(fn)
                rows_out.append((str(dt).split(".")[-1], f"{rows}x{W}", name, us, nbytes / us / 1e3, ok))
                print(f"{rows_out[-1][0]:8s} {rows_out[-1][1]:10s} {name:16s} {us:8.2f} us {nbytes / us / 1e3:7.0f} GB/s"
                      f"  {'ok' if ok else 'WRONG'}", flush=True)
    gpu = torch.cuda.get_device_name(dev)
    lines = [f"# ReLU backward + bias sums on {gpu}", "", "Captured, 20 launches per replay, median; GB/s counts "
             "the act and grad reads and the grad write.", "", "| dtype | shape | variant | us | GB/s | correct |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {d} | {s} | {n} | {us:.2f} | {bw:.0f} | {ok} |" for d, s, n, us, bw, ok in rows_out]
    out = Path(a.out) / f"relu_grad_probe_{slug(gpu)}.md"
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
