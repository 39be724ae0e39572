"""Closed-loop control on the true simulator: gradient MPC through a learned
model against iLQG on the true model, sampling MPC (true and learned dynamics) and random actions.

For each task (default: pendulum-balance, cartpole-balance, swimmer-reach on swimmer6; ``--tasks
all``: every F.2 task) and a trained forward model of its system (``--checkpoints DIR`` holding
``<system>/best``, as ``budget_retrain.py --checkpoints`` packs them; a system without one gets a
model trained here, ``--train-seconds``), N episodes from the same random initial states (and
targets) run in closed loop on the true environment (``make_env``, MuJoCo-Warp on a GPU) under:

- ``gn_mpc``: ``GradientMPC`` through the learned model (task horizon, ``--iterations`` Adam steps
  per control step, plus iterations x horizon at the first state);
- ``ilqg``: ``ILQG.for_task`` on MuJoCo C with the same horizon and the task's cost
  (``task_cost``, running and terminal), one process per episode (``--ilqg-workers``), each in the
  same ``run_episodes`` loop as every planner; tasks ``task_cost`` refuses (swimmer-reach: its
  reward is of displacements) get their own costs (``--ilqg-swimmer own``) or are skipped;
- ``sampling_true``: predictive sampling on the true env (N x ``--samples`` worlds);
- ``sampling_model``: the same sampler through the learned model (a ``RolloutEngine``);
- ``random``: uniform random actions.

Reported: the TRUE return (mean, std over episodes) of each, planning seconds per control step
(host wall clock, device synchronized) and episode-steps per second (N x steps / wall clock of the
whole closed loop), the ratio GN-MPC / iLQG (goal >= 90% on pendulum and cartpole balance and
swimmer6 reach; returns are negative on the balance tasks, so the ratio is iLQG / GN-MPC there:
"fraction of iLQG's performance"), a bar plot and a GIF of GN-MPC per task. Each (task, planner)
is one results record (``gnwarp.eval.records``) appended to ``<out>/results.jsonl``; ``summary.md``
and ``returns.png`` are generated from them by ``gnwarp.eval.summarize`` (``--rebuild``: only that).

    python bench/experiments/control.py --checkpoints ckpts [--episodes 20] [--tasks all]
    python bench/experiments/control.py --quick        # tiny CPU smoke run (temp folder)
"""
from __future__ import annotations

import argparse
import sys
import time
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import device_name, ensure_dataset, experiment_out, gn_sizes  # noqa: E402

DEFAULT_TASKS = "pendulum-balance,cartpole-balance,swimmer-reach"
PLANNERS = ("gn_mpc", "ilqg", "sampling_true", "sampling_model", "random")


def task_system(task, override: str | None = None) -> str:
    """The system a task runs on here: ``override`` (``--system``, e.g. swimmer7 for the zero-shot
    runs of Figure 11) when it fits the task, else SwimmerN tasks on swimmer6."""
    if override:
        if not task.fits(override):
            raise SystemExit(f"--system {override} does not fit task {task.name} (a {task.system} task)")
        return override
    return "swimmer6" if task.system == "swimmer" else task.system


# -- models -----------------------------------------------------------------------------------------

