"""Probe: float32-accurate GEMMs from tensor-core products (fp16x3, bf16x6, tf32x3) at the GN block's shapes.

IEEE float32 GEMMs run on the SIMT units (~48 TFLOP/s on an H200 at the edge-MLP shape); the
forward at batch 4096 in fp32 is bound by them. Splitting each float32 operand into pieces that
tensor cores multiply exactly and summing the products in float32 gives float32-level accuracy
from the faster units:

- ``bf16x6``: x = x0 + x1 + x2 (each bf16, the next one the rounding remainder of the last), and
  x @ w ~ sum of the six products x_i w_j with i + j <= 2, as three GEMMs whose float32 outputs
  add (beta = 1): [x0|x1|x2] @ [w0;w0;w0], [x0|x1] @ [w1;w1], x0 @ w2.
- ``tf32x3``: x = x0 + x1 (tf32 values held in float32), x @ w ~ x0 w0 + x1 w0 + x0 w1, as two
  GEMMs: [x0|x1] @ [w0;w0] then + x0 @ w1.
- ``fp16x3``: the library's (``precision="fp16x3"``, ``gnwarp.gn.fp16x3`` and its kernel in
  ``gnwarp.kernels.gn.fp16x3``): fp16 pieces of x and w scaled by powers of two per row (so each
  row's largest element lies in [2^14, 2^15) and fp16's range holds both pieces), one GEMM over
  [hi | lo | hi] @ [Whi | Whi | Wlo] (3K columns, float32 out), unscaled by the row's and the
  output column's factors in the pieces kernel that follows.

Each is timed beside torch.mm in fp32 (IEEE), tf32 and bf16, in the same run, and its error
measured against float64. The bf16 / tf32 split passes are timed on their own (one fused
elementwise kernel from torch.compile), as are the library's fp16x3 pieces kernel and its
epilogue. (The torch prototype of fp16x3 this probe measured first, two GEMMs unscaled after,
is in git history; its numbers stay in ``bench/results/probes/fp32_emulation_probe_nvidia-h200.md``.)
Usage: ``python bench/probes/fp32_emulation_probe.py [--out DIR]`` (CUDA).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.harness import median_ms, slug  # noqa: E402
from gnwarp.gn import fp16x3  # noqa: E402
from gnwarp.interop import Launcher  # noqa: E402


def split_bf16(x: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """[x0|x1|x2] (bf16, 3 * K columns) with x0 + x1 + x2 ~ x (float32)."""
    x0 = x.to(torch.bfloat16)
    r = x - x0.float()
    x1 = r.to(torch.bfloat16)
    x2 = (r - x1.float()).to(torch.bfloat16)
    return torch.cat([x0, x1, x2], 1)


def fp16_pieces(x: torch.Tensor, weights: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """The library's fp16x3 operand of float32 rows ``x`` [M, K]: (pieces [M, 3K] fp16, 1 / row
    scale [M]); ``weights``: laid out as the GEMM's second operand."""
    M, K = x.shape
    out = torch.empty(M, 3 * K, dtype=torch.float16, device=x.device)
    inv = torch.empty(M, dtype=torch.float32, device=x.device)
    fp16x3.pieces(Launcher(x), K, M, x, out=out, inv=inv, weights=weights)
    return out, inv


