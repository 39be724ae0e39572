"""``gnwarp demo``: the whole pipeline, small enough for a 2-core CPU in a few minutes.

Simulates a small Pendulum dataset (MuJoCo C on a CPU, MuJoCo-Warp on a GPU), trains a GN forward
model and an MLP baseline for the same number of steps, evaluates both against the constant
baseline (one-step, 20- and 100-step rollouts), and writes under ``out``::

    report.md          what was run, the error table, the pictures below
    errors.md          the error table
    errors.png         normalized errors, GN vs MLP vs constant (like the paper's Figs. 4-5)
    states.png         the 13 state variables of one body along a 100-step rollout (Fig. H.1)
    rollouts.gif       true vs predicted motion of a few test rollouts
    training.png       training loss and validation error against training steps
    results.json       the numbers
    <system>.h5, gn/, mlp/   the dataset and the two training runs (checkpoints, CSV logs)
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from gnwarp.files import jsonable
from gnwarp.interop import resolve_device
from gnwarp.models.config import DEFAULT_RUN, GNCoreConfig, ModelConfig

__all__ = ["DemoConfig", "run_demo", "quick_train_keys"]


@dataclass
class DemoConfig:
    """Sizes and budgets of the demo (defaults: ~3 minutes on a 2-core CPU).

    With input noise (D.7.1) the GN first fits the dynamics, then (after ~4k steps here) learns to
    pull a dislocated pendulum back onto its hinge, which is what keeps 100-step rollouts on track;
    8000 steps leave room for both."""
    out: str = "gnwarp-demo"
    system: str = "pendulum"
    dataset: str | None = None            # an existing dataset file to use instead of simulating one
    train_sequences: int = 500
    valid_sequences: int = 20
    test_sequences: int = 100
    num_steps: int = 100
    gn: GNCoreConfig = field(default_factory=lambda: GNCoreConfig(
        latent=64, edge_hidden=(128, 128), node_hidden=(128,), global_hidden=(128,)))
    mlp_size: str = "3x128"
    train_steps: int = 8000
    train_seconds: float | None = 300.0   # cap for the GN; the MLP gets the GN's step count
    batch_size: int = 200
    lr: float = 2e-3                      # short runs: higher than the paper's 1e-4, decayed x0.6 every
    lr_decay: float = 0.6                 # quarter of the run
    lr_decay_every: int = 2000
    noise_std: float = 0.003
    valid_every: int = 500
    animate_rollouts: int = 3
    renderer: str = "auto"                # rollout video: "mujoco" (EGL/OSMesa), "matplotlib", or "auto"
    impl: str = "warp"                    # GN implementation: "warp" (Warp kernels) or "torch" (reference)
    device: str = "auto"
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        if isinstance(self.gn, dict):
            self.gn = GNCoreConfig(**self.gn)


def quick_train_keys() -> dict:
    """``gnwarp train --quick``: the demo's GN sizes (those unlike the paper's) and schedule as
    TrainConfig keys (nested tables for ``model``): a run sized for a CPU in minutes."""
    d, paper = DemoConfig(), dataclasses.asdict(GNCoreConfig())
    gn = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(d.gn).items() if v != paper[k]}
    return {"steps": d.train_steps, "max_seconds": d.train_seconds, "batch_size": d.batch_size, "lr": d.lr,
            "lr_decay": d.lr_decay, "lr_decay_steps": d.lr_decay_every, "valid_every": d.valid_every,
            "valid_sequences": d.valid_sequences, "model": {"gn": gn}}


def run_demo(config: DemoConfig | None = None, **overrides) -> dict:
    """Run the demo; returns a summary (timings, errors, paths). ``overrides``: DemoConfig fields."""
    import torch

    from gnwarp.data.dataset import load
    from gnwarp.data.generation import generate
    from gnwarp.eval.metrics import evaluate
    from gnwarp.eval.report import plot_training, write_report
    from gnwarp.sim.common import resolve_backend
    from gnwarp.train import TrainConfig, load_model, train

    cfg = dataclasses.replace(config or DemoConfig(), **overrides)
    t0 = time.perf_counter()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(cfg.device)
    timings = {}
    say = print if cfg.progress else (lambda *a, **k: None)

    # 1. data
    t = time.perf_counter()
    if cfg.dataset:
        ds = load(cfg.dataset, lazy=False)
        sim_backend = ds.meta["backend"]
        data_path = Path(cfg.dataset)
        say(f"[1/4] using {data_path}: {ds.meta['splits']} sequences of {ds.meta['num_steps']} steps")
    else:
        sim_backend = resolve_backend("auto")
        say(f"[1/4] simulating {cfg.system}: {cfg.train_sequences}/{cfg.valid_sequences}/{cfg.test_sequences} "
            f"sequences x {cfg.num_steps} steps ({sim_backend})")
        ds = generate(cfg.system, (cfg.train_sequences, cfg.valid_sequences, cfg.test_sequences),
                      num_steps=cfg.num_steps, seed=cfg.seed, backend="auto", progress=cfg.progress)
        data_path = out / f"{cfg.system}.h5"
        ds.save(data_path, overwrite=True)
    timings["data"] = time.perf_counter() - t

    # 2. training: GN within the budget, then the MLP for the same number of steps
    common = dict(steps=cfg.train_steps, batch_size=cfg.batch_size, lr=cfg.lr, lr_decay=cfg.lr_decay,
                  lr_decay_steps=cfg.lr_decay_every, noise_std=cfg.noise_std,
                  valid_every=cfg.valid_every, valid_sequences=cfg.valid_sequences, patience=None,
                  checkpoint_every=max(cfg.train_steps, 1), device=str(device), seed=cfg.seed, resume=False,
                  progress=cfg.progress, data=[str(data_path)])
    say(f"[2/4] training a GN ({cfg.impl} implementation, {device}) for up to {cfg.train_steps} steps"
        + (f" or {cfg.train_seconds:g} s" if cfg.train_seconds else ""))
    t = time.perf_counter()
    gn_model = ModelConfig(core="gn", gn=cfg.gn, run=DEFAULT_RUN.replace(impl=cfg.impl))
    gn_run = train(TrainConfig(out=str(out / "gn"), model=gn_model,
                               max_seconds=cfg.train_seconds, **common), [ds])
    timings["train_gn"] = time.perf_counter() - t
    mlp_common = {**common, "steps": gn_run["steps"]}
    say(f"[3/4] training an MLP baseline ({cfg.mlp_size}) for the same {gn_run['steps']} steps")
    layers, width = (int(x) for x in cfg.mlp_size.split("x"))
    t = time.perf_counter()
    mlp_cfg = ModelConfig(core="mlp", mlp=dataclasses.replace(ModelConfig().mlp, layers=layers, width=width))
    mlp_run = train(TrainConfig(out=str(out / "mlp"), model=mlp_cfg, **mlp_common), [ds])
    timings["train_mlp"] = time.perf_counter() - t

    # 3. evaluation on the test split
    say(f"[4/4] evaluating on {len(ds['test'])} test sequences and drawing")
    t = time.perf_counter()
    models = {"GN": load_model(gn_run["best"], device=device),
              f"MLP {cfg.mlp_size}": load_model(mlp_run["best"], device=device)}
    results = {name: evaluate(m, ds, "test", keep_predictions=True) for name, m in models.items()}
    timings["evaluate"] = time.perf_counter() - t

    t = time.perf_counter()
    table = write_report(results, ds, out, cfg.animate_rollouts, cfg.renderer)
    plot_training({"GN": out / "gn" / "log.csv", f"MLP {cfg.mlp_size}": out / "mlp" / "log.csv"},
                  out / "training.png")
    timings["plots"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0

    summary = {
        "system": cfg.system, "device": str(device), "gn_impl": cfg.impl, "simulator": sim_backend,
        "torch_threads": torch.get_num_threads(), "dataset": ds.meta["splits"], "num_steps": ds.meta["num_steps"],
        "gn": {k: gn_run[k] for k in ("steps", "best_step", "seconds", "steps_per_second", "stop")},
        "mlp": {k: mlp_run[k] for k in ("steps", "best_step", "seconds", "steps_per_second", "stop")},
        "results": jsonable(results), "timings_s": timings, "config": jsonable(dataclasses.asdict(cfg)),
    }
    (out / "results.json").write_text(json.dumps(summary, indent=1))
    (out / "report.md").write_text(_report(cfg, summary, table))
    say(f"\n{table}\nwrote {out / 'report.md'} in {timings['total']:.0f} s")
    return summary


def _report(cfg: DemoConfig, s: dict, table: str) -> str:
    tm = s["timings_s"]
    g, m = s["gn"], s["mlp"]
    sizes = s["dataset"]
    return f"""# gnwarp demo: {cfg.system}

