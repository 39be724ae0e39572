"""Probe: how fast an RL policy's squashed output saturates (tanh's flat ends, where its gradient
vanishes), GN networks against MLPs, with and without ``squash_penalty``.

The 4 x H100 sweep's GN policies (swimmer6, spinningup preset) sat at the action bounds from the
first round and stopped changing (``bench/results/rl/README.md``). Here, on any device: random-
action swimmer6 data (MuJoCo C, ``--envs`` x 1000 steps), then ``--updates`` SVG(0) updates of
each variant on the same replay data, and every ``--every`` updates the policy's unbounded output
``u`` on a fixed batch of replay observations: its median |u|, the share of actions with
|tanh(u)| > 0.99 (``saturated``) and the mean of tanh's derivative 1 - tanh(u)^2 (what the policy
gradient is multiplied by). Rows (JSON lines) to ``--out``.

    python bench/probes/rl_saturation.py [--variants gn,gn-penalty,mlp] [--updates 3000] [--device cpu]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from gnwarp.control.vector_env import make_vector_env  # noqa: E402
from gnwarp.rl.config import RLConfig  # noqa: E402
from gnwarp.rl.replay import ReplayBuffer  # noqa: E402
from gnwarp.rl.run import build_agent, check_task, observation_of  # noqa: E402

VARIANTS = {"gn": dict(networks="gn", gn_impl="torch"),
            "gn-penalty": dict(networks="gn", gn_impl="torch", agent_settings={"squash_penalty": 1e-3}),
            "mlp": dict(networks="mlp")}


def random_data(task, obs_fn, envs: int, seed: int, dev: torch.device):
    env = make_vector_env(task, envs, backend="mujoco", output="torch", observation=obs_fn)
    try:
        D, space = env.single_observation_space.shape[0], env.single_action_space
        buf = ReplayBuffer(envs * 1000, D, space.shape[0], num_envs=envs, device=dev)
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        for _ in range(1000):
            a = rng.uniform(space.low, space.high, (envs, space.shape[0])).astype(np.float32)
            nxt, r, term, trunc, _ = env.step(torch.as_tensor(a))   # one episode an env: no reset
            buf.add(obs, a, r, nxt, term, trunc)
            obs = nxt
        return buf, D, space
    finally:
        env.close()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default="gn,gn-penalty,mlp")
    ap.add_argument("--updates", type=int, default=3000)
    ap.add_argument("--every", type=int, default=250)
    ap.add_argument("--envs", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None, help="JSON lines appended here (default: print only)")
    a = ap.parse_args(argv)
    dev = torch.device(a.device)
    base = dict(task="swimmer6", agent="svg0", preset="spinningup", seed=a.seed, device=a.device, out="unused")
    cfg0 = RLConfig.from_dict(base)
    task = check_task(cfg0)
    obs_fn = observation_of(cfg0, task)
    buf, D, space = random_data(task, obs_fn, a.envs, a.seed, dev)
    for name in a.variants.split(","):
        cfg = RLConfig.from_dict({**base, **VARIANTS[name]})
        agent, _ = build_agent(cfg, task, obs_fn, D, space.low, space.high, dev)
        gen = torch.Generator(dev).manual_seed(a.seed)
        probe = buf.sample(256, gen).obs
        t0 = time.perf_counter()
        for k in range(a.updates + 1):
            if k % a.every == 0:
                with torch.no_grad():
                    u = agent.policy_output(probe)
                t = torch.tanh(u)
                row = dict(variant=name, updates=k, median_abs_u=round(float(u.abs().median()), 4),
                           saturated=round(float((t.abs() > 0.99).float().mean()), 4),
                           tanh_grad=float((1 - t * t).mean()), seconds=round(time.perf_counter() - t0, 1),
                           device=a.device, envs=a.envs, seed=a.seed)
                print(json.dumps(row), flush=True)
                if a.out:
                    with open(a.out, "a") as f:
                        f.write(json.dumps(row) + "\n")
            if k < a.updates:
                agent.update(buf.sample(cfg.batch_size or 100, gen))


if __name__ == "__main__":
    main()
