"""Swimmer6: a trained policy's return against its target's distance, from ``gnwarp mpc --policy``
records (``gnwarp.eval.records``, planner "policy": each episode's return, initial state and
target). The distance is the target's from the nose at the episode's start (the suite's reward
measures nose to target; MuJoCo's kinematics of the recorded initial joint positions). Writes a
scatter plot, one series a record (its policy's folder and simulator), and prints per record
the farthest target reached and the nearest missed ("reached": a return of at least
``--reached``, on the 0-1000 scale).

    PYTHONPATH=. python3 bench/rl_targets.py bench/results/rl/h1_swimmer6/policy_mpc.jsonl \\
        bench/results/rl/simulators/records.jsonl --out bench/results/rl/targets_swimmer6.png

``--eval-states``: instead, how many targets of a run's evaluation states (``RLConfig.eval_seed``
K, ``eval_episodes`` N: the states ``gnwarp rl`` evaluates from, ``evaluation_env``) lie within
``--near`` metres of the nose, beside ``--population`` states of another seed (the suite's draw:
``gnwarp.control.dmc.sample_dmc_targets``, a fifth in a box of half-width 0.3 m, the rest in a
4 m square: 44.5% within 1.25 m of the start); rows appended to ``--out`` (JSON lines). A shared
evaluation set's share of near targets moves every return measured on it alike.

    PYTHONPATH=. python3 bench/rl_targets.py --eval-states 50,100 --eval-seeds 0,1,2 \\
        --out bench/results/rl/eval_states_swimmer6.jsonl

``--runs FOLDER``: the target distances of every swimmer6 RL run's evaluation states under FOLDER
(each run evaluates from the same states every time: those of its ``eval_seed``, else of its
seed), one row a set ``{"eval_seed", "episodes", "distances"}``, written to ``--out`` (JSON
lines, whole): what ``bench/results_tables.py`` stratifies the runs' returns by.

    PYTHONPATH=. python3 bench/rl_targets.py --runs bench/results/rl --out bench/results/rl/eval_targets_swimmer6.jsonl
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from gnwarp.eval.records import read_records  # noqa: E402
from gnwarp.files import atomic_write  # noqa: E402

__all__ = ["nose_distances", "episodes", "eval_distances", "run_eval_sets", "main"]


def nose_distances(qpos, targets, task: str = "swimmer6") -> np.ndarray:
    """The distance in the plane from each start's nose (MuJoCo's kinematics of ``qpos`` [N, nq] on
    the task's model) to its target [N, 2 or 3]."""
    import mujoco

    from gnwarp.rl.observations import DMCObservation
    model = DMCObservation(task).system.model
    q, t = np.asarray(qpos, dtype=np.float64), np.asarray(targets, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != model.nq or t.ndim != 2 or len(t) != len(q):
        raise ValueError(f"initial states {q.shape} and targets {t.shape} do not fit the model's {model.nq} qpos")
    data, nose = mujoco.MjData(model), []
    for row in q:
        data.qpos[:] = row
        mujoco.mj_kinematics(model, data)
        nose.append(data.geom("nose").xpos[:2].copy())
    return np.linalg.norm(t[:, :2] - np.asarray(nose), axis=1)


def episodes(rec) -> tuple[np.ndarray, np.ndarray]:
    """(each episode's target distance from the nose at its start, its return) of a policy
    record (``ValueError`` naming what it lacks)."""
    c = rec.config or {}
    if rec.planner != "policy" or not c.get("targets") or not c.get("initial_qpos"):
        raise ValueError(f"not a policy record with targets and initial states (planner {rec.planner!r}, "
                         f"task {rec.task!r})")
    if len(c["targets"]) != len(rec.returns):
        raise ValueError(f"{len(c['targets'])} targets for {len(rec.returns)} returns")
    return nose_distances(c["initial_qpos"], c["targets"]), np.asarray(rec.returns, dtype=np.float64)


def eval_distances(episodes: int, eval_seed: int, task: str = "swimmer6") -> np.ndarray:
    """The nose-to-target distances of the evaluation states of a run with ``eval_episodes``
    ``episodes`` and ``eval_seed`` (its ``evaluation_env``, reset as ``run_rl`` resets it; MuJoCo C)."""
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.run import eval_reset_seed, evaluation_env
    cfg = RLConfig(task=task, agent="svg1", eval_episodes=episodes, eval_seed=eval_seed, backend="mujoco",
                   device="cpu", out="unused", sim_threads=2)
    env = evaluation_env(cfg)
    try:
        env.reset(seed=eval_reset_seed(cfg))
        return nose_distances(env.observe().qpos, env.targets.cpu().numpy(), task)
    finally:
        env.close()


def run_eval_sets(folder) -> dict[tuple[int, int], np.ndarray | None]:
    """{(eval seed, episodes): the target distances its runs recorded, or None}: every swimmer6 RL
    evaluation set under ``folder`` (the states each run evaluates from: ``RLConfig.eval_seed``,
    else the run's seed), sorted; a run's first record holds its states since they are recorded."""
    from gnwarp.eval.records import RecordError
    sets: dict[tuple[int, int], np.ndarray | None] = {}
    for path in sorted(Path(folder).rglob("*.jsonl")):
        try:
            recs = read_records(path)
        except RecordError:
            continue
        for r in recs:
            if r.experiment == "rl" and r.task == "dmc-swimmer-swimmer6" and r.returns:
                c = r.config or {}
                key = (int(r.seed if c.get("eval_seed") is None else c["eval_seed"]), len(r.returns))
                seen = nose_distances(c["initial_qpos"], c["targets"]) if c.get("targets") else None
                sets[key] = seen if seen is not None else sets.get(key)
    return dict(sorted(sets.items()))


def _runs(a) -> int:
    import json
    rows = []
    for (k, n), seen in run_eval_sets(a.runs).items():
        d = eval_distances(n, k)
        if seen is not None and not np.allclose(seen, d, atol=1e-3):   # the sampler is not the runs' any more
            print(f"rl_targets: eval seed {k}, {n} episodes: the runs recorded target distances "
                  f"{np.round(seen, 3).tolist()}, drawn again {np.round(d, 3).tolist()}", file=sys.stderr)
            return 1
        rows.append(dict(eval_seed=k, episodes=n, distances=[round(float(x), 4) for x in d]))
    with atomic_write(a.out) as tmp:
        Path(tmp).write_text("".join(json.dumps(r) + "\n" for r in rows))
    print(f"wrote {len(rows)} evaluation sets' target distances to {a.out}")
    return 0


def _eval_states(a) -> int:
    import json
    import time
    pop = eval_distances(a.population, 10_000)
    p = float((pop < a.near).mean())
    rows = [dict(eval_seed=None, episodes=a.population, near=a.near, share=round(p, 4),
                 mean_distance=round(float(pop.mean()), 3), what="population (eval_seed 10000)")]
    for n in map(int, a.eval_states.split(",")):
        for k in map(int, a.eval_seeds.split(",")):
            d = eval_distances(n, k)
            rows.append(dict(eval_seed=k, episodes=n, near=a.near, share=round(float((d < a.near).mean()), 4),
                             mean_distance=round(float(d.mean()), 3), what="evaluation states"))
    for r in rows:
        r["date"] = time.strftime("%Y-%m-%d")
        print(json.dumps(r))
    with open(a.out, "a") as f:
        f.writelines(json.dumps(r) + "\n" for r in rows)
    print(f"appended {len(rows)} rows to {a.out}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("records", nargs="*", help="records files of gnwarp mpc --policy runs")
    ap.add_argument("--out", required=True, help="the PNG to write (--eval-states: the JSON lines to append to; "
                                                 "--runs: the JSON lines to write whole)")
    ap.add_argument("--reached", type=float, default=500.0, help="a return at least this counts as reached")
    ap.add_argument("--eval-states", default=None, metavar="N,..", help="evaluation sets of these sizes instead")
    ap.add_argument("--eval-seeds", default="0", metavar="K,..", help="their eval_seed values")
    ap.add_argument("--near", type=float, default=1.25, help="a target nearer the nose than this (m) counts as near")
    ap.add_argument("--population", type=int, default=2000, help="states of the suite's distribution to compare with")
    ap.add_argument("--runs", default=None, metavar="FOLDER", help="the target distances of its RL runs' evaluations")
    a = ap.parse_args(argv)
    if a.runs:
        return _runs(a)
    if a.eval_states:
        return _eval_states(a)
    if not a.records:
        ap.error("records files, or --eval-states")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4))
    for path in a.records:
        for rec in read_records(path):
            if rec.planner != "policy":
                continue
            d, r = episodes(rec)
            name = f"{Path(rec.config['policy']).name} ({rec.config.get('backend', '?')})"
            ax.scatter(d, r, label=name, alpha=0.7, marker="x" if "warp" in rec.config.get("backend", "") else "o")
            hit, miss = d[r >= a.reached], d[r < a.reached]
            print(f"{name}: mean {r.mean():.1f}; reached {hit.size} of {d.size}, the farthest at "
                  f"{hit.max() if hit.size else float('nan'):.2f} m; the nearest missed at "
                  f"{miss.min() if miss.size else float('nan'):.2f} m")
    ax.set_xlabel("target's distance from the nose at the start (m)")
    ax.set_ylabel("episode return (1000 steps)")
    ax.set_title("swimmer6: trained SVG(1) policies, return against target distance")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_write(a.out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
