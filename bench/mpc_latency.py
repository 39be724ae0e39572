"""Benchmark: how soon gradient MPC through a learned model acts, and how fast it plans after.

Per system (pendulum, cartpole, swimmer6, cheetah, walker; each with its task of
``gnwarp.control.tasks``) and per (episodes, horizon, iterations), a ``GradientMPC`` plans through
an untrained ``ForwardModel`` (latent 128, every MLP 2 x 256; planning time does not depend on
the weights) bound to ``gnwarp.sim.systems.make(system)``, from the systems' random initial
states, with the library's default first-state handling (a sampled proposal, then a bounded
warm-up). Each configuration runs in fresh processes:

- cold: Warp's kernel cache, the CUDA driver's cache and torch's compile caches point into a new,
  empty folder; the process times planner construction to the first action (capture included);
  ``--cold once``: only for the first configuration of each system and path, whose caches the
  later configurations reuse; ``--cold none``: the machine's own caches, no cold process;
- warm: a second fresh process on the caches the cold one filled times the same first action
  (run again when it compiled anything, so that it loads all it runs from the caches),
  then ``--steps`` more control steps from the same states, each timed with CUDA events (wall
  time on the CPU). Steady = the median over the control steps after the first three (a captured
  iteration records on its first call with the default ``capture_warmup`` of 0, its second with 1); model step fwd+bwd = steady / (iterations x horizon);
  the planner's own counters give the model evaluations per step (checked: every step ran the
  configured iterations over the configured horizon); real-time factor = control timestep /
  steady. The true environment is not stepped (planning time alone).

Paths: "unfused" and "fused" (``GradientMPCConfig(fused=False)`` and ``fused=None``, the
planner's own choice by size, where the config has the field; without it, "unfused" is the
library's one path), "fused_forced" (``fused=True`` at any size: the crossover of the rule), and a torch peer of the same model step
in the same run: the same model with ``impl="torch"`` (the library's default run options otherwise:
TF32 GEMMs) in the same planner, one
planning iteration (rollout, reward, backward to the actions, Adam) captured in a CUDA graph
("torch_graph"), and the same with the model step compiled by ``torch.compile`` inside that
graph ("torch_compile", ``--compile-mode``; the compiled step runs in the planner's own graph, so
a mode that makes CUDA graphs of its own would nest them). A configuration that fails keeps its
error text in its record.

Records (``gnwarp.eval.records``, one JSON line per configuration and path) go to
``<out>/mpc_latency_<gpu>.jsonl``; a rerun skips configurations already recorded (resume), so the
whole grid can run as several commands (``--systems``, ``--configs``, ``--paths``, ``--budget``).
From the records (never typed numbers): ``<out>/../mpc_latency_<gpu>.json`` (a list of rows) and
``<out>/README.md`` (tables).

    python bench/mpc_latency.py --systems pendulum --budget 540     # again until nothing is left
    python bench/mpc_latency.py --systems cheetah --configs 1x50x5,16x50x5 --cold once --budget 540
    python bench/mpc_latency.py --summarize          # regenerate the JSON and README from the records
    python bench/mpc_latency.py --quick              # tiny sizes on the CPU, into a temporary folder
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.harness import QUICK, device_name, results_dir, slug  # noqa: E402
from gnwarp.eval.records import ResultRecord, git_commit, read_records, write_records  # noqa: E402
from gnwarp.models import GNCoreConfig  # noqa: E402

NAME = "mpc_latency"
TASKS = {"pendulum": "pendulum-balance", "cartpole": "cartpole-balance", "swimmer6": "swimmer-reach",
         "cheetah": "cheetah-forward", "walker": "walker-forward"}
CONFIGS = ((1, 50, 5), (1, 50, 1), (16, 50, 5), (256, 50, 5), (4096, 100, 5))
QUICK_CONFIGS = ((1, 4, 1), (2, 4, 2))
PATHS = ("unfused", "fused", "torch_graph", "torch_compile", "fused_forced")
SIZES = GNCoreConfig(latent=128, edge_hidden=(256, 256), node_hidden=(256, 256), global_hidden=(256, 256))
EXPERIMENT = "bench/mpc_latency"
ROW_KEYS = ("system", "episodes", "horizon", "iterations", "path", "first_step_ms", "first_step_cold_ms", "steady_ms",
            "model_step_us", "model_evals_per_step", "control_dt_ms", "gpu")


def parse_configs(text: str) -> list[tuple[int, int, int]]:
    """"1x50x5,16x50x5" -> [(episodes, horizon, iterations), ...]; ValueError naming a bad one."""
    out = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        try:
            n, h, i = (int(v) for v in part.split("x"))
        except ValueError:
            raise ValueError(f"--configs: {part!r} is not EPISODESxHORIZONxITERATIONS (e.g. 1x50x5)") from None
        if min(n, h, i) < 1:
            raise ValueError(f"--configs: {part!r} needs values >= 1")
        out.append((n, h, i))
    return out


# -- one measurement, in a fresh process ----------------------------------------------------------

def _sync(dev) -> None:
    import torch
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def planning_setup(system_name: str, n: int, dev, impl: str = "warp", quick: bool = False):
    """(system, task name, model, initial body states [n, B, 13], targets) of one benchmark
    configuration: an untrained planning core (``SIZES``; ``QUICK`` sizes when ``quick``) on
    ``dev``, seeded initial states from the true simulator (MuJoCo C), the task's targets."""
    import numpy as np
    import torch

    from gnwarp import systems
    from gnwarp.control import get_task, sample_targets
    from gnwarp.data import static_arrays
    from gnwarp.data.generation import initial_states
    from gnwarp.models import ForwardModel, ModelConfig
    from gnwarp.models.config import DEFAULT_RUN
    from gnwarp.sim import make_env

    system = systems.make(system_name)
    task = TASKS[system_name]
    torch.manual_seed(0)
    # the library's default run options (TF32 GEMMs on CUDA) for both implementations; before
    # 2026-11-27 (run "tf32") this was RunOptions(impl=impl): IEEE float32 GEMMs (see NOTES.md)
    model = ForwardModel(ModelConfig(gn=QUICK if quick else SIZES, run=DEFAULT_RUN.replace(impl=impl)),
                         static_arrays([system])[1]).to(dev)
    qpos, qvel = initial_states(system, n, np.random.default_rng(0))
    x = torch.as_tensor(make_env(system, n, backend="mujoco").reset(qpos, qvel), dtype=torch.float32, device=dev)
    return system, task, model, x, sample_targets(get_task(task), system, n, seed=0)


