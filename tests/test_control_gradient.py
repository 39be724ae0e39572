"""Gradient MPC through a learned model (F.1.1, Algorithm F.1) and closed-loop episodes, on the CPU
with a tiny pendulum model and a MuJoCo C environment stub."""
import copy

import mujoco
import numpy as np
import pytest
import torch

from gnwarp import data, systems
from gnwarp.control import GradientMPC, GradientMPCConfig, PlanningError, TaskError, run_episodes
from gnwarp.sim.body_state import body_states
from gnwarp.gn import RunOptions
from gnwarp.models import GNCoreConfig, ModelConfig
from gnwarp.train import TrainConfig, load_model, train
from gnwarp.validation import ConfigError

TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))


@pytest.fixture(scope="module")
def pendulum_data():
    return data.generate("pendulum", (20, 3, 4), num_steps=20, seed=0, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def model(tmp_path_factory, pendulum_data):
    out = tmp_path_factory.mktemp("mpc") / "run"
    cfg = TrainConfig(out=str(out), model=ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch")),
                      steps=150, batch_size=32, lr=3e-3, lr_decay_steps=1000, valid_every=150, valid_sequences=3,
                      log_every=50, checkpoint_every=150, normalizer_warmup=2, progress=False, device="cpu")
    path = train(cfg, [pendulum_data])["last"]
    m = load_model(path, device="cpu")
    m.path = path
    return m


class MjEnv:
    """The true environment's API (``reset``, ``step(ctrl [N, U]) -> body states [N, B, 13]``) on
    MuJoCo C, one MjData per world."""

    def __init__(self, system, n):
        self.system, self.m = system, system.model
        self.d = [mujoco.MjData(self.m) for _ in range(n)]

    def _states(self):
        for d in self.d:
            mujoco.mj_forward(self.m, d)
        return torch.tensor(np.stack([body_states(self.m, d) for d in self.d]), dtype=torch.float32)

    def reset(self, qpos, qvel):
        for d, q, v in zip(self.d, qpos, qvel):
            mujoco.mj_resetData(self.m, d)
            d.qpos[:], d.qvel[:] = q, v
        return self._states()

    def step(self, ctrl):
        for d, c in zip(self.d, np.asarray(torch.as_tensor(ctrl).cpu(), dtype=np.float64)):
            d.ctrl[:] = c
            mujoco.mj_step(self.m, d, nstep=self.system.substeps)
        return self._states()


def x0(pendulum_data, n):
    return torch.as_tensor(np.asarray(pendulum_data["test"].body[:n, 0]))


def test_one_iteration_lowers_the_planned_cost(model, pendulum_data):
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=3, config=GradientMPCConfig(horizon=10, lr=1e-3))
    x = p.check_state(x0(pendulum_data, 3))
    before = p.planned_reward(x)
    r = p.iterate(x, 1)
    assert torch.allclose(r, before, atol=1e-5)        # iterate reports the reward it stepped from
    after = p.planned_reward(x)
    assert (after >= before - 1e-5).all() and after.sum() > before.sum(), (before, after)
    r = p.iterate(x, 30)
    assert p.planned_reward(x).sum() > after.sum()


def test_step_applies_the_first_action_and_shifts_the_plan(model, pendulum_data, monkeypatch):
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=2, config=GradientMPCConfig(horizon=6, proposals=0))
    plan = p.actions.clone()
    z = p.z.clone()
    seen = []
    monkeypatch.setattr(p, "iterate", lambda x, k: seen.append(k))
    a = p.step(x0(pendulum_data, 2))
    assert torch.equal(a, plan[:, 0])
    assert torch.equal(p.z[:, :-1], z[:, 1:]) and torch.equal(p.z[:, -1], z[:, -1])   # the last repeated
    p.step(x0(pendulum_data, 2))
    assert seen == [5 + 4 * 5, 5]                      # warm-up (4 x iterations) at the first state only
    p.reset()
    p.step(x0(pendulum_data, 2))
    assert seen[-1] == 25


def test_actions_stay_in_the_control_range(model, pendulum_data):
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=4,
                    config=GradientMPCConfig(horizon=5, iterations=3, warmup=5, lr=50.0, init_std=5.0))
    x = x0(pendulum_data, 4)
    for _ in range(3):
        a = p.step(x)
        assert a.shape == (4, 1) and (a.abs() <= 1.0).all()
    assert (p.actions.abs() <= 1.0).all() and torch.isfinite(p.z).all()


