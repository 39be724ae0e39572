"""Benchmark: env steps a second of the RL training loop (``gnwarp.rl.loop.run_env_steps``), the
actions picked in turn or ahead (``act_ahead``), on one device.

What ``gnwarp rl`` runs between its evaluations: a run's parts as ``build_run`` makes them
(``--task``, ``--agent``, MLPs of the spinningup preset, ``--envs`` envs on ``--backend``, the
agent on ``--device``, every update replayed from a CUDA graph there), the replay buffer filled
past ``update_after`` first (random actions, not timed), then per way ``--reps`` times
``--steps`` vector steps, each way's repetitions alternating with the other's in the same
process (env steps / s and updates / s of each repetition; the first, which records the update's
graph, is reported apart as ``first_s``). Acting ahead lets a CPU simulator (``--backend mujoco``)
step while the GPU updates; with the agent on the CPU (or the simulator on the GPU) nothing
overlaps, the actions are still picked ahead (other numbers), and the ratio near 1 is the check.

    python bench/rl_loop.py [--task swimmer6] [--agent svg1] [--steps 300] [--reps 3] [--device cuda]
    python bench/rl_loop.py --quick       # tiny sizes on the CPU: a smoke test of the script
    python bench/rl_loop.py --summarize bench/results/rl/rl_loop_nvidia-h200.jsonl   # its table again

``--profile``: afterwards ``--profile-steps`` more vector steps of each way under ``torch.profiler``
(CPU, and CUDA where the agent is), its operators' self times (top 30 by CPU time, then by CUDA
time) and the device operations an update launches written to
``rl_loop_profile_<device>_<task>_<way>.txt`` beside the table: where a vector step's time goes.
Keep the profiled window short: the profiler's tables of 200 walker steps (~3M kernel events)
took ~8 minutes to build on the device.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.harness import add_run_args, device_name, experiment_out, read_rows, save_results, slug  # noqa: E402
from gnwarp.files import atomic_write  # noqa: E402
from gnwarp.rl.config import RLConfig  # noqa: E402
from gnwarp.rl.graphed import Updater  # noqa: E402
from gnwarp.rl.loop import CollectorState, run_env_steps  # noqa: E402
from gnwarp.rl.run import build_run  # noqa: E402


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def loop_parts(cfg: RLConfig) -> dict:
    """A run's parts (``build_run``) with its buffer filled up to the step before the first update
    (the start steps' random actions), the model normalized from it where SVG(N) has one (as
    ``run_rl`` does, before any update), and the updater."""
    from gnwarp.rl.run import normalize_model   # what run_rl does once, before the first update
    p = build_run(cfg)
    agent, env = p["agent"], p["env"]
    state = CollectorState(env.reset(seed=0)[0], cfg.num_envs)
    updater = Updater(agent, p["buffer"], p["generator"], capture=cfg.cuda_graph and p["device"].type == "cuda")
    before = -(-agent.settings.update_after // cfg.num_envs) - 1   # the next step's updates are the first
    run_env_steps(agent, env, p["buffer"], state, before, p["generator"], updater=updater)
    if p["model"] is not None:
        normalize_model(p["model"], p["buffer"])
    return dict(p, state=state, updater=updater)


def time_steps(p: dict, steps: int) -> tuple[float, int]:
    """(seconds, updates) of ``steps`` vector steps of the loop, the device synchronized."""
    _sync(p["device"])
    t = time.perf_counter()
    out = run_env_steps(p["agent"], p["env"], p["buffer"], p["state"], steps, p["generator"], updater=p["updater"])
    _sync(p["device"])
    return time.perf_counter() - t, out["updates"]


def device_ops(table, updates: int) -> str:
    """A line: the device operations (kernels, copies, sets) of a profile's averaged table, their
    number an update and their mean time; the loop's own ranges (``rl.*``) are not operations."""
    from torch.autograd import DeviceType
    ops = [e for e in table if e.device_type == DeviceType.CUDA and not e.key.startswith("rl.")]
    n = sum(e.count for e in ops)
    us = sum(e.self_device_time_total for e in ops)
    if not n or not updates:
        return "no device operations recorded"
    return (f"device operations: {n} ({n / updates:.0f} an update), {us / 1e3:.1f} ms of device time "
            f"({us / n:.2f} us each, {us / 1e3 / updates:.3f} ms an update)")