def model_path(args, system: str, out: Path) -> Path:
    """``<checkpoints>/<system>/best``, or a model trained here (quick: a tiny one)."""
    if args.model:
        return Path(args.model)
    if args.checkpoints:
        p = Path(args.checkpoints) / system / "best"
        if p.exists():
            return p
        print(f"no checkpoint {p}: training one ({args.train_seconds:g} s)", flush=True)
    p = out / "checkpoints" / system / "best"
    if p.exists():
        return p
    from gnwarp.models import ModelConfig
    from gnwarp.train import TrainConfig, Trainer
    data = ensure_dataset(Path(args.data) / f"{system}.h5", system, args.sequences, args.seq_steps, seed=1)
    sizes = gn_sizes(*args.gn)
    cfg = TrainConfig(data=[str(data)], out=str(out / "checkpoints" / system), model=ModelConfig(gn=sizes),
                      steps=args.train_steps, max_seconds=args.train_seconds, batch_size=args.batch, lr=1e-3,
                      lr_decay=0.6, lr_decay_steps=max(1, args.train_steps // 4), valid_every=args.valid_every,
                      valid_sequences=args.sequences[1], patience=None, checkpoint_every=args.train_steps,
                      resume=False, progress=False, device=args.device)
    t0 = time.perf_counter()
    res = Trainer(cfg).run()
    print(f"trained {system}: {res['steps']} steps in {time.perf_counter() - t0:.0f} s -> {res['best']}", flush=True)
    return Path(res["best"])


# -- iLQG: one episode per process ------------------------------------------------------------------

def ilqg_model(system, rk4: str):
    """The model iLQG plans on: the system's own, or (``rk4`` "implicit", for RK4 systems, whose
    derivatives ``mjd_transitionFD`` refuses) a copy integrated implicitly at the same timestep."""
    import copy

    import mujoco
    m = system.model
    if m.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4:
        return m
    if rk4 != "implicit":
        raise ValueError(f"{system.name} integrates with RK4, which mujoco.mjd_transitionFD (iLQG's derivatives) "
                         "does not support (--ilqg-rk4 implicit: plan on an implicit-integrator copy)")
    m = copy.deepcopy(m)
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICIT
    return m


def swimmer_costs(model, target, qpos, qvel):
    """swimmer-reach as iLQG costs from the current state (qpos, qvel), exactly the task's reward
    of a plan starting there: its displacement term telescopes to the head's final displacement
    along the direction to the target (a terminal cost); the shaping 0.01 x squared offset from
    the line is a cost of every state (its state-0 term is zero). Both are ``BodyPointCost``s of
    the head (body 1), with analytic (Gauss-Newton) derivatives."""
    import mujoco

    from gnwarp.control.ilqg import BodyPointCost
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:] = qpos, qvel
    mujoco.mj_forward(model, d)
    head0 = d.xpos[1].copy()
    u = np.zeros(3)
    u[:2] = np.asarray(target, np.float64)[:2] - head0[:2]
    u /= max(np.linalg.norm(u), 1e-9)
    perp = np.array([-u[1], u[0], 0.0])
    W = 0.01 * np.outer(perp, perp)
    return BodyPointCost(model, 1, head0, W=W), BodyPointCost(model, 1, head0, lin=-u, W=W)


def _ilqg_episode(job: dict) -> dict:
    """One closed-loop iLQG episode on a one-world MuJoCo C env (run in a worker process), in the
    ``run_episodes`` loop every planner runs in."""
    torch.set_num_threads(1)
    from gnwarp.control import get_task, run_episodes
    from gnwarp.control.ilqg import ILQG, ILQGSettings
    from gnwarp.sim import make_env
    from gnwarp.sim import systems
    system = systems.make(job["system"])
    task = get_task(job["task"])
    model = ilqg_model(system, job["rk4"])
    settings = ILQGSettings(horizon=job["horizon"], iterations=job["iterations"], warmup=job["warmup"],
                            substeps=system.substeps, nthread=1)
    target = None if job["target"] is None else job["target"][None]
    if task.target == "position":   # the swimmer's cost is measured from the current state: made every step
        planner = ILQG(model, settings=settings, targets=target,
                       costs=lambda i, tgt, qpos, qvel: swimmer_costs(model, tgt, qpos, qvel))
    else:
        planner = ILQG.for_task(system, task, 1, settings, target, model=model)
    env = make_env(system, 1, backend="mujoco")
    out = run_episodes(planner, env, task, job["steps"], qpos0=job["qpos"][None], qvel0=job["qvel"][None],
                       target=target)
    env.close()
    return {"states": out["states"][0], "actions": out["actions"][0], "plan_seconds": list(out["plan_seconds"])}


