"""Benchmark: the system-identification training loop users run (``SysIDTrainer``, what
``gnwarp train --sysid`` runs), the paper's recurrent GN_p against ``SysIDConfig.stateless``
(every step of the window in one batch), beside the true-parameter model's ``Trainer`` loop.

Sizes of the Figure 8 runs (forward core latent 128, edge MLP 2x256, node / global 2x128; GN_p
latent 128, MLPs 128x128, G_ID 10, global 24 where the system has more parameters), batch 200,
20-step windows, the options of the best Figure 8 runs (``--transitions --readout ridge
--ridge-head 64 --param-loss 1 --param-teacher 0.5 --local-params --nominal-static``). Per
system and model, in one process: a short run that compiles the kernels, then a captured run
(steps/s as the Trainer reports them, validation every 500 steps included), the captured step
alone (CUDA events), and ``identify`` of 200 windows (captured, no gradient).

    python bench/sysid_train.py [--systems pendulum,jaco] [--steps 1500]
    python bench/sysid_train.py --quick          # tiny sizes on the CPU: a smoke test of the script
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import (device_name, gn_sizes, median_ms, profile_kernels, results_dir,  # noqa: E402
                           save_results, slug)
from gnwarp import data  # noqa: E402
from gnwarp.models import ModelConfig, RecurrentGNConfig  # noqa: E402
from gnwarp.models.config import DEFAULT_RUN  # noqa: E402
from gnwarp.models import SysIDConfig  # noqa: E402
from gnwarp.train import TrainConfig, Trainer  # noqa: E402
from gnwarp.train import SysIDTrainConfig, SysIDTrainer  # noqa: E402

MODELS = ("true params", "sysid recurrent", "sysid stateless")


def profile_step(t, args, name: str, what: str) -> dict:
    """Kernels and device time per step of trainer ``t``'s eager step (the kernels a replay runs),
    its top kernels appended to the profile file."""
    t.warmup()
    calls, us = profile_kernels(t.step, args.profile, Path(args.out) / f"sysid_train_{slug(name)}_profile.txt", what,
                                top=25)
    return {"kernels_per_step": round(calls), "kernel_us_per_step": round(us, 1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,jaco")
    ap.add_argument("--steps", type=int, default=1500, help="steps of each captured run")
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=results_dir("sysid_train"))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--profile", type=int, default=0,
                    help="also profile this many eager steps of each model (torch.profiler): kernels and device time "
                         "per step, the top kernels written to <out>/sysid_train_<device>_profile.txt")
    args = ap.parse_args(argv)
    latent, edge, node, mlp, g, window, sizes = 128, 256, 128, (128, 128), 10, 20, (2000, 50, 10)
    if args.quick:
        args.device, args.steps, args.batch, args.systems = "cpu", 20, 8, "pendulum"
        latent, edge, node, mlp, g, window, sizes = 8, 16, 16, (16,), 6, 5, (24, 4, 2)
    dev = torch.device(args.device)
    name = device_name(dev)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for system in args.systems.split(","):
            t0 = time.perf_counter()
            ds = data.generate(system, sizes, num_steps=100 if not args.quick else 24, seed=0, backend="mujoco",
                               parameterized=True, progress=False)
            print(f"{system} data {sizes}: {time.perf_counter() - t0:.1f} s", flush=True)
            n_params = len(ds.meta["param_names"])
            gl = max(g, n_params + 4) if n_params > g else g
            ident = RecurrentGNConfig(latent=latent, hidden_edges=g, hidden_nodes=g, hidden_globals=gl, out_edges=g,
                                      out_nodes=g, out_globals=gl, edge_mlp=mlp, node_mlp=mlp, global_mlp=mlp)
            model = ModelConfig(gn=gn_sizes(latent, edge, node), run=DEFAULT_RUN.replace(impl="warp"),
                                recenter=bool(ds.meta.get("translation_invariant", False)))

            def config(tag, steps, **kw):
                kw = {"valid_every": 500, **kw}
                return TrainConfig(out=str(Path(tmp) / system / tag), model=model, steps=steps,
                                   batch_size=args.batch, device=args.device, valid_sequences=min(50, sizes[1]),
                                   checkpoint_every=max(steps, 1), patience=None, progress=False, resume=False,
                                   normalizer_warmup=20 if not args.quick else 2, **kw)

            def trainer(label, tag, steps, **kw):
                if label == "true params":
                    return Trainer(config(tag, steps, **kw), [ds])
                sysid = SysIDConfig(identifier=ident, window=window, transitions=True, readout="ridge",
                                    ridge_head=64, local_params=True, nominal_static=True,
                                    stateless=label.endswith("stateless"))
                return SysIDTrainer(config(tag, steps, **kw), sysid, datasets=[ds],
                                    options=SysIDTrainConfig(param_loss=1.0, param_teacher=0.5))
            for label in MODELS:
                tag = label.replace(" ", "_")
                trainer(label, "warm-" + tag, 30, valid_every=15).run()   # compile and load every kernel
                t = trainer(label, tag, args.steps)
                r = t.run()
                row = dict(device=name, system=system, model=label, steps=r["steps"], seconds=round(r["seconds"], 2),
                           steps_per_s=round(r["steps_per_second"], 1), batch=args.batch, window=window)
                if dev.type == "cuda":
                    row["step_ms"] = round(median_ms(t.step, dev, 100, 5), 3)   # the captured step alone
                if label != "true params":
                    m = t.model.eval().bind(ds)
                    sp = ds["valid"] if len(ds["valid"]) >= args.batch else ds["train"]
                    n = min(args.batch, len(sp))
                    body = torch.as_tensor(np.asarray(sp.body[:n, :window], dtype=np.float32), device=dev)
                    ctrl = torch.as_tensor(np.asarray(sp.ctrl[:n, :window], dtype=np.float32), device=dev)
                    inst = torch.as_tensor(np.asarray(sp.instance[:n]))
                    with torch.no_grad():
                        row["identify_ms"] = round(median_ms(lambda: m.identify(body, ctrl, inst), dev, 20, 2), 3)
                if args.profile and dev.type == "cuda":
                    row.update(profile_step(trainer(label, "prof-" + tag, 10 ** 6, capture=False), args, name,
                                            f"{system}, {label}"))
                rows.append(row)
                print(json.dumps(row), flush=True)
    lines = [f"# The system-identification training loop users run, on {name}", "",
             f"`python bench/sysid_train.py` ({time.strftime('%Y-%m-%d')}): `SysIDTrainer` (`gnwarp train --sysid`) "
             "with the paper's recurrent GN_p and with `SysIDConfig.stateless`, beside the true-parameter model's "
             f"`Trainer`; batch {args.batch}, {window}-step windows, captured steps, validation every 500 steps "
             f"included; one process, each model after a warm-up run of it. `identify`: {args.batch} windows, no gradient.", "",
             "| system | model | loop steps/s | step alone ms | x true params (step) | identify ms | kernels / step "
             "| kernel time / step, us |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ref = next(x for x in rows if x["system"] == r["system"] and x["model"] == "true params")
        ratio = f"{r['step_ms'] / ref['step_ms']:.1f}x" if "step_ms" in r else ""
        lines.append(f"| {r['system']} | {r['model']} | {r['steps_per_s']:.0f} | {r.get('step_ms', '')} | {ratio} | "
                     f"{r.get('identify_ms', '')} | {r.get('kernels_per_step', '')} | {r.get('kernel_us_per_step', '')} |")
    save_results(args.out, "sysid_train", name, args.quick, rows, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
