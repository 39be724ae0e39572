"""Why SVG(1) and SVG(0) learn alike on swimmer6: their policy gradients at the states a trained
agent visits, against the gradient SVG(1) would follow through the true simulator.

SVG(1) ascends J(a) = r(x, a, x') + gamma Q(x', pi(x')) in the action a, with x' the learned
model's prediction m(x, a) (``SVG.policy_objective``); SVG(0) ascends Q(x, a). With x' the true
simulator's next observation f(x, a) instead (MuJoCo C, reset to the visited state and stepped
once), J's action gradient is the one SVG(1) would follow with a perfect model. Per state, at the
policy's mean action (no exploration noise):

- ``g_model``: dJ/da through the learned model (autograd);
- ``g_true``: dJ/da through the true simulator: central differences of J over each action
  component (one-sided at the action box's bounds), each J from one control step of MuJoCo C;
- ``g_zero``: dQ(x, a)/da (SVG(0));
- ``g_model_fd``: the learned model's J differenced as ``g_true`` is: the differences' own error
  (against ``g_model``), measured in the same run.

The cosines between them say whose direction SVG(1)'s model gradient follows: the true one's
(the model informs the update), the critic's dQ/da (the Q-term dominates and the model adds
little), or neither. ``g_zero`` is the agent's own critic's (trained by SVG(1)'s updates): the
direction SVG(0)'s update would take with that critic, not a trained SVG(0) agent's. Also the
model's one-step error there: |m(x, a) - f(x, a)| / |f(x, a) - x|.

    PYTHONPATH=. python3 bench/rl_gradients.py bench/results/rl/agents/svg1-spinningup-mlp-s0 \\
        bench/results/rl/agents/svg1-spinningup-mlp-ahead-s10 --out bench/results/rl/gradients

writes ``records.jsonl`` (one record per agent: per-state cosines and norms) and ``README.md``
(means with 95% t intervals over the states) in ``--out``; ``--summarize`` only rewrites the
README from the records. CPU only (MuJoCo C)."""
from __future__ import annotations

import argparse
import dataclasses
import json
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
PAIRS = (("g_model", "g_true"), ("g_zero", "g_true"), ("g_model", "g_zero"), ("g_model_fd", "g_model"))


def visited_states(agent, env, steps: int, every: int, seed: int) -> dict[str, torch.Tensor]:
    """Observations, qpos, qvel, targets and the world of each (``world``: the states of one world
    lie along one trajectory, so they are not independent) of ``env``'s worlds every ``every``
    control steps of ``steps``, the agent acting as in training (exploring, counting no env steps)."""
    obs, _ = env.reset(seed=seed)
    kept = {"obs": [], "qpos": [], "qvel": [], "targets": [], "world": []}
    for t in range(1, steps + 1):
        with torch.no_grad():
            a = agent.act(obs, deterministic=False, count=False)
        obs, _, _, _, _ = env.step(a)
        if t % every == 0:
            sim = env.observe()
            kept["obs"].append(obs.clone())
            kept["world"].append(torch.arange(obs.shape[0]))
            kept["qpos"].append(torch.as_tensor(sim.qpos).double().clone())
            kept["qvel"].append(torch.as_tensor(sim.qvel).double().clone())
            if env.targets is not None:
                kept["targets"].append(env.targets.clone())
    return {k: torch.cat(v) for k, v in kept.items() if v}


def _lookahead(agent, obs, action, next_obs) -> torch.Tensor:
    """J [B] = r(x, a, x') + gamma Q(x', squash(mean(x'))): SVG(1)'s objective at the mean actions."""
    a2 = agent.squash(agent.policy(next_obs)[0])
    return agent.reward(obs, action, next_obs) + agent.settings.gamma * agent.q(next_obs, a2)


