"""The seams control stands on: every planner implements ``Planner`` (step = optimize then act)
with validated settings and runs in ``run_episodes``; every learned model implements ``Dynamics``;
the true simulator and a learned model both implement ``RolloutDynamics``, so one sampling planner
runs on either."""
import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.control import (PLANNERS, GradientMPC, GradientMPCConfig, Planner, PlanningError, get_planner, planner_name,
                            run_episodes)
from gnwarp.sim.env import make_env
from gnwarp.control.hybrid import HybridPlanner
from gnwarp.control.ilqg import ILQG, ILQGSettings
from gnwarp.control.sampling import (EnvDynamics, ModelDynamics, RandomPlanner, RandomSettings, SamplingConfig,
                                     SamplingPlanner, model_dynamics, true_dynamics)
from gnwarp.dynamics import Dynamics, RolloutDynamics
from gnwarp.gn import RunOptions
from gnwarp.interop import warp
from gnwarp.models import ForwardModel, GNCoreConfig, MLPForwardModel, ModelConfig
from gnwarp.validation import ConfigError

warp()

N = 2
Q0, V0 = np.array([[0.3], [-0.4]]), np.array([[0.1], [0.0]])
TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (4, 1, 1), num_steps=6, seed=0, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def model(pendulum):
    torch.manual_seed(0)
    return ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch")), pendulum.layout)


def make(name: str, model, env):
    """The registered planner ``name`` on pendulum balance, small."""
    entry = get_planner(name)
    if name == "gradient":
        return GradientMPC(model, "pendulum-balance", "pendulum", N,
                           entry.make_settings(horizon=4, iterations=1, warmup=2))
    if name in ("sampling", "mppi"):
        return SamplingPlanner(true_dynamics("pendulum", N, 4, backend="mujoco"), "pendulum-balance", env.ctrlrange,
                               N, entry.make_settings(horizon=4, samples=4, knots=2))
    if name == "ilqg":
        return ILQG.for_task("pendulum", "pendulum-balance", N,
                             entry.make_settings(horizon=4, iterations=1, warmup=2, nthread=1))
    if name == "random":
        return RandomPlanner(env.ctrlrange, N, seed=entry.make_settings(seed=3).seed)
    if name == "hybrid":
        return HybridPlanner(model, "pendulum-balance", "pendulum", N,
                             entry.make_settings(horizon=4, samples=4, elites=2, iterations=1, warmup=1, knots=2))
    raise AssertionError(f"no test planner for {name}")


# the planners of gnwarp.control; "policy" and "policy-mpc" (a trained gnwarp rl agent, registered when
# gnwarp.rl.planner is imported, as another test module may have done) act with or plan over that agent:
# tests/test_rl_policy.py
AGENT_PLANNERS = {"policy", "policy-mpc"}
CONTROL_PLANNERS = [n for n in PLANNERS if n not in AGENT_PLANNERS]


def test_every_registered_planner_runs_in_run_episodes(model):
    env = make_env("pendulum", N, backend="mujoco")
    assert set(CONTROL_PLANNERS) == {"gradient", "sampling", "mppi", "ilqg", "random", "hybrid"}
    assert set(PLANNERS) - set(CONTROL_PLANNERS) <= AGENT_PLANNERS
    for name in CONTROL_PLANNERS:
        planner = make(name, model, env)
        assert isinstance(planner, Planner) and planner_name(planner) == name
        assert planner.needs_sim_state == (name in ("sampling", "mppi", "ilqg"))
        out = run_episodes(planner, env, "pendulum-balance", 3, qpos0=Q0, qvel0=V0)
        assert out["states"].shape == (N, 4, 2, 13) and out["actions"].shape == (N, 3, 1), name
        assert torch.isfinite(out["returns"]).all() and (out["actions"].abs() <= 1).all(), name
        # run_episodes resets the planner (the settings' seed again): the same episodes twice
        again = run_episodes(planner, env, "pendulum-balance", 3, qpos0=Q0, qvel0=V0)
        assert torch.equal(out["actions"], again["actions"]), name


def test_step_is_optimize_then_act(model):
    env = make_env("pendulum", N, backend="mujoco")
    for name in CONTROL_PLANNERS:
        a, b = make(name, model, env), make(name, model, env)
        env.reset(Q0, V0)
        for _ in range(3):
            state = env.observe() if a.needs_sim_state else env.body_states()
            u = a.step(state)
            b.optimize(state)
            assert torch.equal(u, b.act(state, 0)), name
            assert torch.equal(b.act(state, 0), b.act(state, 0)), name   # acting costs no planning
            env.step(u)
        with pytest.raises(PlanningError, match="optimize"):   # one error type for every planner
            b.reset(N)
            b.act(state, 0)
        b.optimize(state)
        for bad in (-1, 1.5, True):
            with pytest.raises(PlanningError, match="time must be an integer >= 0"):
                b.act(state, bad)


