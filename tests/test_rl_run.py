"""The reinforcement-learning run (gnwarp.rl.run, ``gnwarp rl``): its files, exact resume across
calls, refused settings, the command line."""
import csv
import json
import warnings

import numpy as np
import pytest
import torch

from gnwarp.eval.records import read_records
from gnwarp.rl.config import RLConfig
from gnwarp.rl.run import run_rl
from gnwarp.rl.run_log import (CHECKPOINT, LOG_FILE, RECORDS_FILE, RLCheckpointError, load_checkpoint,
                               save_checkpoint)
from gnwarp.validation import ConfigError

warnings.filterwarnings("ignore", message=".*glfw.*")

TINY = dict(task="pendulum-balance", agent="svg0", observation="bodies", num_envs=2, episode_steps=10, env_steps=100,
            hidden=(16,), buffer_size=1000, batch_size=8, start_steps=20, update_after=20, eval_every=40, eval_episodes=3,
            progress=False, device="cpu", backend="mujoco", tensorboard=False, video_episodes=0)


def _tensors_equal(a, b, where=""):
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), where
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _tensors_equal(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _tensors_equal(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def _eval_returns(folder):
    return [(r.env_steps, r.returns) for r in read_records(folder / RECORDS_FILE)]


def test_tiny_run_writes_checkpoint_records_and_log(tmp_path):
    r = run_rl(RLConfig(**TINY, out=str(tmp_path / "a")))
    assert r["stop"] == "done" and r["env_steps"] == 100 and r["rounds"] == 5
    assert r["updates"] == 100 - 20 + 2    # one update per env step from the step reaching update_after
    out = tmp_path / "a"
    assert (out / CHECKPOINT).is_file() and (out / "config.json").is_file()
    recs = read_records(out / RECORDS_FILE)
    # before training, at the first episode end past each multiple of eval_every, at the end
    assert [x.env_steps for x in recs] == [0, 40, 80, 100]
    assert all(x.experiment == "rl" and x.planner == "policy" and x.episodes == 3 and x.episode_steps == 10
               and x.config["agent"] == "svg0" and x.config["networks"] == "mlp"
               and x.config["update_compile"] == "none" for x in recs)   # auto: eager on the CPU
    rows = list(csv.DictReader(open(out / LOG_FILE)))
    assert [int(x["env_steps"]) for x in rows] == [20, 40, 60, 80, 100]
    assert rows[-1]["eval_median"] and not rows[0]["eval_median"] and float(rows[-1]["q_loss"]) >= 0


def test_video_of_the_last_evaluation(tmp_path):
    import imageio.v3 as iio
    from gnwarp.rl.run import evaluate_policy
    cfg = RLConfig(**{**TINY, "video_episodes": 2, "video_steps": 6, "renderer": "matplotlib", "env_steps": 40},
                   out=str(tmp_path / "v"))
    r = run_rl(cfg)
    frames = iio.imread(r["video"], index=None)
    from gnwarp.rl.run import build_run
    parts = build_run(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "w")))
    stride = max(1, round(1 / (25 * parts["env"].system.dt)))     # animate's frame stride at 25 fps at most
    assert r["video"] == str(tmp_path / "v" / "video.gif") and frames.shape[0] == len(range(0, 7, stride))
    assert sorted(p.name for p in (tmp_path / "v").iterdir() if p.name.startswith(".")) == []   # no leftovers
    # the states are the evaluation's episodes: the first envs of a batched evaluation
    returns, states = evaluate_policy(parts["agent"], parts["eval_env"], 5, keep=2, keep_steps=4)
    assert states.shape == (2, 5, parts["env"].system.nbody, 13) and len(returns) == 3
    again, full = evaluate_policy(parts["agent"], parts["eval_env"], 5, keep=3)
    assert again == returns and full.shape[1] == 11 and torch.equal(full[:2, :5], states)
    parts["eval_env"].reset(seed=5)             # the first state is the episode's reset state
    assert torch.equal(full[:, 0], parts["eval_env"].body_states[:3].double().cpu())
    assert not torch.equal(full[:, -1], full[:, 0])
    with pytest.raises(ValueError, match="keep and keep_steps must be >= 0"):
        evaluate_policy(parts["agent"], parts["eval_env"], 5, keep=-1)
    parts["env"].close()
    parts["eval_env"].close()
    assert not run_rl(RLConfig(**{**TINY, "env_steps": 40, "video_episodes": 0}, out=str(tmp_path / "n")))["video"]


def test_a_finished_run_killed_in_its_video_writes_it_on_the_next_call(tmp_path):
    """A call killed while writing the final video (checkpoint saved as done, no video.gif, a
    temporary left): the next call writes the same video, adds no record, and removes the
    killed write's temporary."""
    import subprocess
    import sys

    import imageio.v3 as iio
    cfg = RLConfig(**{**TINY, "video_episodes": 1, "video_steps": 6, "renderer": "matplotlib", "env_steps": 40},
                   out=str(tmp_path / "v"))
    first = run_rl(cfg)
    frames = iio.imread(first["video"], index=None)
    records = (tmp_path / "v" / "records.jsonl").read_text()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    (tmp_path / "v" / "video.gif").unlink()
    (tmp_path / "v" / f".video.gif.tmp-{dead}").write_bytes(b"GIF89a half")   # the killed write's
    again = run_rl(cfg)
    assert again["stop"] == "done" and again["rounds"] == first["rounds"] and again["video"]
    assert np.array_equal(iio.imread(again["video"], index=None), frames)
    assert (tmp_path / "v" / "records.jsonl").read_text() == records
    assert not [p.name for p in (tmp_path / "v").iterdir() if p.name.startswith(".video")]
    third = run_rl(cfg)   # done, with its video: nothing evaluated or written again
    assert third["video"] is None and (tmp_path / "v" / "video.gif").exists()


