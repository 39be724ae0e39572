"""Swimmer6: how a trained agent approaches its targets over an episode, near ones and far ones.

Swimmer6 agents here seldom reach a target that starts more than ~1.25 m from the nose and almost
never one past ~1.6 m (``rl/README.md``, ``rl-reach``). Two reasons would look alike in the returns: the agent
heads for a far target but swims too slowly to get there in the episode's 30 s, or it does not
head for it at all. This runs the agent's deterministic policy on MuJoCo C from the evaluation
states of ``--eval-seed`` (those ``gnwarp rl`` evaluates from with that ``eval_seed``) and records
the nose-to-target distance (the norm of the observation's ``to_target``) every ``--every``
control steps; per episode: the distance at the start, its least and its last value, the return,
whether the nose came within the target's radius, and its fastest approach: the largest fall of
the distance over any ``--window`` seconds, divided by them (an agent swimming for its target
shows its swimming speed; one that holds still, ~0).

    PYTHONPATH=. python3 bench/rl_approach.py bench/results/rl/agents/svg1-spinningup-mlp-ahead-s10 \\
        --out bench/results/rl/approach

writes ``records.jsonl`` (one record per agent, the per-episode numbers and distance series),
``README.md`` (near against far targets: means with 95% t intervals over the episodes) and
``approach_swimmer6.png`` (distance against time, coloured by the starting distance) in ``--out``;
``--summarize`` only rewrites README.md and the plot from the records. CPU (MuJoCo C)."""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.harness import device_name, read_rows, replace_rows  # noqa: E402
from gnwarp.eval.summarize import t_quantile  # noqa: E402
from gnwarp.files import atomic_write  # noqa: E402

RECORDS = "records.jsonl"
NEAR = 1.25   # m: as bench/results_tables.py's stratification
CLOSE = 0.75   # m: nearer targets are reached before a window of approach shows the swimming speed


def approach(folder: Path, episodes: int, eval_seed: int, steps: int | None, every: int, window: float,
             threads: int = 1) -> dict:
    """One agent's record (module docstring)."""
    import mujoco

    from gnwarp.rl.run import check_task, eval_reset_seed, evaluation_env, load_agent
    agent, cfg, obs_fn = load_agent(folder, "cpu")
    task = check_task(cfg)
    if task.name != "dmc-swimmer-swimmer6" or "to_target" not in getattr(obs_fn, "parts", {}):
        raise SystemExit(f"{folder}: a swimmer6 agent on the suite's observation is needed, got {task.name}")
    cfg = dataclasses.replace(cfg, eval_episodes=episodes, eval_seed=eval_seed, backend="mujoco", sim_threads=threads)
    env = evaluation_env(cfg, task, obs_fn)
    part = obs_fn.parts["to_target"]
    try:
        obs, _ = env.reset(seed=eval_reset_seed(cfg))
        T = env.episode_steps if steps is None else min(steps, env.episode_steps)
        dist, ret = [obs[:, part].norm(dim=1)], torch.zeros(episodes, dtype=torch.float64)
        for t in range(1, T + 1):
            with torch.no_grad():
                a = agent.act(obs, deterministic=True, count=False)
            obs, r, _, _, _ = env.step(a)
            ret += torch.as_tensor(r, dtype=torch.float64)
            if t % every == 0 or t == T:
                dist.append(obs[:, part].norm(dim=1))
        dt = float(env.dt)
    finally:
        env.close()
    d = torch.stack(dist, dim=1).double().numpy()          # [episodes, points]
    times = np.asarray([0.0] + [t * dt for t in range(1, T + 1) if t % every == 0 or t == T])
    speed, span = fastest_approach(d, times, window)
    m = obs_fn.system.model
    radius = float(m.geom_size[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "target"), 0])
    return dict(agent=folder.name, task=task.name, env_steps=agent.env_steps, eval_seed=eval_seed, episodes=episodes,
                steps=T, dt=dt, every=every, window=span, target_radius=radius,
                start=d[:, 0].tolist(), least=d.min(axis=1).tolist(), last=d[:, -1].tolist(),
                returns=ret.tolist(), reached=(d.min(axis=1) <= radius).tolist(),
                speed=speed.tolist(), times=times.tolist(),
                distance=d.round(4).tolist(),
                machine=device_name(torch.device("cpu")),
                date=datetime.now(timezone.utc).isoformat(timespec="seconds"))


def fastest_approach(d: np.ndarray, times: np.ndarray, window: float) -> tuple[np.ndarray, float]:
    """(per row of distances ``d`` [episodes, points] at ``times`` [points] (from 0, evenly spaced
    but for a last point that may come sooner): the largest fall of the distance between two
    points one span apart, divided by the span; the span: the most whole grid steps within
    ``window`` seconds, at least one). Pairs reaching the off-grid last point are left out."""
    k = max(1, int(np.searchsorted(times, window, side="right")) - 1)
    k = min(k, times.size - 1)
    on_grid = np.isclose(times[k:] - times[:-k], times[k])
    return (d[:, :-k] - d[:, k:])[:, on_grid].max(axis=1) / times[k], float(times[k])