def test_closed_loop_on_the_true_simulator(model):
    pend = systems.make("pendulum")
    env = MjEnv(pend, 2)
    qpos, qvel = np.array([[3.0], [-2.5]]), np.zeros((2, 1))
    start = env.reset(qpos, qvel)
    p = GradientMPC(model, "pendulum-balance", pend, n=2, config=GradientMPCConfig(horizon=5, iterations=2, warmup=4))
    out = run_episodes(p, env, "pendulum-balance", 4, start)
    assert out["states"].shape == (2, 5, 2, 13) and out["actions"].shape == (2, 4, 1)
    assert torch.equal(out["states"][:, 0], start) and torch.isfinite(out["states"]).all()
    assert out["returns"].shape == (2,) and (out["returns"] < 0).all()
    # the recorded trajectory is the true simulator's under the recorded actions
    env2 = MjEnv(pend, 2)
    env2.reset(qpos, qvel)
    for t in range(4):
        x = env2.step(out["actions"][:, t])
    assert torch.allclose(x, out["states"][:, -1], atol=1e-6)
    try:   # the batched environment, where present, runs the same loop
        from gnwarp.sim import make_env
        env3 = make_env(pend, 2, backend="mujoco")
    except ImportError:
        return
    p.reset()
    out3 = run_episodes(p, env3, "pendulum-balance", 2, env3.reset(qpos, qvel))
    assert torch.allclose(out3["states"][:, 0], start, atol=1e-5) and torch.isfinite(out3["returns"]).all()


def test_clear_errors(model, pendulum_data):
    with pytest.raises(TaskError, match="unknown task 'pendulum-flip'"):
        GradientMPC(model, "pendulum-flip", "pendulum", n=1)
    with pytest.raises(TaskError, match="is for cartpole, but the system is pendulum"):
        GradientMPC(model, "cartpole-balance", "pendulum", n=1)
    with pytest.raises(PlanningError, match="trained on pendulum, not on cartpole"):
        GradientMPC(model, "cartpole-balance", "cartpole", n=1)
    bare = copy.deepcopy(model)
    bare.checkpoint_info = None                        # not from a checkpoint: the feature layout says it
    with pytest.raises(PlanningError, match="does not fit cartpole"):
        GradientMPC(bare, "cartpole-balance", "cartpole", n=1)
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=2, config=GradientMPCConfig(horizon=3))
    x = x0(pendulum_data, 2).clone()
    x[1, 1, 8] = float("nan")
    with pytest.raises(PlanningError, match="episode 1 has NaN or Inf \\(body 1, feature 8\\)"):
        p.step(x)
    with pytest.raises(PlanningError, match=r"states must be \[N, B, 13\] = \[2, 2, 13\]"):
        p.step(x[:1])
    with pytest.raises(ConfigError, match="iterations"):
        GradientMPCConfig(iterations=0)
    with pytest.raises(ConfigError, match="capture_warmup"):
        GradientMPCConfig(capture_warmup=-1)
    from gnwarp.interop import Graphed
    with pytest.raises(ValueError, match="warmup must be an integer >= 0"):
        Graphed(lambda: None, warmup=-1)      # refused before any CUDA call


