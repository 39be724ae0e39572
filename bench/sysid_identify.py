"""Benchmark: system identification at inference (``SysIDModel.identify``, D.6.2), GN_p's loop
over the 20-step window replayed from a CUDA graph against eager, in one process.

A ``SysIDModel`` at the paper's sizes (GN_p latent 128, MLPs 128x128, hidden and G_ID 10; the
forward model as ``bench/experiments/sysid_figures.py`` trains it) on parameterized pendulum and
cheetah data (MuJoCo C), untrained (identification's cost does not depend on the weights). For
each system and batch size N: G_ID of N windows, eager and captured (median of 10, CUDA events;
each mode after a warm-up call that compiled its kernels or captured its graph), the largest
difference between the two, and the 80-step rollout from the window's end for scale.

    python bench/sysid_identify.py [--systems pendulum,cheetah] [--batches 200,1000]
    python bench/sysid_identify.py --quick          # tiny sizes on the CPU (eager only): a smoke test
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import device_name, gn_sizes, median_ms, results_dir, save_results  # noqa: E402


def main(argv=None):
    from gnwarp import data
    from gnwarp.models import ModelConfig, RecurrentGNConfig, SysIDConfig, SysIDModel
    from gnwarp.models.config import DEFAULT_RUN
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cheetah")
    ap.add_argument("--batches", default="200,1000")
    ap.add_argument("--window", type=int, default=20)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=results_dir("sysid_identify"))
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    latent, mlp, g = 128, (128, 128), 10
    if args.quick:
        args.device, args.batches, args.systems, args.window, latent, mlp, g = "cpu", "4", "pendulum", 5, 8, (16,), 3
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    name = device_name(dev)
    rows = []
    batches = [int(b) for b in args.batches.split(",")]
    for system in args.systems.split(","):
        ds = data.generate(system, (max(batches), 1, 1), num_steps=args.window + 80, seed=0, backend="mujoco",
                           parameterized=True, progress=False)
        sp = ds["train"]
        fwd = ModelConfig(gn=gn_sizes(latent, 2 * latent, latent), run=DEFAULT_RUN.replace(impl="warp"),
                          recenter=bool(ds.meta.get("translation_invariant", False)))
        ident = RecurrentGNConfig(latent=latent, hidden_edges=g, hidden_nodes=g, hidden_globals=g, out_edges=g,
                                  out_nodes=g, out_globals=g, edge_mlp=mlp, node_mlp=mlp, global_mlp=mlp)
        torch.manual_seed(0)
        m = SysIDModel(SysIDConfig(forward=fwd, identifier=ident, window=args.window), ds.layout).to(dev).bind(ds)
        m.eval()
        for n in batches:
            body = torch.as_tensor(np.asarray(sp.body[:n], dtype=np.float32), device=dev)
            ctrl = torch.as_tensor(np.asarray(sp.ctrl[:n], dtype=np.float32), device=dev)
            inst = torch.as_tensor(np.asarray(sp.instance[:n]))
            W = args.window
            row = dict(device=name, system=system, sequences=n, window=W)
            with torch.no_grad():
                outs = {}
                for mode, capture in [("eager", False)] + ([("captured", True)] if cuda else []):
                    run = lambda: m.identify(body[:, :W], ctrl[:, :W], inst, capture=capture)  # noqa: E731
                    row[f"{mode}_ms"] = round(median_ms(run, dev, 10 if cuda else 1, 1), 3)
                    outs[mode] = run()
                if cuda:
                    row["max_abs_diff"] = max(float((getattr(outs["captured"], k) - getattr(outs["eager"], k))
                                                    .abs().max()) for k in ("nodes", "edges", "globals"))
                g_id = outs["eager"]
                row["rollout_80_ms"] = round(median_ms(lambda: m.rollout(body[:, W], ctrl[:, W:W + 80], g_id, inst),
                                                       dev, 5 if cuda else 1, 1), 2)
            rows.append(row)
            print(row, flush=True)
    lines = [f"# System identification at inference on {name}", "",
             f"`python bench/sysid_identify.py` ({time.strftime('%Y-%m-%d')}): `SysIDModel.identify` of N "
             f"{args.window}-step windows at the paper's sizes (GN_p latent {latent}, MLPs {'x'.join(map(str, mlp))}, "
             f"G_ID {g}), eager and replayed from a CUDA graph, median of 10 calls (CUDA events) after a warm-up call; "
             "the 80-step rollout from the window's end (eager, the model's usual path) for scale.", "",
             "| system | N | identify eager ms | captured ms | eager / captured | max abs diff | 80-step rollout ms |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r.get("captured_ms")
        ratio = "%.1fx" % (r["eager_ms"] / c) if c else "-"
        lines.append(f"| {r['system']} | {r['sequences']} | {r['eager_ms']} | {c if c else '-'} | {ratio} | "
                     f"{r.get('max_abs_diff', '-')} | {r['rollout_80_ms']} |")
    save_results(args.out, "sysid_identify", name, args.quick, rows, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
