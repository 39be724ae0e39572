"""The architecture ablation of the paper's Figure H.2 on Swimmer6: one GN (an interaction network)
against two GNs, sequential or with the graph skip connection, and two-GN variants whose first GN
does not update the globals, the nodes or the edges of its output graph (``GNCoreConfig``'s
wiring switches); 3 seeds each; mean and spread of the 20-step rollout error on the test split.

Every variant trains the same number of steps (not the same seconds: the IN's steps are cheaper)
with the library's captured step; sizes as the budget experiments (latent 128, edge MLP 2x256,
node/global 2x128), batch 200, lr 1e-3 x0.6 every quarter of the run.

    python bench/experiments/ablation_h2.py [--variants IN,GN2-skip] [--seeds 0,1,2] [--steps 25000]
    python bench/experiments/ablation_h2.py --table-only    # summary and plot from results.jsonl
    python bench/experiments/ablation_h2.py --quick         # tiny CPU smoke run
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import device_name, ensure_dataset, gn_sizes, mean_errors  # noqa: E402

# name -> GNCoreConfig wiring (Figure H.2's bars)
VARIANTS = {
    "IN": dict(blocks=1),
    "GN2-seq": dict(skip=False),
    "GN2-skip": dict(skip=True),
    "no-globals-seq": dict(skip=False, gn1_globals=False),
    "no-globals-skip": dict(skip=True, gn1_globals=False),
    "no-nodes-seq": dict(skip=False, gn1_nodes=False),
    "no-nodes-skip": dict(skip=True, gn1_nodes=False),
    "no-edges-seq": dict(skip=False, gn1_edges=False),
    "no-edges-skip": dict(skip=True, gn1_edges=False),
}


def run_one(args, data, ds, name: str, seed: int, tmp: Path) -> dict:
    import dataclasses

    from gnwarp.eval.metrics import evaluate
    from gnwarp.models import ModelConfig
    from gnwarp.train import TrainConfig, Trainer, load_model
    gn = dataclasses.replace(gn_sizes(args.latent, args.edge_width, args.node_width), **VARIANTS[name])
    cfg = TrainConfig(data=[str(data)], out=str(tmp / f"{name}-{seed}"), model=ModelConfig(gn=gn), steps=args.steps,
                      batch_size=200, lr=1e-3, lr_decay=0.6, lr_decay_steps=max(1, args.steps // 4),
                      valid_every=args.valid_every, valid_sequences=args.valid, patience=None,
                      checkpoint_every=args.steps, resume=False, progress=False, device=args.device, seed=seed,
                      optimizer="flat_adam")
    t = Trainer(cfg)
    n_params = sum(p.numel() for p in t.model.parameters())
    result = t.run()
    model = load_model(result["best"], device=args.device)
    errs = mean_errors(evaluate(model, ds, "test", sequences=args.test, horizons=(20,)))
    return {"variant": name, "seed": seed, "device": device_name(model.device), "steps": result["steps"],
            "seconds": round(result["seconds"], 1), "parameters": n_params, "one_step": errs["one_step"],
            "rollout_20": errs["rollout_20"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--steps", type=int, default=25000)
    ap.add_argument("--sequences", type=int, nargs=3, default=(2000, 50, 200))
    ap.add_argument("--latent", type=int, default=128)
    ap.add_argument("--edge-width", type=int, default=256)
    ap.add_argument("--node-width", type=int, default=128)
    ap.add_argument("--valid-every", type=int, default=2500)
    ap.add_argument("--test", type=int, default=200, help="test sequences evaluated")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "results" / "ablation_h2"))
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    args.valid = args.sequences[1]
    if args.quick:
        args.sequences, args.steps, args.valid, args.test, args.valid_every = (30, 5, 8), 30, 5, 8, 15
        args.latent, args.edge_width, args.node_width, args.device = 16, 32, 16, "cpu"
        args.out = tempfile.mkdtemp(prefix="ablation_h2_")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        from gnwarp.data import load
        with tempfile.TemporaryDirectory() as tmp:
            data = ensure_dataset(Path(tmp) / "swimmer6.h5", "swimmer6", args.sequences, 100 if not args.quick else 20,
                                  seed=1)
            ds = load(data, lazy=False)
            for name in args.variants.split(","):
                for seed in (int(s) for s in args.seeds.split(",")):
                    row = run_one(args, data, ds, name, seed, Path(tmp))
                    print(json.dumps(row), flush=True)
                    with open(out / "results.jsonl", "a") as f:
                        f.write(json.dumps(row) + "\n")
    summarize(out, args)


def summarize(out: Path, args) -> None:
    import numpy as np
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines() if line.strip()]
    by = {}
    for r in rows:
        by.setdefault(r["variant"], []).append(r)
    names = [n for n in VARIANTS if n in by]
    dev = rows[0]["device"] if rows else "?"
    lines = [f"# Figure H.2 ablation on Swimmer6 ({dev})", "",
             f"`python bench/experiments/ablation_h2.py` ({time.strftime('%Y-%m-%d')}): each variant trained "
             f"{rows[0]['steps'] if rows else '?'} steps (batch 200, lr 1e-3 x0.6 every quarter, captured step, "
             "tf32), seeds as listed; 20-step rollout error / constant baseline on the test split, mean over the "
             "state groups; mean and standard deviation over seeds.", "",
             "| variant | seeds | parameters | 20-step error mean | std | one-step mean | seconds per run |",
             "|---|---|---|---|---|---|---|"]
    for n in names:
        e = np.array([r["rollout_20"] for r in by[n]])
        o = np.array([r["one_step"] for r in by[n]])
        lines.append(f"| {n} | {len(e)} | {by[n][0]['parameters']} | {e.mean():.3g} | {e.std():.2g} | {o.mean():.3g} | "
                     f"{np.mean([r['seconds'] for r in by[n]]):.0f} |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 3.8))
    x = np.arange(len(names))
    means = [np.mean([r["rollout_20"] for r in by[n]]) for n in names]
    stds = [np.std([r["rollout_20"] for r in by[n]]) for n in names]
    colors = ["grey" if n == "IN" else "tab:blue" if n.startswith("GN2") else "tab:red" if "globals" in n
              else "tab:purple" if "nodes" in n else "tab:green" for n in names]
    ax.bar(x, means, yerr=stds, color=colors, capsize=4)
    for i, n in enumerate(names):
        ax.scatter([i] * len(by[n]), [r["rollout_20"] for r in by[n]], color="k", s=8, zorder=3)
    ax.set_xticks(x, names, rotation=30, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("20-step rollout error / constant")
    ax.set_title("Swimmer6: architecture ablation (Figure H.2), mean and std over seeds")
    fig.tight_layout()
    fig.savefig(out / "ablation_h2.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