def _mean_ci(v) -> str:
    x = np.asarray(v, dtype=np.float64)
    if x.size == 0:
        return "-"
    if x.size < 2:
        return f"{x.mean():.2f}"
    half = t_quantile(x.size - 1) * x.std(ddof=1) / math.sqrt(x.size)
    return f"{x.mean():.2f} [{x.mean() - half:.2f}, {x.mean() + half:.2f}]"


def table(records: list[dict]) -> list[str]:
    head = ["agent", "env steps", "targets", "episodes", "start (m)", "fastest approach over s (m/s)", "least (m)",
            "last (m)", "reached", "return"]
    windows = {r["window"] for r in records}
    if len(windows) > 1:
        raise SystemExit(f"records of different --window ({sorted(windows)}) in one table: measure again with one")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        start = np.asarray(r["start"])
        for name, m in ((f"< {CLOSE} m", start < CLOSE), (f"{CLOSE}-{NEAR} m", (start >= CLOSE) & (start < NEAR)),
                        (f">= {NEAR} m (far)", start >= NEAR)):
            pick = lambda k: np.asarray(r[k], dtype=np.float64)[m]   # noqa: E731
            lines.append("| " + " | ".join([
                r["agent"], f"{r['env_steps'] / 1000:.0f}k", name, str(int(m.sum())), _mean_ci(pick("start")),
                _mean_ci(pick("speed")), _mean_ci(pick("least")), _mean_ci(pick("last")),
                f"{int(np.asarray(r['reached'])[m].sum())} of {int(m.sum())}", _mean_ci(pick("returns"))]) + " |")
    lines[0] = lines[0].replace("over s", f"over {records[0]['window']:g} s" if records else "over s")
    return lines


def plot(records: list[dict], path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(records), figsize=(5.5 * len(records), 4), squeeze=False)
    cmap = plt.get_cmap("viridis")
    hi = max(max(r["start"]) for r in records)
    for ax, r in zip(axes[0], records):
        for s, d in zip(r["start"], r["distance"]):
            ax.plot(r["times"], d, color=cmap(s / hi), lw=0.9, alpha=0.8)
        ax.axhline(r["target_radius"], color="k", lw=0.6, ls=":")
        ax.set_title(f"{r['agent']} ({r['env_steps'] / 1000:.0f}k), eval_seed {r['eval_seed']}", fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("nose to target (m)")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, hi))
    fig.colorbar(sm, ax=axes[0].tolist(), label="distance at the start (m)")
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def write_outputs(out: Path) -> list[Path]:
    records = read_rows(out / RECORDS) if (out / RECORDS).exists() else []
    if not records:
        raise SystemExit(f"no records in {out / RECORDS}: measure an agent first")
    text = "\n".join([
        "# Swimmer6: how a trained agent approaches near and far targets", "",
        "Generated by `bench/rl_approach.py` from [records.jsonl](records.jsonl) (do not edit; its docstring",
        "defines the columns). Deterministic policy on MuJoCo C from the evaluation states of the records'",
        f"`eval_seed`, by the target's distance from the nose at the start (within {CLOSE} m the target is",
        "reached before a window of approach shows the swimming speed); means with 95% t intervals over the",
        "episodes; \"reached\": the nose within the target's radius at a recorded point. Machines: "
        + (", ".join(sorted({r.get("machine", "not recorded") for r in records}))) + ".", "",
        *table(records), "", "![distance against time](approach_swimmer6.png)", ""])
    with atomic_write(out / "README.md") as tmp:
        Path(tmp).write_text(text)
    return [out / "README.md", plot(records, out / "approach_swimmer6.png")]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("agents", nargs="*", type=Path, help="folders of trained swimmer6 agents (agent.pt or a run)")
    p.add_argument("--episodes", type=int, default=100, help="evaluation episodes (default 100)")
    p.add_argument("--eval-seed", type=int, default=2, help="their states: those of this eval_seed (default 2)")
    p.add_argument("--steps", type=int, default=None, help="control steps an episode (default: the task's)")
    p.add_argument("--every", type=int, default=10, help="record the distance every this many steps")
    p.add_argument("--window", type=float, default=5.0, help="seconds over which the fastest approach is taken")
    p.add_argument("--threads", type=int, default=1, help="MuJoCo C threads")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "rl" / "approach")
    p.add_argument("--summarize", action="store_true", help="only rewrite README.md and the plot from the records")
    a = p.parse_args(argv)
    if not a.summarize:
        if not a.agents:
            p.error("give at least one agent folder (or --summarize)")
        if a.episodes < 2 or a.every < 1 or a.window <= 0 or (a.steps is not None and a.steps < 1):
            p.error("--episodes >= 2, --every >= 1, --window > 0, --steps >= 1")
        recs = [approach(f, a.episodes, a.eval_seed, a.steps, a.every, a.window, a.threads) for f in a.agents]
        a.out.mkdir(parents=True, exist_ok=True)
        replace_rows(a.out / RECORDS, recs, lambda r: (r["agent"], r["eval_seed"], r["episodes"]))
    for f in write_outputs(a.out):
        print(f"wrote {f}")
    print("\n".join(table(read_rows(a.out / RECORDS))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
