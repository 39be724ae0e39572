"""Benchmark: the recurrent one-step model's teacher-forcing step (``TeacherForcingTrainer.step``,
D.7.3), replayed from CUDA graphs against eager, in one process.

The proprioceptive JACO of ``bench/experiments/recurrent_jaco.py`` at its full size (recurrent GN,
latent 128, hidden graph 20, MLPs 256x256, batch 200 windows of 21 observations: 20 recurrent steps
a window), ``--sequences`` simulated on MuJoCo C. For each precision: a short run of each mode
first (kernels compiled, graphs captured), then ``--eager-steps`` eager steps and ``--steps``
captured ones, steps/s over each run (the loss read back once at its end); and
the model's 100-step rollouts (20 warm-up steps) of every training sequence, eager and captured
(median of 5, CUDA events).

    python bench/recurrent_loop.py [--precisions tf32,fp16] [--steps 400] [--eager-steps 40]
    python bench/recurrent_loop.py --quick          # tiny sizes on the CPU (eager only): a smoke test
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.harness import device_name, median_ms, results_dir, save_results  # noqa: E402
from gnwarp.data import proprio  # noqa: E402
from gnwarp.models.recurrent import RecurrentGNConfig  # noqa: E402
from gnwarp.models.recurrent_forward import RecurrentForwardConfig, RecurrentForwardModel  # noqa: E402
from gnwarp.train import TrainConfig, TeacherForcingTrainer  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precisions", default="tf32,fp16")
    ap.add_argument("--steps", type=int, default=400, help="captured steps")
    ap.add_argument("--eager-steps", type=int, default=40)
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--sequences", type=int, default=400)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=results_dir("recurrent_loop"))
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    latent, hidden, mlp = 128, 20, (256, 256)
    if args.quick:
        args.device, args.steps, args.eager_steps, args.batch, args.sequences = "cpu", 0, 4, 8, 8
        args.precisions, latent, hidden, mlp = "tf32", 16, 4, (32,)
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    t0 = time.perf_counter()
    data = proprio.ProprioData.simulate(proprio.proprio_jaco(), (args.sequences, 1, 1), num_steps=100, seed=0,
                                        backend="mujoco", device=dev)
    train = data.split("train")
    print(f"proprio JACO {args.sequences} x 100 steps: {time.perf_counter() - t0:.1f} s", flush=True)
    core = RecurrentGNConfig(latent=latent, hidden_edges=hidden, hidden_nodes=hidden, hidden_globals=hidden,
                             edge_mlp=mlp, node_mlp=mlp, global_mlp=mlp)
    name = device_name(dev)
    rows = []
    for prec in args.precisions.split(","):
        cfg = RecurrentForwardConfig(core=core)
        cfg.run = cfg.run.replace(impl="warp", precision=prec)
        model = RecurrentForwardModel(cfg, data.sizes, data.graphs, data.movable).to(dev)
        modes = [("eager", False, args.eager_steps)] + ([("captured", True, args.steps)] if cuda else [])
        for mode, capture, steps in modes:
            with tempfile.TemporaryDirectory() as run_dir:   # steps only: nothing is written there
                tc = TrainConfig(out=run_dir, batch_size=args.batch, lr=1e-3, device=str(dev), capture=capture,
                                 normalizer_warmup=0, progress=False, resume=False)
                trainer = TeacherForcingTrainer(tc, data, model)
            for _ in range(5):   # compile (and capture)
                trainer.step()
            if cuda:
                torch.cuda.synchronize()
            t = time.perf_counter()
            for _ in range(steps):
                loss = trainer.step()["loss"]
            if steps:
                float(loss)   # the last step's loss on the host: every step has run
            if cuda:
                torch.cuda.synchronize()
            s = time.perf_counter() - t
            row = dict(device=name, precision=prec, mode=mode, steps=steps, seconds=round(s, 3),
                       steps_per_s=round(steps / s, 1) if steps else 0.0, window=21, batch=args.batch)
            with torch.no_grad():   # 100-step rollouts (20 warm-up steps) of every training sequence
                run = lambda: model.rollout(train.instance, train.obs, train.ctrl, warmup=20, capture=capture)  # noqa: E731
                row["rollout_ms"] = round(median_ms(run, dev, 5 if cuda else 1, 1), 2)
                row["rollout_sequences"] = len(train)
            rows.append(row)
            print(row, flush=True)
    lines = [f"# The recurrent model's teacher-forcing loop on {name}", "",
             f"`python bench/recurrent_loop.py` ({time.strftime('%Y-%m-%d')}): `TeacherForcingTrainer.step` on the "
             f"proprioceptive JACO, latent {latent}, hidden graph {hidden}, MLPs {'x'.join(map(str, mlp))}, batch "
             f"{args.batch} windows of 21 observations (20 recurrent steps each); one process, each mode after a "
             "short run of it (5 steps) that compiled its kernels and captured its step.", "",
             "| precision | eager steps/s | captured steps/s | captured / eager | 100-step rollout of "
             f"{len(train)} sequences, eager ms | captured ms |", "|---|---|---|---|---|---|"]
    for prec in args.precisions.split(","):
        e = next(r for r in rows if r["precision"] == prec and r["mode"] == "eager")
        c = next((r for r in rows if r["precision"] == prec and r["mode"] == "captured"), None)
        ratio = f"{c['steps_per_s'] / e['steps_per_s']:.1f}x" if c else "-"
        lines.append(f"| {prec} | {e['steps_per_s']} | {c['steps_per_s'] if c else '-'} | {ratio} | "
                     f"{e['rollout_ms']} | {c['rollout_ms'] if c else '-'} |")
    save_results(args.out, "recurrent_loop", name, args.quick, rows, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
