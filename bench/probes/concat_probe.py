"""Probe: the edge update's concatenated input rows [e, v[sender], v[receiver], u[graph]] at the
benchmark's cheetah shapes, batch 4096 (73728 edges): the library's ``concat_kernel``
(``gnwarp.kernels.gn.graph_ops``) against torch, each checked bit for bit against torch.

The second block's rows (192 + 159 + 159 + 160 -> 672 columns, fp32 in, fp16 out) need ~177 MB
of DRAM traffic (the fp16 rows written once, the edge rows and the node / global tables read
once): ~44 us at 4 TB/s. Variants:

- ``ours vN``: ``concat_kernel`` with ``max_vec`` = N (its tuning knob; the library uses
  ``CONCAT_VEC``): each piece gets its own whole warps, at most N columns per thread
- ``ours fp32 out``: the same writing fp32 (is it the 2-byte stores?)
- ``ours pre-gathered``: the gathered pieces materialized beforehand (is it the gathers?)
- ``torch``: index_select, cat and cast in torch

The committed table ``bench/results/probes/concat_probe_nvidia-h200.md`` also holds two variants
this script does not run (their code is in git history): ``v9 v8``, where every thread tests all
four pieces for each of its columns, and ``pieces vN``, one launch per piece.

``--ncu VARIANT,...`` runs the named variants a few times uncaptured and nothing else (for
``ncu --kernel-name regex:concat``). Usage: ``python bench/probes/concat_probe.py [--out DIR]``
(CUDA); writes ``concat_probe_<gpu>.md``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import EDGE_IN, GLOB_IN, NODE_IN, PAPER, captured_us, make_batch, results_dir, slug  # noqa: E402
from gnwarp.gn import graph_index  # noqa: E402
from gnwarp.gn.config import pad  # noqa: E402
from gnwarp.interop import WP_DTYPE, Launcher  # noqa: E402
from gnwarp.kernels.gn.graph_ops import CONCAT_VEC, concat_kernel, concat_threads  # noqa: E402


def case(name: str, B: int, dev):
    """(pieces [(tensor, index or None)], padded width) of a block's edge concat."""
    g, _ = make_batch("cheetah", B, dev)
    gi = graph_index(g)
    lat = PAPER.latent if name == "gn2" else 0
    gen = torch.Generator(device=dev).manual_seed(1)
    rnd = (lambda r, c: torch.randn(r, c, device=dev, generator=gen))
    e, v, u = rnd(gi.n_edges, EDGE_IN + lat), rnd(gi.n_nodes, NODE_IN + lat), rnd(gi.n_graphs, GLOB_IN + lat)
    pieces = [(e, None), (v, gi.senders), (v, gi.receivers), (u, gi.edge_graph)]
    return pieces, pad(sum(t.shape[1] for t, _ in pieces))


def variants(pieces, width: int, out_dtype):
    """{variant: (fn, its output tensor)} and the expected rows."""
    rows = pieces[0][0].shape[0]
    widths = tuple(t.shape[1] for t, _ in pieces)
    flat = [t.view(-1) for t, _ in pieces]
    idx = [i for _, i in pieces]
    out = torch.empty(rows, width, dtype=out_dtype, device=flat[0].device)
    out32 = torch.empty(rows, width, dtype=torch.float32, device=flat[0].device)
    none = torch.zeros(1, dtype=torch.int32, device=out.device)
    pre = [(t if i is None else t[i.long()]).contiguous() for t, i in pieces]

    def ours(max_vec, dst=out, src=flat, gathered=True):
        g = tuple(gathered and i is not None for i in idx)
        ix = [i if (gathered and i is not None) else none for i in idx]
        kern = concat_kernel(widths, g, (WP_DTYPE[torch.float32],) * 4, WP_DTYPE[dst.dtype], width, max_vec=max_vec)
        n = concat_threads(rows, widths, width, max_vec)
        # a launcher per call: it launches on the current stream (the capture stream)
        return lambda: Launcher(dst)(kern, n, *src, *ix, rows, dst.view(-1))
    res = {f"ours v{v}": (ours(v), out) for v in (2, 4, 8)}
    res["ours fp32 out"] = (ours(CONCAT_VEC, out32), out32)
    res["ours pre-gathered"] = (ours(CONCAT_VEC, src=[t.view(-1) for t in pre], gathered=False), out)

    def torch_fn():
        torch.cat([t if i is None else t.index_select(0, i) for t, i in pieces]
                  + [torch.zeros(rows, width - sum(widths), device=out.device)], 1, out=out32)
        out.copy_(out32)
    res["torch"] = (torch_fn, out)
    expect = torch.cat(pre + [torch.zeros(rows, width - sum(widths), device=out.device)], 1)
    return res, expect


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=results_dir("probes"))
    p.add_argument("--ncu", default="", help="comma-separated variants: run each 3 times, uncaptured, and stop")
    a = p.parse_args()
    dev = torch.device("cuda")
    lines = []
    for name in ("gn2", "gn1"):
        pieces, width = case(name, 4096, dev)
        res, expect = variants(pieces, width, torch.float16)
        rows = expect.shape[0]
        # DRAM bytes at best: the rows written once, every source row read once
        need = rows * width * 2 + sum(t.numel() * 4 for t, _ in pieces[:2]) + pieces[3][0].numel() * 4
        if a.ncu:
            for v in a.ncu.split(","):
                for _ in range(3):
                    res[v][0]()
            torch.cuda.synchronize()
            continue
        for v, (fn, dst) in res.items():
            dst.fill_(float("nan"))
            fn()
            torch.cuda.synchronize()
            ok = torch.equal(dst.float(), expect.to(dst.dtype).float())
            us = captured_us(fn)
            lines.append(f"| {name} | {rows}x{width} | {v} | {us:.1f} | {need / us / 1e3:.0f} | {ok} |")
            print(lines[-1], flush=True)
    if a.ncu:
        return
    gpu = torch.cuda.get_device_name(dev)
    head = [f"# Edge concat variants on {gpu}", "", "Captured, 20 launches per replay, median. GB/s: the fp16 rows "
            "written plus each source row read once (the least DRAM traffic), over the time.", "",
            "| block | rows x cols | variant | us | GB/s | bitwise equal to torch |", "|---|---|---|---|---|---|"]
    out = Path(a.out) / f"concat_probe_{slug(gpu)}.md"
    out.write_text("\n".join(head + lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