def run_precision() -> str:
    """The GEMM precision ``planning_setup``'s models run with here (the library's default run
    options; off CUDA "tf32" runs as "fp32")."""
    import torch

    from gnwarp.models.config import DEFAULT_RUN
    p = DEFAULT_RUN.precision
    return "fp32" if p == "tf32" and not torch.cuda.is_available() else p


def measure(spec: dict) -> dict:
    """One configuration's planning times in this process: ``spec`` = {system, episodes, horizon,
    iterations, path, steps, first_only, quick, compile_mode}. Returns {first_step_ms, and unless
    first_only: plan_ms [steps + 1] (the first action, then each control step), steady_ms,
    model_evals_per_step, ...}."""
    import torch

    from gnwarp.control import GradientMPC, GradientMPCConfig, control_timestep, plan_timing

    n, H, its, path = spec["episodes"], spec["horizon"], spec["iterations"], spec["path"]
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    system, task, model, x, targets = planning_setup(spec["system"], n, dev, "torch" if path.startswith("torch")
                                                     else "warp", spec["quick"])
    if path == "torch_compile":   # the model step compiled; the planner's graph captures what it launches
        model.next_nodes = torch.compile(model.next_nodes, mode=spec["compile_mode"], dynamic=False)
    extra = ({"fused": {"unfused": False, "fused": None, "fused_forced": True}[path]}
             if path in ("unfused", "fused", "fused_forced") else {})
    cfg = GradientMPCConfig(horizon=H, iterations=its, seed=0, **extra)
    _sync(dev)
    t0 = time.perf_counter()
    planner = GradientMPC(model, task, system, n, cfg, targets)   # binds the model: part of the first action
    planner.step(x)
    _sync(dev)
    first = time.perf_counter() - t0
    out = {"first_step_ms": 1e3 * first, "device": device_name(dev), "warmup_iterations": planner.warmup,
           "proposals": cfg.proposals, "proposal_evals": planner.proposal_evals,
           "first_step_evals": planner.evals, "fused": extra.get("fused", "absent"),
           "engine_fused": bool(getattr(planner.engine, "fused", False))}   # what the rule chose
    if spec["first_only"]:
        return out
    evals0, prop0 = planner.evals, planner.proposal_evals
    secs = []
    for _ in range(spec["steps"]):
        if dev.type == "cuda":
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            planner.step(x)
            b.record()
            b.synchronize()
            secs.append(a.elapsed_time(b) / 1e3)
        else:
            t = time.perf_counter()
            planner.step(x)
            secs.append(time.perf_counter() - t)
    steps = spec["steps"]
    ran = (planner.evals - evals0) / steps
    if ran != planner.model_evals_per_step or planner.proposal_evals != prop0:
        raise RuntimeError(f"the planner ran {ran} model steps a control step (and {planner.proposal_evals - prop0} "
                           f"proposal steps), not iterations x horizon = {planner.model_evals_per_step}")
    timing = plan_timing([first] + secs, control_timestep(system))
    out.update(plan_ms=[1e3 * s for s in [first] + secs], steady_ms=timing["steady_ms"],
               steady_after=timing["steady_after"], real_time_factor=timing["real_time_factor"],
               control_dt_ms=timing["control_dt_ms"], model_evals_per_step=planner.model_evals_per_step,
               measured_evals_per_step=ran, model_step_us=1e3 * timing["steady_ms"] / planner.model_evals_per_step,
               episode_steps_per_s=1e3 * n / timing["steady_ms"])
    return out


