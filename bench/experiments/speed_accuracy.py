"""Run time against error.

For each system: GN forward models of three sizes are trained side by side (a fixed wall-clock
budget each), then every model is evaluated in fp32, tf32 and fp16 (and bf16): its 20-step
rollout error on the test split (normalized by the constant baseline) against its time per rollout
step at a large batch, beside MuJoCo-Warp's own time per data step on the same system and batch.

Each (system, size, precision) is a results record (``gnwarp.eval.records``) in
``<out>/results.jsonl``: its error, with the times as metrics; ``summary.md`` is generated from
them (``gnwarp.eval.summarize``), ``speed_accuracy.png`` (error against time) from the same records.

    python bench/experiments/speed_accuracy.py --systems pendulum,cheetah,swimmer6 --seconds 150 \
        --out bench/results/speed_accuracy
    python bench/experiments/speed_accuracy.py --quick
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import (add_run_args, add_training_args, capture, device_name, ensure_dataset,  # noqa: E402
                           experiment_out, forward_args, median_ms, run_side_by_side, train_model)

SIZES = {  # name: (latent, edge hidden, node/global hidden)
    "small": (64, (128,), (64,)),
    "medium": (128, (256, 256), (128, 128)),
    "paper": (128, (512, 512, 512), (256, 256)),
}
PRECISIONS = ("fp32", "tf32", "fp16", "bf16")


def train_child(args):
    from gnwarp.models import GNCoreConfig, ModelConfig
    lat, eh, nh = SIZES[args.size]
    gn = GNCoreConfig(latent=lat, edge_hidden=eh, node_hidden=nh, global_hidden=nh)
    train_model([args.dataset], args.child_out, ModelConfig(core="gn", gn=gn), args.max_steps, seconds=args.seconds,
                lr=args.lr, decay_every=args.max_steps // 4, valid_every=args.valid_every, valid=50)


def time_rollout(model, ds, batch: int, horizon: int, reps: int) -> tuple[float, str]:
    """Seconds per rollout step at ``batch`` graphs: a captured CUDA graph when capture works,
    else the plain loop (timed with CUDA events, median of ``reps``)."""
    import numpy as np
    import torch
    dev = next(model.parameters()).device
    te = ds["test"]
    idx = np.arange(batch) % len(te)
    x0 = torch.as_tensor(te.body[idx, 0], device=dev)
    u = torch.as_tensor(te.ctrl[idx, :horizon], device=dev)
    inst = torch.as_tensor(te.instance[idx], device=dev)
    tmpl = model.template(inst)

    def step():
        with torch.no_grad():
            return model.rollout(x0, u, inst, template=tmpl)

    step()
    mode = "eager"
    fn = step
    if dev.type == "cuda":
        try:
            fn, mode = capture(step, warmup=1), "captured"
        except Exception as e:  # noqa: BLE001 - report the mode that ran
            mode = f"eager (capture failed: {type(e).__name__})"
            torch.cuda.synchronize()
    return median_ms(fn, dev, reps, 0) / 1e3 / horizon, mode


def mjwarp_step_time(system: str, batch: int, steps: int = 50) -> float:
    """Seconds per data step of MuJoCo-Warp at ``batch`` worlds (graph-captured, body states recorded)."""
    import numpy as np

    from gnwarp import data, sim
    from gnwarp.sim.mujoco_warp import simulate_mujoco_warp
    s = sim.make(system)
    rng = np.random.default_rng(0)
    q0, v0 = data.initial_states(s, batch, rng)
    u = sim.random_spline_controls(batch, steps, sim.control_range(s.model), rng)
    simulate_mujoco_warp([s], q0[:8], v0[:8], u[:8, :2])  # compile
    t = time.perf_counter()
    simulate_mujoco_warp([s], q0, v0, u)
    return (time.perf_counter() - t) / steps


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cheetah,swimmer6")
    ap.add_argument("--sizes", default=",".join(SIZES))
    add_training_args(ap, seconds=150.0, max_steps=40000, core_sizes=False)
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--reps", type=int, default=10)
    add_run_args(ap, "speed_accuracy", "--size", "--dataset", "--child-out")
    args = ap.parse_args()
    if args.child:
        return train_child(args)
    if args.quick:
        args.sequences, args.seconds, args.max_steps, args.valid_every = (30, 4, 8), 10.0, 30, 15
        args.batch, args.horizon, args.reps, args.sizes = 16, 5, 2, "small"
    import torch

    from gnwarp import data
    from gnwarp import eval as ev
    from gnwarp.interop import cuda_available
    from gnwarp.train import load_model
    out = experiment_out("speed_accuracy", args.out, args.quick)
    (out / "data").mkdir(parents=True, exist_ok=True)
    names, sizes = args.systems.split(","), args.sizes.split(",")
    for s in names:
        ensure_dataset(out / "data" / f"{s}.h5", s, args.sequences, max(100, args.horizon), seed=3)
    commands = {}
    for s in names:
        for z in sizes:
            commands[f"{s}-{z}"] = [sys.executable, __file__, "--child", "--size", z,
                                    "--dataset", str(out / "data" / f"{s}.h5"), "--child-out", str(out / f"{s}-{z}"),
                                    *forward_args(args, "seconds", "max_steps", "lr", "valid_every")]
    run_side_by_side(commands, out, threads=1)
    rows = []
    cuda = torch.cuda.is_available()
    precisions = PRECISIONS if cuda else ("fp32",)
    for s in names:
        ds = data.load(out / "data" / f"{s}.h5", lazy=False)
        sim_dt = mjwarp_step_time(s, args.batch) if cuda_available() else None
        for z in sizes:
            ck = out / f"{s}-{z}" / "best"
            if not ck.exists():
                rows.append(dict(system=s, size=z, error="training failed"))
                continue
            model = load_model(ck).bind(ds)
            for prec in precisions:
                model.set_options(precision=prec)
                err = ev.evaluate(model, ds, "test", horizons=(args.horizon,))[f"rollout_{args.horizon}"]["mean"]
                dt, mode = time_rollout(model, ds, args.batch, args.horizon, args.reps)
                rows.append(dict(system=s, size=z, precision=prec, rollout_error=err, step_seconds=dt, mode=mode,
                                 mjwarp_step_seconds=sim_dt, batch=args.batch, horizon=args.horizon))
                print(json.dumps(rows[-1]), flush=True)
    from gnwarp.eval.records import git_commit, write_records
    for r in rows:
        if "error" in r:
            print(f"{r['system']} {r['size']}: {r['error']}", flush=True)
    dev, commit = device_name(), git_commit()
    config = {"seconds": args.seconds, "sequences": list(args.sequences), "sequence_steps": max(100, args.horizon)}
    records = [x for r in rows if "error" not in r
               for x in to_records(r, gpu=dev, commit=commit, date=time.strftime("%Y-%m-%d %H:%M"),
                                   test_sequences=args.sequences[2], env_steps=args.sequences[0] * max(100, args.horizon),
                                   config=config)]
    write_records(out / "results.jsonl", records, append=False)
    report(out)


def to_records(r: dict, gpu: str = "unknown", commit: str = "unknown", date: str = "", test_sequences: int = 200,
               env_steps: int | None = None, config: dict | None = None) -> list:
    """One (system, size, precision) row as a results record of errors: the rollout error normalized
    by the constant baseline, averaged over state groups and test sequences (``reported``: the
    per-sequence errors are not kept), episode steps the rollout's horizon; planner "none" on
    learned dynamics, variant "<size>, <precision>". Metrics: ms per rollout step of ``batch``
    graphs, graph-steps per second, MuJoCo-Warp's ms per data step of as many worlds (absent
    without CUDA)."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    system = systems.make(r["system"])
    lat, eh, nh = SIZES[r["size"]]
    metrics = {"ms_per_step": 1e3 * r["step_seconds"], "graph_steps_per_s": r["batch"] / r["step_seconds"]}
    if r.get("mjwarp_step_seconds") is not None:
        metrics["mjwarp_ms_per_step"] = 1e3 * r["mjwarp_step_seconds"]
    return [ResultRecord(
        experiment="speed_accuracy", task=r["system"], system=r["system"], planner="none", dynamics="learned",
        variant=f"{r['size']}, {r['precision']}", episodes=test_sequences, episode_steps=int(r.get("horizon", 20)),
        reported={"mean": float(r["rollout_error"]), "std": None, "of": "errors"}, control_dt=float(system.dt),
        action_repeat=int(system.substeps), env_steps=env_steps, metrics=metrics,
        config={"size": r["size"], "latent": lat, "edge_hidden": list(eh), "node_hidden": list(nh),
                "precision": r["precision"], "mode": r["mode"], "batch": r["batch"], **(config or {})},
        commit=commit, gpu=gpu, date=date)]


