"""Control tasks as Gymnasium vector environments (``gnwarp.control.vector_env``): Gymnasium's
checks that apply to vector envs, seeding, truncation and each autoreset mode, rewards against
``run_episodes`` on the true simulator and states against ``model.rollout`` on a learned model."""
import warnings

import numpy as np
import pytest
import torch
from gymnasium import spaces
from gymnasium.utils.env_checker import (check_reset_options, check_reset_return_type, check_reset_seed_determinism,
                                         check_returned_data_not_reused, data_equivalence)
from gymnasium.utils.passive_env_checker import check_action_space, check_observation_space
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.wrappers.vector import RecordEpisodeStatistics

from gnwarp import data
from gnwarp.control import TASKS, get_task, run_episodes
from gnwarp.control.vector_env import VectorEnvError, make_vector_env
from gnwarp.gn import RunOptions
from gnwarp.interop import warp
from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig
from gnwarp.sim.env import make_env
from gnwarp.sim.systems import make

warp()
warnings.filterwarnings("ignore", message=".*glfw.*")

TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))


def pendulum_env(n=3, steps=4, **kw):
    kw.setdefault("backend", "mujoco")
    return make_vector_env("pendulum-balance", n, episode_steps=steps, seed=0, **kw)


class Replay:
    """A ``Planner`` that plays fixed actions [N, T, U], for ``run_episodes``."""
    needs_sim_state = False

    def __init__(self, actions):
        self.u, self.n, self.t, self.targets, self.device = actions, actions.shape[0], 0, None, torch.device("cpu")

    def reset(self, n, targets=None, seed=None):
        self.t, self.targets = 0, targets

    def optimize(self, state):
        pass

    def act(self, state, time=0):
        return self.u[:, self.t + time]

    def step(self, state):
        a = self.act(state)
        self.t += 1
        return a


def test_spaces_and_gymnasium_checks():
    env = pendulum_env()
    assert isinstance(env, VectorEnv) and env.num_envs == 3
    assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    check_action_space(env.single_action_space)
    check_observation_space(env.single_observation_space)
    assert env.single_action_space == spaces.Box(-1.0, 1.0, (1,), np.float32)
    np.testing.assert_array_equal(env.single_action_space.low, make("pendulum").actuators.sample_range()[:, 0])
    assert env.action_space.shape == (3, 1) and env.observation_space.shape == (3, env.obs_layout.size) == (3, 13)
    assert len(env.obs_names) == 13 and env.obs_names[0] == "pole.pos_x"
    # Gymnasium's single-env checks that hold for a vector env as they are
    check_reset_return_type(env)
    check_reset_seed_determinism(env)
    check_reset_options(env)
    one = pendulum_env(1)
    check_returned_data_not_reused(one)
    obs, infos = env.reset(seed=3)
    assert obs.dtype == np.float32 and obs in env.observation_space and infos == {}
    obs, r, term, trunc, infos = env.step(env.action_space.sample())
    assert obs in env.observation_space and obs.shape == (3, 13)
    assert r.dtype == np.float32 and r.shape == (3,) and term.dtype == trunc.dtype == np.bool_
    assert not term.any() and not trunc.any() and infos == {}
    # the same actions from the same seed: the same transition
    env.action_space.seed(0)
    a = env.action_space.sample()
    outs = []
    for _ in range(2):
        env.reset(seed=7)
        outs.append(env.step(a))
    assert all(data_equivalence(x, y, exact=True) for x, y in zip(outs[0], outs[1]))
    env.close()
    env.close()   # closing twice is allowed


