"""Tiny datasets pinned by checksum: the arrays a seed gives stay the same bit for bit (MuJoCo C
backend, the MuJoCo release they were recorded with; MuJoCo-Warp agrees with MuJoCo C within
tolerance, tests/test_data.py)."""
import hashlib

import mujoco
import numpy as np
import pytest

from gnwarp.data.generation import generate

RECORDED_WITH = "4.0.0"   # mujoco.__version__ of the checksums below
PINNED = {
    ("pendulum", False): "6feb637b7f5994d3eecd833ac7027f93dbb49bb6a91a2f82822aeef17b37b55e",
    ("cartpole", True): "a552d8354e2ec135be2b1946fc4b0b923674b6d384a10bb973982280b4739091",
    ("swimmer", True): "83b8fc22e47291ae730cb90e118e0140d925df321a3ac7d6a9e5e098416e348c",
}


def checksum(ds) -> str:
    """sha256 over every split's body, ctrl, qpos and qvel and the static arrays, in a fixed order."""
    h = hashlib.sha256()
    for split in ("train", "valid", "test"):
        for key in ("body", "ctrl", "qpos", "qvel"):
            h.update(np.ascontiguousarray(getattr(ds[split], key)).tobytes())
    for key in sorted(ds.static):
        h.update(np.ascontiguousarray(ds.static[key]).tobytes())
    return h.hexdigest()


@pytest.mark.skipif(mujoco.__version__ != RECORDED_WITH, reason=f"checksums recorded with MuJoCo {RECORDED_WITH}")
@pytest.mark.parametrize("name,parameterized", list(PINNED))
def test_tiny_dataset_checksum(name, parameterized):
    ds = generate(name, num_sequences=(3, 1, 1), num_steps=8, seed=11, parameterized=parameterized,
                  backend="mujoco", progress=False)
    assert checksum(ds) == PINNED[(name, parameterized)]