def test_cli_mpc(model, tmp_path, capsys):
    from gnwarp.cli import main
    from gnwarp.eval.records import read_records
    video, records = tmp_path / "mpc.gif", tmp_path / "mpc.jsonl"
    args = ["mpc", "--model", str(model.path), "--task", "pendulum-balance", "--episodes", "2", "--steps", "3",
            "--horizon", "3", "--iterations", "1", "--warmup", "0", "--backend", "mujoco", "--video", str(video),
            "--renderer", "matplotlib", "--records", str(records)]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "true return" in out and "+-" in out and video.is_file() and f"wrote {records}" in out
    (rec,) = read_records(records)
    assert (rec.experiment, rec.task, rec.system, rec.planner, rec.dynamics) == (
        "mpc", "pendulum-balance", "pendulum", "gradient", "learned")
    assert rec.episodes == 2 and len(rec.returns) == 2 and rec.episode_steps == 3 and rec.seed == 0
    assert f"true return {sum(rec.returns) / 2:.4g}" in out
    assert rec.env_steps == 20 * 20   # the training split: 20 sequences of 20 steps
    assert np.asarray(rec.config["initial_qpos"]).shape == (2, 1) and rec.config["targets"] is None
    assert rec.control_dt == pytest.approx(0.02) and rec.config["horizon"] == 3
    # the first control step and the steady state apart, the real-time factor from the steady one
    m = rec.metrics
    assert m["first_step_ms"] > 0 and m["steady_ms"] > 0 and m["model_evals_per_step"] == 1 * 3
    assert m["real_time_factor"] == pytest.approx(1e3 * rec.control_dt / m["steady_ms"])
    assert len(m["plan_ms"]) == 3 and m["first_step_ms"] == pytest.approx(m["plan_ms"][0])
    assert m["steady_ms"] == pytest.approx(float(np.median(m["plan_ms"][1:])))   # 3 steps: those after the first
    assert f"first control step {m['first_step_ms']:.1f} ms" in out and f"steady {m['steady_ms']:.2f} ms" in out
    assert f"real-time factor {m['real_time_factor']:.3g}" in out
    assert main(args[:4] + ["cheetah-forward"] + args[5:]) == 2
    assert "the model was trained on pendulum, not on cheetah" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--records", "--video"])
def test_cli_mpc_checks_output_paths_first(tmp_path, capsys, option):
    """A missing output folder is refused before the model is even loaded (here: none exists)."""
    from gnwarp.cli import main
    missing = tmp_path / "missing" / "out.x"
    args = ["mpc", "--model", str(tmp_path / "no-model"), "--task", "pendulum-balance", "--video", "none",
            "--records", str(tmp_path / "r.jsonl"), option, str(missing)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"{option} {missing}" in err and "does not exist" in err and "no-model" not in err


def test_cli_mpc_refuses_a_horizon_that_cannot_fit_before_planning(model, tmp_path, capsys):
    """A horizon whose rollouts need more memory than the machine has is refused, naming the
    sizes, before any planning (it used to run until the machine ran out)."""
    from gnwarp.cli import main
    from gnwarp.control.planner import plan_bytes
    assert plan_bytes(1, 10**8, 2, 1) == 4 * 8 * (10**8 + 1) * 27 and plan_bytes(2, 9, 2, 1, 64, 2) == 4 * 2 * 128 * 10 * 27
    args = ["mpc", "--model", str(model.path), "--task", "pendulum-balance", "--episodes", "1", "--steps", "1",
            "--horizon", str(10**9), "--iterations", "1", "--warmup", "0", "--backend", "mujoco", "--video", "none",
            "--records", str(tmp_path / "r.jsonl")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "planning 1 episodes x 1 rollouts x horizon 1000000000 x 2 bodies needs about" in err, err
    assert "Use a shorter --horizon" in err and not (tmp_path / "r.jsonl").exists()


def test_cli_mpc_refuses_a_records_file_that_is_not_one(tmp_path, capsys):
    from gnwarp.cli import main
    bad = tmp_path / "r.jsonl"
    bad.write_text("not a record\n")
    assert main(["mpc", "--model", str(tmp_path / "no-model"), "--task", "pendulum-balance", "--video", "none",
                 "--records", str(bad)]) == 2
    assert f"{bad}, line 1" in capsys.readouterr().err
    assert bad.read_text() == "not a record\n"


def test_adam_state_is_shifted_with_the_plan(model, pendulum_data):
    """The plan's buffers are updated in place (a captured iteration reads them): after a step
    the moments are shifted like the plan and the step count keeps counting."""
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=2, config=GradientMPCConfig(horizon=6, warmup=0))
    z_buf, x = p.z, x0(pendulum_data, 2)
    p.iterate(p.check_state(x), 2)
    m = p._m.clone()
    p.shift()
    assert p.z is z_buf and torch.equal(p._m[:, :-1], m[:, 1:]) and int(p._t) == 2


@pytest.mark.parametrize("grad_decay", [1.0, 0.5])
def test_prime_leaves_the_plan_and_sizes_the_store(model, pendulum_data, grad_decay):
    """The prime before a recording (``capture_warmup`` 0) runs one model step forward and
    backward but changes nothing the iteration works on (plan, Adam's moments and step, the
    counts); it decides the rollout engine's store from that step, and the iterations after it
    plan what a planner never primed plans."""
    cfg = GradientMPCConfig(horizon=6, warmup=0, grad_decay=grad_decay)
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=2, config=cfg)
    q = GradientMPC(model, "pendulum-balance", "pendulum", n=2, config=cfg)
    x = p.check_state(x0(pendulum_data, 2))
    p._x.copy_(x)
    before = [t.clone() for t in (p.z, p._m, p._v, p._t)]
    p._prime()
    assert all(torch.equal(a, b) for a, b in zip(before, (p.z, p._m, p._v, p._t)))
    assert p.iterations_run == p.evals == 0
    store = (p._step_engine or p.engine).store
    assert store is not None and store.sized and store.generation == (1 if grad_decay < 1 else 0)
    assert not q.engine.store.sized
    torch.testing.assert_close(p.iterate(x, 3), q.iterate(x, 3), rtol=0, atol=0)
    torch.testing.assert_close(p.z, q.z, rtol=0, atol=0)


