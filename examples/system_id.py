"""System identification (paper D.2, Algorithm D.4): on parameterized Pendulum data (each sequence
its own length and mass), a recurrent GN reads a window of states and controls and infers a latent
static graph G_ID, which the forward model then reads in place of the true parameters.

    python examples/system_id.py --out /tmp/gnwarp-sysid --steps 40
"""
import argparse
from pathlib import Path

import torch

from gnwarp import TrainConfig, data
from gnwarp.eval.sysid import sysid_rollout_error
from gnwarp.models import GNCoreConfig, ModelConfig, RecurrentGNConfig, SysIDConfig
from gnwarp.train import SysIDTrainer, load_sysid

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default="gnwarp-sysid", help="output folder (default: %(default)s)")
ap.add_argument("--sequences", type=int, default=24, help="sequences simulated (default: %(default)s)")
ap.add_argument("--steps", type=int, default=40, help="training steps (default: %(default)s)")
args = ap.parse_args()
out = Path(args.out)
W = 5   # identification window (the paper: 20 steps)

ds = data.generate("pendulum", num_sequences=args.sequences, num_steps=30, seed=0, parameterized=True,
                   progress=False)
tiny = GNCoreConfig(latent=16, edge_hidden=(32,), node_hidden=(32,), global_hidden=(32,))
gn_p = RecurrentGNConfig(latent=16, edge_mlp=(32,), node_mlp=(32,), global_mlp=(32,))
cfg = TrainConfig(out=str(out), model=ModelConfig(gn=tiny), steps=args.steps, lr=3e-3,
                  valid_every=args.steps, checkpoint_every=args.steps, valid_sequences=2,
                  resume=False, progress=False)
summary = SysIDTrainer(cfg, SysIDConfig(identifier=gn_p, window=W), datasets=[ds]).run()

model = load_sysid(summary["best"]).bind(ds)
test = ds["test"].load()
body, ctrl, inst = (torch.as_tensor(a) for a in (test.body, test.ctrl, test.instance))
with torch.no_grad():
    g_id = model.identify(body[:, :W], ctrl[:, :W], inst)              # G_ID from each test window
    traj = model.rollout(body[:, W], ctrl[:, W:W + 10], g_id, inst)   # 10 steps after the window
print("G_ID globals:", None if g_id.globals is None else tuple(g_id.globals.shape), "rollout:", tuple(traj.shape))
print("10-step sysid error:", sysid_rollout_error(model, ds, "test", 10))