def report(out: Path) -> Path:
    """``summary.md`` and ``speed_accuracy.png`` from ``out/results.jsonl``."""
    from gnwarp.eval.records import read_records
    from gnwarp.eval.summarize import write_summary
    records = read_records(out / "results.jsonl")
    path = write_summary(records, out, f"Run time against error ({records[-1].gpu})", plot=False)
    _plot(records, out / "speed_accuracy.png")
    print(f"wrote {path}")
    return path


def _plot(records, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    systems = list(dict.fromkeys(r.task for r in records))
    if not systems:
        return
    fig, axes = plt.subplots(1, len(systems), figsize=(4.2 * len(systems), 3.6), squeeze=False)
    marks = {"fp32": "o", "tf32": "s", "fp16": "^", "bf16": "v"}
    for ax, s in zip(axes[0], systems):
        for r in (r for r in records if r.task == s):
            ax.scatter(r.metrics["ms_per_step"], r.reported["mean"], marker=marks[r.config["precision"]],
                       label=r.variant.replace(",", ""))
        sim = next((r.metrics.get("mjwarp_ms_per_step") for r in records if r.task == s), None)
        if sim:
            ax.axvline(sim, color="k", ls="--", lw=1, label="MuJoCo-Warp step")
        ax.set(xscale="log", yscale="log", xlabel="ms per rollout step (batch)",
               ylabel=f"{records[0].episode_steps}-step error / constant", title=s)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

if __name__ == "__main__":
    main()