def true_next(env, states: dict, rows: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The true next observations [M, D] of the visited states ``rows`` [M] under ``actions``
    [M, U], ``env`` holding M worlds: each reset to its state and stepped once."""
    opts = {"qpos": states["qpos"][rows], "qvel": states["qvel"][rows]}
    if "targets" in states:
        opts["targets"] = states["targets"][rows]
    env.reset(options=opts)
    obs, _, _, _, _ = env.step(actions)
    return obs


def action_gradients(agent, states: dict, next_fn, h: float = 1e-2) -> dict[str, torch.Tensor]:
    """``g_model``, ``g_true``, ``g_zero``, ``g_model_fd`` [B, U] (module docstring) and the
    model's relative one-step error [B] at ``states``' observations, at the policy's mean actions;
    ``next_fn(rows, actions) -> next obs`` steps the true simulator (``true_next``)."""
    x = states["obs"]
    B = x.shape[0]
    with torch.no_grad():
        a = agent.squash(agent.policy(x)[0])
    low, high = agent.low.expand_as(a), agent.high.expand_as(a)
    U = a.shape[1]
    a_req = a.clone().requires_grad_(True)
    (g_model,) = torch.autograd.grad(_lookahead(agent, x, a_req, agent.model(x, a_req)).sum(), a_req)
    a_req = a.clone().requires_grad_(True)
    (g_zero,) = torch.autograd.grad(agent.q(x, a_req).sum(), a_req)
    # central differences, one-sided at the bounds: 2U perturbed actions a state
    hi_a, lo_a = [], []
    for j in range(U):
        e = torch.zeros_like(a)
        e[:, j] = h
        hi_a.append(torch.minimum(a + e, high))
        lo_a.append(torch.maximum(a - e, low))
    pert = torch.cat(hi_a + lo_a)                       # [2U B, U]: hi of component 0..U-1, then lo
    rows = torch.arange(B).repeat(2 * U)
    xs = x[rows]
    with torch.no_grad():
        nxt_true = next_fn(rows, pert)
        j_true = _lookahead(agent, xs, pert, nxt_true).reshape(2, U, B)
        j_model = _lookahead(agent, xs, pert, agent.model(xs, pert)).reshape(2, U, B)
        base_true = next_fn(torch.arange(B), a)
        model_err = (agent.model(x, a) - base_true).norm(dim=1) / (base_true - x).norm(dim=1).clamp_min(1e-12)
    step = (torch.stack(hi_a) - torch.stack(lo_a)).diagonal(dim1=0, dim2=2)   # [B, U]: hi_j - lo_j
    g_true = (j_true[0] - j_true[1]).T / step
    g_model_fd = (j_model[0] - j_model[1]).T / step
    return dict(g_model=g_model, g_true=g_true, g_zero=g_zero, g_model_fd=g_model_fd, model_error=model_err)


def cosines(g: dict) -> dict[str, list[float]]:
    """Per-state cosines of the ``PAIRS`` and the gradients' norms."""
    out = {}
    for p, q in PAIRS:
        out[f"cos_{p}_{q}"] = torch.nn.functional.cosine_similarity(g[p], g[q], dim=1).tolist()
    for k in ("g_model", "g_true", "g_zero"):
        out[f"norm_{k}"] = g[k].norm(dim=1).tolist()
    out["model_error"] = g["model_error"].tolist()
    return out


def measure(folder: Path, envs: int, steps: int, every: int, h: float, seed: int, threads: int) -> dict:
    """One agent's record: its visited states, gradients and their per-state comparisons."""
    from gnwarp.rl.run import check_task, evaluation_env, load_agent
    agent, cfg, obs_fn = load_agent(folder, "cpu")
    if getattr(agent, "horizon", 0) != 1:
        raise SystemExit(f"{folder}: agent {cfg.agent}: SVG(1) only (its objective is one model step; SVG(0) and "
                         "DDPG have no model, SVG(N > 1) looks further)")
    task = check_task(cfg)

    def worlds(n: int):   # n worlds of the run's task and observation on MuJoCo C, whatever it trained on
        return evaluation_env(dataclasses.replace(cfg, eval_episodes=n, backend="mujoco", sim_threads=threads),
                              task, obs_fn)
    env = worlds(envs)
    try:
        states = visited_states(agent, env, steps, every, seed)
    finally:
        env.close()
    B, U = states["obs"].shape[0], agent.action_dim
    pool = {}

    def next_fn(rows, actions):
        n = rows.numel()
        if n not in pool:
            pool[n] = worlds(n)
        return true_next(pool[n], states, rows, actions)
    try:
        g = action_gradients(agent, states, next_fn, h)
    finally:
        for e in pool.values():
            e.close()
    return dict(agent=folder.name, task=task.name, agent_kind=cfg.agent, env_steps=agent.env_steps, states=B,
                actions=U, h=h, seed=seed, visited=dict(envs=envs, steps=steps, every=every),
                world=states["world"].tolist(), machine=device_name(torch.device("cpu")),
                date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                **cosines(g))


def _mean_ci(v, world) -> tuple[float, float, float]:
    """The mean of per-state values ``v`` and its 95% interval over the worlds: each world's
    states (one trajectory) averaged first, Student's t over the world means."""
    x, w = np.asarray(v, dtype=np.float64), np.asarray(world)
    ok = np.isfinite(x)
    means = np.asarray([x[ok & (w == k)].mean() for k in np.unique(w[ok])])
    m = float(means.mean())
    if means.size < 2:
        return m, float("nan"), float("nan")
    half = t_quantile(means.size - 1) * float(means.std(ddof=1)) / math.sqrt(means.size)
    return m, m - half, m + half


def table(records: list[dict]) -> list[str]:
    """The README's table: per agent, each cosine's and ratio's mean with its 95% t interval."""
    head = ["agent", "task", "env steps", "states (worlds)", "h", "cos(model, true)", "cos(critic, true)",
            "cos(model, true) - cos(critic, true)", "cos(model, critic)", "cos(model FD, model)",
            "|true| / |critic|", "model error"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        ratio = np.asarray(r["norm_g_true"]) / np.maximum(np.asarray(r["norm_g_zero"]), 1e-12)
        world = r["world"]
        cells = [r["agent"], r["task"].replace("dmc-", ""), f"{r['env_steps'] / 1000:.0f}k",
                 f"{r['states']} ({len(set(world))})", f"{r['h']:g}"]
        gain = np.asarray(r["cos_g_model_g_true"]) - np.asarray(r["cos_g_zero_g_true"])
        for v in (r["cos_g_model_g_true"], r["cos_g_zero_g_true"], gain, r["cos_g_model_g_zero"],
                  r["cos_g_model_fd_g_model"]):
            m, lo, hi = _mean_ci(v, world)
            cells.append(f"{m:+.2f} [{lo:+.2f}, {hi:+.2f}]" if v is gain else f"{m:.2f} [{lo:.2f}, {hi:.2f}]")
        cells.append(f"{np.median(ratio):.2f} (median)")
        cells.append(f"{np.median(r['model_error']):.2f} (median)")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def write_readme(out: Path) -> Path:
    records = read_rows(out / RECORDS)
    text = "\n".join([
        "# SVG(1)'s policy gradient: learned model, true simulator, SVG(0)", "",
        "Generated by `bench/rl_gradients.py` from [records.jsonl](records.jsonl) (do not edit; its docstring",
        "defines every column). Per agent: states visited by the agent acting as in training (exploring), on",
        "MuJoCo C; at each, the policy's mean action; the action gradients of SVG(1)'s objective",
        "r(x, a, x') + gamma Q(x', pi(x')) through the learned model (model) and through the true simulator",
        "(true: central differences of one MuJoCo C control step), and of the agent's own critic Q(x, a)",
        "(critic: the direction SVG(0)'s update takes with this critic; no SVG(0) agent is measured); means",
        "of the per-state cosines (and of the per-state difference of the first two) with 95% t intervals",
        "over the worlds (each world's states, one trajectory, averaged first); \"cos(model FD, model)\"",
        "checks the differences' own error on the learned model.", "", *table(records), ""])
    with atomic_write(out / "README.md") as tmp:
        Path(tmp).write_text(text)
    return out / "README.md"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("agents", nargs="*", type=Path, help="folders of trained SVG(1) agents (agent.pt or a run)")
    p.add_argument("--envs", type=int, default=16, help="worlds run to visit states")
    p.add_argument("--steps", type=int, default=400, help="control steps each world runs")
    p.add_argument("--every", type=int, default=25, help="keep the states of every this many steps")
    p.add_argument("--h", type=float, default=1e-2, help="finite-difference step of an action component")
    p.add_argument("--seed", type=int, default=0, help="reset seed of the visiting worlds")
    p.add_argument("--threads", type=int, default=1, help="MuJoCo C threads")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "rl" / "gradients")
    p.add_argument("--summarize", action="store_true", help="only rewrite README.md from the records")
    a = p.parse_args(argv)
    if not a.summarize:
        if not a.agents:
            p.error("give at least one agent folder (or --summarize)")
        if a.h <= 0 or a.every < 1 or a.steps < a.every or a.envs < 1:
            p.error("--h > 0, --every >= 1, --steps >= --every and --envs >= 1")
        torch.set_num_threads(max(1, a.threads))
        recs = [measure(f, a.envs, a.steps, a.every, a.h, a.seed, a.threads) for f in a.agents]
        a.out.mkdir(parents=True, exist_ok=True)
        replace_rows(a.out / RECORDS, recs,   # a record measured again replaces the earlier one
                     lambda r: (r["agent"], r["h"], r["seed"], json.dumps(r["visited"], sort_keys=True)))
    print(f"wrote {write_readme(a.out)}")
    print("\n".join(table(read_rows(a.out / RECORDS))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