@pytest.mark.parametrize("ahead", [False, True])
def test_resume_equals_uninterrupted_bit_for_bit(tmp_path, ahead):
    cfg = dict(TINY, agent="ddpg", env_steps=80, act_ahead=ahead)
    run_rl(RLConfig(**cfg, out=str(tmp_path / "whole")))
    first = run_rl(RLConfig(**cfg, out=str(tmp_path / "parts"), chunk=25))   # rounds to 2 whole rounds
    assert first["stop"] == "chunk" and first["env_steps"] == 40
    second = run_rl(RLConfig(**cfg, out=str(tmp_path / "parts")))
    assert second["stop"] == "done" and second["env_steps"] == 80
    a = load_checkpoint(tmp_path / "whole" / CHECKPOINT)
    b = load_checkpoint(tmp_path / "parts" / CHECKPOINT)
    for key in ("agent", "buffer", "generator", "rng", "collector"):
        _tensors_equal(a[key], b[key], key)
    assert _eval_returns(tmp_path / "whole") == _eval_returns(tmp_path / "parts")
    rows = [list(csv.DictReader(open(tmp_path / f / LOG_FILE))) for f in ("whole", "parts")]
    assert [r["q_loss"] for r in rows[0]] == [r["q_loss"] for r in rows[1]]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_acting_ahead_with_recorded_updates_equals_eager_cuda(tmp_path):
    """On CUDA, acting ahead (the env stepped while the recorded updates run) gives what eager
    updates in the same order give."""
    params = []
    for graph in (False, True):
        cfg = RLConfig(**{**TINY, "agent": "ddpg", "device": "cuda", "act_ahead": True, "cuda_graph": graph},
                       out=str(tmp_path / f"g{graph}"))
        assert run_rl(cfg)["env_steps"] == 100
        params.append(load_checkpoint(tmp_path / f"g{graph}" / CHECKPOINT)["agent"]["policy"])
    assert params[0].keys() == params[1].keys()
    for k in params[0]:
        torch.testing.assert_close(params[0][k], params[1][k], rtol=1e-5, atol=1e-6)


def test_run_saved_before_a_config_key_existed_resumes_bit_for_bit(tmp_path):
    """A run folder written before ``act_ahead`` existed (its config.json, the checkpoint's config
    and agent settings lack the key) resumes as the key's default, equal to an uninterrupted run."""
    cfg = dict(TINY, agent="ddpg", env_steps=80)
    run_rl(RLConfig(**cfg, out=str(tmp_path / "whole")))
    out = tmp_path / "old"
    run_rl(RLConfig(**cfg, out=str(out), chunk=25))
    saved = json.loads((out / "config.json").read_text())
    del saved["act_ahead"]
    (out / "config.json").write_text(json.dumps(saved))
    ck = load_checkpoint(out / CHECKPOINT)
    del ck["config"]["act_ahead"], ck["agent"]["settings"]["act_ahead"]
    save_checkpoint(out / CHECKPOINT, ck)
    assert run_rl(RLConfig(**cfg, out=str(out)))["env_steps"] == 80
    a, b = load_checkpoint(tmp_path / "whole" / CHECKPOINT), load_checkpoint(out / CHECKPOINT)
    for key in ("agent", "buffer", "collector"):
        _tensors_equal(a[key], b[key], key)
    with pytest.raises(ConfigError, match="act_ahead: differs"):   # the default is what it was run with
        run_rl(RLConfig(**{**cfg, "env_steps": 100, "act_ahead": True}, out=str(out)))


def test_killed_run_drops_rows_past_its_checkpoint(tmp_path):
    out = tmp_path / "k"
    run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(out)))
    saved = (out / CHECKPOINT).read_bytes()
    run_rl(RLConfig(**{**TINY, "env_steps": 80}, out=str(out)))
    (out / CHECKPOINT).write_bytes(saved)          # as if killed after the rows of 60 and 80 steps
    run_rl(RLConfig(**{**TINY, "env_steps": 80}, out=str(out)))
    assert [x.env_steps for x in read_records(out / RECORDS_FILE)] == [0, 40, 80]
    assert [int(x["env_steps"]) for x in csv.DictReader(open(out / LOG_FILE))] == [20, 40, 60, 80]


def test_budget_stops_at_a_round_end(tmp_path):
    r = run_rl(RLConfig(**TINY, out=str(tmp_path / "b"), budget_seconds=1e-3))
    assert r["stop"] == "budget" and r["env_steps"] == 20 and r["rounds"] == 1


def test_budget_keeps_time_for_the_calls_video(tmp_path, monkeypatch):
    """The budget counts the call's end: the video's time, guessed until a call has timed it."""
    import time

    import gnwarp.rl.run as run_mod

    def slow_video(path, *a, **k):
        time.sleep(0.3)
        path.write_bytes(b"GIF89a")
        return path
    monkeypatch.setattr(run_mod, "write_video", slow_video)
    monkeypatch.setattr(run_mod, "VIDEO_SECONDS_GUESS", 1e3)
    cfg = dict(TINY, video_episodes=1, video_steps=5, out=str(tmp_path / "v"), budget_seconds=60.0)
    r = run_rl(RLConfig(**cfg))     # the guess (1000 s) leaves no second round within 60 s
    assert r["stop"] == "budget" and r["rounds"] == 1 and r["video"]
    timing = json.loads((tmp_path / "v" / "timing.json").read_text())
    # the video's time, its 0.3-s sleep included, per step; the checkpoint's
    assert timing["video_seconds_per_step"] >= 0.3 / 5 and timing["checkpoint_seconds"] > 0
    r = run_rl(RLConfig(**cfg))     # the time measured (0.3 s for 5 steps) does
    assert r["stop"] == "done" and r["rounds"] == 5
    (tmp_path / "v" / "timing.json").write_text('{"video_seconds_per_step": "soon"}')   # unreadable: guessed
    r = run_rl(RLConfig(**{**cfg, "env_steps": 140}))
    assert r["stop"] == "budget" and r["rounds"] == 6


