"""Training and generation on 1..N GPUs of one host (``torchrun``): weak and strong scaling, the
all-reduce's share of a training step, and the time to one validation error.

One launch per GPU count, each appending rows to ``--records`` (JSON lines); ``--summarize``
turns the rows of one run into ``bench/results/distributed_<gpu>.json`` and a table:

    python bench/distributed.py --gpus 1,2,4 --data /root/dist/cheetah.h5 --records rec.jsonl

(``--gpus``: the dataset if missing (``--prepare``), one ``torchrun --nproc_per_node N`` launch of
this script per count, in order, then ``--summarize``; a launch whose captured step fails is run
again uncaptured, and says so in its rows.)

Per launch (every rank on its own GPU, rank 0 records):
- generation: each rank simulates ``--gen-per-gpu`` cheetah sequences of ``--gen-steps`` steps with
  MuJoCo-Warp (``gnwarp.data.generation.generate(shard=...)``, the sequences of a dataset of
  ``--gen-per-gpu`` x ranks), timed from a barrier to the last rank's end (after a small warm-up
  generation): data steps per second over all ranks;
- training throughput: the paper's model on the cheetah dataset, the step captured in a CUDA graph
  with its all-reduce inside; weak (``--batch`` graphs per GPU) and strong (``--strong-total``
  graphs per step split over the ranks); graphs per second over all ranks in the steady state
  (``--warmup`` steps, then ``--steps`` timed in two halves); over several ranks with FlatAdam
  the step reduces with one all-reduce after the backward (``overlap_allreduce`` off, the
  default) and the same launch times the peer that reduces GN2's gradients during the backward
  (``step_ms_overlap``; ``overlap_sent``: how many of its eager steps and its capture sent GN2's
  span early, which replays repeat), the halves in turn (A B, B A;
  run h100x2-overlap timed the overlapped step as its main row, then the other, one after the
  other: ``step_ms_one_allreduce``);
- the all-reduce's share: the step's two all-reduces alone (the flat gradient's and the packed
  normalizer sums', each captured and replayed), over the step's time;
- time to error: training from scratch for ``--tte-seconds`` (weak batches; ``--lr-scaling
  linear`` multiplies the learning rate by the ranks), the 20-step validation error every
  ``--tte-every`` steps (validation time not counted); or, with ``--tte-samples-steps N``, on a
  fixed number of graphs (N / GPUs steps, the learning rate decaying with the graphs seen). The
  error jumps 2-5x from one validation to the next, so the summary smooths it: the moving median
  of the last ``--tte-window`` validations; the target is the one-GPU launch's smoothed error at
  its end (or, ``--tte-target all_reach``, the worst launch's), and a launch's time to error is
  when its smoothed error first reaches it (``time_to_raw_error_s``: the first single validation
  at or below the one-GPU launch's best, kept for comparison).
``--summarize --run-id a,b``: every listed run's rows in one summary, each row naming its run.
Efficiency (weak): throughput on N GPUs / (N x throughput on 1 GPU) of the same run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from bench.harness import device_name, slug  # noqa: E402

SYSTEM = "cheetah"


def sync(r):
    if r.device.type == "cuda":
        torch.cuda.synchronize(r.device)


def timed_barrier(r):
    sync(r)
    r.barrier("bench")
    return time.perf_counter()


def bench_generation(r, a) -> dict:
    from gnwarp.data.generation import generate
    backend = "mujoco_warp" if r.device.type == "cuda" else "mujoco_warp_cpu"
    generate(SYSTEM, num_sequences=(8 * r.world, 0, 0), num_steps=4, seed=1, backend=backend, progress=False,
             shard=(r.rank, r.world))    # warm-up: MuJoCo-Warp's kernels loaded
    t0 = timed_barrier(r)
    ds = generate(SYSTEM, num_sequences=(a.gen_per_gpu * r.world, 0, 0), num_steps=a.gen_steps, seed=2,
                  backend=backend, progress=False, shard=(r.rank, r.world))
    t1 = timed_barrier(r)
    n = len(ds["train"])
    sims = r.gather_objects(float(ds.meta["simulation_seconds"]))   # each rank's time in the simulator
    return {"generate_steps_per_s": a.gen_per_gpu * r.world * a.gen_steps / (t1 - t0), "generate_seconds": t1 - t0,
            "generate_sequences_per_gpu": n, "generate_steps": a.gen_steps,
            "generate_sim_seconds": [round(x, 4) for x in sims] if sims else None}


def trainer_for(r, a, batch, out, lr=1e-4, capture=True, overlap=False, **config):
    from gnwarp.train import TrainConfig
    from gnwarp.train.trainer import Trainer
    cfg = TrainConfig.from_dict(dict(data=[a.data], out=out, batch_size=batch, lr=lr, device="auto", resume=False,
                                     progress=False, capture=capture, valid_sequences=a.valid_sequences,
                                     steps=10**9, overlap_allreduce=overlap, optimizer=a.optimizer, seed=a.seed, **config))
    return Trainer(cfg)


def warm(r, a, t) -> None:
    """Trainer ``t`` past its warm-up (captured, where it captures) and ``--warmup`` steps."""
    t.warmup()
    for _ in range(a.warmup):
        t.step()


def timed_steps(r, a, t, steps: int) -> float:
    """Seconds of ``steps`` steps of the warm trainer ``t``, between barriers."""
    t0 = timed_barrier(r)
    for _ in range(steps):
        t.step()
    return timed_barrier(r) - t0


def bench_train(r, a, batch, tag) -> dict:
    from gnwarp.train.optim import FlatAdam
    t = trainer_for(r, a, batch, f"{a.work}/{tag}-{r.world}", capture=not a.no_capture)
    trainers = {"step_ms": t}
    if r.distributed and isinstance(t.optimizer, FlatAdam):   # the peer: GN2's gradients reduced in the backward
        peer = trainer_for(r, a, batch, f"{a.work}/{tag}-{r.world}-overlap", capture=not a.no_capture, overlap=True)
        if peer.buckets is not None:
            trainers["step_ms_overlap"] = peer
    for x in trainers.values():
        warm(r, a, x)
    seconds = dict.fromkeys(trainers, 0.0)
    for order in (list(trainers), list(trainers)[::-1]):   # two halves in turn: order effects fall on both
        for k in order:
            seconds[k] += timed_steps(r, a, trainers[k], a.steps // 2)
    step_s = seconds["step_ms"] / (2 * (a.steps // 2))
    row = {"per_gpu_batch": batch, "step_ms": 1e3 * step_s, "train_graphs_per_s": batch * r.world / step_s,
           "captured": t.captured is not None, "overlap": t.buckets is not None}
    if "step_ms_overlap" in trainers:
        peer = trainers["step_ms_overlap"]
        row["step_ms_overlap"] = 1e3 * seconds["step_ms_overlap"] / (2 * (a.steps // 2))
        row["overlap_sent"], row["overlap_skipped"] = peer.buckets.sent, peer.buckets.skipped   # it did overlap
    if r.distributed:
        grads = (t.optimizer.grad_flat if isinstance(t.optimizer, FlatAdam)
                 else torch.cat([p.detach().reshape(-1) for p in t.model.parameters()]))
        from gnwarp.models.normalizer import Normalizer
        norms = [m for m in t.model.modules() if isinstance(m, Normalizer)]
        packed = torch.zeros(sum(1 + 2 * m.size for m in norms), dtype=torch.float64, device=r.device)
        row["allreduce_ms"] = allreduce_ms(r, grads)
        row["norm_allreduce_ms"] = allreduce_ms(r, packed)
        row["allreduce_share"] = (row["allreduce_ms"] + row["norm_allreduce_ms"]) / row["step_ms"]
    return row


def allreduce_ms(r, like: torch.Tensor) -> float:
    """An all-reduce of a buffer like ``like`` alone (the step's flat gradient, or its packed
    normalizer sums), captured and replayed (eager where not on CUDA)."""
    from gnwarp.interop import Graphed
    buf = like.detach().clone()
    reps = 200

    def many():
        for _ in range(20):
            r.all_reduce_(buf, mean=True)
    run = Graphed(many, warmup=1) if r.device.type == "cuda" else many
    run()
    run()
    t0 = timed_barrier(r)
    for _ in range(reps // 20):
        run()
    t1 = timed_barrier(r)
    return 1e3 * (t1 - t0) / reps


def time_to_error(r, a, target: float | None) -> dict:
    """Train from scratch; validation every ``--tte-every`` steps (not counted). Without a target
    (the one-GPU launch): train ``--tte-seconds`` and report the error reached.

    With ``--tte-samples-steps N`` the launch instead trains a fixed number of graphs: N steps at one
    GPU, N / GPUs steps on several (each of ``--batch`` graphs per GPU), the learning rate halved
    (``--tte-decay``) every ``--tte-decay-every`` one-GPU steps' worth of graphs and validated every
    ``--tte-every`` one-GPU steps' worth: every launch sees the same schedule per graph trained."""
    world = r.world
    lr = 1e-4 * (world if a.lr_scaling == "linear" else 1)
    by_samples = a.tte_samples_steps is not None
    if by_samples:   # every launch the same schedule per graph: each count divides by the GPUs
        bad = {k: v for k, v in (("--tte-samples-steps", a.tte_samples_steps), ("--tte-every", a.tte_every),
                                 ("--tte-decay-every", a.tte_decay_every)) if v % world}
        if bad or a.tte_samples_steps % a.tte_every:
            raise SystemExit(f"time to error on {world} GPUs: {bad or '--tte-samples-steps'} must divide by the GPUs "
                             "(and --tte-samples-steps by --tte-every) for every launch to see the same schedule")
    schedule = dict(lr_decay=a.tte_decay, lr_decay_steps=max(1, a.tte_decay_every // world)) if by_samples else {}
    t = trainer_for(r, a, a.batch, f"{a.work}/tte-{world}", lr=lr, capture=not a.no_capture, **schedule)
    every = max(1, a.tte_every // world) if by_samples else a.tte_every
    total = a.tte_samples_steps // world if by_samples else None
    t.warmup()
    clock, steps, best, reached = 0.0, 0, math.inf, None
    curve = []
    while (steps < total) if by_samples else (clock < a.tte_seconds):   # the whole budget: the summary
        t0 = timed_barrier(r)                                         # reads the time to error from the curve
        for _ in range(every):
            t.step()   # at the schedule's learning rate (the trainer's step count is this loop's)
            steps += 1
        clock += timed_barrier(r) - t0
        clock = r.broadcast_object(clock)   # rank 0's clock: every rank leaves the loop at the same round
        err = t.validate() if r.main else None
        err = r.broadcast_object(err)
        best = min(best, err)
        curve.append([round(clock, 3), steps, err])
        if target is not None and err <= target and reached is None:
            reached = clock
    return {"time_to_raw_error_s": reached if target is not None else clock, "target_error": target,
            "best_error": best, "tte_steps": steps, "lr": lr, "lr_scaling": a.lr_scaling, "tte_curve": curve,
            "tte_protocol": ({"samples_steps": a.tte_samples_steps, "decay": a.tte_decay,
                              "decay_every": a.tte_decay_every, "every": a.tte_every} if by_samples
                             else {"seconds": a.tte_seconds, "every": a.tte_every})}


def prepare(a) -> None:
    from gnwarp.data.generation import generate
    path = Path(a.data)
    if path.exists():
        print(f"{path} exists")
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    backend = "mujoco_warp" if torch.cuda.is_available() else "mujoco"
    ds = generate(SYSTEM, num_sequences=(a.train_sequences, a.valid_sequences, 0), num_steps=100, seed=0,
                  backend=backend, progress=False)
    ds.save(path)
    print(f"wrote {path}: {ds.meta['splits']}")


def one_gpu_target(records: Path, gpu: str, run: str) -> float | None:
    """The best single validation of this run's one-GPU launch (the raw target), if recorded."""
    if not records.is_file():
        return None
    rows = [json.loads(x) for x in records.read_text().splitlines() if x.strip()]
    rows = [x for x in rows if x.get("gpus") == 1 and x.get("mode") == "weak" and x.get("gpu") == gpu
            and x.get("run") == run and x.get("best_error") is not None]
    return rows[-1]["best_error"] if rows else None


def main_launch(a) -> None:
    from gnwarp.distributed import ranks
    r = ranks("auto")
    gpu = device_name(r.device)
    nccl = ".".join(map(str, torch.cuda.nccl.version())) if r.device.type == "cuda" else None
    base = {"gpus": r.world, "gpu": gpu, "nccl": nccl, "backend": r.backend, "run": a.run_id, "seed": a.seed,
            "env": {k: os.environ.get(k) for k in ("NCCL_NVLS_ENABLE", "TORCH_SYMM_MEM_DISABLE_MULTICAST")}}
    rows = []
    gen = {} if a.skip_generation else bench_generation(r, a)
    weak = {**base, "mode": "weak", **bench_train(r, a, a.batch, "weak"), **gen}
    if not a.skip_tte:
        target = None if r.world == 1 else one_gpu_target(Path(a.records), gpu, a.run_id)
        weak.update(time_to_error(r, a, target))
    rows.append(weak)
    if not a.skip_strong and a.strong_total % r.world == 0:
        rows.append({**base, "mode": "strong", **bench_train(r, a, a.strong_total // r.world, "strong")})
    if r.main:
        Path(a.records).parent.mkdir(parents=True, exist_ok=True)
        with open(a.records, "a") as f:
            for row in rows:
                f.write(json.dumps(row) + "\n")
        for row in rows:
            print(json.dumps({k: v for k, v in row.items() if k != "tte_curve"}))
    r.barrier("bench: end")


FIELDS = ("gpus", "mode", "per_gpu_batch", "train_graphs_per_s", "generate_steps_per_s", "time_to_error_s", "gpu",
          "nccl")


def smoothed(curve, window: int) -> tuple[list[float], list[float]]:
    """(times, moving median of the last ``window`` errors) of a [[seconds, steps, error], ...] curve."""
    import statistics
    t = [c[0] for c in curve]
    e = [c[2] for c in curve]
    return t, [statistics.median(e[max(0, i - window + 1):i + 1]) for i in range(len(e))]


def summarize(a) -> None:
    """The summary JSON (every listed run's rows, each with its ``run``) and its table."""
    from gnwarp.files import atomic_write
    records = [json.loads(x) for x in Path(a.records).read_text().splitlines() if x.strip()]
    out, lines = [], []
    for run in [x.strip() for x in (a.run_id or records[-1]["run"]).split(",") if x.strip()]:
        rows = [x for x in records if x.get("run") == run]
        if not rows:
            raise SystemExit(f"{a.records}: no rows of run {run!r}")
        o, t = summarize_run(a, run, rows)
        out += o
        lines += t + [""]
    path = Path(a.summary or ROOT / "bench" / "results" / f"distributed_{slug(out[0]['gpu'])}.json")
    with atomic_write(path) as tmp:
        Path(tmp).write_text(json.dumps(out, indent=1) + "\n")
    table = path.with_suffix(".md")
    with atomic_write(table) as tmp:
        Path(tmp).write_text("\n".join(lines).rstrip() + "\n")
    print("\n".join(lines))
    print(f"wrote {path} and {table}")


def summarize_run(a, run: str, rows: list[dict]) -> tuple[list[dict], list[str]]:
    gpu = rows[0]["gpu"]
    out = [{k: x.get(k) for k in FIELDS} | {"run": run} | {k: x[k] for k in ("allreduce_share", "allreduce_ms", "norm_allreduce_ms",
                                                                 "step_ms", "lr_scaling", "generate_sim_seconds",
                                                                 "captured", "overlap", "step_ms_one_allreduce",
                                                                 "step_ms_overlap", "overlap_sent", "seed") if k in x}
           for x in sorted(rows, key=lambda x: (x["mode"], x["gpus"]))]
    one = {(x["mode"]): x for x in rows if x["gpus"] == 1}
    curves = {x["gpus"]: x.get("tte_curve") for x in rows if x["mode"] == "weak" and x.get("tte_curve")}
    target = smoothed(curves[1], a.tte_window)[1][-1] if 1 in curves else None
    # the run's declared target: --tte-target, else its protocol's (a fixed number of graphs: all_reach)
    tte_target = a.tte_target or ("all_reach" if any("samples_steps" in x.get("tte_protocol", {}) for x in rows)
                                  else "one_gpu_end")
    if tte_target == "all_reach" and 1 in curves:   # the error every launch reaches: the worst end
        target = max(smoothed(c, a.tte_window)[1][-1] for c in curves.values())
    for x, o in zip(sorted(rows, key=lambda x: (x["mode"], x["gpus"])), out):
        c = curves.get(x["gpus"]) if x["mode"] == "weak" else None
        o["time_to_error_s"] = None
        if c and target is not None:
            t, e = smoothed(c, a.tte_window)
            hit = [ti for ti, ei in zip(t, e) if ei <= target]
            o["time_to_error_s"] = hit[0] if hit else None
            o["target_smoothed_error"] = target
            o["tte_target"] = tte_target
            o["trained_s"] = t[-1]
            o["time_to_raw_error_s"] = x.get("time_to_raw_error_s", x.get("time_to_error_s"))
    lines = [f"Run {run} on {gpu} (NCCL {rows[0].get('nccl')}), one launch per GPU count; efficiency = "
             "throughput on N GPUs / (N x on 1 GPU), weak; speed-up for strong.", "",
             "| GPUs | mode | batch per GPU | graphs/s | efficiency | step ms | all-reduce share | "
             "step ms: one all-reduce / overlapped (efficiency) | data steps/s | gen. efficiency | "
             "time to error s (x 1 GPU) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    t_one = next((x["time_to_error_s"] for x in out if x["gpus"] == 1 and x["mode"] == "weak"), None)
    for x in out:
        if x.get("time_to_error_s") is not None and t_one:
            x["time_to_error_ratio"] = x["time_to_error_s"] / t_one
        base = one.get(x["mode"])
        eff = x["train_graphs_per_s"] / (x["gpus"] * base["train_graphs_per_s"]) if base else None
        if x["mode"] == "strong" and base:
            eff = x["train_graphs_per_s"] / base["train_graphs_per_s"] / x["gpus"]
        geff = (x["generate_steps_per_s"] / (x["gpus"] * one["weak"]["generate_steps_per_s"])
                if x.get("generate_steps_per_s") and "weak" in one and one["weak"].get("generate_steps_per_s")
                else None)
        x["train_efficiency"], x["generate_efficiency"] = eff, geff
        ways = {}   # the step with one all-reduce and with the overlapped one, where measured
        if x.get("overlap") is not None and x["gpus"] > 1:
            ways = {"one_allreduce": x.get("step_ms_one_allreduce", None if x["overlap"] else x.get("step_ms")),
                    "overlap": x.get("step_ms") if x["overlap"] else x.get("step_ms_overlap")}
        for way, ms in ways.items():   # efficiency as above: throughput / (N x one GPU's)
            if ms and base and base.get("step_ms"):
                x[f"train_efficiency_{way}"] = x["per_gpu_batch"] * base["step_ms"] / (base["per_gpu_batch"] * ms)
        f = lambda v, p=3: "" if v is None else (f"{v:.{p}g}" if isinstance(v, float) else str(v))  # noqa: E731
        lines.append(f"| {x['gpus']} | {x['mode']} | {x['per_gpu_batch']} | {f(x['train_graphs_per_s'], 4)} | "
                     f"{f(eff)} | {f(x.get('step_ms'))} | {f(x.get('allreduce_share'))} | "
                     + " / ".join(f"{ways[w]:.3g} ({x[f'train_efficiency_{w}']:.3f})" if f"train_efficiency_{w}" in x
                                  else "" for w in ways) + " | "
                     f"{f(x.get('generate_steps_per_s'), 4)} | {f(geff)} | {f(x.get('time_to_error_s'))}"
                     + (f" ({x['time_to_error_ratio']:.2f})" if x.get("time_to_error_ratio") else "") + " |")
    return out, lines


def launch_all(a, argv) -> int:
    """``--gpus 1,2,4``: prepare, one torchrun launch per count, summarize."""
    import subprocess
    import uuid
    counts = [int(x) for x in a.gpus.split(",")]
    rest, skip = [], False
    for x in argv:   # the arguments every launch shares: all but --gpus
        if skip:
            skip = False
            continue
        if x == "--gpus":
            skip = True
            continue
        if not x.startswith("--gpus="):
            rest.append(x)
    me = [sys.executable, str(Path(__file__).resolve())]
    if not Path(a.data).exists():
        subprocess.run(me + rest + ["--prepare"], check=True)
    env = dict(os.environ, GNWARP_BENCH_RUN=a.run_id or f"run-{uuid.uuid4().hex[:8]}")
    failed = []
    for n in counts:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(n), "--master_port",
               str(29500 + n)] + me[1:] + rest
        t0 = time.perf_counter()
        rc = subprocess.run(cmd, env=env).returncode
        if rc != 0 and "--no-capture" not in rest:
            print(f"{n} GPUs: launch failed (exit {rc}); again with --no-capture", flush=True)
            rc = subprocess.run(cmd + ["--no-capture"], env=env).returncode
        print(f"{n} GPUs: exit {rc} after {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(n)
    subprocess.run(me + rest + ["--summarize", "--run-id", env["GNWARP_BENCH_RUN"]])
    return 1 if failed else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="runs/dist/cheetah.h5", help="the training dataset (made by --prepare)")
    ap.add_argument("--records", default="bench/results/distributed/records.jsonl")
    ap.add_argument("--work", default="runs/dist", help="folder of the trainers' (unused) run folders")
    ap.add_argument("--run-id", default=os.environ.get("GNWARP_BENCH_RUN", ""), help="names the run's rows (--summarize: runs, comma-separated)")
    ap.add_argument("--gpus", help="e.g. 1,2,4: one torchrun launch per count, then --summarize")
    ap.add_argument("--prepare", action="store_true", help="write the dataset and stop")
    ap.add_argument("--summarize", action="store_true", help="summary JSON and table from the records")
    ap.add_argument("--summary", help="the summary's path (default bench/results/distributed_<gpu>.json)")
    ap.add_argument("--train-sequences", type=int, default=2000)
    ap.add_argument("--valid-sequences", type=int, default=100)
    ap.add_argument("--batch", type=int, default=200, help="graphs per GPU (weak scaling; the paper's 200)")
    ap.add_argument("--strong-total", type=int, default=800, help="graphs per step over all GPUs (strong)")
    ap.add_argument("--warmup", type=int, default=30)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--gen-per-gpu", type=int, default=4096)
    ap.add_argument("--gen-steps", type=int, default=100)
    ap.add_argument("--tte-seconds", type=float, default=60.0, help="the one-GPU launch's training time")
    ap.add_argument("--tte-window", type=int, default=8, help="validations in the moving median of the error")
    ap.add_argument("--tte-every", type=int, default=250, help="steps between validations")
    ap.add_argument("--tte-samples-steps", type=int, help="train a fixed number of graphs: this many steps at one "
                    "GPU (N / GPUs on N), instead of --tte-seconds")
    ap.add_argument("--tte-decay", type=float, default=0.5, help="with --tte-samples-steps: the learning rate's factor")
    ap.add_argument("--tte-decay-every", type=int, default=7500,
                    help="with --tte-samples-steps: one-GPU steps' worth of graphs per --tte-decay")
    ap.add_argument("--tte-target", choices=["one_gpu_end", "all_reach"],
                    help="summary: the target is the one-GPU launch's smoothed error at its end, or the worst of "
                         "every launch's (an error every launch reaches); default: all_reach for a run on a fixed "
                         "number of graphs (--tte-samples-steps), else one_gpu_end")
    ap.add_argument("--seed", type=int, default=0, help="the trainers' seed (weights and batches)")
    ap.add_argument("--lr-scaling", choices=["none", "linear"], default="linear")
    ap.add_argument("--optimizer", default="auto", choices=["auto", "adam", "flat_adam"],
                    help="TrainConfig.optimizer (auto: FlatAdam on GPUs, torch's Adam on CPUs)")
    ap.add_argument("--skip-generation", action="store_true")
    ap.add_argument("--skip-tte", action="store_true")
    ap.add_argument("--skip-strong", action="store_true")
    ap.add_argument("--no-capture", action="store_true")
    ap.add_argument("--quick", action="store_true", help="CPU-sized")
    a = ap.parse_args(argv)
    if a.quick:
        a.train_sequences, a.valid_sequences, a.batch, a.strong_total = 8, 4, 4, 8
        a.warmup, a.steps, a.gen_per_gpu, a.gen_steps, a.tte_seconds, a.tte_every = 2, 3, 4, 5, 1.0, 2
    if a.gpus:
        return launch_all(a, argv if argv is not None else sys.argv[1:])
    if a.prepare:
        prepare(a)
    elif a.summarize:
        summarize(a)
    else:
        if not Path(a.data).exists():
            raise SystemExit(f"no dataset at {a.data}: run with --prepare first")
        from gnwarp.distributed import close
        done = False
        try:
            main_launch(a)
            done = True
        finally:
            close(sync=done)   # leave the process group before exit (else gloo may abort the process at exit)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