def run_ilqg(args, task, system, qpos, qvel, target, horizon: int) -> dict:
    from concurrent.futures import ProcessPoolExecutor
    import multiprocessing as mp
    from gnwarp.control.ilqg import task_cost
    model = ilqg_model(system, args.ilqg_rk4)        # raises for RK4 systems unless --ilqg-rk4 implicit
    own = task.target == "position" and args.ilqg_swimmer == "own"
    if not own:
        task_cost(model, task, None if target is None else target[0].numpy())   # raises for refused tasks
    n = qpos.shape[0]
    jobs = [{"system": system.name, "task": task.name, "horizon": horizon, "steps": args.steps,
             "iterations": args.ilqg_iterations, "warmup": args.ilqg_warmup, "rk4": args.ilqg_rk4,
             "qpos": qpos[i], "qvel": qvel[i],
             "target": None if target is None else target[i].numpy()} for i in range(n)]
    workers = max(1, min(args.ilqg_workers, n))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        eps = list(pool.map(_ilqg_episode, jobs))
    wall = time.perf_counter() - t0
    states = torch.stack([e["states"] for e in eps])
    actions = torch.stack([e["actions"] for e in eps])
    returns = task.reward(states, actions, target)
    secs = np.concatenate([np.asarray(e["plan_seconds"]) for e in eps])
    return {"returns": returns, "states": states, "plan_seconds": secs, "wall": wall,
            "note": f"{workers} processes, one episode each; {args.ilqg_iterations} iterations/step "
                    f"({args.ilqg_warmup} at the first state)"
                    + ("; planned on an implicit-integrator copy of the RK4 model" if model is not system.model else "")
                    + ("; the task's reward as own running + terminal costs (telescoped displacement)" if own else "")}


# -- the other planners -----------------------------------------------------------------------------

def run_episodes(planner, env, task, steps, *, qpos0, qvel0, target=None) -> dict:
    """The closed loop: ``gnwarp.control.episodes.run_episodes`` (one runner for every planner),
    reset to (qpos0, qvel0); {"returns", "states", "plan_seconds", "wall"} on the CPU."""
    from gnwarp.control.episodes import run_episodes as run
    t0 = time.perf_counter()
    out = run(planner, env, task, steps, qpos0=qpos0, qvel0=qvel0, target=target)
    out["wall"] = time.perf_counter() - t0
    return out


def run_gn_mpc(args, model, task, system, qpos, qvel, target, horizon: int) -> dict:
    from gnwarp.control import GradientMPC, GradientMPCConfig
    from gnwarp.sim import make_env
    n = qpos.shape[0]
    warm = args.iterations * horizon if args.warmup is None else args.warmup   # the paper's, from a random sequence
    cfg = GradientMPCConfig(horizon=horizon, iterations=args.iterations, lr=args.lr, seed=args.seed,
                            warmup=warm, proposals=0)
    planner = GradientMPC(model, task, system, n, cfg, target)
    env = make_env(system, n, backend=args.backend)
    out = run_episodes(planner, env, task, args.steps, qpos0=qpos, qvel0=qvel, target=target)
    env.close()
    out["note"] = f"{args.iterations} Adam steps/step + {warm} at the first state, lr {args.lr}"
    return out


def _reward(task, target, n: int):
    """The task's reward for the sampler: rows are episodes (n) or episodes x samples."""
    def reward(states, actions):
        tgt = None
        if target is not None:
            k = states.shape[0] // n
            tgt = target.to(states.device).repeat_interleave(k, 0)
        return task.reward(states, actions.to(states.device, states.dtype), tgt)
    return reward