def test_a_failed_video_times_nothing(tmp_path, monkeypatch):
    import gnwarp.rl.run as run_mod

    def broken(*a, **k):
        raise RuntimeError("no display")
    monkeypatch.setattr(run_mod, "write_video", broken)
    with pytest.warns(RuntimeWarning, match="no video written"):
        r = run_rl(RLConfig(**dict(TINY, video_episodes=1, video_steps=5, env_steps=40), out=str(tmp_path / "f")))
    timing = json.loads((tmp_path / "f" / "timing.json").read_text())
    assert r["video"] is None and "video_seconds_per_step" not in timing and timing["checkpoint_seconds"] > 0
    assert timing["video_failed"] is True
    # the finished run's next call does not evaluate again for a video that failed
    monkeypatch.setattr(run_mod, "evaluate_policy", lambda *a, **k: pytest.fail("evaluated again"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = run_rl(RLConfig(**dict(TINY, video_episodes=1, video_steps=5, env_steps=40), out=str(tmp_path / "f")))
    assert again["stop"] == "done" and again["video"] is None


def test_svg1_gn_on_swimmer6(tmp_path):
    pytest.importorskip("dm_control")
    cfg = RLConfig(task="swimmer6", agent="svg1", networks="gn", gn_impl="torch", num_envs=2, episode_steps=6,
                   env_steps=12, latent=8, hidden=(8,), model_hidden=(8,), blocks=1, batch_size=4, start_steps=6,
                   update_after=8, buffer_size=100, eval_every=12, eval_episodes=2, progress=False, device="cpu", backend="mujoco",
                   tensorboard=False, video_episodes=0, out=str(tmp_path / "s"))
    r = run_rl(cfg)
    assert r["env_steps"] == 12 and r["updates"] == 12 - 8 + 2
    ck = load_checkpoint(tmp_path / "s" / CHECKPOINT)
    model = ck["agent"]["model"]
    assert float(model["delta_std"].min()) > 0 and not torch.all(model["obs_std"] == 1)   # normalized from data
    recs = read_records(tmp_path / "s" / RECORDS_FILE)
    assert recs[-1].task == "dmc-swimmer-swimmer6" and recs[-1].config["networks"] == "gn"


@pytest.mark.parametrize("kw, key, words", [
    (dict(agent="td3"), "agent", "unknown agent"),
    (dict(agent="svg6"), "agent", "svg0 .. svg5"),
    (dict(agent="svg-1"), "agent", "N = -1"),
    (dict(eval_episodes=0), "eval_episodes", ""),
    (dict(networks="gn"), "networks", "observation"),
    (dict(agent="svg1"), "observation", "ObservationReward"),
    (dict(agent_settings={"gama": 0.9}), "agent_settings", "gama"),
    (dict(agent_settings={"seed": 3}), "agent_settings.seed", ""),
    (dict(agent_settings={"gamma": 2.0}), "agent_settings.gamma", "<= 1"),   # named as the run spells it
    (dict(utd=1e308), "utd", "<= 1000"),            # int(inf) owed updates: a traceback, saved in the folder
    (dict(seed=10**20), "seed", "9223372036854775807"),
])
def test_bad_settings_refused(kw, key, words):
    with pytest.raises(ConfigError) as e:
        RLConfig(**{**TINY, **kw})
    assert e.value.path == key and words in str(e.value)


def test_svgn_on_a_task_without_observation_reward_refused(tmp_path):
    cfg = RLConfig(**{**TINY, "agent": "svg1", "observation": "dmc"}, out=str(tmp_path / "x"))
    with pytest.raises(ConfigError, match="observation"):
        run_rl(cfg)
    assert not (tmp_path / "x").exists()


def test_resume_with_other_settings_refused(tmp_path):
    run_rl(RLConfig(**{**TINY, "env_steps": 20}, out=str(tmp_path / "r")))
    with pytest.raises(ConfigError, match="batch_size"):
        run_rl(RLConfig(**{**TINY, "batch_size": 16}, out=str(tmp_path / "r")))


def test_a_folder_whose_records_starting_over_would_lose_is_refused(tmp_path):
    """No checkpoint to resume: records of another experiment, or evaluations past step 0 (the
    run's checkpoint is gone), stay as they are and the run is refused; a run killed between its
    step-0 evaluation and first checkpoint starts over."""
    from gnwarp.eval.records import ResultRecord, write_records
    foreign = tmp_path / "f"
    foreign.mkdir()
    write_records(foreign / RECORDS_FILE, [ResultRecord(experiment="mpc", task="pendulum-balance", planner="gradient",
                                                        dynamics="learned", episodes=1, episode_steps=5,
                                                        returns=[1.0])])
    before = (foreign / RECORDS_FILE).read_bytes()
    with pytest.raises(ConfigError, match="experiment 'mpc'"):
        run_rl(RLConfig(**TINY, out=str(foreign)))
    assert (foreign / RECORDS_FILE).read_bytes() == before
    lost = tmp_path / "l"
    run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(lost)))
    (lost / CHECKPOINT).unlink()
    before = (lost / RECORDS_FILE).read_bytes()
    with pytest.raises(ConfigError, match="up to 40 env steps but no checkpoint"):
        run_rl(RLConfig(**{**TINY, "agent": "ddpg"}, out=str(lost)))
    assert (lost / RECORDS_FILE).read_bytes() == before
    assert json.loads((lost / "config.json").read_text())["agent"] == "svg0"   # not rewritten
    early = tmp_path / "e"
    run_rl(RLConfig(**{**TINY, "env_steps": 20}, out=str(early)))
    (early / CHECKPOINT).unlink()
    write_records(early / RECORDS_FILE, [r for r in read_records(early / RECORDS_FILE) if r.env_steps == 0],
                  append=False)   # as if killed after the step-0 evaluation, before the first checkpoint
    assert run_rl(RLConfig(**{**TINY, "env_steps": 20}, out=str(early)))["stop"] == "done"


