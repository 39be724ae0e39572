"""Data-generation benchmark: steps/s and end-to-end time per system and backend.

For each system: a warm-up generation (compiles kernels, excluded), then a timed generation of
``--sequences`` sequences of ``--steps`` data steps, and the dataset written to disk. Reports
simulated data steps per second (simulation only), physics steps per second, and the end-to-end
time (simulation + static graphs + writing the HDF5 file), plus graph building throughput
(input graphs built from stored states with GraphBuilder, on the GPU when there is one).

    python bench/datagen.py                         # paper-size cheetah on every available backend
    python bench/datagen.py --systems all --sequences 12000
    python bench/datagen.py --quick                 # tiny CPU smoke run
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.harness import device_name, results_dir, slug  # noqa: E402
from gnwarp import data, sim  # noqa: E402
from gnwarp.interop import cuda_available  # noqa: E402


def run_one(name, backend, sizes, steps, parameterized, tmpdir):
    data.generate(name, (8, 1, 1), num_steps=5, seed=123, parameterized=parameterized, backend=backend,
                  progress=False)  # warm-up: kernel compiles, thread pools
    t0 = time.perf_counter()
    ds = data.generate(name, sizes, num_steps=steps, seed=0, parameterized=parameterized, backend=backend,
                       progress=False)
    t_gen = time.perf_counter() - t0
    path = Path(tmpdir) / f"{name}-{backend}.h5"
    t1 = time.perf_counter()
    ds.save(path, overwrite=True)
    t_save = time.perf_counter() - t1
    size_mb = path.stat().st_size / 2**20
    # graph building throughput from the stored states
    import torch
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    builder = data.GraphBuilder(ds.static, device=dev)
    tr = ds["train"]
    n = min(len(tr), 4096)
    inst = torch.as_tensor(tr.instance[:n], device=dev)
    body = torch.as_tensor(tr.body[:n, 0], device=dev)
    ctrl = torch.as_tensor(tr.ctrl[:n, 0], device=dev)
    builder(inst, body, ctrl)
    if dev == "cuda":
        torch.cuda.synchronize()
    tb = time.perf_counter()
    reps = 20
    for _ in range(reps):
        g = builder(inst, body, ctrl)
    if dev == "cuda":
        torch.cuda.synchronize()
    graphs_per_s = n * reps / (time.perf_counter() - tb)
    nseq = sum(ds.meta["splits"].values())
    sim_s = ds.meta["simulation_seconds"]
    row = dict(system=name, backend=ds.meta["backend"], parameterized=parameterized, sequences=nseq, steps=steps,
               substeps=ds.meta["substeps"], sim_seconds=sim_s, data_steps_per_s=nseq * steps / sim_s,
               physics_steps_per_s=nseq * steps * ds.meta["substeps"] / sim_s, generate_seconds=t_gen,
               save_seconds=t_save, end_to_end_seconds=t_gen + t_save, file_mb=size_mb,
               graphs_built_per_s=graphs_per_s, graph_device=dev, nodes_per_graph=int(g.n_node[0]))
    path.unlink()
    ds.close()
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="cheetah", help="comma list, or 'all'")
    ap.add_argument("--backends", default="auto", help="comma list of mujoco_warp, mujoco, mujoco_warp_cpu; "
                    "'auto' = mujoco_warp (if CUDA) and mujoco")
    ap.add_argument("--sequences", type=int, default=12000, help="total sequences (paper: 10000+1000+1000)")
    ap.add_argument("--c-sequences", type=int, default=None, help="sequences for the MuJoCo C backend")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--parameterized", action="store_true")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (CPU smoke test)")
    ap.add_argument("--out", default=results_dir("datagen"))
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    names = sim.names() if args.systems == "all" else args.systems.split(",")
    names = ["swimmer6" if n == "swimmer" else n for n in names]
    backends = args.backends.split(",")
    if backends == ["auto"]:
        backends = (["mujoco_warp"] if cuda_available() else []) + ["mujoco"]
    if args.quick:
        args.sequences, args.steps = 24, 10
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            for be in backends:
                n = args.c_sequences if (be == "mujoco" and args.c_sequences) else args.sequences
                try:
                    r = run_one(name, be, n, args.steps, args.parameterized, tmp)
                except Exception as e:  # noqa: BLE001 - report and go on with the other peers
                    r = dict(system=name, backend=be, error=f"{type(e).__name__}: {e}")
                rows.append(r)
                print(json.dumps(r), flush=True)
    dev = device_name()
    lines = [f"# Data generation benchmark ({dev}; {os.cpu_count()} CPU cores)", "",
             "| system | backend | sequences x steps | substeps | data steps/s | physics steps/s | sim s | "
             "end-to-end s | file MB | graphs built/s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['system']} | {r['backend']} | error: {r['error'][:80]} | | | | | | | |")
            continue
        lines.append(f"| {r['system']}{' (param)' if r['parameterized'] else ''} | {r['backend']} | "
                     f"{r['sequences']} x {r['steps']} | {r['substeps']} | {r['data_steps_per_s']:.3g} | "
                     f"{r['physics_steps_per_s']:.3g} | {r['sim_seconds']:.2f} | {r['end_to_end_seconds']:.2f} | "
                     f"{r['file_mb']:.0f} | {r['graphs_built_per_s']:.3g} ({r['graph_device']}) |")
    table = "\n".join(lines)
    print(table)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"datagen_{slug(dev.split('(')[0])}{('_' + args.tag) if args.tag else ''}"
    (out / f"{stem}.md").write_text(table + "\n")
    (out / f"{stem}.json").write_text(json.dumps({"device": dev, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