def run_sampler(args, kind: str, model, task, system, qpos, qvel, target, horizon: int) -> dict:
    from gnwarp.sim import make_env
    from gnwarp.control.sampling import RandomPlanner, SamplingConfig, SamplingPlanner, model_dynamics, true_dynamics
    n = qpos.shape[0]
    env = make_env(system, n, backend=args.backend)
    reward = _reward(task, target, n)
    cfg = SamplingConfig(horizon=horizon, samples=args.samples, knots=min(args.knots, horizon), noise=args.noise,
                         seed=args.seed)
    dyn = None
    if kind == "random":
        planner, note = RandomPlanner(env.ctrlrange, n, seed=args.seed, device=env.device), "uniform in the range"
    elif kind == "sampling_true":
        dyn = true_dynamics(system, n, args.samples, backend=args.backend, source=env)
        planner = SamplingPlanner(dyn, reward, env.ctrlrange.cpu(), n, cfg)
        note = f"{args.samples} samples x {n} episodes on the true env ({dyn.env.backend})"
    else:
        dyn = model_dynamics(model, n, args.samples, horizon)
        planner = SamplingPlanner(dyn, reward, env.ctrlrange.cpu(), n, cfg)
        note = f"{args.samples} samples x {n} episodes through the learned model"
    out = run_episodes(planner, env, reward, args.steps, qpos0=qpos, qvel0=qvel)
    env.close()
    if dyn is not None and hasattr(dyn, "env"):
        dyn.env.close()
    out["note"] = note
    return out


# -- one task ---------------------------------------------------------------------------------------

def _steady(secs, n: int, steps: int) -> np.ndarray:
    """Planning seconds per control step without the first step of each episode (the warm-up):
    ``secs`` [steps] (batched planners) or [n x steps] (iLQG, one episode after another)."""
    s = np.asarray(secs, dtype=np.float64).reshape(-1, steps)
    return s[:, 1:].reshape(-1) if steps > 1 else s.reshape(-1)


def run_task(args, name: str, out: Path) -> list[dict]:
    from gnwarp.control import get_task, sample_targets
    from gnwarp.data.generation import initial_states
    from gnwarp.sim import systems
    from gnwarp.train import load_model
    task = get_task(name)
    system = systems.make(task_system(task, args.system))
    horizon = args.horizon or task.horizon
    n = args.episodes
    rng = np.random.default_rng(args.seed)
    qpos, qvel = initial_states(system, n, rng)
    target = sample_targets(task, system, n, args.seed, distance=args.target_distance)
    if args.first:   # the first K of the N episodes' initial states and targets (a slow planner's share)
        n = min(args.first, n)
        qpos, qvel, target = qpos[:n], qvel[:n], None if target is None else target[:n]
    from gnwarp.train.checkpoint import training_env_steps
    path = model_path(args, system.name, out)
    model = load_model(path, device=args.device).bind(system)
    env_steps = training_env_steps(path)   # the learned planners' training data
    rows = []
    for kind in args.planners:
        print(f"{name}: {kind} ...", flush=True)
        row = {"task": name, "system": system.name, "planner": kind, "episodes": n, "steps": args.steps,
               "horizon": horizon, "device": device_name(model.device) if kind != "ilqg" else device_name(
                   torch.device("cpu")), "backend": args.backend if kind != "ilqg" else "mujoco",
               "quick": args.quick, "date": time.strftime("%Y-%m-%d")}
        try:
            if kind == "gn_mpc":
                res = run_gn_mpc(args, model, task, system, qpos, qvel, target, horizon)
            elif kind == "ilqg":
                res = run_ilqg(args, task, system, qpos, qvel, target, horizon)
            else:
                res = run_sampler(args, kind, model, task, system, qpos, qvel, target, horizon)
        except ValueError as e:
            if kind != "ilqg":
                raise
            row.update(skipped=str(e))
            print(f"  skipped: {e}", flush=True)
            rows.append(row)
            continue
        r = torch.as_tensor(res["returns"]).double().cpu()
        row.update(return_mean=float(r.mean()), return_std=float(r.std(unbiased=False)), returns=r.tolist(),
                   plan_ms=1e3 * float(np.mean(_steady(res["plan_seconds"], n, args.steps))),
                   plan_first_ms=1e3 * float(np.asarray(res["plan_seconds"]).reshape(-1)[0]), wall_s=res["wall"],
                   episode_steps_per_s=n * args.steps / res["wall"], note=res["note"])
        row["real_time_factor"] = 1e3 * float(system.dt) / row["plan_ms"] if row["plan_ms"] > 0 else None
        if task.target == "position":   # Figure 11: the head's distance to the target, first and last state
            head = torch.as_tensor(res["states"]).double()[:, :, 1, :2]
            dist = torch.linalg.vector_norm(head - target[:, None, :2].double(), dim=-1)
            row.update(initial_distance=float(dist[:, 0].mean()), final_distance_mean=float(dist[:, -1].mean()),
                       final_distance_std=float(dist[:, -1].std(unbiased=False)), final_distances=dist[:, -1].tolist(),
                       distance_curve=dist.mean(0).tolist())
        print(f"  true return {row['return_mean']:.4g} +- {row['return_std']:.3g}; {row['plan_ms']:.1f} ms/plan; "
              f"{row['episode_steps_per_s']:.1f} episode-steps/s"
              + (f"; distance to target {row['initial_distance']:.3g} -> {row['final_distance_mean']:.3g} m"
                 if "final_distance_mean" in row else ""), flush=True)
        if kind in ("gn_mpc", "sampling_model") and env_steps is not None:
            row["env_steps"] = env_steps
        if kind == "gn_mpc" and args.video:
            row["video"] = video(args, task, system, res["states"], out)
        rows.append(row)
    return rows


