"""gnwarp.rl.slim: a run's copy without its replay buffer's transitions resumes bit for bit (the
buffer rebuilt by re-simulating its actions, checked by its digest); damaged or foreign copies
are refused (CPU, tiny)."""
from __future__ import annotations

import json

import pytest
import torch

from gnwarp.rl.config import RLConfig
from gnwarp.rl.replay import ReplayBuffer, ReplayError
from gnwarp.rl.run import run_rl
from gnwarp.rl.run_log import CHECKPOINT, RECORDS_FILE, load_checkpoint, save_checkpoint
from gnwarp.rl.slim import rebuild_buffer, slim_run
from tests.test_rl_run import TINY, _eval_returns, _tensors_equal


def test_actions_only_state_refuses_sampling_until_rebuilt():
    buf = ReplayBuffer(12, obs_dim=2, action_dim=1, num_envs=2)
    g = torch.Generator().manual_seed(0)
    for t in range(7):   # wraps: 6 rows of 2 envs
        buf.add(torch.full((2, 2), float(t)), torch.full((2, 1), t / 10), torch.ones(2), torch.full((2, 2), t + 1.0),
                torch.zeros(2, dtype=torch.bool), torch.tensor([False, t == 6]))
    d = buf.digest()
    slim = buf.state_dict(actions_only=True)
    assert set(slim) >= {"action", "digest"} and "obs" not in slim and slim["digest"] == d
    other = ReplayBuffer(12, obs_dim=2, action_dim=1, num_envs=2)
    other.load_state_dict(slim)
    assert other.pending_digest == d and torch.equal(other.action, buf.action) and not other.obs.any()
    with pytest.raises(ReplayError, match="actions only"):
        other.sample(4, g)
    with pytest.raises(ReplayError, match="actions only"):
        other.digest()
    for row in range(buf.rows):   # what a rebuild writes: then the digest is the saved one
        other.put_rows([row], buf.obs[row:row + 1], buf.action[row:row + 1], buf.reward[row:row + 1],
                       buf.next_obs[row:row + 1], buf.terminated[row:row + 1], buf.truncated[row:row + 1])
    other.pending_digest = None
    assert other.digest() == d
    other.reward[3, 1] += 1e-7                    # one changed bit of one transition: another digest
    assert other.digest() != d
    with pytest.raises(ReplayError, match="no valid digest"):
        ReplayBuffer(12, obs_dim=2, action_dim=1, num_envs=2).load_state_dict({**slim, "digest": "xyz"})


@pytest.mark.parametrize("ahead, buffer_size", [(False, 1000), (True, 20)])
def test_slim_copy_resumes_bit_for_bit(tmp_path, ahead, buffer_size):
    """A run stopped at 40 env steps, copied slim, resumed to 80 in the copy: the same agent,
    buffer, loop state and evaluations as the run that went on in its own folder (acting ahead,
    a buffer of one round that has wrapped: rebuilt here, in this process)."""
    cfg = dict(TINY, agent="ddpg", env_steps=80, act_ahead=ahead, buffer_size=buffer_size)
    assert run_rl(RLConfig(**cfg, out=str(tmp_path / "run"), chunk=25))["env_steps"] == 40
    slim_run(tmp_path / "run", tmp_path / "slim")
    full_mb, slim_mb = ((tmp_path / f / CHECKPOINT).stat().st_size for f in ("run", "slim"))
    assert slim_mb < full_mb
    ck = load_checkpoint(tmp_path / "slim" / CHECKPOINT)
    assert ck["buffer"]["actions_only"] and "obs" not in ck["buffer"] and ck["config"]["out"] == str(tmp_path / "slim")
    assert (ck["buffer"]["added"], ck["buffer"]["filled"]) == ((20, 10) if buffer_size == 20 else (20, 20))
    assert json.loads((tmp_path / "slim" / "config.json").read_text())["out"] == str(tmp_path / "slim")
    assert (tmp_path / "slim" / RECORDS_FILE).read_text() == (tmp_path / "run" / RECORDS_FILE).read_text()
    run_rl(RLConfig(**cfg, out=str(tmp_path / "run")))
    assert run_rl(RLConfig(**cfg, out=str(tmp_path / "slim")))["env_steps"] == 80
    a, b = (load_checkpoint(tmp_path / f / CHECKPOINT) for f in ("run", "slim"))
    for key in ("agent", "buffer", "generator", "rng", "collector"):
        _tensors_equal(a[key], b[key], key)
    assert _eval_returns(tmp_path / "run") == _eval_returns(tmp_path / "slim")


