"""The learned terminal value: TD(lambda) fitting reduces the TD error, its targets against a
direct computation, translation recentring, safe files, and fitting from closed-loop episodes."""
import pickle

import numpy as np
import pytest
import torch

from gnwarp.control import get_task, run_episodes
from gnwarp.control.sampling import RandomPlanner
from gnwarp.control.value import TerminalValue, ValueFileError, default_recentre, episode_rewards, fit_terminal_value
from gnwarp.sim.env import make_env


def walks(E=16, T=30, seed=0):
    """Synthetic trajectories of 3 bodies: body 1's y decays to 0 with noise, its x drifts
    (irrelevant: a recentred axis); reward -y^2 of the next state."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(E, T + 1, 3, 13)
    x[..., 3] = 1.0
    y, px = torch.randn(E, generator=g) * 2, torch.randn(E, generator=g) * 10
    for t in range(T + 1):
        x[:, t, 1, 0], x[:, t, 1, 1], x[:, t, 2, 1], x[:, t, 2, 0] = px, y, 0.5 * y, px + 1.0
        y = 0.9 * y + 0.1 * torch.randn(E, generator=g)
        px = px + 0.3
    return x, -x[:, 1:, 1, 1].square()


def test_a_value_recentres_the_axes_its_system_records():
    """``TerminalValue.for_system`` reads the system's own ``translation_axes``: a user MJCF
    system that records one gets it (its name is in no table), a built-in one its family's."""
    from gnwarp.sim import systems
    xml = ('<mujoco><worldbody><body name="b"><joint name="x" type="slide" axis="1 0 0"/><geom size="0.1"/>'
           '</body></worldbody><actuator><motor joint="x"/></actuator></mujoco>')
    sliding = systems.from_mjcf_string(xml, name="slider", dt=0.01, translation_axes=(0, 1))
    assert TerminalValue.for_system(sliding).recentre == (0, 1) == default_recentre(sliding)
    assert TerminalValue.for_system(systems.from_mjcf_string(xml, name="slider", dt=0.01)).recentre == ()
    assert TerminalValue.for_system(systems.make("cheetah")).recentre == (0,)


def test_fit_reduces_the_td_error():
    x, r = walks()
    torch.manual_seed(0)
    v = TerminalValue(3, hidden=(32, 32), recentre=(0,), gamma=0.9)
    hist = v.fit(x, r, rounds=6, steps=30, lr=3e-3)
    assert hist["td_error"][-1] < 0.3 * hist["td_error"][0], hist["td_error"]
    # held-out trajectories of the same process: also lower than before fitting
    xt, rt = walks(seed=1)
    fresh = TerminalValue(3, hidden=(32, 32), recentre=(0,), gamma=0.9)
    assert v.td_error(xt, rt) < 0.5 * fresh.td_error(xt, rt)
    # the value learned the shape: states further from y = 0 are worth less
    s = x[:2, 0].clone()
    s[0, 1, 1], s[0, 2, 1], s[1, 1, 1], s[1, 2, 1] = 0.0, 0.0, 2.0, 1.0
    far, near = v(s)[1], v(s)[0]
    assert far < near


def test_lambda_returns_against_a_direct_computation():
    v = TerminalValue(2, gamma=0.8)
    r = torch.tensor([[1.0, 2.0, 3.0]])
    vals = torch.tensor([[0.5, -1.0, 2.0, 4.0]])
    # lambda = 1: the discounted return bootstrapped by the last value; lambda = 0: one-step TD
    mc = [1 + 0.8 * 2 + 0.64 * 3 + 0.512 * 4, 2 + 0.8 * 3 + 0.64 * 4, 3 + 0.8 * 4]
    torch.testing.assert_close(v.lambda_returns(vals, r, 1.0), torch.tensor([mc]))
    torch.testing.assert_close(v.lambda_returns(vals, r, 0.0), r + 0.8 * vals[:, 1:])
    # lambda in between: the (1 - lambda)-weighted mix of n-step returns, the last one taking the rest
    lam = 0.5
    n_step = lambda t, n: sum(0.8 ** k * r[0, t + k] for k in range(n)) + 0.8 ** n * vals[0, t + n]  # noqa: E731
    want = [sum((1 - lam) * lam ** (n - 1) * n_step(t, n) for n in range(1, 3 - t)) + lam ** (2 - t) * n_step(t, 3 - t)
            for t in range(3)]
    torch.testing.assert_close(v.lambda_returns(vals, r, lam), torch.tensor([want]))