@pytest.mark.parametrize("rows", [None, 9])
def test_proposal_starts_adam_from_the_best_sequence(model, pendulum_data, monkeypatch, rows):
    """The proposal rolls out the reset's sequence, the mid sequence and random ones (in batches
    of ``PROPOSAL_ROWS`` rows), keeps each episode's best and counts the model steps it ran."""
    import gnwarp.control.gradient as gradient
    if rows is not None:
        monkeypatch.setattr(gradient, "PROPOSAL_ROWS", rows)   # 3 sequences of 3 episodes a batch
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=3, config=GradientMPCConfig(horizon=8, proposals=6))
    x = p.check_state(x0(pendulum_data, 3))
    z0 = p.z.clone()
    r_random, r_mid = p.planned_reward(x, z0), p.planned_reward(x, torch.zeros_like(z0))
    best = p.propose(x)
    torch.testing.assert_close(p.planned_reward(x), best, rtol=1e-5, atol=1e-5)   # the working sequence is the best
    assert (best >= torch.maximum(r_random, r_mid) - 1e-5).all()
    assert not torch.equal(p.z, z0) or bool((r_random >= r_mid).all())
    batches = 1 if rows is None else 3              # 8 sequences: one batch of 8, or 3 batches of 3
    per = 8 if rows is None else 3
    assert p.proposal_evals == batches * per * 8 and p.evals == 0


def test_bounded_warmup_counts_its_evaluations_and_beats_a_random_plan(model, pendulum_data):
    cfg = GradientMPCConfig(horizon=10, iterations=2)
    p = GradientMPC(model, "pendulum-balance", "pendulum", n=3, config=cfg)
    x = p.check_state(x0(pendulum_data, 3))
    r_random = p.planned_reward(x)
    p.optimize(x)
    assert p.warmup == 4 * 2 and p.model_evals_per_step == 2 * 10
    assert p.last_evals == {"iterations": 2 + 8, "evals": 10 * 10, "proposal_evals": 32 * 10}
    with torch.no_grad():
        r_plan = p.task.reward(p.engine.rollout(x, p.plan), p.plan)
    assert (r_plan >= r_random - 1e-5).all() and r_plan.sum() > r_random.sum(), (r_plan, r_random)
    for _ in range(2):                              # no shortcut: every later step runs the full budget
        p.optimize(x)
        assert p.last_evals == {"iterations": 2, "evals": p.model_evals_per_step, "proposal_evals": 0}
    assert p.evals == 100 + 2 * 20 and p.iterations_run == 14 and p.proposal_evals == 320
    with pytest.raises(ConfigError, match="proposals"):
        GradientMPCConfig(proposals=-1)