def test_gnwarp_check_reads_a_run_folder_as_a_run(tmp_path, capsys):
    """``gnwarp check RUN``: a run's checkpoint.pt read as a resume reads it (not a model
    checkpoint missing model.pt); a damaged one is an error line and exit 1."""
    from gnwarp.cli import main
    out = tmp_path / "c"
    run_rl(RLConfig(**{**TINY, "env_steps": 20}, out=str(out)))
    assert main(["check", str(out)]) == 0
    assert "a gnwarp rl run; checkpoint.pt read and verified" in capsys.readouterr().out
    raw = bytearray((out / CHECKPOINT).read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (out / CHECKPOINT).write_bytes(bytes(raw))
    assert main(["check", str(out)]) == 1
    assert capsys.readouterr().out.startswith("error:")


def test_compiled_run_trains_like_the_eager_one_and_may_change_its_compile_setting(tmp_path):
    """``torch_compile`` traces the update's losses (aot_eager: no compiler needed) with the same
    numbers as eager updates here; a resumed run may change it (as it may change its device: the
    rest of the run rounds as the new setting does)."""
    eager = run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "e"), torch_compile="none"))
    comp = run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "c"), torch_compile="aot_eager"))
    assert comp["updates"] == eager["updates"] == 22
    assert _eval_returns(tmp_path / "c") == _eval_returns(tmp_path / "e")
    more = run_rl(RLConfig(**TINY, out=str(tmp_path / "c"), torch_compile="none"))
    assert more["env_steps"] == TINY["env_steps"] > 40
    assert json.loads((tmp_path / "c" / "config.json").read_text())["torch_compile"] == "none"
    # each evaluation names the update of the call that wrote it: compiled, then eager after the resume
    assert [r.config["update_compile"] for r in read_records(tmp_path / "c" / RECORDS_FILE)] == [
        "aot_eager", "aot_eager", "none", "none"]


def test_auto_compiles_mlp_updates_on_cuda_with_triton_only(monkeypatch):
    from gnwarp.rl.run import compile_backend
    import torch.utils._triton as triton_check
    cfg = RLConfig(**TINY, out="unused")
    assert cfg.torch_compile == "auto" and compile_backend(cfg, "cpu") == "none"
    monkeypatch.setattr(triton_check, "has_triton", lambda: True)
    assert compile_backend(cfg, "cuda") == "inductor"
    assert compile_backend(RLConfig(**{**TINY, "networks": "gn", "observation": "dmc", "task": "swimmer6"},
                                    out="unused"), "cuda") == "none"
    assert compile_backend(RLConfig(**TINY, out="unused", torch_compile="none"), "cuda") == "none"
    assert compile_backend(RLConfig(**TINY, out="unused", torch_compile="aot_eager"), "cpu") == "aot_eager"
    monkeypatch.setattr(triton_check, "has_triton", lambda: False)
    assert compile_backend(cfg, "cuda") == "none"


def test_a_failing_compiler_falls_back_to_eager_only_where_asked(monkeypatch):
    """``compile_update(fallback=True)`` (``torch_compile`` "auto"): a compiler error at the second
    update warns and the losses stay eager with the same values; without it the error surfaces."""
    import warnings

    import torch._dynamo.exc as dynamo_exc
    from gnwarp.rl.agents import _EagerFirst

    def broken(fn, **kw):
        def call(*a, **k):
            raise dynamo_exc.BackendCompilerFailed(lambda *a: None, RuntimeError("no triton"), None)
        return call
    monkeypatch.setattr(torch, "compile", broken)
    f = _EagerFirst(lambda x: x * 2, "inductor", fallback=True)
    assert f(torch.tensor(3.0)) == 6.0
    with pytest.warns(UserWarning, match="runs eagerly: BackendCompilerFailed"):
        assert f(torch.tensor(4.0)) == 8.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert f(torch.tensor(5.0)) == 10.0          # eager from then on, no more warnings
    g = _EagerFirst(lambda x: x * 2, "inductor")
    g(torch.tensor(1.0))
    with pytest.raises(dynamo_exc.BackendCompilerFailed):
        g(torch.tensor(1.0))
    monkeypatch.undo()
    # a backend whose forward compiles but whose backward does not: the failure shows at the
    # compiling call (not at a later backward()), and the loss goes on eagerly with its gradient
    from torch._dynamo.backends.common import aot_autograd

    def no_backward(gm, example_inputs):
        raise RuntimeError("no backward compiler here")
    half = aot_autograd(fw_compiler=lambda gm, ex: gm, bw_compiler=no_backward)
    torch._dynamo.reset()
    w = torch.tensor([1.5, -2.0], requires_grad=True)
    k = _EagerFirst(lambda x: (w * x).square().sum(), half, fallback=True)
    k(torch.ones(2))
    with pytest.warns(UserWarning, match="runs eagerly"):
        loss = k(torch.tensor([2.0, 3.0]))
    loss.backward()
    assert k.fell_back and torch.allclose(w.grad, 2 * w.detach() * torch.tensor([4.0, 9.0]))
    h = _EagerFirst(lambda x: x.undefined_method(), "inductor", fallback=True)
    with pytest.raises(AttributeError):              # the function's own error, at its eager first call
        h(torch.tensor(1.0))


