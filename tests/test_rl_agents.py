"""The RL agents' core: each policy-gradient estimator against finite differences of a
closed-form linear-quadratic objective, bootstrapping at truncation and not at termination, the
replay buffer's checks, sampling and state, exact resume, settings errors, and short runs on a
vector environment."""
import copy
import io
import types
import warnings

import numpy as np
import pytest
import torch
from torch import nn

from gnwarp.rl.agents import DDPG, SVG, make_agent, restore_generator
from gnwarp.rl.loop import CollectorState, run_env_steps
from gnwarp.rl.planner import PolicyPlanner
from gnwarp.rl.replay import ReplayBuffer, ReplayError, Transitions
from gnwarp.rl.settings import AgentSettings
from gnwarp.validation import ConfigError

D, U, B = 3, 2, 5
RNG = np.random.default_rng(0)
A_MAT = 0.9 * np.eye(D) + 0.1 * RNG.standard_normal((D, D))   # the linear model x' = A x + Bm a
B_MAT = RNG.standard_normal((D, U))
P_R = np.diag([1.0, 0.5, 2.0])                                 # reward -x'P x' - a R a + c.x
R_R = np.diag([0.3, 0.7])
C_R = RNG.standard_normal(D)
M = RNG.standard_normal((D + U, D + U))
Q_M = M @ M.T / (D + U) + np.eye(D + U)                        # Q = -z Q_M z + q.z, z = [x, a]
Q_V = RNG.standard_normal(D + U)
GAMMA = 0.9


class LinearPolicy(nn.Module):
    """mean = K x + k; log_std a free vector (state-independent)."""

    def __init__(self, gaussian: bool):
        super().__init__()
        self.K = nn.Parameter(torch.tensor(0.3 * RNG.standard_normal((U, D))))
        self.k = nn.Parameter(torch.tensor(0.2 * RNG.standard_normal(U)))
        self.log_std = nn.Parameter(torch.tensor(np.log([0.4, 0.8])))
        self.gaussian = gaussian

    def forward(self, x):
        mean = x @ self.K.T + self.k
        return (mean, self.log_std.expand_as(mean)) if self.gaussian else mean


class QuadraticQ(nn.Module):
    def forward(self, x, a):
        z = torch.cat([x, a], -1)
        return -((z @ torch.tensor(Q_M)) * z).sum(-1) + z @ torch.tensor(Q_V)


def linear_model(x, a):
    return x @ torch.tensor(A_MAT).T + a @ torch.tensor(B_MAT).T


def quadratic_reward(x, a, x2):
    return -((x2 @ torch.tensor(P_R)) * x2).sum(-1) - ((a @ torch.tensor(R_R)) * a).sum(-1) + x @ torch.tensor(C_R)


def reference_objective(params, obs, noise, horizon, gaussian, squash, xi=None):
    """mean_B of sum_{k<N} gamma^k r_k + gamma^N Q(x_N, a_N) in NumPy float64; ``xi`` [B, D]:
    added to the first predicted state (the replayed transition's residual, model_noise "inferred")."""
    K, k, log_std = params
    low, high = np.array([-1.0, -2.0]), np.array([1.5, 1.0])

    def action(x, eps):
        u = x @ K.T + k + (np.exp(log_std) * eps if gaussian else 0.0)
        return (high + low) / 2 + (high - low) / 2 * np.tanh(u) if squash == "tanh" else u

    x, total = obs, 0.0
    for j in range(horizon):
        a = action(x, noise[j])
        x2 = x @ A_MAT.T + a @ B_MAT.T + (xi if j == 0 and xi is not None else 0.0)
        r = -np.einsum("bi,ij,bj->b", x2, P_R, x2) - np.einsum("bi,ij,bj->b", a, R_R, a) + x @ C_R
        total = total + GAMMA ** j * r
        x = x2
    z = np.concatenate([x, action(x, noise[horizon])], -1)
    return np.mean(total + GAMMA ** horizon * (-np.einsum("bi,ij,bj->b", z, Q_M, z) + z @ Q_V))