Learned forward models of the {cfg.system} (Sanchez-Gonzalez et al., ICML 2018), trained on a
small dataset in a few minutes: a graph network (GN) and an MLP baseline at the same number of
training steps, both evaluated against the constant-prediction baseline.

- Device: {s['device']} ({s['torch_threads']} torch threads); GN implementation: {s['gn_impl']};
  simulator: {s['simulator']}.
- Data: {sizes['train']} train / {sizes['valid']} valid / {sizes['test']} test sequences of {s['num_steps']} steps
  under random spline controls ({tm['data']:.1f} s).
- GN: latent {cfg.gn.latent}, edge MLP {list(cfg.gn.edge_hidden)}, node MLP {list(cfg.gn.node_hidden)},
  {g['steps']} steps of {cfg.batch_size} graphs in {g['seconds']:.0f} s ({g['steps_per_second']:.0f} steps/s;
  stop: {g['stop']}), best validation at step {g['best_step']}.
- MLP {cfg.mlp_size}: {m['steps']} steps in {m['seconds']:.0f} s ({m['steps_per_second']:.0f} steps/s),
  best at step {m['best_step']}.
- Adam, lr {cfg.lr:g} x{cfg.lr_decay:g} every {cfg.lr_decay_every} steps, gradient clipping,
  input noise std {cfg.noise_std:g}. (The paper trains for days at lr 1e-4; this is a short run.)
- Total time: {tm['total']:.0f} s (data {tm['data']:.0f}, GN {tm['train_gn']:.0f}, MLP {tm['train_mlp']:.0f},
  evaluation {tm['evaluate']:.0f}, plots {tm['plots']:.0f}).

## Errors

{table}
Errors are squared differences averaged over bodies, steps and test sequences, per state group,
divided by those of predicting the initial state unchanged; "n/a" marks groups that baseline gets
exactly right (the pendulum's body frame sits on its hinge, so its position never changes).

![errors](errors.png)

## A 100-step rollout

![states](states.png)

![rollouts](rollouts.gif)

(One row per test rollout; columns: true, GN, MLP when rendered with MuJoCo; grey true
under the coloured predictions when drawn with matplotlib.)

## Training

![training](training.png)

Checkpoints: `gn/best`, `mlp/best` (load with `gnwarp.load_model(path)`); logs: `gn/log.csv`, `mlp/log.csv`.
"""
