"""Benchmark: gradient updates per second of the RL agents (``gnwarp.rl.agents``) with MLP or GN
networks, and actions per second of their policies, on one device.

Swimmer6's sizes (25 observation features, 5 actions); ``--networks mlp``: the spinningup preset's
256 x 2 MLPs (SVG(N)'s model a 256 x 2 MLP trained jointly, a stand-in for the GN model); ``gn``:
the GN policy, Q-function and model on swimmer6's observation graph (``gnwarp.rl.gn_nets``
defaults: 2 blocks, latent 64, Warp blocks), what ``gnwarp rl --networks gn`` trains. Per networks,
agent and batch size: a replay buffer of random transitions, then ``--updates`` updates, each
sampling its batch (updates / s, after a warm-up), three ways in the same process: ``eager``
(``agent.update(buffer.sample(...))``), ``updater`` (``gnwarp.rl.graphed.Updater`` uncaptured:
what ``--cuda-graph false`` runs) and ``graph`` (the same, recorded in a CUDA graph and replayed:
what ``gnwarp rl`` runs on CUDA; ``first_graph_s``: its first two calls, the eager one and the
recording, what a run waits for once); and ``act`` on ``--envs`` observations at a time (env
steps / s of the policy alone).

    python bench/rl_agents.py [--agents ddpg,svg0,svg1,svg2] [--batches 100,256] [--updates 500] [--networks mlp,gn]
                              [--compile inductor]   # and with the losses compiled (torch.compile)
    python bench/rl_agents.py --quick       # tiny sizes on the CPU: a smoke test of the script
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from torch import nn  # noqa: E402

from bench.harness import add_run_args, device_name, experiment_out, save_results  # noqa: E402
from gnwarp.rl.agents import make_agent  # noqa: E402
from gnwarp.rl.graphed import Updater  # noqa: E402
from gnwarp.rl.networks import mlp  # noqa: E402
from gnwarp.rl.replay import ReplayBuffer  # noqa: E402
from gnwarp.rl.settings import AgentSettings  # noqa: E402

OBS, ACT = 25, 5   # DMC swimmer6: to_target 2, joints 5, body velocities 6 x 3; 5 joint forces


class MLPModel(nn.Module):
    """``next_obs = obs + mlp([obs, action])``: a stand-in for the learned model."""

    def __init__(self, hidden):
        super().__init__()
        self.net = mlp(OBS + ACT, hidden, OBS)

    def forward(self, obs, action):
        return obs + self.net(torch.cat([obs, action], -1))


def reward(obs, action, next_obs):
    return -next_obs[:, :2].pow(2).sum(-1).sqrt()   # distance to the target


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def filled_buffer(dev, envs: int, steps: int, gen: torch.Generator) -> ReplayBuffer:
    buf = ReplayBuffer(envs * steps, OBS, ACT, num_envs=envs, device=dev)
    for t in range(steps):
        r = lambda *s: torch.randn(*s, generator=gen, device=dev)  # noqa: E731
        buf.add(r(envs, OBS), r(envs, ACT).clamp(-1, 1), r(envs), r(envs, OBS),
                torch.zeros(envs, dtype=torch.bool, device=dev),
                torch.full((envs,), (t + 1) % 1000 == 0, dtype=torch.bool, device=dev))
    return buf


def _make(name: str, batch: int, hidden, dev, networks: str = "mlp"):
    s = AgentSettings(agent=name, hidden=hidden, batch_size=batch, start_steps=0)
    nets = {}
    if networks == "gn":   # the paper's setting: policy, Q and model on the observation graph (Warp blocks)
        from gnwarp.rl.gn_nets import GNObservationModel, make_networks
        from gnwarp.rl.obs_graph import ObservationGraph
        og = ObservationGraph("swimmer6")
        policy, q = make_networks("gn", og, gaussian=s.kind == "svg")
        nets = dict(policy=policy, q=q)
        model = GNObservationModel(og).to(dev) if s.horizon else None
    else:
        model = MLPModel(hidden).to(dev) if s.horizon else None
    return make_agent(s, OBS, [-1.0] * ACT, [1.0] * ACT, model=model, reward=reward if model else None, device=dev,
                      **nets)


def _rate(step, updates: int, dev) -> float:
    """Updates per second of ``step(n)`` doing n updates, after 5 warm-up updates."""
    step(5)
    _sync(dev)
    t0 = time.perf_counter()
    step(updates)
    _sync(dev)
    return updates / (time.perf_counter() - t0)


def time_agent(name: str, batch: int, hidden, dev, buf, updates: int, envs: int, networks: str = "mlp",
               compile_backend: str | None = None) -> dict:
    gen = torch.Generator(dev).manual_seed(0)
    agent = _make(name, batch, hidden, dev, networks)
    out = {}

    def eager(n):
        for _ in range(n):
            out["m"] = agent.update(buf.sample(batch, gen))
    ups = _rate(eager, updates, dev)
    updater = Updater(_make(name, batch, hidden, dev, networks), buf, gen, capture=False)
    ups_updater = _rate(updater.run, updates, dev)
    ups_graph = first_graph = None
    if dev.type == "cuda":
        graphed = Updater(_make(name, batch, hidden, dev, networks), buf, gen, capture=True)
        t0 = time.perf_counter()
        graphed.run(2)
        _sync(dev)
        first_graph = time.perf_counter() - t0
        ups_graph = _rate(graphed.run, updates, dev)
        assert graphed.captured
    ups_comp = first_comp = None
    if compile_backend:   # the losses compiled (Agent.compile_update), recorded in the graph on CUDA
        torch._dynamo.reset()   # each row compiles afresh (else past the recompile limit it would run eagerly)
        ag = _make(name, batch, hidden, dev, networks)
        ag.compile_update(compile_backend)
        comp = Updater(ag, buf, gen, capture=dev.type == "cuda")
        t0 = time.perf_counter()
        comp.run(3)   # eager, compiling, recording
        _sync(dev)
        first_comp = time.perf_counter() - t0
        ups_comp = _rate(comp.run, updates, dev)
    m = out["m"]
    obs = torch.randn(envs, OBS, device=dev)
    for _ in range(3):
        agent.act(obs)
    _sync(dev)
    t0 = time.perf_counter()
    for _ in range(updates):
        agent.act(obs)
    _sync(dev)
    aps = envs * updates / (time.perf_counter() - t0)
    assert all(torch.isfinite(v) for v in m.values()), m
    r = lambda v, k=1: None if v is None else round(v, k)  # noqa: E731
    return dict(agent=name, networks=networks, batch=batch, hidden=list(hidden) if networks == "mlp" else None,
                updates=updates, updates_per_s=round(ups, 1),
                updater_updates_per_s=round(ups_updater, 1), graph_updates_per_s=r(ups_graph),
                graph_speedup=r(ups_graph and ups_graph / ups, 2), first_graph_s=r(first_graph, 3),
                compile_backend=compile_backend, compiled_updates_per_s=r(ups_comp),
                compiled_speedup=r(ups_comp and ups_comp / (ups_graph or ups_updater), 2),
                first_compiled_s=r(first_comp, 2),
                envs=envs, act_env_steps_per_s=round(aps))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agents", default="ddpg,svg0,svg1,svg2")
    ap.add_argument("--batches", default="100,256")
    ap.add_argument("--updates", type=int, default=500)
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--networks", default="mlp", help="mlp, gn, or mlp,gn: GN policy, Q and model on "
                                                         "swimmer6's observation graph, Warp blocks")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--compile", default=None, choices=("inductor", "aot_eager"),
                    help="also time the updates with their losses compiled by torch.compile (this backend), "
                         "recorded in the CUDA graph on CUDA")
    add_run_args(ap, "rl")   # --out, --quick
    args = ap.parse_args(argv)
    if not args.networks.split(",") or set(args.networks.split(",")) - {"mlp", "gn"}:
        ap.error(f"--networks: mlp, gn, or mlp,gn, got {args.networks!r}")
    hidden = (256, 256)
    if args.quick:
        args.device, args.batches, args.updates, hidden = "cpu", "16", 5, (16, 16)
    dev = torch.device(args.device)
    gen = torch.Generator(dev).manual_seed(0)
    buf = filled_buffer(dev, args.envs, 64 if args.quick else 4096, gen)
    name, rows = device_name(dev), []
    for networks, agent, batch in itertools.product(args.networks.split(","), args.agents.split(","),
                                                    (int(b) for b in args.batches.split(","))):
        row = dict(device=name, **time_agent(agent, batch, hidden, dev, buf, args.updates, args.envs, networks,
                                             args.compile))
        rows.append(row)
        print(json.dumps(row), flush=True)
    lines = [f"# RL agents: gradient updates per second, on {name}", "",
             f"`python bench/rl_agents.py` ({time.strftime('%Y-%m-%d')}): swimmer6 sizes ({OBS} observations, "
             f"{ACT} actions); mlp: MLPs {'x'.join(map(str, hidden))}, SVG(N)'s model an MLP of the same widths "
             "trained jointly; gn: GN policy, Q and model on the observation graph (2 blocks, latent 64); each update samples its batch from the replay buffer; acting: "
             f"`act` on {args.envs} observations.", "",
             "| agent | networks | batch | updates / s, eager | Updater uncaptured | CUDA graph | graph / eager "
             "| first two graph updates (s) | compiled losses | compiled / graph | first three compiled updates (s) "
             "| acting, env steps / s |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['agent']} | {r['networks']} | {r['batch']} | {r['updates_per_s']} | {r['updater_updates_per_s']} | "
              f"{r['graph_updates_per_s'] or '-'} | {r['graph_speedup'] or '-'} | {r['first_graph_s'] or '-'} | "
              f"{r['compiled_updates_per_s'] or '-'} | {r['compiled_speedup'] or '-'} | {r['first_compiled_s'] or '-'} | "
              f"{r['act_env_steps_per_s']} |" for r in rows]
    if args.compile:
        lines += ["", f"Compiled losses: `Agent.compile_update(\"{args.compile}\")`; compiled / graph: against the "
                      "CUDA-graph column (uncaptured on a CPU)."]
    save_results(experiment_out("rl", args.out, args.quick), "rl_agents", name, args.quick, rows, lines)


if __name__ == "__main__":
    main()