def profile_steps(p: dict, steps: int, path: Path) -> Path:
    """``steps`` more vector steps under ``torch.profiler`` (CPU, and CUDA where the agent is): their
    wall time, the device operations an update launches, and the operators' self times, the top 30
    by CPU time then by CUDA time, written to ``path``."""
    from torch.profiler import ProfilerActivity, profile

    from gnwarp.rl import loop
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if p["device"].type == "cuda" else [])
    loop.PROFILE_RANGES = True   # the loop's named ranges in the trace
    try:
        with profile(activities=acts) as prof:
            secs, updates = time_steps(p, steps)
    finally:
        loop.PROFILE_RANGES = False
    table = prof.key_averages()
    text = [f"{steps} vector steps of {p['env'].num_envs} envs in {secs:.3f} s under the profiler "
            f"({1e3 * secs / steps:.2f} ms a vector step), {updates} updates"]
    if p["device"].type == "cuda":
        text.append(device_ops(table, updates))
    text += ["", table.table(sort_by="self_cpu_time_total", row_limit=30)]
    if p["device"].type == "cuda":
        text += ["", table.table(sort_by="self_device_time_total", row_limit=30)]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(text) + "\n")
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", default="swimmer6")
    ap.add_argument("--agent", default="svg1")
    ap.add_argument("--envs", type=int, default=10, help="envs stepped together (gnwarp rl's num_envs)")
    ap.add_argument("--steps", type=int, default=300, help="vector steps a repetition")
    ap.add_argument("--reps", type=int, default=3, help="timed repetitions a way (after the first)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--backend", default="mujoco", help="the true simulator (gnwarp rl's --backend)")
    ap.add_argument("--threads", type=int, default=1, help="MuJoCo C's threads (sim_threads)")
    ap.add_argument("--torch-compile", default="auto", choices=("auto", "none", "inductor"),
                    help="the update's torch.compile (gnwarp rl's torch_compile; the rows name the one used)")
    ap.add_argument("--profile", action="store_true", help="then --profile-steps more vector steps a way under "
                    "torch.profiler (its operator table written beside the results)")
    ap.add_argument("--profile-steps", type=int, default=20, help="vector steps profiled a way (keep it short: "
                    "the profiler's tables take minutes for millions of kernel events)")
    ap.add_argument("--summarize", default=None, metavar="JSONL",
                    help="only rewrite the table beside JSONL (an rl_loop_<device>.jsonl) from its rows")
    add_run_args(ap, "rl")   # --out, --quick
    a = ap.parse_args(argv)
    if a.summarize:
        write_table(Path(a.summarize).with_suffix(""))
        return
    if a.quick:
        a.steps, a.reps, a.envs, a.profile_steps = 5, 1, 2, 3
    base = dict(task=a.task, agent=a.agent, num_envs=a.envs, device=a.device, backend=a.backend,
                sim_threads=a.threads, torch_compile=a.torch_compile, progress=False, tensorboard=False, video_episodes=0, eval_episodes=1)
    if a.quick:
        base.update(task="pendulum-balance", agent="svg0", observation="bodies", device="cpu",
                    episode_steps=20, hidden=(16,), batch_size=8, start_steps=10, update_after=10)
    torch.set_num_threads(max(1, a.threads))
    ways = {"in turn": False, "ahead": True}
    parts = {w: loop_parts(RLConfig(**base, act_ahead=ahead, out="unused")) for w, ahead in ways.items()}
    dev = parts["in turn"]["device"]
    name = device_name(dev)
    first = {w: time_steps(p, a.steps)[0] for w, p in parts.items()}   # records the update's graph
    per: dict[str, list[tuple[float, int]]] = {w: [] for w in ways}
    for _ in range(a.reps):
        for w, p in parts.items():
            per[w].append(time_steps(p, a.steps))
    rows = []
    for w, ahead in ways.items():
        rates = [a.steps * a.envs / s for s, _ in per[w]]
        ups = [n / s for s, n in per[w]]
        rows.append(dict(device=name, task=parts[w]["task"].name, agent=parts[w]["agent"].settings.agent,
                         way=w, act_ahead=ahead, envs=a.envs, steps=a.steps, reps=a.reps, backend=a.backend,
                         torch_compile=parts[w]["agent"].compile_used,   # what ran (eager after a failure)
                         env_steps_per_s=round(statistics.median(rates), 1), env_steps_per_s_each=[round(r, 1) for r in rates],
                         updates_per_s=round(statistics.median(ups), 1), first_s=round(first[w], 3),
                         date=time.strftime("%Y-%m-%d")))
        print(json.dumps(rows[-1]), flush=True)
    ratio = rows[1]["env_steps_per_s"] / rows[0]["env_steps_per_s"]
    for r in rows:
        r["ahead_over_in_turn"] = round(ratio, 3)
    out = experiment_out("rl", a.out, a.quick)
    if a.profile:
        for w, p in parts.items():
            path = profile_steps(p, a.profile_steps, out / f"rl_loop_profile_{slug(name)}_{rows[0]['task']}_{w.replace(' ', '_')}.txt")
            print(f"wrote {path}")
    for p in parts.values():
        p["env"].close()
        p["eval_env"].close()
    jsonl = out / f"rl_loop_{slug(name)}{'_quick' if a.quick else ''}.jsonl"   # save_results' file: its rows and ours
    before = read_rows(jsonl) if jsonl.is_file() else []
    save_results(out, "rl_loop", name, a.quick, rows, table_lines(before + rows))


