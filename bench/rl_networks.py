"""Benchmark: the agents' networks on observation graphs (``gnwarp.rl.gn_nets``) against MLPs on
the flat observation: milliseconds of one actor-critic gradient step's network work and of one
action batch.

Per domain and batch size, for MLPs (``--mlp-hidden``), GN networks on the Warp kernels and the
same GN networks on the torch reference: "update" = a Gaussian policy's forward on B
observations, the Q-function on their reparameterized actions and on the replayed actions,
both losses' backward (SVG(0)'s network work, the optimizer excluded); "act" = the policy's
forward on N env observations under no_grad. Random observations (the speed does not depend on
the values).

    python bench/rl_networks.py [--domains swimmer6,cheetah] [--batches 256,1024] [--envs 64]
    python bench/rl_networks.py --quick       # tiny sizes on the CPU: a smoke test of the script
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.harness import add_run_args, device_name, experiment_out, median_ms, save_results  # noqa: E402
from gnwarp.rl.gn_nets import make_networks  # noqa: E402
from gnwarp.rl.obs_graph import ObservationGraph  # noqa: E402


def _kinds(args) -> list[tuple[str, str, dict]]:
    gn = dict(latent=args.latent, hidden=tuple(int(h) for h in args.gn_hidden.split(",")), blocks=args.blocks)
    return [("mlp", "mlp", dict(hidden=tuple(int(h) for h in args.mlp_hidden.split(",")))),
            ("gn", "gn-warp", dict(gn, impl="warp", precision=args.precision)),
            ("gn", "gn-torch", dict(gn, impl="torch", precision=args.precision))]


def measure(og: ObservationGraph, network: str, kw: dict, batch: int, envs: int, dev, reps: int, warmup: int):
    """(update ms, act ms, parameter count) of a (policy, Q) pair."""
    torch.manual_seed(0)
    policy, q = make_networks(network, og, gaussian=True, **kw)
    policy, q = policy.to(dev), q.to(dev)
    obs = torch.randn(batch, og.obs_size, device=dev)
    act = torch.rand(batch, og.nu, device=dev) * 2 - 1
    target = torch.randn(batch, device=dev)
    env_obs = torch.randn(envs, og.obs_size, device=dev)

    def update():
        mean, log_std = policy(obs)
        a = torch.tanh(mean + log_std.exp() * torch.randn_like(mean))
        policy_loss = -q(obs, a).mean()
        q_loss = (q(obs, act) - target).pow(2).mean()
        (policy_loss + q_loss).backward()

    def act_batch():
        with torch.no_grad():
            policy(env_obs)

    n_param = sum(p.numel() for p in list(policy.parameters()) + list(q.parameters()))
    return median_ms(update, dev, reps, warmup), median_ms(act_batch, dev, reps, warmup), n_param


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domains", default="swimmer6,cheetah")
    ap.add_argument("--batches", default="256,1024")
    ap.add_argument("--envs", type=int, default=64)
    ap.add_argument("--latent", type=int, default=64)
    ap.add_argument("--gn-hidden", default="64")
    ap.add_argument("--blocks", type=int, default=2)
    ap.add_argument("--mlp-hidden", default="256,256")
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--device", default="cuda")
    add_run_args(ap, "rl")   # --out, --quick
    args = ap.parse_args(argv)
    if args.quick:
        args.device, args.domains, args.batches, args.envs, args.reps = "cpu", "swimmer6", "8", 4, 3
        args.latent, args.gn_hidden, args.mlp_hidden = 8, "8", "16"
    dev = torch.device(args.device)
    name, rows = device_name(dev), []
    for domain in args.domains.split(","):
        og = ObservationGraph(domain)
        for b in (int(x) for x in args.batches.split(",")):
            for network, label, kw in _kinds(args):
                upd, act, n_param = measure(og, network, kw, b, args.envs, dev, args.reps, warmup=3)
                rows.append(dict(device=name, domain=domain, network=label, batch=b, envs=args.envs,
                                 update_ms=round(upd, 4), updates_per_s=round(1e3 / upd, 1), act_ms=round(act, 4),
                                 params=n_param, precision=args.precision))
                print(json.dumps(rows[-1]), flush=True)
    lines = [f"# Agent networks: observation-graph GNs against MLPs, on {name}", "",
             f"`python bench/rl_networks.py` ({time.strftime('%Y-%m-%d')}): Gaussian policy and Q-function; "
             f"update = SVG(0)'s forward and backward on a batch (no optimizer); act = the policy on {args.envs} "
             f"observations. GN: {args.blocks} blocks, latent {args.latent}, hidden {args.gn_hidden}; "
             f"MLP hidden {args.mlp_hidden}; {args.precision}.", "",
             "| domain | network | batch | update (ms) | updates / s | act (ms) | parameters |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['domain']} | {r['network']} | {r['batch']} | {r['update_ms']} | {r['updates_per_s']} | "
                     f"{r['act_ms']} | {r['params']} |")
    save_results(experiment_out("rl", args.out, args.quick), "rl_networks", name, args.quick, rows, lines)


if __name__ == "__main__":
    main()