def video(args, task, system, states, out: Path) -> str | None:
    from gnwarp.eval.animation import animate
    k = min(3, states.shape[0])
    shim = types.SimpleNamespace(meta={"system": system.name, "parameterized": False, "dt": system.dt},
                                 static={"n_node": np.full(k, system.nbody)})
    path = out / f"gn_mpc_{task.name}.gif"
    try:
        animate(torch.as_tensor(states)[:k].float().numpy(), {}, shim, np.zeros(k, dtype=np.int64), path,
                dt=system.dt, title=f"{task.name}: gradient MPC (learned model), true simulator",
                renderer=args.renderer)
    except Exception as e:  # noqa: BLE001 - a video must not lose the results
        print(f"  no video: {e}", flush=True)
        return None
    return path.name


# -- outputs ----------------------------------------------------------------------------------------

# planner kind of a row -> (registered planner name, dynamics it plans through)
RECORD_NAMES = {"gn_mpc": ("gradient", "learned"), "ilqg": ("ilqg", "true_mujoco_c"),
                "sampling_model": ("sampling", "learned"), "random": ("random", "none")}
# the columns of the summary's ratio: GN-MPC's share of iLQG's performance
RATIO = ("gradient (learned)", "ilqg (true, MuJoCo C)")
METRICS = ("plan_ms", "plan_first_ms", "real_time_factor", "episode_steps_per_s", "wall_s", "initial_distance", "final_distance_mean",
           "final_distance_std", "final_distances", "distance_curve")
CONFIG = ("horizon", "backend", "quick", "note", "source", "video", "iterations", "samples", "knots", "noise", "lr",
          "ilqg_iterations", "ilqg_warmup", "warmup")


def true_dynamics_name(backend: str, device: str) -> str:
    """The dynamics of a planner on the true env: MuJoCo C for backend "mujoco" (and "auto" on a
    CPU-only device), MuJoCo-Warp otherwise."""
    if backend == "mujoco" or (backend == "auto" and not device.startswith("NVIDIA")):
        return "true_mujoco_c"
    return "true_mjwarp"