def test_a_slim_copy_that_does_not_rebuild_is_refused(tmp_path):
    """An action changed in the copy (or another simulator) rebuilds another buffer: refused,
    naming the digest, and nothing trains; a copy of a copy, a full folder and no run refused."""
    cfg = dict(TINY, agent="ddpg", env_steps=80)
    run_rl(RLConfig(**cfg, out=str(tmp_path / "run"), chunk=25))
    slim_run(tmp_path / "run", tmp_path / "slim")
    ck = load_checkpoint(tmp_path / "slim" / CHECKPOINT)
    ck["buffer"]["action"][5, 1, 0] += 0.25
    save_checkpoint(tmp_path / "slim" / CHECKPOINT, ck)
    with pytest.raises(ReplayError, match="rebuilt replay buffer differs from the saved one"):
        run_rl(RLConfig(**cfg, out=str(tmp_path / "slim")))
    assert load_checkpoint(tmp_path / "slim" / CHECKPOINT)["agent"]["env_steps"] == 40   # not trained on
    with pytest.raises(ValueError, match="slim copy already"):
        slim_run(tmp_path / "slim", tmp_path / "again")
    with pytest.raises(ValueError, match="new or empty folder"):
        slim_run(tmp_path / "run", tmp_path / "slim")
    with pytest.raises(FileNotFoundError, match="no gnwarp rl run"):
        slim_run(tmp_path / "nothing", tmp_path / "x")


def test_rebuild_refuses_a_buffer_of_partial_rounds():
    buf = ReplayBuffer(40, obs_dim=3, action_dim=1, num_envs=2)
    buf.added, buf.filled, buf.ptr = 15, 15, 15 % buf.rows   # 15 steps: not whole rounds of 10
    buf.pending_digest = "0" * 64

    def no_env():
        raise AssertionError("no env is made for a buffer that cannot be rebuilt")
    with pytest.raises(ReplayError, match="not whole rounds"):
        rebuild_buffer(buf, no_env, lambda r: r, 10)
    assert buf.pending_digest == "0" * 64


def test_rounds_rebuilt_in_worker_processes_give_the_buffer(tmp_path):
    """Rounds re-simulated in two worker processes (each with its own training env) give the
    saved buffer, on a buffer that has wrapped (in-process rebuilds: the resume tests above)."""
    workers = 2
    from functools import partial

    from gnwarp.rl.run import round_seed, training_env
    cfg = RLConfig(**{**TINY, "agent": "ddpg", "buffer_size": 60}, out=str(tmp_path / "w"))   # 3 rounds kept of 5
    run_rl(cfg)
    ck = load_checkpoint(tmp_path / "w" / CHECKPOINT)
    full = ReplayBuffer(60, obs_dim=ck["buffer"]["obs_dim"], action_dim=1, num_envs=2)
    full.load_state_dict(ck["buffer"])
    assert full.added == 50 and full.filled == 30 and full.ptr == 20   # wrapped
    slim = ReplayBuffer(60, obs_dim=full.obs_dim, action_dim=1, num_envs=2)
    slim.load_state_dict(full.state_dict(actions_only=True))
    assert rebuild_buffer(slim, partial(training_env, cfg), partial(round_seed, cfg.seed), 10, workers=workers) > 0
    assert slim.pending_digest is None
    _tensors_equal(slim.state_dict(), full.state_dict(), "buffer")


