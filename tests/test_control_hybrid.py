"""Planners that reach far, on the CPU with a tiny pendulum model: the hybrid planner (sampled
proposals refined by Adam through the model; CEM on the true simulator), the planned return
(discount, terminal value) that every planner shares, and per-step gradient conditioning."""
import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.control import (GradientMPC, GradientMPCConfig, PlanningError, Task, get_planner, get_task, planner_name,
                            run_episodes)
from gnwarp.control.hybrid import HybridConfig, HybridPlanner
from gnwarp.control.returns import condition_gradient, planned_return, step_rewards
from gnwarp.control.sampling import (EnsembleDynamics, ModelDynamics, SamplingConfig, SamplingPlanner, model_dynamics,
                                     score_rollouts, true_dynamics)
from gnwarp.gn import RunOptions
from gnwarp.interop import warp
from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig
from gnwarp.sim.env import make_env
from gnwarp.validation import ConfigError

warp()

N = 2
Q0, V0 = np.array([[0.3], [-0.4]]), np.array([[0.1], [0.0]])
TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))
TASK = get_task("pendulum-balance")


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (4, 1, 1), num_steps=6, seed=0, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def model(pendulum):
    torch.manual_seed(0)
    return ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch")), pendulum.layout)


@pytest.fixture(scope="module")
def x0():
    env = make_env("pendulum", N, backend="mujoco")
    return torch.as_tensor(env.reset(Q0, V0)).float()


def model_return(model, x, actions, terminal=None, discount=1.0):
    """The reference: the model's own rollout scored by the task's reward (and terminal)."""
    with torch.no_grad():
        return planned_return(TASK.reward, model.rollout(x, actions), actions, None, discount, terminal)


def test_hybrid_refines_its_sampling_proposal_on_the_model(model, x0):
    cfg = dict(horizon=6, samples=8, elites=2, knots=3, lr=0.1, seed=3, warmup=0)
    refined = HybridPlanner(model, TASK, "pendulum", N, HybridConfig(iterations=4, **cfg))
    sampled = HybridPlanner(model, TASK, "pendulum", N, HybridConfig(iterations=0, **cfg))
    assert refined.refinement == "gradient" and not refined.needs_sim_state
    assert planner_name(refined) == "hybrid" and get_planner("hybrid").cls is HybridPlanner
    refined.optimize(x0)
    sampled.optimize(x0)
    # the same proposals (same seed); refinement never loses the sampled best, and here gains
    torch.testing.assert_close(refined.last_sampled, sampled.last_sampled)
    torch.testing.assert_close(sampled.last_refined, sampled.last_sampled)
    assert (refined.last_refined >= refined.last_sampled).all()
    assert (refined.last_refined > refined.last_sampled + 1e-4).all(), (refined.last_sampled, refined.last_refined)
    # the predicted returns are the model's own of the plans
    for p in (refined, sampled):
        torch.testing.assert_close(p.last_refined, model_return(model, x0, p.plan), rtol=1e-4, atol=1e-4)
    assert (refined.plan.abs() <= 1).all() and refined.act(x0, 0).shape == (N, 1)
    # warm start: the next nominal is the plan shifted one step, its last action repeated
    torch.testing.assert_close(refined.nominal[:, :-1], refined.plan[:, 1:])
    torch.testing.assert_close(refined.nominal[:, -1], refined.plan[:, -1])


