"""How precisely must system identification know the parameters? (beyond the paper)

For each parameterized system, simulates test-like sequences (random instances, initial states
and spline controls, MuJoCo C), then re-simulates each from step W (the identification window's
end) with one parameter scaled by (1 + eps) under the same controls, and scores that "perfect
model with a parameter off by eps" exactly as Figure 8 scores learned models: squared error of
the (H = T - W)-step rollout normalized by the constant baseline's, mean over state groups.
A learned sysid model can only be as good as the parameter precision it reaches; this table
says which precision matches a given rollout error (e.g. the true-parameter model's).

Each (system, parameter, eps) is a results record (``gnwarp.eval.records``) in
``<out>/results.jsonl``; ``summary.md`` is generated from them (``gnwarp.eval.summarize``).

    python bench/experiments/sysid_sensitivity.py --systems pendulum,cartpole
    python bench/experiments/sysid_sensitivity.py --quick        # small CPU run (temporary folder)
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
                         "horizon": steps - window, "sequences": sequences, "date": time.strftime("%Y-%m-%d %H:%M")})
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
    ap.add_argument("--quick", action="store_true", help="16 sequences of 30 steps, window 10 (temporary folder)")
    args = ap.parse_args()
    if args.quick:
        args.sequences, args.num_steps, args.window, args.eps = 16, 30, 10, (0.01, 0.1)
    # a --quick run without --out writes to a temporary folder named after the script
    out = experiment_out("sysid_sensitivity" if args.quick else "sysid_figures/sensitivity", args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in filter(None, args.systems.split(",")):
        rows += sensitivity(s, args.sequences, args.num_steps, args.window, args.eps, args.seed)
    from gnwarp.eval.records import git_commit, write_records
    commit = git_commit()
    write_records(out / "results.jsonl", [to_record(r, seed=args.seed, commit=commit) for r in rows], append=False)
    print(f"wrote {report(out)}")


def to_record(row: dict, seed: int | None = None, commit: str = "unknown"):
    """One (system, parameter, eps) row as a results record of errors: task "<system>: <parameter>",
    variant "eps <eps>", the true simulator (MuJoCo C) with that parameter scaled by (1 + eps) as
    the dynamics, its rollout error over the sequences (``reported`` mean; per-sequence errors are
    not kept) from step ``window`` for ``horizon`` steps; no training data (env_steps 0)."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    system = systems.make(row["system"])
    return ResultRecord(
        experiment="sysid_sensitivity", task=f"{row['system']}: {row['param']}", system=row["system"],
        planner="none", dynamics="true_mujoco_c", variant=f"eps {row['eps']:g}", seed=seed,
        episodes=int(row["sequences"]), episode_steps=int(row["horizon"]),
        reported={"mean": float(row["error"]), "std": None, "of": "errors"}, control_dt=float(system.dt),
        action_repeat=int(system.substeps), env_steps=0,
        config={"param": row["param"], "eps": row["eps"], "window": row["window"]}, commit=commit,
        gpu="cpu", date=row.get("date", ""))


def report(out: Path) -> Path:
    """``summary.md`` from ``out/results.jsonl`` (``gnwarp.eval.summarize``)."""
    from gnwarp.eval.records import read_records
    from gnwarp.eval.summarize import write_summary
    return write_summary(read_records(out / "results.jsonl"), out,
                         "Rollout error of the true simulator with one parameter off by eps", plot=False)

if __name__ == "__main__":
    main()