def test_seeding_is_per_env():
    a, b = pendulum_env(3), pendulum_env(2)
    oa, _ = a.reset(seed=5)
    ob, _ = b.reset(seed=6)                        # env i of b is seeded 6 + i: env i + 1 of a
    np.testing.assert_array_equal(oa[1:], ob)
    again, _ = a.reset(seed=5)
    np.testing.assert_array_equal(oa, again)
    other, _ = a.reset(seed=[9, 6, 7])
    np.testing.assert_array_equal(other[1:], ob)
    assert not np.allclose(other[0], oa[0])
    nxt, _ = a.reset()                              # unseeded: each generator continues
    assert not np.allclose(nxt, oa)
    with pytest.raises(VectorEnvError, match="one per env"):
        a.reset(seed=[1, 2])
    # one shared generator: every env's initial state from one call of the task's initial states
    shared = pendulum_env(3, per_env_seeds=False)
    o1, _ = shared.reset(seed=5)
    q, v = data.initial_states(make("pendulum"), 3, np.random.default_rng(5))
    np.testing.assert_allclose(shared.observe().qpos.numpy(), q)
    np.testing.assert_allclose(shared.observe().qvel.numpy(), v)
    o2, _ = shared.reset()
    assert not np.allclose(o1, o2)
    np.testing.assert_array_equal(shared.reset(seed=5)[0], o1)
    with pytest.raises(VectorEnvError, match="per_env_seeds"):
        shared.reset(seed=[1, 2, 3])


def test_truncation_and_next_step_autoreset():
    env, ref = pendulum_env(2, steps=3), pendulum_env(2, steps=3)
    env.reset(seed=1)
    ref.reset(seed=1)
    second, _ = ref.reset()                         # the next episode's first observations
    ones = np.ones((2, 1), np.float32)
    for t in range(3):
        obs, r, term, trunc, _ = env.step(ones)
        assert not term.any() and trunc.all() == (t == 2) and (r != 0).all()
        assert (env.elapsed == t + 1).all()
    # the step after the truncation resets: action ignored (even NaN), reward 0, no flag
    obs, r, term, trunc, _ = env.step(np.full((2, 1), np.nan))
    np.testing.assert_array_equal(obs, second)
    assert (r == 0).all() and not term.any() and not trunc.any() and (env.elapsed == 0).all()
    obs, r, term, trunc, _ = env.step(ones)
    assert (env.elapsed == 1).all() and (r != 0).all()
    # Gymnasium's episode statistics read the declared mode: the returns are the rewards' sums
    stats = RecordEpisodeStatistics(pendulum_env(2, steps=3))
    stats.reset(seed=1)
    rs = [stats.step(ones) for _ in range(3)]
    ep = rs[-1][4]["episode"]
    np.testing.assert_allclose(ep["r"], sum(x[1] for x in rs), rtol=1e-6)
    assert (ep["l"] == 3).all()


def test_same_step_and_disabled_autoreset():
    nxt = pendulum_env(2, steps=3)
    same = pendulum_env(2, steps=3, autoreset_mode="same_step")
    assert same.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    for e in (nxt, same):
        e.reset(seed=2)
    u = np.array([[0.5], [-0.5]], np.float32)
    for t in range(3):
        a, b = nxt.step(u), same.step(u)
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_array_equal(a[3], b[3])
    # the truncating step: the new episode's first observation, the last one in infos
    first_next, *_ = nxt.step(u)
    np.testing.assert_array_equal(b[0], first_next)
    np.testing.assert_array_equal(b[4]["final_obs"], a[0])
    assert b[4]["_final_obs"].all() and b[4]["final_body_states"].shape == (2, 2, 13)
    assert (same.elapsed == 0).all()
    assert same.step(u)[1].all()                   # every step after it is a real transition

    off = pendulum_env(2, steps=2, autoreset_mode="disabled")
    off.reset(seed=0)
    off.step(u)
    assert off.step(u)[3].all()
    with pytest.raises(VectorEnvError, match="autoreset is disabled"):
        off.step(u)
    kept = off.body_states[1]
    off.reset(options={"reset_mask": np.array([True, False])})
    torch.testing.assert_close(off.body_states[1], kept)   # only env 0 started again
    with pytest.raises(VectorEnvError, match="autoreset is disabled"):
        off.step(u)
    off.reset(options={"reset_mask": np.array([False, True])})
    off.step(u)
    np.testing.assert_array_equal(off.elapsed, [1, 1])


