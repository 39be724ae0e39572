"""Probe: how fast do Warp's scalar-access kernels move memory, against torch on the same copy?

Times the blas path's ``concat_kernel`` (``gnwarp.kernels.gn.graph_ops``) at the paper core's
second-block edge shape (73728 rows, pieces 192 + 159 + 159 + 160 fp32 columns -> 672 fp16
columns, three of them gathered), its variants (fp32 output, block sizes, no gathers), a one-line
Warp copy kernel fp32 -> fp16 of the same element count, torch's ``copy_`` of it and the torch
idiom (index, cat, cast). CUDA only.

    python bench/probes/warp_copy_probe.py
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import device_name, median_ms  # noqa: E402
from gnwarp.interop import warp  # noqa: E402
from gnwarp.kernels.gn.graph_ops import concat_kernel, concat_threads  # noqa: E402


def main():
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    if not torch.cuda.is_available():
        print("needs a CUDA device")
        return 1
    warp()  # initialized as the library does
    dev = torch.device("cuda:0")
    wd = wp.device_from_torch(dev)
    stream = wp.stream_from_torch(torch.cuda.current_stream(dev))
    E, N, B, KO = 73728, 32768, 4096, 672
    e = torch.randn(E, 192, device=dev)
    v = torch.randn(N, 159, device=dev)
    u = torch.randn(B, 160, device=dev)
    s = torch.randint(0, N, (E,), device=dev, dtype=torch.int32).sort().values
    r = torch.randint(0, N, (E,), device=dev, dtype=torch.int32).sort().values
    g = torch.arange(E, device=dev, dtype=torch.int32) // 18

    def arr(x):
        return wp.from_torch(x, return_ctype=True)

    def concat(out_dtype, gathered=True, block_dim=256):
        kern = concat_kernel((192, 159, 159, 160), (False, gathered, gathered, gathered), (wp.float32,) * 4,
                             wp.float16 if out_dtype == torch.float16 else wp.float32, KO)
        out = torch.empty(E, KO, device=dev, dtype=out_dtype)
        vv = v if gathered else torch.randn(E, 159, device=dev)
        uu = u if gathered else torch.randn(E, 160, device=dev)
        args = [arr(e), arr(vv), arr(vv), arr(uu), arr(s), arr(s), arr(r), arr(g), E]
        return lambda: wp.launch(kern, dim=concat_threads(E, (192, 159, 159, 160), KO), inputs=args,
                                 outputs=[arr(out)], device=wd, stream=stream, block_dim=block_dim)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def copy_cast(
        # Data in:
        a_in: wp.array(dtype=wp.float32),
        # Data out:
        b_out: wp.array(dtype=wp.float16),
    ):
        i = wp.tid()
        b_out[i] = wp.float16(a_in[i])

    x = torch.randn(E * KO, device=dev)
    y = torch.empty(E * KO, device=dev, dtype=torch.float16)
    sl, rl, gl = s.long(), r.long(), g.long()
    rows = [
        ("concat kernel, gathered, fp32 -> fp16", concat(torch.float16), 4 + 2),
        ("concat kernel, gathered, fp32 -> fp16, block 128", concat(torch.float16, block_dim=128), 4 + 2),
        ("concat kernel, gathered, fp32 -> fp16, block 512", concat(torch.float16, block_dim=512), 4 + 2),
        ("concat kernel, gathered, fp32 -> fp32", concat(torch.float32), 4 + 4),
        ("concat kernel, no gathers, fp32 -> fp16", concat(torch.float16, gathered=False), 4 + 2),
        ("Warp one-line copy kernel fp32 -> fp16", lambda: wp.launch(copy_cast, dim=E * KO, inputs=[arr(x)],
                                                                     outputs=[arr(y)], device=wd, stream=stream), 4 + 2),
        ("torch copy_ fp32 -> fp16", lambda: y.copy_(x), 4 + 2),
        ("torch cat(e, v[s], v[r], u[g]).half()", lambda: torch.cat([e, v[sl], v[rl], u[gl]], 1).half(), None),
    ]
    print(f"# Warp scalar kernels vs torch on one copy ({device_name()}, warp {wp.__version__}, torch {torch.__version__})")
    print(f"\n{E} x {KO} elements\n\n| kernel | us | GB/s (elements x bytes read + written) |\n|---|---|---|")
    for name, fn, nbytes in rows:
        us = median_ms(fn, dev, 20, 3) * 1e3
        bw = f"{E * KO * nbytes / us / 1e3:.0f}" if nbytes else ""
        print(f"| {name} | {us:.1f} | {bw} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