def test_cli_runs_and_resumes(tmp_path, capsys):
    from gnwarp.cli import main
    out = str(tmp_path / "cli")
    argv = ["rl", "--task", "pendulum-balance", "--agent", "svg0", "--observation", "bodies", "--num-envs", "2",
            "--episode-steps", "10", "--env-steps", "60", "--hidden", "16", "--batch-size", "8", "--start-steps",
            "20", "--update-after", "20", "--eval-every", "40", "--eval-episodes", "2", "--device", "cpu",
            "--backend", "mujoco", "--chunk", "20", "--no-tensorboard", "--buffer-size", "1000", "-q", "-o", out, "--set", "agent_settings.gamma=0.9",
            "--video-episodes", "0"]
    assert main(argv) == 0
    assert "run again" in capsys.readouterr().out
    assert main(["rl", "-o", out, "-q"]) == 0                  # the folder's config, to its end
    recs = read_records(tmp_path / "cli" / RECORDS_FILE)
    assert recs[-1].env_steps == 60 and recs[-1].config["agent_settings"]["gamma"] == 0.9
    assert json.loads((tmp_path / "cli" / "config.json").read_text())["chunk"] is None
    assert main(["rl", "-o", out, "--agent", "td3"]) == 2
    assert "unknown agent" in capsys.readouterr().err


def test_svg1_resume_equals_uninterrupted(tmp_path):
    pytest.importorskip("dm_control")
    # the first chunk ends before update_after: the model is normalized after the resume
    cfg = dict(task="swimmer6", agent="svg1", num_envs=2, episode_steps=4, env_steps=24, hidden=(8,),
               model_hidden=(8,), batch_size=4, start_steps=4, update_after=12, buffer_size=100, eval_every=8,
               eval_episodes=2, progress=False, device="cpu", backend="mujoco", tensorboard=False, video_episodes=0)
    run_rl(RLConfig(**cfg, out=str(tmp_path / "whole")))
    assert run_rl(RLConfig(**cfg, out=str(tmp_path / "parts"), chunk=8))["stop"] == "chunk"
    run_rl(RLConfig(**cfg, out=str(tmp_path / "parts")))
    a, b = (load_checkpoint(tmp_path / f / CHECKPOINT) for f in ("whole", "parts"))
    assert a["agent"]["updates"] == 24 - 12 + 2
    _tensors_equal(a["agent"], b["agent"], "agent")
    assert not torch.all(a["agent"]["model"]["obs_std"] == 1)
    assert _eval_returns(tmp_path / "whole") == _eval_returns(tmp_path / "parts")


def test_rl_help_loads_no_heavy_module():
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    code = ("import contextlib, io, sys\nfrom gnwarp.cli import main\nwith contextlib.redirect_stdout(io.StringIO()):\n"
            "    try:\n        main(['rl', '--help'])\n    except SystemExit:\n        pass\n"
            "print(' '.join(m for m in ('torch', 'warp', 'mujoco') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0 and out.stdout.strip() == "", out.stderr


def test_failed_video_warns_and_keeps_the_run(tmp_path, monkeypatch):
    import gnwarp.rl.run as run_mod

    def broken(*a, **k):
        raise RuntimeError("no OpenGL here")
    monkeypatch.setattr(run_mod, "write_video", broken)
    with pytest.warns(RuntimeWarning, match="no video written.*no OpenGL here"):
        r = run_rl(RLConfig(**{**TINY, "env_steps": 40, "video_episodes": 1}, out=str(tmp_path / "f")))
    assert r["stop"] == "done" and r["video"] is None and (tmp_path / "f" / CHECKPOINT).is_file()


def test_checkpoint_runs_no_code_and_detects_corruption(tmp_path):
    import os
    from gnwarp.rl.run_log import save_checkpoint
    path = tmp_path / "c.pt"
    save_checkpoint(path, {"a": torch.arange(5), "n": np.arange(3), "t": (1, "x", None)})
    back = load_checkpoint(path)
    assert torch.equal(back["a"], torch.arange(5)) and torch.equal(back["n"], torch.arange(3)) and back["t"] == (1, "x", None)
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF                       # one flipped byte inside the payload
    path.write_bytes(bytes(raw))
    with pytest.raises(RLCheckpointError, match="is corrupt .its checksum"):
        load_checkpoint(path)
    for outer, words in (({"format": "gnwarp-rl-checkpoint", "version": 99}, "version 99 rl checkpoint"),
                         ({"format": "gnwarp-rl-checkpoint", "version": 1, "sha256": "x", "payload": torch.zeros(3)},
                          "payload is missing or malformed")):
        torch.save(outer, tmp_path / "other.pt")
        with pytest.raises(RLCheckpointError, match=words):
            load_checkpoint(tmp_path / "other.pt")

    class Boom:                                      # a pickle that would run code when loaded
        def __reduce__(self):
            return (os.system, ("echo ran > " + str(tmp_path / "ran"),))
    torch.save({"agent": Boom()}, tmp_path / "evil.pt")
    with pytest.raises(RLCheckpointError, match="holds objects other than tensors and plain values"):
        load_checkpoint(tmp_path / "evil.pt")
    assert not (tmp_path / "ran").exists()
    torch.save({"agent": {}}, tmp_path / "old.pt")   # plain values, but not this format
    with pytest.raises(RLCheckpointError, match="not a gnwarp rl checkpoint"):
        load_checkpoint(tmp_path / "old.pt")
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(RLCheckpointError, match="not a readable"):
        load_checkpoint(tmp_path / "empty.pt")


def test_load_agent_acts_as_the_run_did(tmp_path):
    from gnwarp.rl.run import build_run, load_agent
    cfg = RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "r"))
    run_rl(cfg)
    agent, saved, obs_fn = load_agent(tmp_path / "r", device="cpu")
    ref = load_checkpoint(tmp_path / "r" / CHECKPOINT)["agent"]
    assert saved.agent == "svg0" and obs_fn == "bodies" and agent.updates == ref["updates"] > 0
    assert all(torch.equal(a, b) for a, b in zip(agent.policy.state_dict().values(), ref["policy"].values()))
    obs = torch.randn(4, agent.obs_dim)
    fresh = build_run(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "s")))["agent"]
    assert not torch.equal(agent.act(obs, deterministic=True), fresh.act(obs, deterministic=True))
    with pytest.raises(FileNotFoundError, match="no gnwarp rl run in .*config.json is missing"):
        load_agent(tmp_path / "nothing")
    (tmp_path / "r" / "config.json").write_text("[1, 2]")
    with pytest.raises(ConfigError, match="holds a table of RLConfig keys, got a list"):
        load_agent(tmp_path / "r")