@pytest.mark.parametrize("squash", ["none", "tanh"])
@pytest.mark.parametrize("agent", ["ddpg", "svg0", "svg1", "svg2"])
def test_policy_gradient_matches_finite_differences(agent, squash):
    s = AgentSettings(agent=agent, gamma=GAMMA, hidden=(4,), squash=squash)
    gaussian = s.kind == "svg"
    policy = LinearPolicy(gaussian)
    kw = dict(model=linear_model, reward=quadratic_reward) if s.horizon else {}
    ag = make_agent(s, D, [-1.0, -2.0], [1.5, 1.0], policy=policy, q=QuadraticQ(), dtype=torch.float64, **kw)
    obs = torch.tensor(RNG.standard_normal((B, D)))
    noise = torch.tensor(RNG.standard_normal((s.horizon + 1, B, U)))
    loss = ag.policy_loss(obs, noise)
    params = [ag.policy.K, ag.policy.k, ag.policy.log_std]
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    values = [p.detach().numpy().copy() for p in params]
    ref = lambda v: reference_objective(v, obs.numpy(), noise.numpy(), s.horizon, gaussian, squash)  # noqa: E731
    assert np.isclose(-loss.item(), ref(values), rtol=1e-12, atol=1e-12)
    h = 1e-6
    for i, g in enumerate(grads):
        fd = np.zeros_like(values[i])
        for idx in np.ndindex(values[i].shape):
            up = [v.copy() for v in values]
            dn = [v.copy() for v in values]
            up[i][idx] += h
            dn[i][idx] -= h
            fd[idx] = (ref(up) - ref(dn)) / (2 * h)
        got = np.zeros_like(fd) if g is None else -g.numpy()
        assert np.abs(fd).max() > 1e-3 or i == 2    # the gradient is not trivially zero
        np.testing.assert_allclose(got, fd, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("agent", ["svg1", "svg2"])
def test_inferred_model_noise_gradient_matches_finite_differences(agent):
    """model_noise "inferred": the first predicted state is the replayed next state moved by the
    model's change from the replayed action to the policy's; values and gradients against NumPy."""
    s = AgentSettings(agent=agent, gamma=GAMMA, hidden=(4,), squash="tanh", model_noise="inferred")
    ag = make_agent(s, D, [-1.0, -2.0], [1.5, 1.0], policy=LinearPolicy(True), q=QuadraticQ(), model=linear_model,
                    reward=quadratic_reward, dtype=torch.float64)
    obs = torch.tensor(RNG.standard_normal((B, D)))
    noise = torch.tensor(RNG.standard_normal((s.horizon + 1, B, U)))
    a_rep, x_rep = torch.tensor(RNG.uniform(-1, 1, (B, U))), torch.tensor(RNG.standard_normal((B, D)))
    xi = x_rep.numpy() - (obs.numpy() @ A_MAT.T + a_rep.numpy() @ B_MAT.T)     # the model's residual there
    assert np.abs(xi).max() > 0.1
    loss = ag.policy_loss(obs, noise, (a_rep, x_rep))
    params = [ag.policy.K, ag.policy.k, ag.policy.log_std]
    grads = torch.autograd.grad(loss, params)
    values = [p.detach().numpy().copy() for p in params]
    ref = lambda v: reference_objective(v, obs.numpy(), noise.numpy(), s.horizon, True, "tanh", xi)  # noqa: E731
    assert np.isclose(-loss.item(), ref(values), rtol=1e-12, atol=1e-12)
    assert not np.isclose(ref(values), reference_objective(values, obs.numpy(), noise.numpy(), s.horizon, True, "tanh"))
    h = 1e-6
    for i, g in enumerate(grads):
        fd = np.zeros_like(values[i])
        for idx in np.ndindex(values[i].shape):
            up, dn = [v.copy() for v in values], [v.copy() for v in values]
            up[i][idx] += h
            dn[i][idx] -= h
            fd[idx] = (ref(up) - ref(dn)) / (2 * h)
        np.testing.assert_allclose(-g.numpy(), fd, rtol=1e-6, atol=1e-7)
    with pytest.raises(ConfigError, match="model_noise"):
        AgentSettings(agent="svg0", model_noise="inferred")


def _batch(n=4, d=D, u=U, dtype=torch.float64, **over):
    g = torch.Generator().manual_seed(1)
    b = dict(obs=torch.randn(n, d, generator=g, dtype=dtype), action=torch.rand(n, u, generator=g, dtype=dtype) - 0.5,
             reward=torch.randn(n, generator=g, dtype=dtype), next_obs=torch.randn(n, d, generator=g, dtype=dtype),
             terminated=torch.zeros(n, dtype=torch.bool), truncated=torch.zeros(n, dtype=torch.bool))
    b.update(over)
    return Transitions(**b)


@pytest.mark.parametrize("agent", ["ddpg", "svg0"])
def test_truncation_bootstraps_and_termination_does_not(agent):
    s = AgentSettings(agent=agent, gamma=0.8, hidden=(8,), seed=3)
    ag = make_agent(s, D, [-1.0] * U, [1.0] * U, dtype=torch.float64)
    batch = _batch(terminated=torch.tensor([False, True, False, True]),
                   truncated=torch.tensor([True, False, False, True]))
    state = ag.generator.get_state()
    y = ag.q_target_values(batch)
    ag.generator.set_state(state)                     # the same target-policy noise for SVG
    q2 = ag.q_target(batch.next_obs, ag.target_action(batch.next_obs))
    assert (q2.abs() > 1e-4).all()
    expected = batch.reward + 0.8 * q2 * torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(y, expected, rtol=1e-12, atol=1e-12)


def test_targets_hard_copy_and_polyak():
    batch = _batch()
    hard = DDPG(AgentSettings(preset="paper", target_period=3, hidden=(8,)), D, [-1] * U, [1] * U, dtype=torch.float64)
    before = copy.deepcopy(hard.q_target.state_dict())
    hard.update(batch)
    hard.update(batch)
    assert all(torch.equal(before[k], v) for k, v in hard.q_target.state_dict().items())
    hard.update(batch)
    assert all(torch.equal(hard.q.state_dict()[k], v) for k, v in hard.q_target.state_dict().items())
    soft = DDPG(AgentSettings(polyak=0.9, hidden=(8,)), D, [-1] * U, [1] * U, dtype=torch.float64)
    t0 = [p.clone() for p in soft.q_target.parameters()]
    soft.update(batch)
    for p, t, t_old in zip(soft.q.parameters(), soft.q_target.parameters(), t0):
        torch.testing.assert_close(t, 0.9 * t_old + 0.1 * p, rtol=1e-12, atol=1e-12)


# -- replay buffer ---------------------------------------------------------------------------------
def _add_step(buf, t, done_every=0, E=None):
    E = E or buf.num_envs
    ids = torch.tensor([[t * 10 + e] for e in range(E)], dtype=torch.float32)
    obs = ids.expand(E, buf.obs_dim)
    ends = torch.tensor([done_every > 0 and (t + e) % done_every == done_every - 1 for e in range(E)])
    buf.add(obs, ids.expand(E, buf.action_dim), ids[:, 0], obs + 10, ends & (torch.arange(E) % 2 == 0),
            ends & (torch.arange(E) % 2 == 1))


def test_replay_checks_inputs():
    buf = ReplayBuffer(12, obs_dim=3, action_dim=2, num_envs=2)
    good = dict(obs=np.zeros((2, 3)), action=np.zeros((2, 2)), reward=np.zeros(2), next_obs=np.zeros((2, 3)),
                terminated=np.zeros(2, bool), truncated=np.zeros(2, bool))
    with pytest.raises(ReplayError, match="empty"):
        buf.sample(4)
    for key, bad, msg in (("obs", np.zeros((3, 3)), "shape"), ("action", np.zeros((2, 3)), "shape"),
                          ("terminated", np.zeros(2), "boolean"), ("obs", np.zeros((2, 3), bool), "real numbers"),
                          ("reward", np.array([0.0, np.nan]), r"NaN or Inf values \(envs \[1\]\)")):
        with pytest.raises(ReplayError, match=msg):
            buf.add(**{**good, key: bad})
    assert len(buf) == 0
    buf.add(**good)
    assert len(buf) == 2 and buf.reward.dtype == torch.float32
    for call, msg in ((lambda: buf.sample(0), "batch"), (lambda: buf.sample_sequences(2, 2), "2 stored steps"),
                      (lambda: buf.sample_sequences(2, 0), "length")):
        with pytest.raises(ReplayError, match=msg):
            call()
    for kw, msg in ((dict(capacity=1, num_envs=2), "less than one step"), (dict(capacity=0), "capacity"),
                    (dict(capacity=4, dtype=torch.int32), "dtype")):
        with pytest.raises(ReplayError, match=msg):
            ReplayBuffer(**{"obs_dim": 3, "action_dim": 2, **kw})


def test_replay_ring_keeps_the_newest_and_samples_uniformly():
    buf = ReplayBuffer(9, obs_dim=1, action_dim=1, num_envs=2)     # 4 steps of 2 envs
    assert buf.capacity == 8
    for t in range(7):
        _add_step(buf, t)
    assert len(buf) == 8 and buf.added == 7
    g = torch.Generator().manual_seed(0)
    ids = buf.sample(4000, g).reward.long()
    assert set(ids.tolist()) == {t * 10 + e for t in range(3, 7) for e in range(2)}
    counts = torch.bincount(ids)[ids.unique()]
    assert counts.min() > 400 and counts.max() < 600


def test_sequences_never_cross_an_episode_end():
    buf = ReplayBuffer(3 * 11, obs_dim=2, action_dim=1, num_envs=3)
    for t in range(17):                                            # wraps the 11-step rings
        _add_step(buf, t, done_every=4)
    g = torch.Generator().manual_seed(0)
    seq = buf.sample_sequences(3000, 3, g)
    assert seq.obs.shape == (3000, 3, 2)
    t, e = seq.reward.long() // 10, seq.reward.long() % 10
    assert (t[:, 1:] == t[:, :-1] + 1).all() and (e == e[:, :1]).all()   # consecutive steps of one env
    assert torch.equal(seq.next_obs[:, :-1], seq.obs[:, 1:])
    ends = seq.terminated | seq.truncated
    assert not ends[:, :-1].any() and ends[:, -1].any()            # only the last step may end the episode
    valid = {(tt, ee) for tt in range(6, 15) for ee in range(3)
             if not any((tt + k + ee) % 4 == 3 for k in range(2))}
    assert {(int(a), int(b)) for a, b in zip(t[:, 0], e[:, 0])} == valid
    never = ReplayBuffer(8, obs_dim=2, action_dim=1, num_envs=2)
    for t in range(4):
        _add_step(never, t, done_every=1)
    with pytest.raises(ReplayError, match="within one episode"):
        never.sample_sequences(2, 2)


def test_replay_state_round_trip():
    buf = ReplayBuffer(10, obs_dim=2, action_dim=1, num_envs=2)
    for t in range(7):
        _add_step(buf, t, done_every=3)
    saved = io.BytesIO()
    torch.save(buf.state_dict(), saved)
    other = ReplayBuffer(10, obs_dim=2, action_dim=1, num_envs=2)
    saved.seek(0)
    other.load_state_dict(torch.load(saved))
    for b in (buf, other):
        _add_step(b, 7, done_every=3)
    a, c = (b.sample_sequences(16, 2, torch.Generator().manual_seed(5)) for b in (buf, other))
    assert all(torch.equal(getattr(a, k), getattr(c, k)) for k in ("obs", "action", "reward", "terminated"))
    with pytest.raises(ReplayError, match="num_envs"):
        ReplayBuffer(10, obs_dim=2, action_dim=1, num_envs=1).load_state_dict(buf.state_dict())


def test_replay_state_holds_the_filled_rows_only():
    """A checkpoint grows with the data, not with the capacity; it resumes as the whole ring did."""
    buf = ReplayBuffer(40, obs_dim=2, action_dim=1, num_envs=2)   # 20 rows
    for t in range(7):
        _add_step(buf, t, done_every=3)
    state = buf.state_dict()
    assert state["obs"].shape[0] == buf.filled == 7 < buf.rows
    assert state["obs"].untyped_storage().nbytes() == 7 * 2 * 2 * 4            # a copy, not a view of the ring
    saved = io.BytesIO()
    torch.save(state, saved)
    saved.seek(0)
    other = ReplayBuffer(40, obs_dim=2, action_dim=1, num_envs=2)
    other.obs.fill_(5.0)                                                      # stale contents are cleared
    other.load_state_dict(torch.load(saved))
    assert torch.equal(other.obs, buf.obs) and (other.ptr, other.filled) == (buf.ptr, buf.filled)
    for t in range(7, 30):
        for b in (buf, other):
            _add_step(b, t, done_every=3)
    assert buf.state_dict()["obs"].shape[0] == buf.rows                       # full: the ring as it is
    a, c = (b.sample(16, torch.Generator().manual_seed(2)) for b in (buf, other))
    assert torch.equal(a.obs, c.obs) and torch.equal(a.reward, c.reward)
    with pytest.raises(ReplayError, match=r"obs has shape \(5, 2, 2\); expected \(7, 2, 2\)"):
        other.load_state_dict(dict(state, obs=state["obs"][:5]))
    for bad in (dict(filled=21), dict(ptr=3), dict(added=9)):
        with pytest.raises(ReplayError, match="counters are inconsistent"):
            other.load_state_dict({**state, **bad})


# -- resume, settings ------------------------------------------------------------------------------
class TinyModel(nn.Module):
    def __init__(self, seed):
        super().__init__()
        torch.manual_seed(seed)
        self.lin = nn.Linear(D + U, D)

    def forward(self, x, a):
        return x + self.lin(torch.cat([x, a], -1))


@pytest.mark.parametrize("agent,preset", [("ddpg", "paper"), ("ddpg", "spinningup"), ("svg1", "spinningup")])
def test_resume_continues_bit_for_bit(agent, preset):
    s = dict(agent=agent, preset=preset, hidden=(8, 8), target_period=2, start_steps=4, seed=7)
    reward = lambda x, a, x2: -(x2 ** 2).sum(-1)    # noqa: E731
    kw = lambda seed: dict(model=TinyModel(seed), reward=reward) if agent != "ddpg" else {}  # noqa: E731
    ag = make_agent(AgentSettings(**s), D, [-1] * U, [1] * U, **kw(0))
    batches = [_batch(8, dtype=torch.float32) for _ in range(5)]
    obs = torch.randn(2, D)
    for b in batches[:3]:
        ag.act(obs)
        ag.update(b)
    saved = io.BytesIO()
    torch.save(ag.state_dict(), saved)
    later = [(ag.act(obs), ag.update(b)) for b in batches[3:]]
    fresh = make_agent(AgentSettings(**{**s, "seed": 7}), D, [-1] * U, [1] * U, **kw(1))
    saved.seek(0)
    fresh.load_state_dict(torch.load(saved))   # loads as weights only
    again = [(fresh.act(obs), fresh.update(b)) for b in batches[3:]]
    for (a1, m1), (a2, m2) in zip(later, again):
        assert torch.equal(a1, a2) and all(torch.equal(m1[k], m2[k]) for k in m1)
    s1, s2 = ag.state_dict(), fresh.state_dict()
    for key in ("policy", "q", "policy_target", "q_target") + (("model",) if agent != "ddpg" else ()):
        assert all(torch.equal(s1[key][k], s2[key][k]) for k in s1[key])
    assert (ag.updates, ag.env_steps) == (fresh.updates, fresh.env_steps) == (5, 10)
    with pytest.raises(ConfigError, match="other settings"):
        make_agent(AgentSettings(**{**s, "seed": 8}), D, [-1] * U, [1] * U, **kw(1)).load_state_dict(ag.state_dict())


def test_a_state_saved_on_cuda_loads_on_the_cpu():
    """A GPU-trained agent (CUDA generator state, fused and capturable Adam) acts and trains on the CPU."""
    s = AgentSettings(agent="svg1", hidden=(8,), start_steps=0, seed=3)
    reward = lambda x, a, x2: -(x2 ** 2).sum(-1)    # noqa: E731
    ag = make_agent(s, D, [-1] * U, [1] * U, model=TinyModel(0), reward=reward)
    ag.update(_batch(8, dtype=torch.float32))
    state = ag.state_dict()
    state["generator"] = torch.zeros(16, dtype=torch.uint8)          # what a CUDA generator saves
    for key in ("policy_opt", "q_opt", "model_opt"):
        for g in state[key]["param_groups"]:
            g.update(fused=True, capturable=True)
    cpu = make_agent(s, D, [-1] * U, [1] * U, model=TinyModel(1), reward=reward)
    before = cpu.generator.get_state()
    cpu.load_state_dict(state)
    assert torch.equal(cpu.generator.get_state(), before)             # kept its seed
    assert not restore_generator(torch.Generator(), state["generator"])
    assert restore_generator(torch.Generator(), before)
    obs = torch.randn(3, D)
    assert torch.equal(cpu.act(obs, deterministic=True), ag.act(obs, deterministic=True))
    assert all(not g["fused"] and not g["capturable"] for o in cpu.optimizers() for g in o.param_groups)
    m = cpu.update(_batch(8, dtype=torch.float32))                   # trains on the CPU
    assert all(torch.isfinite(v) for v in m.values())


def test_bad_settings_are_refused():
    for kw, msg in ((dict(agent="ppo"), "unknown agent 'ppo'"), (dict(agent="svg-1"), "N from 1"),
                    (dict(agent="svg99"), "N from 1"), (dict(batch_size=0), "batch_size"),
                    (dict(preset="fast"), "preset"), (dict(gamma=1.5), "gamma"), (dict(agent=3), "agent")):
        with pytest.raises(ConfigError, match=msg):
            AgentSettings(**kw)
    assert AgentSettings(agent="SVG(3)").agent == "svg3" and AgentSettings(agent="svg3").horizon == 3
    assert AgentSettings(preset="paper").target_update == "hard"
    sp = AgentSettings()
    assert (sp.target_update, sp.hidden, sp.batch_size, sp.start_steps, sp.polyak) == ("polyak", (256, 256), 100,
                                                                                       10_000, 0.995)
    with pytest.raises(ConfigError, match="needs a differentiable model and reward"):
        make_agent(AgentSettings(agent="svg1"), D, [-1] * U, [1] * U)
    with pytest.raises(ConfigError, match="needs a differentiable reward"):
        SVG(AgentSettings(agent="svg2"), D, [-1] * U, [1] * U, model=linear_model)
    with pytest.raises(ConfigError, match="DDPG got settings"):
        DDPG(AgentSettings(agent="svg0"), D, [-1] * U, [1] * U)
    with pytest.raises(ConfigError, match="high > low"):
        make_agent(AgentSettings(), D, [1, -1], [1, 1])


# -- a short run on a vector environment ---------------------------------------------------------
@pytest.mark.parametrize("agent", ["ddpg", "svg1"])
def test_short_run_on_a_vector_env(agent):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from gnwarp.control import make_vector_env
        env = make_vector_env("pendulum-balance", 4, episode_steps=20, backend="mujoco", autoreset_mode="same_step")
    obs_dim, act = env.single_observation_space.shape[0], env.single_action_space
    s = AgentSettings(agent=agent, hidden=(32, 32), batch_size=32, start_steps=40, update_after=40, seed=0,
                      updates_per_step=0.25)
    model = TinyModel(0) if agent == "svg1" else None
    if model is not None:
        model.lin = nn.Linear(obs_dim + act.shape[0], obs_dim)
    reward = lambda x, a, x2: -(x2[:, :3] ** 2).sum(-1) - 0.01 * (a ** 2).sum(-1)  # noqa: E731
    ag = make_agent(s, obs_dim, act.low, act.high, model=model, reward=reward)
    buf = ReplayBuffer(10_000, obs_dim, act.shape[0], num_envs=4)
    gen = torch.Generator().manual_seed(0)
    state = CollectorState(env.reset(seed=0)[0], 4)
    first = run_env_steps(ag, env, buf, state, 40, gen)             # 160 env steps
    out = run_env_steps(ag, env, buf, state, 35, gen, model_sequence=2 if agent == "svg1" else None)
    assert len(first["returns"]) == 8 and len(out["returns"]) == 4 and np.isfinite(first["returns"]).all()
    assert first["updates"] + out["updates"] == 66 and all(np.isfinite(v) for v in out["metrics"].values())
    m = out["metrics"]
    from gnwarp.control import Planner
    planner = PolicyPlanner(ag, env.obs_layout, 4, env.targets)
    assert isinstance(planner, Planner) and not planner.needs_sim_state
    got = planner.step(env.body_states)
    assert torch.equal(got, ag.act(state.obs, deterministic=True)) and got.abs().max() > 0
    with pytest.raises(ValueError, match="N=4"):
        planner.act(env.body_states[:2])
    env.close()
    T = buf.filled      # next_obs is the step's own; a truncated one is not the next episode's first
    ends, same = buf.truncated[:T - 1], (buf.next_obs[:T - 1] == buf.obs[1:T]).all(-1)
    assert same[~ends].all() and not same[ends].any()
    assert ag.updates == 66 and int(buf.truncated.sum()) == 12 and not buf.terminated.any()
    assert all(torch.isfinite(p).all() for p in ag.policy.parameters())
    assert ag.act(state.obs, deterministic=True).abs().max() <= 2.0 + 1e-6
    if agent == "svg1":
        assert "model_loss" in m
    back = CollectorState.from_state_dict(state.state_dict())
    assert np.array_equal(back.obs, state.obs) and np.array_equal(back.episode_return, state.episode_return)
    from gymnasium.vector import AutoresetMode
    with pytest.raises(ValueError, match="same_step"):
        run_env_steps(ag, types.SimpleNamespace(metadata={"autoreset_mode": AutoresetMode.NEXT_STEP}), buf, state, 1,
                      gen)


def _pendulum_loop(ahead: bool, output: str = "numpy"):
    """A DDPG agent, its buffer and generator, and the collector state of a 4-env pendulum
    (observations as NumPy arrays or torch tensors)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from gnwarp.control import make_vector_env
        env = make_vector_env("pendulum-balance", 4, episode_steps=20, backend="mujoco", autoreset_mode="same_step",
                              output=output)
    obs_dim, act = env.single_observation_space.shape[0], env.single_action_space
    s = AgentSettings(agent="ddpg", hidden=(16, 16), batch_size=16, start_steps=24, update_after=40, seed=0,
                      updates_per_step=0.5, act_ahead=ahead)
    torch.manual_seed(0)   # the networks' initial weights
    ag = make_agent(s, obs_dim, act.low, act.high)
    buf = ReplayBuffer(1000, obs_dim, act.shape[0], num_envs=4)
    return env, ag, buf, torch.Generator().manual_seed(0), CollectorState(env.reset(seed=0)[0], 4)


@pytest.mark.parametrize("ahead,output", [(False, "numpy"), (True, "numpy"), (True, "torch")])
def test_loop_equals_its_order_written_out(ahead, output):
    """run_env_steps (two calls) against the same order written out step by step: act (ahead: the
    next action picked before the previous step's updates, none carried between calls), step,
    store, update; the same buffer, parameters and counts bit for bit."""
    from gnwarp.rl.graphed import Updater
    from gnwarp.rl.replay import reached_obs
    env, ag, buf, gen, state = _pendulum_loop(ahead, output)
    run_env_steps(ag, env, buf, state, 12, gen)
    run_env_steps(ag, env, buf, state, 13, gen)
    env2, ag2, buf2, gen2, state2 = _pendulum_loop(ahead, output)
    up, obs, owed = Updater(ag2, buf2, gen2, capture=False), state2.obs, 0.0
    for call in (12, 13):
        picked = None
        for i in range(call):
            a = ag2.act(obs) if picked is None else picked
            if picked is not None:
                ag2.count_env_steps(4)
            nxt, r, term, trunc, info = env2.step(a.numpy() if output == "numpy" else a)
            buf2.add(obs, a, r, reached_obs(nxt, info), term, trunc)
            obs = nxt
            picked = ag2.act(obs, count=False) if ahead and i + 1 < call else None
            if ag2.env_steps >= 40:
                owed += 0.5 * 4
                up.run(int(owed))
                owed -= int(owed)
    env.close()
    env2.close()
    assert ag.env_steps == ag2.env_steps == 100 and ag.updates == ag2.updates == 32
    for name in ("obs", "action", "reward", "next_obs"):
        assert torch.equal(getattr(buf, name), getattr(buf2, name)), name
    for p, q in zip(ag.policy.parameters(), ag2.policy.parameters()):
        assert torch.equal(p, q)


def test_acting_ahead_keeps_the_schedule_and_changes_only_what_follows_updates():
    """Acting ahead takes the same env steps and updates; its transitions equal the in-turn
    loop's until the first update (the policy has not changed yet); the action after it differs
    (picked before the update, by the policy the in-turn loop no longer has)."""
    runs = []
    for ahead in (False, True):
        env, ag, buf, gen, state = _pendulum_loop(ahead)
        out = run_env_steps(ag, env, buf, state, 25, gen)
        env.close()
        runs.append((ag, buf, out))
    (a, b, x), (a2, b2, x2) = runs
    assert a.env_steps == a2.env_steps == 100 and x["updates"] == x2["updates"] == a.updates == a2.updates == 32
    first = 40 // 4    # rows (vector steps) before the first update (it follows row first - 1)
    assert torch.equal(b.obs[:first + 1], b2.obs[:first + 1]) and torch.equal(b.action[:first], b2.action[:first])
    assert not torch.equal(b.action[first], b2.action[first])   # ahead: picked before the first update


def test_state_saved_before_a_settings_key_existed_loads():
    """An agent saved before ``act_ahead`` existed (its settings lack the key) loads where the key
    holds its default, and is refused where it does not or where a saved key is unknown."""
    s = AgentSettings(agent="ddpg", hidden=(8,), batch_size=4, seed=0)
    torch.manual_seed(0)
    ag = make_agent(s, 3, [-1.0], [1.0])
    state = ag.state_dict()
    old = dict(state, settings={k: v for k, v in state["settings"].items() if k != "act_ahead"})
    torch.manual_seed(1)
    back = make_agent(s, 3, [-1.0], [1.0])
    back.load_state_dict(old)
    assert all(torch.equal(p, q) for p, q in zip(ag.policy.parameters(), back.policy.parameters()))
    ahead = make_agent(AgentSettings(agent="ddpg", hidden=(8,), batch_size=4, seed=0, act_ahead=True), 3,
                       [-1.0], [1.0])
    with pytest.raises(ConfigError, match=r"other settings \(\['act_ahead'\]\)"):
        ahead.load_state_dict(old)
    with pytest.raises(ConfigError, match="does not know"):
        back.load_state_dict(dict(state, settings={**state["settings"], "warp_speed": 9}))


def test_model_trains_jointly_on_its_own_batch():
    seen = []

    def seq_loss(model, batch):          # a two-step loss on sequences [B, 2]
        seen.append(tuple(batch.obs.shape))
        x1 = model(batch.obs[:, 0], batch.action[:, 0])
        x2 = model(x1, batch.action[:, 1])
        return (x1 - batch.next_obs[:, 0]).pow(2).mean() + (x2 - batch.next_obs[:, 1]).pow(2).mean()

    model = TinyModel(0)
    s = AgentSettings(agent="svg1", hidden=(8,), max_grad_norm=1.0, model_lr=0.02)
    ag = SVG(s, D, [-1] * U, [1] * U, model=model, reward=lambda x, a, x2: -(x2 ** 2).sum(-1),
             model_loss=seq_loss)
    buf = ReplayBuffer(40, D, U, num_envs=2)
    g = torch.Generator().manual_seed(0)
    for _ in range(10):
        x, a = torch.randn(2, D, generator=g), torch.rand(2, U, generator=g) - 0.5
        buf.add(x, a, torch.zeros(2), x + 0.1 * a.sum(-1, keepdim=True), torch.zeros(2, dtype=torch.bool),
                torch.zeros(2, dtype=torch.bool))
    before = copy.deepcopy(model.state_dict())
    losses = [ag.update(buf.sample(16, g), buf.sample_sequences(16, 2, g))["model_loss"] for _ in range(30)]
    assert seen[0] == (16, 2, D) and losses[-1] < 0.5 * losses[0]
    assert not torch.equal(before["lin.weight"], model.lin.weight)
    q_only = DDPG(AgentSettings(hidden=(8,)), D, [-1] * U, [1] * U)
    assert "model_loss" not in q_only.update(buf.sample(8, g))


def test_sequence_starts_follow_adds():
    buf = ReplayBuffer(8, obs_dim=1, action_dim=1, num_envs=1)
    for t in range(3):
        _add_step(buf, t, done_every=2)          # step 1 ends an episode: only step 0 starts a pair
    g = torch.Generator().manual_seed(0)
    assert set(buf.sample_sequences(50, 2, g).reward[:, 0].tolist()) == {0.0}
    _add_step(buf, 3, done_every=2)              # adds the start at step 2
    assert set(buf.sample_sequences(50, 2, g).reward[:, 0].tolist()) == {0.0, 20.0}


@pytest.mark.parametrize("agent", ["ddpg", "svg0"])
def test_saturated_counts_deterministic_actions_at_the_bounds(agent):
    ag = make_agent(AgentSettings(agent=agent, hidden=(8,), seed=1), D, [-1.0] * U, [1.0] * U, dtype=torch.float64)
    obs = torch.randn(16, D, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert ag.saturated(obs) < 0.5   # a fresh policy's outputs are small
    last = [m for m in ag.policy.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.bias[:U] = 50.0   # the outputs (the mean, for SVG) far past tanh's knee
    assert ag.saturated(obs) == 1.0
    with torch.no_grad():
        last.bias[:U] = torch.tensor([50.0] + [0.0] * (U - 1))
        last.weight.zero_()
    assert ag.saturated(obs) == pytest.approx(1 / U)


class FlatQ(nn.Module):
    """A Q-function with no slope in the action (and one parameter, for its optimizer)."""

    def __init__(self):
        super().__init__()
        self.c = nn.Parameter(torch.zeros((), dtype=torch.float64))

    def forward(self, x, a):
        return self.c + 0 * a.sum(-1)


@pytest.mark.parametrize("penalty", [0.0, 1e-2])
def test_squash_penalty_pulls_the_unbounded_output_back_from_tanhs_flat_ends(penalty):
    s = AgentSettings(agent="ddpg", hidden=(8,), seed=2, squash_penalty=penalty)
    ag = make_agent(s, D, [-1.0] * U, [1.0] * U, q=FlatQ(), dtype=torch.float64)
    last = [m for m in ag.policy.modules() if isinstance(m, nn.Linear)][-1]
    with torch.no_grad():
        last.bias[:] = 4.0   # deep in tanh's flat end
    batch = _batch()
    before = ag.policy_output(batch.obs).abs().mean().item()
    for _ in range(20):
        ag.update(batch)
    after = ag.policy_output(batch.obs).abs().mean().item()
    if penalty == 0:
        assert after == pytest.approx(before, abs=1e-9)   # a flat Q gives the policy no gradient at all
    else:
        assert after < before - 0.01


def test_default_model_loss_weighs_each_entry_by_its_change_spread():
    from gnwarp.rl.agents import mse_model_loss
    from gnwarp.rl.networks import ObservationModel
    torch.manual_seed(0)
    model = ObservationModel(2, 1, (8,))
    obs, act = torch.randn(64, 2), torch.randn(64, 1)
    nxt = obs + torch.stack([0.01 * torch.randn(64), 10.0 * torch.randn(64)], -1)
    batch = Transitions(obs, act, torch.zeros(64), nxt, torch.zeros(64, dtype=torch.bool),
                        torch.zeros(64, dtype=torch.bool))
    raw = (model(obs, act) - nxt).pow(2).mean()
    assert torch.equal(mse_model_loss(model, batch), raw)          # delta_std 1 before normalize_from
    model.normalize_from(obs, nxt)
    err = (model(obs, act) - nxt) / model.delta_std
    assert torch.allclose(mse_model_loss(model, batch), err.pow(2).mean())
    assert mse_model_loss(model, batch) < 0.1 * (model(obs, act) - nxt).pow(2).mean()   # not the raw loss
    assert mse_model_loss(lambda o, a: o, batch) == (obs - nxt).pow(2).mean()   # no delta_std: raw units


def test_a_batch_no_machine_holds_is_refused_as_a_setting():
    """batch_size is capped as TrainConfig's is: 10**12 transitions an update is a mistake (it
    failed at the first sample, asking the allocator for terabytes)."""
    from gnwarp.rl.settings import AgentSettings
    with pytest.raises(ConfigError, match="batch_size"):
        AgentSettings(batch_size=10**12)
    assert AgentSettings(batch_size=256).batch_size == 256