def to_record(row: dict, experiment: str = "control", variant: str = "", seed=None, commit: str = "unknown"):
    """A row of this script (a dict with task, system, planner, episodes, steps, returns or
    return_mean / return_std, timings, note ...) as a ``ResultRecord`` (numbers unchanged)."""
    from gnwarp.control import get_task
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    kind = row["planner"]
    if kind == "sampling_true":
        planner, dynamics = "sampling", true_dynamics_name(row.get("backend", "auto"), row.get("device", ""))
    else:
        planner, dynamics = RECORD_NAMES[kind]
    system = systems.make(row.get("system") or task_system(get_task(row["task"])))
    returns = row.get("returns")
    learned = dynamics == "learned"
    return ResultRecord(
        experiment=experiment, task=row["task"], system=system.name, planner=planner, dynamics=dynamics,
        variant=variant, seed=seed, episodes=int(row["episodes"]), episode_steps=int(row["steps"]),
        returns=None if returns is None else [float(x) for x in returns],
        reported=None if returns is not None else {"mean": row["return_mean"], "std": row["return_std"]},
        control_dt=float(system.dt), action_repeat=int(system.substeps),
        env_steps=row.get("env_steps") if learned else 0,
        metrics={k: row[k] for k in METRICS if k in row}, config={k: row[k] for k in CONFIG if k in row},
        commit=commit, gpu=row.get("device", "unknown"), date=row.get("date", ""))


def plot_distances(out: Path, records) -> None:
    """Mean distance from the head to the target over the episode, per (task, system, planner)."""
    far = [r for r in records if r.metrics.get("distance_curve")]
    if not far:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4))
    for r in far:
        ax.plot(r.metrics["distance_curve"], label=f"{r.planner} ({r.dynamics}), {r.system} ({r.episodes} episodes)")
    ax.set_xlabel("control step")
    ax.set_ylabel("distance head - target (m), mean")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "distances.png", dpi=110)
    plt.close(fig)


def summarize(out: Path, records, quick: bool = False) -> None:
    """``out/summary.md`` and ``returns.png`` (``gnwarp.eval.summarize``) and ``distances.png``."""
    from gnwarp.eval.summarize import write_summary
    gpu = next((r.gpu for r in records if r.planner == "gradient"), records[0].gpu if records else "?")
    title = f"Control: true returns in closed loop ({gpu}{', QUICK smoke run' if quick else ''})"
    print(f"wrote {write_summary(records, out, title, ratio_of=RATIO)}")
    plot_distances(out, records)


