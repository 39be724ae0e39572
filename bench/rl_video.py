"""A GIF of a trained ``gnwarp rl`` agent on the true simulator (MuJoCo C), from its run folder or
an ``export_agent`` folder: ``--episodes`` deterministic-policy episodes side by side (initial
states and targets of ``--seed``), ``--steps`` control steps each, at most ``--fps`` frames a
second of simulated time; the episodes' returns (and a position task's targets) are printed and
written beside the GIF (``<gif>.json``), so that what the video shows is on record. A position
target (swimmer6's) is drawn as a red circle by the matplotlib renderer, which "auto" then
picks; "mujoco" draws none.

    PYTHONPATH=. python3 bench/rl_video.py bench/results/rl/agents/svg1-spinningup-mlp-s0 \\
        --out bench/results/rl/svg1_swimmer6.gif --episodes 3 --fps 4 --renderer matplotlib
    PYTHONPATH=. python3 bench/rl_video.py RUN --out /tmp/v.gif --steps 20 --renderer matplotlib   # quick
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

__all__ = ["main"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a gnwarp rl run folder or an export_agent folder")
    ap.add_argument("--out", required=True, help="the GIF to write")
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--steps", type=int, default=1000, help="control steps of each episode shown")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fps", type=float, default=8.0, help="frames a second of simulated time, at most")
    ap.add_argument("--renderer", default="auto", choices=("auto", "mujoco", "matplotlib"))
    a = ap.parse_args(argv)
    if a.episodes < 1 or a.steps < 1 or a.fps <= 0:
        ap.error("--episodes and --steps must be >= 1 and --fps > 0")
    import numpy as np

    from gnwarp.control.vector_env import make_vector_env
    from gnwarp.files import atomic_write
    from gnwarp.rl.run import check_task, evaluate_policy, load_agent, write_video
    agent, cfg, obs_fn = load_agent(a.run, "cpu")
    task = check_task(cfg)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from gnwarp.eval.video import check_video_path
    check_video_path(out)   # a format it can write: before the episodes, not after
    env = make_vector_env(task, a.episodes, backend="mujoco", episode_steps=a.steps, output="torch",
                          observation=obs_fn, seed=a.seed)
    try:
        returns, states = evaluate_policy(agent, env, a.seed, keep=a.episodes)
        title = (f"{cfg.agent} {task.name} after {agent.env_steps} env steps; returns "
                 + ", ".join(f"{r:.0f}" for r in returns) + f" over {a.steps} steps")
        # a task's world-point targets (swimmer6's): recorded always, drawn by matplotlib ("auto" picks it)
        points = (env.targets[:a.episodes].double().cpu().numpy()
                  if task.target == "position" and env.targets is not None else None)
        write_video(out, states, env.system, title, a.renderer, fps_max=a.fps,
                    marks=points if a.renderer != "mujoco" else None)
    finally:
        env.close()
    info = dict(run=str(a.run), task=task.name, agent=cfg.agent, env_steps=agent.env_steps, seed=a.seed,
                steps=a.steps, returns=[float(r) for r in np.asarray(returns)], renderer=a.renderer, fps=a.fps,
                targets=points.round(4).tolist() if points is not None else None)
    with atomic_write(Path(str(out) + ".json")) as tmp:
        Path(tmp).write_text(json.dumps(info, indent=1) + "\n")
    print(f"wrote {out}: returns {', '.join(f'{r:.1f}' for r in info['returns'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
