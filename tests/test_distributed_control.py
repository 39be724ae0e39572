"""Control episodes over several ranks on the CPU (gloo), started as torchrun starts them:
``gnwarp mpc`` on two ranks writes the record one process writes (the same episodes, returns in
the same order), and ``Ranks.map_sharded`` gathers results in the items' order and ends every
rank when one fails."""
import json
from pathlib import Path

import pytest

from gnwarp.distributed import DistributedError, Ranks, unshard
from ranks import start_ranks

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    from gnwarp import data
    from gnwarp.gn import RunOptions
    from gnwarp.models import GNCoreConfig, ModelConfig
    from gnwarp.train import TrainConfig, train
    ds = data.generate("pendulum", (6, 2, 2), num_steps=8, seed=0, backend="mujoco", progress=False)
    out = tmp_path_factory.mktemp("mpc-ranks") / "run"
    cfg = TrainConfig(out=str(out), model=ModelConfig(gn=GNCoreConfig(latent=8, edge_hidden=(8,), node_hidden=(8,),
                                                                      global_hidden=(8,)),
                                                      run=RunOptions(impl="torch")),
                      steps=2, batch_size=4, valid_every=2, valid_sequences=2, checkpoint_every=2,
                      normalizer_warmup=1, progress=False, device="cpu")
    return train(cfg, [ds])["last"]


def mpc_argv(model, records):
    # gradient MPC from the mid sequence (no random draws): each episode's plan is its own, however batched
    return ["mpc", "--model", str(model), "--task", "pendulum-balance", "--episodes", "3", "--steps", "2",
            "--horizon", "3", "--iterations", "1", "--warmup", "1", "--proposals", "0", "--set", "init_std=0",
            "--seed", "4", "--backend", "mujoco", "--device", "cpu", "--video", "none", "--records", str(records),
            "-q"]


def test_mpc_on_two_ranks_writes_the_record_of_one_process(tiny_model, tmp_path, capsys):
    from gnwarp.cli import main
    one, two = tmp_path / "one.jsonl", tmp_path / "two.jsonl"
    assert main(mpc_argv(tiny_model, one)) == 0
    codes, outs = start_ranks(["-m", "gnwarp.cli", *mpc_argv(tiny_model, two)])
    assert codes == [0, 0], "\n".join(outs)
    assert "true return" in outs[0] and "on 2 ranks" in outs[0] and "true return" not in outs[1], outs
    a, = [json.loads(line) for line in one.read_text().splitlines()]
    b, = [json.loads(line) for line in two.read_text().splitlines()]
    assert len(a["returns"]) == 3 and len(set(a["returns"])) == 3, a["returns"]
    assert b["returns"] == pytest.approx(a["returns"], rel=1e-5, abs=1e-6)
    for k in ("initial_qpos", "initial_qvel", "targets", "settings"):
        assert b["config"][k] == a["config"][k], k
    assert b["metrics"]["ranks"] == 2 and "ranks" not in a["metrics"]
    assert len(b["metrics"]["plan_ms"]) == 2 and b["episodes"] == 3
    assert not list(tmp_path.glob("*.tmp*"))


WORKER = """
import sys
from gnwarp.distributed import DistributedError, close, ranks
r = ranks("cpu")
print("sharded", r.map_sharded(range(7), lambda x: (x * x, r.rank)))
print("batched", r.map_sharded(list("abcde"), lambda xs: [x.upper() for x in xs], batched=True))
def fail(x):
    if x == 3:
        raise KeyError("item three")
    return x
try:
    r.map_sharded(range(5), fail)
except DistributedError as e:
    print("other:", e)
except KeyError as e:
    print("own:", e)
close()
"""


def test_map_sharded_gathers_in_the_items_order_and_a_failing_rank_ends_the_others():
    codes, outs = start_ranks(["-c", WORKER], env={"PYTHONPATH": str(ROOT)})
    assert codes == [0, 0], "\n".join(outs)
    squares = [(x * x, x % 2) for x in range(7)]
    assert f"sharded {squares}" in outs[0] and "sharded None" in outs[1]
    assert "batched ['A', 'B', 'C', 'D', 'E']" in outs[0] and "batched None" in outs[1]
    assert "own: 'item three'" in outs[1], outs[1]     # item 3 is rank 1's
    assert "other: rank 0 of 2: map_sharded: rank 1 failed (KeyError: 'item three')" in outs[0], outs[0]


def test_map_sharded_in_one_process_and_unshard():
    one = Ranks()
    assert one.map_sharded(range(4), lambda x: -x) == [0, -1, -2, -3]
    assert one.map_sharded([], lambda xs: 1 / 0, batched=True) == []
    with pytest.raises(ZeroDivisionError):
        one.map_sharded([1], lambda x: 1 / 0)
    with pytest.raises(ValueError, match="returned 1 results for 2 items"):
        one.map_sharded([1, 2], lambda xs: [0], batched=True)
    assert unshard([[0, 3, 6], [1, 4], [2, 5]]) == list(range(7))
    with pytest.raises(DistributedError, match=r"\[1, 2\] results"):
        unshard([[0], [1, 2]])


def test_rl_seeds_on_two_ranks_run_each_seed_once_and_rank_0_prints_them_in_order(tmp_path):
    runs, results = tmp_path / "runs", tmp_path / "res"
    # every seed's process stops at once on an unknown task (a bad key is refused before any starts):
    # what is measured is who ran it and who printed
    codes, outs = start_ranks([str(ROOT / "bench" / "rl_seeds.py"), "--quick", "--seeds", "0-2", "--threads", "1",
                               "--runs", str(runs), "--results", str(results), "--set", "task=no-such-task"])
    assert codes == [1, 0], "\n".join(outs)
    lines = [line for line in outs[0].splitlines() if line.startswith("seed ")]
    assert [line.split(":")[0] for line in lines] == ["seed 0", "seed 1", "seed 2"], outs[0]
    assert all("exit 1" in line for line in lines), lines
    assert "3 seeds in" in outs[0] and "on 2 ranks" in outs[0]
    assert "seed " not in outs[1] and "no-such-task" in outs[0]
    logs = sorted(p.parent.name for p in runs.rglob("call.log"))
    assert logs == ["s0", "s1", "s2"]
    assert all("no-such-task" in p.read_text() for p in runs.rglob("call.log"))
    assert not results.exists()


def test_rl_seeds_rank_env_on_a_cpu_run():
    from bench.rl_seeds import TORCHRUN_VARS, rank_env
    assert rank_env(0, "cpu") == {} and rank_env(5, "cpu") == {}
    assert {"WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_PORT"} <= set(TORCHRUN_VARS)


@pytest.mark.parametrize("command", [["rl", "--agent", "svg0", "-o", "x"],
                                     ["evaluate", "x", "--data", "x.h5"]])
def test_one_process_commands_refuse_torchrun(command, monkeypatch, capsys, tmp_path):
    from gnwarp.cli import main
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main(command) == 2
    err = capsys.readouterr().err
    assert "not under torchrun" in err and f"gnwarp {command[0]}: error" in err
    assert not (tmp_path / "x").exists()