def test_hybrid_runs_on_the_true_dynamics(x0):
    cfg = HybridConfig(horizon=5, samples=6, elites=2, iterations=2, knots=2, seed=1)
    env = make_env("pendulum", N, backend="mujoco")
    p = HybridPlanner(true_dynamics("pendulum", N, 6, backend="mujoco"), TASK, "pendulum", N, cfg)
    assert p.refinement == "cem" and p.needs_sim_state
    env.reset(Q0, V0)
    p.optimize(env.observe())
    assert (p.last_refined >= p.last_sampled).all()
    # the predicted return is the true simulator's return of the plan
    check = make_env("pendulum", N, backend="mujoco")
    check.reset(Q0, V0)
    states = torch.stack([torch.as_tensor(check.body_states()).float()]
                         + [torch.as_tensor(check.step(p.plan[:, t])).float() for t in range(5)], 1)
    torch.testing.assert_close(p.last_refined, TASK.reward(states, p.plan), rtol=1e-4, atol=1e-4)
    out = run_episodes(p, env, TASK, 3, qpos0=Q0, qvel0=V0)
    assert torch.isfinite(out["returns"]).all() and (out["actions"].abs() <= 1).all()
    with pytest.raises(PlanningError, match="refine='gradient' needs a learned Dynamics"):
        HybridPlanner(true_dynamics("pendulum", N, 6, backend="mujoco"), TASK, "pendulum", N,
                      HybridConfig(horizon=5, samples=6, knots=2, refine="gradient"))


def test_hybrid_settings_refuse_bad_values_by_name():
    for kw, field in ((dict(samples=4, elites=5), "elites"), (dict(horizon=3, knots=4), "knots"),
                      (dict(refine="adam"), "refine"), (dict(discount=0.0), "discount"),
                      (dict(grad_norm="global"), "grad_norm"), (dict(iterations=-1), "iterations")):
        with pytest.raises(ConfigError, match=f"^{field}"):
            HybridConfig(**kw)
    for kw, field in ((dict(discount=1.5), "discount"), (dict(grad_norm="layer"), "grad_norm")):
        with pytest.raises(ConfigError, match=f"^{field}"):
            GradientMPCConfig(**kw)
    with pytest.raises(ConfigError, match="^discount"):
        SamplingConfig(discount=-0.5)


def test_planned_return_discount_and_terminal(model, x0):
    u = torch.linspace(-1, 1, N * 5).reshape(N, 5, 1)
    with torch.no_grad():
        s = model.rollout(x0, u)
    per = step_rewards(TASK.reward, s, u)
    torch.testing.assert_close(per.sum(1), TASK.reward(s, u))   # the per-step terms add to the reward
    for t in range(5):
        torch.testing.assert_close(per[:, t], TASK.reward(s[:, t:t + 2], u[:, t:t + 1]))
    value = lambda last: last[:, 1, 0] * 3.0 + 1.0   # noqa: E731
    got = planned_return(TASK.reward, s, u, discount=0.8, terminal=value)
    want = (per * 0.8 ** torch.arange(5.0)).sum(1) + 0.8 ** 5 * value(s[:, -1])
    torch.testing.assert_close(got, want)
    with pytest.raises(TypeError, match="terminal must be a callable"):
        GradientMPC(model, TASK, "pendulum", N, GradientMPCConfig(horizon=5), terminal=3.0)