def child_main(spec_json: str) -> int:
    """``--child SPEC``: measure one spec; the result (or the error) as the last stdout line."""
    try:
        res = measure(json.loads(spec_json))
    except Exception as e:  # noqa: BLE001 - the parent records the error text
        tail = traceback.format_exc().strip().splitlines()[-6:]
        res = {"error": f"{type(e).__name__}: {e}"[:600], "traceback": tail}
    print("RESULT " + json.dumps(res), flush=True)
    return 0


def run_child(spec: dict, cache: Path | None, timeout: float) -> dict:
    """``measure(spec)`` in a fresh process whose Warp kernel cache, CUDA driver cache and torch
    compile caches live in ``cache`` (None: where the environment puts them)."""
    env = dict(os.environ)
    if cache is not None:
        env.update(WARP_CACHE_PATH=str(cache / "warp"), CUDA_CACHE_PATH=str(cache / "nv"),
                   TORCHINDUCTOR_CACHE_DIR=str(cache / "inductor"), TRITON_CACHE_DIR=str(cache / "triton"))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=max(1.0, timeout))
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if not lines:
        return {"error": f"exit code {p.returncode}: {(p.stderr or p.stdout).strip()[-600:]}"}
    return json.loads(lines[-1][len("RESULT "):])


# -- records --------------------------------------------------------------------------------------

def records_path(out: Path, gpu: str) -> Path:
    return Path(out) / f"{NAME}_{slug(gpu)}.jsonl"


def precision(rec: ResultRecord) -> str:
    """The GEMM precision a record planned with: its config's, else "fp32" (records before the
    benchmark took the library's default run options, 2026-11-27, planned with IEEE float32)."""
    return rec.config.get("precision", "fp32")


def record_key(rec: ResultRecord) -> tuple:
    c = rec.config
    return rec.system, rec.episodes, c.get("horizon"), c.get("iterations"), c.get("path"), rec.gpu, precision(rec)


def make_record(system: str, n: int, H: int, its: int, path: str, gpu: str, warm: dict, cold: dict | None,
                steps: int, quick: bool, compile_mode: str, cold_mode: str = "all") -> ResultRecord:
    """A configuration's record: the warm process's measurements with the cold one's first action
    beside them; ``error`` in its config when either failed. ``cold_mode``: the ``--cold`` choice."""
    from gnwarp.sim import systems
    sysm = systems.make(system)
    metrics = {k: v for k, v in warm.items() if k not in ("error", "traceback", "device")}
    if cold is not None and "first_step_ms" in cold:
        metrics["first_step_cold_ms"] = cold["first_step_ms"]
    errors = [f"{what}: {r['error']}" for what, r in (("warm", warm), ("cold", cold)) if r and "error" in r]
    config = {"path": path, "horizon": H, "iterations": its, "steps": steps, "quick": quick,
              "gn": dataclasses.asdict(QUICK if quick else SIZES), "cold": cold_mode,
              "impl": "torch" if path.startswith("torch") else "warp", "precision": run_precision(),
              "note": "timing only: an untrained model, no closed loop (returns not measured)"}
    if path == "torch_compile":
        config["compile_mode"] = compile_mode
    if errors:
        config["error"] = "; ".join(errors)
        config["traceback"] = next((r["traceback"] for r in (warm, cold) if r and "traceback" in r), None)
    return ResultRecord(experiment=EXPERIMENT, task=TASKS[system], system=system, planner="gradient",
                        dynamics="learned", variant=f"{path}/{n}x{H}x{its}", seed=0, episodes=n,
                        episode_steps=steps + 1, reported={"mean": None, "std": None, "of": "returns"},
                        control_dt=float(sysm.dt), action_repeat=int(sysm.substeps), env_steps=0, metrics=metrics,
                        config=config, commit=git_commit(), gpu=gpu, date=time.strftime("%Y-%m-%d %H:%M:%S"))


