"""Quick start: simulate a tiny Pendulum dataset, train a small GN forward model for a few steps,
roll it out from the test sequences' first states and print its normalized errors.

    python examples/quickstart.py --out /tmp/gnwarp-quickstart --steps 200
"""
import argparse
from pathlib import Path

import torch

import gnwarp
from gnwarp import data
from gnwarp.eval.metrics import evaluate
from gnwarp.models import GNCoreConfig
from gnwarp.train import train

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default="gnwarp-quickstart", help="output folder (default: %(default)s)")
ap.add_argument("--sequences", type=int, default=40, help="sequences simulated (default: %(default)s)")
ap.add_argument("--steps", type=int, default=200, help="training steps (default: %(default)s)")
args = ap.parse_args()
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)

# 1. simulate: random spline controls, split train / valid / test in the paper's proportions
ds = data.generate("pendulum", num_sequences=args.sequences, num_steps=50, seed=0, progress=False)
path = ds.save(out / "pendulum.h5", overwrite=True)

# 2. train a small GN (the paper's core is latent 128, edge MLP 3x512: sized for a GPU)
small = GNCoreConfig(latent=32, edge_hidden=(64,), node_hidden=(64,), global_hidden=(64,))
cfg = gnwarp.TrainConfig(data=[str(path)], out=str(out / "run"), steps=args.steps, lr=1e-3,
                         valid_every=max(args.steps // 2, 1), checkpoint_every=max(args.steps // 2, 1),
                         model=gnwarp.ModelConfig(gn=small), resume=False, progress=False)
summary = train(cfg)

# 3. load the best checkpoint and roll it out under the test sequences' controls
model = gnwarp.load_model(out / "run" / "best").bind(ds)
test = ds["test"].load()
with torch.no_grad():
    traj = model.rollout(torch.as_tensor(test.body[:, 0]), torch.as_tensor(test.ctrl[:, :20]),
                         torch.as_tensor(test.instance))
print("rollout:", tuple(traj.shape), "[sequences, steps + 1, bodies, 13]")

# 4. errors normalized by the constant-prediction baseline (1 = no better than standing still)
errors = evaluate(model, ds, "test", horizons=(20,))
print(f"one-step error {errors['one_step']['mean']:.3g}, 20-step rollout error {errors['rollout_20']['mean']:.3g}")
