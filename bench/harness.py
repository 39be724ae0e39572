"""What the scripts under bench/ share: where results go, device names, timing, the benchmark
graphs and the paper's GN core built on them, and the experiments' training and data helpers.

Scripts put the repository root on ``sys.path`` (from their own path) and import this module as
``bench.harness``; the GN core is the library's own (``gnwarp.models.GNCore``).
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from gnwarp.graphs import GraphsTuple
from gnwarp.models import GNCore, GNCoreConfig

RESULTS = Path(__file__).resolve().parent / "results"


def results_dir(name: str = "") -> str:
    """``bench/results/<name>``: relative to the working directory when it lies below it (as
    results files then record it), else absolute."""
    path = RESULTS / name
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def experiment_out(name: str, out: str | None, quick: bool) -> Path:
    """Where an experiment writes: ``out`` when given, else ``bench/results/<name>``; a ``--quick``
    run without ``out`` gets a new temporary folder (a smoke run must not overwrite results)."""
    if out:
        return Path(out)
    if quick:
        return Path(tempfile.mkdtemp(prefix=f"{name}_quick_"))
    return Path(results_dir(name))


# -- devices ------------------------------------------------------------------------------------
def device_name(device: torch.device | None = None) -> str:
    """The name of ``device`` (default: the first GPU where there is one, else the CPU): a GPU's
    name, or the CPU's core count."""
    try:
        if (device.type == "cuda") if device is not None else torch.cuda.is_available():
            return torch.cuda.get_device_name(device if device is not None else 0)
    except Exception:  # noqa: BLE001 - no usable torch CUDA means a CPU run
        pass
    return f"CPU ({os.cpu_count()} cores, {platform.processor() or platform.machine()})"


def slug(name: str) -> str:
    """A device name as it appears in result file names ("NVIDIA H200" -> "nvidia-h200")."""
    return re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-").lower()


