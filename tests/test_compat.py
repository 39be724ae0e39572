"""Files written before a format change still load, and the simulator's data is bit for bit the same.

The fixtures under ``tests/data/compat`` were written once by ``tests/data/make_compat.py`` (see its
docstring for the commit): a tiny Pendulum dataset, a checkpoint of a tiny GN trained 10 steps on
it, that checkpoint's one-step prediction, and the sha256 of every array of the dataset.
"""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.data.dataset import check as check_dataset
from gnwarp.train import load_model
from gnwarp.train.checkpoint import check_checkpoint, load_training, training_env_steps

HERE = Path(__file__).resolve().parent / "data"
COMPAT = HERE / "compat"


@pytest.fixture(scope="module")
def make_compat():
    import importlib.util
    spec = importlib.util.spec_from_file_location("make_compat", HERE / "make_compat.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def expected_sums():
    return json.loads((COMPAT / "pendulum_tiny_sha256.json").read_text())


def test_committed_dataset_loads_with_its_arrays(make_compat, expected_sums):
    ds = data.load(COMPAT / "pendulum_tiny.h5")
    try:
        assert ds.system == "pendulum" and ds.meta["num_steps"] == 10
        assert {s: len(ds[s]) for s in ds.splits} == {"train": 4, "valid": 2, "test": 2}
        train = ds["train"].load()
        assert train.body.shape == (4, 11, 2, 13) and train.ctrl.shape == (4, 10, 1)
        assert train.qpos.shape == (4, 11, 1) and train.instance.shape == (4,)
        assert np.all(np.isfinite(train.body))
        assert make_compat.checksums(ds) == expected_sums
        lines = check_dataset(COMPAT / "pendulum_tiny.h5")
        assert len(lines) == 1 and lines[0].startswith("ok: "), lines
    finally:
        ds.close()


def test_same_seed_simulates_the_same_arrays(make_compat, expected_sums):
    spec = dict(make_compat.SPEC)
    ds = data.generate(spec.pop("system"), spec.pop("num_sequences"), progress=False, **spec)
    got = make_compat.checksums(ds)
    assert sorted(got) == sorted(expected_sums)
    changed = [k for k in got if got[k] != expected_sums[k]]
    assert changed == [], f"arrays differ from the committed checksums: {changed}"


def test_committed_checkpoint_loads_and_predicts_the_same():
    path = COMPAT / "checkpoint"
    lines = check_checkpoint(path)
    assert lines and all(line.startswith("ok: ") for line in lines), lines
    ds = data.load(COMPAT / "pendulum_tiny.h5")
    try:
        model = load_model(path, device="cpu").bind(ds)
        test = ds["test"].load()
    finally:
        ds.close()
    assert model.config.gn.latent == 8
    with torch.no_grad():
        nxt = model.predict(torch.as_tensor(test.body[:, 0]), torch.as_tensor(test.ctrl[:, 0]),
                            torch.as_tensor(test.instance))
    expected = np.load(COMPAT / "checkpoint_prediction.npy")
    assert nxt.shape == expected.shape == (2, 2, 13)
    np.testing.assert_allclose(nxt.numpy(), expected, rtol=1e-5, atol=1e-6)
    training = load_training(path)
    assert training["state"]["step"] == 10
    assert training_env_steps(path) == 4 * 10   # 4 train sequences of 10 steps