@pytest.mark.parametrize("task,system", [("cartpole-balance", "cartpole"), ("swimmer-reach", "swimmer3")])
def test_true_rewards_match_run_episodes(task, system):
    """The vector env's per-step rewards are the task's reward of ``run_episodes``'s trajectory
    for the same actions (out-of-range ones included, clamped the same way)."""
    n, T = 2, 6
    env = make_vector_env(task, n, episode_steps=T, system=system, backend="mujoco", seed=4)
    env.reset(seed=4)
    s = make(system)
    rng = np.random.default_rng(0)
    q0 = np.asarray(s.model.qpos0) + rng.uniform(-0.2, 0.2, (n, s.nq))
    v0 = rng.normal(0, 0.1, (n, s.nv))
    obs, _ = env.reset(options={"qpos": q0, "qvel": v0})
    targets = env.targets
    u = torch.tensor(rng.uniform(-2, 2, (n, T, s.nu)), dtype=torch.float32)   # half outside [-1, 1]
    rewards, states, applied = [], [env.body_states], []
    for t in range(T):
        obs, r, term, trunc, _ = env.step(u[:, t].numpy())
        rewards.append(r)
        states.append(env.body_states)
        applied.append(env.last_actions)
    assert trunc.all() and not term.any()
    out = run_episodes(Replay(u), make_env(s, n, backend="mujoco"), get_task(task), T, qpos0=q0, qvel0=v0,
                       target=targets)
    torch.testing.assert_close(torch.stack(states, 1), out["states"], rtol=0, atol=0)
    torch.testing.assert_close(torch.stack(applied, 1), out["actions"])
    assert out["actions"].abs().max() <= 1.0
    scorer = get_task(task).reward
    per_step = torch.stack([scorer(out["states"][:, t:t + 2], out["actions"][:, t:t + 1], targets)
                            for t in range(T)], 1)
    np.testing.assert_allclose(np.stack(rewards, 1), per_step.numpy(), rtol=1e-6, atol=1e-7)
    if task == "cartpole-balance":   # a reward of each step alone adds up to the episode's
        np.testing.assert_allclose(np.stack(rewards, 1).sum(1), out["returns"].numpy(), rtol=1e-5)
    else:                            # the target relative to the head closes the observation
        head = out["states"][:, -1, 1, :3]
        np.testing.assert_allclose(obs[:, -3:], (targets - head).numpy(), atol=1e-6)


@pytest.fixture(scope="module")
def pendulum_model():
    ds = data.generate("pendulum", (4, 1, 1), num_steps=6, seed=0, backend="mujoco", progress=False)
    torch.manual_seed(0)
    return ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch")), ds.layout)


