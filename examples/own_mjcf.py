"""Your own MuJoCo model: load an MJCF file with ``systems.from_mjcf``, simulate a dataset on it and
train a forward model for a few steps (the same pipeline as the built-in systems).

    python examples/own_mjcf.py --out /tmp/gnwarp-mjcf --steps 50
"""
import argparse
from pathlib import Path

import gnwarp
from gnwarp import data, systems
from gnwarp.models import GNCoreConfig
from gnwarp.train import train

# a two-link arm with a motor at each hinge; any MJCF with joints and actuators works
MJCF = """
<mujoco model="arm">
  <option timestep="0.01"/>
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.04"/>
      <body name="lower" pos="0 0 -0.5">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.04"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="shoulder" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="elbow" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default="gnwarp-mjcf", help="output folder (default: %(default)s)")
ap.add_argument("--sequences", type=int, default=30, help="sequences simulated (default: %(default)s)")
ap.add_argument("--steps", type=int, default=50, help="training steps (default: %(default)s)")
args = ap.parse_args()
out = Path(args.out)
out.mkdir(parents=True, exist_ok=True)
(out / "arm.xml").write_text(MJCF)

arm = systems.from_mjcf(out / "arm.xml", dt=0.02, substeps=2)   # data every 20 ms, physics every 10 ms
print("bodies (world included):", arm.model.nbody, "actuators:", arm.model.nu)
ds = data.generate(arm, num_sequences=args.sequences, num_steps=40, seed=0, progress=False)
path = ds.save(out / "arm.h5", overwrite=True)      # the CLI: gnwarp generate --mjcf arm.xml -o arm.h5

small = GNCoreConfig(latent=32, edge_hidden=(64,), node_hidden=(64,), global_hidden=(64,))
summary = train(gnwarp.TrainConfig(data=[str(path)], out=str(out / "run"), steps=args.steps, lr=1e-3,
                                   valid_every=args.steps, checkpoint_every=args.steps,
                                   model=gnwarp.ModelConfig(gn=small), resume=False, progress=False))
print("best 20-step validation error:", summary["best_error"])
