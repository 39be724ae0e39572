"""Model-predictive control through a learned model (paper F.1.1): train a small Pendulum model,
then plan actions by gradient steps on the task reward of its rollouts and apply them, in closed
loop, on the true simulator (MuJoCo C here).

    python examples/mpc.py --out /tmp/gnwarp-mpc --steps 100
"""
import argparse
from pathlib import Path

import numpy as np

import gnwarp
from gnwarp import control, data, sim, systems
from gnwarp.models import GNCoreConfig
from gnwarp.train import train

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default="gnwarp-mpc", help="output folder (default: %(default)s)")
ap.add_argument("--steps", type=int, default=100, help="training steps (default: %(default)s)")
ap.add_argument("--episodes", type=int, default=2, help="episodes planned together (default: %(default)s)")
ap.add_argument("--control-steps", type=int, default=10, help="control steps per episode (default: %(default)s)")
args = ap.parse_args()
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)

ds = data.generate("pendulum", num_sequences=30, num_steps=40, seed=0, progress=False)
path = ds.save(out / "pendulum.h5", overwrite=True)
small = GNCoreConfig(latent=32, edge_hidden=(64,), node_hidden=(64,), global_hidden=(64,))
train(gnwarp.TrainConfig(data=[str(path)], out=str(out / "run"), steps=args.steps, lr=1e-3,
                         valid_every=args.steps, checkpoint_every=args.steps,
                         model=gnwarp.ModelConfig(gn=small), resume=False, progress=False))
model = gnwarp.load_model(out / "run" / "best")

pend = systems.make("pendulum")
n = args.episodes
env = sim.make_env(pend, n, backend="mujoco")                       # n true worlds, one episode each
planner = control.GradientMPC(model, "pendulum-balance", pend, n,
                              config=control.GradientMPCConfig(horizon=10, iterations=2, warmup=5))
qpos0, qvel0 = data.initial_states(pend, n, np.random.default_rng(0))     # random start states
result = control.run_episodes(planner, env, "pendulum-balance", steps=args.control_steps, qpos0=qpos0, qvel0=qvel0)
print("true returns:", result["returns"].tolist())
print("states:", tuple(result["states"].shape), "actions:", tuple(result["actions"].shape))