def test_bounded_warmup_returns_stay_with_the_papers(model):
    """Closed loop on the true simulator: the proposal with 4 x iterations of warm-up returns what
    the paper's iterations x horizon warm-up from a random sequence returns (to 5%)."""
    from gnwarp.data.generation import initial_states
    pend = systems.make("pendulum")
    n, H, it = 6, 8, 2
    qpos, qvel = initial_states(pend, n, np.random.default_rng(1))
    returns = {}
    for name, extra in (("paper", dict(warmup=it * H, proposals=0)), ("bounded", {})):
        env = MjEnv(pend, n)
        p = GradientMPC(model, "pendulum-balance", pend, n, GradientMPCConfig(horizon=H, iterations=it, **extra))
        returns[name] = run_episodes(p, env, "pendulum-balance", 10, env.reset(qpos, qvel))["returns"].double()
    paper, bounded = returns["paper"].mean(), returns["bounded"].mean()
    assert bounded >= paper - 0.05 * paper.abs(), returns


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("capture_warmup", [0, 1, 2])
def test_cuda_captured_planning_iteration_matches_eager(pendulum_data, capture_warmup):
    """One planning iteration replayed from a CUDA graph (rollout, reward, adjoint backward, Adam)
    plans what eager iterations plan, step after step, recorded after one or two eager ones, or
    at once after the one-step prime (0)."""
    from gnwarp.models.factory import build_model
    torch.manual_seed(0)   # an untrained model on CUDA (the fixture's training runs Warp CPU kernels)
    cfg = TrainConfig(model=ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="warp", precision="fp32")))
    m = build_model(cfg.model, [pendulum_data]).to("cuda")
    plans = {}
    for capture in (True, False):
        p = GradientMPC(m, "pendulum-balance", "pendulum", n=4,
                        config=GradientMPCConfig(horizon=8, iterations=3, warmup=4, capture=capture,
                                                 capture_warmup=capture_warmup))
        assert (p._graph is not None) == capture and (not capture or p._graph.warmup == capture_warmup)
        x, acts = x0(pendulum_data, 4), []
        for _ in range(4):
            acts.append(p.step(x).cpu())
        plans[capture] = (torch.stack(acts), p.actions.cpu())
    torch.testing.assert_close(plans[True][0], plans[False][0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(plans[True][1], plans[False][1], rtol=1e-4, atol=1e-5)


def test_prime_dense_runs_each_weight_shape_and_leaves_the_model(model, monkeypatch):
    """cuBLAS's first use on a thread beside construction (``prime_dense``): every distinct 2-D
    weight shape's GEMMs run once, on stand-ins; the model's parameters and gradients and the
    random generator are untouched, and on the CPU no thread is started."""
    from gnwarp.gn import mlp
    params = list(model.parameters())
    before = [p.detach().clone() for p in params]
    shapes = list(dict.fromkeys(tuple(p.shape) for p in params if p.dim() == 2))
    calls = []
    real = mlp.linear
    monkeypatch.setattr(mlp, "linear", lambda x, w, b, relu: calls.append((tuple(w.shape), relu)) or real(x, w, b, relu))
    rng = torch.get_rng_state()
    assert mlp.prime_dense(params) == min(len(shapes), 8) > 0
    assert calls == [(s, r) for s in shapes[:8] for r in (True, False)]
    assert mlp.prime_dense(params, shapes=1) == 1
    assert torch.equal(torch.get_rng_state(), rng)
    for p, b in zip(params, before):
        assert p.grad is None
        assert torch.equal(p.detach(), b)
    assert mlp.prime_dense_async(model) is None     # CPU parameters: nothing to hide
    with pytest.raises(ConfigError, match="prime_dense"):
        GradientMPCConfig(prime_dense="yes")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_prime_dense_thread_plans_what_the_planner_plans_without_it(pendulum_data):
    """The planner built with its GEMMs primed on a thread acts as one built without; the thread
    has ended when construction returns, and also when construction fails after starting it."""
    import threading
    from gnwarp.models.factory import build_model
    torch.manual_seed(0)
    cfg = TrainConfig(model=ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="warp", precision="fp32")))
    m = build_model(cfg.model, [pendulum_data]).to("cuda")
    alive = lambda: [t for t in threading.enumerate() if t.name == "gnwarp-prime-dense" and t.is_alive()]  # noqa: E731
    acts = {}
    for prime in (True, False):
        p = GradientMPC(m, "pendulum-balance", "pendulum", n=2,
                        config=GradientMPCConfig(horizon=8, iterations=3, warmup=4, prime_dense=prime))
        assert not alive()
        x = x0(pendulum_data, 2)
        acts[prime] = torch.stack([p.step(x).cpu() for _ in range(3)])
    torch.testing.assert_close(acts[True], acts[False], rtol=1e-4, atol=1e-5)
    with pytest.raises(TaskError, match="one entry per episode"):   # in the build, after the thread started
        GradientMPC(m, "pendulum-balance", "pendulum", n=2, config=GradientMPCConfig(horizon=8),
                    targets=torch.zeros(5, 7, 3))
    assert not alive()
