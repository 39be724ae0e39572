"""The results tables of README.md and ``bench/results/*/README.md``, generated from the committed
results records (``gnwarp.eval.records``) and benchmark rows, so that no number is typed by hand.

    PYTHONPATH=. python3 bench/results_tables.py            # rewrite every generated block
    PYTHONPATH=. python3 bench/results_tables.py --check    # exit 1 where a block differs from its records

A generated block sits between ``<!-- results:begin NAME -->`` and ``<!-- results:end NAME -->``;
``TABLES[NAME]`` makes its lines from files under the repository root (the provenance text outside
the markers stays hand-written). Cells of several episodes or seeds read "mean +- h", h the half
width of the 95% t interval of the mean (``gnwarp.eval.summarize.groups``); a single value stands
alone. The files scanned: README.md, ``bench/results/*/README.md`` and
``bench/results/sysid_figures/*/compare.md``.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import statistics
import sys
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from gnwarp.eval.records import read_records  # noqa: E402
from gnwarp.eval.summarize import DYNAMICS_LABELS, Group, groups, ratio  # noqa: E402

__all__ = ["TABLES", "BLOCK", "render", "documents", "run", "main"]

BLOCK = re.compile(r"(<!-- results:begin (?P<name>[\w./-]+) -->\n)(?P<body>.*?)(<!-- results:end (?P=name) -->)", re.S)
TABLES: dict[str, Callable[[Path, Path], list[str]]] = {}
RESULTS = Path("bench") / "results"


def table(name: str):
    """Register ``fn(root, doc) -> lines`` as the maker of block ``name`` (``doc``: the file it sits in)."""
    def wrap(fn):
        TABLES[name] = fn
        return fn
    return wrap


# -- reading -------------------------------------------------------------------------------------
def _groups(root: Path, rel: str) -> list[Group]:
    return groups(read_records(root / RESULTS / rel))


def _find(gs: list[Group], **match) -> Group | None:
    hits = [g for g in gs if all(getattr(g, k) == v for k, v in match.items())]
    return hits[-1] if hits else None


def _rows(root: Path, rel: str) -> list[dict]:
    """A benchmark's JSON-lines rows (or a JSON file's ``rows``)."""
    path = root / RESULTS / rel
    if path.suffix == ".json":
        return json.loads(path.read_text())["rows"]
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _row(rows: list[dict], **match) -> dict:
    hits = [r for r in rows if all(r.get(k) == v for k, v in match.items())]
    if not hits:
        raise LookupError(f"no benchmark row with {match}")
    return hits[-1]   # the newest run of those settings


# -- formatting ----------------------------------------------------------------------------------
def _num(x: float | None, digits: int = 2) -> str:
    """``x`` to ``digits`` significant digits, plainly where it is between 1e-4 and 1e5."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if x == 0:
        return "0"
    if 1e-4 <= abs(x) < 1e5:
        d = max(digits - 1 - int(math.floor(math.log10(abs(x)))), 0)
        return f"{x:.{d}f}"
    return f"{x:.{digits - 1}e}".replace("e-0", "e-").replace("e+0", "e")


def _cell(g: Group | None, digits: int = 3) -> str:
    """"mean +- 95% half width" of a group of several values, the value alone for one."""
    if g is None:
        return "-"
    if g.n > 1 and not math.isnan(g.ci):
        return f"{_num(g.mean, digits)} +- {_num(g.ci, 2)}"
    return _num(g.mean, digits)


def _pct(a: Group | None, b: Group | None) -> str:
    r = ratio(a.mean, b.mean) if a is not None and b is not None else None
    return "-" if r is None else f"{100 * r:.0f}%"


def _mean_se(r: dict) -> str:
    """A summary row's mean +- its standard error (the mean alone for one seed), rounded."""
    return f"{r['mean']:.0f}" + (f" +- {r['se']:.0f}" if r["se"] is not None else "")


def _fastest_1m(root: Path) -> tuple[float, dict] | None:
    """The RL run that trained 1M env steps in the fewest seconds of training (its
    ``progress.csv``'s ``seconds`` at the first round at or past 1M: rounds only, no evaluations
    or checkpoints): (seconds, its last record)."""
    import csv
    best = None
    for prog in sorted((root / RESULTS / "rl").rglob("progress.csv")):
        with open(prog, newline="") as f:
            rows = [r for r in csv.DictReader(f) if int(float(r.get("env_steps") or 0)) >= 1_000_000]
        recs = read_records(prog.with_name("records.jsonl")) if prog.with_name("records.jsonl").is_file() else []
        if rows and recs and (best is None or float(rows[0]["seconds"]) < best[0]):
            best = (float(rows[0]["seconds"]), recs[-1])   # the first round at or past 1M
    return best


def _agent(agent: str) -> str:
    """An RL agent's name in a table: DDPG, SVG(0) .. SVG(5)."""
    return agent.upper().replace("SVG", "SVG(") + (")" if agent.startswith("svg") else "")


def _note(what: str, where: str) -> str:
    return (f"Generated by `python bench/results_tables.py` from {where}: {what}.")


def _pm_note(over: str, where: str) -> str:
    return _note(f"mean +- half width of the 95% t interval of the mean over {over}", where)