def main():
    from gnwarp.control import TASKS
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", default=DEFAULT_TASKS, help=f"comma-separated, or 'all' ({', '.join(TASKS)})")
    ap.add_argument("--planners", default=",".join(PLANNERS))
    ap.add_argument("--checkpoints", default=None, help="folder holding <system>/best forward-model checkpoints")
    ap.add_argument("--model", default=None, help="one forward-model checkpoint for every task (overrides --checkpoints)")
    ap.add_argument("--system", default=None, help="run the tasks on this system (e.g. swimmer7; default: the "
                                                   "task's, swimmer6 for SwimmerN tasks)")
    ap.add_argument("--first", type=int, default=None, help="run only the first K of the --episodes episodes "
                                                             "(same initial states and targets)")
    ap.add_argument("--target-distance", type=float, default=1.0, help="swimmer targets' distance from the origin (m)")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=100, help="control steps per episode")
    ap.add_argument("--horizon", type=int, default=None, help="planning horizon of every planner (default: the task's)")
    ap.add_argument("--iterations", type=int, default=5, help="GN-MPC Adam iterations per control step")
    ap.add_argument("--lr", type=float, default=0.1, help="GN-MPC Adam step size")
    ap.add_argument("--warmup", type=int, default=None,
                    help="GN-MPC iterations at the first state (default: iterations x horizon, as the paper)")
    ap.add_argument("--samples", type=int, default=256, help="sampling MPC candidates per episode")
    ap.add_argument("--knots", type=int, default=4)
    ap.add_argument("--noise", type=float, default=0.2)
    ap.add_argument("--ilqg-iterations", type=int, default=5, help="iLQG iterations per control step")
    ap.add_argument("--ilqg-warmup", type=int, default=50, help="iLQG iterations at the first state")
    ap.add_argument("--ilqg-rk4", choices=["skip", "implicit"], default="skip",
                    help="RK4 systems (cartpole, acrobot), whose derivatives MuJoCo refuses: skip iLQG, or plan on an "
                         "implicit-integrator copy (execution stays on the true RK4 env)")
    ap.add_argument("--ilqg-swimmer", choices=["own", "skip"], default="own",
                    help="swimmer-reach, which task_cost refuses: the same reward as own running + terminal costs "
                         "(exact), or skip")
    ap.add_argument("--ilqg-workers", type=int, default=None, help="processes for iLQG (default: CPU cores)")
    ap.add_argument("--backend", default="auto", help="true env: auto | mujoco | mujoco_warp | mujoco_warp_cpu")
    ap.add_argument("--device", default="auto", help="learned model's device")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--video", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--renderer", default="auto", choices=["auto", "mujoco", "matplotlib"])
    ap.add_argument("--data", default=None, help="dataset folder for models trained here (default: <out>/data)")
    ap.add_argument("--train-seconds", type=float, default=600.0, help="budget of a model trained here")
    ap.add_argument("--train-steps", type=int, default=10**6)
    ap.add_argument("--out", default=None, help="default: bench/results/control (--quick: a temporary folder)")
    ap.add_argument("--rebuild", action="store_true", help="only rebuild summary.md and the plot from results.jsonl "
                    "(the newest row of each task and planner)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes on the CPU: a smoke test of the script")
    args = ap.parse_args()
    import os
    args.ilqg_workers = args.ilqg_workers or os.cpu_count() or 1
    args.sequences, args.seq_steps, args.batch, args.valid_every = (2000, 50, 200), 100, 200, 2000
    args.gn = (128, 256, 128)
    if args.quick:
        args.episodes, args.steps, args.horizon, args.samples = min(args.episodes, 2), min(args.steps, 8), 6, 8
        args.iterations, args.ilqg_iterations, args.ilqg_warmup = 2, 1, 3
        args.sequences, args.seq_steps, args.batch, args.valid_every = (20, 4, 4), 20, 16, 100
        args.gn, args.train_steps, args.train_seconds = (16, 32, 16), 300, 60.0
        args.device, args.backend, args.renderer = "cpu", "mujoco", "matplotlib"
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    args.tasks = list(TASKS) if args.tasks == "all" else args.tasks.split(",")
    args.planners = args.planners.split(",")
    bad = [p for p in args.planners if p not in PLANNERS]
    if bad:
        ap.error(f"unknown planners {bad}; choose from {PLANNERS}")
    out = experiment_out("control", args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    from gnwarp.eval.records import git_commit, read_records, write_records
    if args.rebuild:
        summarize(out, read_records(out / "results.jsonl"), args.quick)
        return
    args.data = args.data or str(out / "data")
    Path(args.data).mkdir(parents=True, exist_ok=True)
    print(f"writing to {out}", flush=True)
    records, commit = [], git_commit()
    settings = {k: getattr(args, k) for k in ("iterations", "samples", "knots", "noise", "lr", "ilqg_iterations",
                                              "ilqg_warmup", "warmup")}
    for name in args.tasks:
        for row in run_task(args, name, out):
            if "skipped" in row:
                continue
            rec = to_record({**row, **settings}, seed=args.seed, commit=commit)
            write_records(out / "results.jsonl", [rec])
            records.append(rec)
    summarize(out, records, args.quick)


if __name__ == "__main__":
    main()