def test_planning_error_stays_importable_from_gradient():
    from gnwarp.control import gradient, returns
    assert gradient.PlanningError is returns.PlanningError is PlanningError


def test_act_reads_the_plan_at_a_later_time(model):
    env = make_env("pendulum", N, backend="mujoco")
    env.reset(Q0, V0)
    p = make("gradient", model, env)
    p.optimize(env.body_states())
    assert torch.equal(p.act(None, 1), p.plan[:, 1]) and torch.equal(p.act(None, 99), p.plan[:, -1])
    il = make("ilqg", model, env)
    il.optimize(env.observe())
    assert il.plan_U.shape == (N, 4, 1) and torch.equal(il.act(None, 2), torch.from_numpy(il.plan_U[:, 2]))
    with pytest.raises(ValueError, match="time"):
        il.act(None, -1)


def test_settings_refuse_bad_values_by_name():
    cases = [(GradientMPCConfig, dict(lr=-1.0), "lr"), (GradientMPCConfig, dict(iterations=0), "iterations"),
             (SamplingConfig, dict(samples=0), "samples"), (SamplingConfig, dict(noise=-0.1), "noise"),
             (SamplingConfig, dict(method="cem"), "method"), (SamplingConfig, dict(temperature=0.0), "temperature"),
             (SamplingConfig, dict(horizon=3, knots=4), "knots"),
             (ILQGSettings, dict(iterations=-1), "iterations"), (ILQGSettings, dict(reg_factor=1.0), "reg_factor"),
             (ILQGSettings, dict(reg_min=10.0, reg_max=1.0), "reg_min"), (ILQGSettings, dict(horizon=0), "horizon"),
             (ILQGSettings, dict(step_sizes=(1.0, -0.5)), "step_sizes"), (ILQGSettings, dict(fd_centered="yes"),
                                                                          "fd_centered"),
             (RandomSettings, dict(seed=-1), "seed")]
    for cls, kw, field in cases:
        with pytest.raises(ConfigError, match=f"^{field}"):
            cls(**kw)
    with pytest.raises(ConfigError, match="^seed"):
        RandomPlanner(np.array([[-1.0, 1.0]]), 1, seed=-2)
    with pytest.raises(ValueError, match="method=.mppi."):
        get_planner("mppi").make_settings(method="best")


def test_registry_and_run_episodes_refusals(model):
    with pytest.raises(ValueError, match="unknown planner 'cem'; registered: gradient, sampling"):
        get_planner("cem")
    with pytest.raises(ValueError, match="not a registered planner"):
        planner_name(object())
    env = make_env("pendulum", N, backend="mujoco")

    class StepOnly:     # a planner without reset / optimize / act is refused, naming what it lacks
        def step(self, x):
            return torch.zeros(N, 1)
    with pytest.raises(TypeError, match="lacks n, targets, device, needs_sim_state, reset, optimize, act"):
        run_episodes(StepOnly(), env, "pendulum-balance", 2, qpos0=Q0)
    # reset's episode count: gradient MPC's is its rollout engine's batch; random actions take any
    with pytest.raises(PlanningError, match="plans 2 episodes"):
        make("gradient", model, env).reset(3)
    r = make("random", model, env)
    r.reset(3)
    r.optimize(None)
    assert r.act(None).shape == (3, 1) and r.n == 3
    s = SamplingPlanner(true_dynamics("pendulum", N, 4, backend="mujoco"), "pendulum-balance", env.ctrlrange, N,
                        targets=torch.zeros(N, 3))
    with pytest.raises(ValueError, match="one entry per episode \\(3\\)"):
        s.reset(3)      # the targets held are for 2 episodes