def _md(head: list[str], rows: list[list[str]]) -> list[str]:
    return (["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            + ["| " + " | ".join(r) + " |" for r in rows])


# -- README.md -----------------------------------------------------------------------------------
@table("headline")
def headline(root: Path, doc: Path) -> list[str]:
    """README.md's headline table: one row per experiment, linking its folder."""
    link = lambda name: f"[bench/results/{name}](bench/results/{name}/README.md)"  # noqa: E731
    rows = []
    dg = _row(_rows(root, "datagen/datagen_nvidia-h200.json"), system="cheetah", backend="mujoco_warp")
    rows.append([f"dataset generation, cheetah, {dg['sequences']} sequences x {dg['steps']} steps, one H200",
                 f"**{dg['end_to_end_seconds']:.2f} s** end to end (MuJoCo-Warp)", link("datagen")])
    run = _train_loop_run(_rows(root, "train_loop/train_loop_nvidia-h200.jsonl"))
    sps = {p: run[p][1]["steps_per_s"] for p in ("tf32", "fp16")}
    rows.append(["`gnwarp train`, paper core, cheetah, one H200",
                 f"**{sps['tf32']:.0f}** steps/s (tf32), **{sps['fp16']:.0f}** (fp16)", link("train_loop")])
    fm = _groups(root, "forward_models/results.jsonl")
    sweep = _groups(root, "mlp_sweep/results.jsonl")
    gn20 = {g.task: g.mean for g in fm if g.variant == "GN" and g.episode_steps == 20}
    best = {s: min(g.mean for g in sweep if g.task == s and g.episode_steps == 20 and g.variant.startswith("MLP"))
            for s in gn20}
    below = sum(gn20[s] < best[s] for s in gn20)
    sizes = len({g.variant for g in sweep if g.variant.startswith("MLP")})
    rows.append([f"forward models on the {len(gn20)} systems",
                 f"GN 20-step error {_num(min(gn20.values()))}-{_num(max(gn20.values()))} of the constant "
                 f"baseline; below the best of {sizes} MLPs on {below} of {len(gn20)}",
                 "[forward_models](bench/results/forward_models/README.md), "
                 "[mlp_sweep](bench/results/mlp_sweep/README.md)"])
    ab = _groups(root, "ablation_h2/results.jsonl")
    one, two = (_find(ab, variant=v, episode_steps=20) for v in ("IN", "GN2-skip"))
    rows.append(["architecture ablation (Figure H.2), 20-step error, 3 seeds",
                 f"two GNs (with skip) {one.mean / two.mean:.1f}x lower than one interaction network "
                 f"({_cell(two, 2)} against {_cell(one, 2)})", link("ablation_h2")])
    med = _sysid_medians(root / RESULTS / "sysid_figures" / "per_sequence", test=1000)
    rows.append(["system identification (Figure 8), sysid / true-parameter model, median over runs on 1000 "
                 "test sequences",
                 ", ".join(f"{med[s]:.2f}x {s}" for s in ("cheetah", "pendulum", "cartpole", "jaco") if s in med),
                 link("sysid_figures")])
    ctl = _groups(root, "control/results.jsonl")
    share = []
    for task, name in (("pendulum-balance", "pendulum"), ("cartpole-balance", "cartpole"),
                       ("acrobot-swingup", "acrobot"), ("swimmer-reach", "swimmer"),
                       ("cheetah-forward", "cheetah-forward"), ("walker-forward", "walker-forward")):
        gn, ilqg = _find(ctl, task=task, planner="gradient", variant=""), _find(ctl, task=task, planner="ilqg")
        share.append(f"{_pct(gn, ilqg)} {name}")
    summary = json.loads((root / RESULTS / "control" / "summary.json").read_text())
    run = [r for r in summary if r["task"] == "dmc-cheetah-run"]
    loop = [r["mean"] for r in run if r["protocol"] == "loop" and r["variant"] == "loop"]
    oracle = [r for r in run if r["planner"] == "sampling" and r["dynamics"] == "true_mjwarp"]
    dmc = ""
    if loop and oracle:
        dmc = (f"; DMC cheetah-run: {min(loop):.0f}-{max(loop):.0f} in the data loop (to "
               f"{max(r['env_steps'] for r in run if r['protocol'] == 'loop') // 1000}k env steps) against "
               f"{oracle[0]['mean']:.0f} for sampling on the true dynamics")
    rows.append(["gradient MPC through the learned model against iLQG on true MuJoCo (returns)",
                 ", ".join(share) + dmc, link("control")])
    lat = {(r["system"], r["episodes"], r["horizon"], r["iterations"], r["path"], r["precision"]): r
           for r in json.loads((root / RESULTS / "mpc_latency_nvidia-h100-80gb-hbm3.json").read_text())}
    one = {p: lat["pendulum", 1, 50, 5, p, "tf32"]["steady_ms"] for p in ("fused", "unfused", "torch_graph")}
    big = {p: lat["pendulum", 4096, 100, 5, p, "tf32"]["steady_ms"] for p in ("fused", "unfused", "torch_graph")}
    rows.append(["gradient MPC planning step, pendulum, 5 iterations, one H100 (TF32)",
                 f"1 episode, horizon 50: **{one['fused']:.0f} ms** per 20 ms control step (fused model step), "
                 f"{one['unfused']:.0f} ms unfused, {one['torch_graph']:.0f} ms a torch peer in a CUDA graph; "
                 f"4096 episodes, horizon 100: **{big['fused']:.0f} ms** (unfused {big['unfused']:.0f}, torch peer "
                 f"{big['torch_graph']:.0f})", link("mpc_latency")])
    dist = json.loads((root / RESULTS / "distributed_nvidia-h100-80gb-hbm3.json").read_text())
    weak = {r["gpus"]: r for r in dist if r["mode"] == "weak" and r["run"] == "h100x4-b"}
    tte = [r for r in dist if r["mode"] == "weak" and r["run"] in ("h100x2-tte-b-s0", "h100x2-tte-b-s1")
           and r["gpus"] == 2]
    if len(tte) != 2 or any(r.get("time_to_error_ratio") is None for r in tte):
        raise SystemExit("distributed summary: runs h100x2-tte-b-s0 and -s1 need their 2-GPU time to error")
    n = max(weak)
    rows.append([f"training and generation on 1-{n} H100s of one host (torch.distributed, NCCL), weak scaling",
                 ", ".join(f"**{weak[g]['train_efficiency']:.0%}** training / {weak[g]['generate_efficiency']:.0%} "
                           f"generation efficiency at {g} GPUs" for g in sorted(weak) if g > 1)
                 + "; later 1-2 GPU runs: **{:.0%}** training at 2 GPUs, time to the same validation error "
                   "**{}** of one GPU's ({} seeds, the same graphs trained, learning rate x GPUs)".format(
                       min(r["train_efficiency"] for r in tte),
                       " and ".join(f"{r['time_to_error_ratio']:.2f}x" for r in tte), len(tte)),
                 link("distributed")])
    every = json.loads((root / RESULTS / "rl" / "summary.json").read_text())
    one = [r for r in every if r["networks"] == "mlp" and r.get("utd", 1.0) == 1   # one update an env step, in turn
           and not r.get("act_ahead", False) and not r.get("settings")]
    rl = [r for r in one if r["task"] == "dmc-swimmer-swimmer6" and r["preset"] == "spinningup"]
    at1m, shared1m = (max((r for r in every if r["task"] == "dmc-swimmer-swimmer6" and r["agent"] == "svg1"
                           and r["preset"] == "spinningup" and r["networks"] == "mlp" and r.get("utd", 1.0) == 1
                           and not r.get("settings") and (r.get("eval_seed") is None) == own
                           and r["env_steps"] == 1000000), key=lambda r: r["seeds"], default=None)
                      for own in (True, False))   # runs on their own seeds' states; on shared states
    fast = _fastest_1m(root)
    at500 = {}   # (task, agent): the 500k row in turn, else acting ahead (walker-walk SVG(1))
    for r in sorted((r for r in every if r["networks"] == "mlp" and r.get("utd", 1.0) == 1
                     and not r.get("settings") and r["env_steps"] == 500000
                     and r["task"] in ("dmc-walker-walk", "dmc-cheetah-run")),
                    key=lambda r: not r.get("act_ahead", False)):
        at500[r["task"].split("-", 1)[1], r["agent"]] = r
    at = {(r["agent"], r["env_steps"]): r for r in rl}
    ups = {r["agent"]: r for r in _rows(root, "rl/rl_agents_nvidia-h100-80gb-hbm3.jsonl")
           if r["batch"] == 100 and r.get("networks", "mlp") == "mlp"}
    names = {a: _agent(a) for a in ("svg1", "svg0", "ddpg")}
    pts = [f"{names[a]} " + " / ".join(_mean_se(at[a, s]) for s in (250000, 500000) if (a, s) in at)
           + f" ({min(at[a, s]['seeds'] for s in (250000, 500000) if (a, s) in at)} seeds)"
           for a in names if (a, 250000) in at]
    last = max(s for (a, s) in at if a == "ddpg")
    rows.append(["RL on DMC (SpinningUp preset, MLPs): swimmer6 return at 250k / 500k env steps, mean +- s.e. "
                 "over seeds",
                 ", ".join(pts) + f"; DDPG at {last / 1e6:g}M {_mean_se(at['ddpg', last])} (SpinningUp 351 +- 19); "
                 + ("" if at1m is None else f"SVG(1){' acting ahead' * bool(at1m.get('act_ahead'))} at 1M "
                    f"{_mean_se(at1m)} ({at1m['seeds']} seed{'s' * (at1m['seeds'] > 1)}; "
                    f"post-stratified by the targets' distance {_stratified_mean_se(root, at1m)}"
                    + ("" if shared1m is None or shared1m.get("act_ahead") != at1m.get("act_ahead") else
                       f"; {_mean_se(shared1m)} raw on {shared1m['seeds']} other seeds evaluated on shared states")
                    + "); ")
                 + "".join(f"{t} {names[a]}{' acting ahead' * bool(w.get('act_ahead'))} at 500k {_mean_se(w)} "
                           f"({w['seeds']} seed{'s' * (w['seeds'] > 1)}); "
                           for (t, a), w in sorted(at500.items()) if a in names)
                 + "updates replayed from a CUDA graph "
                 f"**{ups['svg1']['graph_speedup']:.1f}x** eager's (SVG(1), one H100)"
                 + ("" if fast is None else f"; 1M env steps in **{fast[0] / 60:.0f} min** of training "
                    f"({_agent(fast[1].config['agent'])} on "
                    f"{fast[1].task.replace('dmc-', '')}, one {fast[1].gpu}, "
                    f"{DYNAMICS_LABELS.get(fast[1].dynamics, fast[1].dynamics).removeprefix('true, ')})"), link("rl")])
    rj = _groups(root, "recurrent_jaco/results.jsonl")
    gain = [_find(rj, variant="feed-forward, angle (rad)", episode_steps=t).mean
            / _find(rj, variant="recurrent, angle (rad)", episode_steps=t).mean for t in (1, 10, 20)]
    rows.append(["recurrent model, partly observed JACO, joint-angle error at 1, 10 and 20 steps",
                 f"{min(gain):.1f}-{max(gain):.1f}x lower than feed-forward (equal 150 s budgets: the recurrent "
                 "model trained 954 steps, the feed-forward 1497; both under-trained)", link("recurrent_jaco")])
    return _md(["what", "result", "details"], rows)


def _train_loop_run(rows: list[dict], eager_steps: int = 200, steps: int = 20000) -> dict[str, tuple[dict, dict]]:
    """{precision: (eager row, captured row)} of the newest ``flat_adam`` run of train_loop.py's
    command in its notes (``--eager-steps 200 --steps 20000``): each captured row follows its
    precision's eager row."""
    out = {}
    for eager, cap in zip(rows, rows[1:]):
        if (eager.get("optimizer") == cap.get("optimizer") == "flat_adam" and not eager.get("captured")
                and cap.get("captured") and eager.get("precision") == cap.get("precision")
                and eager.get("steps") == eager_steps and cap.get("steps") == steps):
            out[cap["precision"]] = (eager, cap)
    if not out:
        raise LookupError(f"no train_loop run with --eager-steps {eager_steps} --steps {steps}")
    return out


def _sysid_medians(folder: Path, test: int) -> dict[str, float]:
    """{system: median over the folder's labelled runs on ``test`` test sequences of sysid's error
    / the true-parameter model's}."""
    fig8 = _sysid_runs(folder)
    out = {}
    for s in dict.fromkeys(s for s, _ in fig8):
        vals = [fig8[s, run]["sysid same"].mean / fig8[s, run]["true params"].mean for (t, run) in fig8
                if t == s and {"sysid same", "true params"} <= set(fig8[t, run])
                and fig8[t, run]["true params"].n == test]
        if vals:
            out[s] = statistics.median(vals)
    return out


def _sysid_runs(folder: Path) -> dict[tuple[str, str], dict[str, Group]]:
    """{(system, run): {model: group}} of a sysid_figures folder's Figure 8 records (variant
    "<model> [<run>]")."""
    out: dict[tuple[str, str], dict[str, Group]] = {}
    for g in groups(read_records(folder / "records.jsonl")):
        m = re.fullmatch(r"(.+) \[(.+)\]", g.variant)
        if g.records[-1].experiment != "sysid_figures" or not m:
            continue
        out.setdefault((g.task, m.group(2)), {})[m.group(1)] = g
    return out


# -- bench/results/<name>/README.md ----------------------------------------------------------------
@table("control")
def control_table(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "control/results.jsonl")
    it = _groups(root, "control/swimmer_iterations.jsonl")
    cols = [("GN-MPC (learned)", dict(planner="gradient", dynamics="learned")),
            ("iLQG (true MuJoCo)", dict(planner="ilqg", dynamics="true_mujoco_c")),
            ("sampling (true)", dict(planner="sampling", dynamics="true_mjwarp")),
            ("sampling (learned)", dict(planner="sampling", dynamics="learned")),
            ("random", dict(planner="random", dynamics="none"))]
    summary = json.loads((root / RESULTS / "control" / "summary.json").read_text())
    flat = {r["task"] for r in summary if r.get("discriminative") is False and r["source"].endswith("results.jsonl")}
    rows = []
    for task in dict.fromkeys(g.task for g in gs):
        cells = [_find(gs, task=task, variant="", **m) for _, m in cols]
        name = f"{task} (non-discriminative)" if task in flat else task
        rows.append([name] + [_cell(c, 4) for c in cells] + [_pct(cells[0], cells[1])])
        if task == "swimmer-reach":
            g20 = _find(it, variant="20 iterations, lr 0.1")
            if g20 is not None:
                rows.append(["swimmer-reach, GN-MPC with 20 iterations per step", _cell(g20, 4), "", "", "", "",
                             _pct(g20, cells[1])])
    return [_pm_note("20 episodes", "`results.jsonl` and `swimmer_iterations.jsonl`"), ""] + _md(
        ["task"] + [c for c, _ in cols] + ["GN-MPC / iLQG"], rows)


@table("control-dmc")
def control_dmc(root: Path, doc: Path) -> list[str]:
    """DeepMind Control tasks: every summary row of a "dmc-" task (``bench/control_summary.py``)."""
    rows = [r for r in json.loads((root / RESULTS / "control" / "summary.json").read_text())
            if r["task"].startswith("dmc-") and r["protocol"] == "paper"]
    out = []
    for r in rows:
        recs = read_records(root / r["source"])
        ms = [x.metrics.get("plan_ms_steady") for x in recs if x.task == r["task"] and x.planner == r["planner"]
              and x.dynamics == r["dynamics"] and x.variant == r["variant"]]
        ms = [m for m in ms if m is not None]
        out.append([r["task"], r["planner"] + (f" ({r['variant']})" if r["variant"] else ""), r["dynamics"],
                    str(r["seeds"]), str(r["episodes"]), _num(r["mean"], 3),
                    f"[{_num(r['ci95'][0], 3)}, {_num(r['ci95'][1], 3)}]", r["over"],
                    _num(statistics.median(ms), 3) if ms else "-"])
    return [_note("mean return over all episodes (0-1000 scale), its 95% bootstrap interval over the seeds' means "
                  "(or over the episodes of one seed)", "`summary.json` (from the records under `dmc/`)"), ""] + _md(
        ["task", "planner", "dynamics", "seeds", "episodes", "mean", "95% interval", "over", "plan ms / step"], out)


def _loop_rows(root: Path, rel: str, episodes: str) -> list[str]:
    """A data loop's records (``gnwarp loop``): one row per iteration, the model's errors on the
    iteration's new states beside those on its training data (the paper's Figure H.1)."""
    out = []
    for r in read_records(root / RESULTS / rel):
        e = r.metrics.get("errors", {})
        new, old = e.get("new", {}), e.get("trained", {})
        out.append([str(r.metrics.get("iteration")), str(r.env_steps), _num(statistics.fmean(r.returns), 3),
                    _num(new.get("one_step"), 2), _num(new.get("rollout"), 2), _num(old.get("one_step"), 2),
                    _num(old.get("rollout"), 2)])
    return [_note(f"per iteration: the mean true return of its episodes ({episodes}, before the model trains on "
                  "them) and the model's normalized one-step and 20-step rollout errors on those new states and "
                  "on its training data, before it trains on them", f"`{Path(rel).name}` of `{Path(rel).parent}`"),
            ""] + _md(["iteration", "env steps", "mean return", "new: one-step", "new: rollout", "trained: one-step",
                       "trained: rollout"], out)


@table("control-loop")
def control_loop(root: Path, doc: Path) -> list[str]:
    """The data loop on cheetah-run: one row per iteration."""
    return _loop_rows(root, "control/loop_cheetah_run/records.jsonl", "16, planned")


@table("rl-h1")
def rl_h1(root: Path, doc: Path) -> list[str]:
    """Figure H.1: a model trained on random-control swimmer6 data, on the trained SVG(1) agent's states."""
    return _loop_rows(root, "rl/h1_swimmer6/records.jsonl", "4, the trained SVG(1) policy's")


@table("rl-curves")
def rl_curves(root: Path, doc: Path) -> list[str]:
    """Every learning curve of ``rl/summary.json`` (task, agent, networks, utd, act_ahead, settings, eval_seed) at 100k,
    250k and 500k env steps and at its last point: mean +- s.e. over seeds (median; seeds); the true simulators its seeds ran."""
    from bench.rl_summary import eval_order
    rows = json.loads((root / RESULTS / "rl" / "summary.json").read_text())
    groups: dict[tuple, dict[int, dict]] = {}
    for r in rows:
        groups.setdefault((r["task"], r["agent"], r["preset"], r["networks"], r.get("utd", 1.0),
                           r.get("act_ahead", False), r.get("settings", ""), r.get("eval_seed")), {})[r["env_steps"]] = r
    cell = lambda r: "" if r is None else f"{_mean_se(r)} ({r['median']:.0f}; {r['seeds']})"   # noqa: E731
    order = {"ddpg": -1}
    out = []
    for (task, agent, preset, nets, utd, ahead, tag, es), pts in sorted(groups.items(), key=lambda kv: (
            kv[0][0], kv[0][3] != "mlp", order.get(kv[0][1], 0), kv[0][1], kv[0][4], kv[0][5], kv[0][6],
            eval_order(kv[0][7]))):
        last = max(pts)
        name = _agent(agent)
        name += (("" if utd == 1 else f", {utd:g} updates / env step") + (", acting ahead" if ahead else "")
                 + (f", {tag.replace('=', ' ').replace(',', ', ')}" if tag else "")
                 + ("" if es is None else f", evaluated on the states of eval_seed {es}"))
        sims = sorted({DYNAMICS_LABELS.get(d, d).removeprefix("true, ") for r in pts.values()
                       for d in r["dynamics"]})
        out.append([task.replace("dmc-", ""), name, nets, " and ".join(sims),
                    *(cell(pts.get(s)) for s in (100000, 250000, 500000)),
                    f"{cell(pts[last])} at {last / 1000:.0f}k"])
    return ([_note("mean +- standard error over seeds of each seed's mean evaluation return (median; seeds); "
                   f"preset {', '.join(sorted({k[2] for k in groups}))}", "`summary.json`")]
            + [""] + _md(["task", "agent", "networks", "simulator", "100k", "250k", "500k", "last point"], out))


def _seed_ids(seeds) -> str:
    """Seed numbers as runs: 0-2, 6."""
    out, run = [], []
    for s in sorted(seeds):
        if run and s != run[-1] + 1:
            out.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
            run = []
        run.append(s)
    if run:
        out.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
    return ", ".join(out)


NEAR = 1.25   # m: a swimmer6 target this near the nose at the start counts as near (rl/eval_states_swimmer6.jsonl)


def _stratified_mean_se(root: Path, row: dict) -> str:
    """A swimmer6 summary row's mean +- standard error over its seeds with each seed's mean
    post-stratified by its targets' distance (``_swimmer_strata``), as ``_mean_se`` writes one."""
    from bench.rl_summary import _run, seed_means
    v = seed_means(root, stratify=_swimmer_strata(root))[(row["task"], *_run(row), row["env_steps"])]
    x = [m for m, *_ in v.values()]
    if len(x) < 2:
        return f"{x[0]:.0f}"
    return f"{statistics.fmean(x):.0f} +- {statistics.stdev(x) / math.sqrt(len(x)):.0f}"


def _swimmer_distances(root: Path):
    """A function of a swimmer6 record giving its evaluation episodes' target distances from the
    nose at the start (its evaluation set's, ``rl/eval_targets_swimmer6.jsonl``); None for other
    tasks' records. A swimmer6 record whose set is not in the file raises ``LookupError``
    (``bench/rl_targets.py --runs`` writes it again)."""
    import numpy as np
    sets = {(r["eval_seed"], r["episodes"]): np.asarray(r["distances"])
            for r in _rows(root, "rl/eval_targets_swimmer6.jsonl")}

    def distances(rec):
        if rec.task != "dmc-swimmer-swimmer6":
            return None
        es = (rec.config or {}).get("eval_seed")
        key = (rec.seed if es is None else es, len(rec.returns))
        if key not in sets:
            raise LookupError(f"no target distances of evaluation set {key} (eval seed, episodes) in "
                              "rl/eval_targets_swimmer6.jsonl: run PYTHONPATH=. python3 bench/rl_targets.py --runs "
                              "bench/results/rl --out bench/results/rl/eval_targets_swimmer6.jsonl")
        return sets[key]
    return distances


def _swimmer_strata(root: Path):
    """``bench.rl_summary.seed_means``'s ``stratify`` for swimmer6: a record's episodes whose target
    lies within ``NEAR`` of the nose at the start (``_swimmer_distances``) and the share of such
    targets in the suite's own draw (``rl/eval_states_swimmer6.jsonl``'s population row); None for
    other tasks' records; ``LookupError`` for a swimmer6 record without its set's distances: its raw
    mean must not pass for a stratified one."""
    shares = [r["share"] for r in _rows(root, "rl/eval_states_swimmer6.jsonl")
              if r["eval_seed"] is None and r["near"] == NEAR]
    if not shares:
        raise LookupError(f"no population row at near {NEAR} m in rl/eval_states_swimmer6.jsonl: run PYTHONPATH=. "
                          f"python3 bench/rl_targets.py --eval-states 100 --near {NEAR} --out "
                          "bench/results/rl/eval_states_swimmer6.jsonl")
    share, distances = shares[-1], _swimmer_distances(root)

    def strata(rec):
        d = distances(rec)
        return None if d is None else (d < NEAR, share)
    return strata


REACH_BANDS = (0.0, 0.75, NEAR, 1.6)   # m: lower edges of the target-distance bands of rl-reach
REACH_STEPS = (100000, 250000, 500000, 750000, 1000000)


def _band_names() -> list[str]:
    """The headers of ``REACH_BANDS``' bands (the last open above)."""
    edges = (*REACH_BANDS, math.inf)
    return [f"{lo:g}-{hi:g} m" if math.isfinite(hi) else f">= {lo:g} m" for lo, hi in zip(edges[:-1], edges[1:])]


def _band_cells(ret, dist, count: bool = False) -> list[str]:
    """Per band of ``REACH_BANDS``: the mean of the finite returns ``ret`` whose target distance
    ``dist`` lies in it (with their number when ``count``), "" for none."""
    import numpy as np
    edges = (*REACH_BANDS, math.inf)
    cells = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (dist >= lo) & (dist < hi) & np.isfinite(ret)
        cells.append((f"{ret[m].mean():.0f} ({int(m.sum())})" if count else f"{ret[m].mean():.0f}") if m.any() else "")
    return cells


@table("rl-reach")
def rl_reach(root: Path, doc: Path) -> list[str]:
    """Swimmer6 evaluation returns by the target's distance from the nose at the start: per agent
    (spinningup, MLPs, one update an env step, default settings; in turn and acting ahead
    together) and env steps of ``REACH_STEPS``, the mean return of the episodes whose target lay in
    each band of ``REACH_BANDS`` (their count beside it), pooled over the seeds there (a rerun of a
    seed at the same env steps: the last record stands)."""
    import numpy as np

    from bench.rl_summary import _group, rl_records
    distances = _swimmer_distances(root)
    last: dict[tuple, tuple] = {}
    for r in rl_records(root):
        task, agent, preset, nets, utd, _ahead, tag, _es = _group(r)
        if (task == "dmc-swimmer-swimmer6" and (preset, nets, utd, tag) == ("spinningup", "mlp", 1.0, "")
                and agent in ("ddpg", "svg0", "svg1") and r.env_steps in REACH_STEPS):
            last[agent, r.env_steps, _group(r), r.seed] = (np.asarray(r.values, dtype=np.float64), distances(r))
    out = []
    for agent in ("ddpg", "svg0", "svg1"):
        for steps in REACH_STEPS:
            got = [v for k, v in last.items() if k[:2] == (agent, steps)]
            if not got:
                continue
            ret, dist = np.concatenate([g[0] for g in got]), np.concatenate([g[1] for g in got])
            out.append([_agent(agent), f"{steps / 1000:.0f}k", str(len(got)), *_band_cells(ret, dist, count=True)])
    names = _band_names()
    return [_note("swimmer6, spinningup preset, MLPs, one update an env step, in turn and acting ahead together: "
                  "the mean return of the evaluation episodes whose target started in each band of distance "
                  "from the nose (their number), pooled over the seeds (runs) there", "the records and "
                  "`eval_targets_swimmer6.jsonl`"), ""] + _md(["agent", "env steps", "runs", *names], out)


GAMMA_STEPS = (250000, 500000)
GAMMA_WINDOW = (300000, 500000)   # env steps: the evaluations averaged in rl-gamma's window row


@table("rl-gamma")
def rl_gamma(root: Path, doc: Path) -> list[str]:
    """Swimmer6 SVG(1) (spinningup, MLPs, one update an env step, acting ahead) at each discount
    set alone off its default (``agent_settings.gamma``) against the default (0.99), every run
    evaluated on the same states (one
    ``eval_seed``): at ``GAMMA_STEPS`` and over ``GAMMA_WINDOW`` (each seed's mean of its
    evaluations there, every 50k of the window present), each discount on the seeds it shares
    with 0.99 (two or more, as many evaluation episodes, finite means; a seed's runs share their
    initial weights and states): a 0.99 row on those seeds, then the discount's row (a seed set
    shared by both discounts gets one 0.99 row): the seeds' returns, their mean, the paired
    difference from 0.99 with its 95% t interval, and the mean return per band of the target's
    starting distance (``REACH_BANDS``), pooled over the seeds."""
    import numpy as np

    from bench.rl_summary import _group, paired_difference, rl_records
    from gnwarp.rl.settings import AgentSettings
    default = AgentSettings(agent="svg1", preset="spinningup").gamma
    distances = _swimmer_distances(root)
    got: dict[tuple, dict[int, dict[int, tuple]]] = {}   # (gamma, eval_seed) -> steps -> seed -> (values, distances)
    for r in rl_records(root):
        task, agent, preset, nets, utd, ahead, tag, es = _group(r)
        off = re.fullmatch(r"gamma=([0-9.]+)", tag)   # the discount alone off its default, or nothing off
        gamma = default if tag == "" else float(off.group(1)) if off else None
        if ((task, agent, preset, nets, utd, ahead) == ("dmc-swimmer-swimmer6", "svg1", "spinningup", "mlp", 1.0, True)
                and es is not None and gamma is not None):
            got.setdefault((gamma, es), {}).setdefault(r.env_steps, {})[r.seed] = (
                np.asarray(r.values, dtype=np.float64), distances(r))
    want = (GAMMA_WINDOW[1] - GAMMA_WINDOW[0]) // 50000 + 1

    def point(by: dict, steps) -> dict:   # seed -> (mean, values, distances) at steps, or over the window
        if steps is not None:
            return {k: (float(np.nanmean(v)), v, d) for k, (v, d) in by.get(steps, {}).items()
                    if np.isfinite(v).any()}
        at = [s for s in by if GAMMA_WINDOW[0] <= s <= GAMMA_WINDOW[1] and s % 50000 == 0]
        seeds = set.intersection(*(set(by[s]) for s in at)) if len(at) == want else set()
        return {k: (float(np.mean([np.nanmean(by[s][k][0]) for s in at])),
                    np.concatenate([by[s][k][0] for s in at]), np.concatenate([by[s][k][1] for s in at]))
                for k in seeds if all(np.isfinite(by[s][k][0]).any() for s in at)}

    def row(es, gamma, when, cur: dict, diff: str) -> list[str]:
        seeds = sorted(cur)
        cells = _band_cells(np.concatenate([cur[k][1] for k in seeds]), np.concatenate([cur[k][2] for k in seeds]))
        return [str(es), f"{gamma:g}", when, _seed_ids(seeds), " / ".join(f"{cur[k][0]:.0f}" for k in seeds),
                f"**{statistics.fmean(cur[k][0] for k in seeds):.0f}**", diff, *cells]
    out = []
    for es in sorted({e for g, e in got if g != default and (default, e) in got}):
        for steps in (*GAMMA_STEPS, None):
            when = (f"{steps / 1000:.0f}k" if steps is not None
                    else f"mean of {GAMMA_WINDOW[0] / 1000:.0f}-{GAMMA_WINDOW[1] / 1000:.0f}k")
            base, shown = point(got[default, es], steps), None
            for gamma in sorted(g for g, e in got if e == es and g != default):
                cur = point(got[gamma, es], steps)
                pair = sorted(k for k in set(cur) & set(base) if len(cur[k][1]) == len(base[k][1]))
                if len(pair) < 2:
                    continue
                if pair != shown:
                    out.append(row(es, default, when, {k: base[k] for k in pair}, ""))
                    shown = pair
                d, lo, hi, _ = paired_difference({k: cur[k][0] for k in pair}, {k: base[k][0] for k in pair})
                out.append(row(es, gamma, when, {k: cur[k] for k in pair}, f"{d:+.0f} [{lo:+.0f}, {hi:+.0f}]"))
    names = _band_names()
    return [_note("swimmer6 SVG(1), spinningup preset, MLPs, acting ahead on MuJoCo C, every run on the same "
                  "evaluation states (eval_seed): each discount against gamma 0.99 on the seeds the two share (a "
                  "0.99 row on those seeds above it): the seeds' mean returns (at that point, or each seed's mean "
                  "over the window's evaluations), their mean, the difference from gamma 0.99 paired on the seed "
                  "with its 95% t interval (seeds - 1 degrees of freedom), and the mean return of the episodes "
                  "whose target started in each band of distance from the nose, pooled over the seeds",
                  "the records and `eval_targets_swimmer6.jsonl`"), ""] + _md(
        ["eval_seed", "gamma", "env steps", "seeds", "per seed", "mean", "minus gamma 0.99 (95% interval)", *names], out)


@table("rl-goals")
def rl_goals(root: Path, doc: Path) -> list[str]:
    """SVG(1) against SVG(0) per task (spinningup, MLPs, one update an env step, default agent
    settings; SVG(0) in turn, SVG(1) in turn and, as a row of its own, acting ahead; runs evaluated
    on shared states, ``eval_seed``, against the SVG(0) run of the same loop and states): at every
    250k env steps both reached and at the last point both share, where each has two seeds or
    more, each run's mean +- s.e. over its seeds there (which seeds: a later point holds only
    those that got there) and the difference of means with its 95% Welch interval."""
    from bench.rl_summary import seed_means
    return [_note("spinningup preset, MLPs, where both runs have two seeds or more: mean +- standard error over "
                  "the seeds at that point (a later point holds only the seeds that got there); the difference "
                  "SVG(1) - SVG(0) (SVG(0) in turn) and its 95% Welch interval (Student's t at the "
                  "Welch-Satterthwaite degrees of freedom, rounded down)", "the records"), ""] + _goals(seed_means(root))


@table("rl-goals-stratified")
def rl_goals_stratified(root: Path, doc: Path) -> list[str]:
    """``rl-goals`` on swimmer6 with each seed's mean post-stratified by its targets' distance
    (``_swimmer_strata``): the share of near targets each seed's evaluation drew taken out."""
    from bench.rl_summary import seed_means
    by = {k: v for k, v in seed_means(root, stratify=_swimmer_strata(root)).items() if k[0] == "dmc-swimmer-swimmer6"}
    return [_note(f"as rl-goals, on swimmer6, each seed's mean post-stratified: the mean of its episodes whose "
                  f"target lay within {NEAR} m of the nose at the start and of the rest, weighted by the suite's "
                  "share of such targets", "the records, `eval_targets_swimmer6.jsonl` and "
                  "`eval_states_swimmer6.jsonl`"), ""] + _goals(by)


def _goal_points(steps: list[int]) -> list[int]:
    """The env steps a goals table reports of the sorted ``steps`` both runs reached: every
    multiple of 250k, and the last."""
    at = [s for s in steps if s and s % 250000 == 0]
    return at + ([steps[-1]] if steps and steps[-1] not in at else [])


@table("rl-goals-paired")
def rl_goals_paired(root: Path, doc: Path) -> list[str]:
    """``rl-goals`` blocked on the evaluation states: a run evaluated on its own seed's states
    (no ``eval_seed``) shares them with every other run of that seed and task, so SVG(1) seed k
    against SVG(0) seed k (the same pairs of loops as rl-goals) differs by the agents and their
    training only, not by the targets drawn; the paired difference over the seeds both reached
    (with equal evaluation episodes) and its 95% t interval. Runs evaluated on shared states
    (``eval_seed``: every seed's the same) pair SVG(1) seed k with the SVG(0) run of the same loop
    and states, seed k: blocked on the training seed only (rl-goals' Welch interval, unpaired, is
    the other reading of them)."""
    from bench.rl_summary import paired_difference, seed_means
    from bench.rl_summary import eval_order
    runs: dict[tuple, dict[int, dict[int, tuple]]] = {}
    for (task, agent, preset, nets, utd, ahead, tag, es, steps), v in seed_means(root).items():
        if (preset, nets, utd, tag) == ("spinningup", "mlp", 1.0, "") and agent in ("svg0", "svg1"):
            runs.setdefault((task, agent, ahead, es), {})[steps] = v
    out = []
    for task, ahead, es in sorted({(t, a, e) for t, ag, a, e in runs if ag == "svg1"},
                                  key=lambda k: (k[0], k[1], eval_order(k[2]))):
        one = runs[task, "svg1", ahead, es]
        zero = runs.get((task, "svg0", False, None) if es is None else (task, "svg0", ahead, es), {})
        shared = {s: [k for k in set(one[s]) & set(zero[s]) if one[s][k][1] == zero[s][k][1]   # as many episodes
                      and math.isfinite(one[s][k][0]) and math.isfinite(zero[s][k][0])]
                  for s in set(one) & set(zero)}
        both = sorted(s for s, ks in shared.items() if len(ks) >= 2)
        at = _goal_points(both)
        for s in at:
            a = {k: one[s][k][0] for k in shared[s]}
            b = {k: zero[s][k][0] for k in shared[s]}
            d, lo, hi, seeds = paired_difference(a, b)
            out.append([task.replace("dmc-", ""), ("acting ahead" if ahead else "in turn")
                        + ("" if es is None else f", both on the states of eval_seed {es}"), f"{s / 1000:.0f}k",
                        _seed_ids(seeds), f"{statistics.fmean(a.values()):.0f}",
                        f"{statistics.fmean(b.values()):.0f}", f"{d:+.0f}", f"[{lo:+.0f}, {hi:+.0f}]",
                        "yes" if lo > 0 or hi < 0 else "no"])
    return [_note("spinningup preset, MLPs, runs each evaluated on its own seed's states: SVG(1) seed k "
                  "against SVG(0) seed k (SVG(0) in turn) on the same evaluation states, over the seeds "
                  "both reached; runs on shared states (eval_seed): SVG(1) seed k against SVG(0) seed k of the "
                  "same loop and states (paired on the training seed); the mean of the paired differences and its 95% t interval (seeds - 1 "
                  "degrees of freedom)", "the records"), ""] + _md(
        ["task", "SVG(1) loop", "env steps", "seeds", "SVG(1)", "SVG(0)", "paired difference", "95% interval",
         "excludes 0"], out)


def _goals(by: dict) -> list[str]:
    """rl-goals' table of ``seed_means``' output ``by``."""
    from bench.rl_summary import difference, eval_order
    runs: dict[tuple, dict[int, dict[int, float]]] = {}
    for k, v in by.items():
        task, agent, preset, nets, utd, ahead, tag, es, steps = k
        if (preset, nets, utd, tag) == ("spinningup", "mlp", 1.0, "") and agent in ("svg0", "svg1") and (
                es is not None or (agent, ahead) != ("svg0", True)):
            runs.setdefault((task, agent, ahead, es), {})[steps] = {seed: m for seed, (m, *_) in v.items()}

    def cell(v: dict) -> str:
        x = list(v.values())
        return f"{statistics.fmean(x):.0f} +- {statistics.stdev(x) / math.sqrt(len(x)):.0f} (seeds {_seed_ids(v)})"
    out = []
    for task, ahead, es in sorted({(t, a, e) for t, ag, a, e in runs if ag == "svg1"},
                                  key=lambda k: (k[0], k[1], eval_order(k[2]))):
        one = runs.get((task, "svg1", ahead, es), {})
        zero = runs.get((task, "svg0", False, None) if es is None else (task, "svg0", ahead, es), {})
        both = sorted(s for s in set(one) & set(zero) if min(len(one[s]), len(zero[s])) >= 2)
        at = _goal_points(both)
        for s in at:
            d, lo, hi = difference(list(one[s].values()), list(zero[s].values()))
            out.append([task.replace("dmc-", ""), ("acting ahead" if ahead else "in turn")
                        + ("" if es is None else f", both on the states of eval_seed {es}"), f"{s / 1000:.0f}k",
                        cell(one[s]), cell(zero[s]), f"{d:+.0f}", f"[{lo:+.0f}, {hi:+.0f}]",
                        "yes" if lo > 0 or hi < 0 else "no"])
    return _md(["task", "SVG(1) loop", "env steps", "SVG(1)", "SVG(0)", "difference", "95% interval", "excludes 0"], out)


@table("rl-eval-noise")
def rl_eval_noise(root: Path, doc: Path) -> list[str]:
    """How much of the spread between seeds is the evaluation's own: per swimmer6 curve (MLPs, one
    update an env step, default agent settings) with three seeds or more at 250k and 500k, the
    variance of a seed's mean from its own episodes (their variance / episodes, averaged over the
    seeds) against the variance of the seeds' means, and their ratio. Runs on shared evaluation
    states (``eval_seed``) are left out: there the targets' draw is the same for every seed and
    does not enter the spread between them."""
    from bench.rl_summary import seed_means
    strat = seed_means(root, stratify=_swimmer_strata(root))
    curves: dict[tuple, dict[int, tuple[float, float, int, float]]] = {}
    for key, v in seed_means(root).items():
        task, agent, preset, nets, utd, ahead, tag, es, steps = key
        kept = [seed for seed, (_, _, _, var) in v.items() if math.isfinite(var)]   # the same seeds both ways
        if (task == "dmc-swimmer-swimmer6" and (nets, utd, tag, es) == ("mlp", 1.0, "", None)
                and steps in (250000, 500000) and len(kept) >= 3):
            curves.setdefault((agent, preset, ahead), {})[steps] = (
                statistics.fmean(v[k][3] for k in kept), statistics.variance(v[k][0] for k in kept), len(kept),
                statistics.variance(strat[key][k][0] for k in kept))
    out = []
    for (agent, preset, ahead), pts in sorted(curves.items(), key=lambda kv: (kv[0][0] != "ddpg", kv[0])):
        cell = lambda p: "" if p is None else f"{p[0]:.0f} / {p[1]:.0f} (**{p[0] / p[1]:.2f}**; {p[2]} seeds)"  # noqa: E731
        post = lambda p: "" if p is None else f"{p[3]:.0f} ({p[3] / p[1]:.2f})"  # noqa: E731
        out.append([_agent(agent) + (", acting ahead" if ahead else ", in turn")
                    + ("" if preset == "spinningup" else f", preset {preset}"),
                    cell(pts.get(250000)), post(pts.get(250000)), cell(pts.get(500000)), post(pts.get(500000))])
    return [_note("per swimmer6 curve with three seeds or more at that point: the evaluation's own variance of a "
                  "seed's mean (its episodes' variance / episodes, averaged over the seeds) / the variance of the "
                  "seeds' means (ratio; seeds); then the variance of the seeds' means post-stratified by their "
                  "targets' distance (as rl-goals-stratified; its ratio to the raw one)", "the records"), ""] + _md(
        ["run", "250k", "250k, stratified", "500k", "500k, stratified"], out)


@table("rl-policy-mpc")
def rl_policy_mpc(root: Path, doc: Path) -> list[str]:
    """A trained agent planned over with its own model and Q-function (``policy-mpc``) against its
    policy alone, on the same initial states (``rl/policy_mpc/*.jsonl``): paired per episode."""
    import numpy as np
    from gnwarp.eval.summarize import t_quantile
    recs = [r for p in sorted((root / RESULTS / "rl" / "policy_mpc").glob("*.jsonl")) for r in read_records(p)]
    out = []
    for r in (r for r in recs if r.planner == "policy-mpc"):
        base = [b for b in recs if b.planner == "policy" and b.task == r.task and b.config["policy"] == r.config["policy"]
                and b.config["initial_qpos"] == r.config["initial_qpos"] and len(b.returns) == len(r.returns)]
        if not base:
            raise LookupError(f"no policy record on the initial states of {r.task} {r.config['policy']}")
        d = np.asarray(r.returns) - np.asarray(base[-1].returns)
        half = t_quantile(len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else math.nan
        s = r.config["settings"]
        se = lambda x: _mean_se({"mean": np.mean(x), "se": np.std(x, ddof=1) / math.sqrt(len(x))})   # noqa: E731
        out.append([r.task.replace("dmc-", ""), f"`{Path(r.config['policy']).name}`", str(len(d)), se(base[-1].returns),
                    se(r.returns), f"{d.mean():+.0f} [{d.mean() - half:+.0f}, {d.mean() + half:+.0f}]",
                    f"H {s['horizon']}, {s['samples']} + {s['policy_samples']} sequences, {s['iterations']} iterations, "
                    f"{s['elites']} elites, std {s['init_std']:g} to {s['min_std']:g}, temperature {s['temperature']:g}",
                    f"{r.metrics['steady_ms']:.0f}"])
    return ([_note("true returns (MuJoCo C, 1000-step episodes, the same initial states for both), mean +- standard "
                   "error over episodes; the difference planned - policy per episode with its 95% t interval; "
                   "steady ms a control step for all episodes together on the developers' 2-core CPU",
                   "`rl/policy_mpc/*.jsonl`")] + [""]
            + _md(["task", "agent", "episodes", "policy alone", "planned over (policy-mpc)", "difference [95%]",
                   "planner", "ms / step"], out))


@table("control-fig10")
def control_fig10(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "control/fig10/results.jsonl")
    cols = [("GN-MPC, no params", "no_params"), ("GN-MPC, true params", "true_params"),
            ("GN-MPC, system ID", "sysid")]
    rows = []
    for task in dict.fromkeys(g.task for g in gs):
        cells = [_find(gs, task=task, planner="gradient", variant=v) for _, v in cols]
        rnd = _find(gs, task=task, planner="random")
        rows.append([task] + [_cell(c, 4) for c in cells] + [_cell(rnd, 4), _pct(cells[2], cells[1])])
    return [_pm_note("20 episodes", "`fig10/results.jsonl`"), ""] + _md(
        ["task"] + [c for c, _ in cols] + ["random", "system ID / true"], rows)


@table("control-fig11")
def control_fig11(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "control/fig11/results.jsonl")
    rows = []
    for system in dict.fromkeys(g.system for g in gs):
        def dist(planner):
            g = _find(gs, system=system, planner=planner)
            if g is None:
                return "-", None
            m = g.records[-1].metrics
            return f"{m['initial_distance']:.2f} -> {m['final_distance_mean']:.2f} m", g
        gn, gg = dist("gradient")
        rnd, _ = dist("random")
        il, ig = dist("ilqg")
        rows.append([system, f"{gg.n}", gn, rnd, il + (f" (first {ig.n} episodes)" if ig is not None else "")])
    return [_note("the distance to the target at the start -> the mean at the end of the episodes",
                  "`fig11/results.jsonl`"), ""] + _md(
        ["system", "episodes", "GN-MPC", "random", "iLQG (true)"], rows)


def _error_pivot(root: Path, rel: str, cols: list[tuple[str, dict]], rows_by: str = "task",
                 extra: Callable | None = None) -> list[list[str]]:
    """One row per value of ``rows_by``: its groups matching each column's fields, then ``extra``'s cells."""
    gs = _groups(root, rel)
    out = []
    for key in dict.fromkeys(getattr(g, rows_by) for g in gs):
        cells = [_find(gs, **{rows_by: key}, **m) for _, m in cols]
        out.append([key] + [_cell(c, 2) for c in cells] + (extra(key, gs, cells) if extra else []))
    return out


@table("forward-models")
def forward_models_table(root: Path, doc: Path) -> list[str]:
    cols = [(f"{m} {t}", dict(variant=v, episode_steps=s)) for m, v in (("GN", "GN"), ("MLP", "MLP 3x512"))
            for t, s in (("one-step", 1), ("20-step", 20), ("100-step", 100))]

    def finite(key, gs, cells):
        v = cells[0].records[-1].metrics.get("stability_finite") if cells[0] else None
        return ["-" if v is None else "yes" if v else "no"]
    rows = _error_pivot(root, "forward_models/results.jsonl", cols, extra=finite)
    return [_note("model / constant-baseline error on 200 test sequences", "`results.jsonl`"), ""] + _md(
        ["system"] + [c for c, _ in cols] + ["GN 1000-step rollouts finite"], rows)


@table("mlp-sweep")
def mlp_sweep_table(root: Path, doc: Path) -> list[str]:
    sizes = ["3x128", "3x512", "9x128", "9x512", "5x256"]
    cols = [("GN", dict(variant="GN", episode_steps=20))] + [(s, dict(variant=f"MLP {s}", episode_steps=20))
                                                             for s in sizes]

    def vs(key, gs, cells):
        best = min(c.mean for c in cells[1:] if c is not None)
        r = best / cells[0].mean
        return [f"{r:.1f}x lower" if r >= 1 else f"{1 / r:.1f}x higher"]
    rows = _error_pivot(root, "mlp_sweep/results.jsonl", cols, extra=vs)
    return [_note("20-step model / constant-baseline error, one seed each", "`results.jsonl`"), ""] + _md(
        ["system"] + [c for c, _ in cols] + ["GN vs best MLP"], rows)


@table("budget-retrain")
def budget_retrain_table(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "budget_retrain/results.jsonl")
    rows = []
    for s in dict.fromkeys(g.task for g in gs):
        e = {(v, t): _find(gs, task=s, variant=f"{v} loop", episode_steps=t) for v in ("eager", "captured")
             for t in (1, 20, 100)}
        steps = [e[v, 20].records[-1].metrics.get("train_steps") for v in ("eager", "captured")]
        rows.append([s] + [f"{x / 1000:.0f}k" if x else "-" for x in steps]
                    + [_cell(e[v, t], 2) for t in (20, 100) for v in ("eager", "captured")])
    return [_note("model / constant-baseline error on 200 test sequences, 220 s of training", "`results.jsonl`"),
            ""] + _md(["system", "steps, eager loop", "steps, captured loop", "20-step error, eager", "captured",
                       "100-step error, eager", "captured"], rows)


@table("ablation-h2")
def ablation_table(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "ablation_h2/results.jsonl")
    names = {"IN": "one GN (IN)", "GN2-seq": "two GNs, sequential", "GN2-skip": "two GNs, with skip",
             "no-globals-seq": "first GN keeps input globals, seq", "no-globals-skip": "... skip",
             "no-nodes-seq": "... nodes, seq", "no-nodes-skip": "... nodes, skip",
             "no-edges-seq": "... edges, seq", "no-edges-skip": "... edges, skip"}
    cells = [(names.get(g.variant, g.variant), g) for g in gs if g.episode_steps == 20]
    return [_pm_note("3 seeds", "`results.jsonl`") + " 20-step rollout error / constant.", ""] + _md(
        [n for n, _ in cells], [[_cell(g, 2) for _, g in cells]])


@table("multi-system")
def multi_system_table(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "multi_system/results.jsonl")
    names = {"multi4": "one GN on 4 systems", "multi5": "one GN on 5 systems (with cheetah)"}
    tasks = ["pendulum", "cartpole", "acrobot", "swimmer6", "cheetah"]
    rows = [[names[v]] + [_cell(_find(gs, variant=v, task=t, episode_steps=20), 2) for t in tasks] for v in names]
    sw = [g for g in gs if g.variant == "swimmerN" and g.episode_steps == 20]
    rows.append(["SwimmerN (trained on N = 3-6, 8, 9)"] + [
        _cell(_find(sw, task=t), 2) if t == "swimmer6" else "-" for t in tasks])
    trained = (3, 4, 5, 6, 8, 9)
    unseen = sorted((int(g.task[7:]), g) for g in sw if g.task[7:].isdigit() and int(g.task[7:]) not in trained)
    return ([_note("20-step model / constant-baseline error on 200 test sequences", "`results.jsonl`"), ""]
            + _md(["model"] + tasks, rows) + ["", "SwimmerN on swimmers it never saw (20-step error):", ""]
            + _md([f"N = {n}" for n, _ in unseen], [[_cell(g, 2) for _, g in unseen]]))


@table("recurrent-jaco")
def recurrent_jaco_table(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "recurrent_jaco/results.jsonl")
    steps = [1, 10, 20, 50, 80]
    rows = [[m] + [_cell(_find(gs, variant=f"{m}, angle (rad)", episode_steps=t), 2) for t in steps]
            for m in ("constant", "recurrent", "feed-forward")]
    return [_note("RMS joint-angle error (rad) after the 20-step warm-up, over 200 test sequences",
                  "`results.jsonl`"), ""] + _md(["model"] + [f"{t} step{'s' * (t > 1)}" for t in steps], rows)


@table("speed-accuracy")
def speed_accuracy_table(root: Path, doc: Path) -> list[str]:
    gs = _groups(root, "speed_accuracy/results.jsonl")
    rows = []
    for s in dict.fromkeys(g.task for g in gs):
        mine = [g for g in gs if g.task == s]
        ms = lambda g: g.records[-1].metrics["ms_per_step"]  # noqa: E731
        # ties at the digits shown go to the other measure: the fastest of the equally accurate
        fast = min(mine, key=lambda g: (round(ms(g), 2), g.mean))
        good = min(mine, key=lambda g: (float(_num(g.mean)), ms(g)))
        rows.append([s, f"{ms(fast):.2f} {fast.variant} ({_num(fast.mean)})",
                     f"{ms(good):.2f} {good.variant} ({_num(good.mean)})",
                     f"{good.records[-1].metrics['mjwarp_ms_per_step']:.2f}"])
    return [_note("ms per rollout step of 4096 graphs; 20-step model / constant-baseline error in brackets",
                  "`results.jsonl`"), ""] + _md(
        ["system", "fastest GN: ms/step (error)", "most accurate GN: ms/step (error)", "MuJoCo-Warp ms/step"], rows)


@table("datagen")
def datagen_table(root: Path, doc: Path) -> list[str]:
    warp = _rows(root, "datagen/datagen_nvidia-h200.json")
    mjc = {r["system"]: r for r in _rows(root, "datagen/datagen_nvidia-h200_mujoco_c.json")}
    rows = []
    for r in warp:
        sub = r.get("substeps", 1)
        name = r["system"] + (f" ({sub} substeps)" if sub > 1 else "")
        rate = _num(r["data_steps_per_s"]) + (f" ({_num(r['physics_steps_per_s'])} physics)" if sub > 1 else "")
        c = mjc.get(r["system"])
        rows.append([name, rate, f"{r['end_to_end_seconds']:.2f}", _num(c["data_steps_per_s"]) if c else "-"])
    n = warp[0]
    return [_note(f"{n['sequences']} sequences x {n['steps']} steps on MuJoCo-Warp (MuJoCo C: "
                  f"{next(iter(mjc.values()))['sequences']} sequences)",
                  "`datagen_nvidia-h200.json` and `datagen_nvidia-h200_mujoco_c.json`"), ""] + _md(
        ["system", "MuJoCo-Warp data steps/s", "end-to-end s (sim + graphs + write)", "MuJoCo C data steps/s"], rows)


@table("train-loop")
def train_loop_table(root: Path, doc: Path) -> list[str]:
    rows = _rows(root, "train_loop/train_loop_nvidia-h200.jsonl")
    run = _train_loop_run(rows)
    adam = {p: _row(rows, precision=p, optimizer="adam", captured=True) for p in ("tf32", "fp16")}
    body = [[f"captured, `flat_adam` (the default on CUDA), {run['tf32'][1]['steps']} steps"]
            + [f"**{run[p][1]['steps_per_s']:.0f}**" for p in ("tf32", "fp16")],
            [f"captured, `adam` (an earlier run, {adam['tf32']['steps']} steps)"]
            + [f"{adam[p]['steps_per_s']:.0f}" for p in ("tf32", "fp16")],
            ["eager (`--set capture=false`), `flat_adam`"]
            + [f"{run[p][0]['steps_per_s']:.0f}" for p in ("tf32", "fp16")]]
    return [_note("steps/s of the newest run of `--eager-steps 200 --steps 20000` (the adam row: the newest "
                  "captured adam row)", "`train_loop_nvidia-h200.jsonl`"), ""] + _md(
        ["`gnwarp train` (steps/s)", "tf32", "fp16"], body)


# the parameters whose estimates a system's row shows, and how they read
ESTIMATED = {"pendulum": (["length"], "length"), "cartpole": (["pole_thickness"], "pole thickness"),
             "cheetah": (["length_torso"], "torso length"),
             "jaco": (["gear_joint_1", "gear_joint_2", "gear_joint_3"], "gears of joints 1-3")}


@table("sysid-per-sequence")
def sysid_per_sequence(root: Path, doc: Path) -> list[str]:
    """sysid_figures/README.md: the runs of ``per_sequence/`` on 1000 test sequences, per system."""
    runs = _sysid_runs(root / RESULTS / "sysid_figures" / "per_sequence")
    rows = []
    for s in ("pendulum", "cartpole", "cheetah", "jaco"):
        mine = sorted(((e["sysid same"].records[-1].seed or 0, e) for (t, _), e in runs.items()
                       if t == s and {"sysid same", "true params"} <= set(e) and e["true params"].n == 1000),
                      key=lambda x: x[0])
        if not mine:
            continue
        ratios = [e["sysid same"].mean / e["true params"].mean for _, e in mine]
        m = [e["sysid same"].records[-1].metrics for _, e in mine]
        med = lambda k: statistics.median(x[k] for x in m if k in x)  # noqa: E731
        params, label = ESTIMATED[s]
        est = [x["estimate_rel_rms"][p] for x in m for p in params if p in x.get("estimate_rel_rms", {})]
        teacher = mine[0][1]["sysid same"].records[-1].config.get("param_teacher", 1)
        rows.append([s + (f", teacher {teacher:g}" if teacher != 1 else ""),
                     ", ".join(f"{r:.2f}x" for r in ratios), f"{statistics.median(ratios):.2f}x",
                     f"{med('ratio_without_top_1pct'):.2f}x", f"{med('ratio_median_per_sequence'):.2f}x",
                     f"{label} {_num(100 * min(est), 3)}-{_num(100 * max(est), 3)}%" if est else "-"])
    return [_note("sysid / true-parameter model per run (seeds in order), the medians over runs of the ratio and "
                  "of its paired readings, and the estimates' relative rms error over runs",
                  "`per_sequence/records.jsonl`"), ""] + _md(
        ["system", "sysid / true, per seed", "median", "without the top 1%, median", "per sequence, median",
         "estimate, rel. rms"], rows)


def _span(values: list[float], digits: int = 2) -> str:
    """"lo-hi" of ``values`` at ``digits`` significant digits, one number where they read alike."""
    lo, hi = _num(min(values), digits), _num(max(values), digits)
    return lo if lo == hi else f"{lo}-{hi}"


# the best command's run labels per system in ``nominal_static/`` (the README's first table): the seed, then
# the setting (JACO: the teacher at 0.5 and 24 G_ID globals)
BEST_RUNS = {"pendulum": r"s\d+-ridge-w1-t-q1-h64-f4-gd-loc-nom", "cartpole": r"s\d+-ridge-w1-t-q1-h64-f4-gd-loc-nom",
             "cheetah": r"s\d+-ridge-w1-t-q1-h64-f4-gd-loc-nom", "jaco": r"s\d+-ridge-w1-t-q0.5-h64-f4-g24-loc-nom"}


@table("sysid-best")
def sysid_best(root: Path, doc: Path) -> list[str]:
    """sysid_figures/README.md: the best settings' runs in ``nominal_static/`` (``BEST_RUNS``), per system the
    ranges over runs (true params: over every reference model), each seed's ratio and the estimates."""
    runs = _sysid_runs(root / RESULTS / "sysid_figures" / "nominal_static")
    rows = []
    for s, pattern in BEST_RUNS.items():
        mine = sorted((e["sysid same"].records[-1].seed or 0, e) for (t, run), e in runs.items()
                      if t == s and re.fullmatch(pattern, run) and {"sysid same", "true params"} <= set(e))
        if not mine:
            continue
        es = [e for _, e in mine]
        refs = [x for e in es for x in e["true params"].records[-1].metrics.get("runs", [e["true params"].mean])]
        params, label = ESTIMATED[s]
        est = [e["sysid same"].records[-1].metrics.get("estimate_rel_rms", {}).get(p) for e in es for p in params]
        est = [x for x in est if x is not None]
        rows.append([s, _span([e["no params"].mean for e in es if "no params" in e]), _span(refs),
                     _span([e["sysid same"].mean for e in es]),
                     ", ".join(f"{e['sysid same'].mean / e['true params'].mean:.2f}x" for e in es),
                     f"{label} {_span([100 * x for x in est])}%" if est else "-"])
    return [_note("80-step rollout error / constant, ranges over the best command's runs (seeds in order)",
                  "`nominal_static/records.jsonl`"), ""] + _md(
        ["system", "no params", "true params", "sysid", "sysid / true, per seed", "estimate, rel. rms"], rows)


READOUT_RUNS = ("paper readout, seed 2", "ridge readout, seed 2")   # readouts_6000's same-command A/B


@table("sysid-readouts")
def sysid_readouts(root: Path, doc: Path) -> list[str]:
    """sysid_figures/README.md: the paper's readout beside the ridge readout, ``readouts_6000/``'s seed-2 runs."""
    runs = _sysid_runs(root / RESULTS / "sysid_figures" / "readouts_6000")
    rows = []
    for s in ("pendulum", "cartpole", "cheetah", "jaco"):
        p, r = (runs.get((s, run)) for run in READOUT_RUNS)
        if not p or not r:
            continue
        ratio = [e["sysid same"].mean / e["true params"].mean for e in (p, r)]
        rows.append([s, _span([p["no params"].mean, r["no params"].mean]),
                     f"{_num(p['true params'].mean)} / {_num(r['true params'].mean)}",
                     _num(p["sysid same"].mean, 3), _num(r["sysid same"].mean, 3)]
                    + [f"{x:.3g}x" for x in ratio])
    return [_note("80-step rollout error / constant of the runs " + " and ".join(f"'{x}'" for x in READOUT_RUNS),
                  "`readouts_6000/records.jsonl`"), ""] + _md(
        ["system", "no params", "true params (paper run / ridge run)", "sysid, paper readout", "sysid, ridge readout",
         "sysid / true, paper", "ridge"], rows)


@table("sysid-fig9")
def sysid_fig9(root: Path, doc: Path) -> list[str]:
    """sysid_figures/README.md: Figure 9 of the ridge readout's seed-2 run in ``readouts_6000/``."""
    gs = groups(read_records(root / RESULTS / "sysid_figures" / "readouts_6000" / "records.jsonl"))
    want = f"sysid same [{READOUT_RUNS[1]}]"
    cell = {}
    for g in gs:
        m = re.fullmatch(r"pendulum length x([\d.]+), (with|without) controls", g.task)
        if m and g.variant == want:
            cell[float(m.group(1)), m.group(2)] = g.mean
    rows = [[f"{x:g}", _num(cell.get((x, "with")), 2), _num(cell.get((x, "without")), 2)]
            for x in sorted({x for x, _ in cell})]
    return [_note(f"sysid's 80-step error / constant on pendulums of scaled length, run '{READOUT_RUNS[1]}'",
                  "`readouts_6000/records.jsonl`"), ""] + _md(
        ["length factor", "window with controls", "passive window"], rows)


PROBED = (("pendulum", "length"), ("pendulum", "mass"), ("cartpole", "cart_mass"), ("cartpole", "pole_length"),
          ("cheetah", "length_torso"), ("jaco", "gear_joint_1"))


@table("sysid-probe")
def sysid_probe(root: Path, doc: Path) -> list[str]:
    """sysid_figures/README.md: the linear probe's R^2 of the ridge readout's seed-2 run in ``readouts_6000/``."""
    runs = _sysid_runs(root / RESULTS / "sysid_figures" / "readouts_6000")
    rows = []
    for s, param in PROBED:
        e = runs.get((s, READOUT_RUNS[1]))
        r2 = e["sysid same"].records[-1].metrics.get("probe_r2", {}).get(param) if e else None
        rows.append([s, param.replace("_", " "), "-" if r2 is None else f"{r2:.2f}"])
    return [_note(f"R^2 on test instances of a linear probe from G_ID, run '{READOUT_RUNS[1]}'",
                  "`readouts_6000/records.jsonl`"), ""] + _md(["system", "parameter", "R^2"], rows)


# -- bench/results/sysid_figures/<run set>/compare.md ----------------------------------------------
@table("sysid-compare")
def sysid_compare(root: Path, doc: Path) -> list[str]:
    """A run set's Figure 8 runs side by side, from ``records.jsonl`` beside ``doc``: per system and
    run the errors, the reference runs, sysid / true and, where the run kept its per-sequence
    errors, the ratio's two paired readings (metrics of its sysid record)."""
    runs = _sysid_runs(doc.parent)
    lines = _note("Figure 8 errors per labelled run (80-step rollout error / constant)", "`records.jsonl`")
    rows = []
    for s in dict.fromkeys(s for s, _ in runs):
        for (t, run), e in runs.items():
            if t != s or "sysid same" not in e or "true params" not in e:
                continue
            tp, sy = e["true params"], e["sysid same"]
            spread = ", ".join(_num(x, 3) for x in tp.records[-1].metrics.get("runs", []))
            m = sy.records[-1].metrics
            paired = [f"{m[k]:.2f}x" if isinstance(m.get(k), (int, float)) else "-"
                      for k in ("ratio_without_top_1pct", "ratio_median_per_sequence")]
            rows.append([s, run, str(tp.n), str(m.get("train_steps", "-")),
                         _num(e["no params"].mean, 3) if "no params" in e else "-",
                         _num(tp.mean, 3) + (f" ({spread})" if spread else ""), _num(sy.mean, 3),
                         _num(e["sysid other"].mean, 3) if "sysid other" in e else "-",
                         f"{sy.mean / tp.mean:.2f}x"] + paired)
    return [lines, ""] + _md(["system", "run", "test", "steps", "no params", "true params (runs)", "sysid same",
                              "sysid other", "sysid / true", "without the top 1%", "median per sequence"], rows)


# -- driver --------------------------------------------------------------------------------------
def documents(root: Path) -> list[Path]:
    """The files whose blocks are generated: README.md, each results folder's README.md and the
    sysid_figures run sets' compare.md (those that exist under ``root``)."""
    res = root / RESULTS
    found = [root / "README.md"] + sorted(res.glob("*/README.md")) + sorted(res.glob("sysid_figures/*/compare.md"))
    return [p for p in found if p.is_file()]


def render(text: str, root: Path, doc: Path) -> str:
    """``text`` with each generated block's body remade from the records; ``KeyError`` for a block
    of unknown name."""
    def fill(m):
        name = m.group("name")
        if name not in TABLES:
            raise KeyError(f"{doc}: unknown results block {name!r} (known: {', '.join(sorted(TABLES))})")
        return m.group(1) + "\n".join(TABLES[name](root, doc)) + "\n" + m.group(4)
    return BLOCK.sub(fill, text)


def run(root: Path = ROOT, check: bool = False, files: list[Path] | None = None) -> list[Path]:
    """Regenerate (or, with ``check``, only compare) the blocks of ``files`` (default
    ``documents(root)``); returns the files whose blocks differ from their records (with
    ``check``) or that were rewritten."""
    changed = []
    for doc in files if files is not None else documents(root):
        old = doc.read_text()
        if not BLOCK.search(old):
            continue
        new = render(old, root, doc)
        if new != old:
            changed.append(doc)
            if not check:
                doc.write_text(new)
    return changed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", nargs="*", type=Path, help="files to process (default: every results document)")
    ap.add_argument("--root", type=Path, default=ROOT, help="repository root the records are read under")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 where a block differs")
    args = ap.parse_args(argv)
    changed = run(args.root, args.check, args.files or None)
    for p in changed:
        print(f"{'differs from its records' if args.check else 'rewrote'}: {p}")
    return 1 if args.check and changed else 0


if __name__ == "__main__":
    sys.exit(main())
