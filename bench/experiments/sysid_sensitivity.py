"""How precisely must system identification know the parameters? (issue 16, beyond the paper)

For each parameterized system, simulates test-like sequences (random instances, initial states
and spline controls, MuJoCo C), then re-simulates each from step W (the identification window's
end) with one parameter scaled by (1 + eps) under the same controls, and scores that "perfect
model with a parameter off by eps" exactly as Figure 8 scores learned models: squared error of
the (H = T - W)-step rollout normalized by the constant baseline's, mean over state groups.
A learned sysid model can only be as good as the parameter precision it reaches; this table
says which precision matches a given rollout error (e.g. the true-parameter model's).

    python bench/experiments/sysid_sensitivity.py --systems pendulum,cartpole
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import experiment_out  # noqa: E402


def sensitivity(system: str, sequences: int, steps: int, window: int, eps_list, seed: int) -> list[dict]:
    from gnwarp.data.generation import initial_states
    from gnwarp.eval.metrics import normalized_errors
    from gnwarp.sim import make
    from gnwarp.sim.backends import simulate
    from gnwarp.sim.excitation import control_range, random_spline_controls
    from gnwarp.sim.systems import param_ranges
    rng = np.random.default_rng(seed)
    systems = [make(system, seed=int(s)) for s in rng.integers(1 << 30, size=sequences)]
    q0, v0 = zip(*(initial_states(s, 1, rng) for s in systems))
    q0, v0 = np.concatenate(q0), np.concatenate(v0)
    ctrl = random_spline_controls(sequences, steps, control_range(systems[0].model), rng)
    tr = simulate(systems, q0, v0, ctrl, backend="mujoco")
    true = tr.body[:, window:]
    mask = np.ones((sequences, true.shape[2]), bool)
    mask[:, 0] = False      # the world body
    const = np.broadcast_to(true[:, :1], true.shape)
    ranges = param_ranges(system)
    rows = []
    for key in systems[0].params:
        lo, hi = ranges[key]
        if lo == hi:
            continue
        for eps in eps_list:
            pert = [make(system, params={**s.params, key: float(np.clip(s.params[key] * (1 + eps), lo, hi))})
                    for s in systems]
            t2 = simulate(pert, tr.qpos[:, window].astype(np.float64), tr.qvel[:, window].astype(np.float64),
                          ctrl[:, window:], backend="mujoco")
            err = normalized_errors(t2.body[:, 1:], true[:, 1:], const[:, 1:], mask)["mean"]
            rows.append({"system": system, "param": key, "eps": eps, "error": float(err), "window": window,
                         "horizon": steps - window, "sequences": sequences})
            print(f"{system} {key} eps {eps:g}: {err:.3g}", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cartpole")
    ap.add_argument("--sequences", type=int, default=200)
    ap.add_argument("--num-steps", type=int, default=100)
    ap.add_argument("--window", type=int, default=20)
    ap.add_argument("--eps", type=float, nargs="+", default=(0.003, 0.01, 0.03, 0.1))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="default: bench/results/sysid_figures/sensitivity")
    args = ap.parse_args()
    out = experiment_out("sysid_figures/sensitivity", args.out, False)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in filter(None, args.systems.split(",")):
        rows += sensitivity(s, args.sequences, args.num_steps, args.window, args.eps, args.seed)
    lines = ["# Rollout error of the true simulator with one parameter off by eps", "",
             f"`python bench/experiments/sysid_sensitivity.py` ({time.strftime('%Y-%m-%d')}; MuJoCo C, CPU). "
             f"{args.sequences} sequences per system, random instances and spline controls; rollouts from step "
             f"{args.window} to {args.num_steps}, scored as Figure 8 (squared error / constant baseline, mean over "
             "state groups).", "",
             "| system | parameter | " + " | ".join(f"eps {e:g}" for e in args.eps) + " |",
             "|---|---|" + "---|" * len(args.eps)]
    for (s, p) in dict.fromkeys((r["system"], r["param"]) for r in rows):
        v = [next(r["error"] for r in rows if r["system"] == s and r["param"] == p and r["eps"] == e) for e in args.eps]
        lines.append(f"| {s} | {p} | " + " | ".join(f"{x:.2g}" for x in v) + " |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    import json
    (out / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