@pytest.mark.parametrize("name", ["gradient", "sampling", "ilqg", "hybrid"])
def test_targets_are_checked_and_a_task_of_another_system_refused(name, model):
    """Targets with a NaN, or not one per episode, are refused by every planner that takes them
    (they would be planned for and scored silently); so is a position task's wrong width; and
    ``run_episodes`` refuses to score a task of another system than the env's."""
    env = make_env("pendulum", N, backend="mujoco")
    p = make(name, model, env)
    for bad, words in ((torch.full((N, 3), float("nan")), "finite"), (torch.zeros(N + 1, 3), "one entry per episode")):
        with pytest.raises(ValueError, match=words):
            p.reset(N, targets=bad)
    with pytest.raises(ValueError, match="task 'cheetah-forward' is for cheetah, but the env's system is pendulum"):
        run_episodes(p, env, "cheetah-forward", 2, qpos0=Q0, qvel0=V0)
    if name == "sampling":   # a position task takes [N, 2] or [N, 3]
        sw = make_env("swimmer3", N, backend="mujoco")
        s = SamplingPlanner(true_dynamics("swimmer3", N, 4, backend="mujoco", source=sw), "swimmer-reach",
                            sw.ctrlrange, N, SamplingConfig(horizon=3, samples=4, knots=2))
        with pytest.raises(ValueError, match=r"target positions \[2, 2\] or \[2, 3\], got shape \(2, 7\)"):
            s.reset(N, targets=torch.ones(N, 7))
        s.reset(N, targets=torch.ones(N, 2))
        assert s.targets.shape == (N, 2)


@pytest.mark.parametrize("name", ["gradient", "sampling", "hybrid"])
def test_states_without_values_or_orientation_are_refused(name, model):
    """A NaN in the state, or a body without orientation (a ~zero quaternion), is refused by
    every planner given body states, naming the episode and body (it used to be planned from)."""
    from gnwarp.control import PlanningError
    env = make_env("pendulum", N, backend="mujoco")
    p = make(name, model, env) if name != "sampling" else SamplingPlanner(
        true_dynamics("pendulum", N, 4, backend="mujoco", source=env), "pendulum-balance", env.ctrlrange, N,
        SamplingConfig(horizon=4, samples=4, knots=2))
    p.reset(N)
    x = torch.as_tensor(env.reset(Q0, V0)).float()
    bad = x.clone()
    bad[1, 1, 5] = float("nan")
    with pytest.raises(PlanningError, match="episode 1 has NaN or Inf \\(body 1, feature 5\\)"):
        p.step(bad)
    flat = x.clone()
    flat[0, 1, 3:7] = 0.0
    with pytest.raises(PlanningError, match="episode 0 has no orientation \\(body 1's quaternion"):
        p.step(flat)
    assert p.step(x).shape == (N, 1)


def test_learned_models_implement_dynamics(pendulum, model):
    mlp = MLPForwardModel(pendulum.layout, n_node=2, n_edge=2, size="3x128")
    for m in (model, mlp):
        assert isinstance(m, Dynamics)
    assert not isinstance(object(), Dynamics)
    # the engine asks the model for its input checks: the ranges of the bound source
    engine = model.bind(pendulum).rollout_engine([0, 0], 3)
    x0 = torch.as_tensor(np.asarray(pendulum["test"].body[:1, 0])).repeat(2, 1, 1)
    with torch.no_grad():
        big, edge = torch.full((2, 3, 1), 9.0), torch.full((2, 3, 1), 1.0)
        assert torch.equal(engine.rollout(x0, big), engine.rollout(x0, edge))


def test_one_sampling_planner_on_true_and_learned_dynamics(pendulum, model):
    """The oracle beside the learned model: the same planner and settings through either
    ``RolloutDynamics``; without noise both keep the nominal (the middle of the range)."""
    model.bind(pendulum)
    env = make_env("pendulum", N, backend="mujoco")
    true = true_dynamics("pendulum", N, 4, backend="mujoco")
    learned = model_dynamics(model, N, 4, horizon=5)
    plain = ModelDynamics(model.rollout)
    assert isinstance(true, EnvDynamics) and all(isinstance(d, RolloutDynamics) for d in (true, learned, plain))
    cfg = SamplingConfig(horizon=5, samples=4, knots=2, seed=1)
    outs = {}
    for name, dyn in (("true", true), ("learned", learned), ("plain", plain)):
        planner = SamplingPlanner(dyn, "pendulum-balance", env.ctrlrange, N, cfg)
        outs[name] = run_episodes(planner, env, "pendulum-balance", 3, qpos0=Q0, qvel0=V0)
        assert planner.last_rewards.shape == (N, 4) and torch.isfinite(planner.last_rewards).all()
    # the engine and the model's own rollout are one model: the same plans
    torch.testing.assert_close(outs["learned"]["actions"], outs["plain"]["actions"])
    still = SamplingConfig(horizon=5, samples=4, knots=2, noise=0.0)
    for dyn in (true, plain):
        p = SamplingPlanner(dyn, "pendulum-balance", env.ctrlrange, N, still)
        env.reset(Q0, V0)
        assert torch.equal(p.step(env.observe()), torch.zeros(N, 1))