def test_cli_slim_writes_a_copy_that_resumes(tmp_path, capsys):
    from gnwarp.cli import main
    out, dest = tmp_path / "cli", tmp_path / "cli-slim"
    argv = ["rl", "--task", "pendulum-balance", "--agent", "svg0", "--observation", "bodies", "--num-envs", "2",
            "--episode-steps", "10", "--env-steps", "60", "--hidden", "16", "--batch-size", "8", "--start-steps",
            "20", "--update-after", "20", "--eval-every", "40", "--eval-episodes", "2", "--device", "cpu",
            "--backend", "mujoco", "--video-episodes", "0", "--no-tensorboard", "-q", "-o", str(out), "--chunk", "20"]
    assert main(argv) == 0
    capsys.readouterr()
    assert main(["rl", "-o", str(out), "--slim", str(dest)]) == 0
    assert f"wrote {dest}" in capsys.readouterr().out
    assert main(["check", str(dest)]) == 0
    assert "a slim copy: its replay buffer's transitions are rebuilt on resuming" in capsys.readouterr().out
    assert main(["rl", "-o", str(dest), "-q"]) == 0
    assert "60 of 60 env steps (done)" in capsys.readouterr().out
    assert main(["rl", "-o", str(out), "--slim", str(dest)]) == 2   # not into a folder that holds a run
    assert "new or empty folder" in capsys.readouterr().err
    # training settings with --slim would be ignored: refused by name, nothing written
    assert main(["rl", "-o", str(out), "--slim", str(tmp_path / "other"), "--env-steps", "80", "--set",
                 "agent_settings.gamma=0.9"]) == 2
    err = capsys.readouterr().err
    assert "--env-steps, --set would be ignored" in err and not (tmp_path / "other").exists()


def test_svg1_slim_copy_on_the_suites_swimmer_resumes_bit_for_bit(tmp_path):
    """SVG(1) on swimmer6 with the suite's observation (computed from body states): the copy made
    after the model's first updates rebuilds the same transitions and trains on identically."""
    pytest.importorskip("dm_control")
    cfg = dict(task="swimmer6", agent="svg1", num_envs=2, episode_steps=4, env_steps=24, hidden=(8,),
               model_hidden=(8,), batch_size=4, start_steps=4, update_after=8, buffer_size=100, eval_every=8,
               eval_episodes=2, progress=False, device="cpu", backend="mujoco", tensorboard=False, video_episodes=0)
    run_rl(RLConfig(**cfg, out=str(tmp_path / "run"), chunk=16))
    slim_run(tmp_path / "run", tmp_path / "slim")
    run_rl(RLConfig(**cfg, out=str(tmp_path / "run")))
    run_rl(RLConfig(**cfg, out=str(tmp_path / "slim")))
    a, b = (load_checkpoint(tmp_path / f / CHECKPOINT) for f in ("run", "slim"))
    assert a["agent"]["env_steps"] == 24
    for key in ("agent", "buffer", "generator", "collector"):
        _tensors_equal(a[key], b[key], key)
    assert _eval_returns(tmp_path / "run") == _eval_returns(tmp_path / "slim")


def test_a_buffer_that_keeps_part_of_a_round_is_refused_at_slim_time(tmp_path):
    """25 rows a ring with 10-step episodes: once wrapped, the oldest kept round lost its first
    steps' actions, so a copy could never rebuild it; slim_run says so before anything is written."""
    run_rl(RLConfig(**{**TINY, "agent": "ddpg", "buffer_size": 50}, out=str(tmp_path / "run")))
    with pytest.raises(ValueError, match="not whole rounds of 10 steps"):
        slim_run(tmp_path / "run", tmp_path / "slim")
    assert not (tmp_path / "slim").exists()


def test_slim_copy_is_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """A copy that fails while written leaves no folder (not a half copy the next try refuses as
    "not empty"); a file where the folder should go is refused by name."""
    from gnwarp.rl import slim
    run = tmp_path / "run"
    run_rl(RLConfig(**{**TINY, "agent": "ddpg", "env_steps": 40}, out=str(run)))

    def broken(path, state):
        raise OSError("disk full")
    monkeypatch.setattr(slim, "save_checkpoint", broken)
    with pytest.raises(OSError, match="disk full"):
        slim_run(run, tmp_path / "copy")
    assert not (tmp_path / "copy").exists()
    monkeypatch.undo()
    assert (slim_run(run, tmp_path / "copy") / CHECKPOINT).is_file()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match="new or empty folder"):
        slim_run(run, tmp_path / "afile")