def test_exported_agent_loads_as_the_run_and_cannot_train(tmp_path):
    from gnwarp.rl.run import AGENT_FILE, export_agent, load_agent
    run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "r")))
    dest = export_agent(tmp_path / "r", tmp_path / "x")
    assert sorted(p.name for p in dest.iterdir()) == ["agent.pt", "config.json"]
    assert set(load_checkpoint(dest / AGENT_FILE)) == {"agent"}   # no buffer, loop state or generators
    a, cfg_a, _ = load_agent(tmp_path / "r", "cpu")
    b, cfg_b, _ = load_agent(dest, "cpu")
    obs = torch.randn(5, a.obs_dim)
    assert torch.equal(a.act(obs, deterministic=True), b.act(obs, deterministic=True))
    assert a.updates == b.updates > 0 and cfg_b.out == str(dest) and cfg_a.agent == cfg_b.agent
    with pytest.raises(ConfigError, match="exported agent .*cannot resume training"):
        run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(dest)))
    with pytest.raises(FileNotFoundError, match="checkpoint.pt is missing"):
        export_agent(dest, tmp_path / "y")
    with pytest.raises(ValueError, match="another folder"):
        export_agent(tmp_path / "r", tmp_path / "r")
    run_rl(RLConfig(**{**TINY, "env_steps": 20, "seed": 5}, out=str(tmp_path / "other")))
    before = (tmp_path / "other" / "config.json").read_bytes()
    with pytest.raises(ValueError, match="holds a gnwarp rl run"):
        export_agent(tmp_path / "r", tmp_path / "other")     # another run's folder stays as it was
    assert (tmp_path / "other" / "config.json").read_bytes() == before
    assert export_agent(tmp_path / "r", dest) == dest       # over an earlier export
    from bench.rl_video import main as video   # a GIF of the exported agent, its returns on record
    assert video([str(dest), "--out", str(tmp_path / "v.gif"), "--episodes", "2", "--steps", "4",
                  "--renderer", "matplotlib"]) == 0
    info = json.loads((tmp_path / "v.gif.json").read_text())
    assert (tmp_path / "v.gif").stat().st_size > 0 and len(info["returns"]) == 2 and info["env_steps"] == b.env_steps
    (dest / AGENT_FILE).write_bytes(b"junk")
    with pytest.raises(RLCheckpointError):
        load_agent(dest, "cpu")


def test_a_loaded_agent_refuses_nan_weights_other_networks_and_nan_observations(tmp_path):
    """load_agent refuses weights with NaN (they would act NaN) and weights of other networks
    (a clear error, not torch's size mismatch); act refuses NaN observations, naming the env."""
    from gnwarp.rl.run import AGENT_FILE, export_agent, load_agent
    run_rl(RLConfig(**{**TINY, "env_steps": 20}, out=str(tmp_path / "r")))
    agent, _, _ = load_agent(tmp_path / "r", "cpu")
    obs = torch.zeros(3, agent.obs_dim)
    obs[2, 1] = float("nan")
    with pytest.raises(ValueError, match="obs of env 2 has NaN or Inf \\(feature 1\\)"):
        agent.act(obs, deterministic=True)
    dest = export_agent(tmp_path / "r", tmp_path / "x")
    state = load_checkpoint(dest / AGENT_FILE)
    name = next(iter(state["agent"]["policy"]))
    state["agent"]["policy"][name].fill_(float("nan"))
    save_checkpoint(dest / AGENT_FILE, state)
    with pytest.raises(ValueError, match=f"policy.{name} holds NaN or Inf"):
        load_agent(dest, "cpu")
    wide = export_agent(tmp_path / "r", tmp_path / "w")
    cfg = json.loads((wide / "config.json").read_text())
    (wide / "config.json").write_text(json.dumps({**cfg, "task": "cartpole-balance"}))   # other observations
    with pytest.raises(ConfigError, match="the saved agent's policy does not fit this agent's"):
        load_agent(wide, "cpu")


def test_sim_threads_change_no_result(tmp_path):
    cfg = dict(TINY, agent="ddpg", env_steps=40, num_envs=3)
    a = run_rl(RLConfig(**cfg, out=str(tmp_path / "a")))
    b = run_rl(RLConfig(**cfg, sim_threads=1, out=str(tmp_path / "b")))
    assert a["last_eval"] == b["last_eval"] and a["updates"] == b["updates"]
    _tensors_equal(load_checkpoint(tmp_path / "a" / CHECKPOINT)["buffer"],
                   load_checkpoint(tmp_path / "b" / CHECKPOINT)["buffer"], "buffer")
    with pytest.raises(ConfigError, match="sim_threads"):
        RLConfig(**cfg, sim_threads=0, out=str(tmp_path / "c"))