def test_make_planner_builds_what_the_classes_build(pendulum, model):
    """``make_planner`` through a learned model gives the same episodes as the classes built by
    hand (gradient, hybrid, sampling on ``model_dynamics``), on the true dynamics too; settings
    are checked by name."""
    from gnwarp.control.planner import MODEL_PLANNERS, make_planner, planner_settings
    assert set(MODEL_PLANNERS) <= set(PLANNERS)
    model.bind(pendulum)
    env = make_env("pendulum", N, backend="mujoco")
    small = {"gradient": dict(horizon=4, iterations=1, warmup=2), "sampling": dict(horizon=4, samples=4, knots=2),
             "hybrid": dict(horizon=4, samples=4, elites=2, iterations=1, warmup=1, knots=2)}
    small["mppi"] = small["sampling"]
    by_hand = {
        "gradient": lambda s: GradientMPC(model, "pendulum-balance", "pendulum", N, s),
        "hybrid": lambda s: HybridPlanner(model, "pendulum-balance", "pendulum", N, s),
        "sampling": lambda s: SamplingPlanner(model_dynamics(model, N, 4, 4), "pendulum-balance", env.ctrlrange, N, s)}
    by_hand["mppi"] = by_hand["sampling"]
    for name in MODEL_PLANNERS:
        made = make_planner(name, model, "pendulum-balance", "pendulum", N, small[name])
        assert planner_name(made) == name and made.settings == planner_settings(name, small[name])
        ref = by_hand[name](get_planner(name).make_settings(**small[name]))
        a = run_episodes(made, env, "pendulum-balance", 2, qpos0=Q0, qvel0=V0)
        b = run_episodes(ref, env, "pendulum-balance", 2, qpos0=Q0, qvel0=V0)
        torch.testing.assert_close(a["actions"], b["actions"], msg=name)
    oracle = make_planner("sampling", true_dynamics("pendulum", N, 4, backend="mujoco"), "pendulum-balance",
                          "pendulum", N, small["sampling"])
    assert oracle.needs_sim_state and isinstance(oracle.dynamics, EnvDynamics)
    assert planner_name(make_planner("random", model, "pendulum-balance", "pendulum", N, {"seed": 2})) == "random"
    with pytest.raises(ConfigError, match="nope: is not a setting of planner 'hybrid'; HybridConfig has horizon, "
                                          "samples, elites"):
        planner_settings("hybrid", {"nope": 1})
    with pytest.raises(ValueError, match="registered with method='mppi'"):
        planner_settings("mppi", {"method": "best"})
    with pytest.raises(ValueError, match="unknown planner 'nope'; registered: gradient"):
        make_planner("nope", model, "pendulum-balance", "pendulum", N)
    with pytest.raises(PlanningError, match="'gradient' differentiates a learned Dynamics model; EnvDynamics"):
        make_planner("gradient", true_dynamics("pendulum", N, 4, backend="mujoco"), "pendulum-balance", "pendulum", N)
    with pytest.raises(ValueError, match="'ilqg' .* is not built through a dynamics model"):
        make_planner("ilqg", model, "pendulum-balance", "pendulum", N)


def test_every_planner_defaults_to_the_tasks_horizon():
    """Sampling, like gradient and hybrid, plans the task's horizon unless given one (cartpole
    balance: 100 steps), on a learned model too; an explicit horizon stays; a reward callable,
    which has no horizon, needs one."""
    from gnwarp.control.planner import make_planner
    from gnwarp.control.tasks import get_task
    cart = data.generate("cartpole", (2, 1, 1), num_steps=4, seed=0, backend="mujoco", progress=False)
    torch.manual_seed(0)
    net = ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch")), cart.layout)
    task = get_task("cartpole-balance")
    assert SamplingConfig().horizon is None
    for name, settings in (("sampling", {"samples": 2}), ("hybrid", {"samples": 2, "elites": 1}),
                           ("gradient", {})):
        p = make_planner(name, net, task.name, "cartpole", 1, settings)
        assert p.horizon == task.horizon == 100, name
    s = make_planner("mppi", net, task.name, "cartpole", 1, {"samples": 2, "horizon": 7})
    assert s.horizon == s.settings.horizon == 7
    env = make_env("cartpole", 1, backend="mujoco")
    with pytest.raises(ConfigError, match="horizon: None means the task's horizon"):
        SamplingPlanner(true_dynamics("cartpole", 1, 2, backend="mujoco"), lambda s, a: s.sum((1, 2, 3)),
                        env.ctrlrange, 1, SamplingConfig(samples=2))
    with pytest.raises(ConfigError, match="knots: must not exceed the horizon"):
        SamplingPlanner(true_dynamics("cartpole", 1, 2, backend="mujoco"), "cartpole-balance", env.ctrlrange, 1,
                        SamplingConfig(samples=2, knots=101))
