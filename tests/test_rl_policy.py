"""A trained ``gnwarp rl`` agent as planner "policy": built from its run folder by
``make_planner``, refused for another task, and run by the data loop, whose shard then holds the
policy's own actions on the states it visited and the model's errors on them (Figure H.1)."""
import warnings

import numpy as np
import pytest
import torch

import gnwarp.rl.planner  # noqa: F401 - registers "policy"
from gnwarp.control.planner import get_planner, make_planner, planner_name
from gnwarp.rl.config import RLConfig
from gnwarp.rl.planner import PolicyPlanner, PolicySettings
from gnwarp.rl.run import load_agent, run_rl
from gnwarp.validation import ConfigError

warnings.filterwarnings("ignore", message=".*glfw.*")
RUN = dict(task="pendulum-balance", agent="ddpg", observation="bodies", num_envs=2, episode_steps=10, env_steps=40,
           hidden=(16,), buffer_size=1000, batch_size=8, start_steps=20, update_after=20, eval_every=40,
           eval_episodes=2, progress=False, device="cpu", backend="mujoco", tensorboard=False, video_episodes=0)


@pytest.fixture(scope="module")
def rl_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("rl") / "run"
    run_rl(RLConfig(**RUN, out=str(out)))
    return out


def test_policy_planner_from_a_run_folder(rl_run):
    assert get_planner("policy").settings is PolicySettings
    planner = make_planner("policy", None, "pendulum-balance", "pendulum", 3, {"run": str(rl_run), "device": "cpu"})
    assert isinstance(planner, PolicyPlanner) and planner_name(planner) == "policy" and planner.n == 3
    from gnwarp.sim import make_env
    env = make_env("pendulum", 3, backend="mujoco")
    body = env.reset(np.zeros((3, 1)) + [[0.1], [0.5], [-1.0]], np.zeros((3, 1)))
    agent, _, _ = load_agent(rl_run, "cpu")
    from gnwarp.control.env_observation import ObservationLayout
    from gnwarp.sim import systems
    want = agent.act(ObservationLayout(systems.make("pendulum"), None)(torch.as_tensor(body)),
                     deterministic=True)
    assert torch.equal(planner.step(body), want) and want.abs().max() > 0
    env.close()
    with pytest.raises(ConfigError, match="trained on task 'pendulum-balance', not '.*pendulum-swingup'"):
        make_planner("policy", None, "pendulum-swingup", "pendulum", 1, {"run": str(rl_run), "device": "cpu"})
    with pytest.raises(ConfigError, match="run: must name the folder"):
        PolicySettings()
    with pytest.raises(ConfigError, match="run: no gnwarp rl run in .*none: its config.json is missing"):
        make_planner("policy", None, "pendulum-balance", "pendulum", 1, {"run": str(rl_run.parent / "none")})


def test_the_data_loop_runs_a_trained_policy(rl_run, tmp_path):
    from gnwarp.control.data_loop import LoopConfig, run_loop
    from gnwarp.data.dataset import load
    from gnwarp.eval.records import read_records
    tiny = {"model": {"gn": {"latent": 8, "edge_hidden": [16], "node_hidden": [16], "global_hidden": [16]},
                      "run": {"impl": "torch"}}, "batch_size": 32, "lr": 3e-3, "valid_every": 40, "valid_sequences": 3,
            "log_every": 20, "checkpoint_every": 20, "normalizer_warmup": 2}
    cfg = LoopConfig(task="pendulum-balance", out=str(tmp_path / "loop"), episodes=2, episode_steps=12, seq_len=6,
                     iterations=1, train_steps=20, initial_train_steps=40, seed_sequences=8, seed_valid=3,
                     eval_sequences=100, error_horizon=4, train=tiny, backend="mujoco", device="cpu", progress=False,
                     planner="policy", planner_settings={"run": str(rl_run), "device": "cpu"})
    run_loop(cfg)
    (rec,) = read_records(tmp_path / "loop" / "records.jsonl")
    assert rec.planner == "policy" and len(rec.returns) == 2
    assert all(np.isfinite(rec.metrics["errors"][k]["one_step"]) for k in ("new", "trained"))
    shard = load(tmp_path / "loop" / "data" / "iter-0001.h5", lazy=False)["train"]
    body, ctrl = torch.as_tensor(np.asarray(shard.body)), torch.as_tensor(np.asarray(shard.ctrl))
    agent, _, _ = load_agent(rl_run, "cpu")
    from gnwarp.control.env_observation import ObservationLayout
    from gnwarp.sim import systems
    layout = ObservationLayout(systems.make("pendulum"), None)
    S, T = ctrl.shape[:2]
    acted = agent.act(layout(body[:, :T].reshape(S * T, *body.shape[2:]).float()), deterministic=True)
    torch.testing.assert_close(acted.reshape(S, T, -1).to(ctrl.dtype), ctrl, rtol=1e-5, atol=1e-6)
    with pytest.raises(ConfigError, match="takes no terminal value"):
        LoopConfig(**{**cfg.to_dict(), "out": str(tmp_path / "v"), "value": {}})


def test_gnwarp_mpc_acts_with_a_trained_policy(rl_run, tmp_path, capsys):
    from gnwarp.cli import main
    from gnwarp.eval.records import read_records
    rec_path = tmp_path / "r.jsonl"
    args = ["mpc", "--task", "pendulum-balance", "--policy", str(rl_run), "--episodes", "2", "--steps", "8",
            "--backend", "mujoco", "--device", "cpu", "--video", "none", "--records", str(rec_path), "-q"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "the trained policy of" in out and "true return" in out
    (rec,) = read_records(rec_path)
    assert rec.planner == "policy" and rec.dynamics == "none" and len(rec.returns) == 2 and rec.config["model"] is None
    agent, _, _ = load_agent(rl_run, "cpu")
    assert rec.env_steps == agent.env_steps == 40
    assert main(args[:-1] + ["--horizon", "5"]) == 2          # a planner's setting: refused, naming it
    assert "--horizon set a planner's settings" in capsys.readouterr().err
    assert main(["mpc", "--task", "pendulum-balance", "--episodes", "1", "--video", "none"]) == 2
    assert "--model is required" in capsys.readouterr().err
    for extra, words in ((["--planner", "gradient"], "takes no --planner"), (["--model", str(rl_run)], "takes no --model"),
                         (["--terminal", str(rl_run / "config.json")], "--terminal set a planner's settings"),
                         (["--set", "seed=1"], "--set set a planner's settings")):
        assert main(args[:-1] + extra) == 2
        assert words in capsys.readouterr().err
    assert main(["mpc", "--task", "pendulum-balance", "--planner", "policy", "--video", "none"]) == 2
    assert "--policy" in capsys.readouterr().err   # planner policy names its run with --policy


def test_policy_is_registered_by_its_module_only():
    import gnwarp.control.planner as cp
    entry = cp.PLANNERS.pop("policy")
    try:
        with pytest.raises(ValueError, match="registered by importing gnwarp.rl.planner"):
            cp.get_planner("policy")
    finally:
        cp.PLANNERS["policy"] = entry
