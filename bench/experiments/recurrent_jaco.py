"""Recurrent vs feed-forward one-step models on the proprioceptive JACO (paper Figure 7, D.7.3).

The JACO of ``gnwarp.data.proprio.proprio_jaco`` (40 ms observations of cos q, sin q, qdot per body;
a lagged command behind a soft velocity servo, hidden from the observation) is simulated; a
recurrent GN (``RecurrentForwardModel``, hidden graph of 20 per edge / node / global) and the same
model without memory (its hidden graph reset every step) are trained with teacher forcing on
21-observation windows (``gnwarp.train.TeacherForcingTrainer``: Adam, gradients clipped to norm 1); both are rolled out on test sequences after a warm-up on the true
observations, beside the constant baseline (the last true observation held). Errors per horizon:
RMS joint-angle error (rad, wrapped) and RMS joint-velocity error (rad/s) over the arm's joints.

    python bench/experiments/recurrent_jaco.py --quick              # CPU smoke run, < 1 min
    python bench/experiments/recurrent_jaco.py                      # full size (GPU)

Writes under --out (default bench/results/recurrent_jaco): results.json (every horizon's errors
and the run's settings), results.jsonl (results records, ``gnwarp.eval.records``: per model,
quantity and horizon 1, 5, 10, 20, 50, 80), summary.md generated from them
(``gnwarp.eval.summarize``) and recurrent_jaco.png (error per horizon and one joint's trajectory,
like Figure 7).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import experiment_out  # noqa: E402
from gnwarp.data import proprio  # noqa: E402
from gnwarp.models.recurrent import RecurrentGNConfig  # noqa: E402
from gnwarp.models.recurrent_forward import RecurrentForwardConfig, RecurrentForwardModel  # noqa: E402
from gnwarp.train import TrainConfig, TeacherForcingTrainer  # noqa: E402

FULL = dict(sequences=(2000, 100, 200), steps=100, train_steps=20000, batch=200, lr=1e-3, latent=128,
            hidden=20, mlp=(256, 256), warmup=20, impl="warp")
# --quick runs the GN block's torch reference: on a CPU it is faster than Warp's CPU kernels at this size
QUICK = dict(sequences=(48, 4, 8), steps=50, train_steps=50, batch=12, lr=3e-3, latent=32,
             hidden=8, mlp=(64,), warmup=20, impl="torch")


def errors(pred: torch.Tensor, true: torch.Tensor, movable: torch.Tensor, warmup: int) -> dict[str, list[float]]:
    """RMS angle and velocity errors per horizon 1..T-warmup over sequences and movable bodies."""
    p, t = pred[:, warmup + 1:, movable], true[:, warmup + 1:, movable]
    dq = torch.atan2(p[..., 1] * t[..., 0] - p[..., 0] * t[..., 1], p[..., 0] * t[..., 0] + p[..., 1] * t[..., 1])
    return {"angle": dq.square().mean((0, 2)).sqrt().tolist(),
            "velocity": (p[..., 2] - t[..., 2]).square().mean((0, 2)).sqrt().tolist()}


def plot(res: dict, traces: dict, joint: str, warmup: int, dt: float, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    color = {"true": "k", "constant": "C0", "recurrent": "C1", "feed-forward": "C2"}
    fig, ax = plt.subplots(1, 3, figsize=(14, 3.8))
    for name, r in res.items():
        h = np.arange(1, len(r["angle"]) + 1)
        ax[0].plot(h, r["angle"], color=color[name], label=name)
        ax[1].plot(h, r["velocity"], color=color[name], label=name)
    ax[0].set(xlabel="rollout step after warm-up", ylabel="RMS joint angle error (rad)", yscale="log")
    ax[1].set(xlabel="rollout step after warm-up", ylabel="RMS joint velocity error (rad/s)", yscale="log")
    ax[0].legend()
    t = np.arange(len(traces["true"])) * dt
    for name, q in traces.items():
        ax[2].plot(t, q, color=color[name], label=name, lw=2 if name == "true" else 1)
    ax[2].axvline(warmup * dt, color="gray", ls=":")
    ax[2].set(xlabel="time (s)", ylabel=f"joint angle of {joint} (rad)")
    ax[2].legend(fontsize=8)
    fig.suptitle("Proprioceptive JACO: recurrent vs feed-forward one-step models (cf. Figure 7)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny CPU run (< 1 min)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--train-steps", type=int, default=None)
    ap.add_argument("--seconds", type=float, default=None, help="training cap per model (wall clock)")
    ap.add_argument("--lag", type=float, default=0.2, help="command lag (s) of the simulated arm")
    ap.add_argument("--servo-scale", type=float, default=0.1, help="velocity servo gain, relative to the JACO's")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cfg = dict(QUICK if args.quick else FULL)
    if args.train_steps:
        cfg["train_steps"] = args.train_steps
    out = experiment_out("recurrent_jaco", args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    backend = "mujoco" if args.quick else args.backend
    torch.manual_seed(args.seed)

    t0 = time.perf_counter()
    system = proprio.proprio_jaco(args.lag, args.servo_scale)
    data = proprio.ProprioData.simulate(system, cfg["sequences"], num_steps=cfg["steps"], seed=args.seed,
                                        backend=backend, device=dev)
    test = data.split("test")   # the train split is converted where training reads it
    print(f"simulated {cfg['sequences']} x {cfg['steps']} steps of {system.name} in {time.perf_counter() - t0:.1f} s")

    w = cfg["hidden"]
    core = RecurrentGNConfig(latent=cfg["latent"], hidden_edges=w, hidden_nodes=w, hidden_globals=w,
                             edge_mlp=cfg["mlp"], node_mlp=cfg["mlp"], global_mlp=cfg["mlp"])
    movable = data.movable.to(dev)
    W = cfg["warmup"]
    res, traces, logs = {}, {}, {}
    with torch.no_grad():
        const = test.obs.clone()
        const[:, W + 1:] = test.obs[:, W:W + 1]
    res["constant"] = errors(const, test.obs, movable, W)
    b, j = 0, 2  # trace: the first test sequence, body 2 (the arm's second joint)
    traces["true"] = torch.atan2(test.obs[b, :, j, 1], test.obs[b, :, j, 0]).cpu().numpy()
    for name, recurrent in (("recurrent", True), ("feed-forward", False)):
        run = RecurrentForwardConfig(core=core, recurrent=recurrent)
        run.run = run.run.replace(impl=cfg["impl"])
        model = RecurrentForwardModel(run, data.sizes, data.graphs, data.movable).to(dev)
        t1 = time.perf_counter()
        rows = []
        with tempfile.TemporaryDirectory() as run_dir:   # the Trainer's run folder: checkpoints, log.csv
            tc = TrainConfig(out=run_dir, steps=cfg["train_steps"], batch_size=cfg["batch"], lr=cfg["lr"],
                             lr_decay=1.0, seed=args.seed, max_seconds=args.seconds, log_every=10,
                             valid_every=cfg["train_steps"], checkpoint_every=cfg["train_steps"], patience=None,
                             normalizer_warmup=0, device=str(dev), progress=not args.quick, resume=False)
            trainer = TeacherForcingTrainer(tc, data, model, window=21,
                                            callbacks=[lambda t, ev, info: rows.append(info["row"]) if ev == "log" else 0])
            summary = trainer.run()
        losses = [r["loss"] for r in rows if r.get("loss", "") != ""]
        logs[name] = {"loss_first10": losses[0], "loss_last10": losses[-1], "steps": summary["steps"],
                      "train_seconds": time.perf_counter() - t1}
        with torch.no_grad():
            pred = model.rollout(test.instance, test.obs, test.ctrl, warmup=W)
        res[name] = errors(pred, test.obs, movable, W)
        traces[name] = torch.atan2(pred[b, :, j, 1], pred[b, :, j, 0]).cpu().numpy()
        print(f"{name}: loss {losses[0]:.3g} -> {losses[-1]:.3g} (means over 10 steps)")

    meta = {"config": cfg, "lag": args.lag, "servo_scale": args.servo_scale, "seed": args.seed, "device": str(dev),
            "backend": backend, "quick": args.quick, "training": logs}
    (out / "results.json").write_text(json.dumps({"meta": meta, "errors": res}, indent=1, default=float))
    from gnwarp.eval.records import git_commit, gpu_name, write_records
    records = to_records({"meta": meta, "errors": res}, system, gpu=gpu_name(dev), commit=git_commit(),
                         date=time.strftime("%Y-%m-%d %H:%M"))
    write_records(out / "results.jsonl", records, append=False)
    print(f"wrote {report(out, records)}")
    plot(res, traces, f"body {j}", W, system.dt, out / "recurrent_jaco.png")
    print(f"wrote {out} ({time.perf_counter() - t0:.1f} s)")


HORIZONS = (1, 5, 10, 20, 50, 80)
QUANTITIES = {"angle": "angle (rad)", "velocity": "velocity (rad/s)"}


def to_records(results: dict, system, gpu: str = "unknown", commit: str = "unknown", date: str = "") -> list:
    """``results.json``'s errors as results records: per model ("constant", "recurrent",
    "feed-forward"), quantity and horizon (1, 5, 10, 20, 50, 80 steps after the warm-up, those the
    sequences reach) the RMS error over the test sequences and joints (``reported`` mean: the RMS;
    per-sequence errors are not kept). Task "jaco_proprio", variant "<model>, angle (rad)" or
    "<model>, velocity (rad/s)"; the constant baseline plans with no model (dynamics "none"), the
    others are learned. Metrics of a model's records: its training steps and seconds."""
    from gnwarp.eval.records import ResultRecord
    meta, errs = results["meta"], results["errors"]
    cfg = meta["config"]
    n_test = int(cfg["sequences"][2])
    out = []
    for model, r in errs.items():
        train = meta.get("training", {}).get(model, {})
        metrics = {k: v for k, v in (("train_steps", train.get("steps")), ("train_seconds", train.get("train_seconds")))
                   if v is not None}
        for q, label in QUANTITIES.items():
            for h in HORIZONS:
                if h > len(r[q]):
                    continue
                out.append(ResultRecord(
                    experiment="recurrent_jaco", task="jaco_proprio", system=system.name, planner="none",
                    dynamics="none" if model == "constant" else "learned", variant=f"{model}, {label}",
                    seed=int(meta["seed"]), episodes=n_test, episode_steps=h,
                    reported={"mean": float(r[q][h - 1]), "std": None, "of": "errors"},
                    control_dt=float(system.dt), action_repeat=int(system.substeps),
                    env_steps=0 if model == "constant" else int(cfg["sequences"][0]) * int(cfg["steps"]),
                    metrics=metrics, config={"warmup": cfg["warmup"], "lag": meta["lag"],
                                             "servo_scale": meta["servo_scale"], "quick": meta["quick"], **cfg},
                    commit=commit, gpu=gpu, date=date))
    return out


def report(out: Path, records: list) -> Path:
    """``summary.md`` from the records (``gnwarp.eval.summarize``, no plot: recurrent_jaco.png is the figure)."""
    from gnwarp.eval.summarize import write_summary
    quick = records and records[0].config.get("quick")
    title = (f"Recurrent vs feed-forward, proprioceptive JACO: RMS errors after the warm-up ({records[-1].gpu}"
             f"{', QUICK smoke run' if quick else ''})")
    return write_summary(records, out, title, plot=False)


if __name__ == "__main__":
    main()