def test_learned_env_matches_model_rollout(pendulum_model):
    n, T = 3, 5
    learned = make_vector_env("pendulum-balance", n, dynamics=pendulum_model, episode_steps=T, seed=0)
    true = pendulum_env(n, steps=T)
    assert learned.dynamics == "learned" and true.dynamics == "true"
    assert learned.observation_space == true.observation_space and learned.action_space == true.action_space
    o_l, _ = learned.reset(seed=11)
    o_t, _ = true.reset(seed=11)
    np.testing.assert_allclose(o_l, o_t, atol=1e-6)      # the same initial states, the same layout
    x0 = learned.body_states
    u = torch.tensor(np.random.default_rng(1).uniform(-1.5, 1.5, (n, T, 1)), dtype=torch.float32)
    rewards, states = [], [x0]
    for t in range(T):
        obs, r, _, trunc, _ = learned.step(u[:, t])
        rewards.append(r)
        states.append(learned.body_states)
    assert trunc.all()
    with torch.no_grad():
        ref = pendulum_model.rollout(x0, u)              # clamps as MuJoCo does, like the env
    torch.testing.assert_close(torch.stack(states, 1).to(ref.dtype), ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(obs, learned.obs_layout(ref[:, -1]).numpy(), atol=1e-6)
    task = get_task("pendulum-balance")
    np.testing.assert_allclose(np.stack(rewards, 1).sum(1), task.reward(ref.float(), u.clamp(-1, 1)).numpy(),
                               rtol=1e-5)
    # output="torch": tensors on the model's device
    tl = make_vector_env("pendulum-balance", n, dynamics=pendulum_model, episode_steps=T, seed=0, output="torch")
    obs, _ = tl.reset(seed=11)
    obs, r, term, trunc, _ = tl.step(u[:, 0])
    assert isinstance(obs, torch.Tensor) and obs.dtype == torch.float32 and trunc.dtype == torch.bool
    assert obs.device == pendulum_model.device


def test_translation_invariant_observation_and_bad_inputs():
    env = make_vector_env("cheetah-forward", 2, episode_steps=3, backend="mujoco", seed=0)
    assert env.obs_layout.size == 13 * 7 - 2 and "torso.rel_pos_x" not in env.obs_names
    q0 = np.tile(make("cheetah").model.qpos0, (2, 1))
    shifted = q0.copy()
    shifted[:, 0] += 5.0                                  # rootx: the whole cheetah moved along x
    v0 = np.random.default_rng(0).normal(0, 0.1, (2, 9))
    a, _ = env.reset(options={"qpos": q0, "qvel": v0})
    x = env.body_states[:, 1:, 0]
    b, _ = env.reset(options={"qpos": shifted, "qvel": v0})
    torch.testing.assert_close(env.body_states[:, 1:, 0] - x, torch.full_like(x, 5.0))
    np.testing.assert_allclose(a, b, atol=1e-5)
    with pytest.raises(VectorEnvError, match="env 1 hold NaN"):
        env.step(np.array([[0.0] * 6, [0.0, np.nan, 0, 0, 0, 0]]))
    with pytest.raises(VectorEnvError, match=r"actions must be \[num_envs=2, U=6\]"):
        env.step(np.zeros((2, 5)))
    with pytest.raises(VectorEnvError, match="episode_steps"):
        make_vector_env("cheetah-forward", 2, backend="mujoco")
    with pytest.raises(VectorEnvError, match="autoreset_mode"):
        make_vector_env("cheetah-forward", 2, episode_steps=3, backend="mujoco", autoreset_mode="sometimes")
    with pytest.raises(VectorEnvError, match="dynamics"):
        make_vector_env("cheetah-forward", 2, episode_steps=3, dynamics="learned")
    with pytest.raises(VectorEnvError, match="reset options"):
        env.reset(options={"qpos0": q0})
    with pytest.raises(RuntimeError, match="reset"):
        pendulum_env(2).step(np.zeros((2, 1)))


def test_mujoco_warp_cpu_backend_runs():
    warp_env = make_vector_env("cartpole-balance", 2, episode_steps=3, backend="mujoco_warp_cpu", seed=0)
    c_env = make_vector_env("cartpole-balance", 2, episode_steps=3, backend="mujoco", seed=0)
    assert warp_env.backend == "mujoco_warp_cpu"
    u = np.array([[0.3], [-0.7]], np.float32)
    for e in (warp_env, c_env):
        e.reset(seed=0)
    for _ in range(3):
        ow, rw, _, tw, _ = warp_env.step(u)
        oc, rc, _, tc, _ = c_env.step(u)
        np.testing.assert_allclose(ow, oc, atol=1e-3)
        np.testing.assert_allclose(rw, rc, atol=1e-3)
    assert tw.all() and tc.all()


def test_action_repeat(pendulum_model):
    """An env step of ``action_repeat=2`` is two control steps under its action, its reward their
    sum; the time limit counts control steps."""
    for dyn in ("true", pendulum_model):
        one = make_vector_env("pendulum-balance", 2, dynamics=dyn, backend="mujoco", episode_steps=4, seed=0)
        two = make_vector_env("pendulum-balance", 2, dynamics=dyn, backend="mujoco", episode_steps=4, seed=0,
                              action_repeat=2)
        assert two.dt == 2 * one.dt
        one.reset(seed=3)
        two.reset(seed=3)
        u = np.array([[0.4], [-0.9]], np.float32)
        for t in range(2):
            r1 = one.step(u)[1] + one.step(u)[1]
            o2, r2, _, trunc, _ = two.step(u)
            np.testing.assert_allclose(o2, one.obs_layout(one.body_states).numpy(), atol=1e-6)
            np.testing.assert_allclose(r2, r1, rtol=1e-5)
            assert trunc.all() == (t == 1) and (two.elapsed == 2 * (t + 1)).all()
        assert two.control_steps == one.control_steps == 8
    with pytest.raises(VectorEnvError, match="multiple of action_repeat"):
        make_vector_env("pendulum-balance", 2, backend="mujoco", episode_steps=5, action_repeat=2)


def test_custom_observation_and_sim_state(pendulum_model):
    def angle_and_speed(body, target):
        return torch.stack([body[:, 1, 3], body[:, 1, 10]], 1)   # quat w and angvel x of the pole
    env = pendulum_env(2, observation=angle_and_speed)
    assert env.single_observation_space.shape == (2,) and env.obs_names == ["obs0", "obs1"]
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs, angle_and_speed(env.body_states, None).numpy())
    state = env.observe()
    assert state.qpos.shape == (2, 1) and state.qvel.shape == (2, 1)
    torch.testing.assert_close(state.body, env.body_states)
    learned = make_vector_env("pendulum-balance", 2, dynamics=pendulum_model, episode_steps=3)
    learned.reset(seed=0)
    with pytest.raises(RuntimeError, match="body states only"):
        learned.observe()
    with pytest.raises(VectorEnvError, match="bind it to acrobot"):   # bound to the pendulum: 2 bodies, not 3
        make_vector_env("acrobot-swingup", 2, dynamics=pendulum_model, episode_steps=3)