def test_gradient_includes_the_terminal_value(model, x0):
    """The planner's gradient with a terminal value = its gradient without + discount^H x the
    value's gradient through the rollout (computed apart by autograd)."""
    H, d = 5, 0.9
    value = torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(26, 1), torch.nn.Flatten(0))
    cfg = GradientMPCConfig(horizon=H, discount=d)
    with_v = GradientMPC(model, TASK, "pendulum", N, cfg, terminal=value)
    without = GradientMPC(model, TASK, "pendulum", N, cfg)
    z = torch.randn(N, H, 1, generator=torch.Generator().manual_seed(0)) * 0.5
    x = with_v.check_state(x0)
    r1, g1 = with_v.return_gradient(x, z)
    r0, g0 = without.return_gradient(x, z)
    zz = z.clone().requires_grad_(True)
    v = value(model.rollout(x, with_v.to_actions(zz))[:, -1])
    (gv,) = torch.autograd.grad(v.sum(), zz)
    torch.testing.assert_close(r1 - r0, d ** H * v.detach(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(g1 - g0, d ** H * gv, rtol=1e-3, atol=1e-6)
    assert gv.abs().max() > 1e-4   # the value's gradient is not negligible here
    # a sampling planner and the hybrid add it to each candidate's score too
    sp = SamplingPlanner(model_dynamics(model, N, 4, H), TASK, [[-1.0, 1.0]], N,
                         SamplingConfig(horizon=H, samples=4, knots=2, discount=d), terminal=value)
    sp.optimize(x0)
    u = sp.plan
    torch.testing.assert_close(sp.last_rewards.max(1).values, model_return(model, x0, u, value, d), rtol=1e-4,
                               atol=1e-4)
    hp = HybridPlanner(model, TASK, "pendulum", N, HybridConfig(horizon=H, samples=4, elites=2, iterations=2,
                                                                knots=2, discount=d), terminal=value)
    hp.optimize(x0)
    torch.testing.assert_close(hp.last_refined, model_return(model, x0, hp.plan, value, d), rtol=1e-4, atol=1e-4)


def test_per_step_gradient_conditioning():
    # a gradient whose step norms span 1e8 (as through a long contact-rich rollout), with an Inf
    g = torch.randn(3, 12, 2, generator=torch.Generator().manual_seed(0)) * (10.0 ** -torch.arange(12.0))[:, None]
    g[1, 4, 0] = torch.inf
    g[2, 7] = 0.0
    raw = torch.linalg.vector_norm(condition_gradient(g, "none"), dim=-1)
    c = condition_gradient(g, "step")
    norms = torch.linalg.vector_norm(c, dim=-1)
    assert torch.isfinite(c).all() and raw[0].max() / raw[0].min() > 1e8
    live = norms > 0
    assert live.sum() == 3 * 12 - 1 and not live[2, 7]          # a zero step stays zero
    for n in range(3):
        k = norms[n][live[n]]
        assert k.max() / k.min() < 1 + 1e-5                     # steps equalized
        torch.testing.assert_close(k.square().mean().sqrt(), raw[n].square().mean().sqrt(), rtol=1e-5,
                                   atol=0)
    # directions kept per step
    d0 = g[0] / torch.linalg.vector_norm(g[0], dim=-1, keepdim=True)
    torch.testing.assert_close(c[0] / norms[0][:, None], d0)
    with pytest.raises(ValueError, match="grad_norm"):
        condition_gradient(g, "layer")


def test_long_horizon_gradient_stays_finite_and_conditioned(model, x0):
    """Gradient MPC over 40 steps with grad_norm="step": finite gradient, per-step norms within
    a bounded ratio, and Adam's steps finite."""
    p = GradientMPC(model, TASK, "pendulum", N, GradientMPCConfig(horizon=40, grad_norm="step", lr=0.05))
    x = p.check_state(x0)
    r, g = p.return_gradient(x)
    assert torch.isfinite(r).all() and torch.isfinite(g).all()
    norms = torch.linalg.vector_norm(condition_gradient(g, "step"), dim=-1)
    assert (norms > 0).all() and (norms.max(1).values / norms.min(1).values < 1.001).all()
    before = p.planned_reward(x)
    p.iterate(x, 3)
    assert torch.isfinite(p.z).all() and torch.isfinite(p.planned_reward(x)).all()
    assert not torch.equal(before, p.planned_reward(x))


def toy_member(curv: float):
    """A toy learned dynamics of the pendulum's graph: body 1's x after step t is u_t - curv u_t^2."""
    def rollout(x0, u):
        s = x0[:, None].repeat(1, u.shape[1] + 1, 1, 1).clone()
        s[:, 1:, 1, 0] = u[..., 0] - curv * u[..., 0].square()
        return s
    return ModelDynamics(rollout)


def test_ensemble_scores_mean_minus_spread(x0):
    members = [toy_member(0.0), toy_member(2.0)]      # they agree at u = 0 only
    reward = lambda s, a: s[:, 1:, 1, 0].sum(1)      # noqa: E731
    u = torch.linspace(-1, 1, 5).reshape(5, 1, 1)
    for penalty in (0.0, 4.0):
        ens = EnsembleDynamics(members, penalty)
        got = score_rollouts(ens, x0[:1], u, 5, lambda s: reward(s, u))
        mean, std = u[:, 0, 0] - u[:, 0, 0].square(), u[:, 0, 0].square()   # members u and u - 2u^2
        torch.testing.assert_close(got, mean - penalty * std)
        # a sampling planner and the hybrid (CEM: the ensemble has no gradients) pick the
        # pessimistic optimum argmax u - (1 + penalty) u^2 = 1 / (2 (1 + penalty))
        best = 1 / (2 * (1 + penalty))
        sp = SamplingPlanner(ens, reward, [[-1.0, 1.0]], N, SamplingConfig(horizon=2, samples=64, knots=1, noise=0.6))
        toy = Task("toy-x", "pendulum", 2, lambda s, a, target=None: reward(s, a))
        hp = HybridPlanner(ens, toy, "pendulum", N, HybridConfig(horizon=2, samples=32, elites=4, iterations=3,
                                                                 knots=1, interpolation="zero", noise=0.6))
        assert hp.refinement == "cem"
        for p in (sp, hp):
            p.optimize(x0)
            assert (p.plan[:, 0, 0] - best).abs().max() < 0.1, (penalty, p.plan[:, 0, 0])
    with pytest.raises(ValueError, match=">= 2 RolloutDynamics"):
        EnsembleDynamics(members[:1])
    with pytest.raises(ValueError, match="penalty"):
        EnsembleDynamics(members, -1.0)


def test_hybrid_warms_up_at_the_first_state_only(model, x0):
    p = HybridPlanner(model, TASK, "pendulum", N, HybridConfig(horizon=4, samples=4, elites=2, iterations=1, warmup=3,
                                                               knots=2))
    runs = []
    for reset in (False, False, True):
        if reset:
            p.reset()
        before = p.refiner.iterations_run
        p.optimize(x0)
        runs.append(p.refiner.iterations_run - before)
    assert runs == [4, 1, 4]


def test_grad_decay_weights_later_rewards_by_their_distance(model, x0):
    """With grad_decay d, the gradient reaching action t from the reward of step k >= t is
    weighted d^(k - t): against the per-step rewards' full gradients by autograd apart."""
    H = 5
    z = torch.randn(N, H, 1, generator=torch.Generator().manual_seed(1)) * 0.5
    ref = GradientMPC(model, TASK, "pendulum", N, GradientMPCConfig(horizon=H))
    x = ref.check_state(x0)
    zz = z.clone().requires_grad_(True)
    u = ref.to_actions(zz)
    per = step_rewards(TASK.reward, model.rollout(x, u), u)                # [N, H]
    parts = torch.stack([torch.autograd.grad(per[:, k].sum(), zz, retain_graph=True)[0] for k in range(H)])
    torch.testing.assert_close(ref.return_gradient(x, z)[1], parts.sum(0), rtol=1e-4, atol=1e-6)
    for d in (0.0, 0.5):
        p = GradientMPC(model, TASK, "pendulum", N, GradientMPCConfig(horizon=H, grad_decay=d))
        r, g = p.return_gradient(x, z)
        k, t = torch.arange(H)[:, None], torch.arange(H)[None, :]
        w = torch.where(k >= t, torch.tensor(d) ** (k - t).clamp_min(0), torch.tensor(0.0))   # [k, t]
        want = torch.einsum("kt,kntu->ntu", w, parts)
        torch.testing.assert_close(g, want, rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(r, per.sum(1).detach(), rtol=1e-5, atol=1e-5)   # the return is unchanged
    with pytest.raises(ConfigError, match="^grad_decay"):
        GradientMPCConfig(grad_decay=1.5)
