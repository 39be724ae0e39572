"""DMC tasks (gnwarp.control.dmc): each reward on graph states against the suite's own
``task.get_reward(physics)`` on the same MuJoCo C trajectories, the torch tolerance against
dm_control's, surrogates against the exact rewards, initial states and targets, ``gnwarp mpc``."""
import math

import mujoco
import numpy as np
import pytest
import torch

from gnwarp.control import dmc as cdmc
from gnwarp.control.tasks import TASKS, get_task, sample_targets
from gnwarp.sim import dmc, systems
from gnwarp.sim.body_state import body_states

pytest.importorskip("dm_control")
pytestmark = pytest.mark.filterwarnings("ignore:.*DISPLAY environment variable")
from dm_control.utils import rewards  # noqa: E402


# the suite's task object of each task
SUITE_TASKS = {
    "dmc-cheetah-run": lambda m: m.Cheetah(random=0),
    "dmc-walker-stand": lambda m: m.PlanarWalker(move_speed=0, random=0),
    "dmc-walker-walk": lambda m: m.PlanarWalker(move_speed=1, random=0),
    "dmc-walker-run": lambda m: m.PlanarWalker(move_speed=8, random=0),
    "dmc-hopper-stand": lambda m: m.Hopper(hopping=False, random=0),
    "dmc-hopper-hop": lambda m: m.Hopper(hopping=True, random=0),
    "dmc-swimmer-swimmer6": lambda m: m.Swimmer(random=0),
    "dmc-reacher-easy": lambda m: m.Reacher(target_size=0.05, random=0),
    "dmc-reacher-hard": lambda m: m.Reacher(target_size=0.015, random=0),
    "dmc-cartpole-balance": lambda m: m.Balance(swing_up=False, sparse=False, random=0),
    "dmc-cartpole-swingup": lambda m: m.Balance(swing_up=True, sparse=False, random=0),
    "dmc-pendulum-swingup": lambda m: m.SwingUp(random=0),
    "dmc-acrobot-swingup": lambda m: m.Balance(sparse=False, random=0),
}


def _near(name, system, n, rng):
    """Starts where the reward is neither constant nor trivial: upright and moving fast (speed
    thresholds), near upright (pendulum, acrobot), targets near the finger or nose."""
    m = system.model
    qpos = np.tile(m.qpos0, (n, 1))
    qvel = np.zeros((n, m.nv))
    domain = name.split("-")[1]
    if domain in ("cheetah", "walker", "hopper"):
        qpos[:, 3:] += rng.uniform(-0.1, 0.1, (n, m.nq - 3))
        qvel[:, 0] = np.linspace(0.5, {"cheetah": 14, "walker": 10, "hopper": 3}[domain], n)
    elif domain in ("pendulum", "acrobot"):
        qpos[:] = rng.uniform(-0.3, 0.3, qpos.shape)
    elif domain == "cartpole":
        qpos[:, 0] = rng.uniform(-1, 1, n)
        qvel[:] = rng.normal(0, 3, qvel.shape)
    else:
        qpos[:], qvel[:] = cdmc.randomize_joints(m, n, rng), 0
    return qpos, qvel


def _point(name, system, qpos):
    """World xy of the reacher's finger / the swimmer's nose at qpos."""
    m, d = system.model, mujoco.MjData(system.model)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    return d.geom_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "finger" if "reacher" in name else "nose"), :2]


