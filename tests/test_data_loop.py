"""The data loop (gnwarp.control.data_loop) on the CPU with a tiny pendulum model: an iteration
grows the dataset and writes its record, a loop resumes without redoing or double-counting an
iteration (also after a kill between its shard and its training), a corrupt state file is
refused, and the errors before training are those of the planning model on the new states."""
import dataclasses
import json
import shutil

import numpy as np
import pytest

from gnwarp.control import data_loop
from gnwarp.control.data_loop import LoopConfig, LoopStateError, run_loop
from gnwarp.control.loop_store import read_state
from gnwarp.data.dataset import check, load
from gnwarp.eval.metrics import evaluate
from gnwarp.eval.records import read_records, write_records
from gnwarp.files import sha256_file
from gnwarp.validation import ConfigError

TINY = {"model": {"gn": {"latent": 8, "edge_hidden": [16], "node_hidden": [16], "global_hidden": [16]},
                  "run": {"impl": "torch"}},
        "batch_size": 32, "lr": 3e-3, "valid_every": 40, "valid_sequences": 3, "log_every": 20,
        "checkpoint_every": 20, "normalizer_warmup": 2}
EPISODES, STEPS, SEQ, SEED_SEQ, INITIAL, PER_ITER = 2, 12, 6, 8, 40, 20


def config(out, iterations, **kw) -> LoopConfig:
    return LoopConfig(**{**dict(task="pendulum-balance", out=str(out), episodes=EPISODES, episode_steps=STEPS,
                                seq_len=SEQ, iterations=iterations, train_steps=PER_ITER,
                                initial_train_steps=INITIAL, seed_sequences=SEED_SEQ, seed_valid=3,
                                eval_sequences=100, error_horizon=4, train=TINY, backend="mujoco", device="cpu",
                                progress=False, planner_settings={"iterations": 2, "horizon": 4, "warmup": 1,
                                                                  "proposals": 2}), **kw})


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    """A loop run for 1 iteration, then called again for 2 (as after a kill at iteration 1)."""
    out = tmp_path_factory.mktemp("loop") / "run"
    first = run_loop(config(out, 1))
    after_one = {"shard": sha256_file(out / "data/iter-0001.h5"),
                 "model": sha256_file(out / "models/iter-0001/model.pt"),
                 "records": read_records(out / "records.jsonl"), "state": read_state(out), "result": first}
    second = run_loop(config(out, 2))
    return out, after_one, second


def test_an_iteration_grows_the_dataset_and_writes_its_record(loop):
    out, one, _ = loop
    seed = load(out / "data/seed.h5")
    shard = load(out / "data/iter-0001.h5")
    assert len(seed["train"]) == SEED_SEQ and len(shard["train"]) == EPISODES * STEPS // SEQ
    assert shard["train"].num_steps == SEQ and len(shard["valid"]) == len(shard["test"]) == 0
    assert check(out / "data/iter-0001.h5")[-1].startswith("ok:")   # a valid dataset: gnwarp check
    # the shard's sequences are the episodes cut in pieces: each one's last state the next one's first
    body = np.asarray(shard["train"].body)
    assert np.array_equal(body[0, -1], body[1, 0])
    (rec,) = one["records"]
    seed_steps = SEED_SEQ * SEQ
    assert rec.env_steps == seed_steps + EPISODES * STEPS == one["state"].env_steps
    assert rec.metrics["model_env_steps"] == seed_steps and rec.metrics["iteration"] == 1
    assert len(rec.returns) == EPISODES and rec.metrics["mean_return"] == pytest.approx(np.mean(rec.returns))
    assert rec.experiment == "loop" and rec.config["protocol"] == "loop" and rec.planner == "gradient"
    assert len(rec.config["initial_qpos"]) == EPISODES
    assert one["state"].train_steps == INITIAL + PER_ITER
    # a checkpoint's own count (what gnwarp mpc records as env_steps) agrees
    from gnwarp.train.checkpoint import training_env_steps
    assert training_env_steps(out / "models/iter-0001") == seed_steps
    assert training_env_steps(out / "models/iter-0002") == rec.env_steps
    for which in ("new", "trained"):
        assert np.isfinite(rec.metrics["errors"][which]["one_step"])