# -- processes ----------------------------------------------------------------------------------
def run_side_by_side(commands: dict[str, list[str]], log_dir: Path, threads: int = 2,
                     deadline: float | None = None) -> dict[str, int]:
    """Start every command at once (one process each, sharing the device), wait for all; each
    one's output goes to ``log_dir/<name>.log``. Commands still running ``deadline`` seconds after
    the start are killed (exit code -9 in the result). Returns the exit codes."""
    end = None if deadline is None else time.monotonic() + deadline
    procs = {}
    for name, cmd in commands.items():
        log = open(Path(log_dir) / f"{name}.log", "w")
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                        env={**os.environ, "OMP_NUM_THREADS": str(threads)}), log)
    codes = {}
    for name, (p, log) in procs.items():
        try:
            codes[name] = p.wait(None if end is None else max(0.0, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            codes[name] = p.wait()
        log.close()
    return codes


# -- timing -------------------------------------------------------------------------------------
def median_ms(fn, device: torch.device, reps: int, warmup: int) -> float:
    """Median milliseconds of ``fn()`` over ``reps`` calls after ``warmup``: CUDA events around
    each call on a CUDA ``device``, perf_counter elsewhere."""
    for _ in range(warmup):
        fn()
    ts = []
    if device.type == "cuda":
        torch.cuda.synchronize()
        for _ in range(reps):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            ts.append(a.elapsed_time(b))
    else:
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts)


def profile_kernels(step, steps: int, path: Path, title: str, top: int | None = None,
                    unit: str = "step") -> tuple[float, float]:
    """Kernels per call and device time per call (us, the sum of kernel durations) of ``step()``
    on CUDA, over ``steps`` calls under torch.profiler after five warm-up calls; the heading
    ``title`` and the kernels by time (the first ``top``) appended to ``path``, per call; ``unit``
    names a call there ("... kernels / step")."""
    from torch.profiler import ProfilerActivity, profile  # noqa: PLC0415
    for _ in range(5):
        step()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            step()
        torch.cuda.synchronize()
    per = {}
    path.parent.mkdir(parents=True, exist_ok=True)   # a fresh --out: the results are written after the profile
    for ev in prof.events():
        if ev.device_type == torch.autograd.DeviceType.CUDA:
            k = per.setdefault(ev.name[:90], [0, 0.0])
            k[0] += 1
            k[1] += ev.device_time_total
    calls, us = (sum(v[i] for v in per.values()) / steps for i in (0, 1))
    with open(path, "a") as f:
        f.write(f"== {title}: {calls:.0f} kernels / {unit}, {us:.1f} us device time / {unit} "
                "(sum of kernel durations)\n")
        for n, (c, u) in sorted(per.items(), key=lambda kv: -kv[1][1])[:top]:
            f.write(f"{u / steps:9.1f} us {c / steps:6.1f}x  {n}\n")
    return calls, us


def capture(step, warmup: int = 3, repeat: int = 1):
    """``repeat`` calls of ``step`` as one CUDA graph (gnwarp's Warp launches recorded on torch's
    capture stream); returns its ``replay``. ``warmup`` calls before, on the capture stream,
    compile and load every kernel (which must not happen during capture)."""
    from gnwarp.interop import cuda_graph  # noqa: PLC0415
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        for _ in range(warmup):
            step()
    torch.cuda.current_stream().wait_stream(s)
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with cuda_graph(graph, s):
        for _ in range(repeat):
            step()
    return graph.replay


def captured_us(fn, reps: int = 200, per_replay: int = 20) -> float:
    """Median microseconds of one ``fn()`` on CUDA: ``per_replay`` calls captured in one graph,
    replays timed with CUDA events (launch gaps gone, as in a captured training step)."""
    replay = capture(fn, warmup=5, repeat=per_replay)
    torch.cuda.synchronize()
    return 1e3 * median_ms(replay, torch.device("cuda"), max(1, reps // per_replay), 0) / per_replay


# -- the benchmark graphs and the paper's core ----------------------------------------------------
def _tree_edges(parent, joint_body):
    """Directed edges (both ways) between each joint's body and its parent body."""
    snd = [parent[b] for b in joint_body] + list(joint_body)
    rcv = list(joint_body) + [parent[b] for b in joint_body]
    return snd, rcv


# graph shapes: (nodes, senders, receivers) of one graph; body 0 is the world; joint_body lists
# the body of each joint (root joints repeat body 1). dm_control cheetah: 8 nodes, 9 joints -> 18
# directed edges; swimmer6: 7 nodes, 3 root joints + 5 hinges -> 16 edges; pendulum: 2 nodes, 2 edges
SHAPES = {
    "cheetah": (8, *_tree_edges([0, 0, 1, 2, 3, 1, 5, 6], [1, 1, 1, 2, 3, 4, 5, 6, 7])),
    "swimmer6": (7, *_tree_edges([0, 0, 1, 2, 3, 4, 5], [1, 1, 1, 2, 3, 4, 5, 6])),
    "pendulum": (2, *_tree_edges([0, 0], [1])),
}
# feature widths of every shape, as ../shared/probes/gn_torch_anchor.py; NODE_OUT: the core's
# output (the 13-number change of each body's state)
NODE_IN, EDGE_IN, GLOB_IN, NODE_OUT = 31, 64, 32, 13
INPUT_SIZES = {"nodes": NODE_IN, "edges": EDGE_IN, "globals": GLOB_IN}
PAPER = GNCoreConfig()  # D.2: edge MLP 3x512, node and global MLPs 2x256, latent 128
QUICK = GNCoreConfig(latent=16, edge_hidden=(32,) * 3, node_hidden=(16,) * 2, global_hidden=(16,) * 2)


def uniform_sizes(width: int) -> GNCoreConfig:
    """A core with every MLP layer and the latent ``width`` wide (edge MLP 3 layers, others 2)."""
    return GNCoreConfig(latent=width, edge_hidden=(width,) * 3, node_hidden=(width,) * 2,
                        global_hidden=(width,) * 2)


def make_batch(shape: str, B: int, device, seed: int = 0) -> tuple[GraphsTuple, torch.Tensor]:
    """``B`` graphs of ``shape`` with random features, and a random [nodes, NODE_OUT] target."""
    n, snd, rcv = SHAPES[shape]
    gen = torch.Generator(device="cpu").manual_seed(seed)
    off = torch.arange(B)[:, None] * n
    s = (torch.tensor(snd)[None] + off).reshape(-1)
    r = (torch.tensor(rcv)[None] + off).reshape(-1)
    E = len(snd)
    g = GraphsTuple(nodes=torch.randn(B * n, NODE_IN, generator=gen), edges=torch.randn(B * E, EDGE_IN, generator=gen),
                    globals=torch.randn(B, GLOB_IN, generator=gen), senders=s, receivers=r,
                    n_node=torch.full((B,), n), n_edge=torch.full((B,), E))
    g = GraphsTuple(*(x.to(device) for x in g))
    target = torch.randn(B * n, NODE_OUT, generator=gen).to(device)
    return g, target


def build_core(sizes: GNCoreConfig, options=None) -> GNCore:
    """The library's two-block paper core (``gnwarp.models.GNCore``) on the benchmark graphs'
    feature widths; ``options``: its ``RunOptions`` (default: the library's)."""
    return GNCore(sizes, INPUT_SIZES, options)


# -- the experiments ------------------------------------------------------------------------------
SYSTEMS = ["pendulum", "cartpole", "acrobot", "swimmer6", "cheetah", "walker", "jaco"]


def add_training_args(ap, *, seconds: float, max_steps: int, core_sizes: bool = True) -> None:
    """The options the experiments train their GNs with: data sizes, budget, schedule and (with
    ``core_sizes``) the GN core's sizes (``gn_sizes``)."""
    ap.add_argument("--sequences", type=int, nargs=3, default=(2000, 50, 200), metavar=("TRAIN", "VALID", "TEST"))
    ap.add_argument("--seconds", type=float, default=seconds, help="training cap per model (wall clock)")
    ap.add_argument("--max-steps", type=int, default=max_steps)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--valid-every", type=int, default=2000)
    if core_sizes:
        ap.add_argument("--latent", type=int, default=128)
        ap.add_argument("--edge-width", type=int, default=256)
        ap.add_argument("--node-width", type=int, default=128)


def add_run_args(ap, name: str, *child_options: str) -> None:
    """``--out`` (``experiment_out``), ``--quick``, and what the script's child processes take:
    ``--child`` and ``child_options`` (strings), kept out of ``--help``."""
    ap.add_argument("--out", default=None, help=f"default: bench/results/{name} (--quick: a temporary folder)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes on the CPU: a smoke test of the script")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    for option in child_options:
        ap.add_argument(option, help=argparse.SUPPRESS)


def forward_args(args, *dests: str) -> list[str]:
    """Command-line options repeating ``args``' values of ``dests`` (for a child process)."""
    out = []
    for d in dests:
        out += [f"--{d.replace('_', '-')}", str(getattr(args, d))]
    return out


def gn_sizes(latent: int, edge_width: int, node_width: int, layers: int = 2) -> GNCoreConfig:
    """A GN core with ``layers`` hidden layers per MLP: edge ``edge_width``, node and global
    ``node_width`` wide."""
    return GNCoreConfig(latent=latent, edge_hidden=(edge_width,) * layers, node_hidden=(node_width,) * layers,
                        global_hidden=(node_width,) * layers)


def ensure_dataset(path: Path, system: str, sizes, num_steps: int, seed: int) -> Path:
    """``path``, simulated first (MuJoCo C on every core, (train, valid, test) ``sizes``) unless it
    exists."""
    from gnwarp import data  # noqa: PLC0415
    path = Path(path)
    if not path.exists():
        data.generate(system, tuple(sizes), num_steps=num_steps, seed=seed, backend="mujoco",
                      progress=False).save(path)
    return path


def train_model(data: list[str], out, model, steps: int, *, lr: float, decay_every: int, valid_every: int,
                valid: int, seconds: float | None = None, **config) -> dict:
    """Train ``model`` (a ``ModelConfig``) with the library's ``Trainer``: Adam at ``lr``, x0.6
    every ``decay_every`` steps, ``steps`` steps or ``seconds`` of wall clock, validated every
    ``valid_every`` steps on ``valid`` sequences (the best kept, no early stop), from scratch;
    ``config``: further ``TrainConfig`` fields (``batch_size``, ``device``, ...). Returns the
    run's summary (``best``: the best checkpoint)."""
    from gnwarp.train import TrainConfig, Trainer  # noqa: PLC0415
    cfg = TrainConfig(data=list(data), out=str(out), model=model, steps=steps, max_seconds=seconds, lr=lr,
                      lr_decay=0.6, lr_decay_steps=max(1, decay_every), valid_every=valid_every,
                      valid_sequences=valid, patience=None, checkpoint_every=max(1, steps), resume=False,
                      progress=False, **config)
    return Trainer(cfg).run()


def mean_errors(result: dict) -> dict:
    """An ``eval.evaluate`` result with each horizon's errors reduced to their mean over state groups."""
    return {k: (v["mean"] if isinstance(v, dict) else v) for k, v in result.items()}


def write_summary(out: Path, lines: list[str]) -> None:
    """An experiment's table: printed and written to ``out/summary.md``."""
    table = "\n".join(lines)
    (Path(out) / "summary.md").write_text(table + "\n")
    print(f"{table}\nwrote {Path(out) / 'summary.md'}")


def read_rows(path) -> list[dict]:
    """The rows of a JSON-lines file (``save_results``' ``.jsonl``; blank lines skipped)."""
    import json  # noqa: PLC0415
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def replace_rows(path, rows: list[dict], key) -> list[dict]:
    """``path``'s JSON-lines rows with ``rows`` in place of those whose ``key(row)`` one of them has
    (a measurement made again), ``rows`` last; written whole to a temporary file, then renamed.
    Returns all the rows."""
    import json  # noqa: PLC0415

    from gnwarp.files import atomic_write  # noqa: PLC0415
    path = Path(path)
    new = {key(r) for r in rows}
    kept = [r for r in (read_rows(path) if path.exists() else []) if key(r) not in new] + list(rows)
    with atomic_write(path) as tmp:
        Path(tmp).write_text("".join(json.dumps(r) + "\n" for r in kept))
    return kept


def save_results(out, name: str, device: str, quick: bool, rows: list[dict], lines: list[str]) -> Path:
    """A benchmark's rows appended to ``out/<name>_<device>[_quick].jsonl`` and its table written
    to the ``.md`` beside it (and printed); returns the stem."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{name}_{slug(device)}{'_quick' if quick else ''}"
    import json  # noqa: PLC0415
    with open(stem.with_suffix(".jsonl"), "a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return stem