def mm_fp16x3(a: torch.Tensor, w: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """a @ w.T + bias as the library runs an emulated layer: the pieces of a and w, one GEMM, the
    unscaling epilogue."""
    return fp16x3.mlp_forward(Launcher(a), a, [w], [bias], False, [])[1]


def _rn_tf32(x: torch.Tensor) -> torch.Tensor:
    """x rounded to the nearest tf32 value (10 mantissa bits), held in float32."""
    i = x.view(torch.int32)
    return ((i + 0x1000) & ~0x1FFF).view(torch.float32)


def split_tf32(x: torch.Tensor) -> torch.Tensor:
    x0 = _rn_tf32(x)
    return torch.cat([x0, _rn_tf32(x - x0)], 1)


def mm_bf16x6(a3: torch.Tensor, w: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """a @ w.T for a given as ``split_bf16(a)``, w float32 [N, K]."""
    K = w.shape[1]
    w3 = split_bf16(w)  # [N, 3K]: w0 | w1 | w2
    w0, w1, w2 = w3[:, :K], w3[:, K:2 * K], w3[:, 2 * K:]
    torch.mm(a3, torch.cat([w0, w0, w0], 1).t(), out_dtype=torch.float32, out=out)
    torch.addmm(out, a3[:, :2 * K], torch.cat([w1, w1], 1).t(), out_dtype=torch.float32, out=out)
    torch.addmm(out, a3[:, :K], w2.t(), out_dtype=torch.float32, out=out)
    return out


def mm_tf32x3(a2: torch.Tensor, w: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    K = w.shape[1]
    w2 = split_tf32(w)
    w0, w1 = w2[:, :K], w2[:, K:]
    torch.mm(a2, torch.cat([w0, w0], 1).t(), out=out)
    torch.addmm(out, a2[:, :K], w1.t(), out=out)
    return out


def timed(fn, reps: int = 20) -> float:
    return median_ms(fn, torch.device("cuda"), reps, 3)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    dev = torch.device("cuda")
    torch.manual_seed(0)
    m = torch.backends.cuda.matmul
    rows = []
    import torch._inductor.config as ic
    ic.emulate_precision_casts = True  # else inductor drops the round trip x.to(bf16).float()
    split_c = torch.compile(split_bf16)
    split_t = torch.compile(split_tf32)
    for M, K, N in [(73728, 512, 512), (73728, 512, 128), (32768, 256, 256)]:
        a = torch.relu(torch.randn(M, K, device=dev))
        w = torch.randn(N, K, device=dev) / K ** 0.5
        ref = a.double() @ w.double().t()
        scale = ref.abs().max().item()
        out = torch.empty(M, N, device=dev)
        flop = 2.0 * M * N * K

        def err(y):
            return (y.double() - ref).abs().max().item() / scale

        a16, w16 = a.bfloat16(), w.bfloat16()
        a3, a2 = split_c(a), split_t(a)
        cases = {}
        m.fp32_precision = "ieee"
        cases["fp32 (IEEE)"] = (lambda: torch.mm(a, w.t(), out=out), None)
        cases["bf16 (one product)"] = (lambda: torch.mm(a16, w16.t(), out_dtype=torch.float32, out=out), None)
        cases["bf16x6 (3 GEMMs)"] = (lambda: mm_bf16x6(a3, w, out), None)
        cases["bf16x6 incl. split of a"] = (lambda: mm_bf16x6(split_c(a), w, out), None)
        for name, (fn, _) in cases.items():
            t = timed(fn)
            fn()
            rows.append((f"{M}x{K}@{K}x{N}", name, t, flop / t / 1e9, err(out)))
        h3, h_inv = fp16_pieces(a)
        w3, _ = fp16_pieces(w, weights=True)
        zero = torch.zeros(N, device=dev)
        e16 = err(mm_fp16x3(a, w, zero))
        t = timed(lambda: fp16x3.gemm(h3, w3))
        rows.append((f"{M}x{K}@{K}x{N}", "fp16x3 library (1 GEMM over 3K, pieces given)", t, flop / t / 1e9, e16))
        t = timed(lambda: mm_fp16x3(a, w, zero))
        rows.append((f"{M}x{K}@{K}x{N}", "fp16x3 library incl. pieces of a, w and the epilogue", t, flop / t / 1e9,
                     e16))
        m.fp32_precision = "tf32"
        for name, fn in {"tf32 (one product)": lambda: torch.mm(a, w.t(), out=out),
                         "tf32x3 (2 GEMMs)": lambda: mm_tf32x3(a2, w, out),
                         "tf32x3 incl. split of a": lambda: mm_tf32x3(split_t(a), w, out)}.items():
            t = timed(fn)
            fn()
            rows.append((f"{M}x{K}@{K}x{N}", name, t, flop / t / 1e9, err(out)))
        m.fp32_precision = "ieee"
        t = timed(lambda: split_c(a))
        rows.append((f"{M}x{K}", "split pass bf16x3 (compiled)", t, 0.0, float("nan")))
        t = timed(lambda: split_t(a))
        rows.append((f"{M}x{K}", "split pass tf32x2 (compiled)", t, 0.0, float("nan")))
        t = timed(lambda: fp16_pieces(a))
        rows.append((f"{M}x{K}", "pieces pass fp16x3 + row scales (library kernel)", t, 0.0, float("nan")))
        p = torch.randn(M, K, device=dev)  # a GEMM's output, made the next layer's pieces
        bias, col_inv = torch.randn(K, device=dev), torch.ones(K, device=dev)
        nxt, nxt_inv = torch.empty_like(h3), torch.empty_like(h_inv)
        launch = Launcher(p)
        t = timed(lambda: fp16x3.pieces(launch, K, M, p, epilogue=(h_inv, col_inv, bias), relu=True, out=nxt,
                                        inv=nxt_inv))
        rows.append((f"{M}x{K}", "epilogue fp16x3: unscale, bias, ReLU, pieces (library kernel)", t, 0.0,
                     float("nan")))
        # a's own float32 rounding error is zero; the reference of a random-sign input as well
        b = torch.randn(M, K, device=dev)
        refb = b.double() @ w.double().t()
        torch.mm(b, w.t(), out=out)
        e32 = (out.double() - refb).abs().max().item() / refb.abs().max().item()
        for name, fn in {"bf16x6": lambda: mm_bf16x6(split_c(b), w, out),
                         "fp16x3 library": lambda: mm_fp16x3(b, w, torch.zeros(N, device=dev))}.items():
            y = fn()
            e = (y.double() - refb).abs().max().item() / refb.abs().max().item()
            rows.append((f"{M}x{K}@{K}x{N} signed", f"{name} error / fp32 error", 0.0, 0.0, e / e32))
    gpu = torch.cuda.get_device_name(0)
    lines = [f"# float32 GEMM emulation probe on {gpu}", "",
             f"torch {torch.__version__}; error = max |y - y64| / max |y64| against float64; median of 20 (CUDA events).",
             "", "| shape | method | ms | TFLOP/s | error |", "|---|---|---|---|---|"]
    for shape, name, t, tf, e in rows:
        lines.append(f"| {shape} | {name} | {t:.4f} | {tf:.1f} | {e:.2e} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"fp32_emulation_probe_{slug(gpu)}.md").write_text(text)


if __name__ == "__main__":
    main()
