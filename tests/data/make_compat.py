"""Writes the format fixtures under ``tests/data/compat`` (run once; the files are committed).

    PYTHONPATH=. python3 tests/data/make_compat.py

The dataset, the checkpoint and the checksums were written by the code at commit e848b55, so
``tests/test_compat.py`` shows that files written by that code still load and that a dataset
simulated with the same seed on MuJoCo C is bit for bit the same. Rerunning this script with later
code overwrites that evidence: do so only on purpose (a format change, with its migration).
"""
import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

from gnwarp import data
from gnwarp.gn import RunOptions
from gnwarp.models import GNCoreConfig, ModelConfig
from gnwarp.train import TrainConfig, load_model, train

HERE = Path(__file__).resolve().parent / "compat"
# the dataset both files and the checksum test use: MuJoCo C on the CPU, fixed seed
SPEC = dict(system="pendulum", num_sequences=(4, 2, 2), num_steps=10, seed=0, backend="mujoco")
SPLIT_ARRAYS = ("body", "ctrl", "qpos", "qvel", "instance")


def array_sha256(a) -> str:
    """sha256 of an array's dtype, shape and bytes (C order)."""
    a = np.ascontiguousarray(np.asarray(a))
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def checksums(ds) -> dict[str, str]:
    """{"<split>/<array>": sha256} of every split array and {"static/<key>": ...} of each static array."""
    out = {}
    for name in sorted(ds.splits):
        sp = ds[name].load()
        for k in SPLIT_ARRAYS:
            out[f"{name}/{k}"] = array_sha256(getattr(sp, k))
    for k in sorted(ds.static):
        v = ds.static[k]
        if isinstance(v, np.ndarray):
            out[f"static/{k}"] = array_sha256(v)
    return out


def main() -> int:
    HERE.mkdir(parents=True, exist_ok=True)
    spec = dict(SPEC)
    ds = data.generate(spec.pop("system"), spec.pop("num_sequences"), progress=False, **spec)
    ds.save(HERE / "pendulum_tiny.h5", overwrite=True)
    (HERE / "pendulum_tiny_sha256.json").write_text(json.dumps(checksums(ds), indent=1, sort_keys=True) + "\n")

    torch.manual_seed(0)
    run = HERE / "run"
    shutil.rmtree(run, ignore_errors=True)
    model_cfg = ModelConfig(gn=GNCoreConfig(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,)),
                            run=RunOptions(impl="torch"))
    cfg = TrainConfig(out=str(run), model=model_cfg, steps=10, batch_size=8, lr=3e-3, lr_decay_steps=1000,
                      valid_every=5, valid_sequences=2, log_every=5, checkpoint_every=10, normalizer_warmup=2,
                      progress=False, device="cpu", seed=0)
    train(cfg, [ds])
    shutil.rmtree(HERE / "checkpoint", ignore_errors=True)
    shutil.copytree(run / "last", HERE / "checkpoint")
    shutil.rmtree(run)

    # what the checkpoint predicts for the test split's first step: the load test compares to it
    model = load_model(HERE / "checkpoint", device="cpu").bind(ds)
    test = ds["test"].load()
    with torch.no_grad():
        nxt = model.predict(torch.as_tensor(test.body[:, 0]), torch.as_tensor(test.ctrl[:, 0]),
                            torch.as_tensor(test.instance))
    np.save(HERE / "checkpoint_prediction.npy", nxt.numpy())
    return 0


if __name__ == "__main__":
    sys.exit(main())
