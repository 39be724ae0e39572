"""Probe: the edge update's concatenated input rows [e, v[sender], v[receiver], u[graph]] at the
benchmark's cheetah shapes, batch 4096 (73728 edges).

In v9 the second block's edge concat (192 + 159 + 159 + 160 -> 672 columns, fp32 in, fp16 out)
profiled at ~167 us of the 1.02 ms fp16 forward, ~4x what its DRAM traffic needs (the fp16
rows written once, the edge rows and the node / global tables read once: ~177 MB, ~44 us at
4 TB/s). This times variants on the real index arrays (``graph_index`` of the benchmark's
batch), each checked bit for bit against torch:

- ``v9 v8``: the library's kernel before (v9): each thread owns 8 columns of a row, strided by
  84, and tests all four pieces for each (a predicated load per piece and column)
- ``ours vN``: the library's ``concat_kernel`` with ``max_vec`` = N (the library uses
  ``CONCAT_VEC`` = 8): each piece gets its own whole warps, at most N columns per thread
- ``ours fp32 out``: the same writing fp32 (is it the 2-byte stores?)
- ``ours pre-gathered``: the gathered pieces materialized beforehand (is it the gathers?)
- ``pieces vN``: ``concat_piece_kernel``, one branch-free launch per piece, N columns per thread
- ``torch``: index_select, cat and cast in torch

``--ncu VARIANT,...`` runs the named variants a few times uncaptured and nothing else (for
``ncu --kernel-name regex:concat``). Usage: ``python bench/concat_probe.py [--out DIR]`` (CUDA);
writes ``concat_probe_<gpu>.md``.
"""

import argparse
import functools
import re
import sys
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gn_block import EDGE_IN, GLOB_IN, NODE_IN, PAPER, make_batch  # noqa: E402
from relu_grad_probe import time_us  # noqa: E402

from gnwarp.gn_warp import _Launcher, _pad, graph_index  # noqa: E402
from gnwarp.kernels import gn_block as K  # noqa: E402
from gnwarp.optim import WP_DTYPE  # noqa: E402

wp.config.quiet = True
OPTIONS = {"enable_backward": False}


@functools.cache
def v9_concat_kernel(widths: tuple, gathered: tuple, in_dtypes: tuple, dtype, out_width: int, vec_: int = 8):
    """The library's kernel before (v9): each thread owns ``vec_`` columns of one row, strided by
    ``out_width // vec_``, and tests every piece for each of them."""
    W0, W1, W2, W3 = widths
    G0, G1, G2, G3 = gathered
    T0, T1, T2, T3 = in_dtypes
    K = out_width
    V = vec_
    KV = K // V
    E0 = W0
    E1 = E0 + W1
    E2 = E1 + W2
    E3 = E2 + W3
    T = dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def concat(
        # Data in (flat row-major):
        p0_in: wp.array(dtype=T0),
        p1_in: wp.array(dtype=T1),
        p2_in: wp.array(dtype=T2),
        p3_in: wp.array(dtype=T3),
        index_0: wp.array(dtype=wp.int32),
        index_1: wp.array(dtype=wp.int32),
        index_2: wp.array(dtype=wp.int32),
        index_3: wp.array(dtype=wp.int32),
        # Data out (flat row-major):
        out: wp.array(dtype=T),
    ):
        i = wp.tid()
        r = i // KV
        c0 = i - r * KV
        # first element of each piece's source row
        b0 = r * W0
        b1 = r * W1
        b2 = r * W2
        b3 = r * W3
        if wp.static(W0 > 0 and G0):
            b0 = index_0[r] * W0
        if wp.static(W1 > 0 and G1):
            b1 = index_1[r] * W1
        if wp.static(W2 > 0 and G2):
            b2 = index_2[r] * W2
        if wp.static(W3 > 0 and G3):
            b3 = index_3[r] * W3
        xs = wp.vector(length=V, dtype=T)  # zero: the padding columns
        for k in range(V):
            c = c0 + k * KV
            if wp.static(W0 > 0):
                if c < E0:
                    xs[k] = T(p0_in[b0 + c])
            if wp.static(W1 > 0):
                if c >= E0 and c < E1:
                    xs[k] = T(p1_in[b1 + c - E0])
            if wp.static(W2 > 0):
                if c >= E1 and c < E2:
                    xs[k] = T(p2_in[b2 + c - E1])
            if wp.static(W3 > 0):
                if c >= E2 and c < E3:
                    xs[k] = T(p3_in[b3 + c - E2])
        o = r * K + c0
        for k in range(V):
            out[o + k * KV] = xs[k]

    return concat


@functools.cache
def concat_piece_kernel(width: int, span: int, gathered: bool, in_dtype, dtype, out_width: int, offset: int,
                        vec_: int = 8):
    """One piece of ``concat_kernel``'s rows: out[r, offset:offset + span] = [p_in[row], 0...]
    (``row`` = ``index[r]`` if ``gathered`` else ``r``; columns ``width..span`` zero), with no
    branch on the piece. Launch over ``rows * ceil(span / vec_)`` threads; each owns ``vec_``
    columns of one row strided by ``ceil(span / vec_)``."""
    W, S, V, K, E, Ti, T = width, span, vec_, out_width, offset, in_dtype, dtype
    SV = (S + V - 1) // V

    @wp.kernel(module="unique", module_options=OPTIONS)
    def concat_piece(p_in: wp.array(dtype=Ti), index: wp.array(dtype=wp.int32), out: wp.array(dtype=T)):
        i = wp.tid()
        r = i // SV
        c0 = i - r * SV
        b = r * W
        if wp.static(gathered):
            b = index[r] * W
        xs = wp.vector(length=V, dtype=T)
        for k in range(V):
            c = c0 + k * SV
            if wp.static((k + 1) * SV <= W):  # all of this column block is inside the row
                xs[k] = T(p_in[b + c])
            else:
                if c < W:
                    xs[k] = T(p_in[b + c])
        o = r * K + E + c0
        for k in range(V):
            if wp.static((k + 1) * SV <= S):
                out[o + k * SV] = xs[k]
            else:
                if c0 + k * SV < S:
                    out[o + k * SV] = xs[k]

    return concat_piece