def test_checkpointed_random_states_and_collector_round_trip(tmp_path):
    import random
    from gnwarp.rl.loop import CollectorState
    from gnwarp.rl.run import _rng_states, _set_rng_states
    from gnwarp.rl.run_log import save_checkpoint
    np.random.seed(3)
    np.random.standard_normal()                      # a cached Gaussian in the state
    random.seed(4)
    torch.manual_seed(5)
    states = [CollectorState(None, 2), CollectorState(np.arange(6.0).reshape(2, 3), 2, np.array([1.5, -2.0]), 0.25),
              CollectorState(torch.arange(4.0).reshape(2, 2), 2)]
    save_checkpoint(tmp_path / "c.pt", {"rng": _rng_states(), "collectors": [c.state_dict() for c in states]})
    want = (np.random.standard_normal(3), random.random(), torch.rand(2))
    np.random.seed(0), random.seed(0), torch.manual_seed(0)
    back = load_checkpoint(tmp_path / "c.pt")
    _set_rng_states(back["rng"])
    got = (np.random.standard_normal(3), random.random(), torch.rand(2))
    assert np.array_equal(want[0], got[0]) and want[1] == got[1] and torch.equal(want[2], got[2])
    none, arr, ten = (CollectorState.from_state_dict(d) for d in back["collectors"])
    assert none.obs is None and isinstance(arr.obs, np.ndarray) and np.array_equal(arr.obs, states[1].obs)
    assert np.array_equal(arr.episode_return, [1.5, -2.0]) and arr.owed == 0.25 and arr.obs.dtype == np.float64
    assert isinstance(ten.obs, torch.Tensor) and torch.equal(ten.obs, states[2].obs)


def test_a_policy_that_stops_changing_is_reported(tmp_path):
    """A policy whose updates cannot move it (a learning rate below float32's resolution of its
    weights) gives the same outputs at two evaluations: the run warns; a learning one does not,
    nor does one whose returns merely repeat (a check of the outputs, not the returns)."""
    from gnwarp.rl.run import FrozenPolicyWarning
    frozen = dict(TINY, env_steps=80, agent_settings={"policy_lr": 1e-30})
    with pytest.warns(FrozenPolicyWarning, match="no longer changes"):
        run_rl(RLConfig(**frozen, out=str(tmp_path / "frozen")))
    recs = _eval_returns(tmp_path / "frozen")
    assert recs[1][1] == recs[2][1]   # 40 and 80 env steps: the same actions, the same returns
    with warnings.catch_warnings():
        warnings.simplefilter("error", FrozenPolicyWarning)
        run_rl(RLConfig(**dict(TINY, env_steps=80), out=str(tmp_path / "learning")))
    recs = _eval_returns(tmp_path / "learning")
    assert recs[1][1] != recs[2][1]
    from gnwarp.rl.run import frozen_policy_warning

    class Agent:   # what the check reads of an agent
        updates, env_steps = 10, 100
    prev = {}
    u = torch.ones(3, 2)
    assert not frozen_policy_warning(prev, u, Agent())               # the first evaluation
    Agent.updates = 20
    assert not frozen_policy_warning(prev, u + 1e-6, Agent())        # changed, if only a little
    Agent.updates = 30
    with pytest.warns(FrozenPolicyWarning, match="no longer changes"):
        assert frozen_policy_warning(prev, u + 1e-6, Agent(), saturated=1.0)
    assert not frozen_policy_warning(prev, u + 1e-6, Agent())        # no update in between


def test_eval_seed_shares_the_evaluation_states_between_runs():
    """Runs of other seeds with one ``eval_seed`` evaluate from the same initial states; without
    it each run evaluates from states of its own seed (the records name the setting)."""
    from gnwarp.rl.run import build_run, eval_reset_seed
    first = {}
    for seed, shared in ((0, None), (1, None), (0, 7), (1, 7)):
        cfg = RLConfig(**{**TINY, "env_steps": 40}, seed=seed, eval_seed=shared, out="unused")
        parts = build_run(cfg)
        try:
            first[seed, shared], _ = parts["eval_env"].reset(seed=eval_reset_seed(cfg))
        finally:
            parts["env"].close()
            parts["eval_env"].close()
    assert np.array_equal(first[0, 7], first[1, 7])
    assert not np.array_equal(first[0, None], first[1, None])
    with pytest.raises(ConfigError, match="eval_seed"):
        RLConfig(**TINY, eval_seed=-1, out="unused")


def test_a_run_evaluates_from_its_eval_seeds_states(tmp_path, monkeypatch):
    """run_rl's evaluations (and their first states) start from ``eval_seed``'s reset seed; the
    records say which."""
    from gnwarp.rl import run as rl_run
    seen = []
    real = rl_run.evaluate_policy
    monkeypatch.setattr(rl_run, "evaluate_policy", lambda agent, env, seed, **kw: seen.append(seed) or real(
        agent, env, seed, **kw))
    run_rl(RLConfig(**{**TINY, "env_steps": 40}, seed=3, eval_seed=5, out=str(tmp_path / "r")))
    assert seen and set(seen) == {rl_run.round_seed(5, 0, True)} != {rl_run.round_seed(3, 0, True)}
    assert {r.config["eval_seed"] for r in read_records(tmp_path / "r" / RECORDS_FILE)} == {5}