def test_a_resumed_loop_keeps_iteration_one_and_counts_env_steps_exactly(loop):
    out, one, second = loop
    assert second["iterations"] == 2 and one["result"]["iterations"] == 1
    # iteration 1 not redone: its shard, planning model and record are untouched
    assert sha256_file(out / "data/iter-0001.h5") == one["shard"]
    assert sha256_file(out / "models/iter-0001/model.pt") == one["model"]
    recs = read_records(out / "records.jsonl")
    assert [r.metrics["iteration"] for r in recs] == [1, 2]
    assert recs[0].to_dict() == one["records"][0].to_dict()
    per_iter = EPISODES * STEPS
    assert recs[1].env_steps == recs[0].env_steps + per_iter == second["env_steps"] == read_state(out).env_steps
    assert recs[1].metrics["model_env_steps"] == recs[0].env_steps
    assert read_state(out).train_steps == INITIAL + 2 * PER_ITER
    # run again with nothing left to do: no work, no new record
    assert run_loop(config(out, 2))["iterations"] == 2 and len(read_records(out / "records.jsonl")) == 2


def test_a_kill_between_shard_and_training_resumes_without_planning_again(loop, tmp_path, monkeypatch):
    out = tmp_path / "run"
    shutil.copytree(loop[0], out)

    def killed(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(data_loop, "_train", killed)
    with pytest.raises(KeyboardInterrupt):
        run_loop(config(out, 3))
    assert (out / "data/iter-0003.h5").is_file() and read_state(out).iteration == 2
    # a record written past the state (killed before the state file) is dropped on resume
    recs = (out / "records.jsonl").read_text().splitlines()
    fake = json.loads(recs[-1])
    fake["metrics"]["iteration"] = 3
    (out / "records.jsonl").write_text("\n".join(recs + [json.dumps(fake)]) + "\n")
    monkeypatch.undo()
    monkeypatch.setattr(data_loop, "_collect", lambda *a, **k: pytest.fail("planned iteration 3 again"))
    r = run_loop(config(out, 9, chunk=1))   # one iteration this call: the one whose shard is there
    recs = read_records(out / "records.jsonl")
    assert r["stop"] == "chunk" and [x.metrics["iteration"] for x in recs] == [1, 2, 3]
    assert r["env_steps"] == recs[-1].env_steps == SEED_SEQ * SEQ + 3 * EPISODES * STEPS
    # the kept shard's planning times, from its meta (not planned this call, not 0)
    kept = load(out / "data/iter-0003.h5").meta["loop"]
    assert recs[-1].metrics["plan_seconds"] == kept["plan_seconds"] > 0
    assert recs[-1].metrics["eval_seconds"] == kept["eval_seconds"]
    # a budget the last iteration's duration says the next would overrun: the call's first
    # iteration starts all the same (every call makes progress), no second one
    monkeypatch.undo()
    r = run_loop(config(out, 9, budget_seconds=recs[-1].metrics["iteration_seconds"] / 2))
    assert r["stop"] == "budget" and r["iterations"] == 4


def test_a_corrupt_or_inconsistent_state_file_is_refused(loop, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(loop[0], out)
    state = out / "state.json"
    good = state.read_text()
    state.write_text(good[: len(good) // 2])
    with pytest.raises(LoopStateError, match="state.json is not a valid state file.*not JSON"):
        run_loop(config(out, 2))
    d = json.loads(good)
    d["env_steps"] += 1
    state.write_text(json.dumps(d))
    with pytest.raises(LoopStateError, match="counts .* env steps, its data files hold"):
        run_loop(config(out, 2))
    d = json.loads(good)
    del d["train_steps"]
    state.write_text(json.dumps(d))
    with pytest.raises(LoopStateError, match="lacks train_steps"):
        run_loop(config(out, 2))
    state.write_text(good)
    (out / "data/iter-0002.h5").unlink()
    with pytest.raises(LoopStateError, match="lists data/iter-0002.h5, which is missing"):
        run_loop(config(out, 2))


def test_records_a_lost_state_would_drop_are_refused_not_trimmed(loop, tmp_path):
    """Without state.json, records of iterations past 0 (the state was lost) or of another
    experiment stay as they are and the loop is refused, naming them."""
    out = tmp_path / "run"
    shutil.copytree(loop[0], out)
    (out / "state.json").unlink()
    before = (out / "records.jsonl").read_bytes()
    with pytest.raises(ValueError, match="records of iterations past 0 but the folder has no loop state"):
        run_loop(config(out, 2))
    assert (out / "records.jsonl").read_bytes() == before
    other = tmp_path / "other"
    other.mkdir()
    rec = read_records(out / "records.jsonl")[0]
    write_records(other / "records.jsonl", [dataclasses.replace(rec, experiment="mpc")])
    with pytest.raises(ValueError, match="records of experiment 'mpc', not of a data loop"):
        run_loop(config(other, 1))
    assert len(read_records(other / "records.jsonl")) == 1


def test_errors_before_training_are_the_planning_models_on_the_new_states(loop):
    from gnwarp.train import load_model
    out = loop[0]
    rec = read_records(out / "records.jsonl")[1]
    shard = load(out / "data/iter-0002.h5", lazy=False)
    model = load_model(out / "models/iter-0002", device="cpu")
    direct = evaluate(model, shard, "train", None, (4,))
    got = rec.metrics["errors"]["new"]
    assert got["sequences"] == len(shard["train"])
    assert got["one_step"] == pytest.approx(direct["one_step"]["mean"], rel=1e-6)
    assert got["rollout"] == pytest.approx(direct["rollout_4"]["mean"], rel=1e-6)
    # ... and not those of the model trained on them, nor those on the training data
    trained = evaluate(load_model(out / "model/last", device="cpu"), shard, "train", None, (4,))
    assert trained["one_step"]["mean"] != pytest.approx(got["one_step"], rel=1e-3)
    assert rec.metrics["errors"]["trained"]["one_step"] != pytest.approx(got["one_step"], rel=1e-3)


def test_config_refusals(loop, tmp_path):
    with pytest.raises(ConfigError, match="episode_steps: must be a multiple of seq_len"):
        config(tmp_path, 1, episode_steps=STEPS + 1)
    with pytest.raises(ConfigError, match="train.out: is set by the loop"):
        config(tmp_path, 1, train={**TINY, "out": "x"})
    with pytest.raises(ConfigError, match="planner: unknown planner 'nope'"):
        config(tmp_path, 1, planner="nope")
    with pytest.raises(ConfigError, match="planner_settings.iterations"):
        config(tmp_path, 1, planner_settings={"iterations": 0})
    with pytest.raises(ConfigError, match="holds a loop of another config.*task"):
        run_loop(config(loop[0], 2, task="acrobot-swingup"))
    # a horizon whose rollouts cannot fit: refused before the folder is written, so the corrected
    # rerun in the same folder is taken
    huge = dict(planner_settings={"iterations": 1, "horizon": 10**9, "warmup": 0, "proposals": 1})
    with pytest.raises(ValueError, match="planning 2 episodes x 1 rollouts x horizon 1000000000 .* needs about"):
        run_loop(config(tmp_path / "new", 1, **huge))
    assert not (tmp_path / "new").exists()


def test_the_command_resumes_a_folder_from_its_config_and_plots(loop, capsys, tmp_path):
    from gnwarp.cli import main
    out = loop[0]
    assert main(["loop", "-o", str(out), "--iterations", "2", "-q"]) == 0
    text = capsys.readouterr().out
    assert "2 of 2 iterations finished" in text and (out / "loop.png").stat().st_size > 0
    assert main(["loop", "-o", str(out), "--task", "acrobot-swingup", "-q"]) == 2
    assert "holds a loop of another config" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert main(["loop", "-o", str(tmp_path / "file" / "run"), "-q"]) == 2   # refused before any work
    assert "gnwarp loop: error:" in capsys.readouterr().err and sorted(tmp_path.iterdir()) == [tmp_path / "file"]
    # --budget-seconds and --chunk bind one call: a rerun without them does not take them from config.json
    run = tmp_path / "run"
    shutil.copytree(out, run)
    assert main(["loop", "-o", str(run), "--iterations", "5", "--budget-seconds", "0.001", "--chunk", "9",
                 "--no-plot", "-q"]) == 0
    assert "3 of 5 iterations finished (budget)" in capsys.readouterr().out   # the call's first iteration only
    import argparse

    from gnwarp.control.loop_command import add_loop_arguments, loop_config
    parser = argparse.ArgumentParser()
    add_loop_arguments(parser)
    cfg = loop_config(parser.parse_args(["-o", str(run)]))   # config.json holds both; a rerun takes neither
    assert json.loads((run / "config.json").read_text())["chunk"] == 9
    assert (cfg.iterations, cfg.chunk, cfg.budget_seconds) == (5, None, None)
    assert main(["loop", "-o", str(run), "--no-plot", "-q"]) == 0   # the two left (read back: 4 of 5, budget)
    assert "5 of 5 iterations finished (iterations)" in capsys.readouterr().out


def test_the_tasks_own_initial_states_and_episode_length(tmp_path, monkeypatch):
    """A task with ``initial`` and ``episode_steps`` (the DMC tasks' fields, read with getattr):
    episodes start where ``initial`` puts them and last ``episode_steps`` steps."""
    import dataclasses
    from typing import Callable

    from gnwarp.control.tasks import TASKS, Task

    @dataclasses.dataclass(frozen=True)
    class Timed(Task):
        initial: Callable | None = None
        episode_steps: int | None = None
    calls = []

    def initial(system, n, rng):
        calls.append(n)
        return np.tile([0.3], (n, 1)) + rng.uniform(-0.01, 0.01, (n, 1)), np.zeros((n, 1))
    base = TASKS["pendulum-balance"]
    monkeypatch.setitem(TASKS, "pendulum-timed", Timed("pendulum-timed", "pendulum", 4, base.reward,
                                                       initial=initial, episode_steps=2 * SEQ))
    out = tmp_path / "run"
    run_loop(config(out, 1, task="pendulum-timed", episode_steps=None, planner="random", planner_settings={},
                    eval_episodes=3))
    rec, ev = read_records(out / "records.jsonl")
    assert calls == [EPISODES, 3] and rec.episode_steps == 2 * SEQ and rec.task == "pendulum-timed"
    # the evaluation episodes: a record of their own, their data neither stored nor counted
    assert (rec.variant, ev.variant, ev.episodes, ev.metrics["iteration"]) == ("loop", "loop-eval", 3, 1)
    assert ev.env_steps == ev.metrics["model_env_steps"] == rec.env_steps == read_state(out).env_steps
    assert ev.config["model"] == "models/iter-0002" and (out / "models/iter-0002/model.pt").is_file()
    assert ev.config["initial_qpos"] != rec.config["initial_qpos"][:3]
    assert np.allclose(np.asarray(rec.config["initial_qpos"]), 0.3, atol=0.011)
    shard = load(out / "data/iter-0001.h5", lazy=False)
    assert np.allclose(shard["train"].qpos[::2, 0], np.asarray(rec.config["initial_qpos"]), atol=1e-6)
    assert rec.env_steps == SEED_SEQ * SEQ + EPISODES * 2 * SEQ


def test_the_command_reads_its_config_like_train_does(tmp_path):
    """``gnwarp loop`` and ``gnwarp train`` share one config reader: TOML tables, --set into nested
    keys, and the same refusals (a file that is not text, a key inside a value that is no table)."""
    import argparse

    from gnwarp.cli.common import apply_overrides, read_config
    from gnwarp.control.loop_command import add_loop_arguments, loop_config
    parser = argparse.ArgumentParser()
    add_loop_arguments(parser)
    toml = tmp_path / "loop.toml"
    toml.write_text('task = "pendulum-balance"\nepisodes = 3\n[planner_settings]\niterations = 4\n')
    args = parser.parse_args([str(toml), "-o", str(tmp_path / "run"), "--set", "planner_settings.horizon=6",
                              "--episodes", "5"])
    cfg = loop_config(args)
    assert (cfg.task, cfg.episodes, cfg.planner_settings) == ("pendulum-balance", 5, {"iterations": 4, "horizon": 6})
    binary = tmp_path / "bad.json"
    binary.write_bytes(b"\xff\xfe\x00")
    for read in (lambda p: loop_config(parser.parse_args([p, "-o", str(tmp_path / "run")])), read_config):
        with pytest.raises(ConfigError, match="bad.json: not a text file"):
            read(str(binary))
    for apply in (lambda d, items: loop_config(parser.parse_args([str(toml), "--set", items[0]])), apply_overrides):
        with pytest.raises(ConfigError, match="task: is not a nested config"):
            apply({"task": "x"}, ["task.x=1"])