def table_lines(rows: list[dict]) -> list[str]:
    """The table of every run in ``rows`` (``rl_loop_<device>.jsonl``'s rows, in their order):
    one line a run (its "in turn" and "ahead" rows)."""
    runs: dict[tuple, dict] = {}
    nth: dict[tuple, int] = {}   # per settings: the run its rows fill now
    for r in rows:
        base = (r["device"], r["date"], r["task"], r["agent"], r["backend"], r.get("torch_compile", "not recorded"),
                r["envs"], r["steps"], r["reps"])
        n = nth.setdefault(base, 0)
        if r["way"] in runs.get((*base, n), {}):   # the same settings again (same day): the next run
            n = nth[base] = n + 1
        runs.setdefault((*base, n), {})[r["way"]] = r
    devices = sorted({k[0] for k in runs})
    lines = [f"# RL training loop: env steps a second, actions in turn or ahead, on {', '.join(devices)}", "",
             "Generated by `python bench/rl_loop.py` from the rows of the `.jsonl` beside this file (each run appends "
             "its rows; `--summarize` rewrites this table). Median env steps a second of `reps` alternating "
             "repetitions of `steps` vector steps (the first, which records the update's graph, apart: its seconds "
             "in the last column). `update`: the update's torch.compile (none: eager, in a CUDA graph).", "",
             "| date | task | agent | envs on | update | in turn (env steps / s) | ahead | ahead / in turn | "
             "first repetition (s), in turn / ahead |", "|---|---|---|---|---|---|---|---|---|"]
    for k, ways in runs.items():
        t, h = ways.get("in turn"), ways.get("ahead")
        rate = lambda r: "-" if r is None else f"{r['env_steps_per_s']} ({', '.join(map(str, r['env_steps_per_s_each']))})"  # noqa: E731
        ratio = f"**{h['env_steps_per_s'] / t['env_steps_per_s']:.2f}x**" if t and h else "-"
        first = " / ".join("-" if r is None else str(r["first_s"]) for r in (t, h))
        lines.append(f"| {k[1]} | {k[2]} | {k[3]} | {k[6]} on {k[4]} | {k[5]} | {rate(t)} | {rate(h)} | {ratio} | {first} |")
    return lines


def write_table(stem: Path) -> Path:
    """``stem``.md rewritten from every row of ``stem``.jsonl (``table_lines``); printed."""
    lines = table_lines(read_rows(stem.with_suffix(".jsonl")))
    with atomic_write(stem.with_suffix(".md")) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return stem.with_suffix(".md")

if __name__ == "__main__":
    main()