def test_auto_backend_acting_ahead_is_mujoco_c_and_a_run_keeps_its_simulator(tmp_path, monkeypatch):
    """"auto": MuJoCo C where a run acts ahead (the CPU steps while the GPU updates) or no CUDA is,
    MuJoCo-Warp otherwise; the choice is saved, and a resumed run keeps the simulator it started
    on (a run saved with "auto" before the choice was saved: MuJoCo-Warp on CUDA, as then)."""
    from gnwarp.rl import run_folder
    from gnwarp.sim import common
    for module in (common, run_folder):   # Warp sees a CUDA device (what the simulator needs)
        monkeypatch.setattr(module, "cuda_available", lambda: True)
    assert run_folder.run_backend(RLConfig(act_ahead=True)) == "mujoco"
    assert run_folder.run_backend(RLConfig()) == "mujoco_warp"
    assert run_folder.run_backend(RLConfig(backend="mujoco_warp_cpu", act_ahead=True)) == "mujoco_warp_cpu"
    fresh = RLConfig(**{**TINY, "backend": "auto"}, act_ahead=True, out=str(tmp_path / "f"))
    _, resume, cfg = run_folder.prepare_folder(fresh)
    assert not resume and cfg.backend == "mujoco"
    assert json.loads((tmp_path / "f" / "config.json").read_text())["backend"] == "mujoco"
    for saved, expect in (("auto", "mujoco_warp"), ("mujoco_warp", "mujoco_warp"), ("mujoco", "mujoco")):
        out = tmp_path / saved
        out.mkdir()
        (out / "config.json").write_text(json.dumps({**RLConfig(**TINY, act_ahead=True, out=str(out)).to_dict(),
                                                     "backend": saved}))
        (out / CHECKPOINT).write_bytes(b"")   # a run to resume (its checkpoint is read later)
        _, resume, cfg = run_folder.prepare_folder(RLConfig(**{**TINY, "backend": "auto"}, act_ahead=True, out=str(out)))
        assert resume and cfg.backend == expect, saved
        assert json.loads((out / "config.json").read_text())["backend"] == expect
    with pytest.raises(ConfigError, match="backend"):   # named explicitly, another simulator: refused
        run_folder.prepare_folder(RLConfig(**{**TINY, "backend": "mujoco"}, act_ahead=True, out=str(tmp_path / "auto")))
    old = tmp_path / "old"   # saved with "auto" by older code, resumed naming the simulator it ran on
    old.mkdir()
    (old / "config.json").write_text(json.dumps({**RLConfig(**TINY, out=str(old)).to_dict(), "backend": "auto"}))
    (old / CHECKPOINT).write_bytes(b"")
    _, _, cfg = run_folder.prepare_folder(RLConfig(**{**TINY, "backend": "mujoco_warp"}, out=str(old)))
    assert cfg.backend == "mujoco_warp"
    from gnwarp.eval.records import ResultRecord, write_records
    ran_c = tmp_path / "ran_c"   # saved with "auto" on a machine without CUDA: its records say MuJoCo C
    ran_c.mkdir()
    (ran_c / "config.json").write_text(json.dumps({**RLConfig(**TINY, out=str(ran_c)).to_dict(), "backend": "auto"}))
    (ran_c / CHECKPOINT).write_bytes(b"")
    write_records(ran_c / RECORDS_FILE, [ResultRecord(experiment="rl", task="pendulum-balance", planner="policy",
                                                      dynamics="true_mujoco_c", episodes=1, episode_steps=10,
                                                      returns=[1.0])])
    _, _, cfg = run_folder.prepare_folder(RLConfig(**{**TINY, "backend": "auto"}, out=str(ran_c)))
    assert cfg.backend == "mujoco"   # not the CUDA machine's MuJoCo-Warp
    (old / "config.json").unlink()   # a checkpoint without its config: "auto" cannot know the run's simulator
    with pytest.raises(ConfigError, match="backend.*name it"):
        run_folder.prepare_folder(RLConfig(**{**TINY, "backend": "auto"}, out=str(old)))


def test_the_first_evaluation_records_each_episodes_initial_state_and_target(tmp_path):
    """The run's first record holds what every evaluation starts from (the same states each time);
    later records do not repeat it. A swimmer6 target's distance from the nose follows."""
    cfg = RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "r"))
    run_rl(cfg)
    recs = read_records(tmp_path / "r" / RECORDS_FILE)
    first = recs[0].config
    assert recs[0].env_steps == 0 and len(first["initial_qpos"]) == TINY["eval_episodes"]
    assert first["targets"] is None   # pendulum-balance has none
    assert all("initial_qpos" not in r.config for r in recs[1:])
    from gnwarp.rl.run import eval_reset_seed, evaluation_env
    env = evaluation_env(cfg)
    env.reset(seed=eval_reset_seed(cfg))
    assert np.allclose(first["initial_qpos"], env.observe().qpos, atol=1e-4)
    env.close()
    swim = RLConfig(task="swimmer6", agent="svg1", eval_episodes=3, seed=4, backend="mujoco", device="cpu", out="unused")
    from gnwarp.rl.run import evaluation_states
    env = evaluation_env(swim)
    env.reset(seed=eval_reset_seed(swim))
    states = evaluation_states(env)
    env.close()
    again = evaluation_env(swim)   # another env reset from the same seed: the targets and states recorded
    again.reset(seed=eval_reset_seed(swim))
    assert np.allclose(states["targets"], again.targets, atol=1e-4) and np.asarray(states["targets"]).shape == (3, 3)
    assert np.allclose(states["initial_qpos"], again.observe().qpos, atol=1e-4)
    again.close()


def test_a_run_whose_first_evaluation_raises_closes_its_envs_and_log(tmp_path, monkeypatch):
    """Whatever raises after the envs are built (here the first evaluation) closes both envs and
    the log before the error reaches the caller."""
    from gnwarp.rl import run as rl_run
    closed = []
    real_build = rl_run.build_run

    def build(cfg):
        parts = real_build(cfg)
        for k in ("env", "eval_env"):
            close = parts[k].close
            parts[k].close = lambda k=k, close=close: closed.append(k) or close()
        return parts

    def boom(*a, **kw):
        raise RuntimeError("evaluation failed")
    monkeypatch.setattr(rl_run, "build_run", build)
    monkeypatch.setattr(rl_run, "evaluate_policy", boom)
    real_close = rl_run.RunLog.close
    monkeypatch.setattr(rl_run.RunLog, "close", lambda self: closed.append("log") or real_close(self))
    with pytest.raises(RuntimeError, match="evaluation failed"):
        run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "r")))
    assert sorted(closed) == ["env", "eval_env", "log"]
    # a close that raises leaves the others to run
    closed.clear()
    monkeypatch.setattr(rl_run.RunLog, "close", lambda self: closed.append("log") or 1 / 0)
    with pytest.raises((RuntimeError, ZeroDivisionError)):
        run_rl(RLConfig(**{**TINY, "env_steps": 40}, out=str(tmp_path / "r2")))
    assert sorted(closed) == ["env", "eval_env", "log"]