@pytest.mark.skipif("dmc-cheetah-run" not in TASKS, reason="the DeepMind Control tasks are not in this checkout")
@pytest.mark.parametrize("name", ["cheetah-run", "swimmer-swimmer6"])
def test_dmc_tasks_take_their_episode_steps_scorer_and_targets(name):
    pytest.importorskip("dm_control")
    task = get_task(name)
    env = make_vector_env(name, 2, backend="mujoco", seed=0)
    assert env.episode_steps == task.episode_steps == 1000 and env.system.name == task.system
    env = make_vector_env(name, 2, backend="mujoco", seed=0, episode_steps=4)
    env.reset(seed=0)
    start = env.observe()
    u = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (2, 4, env.nu)), dtype=torch.float32)
    rewards = [env.step(u[:, t].numpy())[1] for t in range(4)]
    out = run_episodes(Replay(u), make_env(env.system, 2, backend="mujoco"), task, 4, qpos0=start.qpos,
                       qvel0=start.qvel, target=env.targets)
    np.testing.assert_allclose(np.stack(rewards, 1).sum(1), out["returns"].numpy(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dynamics", ["true", "learned"])
def test_single_env_passes_gymnasium_check_env(dynamics, pendulum_model):
    from gymnasium.utils.env_checker import check_env

    from gnwarp.control.gym_env import make_control_env
    env = make_control_env("pendulum-balance", dynamics="true" if dynamics == "true" else pendulum_model,
                           backend="mujoco", episode_steps=3, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # every check passes without a warning...
        warnings.filterwarnings("ignore", message=".*(spec|infinity).*")   # ...but those of a Box(-inf, inf)
        check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=1, options={"qpos": [0.3], "qvel": [0.0]})
    assert obs.shape == (13,) and info == {}
    quat_w = obs[env.vector.obs_names.index("pole.quat_w")]
    assert np.isclose(quat_w, np.cos(0.15), atol=1e-6)   # the pole at the given angle (0.3 rad)
    for t in range(3):
        obs, r, term, trunc, info = env.step(np.array([0.5]))
        assert isinstance(r, float) and term is False and trunc == (t == 2)
    with pytest.raises(VectorEnvError, match="autoreset is disabled"):
        env.step(np.array([0.5]))


def test_deferred_action_checks_name_the_env_and_step():
    """Device actions with ``defer_action_checks`` (on by itself for output="torch" on CUDA,
    forced here on the CPU): a NaN row steps with zero actions, is flagged on the device, and the
    flag read every ``action_check_every`` steps (or at the episode's end, or reset) raises naming
    the env and the step; host actions are still checked at once."""
    env = pendulum_env(3, steps=8, output="torch", action_check_every=3)
    assert env.defer_action_checks is False            # CPU: every check at once, as before
    env.reset(seed=0)
    with pytest.raises(VectorEnvError, match="env 1 hold NaN"):
        env.step(torch.tensor([[0.1], [np.nan], [0.2]]))
    env.defer_action_checks = True
    ref = pendulum_env(3, steps=8, output="torch")
    env.reset(seed=0)
    ref.reset(seed=0)
    good = torch.tensor([[0.1], [0.3], [0.2]])
    env.step(good)
    ref.step(good)
    env.step(torch.tensor([[0.1], [np.inf], [0.2]]))   # env step 1: no sync, no error yet
    ref.step(torch.tensor([[0.1], [0.0], [0.2]]))
    torch.testing.assert_close(env.body_states, ref.body_states)   # the bad row stepped with zero actions
    with pytest.raises(VectorEnvError, match=r"env 1 held NaN or Inf at env step 1 .*every 3 steps"):
        env.step(good)                                   # env step 2: the third, the flag is read
    env.step(torch.tensor([[np.nan], [0.0], [0.0]]))
    with pytest.raises(VectorEnvError, match="env 0 held NaN or Inf at env step 3"):
        env.reset()                                      # a reset reads it too
    with pytest.raises(VectorEnvError, match="env 0 hold NaN"):
        env.step(np.array([[np.nan], [0.0], [0.0]]))     # host actions: at once
    with pytest.raises(ValueError, match="action_check_every must be an integer >= 1"):
        pendulum_env(2, action_check_every=0)


class Exploding(torch.nn.Module):
    """A Dynamics wrapper whose rollouts turn NaN in env 1 from the second step on."""

    def __init__(self, model):
        super().__init__()
        self.model, self.steps = model, 0

    def __getattr__(self, name):
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self.model, name)

    def rollout_engine(self, *args, **kw):
        engine, outer = self.model.rollout_engine(*args, **kw), self

        class Engine:
            template = engine.template

            def rollout(self, x, u):
                traj = engine.rollout(x, u)
                outer.steps += 1
                if outer.steps >= 2:
                    traj = traj.clone()
                    traj[1, -1, 1, 0] = float("nan")
                return traj
        return Engine()


@pytest.mark.parametrize("output", ["numpy", "torch"])
def test_a_diverged_learned_env_is_reported(pendulum_model, output):
    env = make_vector_env("pendulum-balance", 3, dynamics=Exploding(pendulum_model), episode_steps=6, seed=0,
                          output=output)
    env.reset(seed=0)
    u = np.zeros((3, 1), np.float32) if output == "numpy" else torch.zeros(3, 1)
    _, _, _, _, infos = env.step(u)
    assert not infos["diverged"].any() and infos["_diverged"].all()
    obs, r, _, _, infos = env.step(u)
    flags = np.asarray(infos["diverged"].cpu() if output == "torch" else infos["diverged"])
    assert flags.tolist() == [False, True, False] and not np.isfinite(np.asarray(obs[1])).all()
    env.sim.engine = pendulum_model.rollout_engine(torch.zeros(3, dtype=torch.int64), 1, ctrl_policy="none",
                                                   check=False)
    _, _, _, _, infos = env.step(u)                      # stays diverged until reset
    assert np.asarray(infos["diverged"].cpu() if output == "torch" else infos["diverged"]).tolist()[1]
    env.reset(options={"reset_mask": np.array([False, True, False])})
    _, _, _, _, infos = env.step(u)
    assert not np.asarray(infos["diverged"].cpu() if output == "torch" else infos["diverged"]).any()
    true = pendulum_env(3)
    true.reset(seed=0)
    assert true.step(np.zeros((3, 1)))[4] == {}          # the true simulator reports no such key


def test_reset_refuses_targets_with_a_nan_or_the_wrong_width():
    """options['targets'] with a NaN would give NaN observations and rewards; a width the task
    does not read would plan and score silently: both are refused, naming what is wrong."""
    env = make_vector_env("swimmer-reach", 2, dynamics="true", backend="mujoco", episode_steps=5, system="swimmer3")
    with pytest.raises(VectorEnvError, match="finite"):
        env.reset(seed=0, options={"targets": np.full((2, 3), np.nan)})
    with pytest.raises(VectorEnvError, match=r"target positions \[2, 2\] or \[2, 3\]"):
        env.reset(seed=0, options={"targets": np.ones((2, 7))})
    obs, _ = env.reset(seed=0, options={"targets": np.ones((2, 3))})
    assert np.isfinite(np.asarray(obs)).all()


@pytest.mark.parametrize("seed", [1.5, -1, "ab", [0, -3], [0, 1, 2]])
def test_reset_refuses_seeds_numpy_would_not_take(seed):
    """A seed that is not an integer >= 0 (or a list of one per env) is one VectorEnvError
    naming it, not numpy's or Python's own error."""
    env = make_vector_env("pendulum-balance", 2, dynamics="true", backend="mujoco", episode_steps=5)
    with pytest.raises(VectorEnvError, match="seed"):
        env.reset(seed=seed)
    env.reset(seed=[0, 1])