@pytest.fixture(scope="module")
def trajectories(suite_physics):
    """Per task: body states [E, T+1, B, 13] and actions [E, T, U] of MuJoCo C trajectories in float64
    (from the task's initial states and from ``_near`` starts), targets [E, 3], and the suite's
    per-step rewards [E, T] from its own task code on its own Physics stepped alongside."""
    out = {}
    rng = np.random.default_rng(0)
    E, T = 4, 5
    for name, make_suite_task in SUITE_TASKS.items():
        task = get_task(name)
        system = systems.make(task.system)
        m, d = system.model, mujoco.MjData(system.model)
        module, physics = suite_physics(task.system)
        suite_task = make_suite_task(module)
        q0, v0 = task.initial(system, E // 2, rng)
        q1, v1 = _near(name, system, E - E // 2, rng)
        qpos, qvel = np.concatenate([q0, q1]), np.concatenate([v0, v1])
        target = sample_targets(task, system, E, seed=1)
        if target is not None:
            target = target.double().numpy()
            for k, r in zip(range(E // 2, E), (0.004, 0.05)):   # a target beside the finger / nose, then further
                a = rng.uniform(0, 2 * np.pi)
                target[k, :2] = _point(name, system, qpos[k]) + r * np.array([np.cos(a), np.sin(a)])
        states, actions, ref = [], [], []
        for k in range(E):
            with physics.reset_context():
                suite_task.initialize_episode(physics)   # the task's model edits (reacher's target size)
            if target is not None:
                physics.named.model.geom_pos["target", "x"] = target[k, 0]
                physics.named.model.geom_pos["target", "y"] = target[k, 1]
            physics.data.qpos[:], physics.data.qvel[:] = qpos[k], qvel[k]
            physics.forward()
            mujoco.mj_resetData(m, d)
            d.qpos[:], d.qvel[:] = qpos[k], qvel[k]
            mujoco.mj_forward(m, d)
            s, a, r = [body_states(m, d)], [], []
            for t in range(T):
                u = rng.uniform(-1, 1, m.nu)
                d.ctrl[:] = u
                mujoco.mj_step(m, d, system.substeps)
                mujoco.mj_forward(m, d)
                s.append(body_states(m, d))
                a.append(u)
                physics.set_control(u)
                physics.step(system.substeps)   # the suite's control step (legacy step, as its Environment)
                r.append(suite_task.get_reward(physics))
            np.testing.assert_allclose(physics.data.qpos, d.qpos, atol=1e-9, err_msg=name)  # same trajectory
            states.append(np.stack(s))
            actions.append(np.stack(a))
            ref.append(r)
        out[name] = (torch.tensor(np.stack(states)), torch.tensor(np.stack(actions)),
                     None if target is None else torch.tensor(target), np.asarray(ref, dtype=np.float64))
    return out


def _per_step(reward, states, actions, target):
    T = actions.shape[1]
    return torch.stack([reward(states[:, t:t + 2], actions[:, t:t + 1], target) for t in range(T)], 1)


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_reward_matches_the_suites_task_code(trajectories, name):
    states, actions, target, ref = trajectories[name]
    task = get_task(name)
    mine = _per_step(task.scorer, states, actions, target)
    assert mine.dtype == torch.float64 and mine.shape == ref.shape
    np.testing.assert_allclose(mine.numpy(), ref, rtol=1e-10, atol=1e-12, err_msg=name)
    # the summed reward is the sum of the per-step ones
    np.testing.assert_allclose(task.scorer(states, actions, target).numpy(), ref.sum(1), rtol=1e-10, atol=1e-10)
    assert np.all((ref >= 0) & (ref <= 1))


def test_the_trajectories_reach_the_interesting_regions(trajectories):
    """The comparison above is not a comparison of zeros: rewards strictly between 0 and 1 on the
    smooth tasks, and both values of every piecewise constant one."""
    for name, (*_, ref) in trajectories.items():
        if name in ("dmc-reacher-easy", "dmc-reacher-hard", "dmc-pendulum-swingup", "dmc-hopper-stand"):
            assert (ref == 0).any() and (ref > 0).any(), name
        else:
            assert ((ref > 1e-3) & (ref < 1 - 1e-6)).any(), name


@pytest.mark.parametrize("sigmoid", cdmc.SIGMOIDS)
def test_tolerance_matches_dm_control(sigmoid):
    x = np.concatenate([np.linspace(-6, 6, 1201), [-1e6, -2.0, 0.0, 0.1, 1.2, 2.0, 1e6]])
    values = (0.0, 0.1, 0.5) if sigmoid in ("cosine", "linear", "quadratic") else (0.1, 0.5, 0.9)
    for bounds in ((0.0, 0.0), (-1.0, 2.0), (1.2, math.inf), (-math.inf, 0.5), (0.0, 0.1)):
        for margin in (0.0, 0.3, 2.0):
            for v in values:
                with np.errstate(over="ignore"):   # dm_control's 1 / cosh overflows to 0 far out
                    want = rewards.tolerance(x, bounds=bounds, margin=margin, sigmoid=sigmoid, value_at_margin=v)
                xt = torch.tensor(x, requires_grad=True)
                got = cdmc.tolerance(xt, bounds=bounds, margin=margin, sigmoid=sigmoid, value_at_margin=v)
                np.testing.assert_allclose(got.detach().numpy(), want, rtol=1e-12, atol=1e-15,
                                           err_msg=f"{sigmoid} {bounds} {margin} {v}")
                if margin > 0:
                    got.sum().backward()
                    assert torch.isfinite(xt.grad).all(), (sigmoid, bounds, margin, v)
    with pytest.raises(ValueError, match="value_at_margin"):
        cdmc.tolerance(torch.zeros(2), margin=1, sigmoid=sigmoid, value_at_margin=1.0)


def test_tolerance_gradient_is_dm_controls_slope():
    """Finite differences of dm_control's tolerance beside torch autograd, outside the bounds."""
    x = np.array([1.35, 1.9, 3.0, -0.7])
    for sigmoid in cdmc.SIGMOIDS:
        kw = dict(bounds=(-0.5, 1.2), margin=0.8, sigmoid=sigmoid, value_at_margin=0.3)
        xt = torch.tensor(x, requires_grad=True)
        cdmc.tolerance(xt, **kw).sum().backward()
        h = 1e-6
        fd = (rewards.tolerance(x + h, **kw) - rewards.tolerance(x - h, **kw)) / (2 * h)
        np.testing.assert_allclose(xt.grad.numpy(), fd, rtol=1e-5, atol=1e-7, err_msg=sigmoid)


@pytest.mark.parametrize("name", sorted(cdmc.SURROGATES))
def test_surrogates_bound_the_exact_reward_and_carry_gradients(trajectories, name):
    """The surrogate equals the exact reward where that is positive (inside its bounds), is at
    least the exact one everywhere, and where the exact one is 0 and flat the surrogate's gradient
    is finite and not zero."""
    states, actions, target, ref = trajectories[name]
    task = get_task(name)
    assert task.score is not None and task.scorer is task.score and task.reward is not task.score
    exact = _per_step(task.score, states, actions, target)
    smooth = _per_step(task.reward, states, actions, target)
    assert (smooth >= exact - 1e-12).all() and (smooth <= 1).all()
    pos = exact > 0
    torch.testing.assert_close(smooth[pos], exact[pos])
    s = states.clone().requires_grad_(True)
    zero = ~pos.all(1)
    task.reward(s, actions, target)[zero].sum().backward()
    assert torch.isfinite(s.grad).all() and s.grad[zero].abs().sum() > 0


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_reward_gradients_are_finite(trajectories, name):
    states, actions, target, _ = trajectories[name]
    task = get_task(name)
    s = states.float().clone().requires_grad_(True)
    a = actions.float().clone().requires_grad_(True)
    tg = None if target is None else target.float()
    r = task.reward(s, a, tg)
    assert r.shape == (s.shape[0],) and torch.isfinite(r).all()
    r.sum().backward()
    assert torch.isfinite(s.grad).all() and (a.grad is None or torch.isfinite(a.grad).all())
    assert s.grad.abs().sum() > 0, name


def test_zero_distance_has_finite_gradients():
    """The reacher's finger and the swimmer's nose exactly on the target."""
    for name in ("dmc-reacher-easy", "dmc-swimmer-swimmer6"):
        task = get_task(name)
        system = systems.make(task.system)
        m, d = system.model, mujoco.MjData(system.model)
        mujoco.mj_forward(m, d)
        s = torch.tensor(np.stack([body_states(m, d)] * 2))[None].requires_grad_(True)
        target = torch.zeros(1, 3, dtype=torch.float64)
        target[0, :2] = torch.tensor(_point(name, system, m.qpos0))
        r = task.reward(s, torch.zeros(1, 1, m.nu, dtype=torch.float64), target)
        assert r.item() == 1.0
        r.backward()
        assert torch.isfinite(s.grad).all()


def test_registry_names_and_fields():
    dmc_names = sorted(n for n, t in TASKS.items() if t.suite == "dmc")
    assert dmc_names == sorted(SUITE_TASKS)
    for name in dmc_names:
        task = TASKS[name]
        assert task.episode_steps == 1000 and task.initial is not None and task.system in dmc.dmc_names()
        assert name.startswith(task.system.replace("swimmer6", "swimmer") + "-")
        assert (task.score is not None) == (name in cdmc.SURROGATES)
    assert get_task("cheetah-run") is TASKS["dmc-cheetah-run"]
    assert get_task("swimmer6") is TASKS["dmc-swimmer-swimmer6"]
    assert get_task("cartpole-balance").suite == "paper" and get_task("cartpole-balance").episode_steps is None
    assert get_task("pendulum-balance").scorer is get_task("pendulum-balance").reward
    with pytest.raises(ValueError, match="needs target="):
        get_task("reacher-easy").reward(torch.zeros(1, 2, 4, 13), torch.zeros(1, 1, 2))
    with pytest.raises(ValueError, match="dmc-hopper"):
        get_task("hopper-hop", "dmc-walker")


def test_initial_states_are_the_suites_distributions():
    rng = np.random.default_rng(0)
    n = 400
    s = {name: systems.make(name) for name in ("dmc-cartpole", "dmc-pendulum", "dmc-walker", "dmc-reacher")}
    q, v = get_task("cartpole-swingup").initial(s["dmc-cartpole"], n, rng)
    assert abs(np.mean(q[:, 1]) - np.pi) < 0.01 and np.std(q[:, 1]) < 0.02 and np.std(v) == pytest.approx(0.01, 0.2)
    q, v = get_task("dmc-cartpole-balance").initial(s["dmc-cartpole"], n, rng)
    assert np.abs(q[:, 0]).max() <= 0.1 and np.abs(q[:, 1]).max() <= 0.034 and np.abs(q[:, 1]).max() > 0.03
    q, v = get_task("pendulum-swingup").initial(s["dmc-pendulum"], n, rng)
    assert q.min() < -3 and q.max() > 3 and (v == 0).all()
    q, v = get_task("walker-walk").initial(s["dmc-walker"], n, rng)
    m = s["dmc-walker"].model
    assert (q[:, :2] == 0).all() and np.abs(q[:, 2]).max() > 3        # slides kept, the free hinge on the circle
    lo, hi = m.jnt_range[3:].T
    assert ((q[:, 3:] >= lo) & (q[:, 3:] <= hi)).all() and q.dtype == np.float64 and v.shape == (n, m.nv)
    targets = sample_targets(get_task("reacher-hard"), s["dmc-reacher"], n, seed=0).double().numpy()
    r = np.linalg.norm(targets[:, :2], axis=1)
    assert targets.shape == (n, 3) and r.min() >= 0.05 and r.max() <= 0.2 and np.allclose(targets[:, 2], 0.01)
    sw = sample_targets(get_task("dmc-swimmer-swimmer6"), None, n, seed=0).numpy()
    close = np.abs(sw[:, :2]).max(1) <= 0.3
    assert 0.1 < close.mean() < 0.35 and np.abs(sw[:, :2]).max() <= 2


def test_cheetah_settles_as_the_suites_reset(suite_physics):
    """The cheetah's initial state: the suite's own initialize_episode (random limited joints, 200
    physics steps inside its reset) from the same random draws."""
    module, physics = suite_physics("dmc-cheetah")
    system = systems.make("dmc-cheetah")
    m = system.model
    for seed in (0, 1):
        suite_task = module.Cheetah(random=seed)
        with physics.reset_context():
            suite_task.initialize_episode(physics)
        limited = m.jnt_limited == 1
        lo, hi = m.jnt_range[limited].T
        qpos = np.tile(m.qpos0, (1, 1))
        qpos[0, limited] = np.random.RandomState(seed).uniform(lo, hi)
        q, v = cdmc.settle(m, qpos, 200)
        np.testing.assert_allclose(q[0], physics.data.qpos, atol=1e-9)
        np.testing.assert_allclose(v[0], physics.data.qvel, atol=1e-9)
    q, v = get_task("cheetah-run").initial(system, 2, np.random.default_rng(0))
    assert np.abs(v).max() < 0.5 and q.shape == (2, 9)   # settled: nearly at rest on the ground


def test_run_episodes_scores_with_the_exact_reward():
    from gnwarp.control.episodes import run_episodes
    from gnwarp.control.sampling import RandomPlanner
    from gnwarp.sim import make_env
    task = get_task("pendulum-swingup")
    system = systems.make(task.system)
    env = make_env(system, 3, backend="mujoco")
    q, v = task.initial(system, 3, np.random.default_rng(0))
    q[0] = 0.0   # one episode starts upright: exact reward 1 while near it
    out = run_episodes(RandomPlanner(env.actuators, 3, seed=0), env, task, 4, qpos0=q, qvel0=v)
    torch.testing.assert_close(out["returns"], task.score(out["states"], out["actions"]))
    assert out["returns"][0] == 4 and set(out["returns"].tolist()) <= {0.0, 1.0, 2.0, 3.0, 4.0}


def test_cli_mpc_on_a_dmc_task(tmp_path, capsys, monkeypatch):
    """`gnwarp mpc --task pendulum-swingup` plans on the DMC pendulum from the task's initial states;
    without --steps an episode is the task's 1000 steps."""
    from gnwarp import data
    from gnwarp.cli import main
    from gnwarp.eval.records import read_records
    from gnwarp.gn import RunOptions
    from gnwarp.models import GNCoreConfig, ModelConfig
    from gnwarp.train import TrainConfig, train
    ds = data.generate("dmc-pendulum", (8, 2, 2), num_steps=6, seed=0, backend="mujoco", progress=False)
    cfg = TrainConfig(out=str(tmp_path / "run"), model=ModelConfig(
        gn=GNCoreConfig(latent=8, edge_hidden=(8,), node_hidden=(8,), global_hidden=(8,)), run=RunOptions(impl="torch")),
        steps=2, batch_size=4, valid_every=2, valid_sequences=2, checkpoint_every=2, normalizer_warmup=1,
        progress=False, device="cpu")
    model = train(cfg, [ds])["last"]
    records = tmp_path / "r.jsonl"
    argv = ["mpc", "--model", str(model), "--task", "pendulum-swingup", "--episodes", "2", "--horizon", "2",
            "--iterations", "1", "--warmup", "0", "--proposals", "2", "--backend", "mujoco", "--video", "none",
            "--records", str(records), "-q", "--seed", "3"]
    assert main(argv + ["--steps", "3"]) == 0
    (rec,) = read_records(records)
    assert (rec.task, rec.system, rec.episode_steps, rec.control_dt) == ("dmc-pendulum-swingup", "dmc-pendulum", 3, 0.02)
    task = get_task("pendulum-swingup")
    q, _ = task.initial(systems.make("dmc-pendulum"), 2, np.random.default_rng(3))
    np.testing.assert_allclose(rec.config["initial_qpos"], q)
    assert all(r in (0.0, 1.0, 2.0, 3.0) for r in rec.returns)   # scored with the exact (0 / 1 per step) reward
    import gnwarp.control
    seen = {}

    def fake_run(planner, env, task, steps, x0=None, **kw):
        seen["steps"] = steps
        raise SystemExit(0)
    monkeypatch.setattr(gnwarp.control, "run_episodes", fake_run)
    with pytest.raises(SystemExit):
        main(argv)
    assert seen["steps"] == 1000
