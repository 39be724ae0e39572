"""Bad input, tried as an adversarial user would: every case runs the `gnwarp` command
line in its own process on a corrupted dataset, checkpoint, MJCF file, config or argument, and
is classified by what the process did:

- "clear error": a non-zero exit whose output ends in one line naming the problem, no traceback;
- "right result": exit 0 where the input is valid (controls: must keep working);
- "unclear error": a non-zero exit with a Python traceback;
- "silently accepted": exit 0 on bad input;
- "crash": killed by a signal (a segmentation fault), or "hang": no exit within the time limit.

Writes the count of cases and their outcomes to ``bench/results/reliability/cases.md`` (and
``cases.jsonl``). The pytest suite (``tests/test_reliability_*.py``) holds the same kinds of case
as fast in-process tests; this script is the end-to-end check, a few minutes on 2 cores.

    python bench/adversarial.py [--only dataset,checkpoint] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MJCF = """<mujoco model="p"><option timestep="{ts}"/>
<worldbody><body name="pole" pos="0 0 1"><joint name="hinge" type="hinge" axis="0 1 0"/>
<geom name="rod" type="capsule" size="{size}" fromto="0 0 0 0 0 -0.5" mass="{mass}"/></body></worldbody>
<actuator><motor joint="hinge" ctrlrange="-1 1" ctrllimited="true"/></actuator></mujoco>"""


def run(cmd: list[str], cwd: Path, timeout: float = 240.0) -> tuple[int | None, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    try:
        p = subprocess.run([sys.executable, "-m", "gnwarp.cli", *cmd], cwd=cwd, env=env, capture_output=True,
                           text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, "no exit within the time limit"
    return p.returncode, (p.stdout + p.stderr)


def classify(rc: int | None, out: str, valid: bool) -> str:
    if rc is None:
        return "hang"
    if rc < 0:
        return "crash"
    if rc == 0:
        return "right result" if valid else "silently accepted"
    if valid:
        return "unclear error" if "Traceback" in out else "clear error (on valid input)"
    return "unclear error" if "Traceback" in out else "clear error"


def last_line(out: str) -> str:
    lines = [ln for ln in out.strip().splitlines() if ln.strip() and not ln.startswith("Warp")]
    return lines[-1][:200] if lines else ""


# -- fixtures: one small valid dataset and checkpoint, then corrupted copies -------------------
def make_fixtures(work: Path) -> tuple[Path, Path]:
    from gnwarp import data
    from gnwarp.models import GNCoreConfig, ModelConfig
    from gnwarp.train import TrainConfig, train
    ds = data.generate("pendulum", (6, 2, 2), num_steps=12, seed=0, backend="mujoco", progress=False)
    path = work / "good.h5"
    ds.save(path, overwrite=True)
    tiny = GNCoreConfig(latent=8, edge_hidden=(8,), node_hidden=(8,), global_hidden=(8,))
    r = train(TrainConfig(data=[str(path)], out=str(work / "run"), model=ModelConfig(gn=tiny), steps=4,
                          batch_size=8, valid_every=2, valid_sequences=2, checkpoint_every=2, progress=False,
                          device="cpu"))
    return path, Path(r["best"])


def dataset_cases(good: Path, work: Path) -> dict[str, Path]:
    import shutil

    import h5py
    cases = {}

    def copy(name):
        p = work / f"{name}.h5"
        shutil.copy(good, p)
        return p

    def edit(name, fn):
        p = copy(name)
        with h5py.File(p, "r+") as f:
            fn(f)
        cases[name] = p

    def setv(key, idx, value):  # "train/..." keys: the same change in the test split (what evaluate reads)
        keys = [key, key.replace("train/", "test/")] if key.startswith("train/") else [key]

        def fn(f):
            for k in keys:
                a = f[k][...]
                a[idx] = value
                f[k][...] = a
        return fn

    def retype(key, dtype):
        def fn(f):
            a = f[key][...].astype(dtype)
            attrs = dict(f[key].attrs)
            del f[key]
            f.create_dataset(key, data=a)
            for k, v in attrs.items():
                f[key].attrs[k] = v
        return fn

    edit("nan_state", setv("train/body", (1, 3, 1, 0), np.nan))
    edit("inf_ctrl", setv("train/ctrl", (0, 2, 0), np.inf))
    edit("huge_state", setv("train/body", (0, 1, 1, 8), 1e30))
    edit("int32_states", retype("train/body", np.int32))
    edit("sender_99", setv("static/senders", (0, 0), 99))
    edit("sender_negative", setv("static/senders", (0, 0), -3))
    edit("sender_1e9", setv("static/senders", (0, 0), 10**9))
    edit("n_node_mismatch", setv("static/n_node", 0, 1))
    edit("n_edge_mismatch", setv("static/n_edge", 0, 0))
    edit("edge_ctrl_out_of_range", setv("static/edge_ctrl", (0, 0, 0), 7))
    # bytes flipped inside the stored states (the checksum must catch them)
    p = copy("flipped_bytes")
    offsets = []
    with h5py.File(p, "r") as f:
        for key in ("train/body", "test/body"):
            ds = f[key]
            offsets.append(ds.id.get_offset() if ds.chunks is None else ds.id.get_chunk_info(0).byte_offset)
    raw = bytearray(p.read_bytes())
    for offset in offsets:
        for k in range(16):
            raw[offset + 64 + k] ^= 0xFF
    p.write_bytes(bytes(raw))
    cases["flipped_bytes"] = p
    p = work / "truncated.h5"
    p.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    cases["truncated"] = p
    p = work / "not_hdf5.h5"
    p.write_text("hello\n")
    cases["not_hdf5"] = p
    cases["missing_file"] = work / "does_not_exist.h5"
    return cases


def checkpoint_cases(good: Path, work: Path) -> dict[str, Path]:
    import hashlib
    import pickle
    import shutil

    import torch
    cases = {}

    def copy(name):
        p = work / f"ckpt_{name}"
        shutil.copytree(good, p)
        return p

    def resign(p):
        m = {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(p.iterdir()) if f.name != "manifest.json"}
        (p / "manifest.json").write_text(json.dumps(m))

    class Payload:
        def __reduce__(self):
            return (os.mkdir, (str(work / "PAYLOAD_RAN"),))

    p = copy("pickle_payload")
    (p / "training.pt").write_bytes(pickle.dumps({"optimizer": Payload()}))
    resign(p)
    cases["pickle_payload"] = p
    p = copy("nan_weights")
    sd = torch.load(p / "model.pt", weights_only=True)
    k = next(k for k, v in sd.items() if v.is_floating_point() and v.numel() > 1 and "norm" not in k)
    sd[k][0] = float("nan")
    torch.save(sd, p / "model.pt")
    resign(p)
    cases["nan_weights"] = p
    p = copy("manifest_without_model")
    m = json.loads((p / "manifest.json").read_text())
    m.pop("model.pt")
    (p / "manifest.json").write_text(json.dumps(m))
    cases["manifest_without_model"] = p
    p = copy("unlisted_file")
    (p / "extra.pt").write_bytes(b"x")
    cases["unlisted_file"] = p
    p = copy("corrupt_weights")
    raw = bytearray((p / "model.pt").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (p / "model.pt").write_bytes(bytes(raw))
    cases["corrupt_weights"] = p
    p = copy("garbage_config")
    (p / "config.json").write_text("{not json")
    resign(p)
    cases["garbage_config"] = p
    p = copy("absurd_size")
    cfg = json.loads((p / "config.json").read_text())
    cfg["model"]["gn"]["edge_hidden"] = [60000, 60000, 60000]
    (p / "config.json").write_text(json.dumps(cfg))
    resign(p)
    cases["absurd_size"] = p
    return cases


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default="dataset,checkpoint,config,mjcf,args,valid")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "reliability"))
    args = ap.parse_args()
    groups = set(args.only.split(","))
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        good, ckpt = make_fixtures(work)

        def case(group, name, cmd, valid=False, check=None):
            rc, out = run(cmd, work)
            outcome = classify(rc, out, valid)
            if check is not None and not check():
                outcome = "unsafe: " + outcome
            rows.append({"group": group, "case": name, "command": " ".join(cmd[:2]), "exit": rc, "outcome": outcome,
                         "message": last_line(out)})
            print(json.dumps(rows[-1]), flush=True)

        if "valid" in groups:  # controls: valid inputs must keep working
            case("valid", "good dataset", ["check", str(good)], valid=True)
            case("valid", "good checkpoint", ["check", str(ckpt)], valid=True)
            case("valid", "evaluate", ["evaluate", str(ckpt), "--data", str(good), "-n", "2", "--horizons", "5"],
                 valid=True)
        if "dataset" in groups:
            for name, p in dataset_cases(good, work).items():
                case("dataset", f"{name}: check", ["check", str(p)])
                case("dataset", f"{name}: evaluate", ["evaluate", str(ckpt), "--data", str(p), "-n", "2",
                                                      "--horizons", "5"])
                case("dataset", f"{name}: train", ["train", "--data", str(p), "-o", str(work / f"t_{name}"),
                                                   "--set", "steps=2", "--set", "device=cpu", "-q"])
        if "checkpoint" in groups:
            for name, p in checkpoint_cases(ckpt, work).items():
                ran = lambda: not (work / "PAYLOAD_RAN").exists()  # noqa: E731
                case("checkpoint", f"{name}: check", ["check", str(p)], check=ran)
                # evaluate reads config.json and model.pt only: with a payload in training.pt its right
                # result is to evaluate the (intact) model without ever unpickling that file
                case("checkpoint", f"{name}: evaluate", ["evaluate", str(p), "--data", str(good), "-n", "2",
                                                         "--horizons", "5"], valid=name == "pickle_payload", check=ran)
        if "config" in groups:
            base = ["train", "--data", str(good), "-o", str(work / "cfg"), "-q", "--set", "device=cpu"]
            for kv in ("steps=abc", "batch_size=1.5", "valid_every=0", "lr_decay_steps=0", "valid_horizon=0",
                       "grad_clip=-1", "model.gn.edge_hidden=5", "seed=-1", "model.gn.latent=10000000",
                       "optimizer=sgd", "no_such_key=1"):
                case("config", f"--set {kv}", [*base, "--set", kv])
            bad = work / "bad.toml"
            bad.write_text("steps = 10\nbatch_size = [\n")
            case("config", "malformed TOML file", ["train", str(bad), "--data", str(good), "-q"])
        if "args" in groups:
            case("args", "evaluate -n -1", ["evaluate", str(ckpt), "--data", str(good), "-n", "-1"])
            case("args", "evaluate --horizons 0", ["evaluate", str(ckpt), "--data", str(good), "--horizons", "0"])
            case("args", "generate --steps 1e9", ["generate", "pendulum", "--steps", "1000000000", "-o",
                                                  str(work / "big.h5"), "-q"])
            case("args", "generate --seed -1", ["generate", "pendulum", "--seed", "-1", "-o", str(work / "s.h5"), "-q"])
            case("args", "unknown system", ["generate", "pendulun", "-o", str(work / "u.h5"), "-q"])
        if "mjcf" in groups:
            for name, kw in {"nan mass": dict(ts=0.01, size=0.05, mass="nan"),
                             "zero timestep": dict(ts=0, size=0.05, mass=1),
                             "negative timestep": dict(ts=-0.01, size=0.05, mass=1),
                             "nan timestep": dict(ts="nan", size=0.05, mass=1),
                             "mass 1e30": dict(ts=0.01, size=0.05, mass=1e30),
                             "size 1e30": dict(ts=0.01, size=1e30, mass=1)}.items():
                f = work / f"{name.replace(' ', '_')}.xml"
                f.write_text(MJCF.format(**kw))
                case("mjcf", name, ["generate", "--mjcf", str(f), "--train", "2", "--valid", "1", "--test", "1",
                                    "--steps", "5", "-o", str(work / f"{f.stem}.h5"), "-q"])
            f = work / "malformed.xml"
            f.write_text("<mujoco><worldbody><body></mujoco>")
            case("mjcf", "malformed XML", ["generate", "--mjcf", str(f), "-o", str(work / "m.h5"), "-q"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cases.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    counts = {}
    for r in rows:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    lines = ["# Bad input, end to end through `gnwarp`", "",
             f"`python bench/adversarial.py` ({time.strftime('%Y-%m-%d')}, CPU, {time.perf_counter() - t0:.0f} s): "
             f"{len(rows)} cases, each in its own process.", "",
             "| outcome | cases |", "|---|---|"] + [f"| {k} | {v} |" for k, v in sorted(counts.items())] + [
             "", "| group | case | command | exit | outcome | last line of output |", "|---|---|---|---|---|---|"]
    for r in rows:
        msg = r["message"].replace("|", "/")
        lines.append(f"| {r['group']} | {r['case']} | `{r['command']}` | {r['exit']} | {r['outcome']} | {msg} |")
    (out / "cases.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[:12]))


if __name__ == "__main__":
    main()