def _num(v):
    """A JSON number rounded to 4 significant digits, or None (missing, NaN, inf)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return None
    return float(f"{v:.4g}") if isinstance(v, float) else v


def summary_rows(records: list[ResultRecord]) -> list[dict]:
    """One row per (system, episodes, horizon, iterations, path, gpu, precision), from the latest record of
    each: the issue's keys (``ROW_KEYS``) plus episode_steps_per_s, real_time_factor, what the
    first action ran (Adam iterations, forward-only proposal model steps per episode) and, for a
    failed run, its error."""
    latest = {}
    for r in records:
        if r.experiment == EXPERIMENT:
            latest[record_key(r)] = r
    rows = []
    for r in latest.values():
        m, c = r.metrics, r.config
        row = {"system": r.system, "episodes": r.episodes, "horizon": c["horizon"], "iterations": c["iterations"],
               "path": c["path"], "precision": precision(r), "first_step_ms": _num(m.get("first_step_ms")),
               "first_step_cold_ms": _num(m.get("first_step_cold_ms")), "steady_ms": _num(m.get("steady_ms")),
               "model_step_us": _num(m.get("model_step_us")), "model_evals_per_step": m.get("model_evals_per_step"),
               "control_dt_ms": 1e3 * r.control_dt if r.control_dt else None, "gpu": r.gpu,
               "episode_steps_per_s": _num(m.get("episode_steps_per_s")),
               "real_time_factor": _num(m.get("real_time_factor")),
               "first_step_iterations": m.get("warmup_iterations", 0) + r.config["iterations"] if m else None,
               "first_step_proposal_evals": m.get("proposal_evals")}
        if "error" in c:
            row["error"] = c["error"]
        rows.append(row)
    order = {s: i for i, s in enumerate(TASKS)}
    rows.sort(key=lambda w: (w["gpu"], order.get(w["system"], 99), w["system"], w["episodes"], w["horizon"],
                             -w["iterations"], w["precision"] != "tf32",
                             PATHS.index(w["path"]) if w["path"] in PATHS else 99))
    return rows


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, int):
        return str(v)
    return f"{v:.{digits}g}" if abs(v) < 10 ** digits else f"{v:.0f}"


def markdown(rows: list[dict]) -> str:
    """The README's tables (one per GPU) of ``summary_rows``."""
    lines = ["# Gradient MPC latency: the first action and the steady state", "",
             "Generated by `bench/mpc_latency.py` from the records beside this file (do not edit). An untrained",
             "`ForwardModel` (latent 128, every MLP 2 x 256) plans each system's task with `GradientMPC`",
             "(default first state: a sampled proposal, then 4 x iterations of warm-up); planning time does",
             "not depend on the weights. First action: a fresh process, planner construction to the first",
             "action (capture included), the kernel caches filled by an earlier process (warm) or empty",
             "(cold). Steady: median over the control steps after the first three (CUDA events). Model step:",
             "steady / (iterations x horizon), forward and backward. RTF: control timestep / steady (> 1:",
             "faster than real time). Paths: the Warp planner unfused / fused, and a torch peer of the same",
             "model step (the same planner on `impl=\"torch\"`), one planning iteration in a CUDA graph,",
             "plain and with `torch.compile` inside. Precision: the planning model's GEMMs (\"tf32\", the",
             "library's default, since 2026-11-27; \"fp32\": IEEE float32, the runs before).", ""]
    for gpu in sorted({r["gpu"] for r in rows}):
        lines += [f"## {gpu}", "",
                  "| system | episodes | horizon | iterations | path | precision | first action (s) | cold (s) "
                  "| steady ms / step | model step us | evals / step | episode-steps / s | RTF | control dt ms |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in (r for r in rows if r["gpu"] == gpu):
            sec = lambda v: None if v is None else v / 1e3  # noqa: E731
            cells = [r["system"], r["episodes"], r["horizon"], r["iterations"], r["path"], r["precision"],
                     _fmt(sec(r["first_step_ms"])), _fmt(sec(r["first_step_cold_ms"])), _fmt(r["steady_ms"]),
                     _fmt(r["model_step_us"]), _fmt(r["model_evals_per_step"]), _fmt(r["episode_steps_per_s"]),
                     _fmt(r["real_time_factor"]), _fmt(r["control_dt_ms"])]
            if "error" in r:
                cells[8] = f"error: {r['error'][:80]}".replace("|", "/")
            lines.append("| " + " | ".join(str(c) for c in cells) + " |")
        lines.append("")
    return "\n".join(lines)


def summarize(out: Path) -> list[Path]:
    """From every records file in ``out``: ``out/../mpc_latency_<gpu>.json`` per GPU and
    ``out/README.md``. Returns the files written."""
    out = Path(out)
    records = []
    for f in sorted(out.glob(f"{NAME}_*.jsonl")):
        records += read_records(f)
    rows = summary_rows(records)
    written = []
    for gpu in sorted({r["gpu"] for r in rows}):
        path = out.parent / f"{NAME}_{slug(gpu)}.json"
        path.write_text(json.dumps([r for r in rows if r["gpu"] == gpu], indent=1) + "\n")
        written.append(path)
    (out / "README.md").write_text(markdown(rows) + "\n")
    return written + [out / "README.md"]


# -- the grid -------------------------------------------------------------------------------------

def resolve_defaults(args) -> None:
    """The grid's flags left unset, filled in place: every system and path, a cold process for
    every configuration; with ``--quick`` (a smoke test of the script in well under a minute on
    a CPU, not the grid) the pendulum, the Warp paths and no cold process."""
    if args.systems is None:
        args.systems = "pendulum" if args.quick else ",".join(TASKS)
    if args.paths is None:
        args.paths = "unfused,fused" if args.quick else ",".join(PATHS)
    if args.cold is None:
        args.cold = "none" if args.quick else "all"


def run(args) -> int:
    quick = args.quick
    out = Path(args.out) if args.out else (Path(tempfile.mkdtemp(prefix=f"{NAME}_quick_")) / NAME if quick
                                           else Path(results_dir(NAME)))
    out.mkdir(parents=True, exist_ok=True)
    if args.summarize:
        for p in summarize(out):
            print(f"wrote {p}")
        return 0
    resolve_defaults(args)
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    unknown = [s for s in systems if s not in TASKS]
    if unknown:
        raise SystemExit(f"--systems: unknown {unknown}; known: {', '.join(TASKS)}")
    configs = parse_configs(args.configs) if args.configs else list(QUICK_CONFIGS if quick else CONFIGS)
    paths = [p.strip() for p in args.paths.split(",") if p.strip()]
    bad = [p for p in paths if p not in PATHS]
    if bad:
        raise SystemExit(f"--paths: unknown {bad}; known: {', '.join(PATHS)}")
    gpu = device_name()
    rec_path = records_path(out, gpu)
    done = {record_key(r) for r in read_records(rec_path) if "error" not in r.config} if rec_path.exists() else set()
    steps = args.steps if args.steps is not None else (4 if quick else 20)
    start = time.monotonic()

    def left() -> float | None:
        return None if args.budget is None else args.budget - (time.monotonic() - start)

    def timeout() -> float:
        rest = left()
        return args.child_timeout if rest is None else max(1.0, min(args.child_timeout, rest))

    with tempfile.TemporaryDirectory(prefix="mpc_latency_caches_") as caches:
        for system in systems:
            for n, H, its in configs:
                for path in paths:
                    key = (system, n, H, its, path, gpu, run_precision())
                    if key in done:
                        print(f"{system} {n}x{H}x{its} {path}: recorded, skipped")
                        continue
                    if left() is not None and left() < min(120.0, args.budget / 4):   # too little for one more
                        print(f"budget of {args.budget:.0f} s spent: stopped before {system} {n}x{H}x{its} {path}; "
                              "run the same command again to go on")
                        for p in summarize(out):
                            print(f"wrote {p}")
                        return 0
                    spec = dict(system=system, episodes=n, horizon=H, iterations=its, path=path, steps=steps,
                                quick=quick, compile_mode=args.compile_mode, first_only=False)
                    warm, cold = measure_config(spec, args.cold, Path(caches), timeout)
                    rec = make_record(system, n, H, its, path, gpu, warm, cold, steps, quick, args.compile_mode,
                                      args.cold)
                    write_records(rec_path, [rec])
                    report(rec)
    for p in summarize(out):
        print(f"wrote {p}")
    return 0


def _cache_files(cache: Path | None) -> set[str]:
    """Every file under ``cache`` (what compiled kernels and graphs a process left there)."""
    if cache is None or not cache.exists():
        return set()
    return {str(f.relative_to(cache)) for f in cache.rglob("*") if f.is_file()}


def measure_config(spec: dict, cold_mode: str, caches: Path, timeout) -> tuple[dict, dict | None]:
    """(warm result, cold result or None) of one configuration, in fresh processes. ``cold_mode``
    "all": a process on new, empty caches times the cold first action, the warm process runs on
    the caches it filled; "once": the same for the first configuration of each (system, path),
    whose caches the later ones reuse; "none": the machine's own caches. A warm process that
    compiled anything (files added to its caches) is run again, so that the warm first action
    loads everything it runs."""
    cold = None
    if cold_mode == "none":
        cache = None
    else:
        name = f"{spec['system']}-{spec['path']}"
        if cold_mode == "all":
            name += f"-{spec['episodes']}x{spec['horizon']}x{spec['iterations']}"
        cache = caches / name
        if not cache.exists():
            cache.mkdir(parents=True)
            cold = run_child({**spec, "first_only": True}, cache, timeout())
    before = _cache_files(cache)
    warm = run_child(spec, cache, timeout())
    if cache is not None and "error" not in warm and _cache_files(cache) - before:
        warm = {**run_child(spec, cache, timeout()), "compiled_in_first_warm_run": True}
    if cold_mode == "all" and cache is not None:
        shutil.rmtree(cache, ignore_errors=True)
    return warm, cold


def report(rec: ResultRecord) -> None:
    c, m = rec.config, rec.metrics
    what = f"{rec.system} {rec.episodes}x{c['horizon']}x{c['iterations']} {c['path']}"
    if "error" in c:
        print(f"{what}: {c['error']}", flush=True)
        return
    cold_s = f"{m['first_step_cold_ms'] / 1e3:.2f} s" if "first_step_cold_ms" in m else "not measured"
    print(f"{what}: first action {m['first_step_ms'] / 1e3:.2f} s (cold: {cold_s}), steady {m['steady_ms']:.2f} ms, "
          f"model step {m['model_step_us']:.0f} us, {m['model_evals_per_step']} evals/step, "
          f"RTF {m['real_time_factor']:.3g}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=None, help="comma-separated systems (default: all; --quick: pendulum)")
    ap.add_argument("--configs", default=None,
                    help="comma-separated EPISODESxHORIZONxITERATIONS (default: the issue's five; --quick: tiny)")
    ap.add_argument("--paths", default=None, help="comma-separated: " + ", ".join(PATHS)
                    + " (default: all; --quick: unfused,fused)")
    ap.add_argument("--steps", type=int, default=None, help="control steps timed after the first (default 20; quick 4)")
    ap.add_argument("--cold", choices=("all", "once", "none"), default=None,
                    help="all: for every configuration a process on new, empty caches times the cold first action "
                         "and the warm process runs on the caches it filled; once: the cold process for the first "
                         "configuration of each system and path, whose caches the later ones reuse; none: one "
                         "process on the machine's own caches. A warm process that compiled anything runs again "
                         "(default: all; --quick: none)")
    ap.add_argument("--compile-mode", default="default",
                    help="torch.compile mode of the torch_compile path (e.g. default, max-autotune-no-cudagraphs)")
    ap.add_argument("--budget", type=float, default=None,
                    help="seconds this command may run: no configuration starts in its last 2 minutes and a "
                         "measuring process is stopped at its end (rerun to resume); default none")
    ap.add_argument("--child-timeout", type=float, default=570.0, help="seconds a measuring process may run")
    ap.add_argument("--summarize", action="store_true", help="only regenerate the JSON and README from the records")
    ap.add_argument("--out", default=None,
                    help=f"records folder (default bench/results/{NAME}; --quick: a temporary one)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes on the CPU: a smoke test of the script")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        return child_main(args.child)
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