def test_recentring_makes_the_value_translation_invariant():
    x, r = walks(E=4, T=3)
    s = x[:, 0]
    v = TerminalValue(3, recentre=(0,))
    plain = TerminalValue(3)
    plain.load_state_dict(v.state_dict())
    moved = s.clone()
    moved[:, 1:, 0] += 7.5
    torch.testing.assert_close(v(moved), v(s))
    assert not torch.allclose(plain(moved), plain(s))
    up = s.clone()
    up[:, 1:, 1] += 7.5      # y is not recentred
    assert not torch.allclose(v(up), v(s))
    flipped = s.clone()
    flipped[:, :, 3:7] *= -1  # q and -q are one orientation
    torch.testing.assert_close(v(flipped), v(s))
    assert default_recentre("cheetah") == (0,) and default_recentre("swimmer6") == (0, 1)
    assert default_recentre("dmc-walker") == (0,) and default_recentre("pendulum") == ()
    # the value is differentiable with respect to the states
    s = s.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(v(s).sum(), s)
    assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_files_round_trip_and_refusals(tmp_path):
    x, r = walks(E=4, T=5)
    v = TerminalValue(3, hidden=(8,), recentre=(0,), gamma=0.95)
    v.fit(x, r, rounds=1, steps=2)
    w = TerminalValue.load(v.save(tmp_path / "v.pt"))
    assert w.config() == v.config() and int(w.fitted) == 1
    torch.testing.assert_close(w(x[:, 2]), v(x[:, 2]))
    with pytest.raises(ValueFileError, match="no terminal-value file"):
        TerminalValue.load(tmp_path / "missing.pt")

    class Evil:
        def __reduce__(self):
            return (print, ("ran",))
    with open(tmp_path / "evil.pt", "wb") as f:
        pickle.dump({"format": "gnwarp-terminal-value", "x": Evil()}, f, protocol=2)
    with pytest.raises(ValueFileError, match="not a readable terminal-value file"):
        TerminalValue.load(tmp_path / "evil.pt")
    blob = torch.load(tmp_path / "v.pt", weights_only=True)
    cases = [(dict(format="other"), "not a terminal-value file"), (dict(version=9), "version 9"),
             (dict(config={"nbody": 3}), "config must hold"),
             (dict(config=dict(blob["config"], gamma=2.0)), "bad config: gamma"),
             (dict(state_dict={k: t for k, t in blob["state_dict"].items() if k != "scale"}), "keys"),
             (dict(state_dict=dict(blob["state_dict"], mean=torch.zeros(5))), "mean.*shape \\[26\\]"),
             (dict(state_dict=dict(blob["state_dict"], scale=torch.tensor(float("nan")))), "NaN")]
    for change, msg in cases:
        torch.save(dict(blob, **change), tmp_path / "bad.pt")
        with pytest.raises(ValueFileError, match=msg):
            TerminalValue.load(tmp_path / "bad.pt")
    # a weight changed after writing (finite, right shape) is caught by the checksum; a file from
    # before the checksum existed still loads
    name = next(k for k, t in blob["state_dict"].items() if t.is_floating_point() and t.numel() > 1)
    flipped = dict(blob["state_dict"], **{name: blob["state_dict"][name].clone().add_(1e-3)})
    torch.save(dict(blob, state_dict=flipped), tmp_path / "flipped.pt")
    with pytest.raises(ValueFileError, match="changed or damaged"):
        TerminalValue.load(tmp_path / "flipped.pt")
    torch.save({k: b for k, b in blob.items() if k != "sha256"}, tmp_path / "older.pt")
    torch.testing.assert_close(TerminalValue.load(tmp_path / "older.pt")(x[:, 2]), v(x[:, 2]))


def test_fit_from_closed_loop_episodes():
    task = get_task("pendulum-balance")
    env = make_env("pendulum", 3, backend="mujoco")
    q = np.array([[0.2], [-0.5], [1.0]])
    out = run_episodes(RandomPlanner(env.ctrlrange, 3, seed=0), env, task, 12, qpos0=q, qvel0=np.zeros((3, 1)))
    rew = episode_rewards(task, out["states"], out["actions"])
    assert rew.shape == (3, 12)
    torch.testing.assert_close(rew.sum(1), out["returns"])
    v = TerminalValue(2, hidden=(16,), gamma=0.9)
    hist = fit_terminal_value([out, out], task, v, rounds=2, steps=10, lr=3e-3)
    assert hist["td_error"][-1] < hist["td_error"][0]
    with pytest.raises(ValueError, match="run_episodes outputs"):
        fit_terminal_value([{"states": out["states"]}], task, v)
    with pytest.raises(ValueError, match="states must be \\[E, T\\+1, 2, 13\\]"):
        v.fit(out["states"][:, :, :1], rew)
