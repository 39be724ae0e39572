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


class _NegSquare(torch.nn.Module):
    """Q(x, a) = -w x^2 (a known value at the horizon)."""

    def __init__(self, w: float):
        super().__init__()
        self.w = w

    def forward(self, x, a):
        return -self.w * (x ** 2).sum(-1)


def _known_svg1(q_weight=1.0):
    """An SVG(1) agent with a known model x' = x + a, reward -(x')^2 and Q -w x^2, actions in [-1, 1]."""
    from gnwarp.rl.agents import make_agent
    from gnwarp.rl.settings import AgentSettings
    torch.manual_seed(0)
    return make_agent(AgentSettings(agent="svg1", hidden=(8,), gamma=0.9), 1, [-1.0], [1.0],
                      model=lambda x, a: x + a, reward=lambda x, a, x2: -(x2 ** 2).sum(-1), q=_NegSquare(q_weight))


def test_policy_mpc_scores_sequences_as_written_and_plans_towards_the_best(rl_run):
    """``PolicyMPC.returns`` is sum gamma^k r + gamma^H Q(x_H, pi(x_H)) through the agent's model;
    its plan from x = 1.5 with the model x' = x + a (reward -(x')^2) heads to 0 at full speed
    (the first action -1), where the untrained policy does not, and the plan is shifted to the
    next step; bad settings are refused naming the key."""
    from gnwarp.rl.planner import PolicyMPC, PolicyMPCSettings
    agent = _known_svg1()
    obs_of = lambda body, targets: body[:, 0, :1]   # noqa: E731
    s = PolicyMPCSettings(run=str(rl_run), device="cpu", horizon=3, samples=64, policy_samples=4, iterations=4,
                          elites=8, temperature=2.0)   # the agent given here, not the run's
    planner = PolicyMPC(agent, obs_of, 2, settings=s)
    obs = torch.tensor([[1.5], [-0.3]])
    acts = torch.tensor([[[[-1.0], [-0.5], [0.0]], [[0.5], [0.0], [0.0]]],
                         [[[0.3], [0.0], [0.0]], [[0.0], [0.0], [0.0]]]])      # [N=2, M=2, H=3, U=1]
    want = torch.zeros(2, 2)
    for i in range(2):
        for m in range(2):
            x = obs[i, 0]
            for k in range(3):
                x = x + acts[i, m, k, 0]
                want[i, m] += 0.9 ** k * -(x ** 2)
            want[i, m] += 0.9 ** 3 * -(x ** 2)
    torch.testing.assert_close(planner.returns(obs, acts), want)
    body = torch.zeros(2, 1, 13)
    body[:, 0, 0] = obs[:, 0]
    a = planner.step(body)
    assert a.shape == (2, 1) and float(a[0, 0]) < -0.9 and abs(float(a[1, 0]) - 0.3) < 0.15
    assert float(agent.act(obs, deterministic=True)[0, 0]) > -0.9     # the untrained policy does not
    assert planner.plan.shape == (2, 3, 1)                               # the plan, kept (shifted next step)
    assert torch.equal(planner.act(body, 0), a) and torch.equal(planner.act(body, 0), a)   # reads, plans nothing
    assert torch.equal(planner.act(body, 1), planner.plan[:, 1]) and torch.equal(planner.act(body, 9), planner.plan[:, 2])
    again = PolicyMPC(agent, obs_of, 2, settings=s).step(body)
    torch.testing.assert_close(a, again)                                 # the seed's draws
    for bad, key in ((dict(elites=300), "elites"), (dict(min_std=1.5), "min_std"), (dict(horizon=0), "horizon")):
        with pytest.raises(ConfigError, match=key):
            PolicyMPCSettings(run=str(rl_run), **bad)


def test_policy_mpc_from_a_run_needs_an_agent_with_a_model(rl_run):
    """make_planner("policy-mpc") over a ddpg run (no model) is refused, naming why."""
    from gnwarp.rl.planner import PolicyMPCSettings
    assert get_planner("policy-mpc").settings is PolicyMPCSettings
    with pytest.raises(ConfigError, match="learned model and reward: ddpg has none"):
        make_planner("policy-mpc", None, "pendulum-balance", "pendulum", 1, {"run": str(rl_run), "device": "cpu"})


def test_gnwarp_mpc_plans_over_a_trained_svg1_agent(tmp_path, capsys):
    """``gnwarp mpc --policy RUN --planner policy-mpc``: a tiny SVG(1) run on swimmer6 planned
    over with its own model and Q-function, in closed loop on MuJoCo C; its record names the
    planner and the learned dynamics; planner settings go through --set and --horizon."""
    from gnwarp.cli import main
    from gnwarp.eval.records import read_records
    run = tmp_path / "svg1"
    run_rl(RLConfig(**{**RUN, "task": "swimmer6", "agent": "svg1", "observation": "dmc", "episode_steps": 10},
                    out=str(run)))
    rec_path = tmp_path / "r.jsonl"
    args = ["mpc", "--task", "swimmer6", "--policy", str(run), "--planner", "policy-mpc", "--episodes", "2",
            "--steps", "4", "--horizon", "2", "--set", "samples=8", "--set", "elites=4", "--set", "iterations=2",
            "--backend", "mujoco", "--device", "cpu", "--video", "none", "--records", str(rec_path), "-q"]
    assert main(args) == 0
    assert "planning over the agent of" in capsys.readouterr().out
    (rec,) = read_records(rec_path)
    assert rec.planner == "policy-mpc" and rec.dynamics == "learned" and len(rec.returns) == 2
    assert rec.config["settings"]["horizon"] == 2 and rec.config["settings"]["samples"] == 8
    for extra, words in ((["--set", "temperature=-1"], "temperature"),
                         (["--warmup", "3"], "--warmup does not apply to planner 'policy-mpc'"),
                         (["--set", "horizon=3"], "--set horizon=3 and --horizon both set horizon"),
                         (["--set", "run=elsewhere"], "both set run: give --policy"),
                         (["--set", "colour=1"], "colour")):
        assert main(args[:-1] + extra) == 2
        assert words in capsys.readouterr().err
    assert main(["mpc", "--task", "swimmer6", "--planner", "policy-mpc", "--video", "none"]) == 2
    assert "give --policy RUN" in capsys.readouterr().err


def test_policy_mpc_never_plans_a_diverging_rollout(rl_run):
    """Sequences whose predicted return is NaN (a model that diverges there) are never elites."""
    from gnwarp.rl.agents import make_agent
    from gnwarp.rl.planner import PolicyMPC, PolicyMPCSettings
    from gnwarp.rl.settings import AgentSettings
    torch.manual_seed(0)
    nan_left = lambda x, a: torch.where(a < 0, torch.full_like(a, float("nan")), x + a)   # noqa: E731
    agent = make_agent(AgentSettings(agent="svg1", hidden=(8,)), 1, [-1.0], [1.0], model=nan_left,
                       reward=lambda x, a, x2: -((x2 - 0.5) ** 2).sum(-1), q=_NegSquare(0.0))
    s = PolicyMPCSettings(run=str(rl_run), device="cpu", horizon=2, samples=32, policy_samples=4, iterations=3,
                          elites=4, temperature=1.0)   # the agent given here, not the run's
    planner = PolicyMPC(agent, lambda body, t: body[:, 0, :1], 1, settings=s)
    a = planner.step(torch.zeros(1, 1, 13))
    assert torch.isfinite(planner.plan).all() and float(a) >= 0