def case(name, B, dev):
    """(pieces [(tensor, index or None)], padded width) of a block's edge concat."""
    g, _ = make_batch("cheetah", B, dev)
    gi = graph_index(g)
    lat = PAPER["latent"] if name == "gn2" else 0
    gen = torch.Generator(device=dev).manual_seed(1)
    rnd = (lambda r, c: torch.randn(r, c, device=dev, generator=gen))
    e, v, u = rnd(gi.n_edges, EDGE_IN + lat), rnd(gi.n_nodes, NODE_IN + lat), rnd(gi.n_graphs, GLOB_IN + lat)
    pieces = [(e, None), (v, gi.senders), (v, gi.receivers), (u, gi.edge_graph)]
    return pieces, _pad(sum(t.shape[1] for t, _ in pieces))


def variants(pieces, K_, out_dtype):
    rows = pieces[0][0].shape[0]
    widths = tuple(t.shape[1] for t, _ in pieces)
    flat = [t.view(-1) for t, _ in pieces]
    idx = [i for _, i in pieces]
    T = WP_DTYPE[out_dtype]
    out = torch.empty(rows, K_, dtype=out_dtype, device=flat[0].device)
    out32 = torch.empty(rows, K_, dtype=torch.float32, device=flat[0].device)
    none = torch.zeros(1, dtype=torch.int32, device=out.device)
    pre = [(t if i is None else t[i.long()]).contiguous() for t, i in pieces]
    res = {}

    def launcher(kern, n, dst, src, ix):
        return lambda: _Launcher(dst).n(kern, n, *src, *ix, dst.view(-1))

    def ours(vec_, dst=out, T_=T, src=flat, gathered=True, v9=False):
        g = tuple(gathered and i is not None for i in idx)
        ix = [i if (gathered and i is not None) else none for i in idx]
        if v9:
            return launcher(v9_concat_kernel(widths, g, (wp.float32,) * 4, T_, K_, vec_), rows * (K_ // vec_),
                            dst, src, ix)
        kern = K.concat_kernel(widths, g, (wp.float32,) * 4, T_, K_, vec_)
        return launcher(kern, K.concat_threads(rows, widths, K_, vec_), dst, src, ix + [rows])
    res["v9 v8"] = (ours(8, v9=True), out)
    for v in (2, 4, 8):
        res[f"ours v{v}"] = (ours(v), out)
    res["ours fp32 out"] = (ours(K.CONCAT_VEC, out32, wp.float32), out32)
    res["ours pre-gathered"] = (ours(K.CONCAT_VEC, src=[t.view(-1) for t in pre], gathered=False), out)

    def pieces_fn(vec_):
        offs, launches = 0, []
        for k, (w, i) in enumerate(zip(widths, idx)):
            span = w if k < 3 else K_ - offs  # the last piece also writes the zero padding
            kern = concat_piece_kernel(w, span, i is not None, wp.float32, T, K_, offs, vec_)
            launches.append((kern, rows * ((span + vec_ - 1) // vec_), flat[k], i if i is not None else none))
            offs += w

        def run():
            la = _Launcher(out)
            for kern, n, src, ix in launches:
                la.n(kern, n, src, ix, out.view(-1))
        return run
    for v in (4, 8):
        res[f"pieces v{v}"] = (pieces_fn(v), out)

    def torch_fn():
        torch.cat([t if i is None else t.index_select(0, i) for t, i in pieces]
                  + [torch.zeros(rows, K_ - sum(widths), device=out.device)], 1, out=out32)
        out.copy_(out32)
    res["torch"] = (torch_fn, out)
    expect = torch.cat(pre + [torch.zeros(rows, K_ - sum(widths), device=out.device)], 1)
    return res, expect


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    p.add_argument("--ncu", default="", help="comma-separated variants: run each 3 times, uncaptured, and stop")
    a = p.parse_args()
    dev = torch.device("cuda")
    lines = []
    for name in ("gn2", "gn1"):
        pieces, K_ = case(name, 4096, dev)
        res, expect = variants(pieces, K_, torch.float16)
        rows = expect.shape[0]
        # DRAM bytes at best: the rows written once, every source row read once
        need = rows * K_ * 2 + sum(t.numel() * 4 for t, _ in pieces[:2]) + pieces[3][0].numel() * 4
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
            us = time_us(fn)
            lines.append(f"| {name} | {rows}x{K_} | {v} | {us:.1f} | {need / us / 1e3:.0f} | {ok} |")
            print(lines[-1], flush=True)
    if a.ncu:
        return
    gpu = torch.cuda.get_device_name(dev)
    slug = re.sub(r"[^A-Za-z0-9]+", "-", gpu).strip("-").lower()
    head = [f"# Edge concat variants on {gpu}", "", "Captured, 20 launches per replay, median. GB/s: the fp16 rows "
            "written plus each source row read once (the least DRAM traffic), over the time.", "",
            "| block | rows x cols | variant | us | GB/s | bitwise equal to torch |", "|---|---|---|---|---|---|"]
    out = Path(a.out) / f"concat_probe_{slug}.md"
    out.write_text("\n".join(head + lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
