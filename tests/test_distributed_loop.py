"""The data loop over two ranks on the CPU (gloo), started as torchrun starts them: from the
same folder (the seed data and its model, which the ranks resume), iteration 1's episodes on
two ranks are one process's (returns, states, actions, errors), rank 0 alone writes the folder
(its value fit included), and the folder it leaves is complete and resumable."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gnwarp.control.data_loop import LoopConfig, run_loop
from gnwarp.control.loop_store import read_state
from gnwarp.data.dataset import check, load
from gnwarp.eval.records import read_records
from ranks import start_ranks

ROOT = Path(__file__).resolve().parent.parent

TINY = {"model": {"gn": {"latent": 8, "edge_hidden": [8], "node_hidden": [8], "global_hidden": [8]},
                  "run": {"impl": "torch"}},
        "batch_size": 8, "valid_every": 10, "valid_sequences": 2, "log_every": 5, "checkpoint_every": 10,
        "normalizer_warmup": 1}
# gradient MPC from the mid sequence (no random draws): each episode's plan is its own, however batched
KEYS = dict(task="pendulum-balance", episodes=3, episode_steps=4, seq_len=4, train_steps=4, initial_train_steps=4,
            seed_sequences=4, seed_valid=2, eval_episodes=3, eval_sequences=8, error_horizon=2, train=TINY,
            backend="mujoco", device="cpu", progress=False, seed=3,
            planner_settings={"iterations": 1, "horizon": 3, "warmup": 1, "proposals": 0, "init_std": 0.0,
                              "discount": 0.9},
            value={"hidden": [8], "rounds": 1, "steps": 2, "batch": 8})

# rank 1 may write nothing: every file of the loop and its training goes through atomic_write or write_records
WORKER = """
import os, sys
import gnwarp.files
if os.environ["RANK"] != "0":
    def refuse(path, *a, **k):
        raise PermissionError(f"rank {os.environ['RANK']} wrote {path}")
    gnwarp.files.atomic_write = refuse
    import gnwarp.eval.records
    gnwarp.eval.records.write_records = refuse
from gnwarp.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_loop_on_two_ranks_collects_one_process_episodes_and_rank_0_writes(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    run_loop(LoopConfig(**KEYS, out=str(one), iterations=0))   # the seed data and its model
    shutil.copytree(one, two)
    run_loop(LoopConfig(**KEYS, out=str(one), iterations=1))
    codes, outs = start_ranks(["-c", WORKER, "loop", "-o", str(two), "--iterations", "1", "-q", "--no-plot"],
                              env={"PYTHONPATH": str(ROOT)})
    assert codes == [0, 0], "\n".join(outs)
    assert "1 of 1 iterations finished" in outs[0] and "iterations finished" not in outs[1], outs
    a, b = load(one / "data/iter-0001.h5", lazy=False), load(two / "data/iter-0001.h5", lazy=False)
    ma, mb = a.meta["loop"], b.meta["loop"]
    assert len(ma["returns"]) == 3 and len(set(ma["returns"])) == 3, ma["returns"]
    assert mb["returns"] == pytest.approx(ma["returns"], rel=1e-5, abs=1e-6)
    for k in ("initial_qpos", "initial_qvel", "targets", "backend", "model"):
        assert mb[k] == ma[k], k
    for k in ("body", "ctrl", "qpos", "qvel"):
        np.testing.assert_allclose(np.asarray(getattr(b["train"], k)), np.asarray(getattr(a["train"], k)),
                                   rtol=1e-5, atol=1e-6, err_msg=k)
    for which in ("new", "trained"):   # measured on rank 0 with the same model on the same states
        assert mb["errors"][which]["one_step"] == pytest.approx(ma["errors"][which]["one_step"], rel=1e-5)
    # the folder is complete: state, record of the data and evaluation episodes, checkpoints
    state = read_state(two)
    assert state.iteration == 1 and state.train_steps == 8 and state.env_steps == read_state(one).env_steps
    recs = read_records(two / "records.jsonl")
    assert [r.variant for r in recs] == ["loop", "loop-eval"] and len(recs[1].returns) == 3
    # the value rank 0 fitted after training, which every rank's evaluation episodes planned with
    assert recs[1].config["value"] == "value/iter-0002.pt" and (two / "value/iter-0002.pt").is_file()
    assert recs[0].returns == pytest.approx(ma["returns"], rel=1e-5, abs=1e-6)
    assert check(two / "data/iter-0001.h5")[-1].startswith("ok:")
    for p in ("models/iter-0001/model.pt", "models/iter-0002/model.pt", "model/last/model.pt"):
        assert (two / p).is_file(), p
    assert json.loads((two / "config.json").read_text())["episodes"] == 3
    assert not [p for p in two.rglob("*") if ".tmp" in p.name]
    # and resumable (the ranks resumed the folder one process left): its state agrees with its files
    r = run_loop(LoopConfig(**KEYS, out=str(two), iterations=1))
    assert r["iterations"] == 1 and r["stop"] == "iterations" and len(read_records(two / "records.jsonl")) == 2


def test_one_ranks_plan_memory_refusal_stops_every_rank_before_the_folder_is_written(tmp_path):
    """Each rank checks its share of the planning memory on its own device; rank 1's refusal
    (rank 0's passes) stops both ranks before rank 0 writes the folder, so a corrected rerun is
    taken there."""
    worker = """
import os, sys
import gnwarp.control.planner
if os.environ["RANK"] == "1":
    def short(*a, **k):
        raise ValueError("rank 1: planning needs more memory than it has")
    gnwarp.control.planner.check_plan_memory = short
from gnwarp.cli import main
sys.exit(main(sys.argv[1:]))
"""
    out = tmp_path / "run"
    codes, outs = start_ranks(["-c", worker, "loop", "-o", str(out), "--task", "pendulum-balance",
                               "--iterations", "1", "--device", "cpu", "--backend", "mujoco", "-q", "--no-plot"],
                              env={"PYTHONPATH": str(ROOT)})
    assert codes == [2, 2], "\n".join(outs)
    assert all("rank 1: planning needs more memory than it has" in o for o in outs), outs
    assert not out.exists()
