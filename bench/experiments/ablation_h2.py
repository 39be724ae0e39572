"""The architecture ablation of the paper's Figure H.2 on Swimmer6: one GN (an interaction network)
against two GNs, sequential or with the graph skip connection, and two-GN variants whose first GN
does not update the globals, the nodes or the edges of its output graph (``GNCoreConfig``'s
wiring switches); 3 seeds each; mean and spread of the 20-step rollout error on the test split.

Every variant trains the same number of steps (not the same seconds: the IN's steps are cheaper)
with the library's captured step; sizes as the budget experiments (latent 128, edge MLP 2x256,
node/global 2x128), batch 200, lr 1e-3 x0.6 every quarter of the run.

Each run's one-step and 20-step errors are results records (``gnwarp.eval.records``), appended to
``<out>/results.jsonl`` as the runs finish; ``summary.md`` (mean and std over the seeds' errors)
is generated from them by ``gnwarp.eval.summarize``, ``ablation_h2.png`` from the same records.

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
            "rollout_20": errs["rollout_20"], "test_sequences": min(args.test, len(ds["test"])),
            "env_steps": args.sequences[0] * args.sequence_steps, "date": time.strftime("%Y-%m-%d %H:%M")}


def to_records(row: dict, commit: str = "unknown") -> list:
    """One run (a variant and seed) as results records of errors: the one-step and 20-step errors
    normalized by the constant baseline, averaged over state groups and test sequences
    (``reported``: per-sequence errors are not kept); task and system swimmer6, planner "none" on
    learned dynamics, the variant's name as the variant, the training seed as the seed. Metrics:
    parameters, training steps and seconds."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    system = systems.make("swimmer6")
    return [ResultRecord(
        experiment="ablation_h2", task="swimmer6", system="swimmer6", planner="none", dynamics="learned",
        variant=row["variant"], seed=int(row["seed"]), episodes=int(row.get("test_sequences", 200)),
        episode_steps=horizon, reported={"mean": float(row[key]), "std": None, "of": "errors"},
        control_dt=float(system.dt), action_repeat=int(system.substeps), env_steps=row.get("env_steps"),
        metrics={"parameters": row["parameters"], "train_steps": row["steps"], "train_seconds": row["seconds"]},
        config={"gn_wiring": VARIANTS[row["variant"]]}, commit=commit, gpu=row.get("device", "unknown"),
        date=row.get("date", "")) for key, horizon in (("one_step", 1), ("rollout_20", 20))]


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
    args.valid, args.sequence_steps = args.sequences[1], 100
    if args.quick:
        args.sequences, args.steps, args.valid, args.test, args.valid_every = (30, 5, 8), 30, 5, 8, 15
        args.latent, args.edge_width, args.node_width, args.device = 16, 32, 16, "cpu"
        args.sequence_steps = 20
        args.out = tempfile.mkdtemp(prefix="ablation_h2_")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        from gnwarp.data import load
        from gnwarp.eval.records import git_commit, write_records
        commit = git_commit()
        with tempfile.TemporaryDirectory() as tmp:
            data = ensure_dataset(Path(tmp) / "swimmer6.h5", "swimmer6", args.sequences, args.sequence_steps, seed=1)
            ds = load(data, lazy=False)
            for name in args.variants.split(","):
                for seed in (int(s) for s in args.seeds.split(",")):
                    row = run_one(args, data, ds, name, seed, Path(tmp))
                    print(json.dumps(row), flush=True)
                    write_records(out / "results.jsonl", to_records(row, commit=commit))
    summarize(out)


def summarize(out: Path) -> None:
    """``summary.md`` (``gnwarp.eval.summarize``) and ``ablation_h2.png`` from ``out/results.jsonl``."""
    import numpy as np

    from gnwarp.eval.records import read_records
    from gnwarp.eval.summarize import write_summary
    records = read_records(out / "results.jsonl")
    title = f"Figure H.2 ablation on Swimmer6 ({records[-1].gpu if records else '?'})"
    print(f"wrote {write_summary(records, out, title, plot=False)}")
    by = {}
    for r in records:
        if r.episode_steps == 20:
            by.setdefault(r.variant, {})[r.seed] = r.reported["mean"]   # a rerun of a seed stands
    names = [n for n in VARIANTS if n in by]
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 3.8))
    x = np.arange(len(names))
    means = [np.mean(list(by[n].values())) for n in names]
    stds = [np.std(list(by[n].values())) for n in names]
    colors = ["grey" if n == "IN" else "tab:blue" if n.startswith("GN2") else "tab:red" if "globals" in n
              else "tab:purple" if "nodes" in n else "tab:green" for n in names]
    ax.bar(x, means, yerr=stds, color=colors, capsize=4)
    for i, n in enumerate(names):
        ax.scatter([i] * len(by[n]), list(by[n].values()), color="k", s=8, zorder=3)
    ax.set_xticks(x, names, rotation=30, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("20-step rollout error / constant")
    ax.set_title("Swimmer6: architecture ablation (Figure H.2), mean and std over seeds")
    fig.tight_layout()
    fig.savefig(out / "ablation_h2.png", dpi=110)
    plt.close(fig)

if __name__ == "__main__":
    main()
